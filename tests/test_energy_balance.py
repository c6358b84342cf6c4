"""Energy balance of the FEM node–face contact (kernels/fem_contact.py, warpdem/stages/fem_contact.py) on kinematic
paths.

A block U is driven at a constant velocity V (every node, warpdem.stages.loads velocity drivers) over fixed blocks, the
contact frictionless and elastic (restitution 1), the tets without bulk viscosity, no gravity. Oracle: with every
moving node driven, velocity Verlet's kicks are overridden and x_{n+1} = x_n + dt V, so the kinetic energy is constant
(no shadow term) and the driver's booked work -½ dt (f_n + f_{n+1}) · V is exactly minus the work of the forces on
U's nodes; the fixed nodes do no work. U's nodes all move by the same float32 increments, so the block is exactly
rigid and its tets carry no force. Hence

    W_contact = -(ΔU_contact + ΔD_contact),  i.e.  Simulation.energy().total stays at its initial value,

for any path; here W_contact = 0 as well (the faces are axis-aligned and V is parallel to them).

Tolerance. Every face in contact is axis-aligned and no z-coordinate changes, so depths and normals are exact; what is
left is the float32 rounding of each contact's ½ k δ² where it is measured or booked: ENERGY_ROUNDOFF ε₃₂ (U + D).
A contact event that creates or loses ½ k δ² without work is off by that much per node: ½ k δ² ≈ 1 J here, against a
tolerance of about 1e-3 J.
"""

from __future__ import annotations

import numpy as np
import pytest

from warpdem.build.builder import InteractionProps, ModelBuilder
from warpdem.build.mesh import box_mesh
from warpdem.simulation import Simulation
from warpdem.stages.energy import EnergyBalance
from warpdem.stages.tets import TetProps

YOUNG = 1.0e8  # [Pa] a soft rock: a long time step
POISSON = 0.25
DENSITY = 2000.0  # [kg/m³]
CELL = 0.25  # [m] mesh cell
OVERLAP = 1.0e-3  # [m] how deep U's bottom starts behind the top of the block under it (4e-3 of a cell)
SPEED = 4.0  # [m/s]
F32_EPS = float(np.finfo(np.float32).eps)
ENERGY_ROUNDOFF = 8.0
"""float32 roundings in one contact's ½ k δ² (the product, its depth's subtraction), measured and booked, with a
factor of 2 of margin."""
FRAMES = 10


def driven_block_over(device: str, lower: list[tuple[tuple, tuple, tuple]], upper: tuple[tuple, tuple, tuple], v):
    """Fixed boxes ``lower`` and a box ``upper`` driven at velocity v [m/s]; boxes as (lo, hi, cells)."""
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.set_tet_properties("rock", TetProps(bulk_viscosity_linear=0.0, bulk_viscosity_quadratic=0.0))
    b.set_interaction("rock", "rock", InteractionProps(friction=0.0, restitution=1.0))
    for box in lower:
        points, tets = box_mesh(*box)
        b.add_tet_mesh(points, tets, "rock", fixed_nodes=np.arange(len(points)))
    points, tets = box_mesh(*upper)
    b.add_node_velocity(b.add_tet_mesh(points, tets, "rock", velocity=v), v)
    model, state = b.finalize(device, safety_factor=0.5)
    return Simulation(model, state)


def balance_errors(sim: Simulation, distance: float) -> tuple[np.ndarray, np.ndarray, object, object]:
    """Run U over ``distance`` [m] in FRAMES frames; the balance error and its tolerance at each, and the first and
    last energy balances."""
    e0 = sim.energy()
    steps = round(distance / SPEED / sim.model.dt) // FRAMES
    errors, tols = [], []
    for _ in range(FRAMES):
        sim.advance(steps)
        e = sim.energy()
        errors.append(e.total - e0.total)
        tols.append(ENERGY_ROUNDOFF * F32_EPS * (e0.elastic + e.elastic + e.dissipated_fem_contact))
    return np.array(errors), np.array(tols), e0, e


def test_block_sliding_down_a_step_and_off_an_edge(device):
    """U rests on two fixed blocks, B and C, C's top a step lower than B's (less than the overlap), and slides from
    B over the step onto C and off C's far edge. Its nodes change target face at the step (to a shallower one: the
    drop of ½ k δ² is booked as dissipated), its trailing corner passes B's side face (it keeps the top it presses),
    and its nodes and the fixed top nodes leave contact while compressed (the spring's energy is booked as they go).
    Before commit 326117a the drops went unbooked: about -260 J."""
    top, step = 2 * CELL, 0.4 * OVERLAP
    b_box = ((0.0, 0.0, 0.0), (4 * CELL, 4 * CELL, top), (4, 4, 2))
    c_box = ((4 * CELL, 0.0, 0.0), (8 * CELL, 4 * CELL, top - step), (4, 4, 2))
    u_box = ((2 * CELL, 0.0, top - OVERLAP), (9 * CELL, 4 * CELL, top - OVERLAP + 2 * CELL), (7, 4, 2))
    sim = driven_block_over(device, [b_box, c_box], u_box, (SPEED, 0.0, 0.0))
    errors, tols, e0, e = balance_errors(sim, 5 * CELL)
    assert e.elastic < 0.5 * e0.elastic  # the path did what it is for: most contacts were left compressed
    np.testing.assert_array_less(np.abs(errors), tols)
    assert tols.max() < 1e-5 * e0.elastic  # the check is tight


def test_block_sliding_onto_another_creates_no_contact_energy(device):
    """U overhangs the right edge of a fixed block L, pressed OVERLAP into it, and slides left onto it: U's nodes
    past the edge slide into L's top faces, and L's top nodes into U's bottom faces, already OVERLAP behind their
    planes. Such a contact starts slack (the depth it had is carried as an offset), or ½ k δ² would appear that no
    force worked for: +370 J at commit e394e34."""
    top = 2 * CELL
    l_box = ((0.0, 0.0, 0.0), (8 * CELL, 4 * CELL, top), (8, 4, 2))
    u_box = ((5 * CELL, 0.0, top - OVERLAP), (10 * CELL, 4 * CELL, top - OVERLAP + 2 * CELL), (5, 4, 2))
    sim = driven_block_over(device, [l_box], u_box, (-SPEED, 0.0, 0.0))
    errors, tols, e0, e = balance_errors(sim, 5 * CELL)
    np.testing.assert_array_less(np.abs(errors), tols)
    assert e.dissipated_fem_contact > 0.2 * e0.elastic  # the path did what it is for: U's trailing edge left L's
    # top nodes while compressed, as its leading edge slid onto new ones
    assert tols.max() < 1e-5 * e0.elastic


# ----------------------------------------------------------------------------------------------------------------
# Sphere contacts (kernels/contact.py): the books of velocity Verlet's own work.
#
# Oracle. Velocity Verlet changes a body's kinetic energy over a step by exactly
#     ΔKE = ½ dt (F_n + F_{n+1})·v_{n+1/2} + S_{n+1} - S_n,   S = dt²/8 (|F|²/m + |T|²/I)
# (F the total force with gravity, T the torque). Gravity's trapezoid is -ΔPE exactly, every contact books
# D = -W - ΔU with W its share of the trapezoid, and the balance carries S as its own line (EnergyBalance.shadow), so
# its total is constant up to the float32 rounding of each step: positions, velocities and booked work, BOOK_ROUNDOFF
# ε₃₂ of the energy in play per step, summed as a random walk over the steps. Without the shadow line the error
# would be S_N - S_0 = O(dt²) (1.3 % of the energy in play at the end of the linear run below, at dt).

BOOK_ROUNDOFF = 16.0
"""float32 roundings per step relative to the energy in play (a position's rounding against the contact force, the
force sums and dot products of the booked work), with margin."""
CLOUD = 40  # spheres
CLOUD_RADIUS = 0.01  # [m]


def shadow_energy_spheres(sim: Simulation) -> float:
    """Verlet's shadow term of the free spheres, dt²/8 Σ (|f + m g|²/m + |t|²/I) [J], at the forces held now."""
    m, s = sim.model, sim.state
    n = sim.particle_count
    free = m.particle_motion.numpy()[:n] == 0
    mass = m.particle_mass.numpy()[:n].astype(np.float64)[free]
    inv_inertia = m.particle_inv_inertia.numpy()[:n].astype(np.float64)[free]
    f = s.particle_f.numpy()[:n].astype(np.float64)[free] + mass[:, None] * np.asarray(m.gravity, dtype=np.float64)
    t = s.particle_t.numpy()[:n].astype(np.float64)[free]
    return m.dt**2 / 8.0 * float(np.sum(np.sum(f * f, axis=1) / mass) + np.sum(inv_inertia * np.sum(t * t, axis=1)))


def sphere_cloud(device: str, laws: tuple[str, str, str], dt_factor: float, lift: float = 0.0) -> Simulation:
    """CLOUD spheres of mixed radii dropped with random velocities and spins into a box whose floor rises at
    0.05 m/s, one sphere driven sideways through them; the whole scene ``lift`` [m] up (gravity's datum)."""
    rng = np.random.default_rng(3)
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.normal, b.tangential, b.rolling = laws
    b.add_material("glass", 2500.0, 5.0e7, 0.25)
    b.default_interaction = InteractionProps(friction=0.5, restitution=0.6, rolling_friction=0.05)
    cells = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(3), indexing="ij"), axis=-1).reshape(-1, 3)
    centers = 0.012 + cells[: CLOUD - 1] * 0.024 + rng.uniform(-0.002, 0.002, (CLOUD - 1, 3))
    centers[:, 2] += lift
    radii = CLOUD_RADIUS * rng.uniform(0.8, 1.0, CLOUD - 1)
    b.add_spheres(centers, radii, "glass", velocity=rng.normal(0.0, 0.3, (CLOUD - 1, 3)), angular_velocity=(0, 5, 0))
    b.add_sphere((0.0, 0.05, 0.02 + lift), CLOUD_RADIUS, "glass", velocity=(0.2, 0.0, 0.0), motion="prescribed")
    b.add_plane_wall((0.0, 0.0, lift), (0.0, 0.0, 1.0), "glass", velocity=(0.0, 0.0, 0.05))
    b.add_box_walls((-0.02, -0.01, lift - 1.0), (0.11, 0.11, lift + 1.0), "glass", open_top=True)
    model, state = b.finalize(device, safety_factor=0.2 * dt_factor)
    return Simulation(model, state)


def run_books(sim: Simulation, duration: float) -> tuple[np.ndarray, int, float, EnergyBalance]:
    """Run ``duration`` [s] in 10 frames; the balance's change at each frame [J], the steps, the largest energy in play
    at the frames [J] and the last balance."""
    e0 = sim.energy()
    in_play = e0.in_play
    frames = 10
    steps = max(1, round(duration / sim.model.dt / frames))
    changes = []
    for _ in range(frames):
        sim.advance(steps)
        e = sim.energy()
        np.testing.assert_allclose(e.shadow, shadow_energy_spheres(sim), rtol=1e-9)
        in_play = max(in_play, e.in_play)
        changes.append(e.total - e0.total)
    return np.array(changes), steps * frames, in_play, e


@pytest.mark.parametrize("laws", [("linear", "linear", "none"), ("hertz", "mindlin", "constant_torque")])
@pytest.mark.parametrize("dt_factor", [1.0, 0.5])
def test_sphere_contact_books_close_the_balance(device, laws, dt_factor):
    """The cloud falls, collides, rolls and slides for 0.15 s, at dt and dt/2: at every frame the balance (with its
    shadow line) is where it started, to float32 rounding. Before the exact books (commit c13349d) friction alone
    was over-counted by several per cent, to first order in dt."""
    sim = sphere_cloud(device, laws, dt_factor)
    changes, steps, in_play, e = run_books(sim, 0.15)
    assert e.dissipated_friction > 0.1 * in_play and e.dissipated_damping > 0.1 * in_play  # it did collide
    assert e.boundary_work != 0.0  # the floor and the driven sphere worked
    if laws[0] == "linear":
        assert e.stiffness_change == 0.0  # k_t is constant: no energy without work
    else:
        assert e.stiffness_change > 0.0  # Mindlin's k_t(δ) springs gained energy as the overlaps grew
    tol = BOOK_ROUNDOFF * F32_EPS * np.sqrt(steps) * in_play
    assert tol < 1e-3 * in_play  # the bound is tighter than the 0.1 %
    np.testing.assert_allclose(changes, 0.0, atol=tol)


def test_balance_error_does_not_depend_on_the_gravity_datum(device):
    """The same cloud 1 m higher (a power of two: float32 coordinates keep their spacing up to one exponent): the
    gravity potential moves by M g · 1 m, ten times the energy in play, but the energy in play (the error's
    scale, EnergyBalance.in_play) does not, beyond the trajectories' float32 divergence, and the relative error stays
    within the rounding bound. The old scale held |gravity potential|: it shrank the error tenfold here."""
    results = []
    for lift in (0.0, 1.0):
        sim = sphere_cloud(device, ("linear", "linear", "none"), 1.0, lift=lift)
        e0 = sim.energy()
        changes, steps, in_play, _ = run_books(sim, 0.05)
        np.testing.assert_allclose(changes, 0.0, atol=BOOK_ROUNDOFF * F32_EPS * np.sqrt(steps) * in_play)
        results.append((e0.gravity_potential, in_play))
    n = sim.particle_count
    free = sim.model.particle_motion.numpy()[:n] == 0  # the driven sphere's weight is its driver's business
    mass = float(sim.model.particle_mass.numpy()[:n][free].sum())
    np.testing.assert_allclose(results[1][0] - results[0][0], mass * 9.81, rtol=1e-5)  # the datum did move
    assert mass * 9.81 > 5.0 * results[0][1]
    np.testing.assert_allclose(results[1][1], results[0][1], rtol=0.05)


def test_sphere_at_rest_in_a_nest_books_no_dissipation(device):
    """A sphere set down in the pocket of three fixed spheres, gravity tilted 10° so that its contacts carry
    tangential load, settles within 1 s (restitution 0.5 and the tangential dashpots). At rest nothing does work: over
    the next 2 s the balance stays flat to the rounding bound (the old books grew monotonically: friction and damping
    both first order in the residual vibration, +6.7e-11 J here) and the friction line moves by less than 1e-3 of the
    contacts' energy. It does move a little: float32 positions at rest advance in whole ulps (1.9e-9 m here), not by
    dt·v, and that difference lands in the normal or the tangential line (about 2e-4 of the contacts' energy)."""
    tilt = np.radians(10.0)
    b = ModelBuilder(gravity=(9.81 * np.sin(tilt), 0.0, -9.81 * np.cos(tilt)))
    b.normal, b.tangential, b.rolling = "linear", "linear", "none"
    b.add_material("glass", 2500.0, 5.0e6, 0.25)
    b.default_interaction = InteractionProps(friction=0.5, restitution=0.5)
    r = CLOUD_RADIUS
    angles = np.radians([90.0, 210.0, 330.0])
    base = np.stack([2 * r / np.sqrt(3) * np.cos(angles), 2 * r / np.sqrt(3) * np.sin(angles), np.zeros(3)], axis=1)
    b.add_spheres(base, r, "glass", motion="fixed")
    b.add_sphere((0.0, 0.0, 2 * r * np.sqrt(2.0 / 3.0) * 1.0005), r, "glass")  # touching all three
    model, state = b.finalize(device)
    sim = Simulation(model, state)
    sim.advance(round(1.0 / model.dt))
    e1 = sim.energy()
    steps = round(2.0 / model.dt)
    sim.advance(steps)
    e2 = sim.energy()
    assert e1.elastic > 0.0 and e1.kinetic < 1e-6 * e1.elastic  # at rest, on its springs
    tol = BOOK_ROUNDOFF * F32_EPS * np.sqrt(steps) * e1.elastic
    np.testing.assert_allclose(e2.total, e1.total, atol=tol)
    assert abs(e2.dissipated_friction - e1.dissipated_friction) < 1e-3 * e1.elastic


@pytest.mark.parametrize("dt_factor", [1.0, 0.5])
def test_bonded_beam_struck_by_a_ball_closes_the_balance(device, dt_factor):
    """A bonded 8×2×2 lattice beam (damped bonds, ζ = 0.1) on the floor is struck by a ball at 3 m/s, hard enough to
    break bonds: the bonds book their dashpots, springs and breakage by the same trapezoid as the contacts
    (kernels/bonds.py), so the balance is where it started, to float32 rounding, at dt and dt/2. Before (commit
    c13349d) the bond dashpots booked (γ v²) dt at the half-step velocity, first order in dt."""
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.normal, b.tangential, b.rolling = "linear", "linear", "none"
    b.add_material("rock", 2600.0, 5.0e7, 0.25)
    b.default_interaction = InteractionProps(friction=0.5, restitution=0.5)
    r = CLOUD_RADIUS
    grid = np.stack(np.meshgrid(np.arange(8), np.arange(2), np.arange(2), indexing="ij"), axis=-1).reshape(-1, 3)
    ids = b.add_spheres(r + grid * 2.0 * r, r, "rock")
    b.add_bonded_group(ids, youngs_modulus=5.0e7, tensile_strength=1.0e5, shear_strength=1.0e5, damping_ratio=0.1)
    b.add_sphere((8.0 * r, 2.0 * r, 6.0 * r), 1.5 * r, "rock", velocity=(0.0, 0.0, -3.0))
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "rock")
    model, state = b.finalize(device, safety_factor=0.2 * dt_factor)
    sim = Simulation(model, state)
    changes, steps, in_play, e = run_books(sim, 0.03)
    assert int(sim.state.bonds_broken_total.numpy()[0]) > 0 and e.released_by_bond_breakage > 0.0
    assert e.dissipated_damping > 0.05 * in_play  # the bond and contact dashpots worked
    tol = BOOK_ROUNDOFF * F32_EPS * np.sqrt(steps) * in_play
    assert tol < 1e-3 * in_play
    np.testing.assert_allclose(changes, 0.0, atol=tol)
