"""Integration stage: velocity Verlet for free spheres, fixed and prescribed spheres, moving walls
(warpdem.stages.integrate, warpdem.kernels.integrate), and the bookkeeping of the work their drivers do.

Oracles:
- free fall: velocity Verlet is exact for a constant acceleration, x(t) = x₀ + v₀ t + g t²/2, v(t) = v₀ + g t, up to
  float32 round-off (bounded below), and the momentum changes by M g t;
- fixed spheres never move; prescribed spheres keep their velocity and spin bit for bit and move by v t;
- energy balance: kinetic + elastic + dissipated − boundary work is constant when a prescribed sphere or a moving
  wall pushes a free sphere, and the work equals the analytic value of the elastic (e = 1) or damped push.

A sphere pushed by a driver of infinite mass moving at V (head-on, restitution e) leaves at (1 + e) V; the driver
does the work W = V · (impulse) = (1 + e) m V², of which ½ m ((1 + e) V)² is kinetic energy and the rest dissipated.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from warpdem.build.builder import InteractionProps, ModelBuilder
from warpdem.simulation import Simulation

EPS32 = float(np.finfo(np.float32).eps)
"""float32 machine epsilon, 2⁻²³: ulp(x) <= EPS32 |x|, and rounding to nearest errs by at most ulp/2."""

RADIUS = 0.01  # [m]
DENSITY = 2500.0  # [kg/m³]
YOUNG = 1.0e7  # [Pa]
POISSON = 0.3  # [-]

# Free fall.
FREE_FALL_DT = 2.0**-10  # [s]; a power of two, so dt and dt/2 · g are exact in float32
FREE_FALL_STEPS = 256
FREE_FALL_FRAMES = 4
GRAVITY = (3.0, -2.0, -9.81)  # [m/s²], tilted: every component is exercised
"""Free-fall tolerances (worst-case bounds, computed in the test): the state is float32 and each of the 2n kicks
v ← v + (dt/2) g rounds by at most ulp(v)/2 (the increment itself is exact: dt is a power of two and g is taken in
float32), so |δv| <= n EPS32 max|v|; each of the n drifts x ← x + dt v rounds by at most ulp(x)/2 and carries the
velocity error, so |δx| <= n EPS32 (max|x| + t max|v|) / 2. A first-order integrator would be off by g dt t / 2,
which the test checks to be at least 4 times these bounds in every component."""

# Pushes by a driver (prescribed sphere or moving wall).
STEPS_PER_CONTACT = 400
"""dt = t_c / STEPS_PER_CONTACT in the push tests."""
DRIVER_SPEED = 0.5  # [m/s]

VERLET_RTOL = (math.pi / STEPS_PER_CONTACT) ** 2
"""Elastic push, after the contact: velocity Verlet's energy error is O((ω dt)²) = (π/400)² = 6e-5 of the energy
exchanged (measured ~3e-6); the rebound speed 2V carries the same relative error."""

DRIVER_WORK_LAG = 0.5
"""During a contact the driver's work is booked per step as F_{n+1} · V dt (the force at the end of the step), which
runs ahead of ∫ F · V dt by ½ V dt (F(t) − F(0)): the energy balance may be off by DRIVER_WORK_LAG · V dt F_max
while the contact lasts; the excess cancels when the force has returned to zero."""

DRIVER_WORK_MARGIN = 1.25
"""The lag above is the leading term; at 400 steps per contact the next ones (the O(dt²) remainder of the rectangle
rule, Verlet's O((ω dt)²) oscillation of the contact energy) are a few % of it (measured: the balance error reaches
99.8 % of the bare lag at the frame nearest the peak force). 25 % covers them."""

DAMPED_RTOL = 2.0 / STEPS_PER_CONTACT
"""Damped or frictional push: the dashpot and the friction force act with the half-step velocity v_{n+1/2}, half a
step old, so the rebound speed and the booked dissipation are off by O(dt/t_c) (measured 0.2/STEPS_PER_CONTACT
for the rebound and 0.5/STEPS_PER_CONTACT of the work for the balance); two steps' worth covers them."""


# ----------------------------------------------------------------------------------------------------------------
# Helpers


def sphere_mass(radius: float = RADIUS, density: float = DENSITY) -> float:
    return density * 4.0 / 3.0 * math.pi * radius**3


def hertz_impact(mstar: float, rstar: float, speed: float) -> tuple[float, float]:
    """Elastic Hertz impact of one material (E* = E / (2 (1 − ν²))): peak force F_max = (4/3) E* √R* δ_max^{3/2} [N]
    with δ_max = (15 m* v² / (16 E* √R*))^{2/5}, and contact time t_c = 2.9432 δ_max / v [s]."""
    estar = YOUNG / (2.0 * (1.0 - POISSON**2))
    delta_max = (15.0 * mstar * speed**2 / (16.0 * estar * math.sqrt(rstar))) ** 0.4
    duration_factor = 2.0 * 0.4 * math.sqrt(math.pi) * math.gamma(0.4) / math.gamma(0.9)
    return 4.0 / 3.0 * estar * math.sqrt(rstar) * delta_max**1.5, duration_factor * delta_max / speed


def builder(
    friction: float = 0.0, restitution: float = 1.0, normal: str = "hertz", tangential: str = "mindlin"
) -> ModelBuilder:
    b = ModelBuilder(normal=normal, tangential=tangential, gravity=(0.0, 0.0, 0.0))
    b.add_material("grain", DENSITY, YOUNG, POISSON)
    b.default_interaction = InteractionProps(friction=friction, restitution=restitution)
    return b


def vec(array) -> np.ndarray:
    """A wp.array of vec3 as float64 numpy (exact: float32 values widen without rounding)."""
    return array.numpy().astype(np.float64)


# ----------------------------------------------------------------------------------------------------------------
# Free spheres


def test_free_fall_is_exact_for_constant_acceleration(device: str) -> None:
    # Velocity Verlet with a constant acceleration: v_{n+1/2} = v_n + g dt/2, x_{n+1} = x_n + dt v_{n+1/2},
    # v_{n+1} = v_{n+1/2} + g dt/2, which sums to x_n = x₀ + v₀ t + g t²/2, v_n = v₀ + g t exactly (t = n dt).
    b = ModelBuilder(gravity=GRAVITY)
    b.add_material("light", 1000.0, YOUNG, POISSON)
    b.add_material("heavy", 7800.0, YOUNG, POISSON)
    # Far apart and moving apart: no contact during the fall.
    b.add_spheres(
        np.array([[0.0, 0.0, 0.5], [0.3, -0.2, 0.4]]),
        np.array([0.01, 0.02]),
        "light",
        velocity=np.array([[0.0, 0.0, 0.0], [1.5, -0.5, 2.0]]),
        angular_velocity=np.array([[0.0, 0.0, 0.0], [10.0, -5.0, 3.0]]),
    )
    b.add_sphere((-0.25, 0.1, 0.6), 0.005, "heavy", velocity=(-0.7, 0.3, -1.0), angular_velocity=(0.0, 0.0, 100.0))
    # No contact ever happens, so the contact time steps do not apply to this (exact) dt, nor does the guard's
    # contact reach (a sphere may move any distance per step when there is nothing it could step over).
    model, state = b.finalize(device, dt=FREE_FALL_DT, sort=False, allow_unstable_dt=True)
    model = dataclasses.replace(model, contact_reach=math.inf)
    g = np.asarray(GRAVITY, dtype=np.float32).astype(np.float64)  # the kernels use g in float32
    mass = model.particle_mass.numpy().astype(np.float64)
    x0, v0 = vec(state.particle_q), vec(state.particle_qd)
    omega0 = state.particle_omega.numpy().copy()
    sim = Simulation(model, state)
    chunk = FREE_FALL_STEPS // FREE_FALL_FRAMES
    for frame in range(1, FREE_FALL_FRAMES + 1):
        sim.advance(chunk)
        n = frame * chunk
        t = n * FREE_FALL_DT
        x_exact = x0 + v0 * t + 0.5 * g * t * t
        v_exact = v0 + g * t
        v_max = max(np.abs(v0).max(), np.abs(v_exact).max())
        x_max = max(np.abs(x0).max(), np.abs(x_exact).max())
        v_atol = n * EPS32 * v_max
        x_atol = n * EPS32 * (x_max + t * v_max) / 2.0
        assert x_atol < 0.25 * 0.5 * np.abs(g).min() * FREE_FALL_DT * t  # a first-order scheme would fail
        x, v = vec(sim.state.particle_q), vec(sim.state.particle_qd)
        np.testing.assert_allclose(v, v_exact, rtol=0.0, atol=v_atol)
        np.testing.assert_allclose(x, x_exact, rtol=0.0, atol=x_atol)
        np.testing.assert_array_equal(sim.state.particle_omega.numpy(), omega0)  # no torque: spin untouched
        # Momentum: Σ m v − Σ m v₀ = (Σ m) g t.
        np.testing.assert_allclose(
            (mass[:, None] * (v - v0)).sum(axis=0), mass.sum() * g * t, rtol=0.0, atol=mass.sum() * v_atol
        )
    np.testing.assert_array_equal(sim.state.particle_f.numpy(), 0.0)  # the fall really was contact-free


SMALL_DT = 5.0e-6  # [s]: not a power of two, so dt/2 · g rounds, and the same way at every kick
SMALL_DT_STEPS = 20_000  # 0.1 s
CARRY_BOUND = 4.0
"""|v − g t| <= CARRY_BOUND EPS32 |g t| at any step count (the test's comment derives it)."""


def test_free_fall_keeps_float32_precision_over_many_small_steps(device: str) -> None:
    # v_n = g t exactly (above). The 2n kicks add the increment fl(dt/2 · g) to a float32 velocity with a carry
    # (kernels/integrate.py carried_sum): Kahan's bound on the sum is 2 ε |v| + O(n ε²) |v| (increments of one sign;
    # n ε² = 3e-10 here), and the increment errs by at most ε/2 (one rounding of dt/2 · g, alike at every kick), so
    # |v − g t| <= 4 ε |g t| whatever n: the bound does not grow with the steps. A sphere's centre is float64 and sums
    # dt v_{k+1/2}, each within that bound: |x − x_exact| <= 4 ε |g| t². A node's displacement is float32: each drift
    # rounds by ulp(u)/2 besides, n ε max|u| / 2 at most. Without the carry the same rounding of every kick piled up
    # to 8e-5 of g t at dt = 1e-5 s and 1.2e-3 at 1e-6 s over 0.1 s, worse the finer the step.
    from warpdem.build.mesh import box_mesh

    b = ModelBuilder(gravity=GRAVITY)
    b.add_material("rock", 2600.0, YOUNG, POISSON)
    b.add_sphere((0.0, 0.0, 0.0), 0.01, "rock")
    points, tets = box_mesh((5.0, 5.0, 5.0), (5.1, 5.1, 5.1), (1, 1, 1))
    b.add_tet_mesh(points, tets, "rock")  # one rigidly falling cell: its tets stay unstrained, no force
    model, state = b.finalize(device, dt=SMALL_DT, allow_unstable_dt=True)
    sim = Simulation(model, state)
    sim.advance(SMALL_DT_STEPS)
    dt32 = float(np.float32(SMALL_DT))  # the kernels take dt in float32
    g = np.asarray(GRAVITY, dtype=np.float32).astype(np.float64)
    t = SMALL_DT_STEPS * dt32
    v_bound = CARRY_BOUND * EPS32 * np.linalg.norm(g) * t
    nn = sim.node_count
    np.testing.assert_allclose(vec(sim.state.particle_qd)[0], g * t, rtol=0.0, atol=v_bound)
    np.testing.assert_allclose(vec(sim.state.node_qd)[:nn], np.tile(g * t, (nn, 1)), rtol=0.0, atol=v_bound)
    x_bound = CARRY_BOUND * EPS32 * np.linalg.norm(g) * t * t
    np.testing.assert_allclose(vec(sim.state.particle_q)[0], 0.5 * g * t * t, rtol=0.0, atol=x_bound)
    u = vec(sim.state.node_u)[:nn]
    u_bound = x_bound + SMALL_DT_STEPS * EPS32 * np.abs(u).max() / 2.0
    np.testing.assert_allclose(u, np.tile(0.5 * g * t * t, (nn, 1)), rtol=0.0, atol=u_bound)
    assert u_bound < 1e-2 * np.abs(0.5 * g * t * t).min()


# ----------------------------------------------------------------------------------------------------------------
# Fixed and prescribed spheres


def test_fixed_sphere_is_not_moved_by_impacts(device: str) -> None:
    # A fixed sphere has infinite mass: hit head-on by a free sphere (m* = m, R* = r/2) it sends it back at e v,
    # and hit obliquely with friction it neither moves nor spins.
    speed, e = 1.0, 0.5
    _, t_contact = hertz_impact(sphere_mass(), 0.5 * RADIUS, speed)
    dt = t_contact / STEPS_PER_CONTACT
    gap = 3.5 * speed * dt
    offset = 0.5 * RADIUS
    b = builder(friction=0.5, restitution=e)
    b.add_sphere((0.0, 0.0, 0.0), RADIUS, "grain", motion="fixed")
    b.add_sphere((2.0 * RADIUS + gap, 0.0, 0.0), RADIUS, "grain", velocity=(-speed, 0.0, 0.0))
    x_oblique = -math.sqrt((2.0 * RADIUS) ** 2 - offset**2) - gap
    b.add_sphere((x_oblique, offset, 0.0), RADIUS, "grain", velocity=(speed, 0.0, 0.0))
    model, state = b.finalize(device, dt=dt, sort=False)
    q0 = state.particle_q.numpy()[0].copy()
    sim = Simulation(model, state)
    sim.advance(2 * STEPS_PER_CONTACT)
    np.testing.assert_array_equal(sim.state.particle_q.numpy()[0], q0)
    np.testing.assert_array_equal(sim.state.particle_qd.numpy()[0], 0.0)
    np.testing.assert_array_equal(sim.state.particle_omega.numpy()[0], 0.0)
    assert np.linalg.norm(sim.state.particle_omega.numpy()[2]) > 0.0  # the oblique hit did exert a torque
    np.testing.assert_allclose(sim.state.particle_qd.numpy()[1, 0], e * speed, rtol=DAMPED_RTOL)
    assert sim.energy().boundary_work == 0.0  # a body that does not move does no work


def test_fixed_sphere_given_a_velocity_does_not_move(device: str) -> None:
    # "fixed (never moves)": a velocity given to a fixed sphere must be ignored, or the builder must refuse it.
    b = builder()
    try:
        b.add_sphere(
            (0.0, 0.0, 0.0), RADIUS, "grain", velocity=(1.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 5.0), motion="fixed"
        )
        model, state = b.finalize(device, dt=1.0e-4, sort=False)
    except ValueError:
        return  # refusing the contradiction is as good as ignoring the velocity
    q0 = state.particle_q.numpy().copy()
    sim = Simulation(model, state)
    sim.advance(100)
    np.testing.assert_array_equal(sim.state.particle_q.numpy(), q0)
    np.testing.assert_array_equal(sim.state.particle_qd.numpy(), 0.0)
    np.testing.assert_array_equal(sim.state.particle_omega.numpy(), 0.0)


def test_prescribed_sphere_pushes_free_sphere_and_books_its_work(device: str) -> None:
    # Elastic, frictionless, head-on: the driver (velocity V, spin Ω about the line of centres) keeps v and ω bit
    # for bit and moves by V t; the free sphere leaves at 2V; the driver's work is 2 m V², and the energy balance
    # stays constant (within the lag of the booked work during the contact).
    speed = DRIVER_SPEED
    mass = sphere_mass()
    f_max, t_contact = hertz_impact(mass, 0.5 * RADIUS, speed)
    dt = t_contact / STEPS_PER_CONTACT
    b = builder()
    velocity, spin = np.array([speed, 0.0, 0.0]), np.array([30.0, 0.0, 0.0])
    b.add_sphere((0.0, 0.0, 0.0), RADIUS, "grain", velocity=velocity, angular_velocity=spin, motion="prescribed")
    b.add_sphere((2.0 * RADIUS + 3.5 * speed * dt, 0.0, 0.0), RADIUS, "grain")
    model, state = b.finalize(device, dt=dt, sort=False)
    x0 = vec(state.particle_q)[0]
    v_driver, w_driver = state.particle_qd.numpy()[0].copy(), state.particle_omega.numpy()[0].copy()
    sim = Simulation(model, state)
    e0 = sim.energy().total
    work = 2.0 * mass * speed**2
    chunk = STEPS_PER_CONTACT // 10
    errors = []
    for frame in range(1, 31):
        sim.advance(chunk)
        n = frame * chunk
        np.testing.assert_array_equal(sim.state.particle_qd.numpy()[0], v_driver)
        np.testing.assert_array_equal(sim.state.particle_omega.numpy()[0], w_driver)
        # x = x₀ + V t: n drifts, each rounding by ulp(x)/2, with the float32 dt · V off by <= EPS32 relative.
        x_atol = EPS32 * (n * np.abs(vec(sim.state.particle_q)[0]).max() / 2.0 + speed * n * dt)
        np.testing.assert_allclose(vec(sim.state.particle_q)[0], x0 + velocity * n * dt, rtol=0.0, atol=x_atol)
        errors.append(sim.energy().total - e0)
    balance = sim.energy()
    np.testing.assert_allclose(sim.state.particle_qd.numpy()[1], [2.0 * speed, 0.0, 0.0], rtol=VERLET_RTOL, atol=0)
    np.testing.assert_allclose(balance.boundary_work, work, rtol=2.0 * VERLET_RTOL)
    lag = DRIVER_WORK_LAG * speed * dt * f_max
    np.testing.assert_allclose(np.abs(errors).max(), 0.0, atol=DRIVER_WORK_MARGIN * lag)
    np.testing.assert_allclose(errors[-1], 0.0, atol=VERLET_RTOL * work)


def test_spinning_prescribed_sphere_books_torque_work(device: str) -> None:
    # A prescribed sphere at rest spinning at Ω drags a free sphere that hits it (friction 0.5, no dashpots, linear
    # springs so that the stored spring energy k_t ξ²/2 has a constant k_t): all the work comes from the torque,
    # W = −Σ T · Ω dt, and kinetic + elastic + friction dissipation − W stays constant.
    speed = DRIVER_SPEED
    mass = sphere_mass()
    t_contact = math.pi * math.sqrt(mass / (YOUNG * RADIUS))  # linear k_n = E r, m* = m
    dt = t_contact / STEPS_PER_CONTACT
    b = builder(friction=0.5, restitution=1.0, normal="linear", tangential="linear")
    spin = np.array([0.0, 0.0, 200.0])
    b.add_sphere((0.0, 0.0, 0.0), RADIUS, "grain", angular_velocity=spin, motion="prescribed")
    b.add_sphere((2.0 * RADIUS + 3.5 * speed * dt, 0.0, 0.0), RADIUS, "grain", velocity=(-speed, 0.0, 0.0))
    model, state = b.finalize(device, dt=dt, sort=False)
    sim = Simulation(model, state)
    e0 = sim.energy()
    sim.advance(2 * STEPS_PER_CONTACT)
    e1 = sim.energy()
    np.testing.assert_array_equal(sim.state.particle_omega.numpy()[0], spin.astype(np.float32))
    np.testing.assert_array_equal(sim.state.particle_qd.numpy()[0], 0.0)
    assert e1.boundary_work > 0.5 * e0.kinetic_translational  # the torque did substantial work
    assert e1.dissipated_friction > 0.1 * e1.boundary_work
    np.testing.assert_allclose(e1.total, e0.total, rtol=0.0, atol=DAMPED_RTOL * e1.boundary_work)


# ----------------------------------------------------------------------------------------------------------------
# Moving walls


@pytest.mark.parametrize("restitution", [1.0, 0.5])
def test_moving_wall_pushes_sphere_and_books_its_work(device: str, restitution: float) -> None:
    # The wall x = V t (normal +x) hits a sphere at rest: it leaves at (1 + e) V, the wall does W = (1 + e) m V²,
    # and kinetic + elastic + dissipated − W stays at its initial value.
    speed, e = DRIVER_SPEED, restitution
    mass = sphere_mass()
    f_max, t_contact = hertz_impact(mass, RADIUS, speed)
    dt = t_contact / STEPS_PER_CONTACT
    b = builder(restitution=e)
    b.add_plane_wall((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), "grain", velocity=(speed, 0.0, 0.0))
    b.add_sphere((RADIUS + 3.5 * speed * dt, 0.0, 0.0), RADIUS, "grain")
    model, state = b.finalize(device, dt=dt, sort=False)
    sim = Simulation(model, state)
    e0 = sim.energy().total
    chunk = STEPS_PER_CONTACT // 10
    errors = []
    for _ in range(30):
        sim.advance(chunk)
        errors.append(sim.energy().total - e0)
    n = 30 * chunk
    balance = sim.energy()
    work = (1.0 + e) * mass * speed**2
    wall_x = float(sim.state.wall_point.numpy()[0, 0])
    np.testing.assert_allclose(wall_x, speed * n * dt, rtol=0.0, atol=EPS32 * n * (wall_x / 2.0 + speed * dt))
    if e == 1.0:
        np.testing.assert_allclose(sim.state.particle_qd.numpy()[0], [2.0 * speed, 0.0, 0.0], rtol=VERLET_RTOL, atol=0)
        np.testing.assert_allclose(balance.boundary_work, work, rtol=2.0 * VERLET_RTOL)
        lag = DRIVER_WORK_LAG * speed * dt * f_max
        np.testing.assert_allclose(np.abs(errors).max(), 0.0, atol=DRIVER_WORK_MARGIN * lag)
        np.testing.assert_allclose(errors[-1], 0.0, atol=VERLET_RTOL * work)
    else:
        np.testing.assert_allclose(sim.state.particle_qd.numpy()[0, 0], (1.0 + e) * speed, rtol=DAMPED_RTOL)
        np.testing.assert_allclose(balance.boundary_work, work, rtol=DAMPED_RTOL)
        assert balance.dissipated_damping > 0.1 * work
        np.testing.assert_allclose(errors[-1], 0.0, atol=DAMPED_RTOL * work)
