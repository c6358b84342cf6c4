"""Topology of the tet mesh (host side): the node → tet stars, tet face neighbours and node duplication that joints
(build time, warpdem.stages.joints) and nodal fracture (run time, warpdem.stages.fracture) both use; the kernels and the
conventions are in :mod:`warpdem.kernels.topology`.

Node duplication is a compaction pass on the device (:class:`warpdem.stages.compaction.Compactor`'s append pass): every
node says how many copies it needs (one per extra component of its star) → exclusive scan → first new slot of each
→ :meth:`~warpdem.stages.compaction.Compactor.replicate` copies every per-node array (:func:`node_arrays`) into the new
slots → masses re-lumped from each component's own tets (Σ ρV₀/4, so the total is unchanged) → tets and face lists
remapped onto the node of their component.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
import warp as wp

from ..fused import WordTable
from ..kernels import topology as kt
from ..model import Model, State
from .compaction import Compactor

# ----------------------------------------------------------------------------------------------------------------
# Node → tet adjacency


class NodeStars:
    """The star of every node (live, active tets holding it) as a CSR on the device, sorted per node.

    Args:
        node_capacity: size of the node arrays.
        tet_capacity: size of the tet arrays.
        device: Warp device.
    """

    def __init__(self, node_capacity: int, tet_capacity: int, device: wp.context.Device) -> None:
        self.device = device
        self.count = wp.zeros(max(node_capacity, 1), dtype=int, device=device)
        self.offset = wp.zeros(max(node_capacity, 1), dtype=int, device=device)
        self.fill = wp.zeros(max(node_capacity, 1), dtype=int, device=device)
        self.tets = wp.zeros(max(4 * tet_capacity, 1), dtype=int, device=device)
        self.tet_face_nbr = wp.full(max(4 * tet_capacity, 1), -1, dtype=int, device=device)

    def build(
        self,
        tet_nodes: wp.array,
        tet_count: wp.array,
        tet_active: wp.array,
        node_count: wp.array,
        face_neighbors: bool = True,
        ref_face_nbr: wp.array | None = None,
    ) -> None:
        """Count → exclusive scan → fill → sort, then (unless ``face_neighbors`` is False) the face neighbours of every
        tet (launches only). Given the unsplit adjacency (``Model.ref_tet_face_nbr``), a face's neighbour is its
        unsplit one where that still holds the face's nodes (four lookups per tet instead of a star search)."""
        d = self.device
        tcap = tet_nodes.shape[0]
        self.count.zero_()
        self.fill.zero_()
        if tcap == 0:
            return
        wp.launch(
            kt.count_node_tets_kernel,
            dim=tcap,
            inputs=[tet_nodes, tet_count, tet_active],
            outputs=[self.count],
            device=d,
        )
        wp.utils.array_scan(self.count, self.offset, inclusive=False)
        wp.launch(
            kt.fill_node_tets_kernel,
            dim=tcap,
            inputs=[tet_nodes, tet_count, tet_active, self.offset],
            outputs=[self.fill, self.tets],
            device=d,
        )
        wp.launch(
            kt.sort_node_tets_kernel,
            dim=self.count.shape[0],
            inputs=[node_count, self.offset, self.count],
            outputs=[self.tets],
            device=d,
        )
        if not face_neighbors:
            return
        if ref_face_nbr is not None:
            wp.launch(
                kt.tet_face_neighbors_from_ref_kernel,
                dim=tcap,
                inputs=[tet_nodes, ref_face_nbr, tet_count, tet_active],
                outputs=[self.tet_face_nbr],
                device=d,
            )
            return
        wp.launch(
            kt.tet_face_neighbors_kernel,
            dim=tcap,
            inputs=[tet_nodes, tet_count, tet_active, self.offset, self.count, self.tets],
            outputs=[self.tet_face_nbr],
            device=d,
        )

    def csr(self) -> list[wp.array]:
        """(offset, count, tets): the arguments kernels take for a star lookup."""
        return [self.offset, self.count, self.tets]


# ----------------------------------------------------------------------------------------------------------------
# The split pass


def node_arrays(obj: object, node_capacity: int) -> list[wp.array]:
    """Per-node arrays of a Model or State to carry into new node slots: fields ``node_*`` of length node_capacity,
    except the energy accumulators (a new node has dissipated nothing yet)."""
    out = []
    for f in dataclasses.fields(obj):
        a = getattr(obj, f.name)
        if not (f.name.startswith("node_") and isinstance(a, wp.array)):
            continue
        if a.ndim == 1 and a.shape[0] == node_capacity and not f.name.startswith("node_energy"):
            out.append(a)
    return out


def node_rows(model: Model, state: State) -> list[tuple[wp.array, int]]:
    """Per-node rows of a State to carry into new node slots, with their row length: the fields of
    :data:`NODE_ROW_FIELDS` with more than one slot per node (a node's wall springs with several walls; a row of one
    slot is a per-node array, which :func:`node_arrays` lists)."""
    out = []
    for name, per in NODE_ROW_FIELDS.items():
        a, k = getattr(state, name, None), int(getattr(model, per))
        if isinstance(a, wp.array) and k > 1 and a.shape[0] == k * model.node_capacity:
            out.append((a, k))
    return out


def carried_node_rows(
    model: Model, state: State, extra_node_arrays: Sequence[wp.array] = ()
) -> list[tuple[wp.array, int]]:
    """Every per-node array a split carries into the daughters' slots, with its row length (:func:`node_arrays` of
    the model and the state, ``extra_node_arrays``, then :func:`node_rows`): the set one fused launch replicates."""
    single = node_arrays(model, model.node_capacity) + node_arrays(state, model.node_capacity) + list(extra_node_arrays)
    return [(a, 1) for a in single] + node_rows(model, state)


class NodeSplitter:
    """Splits nodes whose star the tagged faces cut into several components (module docstring, steps 1–5).

    Args:
        node_capacity: size of the node arrays.
        tet_capacity: size of the tet arrays.
        device: Warp device.
    """

    def __init__(self, node_capacity: int, tet_capacity: int, device: wp.context.Device) -> None:
        self.device = device
        self.node_capacity = node_capacity
        self.stars = NodeStars(node_capacity, tet_capacity, device)
        self.star_comp = wp.zeros(max(4 * tet_capacity, 1), dtype=int, device=device)
        self.copies = wp.zeros(max(node_capacity, 1), dtype=int, device=device)
        self.compactor = Compactor(node_capacity, device)

    def plan(
        self,
        tet_nodes: wp.array,
        tet_count: wp.array,
        tet_active: wp.array,
        node_count: wp.array,
        tet_face_joint: wp.array,
    ) -> wp.array:
        """Build the stars, label their components across the tagged faces and plan the new slots.

        Args:
            tet_face_joint: joint set of each tet-face slot 4t + k, -1 where none, shape (4 tet_capacity,).

        Returns:
            The node count after the split, shape (1,) (may exceed the capacity: grow and redo).
        """
        self.stars.build(tet_nodes, tet_count, tet_active, node_count)
        if self.node_capacity:
            wp.launch(
                kt.label_star_components_kernel,
                dim=self.node_capacity,
                inputs=[tet_nodes, node_count, *self.stars.csr(), self.stars.tet_face_nbr, tet_face_joint],
                outputs=[self.star_comp, self.copies],
                device=self.device,
            )
        self.compactor.plan_append(node_count, self.copies)
        return self.compactor.new_count

    def new_node_count(self) -> int:
        """Node count after the planned split (reads back)."""
        return int(self.compactor.new_count.numpy()[0])

    def split_args(self) -> list[wp.array]:
        """Star CSR, components and first new slots: what a kernel needs to find the node a tet holds after the
        split (``split_node_index``)."""
        return [*self.stars.csr(), self.star_comp, self.compactor.first_new]

    def remap_faces(self, tet_nodes: wp.array, faces: wp.array) -> None:
        """Rewrite a face list (vec3i, pre-split ids) onto the nodes of the tet holding each face. Call before
        :meth:`apply` (it reads the tets' pre-split nodes)."""
        if faces.shape[0]:
            wp.launch(
                kt.remap_split_faces_kernel,
                dim=faces.shape[0],
                inputs=[tet_nodes, *self.split_args()],
                outputs=[faces],
                device=self.device,
            )

    def apply(self, model: Model, state: State, extra_node_arrays: Sequence[wp.array] = ()) -> None:
        """Carry out the planned split in place: replicate every per-node array into the new slots, re-lump the
        masses, remap the tets and set the node count. The new count must fit the capacity."""
        m, s = model, state
        self.compactor.replicate_rows(s.node_count, carried_node_rows(m, s, extra_node_arrays))
        if m.node_capacity:
            wp.launch(
                kt.relump_split_nodes_kernel,
                dim=m.node_capacity,
                inputs=[
                    m.tet_volume,
                    m.tet_material,
                    m.tet_material_table,
                    s.node_count,
                    *self.stars.csr(),
                    self.star_comp,
                    self.copies,
                    self.compactor.first_new,
                ],
                outputs=[m.node_mass, m.node_inv_mass, m.node_damping],
                device=self.device,
            )
        if m.tet_capacity:
            wp.launch(
                kt.remap_split_tets_kernel,
                dim=m.tet_capacity,
                inputs=[s.tet_count, s.tet_active, *self.split_args()],
                outputs=[m.tet_nodes],
                device=self.device,
            )
        self.compactor.finish(s.node_count)

    # --------------------------------------------------------------------------------------------------------
    # Independent sets (nodal fracture): every split node has two sides, star_comp 0 (A, keeps the node) or 1 (B),
    # set by the caller for the split nodes' stars (0 everywhere else), copies[v] = 1 for them; no tet holds two.

    def plan_sides(self, node_count: wp.array) -> wp.array:
        """Plan the new slots of the nodes with ``copies`` = 1 (exclusive scan). Returns the count after the split."""
        self.compactor.plan_append(node_count, self.copies)
        return self.compactor.new_count

    def remap_face_list_sides(self, tet_nodes: wp.array, faces: wp.array) -> None:
        """Rewrite a face list (vec3i, current ids) onto the daughters of its tet's side; before :meth:`apply_sides`."""
        if faces.shape[0]:
            wp.launch(
                kt.remap_split_face_list_kernel,
                dim=faces.shape[0],
                inputs=[tet_nodes, *self.split_args()[:4], self.copies, self.compactor.first_new],
                outputs=[faces],
                device=self.device,
            )

    def hand_over(
        self,
        ref_tet_face_nbr: wp.array,
        count: wp.array,
        tet_face: wp.array,
        a: wp.array,
        b: wp.array,
    ) -> None:
        """Give each element (cohesive or joint: nodes a, b, face slot on A's side ``tet_face``) to the daughters on
        the sides of its representative tets (kernels/topology.py ``hand_over_elements_kernel``)."""
        if a.shape[0]:
            wp.launch(
                kt.hand_over_elements_kernel,
                dim=a.shape[0],
                inputs=[
                    ref_tet_face_nbr,
                    count,
                    tet_face,
                    *self.split_args()[:4],
                    self.copies,
                    self.compactor.first_new,
                ],
                outputs=[a, b],
                device=self.device,
            )

    def sides_table(self, model: Model, state: State, extra_node_arrays: Sequence[wp.array] = ()) -> WordTable:
        """The word table :meth:`apply_sides` replicates through, built now if not kept (Compactor.rows_table)."""
        return self.compactor.rows_table(carried_node_rows(model, state, extra_node_arrays))

    def apply_sides(self, model: Model, state: State, extra_node_arrays: Sequence[wp.array] = ()) -> None:
        """Carry out a planned independent-set split in place: replicate every per-node array into the new slots,
        re-lump both sides' masses, move the + side's tets onto B and set the node count."""
        m, s = model, state
        self.compactor.replicate_rows(s.node_count, carried_node_rows(m, s, extra_node_arrays))
        if m.node_capacity == 0:
            return
        wp.launch(
            kt.relump_split_nodes_kernel,
            dim=m.node_capacity,
            inputs=[
                m.tet_volume,
                m.tet_material,
                m.tet_material_table,
                s.node_count,
                *self.stars.csr(),
                self.star_comp,
                self.copies,
                self.compactor.first_new,
            ],
            outputs=[m.node_mass, m.node_inv_mass, m.node_damping],
            device=self.device,
        )
        wp.launch(
            kt.remap_split_star_tets_kernel,
            dim=m.node_capacity,
            inputs=[*self.split_args()[:4], self.copies, self.compactor.first_new, m.node_capacity],
            outputs=[m.tet_nodes],
            device=self.device,
        )
        self.compactor.finish(s.node_count)


# ----------------------------------------------------------------------------------------------------------------
# The unsplit adjacency and node growth


def reference_face_neighbors(model: Model, state: State) -> wp.array:
    """The tet across each tet-face slot in the unsplit mesh, -1 on its outer surface, shape (4 tet_capacity,), int32
    (the Model field ``ref_tet_face_nbr``). Faces are matched through the nodes' reference positions, which daughters
    share bit for bit, so the result is the same before and after any joints or cracks split the nodes; tet slots
    never move, so it stays valid for the rest of the run. Build time (one host ``np.unique`` of the positions)."""
    d = model.device
    nn, nt = int(state.node_count.numpy()[0]), int(state.tet_count.numpy()[0])
    out = NodeStars(nn, model.tet_capacity, d)
    if nt == 0:
        return out.tet_face_nbr
    _, root = np.unique(model.node_ref_q.numpy()[:nn], axis=0, return_inverse=True)
    tets = model.tet_nodes.numpy().copy()
    tets[:nt] = root.reshape(-1)[tets[:nt]]
    out.build(wp.array(tets, dtype=wp.vec4i, device=d), state.tet_count, state.tet_active, state.node_count)
    return out.tet_face_nbr


NODE_ROW_FIELDS = {
    "node_face_index": "max_node_faces",
    "node_wall_shear": "num_walls",
    "node_face_spring": "node_springs",
    "node_face_offset": "node_springs",
    "node_face_shear": "node_springs",
}
"""State fields with a row of slots per node: the Model attribute that says how many."""

NODE_SCALARS = {"node_count", "node_face_needed", "node_splits_total"}
"""Fields named ``node_*`` that are counters of shape (1,), not per-node arrays."""

NODE_FILL = {"node_face_spring": -1, "node_driver": -1}
"""Per-node fields whose empty slots hold -1 (no face, no driver) rather than 0."""


def _grow(a: wp.array, rows: int, per_row: int, capacity: int, fill: Any) -> wp.array:
    host = a.numpy()
    grown = np.full((capacity * per_row, *host.shape[1:]), fill, dtype=host.dtype)
    grown[: rows * per_row] = host[: rows * per_row]
    return wp.array(grown, dtype=a.dtype, device=a.device)


def regrow_nodes(model: Model, state: State, capacity: int) -> tuple[Model, State]:
    """Copies of a model and state with ``capacity`` node slots: every per-node array of the Model, the State and the
    LoadModel (fields ``node_*``, the star CSR heads, rows of per-node contact slots) grown, the live slots copied,
    new slots empty. Between steps; graphs must be re-captured."""
    old = model.node_capacity
    if capacity <= old:
        return model, state

    def grown_fields(obj: object, per_node: set[str]) -> dict[str, wp.array]:
        out = {}
        for f in dataclasses.fields(obj):
            a = getattr(obj, f.name)
            if not isinstance(a, wp.array):
                continue
            fill = NODE_FILL.get(f.name, 0)
            if f.name in NODE_ROW_FIELDS:
                k = int(getattr(model, NODE_ROW_FIELDS[f.name]))
                out[f.name] = _grow(a, old, k, capacity, fill)
            elif f.name in NODE_SCALARS:
                continue
            elif (f.name.startswith("node_") or f.name in per_node) and a.ndim == 1 and a.shape[0] == max(old, 1):
                out[f.name] = _grow(a, old, 1, capacity, fill)
        return out

    loads = model.loads
    if loads is not None and isinstance(getattr(loads, "node_driver", None), wp.array):
        loads = dataclasses.replace(loads, node_driver=_grow(loads.node_driver, old, 1, capacity, -1))
    model = dataclasses.replace(
        model, node_capacity=capacity, loads=loads, **grown_fields(model, {"star_offset", "star_count"})
    )
    state = dataclasses.replace(state, **grown_fields(state, set()))
    return model, state


def sort_joint_elements(model: Model, state: State) -> None:
    """Re-sort the joint elements by their node pair (min(a, b), max(a, b)) in place (a stable radix sort on the
    device, then every joint array gathered in that order), after a split pass handed some over: the contact stage
    finds a pair's element by binary search (kernels/fem_surface.py ``find_joint``). Launches only."""
    n = model.joint_capacity
    if n == 0:
        return
    d = model.device
    keys = wp.zeros(2 * n, dtype=wp.int64, device=d)  # radix_sort_pairs needs twice the length as scratch
    order = wp.zeros(2 * n, dtype=int, device=d)
    wp.launch(
        kt.element_pair_keys_kernel,
        dim=n,
        inputs=[n, model.node_capacity, model.joint_a, model.joint_b],
        outputs=[keys, order],
        device=d,
    )
    wp.utils.radix_sort_pairs(keys, order, n)
    for a in (
        model.joint_a,
        model.joint_b,
        model.joint_area,
        model.joint_kn,
        model.joint_tet_face,
        model.joint_set,
        state.joint_broken,
    ):
        src = wp.clone(a)
        wp.launch(kt.gather_kernel, dim=n, inputs=[order, src], outputs=[a], device=d)


def live_flags(mask: np.ndarray | None, live: int, capacity: int, where: str, name: str, items: str) -> np.ndarray:
    """Per-slot int32 flags (shape (capacity,)) from a bool mask over the ``live`` items (None: all of them), the
    slots past them 0: which nodes may split, which tets may convert.

    Raises:
        ValueError: the mask does not hold one entry per live item (``where``: the caller, ``name``: the argument).
    """
    flags = np.zeros(capacity, dtype=np.int32)
    if mask is None:
        flags[:live] = 1
        return flags
    mask = np.asarray(mask)
    if mask.shape != (live,):
        raise ValueError(f"{where}: {name} must have one entry per live {items}, shape ({live},), got {mask.shape}")
    flags[:live] = mask.astype(bool)
    return flags


# ----------------------------------------------------------------------------------------------------------------
# Node renumbering (build time)


def renumber_nodes(model: Model, state: State, order: np.ndarray, id_arrays: Sequence[wp.array] = ()) -> None:
    """Renumber the live FEM nodes of a freshly split model in place: new node i is old node ``order[i]``. Every
    per-node array of the Model, the State and the LoadModel (fields ``node_*``, the star CSR heads, the rows of
    :data:`NODE_ROW_FIELDS`) is gathered in that order, and every array of node ids (``tet_nodes``, the joint
    elements' ``joint_a``/``joint_b``, and ``id_arrays``: the load and dashpot faces, warpdem.stages.joints
    ``load_face_arrays``) is mapped through the inverse; the joint elements are re-sorted by their node pair
    (:func:`sort_joint_elements`' key, which ``find_joint`` bisects). Slots past the live count are left as they
    are.

    Build time only, after the joints' pre-split and before the FEM surface is built (warpdem.stages.fem_contact
    ``attach_fem_contact``): no face list, cohesive element, coupling or rigid body refers to a node yet.

    Raises:
        ValueError: ``order`` is not a permutation of the live nodes, or cohesive elements already exist.
    """
    nn = int(state.node_count.numpy()[0])
    nt = int(state.tet_count.numpy()[0])
    order = np.asarray(order, dtype=np.int64)
    if order.shape != (nn,) or not np.array_equal(np.sort(order), np.arange(nn)):
        raise ValueError(f"renumber_nodes: the order must be a permutation of the {nn} live nodes")
    if int(state.cohesive_count.numpy()[0]) != 0:
        raise ValueError("renumber_nodes: build time only (cohesive elements already refer to nodes)")
    inv = np.empty(nn, dtype=np.int32)
    inv[order] = np.arange(nn, dtype=np.int32)
    cap = model.node_capacity

    def gather_rows(a: wp.array, per: int) -> None:
        host = a.numpy()
        rows = host[: cap * per].reshape(cap, per, *host.shape[1:])
        rows[:nn] = rows[order]
        a.assign(host)

    def map_ids(a: wp.array, count: int) -> None:
        host = a.numpy()
        ids = host[:count]
        live = ids >= 0  # -1: no node (an empty slot)
        ids[live] = inv[ids[live]]
        a.assign(host)

    for obj, extra in ((model, {"star_offset", "star_count"}), (state, set()), (model.loads, set())):
        if obj is None or not dataclasses.is_dataclass(obj):
            continue
        for f in dataclasses.fields(obj):
            a = getattr(obj, f.name)
            if not isinstance(a, wp.array) or f.name in NODE_SCALARS:
                continue
            per = int(getattr(model, NODE_ROW_FIELDS[f.name])) if f.name in NODE_ROW_FIELDS else 1
            if (f.name.startswith("node_") or f.name in extra) and a.shape[0] == per * cap and per > 0:
                gather_rows(a, per)
    map_ids(model.tet_nodes, nt)
    for ids in id_arrays:
        map_ids(ids, ids.shape[0])
    n = model.joint_capacity
    if n:
        a = inv[model.joint_a.numpy()[:n]]
        b = inv[model.joint_b.numpy()[:n]]
        sorted_by_pair = np.argsort(np.minimum(a, b).astype(np.int64) * cap + np.maximum(a, b), kind="stable")
        model.joint_a.assign(a[sorted_by_pair].astype(np.int32))
        model.joint_b.assign(b[sorted_by_pair].astype(np.int32))
        for arr in (model.joint_area, model.joint_kn, model.joint_tet_face, model.joint_set):
            arr.assign(arr.numpy()[:n][sorted_by_pair])
