"""Sub-steps of the cohesive elements' daughters: a multiple-time-step velocity Verlet (r-RESPA, Tuckerman, Berne and
Martyna 1992) that moves the nodes of the cohesive elements under the elements' forces in n sub-steps of h = dt/n
between the two half kicks of every other force (warpdem.stages.substep says why and what it books).

A step of a sub-stepped node i, F its forces but the cohesive ones (node_f, with gravity), f its cohesive forces
(``node_f_fast``):

    v0+ = v_n + dt/2 F_n/m                                    (the step's node kernel, kernels/integrate.py)
    n times: v += h/2 f/m; x += h v; f at x; v += h/2 f/m     (:func:`substep_kick_drift_kernel`, the elements)
    v1- = v, v_mean = (x_{n+1} − x_n)/dt                       (:func:`substep_finish_kernel`)
    F_{n+1} at x_{n+1}, with node_qd = v_mean
    v_{n+1} = v1- + dt/2 F_{n+1}/m                            (the next step's node kernel)

Every force but the cohesive ones books its work against node_qd, which during their evaluation holds v_mean, so
that x_{n+1} − x_n = dt node_qd as in a plain step (the contacts' x − dt v is the last position, as they assume).
The kinetic energy the two half kicks dv of F add is m dv·v0+ − ½ m |dv_s|² and m dv·v1- + ½ m |dv_e|²: the
shadow terms as in a plain step, and beyond the lines' m dv·v_mean the rest m dv_s·(v0+ − v_mean) +
m dv_e·(v1- − v_mean), booked per node on ``node_energy_substep`` (kernels/integrate.py ``book_substep_kick``). The
sub-steps are a velocity Verlet of the cohesive forces alone: each element books its trapezoid at h
(kernels/cohesive.py), and their shadow term is (dt/n)²/8 |f|²/m (kernels/books.py).
"""

from __future__ import annotations

import warp as wp

from .integrate import SubstepNodes, book_driver_work, book_substep_kick, carried_sum, start_node_forces
from .loads import NodeDriver, driver_holds
from .neighbors import flag_past_half_fem_skin
from .tets import node_free_directions

wp.set_module_options({"enable_backward": False})


@wp.struct
class StepDrivers:
    """The node velocity drivers as the sub-steps see them: per node its driver or -1 (``node_driver``; empty
    without drivers), the drivers, their number, the clock at the step's start [s] and the step [s]."""

    node_driver: wp.array(dtype=int)
    drivers: wp.array(dtype=NodeDriver)
    num_drivers: int
    time: wp.array(dtype=wp.float64)
    dt: float


@wp.func
def held_by_driver(i: int, drive: StepDrivers) -> bool:
    """Whether a velocity driver holds node i over this step: judged at the step's midpoint, as the step's half kicks
    judge it (kernels/integrate.py), so the sub-steps agree with them."""
    if drive.num_drivers == 0:
        return False
    d = drive.node_driver[i]
    if d < 0:
        return False
    return driver_holds(drive.drivers[d], drive.time[0] + wp.float64(0.5 * drive.dt))


@wp.func
def fast_half_kick(h: float, free: wp.vec3, v: wp.vec3, carry: wp.vec3, f: wp.vec3, inv_mass: float, held: bool):
    """v + h/2 f/m [m/s] by the kicks' compensated sum, in the node's free components; returns (v, carry, the work
    of a driver [J]). A node a driver holds keeps its velocity, and the driver does −½ h f·v against the cohesive
    force ``f`` [N], as it does against the step's other forces (kernels/loads.py ``drive_first_half``)."""
    if held:
        return v, carry, -0.5 * h * wp.dot(f, v)
    v, carry = carried_sum(v, carry, 0.5 * h * f * inv_mass)
    return wp.cw_mul(free, v), wp.cw_mul(free, carry), float(0.0)


@wp.kernel
def substep_kick_drift_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    node_inv_mass: wp.array(dtype=float),
    node_motion: wp.array(dtype=int),
    h: float,
    # In:
    nodes: wp.array(dtype=int),
    count: wp.array(dtype=int),
    first: int,
    drive: StepDrivers,
    # State out:
    node_u: wp.array(dtype=wp.vec3),
    node_q: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    node_qd_carry: wp.array(dtype=wp.vec3),
    node_f_fast: wp.array(dtype=wp.vec3),
    node_energy_boundary_work: wp.array(dtype=wp.float64),
    dx: wp.array(dtype=wp.vec3),
):
    """One sub-step's kicks and drift of a sub-stepped node: the second half kick of the last sub-step (not at the
    first), the first half of this one, x += h v (into the displacement, as the step's drift), the displacement of
    the step summed in ``dx`` [m], and the cohesive forces' accumulator cleared for their evaluation."""
    k = wp.tid()  # one thread per sub-step slot
    if k >= count[0]:
        return
    i = nodes[k]
    free = node_free_directions(node_motion[i])
    f = node_f_fast[i]
    inv_mass = node_inv_mass[i]
    held = held_by_driver(i, drive)
    v = node_qd[i]
    carry = node_qd_carry[i]
    work = float(0.0)
    if first == 0:
        v, carry, work = fast_half_kick(h, free, v, carry, f, inv_mass, held)
    v, carry, work_next = fast_half_kick(h, free, v, carry, f, inv_mass, held)
    book_driver_work(i, work + work_next, node_energy_boundary_work)
    node_qd[i] = v
    node_qd_carry[i] = carry
    u = node_u[i] + h * v
    node_u[i] = u
    node_q[i] = node_ref_q[i] + u
    if first != 0:
        dx[k] = h * v
    else:
        dx[k] = dx[k] + h * v
    node_f_fast[i] = wp.vec3(0.0)


@wp.kernel
def substep_finish_kernel(
    # Model:
    node_mass: wp.array(dtype=float),
    node_inv_mass: wp.array(dtype=float),
    node_motion: wp.array(dtype=int),
    node_damping: wp.array(dtype=float),
    node_contact_stiffness: wp.array(dtype=float),
    h: float,
    dt: float,
    half_fem_skin: float,
    # In:
    nodes: wp.array(dtype=int),
    count: wp.array(dtype=int),
    dx: wp.array(dtype=wp.vec3),
    node_q_at_fem_build: wp.array(dtype=wp.vec3),
    node_q: wp.array(dtype=wp.vec3),
    node_f_fast: wp.array(dtype=wp.vec3),
    sub: SubstepNodes,
    drive: StepDrivers,
    # State out:
    node_qd: wp.array(dtype=wp.vec3),
    node_qd_carry: wp.array(dtype=wp.vec3),
    node_f: wp.array(dtype=wp.vec3),
    node_energy_boundary_work: wp.array(dtype=wp.float64),
    node_energy_damping: wp.array(dtype=wp.float64),
    node_f_viscous: wp.array(dtype=wp.vec3),
    fem_rebuild_flag: wp.array(dtype=int),
):
    """The end of a sub-stepped node's sub-steps: the last sub-step's second half kick (v1-, kept in ``sub.v_end``
    for the next half kick of the other forces), node_qd set to the step's mean velocity dx/dt for the other forces'
    evaluation and books, the first half kick's share off that velocity booked (module docstring), and what the
    drift of a plain node ends with (kernels/integrate.py ``start_node_forces``, the FEM skin check)."""
    k = wp.tid()  # one thread per sub-step slot
    if k >= count[0]:
        return
    i = nodes[k]
    free = node_free_directions(node_motion[i])
    held = held_by_driver(i, drive)
    v, carry, work = fast_half_kick(h, free, node_qd[i], node_qd_carry[i], node_f_fast[i], node_inv_mass[i], held)
    book_driver_work(i, work, node_energy_boundary_work)
    sub.v_end[k] = v
    node_qd_carry[i] = carry
    v_mean = dx[k] / dt
    book_substep_kick(i, k, node_mass[i], sub.dv_start[k], sub.v_start[k], v_mean, sub)
    node_qd[i] = v_mean
    flag_past_half_fem_skin(i, node_q[i], half_fem_skin, node_contact_stiffness, node_q_at_fem_build, fem_rebuild_flag)
    start_node_forces(i, dt, v_mean, node_mass, node_damping, node_f, node_energy_damping, node_f_viscous)


@wp.kernel
def mark_substep_nodes_kernel(
    # State in:
    cohesive_count: wp.array(dtype=int),
    cohesive_a: wp.array(dtype=int),
    cohesive_b: wp.array(dtype=int),
    cohesive_broken: wp.array(dtype=int),
    # State out:
    node_substepped: wp.array(dtype=int),
):
    """Mark (1) the two nodes of every intact live cohesive element; the other nodes hold 0 (filled before). Every
    writer writes the same value."""
    e = wp.tid()  # one thread per cohesive element slot
    if e >= cohesive_count[0] or cohesive_broken[e] != 0:
        return
    node_substepped[cohesive_a[e]] = 1
    node_substepped[cohesive_b[e]] = 1


@wp.kernel
def number_substep_nodes_kernel(
    # State in:
    node_count: wp.array(dtype=int),
    node_substepped: wp.array(dtype=int),
    # Out:
    node_slot: wp.array(dtype=int),
    count: wp.array(dtype=int),
    nodes: wp.array(dtype=int),
):
    """Give each marked node a sub-step slot, -1 to the others (``count`` must start at 0). The slots' order differs
    between runs on a GPU; nothing depends on it: each slot's arithmetic is its node's alone. The marks are the nodes
    of at most the element slots (two each), which ``nodes`` holds; a node past them (none is) would take the plain
    step rather than be written out of bounds."""
    i = wp.tid()  # one thread per node slot
    node_slot[i] = -1
    if i >= node_count[0] or node_substepped[i] == 0:
        return
    k = wp.atomic_add(count, 0, 1)
    if k < nodes.shape[0]:
        node_slot[i] = k
        nodes[k] = i
