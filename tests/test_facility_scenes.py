"""The LDEC §3 facility scenes (scenes/facility_persistent.toml, scenes/facility_nonpersistent.toml): rigid blocks
under a surface blast. tests/test_scenes.py already runs both for two frames (finite state, the books closing to
MESH_BOUND at dt and dt/2, a bit-for-bit restart); this file adds what the scenes are for.

Oracles:
- the scene builds what its header says: every block rigid, the blocks touching the held sides and base held whole
  and only those (a brute force over the blocks' nodes on the box faces), the persistent scene's blocks 2 m cubes
  (8 m³, or cut by a box face or an opening: never larger);
- physics bound: no signal in a jointed rock mass outruns the intact rock's P wave, c_p = sqrt((λ + 2μ)/ρ). The
  rigid blocks carry a signal across themselves at once, so the first motion of a probe d from the loaded patch
  (the mesh node nearest a point straight below ground zero) cannot come before (d − BLOCK)/c_p, BLOCK the blocks'
  size; and the first-arrival speed fitted over the probes (least squares of distance against arrival time) is at
  most c_p, within the sampling: arrivals are read every SAMPLE_STEPS steps, so each is late by at most that, which
  moves the fitted slope by at most SPEED_SLACK of itself over the probes' spread of arrival times;
- free fall: the blocks of the largest room's roof have nothing beneath them and the rock starts unstressed, so
  they fall at g, ½ g t², until the blast's wave reaches them (the start of LDEC's Fig. 8 collapse);
- the books close over the run (the energy error within MESH_BOUND of tests/test_scenes.py);
- the report's measures (benchmarks/facility_scenes.py) on inputs whose answer is known: the attenuation fits
  recover the n and α that made exact synthetic PPVs; the first pulse's window keeps a pulse and leaves out a later,
  larger echo; the echo distance is the nearest mirror image of ground zero, worked out by hand; every free-field
  probe's straight path from ground zero, sampled 50 times finer than the report samples it, meets no opening, and
  no probe lies over one; the chimney counts the layers that sank into an opening relative to the rest of their
  layer, not a push shared by the whole layer.

The collapse itself (70 ms, minutes of steps) is the report's: benchmarks/facility_scenes.py.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from warpdem.scene import load_scene
from warpdem.stages.energy import balance_error

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
# The sections and roof blocks as the scenes' report measures them (benchmarks/facility_scenes.py, not an installed
# module).
_spec = importlib.util.spec_from_file_location(
    "facility_scenes", Path(__file__).resolve().parent.parent / "benchmarks" / "facility_scenes.py"
)
facility = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = facility  # its dataclasses look their module up there
_spec.loader.exec_module(facility)
BLOCK = 2.0
"""Joint spacing of the facility scenes: the blocks' edge [m]."""
SAMPLE_STEPS = 2
"""Steps between read-backs of the probes' speeds."""
ARRIVAL_FRACTION = 0.1
"""First arrival: a probe's speed first exceeds this fraction of its peak (benchmarks/facility_scenes.py's)."""
PROBE_DEPTHS = (2.0, 4.0, 6.0, 8.0)
"""Depths of the probes below ground zero [m], above the main tunnel's roof (13 m down)."""
END_TIME = facility.WAVE_WINDOW
"""Simulated time [s]: the report's window for the direct wave (10 ms). The P wave of the granite crosses the probes
(8 m) in 1.7 ms, but the weak-shear joints (μ = 0.15) spread the pulse: the deeper probes peak only after 4 ms, and
a first arrival read against a peak taken too early (a tenth of a precursor's) comes too soon."""
FREE_FALL_STEPS = 60
"""Steps the roof's free fall is followed for: 0.9 ms at the scene's 14.7 µs, before the blast's wave can reach the
roof 10 m below the surface, (10 m − BLOCK)/c_p = 1.7 ms (the bound the first-arrival test checks)."""
FREE_FALL_TOL = 0.12
"""Relative tolerance of the roof's drop against ½ g t² (test_largest_room_roof_falls_freely_until_the_wave_arrives):
dt/t ≤ 0.1 past ten steps, and the contact forces of float32 positions, ~1 % of the weight. Measured: 2e-3 at
60 steps, 1e-7 at 10."""
MESH_BOUND = 5e-3
"""tests/test_scenes.py's bound on the books of a scene with tets, relative to the energy in play."""


@pytest.fixture(scope="module")
def persistent():
    """The persistent scene, built on the CPU (the mesh takes Gmsh tens of seconds; the tests share it)."""
    scene = load_scene(SCENES_DIR / "facility_persistent.toml")
    # As the runner does for rigid blocks from the start with dt = "auto": the blocks' own step.
    return scene, facility.build_simulation(scene, "cpu")


def test_blocks_are_rigid_and_the_frame_is_held(persistent):
    scene, sim = persistent
    s, m = sim.state, sim.model
    assert sim.rigid
    nn, nt = int(s.node_count.numpy()[0]), int(s.tet_count.numpy()[0])
    body = s.node_body.numpy()[:nn]
    assert np.all(body >= 0)  # every node follows a body
    x = m.node_ref_q.numpy()[:nn].astype(np.float64)
    lo, hi = np.asarray(scene.mesh.lo), np.asarray(scene.mesh.hi)
    tol = 1e-6 * float(np.linalg.norm(hi - lo))
    on_frame = np.any(np.abs(x - lo) <= tol, axis=1) | np.any(np.abs(x[:, :2] - hi[:2]) <= tol, axis=1)
    count = s.body_mass.shape[0]
    expected = np.bincount(body, weights=on_frame, minlength=count) > 0  # brute force: a node on a held face
    np.testing.assert_array_equal(s.body_fixed.numpy() != 0, expected)
    assert 0 < expected.sum() < count
    # Blocks: 2 m cubes, or pieces of one cut by a box face or an opening.
    tets = m.tet_nodes.numpy()[:nt].astype(np.int64)
    volume = np.bincount(body[tets[:, 0]], weights=m.tet_volume.numpy()[:nt].astype(np.float64), minlength=count)
    assert volume.max() <= BLOCK**3 * (1.0 + 1e-5)
    np.testing.assert_allclose(np.median(volume), BLOCK**3, rtol=1e-5)


@pytest.fixture(scope="module")
def blast(persistent):
    """The persistent scene's first END_TIME: the probes' speeds straight below ground zero (every SAMPLE_STEPS
    steps), the largest room's roof blocks' mean drop (each step until FREE_FALL_STEPS), and the books."""
    scene, sim = persistent
    cyl = scene.loads[0].region.cylinder
    top = scene.mesh.hi[2]
    ref = sim.model.node_ref_q.numpy()[: int(sim.state.node_count.numpy()[0])].astype(np.float64)
    probes = [
        int(np.argmin(np.linalg.norm(ref - (cyl.center[0], cyl.center[1], top - d), axis=1))) for d in PROBE_DEPTHS
    ]
    room = next(sec for sec in facility.facility_sections(scene) if sec.kind == "room")
    planes = facility.bedding_planes(scene)
    centres = facility.block_centres(sim)
    start = sim.energy()
    in_play = start.in_play
    steps = round(END_TIME / sim.model.dt)
    times, speeds, drops = [0.0], [np.zeros(len(probes))], [0.0]
    for done in range(1, steps + 1):
        sim.advance(1)
        if done <= FREE_FALL_STEPS:
            drops.append(facility.roof_motion(sim, centres, room, planes)[0])
        if done % SAMPLE_STEPS == 0:
            times.append(done * sim.model.dt)
            speeds.append(np.linalg.norm(sim.state.node_qd.numpy()[probes].astype(np.float64), axis=1))
            in_play = max(in_play, sim.energy().in_play)
    return {
        "depth": top - ref[probes, 2],  # distance from the loaded patch straight above them
        "time": np.asarray(times),
        "speed": np.stack(speeds),
        "drop": np.asarray(drops),
        "room": room,
        "books": balance_error(start, sim.energy(), in_play),
    }


def test_first_arrival_below_ground_zero_is_slower_than_the_p_wave(persistent, blast):
    scene, sim = persistent
    c_p = facility.p_wave_speed(scene)
    depth, t, v = blast["depth"], blast["time"], blast["speed"]
    peak = v.max(axis=0)
    assert np.all(peak > 0.0)
    arrival = t[np.argmax(v > ARRIVAL_FRACTION * peak, axis=0)]
    assert np.all(arrival > 0.0)  # every probe was reached within the run
    earliest = (depth - BLOCK) / c_p
    assert np.all(arrival >= earliest), f"arrivals {arrival} before (d − block)/c_p = {earliest}"
    speed = float(np.polyfit(arrival, depth, 1)[0])
    slack = 2.0 * SAMPLE_STEPS * sim.model.dt / float(np.ptp(arrival))
    assert 0.0 < speed <= c_p * (1.0 + slack), f"first-arrival speed {speed:.0f} m/s against c_p = {c_p:.0f} m/s"
    # The books close over the run, as over the smoke test's two frames.
    assert abs(blast["books"]) <= MESH_BOUND


def test_largest_room_roof_falls_freely_until_the_wave_arrives(persistent, blast):
    """The collapse LDEC's Fig. 8 shows starts here: the blocks of the largest room's roof have nothing beneath
    them, and the rock starts unstressed, so the vertical persistent joints beside them carry no normal stress and
    no friction: they fall from rest at g, drop = ½ g t², until the blast's wave reaches them. Oracle: the exact
    free fall. The step integrates a constant acceleration exactly up to O(dt/t) (a kick–drift scheme's ½ g t (t
    ± dt)), and the blocks' float32 node positions (~1e-6 m at 10 m) put contact forces of k_n A × 1e-6 m on the
    joints at most, a fraction k_n A 1e-6 / (m g) ~ 1 % of a roof block's weight: FREE_FALL_TOL."""
    scene, sim = persistent
    dt = sim.model.dt
    g = -scene.gravity.vector[2]
    t = dt * np.arange(len(blast["drop"]))
    later = t > 10.0 * dt  # where the O(dt/t) term is within 10 %
    expected = 0.5 * g * t[later] ** 2
    np.testing.assert_allclose(blast["drop"][later], expected, rtol=FREE_FALL_TOL)


def test_attenuation_fits_recover_the_law_that_made_the_data():
    """Oracle: exact PPVs from each law; a least-squares line through exact points returns its slope to float64
    round-off (relative 1e-12 over these few points)."""
    r = np.array([6.0, 6.5, 8.0, 9.3, 10.0, 12.0])
    fit = facility.attenuation_fit(r, 40.0 * r**-1.7)
    np.testing.assert_allclose(fit["n"], 1.7, rtol=1e-12)
    assert fit["n_se"] < 1e-10 and fit["probes"] == len(r)
    fit = facility.attenuation_fit(r, 40.0 * np.exp(-0.08 * r) / r)
    np.testing.assert_allclose(fit["alpha"], 0.08, rtol=1e-12)


def test_first_pulse_window_keeps_the_pulse_and_leaves_out_the_echo():
    """A probe 8 m from ground zero is reached at about 2 ms by a pulse peaking at 1 m/s at 2.3 ms; its echo, from the
    mirror image 12 m away (the window closes at t_a r'/r, about 3.1 ms), peaks at 3 m/s at 3.5 ms, and the rock
    settles at 0.01 m/s before the wave. Oracle: the pulse's peak, 1 m/s, and its arrival, the first sample past a
    tenth of the series' peak."""
    t = np.arange(0.0, 6e-3, 1e-5)
    v = 0.01 + np.exp(-(((t - 2.3e-3) / 2e-4) ** 2)) + 3.0 * np.exp(-(((t - 3.5e-3) / 2e-4) ** 2))
    arrival, ppv = facility.first_pulse_ppv(t, v, 8.0, 12.0, 3.3e-3)
    np.testing.assert_allclose(ppv, 1.01, rtol=1e-6)  # its peak sample sits on the pulse's peak
    assert t[np.argmax(v > 0.3)] == arrival and arrival < 2.3e-3
    # A window as long as the load's pulse, with the echo far away, takes the echo's peak.
    np.testing.assert_allclose(facility.first_pulse_ppv(t, v, 8.0, 100.0, 3.3e-3)[1], 3.01, rtol=1e-3)
    # Never reached: no first pulse.
    assert all(np.isnan(facility.first_pulse_ppv(t, np.zeros_like(t), 8.0, 12.0, 3.3e-3)))


def test_free_field_probes_see_the_wave_through_rock_alone():
    """Oracle: the report's probe filter against a finer brute force. Ground zero (12, 12, 20) in the 24 × 24 × 20 m
    box: a point straight below it at depth d has its nearest mirror image in a side, at sqrt(24² + d²), or in the
    base, at 40 − d, by hand. Every free-field probe lies in the rock, over no opening, and its straight path from
    ground zero sampled every millimetre meets no opening; there are probes at three distances at least (the fit's
    slope is determined)."""
    for name in facility.SCENES:
        scene = load_scene(SCENES_DIR / f"{name}.toml")
        sections = facility.facility_sections(scene)
        gz, _ = facility.load_patch(scene)
        for d in (4.0, 10.0, 18.0):
            np.testing.assert_allclose(
                facility.echo_distance(scene, gz - (0.0, 0.0, d)), min(np.hypot(24.0, d), 40.0 - d), rtol=1e-12
            )
        probes = facility.attenuation_probes(scene)
        assert len({r for r, _ in probes}) >= 3
        for r, p in probes:
            np.testing.assert_allclose(np.linalg.norm(p - gz), r, rtol=1e-12)
            assert not facility.over_opening(sections, p)
            path = gz + np.linspace(0.0, 1.0, round(r / 1e-3) + 1)[:, None] * (p - gz)
            assert not any(np.any(sec.contains(path)) for sec in sections), f"{name}: probe at {p} is shadowed"


def test_chimney_counts_the_sinking_into_an_opening_not_the_layers_shared_push():
    """Oracle: a built displacement field. Blocks of the joint spacing on a grid over a room 8 m across with its roof
    at z = 9 m, bedding planes at even heights: a 1 m roof bed (centres at 9.5 m), then whole beds (centres at 11,
    13, ... m). The whole rock is pushed down 5 cm (the blast's push, shared by every layer), and the blocks over the
    room's footprint in the roof bed and the bed above sink a further CHIMNEY_DROP + 2 cm (a chimney 3 m high, to the
    plane at 12 m), those of the next bed half of CHIMNEY_DROP (not collapsed). Held blocks (the outer ring) moved
    nothing: they are no reference. The bedding planes are the persistent scene's."""
    planes = facility.bedding_planes(load_scene(SCENES_DIR / "facility_persistent.toml"))
    np.testing.assert_array_equal(planes, np.arange(2.0, 20.0, 2.0))
    room = facility.Section("room", (8.0, 8.0, 3.0), (16.0, 16.0, 9.0), "room")
    axis = np.arange(1.0, 24.0, facility.LAYER)
    heights = np.array([9.5, 11.0, 13.0, 15.0, 17.0, 19.0])
    centres = np.stack(np.meshgrid(axis, axis, heights, indexing="ij"), -1).reshape(-1, 3)
    fixed = (centres[:, 0] < 2.0) | (centres[:, 0] > 22.0)
    dc = np.zeros_like(centres)
    dc[~fixed, 2] = -0.05
    over = np.all((centres[:, :2] > 8.0) & (centres[:, :2] < 16.0), axis=1)
    dc[over & (centres[:, 2] < 12.0), 2] -= facility.CHIMNEY_DROP + 0.02
    dc[over & (centres[:, 2] == 13.0), 2] -= 0.5 * facility.CHIMNEY_DROP
    ((height, layers),) = facility.chimneys(centres, fixed, dc, [room], planes, 20.0)
    assert height == 3.0
    np.testing.assert_allclose(
        layers[:3], [facility.CHIMNEY_DROP + 0.02] * 2 + [0.5 * facility.CHIMNEY_DROP], rtol=1e-9
    )
    np.testing.assert_allclose(layers[3:], 0.0, atol=1e-15)
    # The shared push alone is no chimney.
    dc[over, 2] = -0.05
    assert facility.chimneys(centres, fixed, dc, [room], planes, 20.0)[0][0] == 0.0


def test_diffraction_probes_lie_in_the_rooms_shadow_and_on_a_lit_ring():
    """Oracle: the geometry, by a finer brute force. Every shadow probe lies SHADOW_DEPTH below the largest room's
    floor, inside its footprint, and the straight path from ground zero to it (sampled every millimetre) runs through
    the room; every lit probe lies at the same depth, LIT_RING from ground zero horizontally, over no opening, and its
    path meets none. Both sets are not empty (the measure is defined)."""
    for name in facility.SCENES:
        scene = load_scene(SCENES_DIR / f"{name}.toml")
        sections = facility.facility_sections(scene)
        room = next(sec for sec in sections if sec.kind == "room")
        gz, _ = facility.load_patch(scene)
        probes = facility.diffraction_probes(scene)
        assert probes["shadow"] and probes["lit"]

        def path(p: np.ndarray, gz: np.ndarray = gz) -> np.ndarray:
            return gz + np.linspace(0.0, 1.0, round(np.linalg.norm(p - gz) / 1e-3) + 1)[:, None] * (p - gz)

        for p in probes["shadow"]:
            assert p[2] == room.lo[2] - facility.SHADOW_DEPTH
            assert np.all((p[:2] > room.lo[:2]) & (p[:2] < room.hi[:2]))
            assert np.any(room.contains(path(p))), f"{name}: shadow probe at {p} is lit"
        for p in probes["lit"]:
            assert p[2] == room.lo[2] - facility.SHADOW_DEPTH
            np.testing.assert_allclose(np.hypot(*(p[:2] - gz[:2])), facility.LIT_RING, rtol=1e-12)
            assert not facility.over_opening(sections, p)
            assert not any(np.any(sec.contains(path(p))) for sec in sections), f"{name}: lit probe at {p} is shadowed"


def test_diffraction_measure_takes_out_the_spreading_and_reads_the_shadows_share():
    """Oracle: built rows. A wave spreading as 1/r (PPV = 30 / r) gives PPV·r = 30 on both sides; in a shadow that
    passes a share s of it, PPV·r = 30 s there, so the measure is s exactly (means of equal values, standard error
    0), whatever the probes' distances. Scatter about those values: the mean's standard error s/sqrt(k) by hand. A
    probe the wave never reached (NaN) is left out; with fewer than two reached on a side, the measure is NaN."""
    lit = [{"distance": r, "arrival": r / 3000.0, "ppv": 30.0 / r} for r in (17.6, 18.4, 19.2)]
    lit.append({"distance": 19.0, "arrival": float("nan"), "ppv": float("nan")})
    shadow = [{"distance": r, "arrival": r / 2500.0, "ppv": 0.4 * 30.0 / r} for r in (17.5, 17.6, 17.8, 17.9)]
    d = facility.diffraction_summary(shadow, lit)
    np.testing.assert_allclose(d["ratio"], 0.4, rtol=1e-14)
    assert d["ratio_se"] < 1e-14
    np.testing.assert_allclose(d["lit_arrival"], 18.4 / 3000.0, rtol=1e-14)
    np.testing.assert_allclose(d["shadow_arrival"], 17.7 / 2500.0, rtol=1e-14)
    assert tuple(d["reached"]) == (4, 3)
    # PPV·r of 10 and 14 in the shadow (mean 12, s = 2 sqrt(2), s.e. 2), 30 on the ring: 0.4 ± 2/30.
    scattered = [{"distance": 20.0, "arrival": 0.0, "ppv": v / 20.0} for v in (10.0, 14.0)]
    d = facility.diffraction_summary(scattered, lit)
    np.testing.assert_allclose([d["ratio"], d["ratio_se"]], [0.4, 2.0 / 30.0], rtol=1e-13)
    assert np.isnan(facility.diffraction_summary(shadow, lit[2:])["ratio"])
