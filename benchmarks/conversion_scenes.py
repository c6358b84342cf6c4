"""Reports of the FEM→DEM conversion scenes (issue 10 §7): ``python benchmarks/conversion_scenes.py [SCENE ...]
[--device cpu] [--end-time T] [--resolution R]`` with SCENE among masonry_wall_blast, masonry_tunnel_blast,
dam_crest_blast (default: all three).

Each scene is built as ``warpdem run`` builds it (:func:`warpdem.build.scene_build.build_scene`, the
``start_as_spheres`` region converted on the new Simulation) and stepped in Python, sampling between steps (conversion
passes run inside ``Simulation.advance``). A converted tet is a live tet with ``tet_active`` = 0; its place is its
centroid at the reference positions. Per sample: converted tets (per material), spheres, intact and broken bonds, the
fastest sphere, and the fractured zone's extent: the distance of the farthest converted tet from the scene's charge (the
centre of the pressure load's region, or of its face set); the tets converted by the passes (not the start_as_spheres
region) are counted apart.

A scene whose charge sits in a solid inside a circular tunnel (masonry_tunnel_blast: the concrete box in the lined
tunnel) also reports its fragments (the spheres the start_as_spheres region became, known by their ids) and the
lining (the tets ``[conversion].region`` lets convert, less that region): per sample the fastest fragment and the
lining's converted fraction, and, checked every :data:`HIT_CHECK` steps, the first time a fragment reaches the
tunnel's wall (its centre's distance from the axis plus its radius reaches the tunnel's radius, where the sphere–face
contact starts) and the first time a lining tet converts.
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
HIT_CHECK = 5
"""Steps between the checks for the first fragment at the tunnel's wall (6.5 µs on masonry_tunnel_blast)."""


def charge_point(scene) -> np.ndarray:
    """Centre of the first pressure load's region (the charge) [m]; for a load on a solid's cavity the cavity's
    centre, on 'opening' the opening's."""
    load = next(entry for entry in scene.loads if entry.kind == "pressure")
    if load.region is not None:
        lo, hi = load.region.bounds()
        return 0.5 * (lo + hi)
    mesh = scene.mesh
    for solid in getattr(mesh, "solids", []):
        if load.faces == f"{solid.name}_cavity":
            return 0.5 * (np.asarray(solid.cavity.lo) + np.asarray(solid.cavity.hi))
    opening = mesh.openings[0]
    centre = 0.5 * (np.asarray(mesh.lo) + np.asarray(mesh.hi))
    centre[[1 if opening.axis == "x" else 0, 2]] = opening.center
    return centre


def tunnel_wall(scene) -> tuple[np.ndarray, int, float] | None:
    """The circular tunnel a solid stands in: a point of its axis [m], the axis (0 x, 1 y) and its radius [m]; None
    for a scene without a solid in a circular tunnel."""
    mesh = scene.mesh
    if not getattr(mesh, "solids", None):
        return None
    for opening in mesh.openings:
        if opening.kind == "tunnel" and opening.shape == "circular":
            point = np.zeros(3)
            point[[1 if opening.axis == "x" else 0, 2]] = opening.center
            return point, 0 if opening.axis == "x" else 1, float(opening.radius)
    return None


def wall_reach(sim, started: int, wall: tuple[np.ndarray, int, float]) -> tuple[float, float]:
    """How far the fragments (spheres with id < ``started``) reach towards the tunnel's wall: the largest distance
    from the axis plus radius [m], and the fastest fragment's speed [m/s]."""
    n = sim.particle_count
    if not n or not started:
        return 0.0, 0.0
    fragment = sim.model.particle_id.numpy()[:n] < started
    q = sim.state.particle_q.numpy()[:n][fragment]
    point, axis, _ = wall
    across = np.delete(q - point, axis, axis=1)
    reach = np.linalg.norm(across, axis=1) + sim.model.particle_radius.numpy()[:n][fragment]
    speed = np.linalg.norm(sim.state.particle_qd.numpy()[:n][fragment], axis=1)
    return float(reach.max()), float(speed.max())


def report(scene, device: str, end_time: float | None) -> list[str]:
    """Converted tets, spheres, bonds and the fractured zone's extent over the run."""
    from warpdem.build.scene_build import build_scene, start_as_spheres
    from warpdem.simulation import Simulation

    model, state = build_scene(scene, device)
    sim = Simulation(model, state)
    started = start_as_spheres(scene, sim)
    nt = int(sim.state.tet_count.numpy()[0])
    tets = sim.model.tet_nodes.numpy()[:nt]
    centroid = sim.model.node_ref_q.numpy()[tets].astype(np.float64).mean(axis=1)
    material = sim.model.tet_material.numpy()[:nt]
    names = sim.model.material_names
    charge = charge_point(scene)
    distance = np.linalg.norm(centroid - charge, axis=1)
    initial = sim.state.tet_active.numpy()[:nt] == 0  # the start_as_spheres region
    steps = max(1, round((end_time or scene.run.end_time) / sim.model.dt))
    out = [
        f"{scene.name}: {nt} tets, {int(sim.state.node_count.numpy()[0])} nodes, dt = {sim.model.dt * 1e6:.3f} µs, "
        f"{steps} steps; {started} tets start as spheres; charge at {np.round(charge, 3).tolist()} m"
    ]
    wall = tunnel_wall(scene)
    lining = np.zeros(nt, dtype=bool)
    if wall is not None:
        region = scene.conversion.region
        lining = ~initial if region is None else region.contains(centroid) & ~initial
    first_hit = first_lining = None
    e0 = sim.energy()
    in_play = e0.in_play
    done = 0
    wall0 = time.perf_counter()
    for k in range(1, SAMPLES + 1):
        target = steps * k // SAMPLES
        while target > done:
            chunk = min(target - done, HIT_CHECK) if wall is not None else target - done
            sim.advance(chunk)
            done += chunk
            if wall is None:
                continue
            if first_hit is None and wall_reach(sim, started, wall)[0] >= wall[2]:
                first_hit = sim.time
            if first_lining is None and np.any((sim.state.tet_active.numpy()[:nt] == 0) & lining):
                first_lining = sim.time
        converted = sim.state.tet_active.numpy()[:nt] == 0
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
        line = (
            f"  t = {sim.time * 1e3:6.3f} ms  converted {per_material}  spheres {n:5d}  "
            f"bonds {nb - live_broken:5d} intact {broken:5d} broken  "
            f"fastest {float(speed.max(initial=0.0)):7.1f} m/s  zone {extent:5.2f} m "
            f"({int(np.count_nonzero(adaptive))} tets converted adaptively)  "
            # A scene at rest (a charge that has not fired) has nothing in play to scale by.
            f"balance {(energy.total - e0.total) / in_play if in_play > 0.0 else 0.0:+.1e}"
        )
        if wall is not None:
            reach, fastest = wall_reach(sim, started, wall)
            share = np.count_nonzero(converted & lining) / max(1, np.count_nonzero(lining))
            line += f"  fragments: fastest {fastest:6.1f} m/s, reach {reach:4.2f} m  lining converted {share:6.1%}"
        out.append(line)
    seconds = time.perf_counter() - wall0
    if wall is not None:

        def when(t: float | None) -> str:
            return "not by the end" if t is None else f"at {t * 1e3:.3f} ms"

        out.append(
            f"{scene.name}: the first fragment reaches the tunnel's wall (radius {wall[2]:g} m) {when(first_hit)}; the "
            f"first lining tet converts {when(first_lining)} (checked every {HIT_CHECK} steps); "
            f"{int(np.count_nonzero(lining))} lining tets"
        )
    out.append(f"{scene.name}: {done} steps in {seconds:.0f} s wall on {device}")
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
