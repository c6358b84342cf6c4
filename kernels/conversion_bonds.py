"""The bonds of converted tets (CIMNE §4–5, DESIGN.md stage 7; warpdem/stages/lattice.py): each bond of the edge network
written into its slot, born relaxed, and the bonds' re-sort by key after the pass (``bond_sort_keys_kernel`` →
host sort → ``inverse_order_kernel``). kernels/conversion.py runs the rest of the conversion pass;
kernels/multisphere.py writes the four-sphere lattice with :func:`write_lattice_bond` too.
"""

from __future__ import annotations

import warp as wp

from .conversion import ConversionMaterial, bonds_to, edge_neighbor, lattice_stiffness

wp.set_module_options({"enable_backward": False})


@wp.func
def write_lattice_bond(
    b: int,
    i: int,
    j: int,
    particle_capacity: int,
    ma: ConversionMaterial,
    mb: ConversionMaterial,
    vb: float,
    length: float,
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
    """Write bond slot b between spheres i < j of the converted lattice (one or four spheres per tet): the share vb
    [m³] of volume it carries, its length [m] and the conversion materials of its two ends. Born relaxed (rest length =
    length: the strain energy the tets held is booked as released), normal springs alone (k_s = 0: the edge network
    is rigid, warpdem.stages.lattice), no dashpot, no history."""
    bond_i[b] = i
    bond_j[b] = j
    bond_key[b] = wp.int64(i) * wp.int64(particle_capacity) + wp.int64(j)
    bond_rest_length[b] = length
    bond_kn[b] = lattice_stiffness(ma, mb, vb, length)
    bond_ks[b] = 0.0
    bond_area[b] = vb / length
    # k_b L / (E A_b) = κ: a strength κ T_f / S per unit A_b breaks the bond at the stretch L T_f / (S E).
    bond_tensile_strength[b] = wp.min(ma.bond_tensile_strength, mb.bond_tensile_strength)
    bond_shear_strength[b] = wp.min(ma.bond_shear_strength, mb.bond_shear_strength)
    bond_damping[b] = 0.0
    bond_shear[b] = wp.vec3(0.0)
    bond_broken[b] = 0
    bond_energy_prev[b] = wp.vec2(0.0)


@wp.kernel
def write_conversion_bonds_kernel(
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
    degree: wp.array(dtype=int),
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
    t = wp.tid()  # one thread per tet slot: a converting tet writes the bonds it owns (count_conversion_links)
    if t >= tet_count[0] or flag[t] == 0:
        return
    b = bond_count[0] + offset[t]
    nodes = tet_nodes[t]
    for a in range(4):
        v = nodes[a]
        for e in range(star_offset[v], star_offset[v] + star_count[v]):
            nbr = edge_neighbor(tet_nodes, star_tets, t, a, e)
            if nbr < 0:
                continue
            if not bonds_to(was_sphere, flag, t, nbr):
                continue
            si = tet_sphere[t]
            sj = tet_sphere[nbr]
            i = wp.min(si, sj)
            j = wp.max(si, sj)
            length = wp.length(wp.vec3(particle_q[i] - particle_q[j]))
            vb = tet_volume[t] / float(degree[t]) + tet_volume[nbr] / float(degree[nbr])
            ma = conversion_material_table[tet_material[t]]
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
def bond_sort_keys_kernel(
    # State in:
    bond_count: wp.array(dtype=int),
    bond_key: wp.array(dtype=wp.int64),
    # Out:
    keys: wp.array(dtype=wp.int64),
    order: wp.array(dtype=int),
):
    b = wp.tid()  # one thread per bond slot: (key, slot) pairs for the radix sort
    if b >= bond_count[0]:
        return
    keys[b] = bond_key[b]
    order[b] = b


@wp.kernel
def inverse_order_kernel(
    # State in:
    bond_count: wp.array(dtype=int),
    # In:
    order: wp.array(dtype=int),
    # Out:
    old_to_new: wp.array(dtype=int),
):
    b = wp.tid()  # one thread per sorted slot: old slot order[b] moves to b
    if b >= bond_count[0]:
        return
    old_to_new[order[b]] = b
