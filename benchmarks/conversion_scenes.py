"""Reports of the FEM→DEM conversion scenes (issue 10 §7): ``python benchmarks/conversion_scenes.py [SCENE ...]
[--device cpu] [--end-time T] [--resolution R]`` with SCENE among masonry_wall_blast, masonry_tunnel_blast,
dam_crest_blast (default: all three).

Each scene is built as ``warpdem run`` builds it (:func:`warpdem.build.scene_build.build_scene`, the
``start_as_spheres`` region converted on the new Simulation) and stepped in Python, sampling between steps (conversion
passes run inside ``Simulation.advance``). A converted tet is a live tet with a sphere (``tet_sphere`` >= 0; with the
overlap band, the default, those in the band stay active with weight alpha); its place is its centroid at the reference
positions. Per sample: converted tets (per material), spheres, intact and broken bonds, the fastest sphere, and the
fractured zone: its extent, the distance of the farthest converted tet from the scene's charge (the centre of the
pressure load's region, or an arch dam's charge disc), and its volume, the converted tets' reference volumes; the tets
converted by the passes (not the start_as_spheres region) are counted apart.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
SCENES = ("masonry_wall_blast", "masonry_tunnel_blast", "dam_crest_blast")
SAMPLES = 20
"""Samples over a run."""


def charge_point(scene) -> np.ndarray:
    """Centre of the first pressure load's region (the charge) [m]; the opening's centre for a load on 'opening'; an
    arch dam's charge disc's centre."""
    load = next(entry for entry in scene.loads if entry.kind == "pressure")
    if load.region is not None:
        lo, hi = load.region.bounds()
        return 0.5 * (lo + hi)
    mesh = scene.mesh
    if mesh.kind == "arch_dam":
        return np.asarray(mesh.charge_center(), dtype=np.float64)
    opening = mesh.openings[0]
    centre = 0.5 * (np.asarray(mesh.lo) + np.asarray(mesh.hi))
    centre[[1 if opening.axis == "x" else 0, 2]] = opening.center
    return centre


def report(scene, device: str, end_time: float | None) -> list[str]:
    """Converted tets, spheres, bonds and the fractured zone's extent over the run."""
    from warpdem.build.scene_build import build_scene, start_as_spheres
    from warpdem.simulation import Simulation

    model, state = build_scene(scene, device)
    sim = Simulation(model, state)
    started = start_as_spheres(scene, sim)
    nt = int(sim.state.tet_count.numpy()[0])
    tets = sim.model.tet_nodes.numpy()[:nt]
    corners = sim.model.node_ref_q.numpy()[tets].astype(np.float64)
    centroid = corners.mean(axis=1)
    volume = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) / 6.0
    material = sim.model.tet_material.numpy()[:nt]
    names = sim.model.material_names
    charge = charge_point(scene)
    distance = np.linalg.norm(centroid - charge, axis=1)
    initial = sim.state.tet_sphere.numpy()[:nt] >= 0  # the start_as_spheres region
    steps = max(1, round((end_time or scene.run.end_time) / sim.model.dt))
    out = [
        f"{scene.name}: {nt} tets, {int(sim.state.node_count.numpy()[0])} nodes, dt = {sim.model.dt * 1e6:.3f} µs, "
        f"{steps} steps; {started} tets start as spheres; charge at {np.round(charge, 3).tolist()} m"
    ]
    e0 = sim.energy()
    in_play = e0.in_play
    done = 0
    wall0 = time.perf_counter()
    for k in range(1, SAMPLES + 1):
        target = steps * k // SAMPLES
        if target > done:
            sim.advance(target - done)
            done = target
        converted = sim.state.tet_sphere.numpy()[:nt] >= 0
        n = sim.particle_count
        speed = np.linalg.norm(sim.state.particle_qd.numpy()[:n], axis=1) if n else np.zeros(1)
        nb = sim.bond_count
        # Broken bonds are compacted out of the live ones between passes: the count since the start is the
        # state's counter (as the time series' bonds_broken), not the live bonds' flags.
        broken = int(sim.state.bonds_broken_total.numpy()[0])
        live_broken = int(np.count_nonzero(sim.state.bond_broken.numpy()[:nb])) if nb else 0
        per_material = ", ".join(
            f"{names[m]} {int(np.count_nonzero(converted & (material == m)))}/{int(np.count_nonzero(material == m))}"
            for m in np.unique(material)
        )
        extent = float(distance[converted].max()) if converted.any() else 0.0
        adaptive = converted & ~initial
        energy = sim.energy()
        in_play = max(in_play, energy.in_play)
        out.append(
            f"  t = {sim.time * 1e3:6.3f} ms  converted {per_material}  spheres {n:5d}  "
            f"bonds {nb - live_broken:5d} intact {broken:5d} broken  "
            f"fastest {float(speed.max(initial=0.0)):7.1f} m/s  "
            f"zone {extent:5.2f} m {float(volume[converted].sum()):7.2f} m³ "
            f"({int(np.count_nonzero(adaptive))} tets converted adaptively)  "
            f"balance {(energy.total - e0.total) / in_play:+.1e}"
        )
    wall = time.perf_counter() - wall0
    out.append(f"{scene.name}: {done} steps in {wall:.0f} s wall on {device}")
    return out


def main(argv: list[str] | None = None) -> int:
    from scene_reports import chosen_scenes, scene_parser  # beside this script, in benchmarks/

    parser = scene_parser(__doc__, SCENES)
    parser.add_argument("--resolution", type=float, help="run.resolution (default: the scene's)")
    args = parser.parse_args(argv)
    names = chosen_scenes(parser, args, SCENES)
    from warpdem.cli import init_warp
    from warpdem.scene import load_scene

    init_warp()
    for name in names:
        scene = load_scene(SCENES_DIR / f"{name}.toml")
        if args.resolution is not None:
            scene = scene.model_copy(update={"run": scene.run.model_copy(update={"resolution": args.resolution})})
        print("\n".join(report(scene, args.device, args.end_time)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
