"""A continuum's items as a rank holds them (issue 25): the FEM nodes, tets, boundary faces, joint elements and loaded
faces of the whole run taken into a subdomain's own Model and State, and the ones a rank owns written back into the
whole run's State.

An item's global id is its index in the whole model the scene builds (every rank builds it alike). A subdomain keeps
each kind of item sorted by global id, so its loops run in the whole run's order and every force on an owned node sums
in the same order as in one process (warpdem.parallel.continuum). Which arrays are per item is read from their names
and shapes, as warpdem.stages.topology grows them (``node_*`` per node, with the rows of slots of
:data:`~warpdem.stages.topology.NODE_ROW_FIELDS`; ``tet_*``, ``face_*``, ``joint_*``, ``load_face_*``; the tet-face
slots 4t + k of :data:`TET_FACE_FIELDS`); every other array (walls, tables, clock, counters) is copied whole. Ids held
in arrays (:data:`REFERS`: a tet's nodes, a face's tet, a spring's face, a list's faces) are translated both ways; an id
a rank does not hold becomes -1 (a surface, no spring) or leaves its list, only in items at the rim of what a rank
holds, which no owned item reads (warpdem.parallel.continuum.halo_width says why).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np
import warp as wp

from ..load_data import FaceSet, LoadModel
from ..model import Model, State
from ..stages.topology import NODE_ROW_FIELDS, NODE_SCALARS
from .domain import Slabs
from .rows import _write

SPACES = ("node", "tet", "face", "joint", "load_face")
"""The kinds of item, each with its own global ids."""

COUNTS = {"node": "node_count", "tet": "tet_count", "face": "face_count", "joint": "joint_count"}
"""The State's live count of each kind (a loaded face's count is its set's length)."""

CAPACITIES = {"node": "node_capacity", "tet": "tet_capacity", "face": "face_capacity", "joint": "joint_capacity"}
"""The Model's slot count of each kind."""

TET_FACE_FIELDS = ("tet_face_joint", "tet_face_nbr", "ref_tet_face_nbr")
"""Model fields with four slots per tet (tet-face slot 4t + k: the face opposite node k)."""

TABLES = {"tet_material_table", "joint_material_table"}
"""Per material or joint set, whatever their length: never per item."""

REFERS = {
    "tet_nodes": "node",
    "face_nodes": "node",
    "face_tet": "tet",
    "joint_a": "node",
    "joint_b": "node",
    "joint_tet_face": "tet_face",
    "tet_face_nbr": "tet",
    "ref_tet_face_nbr": "tet",
    "node_face_spring": "face",
}
"""Arrays of item ids (-1: none), by the kind they name ("tet_face": a tet-face slot 4t + k)."""

FACE_SET_REFERS = {"nodes": "node", "tet": "tet"}
"""The same for a loaded face set's arrays (warpdem.load_data.FaceSet)."""

LISTS = {"node_face_index": "node_face_count"}
"""Candidate lists (a row of slots per node, the first ``count`` live): faces by id, kept in order, those not held
dropped."""


def layout(name: str, array: Any, model: Model) -> tuple[str, int] | None:
    """The kind of item a Model or State array ``name`` is indexed by and its slots per item; None where it is not per
    item (copied whole)."""
    if not isinstance(array, wp.array) or name in NODE_SCALARS or name in TABLES or name in COUNTS.values():
        return None
    if name in TET_FACE_FIELDS:
        return "tet", 4
    if name in NODE_ROW_FIELDS:
        per = int(getattr(model, NODE_ROW_FIELDS[name]))
        return ("node", per) if per else None
    if name.startswith("load_face_"):
        return "load_face", 1
    for space, capacity in CAPACITIES.items():
        if name.startswith(space + "_") and array.shape[0] == int(getattr(model, capacity)):
            return space, 1
    return None


def face_sets(loads: LoadModel | None) -> Iterator[tuple[str, FaceSet]]:
    """The loaded face sets of ``loads`` by key: the pressure sets by history kind, then ``"dashpots"``."""
    if loads is None:
        return
    yield from loads.pressure.items()
    if loads.dashpots is not None:
        yield "dashpots", loads.dashpots


@dataclasses.dataclass
class Held:
    """The items a rank holds, owned or as ghosts: global ids by kind (sorted), and of each loaded face set the faces
    (their index in the whole set).

    Attributes:
        ids: global ids by kind (:data:`SPACES`), each shape (n,), int64; a loaded face's is its slot in the State's
            per-loaded-face arrays (the pressure sets one after the other).
        sets: by face set key (:func:`face_sets`), the faces held, shape (n,), int64.
    """

    ids: dict[str, np.ndarray]
    sets: dict[str, np.ndarray]

    def local_of(self, space: str, size: int) -> np.ndarray:
        """Global id → local index of kind ``space`` (-1 where not held), shape (size,)."""
        out = np.full(size, -1, dtype=np.int64)
        out[self.ids[space]] = np.arange(len(self.ids[space]))
        return out


def live_count(state: State, space: str) -> int:
    """The live items of kind ``space`` (one of :data:`COUNTS`) in ``state`` (reads back)."""
    return int(getattr(state, COUNTS[space]).numpy()[0])


def held_items(model: Model, state: State, slabs: Slabs, rank: int) -> Held:
    """What rank ``rank`` holds of the whole run ``model``/``state``: every tet with a node within its slab's halo
    (``slabs.holds``), all their nodes, the boundary faces of those tets, the joint elements with both nodes and the
    tet of their face held, the loaded faces with all three nodes (and a pressure face's tet) held."""
    nn, nt, nf, nj = (live_count(state, s) for s in ("node", "tet", "face", "joint"))
    near = slabs.holds(state.node_q.numpy()[:nn], rank)
    tet_nodes = model.tet_nodes.numpy()[:nt]
    tet_held = near[tet_nodes].any(axis=1)
    node_held = near.copy()
    node_held[tet_nodes[tet_held].ravel()] = True
    faces = np.flatnonzero(tet_held[model.face_tet.numpy()[:nf]]) if nf else np.zeros(0, dtype=np.int64)
    joints = np.zeros(0, dtype=np.int64)
    if nj:
        a, b = model.joint_a.numpy()[:nj], model.joint_b.numpy()[:nj]
        joints = np.flatnonzero(node_held[a] & node_held[b] & tet_held[model.joint_tet_face.numpy()[:nj] // 4])
    sets, loaded = {}, []
    for key, faces_of_set in face_sets(model.loads):
        keep = node_held[faces_of_set.nodes.numpy()].all(axis=1)
        if faces_of_set.tet is not None:
            keep &= tet_held[faces_of_set.tet.numpy()]
        sets[key] = np.flatnonzero(keep)
        if key != "dashpots":
            loaded.append(faces_of_set.first + sets[key])
    ids = {
        "node": np.flatnonzero(node_held),
        "tet": np.flatnonzero(tet_held),
        "face": faces,
        "joint": joints,
        "load_face": np.concatenate(loaded) if loaded else np.zeros(0, dtype=np.int64),
    }
    return Held({k: v.astype(np.int64) for k, v in ids.items()}, sets)


class Ids:
    """Translation of item ids between the whole run and one rank's subdomain (:class:`Held`)."""

    def __init__(self, held: Held, model: Model) -> None:
        self.held = held
        size = {space: int(getattr(model, cap)) + 1 for space, cap in CAPACITIES.items()}
        self.local = {space: held.local_of(space, size[space]) for space in ("node", "tet", "face")}

    def to_local(self, values: np.ndarray, space: str) -> np.ndarray:
        """Whole ids (-1: none) → local ids, -1 where not held."""
        if space == "tet_face":
            tet = self.to_local(np.where(values >= 0, values // 4, -1), "tet")
            return np.where(tet >= 0, 4 * tet + values % 4, -1)
        return np.where(values >= 0, self.local[space][np.maximum(values, 0)], -1)

    def to_whole(self, values: np.ndarray, space: str) -> np.ndarray:
        """Local ids (-1: none) → whole ids."""
        if space == "tet_face":
            tet = self.to_whole(np.where(values >= 0, values // 4, -1), "tet")
            return np.where(tet >= 0, 4 * tet + values % 4, -1)
        return np.where(values >= 0, self.held.ids[space][np.maximum(values, 0)], -1)


def _rows(array: wp.array, per: int, ids: np.ndarray) -> np.ndarray:
    """The slots of the items ``ids`` of an array with ``per`` slots an item, flattened as the array."""
    host = array.numpy()
    width = host.shape[0] // per if per else 0
    shaped = host[: width * per].reshape(width, per, *host.shape[1:])
    return shaped[ids].reshape(len(ids) * per, *host.shape[1:])


def _compact_lists(index: np.ndarray, count: np.ndarray, ids: Ids) -> tuple[np.ndarray, np.ndarray]:
    """Candidate lists (n, K) with live counts (n,) in whole face ids → local ids, the faces not held dropped, the rest
    kept in order at the front."""
    k = index.shape[1]
    live = np.arange(k)[None, :] < np.minimum(count, k)[:, None]
    local = np.where(live, ids.to_local(np.where(live, index, -1), "face"), -1)
    keep = local >= 0
    order = np.argsort(~keep, axis=1, kind="stable")
    return np.take_along_axis(np.where(keep, local, 0), order, axis=1).astype(np.int32), keep.sum(axis=1)


def _star(model: Model, ids: Ids) -> dict[str, np.ndarray]:
    """The node → tet adjacency of the held nodes: each node's held tets, in order (local ids)."""
    nodes = ids.held.ids["node"]
    offset, count = model.star_offset.numpy()[nodes], model.star_count.numpy()[nodes]
    total = int(count.sum())
    at = np.arange(total) - np.repeat(np.cumsum(count) - count, count) + np.repeat(offset, count)
    tets = ids.to_local(model.star_tets.numpy()[at], "tet")
    keep = tets >= 0
    new_count = np.bincount(np.repeat(np.arange(len(nodes)), count)[keep], minlength=len(nodes)).astype(np.int32)
    star_tets = np.zeros(4 * len(ids.held.ids["tet"]), dtype=np.int32)
    star_tets[: int(keep.sum())] = tets[keep]
    return {
        "star_offset": (np.cumsum(new_count) - new_count).astype(np.int32),
        "star_count": new_count,
        "star_tets": star_tets,
    }


def _local_loads(loads: LoadModel | None, held: Held, ids: Ids) -> LoadModel | None:
    """The loaded face sets of what is held (their State slots renumbered set after set), node drivers per node."""
    if loads is None:
        return None
    changes: dict[str, Any] = {"pressure": {}}
    first = 0
    for key, faces in face_sets(loads):
        at = held.sets[key]
        arrays = {}
        for f in dataclasses.fields(faces):
            a = getattr(faces, f.name)
            if isinstance(a, wp.array):
                rows = a.numpy()[at]
                if f.name in FACE_SET_REFERS:
                    rows = ids.to_local(rows, FACE_SET_REFERS[f.name]).astype(rows.dtype)
                arrays[f.name] = wp.array(rows, dtype=a.dtype, device=a.device)
        local = dataclasses.replace(faces, **arrays)
        if key == "dashpots":
            changes["dashpots"] = local
        else:
            changes["pressure"][key] = dataclasses.replace(local, first=first)
            first += len(at)
    if loads.node_driver is not None:
        changes["node_driver"] = wp.array(
            loads.node_driver.numpy()[held.ids["node"]], dtype=int, device=loads.node_driver.device
        )
    return dataclasses.replace(loads, **changes)


def take(model: Model, state: State, held: Held) -> tuple[Model, State]:
    """A Model and State of the items ``held`` of the whole run ``model``/``state`` (capacities: what is held), ids
    translated; everything not per item copied. The face grid keeps the whole run's buckets (``face_grid_owners``),
    so that candidates come in the same order."""
    device = model.device
    ids = Ids(held, model)
    counts = {space: len(held.ids[space]) for space in SPACES}

    def taken(obj: Model | State) -> dict[str, wp.array]:
        out = {}
        for f in dataclasses.fields(obj):
            a = getattr(obj, f.name)
            where = layout(f.name, a, model)
            if where is None:
                if isinstance(a, wp.array) and obj is state:
                    out[f.name] = wp.clone(a)
                continue
            space, per = where
            rows = _rows(a, per, held.ids[space])
            if f.name in REFERS:
                rows = ids.to_local(rows, REFERS[f.name]).astype(rows.dtype)
            out[f.name] = wp.array(rows, dtype=a.dtype, device=device)
        return out

    mfields = taken(model)
    if model.star_offset is not None:
        mfields.update({k: wp.array(v, dtype=int, device=device) for k, v in _star(model, ids).items()})
    sfields = taken(state)
    k = model.max_node_faces
    nodes = held.ids["node"]
    index = state.node_face_index.numpy().reshape(-1, k)[nodes]
    local, count = _compact_lists(index, state.node_face_count.numpy()[nodes], ids)
    sfields["node_face_index"] = wp.array(local.ravel(), dtype=int, device=device)
    sfields["node_face_count"] = wp.array(count.astype(np.int32), dtype=int, device=device)
    for space, name in COUNTS.items():
        sfields[name] = wp.array([counts[space]], dtype=int, device=device)
    local_model = dataclasses.replace(
        model,
        **mfields,
        **{CAPACITIES[space]: counts[space] for space in CAPACITIES},
        face_grid_owners=model.face_grid_owners or model.face_capacity,
        loads=_local_loads(model.loads, held, ids),
    )
    return local_model, State(**sfields)


@dataclasses.dataclass
class Part:
    """The State rows of the items a rank owns, keyed by whole id: what it sends to rank 0 (output) or to every rank
    (a new decomposition).

    Attributes:
        ids: whole ids by kind, each shape (n,).
        fields: State rows by field name, shape (n, slots, ...) for an array with several slots per item, else
            (n, ...); ids in whole numbering.
        needs: the most candidate faces a node of the rank's needed at a list build (``node_face_needed``).
        rebuild: 1 where the rank's lists are due to be built at the next step (``fem_rebuild_flag``).
    """

    ids: dict[str, np.ndarray]
    fields: dict[str, np.ndarray]
    needs: int = 0
    rebuild: int = 0


def owned_part(model: Model, state: State, ids: Ids, owned: dict[str, np.ndarray]) -> Part:
    """The rows of the local items ``owned`` (local indices by kind) of a subdomain, ids made whole."""
    fields = {}
    for f in dataclasses.fields(state):
        a = getattr(state, f.name)
        where = layout(f.name, a, model)
        if where is None or where[0] not in owned:
            continue
        space, per = where
        rows = _rows(a, per, owned[space])
        if per > 1:
            rows = rows.reshape(len(owned[space]), per, *rows.shape[1:])
        if f.name in REFERS:
            rows = ids.to_whole(rows, REFERS[f.name]).astype(rows.dtype)
        elif f.name in LISTS:
            count = getattr(state, LISTS[f.name]).numpy()[owned[space]]
            live = np.arange(per)[None, :] < np.minimum(count, per)[:, None]
            rows = np.where(live, ids.to_whole(np.where(live, rows, -1), "face"), 0).astype(rows.dtype)
        fields[f.name] = rows
    return Part({space: ids.held.ids[space][local] for space, local in owned.items()}, fields)


def write_parts(model: Model, state: State, parts: list[Part]) -> None:
    """Write every part's rows into the whole run's ``state`` at their ids (the state must have at least each part's
    list slots)."""
    for part in parts:
        for name, rows in part.fields.items():
            array = getattr(state, name)
            space, per = layout(name, array, model)
            host = array.numpy()
            shape = (host.shape[0] // per, per, *host.shape[1:]) if per > 1 else host.shape
            view = host.reshape(shape)
            at = part.ids[space]
            if per > 1 and rows.shape[1] < per:  # fewer list slots than the whole: the first ones
                view[at, : rows.shape[1]] = rows
            else:
                view[at] = rows
            _write(array, view)
