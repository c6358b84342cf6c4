"""One rank's spheres in a run decomposed in space (issue 25): its owned spheres, their bonds and their ghosts, stepped
as a :class:`~warpdem.parallel.ranked.Ranked` whose halo carries the centres, velocities and spins of the spheres.

The list rebuild is decided by all ranks together. At a rebuild where a sphere has moved more
than the migration margin since the last migration, the spheres migrate to the slab their centre is in, each with its
whole history (the slots keyed by partner id), the ghosts are chosen again, and the slabs are cut again first when the
ranks' measured work differs by more than 10 % (checked at list rebuilds, a migration then taking place).

On the CPU a rank's result is the one-process result bit for bit: a subdomain keeps its spheres sorted by global id
and its grid has the whole run's cells and hash table, so every thread sees the same pairs in the same order and every
force sums in the same order (tests/test_parallel.py holds it).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import warp as wp

from ..kernels import halo as kh
from ..model import NEIGHBOR_FIELDS, Model, State
from ..simulation import regrow_neighbors
from .domain import Slabs
from .ranked import Channel, Ranked
from .rows import Bonds, Rows, bonds_of, fill, rows_of, subdomain, write_rows

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


SPHERE_FIELDS = ("particle_q", "particle_qd", "particle_omega")
"""What the halo refreshes of a ghost sphere: centre, velocity, spin."""


class Subdomain(Ranked):
    """A rank's spheres and ghosts of the whole run ``model``/``state`` (which every rank builds alike), stepped.

    Args:
        comm: the MPI communicator (mpi4py).
        model: the whole run's model, spheres indexed by global id.
        state: the whole run's state.
        primed: the whole state holds its forces (a restart): no evaluation at set-up, the lists kept.
        **kwargs: as :class:`~warpdem.parallel.ranked.Ranked`'s.
    """

    def __init__(self, comm: Any, model: Model, state: State, *, primed: bool = False, **kwargs: Any) -> None:
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
        # Bonds only break (none is made here): the whole run's broken count follows from the intact ones.
        self._bonds_start = len(bonds)
        self._broken_start = int(state.bonds_broken_total.numpy()[0]) - int(
            np.count_nonzero(bonds.fields["bond_broken"])
        )
        local_model, local_state = subdomain(
            template,
            state,
            mine,
            my_bonds,
            model.max_neighbors,
            capacity_for(len(mine)),
            bond_capacity_for(model, len(my_bonds)),
        )
        self._allocate_flags(local_model.particle_capacity, model.device)
        self._adopt(mine.gid, self.slabs.owner(mine.fields["particle_q"]), mine.fields["particle_q"])
        super().__init__(comm, local_model, local_state, 2, primed=primed, **kwargs)

    # ------------------------------------------------------------------------------------------------------------
    def _allocate_flags(self, capacity: int, device: Any) -> None:
        """The per-sphere arrays of the subdomain's own: owned flags, centres at the last migration."""
        self.owned = wp.zeros(capacity, dtype=int, device=device)
        self._q_at_migration = wp.zeros(capacity, dtype=wp.vec3d, device=device)

    def _adopt(self, gid: np.ndarray, owner: np.ndarray, q: np.ndarray) -> None:
        """Take ``gid`` (sorted) as the local spheres, with ``owner`` their ranks and ``q`` their centres (all shape
        (n, ...)): the owned flags, the centres the margin is measured from, and the halo's channel (a sender and a
        receiver decide from the same centres)."""
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
        held_by = [self.slabs.holds(q, d) for d in range(size)]
        self.channels = [Channel.between(SPHERE_FIELDS, np.float64, 1, rank, owner, held_by, self.owned.device)]

    def _setup(self) -> None:
        super()._setup()
        self._lists_kept: list[wp.array] | None = None  # the lists before a rebuild (made at the first)

    def _flag_moved(self) -> None:
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

    def _exchange(self) -> None:
        """The ghosts' positions and velocities from their owners, then what every rank decides together from its
        owned spheres: a list rebuild (one past half the skin since the last), and before it a migration (one past
        the margin since the last, or the ranks' work uneven)."""
        moved = self._halo()
        if moved[0]:
            busy = self._measured_work()
            if moved[1] or busy is not None:
                self._migrate(busy)
            self._rebuild_lists()

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
                self._allocate_flags(cap, m.device)
            self._setup()
        self._adopt(arrived.gid, owner, arrived.fields["particle_q"])
        self.migrations += 1

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

    def owned_part(self) -> tuple[Rows, Bonds, int]:
        return (*self.owned_rows(), int(self.state.nbr_needed.numpy()[0]))

    def write_whole(self, model: Model, state: State, parts: list[tuple[Rows, Bonds, int]]) -> tuple[Model, State]:
        """Every rank's owned spheres and bonds into the whole run's state; the broken-bond count follows from the
        intact bonds (each rank counts the bonds it holds, some twice)."""
        rows = Rows.join([p[0] for p in parts])
        bonds = Bonds.join([p[1] for p in parts])
        k = rows.fields["nbr_shear"].shape[1]
        if k > model.max_neighbors:
            model, state = regrow_neighbors(model, state, k)
        write_rows(model, state, rows, bonds)
        if model.bond_capacity:
            intact = int(np.count_nonzero(bonds.fields["bond_broken"] == 0))
            state.bonds_broken_total.fill_(self._broken_start + self._bonds_start - intact)
        self._share_into(state)
        state.nbr_needed.fill_(max(p[2] for p in parts))
        return model, state
