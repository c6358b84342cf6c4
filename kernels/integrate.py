"""Time integration of spheres and FEM nodes: velocity Verlet in two half kicks around the force evaluation.

Step n → n+1 (LIGGGHTS ``fix nve/sphere``): first half kick and drift, v ← v + dt/2 a_n, x ← x + dt v, which also
clears the force accumulators for the new evaluation; then, after the forces at x_{n+1}, the second half kick
v ← v + dt/2 a_{n+1}. Sphere centres are float64 (the drift adds the float32 dt·v without loss at any offset);
velocities and forces are float32, and each kick adds its increment to the velocity with a carry of what the float32
sums rounded off (:func:`carried_sum`), so a small increment repeated over many steps is not lost to rounding.
Rotation of spheres is isotropic (I = 2/5 m r²), so ω is kicked the same way, without a carry (no constant increment
drives a spin). FEM nodes (lumped mass, translation only) take the same two half kicks in their own kernels (with
the carry); they drift their displacement,
u ← u + dt v, and x = X + u follows. Their held components (fixed, rollers) stay zero, and a node with a velocity
driver (warpdem.stages.loads) holds its velocity while the driver does, the driver's work booked. The state's time
advances last, after the second half kick.

Between two steps of one run nothing happens but the clock: the second half kick of step n and the first of step n+1
use the same forces, so the ``kick_drift_*`` kernels do both in one pass over the arrays (the body of a run of steps,
warpdem.simulation), with the arithmetic of the two separate halves in the same order, bit for bit. Each half is a
function below; the first-half and kick-drift kernels come from one factory each.
"""

from __future__ import annotations

import warp as wp

from .contact import MOTION_FREE
from .loads import NodeDriver, drive_first_half, drive_second_half, driver_holds
from .neighbors import flag_past_half_fem_skin
from .rigid import NODE_RIGID, PoseAhead, node_velocity_ahead
from .tets import node_free_directions

wp.set_module_options({"enable_backward": False})


# ----------------------------------------------------------------------------------------------------------------
# One half of a step for one sphere or node.


@wp.func
def carried_sum(v: wp.vec3, carry: wp.vec3, dv: wp.vec3):
    """v + dv in float32 by compensated (Kahan) summation [m/s]: ``carry`` holds what the earlier sums rounded off
    and joins dv; returns (the rounded sum, the new carry). The velocity the kicks have
    summed is the returned one plus its carry, to float32 rounding of the carry, whose size stays within half a unit
    in the last place of v, so no rounding piles up: a constant increment (gravity's dt g/2 a half kick) that rounds
    the same way at every kick drifted a free fall's velocity by 1.2e-3 of g t over 0.1 s at dt = 1 µs, more the
    finer the step (warpdem.model.State ``particle_qd_carry``). Plain float32 arithmetic, which the compilers keep
    as written (Warp compiles without fast-math reassociation)."""
    y = dv + carry
    t = v + y
    return t, y - (t - v)


@wp.func
def kick_particle(
    i: int,
    dt: float,
    gravity: wp.vec3,
    particle_inv_mass: wp.array(dtype=float),
    particle_inv_inertia: wp.array(dtype=float),
    particle_f: wp.array(dtype=wp.vec3),
    particle_t: wp.array(dtype=wp.vec3),
    v: wp.vec3,
    carry: wp.vec3,
    omega: wp.vec3,
):
    """Half kick of a free sphere: v + dt/2 (f/m + g) [m/s] (:func:`carried_sum`, returning the new carry) and
    ω + dt/2 t/I [rad/s]."""
    v, carry = carried_sum(v, carry, 0.5 * dt * (particle_f[i] * particle_inv_mass[i] + gravity))
    return v, carry, omega + 0.5 * dt * particle_inv_inertia[i] * particle_t[i]


@wp.func
def drift_particle(
    i: int,
    dt: float,
    half_skin: float,
    v: wp.vec3,
    particle_q_at_build: wp.array(dtype=wp.vec3d),
    particle_q: wp.array(dtype=wp.vec3d),
    particle_f: wp.array(dtype=wp.vec3),
    particle_t: wp.array(dtype=wp.vec3),
    rebuild_flag: wp.array(dtype=int),
):
    """Drift by dt with v, clear the force and torque accumulators, flag a rebuild when the sphere moved half the
    skin since the neighbour list was built (the Verlet-skin criterion).

    The centre is float64: the increment dt·v (float32, the same at any offset) is added without loss wherever the
    sphere is (a float32 coordinate of 10 m has a spacing of 1 µm, and dt·v of a microsecond step is often less).
    """
    x = particle_q[i] + wp.vec3d(dt * v)
    particle_q[i] = x
    particle_f[i] = wp.vec3(0.0)
    particle_t[i] = wp.vec3(0.0)
    moved = wp.vec3(x - particle_q_at_build[i])
    if wp.dot(moved, moved) > half_skin * half_skin:
        rebuild_flag[0] = 1


@wp.func
def book_contact_work_ahead(
    i: int,
    dt: float,
    v: wp.vec3,
    omega: wp.vec3,
    contact_sums: wp.array(dtype=wp.mat33),
    energy_damping: wp.array(dtype=wp.float64),
    energy_friction: wp.array(dtype=wp.float64),
):
    """Book minus the half of the sphere contacts' work that lies ahead of their evaluation, -½ dt f_n·v_{n+1/2}
    (normal → damping, tangential and rolling with ½ dt t_n·ω_{n+1/2} → friction) [J], now that v_{n+1/2} is known,
    and clear the sums for the next evaluation (the other half: kernels/contact.py ``make_contact_kernels``)."""
    sums = contact_sums[i]
    # Most spheres of a loose packing touched nothing: their sums are zero already and are left unwritten (the
    # stores, not the arithmetic, are what the books cost a sphere here).
    if sums == wp.mat33(0.0):
        return
    fn = sums[0]
    ft = sums[1]
    tt = sums[2]
    w_n = 0.5 * dt * wp.dot(fn, v)
    w_t = 0.5 * dt * (wp.dot(ft, v) + wp.dot(tt, omega))
    if w_n != 0.0:
        energy_damping[i] = energy_damping[i] - wp.float64(w_n)
    if w_t != 0.0:
        energy_friction[i] = energy_friction[i] - wp.float64(w_t)
    contact_sums[i] = wp.mat33(0.0)


@wp.func
def held_particle_work(
    i: int,
    dt: float,
    particle_f: wp.array(dtype=wp.vec3),
    particle_t: wp.array(dtype=wp.vec3),
    v: wp.vec3,
    omega: wp.vec3,
) -> wp.float64:
    """Work [J] of whatever holds a fixed or prescribed sphere on its path against the contact forces over a half
    step, -(f·v + t·ω) dt (zero for a fixed sphere)."""
    return wp.float64(-(wp.dot(particle_f[i], v) + wp.dot(particle_t[i], omega)) * dt)


@wp.func
def node_kick(
    i: int,
    dt: float,
    gravity: wp.vec3,
    free: wp.vec3,
    v: wp.vec3,
    carry: wp.vec3,
    node_inv_mass: wp.array(dtype=float),
    node_f: wp.array(dtype=wp.vec3),
):
    """Half kick of a node without its driver: v + dt/2 (f/m + g) [m/s] by :func:`carried_sum`, in its free
    components (the held ones and their carry zero); returns (v, carry)."""
    v, carry = carried_sum(v, carry, 0.5 * dt * (node_f[i] * node_inv_mass[i] + gravity))
    return wp.cw_mul(free, v), wp.cw_mul(free, carry)


@wp.func
def node_first_half_velocity(
    i: int,
    dt: float,
    gravity: wp.vec3,
    t_step: wp.float64,
    free: wp.vec3,
    v_old: wp.vec3,
    carry: wp.vec3,
    node_mass: wp.array(dtype=float),
    node_inv_mass: wp.array(dtype=float),
    node_driver: wp.array(dtype=int),
    drivers: wp.array(dtype=NodeDriver),
    num_drivers: int,
    node_f: wp.array(dtype=wp.vec3),
):
    """v_{n+1/2} of a node from v_n = ``v_old`` [m/s], with its kicks' carry (:func:`carried_sum`), the new carry and
    the driver's work [J] over the half step starting at t_step.

    Held velocity components stay zero (fixed nodes, rollers), so the constraints do no work. A driven node holds the
    driver's velocity over steps whose midpoint it covers (kernels/loads.py), its carry zero meanwhile; the driver
    works against gravity only where the node's weight counts in the potential (inv_mass > 0).
    """
    v, carry = node_kick(i, dt, gravity, free, v_old, carry, node_inv_mass, node_f)
    work = float(0.0)
    if num_drivers > 0:
        d = node_driver[i]
        if d >= 0:
            weight = node_mass[i] * gravity * wp.where(node_inv_mass[i] > 0.0, 1.0, 0.0)
            t_mid = t_step + wp.float64(0.5 * dt)
            v, work = drive_first_half(drivers[d], t_mid, dt, free, v_old, v, node_f[i] + weight, node_mass[i])
            if driver_holds(drivers[d], t_mid):
                carry = wp.vec3(0.0)
    return v, carry, work


@wp.func
def node_second_half_velocity(
    i: int,
    dt: float,
    gravity: wp.vec3,
    t_step: wp.float64,
    free: wp.vec3,
    v_half: wp.vec3,
    carry: wp.vec3,
    node_mass: wp.array(dtype=float),
    node_inv_mass: wp.array(dtype=float),
    node_driver: wp.array(dtype=int),
    drivers: wp.array(dtype=NodeDriver),
    num_drivers: int,
    node_f: wp.array(dtype=wp.vec3),
):
    """v_{n+1} of a node from v_{n+1/2} [m/s] with its kicks' carry, the new carry and the driver's work [J] (the step
    started at t_step: the driver is judged at the same midpoint as in the first half, so both halves agree bit for
    bit)."""
    v, carry = node_kick(i, dt, gravity, free, v_half, carry, node_inv_mass, node_f)
    work = float(0.0)
    if num_drivers > 0:
        d = node_driver[i]
        if d >= 0:
            weight = node_mass[i] * gravity * wp.where(node_inv_mass[i] > 0.0, 1.0, 0.0)
            t_mid = t_step + wp.float64(0.5 * dt)
            v, work = drive_second_half(drivers[d], t_mid, dt, v, node_f[i] + weight)
            if driver_holds(drivers[d], t_mid):
                carry = wp.vec3(0.0)
    return v, carry, work


@wp.func
def book_driver_work(i: int, work: float, node_energy_boundary_work: wp.array(dtype=wp.float64)):
    """Add a velocity driver's work [J] to node i's load-work line (``node_energy_boundary_work``); an exact zero
    (no driver) is not stored."""
    if work != 0.0:
        node_energy_boundary_work[i] = node_energy_boundary_work[i] + wp.float64(work)


@wp.func
def start_node_forces(
    i: int,
    dt: float,
    v: wp.vec3,
    node_mass: wp.array(dtype=float),
    node_damping: wp.array(dtype=float),
    node_f: wp.array(dtype=wp.vec3),
    node_energy_damping: wp.array(dtype=wp.float64),
    node_f_viscous: wp.array(dtype=wp.vec3),
):
    """What a node's drift ends with (:func:`drift_node`): the half ahead of the last evaluation's viscous forces
    booked against the step's velocity ``v`` [m/s], the accumulator started at the damping force −α m v and the half
    behind of that force booked (also after a sub-stepped node's sub-steps, warpdem.stages.substep, with v the
    step's mean velocity)."""
    alpha = node_damping[i]
    f_viscous = node_f_viscous[i]
    dissipated = -0.5 * dt * wp.dot(f_viscous, v)
    f0 = wp.vec3(0.0)
    if alpha > 0.0:
        f0 = -alpha * node_mass[i] * v
        dissipated = dissipated + 0.5 * alpha * node_mass[i] * wp.dot(v, v) * dt
    if dissipated != 0.0:
        node_energy_damping[i] = node_energy_damping[i] + wp.float64(dissipated)
    if alpha > 0.0 or wp.length_sq(f_viscous) > 0.0:  # a node no compressed tet touched keeps its zero unwritten
        node_f_viscous[i] = f0
    node_f[i] = f0


@wp.func
def drift_node(
    i: int,
    dt: float,
    half_fem_skin: float,
    v: wp.vec3,
    node_ref_q: wp.array(dtype=wp.vec3),
    node_mass: wp.array(dtype=float),
    node_damping: wp.array(dtype=float),
    node_contact_stiffness: wp.array(dtype=float),
    node_q_at_fem_build: wp.array(dtype=wp.vec3),
    node_u: wp.array(dtype=wp.vec3),
    node_q: wp.array(dtype=wp.vec3),
    node_f: wp.array(dtype=wp.vec3),
    node_energy_damping: wp.array(dtype=wp.float64),
    node_f_viscous: wp.array(dtype=wp.vec3),
    fem_rebuild_flag: wp.array(dtype=int),
):
    """Drift a node by dt with v_{n+1/2}, start its force accumulator, and flag an FEM contact-list rebuild when a
    contact node (one on the surface) has moved half the FEM skin since the lists were built (the Verlet-skin
    criterion, as spheres do; ``half_fem_skin`` < 0: the model has no FEM contact).

    The drift goes into the displacement, small next to the coordinates, so float32 keeps the increment. The force
    accumulator starts from the mass-proportional damping force -α m v at the half-step velocity (the
    central-difference choice), which then acts in both half kicks around the new forces.

    The viscous books follow Verlet's trapezoid ½ dt f_n·(v_{n-1/2} + v_{n+1/2}) of each dissipative force f_n: first
    the half ahead of the last evaluation's bulk-viscosity and damping forces (``node_f_viscous``), -½ dt f_n·v_{n+1/2}
    with v = v_{n+1/2} just kicked; then the half behind of the new damping force, ½ dt α m |v|², which starts the
    sums again (the tets add their viscous forces and book their half behind, kernels/tets.py).
    """
    u = node_u[i] + dt * v
    node_u[i] = u
    x = node_ref_q[i] + u
    node_q[i] = x
    flag_past_half_fem_skin(i, x, half_fem_skin, node_contact_stiffness, node_q_at_fem_build, fem_rebuild_flag)
    start_node_forces(i, dt, v, node_mass, node_damping, node_f, node_energy_damping, node_f_viscous)


@wp.kernel
def book_half_ahead_kernel(
    # Model:
    dt: float,
    # State in:
    node_count: wp.array(dtype=int),
    ahead: PoseAhead,
    # In:
    sign: float,
    rigid_only: int,
    # State out:
    node_f_kind: wp.array(dtype=wp.vec3),
    node_energy_kind: wp.array(dtype=wp.float64),
):
    """Book ``sign`` × the half of the last evaluation's work of one kind of force that lies ahead of it,
    ½ dt f_n·v_{n+1/2} [J], now that v_{n+1/2} is known (after the drift, before the new evaluation), and clear the
    kind's sums for the new evaluation. v_{n+1/2} is ``node_qd`` for a node of its own; for a node of a rigid body
    it is its velocity at the pose the force was made at (kernels/rigid.py ``node_velocity_ahead``; ``node_body`` is
    empty before a switch: no node follows a body). The kinds: the FEM contacts and joint dashpots (``node_f_contact``
    into ``node_energy_contact``, sign −1: what they take out; the half behind: kernels/fem_contact.py,
    kernels/joints.py), the sphere–face contacts' forces on the face nodes (``node_f_sphere_face`` into
    ``node_energy_sphere_face``, −1; the rest: kernels/sphere_face.py), the non-reflecting dashpots
    (``node_f_absorbed`` into ``node_energy_absorbed``, −1) and the
    pressure loads (``node_f_load`` into ``node_energy_boundary_work``, +1: work put in; kernels/loads.py), and with
    ``rigid_only`` the viscous forces of deformable tets on rigid blocks' nodes (``node_f_viscous`` into
    ``node_energy_damping``, −1; the other nodes' are booked in the drift, :func:`drift_node`)."""
    i = wp.tid()  # one thread per node slot
    if i >= node_count[0]:
        return
    if rigid_only != 0:
        if ahead.node_body.shape[0] == 0:
            return
        if ahead.node_body[i] < 0:
            return
    f = node_f_kind[i]
    if wp.length_sq(f) > 0.0:  # a node no such force touched keeps its zero unwritten
        v = node_velocity_ahead(i, ahead)
        node_energy_kind[i] = node_energy_kind[i] + wp.float64(sign * 0.5 * dt * wp.dot(f, v))
        node_f_kind[i] = wp.vec3(0.0)


# ----------------------------------------------------------------------------------------------------------------
# Kernels: the first and the second half of a step, and the two fused across a step boundary.


def make_particle_drift_kernel(after_second_half: bool) -> wp.Kernel:
    """The sphere kernel that ends a half step in a drift: the first half (kick, drift, clear, flag), or with
    ``after_second_half`` the second half of step n before it (kick-drift: the same forces f_{n+1} twice, the work of
    driven spheres booked), the choice made at code generation."""

    @wp.kernel(enable_backward=False, module="unique")
    def drift_particles_kernel(
        # Model:
        particle_inv_mass: wp.array(dtype=float),
        particle_inv_inertia: wp.array(dtype=float),
        particle_motion: wp.array(dtype=int),
        gravity: wp.vec3,
        dt: float,
        half_skin: float,
        # State in:
        particle_count: wp.array(dtype=int),
        particle_q_at_build: wp.array(dtype=wp.vec3d),
        # In:
        track_energy: int,
        # State out:
        particle_q: wp.array(dtype=wp.vec3d),
        particle_qd: wp.array(dtype=wp.vec3),
        particle_qd_carry: wp.array(dtype=wp.vec3),
        particle_omega: wp.array(dtype=wp.vec3),
        particle_f: wp.array(dtype=wp.vec3),
        particle_t: wp.array(dtype=wp.vec3),
        rebuild_flag: wp.array(dtype=int),
        energy_boundary_work: wp.array(dtype=wp.float64),
        contact_sums: wp.array(dtype=wp.mat33),
        energy_damping: wp.array(dtype=wp.float64),
        energy_friction: wp.array(dtype=wp.float64),
    ):
        i = wp.tid()  # one thread per particle slot
        if i >= particle_count[0]:
            return
        v = particle_qd[i]
        omega = particle_omega[i]
        if particle_motion[i] == MOTION_FREE:
            carry = particle_qd_carry[i]
            if wp.static(after_second_half):
                v, carry, omega = kick_particle(
                    i, dt, gravity, particle_inv_mass, particle_inv_inertia, particle_f, particle_t, v, carry, omega
                )
            v, carry, omega = kick_particle(
                i, dt, gravity, particle_inv_mass, particle_inv_inertia, particle_f, particle_t, v, carry, omega
            )
            particle_qd[i] = v
            particle_qd_carry[i] = carry
            particle_omega[i] = omega
        else:
            # A driven sphere is held on its path by whatever drives it: ½ dt of the work of f_{n+1} in each half
            # kick around it, as velocity Verlet does the work of every force.
            held_dt = 0.5 * dt
            if wp.static(after_second_half):
                held_dt = dt
            w = held_particle_work(i, held_dt, particle_f, particle_t, v, omega)
            energy_boundary_work[i] = energy_boundary_work[i] + w
        # Fixed spheres have v = 0; prescribed ones keep their velocity and spin.
        if track_energy != 0:  # else the sums stay zero: the contacts do not fill them
            book_contact_work_ahead(
                i,
                dt,
                v,
                omega,
                contact_sums,
                energy_damping,
                energy_friction,
            )
        drift_particle(i, dt, half_skin, v, particle_q_at_build, particle_q, particle_f, particle_t, rebuild_flag)

    return drift_particles_kernel


integrate_first_half_kernel = make_particle_drift_kernel(after_second_half=False)
kick_drift_particles_kernel = make_particle_drift_kernel(after_second_half=True)


@wp.kernel
def integrate_second_half_kernel(
    # Model:
    particle_inv_mass: wp.array(dtype=float),
    particle_inv_inertia: wp.array(dtype=float),
    particle_motion: wp.array(dtype=int),
    gravity: wp.vec3,
    dt: float,
    # State in:
    particle_count: wp.array(dtype=int),
    particle_f: wp.array(dtype=wp.vec3),
    particle_t: wp.array(dtype=wp.vec3),
    # State out:
    particle_qd: wp.array(dtype=wp.vec3),
    particle_qd_carry: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    energy_boundary_work: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per particle slot
    if i >= particle_count[0]:
        return
    if particle_motion[i] == MOTION_FREE:
        v, carry, omega = kick_particle(
            i,
            dt,
            gravity,
            particle_inv_mass,
            particle_inv_inertia,
            particle_f,
            particle_t,
            particle_qd[i],
            particle_qd_carry[i],
            particle_omega[i],
        )
        particle_qd[i] = v
        particle_qd_carry[i] = carry
        particle_omega[i] = omega
    else:
        # A driven sphere is held on its path by whatever drives it (the second half of the step's work).
        w = held_particle_work(i, 0.5 * dt, particle_f, particle_t, particle_qd[i], particle_omega[i])
        energy_boundary_work[i] = energy_boundary_work[i] + w


@wp.struct
class SubstepNodes:
    """The nodes whose cohesive forces are sub-stepped (warpdem.stages.substep; r-RESPA) as the step's node kernels
    see them: ``node_slot`` per node slot its sub-step slot or -1 (empty: no sub-steps); per sub-step slot the
    velocity after the step's first half kick (``v_start``), that kick's increment (``dv_start``) and the velocity
    the sub-steps ended with (``v_end``), all [m/s]; ``node_energy_substep`` the State's line [J]."""

    node_slot: wp.array(dtype=int)
    v_start: wp.array(dtype=wp.vec3)
    dv_start: wp.array(dtype=wp.vec3)
    v_end: wp.array(dtype=wp.vec3)
    node_energy_substep: wp.array(dtype=wp.float64)


@wp.func
def substep_slot(i: int, sub: SubstepNodes) -> int:
    """Node i's sub-step slot, -1 when its forces are not sub-stepped."""
    if sub.node_slot.shape[0] == 0:
        return -1
    return sub.node_slot[i]


@wp.func
def velocity_before_kick(i: int, slot: int, v: wp.vec3, sub: SubstepNodes) -> wp.vec3:
    """The velocity the second half kick starts from [m/s]: ``node_qd`` (``v``), or for a sub-stepped node the
    velocity its sub-steps ended with (``node_qd`` holds the step's mean velocity for the forces' evaluation)."""
    if slot >= 0:
        return sub.v_end[slot]
    return v


@wp.func
def book_substep_kick(
    i: int, slot: int, mass: float, dv: wp.vec3, v_kicked: wp.vec3, v_mean: wp.vec3, sub: SubstepNodes
):
    """Book m dv·(v_kicked − v_mean) [J] for a sub-stepped node (``slot`` ≥ 0): what a half kick ``dv`` of the
    forces other than the cohesive ones adds to the kinetic energy beyond the ½ dt f·v_mean their lines book,
    ``v_kicked`` the velocity the kick took the node from (second half) or to (first half), ``v_mean`` the step's
    mean velocity (warpdem.stages.substep)."""
    if slot >= 0:
        w = wp.float64(mass) * wp.float64(wp.dot(dv, v_kicked - v_mean))
        if w != wp.float64(0.0):
            sub.node_energy_substep[i] = sub.node_energy_substep[i] + w


def make_node_drift_kernel(after_second_half: bool) -> wp.Kernel:
    """The FEM node kernel that ends a half step in a drift: the first half, or with ``after_second_half`` the second
    half of step n before it (kick-drift), the choice made at code generation. The second half judges drivers at
    t_n + dt/2 (``time`` holds t_n), the first at t + dt/2 with t = t_n + dt (the clock's own sum, as it will read
    after this kernel) in a kick-drift and t = t_n otherwise."""

    @wp.kernel(enable_backward=False, module="unique")
    def drift_nodes_kernel(
        # Model:
        node_ref_q: wp.array(dtype=wp.vec3),
        node_mass: wp.array(dtype=float),
        node_inv_mass: wp.array(dtype=float),
        node_motion: wp.array(dtype=int),
        node_damping: wp.array(dtype=float),
        node_driver: wp.array(dtype=int),
        drivers: wp.array(dtype=NodeDriver),
        num_drivers: int,
        node_contact_stiffness: wp.array(dtype=float),
        gravity: wp.vec3,
        dt: float,
        half_fem_skin: float,
        dt64: wp.float64,
        # State in:
        node_count: wp.array(dtype=int),
        time: wp.array(dtype=wp.float64),
        node_q_at_fem_build: wp.array(dtype=wp.vec3),
        sub: SubstepNodes,
        # State out:
        node_u: wp.array(dtype=wp.vec3),
        node_q: wp.array(dtype=wp.vec3),
        node_qd: wp.array(dtype=wp.vec3),
        node_qd_carry: wp.array(dtype=wp.vec3),
        node_f: wp.array(dtype=wp.vec3),
        node_energy_damping: wp.array(dtype=wp.float64),
        node_f_viscous: wp.array(dtype=wp.vec3),
        node_energy_boundary_work: wp.array(dtype=wp.float64),
        fem_rebuild_flag: wp.array(dtype=int),
    ):
        i = wp.tid()  # one thread per FEM node slot
        if i >= node_count[0]:
            return
        motion = node_motion[i]
        if motion == NODE_RIGID:
            if num_drivers == 0 or node_driver[i] < 0:
                # A rigid block's node: its body's pose sets its displacement, position and velocity right after
                # this kernel (kernels/rigid.py), and checks its skin; what is left of the drift below for a node
                # with no free direction is its force accumulator started at zero (v = 0: no damping force). The
                # viscous forces of deformable tets next to it are booked and cleared after the body's drift, at the
                # pose they were made at (warpdem.stages.rigid.drift_bodies).
                node_f[i] = wp.vec3(0.0)
                return
        free = node_free_directions(motion)
        slot = substep_slot(i, sub)
        v = node_qd[i]
        carry = node_qd_carry[i]
        t_step = time[0]
        work = float(0.0)
        if wp.static(after_second_half):
            v_mean = v
            v = velocity_before_kick(i, slot, v, sub)
            v_before = v
            v, carry, work = node_second_half_velocity(
                i,
                dt,
                gravity,
                t_step,
                free,
                v,
                carry,
                node_mass,
                node_inv_mass,
                node_driver,
                drivers,
                num_drivers,
                node_f,
            )
            book_substep_kick(i, slot, node_mass[i], v - v_before, v_before, v_mean, sub)
            t_step = t_step + dt64
        v_n = v
        v, carry, work_next = node_first_half_velocity(
            i, dt, gravity, t_step, free, v, carry, node_mass, node_inv_mass, node_driver, drivers, num_drivers, node_f
        )
        if work != 0.0 or work_next != 0.0:
            node_energy_boundary_work[i] = node_energy_boundary_work[i] + wp.float64(work) + wp.float64(work_next)
        node_qd[i] = v
        node_qd_carry[i] = carry
        if slot >= 0:
            # The sub-steps drift the node under its cohesive forces, and their last kernel starts its accumulator
            # (kernels/substep.py); its share of this kick is booked there, against the step's mean velocity.
            sub.v_start[slot] = v
            sub.dv_start[slot] = v - v_n
            return
        drift_node(
            i,
            dt,
            half_fem_skin,
            v,
            node_ref_q,
            node_mass,
            node_damping,
            node_contact_stiffness,
            node_q_at_fem_build,
            node_u,
            node_q,
            node_f,
            node_energy_damping,
            node_f_viscous,
            fem_rebuild_flag,
        )

    return drift_nodes_kernel


integrate_nodes_first_half_kernel = make_node_drift_kernel(after_second_half=False)
kick_drift_nodes_kernel = make_node_drift_kernel(after_second_half=True)


@wp.kernel
def integrate_nodes_second_half_kernel(
    # Model:
    node_mass: wp.array(dtype=float),
    node_inv_mass: wp.array(dtype=float),
    node_motion: wp.array(dtype=int),
    node_driver: wp.array(dtype=int),
    drivers: wp.array(dtype=NodeDriver),
    num_drivers: int,
    gravity: wp.vec3,
    dt: float,
    # State in:
    node_count: wp.array(dtype=int),
    time: wp.array(dtype=wp.float64),
    node_f: wp.array(dtype=wp.vec3),
    sub: SubstepNodes,
    # State out:
    node_qd: wp.array(dtype=wp.vec3),
    node_qd_carry: wp.array(dtype=wp.vec3),
    node_energy_boundary_work: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per FEM node slot
    if i >= node_count[0]:
        return
    free = node_free_directions(node_motion[i])
    slot = substep_slot(i, sub)
    v_mean = node_qd[i]
    v_before = velocity_before_kick(i, slot, v_mean, sub)
    v, carry, work = node_second_half_velocity(
        i,
        dt,
        gravity,
        time[0],
        free,
        v_before,
        node_qd_carry[i],
        node_mass,
        node_inv_mass,
        node_driver,
        drivers,
        num_drivers,
        node_f,
    )
    book_driver_work(i, work, node_energy_boundary_work)
    book_substep_kick(i, slot, node_mass[i], v - v_before, v_before, v_mean, sub)
    node_qd[i] = v
    node_qd_carry[i] = carry


@wp.kernel
def advance_time_kernel(
    # Model:
    dt: wp.float64,
    # State out:
    time: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread
    time[i] = time[i] + dt


@wp.kernel
def advance_walls_kernel(
    # Model:
    wall_velocity: wp.array(dtype=wp.vec3),
    dt: float,
    # State out:
    wall_point: wp.array(dtype=wp.vec3d),
):
    w = wp.tid()  # one thread per wall; its point is float64, as sphere centres are
    wall_point[w] = wall_point[w] + wp.vec3d(dt * wall_velocity[w])
