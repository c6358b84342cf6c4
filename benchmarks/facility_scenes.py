"""Report of the LDEC §3 facility scenes (issue 11 §4): ``python benchmarks/facility_scenes.py [SCENE ...]
[--device cpu] [--end-time T] [--json FILE] [--picture PNG]`` with SCENE among facility_persistent,
facility_nonpersistent (default: both, printed side by side).

Each scene is built as ``python -m warpdem`` builds it (:func:`warpdem.scene_build.build_scene`, rigid blocks from
t = 0) and stepped in Python, read back every SAMPLE_STEPS steps. What LDEC §3 reports, measured:

- wave speed by direction: probes on three rays from ground zero (the centre of the loaded patch on the surface):
  straight down, 45° and 75° from the vertical. A probe is the mesh node nearest each point 2, 4, ... m along the
  ray; its first arrival is the first sample at which its speed exceeds ARRIVAL_FRACTION of its own peak (and
  ARRIVAL_FLOOR, above the settling under gravity; a probe that never exceeds it is not reached). The
  distance travelled is the distance from the loaded patch (a disc of the load's radius on the surface), and the
  ray's speed the least-squares slope of distance against arrival time (anisotropy: the ratio of the slopes), set
  against the granite's P-wave speed c_p = sqrt((λ + 2μ)/ρ);
- attenuation with depth: the peak particle speed (PPV) of the probes straight down, and the exponent n of a
  least-squares fit PPV ∝ d⁻ⁿ;
- rubble: the volume of block material inside each opening's original cross-section (each tet sampled at the four
  points of the degree-2 Keast rule, each carrying a quarter of its volume, at the blocks' current pose), every
  RUBBLE_INTERVAL, section by section: the largest room, the plain tunnel stretches, the junctions (main tunnel with
  the shaft and with the access tunnel), the access tunnel's arms, the shaft; and summed by kind (room, junctions,
  straight stretches);
- the largest room's roof over time: the blocks over its footprint within one 2 m layer above its roof, their mean
  and largest drop and mean sinking speed, against free fall from rest (½ g t², g t);
- chimney: above each opening section, the blocks whose centre lies over its footprint and above its roof, by 2 m
  layer up from the roof: the largest displacement of a block in each layer; the chimney is the height above the roof
  up to which every layer holds a block displaced more than CHIMNEY_DISPLACEMENT.

Wave figures are read within WAVE_WINDOW; the rest at the end (the scene's end_time unless ``--end-time``).
"""

from __future__ import annotations

import itertools
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
SCENES = ("facility_persistent", "facility_nonpersistent")
SAMPLE_STEPS = 4
"""Steps between read-backs of the probes' velocities (4 steps of ~15 µs: arrival times to ~0.06 ms)."""
ARRIVAL_FRACTION = 0.1
"""A probe's first arrival: its speed first exceeds this fraction of its own peak speed, and ARRIVAL_FLOOR."""
ARRIVAL_FLOOR = 0.05
"""Least speed of a first arrival [m/s]: the rock starts unstressed and settles under gravity at up to g t (0.05 m/s
by 5 ms), which far probes of small peak speed would otherwise take for the wave."""
RAYS = {"down": 0.0, "45°": 45.0, "75°": 75.0}
"""Probe rays from ground zero: angle from the vertical [deg], in the y-z plane (towards −y), away from the
openings' footprints along y = 12 m where the angle allows."""
PROBE_DISTANCES = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0)
"""Distances of the probes along each ray from ground zero [m] (those outside the rock are dropped)."""
CHIMNEY_DISPLACEMENT = 0.01
"""A block above an opening counts as part of a chimney once its centre has moved more than this [m]."""
LAYER = 2.0
"""Height of the layers the chimney is counted in [m] (the joint spacing of both scenes)."""
ENERGY_SAMPLES = 25
"""Samples between readings of the energy in play (the balance's scale, its largest value over the run)."""
SNAPSHOT_TIME = 0.01
WAVE_WINDOW = 0.01
"""The probes' speeds are read up to this time [s]: the direct wave has passed every probe by 5 ms, and later the
blocks over the room fall freely (g t), which is not the wave's PPV."""
RUBBLE_INTERVAL = 0.005
"""Time between readings of the rubble in each section and of the room's roof [s]."""
REPORT_EVERY = 2
"""The side-by-side table prints every this many readings of the room (and the last)."""
"""Time of the velocity-field section [s]: LDEC's Fig. 7 compares the velocity fields at 30 ms, 10 ms at 1:3."""
KEAST_2 = np.array(
    [
        [0.5854101966249685, 0.1381966011250105, 0.1381966011250105, 0.1381966011250105],
        [0.1381966011250105, 0.5854101966249685, 0.1381966011250105, 0.1381966011250105],
        [0.1381966011250105, 0.1381966011250105, 0.5854101966249685, 0.1381966011250105],
        [0.1381966011250105, 0.1381966011250105, 0.1381966011250105, 0.5854101966249685],
    ]
)
"""Barycentric coordinates of the 4-point degree-2 rule on a tet (each point weighs a quarter of the volume)."""


@dataclass(frozen=True)
class Section:
    """A part of an opening's original cross-section: an axis-aligned box [m], and the footprint its chimney is
    counted over (the box's x-y extent) from its roof (``hi[2]``) up. ``kind``: "room" (the largest room),
    "junction" (where two openings cross), "tunnel" (a straight stretch) or "shaft"."""

    name: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    kind: str = "tunnel"

    @property
    def volume(self) -> float:
        return float(np.prod(np.subtract(self.hi, self.lo)))

    def contains(self, x: np.ndarray) -> np.ndarray:
        return np.all((x >= np.asarray(self.lo)) & (x <= np.asarray(self.hi)), axis=-1)


def facility_sections(scene) -> list[Section]:
    """The openings of a facility scene cut into sections: the largest room; the main tunnel (axis x) into its
    straight stretches and its junctions (with the lift shaft and with the access tunnel; the stretch inside the
    room is the room's); the access tunnel (axis y) into its two arms; the shaft above the main tunnel's roof. Read
    from the scene's ``[[mesh.openings]]``: rectangular tunnels along x and y, and two rooms, the one that reaches the
    surface being the shaft."""
    tunnels = [o for o in scene.mesh.openings if o.kind == "tunnel"]
    main = next(o for o in tunnels if o.axis == "x")
    access = next(o for o in tunnels if o.axis == "y")
    top = scene.mesh.hi[2]
    rooms = [o for o in scene.mesh.openings if o.kind == "room"]
    shaft = next(o for o in rooms if o.hi[2] >= top)
    room = next(o for o in rooms if o.hi[2] < top)

    def box(t, start: float, end: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        c, zc = t.center
        lo_t, hi_t = (c - 0.5 * t.width, zc - 0.5 * t.height), (c + 0.5 * t.width, zc + 0.5 * t.height)
        if t.axis == "x":
            return (start, lo_t[0], lo_t[1]), (end, hi_t[0], hi_t[1])
        return (lo_t[0], start, lo_t[1]), (hi_t[0], end, hi_t[1])

    (m0, m1), (a0, a1) = main.span, access.span
    crossings = {
        (shaft.lo[0], shaft.hi[0]): "main tunnel x shaft (junction)",
        (
            access.center[0] - 0.5 * access.width,
            access.center[0] + 0.5 * access.width,
        ): "main tunnel x access (junction)",
        (room.lo[0], room.hi[0]): None,  # inside the room: the room's section
    }
    cuts = sorted({m0, m1, *(x for pair in crossings for x in pair if m0 < x < m1)})
    out = [Section("largest room", tuple(room.lo), tuple(room.hi), "room")]
    for x0, x1 in itertools.pairwise(cuts):
        name = next(
            (n for (c0, c1), n in crossings.items() if c0 <= x0 and x1 <= c1), f"main tunnel, x {x0:g}-{x1:g} m"
        )
        if name is not None:
            out.append(Section(name, *box(main, x0, x1), "junction" if "junction" in name else "tunnel"))
    my0, my1 = main.center[0] - 0.5 * main.width, main.center[0] + 0.5 * main.width
    out.append(Section("access tunnel, south arm", *box(access, a0, my0)))
    out.append(Section("access tunnel, north arm", *box(access, my1, a1)))
    roof = main.center[1] + 0.5 * main.height
    out.append(Section("lift shaft (above the tunnel)", (shaft.lo[0], shaft.lo[1], roof), tuple(shaft.hi), "shaft"))
    return [Section(s.name, s.lo, (s.hi[0], s.hi[1], min(s.hi[2], top)), s.kind) for s in out]


def p_wave_speed(scene) -> float:
    """c_p = sqrt((λ + 2μ)/ρ) of the rock [m/s] = sqrt(E (1 − ν) / ((1 + ν)(1 − 2ν) ρ))."""
    mat = scene.materials[scene.mesh.material]
    e, nu, rho = mat.youngs_modulus, mat.poisson_ratio, mat.density
    return math.sqrt(e * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu) * rho))


def load_patch(scene) -> tuple[np.ndarray, float]:
    """Ground zero (the centre of the loaded patch on the surface) [m] and the patch's radius [m]."""
    cyl = scene.loads[0].region.cylinder
    return np.array([cyl.center[0], cyl.center[1], scene.mesh.hi[2]]), float(cyl.radius)


def probe_points(scene) -> dict[str, list[tuple[float, np.ndarray]]]:
    """(distance along the ray [m], point [m]) of the probes of each ray that lie in the rock: inside the box, in
    none of the openings."""
    gz, _ = load_patch(scene)
    lo, hi = np.asarray(scene.mesh.lo), np.asarray(scene.mesh.hi)
    sections = facility_sections(scene)
    out = {}
    for name, angle in RAYS.items():
        a = math.radians(angle)
        direction = np.array([0.0, -math.sin(a), -math.cos(a)])
        pts = [(r, gz + r * direction) for r in PROBE_DISTANCES]
        out[name] = [
            (r, p)
            for r, p in pts
            if np.all(p >= lo + 0.5) and np.all(p <= hi - 0.5) and not any(sec.contains(p) for sec in sections)
        ]
    return out


def patch_distance(scene, x: np.ndarray) -> float:
    """Distance from a point to the loaded patch (a disc on the surface) [m]."""
    gz, radius = load_patch(scene)
    rho = math.hypot(x[0] - gz[0], x[1] - gz[1])
    return math.hypot(max(rho - radius, 0.0), gz[2] - x[2])


def current_positions(sim) -> np.ndarray:
    """Node positions now [m], shape (N, 3), float64 (reference + displacement)."""
    nn = int(sim.state.node_count.numpy()[0])
    return sim.model.node_ref_q.numpy()[:nn].astype(np.float64) + sim.state.node_u.numpy()[:nn].astype(np.float64)


def rubble(sim, sections: list[Section]) -> list[float]:
    """Volume of block material inside each section at the blocks' current pose [m³] (module docstring)."""
    s, m = sim.state, sim.model
    nt = int(s.tet_count.numpy()[0])
    tets = m.tet_nodes.numpy()[:nt].astype(np.int64)
    x = current_positions(sim)
    volume = m.tet_volume.numpy()[:nt].astype(np.float64)
    points = np.einsum("qa,tai->tqi", KEAST_2, x[tets])  # (T, 4, 3)
    return [float(np.sum(0.25 * volume[:, None] * sec.contains(points))) for sec in sections]


def block_centres(sim) -> np.ndarray:
    """Each body's centre of mass at the switch [m], shape (B, 3): the volume-weighted centroid of its tets."""
    s, m = sim.state, sim.model
    nt = int(s.tet_count.numpy()[0])
    tets = m.tet_nodes.numpy()[:nt].astype(np.int64)
    body = s.node_body.numpy()[tets[:, 0]].astype(np.int64)
    x0 = m.node_ref_q.numpy().astype(np.float64) + s.node_rigid_u0.numpy().astype(np.float64)
    centroid = x0[tets].mean(axis=1)
    volume = m.tet_volume.numpy()[:nt].astype(np.float64)
    count = s.body_mass.shape[0]
    weight = np.bincount(body, weights=volume, minlength=count)
    return (
        np.stack([np.bincount(body, weights=volume * centroid[:, k], minlength=count) for k in range(3)], 1)
        / (weight[:, None])
    )


def roof_motion(sim, centres: np.ndarray, room: Section) -> tuple[float, float, float]:
    """The largest room's roof: the blocks whose centre lies over the room's footprint and within LAYER above its
    roof. Their mean and largest downward displacement [m] and their mean downward speed [m/s]."""
    over = np.all((centres[:, :2] > room.lo[:2]) & (centres[:, :2] < room.hi[:2]), axis=1)
    roof = over & (centres[:, 2] > room.hi[2]) & (centres[:, 2] <= room.hi[2] + LAYER)
    drop = -sim.state.body_dc.numpy()[roof, 2]
    sink = -sim.state.body_v.numpy()[roof, 2]
    return float(drop.mean()), float(drop.max()), float(sink.mean())


def chimneys(sim, sections: list[Section], top: float) -> list[tuple[float, list[float]]]:
    """For each section: the chimney height above its roof [m] and the largest block displacement of each 2 m layer
    above the roof [m] (module docstring)."""
    centres = block_centres(sim)
    moved = np.linalg.norm(sim.state.body_dc.numpy(), axis=1)
    out = []
    for sec in sections:
        over = np.all((centres[:, :2] >= sec.lo[:2]) & (centres[:, :2] <= sec.hi[:2]), axis=1)
        roof = sec.hi[2]
        layers = []
        for k in range(max(0, math.ceil((top - roof) / LAYER))):
            inside = over & (centres[:, 2] > roof + k * LAYER) & (centres[:, 2] <= roof + (k + 1) * LAYER)
            layers.append(float(moved[inside].max()) if np.any(inside) else 0.0)
        height = 0.0
        for k, d in enumerate(layers):
            if d <= CHIMNEY_DISPLACEMENT:
                break
            height = min((k + 1) * LAYER, top - roof)
        out.append((height, layers))
    return out


def plane_section(points: np.ndarray, tets: np.ndarray, axis: int, at: float) -> tuple[list[np.ndarray], np.ndarray]:
    """The polygons where the plane x[axis] = at cuts the tets (triangles or quadrilaterals, in the plane's other two
    coordinates, in order around their centre), and the tet each belongs to."""
    d = points[tets][:, :, axis] - at  # (T, 4)
    cut = np.flatnonzero((d.min(axis=1) < 0.0) & (d.max(axis=1) > 0.0))
    keep = [k for k in range(3) if k != axis]
    polygons = []
    for t in cut:
        corners = []
        for a, b in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
            da, db = d[t, a], d[t, b]
            if (da < 0.0) != (db < 0.0):
                pa, pb = points[tets[t, a]], points[tets[t, b]]
                corners.append((pa + da / (da - db) * (pb - pa))[keep])
        c = np.asarray(corners)
        centre = c.mean(axis=0)
        polygons.append(c[np.argsort(np.arctan2(c[:, 1] - centre[1], c[:, 0] - centre[0]))])
    return polygons, cut


def draw_sections(results: list[dict], path: Path) -> None:
    """One row per scene: the section through the main tunnel's axis (y = const) coloured by the blocks' speed at
    SNAPSHOT_TIME, and by their displacement at the end (log scales)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import LogNorm

    fig, axes = plt.subplots(len(results), 2, figsize=(12, 4.6 * len(results)), squeeze=False)
    for row, r in zip(axes, results, strict=True):
        pic = r["_pictures"]
        for ax, (x, value, title, unit, lo) in zip(
            row,
            (
                (pic["x_snap"], pic["speed_snap"], f"speed at {pic['t_snap'] * 1e3:.0f} ms", "m/s", 1e-3),
                (pic["x_end"], pic["moved_end"], f"displacement at {r['end_time'] * 1e3:.0f} ms", "m", 1e-4),
            ),
            strict=True,
        ):
            # A hair off the plane: nodes lying on it exactly would leave their tets out of the section.
            polygons, tet = plane_section(x, pic["tets"], 1, pic["y"] + 1e-3)
            values = np.maximum(value[tet], lo)
            collection = PolyCollection(
                polygons, array=values, cmap="inferno", norm=LogNorm(lo, max(values.max(), lo * 10))
            )
            collection.set_edgecolor("face")
            ax.add_collection(collection)
            ax.set_xlim(pic["lo"][0], pic["hi"][0])
            ax.set_ylim(pic["lo"][2], pic["hi"][2])
            ax.set_aspect("equal")
            ax.set_title(f"{r['scene']}: {title}, section y = {pic['y']:g} m")
            ax.set_xlabel("x [m]")
            ax.set_ylabel("z [m]")
            fig.colorbar(collection, ax=ax, label=unit, shrink=0.8)
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(path)


def report(scene, device: str, end_time: float | None) -> dict:
    """Runs one scene and measures what the module docstring lists; returns the figures as a dict."""
    from warpdem.rigid import rigid_time_step
    from warpdem.scene_build import build_scene
    from warpdem.simulation import Simulation

    start = time.perf_counter()
    model, state = build_scene(scene, device)
    if scene.rigid.enabled and scene.run.dt == "auto":  # as the runner does: the blocks' own step
        model = rigid_time_step(model, state, scene.run.safety_factor)
    sim = Simulation(model, state)
    built = time.perf_counter() - start
    ref = model.node_ref_q.numpy()[: int(state.node_count.numpy()[0])].astype(np.float64)
    probes = {
        ray: [(patch_distance(scene, p), int(np.argmin(np.linalg.norm(ref - p, axis=1)))) for _, p in pts]
        for ray, pts in probe_points(scene).items()
    }
    nodes = np.array(sorted({i for pts in probes.values() for _, i in pts}))
    steps = max(1, round((end_time or scene.run.end_time) / model.dt))
    times, speeds = [0.0], [np.zeros(len(nodes))]
    nt = int(sim.state.tet_count.numpy()[0])
    tets = model.tet_nodes.numpy()[:nt].astype(np.int64)
    tet_body = sim.state.node_body.numpy()[tets[:, 0]].astype(np.int64)
    snap_step = min(steps, round(SNAPSHOT_TIME / model.dt))
    wave_steps = min(steps, round(WAVE_WINDOW / model.dt))
    rubble_steps = max(1, round(RUBBLE_INTERVAL / model.dt))
    sections = facility_sections(scene)
    room = next(sec for sec in sections if sec.kind == "room")
    pictures = {"tets": tets, "y": 0.5 * (room.lo[1] + room.hi[1])}
    pictures.update(lo=np.asarray(scene.mesh.lo), hi=np.asarray(scene.mesh.hi))
    from warpdem.simulation import balance_error

    start_energy = sim.energy()
    in_play = start_energy.in_play
    history = {"time": [0.0], "rubble": [[0.0] * len(sections)], "roof": [(0.0, 0.0, 0.0)]}
    centres = None
    done, samples = 0, 0
    while done < steps:
        # Stop at every read-back the run needs: the probes (every SAMPLE_STEPS steps within WAVE_WINDOW), the
        # snapshot, the rubble and roof (every rubble_steps steps), the end.
        marks = [steps, snap_step, rubble_steps * (done // rubble_steps + 1)]
        if done < wave_steps:
            marks.append(min(done + SAMPLE_STEPS, wave_steps))
        n = min(m for m in marks if m > done) - done
        sim.advance(n)
        done += n
        samples += 1
        if done == snap_step:
            pictures["t_snap"] = done * model.dt
            pictures["x_snap"] = current_positions(sim)
            pictures["speed_snap"] = np.linalg.norm(sim.state.body_v.numpy(), axis=1)[tet_body]
        if done <= wave_steps:
            v = sim.state.node_qd.numpy()[nodes].astype(np.float64)
            times.append(done * model.dt)
            speeds.append(np.linalg.norm(v, axis=1))
        if done % rubble_steps == 0 or done == steps:
            centres = block_centres(sim) if centres is None else centres
            history["time"].append(done * model.dt)
            history["rubble"].append(rubble(sim, sections))
            history["roof"].append(roof_motion(sim, centres, room))
        if samples % ENERGY_SAMPLES == 0 or done == steps:
            in_play = max(in_play, sim.energy().in_play)
    run = time.perf_counter() - start - built
    t, speed = np.asarray(times), np.stack(speeds)
    column = {int(i): k for k, i in enumerate(nodes)}
    c_p = p_wave_speed(scene)
    waves = {}
    for ray, pts in probes.items():
        rows = []
        for d, i in pts:
            v = speed[:, column[i]]
            peak = float(v.max())
            threshold = max(ARRIVAL_FRACTION * peak, ARRIVAL_FLOOR)
            arrival = float(t[np.argmax(v > threshold)]) if peak > threshold else math.nan
            rows.append({"distance": d, "node": i, "arrival": arrival, "ppv": peak})
        d = np.array([r["distance"] for r in rows])
        ta = np.array([r["arrival"] for r in rows])
        ok = np.isfinite(ta)
        slope = float(np.polyfit(ta[ok], d[ok], 1)[0]) if np.count_nonzero(ok) >= 3 else math.nan
        waves[ray] = {"probes": rows, "speed": slope}
    down = waves["down"]["probes"]
    d = np.array([r["distance"] for r in down])
    ppv = np.array([r["ppv"] for r in down])
    exponent = float(-np.polyfit(np.log(d), np.log(ppv), 1)[0]) if np.all(ppv > 0) else math.nan
    pictures["x_end"] = current_positions(sim)
    pictures["moved_end"] = np.linalg.norm(sim.state.body_dc.numpy(), axis=1)[tet_body]
    volumes = history["rubble"][-1]
    chimney = chimneys(sim, sections, float(scene.mesh.hi[2]))
    return {
        "scene": scene.name,
        "blocks": int(sim.state.body_mass.shape[0]),
        "tets": int(sim.state.tet_count.numpy()[0]),
        "dt": model.dt,
        "steps": steps,
        "end_time": steps * model.dt,
        "build_s": built,
        "run_s": run,
        "c_p": c_p,
        "books": balance_error(start_energy, sim.energy(), in_play),
        "in_play": in_play,
        "_pictures": pictures,
        "waves": waves,
        "attenuation_exponent": exponent,
        "sections": [
            {"name": s.name, "kind": s.kind, "volume": s.volume, "rubble": v, "chimney": c[0], "layers": c[1]}
            for s, v, c in zip(sections, volumes, chimney, strict=True)
        ],
        "history": history,
        "gravity": float(-scene.gravity.vector[2]) if scene.gravity is not None else 0.0,
    }


def format_side_by_side(results: list[dict]) -> list[str]:
    """The figures of the scenes in columns, one row per quantity."""
    names = [r["scene"].removeprefix("facility_") for r in results]
    width = 24

    def row(label: str, values: list[str]) -> str:
        return f"{label:<44}" + "".join(f"{v:>{width}}" for v in values)

    lines = [row("", names)]
    lines.append(row("blocks / tets", [f"{r['blocks']} / {r['tets']}" for r in results]))
    lines.append(
        row(
            "dt [µs], steps, end [ms]",
            [f"{r['dt'] * 1e6:.2f}, {r['steps']}, {r['end_time'] * 1e3:.1f}" for r in results],
        )
    )
    lines.append(row("build / run wall [s]", [f"{r['build_s']:.0f} / {r['run_s']:.0f}" for r in results]))
    lines.append(row("books: error / energy in play", [f"{r['books']:+.2e} of {r['in_play']:.3g} J" for r in results]))
    lines.append(
        f"wave speed by direction (first arrival at {ARRIVAL_FRACTION:.0%} of each probe's peak speed; "
        f"granite c_p = {results[0]['c_p']:.0f} m/s):"
    )
    for ray in RAYS:
        lines.append(
            row(
                f"  {ray}: speed [m/s] (/c_p)",
                [f"{r['waves'][ray]['speed']:.0f} ({r['waves'][ray]['speed'] / r['c_p']:.2f})" for r in results],
            )
        )
        for k in range(len(results[0]["waves"][ray]["probes"])):
            p0 = results[0]["waves"][ray]["probes"][k]
            lines.append(
                row(
                    f"    d = {p0['distance']:5.2f} m: arrival [ms], PPV [m/s]",
                    [
                        f"{probe['arrival'] * 1e3:.2f}, {probe['ppv']:.3g}"
                        for probe in (r["waves"][ray]["probes"][k] for r in results)
                    ],
                )
            )
    lines.append(
        row(
            "anisotropy: speed down / 45° / 75°",
            [
                f"1 / {r['waves']['45°']['speed'] / r['waves']['down']['speed']:.2f} / "
                f"{r['waves']['75°']['speed'] / r['waves']['down']['speed']:.2f}"
                for r in results
            ],
        )
    )
    lines.append(row("attenuation: PPV ∝ d^-n straight down, n", [f"{r['attenuation_exponent']:.2f}" for r in results]))
    lines.append(
        f"rubble in each opening section at the end [m³] (share of the section); chimney above it [m] "
        f"(layers with a block moved > {CHIMNEY_DISPLACEMENT * 100:.0f} cm):"
    )
    for k, sec in enumerate(results[0]["sections"]):
        lines.append(
            row(
                f"  {sec['name']} ({sec['volume']:.0f} m³)",
                [
                    f"{s['rubble']:.2f} ({s['rubble'] / s['volume']:.1%}), {s['chimney']:.0f} m"
                    for s in (r["sections"][k] for r in results)
                ],
            )
        )
    lines.append("rubble at the end by kind of section [m³] (share of their volume):")
    for kind, label in (("room", "largest room"), ("junction", "junctions"), ("tunnel", "straight tunnel stretches")):
        cells = []
        for r in results:
            parts = [s for s in r["sections"] if s["kind"] == kind]
            total, volume = sum(s["rubble"] for s in parts), sum(s["volume"] for s in parts)
            cells.append(f"{total:.2f} ({total / volume:.1%})")
        lines.append(row(f"  {label}", cells))
    lines.append(
        "largest room over time: rubble [m³]; its roof blocks' mean / largest drop [cm] and mean sinking speed [m/s] "
        "(free fall from rest: ½ g t², g t):"
    )
    for k, when in enumerate(results[0]["history"]["time"]):
        if k == 0 or (k % REPORT_EVERY and k != len(results[0]["history"]["time"]) - 1):
            continue
        g = results[0]["gravity"]
        cells = []
        for r in results:
            h = r["history"]
            if k >= len(h["time"]):
                cells.append("")
                continue
            room = next(i for i, s in enumerate(r["sections"]) if s["kind"] == "room")
            mean, most, sink = h["roof"][k]
            cells.append(f"{h['rubble'][k][room]:.2f}; {mean * 100:.1f} / {most * 100:.1f}, {sink:.2f}")
        lines.append(row(f"  t = {when * 1e3:5.1f} ms ({0.5 * g * when**2 * 100:.1f} cm, {g * when:.2f} m/s)", cells))
    lines.append("largest block displacement [cm] by 2 m layer above each section's roof, bottom up:")
    for k, sec in enumerate(results[0]["sections"]):
        for r in results:
            layers = " ".join(f"{d * 100:.1f}" for d in r["sections"][k]["layers"])
            lines.append(f"  {sec['name']:<36} {r['scene'].removeprefix('facility_'):<14} {layers}")
    return lines


def main(argv: list[str] | None = None) -> int:
    from scene_reports import chosen_scenes, scene_parser  # beside this script, in benchmarks/

    parser = scene_parser(__doc__, SCENES, every="both")
    parser.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    parser.add_argument("--picture", type=Path, help="also draw the sections of the scenes to this PNG file")
    args = parser.parse_args(argv)
    names = chosen_scenes(parser, args, SCENES)
    from warpdem.cli import init_warp
    from warpdem.scene import load_scene

    init_warp()
    results = []
    for name in names:
        results.append(report(load_scene(SCENES_DIR / f"{name}.toml"), args.device, args.end_time))
        print(f"{name}: built in {results[-1]['build_s']:.0f} s, ran in {results[-1]['run_s']:.0f} s", flush=True)
    print("\n".join(format_side_by_side(results)))
    if args.picture is not None:
        draw_sections(results, args.picture)
    if args.json is not None:
        args.json.write_text(json.dumps([{k: v for k, v in r.items() if k != "_pictures"} for r in results], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
