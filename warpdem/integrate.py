"""Integration stage (host side): the two half kicks of velocity Verlet around the force evaluation, for spheres and
FEM nodes (with their constraints and velocity drivers), moving walls, and the state's time."""

from __future__ import annotations

import warp as wp

from .kernels import integrate as ki
from .model import Model, State


def integrate_first_half(model: Model, state: State) -> None:
    """Kick by dt/2 with the forces of the last evaluation, drift by dt, clear the force accumulators (FEM nodes:
    start them at the mass-proportional damping force) and raise the rebuild flag if a sphere has moved half the
    skin."""
    m, s = model, state
    wp.launch(
        ki.integrate_first_half_kernel,
        dim=m.particle_capacity,
        inputs=[
            # Model:
            m.particle_inv_mass,
            m.particle_inv_inertia,
            m.particle_motion,
            wp.vec3(*m.gravity),
            m.dt,
            0.5 * m.skin,
            # State in:
            s.particle_count,
            s.particle_q_at_build,
        ],
        outputs=[s.particle_q, s.particle_qd, s.particle_omega, s.particle_f, s.particle_t, s.rebuild_flag],
        device=m.device,
    )
    if m.node_capacity:
        node_driver, drivers, num_drivers = _node_drivers(m)
        wp.launch(
            ki.integrate_nodes_first_half_kernel,
            dim=m.node_capacity,
            inputs=[
                # Model:
                m.node_ref_q,
                m.node_mass,
                m.node_inv_mass,
                m.node_motion,
                m.node_damping,
                node_driver,
                drivers,
                num_drivers,
                wp.vec3(*m.gravity),
                m.dt,
                # State in:
                s.node_count,
                s.time,
            ],
            outputs=[s.node_u, s.node_q, s.node_qd, s.node_f, s.node_energy_damping, s.node_energy_boundary_work],
            device=m.device,
        )
    if m.walls_move:
        wp.launch(
            ki.advance_walls_kernel,
            dim=m.num_walls,
            inputs=[m.wall_velocity, m.dt],
            outputs=[s.wall_point],
            device=m.device,
        )


def integrate_second_half(model: Model, state: State) -> None:
    """Kick by dt/2 with the forces at the new positions; count the work of driven spheres and nodes; advance the
    state's time by dt (last, so that both halves of the step see the same t_n)."""
    m, s = model, state
    wp.launch(
        ki.integrate_second_half_kernel,
        dim=m.particle_capacity,
        inputs=[
            # Model:
            m.particle_inv_mass,
            m.particle_inv_inertia,
            m.particle_motion,
            wp.vec3(*m.gravity),
            m.dt,
            # State in:
            s.particle_count,
            s.particle_f,
            s.particle_t,
        ],
        outputs=[s.particle_qd, s.particle_omega, s.energy_boundary_work],
        device=m.device,
    )
    if m.node_capacity:
        node_driver, drivers, num_drivers = _node_drivers(m)
        wp.launch(
            ki.integrate_nodes_second_half_kernel,
            dim=m.node_capacity,
            inputs=[
                # Model:
                m.node_mass,
                m.node_inv_mass,
                m.node_motion,
                node_driver,
                drivers,
                num_drivers,
                wp.vec3(*m.gravity),
                m.dt,
                # State in:
                s.node_count,
                s.time,
                s.node_f,
            ],
            outputs=[s.node_qd, s.node_energy_boundary_work],
            device=m.device,
        )
    wp.launch(ki.advance_time_kernel, dim=1, inputs=[wp.float64(m.dt)], outputs=[s.time], device=m.device)


def _node_drivers(model: Model) -> tuple[wp.array | None, wp.array | None, int]:
    """The node velocity drivers of a model (warpdem.loads): per-node driver ids, drivers, their count."""
    loads = model.loads
    if loads is None or loads.num_drivers == 0:
        return None, None, 0
    return loads.node_driver, loads.drivers, loads.num_drivers
