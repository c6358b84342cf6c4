"""Integration stage (host side): the two half kicks of velocity Verlet around the force evaluation, for spheres and
FEM nodes (with their constraints and velocity drivers), moving walls, and the state's time.

A run of n steps is ``integrate_first_half``, forces, then n - 1 times ``kick_drift`` (the second half of one step
and the first half of the next in one pass: the two use the same forces), forces, and last ``integrate_second_half``:
the same arithmetic as n separate steps, bit for bit, with one pass over the sphere and node arrays fewer per step.
"""

from __future__ import annotations

import warp as wp

from ..kernels import integrate as ki
from ..kernels import rigid as kr
from ..model import Model, State
from .neighbors import make_struct

NO_SUBSTEPS = ki.SubstepNodes()
"""The sub-stepped nodes of a step without sub-steps: none (the struct's arrays unset, so ``node_slot`` is empty and
every node takes the plain step; kernels/integrate.py ``substep_slot``)."""


def integrate_first_half(
    model: Model,
    state: State,
    track_energy: bool = True,
    nodes: bool = True,
    sub: ki.SubstepNodes | None = None,
) -> None:
    """Kick by dt/2 with the forces of the last evaluation, drift by dt, clear the force accumulators (FEM nodes:
    start them at the mass-proportional damping force) and raise the rebuild flags if a sphere has moved half the
    skin or a surface node half the FEM skin; with ``track_energy`` book the half of the sphere contacts' and bonds'
    work that lies ahead of their evaluation (kernels/integrate.py ``book_contact_work_ahead``). ``nodes``: False
    skips the FEM node kernel (every node rigid and undriven: warpdem.stages.rigid ``every_node_rigid``). ``sub``:
    the sub-stepped nodes (warpdem.stages.substep ``Substeps.nodes_struct``), which are kicked but not drifted here;
    None: none."""
    _drift(model, state, ki.integrate_first_half_kernel, ki.integrate_nodes_first_half_kernel, track_energy, nodes, sub)
    _advance_walls(model, state)


def pose_ahead(state: State) -> kr.PoseAhead:
    """The arrays the half ahead of a force's work is booked against, as the kernels take them (kernels/rigid.py
    ``PoseAhead``): made at each launch, so that it holds the State's arrays after any growth."""
    s = state
    return make_struct(
        kr.PoseAhead,
        node_qd=s.node_qd,
        node_body=s.node_body,
        node_rigid_r0=s.node_rigid_r0,
        body_fixed=s.body_fixed,
        body_v=s.body_v,
        body_q_before=s.body_q_before,
        body_omega_ahead=s.body_omega_ahead,
    )


def book_half_ahead(
    model: Model,
    state: State,
    dt: float,
    node_f_kind: wp.array,
    node_energy_kind: wp.array,
    sign: float,
    rigid_only: bool = False,
) -> None:
    """Book ``sign`` × ½ dt f_n·v_{n+1/2} [J] of one kind of node force kept from the last evaluation
    (``node_f_kind``, shape (node_capacity,), vec3) into its line (``node_energy_kind``, float64), each node against
    the velocity of the half step ahead of that evaluation (a rigid body's node: at the pose the force was made at,
    kernels/rigid.py ``node_velocity_ahead``), and clear the kind's sums (launches only). Call it after the drift and
    before the kind's new evaluation: sign −1 for a line of what the forces take out (contacts, dashpots), +1 for
    work put in (loads); ``rigid_only``: the rigid blocks' nodes alone (the viscous forces, whose other nodes the
    node drift books)."""
    m, s = model, state
    wp.launch(
        ki.book_half_ahead_kernel,
        dim=m.node_capacity,
        inputs=[
            dt,
            s.node_count,
            pose_ahead(s),
            sign,
            int(rigid_only),
        ],
        outputs=[node_f_kind, node_energy_kind],
        device=m.device,
    )


def integrate_second_half(model: Model, state: State, sub: ki.SubstepNodes | None = None) -> None:
    """Kick by dt/2 with the forces at the new positions; count the work of driven spheres and nodes; advance the
    state's time by dt (last, so that both halves of the step see the same t_n). ``sub``: as in
    :func:`integrate_first_half` (a sub-stepped node is kicked from the velocity its sub-steps ended with)."""
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
        outputs=[s.particle_qd, s.particle_qd_carry, s.particle_omega, s.energy_boundary_work],
        device=m.device,
    )
    if m.node_capacity:
        node_driver, drivers, num_drivers = node_drivers(m)
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
                sub if sub is not None else NO_SUBSTEPS,
            ],
            outputs=[s.node_qd, s.node_qd_carry, s.node_energy_boundary_work],
            device=m.device,
        )
    _advance_time(m, s)


def kick_drift(
    model: Model,
    state: State,
    track_energy: bool = True,
    nodes: bool = True,
    sub: ki.SubstepNodes | None = None,
) -> None:
    """The second half of step n and the first half of step n + 1 in one pass (:func:`integrate_second_half` then
    :func:`integrate_first_half`, bit for bit): kick by dt/2 twice with the forces f_{n+1}, book the work of driven
    spheres and nodes, drift, clear the accumulators, flag a rebuild; the clock advances in between. ``nodes`` and
    ``sub``: as in :func:`integrate_first_half`."""
    _drift(model, state, ki.kick_drift_particles_kernel, ki.kick_drift_nodes_kernel, track_energy, nodes, sub)
    # The nodes judged their drivers at t_n + dt/2 and t_n + 3dt/2 from the clock as it was; it moves on now, before
    # the walls and the forces of step n + 1, as between two separate steps.
    _advance_time(model, state)
    _advance_walls(model, state)


def _drift(
    m: Model,
    s: State,
    particle_kernel: wp.Kernel,
    node_kernel: wp.Kernel,
    track_energy: bool,
    nodes: bool = True,
    sub: ki.SubstepNodes | None = None,
) -> None:
    """Launch the sphere and node kernels that end a half step in a drift (first half, or kick-drift); the node
    kernel only with ``nodes``, ``sub`` its sub-stepped nodes (None: none)."""
    wp.launch(
        particle_kernel,
        dim=m.particle_capacity,
        inputs=[*_particle_drift_inputs(m, s), int(track_energy)],
        outputs=_particle_drift_outputs(s),
        device=m.device,
    )
    if m.node_capacity and nodes:
        wp.launch(
            node_kernel,
            dim=m.node_capacity,
            inputs=[
                *_node_drift_model(m),
                s.node_count,
                s.time,
                s.node_q_at_fem_build,
                sub if sub is not None else NO_SUBSTEPS,
            ],
            outputs=_node_drift_outputs(s),
            device=m.device,
        )


def _particle_drift_inputs(m: Model, s: State) -> list:
    """Inputs of the sphere kernels that end in a drift (first half and kick-drift)."""
    return [
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
    ]


def _particle_drift_outputs(s: State) -> list:
    """Outputs of the sphere kernels that end in a drift."""
    return [
        s.particle_q,
        s.particle_qd,
        s.particle_qd_carry,
        s.particle_omega,
        s.particle_f,
        s.particle_t,
        s.rebuild_flag,
        s.energy_boundary_work,
        s.contact_sums,
        s.energy_damping,
        s.energy_friction,
    ]


def _node_drift_model(m: Model) -> list:
    """Model inputs of the node kernels that end in a drift (first half and kick-drift)."""
    node_driver, drivers, num_drivers = node_drivers(m)
    return [
        m.node_ref_q,
        m.node_mass,
        m.node_inv_mass,
        m.node_motion,
        m.node_damping,
        node_driver,
        drivers,
        num_drivers,
        m.node_contact_stiffness,
        wp.vec3(*m.gravity),
        m.dt,
        # A node on the surface flags an FEM contact-list rebuild when it has moved half the FEM skin.
        0.5 * m.fem_skin if m.face_capacity else -1.0,
        wp.float64(m.dt),  # the clock's increment, for the driver times of a kick-drift
    ]


def _node_drift_outputs(s: State) -> list:
    """Outputs of the node kernels that end in a drift."""
    return [
        s.node_u,
        s.node_q,
        s.node_qd,
        s.node_qd_carry,
        s.node_f,
        s.node_energy_damping,
        s.node_f_viscous,
        s.node_energy_boundary_work,
        s.fem_rebuild_flag,
    ]


def _advance_walls(m: Model, s: State) -> None:
    if m.walls_move:
        wp.launch(
            ki.advance_walls_kernel,
            dim=m.num_walls,
            inputs=[m.wall_velocity, m.dt],
            outputs=[s.wall_point],
            device=m.device,
        )


def _advance_time(m: Model, s: State) -> None:
    wp.launch(ki.advance_time_kernel, dim=1, inputs=[wp.float64(m.dt)], outputs=[s.time], device=m.device)


def node_drivers(model: Model) -> tuple[wp.array | None, wp.array | None, int]:
    """The node velocity drivers of a model (warpdem.stages.loads): per-node driver ids, drivers, their count."""
    loads = model.loads
    if loads is None or loads.num_drivers == 0:
        return None, None, 0
    return loads.node_driver, loads.drivers, loads.num_drivers
