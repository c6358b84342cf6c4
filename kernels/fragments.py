"""Fragments: connected components of the material over FEM nodes and spheres, by union–find on the device.

Items are numbered in one array: FEM node n is item n, sphere p is item ``node_capacity + p``. Every link the
material still holds (an active tet's four nodes, an intact cohesive or joint element, an intact bond, a penalty
coupling into an active tet) unites its two items. The union hooks the larger root under the smaller one with an
atomic compare-and-swap, and ``find_root`` halves paths as it walks (ECL-CC style): parents only ever decrease and
stay inside their component, so whatever order the threads run in, the root of each component is its smallest item
— the final labels are deterministic by construction.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def find_root(parent: wp.array(dtype=int), x: int) -> int:
    """Root of item ``x``; path halving on the way (a benign race: any ancestor written is a valid parent)."""
    node = x
    up = parent[node]
    while up != node:
        grand = parent[up]
        if grand != up:
            parent[node] = grand
        node = up
        up = parent[node]
    return node


@wp.func
def unite(parent: wp.array(dtype=int), a: int, b: int):
    """Join the components of items ``a`` and ``b``: the larger root is hooked under the smaller one, retried when
    another thread hooked it first (compare-and-swap on a root that is still a root)."""
    done = int(0)
    while done == 0:
        ra = find_root(parent, a)
        rb = find_root(parent, b)
        if ra == rb:
            done = 1
        else:
            lo = wp.min(ra, rb)
            hi = wp.max(ra, rb)
            if wp.atomic_cas(parent, hi, hi, lo) == hi:
                done = 1


@wp.kernel
def init_items_kernel(
    # Model:
    node_mass: wp.array(dtype=float),
    particle_motion: wp.array(dtype=int),
    # State in:
    node_count_in: wp.array(dtype=int),
    particle_count_in: wp.array(dtype=int),
    # Out:
    is_item: wp.array(dtype=int),
    parent: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per item slot (node_capacity + particle_capacity)
    parent[i] = i
    node_capacity = node_mass.shape[0]
    live = int(0)
    if i < node_capacity:
        # A node all of whose tets converted has no mass left: no material, no fragment.
        if i < node_count_in[0] and node_mass[i] > 0.0:
            live = 1
    else:
        p = i - node_capacity
        # Spheres the scene holds (fixed, prescribed) are boundaries, not material.
        if p < particle_count_in[0] and particle_motion[p] == 0:
            live = 1
    is_item[i] = live


@wp.kernel
def unite_tets_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    tet_count_in: wp.array(dtype=int),
    tet_active_in: wp.array(dtype=int),
    # In:
    is_item: wp.array(dtype=int),
    # Out:
    parent: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot
    if t >= tet_count_in[0] or tet_active_in[t] == 0:
        return
    nodes = tet_nodes[t]
    for k in range(1, 4):
        if is_item[nodes[0]] != 0 and is_item[nodes[k]] != 0:
            unite(parent, nodes[0], nodes[k])


@wp.kernel
def unite_pairs_kernel(
    # In:
    count: wp.array(dtype=int),
    item_a: wp.array(dtype=int),
    item_b: wp.array(dtype=int),
    broken: wp.array(dtype=int),
    offset: int,
    is_item: wp.array(dtype=int),
    # Out:
    parent: wp.array(dtype=int),
):
    k = wp.tid()  # one thread per link slot (cohesive element, joint element or bond; over its capacity)
    if k >= count[0] or broken[k] != 0:
        return
    a = item_a[k] + offset
    b = item_b[k] + offset
    if is_item[a] != 0 and is_item[b] != 0:
        unite(parent, a, b)


@wp.kernel
def unite_couplings_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    tet_active_in: wp.array(dtype=int),
    coupling_count_in: wp.array(dtype=int),
    coupling_particle_in: wp.array(dtype=int),
    coupling_tet_in: wp.array(dtype=int),
    # In:
    node_capacity: int,
    is_item: wp.array(dtype=int),
    # Out:
    parent: wp.array(dtype=int),
):
    k = wp.tid()  # one thread per coupling slot
    if k >= coupling_count_in[0]:
        return
    t = coupling_tet_in[k]
    # A coupling into a tet that has converted too is released (awaiting compaction): it holds nothing.
    if tet_active_in[t] == 0:
        return
    sphere = node_capacity + coupling_particle_in[k]
    node = tet_nodes[t][0]  # the tet itself joins its four nodes
    if is_item[sphere] != 0 and is_item[node] != 0:
        unite(parent, sphere, node)


@wp.kernel
def flag_roots_kernel(
    # In:
    is_item: wp.array(dtype=int),
    # Out:
    parent: wp.array(dtype=int),
    is_root: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per item slot
    if is_item[i] == 0:
        is_root[i] = 0
        return
    root = find_root(parent, i)
    parent[i] = root
    if root == i:
        is_root[i] = 1
    else:
        is_root[i] = 0


@wp.kernel
def fragment_labels_kernel(
    # In:
    is_item: wp.array(dtype=int),
    parent: wp.array(dtype=int),
    is_root: wp.array(dtype=int),
    root_offset: wp.array(dtype=int),
    # Out:
    label: wp.array(dtype=int),
    fragment_count: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per item slot
    if is_item[i] != 0:
        # Roots are numbered by the exclusive scan in item order: fragment ids follow their smallest items.
        label[i] = root_offset[parent[i]]
    else:
        label[i] = -1
    last = is_item.shape[0] - 1
    if i == last:
        fragment_count[0] = root_offset[last] + is_root[last]


@wp.kernel
def unite_masked_tets_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_mask: wp.array(dtype=int),
    # State in:
    tet_count_in: wp.array(dtype=int),
    tet_active_in: wp.array(dtype=int),
    # In:
    is_item: wp.array(dtype=int),
    # Out:
    parent: wp.array(dtype=int),
):
    """The blocks of rigid mode (warpdem.stages.rigid): only deformable tets (``tet_active`` 1) where ``tet_mask`` is
    set unite their nodes; no element, bond or coupling glues anything."""
    t = wp.tid()  # one thread per tet slot
    if t >= tet_count_in[0] or tet_active_in[t] != 1 or tet_mask[t] == 0:
        return
    nodes = tet_nodes[t]
    for k in range(1, 4):
        if is_item[nodes[0]] != 0 and is_item[nodes[k]] != 0:
            unite(parent, nodes[0], nodes[k])
