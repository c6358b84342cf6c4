"""Time integration of spheres and FEM nodes: velocity Verlet in two half kicks around the force evaluation.

Step n → n+1 (LIGGGHTS ``fix nve/sphere``): first half kick and drift, v ← v + dt/2 a_n, x ← x + dt v, which also
clears the force accumulators for the new evaluation; then, after the forces at x_{n+1}, the second half kick
v ← v + dt/2 a_{n+1}. Rotation of spheres is isotropic (I = 2/5 m r²), so ω is kicked the same way. FEM nodes
(lumped mass, translation only) take the same two half kicks in their own kernels; they drift their displacement,
u ← u + dt v, and x = X + u follows. Their held components (fixed, rollers) stay zero, and a node with a velocity
driver (warpdem.loads) holds its velocity while the driver does, the driver's work booked. The state's time advances
last, after the second half kick.
"""

from __future__ import annotations

import warp as wp

from .contact import MOTION_FREE
from .loads import NodeDriver, drive_first_half, drive_second_half
from .tets import node_free_directions

wp.set_module_options({"enable_backward": False})


@wp.kernel
def integrate_first_half_kernel(
    # Model:
    particle_inv_mass: wp.array(dtype=float),
    particle_inv_inertia: wp.array(dtype=float),
    particle_motion: wp.array(dtype=int),
    gravity: wp.vec3,
    dt: float,
    half_skin: float,
    # State in:
    particle_count: wp.array(dtype=int),
    particle_q_at_build: wp.array(dtype=wp.vec3),
    # State out:
    particle_q: wp.array(dtype=wp.vec3),
    particle_qd: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    particle_f: wp.array(dtype=wp.vec3),
    particle_t: wp.array(dtype=wp.vec3),
    rebuild_flag: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per particle slot
    if i >= particle_count[0]:
        return
    v = particle_qd[i]
    if particle_motion[i] == MOTION_FREE:
        v = v + 0.5 * dt * (particle_f[i] * particle_inv_mass[i] + gravity)
        particle_qd[i] = v
        particle_omega[i] = particle_omega[i] + 0.5 * dt * particle_inv_inertia[i] * particle_t[i]
    # Fixed spheres have v = 0; prescribed ones keep their velocity and spin.
    x = particle_q[i] + dt * v
    particle_q[i] = x
    particle_f[i] = wp.vec3(0.0)
    particle_t[i] = wp.vec3(0.0)
    # Verlet skin: the neighbour list stays valid while no sphere has moved half the skin since it was built.
    moved = x - particle_q_at_build[i]
    if wp.dot(moved, moved) > half_skin * half_skin:
        rebuild_flag[0] = 1


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
    particle_omega: wp.array(dtype=wp.vec3),
    energy_boundary_work: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per particle slot
    if i >= particle_count[0]:
        return
    if particle_motion[i] == MOTION_FREE:
        particle_qd[i] = particle_qd[i] + 0.5 * dt * (particle_f[i] * particle_inv_mass[i] + gravity)
        particle_omega[i] = particle_omega[i] + 0.5 * dt * particle_inv_inertia[i] * particle_t[i]
    else:
        # A driven sphere is held on its path by whatever drives it, which does the work -F.v against the
        # contact forces (zero for a fixed sphere).
        w = -(wp.dot(particle_f[i], particle_qd[i]) + wp.dot(particle_t[i], particle_omega[i])) * dt
        energy_boundary_work[i] = energy_boundary_work[i] + wp.float64(w)


@wp.kernel
def integrate_nodes_first_half_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    node_mass: wp.array(dtype=float),
    node_inv_mass: wp.array(dtype=float),
    node_motion: wp.array(dtype=int),
    node_damping: wp.array(dtype=float),
    node_driver: wp.array(dtype=int),
    drivers: wp.array(dtype=NodeDriver),
    num_drivers: int,
    gravity: wp.vec3,
    dt: float,
    # State in:
    node_count: wp.array(dtype=int),
    time: wp.array(dtype=wp.float64),
    # State out:
    node_u: wp.array(dtype=wp.vec3),
    node_q: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    node_f: wp.array(dtype=wp.vec3),
    node_energy_damping: wp.array(dtype=wp.float64),
    node_energy_boundary_work: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per FEM node slot
    if i >= node_count[0]:
        return
    # Held velocity components stay zero (fixed nodes, rollers), so the constraints do no work.
    free = node_free_directions(node_motion[i])
    v_old = node_qd[i]
    v = wp.cw_mul(free, v_old + 0.5 * dt * (node_f[i] * node_inv_mass[i] + gravity))
    if num_drivers > 0:
        d = node_driver[i]
        if d >= 0:
            # A driven node holds the driver's velocity over steps whose midpoint it covers (kernels/loads.py); the
            # driver works against gravity only where the node's weight counts in the potential (inv_mass > 0).
            weight = node_mass[i] * gravity * wp.where(node_inv_mass[i] > 0.0, 1.0, 0.0)
            t_mid = time[0] + wp.float64(0.5 * dt)
            v, work = drive_first_half(drivers[d], t_mid, dt, free, v_old, v, node_f[i] + weight, node_mass[i])
            node_energy_boundary_work[i] = node_energy_boundary_work[i] + wp.float64(work)
    node_qd[i] = v
    # The drift goes into the displacement, small next to the coordinates, so float32 keeps the increment.
    u = node_u[i] + dt * v
    node_u[i] = u
    node_q[i] = node_ref_q[i] + u
    # The force accumulator starts from the mass-proportional damping force -α m v at the half-step velocity (the
    # central-difference choice), which then acts in both half kicks around the new forces.
    alpha = node_damping[i]
    node_f[i] = -alpha * node_mass[i] * v
    if alpha > 0.0:
        node_energy_damping[i] = node_energy_damping[i] + wp.float64(alpha * node_mass[i] * wp.dot(v, v) * dt)


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
    # State out:
    node_qd: wp.array(dtype=wp.vec3),
    node_energy_boundary_work: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per FEM node slot
    if i >= node_count[0]:
        return
    free = node_free_directions(node_motion[i])
    v = wp.cw_mul(free, node_qd[i] + 0.5 * dt * (node_f[i] * node_inv_mass[i] + gravity))
    if num_drivers > 0:
        d = node_driver[i]
        if d >= 0:
            weight = node_mass[i] * gravity * wp.where(node_inv_mass[i] > 0.0, 1.0, 0.0)
            # The same midpoint as the first half (time still holds t_n), so both halves agree bit for bit.
            t_mid = time[0] + wp.float64(0.5 * dt)
            v, work = drive_second_half(drivers[d], t_mid, dt, v, node_f[i] + weight)
            node_energy_boundary_work[i] = node_energy_boundary_work[i] + wp.float64(work)
    node_qd[i] = v


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
    wall_point: wp.array(dtype=wp.vec3),
):
    w = wp.tid()  # one thread per wall
    wall_point[w] = wall_point[w] + dt * wall_velocity[w]
