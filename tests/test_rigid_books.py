"""The energy books of rigid blocks that turn under their forces (kernels/rigid.py ``node_velocity_ahead``,
kernels/integrate.py ``book_half_ahead_kernel``, kernels/loads.py).

Oracle: velocity Verlet's energy identity for a body. A half kick of L by ½ dt T at a fixed pose q changes
½ L·I(q)⁻¹L by exactly ½ dt T·ω(q, L̄), L̄ the mean of L before and after (the kinetic energy is quadratic in L at a
fixed pose), and likewise ½ M V² by ½ dt F·V̄. With T = Σ R(q) r0_i × f_i and F = Σ f_i that is, per node,
½ dt Σ f_i·(V + ω(q, L) × R(q) r0_i) at the kick's mean momenta, which is Verlet's trapezoid
½ dt f_n·(v_{n−1/2} + v_{n+1/2}) of every force with both halves at q_n, the pose f_n was made at, and a shadow term
dt²/8 (|F|²/M + T·I⁻¹T) (warpdem.stages.rigid.body_energy). The free rotor between the kicks keeps |L| and, about a
principal axis of the body, ½ L·ω exactly. So where every force books its work that way, kinetic − shadow plus the
books is constant to rounding: the balance of warpdem.stages.energy.EnergyBalance closes.

Before the half ahead of each evaluation was booked at the next pose, V + ω(q_{n+1}, L_{n+1/2}) × R(q_{n+1}) r0: an
error of relative size ω dt per step in the work of any force with a torque (measured, in the cases below: 5.6e-4
for the blast, 1.4e-4 on the roller plane, 5.7e-5 against the dashpots, 8.0e-6 on the rough plane; the cohesive
elements, which book both halves of their trapezoid at the evaluation, 3.7e-6 with the others' books right).

Tolerance BOOKS_RTOL: the booked halves are float32 products f·v of float32 forces and float32 velocities rounded
once from the body's float64 motion (a relative error of a few ε₃₂ per term), summed in float64; the kinetic energy
is float64 of the same float32 forces. The terms of one force mostly share a sign, so the error stays below a few
ε₃₂ of the work in play however many steps: 2 ε₃₂ = 2.4e-7. The free rotor adds its splitting error off a principal
axis, O((ω dt)²) of the spin energy and bounded (the dashpot block, whose drag tips L off its axis: 2e-8). Measured
after the fix: 2.9e-9, 3.8e-9, 2.2e-8, 1.6e-9, 1.3e-9.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_cohesive import set_elements
from test_conversion import worst_balance_error
from test_fem_contact import two_blocks

from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import boundary_faces, box_mesh
from warpdem.simulation import Simulation
from warpdem.stages.fracture import fracture_state
from warpdem.stages.loads import PressureHistory

F32_EPS = float(np.finfo(np.float32).eps)
BOOKS_RTOL = 2.0 * F32_EPS  # module docstring


def spin_nodes(model, state, omega, velocity=(0.0, 0.0, 0.0), nodes=None) -> None:
    """Give ``nodes`` (all: None) the rigid velocity field V + ω × (x − c) about their centre of mass c [m/s]."""
    x = model.node_ref_q.numpy().astype(np.float64) + state.node_u.numpy()
    m = model.node_mass.numpy().astype(np.float64)
    nodes = np.arange(len(x)) if nodes is None else nodes
    c = (m[nodes, None] * x[nodes]).sum(axis=0) / m[nodes].sum()
    v = state.node_qd.numpy()
    v[nodes] = (np.asarray(velocity) + np.cross(np.asarray(omega, dtype=np.float64), x[nodes] - c)).astype(np.float32)
    state.node_qd.assign(v)


def worst_balance(model, state, frames: int, steps: int) -> tuple[float, np.ndarray, np.ndarray, Simulation]:
    """Switch every block rigid at once, run ``frames`` × ``steps`` steps and return the largest |balance error|
    over the frames [-], the last body's angular momentum at the switch and at the end [kg m²/s], and the run."""
    sim = Simulation(model, state)
    sim.switch_to_rigid()
    l0 = sim.state.body_l.numpy()[-1].copy()
    worst = worst_balance_error(sim, frames, steps)
    return worst, l0, sim.state.body_l.numpy()[-1], sim


@pytest.mark.parametrize("roller", [False, True])
def test_block_turned_by_an_off_centre_blast_closes_its_books(device, roller):
    """A 2 × 1 × 0.5 m block, rigid from t = 0, under a 300 MPa blast on one half of a face: the load's torque spins
    it (free: about y, from the right half of its top; on a roller floor: about z, from the upper half of its x+
    face, the floor's reaction doing no work). The load work equals the kinetic energy it gave (less the shadow
    term) to BOOKS_RTOL."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (2.0, 1.0, 0.5), (4, 2, 1))
    faces = boundary_faces(tets)
    c = points[faces].mean(axis=1)
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", 2600.0, 4.0e10, 0.25)
    b.add_tet_mesh(points, tets, "rock")
    if roller:
        loaded = faces[np.isclose(c[:, 0], 2.0) & (c[:, 1] > 0.5)]
        b.add_boundary(faces[np.isclose(c[:, 2], 0.0)], "roller")
    else:
        loaded = faces[np.isclose(c[:, 2], 0.5) & (c[:, 0] > 1.0)]
    b.add_face_pressure(loaded, PressureHistory.blast(3.0e8, 1.0e-4, 2.0e-3), "charge")
    model, state = b.finalize(device, safety_factor=0.5)
    worst, _, spin, _ = worst_balance(model, state, 10, 20)
    axis = 2 if roller else 1
    assert abs(spin[axis]) > 1.0e4  # it turns: |L| 3.5e4 (roller), 2.8e5 kg m²/s (free) measured
    assert worst < BOOKS_RTOL


def test_spinning_block_slowed_by_dashpots_closes_its_books(device):
    """A 1 × 0.6 × 0.3 m block spun at 200 rad/s about z and moving at 1.1 m/s, its faces on non-reflecting
    dashpots: the drag takes its motion out within a few milliseconds. What the dashpots absorbed (booked from
    ``node_f_absorbed``) equals the kinetic energy lost to BOOKS_RTOL."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 0.6, 0.3), (3, 2, 1))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", 2000.0, 1.0e8, 0.25)
    b.add_tet_mesh(points, tets, "rock")
    b.add_boundary(boundary_faces(tets), "non_reflecting")
    model, state = b.finalize(device, safety_factor=0.5)
    spin_nodes(model, state, (0.0, 0.0, 200.0), (1.0, 0.5, 0.0))
    worst, start, end, _ = worst_balance(model, state, 10, 2)
    assert np.linalg.norm(end) < 0.01 * np.linalg.norm(start)  # the dashpots took the spin (measured to 1e-4)
    assert worst < BOOKS_RTOL


def test_spinning_block_on_a_rough_plane_closes_its_books(device):
    """The upper block of tests/test_fem_contact.py's jointed box (friction 0.3, gravity tilted 10°, the lower
    block held) spun at 12 rad/s about the joint's normal: its corners drag and dig in, friction brakes it and it
    hops. The node–face contacts' dissipation (booked from ``node_f_contact``) closes the books to BOOKS_RTOL."""
    model, state, upper = two_blocks(device, 10.0, 2)
    spin_nodes(model, state, (0.0, 0.0, 12.0), nodes=upper)
    worst, start, end, _ = worst_balance(model, state, 10, 30)
    assert end[2] < 0.98 * start[2]  # friction braked the spin (measured to 0.96 of it)
    assert worst < BOOKS_RTOL


def test_block_spun_off_its_cohesive_elements_closes_its_books(device):
    """The same upper block glued to its held base by cohesive elements at its nine joint nodes (each pair of
    daughters across the joint; f_c 200 kN, Γ 50 J/m², 0.25 m² each, p1 along the normal) and spun at 4 rad/s about
    the normal: the spin tears the elements (their opening grows as ω t r) and then friction brakes it. The elements'
    books (their trapezoid, with f_n's half at the pose it was made at) close the balance to BOOKS_RTOL."""
    model, state, upper = two_blocks(device, 0.0, 2)
    x = model.node_ref_q.numpy()
    nodes = np.arange(int(state.node_count.numpy()[0]))
    joint = nodes[np.isclose(x[nodes, 2], 0.5)]
    above = np.isin(joint, upper)
    pairs = [(a, b) for a in joint[~above] for b in joint[above] if np.array_equal(x[a], x[b])]
    assert len(pairs) == 9
    model = dataclasses.replace(model, cohesive_capacity=len(pairs))
    state = dataclasses.replace(state, **fracture_state(model))
    a, b = zip(*pairs, strict=True)
    set_elements(state, list(a), list(b), 1.0, (0.0, 0.0, 1.0), fc=2.0e5, gamma=50.0, area=0.25)
    spin_nodes(model, state, (0.0, 0.0, 4.0), nodes=upper)
    worst, start, end, sim = worst_balance(model, state, 10, 20)
    assert int(sim.state.cohesive_broken_total.numpy()[0]) == len(pairs)  # all torn
    assert end[2] < 0.97 * start[2]  # the elements and friction braked the spin (measured to 0.94 of it)
    assert worst < BOOKS_RTOL
