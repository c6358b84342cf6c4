"""Joints: pre-split faces (the topology pass of ldec_fem_dem_fracture.txt §2.2 run on given faces, §3) and the
cohesive joint interface elements between the daughter nodes.

The topology of the pass (stars, face neighbours, components, node duplication, remaps) lives in
:mod:`warpdem.kernels.topology`, shared with nodal fracture.

Joint interface element (a cohesive element A–B between two daughter nodes, as LDEC's, but with a joint's
strengths): relative displacement g = u_B - u_A (equal reference positions), normal n out of A's joint face
(current positions), g_n = g · n (> 0 opening), g_t = g - g_n n. While intact it is a spring F_B = -k_n g_n n -
k_t g_t (F_A = -F_B) with a dashpot on the relative velocity. It fails in tension when k_n g_n > σ_t A and in
shear when |k_t g_t| > c A + μ max(0, -k_n g_n) (Mohr–Coulomb with cohesion c); a failed element carries nothing
and the pair is left to the frictional node–face contact (kernels/fem_contact.py).
"""

from __future__ import annotations

import warp as wp

from .contact import ContactPair
from .tets import TetMaterial
from .topology import face_in_tet, split_node_index, star_find, tet_face, triangle_area_vector

wp.set_module_options({"enable_backward": False})

NO_KEY = wp.constant(wp.int64(0x7FFFFFFFFFFFFFFF))
"""Sort key of an emitted joint-pair slot that holds no pair (sorted past every real key)."""

JOINT_INTACT = wp.constant(0)
JOINT_BROKEN_TENSION = wp.constant(1)
JOINT_BROKEN_SHEAR = wp.constant(2)


@wp.struct
class JointMaterial:
    """Properties of one joint set, one entry per set.

    Attributes:
        contact: contact properties of the joint's faces: friction μ, shear/normal stiffness ratio (kt_ratio), and
            the damping ratio ζ of the normal and tangential dashpots (damp_n = damp_t = ζ of the restitution).
        cohesion: cohesion c of an intact joint [Pa].
        tensile_strength: tensile strength σ_t of an intact joint [Pa].
        stiffness_factor: penalty factor f of the joint's faces: a face of a tet of Young's modulus E and height h
            over the face is a spring of f E / h per unit area [-] (0 for a joint given a normal stiffness).
        face_normal_stiffness: the mesh-independent part of each face's spring, k_n / 2 per unit area for a joint
            of normal stiffness k_n [Pa/m] (both faces together make k_n); 0 for a joint given a penalty factor.
        bonded: 1 when the joint starts intact (c > 0 or σ_t > 0), 0 for a purely frictional joint.
    """

    contact: ContactPair
    cohesion: float
    tensile_strength: float
    stiffness_factor: float
    face_normal_stiffness: float
    bonded: int


@wp.func
def youngs_modulus(mat: TetMaterial) -> float:
    """E = μ (3λ + 2μ) / (λ + μ) [Pa] from the Lamé parameters."""
    return mat.mu * (3.0 * mat.lam + 2.0 * mat.mu) / (mat.lam + mat.mu)


# ----------------------------------------------------------------------------------------------------------------
# Pre-splitting joints.


@wp.kernel
def flag_joint_faces_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    # In:
    joint_face_nodes: wp.array(dtype=wp.vec3i),
    joint_face_set: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # Out:
    tet_face_joint: wp.array(dtype=int),
    joint_face_tets: wp.array(dtype=wp.vec2i),
    unmatched: wp.array(dtype=int),
):
    j = wp.tid()  # one thread per joint face: it tags the tet-face slots on both sides with its joint set
    f = joint_face_nodes[j]
    start = star_offset[f[0]]
    found = int(0)
    lo = int(-1)
    hi = int(-1)
    for e in range(start, start + star_count[f[0]]):  # ascending tet index
        t = star_tets[e]
        k = face_in_tet(tet_nodes[t], f[0], f[1], f[2])
        if k >= 0:
            tet_face_joint[4 * t + k] = joint_face_set[j]
            if found == 0:
                lo = t
            else:
                hi = t
            found += 1
    joint_face_tets[j] = wp.vec2i(lo, hi)
    if found != 2:
        wp.atomic_add(unmatched, 0, 1)  # a joint face that is not an interior face of the mesh


# ----------------------------------------------------------------------------------------------------------------
# Joint interface elements: one per pair of daughter nodes facing each other across a bonded joint.


@wp.func
def face_stiffness_per_area(t: int, area: float, tet_volume: wp.array(dtype=float), mat: TetMaterial) -> float:
    """E / h [Pa/m] of tet t behind a face of area A: h = 3 V₀ / A is the tet's height over that face."""
    return youngs_modulus(mat) * area / (3.0 * tet_volume[t])


@wp.func
def joint_face_spring(
    jm: JointMaterial, t: int, area: float, tet_volume: wp.array(dtype=float), mat: TetMaterial
) -> float:
    """Normal spring per unit area of one face of a joint, on tet t's side [Pa/m]: f E / h + k_n / 2 (one of the
    two terms is 0: a joint takes a penalty factor f or a normal stiffness k_n)."""
    return jm.stiffness_factor * face_stiffness_per_area(t, area, tet_volume, mat) + jm.face_normal_stiffness


@wp.kernel
def emit_joint_pairs_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    joint_material_table: wp.array(dtype=JointMaterial),
    # In:
    joint_face_nodes: wp.array(dtype=wp.vec3i),
    joint_face_set: wp.array(dtype=int),
    joint_face_tets: wp.array(dtype=wp.vec2i),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    # Out:
    pair_key: wp.array(dtype=wp.int64),
    pair_value: wp.array(dtype=int),
    pair_area: wp.array(dtype=float),
    pair_kn: wp.array(dtype=float),
    pair_tet_face: wp.array(dtype=int),
    pair_set: wp.array(dtype=int),
):
    j = wp.tid()  # one thread per joint face; it emits one pair per vertex into slots 3j .. 3j+2
    f = joint_face_nodes[j]
    s = joint_face_set[j]
    sides = joint_face_tets[j]
    bonded = int(0)
    if sides[0] >= 0 and sides[1] >= 0:
        bonded = joint_material_table[s].bonded
    x0 = node_ref_q[f[0]]
    area = wp.length(triangle_area_vector(x0, node_ref_q[f[1]], node_ref_q[f[2]]))
    for i in range(3):
        slot = 3 * j + i
        pair_value[slot] = slot
        pair_key[slot] = NO_KEY
        if bonded == 0:
            continue
        v = f[i]
        ea = star_find(star_tets, star_offset[v], star_count[v], sides[0])
        eb = star_find(star_tets, star_offset[v], star_count[v], sides[1])
        a = split_node_index(v, star_comp[ea], first_new)
        b = split_node_index(v, star_comp[eb], first_new)
        if a == b:
            continue  # the rim of a joint that ends inside the rock: the node was not split
        ta = sides[0]
        tb = sides[1]
        if b < a:  # the element's node A is the lower index; its joint face gives the normal
            tmp = a
            a = b
            b = tmp
            ta = sides[1]
            tb = sides[0]
        # Two-sided penalty per unit area f (E_A/h_A + E_B/h_B), or k_n: the same interface stiffness as the two
        # passes of the frictional node–face contact, so a joint's stiffness does not jump when it fails.
        jm = joint_material_table[s]
        ka = joint_face_spring(jm, ta, area, tet_volume, tet_material_table[tet_material[ta]])
        kb = joint_face_spring(jm, tb, area, tet_volume, tet_material_table[tet_material[tb]])
        share = area / 3.0
        pair_key[slot] = wp.int64(a) * wp.int64(node_ref_q.shape[0]) + wp.int64(b)
        pair_area[slot] = share
        pair_kn[slot] = (ka + kb) * share
        pair_tet_face[slot] = 4 * ta + face_in_tet(tet_nodes[ta], f[0], f[1], f[2])
        pair_set[slot] = s


@wp.kernel
def flag_pair_runs_kernel(
    # In:
    num: int,
    sorted_key: wp.array(dtype=wp.int64),
    # Out:
    run_start: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per sorted pair slot (of the first num)
    run_start[i] = 0
    if i >= num or sorted_key[i] == NO_KEY:
        return
    # Two branches, not one `or`: Warp evaluates both operands, and sorted_key[i - 1] does not exist for i = 0.
    if i == 0:  # noqa: SIM114
        run_start[i] = 1
    elif sorted_key[i - 1] != sorted_key[i]:
        run_start[i] = 1


@wp.kernel
def reduce_joint_pairs_kernel(
    # In:
    num: int,
    node_capacity: int,
    sorted_key: wp.array(dtype=wp.int64),
    sorted_value: wp.array(dtype=int),
    run_start: wp.array(dtype=int),
    run_offset: wp.array(dtype=int),
    pair_area: wp.array(dtype=float),
    pair_kn: wp.array(dtype=float),
    pair_tet_face: wp.array(dtype=int),
    pair_set: wp.array(dtype=int),
    # Out:
    joint_a: wp.array(dtype=int),
    joint_b: wp.array(dtype=int),
    joint_area: wp.array(dtype=float),
    joint_kn: wp.array(dtype=float),
    joint_tet_face: wp.array(dtype=int),
    joint_set: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per sorted pair slot; the first slot of each run of equal keys sums the run in order
    if i >= num or run_start[i] == 0:
        return
    key = sorted_key[i]
    out = run_offset[i]
    first = sorted_value[i]
    area = float(0.0)
    kn = float(0.0)
    e = i
    while e < num:
        if sorted_key[e] != key:
            break
        area += pair_area[sorted_value[e]]
        kn += pair_kn[sorted_value[e]]
        e += 1
    joint_a[out] = int(key // wp.int64(node_capacity))
    joint_b[out] = int(key % wp.int64(node_capacity))
    joint_area[out] = area
    joint_kn[out] = kn
    joint_tet_face[out] = pair_tet_face[first]
    joint_set[out] = pair_set[first]


# ----------------------------------------------------------------------------------------------------------------
# Joint interface element forces (part of the contact stage).


@wp.func
def tet_face_normal(tet_nodes: wp.array(dtype=wp.vec4i), tet_face_slot: int, node_q: wp.array(dtype=wp.vec3)):
    """Outward unit normal of tet-face slot 4t + k at the current positions."""
    f = tet_face(tet_nodes[tet_face_slot // 4], tet_face_slot % 4)
    return wp.normalize(triangle_area_vector(node_q[f[0]], node_q[f[1]], node_q[f[2]]))


@wp.func
def joint_element_force(
    g: wp.vec3, v_rel: wp.vec3, n: wp.vec3, kn: float, area: float, mstar: float, mat: JointMaterial
) -> wp.mat33:
    """Force on node B of an intact joint element and its failure mode.

    g = u_B - u_A [m], v_rel = v_B - v_A [m/s], n the unit normal out of A's face. Elastic springs k_n (normal)
    and k_t = kt_ratio k_n (tangential) with dashpots 2 ζ sqrt(m* k); strength checks on the elastic forces:
    tension k_n g_n > σ_t A, or shear |k_t g_t| > c A + μ max(0, -k_n g_n) (Mohr–Coulomb).

    Returns:
        Rows: (elastic force on B [N], dashpot force on B [N], (failure mode JOINT_INTACT / JOINT_BROKEN_TENSION /
        JOINT_BROKEN_SHEAR, elastic energy [J], 0)).
    """
    p = mat.contact
    gn = wp.dot(g, n)
    gt = g - gn * n
    kt = p.kt_ratio * kn
    vn = wp.dot(v_rel, n)
    vt = v_rel - vn * n
    fn_el = kn * gn  # tension positive
    ft_el = kt * gt
    mode = float(JOINT_INTACT)
    if fn_el > mat.tensile_strength * area:
        mode = float(JOINT_BROKEN_TENSION)
    elif wp.length(ft_el) > mat.cohesion * area + p.friction * wp.max(-fn_el, 0.0):
        mode = float(JOINT_BROKEN_SHEAR)
    f_el = -fn_el * n - ft_el
    f_damp = -2.0 * p.damp_n * wp.sqrt(mstar * kn) * vn * n - 2.0 * p.damp_t * wp.sqrt(mstar * kt) * vt
    energy = 0.5 * (kn * gn * gn + kt * wp.dot(gt, gt))
    return wp.mat33(f_el[0], f_el[1], f_el[2], f_damp[0], f_damp[1], f_damp[2], mode, energy, 0.0)


@wp.kernel
def eval_joints_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    node_inv_mass: wp.array(dtype=float),
    joint_a: wp.array(dtype=int),
    joint_b: wp.array(dtype=int),
    joint_area: wp.array(dtype=float),
    joint_kn: wp.array(dtype=float),
    joint_tet_face: wp.array(dtype=int),
    joint_set: wp.array(dtype=int),
    joint_material_table: wp.array(dtype=JointMaterial),
    dt: float,
    # State in:
    joint_count: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    node_q: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    # State out:
    joint_broken: wp.array(dtype=int),
    joints_broken_total: wp.array(dtype=int),
    fem_rebuild_flag: wp.array(dtype=int),
    node_f: wp.array(dtype=wp.vec3),
    node_f_contact: wp.array(dtype=wp.vec3),
    node_energy_contact: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per joint element slot
    if i >= joint_count[0] or joint_broken[i] != JOINT_INTACT:
        return
    a = joint_a[i]
    b = joint_b[i]
    inv_sum = node_inv_mass[a] + node_inv_mass[b]
    if inv_sum == 0.0:
        return
    mat = joint_material_table[joint_set[i]]
    n = tet_face_normal(tet_nodes, joint_tet_face[i], node_q)
    # u_B - u_A, not x_B - x_A: the daughters share their reference position, and displacements keep float32
    # precision where coordinates would not.
    g = node_u[b] - node_u[a]
    v_rel = node_qd[b] - node_qd[a]
    out = joint_element_force(g, v_rel, n, joint_kn[i], joint_area[i], 1.0 / inv_sum, mat)
    mode = int(out[2, 0])
    if mode != JOINT_INTACT:
        if dt > 0.0:  # the set-up evaluation (dt = 0) changes no history
            joint_broken[i] = mode
            wp.atomic_add(joints_broken_total, 0, 1)
            fem_rebuild_flag[0] = 1  # the pair enters the node–face contact list at the next build
            # The springs' elastic energy is released (booked as dissipated, as a broken bond's is).
            wp.atomic_add(node_energy_contact, a, wp.float64(out[2, 1]))
        return
    f = out[0] + out[1]
    wp.atomic_add(node_f, b, f)
    wp.atomic_add(node_f, a, -f)
    # The dashpots' work as Verlet does it, ½ dt F_damp·(v_{n-1/2} + v_{n+1/2}) on the relative motion (v_rel is
    # v_{n-1/2} here): the half behind is booked now, and the force joins node_f_contact, whose half ahead the next
    # evaluation books against v_{n+1/2} (kernels/integrate.py book_half_ahead_kernel). The springs need no
    # booking: their energy is read at the current positions.
    wp.atomic_add(node_energy_contact, a, wp.float64(-0.5 * wp.dot(out[1], v_rel) * dt))
    wp.atomic_add(node_f_contact, b, out[1])
    wp.atomic_add(node_f_contact, a, -out[1])
