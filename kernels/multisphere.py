"""Several spheres per converted tet (``spheres_per_tet`` = 4; warpdem/stages/multisphere.py has the design and its
reasons): the kernels of the conversion pass that differ from the one-sphere pass of kernels/conversion.py.

Sphere a of tet t (local node a) sits at s_a = (x_a + c) / 2, the centroid of the corner sub-tet at node a of the
1:8 midpoint subdivision, and lives in slot ``tet_sphere[t] + a``. Its bonds: the six between the spheres of its own
tet, and one to sphere a' of every converted tet t' that shares an edge through node a (t' holds node a as its
local node a'). The pass runs ``sub_edge_degree_kernel`` and ``count_sub_links_kernel`` (after the flags' scan and
the stars of all live tets) → exclusive scans → the host grows the capacities → kernels/conversion.py's
``spawn_spheres_kernel`` (with ``spheres_per_tet`` = 4) → ``write_sub_bonds_kernel`` → bonds re-sorted → nodes
re-lumped → couplings released → ``write_sub_couplings_kernel``.
"""

from __future__ import annotations

import warp as wp

from .conversion import (
    ConversionMaterial,
    bonds_to,
    capped_coupling_stiffness,
    centroid64,
    couples_to,
    lattice_stiffness,
)
from .conversion_bonds import write_lattice_bond
from .coupling import coupling_gap, current_barycentric

wp.set_module_options({"enable_backward": False})

SPHERES = wp.constant(4)
"""Spheres per tet of this sub-lattice (one per corner sub-tet)."""


@wp.func
def local_index(nodes: wp.vec4i, v: int) -> int:
    """The local index of node v in a tet's ``nodes`` (-1 when it holds no such node)."""
    for a in range(4):
        if nodes[a] == v:
            return a
    return -1


@wp.func
def edge_neighbor_through(tet_nodes: wp.array(dtype=wp.vec4i), star_tets: wp.array(dtype=int), t: int, e: int) -> int:
    """The tet at star slot e of one of tet t's nodes v when it shares an edge through v with t (it holds v and at
    least one more of t's nodes), else -1. Split nodes are different nodes: no neighbour across a crack."""
    n = star_tets[e]
    if n == t:
        return -1
    # n holds v (it is in v's star): it shares an edge through v when it holds another node of t too.
    nodes = tet_nodes[t]
    other = tet_nodes[n]
    held = int(0)
    for i in range(4):
        for j in range(4):
            if nodes[i] == other[j]:
                held += 1
    if held < 2:
        return -1
    return n


@wp.func
def sphere_volume_share(tet_volume: wp.array(dtype=float), sub_degree: wp.array(dtype=int), t: int, a: int) -> float:
    """V_s / Z_s of sphere a of tet t [m³]: its quarter of the tet's volume over its bonds in the full network (3 in
    its tet + one per tet sharing an edge through node a), so the bonds' V_b = Σ over both ends sum to V."""
    return 0.25 * tet_volume[t] / float(3 + sub_degree[SPHERES * t + a])


@wp.kernel
def sub_edge_degree_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    tet_count: wp.array(dtype=int),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # Out:
    sub_degree: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot: for each node a, the live tets sharing an edge through it
    for a in range(4):
        sub_degree[SPHERES * t + a] = 0
    if t >= tet_count[0]:
        return
    nodes = tet_nodes[t]
    for a in range(4):
        v = nodes[a]
        z = int(0)
        for e in range(star_offset[v], star_offset[v] + star_count[v]):
            if edge_neighbor_through(tet_nodes, star_tets, t, e) >= 0:
                z += 1
        sub_degree[SPHERES * t + a] = z


@wp.kernel
def count_sub_links_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    tet_sphere: wp.array(dtype=int),
    # In:
    flag: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # Out:
    bonds: wp.array(dtype=int),
    couplings: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot: the bonds its new spheres own and their couplings (before the pass)
    bonds[t] = 0
    couplings[t] = 0
    if t >= tet_count[0] or flag[t] == 0:
        return
    nb = int(6)  # the six bonds between its own four spheres
    nc = int(0)
    nodes = tet_nodes[t]
    for a in range(4):
        v = nodes[a]
        for e in range(star_offset[v], star_offset[v] + star_count[v]):
            n = edge_neighbor_through(tet_nodes, star_tets, t, e)
            if n < 0:
                continue
            if bonds_to(tet_sphere, flag, t, n):
                nb += 1
            elif couples_to(tet_active, flag, n):
                nc += 1
    bonds[t] = nb
    couplings[t] = nc


@wp.kernel
def write_sub_bonds_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    conversion_material_table: wp.array(dtype=ConversionMaterial),
    particle_capacity: int,
    # State in:
    tet_count: wp.array(dtype=int),
    bond_count: wp.array(dtype=int),
    particle_q: wp.array(dtype=wp.vec3d),
    tet_sphere: wp.array(dtype=int),
    # In:
    flag: wp.array(dtype=int),
    was_sphere: wp.array(dtype=int),
    offset: wp.array(dtype=int),
    sub_degree: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # State out:
    bond_i: wp.array(dtype=int),
    bond_j: wp.array(dtype=int),
    bond_key: wp.array(dtype=wp.int64),
    bond_rest_length: wp.array(dtype=float),
    bond_kn: wp.array(dtype=float),
    bond_ks: wp.array(dtype=float),
    bond_area: wp.array(dtype=float),
    bond_tensile_strength: wp.array(dtype=float),
    bond_shear_strength: wp.array(dtype=float),
    bond_damping: wp.array(dtype=float),
    bond_shear: wp.array(dtype=wp.vec3),
    bond_broken: wp.array(dtype=int),
    bond_energy_prev: wp.array(dtype=wp.vec2),
):
    t = wp.tid()  # one thread per tet slot: a converting tet writes the bonds it owns (count_sub_links_kernel)
    if t >= tet_count[0] or flag[t] == 0:
        return
    b = bond_count[0] + offset[t]
    first = tet_sphere[t]
    nodes = tet_nodes[t]
    ma = conversion_material_table[tet_material[t]]
    # Its own six (a < a2: i < j), then one per converted tet sharing an edge through each node, in star order.
    for a in range(4):
        for a2 in range(a + 1, 4):
            i = first + a
            j = first + a2
            length = wp.length(wp.vec3(particle_q[i] - particle_q[j]))
            vb = sphere_volume_share(tet_volume, sub_degree, t, a) + sphere_volume_share(tet_volume, sub_degree, t, a2)
            write_lattice_bond(
                b,
                i,
                j,
                particle_capacity,
                ma,
                ma,
                vb,
                length,
                bond_i,
                bond_j,
                bond_key,
                bond_rest_length,
                bond_kn,
                bond_ks,
                bond_area,
                bond_tensile_strength,
                bond_shear_strength,
                bond_damping,
                bond_shear,
                bond_broken,
                bond_energy_prev,
            )
            b += 1
    for a in range(4):
        v = nodes[a]
        for e in range(star_offset[v], star_offset[v] + star_count[v]):
            nbr = edge_neighbor_through(tet_nodes, star_tets, t, e)
            if nbr < 0:
                continue
            if not bonds_to(was_sphere, flag, t, nbr):
                continue
            a2 = local_index(tet_nodes[nbr], v)
            si = first + a
            sj = tet_sphere[nbr] + a2
            i = wp.min(si, sj)
            j = wp.max(si, sj)
            length = wp.length(wp.vec3(particle_q[i] - particle_q[j]))
            vb = sphere_volume_share(tet_volume, sub_degree, t, a) + sphere_volume_share(
                tet_volume, sub_degree, nbr, a2
            )
            mb = conversion_material_table[tet_material[nbr]]
            write_lattice_bond(
                b,
                i,
                j,
                particle_capacity,
                ma,
                mb,
                vb,
                length,
                bond_i,
                bond_j,
                bond_key,
                bond_rest_length,
                bond_kn,
                bond_ks,
                bond_area,
                bond_tensile_strength,
                bond_shear_strength,
                bond_damping,
                bond_shear,
                bond_broken,
                bond_energy_prev,
            )
            b += 1


@wp.kernel
def write_sub_couplings_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    conversion_material_table: wp.array(dtype=ConversionMaterial),
    particle_mass: wp.array(dtype=float),
    node_mass: wp.array(dtype=float),
    # State in:
    tet_count: wp.array(dtype=int),
    coupling_count: wp.array(dtype=int),
    particle_q: wp.array(dtype=wp.vec3d),
    node_u: wp.array(dtype=wp.vec3),
    tet_active: wp.array(dtype=int),
    tet_sphere: wp.array(dtype=int),
    # In:
    flag: wp.array(dtype=int),
    offset: wp.array(dtype=int),
    sub_degree: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # State out:
    coupling_particle: wp.array(dtype=int),
    coupling_tet: wp.array(dtype=int),
    coupling_bary: wp.array(dtype=wp.vec4),
    coupling_k: wp.array(dtype=float),
    coupling_energy_prev: wp.array(dtype=float),
    coupling_rest: wp.array(dtype=wp.vec3),
):
    t = wp.tid()  # one thread per tet slot: a converted tet writes its spheres' couplings (after compaction)
    if t >= tet_count[0] or flag[t] == 0:
        return
    c = coupling_count[0] + offset[t]
    nodes = tet_nodes[t]
    for a in range(4):
        v = nodes[a]
        p = tet_sphere[t] + a
        x = particle_q[p]
        for e in range(star_offset[v], star_offset[v] + star_count[v]):
            nbr = edge_neighbor_through(tet_nodes, star_tets, t, e)
            if nbr < 0:
                continue
            if tet_sphere[nbr] >= 0 or not couples_to(tet_active, flag, nbr):
                continue
            n = tet_nodes[nbr]
            # N_a at the sphere's centre in the neighbour's current configuration (born relaxed, CIMNE eq. 9).
            bary = current_barycentric(x, n, node_ref_q, node_u)
            # k_n of the bond the sphere would have with the neighbour's sphere at node v, (x_v + c_n) / 2.
            a2 = local_index(n, v)
            xv = wp.vec3d(node_ref_q[v]) + wp.vec3d(node_u[v])
            mate = wp.float64(0.5) * (xv + centroid64(node_ref_q, node_u, n))
            length = wp.length(wp.vec3(mate - x))
            vb = sphere_volume_share(tet_volume, sub_degree, t, a) + sphere_volume_share(
                tet_volume, sub_degree, nbr, a2
            )
            kn = lattice_stiffness(
                conversion_material_table[tet_material[t]], conversion_material_table[tet_material[nbr]], vb, length
            )
            coupling_particle[c] = p
            coupling_tet[c] = nbr
            coupling_bary[c] = bary
            coupling_k[c] = capped_coupling_stiffness(kn, bary, n, node_mass, particle_mass[p])
            coupling_energy_prev[c] = 0.0
            # The gap N_a leaves in float32 (~ε₃₂ × the tet's size) is the spring's rest gap: born relaxed.
            coupling_rest[c] = wp.vec3(coupling_gap(x, n, bary, node_ref_q, node_u))
            c += 1


@wp.kernel
def scale_count_kernel(
    # In:
    count: wp.array(dtype=int),
    factor: int,
    # Out:
    scaled: wp.array(dtype=int),
):
    _ = wp.tid()  # one thread: spheres spawned = converting tets × spheres per tet
    scaled[0] = count[0] * factor
