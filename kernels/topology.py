"""Topology of the tet mesh and node duplication: the one place that joints (build time), nodal fracture (run time)
and later conversion change the mesh (STYLE.md), kernels and wp.funcs only (host side: warpdem/stages/topology.py).

Topology conventions. Face k of a positively oriented tet is the face opposite its node k, listed so that its
right-hand normal points out of the tet (:func:`tet_face`, the table of ``warpdem.build.mesh.TET_FACES``); tet-face
slot ``4 t + k``. The *star* of a node is the list of live, active tets that hold it: a CSR layout
(``star_offset[n]``, ``star_count[n]``, ``star_tets``) built count → exclusive scan → fill, each node's list then
sorted ascending so that everything derived from it is deterministic.

Splitting a node. Its star falls into connected components when tets that meet across a face holding the node
are joined, except across a joint face. Component 0 (the one holding the lowest tet index) keeps the node; every
further component takes a new node slot, appended after the live nodes in the order of their parents
(warpdem.stages.compaction's append pass), and its tets are remapped onto it. Each component is ordered by its lowest
tet index, so the result does not depend on thread scheduling.

Tet-face slots never move: a split rewrites node indices inside tets, never which tet sits in which slot, so an
adjacency by tet slot made once on the unsplit mesh (``ref_tet_face_nbr``, matching faces by reference positions,
which daughters share) still names the tet that was across each face after any number of splits.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .tets import TetMaterial

wp.set_module_options({"enable_backward": False})


# ----------------------------------------------------------------------------------------------------------------
# Topology helpers.


@wp.func
def tet_face(n: wp.vec4i, k: int) -> wp.vec3i:
    """Nodes of face k (opposite node k) of a positively oriented tet, in outward (right-hand) order."""
    if k == 0:
        return wp.vec3i(n[1], n[2], n[3])
    if k == 1:
        return wp.vec3i(n[0], n[3], n[2])
    if k == 2:
        return wp.vec3i(n[0], n[1], n[3])
    return wp.vec3i(n[0], n[2], n[1])


@wp.func
def local_index(n: wp.vec4i, v: int) -> int:
    """Position of node v in a tet (0..3), -1 if the tet does not hold it."""
    for k in range(4):
        if n[k] == v:
            return k
    return -1


@wp.func
def face_in_tet(n: wp.vec4i, a: int, b: int, c: int) -> int:
    """Local face index k of the face (a, b, c) in a tet (the node not on it), -1 if the tet does not hold it."""
    if local_index(n, a) < 0 or local_index(n, b) < 0 or local_index(n, c) < 0:
        return -1
    for k in range(4):
        if n[k] != a and n[k] != b and n[k] != c:
            return k
    return -1


@wp.func
def star_find(star_tets: wp.array(dtype=int), start: int, count: int, t: int) -> int:
    """Entry of tet t in a node's sorted star segment [start, start + count) (binary search), -1 if absent."""
    lo = start
    hi = start + count
    while lo < hi:
        mid = (lo + hi) // 2
        if star_tets[mid] < t:
            lo = mid + 1
        else:
            hi = mid
    if lo < start + count:
        if star_tets[lo] == t:
            return lo
    return -1


@wp.func
def label_star(
    tet_nodes: wp.array(dtype=wp.vec4i),
    start: int,
    count: int,
    star_tets: wp.array(dtype=int),
    v: int,
    tet_face_nbr: wp.array(dtype=int),
    tet_face_joint: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
) -> int:
    """Connected components of node v's star segment [start, start + count): star_comp[e] = 0, 1, 2, ... in order of
    each component's lowest tet; returns the number of components. Two star tets are joined across a face that
    holds v, that ``tet_face_nbr`` names, that is no joint face (``tet_face_joint`` >= 0; an empty array: none), and
    that the tet across still holds (with an adjacency of the unsplit mesh, a face a split has opened is no join)."""
    # Label propagation to a fixed point: every entry takes the smallest local index reachable through a joining
    # face. Entries are sorted by tet index, so component labels follow the lowest tet.
    for i in range(count):
        star_comp[start + i] = i
    changed = int(1)
    while changed != 0:
        changed = int(0)
        for i in range(count):
            t = star_tets[start + i]
            n = tet_nodes[t]
            for k in range(4):
                if n[k] == v:
                    continue  # the face opposite v does not hold v
                if tet_face_joint.shape[0] > 0:
                    if tet_face_joint[4 * t + k] >= 0:
                        continue
                t2 = tet_face_nbr[4 * t + k]
                if t2 < 0:
                    continue
                e2 = star_find(star_tets, start, count, t2)
                if e2 < 0:
                    continue
                f = tet_face(n, k)
                if face_in_tet(tet_nodes[t2], f[0], f[1], f[2]) < 0:
                    continue
                a = star_comp[start + i]
                b = star_comp[e2]
                if b < a:
                    star_comp[start + i] = b
                    changed = 1
                elif a < b:
                    star_comp[e2] = a
                    changed = 1
    # Labels → ordinals 0, 1, 2, ... in order of each component's lowest tet. A component's root (label == own
    # index) precedes its other entries, so one pass over the roots and one over the rest suffice.
    ordinal = int(0)
    for i in range(count):
        if star_comp[start + i] == i:
            star_comp[start + i] = -1 - ordinal  # marked, so that the second pass tells roots from members
            ordinal += 1
    for i in range(count):
        c = star_comp[start + i]
        if c >= 0:
            star_comp[start + i] = star_comp[start + c]
    for i in range(count):
        star_comp[start + i] = -1 - star_comp[start + i]
    return ordinal


@wp.func
def split_node_index(v: int, component: int, first_new: wp.array(dtype=int)) -> int:
    """Node that component c of node v's star holds after a split: v itself for c = 0, else v's (c-1)-th new slot."""
    if component == 0:
        return v
    return first_new[v] + component - 1


@wp.func
def triangle_area_vector(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """(b - a) × (c - a) / 2: the area [m²] times the right-hand unit normal."""
    return 0.5 * wp.cross(b - a, c - a)


# ----------------------------------------------------------------------------------------------------------------
# Node → tet adjacency (the star CSR): count → exclusive scan → fill → sort.


@wp.kernel
def count_node_tets_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    # Out:
    star_count: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot
    if t >= tet_count[0] or tet_active[t] == 0:
        return
    n = tet_nodes[t]
    for k in range(4):
        wp.atomic_add(star_count, n[k], 1)


@wp.kernel
def fill_node_tets_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    # In:
    star_offset: wp.array(dtype=int),
    # Out:
    star_fill: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot
    if t >= tet_count[0] or tet_active[t] == 0:
        return
    n = tet_nodes[t]
    for k in range(4):
        slot = wp.atomic_add(star_fill, n[k], 1)
        star_tets[star_offset[n[k]] + slot] = t


@wp.kernel
def sort_node_tets_kernel(
    # In:
    node_count: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    # Out:
    star_tets: wp.array(dtype=int),
):
    v = wp.tid()  # one thread per node slot; insertion sort of its own (short) star
    if v >= node_count[0]:
        return
    start = star_offset[v]
    for i in range(1, star_count[v]):
        key = star_tets[start + i]
        j = i - 1
        # The bound is its own test: Warp evaluates both operands of `and`, and star_tets[start - 1] may not exist.
        while j >= 0:
            if star_tets[start + j] <= key:
                break
            star_tets[start + j + 1] = star_tets[start + j]
            j -= 1
        star_tets[start + j + 1] = key


@wp.kernel
def tet_face_neighbors_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # Out:
    tet_face_nbr: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot; writes the neighbour across each of its four faces (-1: none)
    for k in range(4):
        tet_face_nbr[4 * t + k] = -1
    if t >= tet_count[0] or tet_active[t] == 0:
        return
    n = tet_nodes[t]
    for k in range(4):
        f = tet_face(n, k)
        start = star_offset[f[0]]
        for e in range(start, start + star_count[f[0]]):
            t2 = star_tets[e]
            if t2 != t and face_in_tet(tet_nodes[t2], f[0], f[1], f[2]) >= 0:
                tet_face_nbr[4 * t + k] = t2
                break


# ----------------------------------------------------------------------------------------------------------------
# Splitting nodes: components of a star, re-lumped masses, remapped tets and faces.


@wp.kernel
def label_star_components_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    node_count: wp.array(dtype=int),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    tet_face_nbr: wp.array(dtype=int),
    tet_face_joint: wp.array(dtype=int),
    # Out:
    star_comp: wp.array(dtype=int),
    copies: wp.array(dtype=int),
):
    v = wp.tid()  # one thread per node slot; it labels its own star (no other thread touches those entries)
    if v >= node_count[0]:
        return
    ordinal = label_star(
        tet_nodes, star_offset[v], star_count[v], star_tets, v, tet_face_nbr, tet_face_joint, star_comp
    )
    copies[v] = wp.max(ordinal - 1, 0)


@wp.kernel
def relump_split_nodes_kernel(
    # Model:
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    # State in:
    node_count: wp.array(dtype=int),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    copies: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    # Out:
    node_mass: wp.array(dtype=float),
    node_inv_mass: wp.array(dtype=float),
    node_damping: wp.array(dtype=float),
):
    v = wp.tid()  # one thread per parent node slot; it writes its own mass and its copies'
    if v >= node_count[0]:
        return
    if copies[v] == 0:
        return  # an unsplit node keeps its lumped mass
    held = node_inv_mass[v] == 0.0  # a held node (fixed, massless) stays held on every side
    start = star_offset[v]
    for c in range(copies[v] + 1):
        dst = split_node_index(v, c, first_new)
        if dst >= node_mass.shape[0]:
            continue  # past capacity: the host grows and redoes the pass
        # Σ ρ V₀ / 4 over this component's tets, in ascending tet order (deterministic sums).
        mass = float(0.0)
        damping = float(0.0)
        for e in range(start, start + star_count[v]):
            if star_comp[e] != c:
                continue
            t = star_tets[e]
            mat = tet_material_table[tet_material[t]]
            quarter = 0.25 * mat.density * tet_volume[t]
            mass += quarter
            damping += quarter * mat.alpha
        node_mass[dst] = mass
        if mass > 0.0:
            node_damping[dst] = damping / mass
        else:
            node_damping[dst] = 0.0
        if held or mass <= 0.0:
            node_inv_mass[dst] = 0.0
        else:
            node_inv_mass[dst] = 1.0 / mass


@wp.kernel
def remap_split_tets_kernel(
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    # Out:
    tet_nodes: wp.array(dtype=wp.vec4i),
):
    t = wp.tid()  # one thread per tet slot; it rewrites its own four node indices
    if t >= tet_count[0] or tet_active[t] == 0:
        return
    n = tet_nodes[t]
    out = n
    for k in range(4):
        v = n[k]
        e = star_find(star_tets, star_offset[v], star_count[v], t)
        out[k] = split_node_index(v, star_comp[e], first_new)
    tet_nodes[t] = out


@wp.kernel
def remap_split_faces_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    # Out:
    faces: wp.array(dtype=wp.vec3i),
):
    i = wp.tid()  # one thread per face of a face list (given in pre-split node ids, before the tets are remapped)
    f = faces[i]
    # The face's nodes become those of the (lowest) tet that holds it, on whichever side of a joint that tet lies.
    start = star_offset[f[0]]
    owner = int(-1)
    for e in range(start, start + star_count[f[0]]):
        if face_in_tet(tet_nodes[star_tets[e]], f[0], f[1], f[2]) >= 0:
            owner = star_tets[e]
            break
    if owner < 0:
        return
    out = f
    for a in range(3):
        v = f[a]
        e = star_find(star_tets, star_offset[v], star_count[v], owner)
        out[a] = split_node_index(v, star_comp[e], first_new)
    faces[i] = out


# ----------------------------------------------------------------------------------------------------------------
# Splitting an independent set of nodes (nodal fracture): every split node has two sides (star_comp 0 / 1) and no
# tet holds two split nodes, so each split node rewrites its own star's tets and nothing else writes there.


@wp.func
def follow_split(
    v: int,
    t: int,
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    copies: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
) -> int:
    """The node tet t holds in place of v after a split: v's daughter on t's side when v splits and t is in its star,
    else v itself."""
    if v < 0 or v >= copies.shape[0]:
        return v
    if copies[v] == 0:
        return v
    e = star_find(star_tets, star_offset[v], star_count[v], t)
    if e < 0:
        return v
    return split_node_index(v, star_comp[e], first_new)


@wp.kernel
def remap_split_star_tets_kernel(
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    copies: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    node_capacity: int,
    # Out:
    tet_nodes: wp.array(dtype=wp.vec4i),
):
    v = wp.tid()  # one thread per node slot; a split node rewrites itself in the tets of its star that leave it
    if copies[v] == 0:
        return
    start = star_offset[v]
    for e in range(start, start + star_count[v]):
        c = star_comp[e]
        if c == 0:
            continue
        dst = split_node_index(v, c, first_new)
        if dst >= node_capacity:
            continue  # past capacity: nothing is written (the host grows first; kernels/compaction.py)
        t = star_tets[e]
        n = tet_nodes[t]
        n[local_index(n, v)] = dst
        tet_nodes[t] = n


@wp.kernel
def remap_split_face_list_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    copies: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    # Out:
    faces: wp.array(dtype=wp.vec3i),
):
    i = wp.tid()  # one thread per face of a face list (current node ids; launched before the tets are remapped)
    f = faces[i]
    out = f
    for a in range(3):
        v = f[a]
        if v < 0 or v >= copies.shape[0]:
            continue
        if copies[v] == 0:
            continue
        # The face follows the tet that holds it (a boundary face has one): v's daughter on that tet's side. Only a
        # split node's star is searched, and that star is fresh (a node splits at most once per pass).
        start = star_offset[v]
        for e in range(start, start + star_count[v]):
            if face_in_tet(tet_nodes[star_tets[e]], f[0], f[1], f[2]) >= 0:
                out[a] = split_node_index(v, star_comp[e], first_new)
                break
    faces[i] = out


@wp.kernel
def hand_over_elements_kernel(
    # Model:
    ref_tet_face_nbr: wp.array(dtype=int),
    # State in:
    element_count: wp.array(dtype=int),
    element_tet_face: wp.array(dtype=int),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    copies: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    # Out:
    element_a: wp.array(dtype=int),
    element_b: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per element slot (cohesive or joint): its nodes follow their representative tets
    if i >= element_count[0]:
        return
    # Representative tets: A's is the tet of the element's face slot, B's the tet across it in the unsplit mesh.
    # Each always holds its node, so a split hands the element to the daughter on that tet's side.
    slot = element_tet_face[i]
    if slot < 0:
        return
    element_a[i] = follow_split(
        element_a[i], slot // 4, star_offset, star_count, star_tets, star_comp, copies, first_new
    )
    tb = ref_tet_face_nbr[slot]
    if tb >= 0:
        element_b[i] = follow_split(element_b[i], tb, star_offset, star_count, star_tets, star_comp, copies, first_new)


@wp.kernel
def tet_face_neighbors_from_ref_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    ref_tet_face_nbr: wp.array(dtype=int),
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    # Out:
    tet_face_nbr: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot; the current neighbour across each face: the unsplit one, if it still
    # holds the face's three nodes (splits only ever separate tets, never join new ones)
    for k in range(4):
        tet_face_nbr[4 * t + k] = -1
    if t >= tet_count[0] or tet_active[t] == 0:
        return
    n = tet_nodes[t]
    for k in range(4):
        t2 = ref_tet_face_nbr[4 * t + k]
        if t2 < 0:
            continue
        if tet_active[t2] == 0:
            continue
        f = tet_face(n, k)
        if face_in_tet(tet_nodes[t2], f[0], f[1], f[2]) >= 0:
            tet_face_nbr[4 * t + k] = t2


# ----------------------------------------------------------------------------------------------------------------
# Element order: joint elements are kept sorted by their node pair (min, max), which the contact stage's binary
# search (kernels/fem_contact.py ``find_joint``) relies on; a hand-over can move a pair, so it is re-sorted.


@wp.kernel
def element_pair_keys_kernel(
    # In:
    count: int,
    node_capacity: int,
    element_a: wp.array(dtype=int),
    element_b: wp.array(dtype=int),
    # Out:
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per element: its sort key min(a, b) · node_capacity + max(a, b)
    if i >= count:
        return
    a = element_a[i]
    b = element_b[i]
    keys[i] = wp.int64(wp.min(a, b)) * wp.int64(node_capacity) + wp.int64(wp.max(a, b))
    values[i] = i


@wp.kernel
def gather_kernel(
    # In:
    order: wp.array(dtype=int),
    src: wp.array(dtype=Any),
    # Out:
    dst: wp.array(dtype=Any),
):
    i = wp.tid()  # one thread per slot: dst[i] = src[order[i]]
    dst[i] = src[order[i]]
