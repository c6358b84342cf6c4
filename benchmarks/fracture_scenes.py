"""Reports of the fracture scenes (issue 9 §7): ``python benchmarks/fracture_scenes.py [SCENE ...] [--device cpu]
[--end-time T]`` with SCENE among pmma_plate, brazilian_disc, boulder_impact (default: all three).

Each scene of ``scenes/`` is built as ``warpdem run`` builds it (:func:`warpdem.scene_build.build_scene`) and stepped
in Python, sampling between steps (split passes run inside ``Simulation.advance``):

- ``pmma_plate`` (LDEC Fig. 4): the crack tip on each side is the farthest node born by a split (a daughter: an index
  past the built node count) along x, at its reference position; the tip speed is the least-squares slope of the
  tip position against time over the run from the seed tip to 90 % of the way to the plate edge; its ratio to the
  Rayleigh wave speed c_R ≈ c_s (0.862 + 1.14 ν)/(1 + ν) (Freund's approximation), c_s = sqrt(G/ρ).
- ``brazilian_disc``: the load P of the top platen is the sum of the elastic penalty forces of the nodes behind it,
  Σ k_v max(0, −gap_v) (the node–wall law of warpdem.fem_contact without its dashpot, which is small at this rate),
  so σ_t = 2P/(πDt) of the peak against T_f; the split is told by the daughters' distance from the loaded diameter.
- ``boulder_impact``: fragments are the connected pieces of the rock: tets joined through shared nodes and through
  the cohesive elements not yet broken; pieces of at least MIN_FRAGMENT_TETS tets are counted as fragments.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
SAMPLES = 100
"""Samples over a run (the tip positions, platen loads and fragment counts are read back this often)."""
WINDOW = 20
"""Samples of the running crack over which the fastest tip speed is fitted."""
MIN_FRAGMENT_TETS = 4
"""A piece of the boulder of fewer tets is a chip, not a fragment."""


def rayleigh_speed(youngs_modulus: float, poisson_ratio: float, density: float) -> float:
    """c_R ≈ c_s (0.862 + 1.14 ν)/(1 + ν) [m/s], c_s = sqrt(E / (2 (1 + ν) ρ)) (Freund 1990, within 0.5 %)."""
    c_s = math.sqrt(youngs_modulus / (2.0 * (1.0 + poisson_ratio) * density))
    return c_s * (0.862 + 1.14 * poisson_ratio) / (1.0 + poisson_ratio)


def _stepped(scene, device: str, end_time: float | None) -> Iterator[tuple[float, object, int]]:
    """Builds the scene and yields ``(time [s], simulation, built node count)`` after each of SAMPLES chunks."""
    from warpdem.scene_build import build_scene
    from warpdem.simulation import Simulation

    model, state = build_scene(scene, device)
    n0 = int(state.node_count.numpy()[0])
    sim = Simulation(model, state)
    steps = max(1, round((end_time or scene.run.end_time) / model.dt))
    done = 0
    for k in range(1, SAMPLES + 1):
        target = steps * k // SAMPLES
        if target > done:
            sim.advance(target - done)
            done = target
        yield done * model.dt, sim, n0


def _daughters(sim, n0: int) -> np.ndarray:
    """Reference positions of the nodes born by splits [m], shape (K, 3), float64."""
    n = int(sim.state.node_count.numpy()[0])
    return sim.model.node_ref_q.numpy()[n0:n].astype(np.float64)


def pmma_plate(scene, device: str, end_time: float | None) -> list[str]:
    """Crack-tip positions and speed against the Rayleigh wave speed."""
    mat = scene.materials[scene.mesh.material]
    c_r = rayleigh_speed(mat.youngs_modulus, mat.poisson_ratio, mat.density)
    from warpdem.scene_mesh import rock_mesh, seed_crack_faces

    mesh = rock_mesh(scene)
    seed_faces = seed_crack_faces(mesh.points, mesh.tets, scene.fracture.seed_cracks[0], "seed_cracks[0]")
    seed_tip = float(np.abs(mesh.points[seed_faces][..., 0]).max())  # the rim of the seed crack along x
    edge = float(scene.mesh.hi[0])
    times, tips, lines = [], [], []
    for t, sim, n0 in _stepped(scene, device, end_time):
        x = _daughters(sim, n0)
        right = float(x[:, 0].max()) if len(x) else 0.0
        left = float(-x[:, 0].min()) if len(x) else 0.0
        times.append(t)
        tips.append(max(right, left, 0.0))
        lines.append(f"  t = {t * 1e6:7.2f} µs  tips x = {-left * 1e3:7.2f} / {right * 1e3:6.2f} mm  splits {len(x)}")
    times_a, tips_a = np.asarray(times), np.asarray(tips)
    running = (tips_a > seed_tip) & (tips_a <= seed_tip + 0.9 * (edge - seed_tip))
    out = [f"pmma_plate: c_R = {c_r:.0f} m/s; seed tips at ±{seed_tip * 1e3:.1f} mm, plate edge at {edge * 1e3:.1f} mm"]
    out += lines[:: max(1, len(lines) // 20)]
    if np.count_nonzero(running) >= 3:
        speed = float(np.polyfit(times_a[running], tips_a[running], 1)[0])
        start = times_a[running][0]
        # The fastest stretch: the least-squares slope over any WINDOW consecutive running samples.
        t_run, x_run = times_a[running], tips_a[running]
        window = min(WINDOW, len(t_run))
        fastest = max(
            float(np.polyfit(t_run[i : i + window], x_run[i : i + window], 1)[0])
            for i in range(len(t_run) - window + 1)
        )
        out.append(
            f"pmma_plate: crack running from t = {start * 1e6:.1f} µs, tip speed {speed:.0f} m/s"
            f" = {speed / c_r:.2f} c_R (fastest over {window} samples: {fastest:.0f} m/s = {fastest / c_r:.2f} c_R)"
        )
    else:
        out.append("pmma_plate: the crack did not run (fewer than 3 samples between the seed tip and the edge)")
    return out


def brazilian_disc(scene, device: str, end_time: float | None) -> list[str]:
    """Peak platen load P and σ_t = 2P/(πDt) against T_f; where the split runs."""
    mesh = scene.mesh
    diameter, thickness = 2.0 * mesh.radius, mesh.height
    t_f = scene.materials[mesh.material].tensile_strength
    top = max(range(len(scene.walls)), key=lambda i: scene.walls[i].point[2])
    peak, peak_t, lines, first = 0.0, 0.0, [], None
    x = np.zeros((0, 3))
    for t, sim, n0 in _stepped(scene, device, end_time):
        n = int(sim.state.node_count.numpy()[0])
        q = sim.state.node_q.numpy()[:n].astype(np.float64)
        k = sim.model.node_contact_stiffness.numpy()[:n].astype(np.float64)
        gap = (q - sim.state.wall_point.numpy()[top]) @ np.asarray(scene.walls[top].normal)
        load = float(np.sum(k * np.maximum(-gap, 0.0)))
        if load > peak:
            peak, peak_t = load, t
        x = _daughters(sim, n0)
        if len(x) and first is None:
            first = (t, load, x.copy())
        lines.append(f"  t = {t * 1e6:7.1f} µs  P = {load / 1e3:7.2f} kN  splits {len(x)}")
    out = lines[:: max(1, len(lines) // 20)]

    def sigma(p: float) -> str:
        value = 2.0 * p / (math.pi * diameter * thickness)
        return f"σ_t = 2P/(πDt) = {value / 1e6:.2f} MPa = {value / t_f:.2f} T_f"

    if first is not None:
        t1, p1, x1 = first
        r1 = np.linalg.norm(x1[:, [0, 2]], axis=1)
        out.append(
            f"brazilian_disc: first splits at t = {t1 * 1e6:.0f} µs, P = {p1 / 1e3:.2f} kN, {sigma(p1)}; "
            f"{len(x1)} nodes, {r1.max() * 1e3:.1f} mm or less from the disc's axis"
        )
    out.append(
        f"brazilian_disc: peak P = {peak / 1e3:.2f} kN at t = {peak_t * 1e6:.0f} µs, {sigma(peak)} "
        f"(T_f = {t_f / 1e6:.1f} MPa)"
    )
    if len(x):
        off = np.abs(x[:, 0])  # distance from the loaded (vertical, x = 0) diameter
        out.append(
            f"brazilian_disc: {len(x)} splits; distance from the loaded diameter: median {np.median(off) * 1e3:.1f} "
            f"mm, 90 % within {np.quantile(off, 0.9) * 1e3:.1f} mm (D = {diameter * 1e3:.0f} mm); heights "
            f"{x[:, 2].min() * 1e3:.1f} to {x[:, 2].max() * 1e3:.1f} mm"
        )
    return out


def fragments(sim) -> np.ndarray:
    """Tet count of each connected piece of the rock (shared nodes and intact cohesive elements), largest first."""
    from warpdem.geology import component_labels

    s = sim.state
    nt, nn = int(s.tet_count.numpy()[0]), int(s.node_count.numpy()[0])
    tets = sim.model.tet_nodes.numpy()[:nt].astype(np.int64)
    # Vertices: nodes 0..nn-1; each tet joins its four nodes, each intact cohesive element its two daughters.
    a = [np.repeat(tets[:, 0], 3)]
    b = [tets[:, 1:].reshape(-1)]
    count = int(s.cohesive_count.numpy()[0])
    if count:
        intact = s.cohesive_broken.numpy()[:count] == 0
        a.append(s.cohesive_a.numpy()[:count][intact])
        b.append(s.cohesive_b.numpy()[:count][intact])
    labels = component_labels(nn, np.concatenate(a), np.concatenate(b))
    return np.sort(np.bincount(labels[tets[:, 0]]))[::-1]


def boulder_impact(scene, device: str, end_time: float | None) -> list[str]:
    """Fragments of the boulder over time."""
    lines = []
    pieces = np.zeros(1, np.int64)
    for t, sim, n0 in _stepped(scene, device, end_time):
        pieces = fragments(sim)
        big = pieces[pieces >= MIN_FRAGMENT_TETS]
        splits = int(sim.state.node_count.numpy()[0]) - n0
        lines.append(
            f"  t = {t * 1e3:6.2f} ms  splits {splits:5d}  pieces {len(pieces):4d}  fragments (>= {MIN_FRAGMENT_TETS} "
            f"tets) {len(big):3d}  largest {pieces[0] / pieces.sum():.2f} of the tets"
        )
    big = pieces[pieces >= MIN_FRAGMENT_TETS]
    out = lines[:: max(1, len(lines) // 20)]
    out.append(
        f"boulder_impact: {len(big)} fragments of >= {MIN_FRAGMENT_TETS} tets (largest {pieces[0]} of {pieces.sum()} "
        f"tets, {pieces[0] / pieces.sum():.0%}), {len(pieces) - len(big)} chips"
    )
    return out


REPORTS: dict[str, Callable[..., list[str]]] = {
    "pmma_plate": pmma_plate,
    "brazilian_disc": brazilian_disc,
    "boulder_impact": boulder_impact,
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="*", metavar="SCENE", help=f"one of {', '.join(REPORTS)} [all]")
    parser.add_argument("--device", default="cpu", help="Warp device [cpu]")
    parser.add_argument("--end-time", type=float, help="simulated end time [s] (default: the scene's)")
    args = parser.parse_args(argv)
    unknown = [name for name in args.scenes if name not in REPORTS]
    if unknown:
        parser.error(f"unknown scene {unknown[0]!r}; allowed: {', '.join(REPORTS)}")
    from warpdem.cli import init_warp
    from warpdem.scene import load_scene

    init_warp()
    for name in args.scenes or list(REPORTS):
        start = time.perf_counter()
        lines = REPORTS[name](load_scene(SCENES_DIR / f"{name}.toml"), args.device, args.end_time)
        print("\n".join(lines))
        print(f"{name}: {time.perf_counter() - start:.0f} s wall on {args.device}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
