"""Rigid blocks (kernels/rigid.py, warpdem/stages/rigid.py) and the switch from deformable tets
(Simulation.switch_to_rigid).

Oracles:
- inertia: a box block meshed by tets has the principal moments M (b² + c²)/12 … of the uniform box (the tet second
  moment is exact, so only the float32 node positions and masses round it: INERTIA_RTOL);
- free flight (no gravity, no contact): linear and angular momentum of the body stay exactly what they were (no force,
  no torque), the nodes keep their mutual distances (a rigid motion, to float32 rounding of u over the block size),
  and the nodes' momentum is the body's;
- an asymmetric box (three distinct moments) spun about an axis near its intermediate axis tumbles as Euler's
  equations dL/dt = L × I⁻¹L (body frame) integrated in float64 by RK4 at a quarter of the step: the error of ω(t)
  over two tumbling flips shrinks by ≥ 3× when dt halves (the splitting is second order: 4× in exact arithmetic;
  the exponential divergence of the intermediate-axis instability makes the constant large, not the order), and is
  a small fraction of |ω| at the finer step;
- a block on a joint inclined beyond atan μ (the base held) slides with a = g (sin θ − μ cos θ) in both modes (the
  deformable case is tests/test_fem_contact.py's, with the same SLIDE_RTOL), and the onset of sliding is the same
  in both: it holds at 15°, slides at 18° (atan 0.3 = 16.7°);
- the switch: each block takes the total mass, momentum and angular momentum of its nodes (float64 sums of what was
  there, to 1e-12 relative), the energy books do not jump across it (SWITCH_RTOL of the energy in play: float64 sums
  of float32 terms) and close afterwards as Verlet closes them (BOOKS_RTOL);
- a rigid half next to a deformable half (shared nodes, no joint): total momentum (deformable nodes + body) conserved
  to float32 rounding (a random walk over the steps) and the books close (BOOKS_RTOL, bulk viscosity off);
- the element-mode energy of the energy-fraction criterion: zero for a rigid velocity field, and what a least-squares
  rigid fit (numpy lstsq, an independent route) leaves of a random one;
- restart: a run checkpointed after the switch continues bit for bit, and a timed switch equals an explicit one at
  that step bit for bit; the surface written to USD/VTU is unchanged by the switch;
- the [rigid] scene table: its region and materials pick exactly the tets a brute force finds; bad tables are
  one-line scene errors naming the file and key.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import warp as wp
from test_fem_contact import FRICTION, GRAVITY, SLIDE_RTOL, centre_of_mass_motion, two_blocks

from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import box_mesh
from warpdem.simulation import Simulation
from warpdem.stages.fragments import block_labels
from warpdem.stages.joints import JointProps
from warpdem.stages.rigid import angular_velocities, body_frames, box_inertia, element_mode_energy

DENSITY = 2000.0  # [kg/m³]
YOUNG = 1.0e8  # [Pa]
POISSON = 0.25
F32_EPS = float(np.finfo(np.float32).eps)
INERTIA_RTOL = 8.0 * F32_EPS  # float32 node masses and positions, summed in float64
SWITCH_RTOL = 1.0e-9  # measured 0: positions do not move; float64 sums of float32 terms could round
BOOKS_RTOL = 1.0e-3  # Verlet on the contact and joint springs at half the stable step (measured 3.8e-8)


def box_block(device, size=(1.0, 0.6, 0.3), divisions=(3, 2, 1), velocity=(0.0, 0.0, 0.0), gravity=(0.0, 0.0, 0.0)):
    points, tets = box_mesh((0.0, 0.0, 0.0), size, divisions)
    b = ModelBuilder(gravity=gravity)
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(points, tets, "rock", velocity=velocity)
    return b.finalize(device, safety_factor=0.5)


def test_box_block_has_the_inertia_of_a_box(device):
    size = (1.0, 0.6, 0.3)
    model, state = box_block(device, size)
    sim = Simulation(model, state)
    report = sim.switch_to_rigid()
    assert (report.bodies, report.fixed, report.tets) == (1, 0, 36)
    mass = DENSITY * np.prod(size)
    np.testing.assert_allclose(sim.state.body_mass.numpy(), [mass], rtol=INERTIA_RTOL)
    np.testing.assert_allclose(sim.state.body_inertia.numpy()[0], box_inertia(mass, size), rtol=INERTIA_RTOL)
    # Principal axes along the box's edges, right-handed.
    axes = sim.state.body_axes.numpy()[0]
    np.testing.assert_allclose(np.abs(axes), np.eye(3), atol=1e-6)
    assert np.linalg.det(axes) > 0.0


def test_free_flight_conserves_momentum_and_angular_momentum(device):
    model, state = box_block(device, velocity=(1.0, -0.5, 0.2))
    sim = Simulation(model, state)
    sim.switch_to_rigid()
    sim.state.body_l.assign(np.array([[0.7, 5.0, -1.2]]))
    n = int(sim.state.node_count.numpy()[0])
    mass = model.node_mass.numpy()[:n].astype(np.float64)

    def positions() -> np.ndarray:
        return model.node_ref_q.numpy()[:n].astype(np.float64) + sim.state.node_u.numpy()[:n].astype(np.float64)

    x0 = positions()
    p0, l0 = sim.state.body_v.numpy() * sim.state.body_mass.numpy()[:, None], sim.state.body_l.numpy().copy()
    e0 = sim.energy()
    sim.advance(400)
    # No force and no torque: the body's momenta are exactly what they were.
    np.testing.assert_array_equal(sim.state.body_v.numpy() * sim.state.body_mass.numpy()[:, None], p0)
    np.testing.assert_array_equal(sim.state.body_l.numpy(), l0)
    # The nodes moved rigidly: their mutual distances are kept to the float32 rounding of u (size of the block).
    x1 = positions()
    d0 = np.linalg.norm(x0[:, None] - x0[None], axis=2)
    d1 = np.linalg.norm(x1[:, None] - x1[None], axis=2)
    np.testing.assert_allclose(d1, d0, atol=8.0 * F32_EPS * (1.0 + np.abs(x1).max()))
    assert np.abs(x1 - x0).max() > 0.1  # it did fly and turn
    # The nodes carry the body's momentum (their velocities are its rigid field v + ω × r, float32).
    v = sim.state.node_qd.numpy()[:n].astype(np.float64)
    np.testing.assert_allclose(
        (mass[:, None] * v).sum(axis=0), p0[0], atol=8.0 * F32_EPS * np.abs(mass[:, None] * v).sum()
    )
    # The free rotor conserves the energy to O((ω dt)²) (bounded, symplectic), here below 1e-6.
    omega = np.linalg.norm(angular_velocities(sim.state))
    assert (omega * model.dt) ** 2 < 1e-6
    np.testing.assert_allclose(sim.energy().total, e0.total, rtol=1e-6)


def euler_reference(moments: np.ndarray, l_body: np.ndarray, times: np.ndarray, h: float) -> np.ndarray:
    """Body-frame ω(t) of a free asymmetric top: Euler's equations dL/dt = L × (L / I) by RK4 in float64 at step h
    (plain floats: a numpy call per component would cost more than the whole simulated run)."""
    i1, i2, i3 = (float(x) for x in moments)

    def rate(a: float, b: float, c: float) -> tuple[float, float, float]:
        wa, wb, wc = a / i1, b / i2, c / i3
        return b * wc - c * wb, c * wa - a * wc, a * wb - b * wa

    out, (a, b, c), t = [], (float(x) for x in l_body), 0.0
    for target in times:
        while t < target - 1e-12:
            k = min(h, target - t)
            p1 = rate(a, b, c)
            p2 = rate(a + 0.5 * k * p1[0], b + 0.5 * k * p1[1], c + 0.5 * k * p1[2])
            p3 = rate(a + 0.5 * k * p2[0], b + 0.5 * k * p2[1], c + 0.5 * k * p2[2])
            p4 = rate(a + k * p3[0], b + k * p3[1], c + k * p3[2])
            a += k / 6.0 * (p1[0] + 2.0 * p2[0] + 2.0 * p3[0] + p4[0])
            b += k / 6.0 * (p1[1] + 2.0 * p2[1] + 2.0 * p3[1] + p4[1])
            c += k / 6.0 * (p1[2] + 2.0 * p2[2] + 2.0 * p3[2] + p4[2])
            t += k
        out.append((a / i1, b / i2, c / i3))
    return np.array(out)


def tumble_error(device, dt: float) -> tuple[float, float]:
    """Largest |ω_body(t) − ω_Euler(t)| over two flips of a box spun near its intermediate axis, and max |ω|."""
    model, state = box_block(device, size=(1.0, 0.6, 0.3), divisions=(2, 1, 1))
    model = dataclasses.replace(model, dt=dt)  # no contact: any step is stable
    sim = Simulation(model, state)
    sim.switch_to_rigid()
    axes0, moments = body_frames(sim.state)
    l_body = np.array([0.1, 8.0, 0.1]) * moments[0, 1]  # 8 rad/s about the intermediate axis, perturbed
    sim.state.body_l.assign((axes0[0] @ l_body)[None])
    period = 4.0  # [s]: two flips of this box (the reference shows them, at 1.2 s and 3.45 s)
    samples = 40
    times = np.linspace(period / samples, period, samples)
    per = round(times[0] / dt)
    got = []
    for _ in times:
        sim.advance(per)
        axes, _ = body_frames(sim.state)
        got.append(axes[0].T @ angular_velocities(sim.state)[0])
    ref = euler_reference(moments[0], l_body, times, dt / 4.0)  # RK4's O(h⁴) ≪ the splitting's O(dt²)
    flips = np.count_nonzero(np.diff(np.sign(ref[:, 1])))
    assert flips >= 2  # it does tumble: ω about the intermediate axis changes sign
    return float(np.abs(np.array(got) - ref).max()), float(np.abs(ref).max())


def test_asymmetric_block_tumbles_as_euler_equations_say(device):
    # Measured: 2.35e-3, 5.9e-4, 1.5e-4 rad/s at dt = 4, 2, 1 ms (|ω| = 8 rad/s): second order.
    coarse, scale = tumble_error(device, 4.0e-3)
    fine, _ = tumble_error(device, 2.0e-3)
    assert fine < coarse / 3.0  # second order (4× in exact arithmetic)
    assert fine < 1e-3 * scale


def slide(device, theta: float, mode: str) -> tuple[float, float]:
    """The block of tests/test_fem_contact.py on a joint at θ [°], its base held, for 0.1 s in ``mode``: the
    acceleration of the top block's centre of mass along the slope, fitted over the last 70 % of the run (after the
    first touch) [m/s²], and its displacement then [m]. In rigid mode the base is one held body, the top one free
    body, and the joint's node–face contacts act between them."""
    model, state, upper = two_blocks(device, theta, 2)
    sim = Simulation(model, state)
    if mode == "rigid":
        report = sim.switch_to_rigid()
        assert (report.bodies, report.fixed) == (2, 1)
    chunks = 40
    per = max(int(0.1 / model.dt) // chunks, 1)
    times, speeds = [], []
    for _ in range(chunks):
        sim.advance(per)
        times.append(sim.time)
        speeds.append(centre_of_mass_motion(sim, upper)[1][0])
    times, speeds = np.array(times), np.array(speeds)
    late = times > 0.3 * times[-1]
    return float(np.polyfit(times[late], speeds[late], 1)[0]), float(centre_of_mass_motion(sim, upper)[0][0])


@pytest.mark.parametrize("mode", ["deformable", "rigid"])
def test_block_slides_above_friction_angle_in_both_modes(device, mode):
    """θ = 30° > atan μ: a = g (sin θ − μ cos θ) to SLIDE_RTOL (the deformable case is test_fem_contact.py's)."""
    theta = 30.0
    a, _ = slide(device, theta, mode)
    expected = GRAVITY * (math.sin(math.radians(theta)) - FRICTION * math.cos(math.radians(theta)))
    np.testing.assert_allclose(a, expected, rtol=SLIDE_RTOL)


@pytest.mark.parametrize("mode", ["deformable", "rigid"])
def test_sliding_onset_is_the_same_in_both_modes(device, mode):
    """Either side of the friction angle atan 0.3 = 16.7°: at 15° the block holds (it moves less than 5 % of a free
    slide's g sin θ t²/2), at 18° it slides with g (sin θ − μ cos θ) = 0.23 m/s², to SLIDE_RTOL of the driving
    g sin θ (the net acceleration is a small difference). Measured: 0.239 (deformable) and 0.2323 (rigid)."""
    _, u = slide(device, 15.0, mode)
    assert abs(u) < 0.05 * 0.5 * GRAVITY * math.sin(math.radians(15.0)) * 0.1**2  # measured 2.1e-4, 1.1e-5 m
    theta = 18.0
    a, _ = slide(device, theta, mode)
    drive = GRAVITY * math.sin(math.radians(theta))
    expected = drive - GRAVITY * FRICTION * math.cos(math.radians(theta))
    assert expected > 0.0
    np.testing.assert_allclose(a, expected, atol=SLIDE_RTOL * drive)


def jointed_pair(device, velocity_noise: float = 0.05):
    """Two blocks of a 1 m box cut by a joint at z = 0.5, free in space (no gravity), with random node velocities
    (element modes) and a random strain: what a blast leaves before the switch."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    from test_fem_contact import plane_faces

    b = ModelBuilder(gravity=(0.0, 0.0, -GRAVITY))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    js = b.add_joint_set(JointProps(friction=FRICTION, restitution=0.5))
    b.add_tet_mesh(points, tets, "rock", joint_faces=plane_faces(points, tets, 2, 0.5), joint_set=js)
    model, state = b.finalize(device, safety_factor=0.5)
    rng = np.random.default_rng(1)
    cap = model.node_capacity
    drift = np.array([0.3, 0.0, 0.1])
    state.node_qd.assign((rng.normal(scale=velocity_noise, size=(cap, 3)) + drift).astype(np.float32))
    return model, state


def test_switch_conserves_mass_momentum_and_closes_the_books(device):
    model, state = jointed_pair(device)
    sim = Simulation(model, state)
    sim.advance(50)  # strain the tets and the joint
    n = int(sim.state.node_count.numpy()[0])
    mass = model.node_mass.numpy()[:n].astype(np.float64)
    x = model.node_ref_q.numpy()[:n].astype(np.float64) + sim.state.node_u.numpy()[:n].astype(np.float64)
    v = sim.state.node_qd.numpy()[:n].astype(np.float64)
    before = sim.energy()
    in_play = before.in_play
    report = sim.switch_to_rigid()
    after = sim.energy()
    assert report.bodies == 2 and report.released > 0.0
    s = sim.state
    body_of = s.node_body.numpy()[:n]
    for b in range(2):
        mine = body_of == b
        m = mass[mine]
        com = (m[:, None] * x[mine]).sum(axis=0) / m.sum()
        np.testing.assert_allclose(s.body_mass.numpy()[b], m.sum(), rtol=1e-15)
        np.testing.assert_allclose(
            s.body_mass.numpy()[b] * s.body_v.numpy()[b], (m[:, None] * v[mine]).sum(axis=0), rtol=1e-12, atol=1e-12
        )
        l_nodes = (m[:, None] * np.cross(x[mine] - com, v[mine])).sum(axis=0)
        np.testing.assert_allclose(s.body_l.numpy()[b], l_nodes, rtol=1e-12, atol=1e-12 * np.abs(l_nodes).max())
    # The joint separates the blocks: the tets above it make one body, those below the other.
    nt = int(s.tet_count.numpy()[0])
    tets = model.tet_nodes.numpy()[:nt]
    above = model.node_ref_q.numpy()[tets].mean(axis=1)[:, 2] > 0.5
    assert len(set(body_of[tets[above]].ravel())) == 1 and len(set(body_of[tets[~above]].ravel())) == 1
    assert body_of[tets[above][0, 0]] != body_of[tets[~above][0, 0]]
    # The books do not jump: what the tets and element modes held is booked as released.
    assert abs(after.total - before.total) < SWITCH_RTOL * in_play
    np.testing.assert_allclose(after.strain, 0.0)
    # The release's parts as the report says them: strain + element-mode kinetic energy (the nodes' kinetic energy
    # beyond the bodies') and the change of Verlet's shadow term, each from the two energy tallies (float64 sums).
    np.testing.assert_allclose(report.shadow, after.shadow - before.shadow, rtol=1e-12)
    np.testing.assert_allclose(
        report.released - report.shadow, before.strain + before.kinetic - after.kinetic, rtol=1e-9
    )
    # And close afterwards: the blocks fall, touch and rub on the joint.
    sim.advance(400)
    later = sim.energy()
    assert abs(later.total - after.total) < BOOKS_RTOL * max(in_play, later.in_play)


def test_rigid_restart_continues_bit_for_bit(device, tmp_path):
    from warpdem.io.restart import restore_checkpoint, save_checkpoint

    model, state = jointed_pair(device)
    template = state.clone()
    sim = Simulation(model, state)
    sim.advance(20)
    sim.switch_to_rigid()
    sim.advance(30)
    path = save_checkpoint(tmp_path / "c.h5", sim, 1, {})
    sim.advance(100)
    fresh_model, _ = jointed_pair(device)
    model2, state2, attrs = restore_checkpoint(path, fresh_model, template)
    again = Simulation(model2, state2, primed=True, step=int(attrs["step"]), time=float(attrs["time"]))
    assert again.rigid
    again.advance(100)
    for name, a in sim.state.arrays().items():
        np.testing.assert_array_equal(getattr(again.state, name).numpy(), a.numpy(), err_msg=name)


def test_switch_at_a_time_is_the_switch_at_that_step(device):
    """A model told to switch at t = 10 dt (``rigid_switch_time``) and run 25 steps in one advance ends bit for bit
    where 10 steps, an explicit switch and 15 steps end: the advance ends a chunk on the switch step."""
    model, state = jointed_pair(device)
    timed = Simulation(dataclasses.replace(model, rigid_switch=True, rigid_switch_time=10 * model.dt), state.clone())
    assert not timed.rigid
    timed.advance(25)
    assert timed.rigid and timed.rigid_report is not None
    model2, state2 = jointed_pair(device)
    manual = Simulation(model2, state2)
    manual.advance(10)
    manual.switch_to_rigid()
    manual.advance(15)
    for name, a in manual.state.arrays().items():
        np.testing.assert_array_equal(getattr(timed.state, name).numpy(), a.numpy(), err_msg=name)


def test_element_mode_energy_of_rigid_and_deforming_motion(device):
    """The criterion's element-mode energy (the nodes' kinetic energy beyond each block's rigid motion): zero for a
    rigid field v + ω × r (to float32 rounding of the node velocities); for a random field, what a least-squares
    rigid fit leaves over; and a switch by ``rigid_energy_fraction`` happens on the first check where the fraction
    is below it, never where it is above."""
    model, state = jointed_pair(device, velocity_noise=0.0)
    n = int(state.node_count.numpy()[0])
    x = model.node_ref_q.numpy()[:n].astype(np.float64)
    spin = np.array([0.2, -0.5, 1.0])
    centre = x.mean(axis=0)
    rigid = np.zeros((model.node_capacity, 3), dtype=np.float32)
    rigid[:n] = np.array([0.3, 0.0, 0.1]) + np.cross(spin, x - centre)
    state.node_qd.assign(rigid)
    element, total = element_mode_energy(model, state)
    assert total > 0.0 and element < 16.0 * F32_EPS * total
    # Equal and opposite velocities on the two joint faces of each block's bottom and top: no momentum, no spin.
    # A random field: the element-mode energy is what a least-squares fit of a rigid field V + Ω × (x − x̄) per block
    # (in the mass metric, numpy lstsq: an independent route to the same projection) leaves over.
    rng = np.random.default_rng(3)
    noisy = np.zeros_like(rigid)
    noisy[:n] = rng.normal(size=(n, 3))
    state.node_qd.assign(noisy)
    element, total = element_mode_energy(model, state)
    label, count = block_labels(model, state)
    mass = model.node_mass.numpy()[:n].astype(np.float64)
    v = noisy[:n].astype(np.float64)
    residual = 0.0
    for b in range(count):
        mine = label == b
        m, r = mass[mine], x[mine] - (mass[mine, None] * x[mine]).sum(axis=0) / mass[mine].sum()
        rows = np.zeros((3 * len(m), 6))
        for k in range(3):
            e = np.eye(3)[k]
            rows[k::3, :3] = e
            rows[k::3, 3:] = np.cross(r, e)  # (Ω × r)_k = Ω · (r × e_k): a row in Ω
        w = np.repeat(np.sqrt(m), 3)
        fit, *_ = np.linalg.lstsq(rows * w[:, None], v[mine].ravel() * w, rcond=None)
        left = v[mine].ravel() - rows @ fit
        residual += 0.5 * np.sum(np.repeat(m, 3) * left * left)
    np.testing.assert_allclose(element, residual, rtol=1e-9)
    assert element < total
    # The switch by the criterion: the rigid field switches at once (step 0 is a check), the stretch never does.
    state.node_qd.assign(rigid)
    switched = Simulation(dataclasses.replace(model, rigid_energy_fraction=0.5, rigid_check_interval=5), state)
    assert switched.rigid
    _, fresh = jointed_pair(device, velocity_noise=0.0)
    fresh.node_qd.assign(noisy)
    kept = Simulation(dataclasses.replace(model, rigid_energy_fraction=0.5, rigid_check_interval=5), fresh)
    assert element > 0.5 * total  # the random field is mostly element modes: no switch
    kept.advance(5)
    assert not kept.rigid


# ----------------------------------------------------------------------------------------------------------------
# The [rigid] scene table


def test_rigid_scene_keys_and_the_tets_they_pick(tmp_path):
    """Defaults off; a switch time with a region and a material picks exactly the tets whose centroid is inside
    (brute force over the built tets) and sets the model's switch."""
    from test_scene import MESH_BASE, write

    from warpdem.build.scene_build import finalize_scene, scene_builder, tet_centroids
    from warpdem.scene import load_scene

    scene = load_scene(write(tmp_path, MESH_BASE))
    assert not scene.rigid.active and scene.rigid.check_interval == 100
    text = MESH_BASE + (
        '\n[rigid]\nswitch_time = 0.004\nmaterials = ["rock"]\nregion = { box = { lo = [0, 0, 1], hi = [1, 1, 3] } }\n'
    )
    scene = load_scene(write(tmp_path, text))
    model, state = finalize_scene(scene, scene_builder(scene), "cpu")
    assert model.rigid_switch and model.rigid_switch_time == 0.004 and model.rigid_energy_fraction == 0.0
    nt = int(state.tet_count.numpy()[0])
    c = tet_centroids(model, state)
    inside = np.all((c >= [0, 0, 1]) & (c <= [1, 1, 3]), axis=1)
    np.testing.assert_array_equal(model.tet_may_rigid.numpy()[:nt] != 0, inside)
    assert 0 < inside.sum() < nt


@pytest.mark.parametrize(
    ("table", "phrase"),
    [
        ("enabled = true\nswitch_time = 0.001", "rigid: takes at most one of 'enabled', 'switch_time'"),
        ("energy_fraction = 1.5", "rigid.energy_fraction"),
        ('enabled = true\nmaterials = ["granite"]', "rigid.materials: 'granite' is not a material"),
        ("enabled = true\nregion = { box = { lo = [5, 5, 5], hi = [6, 6, 6] } }", "rigid: no tet of the mesh"),
    ],
)
def test_bad_rigid_table_is_a_one_line_scene_error(tmp_path, table, phrase):
    from test_scene import MESH_BASE, write

    from warpdem.build.scene_build import finalize_scene, scene_builder
    from warpdem.scene import SceneError, load_scene

    path = write(tmp_path, MESH_BASE + f"\n[rigid]\n{table}\n")
    with pytest.raises(SceneError) as info:
        scene = load_scene(path)
        finalize_scene(scene, scene_builder(scene), "cpu")
    message = str(info.value)
    assert phrase in message and "\n" not in message and str(path) in message


def test_rigid_blocks_keep_their_surface_in_the_output(device):
    """The rock surface written to USD/VTU (warpdem.io.output.RockFrames) is the same set of faces before and after the
    switch: rigid tets (tet_active 2) are still material, only their elastic force is off."""
    from warpdem.io.output import RockFrames

    model, state = jointed_pair(device)
    sim = Simulation(model, state)
    before = RockFrames().surface(sim.model, sim.state).faces
    sim.switch_to_rigid()
    after = RockFrames().surface(sim.model, sim.state).faces
    assert len(before) > 0
    np.testing.assert_array_equal(np.sort(np.sort(after, axis=1), axis=0), np.sort(np.sort(before, axis=1), axis=0))


def test_rigid_region_next_to_deformable_tets_conserves_momentum(device):
    """A box whose upper half turns rigid (``tet_may_rigid``) while its lower half stays deformable, with no joint
    between them: the nodes they share follow the body, the deformable tets' forces on them act on the body. No
    external force: the total momentum (deformable nodes + body) is conserved to float32 rounding of the nodes'
    updates (a random walk, MOMENTUM_ROUNDOFF ε₃₂ √steps of Σ m |v|), and the books close, bulk viscosity
    included."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    # Bulk viscosity on (the default): the deformable tets' viscous forces on the shared nodes book their half ahead at
    # the body's pose they were made at, after its drift (warpdem.stages.rigid.drift_bodies). Measured: 5.3e-5 of the
    # energy in play over 300 steps (3.5e-2 when the rigid nodes' half ahead was dropped).
    rng = np.random.default_rng(5)
    b.add_tet_mesh(points, tets, "rock", velocity=rng.normal(scale=0.05, size=points.shape))
    model, state = b.finalize(device, safety_factor=0.5)
    upper = np.zeros(model.tet_capacity, dtype=np.int32)
    upper[: len(tets)] = points[tets].mean(axis=1)[:, 2] > 0.5
    model = dataclasses.replace(model, tet_may_rigid=wp.array(upper, dtype=int, device=model.device))
    sim = Simulation(model, state)
    sim.advance(20)
    n = sim.node_count
    mass = model.node_mass.numpy()[:n].astype(np.float64)

    def momentum() -> tuple[np.ndarray, float]:
        free = sim.model.node_motion.numpy()[:n] != 8
        v = sim.state.node_qd.numpy()[:n].astype(np.float64)
        p = (mass[free, None] * v[free]).sum(axis=0)
        scale = float((mass[:, None] * np.abs(v)).sum())
        if sim.rigid:
            p += (sim.state.body_mass.numpy()[:, None] * sim.state.body_v.numpy()).sum(axis=0)
        return p, scale

    p0, _ = momentum()
    report = sim.switch_to_rigid()
    assert (report.bodies, report.tets) == (1, int(upper.sum()))
    p1, _ = momentum()
    e1 = sim.energy()
    steps = 300
    sim.advance(steps)
    p2, scale = momentum()
    np.testing.assert_allclose(p1, p0, atol=8.0 * F32_EPS * scale)
    np.testing.assert_allclose(p2, p1, atol=4.0 * F32_EPS * math.sqrt(steps) * scale)
    assert e1.strain > 0.0  # the deformable half still strains
    assert abs(sim.energy().total - e1.total) < BOOKS_RTOL * e1.in_play


# ----------------------------------------------------------------------------------------------------------------
# Roller constraints on bodies (kernels/rigid.py: the allowed motions of a body on one roller plane, two, or three)


def tilted_box(device, rotation: np.ndarray, velocity: np.ndarray, spin: np.ndarray, gravity=(0.0, 0.0, -9.81)):
    """The asymmetric box (1 × 0.6 × 0.3 m, three distinct moments) turned by ``rotation``, its lowest node(s) on a
    roller plane of normal z (held to z = its lowest point), with the rigid velocity field velocity + spin × (x − c).
    Returns the model, the state and the box's inertia tensor in the world frame (from box_inertia)."""
    size = (1.0, 0.6, 0.3)
    points, tets = box_mesh((0.0, 0.0, 0.0), size, (3, 2, 1))
    centre0 = 0.5 * np.array(size)
    points = (points - centre0) @ rotation.T + np.array([0.0, 0.0, 2.0])
    centre = np.array([0.0, 0.0, 2.0])
    b = ModelBuilder(gravity=gravity)
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(points, tets, "rock", velocity=velocity + np.cross(spin, points - centre))
    low = np.flatnonzero(points[:, 2] < points[:, 2].min() + 1e-9)
    b.add_boundary(low, "roller", normal=(0.0, 0.0, 1.0))
    model, state = b.finalize(device, safety_factor=0.5)
    mass = DENSITY * np.prod(size)
    inertia = rotation @ np.diag(box_inertia(mass, size)) @ rotation.T
    return model, state, inertia


def rotation_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: the rotation by ``angle`` [rad] about the unit ``axis``, (3, 3)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def test_block_on_a_roller_plane_slides_and_turns_as_the_plane_allows(device):
    """A tilted asymmetric box (no principal axis along z) with its lowest node on a roller plane z = const, under
    gravity, thrown with a velocity and a spin that both leave the plane. The switch keeps the allowed part of the
    nodes' momentum: P less its z component, and ℓ = L·z (L the nodes' angular momentum, numpy); the body then
    moves as the constrained Lagrangian ½ M |v_xy|² + ½ I_z θ̇² says (I_z = z·I z from box_inertia turned, not
    from the body's arrays): c(t) = c0 + v_xy t, θ = ℓ t / I_z about z, every node x(t) = c(t) + R_z(θ)(x0 − c0)
    (to float32 rounding of u over the block: NODE_ATOL), its z exactly kept (gravity and the normal parts are the
    rollers'), P_xy and ℓ exactly constant (no force), and the energy constant (the rollers do no work)."""
    tilt = rotation_matrix(np.array([1.0, 0.4, 0.0]) / math.hypot(1.0, 0.4), 0.6)
    velocity, spin = np.array([0.3, -0.2, 0.5]), np.array([0.4, -0.7, 1.5])
    model, state, inertia = tilted_box(device, tilt, velocity, spin)
    sim = Simulation(model, state)
    n = sim.node_count
    mass = model.node_mass.numpy()[:n].astype(np.float64)
    x0 = model.node_ref_q.numpy()[:n].astype(np.float64)
    v0 = sim.state.node_qd.numpy()[:n].astype(np.float64)
    com = (mass[:, None] * x0).sum(axis=0) / mass.sum()
    l_nodes = (mass[:, None] * np.cross(x0 - com, v0)).sum(axis=0)
    report = sim.switch_to_rigid()
    assert (report.bodies, report.fixed, report.planar, report.lines) == (1, 0, 1, 0)
    s = sim.state
    np.testing.assert_array_equal(s.body_axis.numpy()[0], [0.0, 0.0, 1.0])
    p_xy = (mass[:, None] * v0).sum(axis=0) * np.array([1.0, 1.0, 0.0])
    np.testing.assert_allclose(s.body_v.numpy()[0] * s.body_mass.numpy()[0], p_xy, rtol=1e-12, atol=1e-12)
    assert s.body_v.numpy()[0, 2] == 0.0
    ell = l_nodes[2]
    np.testing.assert_allclose(s.body_l.numpy()[0], [0.0, 0.0, ell], rtol=1e-12, atol=1e-12 * abs(ell))
    u0 = s.node_u.numpy()[:n].copy()
    e0 = sim.energy()
    p0, l0 = s.body_v.numpy().copy(), s.body_l.numpy().copy()
    steps = 600
    sim.advance(steps)
    t = sim.time
    np.testing.assert_array_equal(s.body_v.numpy(), p0)
    np.testing.assert_array_equal(s.body_l.numpy(), l0)
    np.testing.assert_array_equal(s.node_u.numpy()[:n, 2], u0[:, 2])  # every node stays at its height
    theta = ell * t / inertia[2, 2]
    assert abs(theta) > 0.3 and np.linalg.norm(p0[0, :2]) * t > 0.05  # it did slide and turn
    c = com + p0[0] * t
    expected = c + (x0 - com) @ rotation_matrix(np.array([0.0, 0.0, 1.0]), theta).T
    x1 = x0 + s.node_u.numpy()[:n].astype(np.float64)
    NODE_ATOL = 16.0 * F32_EPS * (1.0 + np.abs(x1).max())  # float32 u of the nodes, the float64 pose rounded once
    np.testing.assert_allclose(x1, expected, atol=NODE_ATOL)
    np.testing.assert_allclose(sim.energy().total, e0.total, rtol=1e-9)


def pushed_box(device, rollers: list[tuple[str, tuple[float, float, float]]], pressure: float = 2.0e4):
    """A 1 m box (2³ Kuhn cells) under gravity −z, a constant pressure on its x+ face, its faces named in ``rollers``
    on roller planes (face name, normal). Returns model, state, the pressure's force [N] and the box mass [kg]."""
    from warpdem.stages.loads import PressureHistory

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    b = ModelBuilder(gravity=(0.0, 0.0, -GRAVITY))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(points, tets, "rock")
    faces = {}
    for name, axis, value in (("x+", 0, 1.0), ("x-", 0, 0.0), ("y+", 1, 1.0), ("y-", 1, 0.0), ("z-", 2, 0.0)):
        faces[name] = np.flatnonzero(np.abs(points[:, axis] - value) < 1e-9)
    from test_fem_contact import plane_faces

    loaded = plane_faces(points, tets, 0, 1.0)
    b.add_face_pressure(loaded, PressureHistory.table([0.0, 10.0], [pressure, pressure]))
    for name, normal in rollers:
        b.add_boundary(faces[name], "roller", normal=normal)
    model, state = b.finalize(device, safety_factor=0.5)
    return model, state, np.array([-pressure * 1.0, 0.0, 0.0]), DENSITY * 1.0


@pytest.mark.parametrize(
    ("rollers", "allowed", "kind"),
    [
        ([("y-", (0, -1, 0)), ("y+", (0, 1, 0))], np.diag([1.0, 0.0, 1.0]), "planar"),
        ([("x-", (-1, 0, 0)), ("y-", (0, -1, 0))], np.diag([0.0, 0.0, 1.0]), "lines"),
        ([("x-", (-1, 0, 0)), ("y-", (0, -1, 0)), ("z-", (0, 0, -1))], np.zeros((3, 3)), "fixed"),
    ],
    ids=["between-two-walls", "two-planes", "three-planes"],
)
def test_block_on_rollers_moves_as_its_planes_allow(device, rollers, allowed, kind):
    """A rigid box under gravity and a constant pressure on its x+ face (its force through the centre of mass: no
    torque): between two parallel roller walls (y− and y+) it accelerates with a = P (F/M + g) in the xz plane; on two
    planes that meet (x−, y−) along their line, z, only (the push is the x− roller's); on three it is held. Velocity
    Verlet is exact for a constant acceleration: v = a t and c − c0 = ½ a t² to the float32 rounding of g and of the
    load's force (4 ε₃₂; the body sums in float64); no spin; the books close (the rollers do no work: BOOKS_RTOL)."""
    model, state, force, mass = pushed_box(device, rollers)
    sim = Simulation(model, state)
    report = sim.switch_to_rigid()
    assert getattr(report, kind) == 1
    e0 = sim.energy()
    steps = 400
    sim.advance(steps)
    t = sim.time
    a = allowed @ (force / mass + np.array([0.0, 0.0, -GRAVITY]))
    s = sim.state
    np.testing.assert_allclose(s.body_v.numpy()[0], a * t, rtol=4.0 * F32_EPS, atol=1e-12)
    np.testing.assert_allclose(s.body_dc.numpy()[0], 0.5 * a * t * t, rtol=4.0 * F32_EPS, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(angular_velocities(s)), 0.0, atol=1e-9)
    e1 = sim.energy()
    assert abs(e1.total - e0.total) < BOOKS_RTOL * max(e1.in_play, 1e-12) + 1e-9


def test_roller_walls_keep_the_allowed_momentum_of_colliding_blocks(device):
    """The jointed pair (two blocks, a frictionless joint) between roller walls y− and y+, thrown together in the xz
    plane with spin about y, no gravity: the contacts are internal and frictionless (a normal force pair on one line
    has no torque), so the total momentum in the plane (P_x, P_z) and the angular momentum about y
    (ℓ_A + ℓ_B + (c_A × P_A + c_B × P_B)·y) stay constant to float rounding of the summed float32 contact forces
    (MOMENTUM_ROUNDOFF ε₃₂ √steps of the impulse scale), and the books close."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    from test_fem_contact import plane_faces

    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    js = b.add_joint_set(JointProps(friction=0.0, restitution=1.0))
    centre = np.array([0.5, 0.5, 0.5])
    upper = points[:, 2] > 0.5
    velocity = np.where(upper[:, None], [0.2, 0.0, -0.6], [-0.1, 0.0, 0.4]) + np.cross([0.0, 1.5, 0.0], points - centre)
    b.add_tet_mesh(points, tets, "rock", velocity=velocity, joint_faces=plane_faces(points, tets, 2, 0.5), joint_set=js)
    b.add_boundary(np.flatnonzero(points[:, 1] < 1e-9), "roller", normal=(0.0, -1.0, 0.0))
    b.add_boundary(np.flatnonzero(points[:, 1] > 1.0 - 1e-9), "roller", normal=(0.0, 1.0, 0.0))
    model, state = b.finalize(device, safety_factor=0.5)
    sim = Simulation(model, state)
    report = sim.switch_to_rigid()
    assert (report.bodies, report.planar) == (2, 2)

    def momenta() -> tuple[np.ndarray, float, float]:
        s = sim.state
        m = s.body_mass.numpy()
        p = m[:, None] * s.body_v.numpy()
        n = sim.node_count
        x = sim.model.node_ref_q.numpy()[:n].astype(np.float64) + s.node_u.numpy()[:n].astype(np.float64)
        nm = sim.model.node_mass.numpy()[:n].astype(np.float64)
        body = s.node_body.numpy()[:n]
        c = np.array([(nm[body == k, None] * x[body == k]).sum(axis=0) / nm[body == k].sum() for k in range(2)])
        ell = s.body_l.numpy()[:, 1].sum() + np.cross(c, p)[:, 1].sum()
        return p.sum(axis=0), float(ell), float(np.abs(p).sum())

    p0, l0, scale = momenta()
    e0 = sim.energy()
    pa0 = sim.state.body_v.numpy()[0].copy()
    steps = 600
    sim.advance(steps)
    p1, l1, _ = momenta()
    assert np.abs(sim.state.body_v.numpy()[0] - pa0).max() > 0.1  # they did collide
    # No dashpot (restitution 1): the contacts' line holds only what Verlet's trapezoid does across the springs'
    # closings and openings, of either sign (D = -W - ΔU); the books closing is the check.
    roundoff = 8.0 * F32_EPS * math.sqrt(steps) * scale
    np.testing.assert_allclose(p1[[0, 2]], p0[[0, 2]], atol=roundoff)
    assert p1[1] == 0.0
    np.testing.assert_allclose(l1, l0, atol=roundoff * 1.0)  # lever arms below 1 m
    e1 = sim.energy()
    assert abs(e1.total - e0.total) < BOOKS_RTOL * max(e0.in_play, e1.in_play)


# ----------------------------------------------------------------------------------------------------------------
# The rigid step after a later switch (Simulation.set_time_step, warpdem.runner.FrameGrid)


def test_a_change_of_time_step_keeps_the_books_closed(device):
    """Between two whole steps a change of dt moves nothing: only Verlet's shadow term S = dt²/8 Σ |f|²/m changes,
    by (dt_new/dt_old)² at the same forces (float64 sums of the same float32 forces: 1e-12), and that is what the
    ``step_change`` line books, so the total does not move (SWITCH_RTOL); afterwards the books close at the new step
    as Verlet closes them (BOOKS_RTOL)."""
    from warpdem.stages.rigid_step import rigid_step_after_switch

    model, state = jointed_pair(device)
    sim = Simulation(model, state)
    sim.advance(50)
    sim.switch_to_rigid()
    sim.advance(30)
    before = sim.energy()
    critical = rigid_step_after_switch(sim.model, sim.state)
    new_dt = 0.5 * critical.value
    ratio = new_dt / model.dt
    assert abs(ratio - 1.0) > 0.1 and before.shadow > 0.0
    booked = sim.set_time_step(new_dt, critical)
    after = sim.energy()
    assert sim.model.dt == new_dt and sim.model.critical_dt == critical.value
    assert sim.model.deformable_critical_dt == model.critical_dt
    np.testing.assert_allclose(after.shadow, before.shadow * ratio**2, rtol=1e-12)
    np.testing.assert_allclose(booked, after.shadow - before.shadow, rtol=1e-12)
    np.testing.assert_allclose(after.step_change, booked, rtol=1e-12)
    assert abs(after.total - before.total) < SWITCH_RTOL * before.in_play
    sim.advance(400)
    later = sim.energy()
    assert abs(later.total - after.total) < BOOKS_RTOL * max(after.in_play, later.in_play)
    with pytest.raises(ValueError, match="positive finite"):
        sim.set_time_step(0.0)


SWITCH_SCENE = """\
schema_version = 1
name = "pushed_column"

[run]
end_time = 0.004
output_rate = 5000.0
safety_factor = 0.5

[materials.rock]
density = 2600.0
youngs_modulus = 5e10
poisson_ratio = 0.25
bulk_viscosity_linear = 0.0
bulk_viscosity_quadratic = 0.0

[mesh]
kind = "box"
lo = [0.0, 0.0, 0.0]
hi = [1.0, 1.0, 4.0]
divisions = [3, 3, 12]
material = "rock"

[[loads]]
kind = "pressure"
faces = "x+"
history = { kind = "table", times = [0.0, 1.0], values = [2.0e6, 2.0e6] }

[[boundaries]]
faces = "z-"
kind = "roller"

[contact]
# Softer outer faces than the rock's E / h behind them (1.5e11 Pa/m here): the rigid step assumes every surface node
# pressed by springs on up to three face planes (warpdem.stages.rigid_step.rigid_critical_step, SPRING_BOUND), and
# with E / h it would fall just below the deformable step, leaving no step to gain at the switch.
surface_normal_stiffness = 1.2e11

[rigid]
switch_time = 0.0011

[output]
directory = "out"
checkpoint_every = 0.0004
"""
"""A column on a roller floor pushed sideways by a constant pressure, deformable until 1.1 ms (inside frame 6 of 0.2
ms frames), then one rigid body sliding on the floor."""


@pytest.fixture(scope="module")
def switch_run(tmp_path_factory):
    from test_scene import write

    from warpdem.runner import RunOptions, run_scene
    from warpdem.scene import load_scene

    folder = tmp_path_factory.mktemp("switch")
    scene = load_scene(write(folder, SWITCH_SCENE))
    summary = run_scene(scene, RunOptions(device="cpu", out_dir=folder / "out", quiet=True))
    return scene, folder, summary


def test_a_later_switch_takes_the_rigid_step_on_the_frame_grid(switch_run):
    """With dt = "auto" the run takes the rigid step at the switch itself: the rest of the frame the switch falls in
    (steps s..E of the old step, s = ⌈t_switch / dt_old⌉, E = 6 n_old) as m = ⌈(E − s) dt_old / dt_new⌉ bridge steps of
    (E − s) dt_old / m ≤ dt_new, then period / n from that frame's end on, n the fewest steps per frame within safety ×
    the critical step after the switch (warpdem.stages.rigid_step.rigid_step_after_switch); the run says so. The step
    count is that arithmetic exactly; frame k still lands on k / rate (the device clock's float64 sum of steps: 1e-12 of
    the end time); the changes book their shadow term (``step_change``) and the balance closes across them (no bulk
    viscosity: the books of the deformable phase close as Verlet closes them); the column slides on its floor with
    the load's impulse."""
    import csv

    from warpdem.io.checkpoint import read_checkpoint

    summary = switch_run[2]
    assert "time step" in summary.rigid and "after the switch" in summary.rigid
    arrays, attrs = read_checkpoint(summary.checkpoints[-1])
    dt_after, critical, substeps = attrs["dt"], attrs["critical_dt"], attrs["substeps"]
    assert attrs["grid_frame"] == 6 and attrs["rigid_step_taken"]
    period = 1.0 / 5000.0
    assert substeps == math.ceil(period / (0.5 * critical)) and dt_after == period / substeps
    first = read_checkpoint(summary.checkpoints[0])[1]
    assert first["grid_frame"] == 0 and first["dt"] < dt_after  # a gain
    dt_before, n_before = first["dt"], first["substeps"]
    switch = math.ceil(0.0011 / dt_before * (1.0 - 1e-9))
    frame_end = 6 * n_before
    assert 5 * n_before < switch < frame_end  # inside frame 6: a bridge
    bridge = math.ceil((frame_end - switch) * dt_before / dt_after * (1.0 - 1e-9))
    assert attrs["grid_step"] == switch + bridge and attrs["step"] == switch + bridge + 14 * substeps
    with open(summary.series_path) as f:
        rows = list(csv.DictReader(f))
    times = np.array([float(r["time"]) for r in rows])
    np.testing.assert_allclose(times, np.arange(len(times)) * period, rtol=0.0, atol=1e-12 * times[-1])
    assert len(times) == 21
    step_change = np.array([float(r["energy_step_change"]) for r in rows])
    assert np.all(step_change[:6] == 0.0) and np.all(step_change[6:] != 0.0)
    assert abs(summary.energy_error) < BOOKS_RTOL
    # Momentum: the floor and gravity push along z only, so P_x is the load's impulse −p A t (A = 4 m², M = ρ 4 m³),
    # to the change of the loaded area while the column strains (a follower load: O(p/E) = 4e-5; measured 9e-6).
    v = arrays["state/body_v"][0]
    impulse = -2.0e6 * 4.0 * attrs["time"] / (2600.0 * 4.0)
    np.testing.assert_allclose(v[0], impulse, rtol=4.0 * 2.0e6 / 5.0e10)
    assert v[2] == 0.0 and abs(v[1]) < 4.0 * 2.0e6 / 5.0e10 * abs(impulse)


def test_restart_across_the_switch_and_the_step_change_is_bit_for_bit(switch_run):
    """Restarts from a checkpoint before the switch (frame 4), from the end of the frame the switch bridged (frame 6,
    where the grid's step took over from the bridge's) and from one after (frame 8) end with the uninterrupted run's
    arrays and step, bit for bit (CPU)."""
    import shutil

    from warpdem.io.checkpoint import read_checkpoint
    from warpdem.runner import RunOptions, run_scene

    scene, folder, summary = switch_run
    end_arrays, end_attrs = read_checkpoint(summary.checkpoints[-1])
    for frame in (4, 6, 8):
        copy = folder / f"restart{frame}"
        shutil.copytree(folder / "out", copy)
        checkpoint = next(p for p in (copy / "checkpoints").iterdir() if read_checkpoint(p)[1]["frame"] == frame)
        again = run_scene(scene, RunOptions(device="cpu", out_dir=copy, quiet=True, restart=checkpoint))
        arrays, attrs = read_checkpoint(again.checkpoints[-1])
        assert attrs["dt"] == end_attrs["dt"] and attrs["step"] == end_attrs["step"]
        assert arrays.keys() == end_arrays.keys()
        for name, a in end_arrays.items():
            np.testing.assert_array_equal(arrays[name], a, err_msg=f"restart from frame {frame}: {name}")


def test_a_switch_on_a_frame_end_or_in_a_short_last_frame_keeps_the_frames_on_the_grid(tmp_path):
    """A switch on a frame's end (t = 1.2 ms, frame 6 at step 72) takes the rigid step there, with no bridge: the
    grid is anchored at step 72. A switch in a run's short last frame (t = 1.1 ms, the run ending at 1.15 ms, step
    69 of the 72 that frame 6 would have) leaves the step to a restart that continues the run (the checkpoint says it
    is not taken): the restart bridges from step 69 to the end of frame 7 on the grid, so every frame after it still
    lands on k × period (the device clock: 1e-12 of the end time)."""
    import csv

    from test_scene import write

    from warpdem.io.checkpoint import read_checkpoint
    from warpdem.runner import RunOptions, run_scene
    from warpdem.scene import load_scene

    period = 2.0e-4
    text = SWITCH_SCENE.replace("switch_time = 0.0011", "switch_time = 0.0012").replace(
        "end_time = 0.004", "end_time = 0.0016"
    )
    scene = load_scene(write(tmp_path, text))
    summary = run_scene(scene, RunOptions(device="cpu", out_dir=tmp_path / "boundary", quiet=True))
    attrs = read_checkpoint(summary.checkpoints[-1])[1]
    first = read_checkpoint(summary.checkpoints[0])[1]
    assert attrs["grid_step"] == 6 * first["substeps"] == 72 and attrs["grid_frame"] == 6
    assert attrs["step"] == 72 + 2 * attrs["substeps"] and attrs["dt"] == period / attrs["substeps"] > first["dt"]

    short = tmp_path / "short"
    short.mkdir()
    text = SWITCH_SCENE.replace("end_time = 0.004", "end_time = 0.00115")
    scene = load_scene(write(short, text))
    summary = run_scene(scene, RunOptions(device="cpu", out_dir=short / "out", quiet=True))
    attrs = read_checkpoint(summary.checkpoints[-1])[1]
    assert attrs["step"] == 69 and attrs["frame"] == 6 and not attrs["rigid_step_taken"]
    assert attrs["dt"] == first["dt"] and attrs["grid_step"] == 0
    again = run_scene(
        scene,
        RunOptions(device="cpu", out_dir=short / "out", quiet=True, restart=summary.checkpoints[-1], end_time=0.0016),
    )
    attrs = read_checkpoint(again.checkpoints[-1])[1]
    assert attrs["grid_frame"] == 7 and attrs["rigid_step_taken"] and attrs["dt"] > first["dt"]
    with open(again.series_path) as f:
        times = np.array([float(r["time"]) for r in csv.DictReader(f)])
    assert len(times) == 9  # frames 0 … 8; frame 6 at the short run's end, 1.15 ms
    on_grid = np.r_[np.arange(6), np.arange(7, 9)]
    np.testing.assert_allclose(times[on_grid], on_grid * period, rtol=0.0, atol=1e-12 * times[-1])


def test_an_explicit_time_step_is_kept_across_the_switch(tmp_path):
    """A scene's own dt is the user's choice: the run keeps it across the switch (no bridge, no new grid, nothing
    booked as a step change) and says so; the frames stay those of that dt, so the run ends at step T / dt."""
    from test_scene import write

    from warpdem.io.checkpoint import read_checkpoint
    from warpdem.runner import RunOptions, run_scene
    from warpdem.scene import load_scene

    dt = 2.0e-5  # 10 steps per 0.2 ms frame; below both stable steps (3.5e-5 s deformable, 4.8e-5 s rigid)
    text = SWITCH_SCENE.replace("safety_factor = 0.5", f"dt = {dt!r}").replace("end_time = 0.004", "end_time = 0.0016")
    scene = load_scene(write(tmp_path, text))
    summary = run_scene(scene, RunOptions(device="cpu", out_dir=tmp_path / "out", quiet=True))
    assert f"time step kept at {dt:.4g} s" in summary.rigid
    arrays, attrs = read_checkpoint(summary.checkpoints[-1])
    assert attrs["dt"] == dt and attrs["step"] == 80 and attrs["grid_step"] == 0 and attrs["substeps"] == 10
    assert arrays["state/rigid_switched"][0] == 1 and arrays["state/energy_step_change"][0] == 0.0


# ----------------------------------------------------------------------------------------------------------------
# The step of a mixed model after a switch (warpdem.stages.rigid_step.deformable_critical_step)

STEP_RTOL = 16.0 * F32_EPS
"""The step of what is left from the model's float32 numbers (material table, reference positions, node masses and
contact stiffnesses) against the builder's float64 ones: a few ε₃₂ through the square roots (measured ≤ 1.2e-8)."""


def two_material_column(device, lower: bool = False, dashpots: bool = True, wall: bool = True):
    """A 1 × 1 × 2 m column of 2 × 2 × 4 Kuhn cells: the upper half of a stiff, dense rock (E 10×, ρ 4×: its tets and
    surface springs need 1/1.6 of the soft ones' step, its body a longer one), the lower half soft; non-reflecting
    dashpots on the bottom face and a wall 1 m below (so the builder counts the contact springs), each optional.
    ``lower``: the lower half built alone (the same tets and nodes); else the upper half may turn rigid."""
    from warpdem.build.mesh import boundary_faces

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 2.0), (2, 2, 4))
    upper = points[tets].mean(axis=1)[:, 2] > 1.0
    if lower:
        used = np.unique(tets[~upper])
        renumber = np.full(len(points), -1)
        renumber[used] = np.arange(len(used))
        points, tets, upper = points[used], renumber[tets[~upper]], upper[~upper]
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("soft", DENSITY, YOUNG, POISSON)
    b.add_material("stiff", 4.0 * DENSITY, 10.0 * YOUNG, POISSON)
    b.add_tet_mesh(points, tets, ["stiff" if u else "soft" for u in upper])
    if dashpots:
        faces = boundary_faces(tets)
        b.add_boundary(faces[np.all(points[faces][:, :, 2] == 0.0, axis=1)], "non_reflecting")
    if wall:
        b.add_plane_wall((0.0, 0.0, -1.0), (0.0, 0.0, 1.0), "soft")
    model, state = b.finalize(device, safety_factor=0.5)
    if not lower:
        may = np.zeros(model.tet_capacity, dtype=np.int32)
        may[: len(tets)] = upper
        model = dataclasses.replace(model, tet_may_rigid=wp.array(may, dtype=int, device=model.device))
    return model, state


@pytest.mark.parametrize(
    ("dashpots", "wall", "setter"),
    [(True, False, "dashpots"), (False, True, "contact penalty springs"), (False, False, "tet")],
)
def test_step_after_a_partial_switch_is_that_of_what_is_left(device, dashpots, wall, setter):
    """After the stiff upper half of the column turns rigid, the step is min(the bodies' step, the builder's step of
    the soft lower half built alone); the soft half's own is set by its dashpots (no wall: one body, no contact can
    engage), by the contact springs of its surface nodes (a wall; here the soft half sets the run's step), or by its
    tets (no dashpots, no wall). None of these does the rigid half change (its nodes on the shared face follow the
    body). With the wall the whole model's step (set by the stiff half's springs) no longer bounds the run; without
    it the bodies' own step (every surface node taken as pressed on up to three planes, SPRING_BOUND) sets the run's.
    Both sides are float64 numpy sums of the same numbers, float32 on the model's side (STEP_RTOL)."""
    from warpdem.stages.rigid_step import (
        contact_damping_ratio,
        deformable_critical_step,
        rigid_critical_step,
        rigid_step_after_switch,
    )

    model, state = two_material_column(device, dashpots=dashpots, wall=wall)
    alone, _ = two_material_column(device, lower=True, dashpots=dashpots, wall=wall)
    sim = Simulation(model, state)
    sim.switch_to_rigid()
    left = deformable_critical_step(sim.model, sim.state)
    np.testing.assert_allclose(left.value, alone.critical_dt, rtol=STEP_RTOL)
    assert setter in left.source and setter in alone.critical_dt_source
    after = rigid_step_after_switch(sim.model, sim.state)
    bodies = rigid_critical_step(sim.model, sim.state, contact_damping_ratio(sim.model))
    np.testing.assert_allclose(after.value, min(bodies, alone.critical_dt), rtol=STEP_RTOL)
    if wall:
        assert after.value > 1.2 * model.critical_dt  # the stiff half's step (1.6× smaller in springs) is gone


def add_sphere_heap(b: ModelBuilder, normal: str) -> None:
    """Spheres beside the column of :func:`two_material_column` (x > 2 m, clear of it): a bonded 3 × 2 row of r = 0.2 m
    soft spheres and four loose ones of r = 0.15 m, of a third material, moving at up to 0.5 m/s (so the Hertz
    impact bound counts), and, with the linear law, one lighter material."""
    b.add_material("grain", 0.5 * DENSITY, 2.0 * YOUNG, 0.3)
    i, j = np.meshgrid(np.arange(3), np.arange(2), indexing="ij")
    row = np.stack([2.5 + 0.4 * i.ravel(), 0.4 * j.ravel(), np.full(6, 0.5)], axis=1)
    ids = b.add_spheres(row, 0.2, "soft", velocity=(0.0, 0.0, -0.5))
    b.add_bonded_group(ids, youngs_modulus=YOUNG, tensile_strength=1.0e6, shear_strength=1.0e6, damping_ratio=0.1)
    loose = np.array([[2.5, 1.5, 1.5], [3.0, 1.5, 1.5], [3.5, 1.5, 1.5], [4.0, 1.5, 1.5]])
    b.add_spheres(loose, 0.15, "grain" if normal == "hertz" else "soft", velocity=(0.3, 0.0, 0.0), part="loose")


@pytest.mark.parametrize("normal", ["hertz", "linear"])
def test_spheres_left_after_a_switch_take_their_own_step(device, normal):
    """Spheres beside a column that turns rigid whole bound the step after the switch by their own step, the one the
    builder gives the same spheres built alone (their contacts: Rayleigh or linear, and the Hertz impact at the
    fastest approach; their bonds' translational and rotational modes), no longer by the whole model's (set by the
    column's stiff tets); the step after the switch is the least of theirs and the body's. Both from the same
    numbers, float32 on the model's side (E, ν recovered from the material pair table, masses and radii):
    STEP_RTOL."""
    from warpdem.stages.rigid_step import (
        contact_damping_ratio,
        deformable_critical_step,
        rigid_critical_step,
        rigid_step_after_switch,
    )

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 2.0), (2, 2, 4))
    whole = ModelBuilder(normal=normal, tangential="linear", gravity=(0.0, 0.0, 0.0))
    alone = ModelBuilder(normal=normal, tangential="linear", gravity=(0.0, 0.0, 0.0))
    for b in (whole, alone):
        b.add_material("soft", DENSITY, YOUNG, POISSON)
        b.add_material("stiff", 4.0 * DENSITY, 10.0 * YOUNG, POISSON)
        add_sphere_heap(b, normal)
    whole.add_tet_mesh(points, tets, "stiff")
    model, state = whole.finalize(device, safety_factor=0.5)
    spheres, _ = alone.finalize(device, safety_factor=0.5)
    sim = Simulation(model, state)
    sim.switch_to_rigid()
    left = deformable_critical_step(sim.model, sim.state)
    np.testing.assert_allclose(left.value, spheres.critical_dt, rtol=STEP_RTOL)
    assert left.source.split("(")[0] == spheres.critical_dt_source.split("(")[0]
    assert left.value > 1.5 * model.critical_dt  # the stiff tets' step no longer bounds the run
    bodies = rigid_critical_step(sim.model, sim.state, contact_damping_ratio(sim.model))
    after = rigid_step_after_switch(sim.model, sim.state)
    np.testing.assert_allclose(after.value, min(bodies, spheres.critical_dt), rtol=STEP_RTOL)


def test_converted_spheres_left_after_a_switch_keep_their_lattice_step(device):
    """A bar pulled apart converts its middle into bonded spheres coupled to the ends; the ends then turn rigid. The
    spheres' step is the converted lattice's bound (warpdem.stages.conversion.conversion_critical_step over the tets
    that converted, the bound the conversion's attach checks the step against: ω² = Σ k_b / m per sphere), not the
    stiffer-looking bond_critical_step of their bonds (most bonds on a sphere × the stiffest); run at half of it the
    bonded spheres between the two driven blocks stay stable and the books close (test_conversion's bound)."""
    from test_conversion import ENERGY_BOUND, bar, worst_balance_error

    from warpdem.stages.conversion import conversion_critical_step
    from warpdem.stages.rigid_step import rigid_step_after_switch, sphere_critical_step

    model, state, _, _ = bar(device, driver_speed=2.0)
    sim = Simulation(model, state)
    sim.advance(60)
    nt = int(sim.state.tet_count.numpy()[0])
    converted = sim.state.tet_sphere.numpy()[:nt] >= 0
    assert converted.sum() > 0
    sim.switch_to_rigid()
    spheres = sphere_critical_step(sim.model, sim.state)
    lattice, _ = conversion_critical_step(sim.model, sim.state, converted)
    assert spheres.value == lattice and "conversion_critical_step" in spheres.source
    assert lattice >= model.critical_dt  # the converted tets are some of those that may convert
    after = rigid_step_after_switch(sim.model, sim.state)
    sim.set_time_step(0.5 * after.value, after)
    assert worst_balance_error(sim, 10, 20) < ENERGY_BOUND


# ----------------------------------------------------------------------------------------------------------------
# Checkpoints of an older format (warpdem.io.restart.FIELD_MIGRATIONS)


def as_old_checkpoint(source, target, keys, version=1):
    """A copy of a checkpoint as an older format (``version``) wrote it: without ``keys`` (``state/<name>``,
    ``model/<name>``, ``attribute <name>``) and with its version attribute set to ``version``."""
    import shutil

    import h5py

    if source != target:
        shutil.copyfile(source, target)
    with h5py.File(target, "r+") as f:
        for key in keys:
            if key.startswith("attribute "):
                del f.attrs[key.removeprefix("attribute ")]
            else:
                del f[key]
        f.attrs["warpdem_format_version"] = version
    return target


def frame_checkpoint(switch_run, copy_name, frame):
    """A copy of the switch run's output folder (``copy_name``) and the path of its checkpoint of ``frame`` in it."""
    import shutil

    from warpdem.io.checkpoint import read_checkpoint

    _, folder, _ = switch_run
    copy = folder / copy_name
    shutil.copytree(folder / "out", copy)
    return copy, next(p for p in (copy / "checkpoints").iterdir() if read_checkpoint(p)[1]["frame"] == frame)


def assert_restart_ends_as_the_run(switch_run, copy, path, what):
    """Restarts the switch run from ``path`` into ``copy`` and compares its last checkpoint with the uninterrupted
    run's, array by array, bit for bit (CPU)."""
    from warpdem.io.checkpoint import read_checkpoint
    from warpdem.runner import RunOptions, run_scene

    scene, _, summary = switch_run
    end_arrays, _ = read_checkpoint(summary.checkpoints[-1])
    again = run_scene(scene, RunOptions(device="cpu", out_dir=copy, quiet=True, restart=path))
    arrays, _ = read_checkpoint(again.checkpoints[-1])
    assert arrays.keys() == end_arrays.keys()
    for name, a in end_arrays.items():
        np.testing.assert_array_equal(arrays[name], a, err_msg=f"restart from {what}: {name}")


def test_an_old_checkpoint_resumes_bit_for_bit_where_its_fields_fill_exactly(switch_run):
    """A checkpoint of format 1 lacks the fields added since (warpdem.io.restart.FIELD_MIGRATIONS). Before the switch
    (frame 4) every one of them has its fresh value in the run (no contact, no pass, no viscosity, no change of
    step, no body): a restart fills them and ends with the uninterrupted run's arrays, bit for bit (CPU)."""
    from warpdem.io.checkpoint import read_checkpoint
    from warpdem.io.restart import FIELD_MIGRATIONS

    copy, path = frame_checkpoint(switch_run, "old4", 4)
    arrays, attrs = read_checkpoint(path)
    # The kicks' carries (format 5) stay: an older file's run carried nothing, so zero was its carry, where this
    # run's deformable column has carried since its first kick.
    keys = [
        k
        for k in FIELD_MIGRATIONS
        if (k in arrays or k.removeprefix("attribute ") in attrs) and FIELD_MIGRATIONS[k].since < 5
    ]
    assert len(keys) >= 30  # every state field of the table, tet_may_rigid and the five scalars
    as_old_checkpoint(path, path, keys)
    assert_restart_ends_as_the_run(switch_run, copy, path, "an old frame-4 checkpoint")


def test_a_format_2_checkpoint_after_the_switch_resumes_bit_for_bit(switch_run):
    """Format 3 added the pressure loads' forces kept per node (``node_f_load``) and the bodies' drift scratch
    (``body_q_before``, ``body_omega_ahead``). A format-2 checkpoint after the switch and the change of step (frame 8:
    the rigid column pushed by its load) lacks them: a restart makes the load's forces again at the checkpoint's time
    and positions and zeroes the scratch (the next drift writes it before anything reads it), and ends with the
    uninterrupted run's arrays, bit for bit (CPU)."""
    from warpdem.io.checkpoint import read_checkpoint

    copy, path = frame_checkpoint(switch_run, "old8", 8)
    arrays, _ = read_checkpoint(path)
    assert np.any(arrays["state/node_f_load"] != 0.0) and len(arrays["state/body_q_before"]) == 1
    as_old_checkpoint(path, path, ["state/node_f_load", "state/body_q_before", "state/body_omega_ahead"], version=2)
    assert_restart_ends_as_the_run(switch_run, copy, path, "a format-2 frame-8 checkpoint")


def test_a_format_3_checkpoint_puts_each_nodes_one_spring_into_slot_0(device, tmp_path):
    """Format 4 holds node_springs node–face springs per node (``node_face_spring``, ``_offset``, ``_shear`` rows and
    the model scalar ``node_springs``); format 3 held one per node. Two rigid blocks meet on one joint plane, so every
    node's spring lies in slot 0 of its row and the others are empty (checked): its checkpoint written as format 3
    wrote it (slot 0 only, no ``node_springs``) restarts with each node's spring in slot 0
    (warpdem.io.restart.FIELD_RESHAPES) and ends 100 steps later as the uninterrupted run, bit for bit (CPU)."""
    import h5py

    from warpdem.io.restart import restore_checkpoint, save_checkpoint

    model, state, _ = two_blocks(device, 10.0, 2)  # the upper block resting on the held lower one
    template = state.clone()
    sim = Simulation(model, state)
    sim.switch_to_rigid()
    sim.advance(50)
    k = sim.model.node_springs
    springs = sim.state.node_face_spring.numpy().reshape(-1, k)
    assert np.any(springs[:, 0] >= 0) and np.all(springs[:, 1:] == -1)
    path = save_checkpoint(tmp_path / "c.h5", sim, 1, {})
    with h5py.File(path, "r+") as f:
        for name in ("node_face_spring", "node_face_offset", "node_face_shear"):
            rows = f["state"][name][...]
            del f["state"][name]
            f["state"][name] = rows.reshape(len(rows) // k, k, *rows.shape[1:])[:, 0]
        del f.attrs["node_springs"]
        f.attrs["warpdem_format_version"] = 3
    sim.advance(100)
    fresh_model, _, _ = two_blocks(device, 10.0, 2)
    model2, state2, attrs = restore_checkpoint(path, fresh_model, template)
    assert model2.node_springs == k
    again = Simulation(model2, state2, primed=True, step=int(attrs["step"]), time=float(attrs["time"]))
    again.advance(100)
    for name, a in sim.state.arrays().items():
        np.testing.assert_array_equal(getattr(again.state, name).numpy(), a.numpy(), err_msg=name)


@pytest.mark.parametrize(
    ("key", "why"),
    [
        ("state/body_constraint", "its blocks had turned rigid"),
        ("state/energy_step_change", "the time step had changed"),
        ("attribute deformable_critical_dt", "the time step had changed"),
    ],
)
def test_an_old_checkpoint_is_refused_where_a_field_would_not_fill_exactly(switch_run, tmp_path, key, why):
    """After the switch and the change of step (frame 8) the bodies' roller constraints, the step-change line and the
    deformable step are the run's own, not a fresh model's: a format-1 checkpoint without one of them is refused with
    one line naming the file, the field and why. A format-2 file must hold every field: one that lacks it is refused
    as incomplete."""
    import h5py

    from warpdem.io.checkpoint import CheckpointError, read_checkpoint
    from warpdem.runner import RunOptions, run_scene

    scene, _, summary = switch_run
    source = next(p for p in summary.checkpoints if read_checkpoint(p)[1]["frame"] == 8)
    path = as_old_checkpoint(source, tmp_path / source.name, [key])
    name = key.removeprefix("attribute ").removeprefix("state/")
    options = RunOptions(device="cpu", out_dir=tmp_path / "out", quiet=True, restart=path)
    with pytest.raises(CheckpointError) as info:
        run_scene(scene, options)
    message = str(info.value)
    assert str(path) in message and name in message and why in message and "\n" not in message
    with h5py.File(path, "r+") as f:
        f.attrs["warpdem_format_version"] = 2
    with pytest.raises(CheckpointError, match=r"missing .*written by an older warpdem"):
        run_scene(scene, options)


def test_rigid_only_model_skips_the_node_drift_bit_for_bit(device):
    """A model whose nodes are all rigid and undriven skips the node kernels' drift: the bodies' pose starts the
    nodes' force accumulators instead (kernels/rigid.py ``pose_nodes_kernel``); with no tet left deformable it skips
    the tet stage too (its kernel returns at every rigid tet) and the viscous half ahead. Oracle: the same run with
    those kernels launched, bit for bit (the rattling jointed cube of 8 blocks, 60 steps, with the books kept); a
    model with a node left deformable, or a driven rigid node, keeps the node kernels (warpdem.stages.rigid
    ``every_node_rigid``), and one with a tet left deformable the tet stage."""
    from warpdem.bench import jointed_cube

    skip, launch = jointed_cube(2, device), jointed_cube(2, device)
    assert not skip.drift_nodes and not skip.deformable_tets and launch.rigid
    launch.drift_nodes = True
    launch.deformable_tets = True
    for sim in (skip, launch):
        sim.track_energy = True
        sim.advance(60)
    assert np.count_nonzero(skip.state.node_face_spring.numpy()[: skip.node_count] >= 0) > 0
    for name in ("node_u", "node_qd", "node_f", "node_f_viscous", "body_q", "body_l", "body_dc", "body_v"):
        np.testing.assert_array_equal(getattr(skip.state, name).numpy(), getattr(launch.state, name).numpy(), name)
    assert skip.energy().total == launch.energy().total

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    for half_rigid, driven in ((True, False), (False, True)):
        b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
        b.add_material("rock", DENSITY, YOUNG, POISSON)
        b.add_tet_mesh(points, tets, "rock")
        if driven:
            b.add_node_velocity(np.array([0]), (0.0, 0.0, 0.1))
        model, state = b.finalize(device, safety_factor=0.5)
        if half_rigid:
            upper = np.zeros(model.tet_capacity, dtype=np.int32)
            upper[: len(tets)] = points[tets].mean(axis=1)[:, 2] > 0.5
            model = dataclasses.replace(model, tet_may_rigid=wp.array(upper, dtype=int, device=model.device))
        sim = Simulation(model, state)
        sim.switch_to_rigid()
        assert sim.rigid and sim.drift_nodes
        assert sim.deformable_tets == half_rigid


def test_a_spring_that_starts_at_the_switch_starts_relaxed(device):
    # The switch re-evaluates the forces where nothing moved, as a topology pass does, so a node–face spring that
    # starts there carries the node's depth as its offset: U = ½ k (δ − offset)² = 0, and the books do not jump. A node
    # found behind a face only at the switch happens where a deep node slid over its face's edge out of its candidate
    # list (limestone_tunnel at resolution 3 by the charge); here the springs of a block resting on another are let go
    # by hand before the switch, and every node pressed into the joint finds its face again at the switch.
    model, state, _ = two_blocks(device, 0.0)
    sim = Simulation(model, state)
    sim.advance(200)  # the upper block rests on the held one: its nodes are behind the lower block's faces
    s = sim.state
    n = int(s.node_count.numpy()[0])
    assert np.count_nonzero(s.node_face_spring.numpy()[:n] >= 0) > 0
    s.node_face_spring.fill_(-1)
    s.node_face_offset.zero_()
    s.node_face_shear.zero_()
    s.node_contact_energy_prev.zero_()
    before = sim.energy()
    sim.switch_to_rigid()
    after = sim.energy()
    # The springs are back (the same nodes find their faces), at no energy: elastic energy and books unchanged to the
    # float64 sums of float32 terms (SWITCH_RTOL of the energy in play).
    assert np.count_nonzero(sim.state.node_face_spring.numpy()[:n] >= 0) > 0
    assert abs(after.elastic - before.elastic) < SWITCH_RTOL * before.in_play
    assert abs(after.total - before.total) < SWITCH_RTOL * before.in_play
