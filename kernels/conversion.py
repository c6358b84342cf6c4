"""Adaptive FEM→DEM conversion (CIMNE §4–5, DESIGN.md stage 7): the conversion properties of a material, and the
kernels of the between-steps conversion pass (criterion per tet, spawning spheres and their bonds).

The pass (warpdem/stages/conversion.py) runs them in this order: ``flag_conversion_kernel`` (criterion) → exclusive scan
of the flags (sphere slots) → ``count_conversion_links_kernel`` over the stars of all live tets (it also marks the
converting tets and their edge neighbours) → ``edge_degree_kernel`` for the marked tets alone → exclusive scans
(bond and coupling slots) → the host grows the capacities → ``spawn_spheres_kernel`` →
``write_conversion_bonds_kernel`` (kernels/conversion_bonds.py) → bonds re-sorted by key →
``relump_converted_nodes_kernel`` over the nodes the converted tets held → couplings of converted tets released →
``write_conversion_couplings_kernel``.
"""

from __future__ import annotations

import warp as wp

from .coupling import coupling_gap, current_barycentric
from .tets import TET_ACTIVE, TetMaterial
from .topology import local_index

wp.set_module_options({"enable_backward": False})

CRITERION_TRESCA = wp.constant(0)
CRITERION_RANKINE = wp.constant(1)
CRITERION_MOHR_COULOMB = wp.constant(2)

NEVER = wp.constant(3.4e38)
"""Strength of a material that never converts [Pa]."""

F32_EPS = wp.constant(1.1920929e-7)
"""float32 machine epsilon: the sphere radius keeps 8 ulps of the larger of |centroid| and the tet's size clear of
the faces, so float32 node positions (ulp(|x|)/2) never make a new sphere overlap its own tet's neighbours."""


@wp.struct
class ConversionMaterial:
    """Conversion properties of one material (index = material id).

    Attributes:
        criterion: CRITERION_TRESCA ((σ1 − σ3)/2 ≥ f τ_f), CRITERION_RANKINE (σ1 ≥ f T_f) or CRITERION_MOHR_COULOMB
            ((σ1 (1 + sin φ) − σ3 (1 − sin φ)) / (2 c cos φ) ≥ f, tension positive: the uniaxial tensile strength
            is 2 c cos φ / (1 + sin φ), the compressive one 2 c cos φ / (1 − sin φ)), int32.
        fraction: f, the fraction of the strength at which a tet converts (0.9: CIMNE's 90 %) [-].
        tresca_strength: τ_f [Pa] (a very large value, 3.4e38: never by Tresca).
        tensile_strength: T_f [Pa] (Rankine; also the bonds' tensile strength).
        cohesion: c of Mohr–Coulomb [Pa].
        friction_angle: φ of Mohr–Coulomb [rad].
        bond_modulus: κ E, the modulus of the new bonds' normal springs k_b = κ E V_b / L_b² [Pa]
            (warpdem.stages.lattice: the edge network's energy equivalence, κ measured on a bar).
        bond_shear_ratio: k_s / k_n of the new bonds (0: normal springs alone; the edge network is rigid) [-].
        bond_tensile_strength: the new bonds' tensile strength (κ / S) T_f per unit A_b = V_b / L_b [Pa]: a bond
            breaks at the stretch L_b T_f / (S E) (S = warpdem.stages.lattice.STRENGTH_FACTOR), so a bar fails at T_f.
        bond_shear_strength: (κ / S) τ_f (T_f without τ_f) [Pa] (inactive without shear springs).
        converts: 1 when the material converts at all, else 0.
    """

    criterion: int
    fraction: float
    tresca_strength: float
    tensile_strength: float
    cohesion: float
    friction_angle: float
    bond_modulus: float
    bond_shear_ratio: float
    bond_tensile_strength: float
    bond_shear_strength: float
    converts: int


@wp.func
def principal_extremes(s: wp.mat33) -> wp.vec2:
    """(σ1, σ3): the largest and smallest principal stress of a symmetric stress [Pa] (wp.eig3, tension positive)."""
    _q, d = wp.eig3(s)
    return wp.vec2(wp.max(d[0], wp.max(d[1], d[2])), wp.min(d[0], wp.min(d[1], d[2])))


@wp.func
def conversion_measure(s: wp.mat33, mat: ConversionMaterial) -> float:
    """The criterion's stress over its strength [-]: the tet converts when this reaches ``mat.fraction``.

    Tresca (σ1 − σ3) / (2 τ_f); Rankine σ1 / T_f; Mohr–Coulomb (σ1 (1 + sin φ) − σ3 (1 − sin φ)) / (2 c cos φ)
    (CIMNE §5 step 3: point-wise stresses at the element centroid, constant in a linear tet)."""
    p = principal_extremes(s)
    if mat.criterion == CRITERION_RANKINE:
        return p[0] / mat.tensile_strength
    if mat.criterion == CRITERION_MOHR_COULOMB:
        sin_phi = wp.sin(mat.friction_angle)
        return (p[0] * (1.0 + sin_phi) - p[1] * (1.0 - sin_phi)) / (2.0 * mat.cohesion * wp.cos(mat.friction_angle))
    return (p[0] - p[1]) / (2.0 * mat.tresca_strength)


@wp.kernel
def flag_conversion_kernel(
    # Model:
    tet_material: wp.array(dtype=int),
    conversion_material_table: wp.array(dtype=ConversionMaterial),
    tet_may_convert: wp.array(dtype=int),
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    tet_stress: wp.array(dtype=wp.mat33),
    # In:
    forced: wp.array(dtype=int),
    use_forced: int,
    # Out:
    flag: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot
    flag[t] = 0
    if t >= tet_count[0]:
        return
    if tet_active[t] != TET_ACTIVE:
        return
    if use_forced != 0:
        flag[t] = wp.where(forced[t] != 0, 1, 0)
        return
    if tet_may_convert[t] == 0:
        return
    mat = conversion_material_table[tet_material[t]]
    if mat.converts == 0:
        return
    # not (< f) rather than ≥ f: a non-finite stress converts (the guard reports it; nothing is left half-done).
    if not (conversion_measure(tet_stress[t], mat) < mat.fraction):
        flag[t] = 1


@wp.kernel
def scan_total_kernel(
    # In:
    flag: wp.array(dtype=int),
    offset: wp.array(dtype=int),
    # Out:
    total: wp.array(dtype=int),
):
    _ = wp.tid()  # one thread: the sum of an exclusive scan is its last offset plus its last entry
    last = flag.shape[0] - 1
    total[0] = offset[last] + flag[last]


@wp.func
def shares_face(n: wp.vec4i, face: wp.vec3i) -> bool:
    """Whether tet nodes ``n`` hold the three nodes of ``face`` (the face is still shared, not cut by a crack)."""
    hits = int(0)
    for a in range(3):
        for b in range(4):
            if n[b] == face[a]:
                hits += 1
    return hits == 3


@wp.func
def edge_neighbor(tet_nodes: wp.array(dtype=wp.vec4i), star_tets: wp.array(dtype=int), t: int, a: int, e: int) -> int:
    """The tet at star slot e of tet t's local node a when it shares an edge (two nodes or more) with t and a is the
    first node of t it holds (so each edge neighbour is seen once, scanning a = 0..3 and each star in order), else
    -1. Nodes split by a crack are different nodes: no neighbour across a crack or a joint."""
    n = star_tets[e]
    if n == t:
        return -1
    # n is in the star of t's node a, so it holds that node: it is an edge neighbour seen here when it holds none of
    # t's nodes before a and one after it (at most 12 comparisons, with early exits: this test runs ~100 times per
    # converting tet and pass).
    nodes = tet_nodes[t]
    other = tet_nodes[n]
    for i in range(a):
        if local_index(other, nodes[i]) >= 0:
            return -1
    for i in range(a + 1, 4):
        if local_index(other, nodes[i]) >= 0:
            return n
    return -1


@wp.func
def edge_degree(
    tet_nodes: wp.array(dtype=wp.vec4i),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    t: int,
) -> int:
    """Z_t: the tets of the stars that share an edge with tet t (warpdem.stages.lattice), each seen once
    (edge_neighbor)."""
    z = int(0)
    nodes = tet_nodes[t]
    for a in range(4):
        v = nodes[a]
        for e in range(star_offset[v], star_offset[v] + star_count[v]):
            if edge_neighbor(tet_nodes, star_tets, t, a, e) >= 0:
                z += 1
    return z


@wp.kernel
def edge_degree_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # State in:
    tet_count: wp.array(dtype=int),
    # In:
    needed: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # Out:
    degree: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot: Z_t of the tets the pass reads it for (``needed``), else 0
    degree[t] = 0
    if t >= tet_count[0] or needed[t] == 0:
        return
    degree[t] = edge_degree(tet_nodes, star_offset, star_count, star_tets, t)


@wp.func
def bonds_to(tet_sphere: wp.array(dtype=int), flag: wp.array(dtype=int), t: int, n: int) -> bool:
    """Whether converting tet t's sphere owns a bond to edge neighbour n's: n converted in an earlier pass, or
    converts in this one with a larger index (each bond has one owner, so it is written once)."""
    if tet_sphere[n] >= 0:
        return True
    return flag[n] != 0 and n > t


@wp.func
def couples_to(tet_active: wp.array(dtype=int), flag: wp.array(dtype=int), n: int) -> bool:
    """Whether edge neighbour n stays a tet through this pass (active, not converting): the sphere couples to it."""
    return tet_active[n] == TET_ACTIVE and flag[n] == 0


@wp.kernel
def count_conversion_links_kernel(
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
    needed: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot: the bonds its new sphere owns and its couplings (before the pass)
    bonds[t] = 0
    couplings[t] = 0
    if t >= tet_count[0] or flag[t] == 0:
        return
    # The tets whose Z the bonds and couplings of this one read: itself and its edge neighbours (``needed`` zeroed
    # before the launch; several threads may write the same 1).
    needed[t] = 1
    nb = int(0)
    nc = int(0)
    nodes = tet_nodes[t]
    for a in range(4):
        v = nodes[a]
        for e in range(star_offset[v], star_offset[v] + star_count[v]):
            n = edge_neighbor(tet_nodes, star_tets, t, a, e)
            if n < 0:
                continue
            needed[n] = 1
            if bonds_to(tet_sphere, flag, t, n):
                nb += 1
            elif couples_to(tet_active, flag, n):
                nc += 1
    bonds[t] = nb
    couplings[t] = nc


@wp.func
def lattice_stiffness(mat_t: ConversionMaterial, mat_n: ConversionMaterial, volume: float, length: float) -> float:
    """k_b = κ E V_b / L_b² [N/m] of a bond of the edge network (warpdem.stages.lattice: energy equivalence under an
    affine strain, with the factor κ measured on a bar); E the mean of the two materials' (``bond_modulus`` holds κ E),
    V_b = V_t / Z_t + V_n / Z_n the volume the bond stands for."""
    return 0.5 * (mat_t.bond_modulus + mat_n.bond_modulus) * volume / (length * length)


@wp.func
def capped_coupling_stiffness(
    kn: float, bary: wp.vec4, nodes: wp.vec4i, node_mass: wp.array(dtype=float), ms: float
) -> float:
    """k = k_n min(1, 2 / (1 + m_s Σ N_a² / m_a)) [N/m] (warpdem.stages.coupling.coupling_stiffness)."""
    ratio = float(0.0)
    for k in range(4):
        ratio += bary[k] * bary[k] / node_mass[nodes[k]]
    return kn * wp.min(1.0, 2.0 / (1.0 + ratio * ms))


@wp.func
def centroid64(node_ref_q: wp.array(dtype=wp.vec3), node_u: wp.array(dtype=wp.vec3), n: wp.vec4i) -> wp.vec3d:
    """Current centroid Σ (X_a + u_a) / 4 in float64 [m] (X + u keeps the displacements' precision far from the
    origin; the same sum the energy books use for the nodes' gravity potential)."""
    c = wp.vec3d(0.0, 0.0, 0.0)
    for a in range(4):
        c += wp.vec3d(node_ref_q[n[a]]) + wp.vec3d(node_u[n[a]])
    return c * wp.float64(0.25)


@wp.func
def face_distance(x: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """Distance from x to the plane of the triangle (a, b, c) [m]."""
    nrm = wp.normalize(wp.cross(b - a, c - a))
    return wp.abs(wp.dot(x - a, nrm))


@wp.func
def centroid_clearance(r0: wp.vec3, r1: wp.vec3, r2: wp.vec3, r3: wp.vec3) -> float:
    """The smallest distance from a tet's centroid to its faces, h_min / 4 [m], from its nodes relative to the
    centroid (r_a = x_a − c)."""
    origin = wp.vec3(0.0)
    return wp.min(
        wp.min(face_distance(origin, r1, r2, r3), face_distance(origin, r0, r3, r2)),
        wp.min(face_distance(origin, r0, r1, r3), face_distance(origin, r0, r2, r1)),
    )


@wp.func
def clear_radius(clearance: float, scale: float) -> float:
    """A sphere radius that keeps ``clearance`` [m] less 8 float32 ulps of ``scale`` (the larger of |centroid| and the
    tet's size) [m]: float32 node positions never make it overlap what lies ``clearance`` away. At least half the
    clearance: a tiny tet far out, where float32 cannot resolve it, still gets a sphere."""
    return wp.max(clearance - 8.0 * F32_EPS * scale, 0.5 * clearance)


@wp.func
def tet_spin(
    r0: wp.vec3, r1: wp.vec3, r2: wp.vec3, r3: wp.vec3, v0: wp.vec3, v1: wp.vec3, v2: wp.vec3, v3: wp.vec3
) -> wp.vec3:
    """ω [rad/s]: the axial vector of the antisymmetric part of the velocity gradient L = [v_a − v_0] [x_a − x_0]⁻¹
    (current configuration; nodes r_a, velocities v_a)."""
    dx = wp.matrix_from_cols(r1 - r0, r2 - r0, r3 - r0)
    dv = wp.matrix_from_cols(v1 - v0, v2 - v0, v3 - v0)
    grad = dv * wp.inverse(dx)
    return wp.vec3(0.5 * (grad[2, 1] - grad[1, 2]), 0.5 * (grad[0, 2] - grad[2, 0]), 0.5 * (grad[1, 0] - grad[0, 1]))


@wp.kernel
def spawn_spheres_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    conversion_part: int,
    spheres_per_tet: int,
    # State in:
    tet_count: wp.array(dtype=int),
    particle_count: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    # In:
    flag: wp.array(dtype=int),
    offset: wp.array(dtype=int),
    strain_energy: wp.array(dtype=wp.float64),
    # Model out:
    particle_radius: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    particle_inv_mass: wp.array(dtype=float),
    particle_inv_inertia: wp.array(dtype=float),
    particle_material: wp.array(dtype=int),
    particle_motion: wp.array(dtype=int),
    particle_part: wp.array(dtype=int),
    particle_id: wp.array(dtype=int),
    # State out:
    particle_q: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    particle_q_at_build: wp.array(dtype=wp.vec3d),
    tet_active: wp.array(dtype=int),
    tet_sphere: wp.array(dtype=int),
    # Out:
    node_touched: wp.array(dtype=int),
    released: wp.array(dtype=wp.float64),
):
    """Spawn the spheres of each converting tet: ``spheres_per_tet`` = 1, one sphere at the centroid c with the tet's
    ρ V₀, its mean velocity and its spin; = 4, sphere a (slot ``tet_sphere[t] + a``) at s_a = c + r_a / 2, the centroid
    of the corner sub-tet of the 1:8 midpoint subdivision at node a, with node a's lumped share ρ V₀ / 4 and the linear
    velocity field at s_a (kernels/multisphere.py has the four-sphere lattice)."""
    t = wp.tid()  # one thread per tet slot: a converting tet writes its spheres at particle_count + k × its scan offset
    released[t] = wp.float64(0.0)
    if t >= tet_count[0] or flag[t] == 0:
        return
    first = particle_count[0] + spheres_per_tet * offset[t]
    n = tet_nodes[t]
    mat = tet_material_table[tet_material[t]]
    node_mass = 0.25 * mat.density * tet_volume[t]  # each node's lumped share ρ V₀ / 4 (×0.25 is exact)
    # One sphere takes exactly the ρ V₀ the four nodes lose; four take one node's share each.
    mass = mat.density * tet_volume[t]
    share = 1.0  # the sphere's clearance from the faces, relative to the centroid's h_k / 4
    if spheres_per_tet == 4:
        mass = node_mass
        share = 0.5
    c64 = centroid64(node_ref_q, node_u, n)
    c = wp.vec3(c64)
    r0 = wp.vec3(wp.vec3d(node_ref_q[n[0]]) + wp.vec3d(node_u[n[0]]) - c64)
    r1 = wp.vec3(wp.vec3d(node_ref_q[n[1]]) + wp.vec3d(node_u[n[1]]) - c64)
    r2 = wp.vec3(wp.vec3d(node_ref_q[n[2]]) + wp.vec3d(node_u[n[2]]) - c64)
    r3 = wp.vec3(wp.vec3d(node_ref_q[n[3]]) + wp.vec3d(node_u[n[3]]) - c64)
    # Radius: the smallest distance from the centroid to a face (h_k / 4 of the tet's heights; a corner sub-tet's
    # centroid lies h_k / 8 from its faces), less a float32 margin of 8 ulps of the larger of |c| and the tet's size,
    # so each sphere touches its (sub-)tet's nearest face and overlaps no neighbour (tet or sphere) at birth.
    scale = wp.max(wp.max(wp.abs(c[0]), wp.max(wp.abs(c[1]), wp.abs(c[2]))), wp.length(r0))
    radius = clear_radius(share * centroid_clearance(r0, r1, r2, r3), scale)
    v0 = node_qd[n[0]]
    v1 = node_qd[n[1]]
    v2 = node_qd[n[2]]
    v3 = node_qd[n[3]]
    vbar = 0.25 * (v0 + v1 + v2 + v3)  # Σ_a (ρ V₀ / 4) v_a = ρ V₀ v̄: the tet's momentum
    omega = tet_spin(r0, r1, r2, r3, v0, v1, v2, v3)  # every sphere of the tet
    inertia = 0.4 * mass * radius * radius
    ke_spheres = wp.float64(0.0)
    for a in range(spheres_per_tet):
        slot = first + a
        q = c64
        v = vbar
        if spheres_per_tet == 4:
            r = r0
            va = v0
            if a == 1:
                r = r1
                va = v1
            elif a == 2:
                r = r2
                va = v2
            elif a == 3:
                r = r3
                va = v3
            # The linear velocity field at s_a: v̄ + (v_a − v̄)/2. Σ_a (m/4) v(s_a) = m v̄ exactly (Σ_a v_a = 4 v̄).
            q = c64 + wp.float64(0.5) * wp.vec3d(r)
            v = 0.5 * (va + vbar)
        particle_radius[slot] = radius
        particle_mass[slot] = mass
        particle_inv_mass[slot] = 1.0 / mass
        particle_inv_inertia[slot] = 1.0 / inertia
        particle_material[slot] = tet_material[t]
        particle_motion[slot] = 0
        particle_part[slot] = conversion_part
        particle_id[slot] = slot
        particle_q[slot] = q
        particle_q_at_build[slot] = q
        particle_qd[slot] = v
        particle_omega[slot] = omega
        ke_spheres += wp.float64(0.5) * wp.float64(mass) * wp.float64(wp.dot(v, v))
        ke_spheres += wp.float64(0.5) * wp.float64(inertia) * wp.float64(wp.dot(omega, omega))
    ke_nodes = wp.float64(0.0)
    for a in range(4):
        node_touched[n[a]] = 1
        va = node_qd[n[a]]
        ke_nodes += wp.float64(0.5) * wp.float64(node_mass) * wp.float64(wp.dot(va, va))
    tet_active[t] = 0
    tet_sphere[t] = first
    # What the mechanical books lose: the strain energy, and the nodes' kinetic energy beyond the spheres' (the
    # motion relative to the centroid that neither the spheres' orbits nor their spins carry).
    released[t] = strain_energy[t] + ke_nodes - ke_spheres


@wp.kernel
def relump_converted_nodes_kernel(
    # Model:
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    # State in:
    node_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    # In:
    node_touched: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # Model out:
    node_mass: wp.array(dtype=float),
    node_inv_mass: wp.array(dtype=float),
    node_damping: wp.array(dtype=float),
    node_motion: wp.array(dtype=int),
    # State out:
    node_qd: wp.array(dtype=wp.vec3),
):
    v = wp.tid()  # one thread per node slot; only the nodes of converted tets change
    if v >= node_count[0] or node_touched[v] == 0:
        return
    # Σ ρ V₀ / 4 over the node's remaining active tets, in ascending tet order (deterministic sums); the star holds
    # every live tet of the node, converted ones included.
    mass = float(0.0)
    damping = float(0.0)
    start = star_offset[v]
    for e in range(start, start + star_count[v]):
        t = star_tets[e]
        if tet_active[t] == 0:  # (converted: as the stars of active tets skip it, kernels/topology.py)
            continue
        mat = tet_material_table[tet_material[t]]
        quarter = 0.25 * mat.density * tet_volume[t]
        mass += quarter
        damping += quarter * mat.alpha
    node_mass[v] = mass
    if mass > 0.0:
        node_damping[v] = damping / mass
        if node_inv_mass[v] != 0.0:  # a held node stays held
            node_inv_mass[v] = 1.0 / mass
    else:
        # No tet left: the node is deactivated — no mass, held (gravity does not move it), at rest; it has no
        # boundary face, so the contact stages skip it (zero penalty stiffness).
        node_damping[v] = 0.0
        node_inv_mass[v] = 0.0
        node_motion[v] = 1
        node_qd[v] = wp.vec3(0.0)


@wp.kernel
def add_released_kernel(
    # In:
    total: wp.array(dtype=wp.float64),
    converted: wp.array(dtype=int),
    spawned: wp.array(dtype=int),
    # State out:
    energy_released_conversion: wp.array(dtype=wp.float64),
    tets_converted_total: wp.array(dtype=int),
    spheres_spawned_total: wp.array(dtype=int),
    particle_count: wp.array(dtype=int),
):
    _ = wp.tid()  # one thread: the pass's totals into the state's counters
    energy_released_conversion[0] = energy_released_conversion[0] + total[0]
    tets_converted_total[0] = tets_converted_total[0] + converted[0]
    spheres_spawned_total[0] = spheres_spawned_total[0] + spawned[0]
    particle_count[0] = particle_count[0] + spawned[0]


@wp.kernel
def add_bond_count_kernel(
    # In:
    counts: wp.array(dtype=int),
    # State out:
    bond_count: wp.array(dtype=int),
):
    _ = wp.tid()  # one thread: the pass's new bonds (counts[1]) join the live ones
    bond_count[0] = bond_count[0] + counts[1]


@wp.kernel
def iota_kernel(
    # Out:
    order: wp.array(dtype=int),
):
    b = wp.tid()  # one thread per slot: the identity order
    order[b] = b


@wp.kernel
def write_conversion_couplings_kernel(
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
    degree: wp.array(dtype=int),
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
    t = wp.tid()  # one thread per tet slot: a converted tet writes its sphere's couplings (after compaction)
    if t >= tet_count[0] or flag[t] == 0:
        return
    c = coupling_count[0] + offset[t]
    p = tet_sphere[t]
    x = particle_q[p]
    nodes = tet_nodes[t]
    for a in range(4):
        v = nodes[a]
        for e in range(star_offset[v], star_offset[v] + star_count[v]):
            nbr = edge_neighbor(tet_nodes, star_tets, t, a, e)
            if nbr < 0:
                continue
            if tet_sphere[nbr] >= 0 or not couples_to(tet_active, flag, nbr):
                continue
            n = tet_nodes[nbr]
            # N_a at the sphere's centre in the neighbour's current configuration: Σ N_a x_a = x_p, a spring born
            # relaxed (CIMNE eq. 9 with zero residual).
            bary = current_barycentric(x, n, node_ref_q, node_u)
            # The stiffness rule (warpdem.stages.coupling.coupling_stiffness): k = k_n min(1, 2 / (1 + m_s Σ N_a² /
            # m_a)), k_n the bond the sphere would have with a sphere at the neighbour's centroid.
            mid = wp.vec3d(0.0, 0.0, 0.0)
            for k in range(4):
                mid += wp.vec3d(node_ref_q[n[k]]) + wp.vec3d(node_u[n[k]])
            length = wp.length(wp.vec3(mid * wp.float64(0.25) - x))
            vb = tet_volume[t] / float(degree[t]) + tet_volume[nbr] / float(degree[nbr])
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
def add_coupling_count_kernel(
    # In:
    total: wp.array(dtype=int),
    # State out:
    coupling_count: wp.array(dtype=int),
):
    _ = wp.tid()  # one thread: the pass's new couplings join the live ones
    coupling_count[0] = coupling_count[0] + total[0]


@wp.kernel
def drop_converted_faces_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    face_tet: wp.array(dtype=int),
    hand_over: int,
    # State in:
    node_u: wp.array(dtype=wp.vec3),
    tet_sphere: wp.array(dtype=int),
    # Model out:
    face_nodes: wp.array(dtype=wp.vec3i),
    face_edge_a: wp.array(dtype=wp.vec3),
    face_edge_b: wp.array(dtype=wp.vec3),
    face_handed_area: wp.array(dtype=wp.vec3),
):
    f = wp.tid()  # one thread per loaded face: it stays while an active tet holds its three nodes
    n = face_nodes[f]
    if n[0] == n[1]:
        # Dropped before (a restart's collapsed triple, its edges from the scene: zeroed again; its hand-over, if
        # any, came with the checkpoint).
        face_edge_a[f] = wp.vec3(0.0)
        face_edge_b[f] = wp.vec3(0.0)
        return
    start = star_offset[n[0]]
    for e in range(start, start + star_count[n[0]]):
        if shares_face(tet_nodes[star_tets[e]], n):
            return
    if hand_over != 0:
        if tet_sphere[face_tet[f]] >= 0:
            # A pressure face of a tet that turned into spheres: its push goes on there with the area vector it has
            # now (kernels/loads.py, Hand-over), ½ (x1 - x0) × (x2 - x0) from its reference edges and displacements.
            ea = face_edge_a[f] + (node_u[n[1]] - node_u[n[0]])
            eb = face_edge_b[f] + (node_u[n[2]] - node_u[n[0]])
            face_handed_area[f] = 0.5 * wp.cross(ea, eb)
    # Its tet converted: the face is dropped, collapsed onto its first node with zero reference edges (zero area, so
    # no force and no work; a collapsed triple, as a checkpoint keeps it, is recognised as dropped).
    face_nodes[f] = wp.vec3i(n[0], n[0], n[0])
    face_edge_a[f] = wp.vec3(0.0)
    face_edge_b[f] = wp.vec3(0.0)
