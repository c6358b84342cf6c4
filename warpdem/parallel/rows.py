"""Spheres as host rows, keyed by global id: what a rank sends when spheres migrate or become ghosts, what it builds
its subdomain's Model and State from, and what rank 0 writes back into the whole state for output.

A sphere's global id is its index in the whole model the scene builds (every rank builds it the same way); a
subdomain keeps its spheres sorted by global id, so its loops run in the whole run's order. A slot's partner is held
as a global id in rows (a local index means nothing on another rank) and translated back where the rows land.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from ..model import BOND_FIELDS, NEIGHBOR_FIELDS, PARTICLE_MODEL_FIELDS, PARTICLE_STATE_FIELDS, Model, State

MODEL_FIELDS = tuple(PARTICLE_MODEL_FIELDS)
"""Model fields with one entry per sphere."""

STATE_FIELDS = tuple(name for name in PARTICLE_STATE_FIELDS if name != "nbr_count")
"""State fields with one entry per sphere besides its list (``nbr_count`` and the slots travel apart)."""

PARTNER = "nbr_partner"
"""The rows' name of the slots' partners as global ids (-1 past a sphere's count)."""

BOND_ROW_FIELDS = tuple(name for name in BOND_FIELDS if name not in ("bond_i", "bond_j", "bond_key"))
"""Bond fields a bond carries between ranks (its ends travel as global ids, its key is made where it lands)."""


@dataclasses.dataclass
class Rows:
    """Host rows of some spheres.

    Attributes:
        gid: global ids, shape (n,), int64.
        fields: per-sphere arrays by field name, each shape (n, ...): the Model and State fields above, ``wall_shear``
            (n, num_walls, 3), ``nbr_count`` (n,), and the slots (n, K, ...) of ``nbr_shear`` and :data:`PARTNER` (a
            slot's bond is not carried: where the rows land it is looked up by key, as a list build finds it).
    """

    gid: np.ndarray
    fields: dict[str, np.ndarray]

    def __len__(self) -> int:
        return int(self.gid.shape[0])

    def take(self, where: np.ndarray) -> Rows:
        """The rows at ``where`` (indices or a mask)."""
        return Rows(self.gid[where], {name: a[where] for name, a in self.fields.items()})

    @staticmethod
    def join(parts: list[Rows]) -> Rows:
        """Rows of several parts in one, sorted by global id (the parts hold no id twice). Slots are padded to the
        widest part's K (partner -1)."""
        parts = [p for p in parts if p.fields]
        k = max(p.fields[PARTNER].shape[1] for p in parts)
        gid = np.concatenate([p.gid for p in parts])
        order = np.argsort(gid, kind="stable")
        fields = {}
        for name in parts[0].fields:
            arrays = [_pad_slots(name, p.fields[name], k) for p in parts]
            fields[name] = np.concatenate(arrays)[order]
        return Rows(gid[order], fields)


@dataclasses.dataclass
class Bonds:
    """Host rows of some bonds.

    Attributes:
        ends: the two spheres' global ids, lower first, shape (n, 2), int64.
        fields: :data:`BOND_ROW_FIELDS` by name, each shape (n, ...).
    """

    ends: np.ndarray
    fields: dict[str, np.ndarray]

    def __len__(self) -> int:
        return int(self.ends.shape[0])

    def take(self, where: np.ndarray) -> Bonds:
        """The bonds at ``where`` (indices or a mask)."""
        return Bonds(self.ends[where], {name: a[where] for name, a in self.fields.items()})

    @staticmethod
    def join(parts: list[Bonds]) -> Bonds:
        """The bonds of several parts in one, in key order (lower end, then upper), each once."""
        ends = np.concatenate([p.ends for p in parts])
        order = np.lexsort((ends[:, 1], ends[:, 0]))
        ends = ends[order]
        first = np.ones(len(ends), dtype=bool)
        first[1:] = np.any(ends[1:] != ends[:-1], axis=1)
        fields = {name: np.concatenate([p.fields[name] for p in parts])[order][first] for name in parts[0].fields}
        return Bonds(ends[first], fields)


def bonds_of(state: State, gid: np.ndarray) -> Bonds:
    """The live bonds (broken ones not yet compacted included) of a model whose spheres have the global ids ``gid``."""
    n = int(state.bond_count.numpy()[0])
    i, j = state.bond_i.numpy()[:n], state.bond_j.numpy()[:n]
    ends = np.stack([gid[i], gid[j]], axis=1).astype(np.int64)
    return Bonds(ends, {name: getattr(state, name).numpy()[:n].copy() for name in BOND_ROW_FIELDS})


def _bond_arrays(bonds: Bonds, gid: np.ndarray, particle_capacity: int, capacity: int) -> dict[str, np.ndarray]:
    """The State bond arrays of ``bonds`` (each end among ``gid``, sorted) at ``capacity`` slots, keyed by the local
    indices (the key order is the global one: local indices follow global ids)."""
    n = len(bonds)
    local = np.searchsorted(gid, bonds.ends)
    if n and not np.array_equal(gid[np.minimum(local, len(gid) - 1)], bonds.ends):
        raise ValueError("a bond whose two spheres are not both held")
    arrays = {
        "bond_i": local[:, 0].astype(np.int32),
        "bond_j": local[:, 1].astype(np.int32),
        "bond_key": (local[:, 0] * particle_capacity + local[:, 1]).astype(np.int64),
        **bonds.fields,
    }
    out = {}
    for name, a in arrays.items():
        full = np.zeros((capacity, *a.shape[1:]), dtype=a.dtype)
        full[:n] = a
        out[name] = full
    return out


def _pad_slots(name: str, a: np.ndarray, k: int) -> np.ndarray:
    if name not in (*NEIGHBOR_FIELDS, PARTNER) or a.shape[1] == k:
        return a
    fill = -1 if name == PARTNER else 0
    pad = [(0, 0), (0, k - a.shape[1])] + [(0, 0)] * (a.ndim - 2)
    return np.pad(a, pad, constant_values=fill)


def rows_of(model: Model, state: State, gid: np.ndarray, local: np.ndarray) -> Rows:
    """The rows of the local spheres ``local`` (indices) of a subdomain whose spheres have the global ids ``gid``
    (shape (particle_count,))."""
    cap, k, walls = model.particle_capacity, model.max_neighbors, model.num_walls
    fields = {name: getattr(model, name).numpy()[local] for name in MODEL_FIELDS}
    fields.update({name: getattr(state, name).numpy()[local] for name in STATE_FIELDS})
    fields["wall_shear"] = state.wall_shear.numpy().reshape(cap, walls, 3)[local]
    count = np.minimum(state.nbr_count.numpy()[local], k)
    fields["nbr_count"] = count
    index = state.nbr_index.numpy().reshape(cap, k)[local]
    live = np.arange(k)[None, :] < count[:, None]
    fields[PARTNER] = np.where(live, gid[np.where(live, index, 0)], -1).astype(np.int64)
    fields["nbr_shear"] = state.nbr_shear.numpy().reshape(cap, k, 3)[local]
    return Rows(gid[local].astype(np.int64), fields)


def _slot_arrays(rows: Rows, k: int, bond_key: np.ndarray, particle_capacity: int) -> dict[str, np.ndarray]:
    """``nbr_count`` and the slots of ``rows`` as local arrays (n, k, ...): the partners found among the rows as local
    indices, moved to the front of their sphere's slots in their order; a partner not among them is dropped (the list
    is rebuilt right after: it only carries history). A slot's bond is looked up in ``bond_key`` (the live bonds'
    local keys, ascending), as a list build finds it."""
    n = len(rows)
    partner = _pad_slots(PARTNER, rows.fields[PARTNER], k)[:, :k]
    found = np.minimum(np.searchsorted(rows.gid, partner), max(n - 1, 0))
    keep = (partner >= 0) & (rows.gid[found] == partner) if n else partner >= 0
    count = keep.sum(axis=1).astype(np.int32)
    live = np.arange(k)[None, :] < count[:, None]
    index = np.where(keep, found, 0)
    shear = _pad_slots("nbr_shear", rows.fields["nbr_shear"], k)[:, :k]
    # Only a sphere that lost a partner ahead of a kept one has slots to move forward (most keep every partner, or
    # lose their last ones): the stable partition is taken over those rows alone.
    moved = np.flatnonzero(np.any(keep != live, axis=1))
    if len(moved):
        order = np.argsort(~keep[moved], axis=1, kind="stable")
        index[moved] = np.take_along_axis(index[moved], order, axis=1)
        shear = shear.copy()
        shear[moved] = np.take_along_axis(shear[moved], order[..., None], axis=1)
    bond = _slot_bonds(bond_key, np.arange(n)[:, None].astype(np.int64) * particle_capacity + index, live)
    return {
        "nbr_count": count,
        "nbr_index": np.where(live, index, 0).astype(np.int32),
        "nbr_shear": np.where(live[..., None], shear, 0.0).astype(np.float32),
        "nbr_bond": bond,
    }


def _slot_bonds(bond_key: np.ndarray, key: np.ndarray, live: np.ndarray) -> np.ndarray:
    """Each live slot's bond: the index of its pair's key ``key`` (i * capacity + j) in the ascending ``bond_key``,
    -1 where the pair has none or the slot is dead (int32, the shape of ``key``)."""
    bond = np.full(key.shape, -1, dtype=np.int32)
    if len(bond_key):
        at = np.minimum(np.searchsorted(bond_key, key), len(bond_key) - 1)
        bond = np.where(live & (bond_key[at] == key), at, -1).astype(np.int32)
    return bond


def _write(array: wp.array, host: np.ndarray) -> None:
    """Copy ``host`` into ``array`` (its shape as ``host``'s): on the CPU through the array's own host view, no
    staging copy, and nothing to do where ``host`` is that view."""
    if array.device.is_cpu:
        view = array.numpy().reshape(host.shape)
        if not np.shares_memory(view, host):
            np.copyto(view, host)
    else:
        array.assign(host)


def _local_arrays(
    rows: Rows, bonds: Bonds, k: int, cap: int, bond_cap: int
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The Model and State per-sphere and per-bond arrays of ``rows`` and ``bonds`` at capacities ``cap`` (≥ len(rows))
    and ``bond_cap`` with ``k`` slots, as host arrays shaped like the device ones (slots and wall histories flattened);
    dead slots zero (bond -1)."""
    n = len(rows)

    def padded(a: np.ndarray, fill: float = 0) -> np.ndarray:
        full = np.full((cap, *a.shape[1:]), fill, dtype=a.dtype)
        full[:n] = a
        return full

    model = {name: padded(rows.fields[name], PARTICLE_MODEL_FIELDS[name]) for name in MODEL_FIELDS}
    state = {name: padded(rows.fields[name]) for name in STATE_FIELDS}
    state["wall_shear"] = padded(rows.fields["wall_shear"]).reshape(-1, 3)
    if bond_cap:
        state.update(_bond_arrays(bonds, rows.gid, cap, bond_cap))
    keys = state["bond_key"][: len(bonds)] if bond_cap else np.zeros(0, dtype=np.int64)
    for name, a in _slot_arrays(rows, k, keys, cap).items():
        full = padded(a, -1 if name == "nbr_bond" else 0)
        state[name] = full if name == "nbr_count" else full.reshape(cap * k, *a.shape[2:])
    return model, state


def subdomain(
    model: Model, state: State, rows: Rows, bonds: Bonds, max_neighbors: int, capacity: int, bond_capacity: int
) -> tuple[Model, State]:
    """A Model and State of the spheres of ``rows`` (sorted by global id) in ``capacity`` slots (≥ len(rows), ≥ 1),
    with ``max_neighbors`` list slots each, and of ``bonds`` in ``bond_capacity`` slots (0 where the model has no
    bonds); everything else (walls, clock, counters, tables) is copied from ``model``/``state``."""
    device = model.device
    mhost, shost = _local_arrays(rows, bonds, max_neighbors, capacity, bond_capacity)
    mfields = {name: wp.array(a, dtype=getattr(model, name).dtype, device=device) for name, a in mhost.items()}
    sfields = {name: wp.clone(a) for name, a in state.arrays().items()}
    sfields.update({name: wp.array(a, dtype=getattr(state, name).dtype, device=device) for name, a in shost.items()})
    sfields["particle_count"] = wp.array([len(rows)], dtype=int, device=device)
    sfields["bond_count"] = wp.array([len(bonds)], dtype=int, device=device)
    local_model = dataclasses.replace(
        model, particle_capacity=capacity, max_neighbors=max_neighbors, bond_capacity=bond_capacity, **mfields
    )
    return local_model, State(**sfields)


def fill(model: Model, state: State, rows: Rows, bonds: Bonds) -> None:
    """Write the spheres of ``rows`` and the ``bonds`` into a subdomain's own arrays (no allocation: recorded graphs
    stay valid); they must fit its capacities and its ``max_neighbors``."""
    mhost, shost = _local_arrays(rows, bonds, model.max_neighbors, model.particle_capacity, model.bond_capacity)
    for obj, host in ((model, mhost), (state, shost)):
        for name, a in host.items():
            _write(getattr(obj, name), a)
    state.particle_count.fill_(len(rows))
    state.bond_count.fill_(len(bonds))


def write_rows(model: Model, state: State, rows: Rows, bonds: Bonds) -> None:
    """Write ``rows`` and ``bonds`` into the whole run's ``state`` at their global ids (the whole model's order),
    slots with their partners as whole indices and their bonds looked up by key; ``state`` must have at least the
    rows' K slots (``model.max_neighbors``) and room for the bonds."""
    cap, k, walls = model.particle_capacity, model.max_neighbors, model.num_walls
    at = rows.gid

    def scatter(array: wp.array, shape: tuple[int, ...], values: np.ndarray) -> None:
        """``values`` into the rows ``at`` of ``array`` seen as ``shape`` (on the CPU in place, through its view)."""
        host = array.numpy().reshape(shape)
        host[at] = values
        _write(array, host)

    for name in STATE_FIELDS:
        array = getattr(state, name)
        scatter(array, array.numpy().shape, rows.fields[name])
    scatter(state.wall_shear, (cap, walls, 3), rows.fields["wall_shear"])
    scatter(state.nbr_count, (cap,), rows.fields["nbr_count"])
    keys = np.zeros(0, dtype=np.int64)
    if model.bond_capacity:
        whole = np.arange(cap, dtype=np.int64)
        for name, host in _bond_arrays(bonds, whole, cap, model.bond_capacity).items():
            _write(getattr(state, name), host)
        state.bond_count.fill_(len(bonds))
        keys = state.bond_key.numpy()[: len(bonds)]
    partner = _pad_slots(PARTNER, rows.fields[PARTNER], k)[:, :k]
    live = partner >= 0
    scatter(state.nbr_index, (cap, k), np.maximum(partner, 0).astype(np.int32))
    scatter(state.nbr_shear, (cap, k, 3), _pad_slots("nbr_shear", rows.fields["nbr_shear"], k)[:, :k])
    scatter(state.nbr_bond, (cap, k), _slot_bonds(keys, at[:, None] * cap + np.maximum(partner, 0), live))
