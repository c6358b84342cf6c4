"""One rank's part of a continuum run decomposed in space (issue 25): Cosserat tets with their FEM nodes, boundary faces
and node–face and node–wall contact, joint elements, pressure loads, non-reflecting dashpots and node drivers; stepped
as a :class:`~warpdem.parallel.ranked.Ranked` whose halo carries the displacements, positions and velocities of the
nodes.

A node belongs to the slab its position lies in when the items are decomposed. A rank holds every tet with a node
within its slab's halo width, with all their nodes (topological ghosts, as GEOS), their boundary faces, the joint
elements and loaded faces on held nodes (warpdem.parallel.items). Forces on ghosts are computed again where they are
held and nothing is sent back. Each step the ranks decide together, from their owned nodes, what one process decides
from all: an FEM list rebuild (a contact node past half the FEM skin since the last build), and before it a new
decomposition (a node past the margin since the last). A new decomposition gathers every rank's owned items on every
rank, into the whole run's state each keeps, and cuts that again.

On the CPU a rank's result is the one-process result bit for bit: every kind of item is kept in global-id order and the
face grid has the whole run's buckets, so an owned node's tets, joint elements, loaded faces and contacts add their
forces in the order one process adds them (tests/test_parallel.py holds it).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from ..kernels import halo as kh
from ..kernels.node_face_list import RIM_REACH
from ..model import Model, State
from ..stages.fem_contact import FemContact, regrow_fem_contacts
from .domain import Slabs
from .items import Ids, Part, face_sets, held_items, live_count, owned_part, take, write_parts
from .ranked import Channel, Ranked

NODE_FIELDS = ("node_u", "node_q", "node_qd")
"""What the halo refreshes of a ghost node: displacement (the tets read it), position (the contacts), velocity."""

MARGIN_SKINS = 2.0
"""How far a node may move from where the items were last decomposed before they are decomposed again, in FEM skins
(a tenth of the longest tet edge where the model has no FEM contact)."""


def fem_reach(model: Model) -> float:
    """The farthest a node's FEM contacts reach [m]: a node–face candidate's search radius
    (warpdem.stages.fem_contact.FemContact ``node_search``), a face's extent from its centroid (twice its reference
    radius: a face stretched that far is still offered), and the FEM skin."""
    node_search = RIM_REACH * model.face_radius + max(model.fem_skin, model.face_depth_max)
    return node_search + 2.0 * model.face_radius + model.fem_skin


def longest_edge(model: Model, state: State) -> float:
    """The longest reference edge of the live tets [m]."""
    nt = live_count(state, "tet")
    x = model.node_ref_q.numpy()[model.tet_nodes.numpy()[:nt]]
    edges = [x[:, a] - x[:, b] for a in range(4) for b in range(a + 1, 4)]
    return float(max(np.linalg.norm(e, axis=1).max(initial=0.0) for e in edges))


def decomposition_margin(model: Model, state: State) -> float:
    """How far a node may move between two decompositions [m] (:data:`MARGIN_SKINS`)."""
    return MARGIN_SKINS * model.fem_skin if model.fem_skin > 0.0 else 0.1 * longest_edge(model, state)


def halo_width(model: Model, state: State) -> float:
    """Ghost width beyond a slab [m]: twice the FEM contacts' reach R, the longest tet edge L and twice the margin.

    An owned node's forces read its own tets (held: a tet with a node in the halo region is, with all its nodes), the
    faces it may touch (within R of it), and the nodes n that touch the faces it is a node of (within R) with their
    own contact springs, which they choose among their own candidate faces (within R of n, 2R of the slab: their tets
    have a node there) by the tets around n and across their faces (with a node within R + L of the slab). Nodes move
    at most the margin from where the items were decomposed, so two of them come at most twice the margin closer.
    Everything an owned node's forces read is then held, with the state one process gives it."""
    return 2.0 * fem_reach(model) + longest_edge(model, state) + 2.0 * decomposition_margin(model, state)


class ContinuumSubdomain(Ranked):
    """A rank's nodes, tets, faces, joint elements and loaded faces of the whole run ``model``/``state`` (which every
    rank builds alike and keeps, the items it does not own as of the last decomposition), stepped.

    Args:
        comm: the MPI communicator (mpi4py).
        model: the whole run's model, items indexed by global id.
        state: the whole run's state.
        primed: the whole state holds its forces (a restart): no evaluation at set-up, the lists kept.
        **kwargs: as :class:`~warpdem.parallel.ranked.Ranked`'s.
    """

    def __init__(self, comm: Any, model: Model, state: State, *, primed: bool = False, **kwargs: Any) -> None:
        self.comm = comm
        self.whole_model, self.whole_state = model, state
        self._noise_depth = 0.0
        if model.face_capacity:
            whole = FemContact(model, state, has_spheres=False)
            if not primed:
                whole.seat_walls()  # what one process does first, over every node
            # The set-up's rounding allowance is the whole run's (from its largest coordinate), not the slab's.
            self._noise_depth = whole.noise_depth
        nj = live_count(state, "joint")
        self._joints_broken_base = int(state.joints_broken_total.numpy()[0]) - int(
            np.count_nonzero(state.joint_broken.numpy()[:nj])
        )
        self._margin = decomposition_margin(model, state)
        self._halo_width = halo_width(model, state)
        local_model, local_state = self._decompose()
        super().__init__(comm, local_model, local_state, 2, primed=primed, **kwargs)
        # A joint element that failed in the last step asks for a list build at the next (kernels/joints.py): what the
        # flag holds after the forces (the set-up's, or a checkpoint's), left here for the next step's decision.
        self._joint_failed = wp.clone(self.state.fem_rebuild_flag)

    # ------------------------------------------------------------------------------------------------------------
    def _decompose(self) -> tuple[Model, State]:
        """Cut the whole run's nodes into slabs of equal counts, and take this rank's items out of the whole run (every
        rank decides every rank's, from the same whole state, so that the halo's sends and receives match). Returns
        the rank's model and state."""
        m, s = self.whole_model, self.whole_state
        rank, size = self.comm.Get_rank(), self.comm.Get_size()
        nn = live_count(s, "node")
        q = s.node_q.numpy()[:nn]
        self.slabs = Slabs.balanced(q, np.ones(nn), size, self._halo_width)
        held = [held_items(m, s, self.slabs, r) for r in range(size)]
        # The largest share of the nodes one rank holds: near 1, the ranks step the whole model each.
        self.held_share = max(len(h.ids["node"]) for h in held) / max(nn, 1)
        mine = held[rank]
        self._ids = Ids(mine, m)
        local_model, local_state = take(m, s, mine)
        owner = self.slabs.owner(q)
        nodes = mine.ids["node"]
        node_owner = owner[nodes]
        held_by = [np.isin(nodes, other.ids["node"]) for other in held]
        self.channels = [Channel.between(NODE_FIELDS, np.float32, 2, rank, node_owner, held_by, m.device)]
        # Who owns what besides the nodes (for output and the next decomposition): a tet, its lowest node's owner; a
        # joint element, its node A's (the lower); a loaded face, its first node's. Each holds the item whole.
        loaded = [faces.nodes.numpy()[mine.sets[key], 0] for key, faces in face_sets(m.loads) if key != "dashpots"]
        owners = {
            "node": node_owner,
            "tet": owner[m.tet_nodes.numpy()[mine.ids["tet"]].min(axis=1)] if len(mine.ids["tet"]) else node_owner[:0],
            "joint": owner[m.joint_a.numpy()[mine.ids["joint"]]],
            "load_face": owner[np.concatenate(loaded)] if loaded else node_owner[:0],
        }
        self._owned = {space: np.flatnonzero(o == rank) for space, o in owners.items()}
        self.owned = wp.array((node_owner == rank).astype(np.int32), dtype=int, device=m.device)
        self._q_at_decomposition = wp.clone(local_state.node_q)
        return local_model, local_state

    def _setup(self) -> None:
        super()._setup()
        if self.fem_contact is not None:
            self.fem_contact.noise_depth = self._noise_depth

    def _flag_moved(self) -> None:
        m, s = self.model, self.state
        self._moved.zero_()
        wp.launch(
            kh.owned_nodes_moved_kernel,
            dim=m.node_capacity,
            inputs=[
                0.5 * m.fem_skin if m.face_capacity else -1.0,
                self._margin,
                m.node_contact_stiffness,
                s.node_count,
                self.owned,
                s.node_q,
                s.node_q_at_fem_build,
                self._q_at_decomposition,
                self._joint_failed,
            ],
            outputs=[self._moved],
            device=m.device,
        )
        s.fem_rebuild_flag.zero_()

    def _forces(self) -> None:
        super()._forces()
        # What is left of the build flag after the forces is the joint elements' (the step's own build lowered the
        # rest): kept for the next step's decision, since the drift raises the flag for ghosts too.
        wp.copy(self._joint_failed, self.state.fem_rebuild_flag)

    def _exchange(self) -> None:
        """The ghosts' displacements, positions and velocities from their owners, then what every rank decides
        together from its owned nodes: a new decomposition (a node past the margin), an FEM list rebuild (a contact
        node past half the FEM skin)."""
        moved = self._halo()
        if moved[1]:
            self._redecompose()
        if moved[0]:
            self._rebuild_fem_lists()

    def _redecompose(self) -> None:
        """Every rank's owned items into every rank's whole run, and the items decomposed again from it."""
        parts = self.comm.allgather(self.owned_part())
        self.whole_model, self.whole_state = self.write_whole(self.whole_model, self.whole_state, parts)
        self.model, self.state = self._decompose()
        self._setup()
        self.migrations += 1

    def _rebuild_fem_lists(self) -> None:
        """Rebuild the FEM lists now (the step's own rebuild, taken out of its graph so that its count can be read):
        where any rank's overflowed, every rank grows its slots and builds again (a one-process run redoes the steps
        from its snapshot instead; both end with the lists the larger slots would have built, counted once)."""
        from mpi4py import MPI

        builds = int(self.state.fem_rebuild_total.numpy()[0])
        while True:
            self.fem_contact.rebuild()
            needed = self.comm.allreduce(self._needs(), op=MPI.MAX)
            k = self.model.max_node_faces
            if needed <= k:
                return
            while k < needed:
                k *= 2
            self.model, self.state = regrow_fem_contacts(self.model, self.state, self.model.max_sphere_faces, k)
            self.state.fem_rebuild_total.fill_(builds)
            self._setup()
            self.growths += 1

    def _epilogue(self) -> None:
        fem = self.fem_contact
        if fem is not None:
            wp.launch(
                kh.forget_ghost_records_kernel,
                dim=self.model.node_capacity,
                inputs=[self.state.node_count, self.owned],
                outputs=[fem.node_passed],
                device=self.model.device,
            )
        super()._epilogue()

    # ------------------------------------------------------------------------------------------------------------
    def owned_part(self) -> Part:
        part = owned_part(self.model, self.state, self._ids, self._owned)
        part.needs = self._needs()
        part.rebuild = int(self._joint_failed.numpy()[0])
        return part

    def _needs(self) -> int:
        """The most candidate faces a node of this rank's needed at a list build (reads back)."""
        return int(self.state.node_face_needed.numpy()[0])

    def write_whole(self, model: Model, state: State, parts: list[Part]) -> tuple[Model, State]:
        """Every rank's owned items into the whole run's state (its node–face slots grown to the widest part's), the
        clock and counters every rank shares from this rank's; the failed joint elements counted from their flags
        (each rank counts those it holds, some twice)."""
        k = max(p.fields["node_face_index"].shape[1] for p in parts)
        if k > model.max_node_faces:
            model, state = regrow_fem_contacts(model, state, model.max_sphere_faces, k)
        write_parts(model, state, parts)
        self._share_into(state)
        state.node_face_needed.fill_(max(p.needs for p in parts))
        state.fem_rebuild_flag.fill_(max(p.rebuild for p in parts))
        nj = live_count(state, "joint")
        state.joints_broken_total.fill_(
            self._joints_broken_base + int(np.count_nonzero(state.joint_broken.numpy()[:nj]))
        )
        return model, state
