"""Time integration of spheres: velocity Verlet in two half kicks around the force evaluation.

Step n → n+1 (LIGGGHTS ``fix nve/sphere``): first half kick and drift, v ← v + dt/2 a_n, x ← x + dt v, which also
clears the force accumulators for the new evaluation; then, after the forces at x_{n+1}, the second half kick
v ← v + dt/2 a_{n+1}. Rotation of spheres is isotropic (I = 2/5 m r²), so ω is kicked the same way.
"""

from __future__ import annotations

import warp as wp

from .contact import MOTION_FREE

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
def advance_walls_kernel(
    # Model:
    wall_velocity: wp.array(dtype=wp.vec3),
    dt: float,
    # State out:
    wall_point: wp.array(dtype=wp.vec3),
):
    w = wp.tid()  # one thread per wall
    wall_point[w] = wall_point[w] + dt * wall_velocity[w]
