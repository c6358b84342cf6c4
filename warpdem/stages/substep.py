"""Sub-steps of the cohesive elements' daughters (host side): ``[fracture] cohesive_substeps`` n > 1 moves the nodes
of the intact cohesive elements under the elements' forces in n velocity-Verlet sub-steps of dt/n between the two
half kicks of every other force, a multiple-time-step integration (r-RESPA: Tuckerman, Berne and Martyna, J. Chem.
Phys. 97, 1992; the arithmetic in kernels/substep.py).

Why. An element opens through δ_c in a step or less where a blast drives a crack: β = f_c dt² (1/m_A + 1/m_B)/δ_c,
the share of δ_c the element's peak force opens in one step, has a median of 4 and reaches 56 on limestone_tunnel.
The law is then not resolved: the force is born at f_c, keeps its birth direction while the opening is below the
step's threshold s = min(δ_c, f_c dt² (1/m_A + 1/m_B)) (kernels/cohesive.py ``open_length``), and drops to zero at
the break, all within a step, and the work the element does differs from Γ A_f by a multiple of it, of either sign
(the ``coh. trapezoid`` line). Halving the whole step shrinks β by four but costs every force twice; the elements'
own nodes are a small share of the model, so only they take the short step: with n sub-steps β falls by n², the
threshold s by n², and the element's work converges to Γ A_f (tests/test_substep.py).

What it books. The sub-steps are a velocity Verlet of the cohesive forces alone, whose elements book their
trapezoid at dt/n as at dt (kernels/cohesive.py), with their shadow term (dt/n)²/8 |f|²/m (kernels/books.py). The
other forces are evaluated once a step with the nodes' velocity set to the step's mean (x_{n+1} − x_n)/dt, so their
lines book what they book in a plain step and the contacts' last position x − dt v holds; what their half kicks add
to the kinetic energy beyond that, m dv·(v − v_mean) at the velocities the kicks start from and end at, goes to the
``substep_work`` line (kernels/substep.py). The books close to rounding with any n.

Cost: per sub-step two launches (the nodes' kick and drift, over the sub-step slots; the elements, over theirs);
the sub-stepped nodes are listed on the device after every pass, the launches run over capacities, so a pass needs
no new graph. A node a velocity driver holds keeps its velocity through the sub-steps, the driver doing the work
against the cohesive forces (kernels/substep.py). Not after a rigid switch (fracture stops there: the elements take
the step again, warpdem.simulation).
"""

from __future__ import annotations

import warp as wp

from ..kernels import integrate as ki
from ..kernels import substep as ks
from ..model import Model, State
from .cohesive import eval_cohesive
from .integrate import node_drivers
from .neighbors import make_struct


class Substeps:
    """The sub-stepped nodes of a model and their scratch (device arrays sized by the node and cohesive capacities:
    make a new one after either grows).

    Args:
        model: a model with ``cohesive_substeps`` > 1 and cohesive element slots.
        state: its state (the arrays the step's kernels take are read from it at each launch).
    """

    def __init__(self, model: Model, state: State) -> None:
        d = model.device
        self.n = int(model.cohesive_substeps)
        self.capacity = min(model.node_capacity, 2 * model.cohesive_capacity)
        self.node_slot = wp.full(model.node_capacity, -1, dtype=int, device=d)
        self.count = wp.zeros(1, dtype=int, device=d)
        self.nodes = wp.zeros(self.capacity, dtype=int, device=d)
        self.dx = wp.zeros(self.capacity, dtype=wp.vec3, device=d)
        self.v_start = wp.zeros(self.capacity, dtype=wp.vec3, device=d)
        self.dv_start = wp.zeros(self.capacity, dtype=wp.vec3, device=d)
        self.v_end = wp.zeros(self.capacity, dtype=wp.vec3, device=d)
        self.number(model, state)

    def mark(self, model: Model, state: State) -> None:
        """Sub-step from now on the nodes of the intact live cohesive elements (``State.node_substepped``; launches
        only). Called after a pass that split or converted, the points of a run that every run of the scene passes
        at the same step: the set is part of the state (a checkpoint holds it) and changes nowhere else, so where a
        run is cut into pieces or restarted does not change which nodes are sub-stepped, nor their bits."""
        state.node_substepped.zero_()
        wp.launch(
            ks.mark_substep_nodes_kernel,
            dim=model.cohesive_capacity,
            inputs=[state.cohesive_count, state.cohesive_a, state.cohesive_b, state.cohesive_broken],
            outputs=[state.node_substepped],
            device=model.device,
        )
        self.number(model, state)

    def number(self, model: Model, state: State) -> None:
        """Give the marked nodes their sub-step slots (launches only)."""
        if int(model.node_capacity) > self.node_slot.shape[0]:
            raise ValueError("Substeps.number: the node capacity grew; make a new Substeps")
        self.count.zero_()
        wp.launch(
            ks.number_substep_nodes_kernel,
            dim=model.node_capacity,
            inputs=[state.node_count, state.node_substepped],
            outputs=[self.node_slot, self.count, self.nodes],
            device=model.device,
        )

    def nodes_struct(self, state: State) -> ki.SubstepNodes:
        """The struct the step's node kernels take (kernels/integrate.py ``SubstepNodes``)."""
        return make_struct(
            ki.SubstepNodes,
            node_slot=self.node_slot,
            v_start=self.v_start,
            dv_start=self.dv_start,
            v_end=self.v_end,
            node_energy_substep=state.node_energy_substep,
        )

    def run(self, model: Model, state: State, track_energy: bool) -> None:
        """The sub-steps of a step, after the node kernel's first half kick and before the other forces (launches
        only): n times the nodes' kicks and drift and the elements' forces at dt/n, then the last half kick and the
        end of the drift (kernels/substep.py)."""
        m, s, d = model, state, model.device
        h = m.dt / self.n
        drive = self._drivers(m, s)
        for k in range(self.n):
            wp.launch(
                ks.substep_kick_drift_kernel,
                dim=self.capacity,
                inputs=[m.node_ref_q, m.node_inv_mass, m.node_motion, h, self.nodes, self.count, int(k == 0), drive],
                outputs=[
                    s.node_u,
                    s.node_q,
                    s.node_qd,
                    s.node_qd_carry,
                    s.node_f_fast,
                    s.node_energy_boundary_work,
                    self.dx,
                ],
                device=d,
            )
            eval_cohesive(m, s, dt=h, track_energy=track_energy, substeps=self.n)
        wp.launch(
            ks.substep_finish_kernel,
            dim=self.capacity,
            inputs=[
                # Model:
                m.node_mass,
                m.node_inv_mass,
                m.node_motion,
                m.node_damping,
                m.node_contact_stiffness,
                h,
                m.dt,
                0.5 * m.fem_skin if m.face_capacity else -1.0,
                # In:
                self.nodes,
                self.count,
                self.dx,
                s.node_q_at_fem_build,
                s.node_q,
                s.node_f_fast,
                self.nodes_struct(s),
                drive,
            ],
            outputs=[
                s.node_qd,
                s.node_qd_carry,
                s.node_f,
                s.node_energy_boundary_work,
                s.node_energy_damping,
                s.node_f_viscous,
                s.fem_rebuild_flag,
            ],
            device=d,
        )

    def _drivers(self, model: Model, state: State) -> ks.StepDrivers:
        """The node velocity drivers as the sub-step kernels take them (kernels/substep.py ``StepDrivers``; without
        drivers the arrays stay unset, so the kernels see none)."""
        node_driver, drivers, num = node_drivers(model)
        return make_struct(
            ks.StepDrivers, node_driver=node_driver, drivers=drivers, num_drivers=num, time=state.time, dt=model.dt
        )
