"""One rank's part of a run decomposed in space (issue 25): its owned spheres and their ghosts, stepped as a
:class:`~warpdem.simulation.Simulation` with a forward halo message between the drift and the forces.

Per step (DESIGN.md, "Scale"): after the drift each rank sends the centres, velocities and spins of its owned spheres
that others hold as ghosts, one message per neighbour; forces on ghosts are computed again where they are held
("newton off"), nothing is sent back; the same message carries the reduction of the owned spheres' skin tests, so the
ranks meet once a step. The list rebuild is decided by all ranks together. At a rebuild where a sphere has moved more
than the migration margin since the last migration, the spheres migrate to the slab their centre is in, each with its
whole history (the slots keyed by partner id), the ghosts are chosen again, and the slabs are cut again first when the
ranks' measured work differs by more than 10 % (checked at list rebuilds, a migration then taking place).

On the CPU a rank's result is the one-process result bit for bit: a subdomain keeps its spheres sorted by global id
and its grid has the whole run's cells and hash table, so every thread sees the same pairs in the same order and every
force sums in the same order (tests/test_parallel.py holds it).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
import warp as wp

from ..kernels import halo as kh
from ..model import NEIGHBOR_FIELDS, Model, State
from ..simulation import Simulation, regrow_neighbors
from ..stages.guard import UnstableRunError
from ..stages.integrate import integrate_first_half, kick_drift
from .domain import Slabs
from .rows import Bonds, Rows, bonds_of, fill, rows_of, subdomain

IMBALANCE = 1.10
"""Largest rank's measured step work over the mean before the slabs are cut again (at a list rebuild)."""

MEASURED = 0.25
"""Seconds of step work each rank must have measured before the ranks' work is compared: less is noise."""

HEADROOM = 1.25
"""Sphere slots a subdomain allocates per sphere it holds, so that migrations fill its arrays in place (no new arrays,
the step's recorded graphs kept) until it holds more."""

MARGIN_SKINS = 2.0
"""How far a sphere may move from where it last migrated before the spheres migrate again (at the next list rebuild),
in skins: the lists are rebuilt every half skin of motion, the spheres migrate (and the ghosts are chosen again) about
every fourth time."""


def capacity_for(n: int) -> int:
    """Sphere slots for a subdomain of ``n`` spheres (:data:`HEADROOM`, at least 16)."""
    return max(16, int(HEADROOM * n) + 1)


def migration_margin(model: Model) -> float:
    """How far a sphere may move between migrations [m] (:data:`MARGIN_SKINS` skins)."""
    return MARGIN_SKINS * model.skin


def halo_width(model: Model, longest_bond: float = 0.0) -> float:
    """Ghost width beyond a slab [m]: max(2 r_max, the longest bond's rest length) + 2 skin + 2 margin.

    The spheres migrate at a list rebuild where one has moved more than the margin since the last migration; between
    two rebuilds each moves less than half the skin, so until a migration none is further than margin + skin/2 from
    where it migrated. A pair a list may hold is closer than r_i + r_j + skin ≤ 2 r_max + skin when the list is built,
    so its partner was within 2 r_max + skin + 2 (margin + skin/2) of the owned sphere's slab at the migration: it is
    held. A subdomain made between two builds (a restart) holds the pairs of the lists it inherits too (closer than
    2 r_max + 2 skin). A bond's two spheres lie within its rest length plus the skin of each other (it breaks first),
    so the bonds of an owned sphere are held whole too."""
    reach = max(2.0 * model.max_radius, longest_bond)
    return reach + 2.0 * model.skin + 2.0 * migration_margin(model)


def bond_capacity_for(model: Model, n: int) -> int:
    """Bond slots for a subdomain of ``n`` bonds: none where the model has none, else as :func:`capacity_for`."""
    return capacity_for(n) if model.bond_capacity else 0


class Subdomain(Simulation):
    """A rank's spheres and ghosts of the whole run ``model``/``state`` (which every rank builds alike), stepped.

    Args:
        comm: the MPI communicator (mpi4py).
        model: the whole run's model, spheres indexed by global id.
        state: the whole run's state.
        primed: the whole state holds its forces (a restart): no evaluation at set-up, the lists kept.
        **kwargs: as :class:`~warpdem.simulation.Simulation`'s. A step is not one recorded graph here: the halo runs
            on the host between its two halves, each recorded after its first eager run (:meth:`_body`).
    """

    def __init__(self, comm: Any, model: Model, state: State, *, primed: bool = False, **kwargs: Any) -> None:
        if model.device.is_cuda:
            raise NotImplementedError("a decomposed run on CUDA devices is not built yet: run its ranks on the CPU")
        self.comm = comm
        n = int(state.particle_count.numpy()[0])
        q = state.particle_q.numpy()[:n]
        whole = np.arange(n)
        # The whole run's largest radius and sphere capacity: every rank's grid has the whole run's cells and buckets.
        template = dataclasses.replace(model, radius_bound=model.max_radius, grid_owners=model.particle_capacity)
        bonds = bonds_of(state, whole)
        longest = float(bonds.fields["bond_rest_length"].max()) if len(bonds) else 0.0
        self.slabs = Slabs.balanced(q, np.ones(n), comm.Get_size(), halo_width(template, longest))
        held = self.slabs.holds(q, comm.Get_rank())
        mine = rows_of(template, state, whole, np.flatnonzero(held))
        my_bonds = bonds.take(held[bonds.ends[:, 0]] & held[bonds.ends[:, 1]])
        self._moved = wp.zeros(2, dtype=int, device=model.device)
        self._views_of: State | None = None
        self._busy = 0.0  # seconds of this rank's own step work since the ranks' work was last compared
        self._slowest = -1  # the rank found slowest at that comparison (-1: none)
        local_model, local_state = subdomain(
            template,
            state,
            mine,
            my_bonds,
            model.max_neighbors,
            capacity_for(len(mine)),
            bond_capacity_for(model, len(my_bonds)),
        )
        self._allocate_flags(local_model.particle_capacity)
        self._adopt(mine.gid, self.slabs.owner(mine.fields["particle_q"]), mine.fields["particle_q"])
        super().__init__(local_model, local_state, use_graph=False, primed=primed, **kwargs)

    # ------------------------------------------------------------------------------------------------------------
    def _allocate_flags(self, capacity: int) -> None:
        """The per-sphere arrays of the subdomain's own: owned flags, centres at the last migration."""
        device = self._moved.device
        self.owned = wp.zeros(capacity, dtype=int, device=device)
        self._q_at_migration = wp.zeros(capacity, dtype=wp.vec3d, device=device)

    def _adopt(self, gid: np.ndarray, owner: np.ndarray, q: np.ndarray) -> None:
        """Take ``gid`` (sorted) as the local spheres, with ``owner`` their ranks and ``q`` their centres (all shape
        (n, ...)): the owned flags, the centres the margin is measured from, and the halo's send and receive lists
        (local indices in global-id order on both sides; a sender and a receiver decide from the same centres)."""
        rank, size = self.comm.Get_rank(), self.comm.Get_size()
        self.gid = gid
        owned = owner == rank
        flags = np.zeros(self.owned.shape[0], dtype=np.int32)
        flags[: len(gid)] = owned
        self.owned.assign(flags)
        at = np.zeros((self.owned.shape[0], 3))
        at[: len(gid)] = q
        self._q_at_migration.assign(at)
        self._owned_host = owned
        recv = {src: np.flatnonzero(owner == src) for src in range(size) if src != rank}
        self._recv = {src: idx for src, idx in recv.items() if len(idx)}
        mine = np.flatnonzero(owned)
        send = {d: mine[self.slabs.holds(q[mine], d)] for d in range(size) if d != rank}
        self._send = {d: idx for d, idx in send.items() if len(idx)}
        # The halo's message buffers, made once per migration.
        self._outbox = {d: np.empty((len(idx), 9)) for d, idx in self._send.items()}
        self._inbox = {src: np.empty((len(idx), 9)) for src, idx in self._recv.items()}

    def _setup(self) -> None:
        super()._setup()
        self._halves: tuple | None = None  # new arrays: the recorded halves are recorded again
        self._lists_kept: list[wp.array] | None = None  # the lists before a rebuild (made at the first)

    def _flag_moved(self) -> None:
        """The skin and margin tests over owned spheres into ``_moved``, and the drift's own flag lowered (a ghost's
        drift on a partial force may have raised it; the rebuild is decided together, :meth:`_exchange`). Launches
        only."""
        m, s = self.model, self.state
        self._moved.zero_()
        wp.launch(
            kh.owned_moved_kernel,
            dim=m.particle_capacity,
            inputs=[
                0.5 * m.skin,
                migration_margin(m),
                s.particle_count,
                self.owned,
                s.particle_q,
                s.particle_q_at_build,
                self._q_at_migration,
            ],
            outputs=[self._moved],
            device=m.device,
        )
        s.rebuild_flag.zero_()

    def _drift_half(self) -> None:
        """A step's launches before the halo: kick, drift, the skin test."""
        kick_drift(self.model, self.state, self.track_energy, self.drift_nodes)
        self._flag_moved()

    def _head(self) -> None:
        integrate_first_half(self.model, self.state, self.track_energy, self.drift_nodes)
        self._flag_moved()
        self._exchange()
        self._forces()

    def _body(self) -> None:
        halves = self._halves
        start = time.perf_counter()
        if halves is None:
            self._drift_half()
        else:
            wp.capture_launch(halves[0])
        self._busy += time.perf_counter() - start
        self._exchange()
        start = time.perf_counter()
        if self._halves is None:  # none yet, or a growth dropped them
            self._forces()
            self._record_halves()
        else:
            wp.capture_launch(self._halves[1])
        # The rank's own work (its kernels run on this thread on the CPU), not its waits: the measured cost the slabs
        # are balanced by.
        self._busy += time.perf_counter() - start

    def _record_halves(self) -> None:
        """Record the two halves of a step (after an eager run of each, so every kernel is compiled)."""
        graphs = []
        for part in (self._drift_half, self._forces):
            with wp.ScopedCapture(device=self.model.device) as capture:
                part()
            graphs.append(capture.graph)
        self._halves = tuple(graphs)

    def _exchange(self) -> None:
        """Between the drift and the forces: the ghosts' positions and velocities from their owners, then what every
        rank decides together from its owned spheres: a list rebuild (one past half the skin since the last), and
        before it a migration (one past the margin since the last)."""
        moved = self._halo()
        if moved[0]:
            busy = self._measured_work()
            if moved[1] or busy is not None:
                self._migrate(busy)
            self._rebuild_lists()

    def _measured_work(self) -> np.ndarray | None:
        """At a list rebuild: every rank's measured step work since the last decision [s] (the same figures on every
        rank) when the same rank's exceeded the mean by more than :data:`IMBALANCE` twice running, so that the slabs
        are cut again; None when they are even, when too little was measured to tell (under :data:`MEASURED` on some
        rank), or on the first uneven window (a 2-core machine's timings wander by ±20 % between windows of one cut:
        one window alone would cut the slabs back and forth)."""
        busy = np.array(self.comm.allgather(self._busy))
        if busy.min() < MEASURED:
            return None
        self._busy = 0.0
        slowest = int(np.argmax(busy)) if busy.max() > IMBALANCE * busy.mean() else -1
        confirmed = slowest >= 0 and slowest == self._slowest
        self._slowest = -1 if confirmed else slowest
        return busy if confirmed else None

    def _halo(self) -> np.ndarray:
        """One message to each rank that holds owned spheres as ghosts: centres, velocities, spins (float64 rows of 9;
        float32 values go through float64 exactly); with it, one reduction of the owned spheres' skin and margin
        tests, whose result it returns (shape (2,): list rebuild, migration due). One wait for both, so the ranks meet
        once a step."""
        from mpi4py import MPI

        q, v, w, flags = self._host_views()
        moved = np.zeros(2, dtype=np.int32)
        requests = [self.comm.Iallreduce(flags, moved, op=MPI.MAX)]
        for src, block in self._inbox.items():
            requests.append(self.comm.Irecv(block, source=src, tag=1))
        for dest, idx in self._send.items():
            block = self._outbox[dest]
            block[:, 0:3] = q[idx]
            block[:, 3:6] = v[idx]
            block[:, 6:9] = w[idx]
            requests.append(self.comm.Isend(block, dest=dest, tag=1))
        MPI.Request.Waitall(requests)
        for src, idx in self._recv.items():
            block = self._inbox[src]
            q[idx] = block[:, 0:3]
            v[idx] = block[:, 3:6]
            w[idx] = block[:, 6:9]
        return moved

    def _host_views(self) -> tuple[np.ndarray, ...]:
        """The host views of the arrays the halo reads and writes (on the CPU the arrays themselves; made once per
        State, as a view costs tens of microseconds to make)."""
        s = self.state
        if self._views_of is not s:
            self._views = (s.particle_q.numpy(), s.particle_qd.numpy(), s.particle_omega.numpy(), self._moved.numpy())
            self._views_of = s
        return self._views

    def _rebalance(self, q_owned: np.ndarray, busy: np.ndarray) -> None:
        """Cut the slabs again by the ranks' measured work ``busy`` [s] (shape (ranks,), the same on every rank): each
        owned sphere weighs its rank's work over its owned count, so a slab that took longer gives up spheres in
        proportion."""
        share = busy[self.comm.Get_rank()] / max(len(q_owned), 1)
        q_all = np.concatenate(self.comm.allgather(q_owned))
        w_all = np.concatenate(self.comm.allgather(np.full(len(q_owned), share)))
        balanced = Slabs.balanced(q_all, w_all, len(busy), self.slabs.halo)
        if balanced.axis == self.slabs.axis:
            # Half way to the cuts the measurement asks for: the measurement is noisy and each cut costs a migration.
            cuts = tuple(0.5 * (a + b) for a, b in zip(self.slabs.cuts, balanced.cuts, strict=True))
            balanced = Slabs(balanced.axis, cuts, balanced.halo)
        self.slabs = balanced

    def _migrate(self, busy: np.ndarray | None = None) -> None:
        """Owned spheres (with their lists) to every rank that holds them by the slabs (cut again first by the ranks'
        measured work ``busy`` where given, :meth:`_measured_work`), and the subdomain made of what arrives: in its
        own arrays where they hold it."""
        m, s = self.model, self.state
        size = self.comm.Get_size()
        owned = np.flatnonzero(self._owned_host)
        rows = rows_of(m, s, self.gid, owned)
        q = rows.fields["particle_q"]
        if busy is not None:
            self._rebalance(q, busy)
        rows.fields["rank"] = self.slabs.owner(q)
        # A bond goes with its lower sphere's owner, to every rank that holds both its spheres.
        bonds, ends = self._owned_bonds()
        q_local = s.particle_q.numpy()
        lower_q, upper_q = q_local[ends[:, 0]], q_local[ends[:, 1]]
        outgoing = [
            (rows.take(self.slabs.holds(q, d)), bonds.take(self.slabs.holds(lower_q, d) & self.slabs.holds(upper_q, d)))
            for d in range(size)
        ]
        parts = self.comm.alltoall(outgoing)
        arrived = Rows.join([p[0] for p in parts])
        arrived_bonds = Bonds.join([p[1] for p in parts])
        owner = arrived.fields.pop("rank")
        if len(arrived) <= m.particle_capacity and len(arrived_bonds) <= m.bond_capacity:
            fill(m, s, arrived, arrived_bonds)  # in place: the recorded halves stay valid
        else:
            cap = max(m.particle_capacity, capacity_for(len(arrived)))
            bond_cap = max(m.bond_capacity, bond_capacity_for(m, len(arrived_bonds)))
            self.model, self.state = subdomain(m, s, arrived, arrived_bonds, m.max_neighbors, cap, bond_cap)
            if cap != self.owned.shape[0]:
                self._allocate_flags(cap)
            self._setup()
        self._adopt(arrived.gid, owner, arrived.fields["particle_q"])

    def _rebuild_lists(self) -> None:
        """Rebuild the lists now (the step's own rebuild, taken out of its graph so that its count can be read): where
        any rank's overflowed, every rank grows its slots and builds again from the lists as they were (a one-process
        run redoes the steps from its snapshot instead; both end with the lists the larger slots would have built)."""
        from mpi4py import MPI

        names = ("nbr_count", *NEIGHBOR_FIELDS, "rebuild_total")
        while True:
            if self._lists_kept is None:  # once per set of arrays: a rebuild copies, it does not allocate
                self._lists_kept = [wp.empty_like(getattr(self.state, name)) for name in names]
            for name, kept in zip(names, self._lists_kept, strict=True):
                wp.copy(kept, getattr(self.state, name))
            self.neighbors.rebuild()
            needed = self.comm.allreduce(int(self.state.nbr_needed.numpy()[0]), op=MPI.MAX)
            k = self.model.max_neighbors
            if needed <= k:
                return
            for name, kept in zip(names, self._lists_kept, strict=True):
                wp.copy(getattr(self.state, name), kept)
            while k < needed:
                k *= 2
            self.model, self.state = regrow_neighbors(self.model, self.state, k)
            self._setup()
            self.growths += 1

    def _advance_chunk(self, n_steps: int) -> int:
        """n steps, then the status read: the guard's verdict is every rank's (one rank's bad sphere stops all)."""
        self._run(n_steps)
        self._epilogue()
        status = self.status.read()
        self.step_count += n_steps
        self.time = status.time
        report = self.guard.interpret(status.guard)
        from mpi4py import MPI

        if self.comm.allreduce(report is not None, op=MPI.LOR):
            if report is not None:
                raise self.guard.error(self.model, self.state, report, self.step_count, self.time)
            raise UnstableRunError(
                self.time, self.step_count, "another rank's spheres", "see the first rank's message", ""
            )
        # Broken bonds compacted away at the chunk's end, as in one process (every rank sees the same bonds break).
        self.remove_broken_bonds(status.bonds_broken)
        return 0

    def halo_bytes(self) -> int:
        """Bytes this rank sends in a step's halo messages (9 float64 a ghost it feeds)."""
        return sum(72 * len(idx) for idx in self._send.values())

    def _owned_bonds(self) -> tuple[Bonds, np.ndarray]:
        """The bonds whose lower sphere this rank owns (each bond is sent or gathered by that rank only), and their
        two spheres' local indices, shape (n, 2)."""
        bonds = bonds_of(self.state, self.gid)
        ends = np.searchsorted(self.gid, bonds.ends)
        mine = self._owned_host[ends[:, 0]]
        return bonds.take(mine), ends[mine]

    def owned_rows(self) -> tuple[Rows, Bonds]:
        """The rows of the spheres this rank owns (global ids, whole histories), and the bonds whose lower sphere it
        owns."""
        return rows_of(self.model, self.state, self.gid, np.flatnonzero(self._owned_host)), self._owned_bonds()[0]
