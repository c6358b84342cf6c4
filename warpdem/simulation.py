"""The step pipeline: one explicit time step as an ordered list of stages, run as a captured graph.

A step (DESIGN.md, stages in order):

1. integrate, first half — kick by dt/2, drift by dt, clear forces, flag a neighbour rebuild if needed (spheres
   and FEM nodes);
2. tetrahedra — Cosserat point element forces, bulk viscosity and Cauchy stresses;
3. contact search — rebuild the skinned neighbour list from the hash grid when flagged (conditional node);
4. contact — sphere–sphere and sphere–wall forces with tangential history;
5. bonds — cohesive bond forces and breakage;
6. integrate, second half — kick by dt/2 with the new forces.

The step allocates nothing and reads nothing back. Between frames (:meth:`Simulation.advance`) the host checks the
device's overflow counters; if a capacity was exceeded it grows the buffers ×2, restores the state saved at the
start of the advance and runs it again, so nothing is ever dropped. Topology passes (removing broken bonds) run
there too.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from .bonds import bond_energy, compact_bonds, eval_bonds
from .compaction import Compactor
from .contact import NeighborList, contact_energy, eval_contacts
from .integrate import integrate_first_half, integrate_second_half
from .model import NEIGHBOR_FIELDS, Model, State
from .tets import eval_tets, tet_energy


@dataclass
class EnergyBalance:
    """Energy bookkeeping of a DEM/FEM system [J].

    ``total`` = kinetic + elastic + strain + gravity potential + dissipated − boundary work; it stays at its initial
    value up to time-discretisation error (and the known non-conservation of a Mindlin spring whose stiffness
    changes with the overlap). Spheres and FEM nodes share the gravity potential; ``kinetic_nodes`` is the FEM
    nodes' kinetic energy, ``strain`` the tets' strain energy, ``dissipated_viscous`` what bulk viscosity and
    mass-proportional damping took from the continuum.
    """

    kinetic_translational: float
    kinetic_rotational: float
    elastic: float
    gravity_potential: float
    dissipated_damping: float
    dissipated_friction: float
    released_by_bond_breakage: float
    boundary_work: float
    kinetic_nodes: float = 0.0
    strain: float = 0.0
    dissipated_viscous: float = 0.0

    @property
    def kinetic(self) -> float:
        return self.kinetic_translational + self.kinetic_rotational + self.kinetic_nodes

    @property
    def total(self) -> float:
        return (
            self.kinetic
            + self.elastic
            + self.gravity_potential
            + self.dissipated_damping
            + self.dissipated_friction
            + self.released_by_bond_breakage
            - self.boundary_work
            + self.strain
            + self.dissipated_viscous
        )


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
        step: step counter of ``state``; time: its simulated time [s].
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
        time: float = 0.0,
    ) -> None:
        self.model = model
        self.state = state
        self.track_energy = track_energy
        self.use_graph = use_graph
        self.step_count = step
        self.time = time
        self.growths = 0
        self._setup()
        if not primed:
            self.evaluate_forces()
            # The set-up build is checked like any other: a list that overflowed here would be the snapshot the
            # first advance restores, so grow until it fits and evaluate again.
            while self._grow_if_overflowed(self.state):
                self.evaluate_forces()

    def _setup(self) -> None:
        # A model of tets alone has no sphere to size the contact grid by: its sphere contact stages are skipped.
        self.has_spheres = self.model.max_radius > 0.0
        self.neighbors = NeighborList(self.model, self.state) if self.has_spheres else None
        self.bond_compactor = Compactor(self.model.bond_capacity, self.model.device)
        self._snapshot: State | None = None
        self._graph = None

    # ------------------------------------------------------------------------------------------------------------
    def step(self) -> None:
        """One time step, the stages in the order of the physics (launches only)."""
        m, s = self.model, self.state
        integrate_first_half(m, s)
        eval_tets(m, s)
        if self.has_spheres:
            self.neighbors.rebuild_if_needed()
            eval_contacts(m, s, self.track_energy)
        eval_bonds(m, s)
        integrate_second_half(m, s)

    def evaluate_forces(self) -> None:
        """Forces at the current positions without advancing time or history (the set-up evaluation)."""
        m, s = self.model, self.state
        s.particle_f.zero_()
        s.particle_t.zero_()
        s.node_f.zero_()
        eval_tets(m, s, dt=0.0)
        if self.has_spheres:
            s.rebuild_flag.fill_(1)
            self.neighbors.rebuild_if_needed()
            eval_contacts(m, s, self.track_energy, dt=0.0)
        eval_bonds(m, s, dt=0.0)

    def _run(self, n_steps: int) -> None:
        if not self.use_graph or n_steps < 2:
            for _ in range(n_steps):
                self.step()
            return
        if self._graph is None:
            # The first step compiles the kernels outside the capture; the rest replay the recorded step.
            self.step()
            n_steps -= 1
            try:
                with wp.ScopedCapture(device=self.model.device) as capture:
                    self.step()
            except RuntimeError as exc:
                # Conditional graph nodes need CUDA 12.4+; without them the same launches run one by one.
                warnings.warn(f"graph capture unavailable ({exc}); running steps without a graph", stacklevel=2)
                self.use_graph = False
                self._run(n_steps)
                return
            self._graph = capture.graph
        for _ in range(n_steps):
            wp.capture_launch(self._graph)

    def advance(self, n_steps: int) -> None:
        """Run ``n_steps`` steps, then the between-step work: overflow check (grow and redo), bond compaction."""
        if self._snapshot is None:
            self._snapshot = self.state.clone()
        else:
            self._snapshot.assign(self.state)
        while True:
            self._run(n_steps)
            # A particle had more neighbours than slots: some contacts were not seen. Grow, restore, redo.
            if not self._grow_if_overflowed(self._snapshot):
                break
            self._snapshot = self.state.clone()
        self.step_count += n_steps
        self.time += n_steps * self.model.dt
        self.remove_broken_bonds()

    def _grow_if_overflowed(self, restore_from: State) -> bool:
        """If the last neighbour build needed more slots than there are, grow ×2 until they fit and continue from
        ``restore_from`` (a state whose own list fits). Returns whether it grew."""
        needed = int(self.state.nbr_needed.numpy()[0])
        if needed <= self.model.max_neighbors:
            return False
        k = self.model.max_neighbors
        while k < needed:
            k *= 2
        self.model, self.state = regrow_neighbors(self.model, restore_from, k)
        self.growths += 1
        self._setup()
        return True

    def remove_broken_bonds(self) -> int:
        """Compact broken bonds away (a topology pass between steps). Returns the live bond count."""
        if self.model.bond_capacity == 0:
            return 0
        broken = int(np.count_nonzero(self.state.bond_broken.numpy()[: self.bond_count]))
        if broken:
            compact_bonds(self.model, self.state, self.bond_compactor)
        return self.bond_count

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
        """The energy balance now (reads back; call between steps)."""
        m, s = self.model, self.state
        n = self.particle_count
        mass = m.particle_mass.numpy()[:n].astype(np.float64)
        radius = m.particle_radius.numpy()[:n].astype(np.float64)
        free = m.particle_motion.numpy()[:n] == 0
        v = s.particle_qd.numpy()[:n].astype(np.float64)
        w = s.particle_omega.numpy()[:n].astype(np.float64)
        q = s.particle_q.numpy()[:n].astype(np.float64)
        inertia = 0.4 * mass * radius**2
        e_contact, _ = contact_energy(m, s)
        e_bond, _ = bond_energy(m, s)
        g = np.asarray(m.gravity, dtype=np.float64)
        nn = self.node_count
        node_mass = m.node_mass.numpy()[:nn].astype(np.float64)
        node_v = s.node_qd.numpy()[:nn].astype(np.float64)
        # X + u in float64 rather than the float32 sum node_q, so the potential keeps the displacements' precision.
        node_q = m.node_ref_q.numpy()[:nn].astype(np.float64) + s.node_u.numpy()[:nn].astype(np.float64)
        moving = m.node_inv_mass.numpy()[:nn] > 0.0
        return EnergyBalance(
            kinetic_translational=float(0.5 * np.sum(mass * np.sum(v * v, axis=1))),
            kinetic_rotational=float(0.5 * np.sum(inertia * np.sum(w * w, axis=1))),
            elastic=e_contact + e_bond,
            gravity_potential=float(
                -np.sum(mass[free] * (q[free] @ g)) - np.sum(node_mass[moving] * (node_q[moving] @ g))
            ),
            dissipated_damping=float(s.energy_damping.numpy()[:n].sum()),
            dissipated_friction=float(s.energy_friction.numpy()[:n].sum()),
            released_by_bond_breakage=float(s.energy_bond_broken.numpy()[:n].sum()),
            boundary_work=float(s.energy_boundary_work.numpy()[:n].sum()),
            kinetic_nodes=float(0.5 * np.sum(node_mass * np.sum(node_v * node_v, axis=1))),
            strain=tet_energy(m, s),
            dissipated_viscous=float(s.node_energy_damping.numpy()[:nn].sum()),
        )

    def contact_count(self) -> int:
        """Touching sphere–sphere pairs now (reads back)."""
        return contact_energy(self.model, self.state)[1]
