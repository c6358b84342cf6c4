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
- the books close over the run (the energy error within MESH_BOUND of tests/test_scenes.py).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from warpdem.rigid import rigid_time_step
from warpdem.scene import load_scene
from warpdem.scene_build import build_scene
from warpdem.simulation import Simulation, balance_error

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
BLOCK = 2.0
"""Joint spacing of the facility scenes: the blocks' edge [m]."""
SAMPLE_STEPS = 2
"""Steps between read-backs of the probes' speeds."""
ARRIVAL_FRACTION = 0.1
"""First arrival: a probe's speed first exceeds this fraction of its peak (benchmarks/facility_scenes.py's)."""
PROBE_DEPTHS = (2.0, 4.0, 6.0, 8.0)
"""Depths of the probes below ground zero [m], above the main tunnel's roof (13 m down)."""
END_TIME = 4.0e-3
"""Simulated time [s]: the P wave of the granite crosses the probes (8 m) in 1.7 ms; a block mass at half its speed
by 3.4 ms, and the blast's pulse rises in 0.1 ms."""
MESH_BOUND = 5e-3
"""tests/test_scenes.py's bound on the books of a scene with tets, relative to the energy in play."""


def p_wave_speed(scene) -> float:
    """c_p = sqrt(E (1 − ν) / ((1 + ν)(1 − 2ν) ρ)) [m/s] of the scene's rock."""
    mat = scene.materials[scene.mesh.material]
    e, nu, rho = mat.youngs_modulus, mat.poisson_ratio, mat.density
    return math.sqrt(e * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu) * rho))


@pytest.fixture(scope="module")
def persistent():
    """The persistent scene, built on the CPU (the mesh takes Gmsh tens of seconds; the tests share it)."""
    scene = load_scene(SCENES_DIR / "facility_persistent.toml")
    model, state = build_scene(scene, "cpu")
    # As the runner does for rigid blocks from the start with dt = "auto": the blocks' own step.
    return scene, Simulation(rigid_time_step(model, state, scene.run.safety_factor), state)


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


def test_first_arrival_below_ground_zero_is_slower_than_the_p_wave(persistent):
    scene, sim = persistent
    c_p = p_wave_speed(scene)
    cyl = scene.loads[0].region.cylinder
    top = scene.mesh.hi[2]
    ref = sim.model.node_ref_q.numpy()[: int(sim.state.node_count.numpy()[0])].astype(np.float64)
    probes = [
        int(np.argmin(np.linalg.norm(ref - (cyl.center[0], cyl.center[1], top - d), axis=1))) for d in PROBE_DEPTHS
    ]
    depth = top - ref[probes, 2]  # distance from the loaded patch straight above them
    start = sim.energy()
    in_play = start.in_play
    steps = round(END_TIME / sim.model.dt)
    times, speeds = [0.0], [np.zeros(len(probes))]
    for done in range(SAMPLE_STEPS, steps + 1, SAMPLE_STEPS):
        sim.advance(SAMPLE_STEPS)
        times.append(done * sim.model.dt)
        speeds.append(np.linalg.norm(sim.state.node_qd.numpy()[probes].astype(np.float64), axis=1))
        in_play = max(in_play, sim.energy().in_play)
    t, v = np.asarray(times), np.stack(speeds)
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
    assert abs(balance_error(start, sim.energy(), in_play)) <= MESH_BOUND
