"""Report of the LDEC §3 facility scenes (issue 11 §4): ``python benchmarks/facility_scenes.py [SCENE ...]
[--device cpu] [--end-time T] [--json FILE] [--picture PNG]`` with SCENE among facility_persistent,
facility_nonpersistent (default: both, printed side by side).

Each scene is built as ``python -m warpdem`` builds it (:func:`warpdem.build.scene_build.build_scene`, rigid blocks from
t = 0) and stepped in Python, read back every SAMPLE_STEPS steps. What LDEC §3 reports, measured:

- wave speed by direction: probes on three rays from ground zero (the centre of the loaded patch on the surface):
  straight down, 45° and 75° from the vertical. A probe is the mesh node nearest each point 2, 4, ... m along the ray;
  its first arrival is the first sample at which its speed exceeds ARRIVAL_FRACTION of its own peak (and
  ARRIVAL_FLOOR, above the settling under gravity; a probe that never exceeds it is not reached). The distance
  travelled is the distance from the loaded patch (a disc of the load's radius on the surface), and the ray's speed
  the least-squares slope of distance against arrival time (anisotropy: the ratio of the slopes), set against the
  granite's P-wave speed c_p = sqrt((λ + 2μ)/ρ);
- attenuation with distance, as LDEC's Fig. 7 shows it (the wave): the peak particle speed of the first pulse (PPV) at
  free-field probes, fitted over all of them as PPV ∝ r⁻ⁿ (r the distance from ground zero) and as PPV ∝ e^(−α r)/r (a
  body wave's geometric spreading 1/r times an attenuation coefficient α [1/m]). The probes: the mesh node nearest
  each point 2, 4, ... m from ground zero on rays at ATTENUATION_POLAR from the vertical and ATTENUATION_AZIMUTHS
  around it, kept only where the wave reaches them through rock alone: the straight path from ground zero crosses no
  opening (no diffracted or shadowed probes), the probe's block does not reach over an opening (the column above an
  opening has nothing beneath it: the blast drives it down as a whole into the opening, which is collapse, not the
  wave, and the opening's roof sends the pulse back as a free-surface reflection; this leaves out every probe within 4
  m of ground zero, which lies over the largest room), and its block is not held. The wave's particle velocity: the
  probe's velocity less that of the same node in the scene run without its loads (:func:`settling_velocities`: the
  unstressed rock settling under gravity, as fast as the far probes' PPV). Its first pulse: its speed from its first
  arrival t_a (the first sample past ARRIVAL_FRACTION of its peak) for T + t_a, T the load's pulse, rise + decay time
  (3.3 ms: the load's history is done to e⁻¹ of its peak), lengthened by as much as the travel time because the
  jointed mass spreads the pulse as it goes (the blocks on their joint springs are a lattice that passes nothing much
  faster than its blocks' natural period, 2π sqrt(m / (k_n A)) ~ 9 ms: the particle speed at the probes rises for
  milliseconds after the first arrival); cut short where the wave reflected by the held frame can arrive, at t_a r'/r,
  r' the distance from the mirror image of ground zero in the nearest held face (the echo at the direct wave's own
  mean speed), which in this 24 m box is what ends most windows. As a check of the window, the same fit of the largest
  speed within WAVE_WINDOW (echoes included: LDEC's Fig. 7 at 30 ms, 10 ms at 1:3);
- diffraction around the largest room (LDEC: "the irregular model resulted in more diffraction of waves around
  cavities"): the first-pulse PPV (as above) at SHADOW probes, the free nodes nearest points half a metre below the
  room's floor over its footprint (inset by a metre), which the straight path from ground zero reaches only through
  the room, against LIT probes at the same depth on a ring of LIT_RING about ground zero whose straight path crosses
  no opening. Each PPV is scaled by its distance r from ground zero (a body wave's spreading, 1/r, taken out) and the
  measure is the mean of PPV·r in the shadow over its mean on the lit ring, with its standard error: 0 for a cavity
  that casts a full shadow, more where the wave bends round it. Not a transmitted share: the patch radiates more
  straight down than 25° off the vertical, where the ring lies, so an unobstructed rock reads above 1; the measure is
  for comparing the two geologies, which share the source. The first arrivals' medians beside it;
- the load as delivered: the loaded area [m²] and the normal impulse [N s] of the pressure load at the end (the
  run's summary's figures, warpdem.load_data), so the two geologies are seen to take the same blast;
- rubble: the volume of block material inside each opening's original cross-section (each tet sampled at the four
  points of the degree-2 Keast rule, each carrying a quarter of its volume, at the blocks' current pose), every
  RUBBLE_INTERVAL, section by section: the largest room, the plain tunnel stretches, the junctions (main tunnel with
  the shaft and with the access tunnel), the access tunnel's arms, the shaft; and summed by kind (room, junctions,
  straight stretches);
- the largest room's roof over time: the blocks over its footprint in the first layer above its roof (the roof bed, up
  to the first bedding plane), their mean and largest drop and mean sinking speed, against free fall from rest (½ g
  t², g t);
- chimney (collapse above an opening), every RUBBLE_INTERVAL: above each opening section, the blocks whose centre lies
  over its footprint (strictly inside: a block straddling a wall rests on it), layer by layer up from its roof: the
  roof bed, then bed by bed between the bedding planes (:func:`layer_edges`). A block's sinking is its drop relative
  to the mean drop of the same layer's free-field blocks, those that reach over no opening (centre ± half a block) and
  are not held: what the blast pushed down and what the rock settles by, everywhere, is taken out, and what is left is
  the block's slip into the opening. A layer has collapsed when one of its blocks has sunk more than CHIMNEY_DROP; the
  chimney is the height above the roof of the top of the highest layer up to which every layer has collapsed.

Wave figures are read within WAVE_WINDOW; the rest at the end (the scene's end_time unless ``--end-time``: the
chimneys and the largest room's rubble are reported at 200 ms, ``--end-time 0.2``).
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
ATTENUATION_POLAR = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)
"""Angles from the vertical of the attenuation probes' rays [deg]."""
ATTENUATION_AZIMUTHS = 8
"""Rays at each angle from the vertical, evenly spaced around it (every 45°: along and between the openings' axes)."""
SHADOW_DEPTH = 0.5
"""Depth of the diffraction probes below the largest room's floor [m]: in the blocks the room's floor cuts, above
the held base layer."""
LIT_RING = 8.0
"""Horizontal radius of the lit diffraction probes' ring about ground zero [m]: outside the room's footprint and the
main tunnel's, at 17.5-19.2 m from ground zero as the shadow probes' 17.5-17.8 m."""
LIT_AZIMUTHS = 16
"""Points on the lit ring, evenly spaced (those whose path crosses an opening, or that lie over one, are dropped)."""
CHIMNEY_DROP = 0.1
"""A block above an opening has collapsed once it has sunk this much below its layer's reference blocks [m]. The
joints close under the blast's peak by p/k_n = 100 MPa / 2.5 GPa/m = 4 cm at the surface (less deeper, where the
pulse has spread) and open again after it: a sinking of more than twice that, 5 % of a block's size, is slip on the
joints, not their elastic closure."""
LAYER = 2.0
"""The blocks' size [m] (the joint spacing of both scenes): a block whose centre lies more than half of it outside a
footprint does not reach over it."""
ENERGY_SAMPLES = 25
"""Samples between readings of the energy in play (the balance's scale, its largest value over the run)."""
SNAPSHOT_TIME = 0.01
"""Time of the velocity-field section [s]: LDEC's Fig. 7 compares the velocity fields at 30 ms, 10 ms at 1:3."""
WAVE_WINDOW = 0.01
"""The probes' speeds are read up to this time [s]: the direct wave has passed every probe by 5 ms, and later the
blocks over the room fall freely (g t), which is not the wave's PPV."""
RUBBLE_INTERVAL = 0.005
"""Time between readings of the rubble in each section and of the room's roof [s]."""
REPORT_EVERY = 2
"""The side-by-side table prints every this many readings of the room (and the last)."""
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


def in_box(lo: np.ndarray, hi: np.ndarray, p: np.ndarray) -> bool:
    """Whether a probe point ``p`` [m] lies at least half a metre inside the box ``lo``..``hi`` [m] (its nearest node
    is then not on a held face)."""
    return bool(np.all(p >= lo + 0.5) and np.all(p <= hi - 0.5))


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
        out[name] = [(r, p) for r, p in pts if in_box(lo, hi, p) and not any(sec.contains(p) for sec in sections)]
    return out


def over_opening(sections: list[Section], lo: np.ndarray, hi: np.ndarray | None = None) -> bool:
    """Whether a point ``lo`` [m], or a box ``lo``..``hi`` [m] (a block's extent), lies in the column above an
    opening section: overlapping its footprint (strictly: a box that only touches a wall's plane does not), not below
    its roof."""
    hi = lo if hi is None else hi
    return any(bool(np.all((hi[:2] > sec.lo[:2]) & (lo[:2] < sec.hi[:2])) and hi[2] > sec.hi[2]) for sec in sections)


def attenuation_probes(scene) -> list[tuple[float, np.ndarray]]:
    """(distance from ground zero [m], point [m]) of the free-field probes of the attenuation fit (module docstring):
    on rays at ATTENUATION_POLAR from the vertical and ATTENUATION_AZIMUTHS around it, at PROBE_DISTANCES, in the
    rock at least 0.5 m inside the box, not over an opening, and reached from ground zero along a straight path
    through no opening (checked every 5 cm). Whether a probe's block is held is for the caller (the built model)."""
    gz, _ = load_patch(scene)
    lo, hi = np.asarray(scene.mesh.lo), np.asarray(scene.mesh.hi)
    sections = facility_sections(scene)
    out = []
    for polar in ATTENUATION_POLAR:
        a = math.radians(polar)
        for k in range(ATTENUATION_AZIMUTHS if polar > 0.0 else 1):
            b = 2.0 * math.pi * k / ATTENUATION_AZIMUTHS
            direction = np.array([math.sin(a) * math.cos(b), math.sin(a) * math.sin(b), -math.cos(a)])
            for r in PROBE_DISTANCES:
                p = gz + r * direction
                if not in_box(lo, hi, p) or over_opening(sections, p):
                    continue
                if through_rock(sections, gz, p):
                    out.append((r, p))
    return out


def through_rock(sections: list[Section], gz: np.ndarray, p: np.ndarray) -> bool:
    """Whether the straight path from ground zero ``gz`` to ``p`` [m] crosses no opening section (checked every
    5 cm)."""
    r = float(np.linalg.norm(p - gz))
    path = gz + np.linspace(0.0, 1.0, max(2, math.ceil(r / 0.05) + 1))[:, None] * (p - gz)
    return not any(np.any(sec.contains(path)) for sec in sections)


def diffraction_probes(scene) -> dict[str, list[np.ndarray]]:
    """The points [m] of the diffraction measure (module docstring): "shadow", every 2 m over the largest room's
    footprint inset by 1 m, SHADOW_DEPTH below its floor (the path from ground zero runs through the room); "lit",
    LIT_AZIMUTHS points on a ring of LIT_RING about ground zero at the same depth, kept where the path crosses no
    opening and the point lies over none, at least 0.5 m inside the box. Whether a probe's block is held is for the
    caller."""
    gz, _ = load_patch(scene)
    lo, hi = np.asarray(scene.mesh.lo), np.asarray(scene.mesh.hi)
    sections = facility_sections(scene)
    room = next(sec for sec in sections if sec.kind == "room")
    z = room.lo[2] - SHADOW_DEPTH
    grid = [np.arange(room.lo[k] + 1.0, room.hi[k] - 0.5, 2.0) for k in range(2)]
    shadow = [np.array([x, y, z]) for x in grid[0] for y in grid[1]]
    lit = []
    for k in range(LIT_AZIMUTHS):
        b = 2.0 * math.pi * k / LIT_AZIMUTHS
        p = np.array([gz[0] + LIT_RING * math.cos(b), gz[1] + LIT_RING * math.sin(b), z])
        if in_box(lo, hi, p) and not over_opening(sections, p) and through_rock(sections, gz, p):
            lit.append(p)
    return {"shadow": shadow, "lit": lit}


def echo_distance(scene, x: np.ndarray) -> float:
    """Distance from the mirror image of ground zero in the nearest held face of the box (the sides and the base,
    fixed in both scenes) to a point [m]: the path of the first wave the frame reflects to it."""
    gz, _ = load_patch(scene)
    lo, hi = np.asarray(scene.mesh.lo), np.asarray(scene.mesh.hi)
    images = []
    for axis, plane in ((0, lo[0]), (0, hi[0]), (1, lo[1]), (1, hi[1]), (2, lo[2])):
        image = gz.copy()
        image[axis] = 2.0 * plane - gz[axis]
        images.append(float(np.linalg.norm(x - image)))
    return min(images)


def first_arrival(t: np.ndarray, v: np.ndarray, floor: float = ARRIVAL_FLOOR) -> tuple[float, float]:
    """A probe's first arrival [s] from its speeds v [m/s] sampled at times t [s]: the first sample past
    ARRIVAL_FRACTION of its peak speed and ``floor`` [m/s] (NaN if never); and that peak [m/s]."""
    peak = float(v.max())
    threshold = max(ARRIVAL_FRACTION * peak, floor)
    return (float(t[np.argmax(v > threshold)]) if peak > threshold else math.nan), peak


def first_pulse_ppv(t: np.ndarray, v: np.ndarray, distance: float, echo: float, pulse: float) -> tuple[float, float]:
    """The first pulse's peak particle speed [m/s] of a probe (module docstring): the largest speed v [m/s] of the
    wave (the settling under gravity taken out) at times t [s] within [t_a, t_a + min(pulse + t_a, t_a (echo −
    distance) / distance)], t_a its first arrival [s], ``pulse`` the load's rise + decay time [s], ``distance`` and
    ``echo`` its distances from ground zero and from its mirror image in the held frame [m]. Returns (t_a, PPV),
    NaN where the wave never arrived."""
    arrival, _ = first_arrival(t, v, floor=0.0)  # the settling is taken out of v: no floor above it
    if not math.isfinite(arrival):
        return math.nan, math.nan
    end = arrival + min(pulse + arrival, arrival * (echo - distance) / distance)
    return arrival, float(v[(t >= arrival) & (t <= end)].max())


def attenuation_fit(r: np.ndarray, ppv: np.ndarray) -> dict:
    """Least-squares fits of the first-pulse PPV [m/s] against the distance r [m]: PPV ∝ r⁻ⁿ (log PPV against log r)
    and PPV ∝ e^(−α r)/r (log(PPV r) against r). Returns n, α [1/m], their standard errors and the probe count."""
    (slope_n, _), cov_n = np.polyfit(np.log(r), np.log(ppv), 1, cov=True)
    (slope_a, _), cov_a = np.polyfit(r, np.log(ppv * r), 1, cov=True)
    return {
        "n": float(-slope_n),
        "n_se": float(math.sqrt(cov_n[0, 0])),
        "alpha": float(-slope_a),
        "alpha_se": float(math.sqrt(cov_a[0, 0])),
        "probes": len(r),
    }


def diffraction_summary(shadow: list[dict], lit: list[dict]) -> dict:
    """The diffraction measure from the shadow and lit probes' rows (``distance`` [m], ``arrival`` [s], ``ppv``
    [m/s]; module docstring): ``ratio``, the mean of PPV·r over the reached shadow probes (an average over the room's
    footprint: the probes lie on an even grid) over its mean on the lit ring, with its standard error ``ratio_se``
    (each mean's standard error, s/sqrt(k), propagated to first order; NaN without two reached probes on either side);
    the medians of the first arrivals [s]; and the probes reached on each side."""

    def reached(rows: list[dict]) -> np.ndarray:
        ok = [p for p in rows if math.isfinite(p["ppv"]) and p["ppv"] > 0.0]
        return np.array([[p["ppv"] * p["distance"], p["arrival"]] for p in ok]).reshape(-1, 2)

    s, li = reached(shadow), reached(lit)
    if len(s) < 2 or len(li) < 2:
        nan = math.nan
        return {"ratio": nan, "ratio_se": nan, "shadow_arrival": nan, "lit_arrival": nan, "reached": (len(s), len(li))}
    mean_s, mean_l = float(s[:, 0].mean()), float(li[:, 0].mean())
    rel_s = float(s[:, 0].std(ddof=1)) / math.sqrt(len(s)) / mean_s
    rel_l = float(li[:, 0].std(ddof=1)) / math.sqrt(len(li)) / mean_l
    ratio = mean_s / mean_l
    return {
        "ratio": ratio,
        "ratio_se": ratio * math.hypot(rel_s, rel_l),
        "shadow_arrival": float(np.median(s[:, 1])),
        "lit_arrival": float(np.median(li[:, 1])),
        "reached": (len(s), len(li)),
    }


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


def bedding_planes(scene) -> np.ndarray:
    """Heights of the bedding planes [m], sorted: the planes of the horizontal joint sets (dip 0) strictly inside
    the box (``n · x = offset + k spacing`` with n = ±z, warpdem.build.geology.joint_normal)."""
    from warpdem.build.geology import joint_normal

    lo, hi = float(scene.mesh.lo[2]), float(scene.mesh.hi[2])
    heights = set()
    for js in scene.mesh.joint_sets:
        if js.dip != 0.0:
            continue
        nz = float(joint_normal(js.dip, js.dip_direction)[2])  # ±1
        d0, d1 = sorted((lo * nz, hi * nz))
        for k in range(math.floor((d0 - js.offset) / js.spacing), math.ceil((d1 - js.offset) / js.spacing) + 1):
            z = (js.offset + k * js.spacing) / nz
            if lo < z < hi:
                heights.add(round(z, 9))
    return np.array(sorted(heights))


def layer_edges(planes: np.ndarray, roof: float, top: float) -> np.ndarray:
    """The layers above an opening's roof [m]: from the roof to the first bedding plane above it, then bed by bed to
    the surface ``top`` (a block belongs to the layer its centre lies in)."""
    if roof >= top:  # the shaft: open to the surface, nothing above it
        return np.array([roof])
    return np.concatenate([[roof], planes[(planes > roof) & (planes < top)], [top]])


def roof_motion(sim, centres: np.ndarray, room: Section, planes: np.ndarray) -> tuple[float, float, float]:
    """The largest room's roof: the blocks whose centre lies over the room's footprint, in the first layer above
    its roof (up to the first bedding plane, ``planes`` [m]). Their mean and largest downward displacement [m] and
    their mean downward speed [m/s]."""
    first = layer_edges(planes, room.hi[2], np.inf)[1]
    over = np.all((centres[:, :2] > room.lo[:2]) & (centres[:, :2] < room.hi[:2]), axis=1)
    roof = over & (centres[:, 2] > room.hi[2]) & (centres[:, 2] <= first)
    drop = -sim.state.body_dc.numpy()[roof, 2]
    sink = -sim.state.body_v.numpy()[roof, 2]
    return float(drop.mean()), float(drop.max()), float(sink.mean())


def chimneys(
    centres: np.ndarray, fixed: np.ndarray, dc: np.ndarray, sections: list[Section], planes: np.ndarray, top: float
) -> list[tuple[float, list[float]]]:
    """For each section: the chimney height above its roof [m] and the largest sinking of a block in each layer
    above the roof (:func:`layer_edges`) [m] (module docstring), from the blocks' centres at the switch [m], shape
    (B, 3), whether each is held, shape (B,), their displacements now [m], shape (B, 3), and the bedding planes [m]."""
    half = 0.5 * LAYER  # a block's half size: a block whose centre is that far from a footprint does not overlap it
    free_field = ~fixed & ~np.array([over_opening(sections, c - half, c + half) for c in centres])
    out = []
    for sec in sections:
        over = np.all((centres[:, :2] > sec.lo[:2]) & (centres[:, :2] < sec.hi[:2]), axis=1)
        edges = layer_edges(planes, sec.hi[2], top)
        layers = []
        for z0, z1 in itertools.pairwise(edges):
            band = (centres[:, 2] > z0) & (centres[:, 2] <= z1)
            inside, reference = over & band, free_field & band
            settled = float(dc[reference, 2].mean()) if np.any(reference) else 0.0
            layers.append(float(np.max(settled - dc[inside, 2])) if np.any(inside) else 0.0)
        height = 0.0
        for z1, d in zip(edges[1:], layers, strict=True):
            if d <= CHIMNEY_DROP:
                break
            height = z1 - sec.hi[2]
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


def build_simulation(scene, device: str):
    """The scene built as ``python -m warpdem`` builds it (:func:`warpdem.build.scene_build.build_scene`), with the
    rigid blocks' own step where ``dt = "auto"`` (as the runner sets it), as a
    :class:`warpdem.simulation.Simulation`."""
    from warpdem.build.scene_build import build_scene
    from warpdem.simulation import Simulation
    from warpdem.stages.rigid_step import rigid_time_step

    model, state = build_scene(scene, device)
    if scene.rigid.enabled and scene.run.dt == "auto":
        model = rigid_time_step(model, state, scene.run.safety_factor)
    return Simulation(model, state)


def settling_velocities(
    scene, device: str, dt: float, ref: np.ndarray, nodes: np.ndarray, marks: list[int]
) -> np.ndarray:
    """Velocities [m/s] of ``nodes``, shape (len(marks), N, 3), after each of ``marks`` steps of ``dt`` [s] in the
    scene with its loads taken off: the rock under gravity alone, which starts unstressed and settles (its blocks
    fall at g until the joints beneath them take their weight, up to g t ~ 0.05-0.1 m/s within the wave's window,
    as large as the far probes' PPV). The loaded run less this one is the blast's wave: exactly while the joints
    respond linearly (penalty springs in contact, no slip), approximately where the wave makes them slip.
    ``ref`` and ``dt`` are the loaded model's node reference positions [m] and step [s]: the same are checked."""
    sim = build_simulation(scene.model_copy(update={"loads": []}), device)
    # The same mesh and blocks, so the same step (the blocks' own: their contacts, not the loads).
    if sim.model.dt != dt or not np.array_equal(sim.model.node_ref_q.numpy()[: len(ref)].astype(np.float64), ref):
        raise RuntimeError(f"{scene.name}: the scene without its loads builds another mesh or step")
    out, done = [], 0
    for mark in marks:
        sim.advance(mark - done)
        done = mark
        out.append(sim.state.node_qd.numpy()[nodes].astype(np.float64))
    return np.stack(out)


def report(scene, device: str, end_time: float | None) -> dict:
    """Runs one scene and measures what the module docstring lists; returns the figures as a dict (entries whose
    name starts with an underscore hold arrays: the pictures' and the blocks' history, left out of the JSON)."""
    from warpdem.stages.energy import balance_error

    start = time.perf_counter()
    sim = build_simulation(scene, device)
    model, state = sim.model, sim.state
    built = time.perf_counter() - start
    ref = model.node_ref_q.numpy()[: int(state.node_count.numpy()[0])].astype(np.float64)
    fixed = sim.state.body_fixed.numpy() != 0
    node_body = sim.state.node_body.numpy()

    def nearest(p: np.ndarray) -> int:
        return int(np.argmin(np.linalg.norm(ref - p, axis=1)))

    probes = {ray: [(patch_distance(scene, p), nearest(p)) for _, p in pts] for ray, pts in probe_points(scene).items()}
    field = {}  # node -> (distance from ground zero, echo distance): one probe per node, held blocks left out
    # Each block's extent [m] at the start: a probe's block must not reach over an opening either.
    extent_lo = np.full((len(fixed), 3), np.inf)
    extent_hi = np.full((len(fixed), 3), -np.inf)
    np.minimum.at(extent_lo, node_body[: len(ref)], ref)
    np.maximum.at(extent_hi, node_body[: len(ref)], ref)
    sections = facility_sections(scene)
    for r, p in attenuation_probes(scene):
        i = nearest(p)
        b = node_body[i]
        if not fixed[b] and i not in field and not over_opening(sections, extent_lo[b], extent_hi[b]):
            field[i] = (r, echo_distance(scene, ref[i]))
    free_nodes = np.flatnonzero(~fixed[node_body[: len(ref)]])
    gz, _ = load_patch(scene)
    bent = {}  # kind -> {node: distance from ground zero}: the diffraction probes, in free blocks (the base is held)
    for kind, pts in diffraction_probes(scene).items():
        near = (free_nodes[np.argmin(np.linalg.norm(ref[free_nodes] - q, axis=1))] for q in pts)
        bent[kind] = {int(i): float(np.linalg.norm(ref[i] - gz)) for i in near}
    nodes = np.array(
        sorted({i for pts in probes.values() for _, i in pts} | set(field) | {i for d in bent.values() for i in d})
    )
    steps = max(1, round((end_time or scene.run.end_time) / model.dt))
    times, sampled, velocities = [0.0], [], [np.zeros((len(nodes), 3))]
    nt = int(sim.state.tet_count.numpy()[0])
    tets = model.tet_nodes.numpy()[:nt].astype(np.int64)
    tet_body = node_body[tets[:, 0]].astype(np.int64)
    snap_step = min(steps, round(SNAPSHOT_TIME / model.dt))
    wave_steps = min(steps, round(WAVE_WINDOW / model.dt))
    rubble_steps = max(1, round(RUBBLE_INTERVAL / model.dt))
    room = next(sec for sec in sections if sec.kind == "room")
    top = float(scene.mesh.hi[2])
    planes = bedding_planes(scene)
    pictures = {"tets": tets, "y": 0.5 * (room.lo[1] + room.hi[1])}
    pictures.update(lo=np.asarray(scene.mesh.lo), hi=np.asarray(scene.mesh.hi))
    centres = block_centres(sim)
    start_energy = sim.energy()
    in_play = start_energy.in_play
    history = {
        "time": [0.0],
        "rubble": [[0.0] * len(sections)],
        "roof": [(0.0, 0.0, 0.0)],
        "chimney": [[0.0] * len(sections)],
    }
    blocks = {"centres": centres, "fixed": fixed, "dc": [np.zeros_like(centres)], "v": [np.zeros_like(centres)]}
    done, samples = 0, 0
    while done < steps:
        # Stop at every read-back the run needs: the probes (every SAMPLE_STEPS steps within WAVE_WINDOW), the
        # snapshot, the rubble, roof and chimneys (every rubble_steps steps), the end.
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
            times.append(done * model.dt)
            sampled.append(done)
            velocities.append(sim.state.node_qd.numpy()[nodes].astype(np.float64))
        if done % rubble_steps == 0 or done == steps:
            dc = sim.state.body_dc.numpy().astype(np.float64)
            history["time"].append(done * model.dt)
            history["rubble"].append(rubble(sim, sections))
            history["roof"].append(roof_motion(sim, centres, room, planes))
            history["chimney"].append([h for h, _ in chimneys(centres, fixed, dc, sections, planes, top)])
            blocks["dc"].append(dc)
            blocks["v"].append(sim.state.body_v.numpy().astype(np.float64))
        if samples % ENERGY_SAMPLES == 0 or done == steps:
            in_play = max(in_play, sim.energy().in_play)
    velocities = np.stack(velocities)
    settling = settling_velocities(scene, device, model.dt, ref, nodes, sampled)
    run = time.perf_counter() - start - built
    t, speed = np.asarray(times), np.linalg.norm(velocities, axis=2)
    wave = np.linalg.norm(velocities - np.concatenate([np.zeros((1, len(nodes), 3)), settling]), axis=2)
    column = {int(i): k for k, i in enumerate(nodes)}
    c_p = p_wave_speed(scene)
    waves = {}
    for ray, pts in probes.items():
        rows = []
        for d, i in pts:
            arrival, peak = first_arrival(t, speed[:, column[i]])
            rows.append({"distance": d, "node": i, "arrival": arrival, "ppv": peak})
        d = np.array([r["distance"] for r in rows])
        ta = np.array([r["arrival"] for r in rows])
        ok = np.isfinite(ta)
        slope = float(np.polyfit(ta[ok], d[ok], 1)[0]) if np.count_nonzero(ok) >= 3 else math.nan
        waves[ray] = {"probes": rows, "speed": slope}
    history_load = scene.loads[0].history
    pulse = history_load.rise_time + history_load.decay_time
    free_field = []
    for i, (r, echo) in sorted(field.items(), key=lambda item: item[1][0]):
        arrival, ppv = first_pulse_ppv(t, wave[:, column[i]], r, echo, pulse)
        free_field.append({"distance": r, "node": i, "echo": echo, "arrival": arrival, "ppv": ppv})
    reached = [p for p in free_field if math.isfinite(p["ppv"]) and p["ppv"] > 0.0]
    attenuation = attenuation_fit(np.array([p["distance"] for p in reached]), np.array([p["ppv"] for p in reached]))
    attenuation.update(pulse=pulse, unreached=len(free_field) - len(reached))
    # The window's check: the largest speed of the wave within WAVE_WINDOW, the frame's echoes included.
    whole = np.array([float(wave[:, column[p["node"]]].max()) for p in reached])
    attenuation["window"] = attenuation_fit(np.array([p["distance"] for p in reached]), whole)
    diffraction = {}
    for kind, probes_of_kind in bent.items():
        rows = []
        for i, r in probes_of_kind.items():
            arrival, ppv = first_pulse_ppv(t, wave[:, column[i]], r, echo_distance(scene, ref[i]), pulse)
            rows.append({"distance": r, "node": i, "arrival": arrival, "ppv": ppv})
        diffraction[kind] = rows
    diffraction.update(diffraction_summary(diffraction["shadow"], diffraction["lit"]))
    loads = sim.model.loads
    load = {
        "area": float(loads.loaded_areas()[0]),
        "impulse": float(loads.impulses(sim.state.load_face_impulse.numpy())[0]),
    }
    pictures["x_end"] = current_positions(sim)
    pictures["moved_end"] = np.linalg.norm(sim.state.body_dc.numpy(), axis=1)[tet_body]
    volumes = history["rubble"][-1]
    chimney = chimneys(centres, fixed, blocks["dc"][-1], sections, planes, top)
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
        "_blocks": blocks,
        "_wave": {"time": t, "velocity": velocities, "settling": settling, "nodes": nodes},
        "waves": waves,
        "free_field": free_field,
        "attenuation": attenuation,
        "diffraction": diffraction,
        "load": load,
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
    width = 26

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
    lines.append(
        row("load: area [m²], impulse [N s]", [f"{r['load']['area']:.1f}, {r['load']['impulse']:.4g}" for r in results])
    )
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
    lines.append(
        f"attenuation: first-pulse PPV (for {results[0]['attenuation']['pulse'] * 1e3:.1f} ms + the travel time "
        "after the first arrival, until the held frame's echo) at the free-field probes (not over an opening, reached "
        "through rock alone; the settling under gravity taken out):"
    )
    lines.append(
        row(
            "  probes fitted (not reached)",
            [f"{r['attenuation']['probes']} ({r['attenuation']['unreached']})" for r in results],
        )
    )
    for lo_r, hi_r in itertools.pairwise((0.0, 3.0, 5.0, 7.0, 9.0, 11.0, 13.0)):
        cells = []
        for r in results:
            ppv = [p["ppv"] for p in r["free_field"] if lo_r < p["distance"] <= hi_r and math.isfinite(p["ppv"])]
            cells.append(f"{np.median(ppv):.3g} ({len(ppv)})" if ppv else "-")
        lines.append(row(f"  r {lo_r:g}-{hi_r:g} m: median PPV [m/s] (probes)", cells))
    lines.append(
        row(
            "  PPV ∝ r^-n: n ± s.e.",
            [f"{r['attenuation']['n']:.2f} ± {r['attenuation']['n_se']:.2f}" for r in results],
        )
    )
    lines.append(
        row(
            "  PPV ∝ exp(-α r)/r: α ± s.e. [1/m]",
            [f"{r['attenuation']['alpha']:.3f} ± {r['attenuation']['alpha_se']:.3f}" for r in results],
        )
    )
    lines.append(
        row(
            f"  check: largest speed within {WAVE_WINDOW * 1e3:.0f} ms, n; α",
            [f"{r['attenuation']['window']['n']:.2f}; {r['attenuation']['window']['alpha']:.3f}" for r in results],
        )
    )
    lines.append(
        row(
            "diffraction: mean PPV·r shadow / lit ± s.e. (probes)",
            [
                f"{r['diffraction']['ratio']:.2f} ± {r['diffraction']['ratio_se']:.2f} "
                f"({r['diffraction']['reached'][0]} / {r['diffraction']['reached'][1]})"
                for r in results
            ],
        )
    )
    lines.append(
        row(
            "  first arrival, shadow / lit [ms]",
            [
                f"{r['diffraction']['shadow_arrival'] * 1e3:.2f} / {r['diffraction']['lit_arrival'] * 1e3:.2f}"
                for r in results
            ],
        )
    )
    lines.append(
        f"rubble in each opening section at the end [m³] (share of the section); chimney above it [m] "
        f"(layers with a block sunk > {CHIMNEY_DROP * 100:.0f} cm below its layer's free-field blocks):"
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
        "largest room over time: rubble [m³]; its roof bed's blocks' mean / largest drop [cm] and mean sinking speed "
        "[m/s] (free fall from rest: ½ g t², g t):"
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
    lines.append("chimney over time [m] above the sections where one grew:")
    grew = [
        k
        for k in range(len(results[0]["sections"]))
        if any(any(c[k] > 0.0 for c in r["history"]["chimney"]) for r in results)
    ]
    for k, when in enumerate(results[0]["history"]["time"]):
        if k == 0 or (k % REPORT_EVERY and k != len(results[0]["history"]["time"]) - 1):
            continue
        cells = []
        for r in results:
            h = r["history"]
            cells.append(" / ".join(f"{h['chimney'][k][j]:.0f}" for j in grew) if k < len(h["time"]) else "")
        lines.append(row(f"  t = {when * 1e3:5.1f} ms", cells))
    lines.append("  (" + "; ".join(results[0]["sections"][j]["name"] for j in grew) + ")")
    lines.append(
        "largest sinking below the layer's free-field blocks [cm], layer by layer above each section's roof (the roof "
        "bed, then bed by bed), bottom up:"
    )
    for k, sec in enumerate(results[0]["sections"]):
        for r in results:
            layers = " ".join(f"{d * 100:.1f}" for d in r["sections"][k]["layers"])
            lines.append(f"  {sec['name']:<36} {r['scene'].removeprefix('facility_'):<14} {layers}")
    return lines


def run_scenes(names: list[str] | tuple[str, ...], device: str, end_time: float | None) -> list[dict]:
    """Runs each named scene (:func:`report`) to ``end_time`` [s] (the scene's if None), saying how long each took."""
    from warpdem.cli import init_warp
    from warpdem.scene import load_scene

    init_warp()
    results = []
    for name in names:
        results.append(report(load_scene(SCENES_DIR / f"{name}.toml"), device, end_time))
        print(f"{name}: built in {results[-1]['build_s']:.0f} s, ran in {results[-1]['run_s']:.0f} s", flush=True)
    return results


def figures_json(results: list[dict]) -> str:
    """The runs' figures as JSON: every entry but the arrays (names starting with an underscore)."""
    return json.dumps([{k: v for k, v in r.items() if not k.startswith("_")} for r in results], indent=1)


def main(argv: list[str] | None = None) -> int:
    from scene_reports import chosen_scenes, scene_parser  # beside this script, in benchmarks/

    parser = scene_parser(__doc__, SCENES, every="both")
    parser.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    parser.add_argument("--picture", type=Path, help="also draw the sections of the scenes to this PNG file")
    args = parser.parse_args(argv)
    results = run_scenes(chosen_scenes(parser, args, SCENES), args.device, args.end_time)
    print("\n".join(format_side_by_side(results)))
    if args.picture is not None:
        draw_sections(results, args.picture)
    if args.json is not None:
        args.json.write_text(figures_json(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
