"""Energy balance of the FEM node–face contact (kernels/fem_contact.py, warpdem/fem_contact.py) on kinematic paths.

A block U is driven at a constant velocity V (every node, warpdem.loads velocity drivers) over fixed blocks, the
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

from warpdem.builder import InteractionProps, ModelBuilder
from warpdem.mesh import box_mesh
from warpdem.simulation import Simulation
from warpdem.tets import TetProps

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
