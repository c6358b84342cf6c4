"""Report of the LDEC §4 limestone tunnel (scenes/limestone_tunnel.toml): ``python benchmarks/limestone_tunnel.py
[--scene PATH] [--device cpu] [--end-time T] [--resolution R] [--top free|non_reflecting] [--friction MU]
[--switch-time T] [--samples N] [--csv PATH]``.

``--friction`` sets the friction coefficient of every joint and of rock on rock where no joint is (the scene's
``[joints]`` and ``[interactions.default]``, both 0.6); ``--switch-time`` the time the pieces turn into rigid blocks
(``[rigid] switch_time``, 10 ms): the two knobs of why the rubble does or does not fill the tunnel (docs/scenes.md).

``--top non_reflecting`` adds Lysmer–Kuhlemeyer dashpots on the slab's top (z+) to the scene: a tunnel deep in the
rock, whose charge's wave leaves through the top instead of coming back from a free surface as tension, so the cover
is not spalled and thrown (the scene's own top is free: docs/scenes.md).

The scene is built as ``warpdem run`` builds it (:func:`warpdem.build.scene_build.build_scene`) and stepped in Python,
sampling between steps (the fracture passes and the switch to rigid blocks run inside ``Simulation.advance``). At the
first sample after the switch the run takes the rigid blocks' step, ``safety_factor`` × the critical step after the
switch (warpdem.stages.rigid_step.rigid_step_after_switch), as ``warpdem run`` does at its first frame after it.

Rubble: the volume of the tets (and of the spheres, were any converted) whose centroid lies inside the tunnel's
original cross-section (the rectangle its cut-out cells span, through the slab's depth), at the current positions;
0 at the start by construction (no centroid lies in the opening). The fill fraction is that solid volume over the
tunnel's volume; a loose pile fills the tunnel once its solid fraction nears that of rubble (≈ 0.6), which is what
"fills" means below. Per sample: time, rubble volume and fill fraction, the rubble's pieces (distinct rigid bodies or
fragments among those tets), node splits, and the phase (deformable or rigid). At the end: the peak particle speed
(PPV) at the tunnel in the deformable phase against the charge's scaled-distance law (:func:`ppv_law`), the switch's
RigidReport (the rigid step's gain over the deformable step), the cover (the highest rock at the end against the
slab's top: how far the charge threw the rock over it), the energy balance and the wall time.

PPV: each node's largest speed |v| over the deformable phase (sampled every step), in two bands of the rock 0.5-1 m
from the tunnel (PPV_BANDS: its left wall, facing the charge, and its roof), each summarised by the median over its
nodes, against the law at each node's distance R from the charge's centre (the borehole's axis, the second opening).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "limestone_tunnel.toml"
RUBBLE_SOLID_FRACTION = 0.6
"""Solid fraction of a loose rubble pile: the fill fraction at which the tunnel counts as filled [-]."""
CHARGE_MASS = 1000.0
"""LDEC §4's charge: a tamped one-ton detonation [kg of TNT]."""
PPV_K, PPV_BETA = 1.14, 1.6
"""Square-root scaled-distance law PPV = K (R/sqrt(W))^-beta of a confined charge: K [m/s] for R in m and W in kg
(Dowding 1985, Blast Vibration Monitoring and Control: 160 in/s × (D [ft]/sqrt(W [lb]))^-1.6, the upper bound of
confined charges; 160 in/s × (3.281/sqrt(2.205))^-1.6 = 1.14 m/s)."""
PPV_BANDS = (0.5, 1.0)
"""Distances [m] into the rock from the tunnel's faces between which the PPV is taken."""


def ppv_law(distance: np.ndarray | float, charge: float = CHARGE_MASS) -> np.ndarray | float:
    """Peak particle speed [m/s] at ``distance`` R [m] from a tamped ``charge`` W [kg]: K (R/sqrt(W))^-beta."""
    return PPV_K * (np.asarray(distance) / np.sqrt(charge)) ** -PPV_BETA


def ppv_bands(ref: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> dict[str, np.ndarray]:
    """Masks over the nodes' reference positions ``ref`` (n, 3) [m] of the rock PPV_BANDS from the tunnel [lo, hi]:
    its left wall (x, the charge's side, beside the tunnel's height) and its roof (z, over the tunnel's width)."""
    near, far = PPV_BANDS
    tol = 1e-6  # nodes on the bands' limits (the grid's lines) count
    x, z = ref[:, 0], ref[:, 2]
    return {
        "left wall": (x >= lo[0] - far - tol) & (x <= lo[0] - near + tol) & (z >= lo[2]) & (z <= hi[2]),
        "roof": (z >= hi[2] + near - tol) & (z <= hi[2] + far + tol) & (x >= lo[0]) & (x <= hi[0]),
    }


def ppv_lines(peak: np.ndarray, ref: np.ndarray, lo: np.ndarray, hi: np.ndarray, charge_xz: np.ndarray) -> list[str]:
    """Report lines of the nodes' peak speeds ``peak`` (n,) [m/s] in the PPV bands against :func:`ppv_law`."""
    distance = np.hypot(ref[:, 0] - charge_xz[0], ref[:, 2] - charge_xz[1])
    lines = []
    bands = ppv_bands(ref, lo, hi)
    for name, mask in (*bands.items(), ("both", np.logical_or(*bands.values()))):
        r, v = distance[mask], peak[mask]
        lines.append(
            f"PPV {name} ({PPV_BANDS[0]}-{PPV_BANDS[1]} m into the rock, {mask.sum()} nodes, R {r.min():.2f}-"
            f"{r.max():.2f} m): median {np.median(v):.2f} m/s (range {v.min():.2f}-{v.max():.2f}); the law "
            f"{PPV_K} (R/sqrt({CHARGE_MASS:.0f} kg))^-{PPV_BETA} at the median R {np.median(r):.2f} m: "
            f"{float(ppv_law(np.median(r))):.2f} m/s; median of PPV/law {np.median(v / ppv_law(r)):.3f}"
        )
    return lines


def tunnel_section(scene) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) [m] of the tunnel's cut-out: the box spanned by the mesh's opening faces within half a block of the
    first opening's nominal rectangle (the charge's borehole, the second opening, lies elsewhere)."""
    from warpdem.build.scene_mesh import rock_mesh

    mesh = scene.mesh
    tunnel = mesh.openings[0]
    rock = rock_mesh(scene)
    centre = np.array([tunnel.center[0], 0.0, tunnel.center[1]])
    half = np.array([0.5 * tunnel.width, np.inf, 0.5 * tunnel.height]) + max(mesh.brick) / 2.0
    x = rock.points[rock.boundary_faces["opening"]].reshape(-1, 3)
    near = np.all(np.abs(x - centre) <= half, axis=1)
    return x[near].min(axis=0), x[near].max(axis=0)


def report(
    scene, device: str, end_time: float | None, samples: int, csv_path: Path | None, emit: Callable[[str], None] = print
) -> list[str]:
    """Run the scene to ``end_time`` (default its own), sampling ``samples`` times; each report line goes to ``emit``
    as it is made (a long run shows its progress) and all are returned."""
    from warpdem.build.scene_build import build_scene
    from warpdem.simulation import Simulation
    from warpdem.stages.energy import balance_error
    from warpdem.stages.rigid_step import rigid_step_after_switch

    model, state = build_scene(scene, device)
    sim = Simulation(model, state)
    lo, hi = tunnel_section(scene)
    tunnel_volume = float(np.prod(hi - lo))
    end = end_time or scene.run.end_time
    steps = max(1, round(end / sim.model.dt))
    period = end / samples  # a sample every period [s] (samples + 1 rows)
    out: list[str] = []

    def say(line: str) -> None:
        out.append(line)
        emit(line)

    for line in (
        f"{scene.name}: {int(sim.state.tet_count.numpy()[0])} tets, {int(sim.state.node_count.numpy()[0])} nodes, "
        f"dt = {sim.model.dt * 1e6:.3f} µs, {steps} steps at it; tunnel {hi[0] - lo[0]:.3f} m × {hi[2] - lo[2]:.3f} m "
        f"(x {lo[0]:.3f}..{hi[0]:.3f}, z {lo[2]:.3f}..{hi[2]:.3f}), volume {tunnel_volume:.4f} m³",
        f"{'t [ms]':>8} {'phase':>10} {'rubble [m³]':>12} {'fill':>7} {'pieces':>7} {'splits':>7} {'wall [s]':>9}",
    ):
        say(line)
    rows = []
    ref = sim.model.node_ref_q.numpy().astype(np.float64)
    top = float(ref[:, 2].max())  # the slab's top [m]
    peak = np.zeros(len(ref))  # the nodes' largest speed in the deformable phase [m/s] (daughters of splits left out)
    e0 = sim.energy()
    in_play = e0.in_play
    wall = time.perf_counter()
    taken = False
    while True:
        rubble, pieces = rubble_volume(sim, lo, hi)
        splits = int(sim.state.node_splits_total.numpy()[0])
        in_play = max(in_play, sim.energy().in_play)
        phase = "rigid" if sim.rigid else "deformable"
        rows.append((sim.time, phase, rubble, rubble / tunnel_volume, pieces, splits))
        say(
            f"{sim.time * 1e3:8.2f} {phase:>10} {rubble:12.5f} {rubble / tunnel_volume:7.3f} {pieces:7d} {splits:7d} "
            f"{time.perf_counter() - wall:9.1f}"
        )
        if sim.time >= end - 0.5 * sim.model.dt:
            break
        if sim.rigid and not taken and scene.run.dt == "auto":
            critical = rigid_step_after_switch(sim.model, sim.state)
            sim.set_time_step(scene.run.safety_factor * critical.value, critical)
            taken = True
        todo = max(1, min(round(period / sim.model.dt), round((end - sim.time) / sim.model.dt)))
        while todo > 0 and not sim.rigid:  # step by step while deformable, for the PPV
            sim.advance(1)
            todo -= 1
            if not sim.rigid:  # the switch step's speeds are the blocks' (the same motion, counted once before)
                np.maximum(peak, np.linalg.norm(sim.state.node_qd.numpy()[: len(ref)], axis=1), out=peak)
        if todo > 0:
            sim.advance(todo)
    wall = time.perf_counter() - wall
    for line in ppv_lines(peak, ref, lo, hi, np.asarray(scene.mesh.openings[1].center)):
        say(line)
    if sim.rigid_report is not None:
        say(sim.rigid_report.format())
    heights = rock_heights(sim)
    say(
        f"cover: the highest rock at z = {heights.max():.2f} m against the slab's top at {top:.2f} m; "
        f"{np.count_nonzero(heights > top + 1.0)} nodes more than 1 m above it"
    )
    error = balance_error(e0, sim.energy(), in_play)
    say(f"balance error {error:+.3e} of {in_play:.4g} J in play; wall time {wall:.1f} s (sampling included)")
    fill = rows[-1][3]
    verdict = "fills" if fill >= RUBBLE_SOLID_FRACTION else "does not fill"
    say(
        f"rubble at {rows[-1][0] * 1e3:.1f} ms: {rows[-1][2]:.4f} m³ = {fill:.3f} of the tunnel's volume: the tunnel "
        f"{verdict} (a loose pile fills it at a solid fraction of about {RUBBLE_SOLID_FRACTION})"
    )
    if csv_path is not None:
        tmp = csv_path.with_suffix(csv_path.suffix + ".tmp")
        with tmp.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["time_s", "phase", "rubble_m3", "fill_fraction", "pieces", "splits"])
            w.writerows(rows)
        tmp.replace(csv_path)
    return out


def rock_heights(sim) -> np.ndarray:
    """The live nodes' heights z now [m], shape (N,), float64: how far the charge threw the rock over the slab."""
    nn = int(sim.state.node_count.numpy()[0])
    return sim.state.node_q.numpy()[:nn, 2].astype(np.float64)


def rubble_volume(sim, lo: np.ndarray, hi: np.ndarray) -> tuple[float, int]:
    """Volume [m³] of the live tets (and spheres) whose centroid lies in the tunnel's cross-section [lo, hi] (x, z;
    the whole depth along y), and how many pieces (rigid bodies, else fragments) they belong to."""
    m, s = sim.model, sim.state
    nt = int(s.tet_count.numpy()[0])
    tets = m.tet_nodes.numpy()[:nt]
    active = s.tet_active.numpy()[:nt] != 0  # deformable or rigid; 0 = converted to a sphere
    x = s.node_q.numpy().astype(np.float64)[tets].mean(axis=1)
    inside = active & np.all((x[:, [0, 2]] > lo[[0, 2]]) & (x[:, [0, 2]] < hi[[0, 2]]), axis=1)
    volume = float(m.tet_volume.numpy()[:nt][inside].astype(np.float64).sum())
    if sim.rigid and getattr(s, "node_body", None) is not None:
        pieces = len(np.unique(s.node_body.numpy()[tets[inside, 0]]))
    else:
        pieces = len(np.unique(tets[inside, 0])) if np.any(inside) else 0
    npart = int(s.particle_count.numpy()[0]) if getattr(s, "particle_count", None) is not None else 0
    if npart:
        q = s.particle_q.numpy()[:npart].astype(np.float64)
        r = m.particle_radius.numpy()[:npart].astype(np.float64)
        hit = np.all((q[:, [0, 2]] > lo[[0, 2]]) & (q[:, [0, 2]] < hi[[0, 2]]), axis=1)
        volume += float((4.0 / 3.0 * np.pi * r[hit] ** 3).sum())
    return volume, pieces


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=SCENE, help="scene file; default scenes/limestone_tunnel.toml")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--end-time", type=float, default=None, help="simulated time [s]; default the scene's")
    parser.add_argument("--resolution", type=float, default=None, help="[run] resolution; default the scene's")
    parser.add_argument(
        "--top",
        choices=("free", "non_reflecting"),
        default="free",
        help="the slab's top as the scene has it (free), or with non-reflecting dashpots added (a deep tunnel)",
    )
    parser.add_argument("--friction", type=float, default=None, help="joints' and rock-on-rock friction; default 0.6")
    parser.add_argument("--switch-time", type=float, default=None, help="[rigid] switch_time [s]; default the scene's")
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--csv", type=Path, default=None, help="write the samples to this CSV file")
    args = parser.parse_args(argv)
    from warpdem.cli import init_warp
    from warpdem.scene import load_scene

    init_warp(quiet=True)
    scene = load_scene(args.scene)
    if args.resolution is not None:
        scene = scene.model_copy(update={"run": scene.run.model_copy(update={"resolution": args.resolution})})
    if args.friction is not None:
        if not args.friction >= 0.0:
            parser.error(f"--friction: {args.friction:g} is not a friction coefficient (allowed: >= 0)")
        default = scene.interactions.default.model_copy(update={"friction": args.friction})
        scene = scene.model_copy(
            update={
                "joints": scene.joints.model_copy(update={"friction": args.friction}),
                "interactions": scene.interactions.model_copy(update={"default": default}),
            }
        )
    if args.switch_time is not None:
        if not args.switch_time > 0.0:
            parser.error(f"--switch-time: {args.switch_time:g} s is not a time after the start (allowed: > 0)")
        scene = scene.model_copy(update={"rigid": scene.rigid.model_copy(update={"switch_time": args.switch_time})})
    if args.top == "non_reflecting":
        from warpdem.scene.loads import Boundary

        top = Boundary(faces="z+", kind="non_reflecting")
        scene = scene.model_copy(update={"boundaries": [*scene.boundaries, top]})
    report(scene, args.device, args.end_time, args.samples, args.csv, emit=lambda line: print(line, flush=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
