"""The step pipeline: one explicit time step as an ordered list of stages, run as a captured graph.

A step (DESIGN.md, stages in order):

1. integrate, first half — kick by dt/2, drift by dt, clear forces, flag a neighbour rebuild if needed (spheres
   and FEM nodes);
2. tetrahedra — Cosserat point element forces and bulk viscosity (their Cauchy stresses are refreshed between steps);
   cohesive elements between the daughters of split nodes (LDEC eqs. 5–8, warpdem.stages.cohesive);
3. contact search — rebuild the skinned neighbour list from the hash grid when flagged (conditional node);
4. contact — sphere–sphere and sphere–wall forces with tangential history; FEM contact (its lists rebuilt in a
   conditional node when a node moved half the FEM skin or the sphere list was rebuilt): sphere–face, node–face
   across joints and cracks, node–wall, and the joint interface elements (warpdem.stages.fem_contact,
   warpdem.stages.joints);
5. bonds — cohesive bond forces and breakage; the penalty couplings of converted spheres to the continuum
   (warpdem.stages.coupling);
6. loads and boundaries — pressure histories on faces, non-reflecting dashpots (fixed and roller nodes and velocity
   drivers are held by the integrator);
7. integrate, second half — kick by dt/2 with the new forces; advance the time.

The step allocates nothing and reads nothing back. Between frames (:meth:`Simulation.advance`) the host checks the
device's overflow counters; if a capacity was exceeded it grows the buffers ×2, restores the state saved at the
start of the advance and runs it again, so nothing is ever dropped. Topology passes (removing broken bonds and
cohesive elements) run there too. With nodal fracture or FEM→DEM conversion on, an advance runs in chunks that
end on multiples of ``model.fracture_interval`` and ``model.conversion_interval`` steps, each chunk with its own
overflow redo, and the passes due after each (:meth:`Simulation.conversion_pass`, warpdem.stages.conversion, then
:meth:`Simulation.fracture_pass`, warpdem.stages.fracture): a redo never crosses a topology pass.

Rigid blocks (warpdem.stages.rigid): once the blocks turned rigid (:meth:`Simulation.switch_to_rigid`, from the start,
at a time, or by the kinetic energy of the element modes), each half of the integration is followed by the bodies'
(kick, drift and free rotor, then their nodes' pose; the second half kick) and the forces by their reduction to a force
and a torque per body; the tets of the blocks carry no force.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable, Sequence

import numpy as np
import warp as wp

from .kernels import rigid as kernels_rigid
from .kernels.tets import TET_ACTIVE
from .model import NEIGHBOR_FIELDS, Model, State
from .recorded import Recorded, arrays_key
from .stages import overlap_band
from .stages.bonds import compact_bonds, eval_bonds
from .stages.cohesive import compact_cohesive, eval_cohesive, regrow_cohesive
from .stages.compaction import Compactor
from .stages.contact import NeighborList, contact_energy, eval_contacts
from .stages.conversion import (
    ConversionPass,
    ConversionReport,
    drop_converted_load_faces,
    grown,
    regrow_bonds,
    regrow_particles,
)
from .stages.coupling import eval_coupling, regrow_coupling
from .stages.energy import CONTACT, CONVERSION, SHADOW, BookTerms, DeviceBooks, EnergyBalance
from .stages.fem_contact import (
    FemContact,
    fem_contact_growth,
    hold_contact_stiffness,
    regrow_fem_contacts,
)
from .stages.fem_surface import SurfaceScratch, face_slots, rebuild_surface, remap_face_ids
from .stages.fracture import FracturePass, SplitReport
from .stages.guard import CriticalStep, GuardReport, StabilityGuard, UnstableRunError
from .stages.integrate import integrate_first_half, integrate_second_half, kick_drift
from .stages.loads import eval_loads, relax_to_equilibrium
from .stages.rigid import (
    RigidReport,
    drift_bodies,
    element_mode_energy,
    every_node_rigid,
    has_bodies,
    kick_bodies,
    make_bodies,
    pose_nodes,
    reduce_body_forces,
)
from .stages.rigid_step import rigid_step_after_switch
from .stages.status import ChunkStatus, StatusReader
from .stages.substep import Substeps
from .stages.tets import eval_tet_stresses, eval_tets
from .stages.topology import regrow_nodes

NODE_RIGID = int(kernels_rigid.NODE_RIGID)
MARK_CONTACT, MARK_SHADOW, MARK_SLOTS = 0, 1, 2
"""Slots of the energy books' marks across a topology pass (Simulation._mark_books): the FEM contacts' lines, and
the shadow term (with the couplings' springs in a conversion pass)."""


def regrow_neighbors(model: Model, state: State, max_neighbors: int) -> tuple[Model, State]:
    """Return a model and state with ``max_neighbors`` slots per particle, the existing slots copied over."""
    old_k = model.max_neighbors
    cap = model.particle_capacity
    fields = {}
    for name in NEIGHBOR_FIELDS:
        old = getattr(state, name)
        host = old.numpy().reshape(cap, old_k, *old.numpy().shape[1:])
        pad = [(0, 0), (0, max_neighbors - old_k)] + [(0, 0)] * (host.ndim - 2)
        fill = -1 if name == "nbr_bond" else 0
        grown = np.pad(host, pad, constant_values=fill).reshape(cap * max_neighbors, *host.shape[2:])
        fields[name] = wp.array(grown, dtype=old.dtype, device=model.device)
    return dataclasses.replace(model, max_neighbors=max_neighbors), dataclasses.replace(state, **fields)


class Simulation:
    """Steps a Model/State pair on its device.

    Args:
        model: the static model.
        state: the initial state; its ``particle_f``/``particle_t`` are evaluated here unless ``primed``.
        track_energy: accumulate dissipated energy per particle (slightly slower contact kernel).
        use_graph: run steps as a captured graph (CUDA graph on GPUs, Warp's recorded graph on the CPU).
        primed: the state already holds the forces at its positions (a restart from a checkpoint).
        step: step counter of ``state``; time: its simulated time [s], written to ``state.time`` (None: read from
            ``state.time``).
    """

    def __init__(
        self,
        model: Model,
        state: State,
        *,
        track_energy: bool = True,
        use_graph: bool = True,
        primed: bool = False,
        step: int = 0,
        time: float | None = None,
    ) -> None:
        self.model = model
        self.state = state
        self.track_energy = track_energy
        self._device_books: DeviceBooks | None = None
        self._book_marks: wp.array | None = None
        self._surface_scratch_kept: SurfaceScratch | None = None
        # The boundary face count before a topology pass, kept on the device (carrying face ids over reads it).
        self._faces_before = wp.zeros(1, dtype=int, device=model.device)
        self.use_graph = use_graph
        self.step_count = step
        if time is None:
            time = float(state.time.numpy()[0])
        else:
            state.time.fill_(time)
        self.time = time
        self.growths = 0
        self.guard = StabilityGuard(model.device)
        self.status = StatusReader(model.device)
        self.rigid_report: RigidReport | None = None
        if model.tet_may_convert is not None:
            # A restart: the checkpoint keeps dropped load faces as collapsed node triples; their edges come from the
            # scene and are zeroed again (a no-op at t = 0).
            drop_converted_load_faces(model, state)
        self._setup()
        # The conversion pass's scratch and the stars of all live tets live as long as the simulation (grown with
        # the capacities): made here, not at the first pass.
        self._conversion: ConversionPass | None = None
        self._band_edges: np.ndarray | None = None  # the band's edge ids (Simulation._band_incidence)
        if model.tet_may_convert is not None:
            self._conversion = ConversionPass(model)
            self._conversion.build_stars(model, state)
        if not primed:
            if self.fem_contact is not None:
                self.fem_contact.seat_walls()  # rock meshed onto a wall does not press on it at rest
            self.evaluate_forces()
            # The set-up build is checked like any other: a list that overflowed here would be the snapshot the
            # first advance restores, so grow until it fits and evaluate again.
            while self._grow_if_overflowed(self.state):
                self.evaluate_forces()
            self._switch_if_due()

    @property
    def track_energy(self) -> bool:
        """Whether the step keeps the energy books (the dissipation accumulators and the half-ahead sums)."""
        return self._track_energy

    @track_energy.setter
    def track_energy(self, on: bool) -> None:
        # A change after set-up re-captures the step (its launches differ) and clears the contacts' half-ahead sums:
        # without the books and without joint elements nothing books or clears them (warpdem.stages.fem_contact
        # eval_fem_contacts skips that launch), so forces kept from the last booked evaluation would otherwise be
        # booked against the velocities of a step long after.
        changed = hasattr(self, "_track_energy") and self._track_energy != bool(on)
        self._track_energy = bool(on)
        if changed:
            self._graphs = None
            self.state.node_f_contact.zero_()
            self.state.node_f_sphere_face.zero_()
            self.state.sphere_face_f.zero_()
            self.state.sphere_face_t.zero_()

    def _setup(self) -> None:
        # A model of tets alone has no sphere to size the contact grid by: its sphere contact stages are skipped.
        self.has_spheres = self.model.max_radius > 0.0
        self.neighbors = NeighborList(self.model, self.state) if self.has_spheres else None
        self.fem_contact = FemContact(self.model, self.state, self.has_spheres) if self.model.face_capacity else None
        fem = self.fem_contact
        self.guard.watch(*((fem.node_passed, fem.sphere_passed) if fem is not None else (None, None)))
        self.bond_compactor = Compactor(self.model.bond_capacity, self.model.device)
        self.cohesive_compactor = Compactor(self.model.cohesive_capacity, self.model.device)
        self.coupling_compactor = Compactor(self.model.coupling_capacity, self.model.device)
        self._fracture: FracturePass | None = None
        self._face_slot: wp.array | None = None
        self._snapshot: State | None = None
        self._snapshot_step: int | None = None  # the step of the snapshot; None: take one at the next chunk
        self._snapshot_time = 0.0
        self._graphs: tuple | None = None
        # Between-steps work made of launches only, recorded and replayed (warpdem.recorded); new stages, new records.
        self._force_recording = Recorded(self.model.device)
        self._epilogue_recording = Recorded(self.model.device)
        self._split_books_recording = Recorded(self.model.device)
        self._refresh_recording = Recorded(self.model.device)
        self._surface_recordings = (Recorded(self.model.device), Recorded(self.model.device))
        self.rigid = has_bodies(self.state)
        # Every node a rigid body's, none driven: the bodies' pose does all the node kernels' drift would (fixed
        # after the switch: no topology pass runs then).
        self.drift_nodes = not every_node_rigid(self.model, self.state)
        # Some tet left deformable: its viscous forces on a body's nodes have a half ahead to book after the bodies'
        # drift (warpdem.stages.rigid.drift_bodies); with none the step skips the tet stage (every tet_active changes in
        # a switch or a pass, each followed by this set-up).
        nt = int(self.state.tet_count.numpy()[0])
        self.deformable_tets = bool(np.any(self.state.tet_active.numpy()[:nt] == int(TET_ACTIVE)))
        # The cohesive elements' nodes sub-stepped (warpdem.stages.substep); the rigid switch sets the model's
        # sub-steps to 1 (the elements take the blocks' step).
        m = self.model
        self.substeps = Substeps(m, self.state) if m.cohesive_substeps > 1 and m.cohesive_capacity else None

    # ------------------------------------------------------------------------------------------------------------
    def step(self) -> None:
        """One time step, the stages in the order of the physics (launches only): a run of one step."""
        self._head()
        self._tail()

    def _forces(self) -> None:
        """Stages 2–6 of a step: every force at the drifted positions (launches only)."""
        m, s = self.model, self.state
        if self.deformable_tets:
            eval_tets(m, s)  # with every tet rigid or gone its kernel returns at each (a launch over every slot)
        if m.cohesive_capacity and self.substeps is None:  # sub-stepped: evaluated in the sub-steps
            eval_cohesive(m, s, track_energy=self.track_energy)
        if self.has_spheres:
            self.neighbors.rebuild_if_needed()
            eval_contacts(m, s, self.track_energy)
        if self.fem_contact is not None:
            self.fem_contact.eval(self.track_energy)
        eval_bonds(m, s, track_energy=self.track_energy)
        eval_coupling(m, s, track_energy=self.track_energy)
        eval_loads(m, s)
        if self.rigid:
            reduce_body_forces(m, s)

    def _head(self) -> None:
        """First half of the first step of a run, and its forces."""
        integrate_first_half(self.model, self.state, self.track_energy, self.drift_nodes, self._substep_nodes())
        self._substep()
        if self.rigid:
            drift_bodies(self.model, self.state, after_second_half=False, deformable=self.deformable_tets)
        self._forces()

    def _body(self) -> None:
        """Second half of a step, first half of the next (one pass: warpdem.stages.integrate.kick_drift), its forces."""
        kick_drift(self.model, self.state, self.track_energy, self.drift_nodes, self._substep_nodes())
        self._substep()
        if self.rigid:
            drift_bodies(self.model, self.state, after_second_half=True, deformable=self.deformable_tets)
        self._forces()

    def _tail(self) -> None:
        """Second half of the last step of a run."""
        integrate_second_half(self.model, self.state, self._substep_nodes())
        if self.rigid:
            kick_bodies(self.model, self.state)

    def _substep_nodes(self):
        """The sub-stepped nodes as the step's node kernels take them (None: no sub-steps)."""
        return self.substeps.nodes_struct(self.state) if self.substeps is not None else None

    def _substep(self) -> None:
        """The sub-steps of the cohesive elements' nodes, between the first half kick and the other forces."""
        if self.substeps is not None:
            self.substeps.run(self.model, self.state, self.track_energy)

    def evaluate_forces(self, after_pass: bool = False, rebuild_fem: bool = True) -> None:
        """Forces at the current positions without advancing time or history (the set-up evaluation; ``after_pass``:
        the re-evaluation after a topology pass, where node–face springs that start start relaxed: nothing moved).
        ``rebuild_fem``: rebuild the FEM contact lists first (False: they are up to date, FemContact.refresh_near)."""
        m, s = self.model, self.state
        key = (arrays_key(m, m.loads, s), after_pass, rebuild_fem, self.track_energy)
        self._recorded(self._force_recording, key, lambda: self._evaluate_forces(after_pass, rebuild_fem))

    def _evaluate_forces(self, after_pass: bool, rebuild_fem: bool) -> None:
        """:meth:`evaluate_forces`'s launches."""
        m, s = self.model, self.state
        s.particle_f.zero_()
        s.particle_t.zero_()
        s.contact_sums.zero_()
        s.node_f.zero_()
        # The next kick books the half ahead of exactly the viscous forces evaluated here (none of the damping: it
        # starts with the next drift), whatever a pass took out since the last step (warpdem.stages.integrate).
        s.node_f_viscous.zero_()
        eval_tets(m, s, dt=0.0)
        s.node_f_fast.zero_()
        if m.cohesive_capacity:
            substeps = self.substeps.n if self.substeps is not None else 1
            eval_cohesive(m, s, dt=0.0, track_energy=self.track_energy, substeps=substeps)
        if self.has_spheres:
            s.rebuild_flag.fill_(1)
            self.neighbors.rebuild_if_needed()
            eval_contacts(m, s, self.track_energy, dt=0.0)
        if self.fem_contact is not None:
            if rebuild_fem:
                s.fem_rebuild_flag.fill_(1)
            self.fem_contact.eval(self.track_energy, dt=0.0, born_relaxed=after_pass)
        eval_bonds(m, s, dt=0.0, track_energy=self.track_energy)
        eval_coupling(m, s, dt=0.0, track_energy=self.track_energy)
        eval_loads(m, s, dt=0.0)
        if self.rigid:
            reduce_body_forces(m, s)
        eval_tet_stresses(m, s)

    def relax_to_equilibrium(self, **kwargs) -> int:
        """Damped dynamic relaxation of the FEM nodes to the geostatic state before dynamics starts (keyword
        arguments and return value: :func:`warpdem.stages.loads.relax_to_equilibrium`)."""
        steps = relax_to_equilibrium(self, **kwargs)
        eval_tet_stresses(self.model, self.state)
        return steps

    def _run(self, n_steps: int) -> None:
        """n steps as head, n - 1 bodies, tail: bit for bit n calls of :meth:`step`, with one pass over the sphere and
        node arrays fewer per step. Under a graph each of the three parts is a captured graph, replayed."""
        if n_steps <= 0:
            return
        parts = (self._head, self._body, self._tail)
        # The parts to run: head, n - 1 bodies, tail, as (part, repeats), so memory does not grow with n.
        sequence = [(0, 1), (1, n_steps - 1), (2, 1)]
        if self.use_graph and self._graphs is None:
            # The first head runs eagerly, compiling every kernel of the step outside a capture; the three parts are
            # then recorded (not run) for replay.
            self._head()
            sequence = sequence[1:]
            try:
                graphs = []
                for part in parts:
                    with wp.ScopedCapture(device=self.model.device) as capture:
                        part()
                    graphs.append(capture.graph)
                self._graphs = tuple(graphs)
            except RuntimeError as exc:
                # Conditional graph nodes need CUDA 12.4+; without them the same launches run one by one.
                warnings.warn(f"graph capture unavailable ({exc}); running steps without a graph", stacklevel=2)
                self.use_graph = False
        for index, repeats in sequence:
            for _ in range(repeats):
                if self.use_graph:
                    wp.capture_launch(self._graphs[index])
                else:
                    parts[index]()

    def advance(self, n_steps: int, stop_at_switch: bool = False) -> int:
        """Run ``n_steps`` steps, then the between-step work: overflow check (grow and redo), stability guard, bond
        and cohesive compaction. With conversion or nodal fracture on, the steps run in chunks ending on multiples of
        ``model.conversion_interval`` and of ``model.fracture_interval`` (counted from step 0), each followed by the
        passes due there: first the conversion pass (:meth:`conversion_pass`), then the split pass
        (:meth:`fracture_pass`). A rigid switch due (:meth:`_switch_if_due`) ends a chunk too; with ``stop_at_switch``
        the call returns right after it, so that the caller can take another time step from the switch on (the
        runner's rigid step, warpdem.runner.take_rigid_step) before the next step is taken at the old one.

        Why conversion first: a tet that qualifies for both has failed as a whole; converting it hands its mass and
        momentum to a sphere and takes its stress out of the nodal averages, so the split pass that follows sees only
        the continuum that remains. Splitting first would create cohesive elements (and crack area, booked at birth)
        across faces of a tet that then stops existing as a continuum, and split nodes whose stars the conversion
        would empty at once.

        Returns:
            The steps run: ``n_steps``, or fewer when ``stop_at_switch`` stopped at a switch.

        Raises:
            warpdem.stages.guard.UnstableRunError: the state went non-finite or ran away (warpdem.stages.guard); the
                simulation is left at the first bad step.
        """
        remaining = n_steps
        # The caller may have changed the state since the last call: the redo snapshot is taken afresh.
        self._snapshot_step = None
        while remaining > 0:
            kc, kf = self.model.conversion_interval, self.model.fracture_interval
            intervals = [k for k in (kc, kf, self._rigid_check_interval()) if k > 0]
            switch = self._rigid_switch_step()
            if self.model.rigid_switch and not self.rigid and switch > self.step_count:
                intervals.append(switch)  # a chunk ends on the switch step (counted from step 0, as the passes)
            chunk = min(remaining, *(k - self.step_count % k for k in intervals)) if intervals else remaining
            rewound = self._advance_chunk(chunk)
            if rewound:  # a list overflowed and grew: back at the snapshot, the chunks since run again, passes too
                remaining += rewound
                continue
            remaining -= chunk
            # The chunk ended with the tet stresses evaluated, and a pass leaves them evaluated (evaluate_forces), so
            # the passes need not evaluate them again (one tet pass each, as much as a third of a step).
            if kc > 0 and self.step_count % kc == 0:
                self.conversion_pass(stresses_current=True)
            if kf > 0 and self.step_count % kf == 0:
                self.fracture_pass(stresses_current=True)
            if self._switch_if_due() is not None and stop_at_switch:
                break
        return n_steps - remaining

    def _rigid_switch_step(self) -> int:
        """The step on which the scene's rigid switch falls: the first at or after ``rigid_switch_time`` (a relative
        1e-9 of slack, so a time that is a whole number of steps in decimal is not pushed one step on by rounding)."""
        return max(0, math.ceil(self.model.rigid_switch_time / self.model.dt * (1.0 - 1e-9)))

    def _rigid_check_interval(self) -> int:
        """Steps between two checks of the kinetic-energy criterion of the rigid switch (0: none due)."""
        m = self.model
        return m.rigid_check_interval if (m.rigid_energy_fraction > 0.0 and not self.rigid) else 0

    def _switch_if_due(self) -> RigidReport | None:
        """Turn the blocks rigid now if the scene asks for it at this step (``rigid_switch_time``) or the kinetic
        energy of the element modes fell below ``rigid_energy_fraction`` of the nodes' (checked every
        ``rigid_check_interval`` steps). Returns what the switch did, None when not due."""
        m = self.model
        if self.rigid or m.node_capacity == 0:
            return None
        due = m.rigid_switch and self._rigid_switch_step() <= self.step_count
        every = self._rigid_check_interval()
        if not due and every > 0 and self.step_count % every == 0:
            element, total = element_mode_energy(m, self.state)
            due = total > 0.0 and element < m.rigid_energy_fraction * total
        return self.switch_to_rigid() if due else None

    def switch_to_rigid(self) -> RigidReport:
        """Turn every block rigid now, between steps (warpdem.stages.rigid.make_bodies): each takes the mass, momentum
        and angular momentum of its nodes; the strain energy of its tets and the kinetic energy of its element modes are
        booked as ``released_rigid_switch`` (with the change of the shadow term, as a conversion pass books it), so
        the books stay closed across the switch. Fracture and conversion passes stop. Forces are re-evaluated at the
        current positions (dt = 0) and the graphs re-captured.

        Raises:
            ValueError: the blocks already turned rigid.
        """
        if self.rigid:
            raise ValueError("switch_to_rigid: the blocks are rigid already")
        m, s = self.model, self.state
        before = self.energy() if self.track_energy else None
        s, report = make_bodies(m, s)
        self.model = dataclasses.replace(m, fracture_interval=0, conversion_interval=0, cohesive_substeps=1)
        self.state = s
        self._setup()
        # The nodes take their bodies' velocity field (positions are unchanged: u = u0 at the switch).
        pose_nodes(self.model, self.state, move=False)
        # As after a topology pass, node–face springs that start now start relaxed: nothing moved, but the contact
        # model did (a rigid node's normal turns with its body, a face of its own body is no candidate), and a node
        # of a block crushed next to a charge can find itself centimetres behind a face only now (up to 35 kJ a
        # node in limestone_tunnel at resolution 3 switched at 0.5 ms): its depth is carried as an offset.
        self.evaluate_forces(after_pass=True)
        while self._grow_if_overflowed(self.state):
            self.evaluate_forces(after_pass=True)
        if before is not None:
            after = self.energy()
            released = before.strain - after.strain + before.kinetic - after.kinetic - (before.shadow - after.shadow)
            booked = self.state.energy_released_rigid
            booked.assign(booked.numpy() + released)
            report.released = released
            report.shadow = after.shadow - before.shadow
        report.critical_dt = rigid_step_after_switch(self.model, self.state).value
        m = self.model
        report.deformable_dt = m.deformable_critical_dt if m.deformable_critical_dt > 0.0 else m.critical_dt
        report.dt_before = report.dt_after = m.dt
        self.rigid_report = report
        return report

    def set_time_step(self, dt: float, critical: CriticalStep | None = None) -> float:
        """Take a new time step from the next step on, between steps (the rigid step after a switch: the runner,
        warpdem.runner). Velocity Verlet books each step's trapezoid of work and its shadow term S = dt²/8 Σ |f|²/m at
        that step's own dt, and a change between two whole steps leaves positions, velocities and forces as they
        are: only the shadow term changes, S(dt_new) − S(dt_old) at the forces now, booked as ``step_change`` so the
        books stay closed across the change. The stages are set up again (the step is a launch argument: graphs are
        re-captured). With ``critical`` the model's critical step and its source become it (the guard's messages),
        the step before kept as ``deformable_critical_dt``. Reads back.

        Returns:
            The energy booked [J] (0 when energy is not tracked).

        Raises:
            ValueError: dt is not a positive finite number.
        """
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"set_time_step: the time step must be a positive finite number of seconds, got {dt!r}")
        m = self.model
        before = self.shadow() if self.track_energy else 0.0
        changes: dict = {"dt": float(dt)}
        if critical is not None:
            changes.update(
                critical_dt=critical.value,
                critical_dt_source=critical.source,
                deformable_critical_dt=m.deformable_critical_dt if m.deformable_critical_dt > 0.0 else m.critical_dt,
            )
        self.model = dataclasses.replace(m, **changes)
        self._setup()
        booked = 0.0
        if self.track_energy:
            booked = self.shadow() - before
            line = self.state.energy_step_change
            line.assign(line.numpy() + booked)
        if self.rigid_report is not None:
            self.rigid_report.dt_after = float(dt)
        return booked

    def _advance_chunk(self, n_steps: int) -> int:
        """:meth:`advance` without split passes. Returns the steps it went back (0 normally): when a list overflowed
        and the snapshot it restored is from an earlier chunk, the caller runs the chunks since it again.

        The snapshot a redo starts from is a copy of the whole State (one launch, warpdem.fused), taken at the first
        chunk of an :meth:`advance` call and again after any chunk whose between-steps work changed something (a
        compaction, a pass that split or converted, a growth, a switch: each sets ``_snapshot_step`` to None). Chunks
        whose work changed nothing share it, so a pass every step does not copy the State every step; a redo from an
        earlier chunk runs those chunks again with their passes, as the run would have with the larger lists."""
        if self._snapshot_step is None:
            if self._snapshot is None:
                self._snapshot = self.state.clone()
            else:
                self._snapshot.assign(self.state)
            self._snapshot_step, self._snapshot_time = self.step_count, self.time
        start, start_time = self._snapshot_step, self._snapshot_time  # a growth's set-up clears them
        while True:
            self._run(n_steps)
            # Everything the host needs to know now, in one read-back (warpdem.stages.status).
            m, s = self.model, self.state
            self._recorded(self._epilogue_recording, (arrays_key(m, s), self.has_spheres), self._epilogue)
            status = self.status.read()
            # A particle had more neighbours than slots: some contacts were not seen. Grow, restore, redo.
            if not self._grow_if_overflowed(self._snapshot, status):
                break
            # The state is the snapshot now, grown: it is the snapshot of the redo.
            self._snapshot = self.state.clone()
            self._snapshot_step, self._snapshot_time = start, start_time
            back = self.step_count - start
            if back:
                self.step_count, self.time = start, start_time
                return back
        self.step_count += n_steps
        # The device clock is the reference (time-dependent loads read it); the host copy follows it bit for bit, so
        # a restart from a checkpoint continues on the same clock.
        self.time = status.time
        report = self.guard.interpret(status.guard)
        if report is not None:
            raise self._first_bad_step(report, self.step_count - self._snapshot_step)
        self.remove_broken_bonds(status.bonds_broken)
        self.remove_broken_cohesive(status.cohesive_broken, status.cohesive_count)
        # No stage of the step reads the tet stresses; they are brought up to date for whoever reads the state now.
        eval_tet_stresses(self.model, self.state)
        return 0

    def _epilogue(self) -> None:
        """The chunk's launches before its status read: the stability guard, then the status gathered (launches
        only)."""
        self.guard.launch(self.model, self.state, sphere_lists=self.has_spheres)
        self.status.launch(self.model, self.state, self.guard.report, self.guard.clean)

    def _recorded(
        self, recording: Recorded, key: tuple, body: Callable[[], None], retain: Sequence[object] = ()
    ) -> None:
        """Run ``body`` (launches only) through ``recording`` (warpdem.recorded; ``retain`` as there), or eagerly
        without graphs."""
        if self.use_graph:
            recording.run(key, body, retain=retain)
        else:
            body()

    def _first_bad_step(self, report: GuardReport, n_steps: int) -> UnstableRunError:
        """The error for a run of ``n_steps`` that ended in a bad state (the steps since the snapshot: the chunks
        between changed nothing but the steps): the run is replayed from its snapshot one step at a time (bit for bit
        the same steps, warpdem.simulation._run) up to the first step the guard refuses, so that the error names where
        the blow-up began, not where the run ended (where the replay differs, as atomics may on a GPU, and stays good,
        the run's own end)."""
        step = self.step_count
        if n_steps > 1:
            self.state.assign(self._snapshot)
            for k in range(1, n_steps + 1):
                self._run(1)
                found = self.guard.check(self.model, self.state)
                if found is not None:
                    report, step = found, step - n_steps + k
                    break
        self.step_count = step
        self.time = float(self.state.time.numpy()[0])
        return self.guard.error(self.model, self.state, report, step, self.time)

    def _grow_if_overflowed(self, restore_from: State, status: ChunkStatus | None = None) -> bool:
        """If the last neighbour build (or FEM contact build) needed more slots than there are, grow ×2 until they
        fit and continue from ``restore_from`` (a state whose own lists fit). Returns whether it grew. ``status``: the
        counts as the chunk status read them (None: read them now)."""
        if status is None:
            needed, sphere_face, node_face = self.status.read_needs(self.state)
            fem = fem_contact_growth(self.model, self.state, sphere_face, node_face)
        else:
            needed = status.nbr_needed
            fem = fem_contact_growth(self.model, self.state, status.sphere_face_needed, status.node_face_needed)
        if needed <= self.model.max_neighbors and fem is None:
            return False
        model, state = self.model, restore_from
        if needed > model.max_neighbors:
            k = model.max_neighbors
            while k < needed:
                k *= 2
            model, state = regrow_neighbors(model, state, k)
        if fem is not None:
            model, state = regrow_fem_contacts(model, state, *fem)
        self.model, self.state = model, state
        self.growths += 1
        self._setup()
        return True

    def remove_broken_bonds(self, broken: int | None = None) -> int:
        """Compact broken bonds away (a topology pass between steps). Returns the live bond count (reads back).
        ``broken``: how many live bonds are broken, as the chunk status counted them (None: count them now)."""
        if self.model.bond_capacity == 0:
            return 0
        if broken is None:
            broken = int(np.count_nonzero(self.state.bond_broken.numpy()[: self.bond_count]))
        if broken:
            compact_bonds(self.model, self.state, self.bond_compactor)
            self._snapshot_step = None  # a redo must not cross a topology change
        return self.bond_count

    def remove_broken_cohesive(self, broken: int | None = None, count: int | None = None) -> int:
        """Compact broken cohesive elements away (between steps). Returns the live element count. ``broken`` and
        ``count``: the broken and live elements as the chunk status counted them (None: read them back now)."""
        if self.model.cohesive_capacity == 0:
            return 0
        s = self.state
        n = int(s.cohesive_count.numpy()[0]) if count is None else count
        if broken is None:
            broken = int(np.count_nonzero(s.cohesive_broken.numpy()[:n])) if n else 0
        if broken:
            self._snapshot_step = None  # a redo must not cross a topology change
            return compact_cohesive(self.model, s, self.cohesive_compactor)
        return n

    # ------------------------------------------------------------------------------------------------------------
    def fracture_pass(self, stresses_current: bool = False) -> SplitReport:
        """One split pass now, between steps (warpdem.stages.fracture): candidates, capacities grown ×2 to hold them,
        rounds of independent sets; after splits the surface and contact lists are rebuilt and the forces re-evaluated
        at the current positions (dt = 0; what the rebuild gives the FEM contact springs is booked,
        :meth:`_book_contact_topology`, and the change of Verlet's shadow term goes to ``energy_step_change``).
        Captured graphs are kept unless an array they read was reallocated. Reads back a few counts.
        ``stresses_current``: the tet stresses are up to date (as :meth:`conversion_pass`).

        Returns:
            What the pass did (no-op report when fracture is off).
        """
        if self.model.fracture_interval <= 0:
            return SplitReport(0, 0, False)
        grew = False
        while True:
            if self._fracture is None or not self._fracture.fits(self.model):
                self._fracture = FracturePass(self.model, use_graph=self.use_graph)
            key, retain = self._prepare_split()
            # One device program and one read-back (FracturePass.find_and_split): the bound, the search, and the rounds
            # where there is room for them.
            found = self._fracture.find_and_split(
                self.model, self.state, self._before_split, stresses_current, key=key, retain=retain
            )
            if found.candidates == 0:
                return SplitReport(0, 0, grew)
            if found.go:
                break
            self._grow_for_split(found.candidates)  # no room: nothing changed; grow and search again
            grew = True
            stresses_current = True  # the search evaluated them, and a growth moves nothing
        self._snapshot_step = None  # the pass split: a redo must not cross it
        splits = found.after - found.before
        if splits:
            self._after_split(splits)
            if self.substeps is not None:  # the new elements' daughters take the sub-steps from the next step
                self.substeps.mark(self.model, self.state)
            if self.track_energy:
                retain = self._prepare_books()
                key = (arrays_key(self.model, self.state), *(id(x) for x in retain))
                self._recorded(self._split_books_recording, key, self._book_split, retain)
        return SplitReport(splits, found.rounds, grew)

    def _book_split(self) -> None:
        """Book what a pass that split changed (launches only): the FEM contacts' lines, and Verlet's shadow term."""
        self._book_contact_topology()
        # The pass changes the forces the next kick uses (daughters lighter than their parent, a face's share of a
        # contact force on one daughter, the re-evaluation at dt = 0) with the velocities as they were: Verlet's
        # shadow term moves by S(f_new) - S(f_old) with no force working, as at a change of step.
        self._book_change(SHADOW, MARK_SHADOW, self.state.energy_step_change)

    def _prepare_split(self) -> tuple[tuple, list]:
        """Make what :meth:`_before_split` launches into (the faces' slots, the books' scratch, marks and weights), so
        that a recording of the pass allocates nothing; returns what the pass's recording must be keyed on and keep
        (warpdem.recorded) besides the model and state."""
        m = self.model
        slots = max(m.face_capacity, 1)
        if m.face_capacity and (self._face_slot is None or self._face_slot.shape[0] != slots):
            self._face_slot = wp.full(slots, -1, dtype=int, device=m.device)
        retain: list = [self._face_slot, *(self._prepare_books() if self.track_energy else [])]
        return (*(id(x) for x in retain), self.track_energy), retain

    def _prepare_books(self) -> list:
        """The books' scratch, marks and the weights a split pass books with, made now; returns them (what a recording
        that marks or books them must keep)."""
        books = self._books()
        books.prepare(CONTACT, SHADOW)
        return [books, self._marks()]

    def _before_split(self) -> None:
        """What must be taken before the rounds change the topology (launches only): each boundary face's tet-face
        slot (the remap of the contacts' face ids), the contact stiffness held by the surface nodes
        (hold_contact_stiffness), and the marks of the books the pass changes."""
        m, s = self.model, self.state
        if m.face_capacity:
            face_slots(m, s, self._face_slot)
            wp.copy(self._faces_before, s.face_count)
        hold_contact_stiffness(m, s)
        self._mark_books(CONTACT, MARK_CONTACT)
        self._mark_books(SHADOW, MARK_SHADOW)

    def _mark_books(self, terms: BookTerms, slot: int) -> None:
        """Keep ``terms`` of the energy books now on the device (warpdem.stages.energy.DeviceBooks.mark; launches
        only; nothing when energy is not tracked)."""
        if self.track_energy:
            self._books().mark(self.model, self.state, terms, self._marks(), slot)

    def _book_change(self, terms: BookTerms, slot: int, into: wp.array) -> None:
        """Add what ``terms`` changed by since :meth:`_mark_books` to ``into[0]`` (DeviceBooks.book; launches only;
        nothing when energy is not tracked)."""
        if self.track_energy:
            self._books().book(self.model, self.state, terms, self._marks(), slot, into)

    def _surface_scratch(self) -> SurfaceScratch:
        """The surface rebuild's scratch (warpdem.stages.fem_surface.SurfaceScratch), made again when the node or tet
        capacity has grown."""
        m = self.model
        if self._surface_scratch_kept is None or not self._surface_scratch_kept.fits(m):
            self._surface_scratch_kept = SurfaceScratch(m.node_capacity, m.tet_capacity, m.device)
        return self._surface_scratch_kept

    def _marks(self) -> wp.array:
        """The books' marks across a pass (float64, one slot per MARK_*), made once."""
        if self._book_marks is None:
            self._book_marks = wp.zeros(MARK_SLOTS, dtype=wp.float64, device=self.model.device)
        return self._book_marks

    def _book_contact_topology(self) -> None:
        """Book what the FEM contacts' lines gained across a topology pass (their mark taken just before it) as
        energy put in without work (``energy_contact_topology``).

        A pass moves nothing, so no contact force works across it. The surface is rebuilt, and the penalty stiffness
        of a split node's daughters (and of a converted tet's neighbours) is re-lumped over their new faces, but a
        node in contact keeps the stiffness per unit mass it held before the pass
        (warpdem.stages.fem_contact.hold_contact_stiffness): the daughters' springs sum to the parent's, so a split
        leaves them as they were to float32 rounding, and a conversion can only lower them (a node that lost mass to
        spheres presses with ω² m_new ≤ k). What is left to book: that loss, sphere–face springs on faces born inside an
        overlap, springs the dt = 0 re-evaluation starts or lets go of on the new faces, and rounding. Before the
        hold, each pass created ½ Δk δ² at every split node pressed by δ into the ground or a face: 8.8 kJ by 4.5 ms
        on the boulder scene, a third of its energy in play, which its dashpots then took out."""
        self._book_change(CONTACT, MARK_CONTACT, self.state.energy_contact_topology)

    def _grow_for_split(self, candidates: int) -> bool:
        """Grow the node and cohesive capacities ×2 until they hold ``candidates`` more of each (the most a pass can
        add). Returns whether anything grew (the stages are then set up again and graphs re-captured)."""
        m, s = self.model, self.state
        nodes = int(s.node_count.numpy()[0]) + candidates
        elements = int(s.cohesive_count.numpy()[0]) + candidates
        if nodes <= m.node_capacity and elements <= m.cohesive_capacity:
            return False
        if nodes > m.node_capacity:
            cap = max(m.node_capacity, 1)
            while cap < nodes:
                cap *= 2
            m, s = regrow_nodes(m, s, cap)
        if elements > m.cohesive_capacity:
            cap = max(m.cohesive_capacity, 1)
            while cap < elements:
                cap *= 2
            m, s = regrow_cohesive(m, s, cap)
        self.model, self.state = m, s
        self.growths += 1
        self._setup()
        return True

    def _after_split(self, new_nodes: int) -> None:
        """After a pass that split nodes (``new_nodes`` daughters from the pass's first new slot on): rebuild the
        surface on the device (crack faces become contact faces), carry the face ids of the contact state over, bring
        the contact lists up to date (near the daughters only where the stage allows, FemContact.refresh_near; else
        rebuilt whole) and re-evaluate the forces at dt = 0. The face count before the pass and the first daughter's
        slot are read on the device, so the carry-over and the refresh are one recording (warpdem.recorded)."""
        m, s = self.model, self.state
        refreshed = False
        if m.face_capacity:
            surface = self._surface_recordings if self.use_graph else None
            model, slot_to_face = rebuild_surface(m, s, self._surface_scratch(), surface)
            same = all(
                getattr(model, f) is getattr(m, f) for f in ("face_nodes", "star_tets", "node_contact_stiffness")
            )
            same = same and (model.face_radius, model.face_depth_max) == (m.face_radius, m.face_depth_max)
            self.model = model
            if same and self.fem_contact.refreshes_near:
                self.fem_contact.model = model
                fem, first_new = self.fem_contact, self._fracture.first_new_slot
                retain = [fem, self._face_slot, slot_to_face, self._fracture]
                key = (arrays_key(model, s), *(id(x) for x in retain))

                def refresh() -> None:
                    remap_face_ids(model, s, self._face_slot, self._faces_before, slot_to_face)
                    fem.refresh_near(first_new, self._face_slot, self._faces_before, slot_to_face)

                self._recorded(self._refresh_recording, key, refresh, retain)
                refreshed = True
            else:
                remap_face_ids(model, s, self._face_slot, self._faces_before, slot_to_face)
                if not same:
                    # A face array grew or the faces' extent (baked into the launches) changed: new stage, new graphs.
                    self._setup()
        self.evaluate_forces(after_pass=True, rebuild_fem=not refreshed)
        while self._grow_if_overflowed(self.state):
            self.evaluate_forces(after_pass=True)

    # ------------------------------------------------------------------------------------------------------------
    def conversion_pass(self, stresses_current: bool = False) -> ConversionReport:
        """One conversion pass now, between steps (warpdem.stages.conversion): tets at their criterion turn into bonded
        spheres; capacities grow ×2 first to hold what the pass writes; then the surface and contact lists are
        rebuilt, the stages set up again (sphere contact comes alive with the first spheres) and the forces
        re-evaluated at the current positions (dt = 0). Reads back a few counts. ``stresses_current``: the tet
        stresses are up to date (evaluated at the current positions since anything last moved), so the pass does not
        evaluate them again.

        Returns:
            What the pass did (no-op report when conversion is off).
        """
        if self.model.conversion_interval <= 0:
            return ConversionReport(0, 0, 0, 0, False)
        return self._convert(None, stresses_current)

    def convert_tets(self, mask: np.ndarray) -> ConversionReport:
        """Convert the given tets now, whatever their stress (e.g. a scene region that starts as spheres), as a
        conversion pass does (:meth:`conversion_pass`); tets already converted are skipped.

        Args:
            mask: bool per live tet, shape (tet_count,).

        Raises:
            ValueError: conversion is not attached (warpdem.stages.conversion.attach_conversion) or the mask has the
                wrong shape.
        """
        m = self.model
        if m.conversion_material_table is None:
            raise ValueError("convert_tets: conversion is not attached (warpdem.stages.conversion.attach_conversion)")
        nt = int(self.state.tet_count.numpy()[0])
        mask = np.asarray(mask)
        if mask.shape != (nt,):
            raise ValueError(f"convert_tets: mask must have one entry per live tet, shape ({nt},), got {mask.shape}")
        forced = np.zeros(m.tet_capacity, dtype=np.int32)
        forced[:nt] = mask.astype(bool)
        return self._convert(forced)

    def _convert(self, forced: np.ndarray | None, stresses_current: bool = False) -> ConversionReport:
        """A conversion pass of the tets the criterion flags (``forced`` None) or of ``forced`` (int per tet slot);
        ``stresses_current``: as :meth:`conversion_pass`."""
        if self._conversion is None or not self._conversion.fits(self.model):
            self._conversion = ConversionPass(self.model)
        band = self.model.band_width > 0
        if band and forced is not None:
            # A band tet is converted already (it keeps α of its FEM element): it does not convert again.
            forced = np.where(self.state.tet_sphere.numpy() >= 0, 0, forced).astype(np.int32)
        tets, bonds, couplings = self._conversion.find(self.model, self.state, forced, stresses_current)
        if tets == 0:
            return ConversionReport(0, 0, 0, 0, False)
        self._snapshot_step = None  # a redo must not cross a conversion
        spawned = tets * self.model.spheres_per_tet
        # The band replaces the tie's couplings by one per band sphere: slots for each new sphere and the live ones.
        grew = self._grow_for_conversion(spawned, bonds, max(couplings, spawned) if band else couplings)
        m, s = self.model, self.state
        wp.copy(self._faces_before, s.face_count)
        if m.face_capacity:
            self._face_slot = face_slots(m, s, self._face_slot)
        self._mark_books(CONVERSION, MARK_SHADOW)
        hold_contact_stiffness(m, s)
        self._mark_books(CONTACT, MARK_CONTACT)
        snap = overlap_band.snapshot(m, s) if band else None
        self._conversion.convert(m, s, self.coupling_compactor)
        if snap is not None:
            overlap_band.apply_band(m, s, snap, self._band_incidence())
        self._after_conversion()
        self._book_contact_topology()
        # The leapfrog kinetic energy the scheme conserves is kinetic − shadow; the pass changes the shadow term
        # (lighter nodes, new free faces, the spheres' forces) without any work, and releases the springs of
        # couplings to the converted tets (new couplings are born relaxed): both booked as released with the rest,
        # so the books stay closed across the pass.
        self._book_change(CONVERSION, MARK_SHADOW, self.state.energy_released_conversion)
        if self.substeps is not None:
            self.substeps.mark(self.model, self.state)
        return ConversionReport(tets, spawned, bonds, couplings, grew)

    def _band_incidence(self) -> np.ndarray:
        """The live tets' edge ids (warpdem.stages.overlap_band.edge_incidence), kept while nodes cannot split."""
        m = self.model
        if self._band_edges is None or m.fracture_material_table is not None:
            nt = int(self.state.tet_count.numpy()[0])
            self._band_edges = overlap_band.edge_incidence(m.tet_nodes.numpy()[:nt])
        return self._band_edges

    def _grow_for_conversion(self, spheres: int, bonds: int, couplings: int) -> bool:
        """Grow the particle, bond and coupling capacities ×2 until they hold ``spheres``, ``bonds`` and
        ``couplings`` more (what the pass writes; couplings before the pass releases any). Returns whether anything
        grew."""
        m, s = self.model, self.state
        particles = self.particle_count + spheres
        total_bonds = self.bond_count + bonds
        total_couplings = int(s.coupling_count.numpy()[0]) + couplings
        grew = False
        if total_couplings > m.coupling_capacity:
            m, s = regrow_coupling(m, s, grown(m.coupling_capacity, total_couplings))
            grew = True
        if particles > m.particle_capacity:
            m, s = regrow_particles(m, s, grown(m.particle_capacity, particles))
            grew = True
        if total_bonds > m.bond_capacity:
            m, s = regrow_bonds(m, s, grown(m.bond_capacity, total_bonds))
            grew = True
        if grew:
            self.model, self.state = m, s
            self.growths += 1
            self.coupling_compactor = Compactor(m.coupling_capacity, m.device)
        return grew

    def _after_conversion(self) -> None:
        """After a pass that converted tets: rebuild the surface on the device (the faces of converted tets'
        neighbours become contact faces), carry the face ids of the contact state over, set the stages up again
        (new spheres, possibly the first: sphere contact comes alive; graphs re-captured) and re-evaluate the forces
        at dt = 0 (the contact lists rebuilt once: the new spheres' face slots are sized first)."""
        m, s = self.model, self.state
        if m.face_capacity:
            model, slot_to_face = rebuild_surface(m, s, self._surface_scratch())
            remap_face_ids(model, s, self._face_slot, self._faces_before, slot_to_face)
            self.model = model
            drop_converted_load_faces(model, s)
        self._setup()
        if self.fem_contact is not None and self.has_spheres:
            # The new spheres' face lists, sized first: an overflowing build would redo the whole force evaluation
            # and every list (the node lists, the bulk of it, twice), where this builds the few spheres' lists once
            # more (the lists the evaluation then builds are the same).
            s = self.state
            kept = [wp.clone(a) for a in (s.sphere_face_count, s.sphere_face_index, s.sphere_face_shear)]
            self.fem_contact.rebuild_sphere_faces()
            fem = fem_contact_growth(self.model, s)
            if fem is not None:
                # The lists as they were (an overflowing build dropped candidates, and their shear with them).
                for a, old in zip((s.sphere_face_count, s.sphere_face_index, s.sphere_face_shear), kept, strict=True):
                    wp.copy(a, old)
                self.model, self.state = regrow_fem_contacts(self.model, s, *fem)
                self.growths += 1
                self._setup()
        self.evaluate_forces(after_pass=True)
        while self._grow_if_overflowed(self.state):
            self.evaluate_forces(after_pass=True)

    @property
    def bond_count(self) -> int:
        """Live bonds (host read-back)."""
        return int(self.state.bond_count.numpy()[0])

    @property
    def node_count(self) -> int:
        """Live FEM nodes (host read-back)."""
        return int(self.state.node_count.numpy()[0])

    @property
    def particle_count(self) -> int:
        """Live particles (host read-back)."""
        return int(self.state.particle_count.numpy()[0])

    # ------------------------------------------------------------------------------------------------------------
    def energy(self) -> EnergyBalance:
        """The energy balance now, reduced on the device (warpdem.stages.energy.DeviceBooks; one read-back; call
        between steps)."""
        return self._books().read(self.model, self.state)

    def shadow(self) -> float:
        """Verlet's shadow term of the energy books now [J] (warpdem.stages.energy.DeviceBooks; one read-back)."""
        return self._books().shadow(self.model, self.state)

    def _books(self) -> DeviceBooks:
        """The device books' scratch, made again when the capacities have grown."""
        if self._device_books is None or not self._device_books.fits(self.model, self.has_spheres):
            self._device_books = DeviceBooks(self.model, self.has_spheres)
        return self._device_books

    def contact_count(self) -> int:
        """Touching sphere–sphere pairs now (reads back)."""
        return contact_energy(self.model, self.state)[1]
