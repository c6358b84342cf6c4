"""Skinned (Verlet) candidate lists from a hash grid: one builder for the sphere–sphere list (kernels/contact.py) and
the sphere–face and node–face lists (kernels/fem_contact.py).

An owner (a sphere or an FEM node) queries the grid around its position and keeps, in query order, the candidates
(spheres or faces) that its list's test accepts, in its fixed slots ``owner * K .. owner * K + K - 1``. Past K the
count keeps growing without writing, and the largest count goes to ``needed``, so the host learns the size it must
grow to (STYLE "Dynamic sizes"). A list with per-slot history (a pair's tangential spring, its bond) carries it across
a rebuild by finding the candidate among the owner's old slots; a pair that is new gets the history's default. Such a
list is built into scratch arrays and then committed over the old one (the build reads the old one); a list without
history is built in place.

A kind of list is a :class:`ListSpec`; :func:`make_list_kernels` specialises the build and commit kernels for it at
code generation. This module has no ``from __future__ import annotations``: the kernels' parameter annotations name
the spec's struct types, which Warp resolves only when they are evaluated in the factory's scope.
"""

import dataclasses
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.struct
class NoHistory:
    """The per-slot history of a list that carries none."""


@dataclasses.dataclass(frozen=True)
class ListSpec:
    """One kind of skinned list, as code-generation-time choices.

    Attributes:
        inputs: wp.struct of the Model and State arrays (and constants) that the functions below read.
        radius: wp.func (inputs, owner) -> query radius around the owner [m].
        accept: wp.func (inputs, owner, owner position, candidate) -> whether the candidate enters the list (the
            candidate is below the live candidate count).
        active: wp.func (inputs, owner) -> whether the owner has a list at all (an inactive one gets count 0), or
            None when every live owner has one.
        history: wp.struct of the per-slot history arrays, :class:`NoHistory` for a list without history.
        copy: wp.func (from history, from slot, to history, to slot) that copies one slot's history (a pair found
            in the old list, and the commit); None without history.
        fresh: wp.func (inputs, history, slot, owner, candidate) that writes the history of a pair new to the list;
            None without history.
        owner_vec: type of the owners' positions, ``wp.vec3`` (FEM nodes) or ``wp.vec3d`` (spheres, whose centres are
            float64 so that nothing depends on where the origin is); ``accept`` receives one.
        grid_vec: type of the grid's points, ``wp.vec3`` or ``wp.vec3d``; the owner's position is converted to it
            for the query (the grid only proposes candidates, ``accept`` decides).
        kept: wp.func (inputs, owner) -> whether the owner keeps its list as it is (a partial rebuild: its slots are
            neither read nor written), or None when a rebuild rebuilds every owner. Only for a list without history
            (one built in place).
    """

    inputs: Any
    radius: wp.Function
    accept: wp.Function
    active: wp.Function | None = None
    history: Any = NoHistory
    copy: wp.Function | None = None
    fresh: wp.Function | None = None
    owner_vec: Any = wp.vec3
    grid_vec: Any = wp.vec3
    kept: wp.Function | None = None


@dataclasses.dataclass(frozen=True)
class ListKernels:
    """The kernels of one kind of list (:func:`make_list_kernels`).

    Attributes:
        build: ``build_list_kernel``, one thread per owner slot.
        commit: ``commit_list_kernel`` (new list → state list), None for a list without history (built in place).
        spec: the kind of list.
    """

    build: wp.Kernel
    commit: wp.Kernel | None
    spec: ListSpec


@wp.func
def flag_past_half_fem_skin(
    i: int,
    x: wp.vec3,
    half_fem_skin: float,
    node_contact_stiffness: wp.array(dtype=float),
    node_q_at_fem_build: wp.array(dtype=wp.vec3),
    fem_rebuild_flag: wp.array(dtype=int),
):
    """Raise the FEM contact lists' rebuild flag when node i, a contact node (on the surface: a penalty stiffness),
    now at x [m] has moved more than half the FEM skin since the lists were built: the Verlet-skin criterion, as the
    spheres' (``half_fem_skin`` < 0: the model has no FEM contact). The node drift and the rigid bodies' pose use it."""
    if half_fem_skin >= 0.0:
        if node_contact_stiffness[i] != 0.0:
            moved = x - node_q_at_fem_build[i]
            if wp.dot(moved, moved) > half_fem_skin * half_fem_skin:
                fem_rebuild_flag[0] = 1


@wp.func
def find_slot(index: wp.array(dtype=int), first: int, count: int, candidate: int) -> int:
    """The slot among ``first .. first + count - 1`` that holds candidate, -1 if none does."""
    for s in range(count):
        if index[first + s] == candidate:
            return first + s
    return -1


def make_list_kernels(spec: ListSpec) -> ListKernels:
    """Build and commit kernels of one kind of list, specialised at code generation (call once per kind).

    Args:
        spec: the kind of list.
    """
    Inputs = spec.inputs
    History = spec.history
    radius = spec.radius
    accept = spec.accept
    active = spec.active
    kept = spec.kept
    copy = spec.copy
    fresh = spec.fresh
    OwnerVec = spec.owner_vec
    GridVec = spec.grid_vec
    GridScalar = GridVec._wp_scalar_type_
    has_history = History is not NoHistory
    if (copy is not None) != has_history or (fresh is not None) != has_history:
        raise ValueError("a list with history needs its history struct, copy and fresh; one without, none of them")
    if kept is not None and has_history:
        raise ValueError("a partial rebuild (kept) is for a list built in place, one without history")

    @wp.kernel(enable_backward=False, module="unique")
    def build_list_kernel(
        # Model:
        max_slots: int,
        # In:
        inputs: Inputs,
        # State in:
        grid: wp.uint64,
        owner_count: wp.array(dtype=int),
        owner_q: wp.array(dtype=OwnerVec),
        candidate_count: wp.array(dtype=int),
        list_count: wp.array(dtype=int),
        list_index: wp.array(dtype=int),
        list_history: History,
        # Out:
        new_count: wp.array(dtype=int),
        new_index: wp.array(dtype=int),
        new_history: History,
        needed: wp.array(dtype=int),
    ):
        i = wp.tid()  # one thread per owner slot; it writes its own slots
        if i >= owner_count[0]:
            return
        if wp.static(kept is not None):
            if kept(inputs, i):
                return
        if wp.static(active is not None):
            if not active(inputs, i):
                new_count[i] = 0
                return
        x = owner_q[i]
        n_candidates = candidate_count[0]
        first = i * max_slots
        if wp.static(has_history):
            old_n = wp.min(list_count[i], max_slots)
        count = int(0)
        query = wp.hash_grid_query(grid, GridVec(x), GridScalar(radius(inputs, i)))
        for c in query:
            if c >= n_candidates:
                continue
            if not accept(inputs, i, x, c):
                continue
            if count < max_slots:
                slot = first + count
                new_index[slot] = c
                if wp.static(has_history):
                    old = find_slot(list_index, first, old_n, c)
                    if old >= 0:
                        copy(list_history, old, new_history, slot)
                    else:
                        fresh(inputs, new_history, slot, i, c)
            count += 1
        new_count[i] = count
        wp.atomic_max(needed, 0, count)

    if not has_history:
        return ListKernels(build_list_kernel, None, spec)

    @wp.kernel(enable_backward=False, module="unique")
    def commit_list_kernel(
        # Model:
        max_slots: int,
        # State in:
        owner_count: wp.array(dtype=int),
        # In:
        new_count: wp.array(dtype=int),
        new_index: wp.array(dtype=int),
        new_history: History,
        # State out:
        list_count: wp.array(dtype=int),
        list_index: wp.array(dtype=int),
        list_history: History,
    ):
        i = wp.tid()  # one thread per owner slot
        if i >= owner_count[0]:
            return
        list_count[i] = new_count[i]
        for s in range(wp.min(new_count[i], max_slots)):
            slot = i * max_slots + s
            list_index[slot] = new_index[slot]
            copy(new_history, slot, list_history, slot)

    return ListKernels(build_list_kernel, commit_list_kernel, spec)


def make_finish_rebuild_kernel(vec_type: type) -> wp.Kernel:
    """The kernel that ends a rebuild, for owners whose positions are ``vec_type`` (wp.vec3 nodes, wp.vec3d spheres).

    One concrete kernel per type, not one generic (``Any``) kernel: Warp 1.19's recording of a CPU graph replays a
    generic kernel launched inside a ``capture_if`` branch with the overload of another launch, so the sphere list's
    ``q_at_build`` (vec3d) was written through the nodes' vec3 overload and kept its old value; every replayed step then
    saw the sphere half a skin away and rebuilt (issue 9, boulder_impact).
    """

    def finish_rebuild_kernel(
        # State in:
        owner_count: wp.array(dtype=int),
        owner_q: wp.array(dtype=vec_type),
        # State out:
        q_at_build: wp.array(dtype=vec_type),
        rebuild_flag: wp.array(dtype=int),
        rebuild_total: wp.array(dtype=int),
    ):
        i = wp.tid()  # one thread per owner slot (at least one thread): the positions the skin is measured from
        if i == 0:
            rebuild_flag[0] = 0
            rebuild_total[0] = rebuild_total[0] + 1
        if i < owner_count[0]:
            q_at_build[i] = owner_q[i]

    return wp.Kernel(finish_rebuild_kernel, key=f"finish_rebuild_kernel_{vec_type.__name__}")


FINISH_REBUILD_KERNELS = {wp.vec3: make_finish_rebuild_kernel(wp.vec3), wp.vec3d: make_finish_rebuild_kernel(wp.vec3d)}
