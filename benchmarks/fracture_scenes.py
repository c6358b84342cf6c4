"""Reports of the fracture scenes (issue 9 §7, issue 27): ``python benchmarks/fracture_scenes.py [SCENE ...]
[--device cpu] [--end-time T] [--checkpoint FILE]`` with SCENE among pmma_plate, brazilian_disc, boulder_impact,
pmma_plate_remote, pmma_plate_branching (default: all).

Each scene of ``scenes/`` is built as ``warpdem run`` builds it (:func:`warpdem.build.scene_build.build_scene`) and
stepped in Python, sampling between steps (split passes run inside ``Simulation.advance``):

- ``pmma_plate`` (LDEC Fig. 4): the crack tip on each side is the farthest node born by a split (a daughter: an index
  past the built node count) along x, at its reference position; the tip speed is the least-squares slope of the
  tip position against time over the run from the seed tip to 90 % of the way to the plate edge; its ratio to the
  Rayleigh wave speed c_R ≈ c_s (0.862 + 1.14 ν)/(1 + ν) (Freund's approximation), c_s = sqrt(G/ρ).
- ``pmma_plate_remote`` (LDEC Fig. 4 as published: remote tension on a plate whose edges are far): the tip as for
  ``pmma_plate``; the plateau speed is the least-squares slope over a window that starts PLATEAU_FROM past the seed's
  tip and ends when the crack's first waves are back from the loaded edges (2 H / c_d after it started, c_d the
  dilatational speed) or PLATEAU_EDGE before the plate's edge; the mesh size in δ_c = 2Γ/T_f. ``pmma_plate_branching``
  (every node free to split, 1.5 × the load): the same, and how far off the centre line the splits go (branching).
- ``brazilian_disc``: the load P of the top platen is the sum of the elastic penalty forces of the nodes behind it,
  Σ k_v max(0, −gap_v) (the node–wall law of warpdem.stages.fem_contact without its dashpot, which is small at this
  rate), so σ_t = 2P/(πDt) at the first split and at the peak against T_f, and the lowest load after the peak (a disc
  that has split through drops its load); the split is told by the daughters' distance from the loaded diameter (at the
  peak and at the end), and whether the crack has let go by its cohesive elements (broken, and the opening d_max/δ_c
  of those still intact), the fragments (as for ``boulder_impact``) and the crack faces still held by a node.
- ``boulder_impact``: fragments are the connected pieces of the rock: tets joined through shared nodes and through
  the cohesive elements not yet broken; pieces of at least MIN_FRAGMENT_TETS tets are counted as fragments.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
SAMPLES = 100
"""Samples over a run (the tip positions, platen loads and fragment counts are read back this often)."""
WINDOW = 20
"""Samples of the running crack over which the fastest tip speed is fitted."""
MIN_FRAGMENT_TETS = 4
"""A piece of the boulder of fewer tets is a chip, not a fragment."""
PLATEAU_FROM = 5.0
"""How far past the seed's tip the remote plate's plateau window starts [elements]: the tip's start-up."""
PLATEAU_EDGE = 5.0
"""How close to the plate's edge the window ends at the latest [elements]."""


def rayleigh_speed(youngs_modulus: float, poisson_ratio: float, density: float) -> float:
    """c_R ≈ c_s (0.862 + 1.14 ν)/(1 + ν) [m/s], c_s = sqrt(E / (2 (1 + ν) ρ)) (Freund 1990, within 0.5 %)."""
    c_s = math.sqrt(youngs_modulus / (2.0 * (1.0 + poisson_ratio) * density))
    return c_s * (0.862 + 1.14 * poisson_ratio) / (1.0 + poisson_ratio)


def _stepped(scene, device: str, end_time: float | None) -> Iterator[tuple[float, object, int]]:
    """Builds the scene and yields ``(time [s], simulation, built node count)`` after each of SAMPLES chunks."""
    from warpdem.build.scene_build import build_scene
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
    from warpdem.build.scene_mesh import rock_mesh, seed_crack_faces

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


def platen_load(sim, wall: int, normal: np.ndarray) -> float:
    """Load P [N] on a platen (wall ``wall`` of unit ``normal``): the sum of the elastic penalty forces of the nodes
    behind it, Σ k_v max(0, −gap_v) (the node–wall law of warpdem.stages.fem_contact without its dashpot; k_v the
    stiffness in use, which a node pressed across a split keeps)."""
    from warpdem.stages.fem_contact import contact_stiffness_in_use

    n = int(sim.state.node_count.numpy()[0])
    q = sim.state.node_q.numpy()[:n].astype(np.float64)
    k = contact_stiffness_in_use(sim.model, sim.state)
    gap = (q - sim.state.wall_point.numpy()[wall].astype(np.float64)) @ normal
    return float(np.sum(k * np.maximum(-gap, 0.0)))


def brazilian_disc(scene, device: str, end_time: float | None) -> list[str]:
    """Peak platen load P, σ_t = 2P/(πDt) against T_f, the load after the peak, and where the split runs."""
    mesh = scene.mesh
    diameter, thickness = 2.0 * mesh.radius, mesh.height
    t_f = scene.materials[mesh.material].tensile_strength
    top = max(range(len(scene.walls)), key=lambda i: scene.walls[i].point[2])
    normal = np.asarray(scene.walls[top].normal, dtype=np.float64)
    times, loads, born, lines = [], [], [], []
    first = sim = None
    for t, sim, n0 in _stepped(scene, device, end_time):
        load = platen_load(sim, top, normal)
        x = _daughters(sim, n0)
        if len(x) and first is None:
            first = (t, load, x.copy())
        times.append(t)
        loads.append(load)
        born.append(x)
        lines.append(f"  t = {t * 1e6:7.1f} µs  P = {load / 1e3:7.2f} kN  splits {len(x)}")
    out = lines[:: max(1, len(lines) // 20)]

    def sigma(p: float) -> str:
        value = 2.0 * p / (math.pi * diameter * thickness)
        return f"σ_t = 2P/(πDt) = {value / 1e6:.2f} MPa = {value / t_f:.2f} T_f"

    def path(x: np.ndarray) -> str:
        off = np.abs(x[:, 0])  # distance from the loaded (vertical, x = 0) diameter
        return (
            f"{len(x)} split nodes, distance from the loaded diameter: median {np.median(off) * 1e3:.1f} mm, "
            f"90 % within {np.quantile(off, 0.9) * 1e3:.1f} mm, max {off.max() * 1e3:.1f} mm (D = "
            f"{diameter * 1e3:.0f} mm); heights {x[:, 2].min() * 1e3:.1f} to {x[:, 2].max() * 1e3:.1f} mm"
        )

    if first is not None:
        t1, p1, x1 = first
        out.append(
            f"brazilian_disc: first splits at t = {t1 * 1e6:.0f} µs, P = {p1 / 1e3:.2f} kN, {sigma(p1)}; "
            f"{len(x1)} nodes, {np.abs(x1[:, 2]).max() * 1e3:.1f} mm or less from the centre's height"
        )
    i_peak = int(np.argmax(loads))
    peak = loads[i_peak]
    after = min(loads[i_peak:])
    out.append(
        f"brazilian_disc: peak P = {peak / 1e3:.2f} kN at t = {times[i_peak] * 1e6:.0f} µs, {sigma(peak)} "
        f"(T_f = {t_f / 1e6:.1f} MPa); lowest load after it {after / 1e3:.2f} kN = {after / peak:.2f} of the peak"
    )
    if len(born[i_peak]):
        out.append(f"brazilian_disc: at the peak, {path(born[i_peak])}")
    if len(born[-1]):
        out.append(f"brazilian_disc: at the end, {path(born[-1])}")
    if sim is not None:
        # Whether the crack has let go: the halves separate only once its cohesive elements are broken (d_max ≥ δ_c).
        s = sim.state
        alive = int(s.cohesive_count.numpy()[0])
        opening = s.cohesive_d_max.numpy()[:alive] / np.maximum(s.cohesive_delta_c.numpy()[:alive], 1e-30)
        out.append(
            f"brazilian_disc: cohesive elements at the end: {int(s.cohesive_broken_total.numpy()[0])} broken, {alive} "
            f"intact (opening d_max/δ_c median {np.median(opening) if alive else 0.0:.2f}, largest "
            f"{opening.max() if alive else 0.0:.2f})"
        )
        pieces = fragments(sim)
        open_, one, two = crack_face_states(sim)
        out.append(
            f"brazilian_disc: at the end, {int(np.sum(pieces >= MIN_FRAGMENT_TETS))} fragment(s) of "
            f">= {MIN_FRAGMENT_TETS} tets (largest {pieces[0]} of {pieces.sum()} tets); crack faces {open_} open, "
            f"{one} held by one node, {two} by two"
        )
    return out


def fragments(sim) -> np.ndarray:
    """Tet count of each connected piece of the rock of a simulation, largest first (:func:`fragment_sizes`)."""
    s = sim.state
    count = int(s.cohesive_count.numpy()[0])
    return fragment_sizes(
        sim.model.tet_nodes.numpy()[: int(s.tet_count.numpy()[0])],
        int(s.node_count.numpy()[0]),
        s.cohesive_a.numpy()[:count],
        s.cohesive_b.numpy()[:count],
        s.cohesive_broken.numpy()[:count],
    )


def crack_face_states(sim) -> np.ndarray:
    """Faces of the unsplit mesh between two tets (``ref_tet_face_nbr``) by the nodes the two tets still share on
    them: counts of (0: open, 1 and 2: held by one or two nodes, a hinge), the intact (3) left out."""
    from warpdem.tables import TET_FACES

    nt = int(sim.state.tet_count.numpy()[0])
    tets = sim.model.tet_nodes.numpy()[:nt].astype(np.int64)
    nbr = sim.model.ref_tet_face_nbr.numpy()[: 4 * nt].reshape(nt, 4).astype(np.int64)
    t, k = np.nonzero(nbr > np.arange(nt)[:, None])  # each interior face once, from its lower tet
    faces = tets[t[:, None], np.asarray(TET_FACES)[k]]  # (F, 3)
    shared = (faces[:, :, None] == tets[nbr[t, k]][:, None, :]).any(axis=2).sum(axis=1)
    return np.bincount(shared, minlength=4)[:3]


def fragment_sizes(
    tets: np.ndarray, node_count: int, cohesive_a: np.ndarray, cohesive_b: np.ndarray, broken: np.ndarray
) -> np.ndarray:
    """Tet count of each connected piece of the rock (tets joined through shared nodes and through the cohesive
    elements not yet broken), largest first; the arrays of the live tets (T, 4) and cohesive elements (C,)."""
    from warpdem.build.geology import component_labels

    tets = np.asarray(tets, dtype=np.int64)
    intact = np.asarray(broken) == 0
    a = np.concatenate([np.repeat(tets[:, 0], 3), np.asarray(cohesive_a)[intact]])
    b = np.concatenate([tets[:, 1:].reshape(-1), np.asarray(cohesive_b)[intact]])
    labels = component_labels(node_count, a, b)
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
        print(lines[-1], flush=True)  # a long run: show it as it goes
    big = pieces[pieces >= MIN_FRAGMENT_TETS]
    out = lines[:: max(1, len(lines) // 20)]
    out.append(
        f"boulder_impact: {len(big)} fragments of >= {MIN_FRAGMENT_TETS} tets (largest {pieces[0]} of {pieces.sum()} "
        f"tets, {pieces[0] / pieces.sum():.0%}), {len(pieces) - len(big)} chips"
    )
    return out


def checkpoint_fragments(path: Path) -> str:
    """The fragments of the rock in a checkpoint of any run (``warpdem run``), as :func:`boulder_impact` counts them."""
    from warpdem.io.checkpoint import read_checkpoint

    arrays, attrs = read_checkpoint(path)
    count = int(arrays["state/cohesive_count"][0])
    pieces = fragment_sizes(
        arrays["model/tet_nodes"][: int(arrays["state/tet_count"][0])],
        int(arrays["state/node_count"][0]),
        arrays["state/cohesive_a"][:count],
        arrays["state/cohesive_b"][:count],
        arrays["state/cohesive_broken"][:count],
    )
    big = pieces[pieces >= MIN_FRAGMENT_TETS]
    return (
        f"{path.name} (t = {float(attrs['time']) * 1e3:.2f} ms): {len(big)} fragments of >= {MIN_FRAGMENT_TETS} tets, "
        f"sizes {big.tolist()} of {pieces.sum()} tets, {len(pieces) - len(big)} chips"
    )


def dilatational_speed(youngs_modulus: float, poisson_ratio: float, density: float) -> float:
    """c_d = sqrt(E (1 − ν) / ((1 + ν)(1 − 2ν) ρ)) [m/s]: the fastest wave, the first to come back from an edge."""
    nu = poisson_ratio
    return math.sqrt(youngs_modulus * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu) * density))


class RemotePlate(NamedTuple):
    """What the remote-tension plates' reports measure against (LDEC Fig. 4): the speeds, the mesh and the geometry.

    Attributes:
        c_r: Rayleigh speed [m/s]. c_d: dilatational speed [m/s], the first wave back from an edge.
        h: element size along x [m]. delta_c: the linear law's critical opening 2Γ/T_f [m].
        edge: the plate's edge along x [m]. half_height: half its height [m].
        seed_tip: the seed's rim [m], its tip nodes' x (they split first) and half an element: the last grid plane
            inside the seed crack's box (which reaches half an element past the tips, so that no node lies on its edge).
        unconstrained: every node may split (no ``[fracture].region``).
    """

    c_r: float
    c_d: float
    h: float
    delta_c: float
    edge: float
    half_height: float
    seed_tip: float
    unconstrained: bool

    @staticmethod
    def of(scene) -> RemotePlate:
        mat = scene.materials[scene.mesh.material]
        h = (scene.mesh.hi[0] - scene.mesh.lo[0]) / scene.mesh.divisions[0]
        return RemotePlate(
            c_r=rayleigh_speed(mat.youngs_modulus, mat.poisson_ratio, mat.density),
            c_d=dilatational_speed(mat.youngs_modulus, mat.poisson_ratio, mat.density),
            h=h,
            delta_c=2.0 * mat.fracture_energy / mat.tensile_strength,
            edge=float(scene.mesh.hi[0]),
            half_height=float(scene.mesh.hi[1]),
            seed_tip=(math.floor(scene.fracture.seed_cracks[0].region.box.hi[0] / h) + 0.5) * h,
            unconstrained=scene.fracture.region is None,
        )

    def plateau(self, times: np.ndarray, tips: np.ndarray) -> tuple[float | None, np.ndarray]:
        """The crack's start [s] (None: it did not start) and the plateau window over the samples ``times`` [s],
        ``tips`` (the tip's |x| [m]): from PLATEAU_FROM past the seed's tip (the start-up over) until the crack's own
        first waves are back from the loaded edges (start + 2 H / c_d) or the tip is within PLATEAU_EDGE of the
        plate's edge, whichever is first."""
        started = np.nonzero(tips > self.seed_tip + 0.5 * self.h)[0]
        if len(started) == 0:
            return None, np.zeros(len(times), dtype=bool)
        t0 = float(times[started[0]])
        t_back = t0 + 2.0 * self.half_height / self.c_d
        window = (
            (tips >= self.seed_tip + PLATEAU_FROM * self.h)
            & (times <= t_back)
            & (tips <= self.edge - PLATEAU_EDGE * self.h)
        )
        return t0, window


def pmma_plate_remote(scene, device: str, end_time: float | None) -> list[str]:
    """The remote-tension plates (LDEC Fig. 4 as published, and its unconstrained variant): the tip speed's plateau
    against c_R over a stated window; where every node may split (no ``[fracture].region``), how far from the centre
    line the splits reach (branching)."""
    plate = RemotePlate.of(scene)
    c_r, h, edge = plate.c_r, plate.h, plate.edge
    name = scene.name
    times, tips, lines, off_line = [], [], [], []
    for t, sim, n0 in _stepped(scene, device, end_time):
        x = _daughters(sim, n0)
        tip = float(np.abs(x[:, 0]).max()) if len(x) else 0.0
        times.append(t)
        tips.append(tip)
        off = float(np.abs(x[:, 1]).max()) if len(x) else 0.0
        off_line.append(off)
        lines.append(
            f"  t = {t * 1e6:7.1f} µs  tip |x| = {tip * 1e3:6.1f} mm  splits {len(x):5d}  max |y| {off * 1e3:5.1f} mm"
        )
        if tip >= edge - h:
            break  # through to the edge: nothing more to measure
    times_a, tips_a = np.asarray(times), np.asarray(tips)
    out = [
        f"{name}: c_R = {c_r:.0f} m/s, c_d = {plate.c_d:.0f} m/s; h = {h * 1e3:.1f} mm = {h / plate.delta_c:.0f} δ_c "
        f"(δ_c = 2Γ/T_f = {plate.delta_c * 1e6:.0f} µm; LDEC: 1000 δ_c); plate {2 * edge * 1e3:.0f} × "
        f"{2 * plate.half_height * 1e3:.0f} mm"
    ]
    out += lines[:: max(1, len(lines) // 25)]
    t0, window = plate.plateau(times_a, tips_a)
    if t0 is None:
        return [*out, f"{name}: the crack did not start"]
    if np.count_nonzero(window) >= 3:
        t_w, x_w = times_a[window], tips_a[window]
        speed = float(np.polyfit(t_w, x_w, 1)[0])
        out.append(
            f"{name}: crack starts at t = {t0 * 1e6:.1f} µs; plateau window t = {t_w[0] * 1e6:.1f} .. "
            f"{t_w[-1] * 1e6:.1f} µs, tip |x| = {x_w[0] * 1e3:.1f} .. {x_w[-1] * 1e3:.1f} mm ({len(t_w)} samples): "
            f"tip speed {speed:.0f} m/s = {speed / c_r:.2f} c_R (LDEC: near c_R)"
        )
        thirds = np.array_split(np.arange(len(t_w)), 3)
        parts = [f"{float(np.polyfit(t_w[k], x_w[k], 1)[0]) / c_r:.2f}" for k in thirds if len(k) >= 2]
        out.append(f"{name}: the window's thirds: {' / '.join(parts)} c_R")
    else:
        out.append(f"{name}: fewer than 3 samples in the plateau window (crack starts at t = {t0 * 1e6:.1f} µs)")
    if plate.unconstrained:
        out.append(
            f"{name}: splits reach |y| = {max(off_line) * 1e3:.1f} mm off the centre line "
            f"({max(off_line) / h:.1f} h); a branch leaves the line where |y| grows with |x|"
        )
    return out


REPORTS: dict[str, Callable[..., list[str]]] = {
    "pmma_plate": pmma_plate,
    "brazilian_disc": brazilian_disc,
    "boulder_impact": boulder_impact,
    "pmma_plate_remote": pmma_plate_remote,
    "pmma_plate_branching": pmma_plate_remote,
}


def main(argv: list[str] | None = None) -> int:
    from scene_reports import chosen_scenes, scene_parser  # beside this script, in benchmarks/

    parser = scene_parser(__doc__, REPORTS)
    parser.add_argument("--checkpoint", type=Path, help="only count the rock fragments in this checkpoint of a run")
    args = parser.parse_args(argv)
    if args.checkpoint is not None:
        print(checkpoint_fragments(args.checkpoint))
        return 0
    names = chosen_scenes(parser, args, REPORTS)
    from warpdem.cli import init_warp
    from warpdem.scene import load_scene

    init_warp()
    for name in names:
        start = time.perf_counter()
        lines = REPORTS[name](load_scene(SCENES_DIR / f"{name}.toml"), args.device, args.end_time)
        print("\n".join(lines))
        print(f"{name}: {time.perf_counter() - start:.0f} s wall on {args.device}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
