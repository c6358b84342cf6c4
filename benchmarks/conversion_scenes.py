"""Reports of the FEM→DEM conversion scenes (issue 10 §7): ``python benchmarks/conversion_scenes.py [SCENE ...]
[--device cpu] [--end-time T] [--resolution R]`` with SCENE among masonry_wall_blast, masonry_tunnel_blast,
dam_crest_blast (default: all three).

Each scene is built as ``warpdem run`` builds it (:func:`warpdem.build.scene_build.build_scene`, the
``start_as_spheres`` region converted on the new Simulation; with ``dt = "auto"`` the step that lands on the frames,
as the command line takes it: :func:`cli_model`) and stepped in Python, sampling between steps (conversion passes run
inside ``Simulation.advance``). A converted tet is a live tet with a sphere (``tet_sphere`` >= 0; with the
overlap band, the default, those in the band stay active with weight alpha); its place is its centroid at the reference
positions. Per sample: converted tets (per material), spheres, intact and broken bonds, the fastest sphere, and the
fractured zone: its extent, the distance of the farthest converted tet from the scene's charge (the centre of the
pressure load's region, or an arch dam's charge disc), and its volume, the converted tets' reference volumes; the tets
converted by the passes (not the start_as_spheres region) are counted apart.

``masonry_wall_blast`` gets a report of its own (:func:`wall_report`, CIMNE §6.1, Figs. 4–5): the wall is its masonry
tets. Every ``HIT_EVERY`` until the first hit, the first fragment hit (the first sample at which a box sphere's
surface reaches the wall's exposed face, x_c + r ≥ the smallest current x of the wall's face x = 1.45 m, within the
wall's height); every ``WALL_EVERY``: the DEM zone (the share of the wall's tets converted, Fig. 5's sequence), the
wall's largest intact piece as a share of the wall's mass (label_fragments: tets through shared nodes, bonds,
couplings; the wall's nodes and the spheres of its converted tets), the crest's mean horizontal displacement, and the
time of failure: the first sample at which the largest intact piece holds less than half the wall's mass
(FAILED_SHARE) — the wall is then in pieces, none of which carries the rest; a wall that keeps a piece of more than
half its mass to the end has not failed.

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
    centre, on 'opening' the opening's; an arch dam's charge disc's centre."""
    load = next(entry for entry in scene.loads if entry.kind == "pressure")
    if load.region is not None:
        lo, hi = load.region.bounds()
        return 0.5 * (lo + hi)
    mesh = scene.mesh
    if mesh.kind == "arch_dam":
        return np.asarray(mesh.charge_center(), dtype=np.float64)
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


def cli_model(scene, device: str):
    """The scene's model and state as the command line steps them: built by ``build_scene``, with ``dt = "auto"``
    the step that lands on the frames (warpdem.runner.timing.frame_step), so the report follows the command line's run
    (and the seed report's) rather than one a step apart, which a blast's chaos takes elsewhere."""
    import dataclasses

    from warpdem.build.scene_build import build_scene
    from warpdem.runner.timing import frame_step

    model, state = build_scene(scene, device)
    if scene.run.dt == "auto":
        model = dataclasses.replace(model, dt=frame_step(model.dt, 1.0 / scene.run.output_rate)[1])
    return model, state


def report(scene, device: str, end_time: float | None) -> list[str]:
    """Converted tets, spheres, bonds and the fractured zone's extent over the run."""
    from warpdem.build.scene_build import start_as_spheres
    from warpdem.simulation import Simulation

    sim = Simulation(*cli_model(scene, device))
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
            if first_lining is None and np.any((sim.state.tet_sphere.numpy()[:nt] >= 0) & lining):
                first_lining = sim.time
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
        line = (
            f"  t = {sim.time * 1e3:6.3f} ms  converted {per_material}  spheres {n:5d}  "
            f"bonds {nb - live_broken:5d} intact {broken:5d} broken  "
            f"fastest {float(speed.max(initial=0.0)):7.1f} m/s  "
            f"zone {extent:5.2f} m {float(volume[converted].sum()):7.2f} m³ "
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


HIT_EVERY = 2.0e-5
"""Sampling interval until the first hit [s] (the hit's time to this)."""
WALL_EVERY = 5.0e-4
"""Sampling interval of the wall after the first hit [s]."""
FAILED_SHARE = 0.5
"""The wall has failed when its largest intact piece holds less than this share of its mass [-]."""
WALL_FACE_X = 1.45
"""The wall's face towards the box [m] (scenes/masonry_wall_blast.toml)."""


def wall_resolution(points: np.ndarray, tets: np.ndarray) -> tuple[float, float]:
    """The wall's tets' mean edge and its thickness along x (across the wall) [m]: ``points`` the reference node
    positions, shape (N, 3), ``tets`` the wall's tets, shape (T, 4). Their ratio is the elements through the wall."""
    from warpdem.tables import TET_EDGES

    corners = points[tets].astype(np.float64)
    edge = float(np.linalg.norm(corners[:, TET_EDGES[:, 1]] - corners[:, TET_EDGES[:, 0]], axis=2).mean())
    x = corners[..., 0]
    return edge, float(x.max() - x.min())


def largest_piece_share(sim, tets: np.ndarray, nodes: np.ndarray) -> float:
    """The largest intact piece of a part of the mesh as a share of the part's mass [-]: the part is the tets flagged
    in ``tets`` (shape (T,), bool) and their nodes (``nodes``, shape (N,), bool); its mass is its nodes' lumped mass
    and the spheres of its converted tets (with the overlap band a band tet's mass is split between the two, so the
    sum is the part's mass whatever has converted). Pieces are label_fragments' (tets through shared nodes, bonds,
    couplings)."""
    from warpdem.stages.fragments import label_fragments

    m, s = sim.model, sim.state
    nt, nn, n = len(tets), len(nodes), sim.particle_count
    sphere = s.tet_sphere.numpy()[:nt]
    mine = sphere[tets & (sphere >= 0)]
    fragments = label_fragments(m, s)
    labels = np.concatenate([fragments.node_label[:nn][nodes], fragments.particle_label[:n][mine]])
    masses = np.concatenate([m.node_mass.numpy()[:nn][nodes], m.particle_mass.numpy()[:n][mine]]).astype(np.float64)
    whole = labels >= 0
    pieces = np.bincount(labels[whole], weights=masses[whole])
    return float(pieces.max() / masses.sum()) if len(pieces) else 0.0


def wall_report(scene, device: str, end_time: float | None) -> list[str]:
    """The masonry wall's first hit, DEM zone, largest intact piece and failure over the run (module docstring)."""
    from warpdem.build.scene_build import start_as_spheres
    from warpdem.simulation import Simulation

    wall0 = time.perf_counter()
    sim = Simulation(*cli_model(scene, device))
    started = start_as_spheres(scene, sim)
    m, s = sim.model, sim.state
    nt, nn = int(s.tet_count.numpy()[0]), sim.node_count
    tets = m.tet_nodes.numpy()[:nt]
    ref = m.node_ref_q.numpy()[:nn].astype(np.float64)
    wall = m.tet_material.numpy()[:nt] == m.material_names.index("masonry")
    wall_nodes = np.zeros(nn, dtype=bool)
    wall_nodes[np.unique(tets[wall])] = True
    face = wall_nodes & np.isclose(ref[:, 0], WALL_FACE_X, atol=1e-6)
    top = float(ref[wall_nodes, 2].max())
    crest = wall_nodes & np.isclose(ref[:, 2], top, atol=1e-6)
    box = sim.particle_count  # the box's spheres, the first slots
    box_radius = m.particle_radius.numpy()[:box].astype(np.float64)
    h, thickness = wall_resolution(ref, tets[wall])
    steps = max(1, round((end_time or scene.run.end_time) / m.dt))
    out = [
        f"{scene.name}: {nt} tets ({int(wall.sum())} in the wall, mean edge {h * 1e3:.1f} mm: {thickness / h:.1f} "
        f"through its {thickness:.2f} m), {nn} nodes, dt = {m.dt * 1e6:.3f} µs, {steps} steps; {started} tets start "
        f"as spheres (the box)"
    ]
    e0 = sim.energy()
    in_play = e0.in_play
    done, hit, failed, share = 0, None, None, 1.0
    next_sample = WALL_EVERY
    while done < steps:
        k = min(max(1, round((HIT_EVERY if hit is None else WALL_EVERY) / sim.model.dt)), steps - done)
        sim.advance(k)
        done += k
        m, s = sim.model, sim.state
        u = s.node_u.numpy()[:nn].astype(np.float64)
        if hit is None:
            q = s.particle_q.numpy()[:box]
            in_height = (q[:, 2] >= 0.0) & (q[:, 2] <= top)
            reach = (q[:, 0] + box_radius)[in_height]
            if len(reach) and reach.max() >= float((ref[face, 0] + u[face, 0]).min()):
                hit = sim.time
                out.append(f"  first hit on the wall at {hit * 1e3:.3f} ms (sampled every {HIT_EVERY * 1e3:.2f} ms)")
        if sim.time < next_sample - 0.5 * m.dt and done < steps:
            continue
        next_sample = sim.time + WALL_EVERY
        converted = s.tet_sphere.numpy()[:nt] >= 0  # a tet with a sphere; band tets stay active (weight alpha)
        share = largest_piece_share(sim, wall, wall_nodes)
        n = sim.particle_count
        if failed is None and share < FAILED_SHARE:
            failed = sim.time
        energy = sim.energy()
        in_play = max(in_play, energy.in_play)
        out.append(
            f"  t = {sim.time * 1e3:6.3f} ms  wall converted {int(converted[wall].sum()):5d}/{int(wall.sum())} "
            f"({converted[wall].mean():5.1%})  largest intact piece {share:5.1%} of the wall  "
            f"crest u_x {float(u[crest, 0].mean()) * 1e3:+7.2f} mm  spheres {n:5d}  "
            f"balance {(energy.total - e0.total) / in_play:+.1e}"
        )
    verdict = (
        f"failed at {failed * 1e3:.2f} ms (largest intact piece below {FAILED_SHARE:.0%} of the wall's mass)"
        if failed is not None
        else f"not failed by {sim.time * 1e3:.2f} ms (a piece of {share:.1%} of its mass holds together)"
    )
    first = f"{hit * 1e3:.3f} ms" if hit is not None else "none"
    out.append(
        f"{scene.name}: first hit {first}; the wall {verdict}; {done} steps in {time.perf_counter() - wall0:.0f} s "
        f"wall on {device} (build included)"
    )
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
        make = wall_report if name == "masonry_wall_blast" else report
        print("\n".join(make(scene, args.device, args.end_time)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
