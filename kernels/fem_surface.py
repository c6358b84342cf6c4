"""The FEM contact surface (DESIGN.md stage 4): the boundary faces of the tet mesh, the nodes' penalty stiffness,
the faces' extents, centres and normals, and the point–triangle geometry every FEM contact uses.

Surface. The boundary faces are the faces of live, active tets that no other active tet shares (after joints are
pre-split, both faces of a joint are boundary faces), listed in outward order so that n_f, the right-hand unit
normal, points out of the rock. A node's penalty stiffness is Σ over its boundary faces of f E A / (3 h) [N/m]:
each face, of area A on a tet of modulus E and height h over it, is a spring f E / h per unit area shared by its
three nodes (f the face's stiffness factor: its joint set's, or the model's for other faces). The held stiffness
across topology passes, the rigid normals and the contacts themselves: kernels/fem_contact.py.
"""

from __future__ import annotations

import warp as wp

from .joints import JointMaterial, face_stiffness_per_area, joint_face_spring
from .rigid import TET_RIGID
from .tets import TetMaterial
from .topology import local_index, tet_face, triangle_area_vector

wp.set_module_options({"enable_backward": False})


BARY_EPS = wp.constant(1.0e-5)
"""A barycentric weight above this is inside the triangle; a contact point with all three above it is in the
face's interior, otherwise on an edge or vertex [-] (which of two equally deep faces a node takes; how far outside a
node–face contact may lie: RIM_EPS, KEEP_EPS)."""

RIM_EPS = wp.constant(1.0e-2)
"""A node may take a face as a new target while its projection lies within this barycentric margin outside the
triangle: past an edge by up to RIM_EPS of the triangle's height over that edge (3 mm on a 30 cm face) [-]; a crack's
face within BARY_EPS (:func:`rim_margins`). A node on
the rim of a joint sits on the edge of the face opposite, and where the two faces are one cell across, every node of
each is a corner of the other: a shift along the joint (another joint's compression, 3e-3 of the face at the
limestone tunnel's head joints; float32 rounding where the faces are aligned) puts them all just outside the face
opposite, and with a margin of rounding's size (BARY_EPS) nothing held that joint (tests/test_rim_contact.py). The
spring still acts along the face's normal, its reaction at the node's projection (kernels/fem_contact.py); a node
that passes beside a face within the margin, behind its plane, meets a ledge of that width (its spring starts at the
depth gained in the step, so no energy is created).

Why not on a crack's faces: the ledge is as wide there, and wider than the openings. A crack runs
through tets, so its faces kink; at a kink a daughter node lies behind the plane of the face beyond the kink, past its
edge, without touching it, and a margin of 1e-2 of a 4 mm face (40 µm, some δ_c) pushed it out: the Brazilian disc's
crack no longer let go (its load rose to 1.31 T_f by 0.8 ms, where it peaks at T_f and falls to 0.90 of the peak by
0.64 ms). Joints are planes cut before the run, and the bodies' outer faces meet at their edges only."""

KEEP_EPS = wp.constant(2.0e-2)
"""A node keeps its target face while its projection lies within this barycentric margin outside the triangle, twice
the RIM_EPS a new target may take, so that a node taken at the rim is not dropped and restarted step after step by
float32 rounding or a little shear [-]; a crack's face within FACE_KEEP_EPS."""

FACE_KEEP_EPS = wp.constant(1.0e-3)
"""A node keeps a crack's face as its target while its projection lies within this barycentric margin outside the
triangle (new targets need BARY_EPS): float32 rounding and a little shear do not drop and restart it [-]."""


@wp.func
def face_tet_slot(
    f: int,
    tet_nodes: wp.array(dtype=wp.vec4i),
    face_nodes: wp.array(dtype=wp.vec3i),
    face_tet: wp.array(dtype=int),
) -> int:
    """The tet-face slot 4t + k of boundary face f: t its tet, k the tet's node that is not one of its three (-1 when
    every node is: the face no longer matches its tet)."""
    t = face_tet[f]
    n = face_nodes[f]
    nodes = tet_nodes[t]
    from_k = int(-1)
    for k in range(4):
        if nodes[k] != n[0] and nodes[k] != n[1] and nodes[k] != n[2]:
            from_k = k
    if from_k < 0:
        return -1
    return 4 * t + from_k


@wp.struct
class RimFaces:
    """What :func:`rim_margins` and the set-up's convex-edge test (kernels/node_face_target.py
    ``exits_over_convex_edge``) read: the Model arrays of those names (``ref_tet_face_nbr`` empty where neither
    fracture nor conversion is attached: then no face was inside the built mesh)."""

    face_joint: wp.array(dtype=int)
    face_tet: wp.array(dtype=int)
    face_nodes: wp.array(dtype=wp.vec3i)
    tet_nodes: wp.array(dtype=wp.vec4i)
    ref_tet_face_nbr: wp.array(dtype=int)
    tet_face_joint: wp.array(dtype=int)


@wp.func
def rim_margins(f: int, rims: RimFaces) -> wp.vec2:
    """The barycentric margins outside face f [-] within which a node may take it as a new target and keep it as
    one: (BARY_EPS, FACE_KEEP_EPS) for a face of a crack or of a converted tet's hole (a face inside the built mesh,
    ``ref_tet_face_nbr`` >= 0 across its tet-face slot, that is no joint face), (RIM_EPS, KEEP_EPS) for any other:
    the outer surfaces of the bodies, joints, openings (RIM_EPS says why)."""
    if rims.face_joint[f] < 0 and rims.ref_tet_face_nbr.shape[0] > 0:
        slot = face_tet_slot(f, rims.tet_nodes, rims.face_nodes, rims.face_tet)
        if slot >= 0 and rims.ref_tet_face_nbr[slot] >= 0:
            return wp.vec2(BARY_EPS, FACE_KEEP_EPS)
    return wp.vec2(RIM_EPS, KEEP_EPS)


TIE_EPS = wp.constant(4.0e-6)
"""Relative tolerance (about 32 float32 ulps of the lengths involved) within which two contacts are equally near:
the same edge or vertex point computed from two faces differs by rounding only [-]."""


# ----------------------------------------------------------------------------------------------------------------
# Geometry.


@wp.func
def closest_point_barycentric(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Barycentric weights (w_a, w_b, w_c) of the point of triangle abc closest to p (Ericson, Real-Time Collision
    Detection §5.1.5: Voronoi regions of the vertices, edges and face)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return wp.vec3(1.0 - v, v, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return wp.vec3(1.0 - w, 0.0, w)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - w, w)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return wp.vec3(1.0 - v - w, v, w)


@wp.func
def projection_barycentric(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, area2: wp.vec3) -> wp.vec3:
    """Barycentric weights of the projection of p onto the plane of triangle abc (may be negative outside it);
    area2 = (b - a) × (c - a)."""
    inv = 1.0 / wp.dot(area2, area2)
    wa = wp.dot(wp.cross(c - b, p - b), area2) * inv
    wb = wp.dot(wp.cross(a - c, p - c), area2) * inv
    return wp.vec3(wa, wb, 1.0 - wa - wb)


@wp.func
def relative_position(q: wp.vec3, x: wp.vec3d) -> wp.vec3:
    """q - x [m]: a float32 point (an FEM node) seen from a float64 sphere centre, the difference formed in float64
    and rounded once."""
    return wp.vec3(wp.vec3d(q) - x)


@wp.func
def min3(w: wp.vec3) -> float:
    return wp.min(w[0], wp.min(w[1], w[2]))


@wp.func
def nearer(d: float, interior: int, f: int, best_d: float, best_interior: int, best_f: int, tol: float) -> bool:
    """Whether a contact (distance or depth d, interior flag, face f) beats the best so far: nearer by more than tol;
    or as near and in a face's interior where the best is not; or as near, of the same kind, and a lower face index."""
    if best_f < 0:
        return True
    if d < best_d - tol:
        return True
    if d > best_d + tol:
        return False
    if interior != best_interior:
        return interior > best_interior
    return f < best_f


@wp.func
def in_one_ring(
    v: int,
    u: int,
    tet_nodes: wp.array(dtype=wp.vec4i),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
) -> bool:
    """Whether node u is node v or shares a tet with it."""
    found = bool(u == v)
    start = star_offset[v]
    for e in range(start, start + star_count[v]):
        if local_index(tet_nodes[star_tets[e]], u) >= 0:
            found = True
    return found


@wp.func
def find_joint(joint_a: wp.array(dtype=int), joint_b: wp.array(dtype=int), count: int, a: int, b: int) -> int:
    """Index of the joint element of nodes {a, b}, a < b, in the elements sorted by their pair (min, max) (binary
    search), -1 if absent. An element's A may be the larger index once a split pass handed it over
    (warpdem.stages.topology .sort_joint_elements keeps the order)."""
    lo = int(0)
    hi = count
    while lo < hi:
        mid = (lo + hi) // 2
        ma = wp.min(joint_a[mid], joint_b[mid])
        mb = wp.max(joint_a[mid], joint_b[mid])
        if ma < a or (ma == a and mb < b):
            lo = mid + 1
        else:
            hi = mid
    if lo < count:
        if wp.min(joint_a[lo], joint_b[lo]) == a and wp.max(joint_a[lo], joint_b[lo]) == b:
            return lo
    return -1


@wp.func
def held_by_joint(
    v: int,
    u: int,
    joint_a: wp.array(dtype=int),
    joint_b: wp.array(dtype=int),
    joint_count: int,
    joint_broken: wp.array(dtype=int),
) -> bool:
    """Whether nodes v and u are the daughters of an intact joint element."""
    k = find_joint(joint_a, joint_b, joint_count, wp.min(v, u), wp.max(v, u))
    if k < 0:
        return False
    return joint_broken[k] == 0


# ----------------------------------------------------------------------------------------------------------------
# Surface topology (after every topology pass): flag → scan → scatter through warpdem.stages.compaction.


@wp.kernel
def count_tet_faces_kernel(
    # State in:
    tet_count: wp.array(dtype=int),
    # Out:
    tet_face_count: wp.array(dtype=int),
):
    tet_face_count[0] = 4 * tet_count[0]  # one thread


@wp.kernel
def flag_boundary_faces_kernel(
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    # In:
    tet_face_nbr: wp.array(dtype=int),
    # Out:
    dead: wp.array(dtype=int),
):
    s = wp.tid()  # one thread per tet-face slot 4t + k
    t = s // 4
    dead[s] = 1
    if t < tet_count[0]:
        if tet_active[t] != 0 and tet_face_nbr[s] < 0:
            dead[s] = 0


@wp.kernel
def scatter_boundary_faces_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_volume: wp.array(dtype=float),
    tet_face_joint: wp.array(dtype=int),
    # In:
    tet_face_count: wp.array(dtype=int),
    old_to_new: wp.array(dtype=int),
    # Out:
    face_nodes: wp.array(dtype=wp.vec3i),
    face_tet: wp.array(dtype=int),
    face_joint: wp.array(dtype=int),
    face_depth: wp.array(dtype=float),
):
    s = wp.tid()  # one thread per tet-face slot; a boundary one writes its face
    if s >= tet_face_count[0]:
        return
    f = old_to_new[s]
    if f < 0 or f >= face_nodes.shape[0]:
        return
    t = s // 4
    nodes = tet_face(tet_nodes[t], s % 4)
    area = wp.length(triangle_area_vector(node_ref_q[nodes[0]], node_ref_q[nodes[1]], node_ref_q[nodes[2]]))
    face_nodes[f] = nodes
    face_tet[f] = t
    face_joint[f] = tet_face_joint[s]
    face_depth[f] = 0.5 * 3.0 * tet_volume[t] / area


@wp.kernel
def node_contact_stiffness_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    tet_face_nbr: wp.array(dtype=int),
    tet_face_joint: wp.array(dtype=int),
    joint_material_table: wp.array(dtype=JointMaterial),
    stiffness_factor: float,
    face_normal_stiffness: float,
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # State in:
    node_count: wp.array(dtype=int),
    # Out:
    node_contact_stiffness: wp.array(dtype=float),
    node_contact_material: wp.array(dtype=int),
):
    v = wp.tid()  # one thread per node slot; sums over its own star in ascending tet order (deterministic)
    node_contact_stiffness[v] = 0.0
    node_contact_material[v] = 0
    if v >= node_count[0]:
        return
    k_sum = float(0.0)
    start = star_offset[v]
    for e in range(start, start + star_count[v]):
        t = star_tets[e]
        n = tet_nodes[t]
        if e == start:
            node_contact_material[v] = tet_material[t]
        for k in range(4):
            if n[k] == v or tet_face_nbr[4 * t + k] >= 0:
                continue  # the face opposite v does not hold v; a face with a neighbour is inside the rock
            f = tet_face(n, k)
            area = wp.length(triangle_area_vector(node_ref_q[f[0]], node_ref_q[f[1]], node_ref_q[f[2]]))
            mat = tet_material_table[tet_material[t]]
            js = tet_face_joint[4 * t + k]
            # The face's spring per unit area (f E / h, h = 3 V₀ / A, or k_n / 2; a joint's own: joint_face_spring)
            # over A / 3.
            per_area = stiffness_factor * face_stiffness_per_area(t, area, tet_volume, mat) + face_normal_stiffness
            if js >= 0:
                per_area = joint_face_spring(joint_material_table[js], t, area, tet_volume, mat)
            k_sum += per_area * area / 3.0
    node_contact_stiffness[v] = k_sum


@wp.func
def held_stiffness(k_lumped: float, hold: wp.float64, mass: float) -> float:
    """Penalty stiffness a node's springs use [N/m]: its held ω² [1/s²] times its mass [kg], or the lumped stiffness
    of its faces when none is held ("Held stiffness")."""
    if hold > wp.float64(0.0):
        return float(hold * wp.float64(mass))
    return k_lumped


@wp.kernel
def hold_contact_stiffness_kernel(
    # Model:
    node_contact_stiffness: wp.array(dtype=float),
    node_mass: wp.array(dtype=float),
    # State in:
    node_count: wp.array(dtype=int),
    # State out:
    node_contact_hold: wp.array(dtype=wp.float64),
):
    v = wp.tid()  # one thread per node slot: before a topology pass, hold the stiffness in use as ω² = k / m
    if v >= node_count[0] or node_contact_hold[v] > wp.float64(0.0):
        return  # a node that holds one already uses it
    k = node_contact_stiffness[v]
    m = node_mass[v]
    if k > 0.0 and m > 0.0:
        node_contact_hold[v] = wp.float64(k) / wp.float64(m)


@wp.kernel
def face_extent_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    face_nodes: wp.array(dtype=wp.vec3i),
    face_depth: wp.array(dtype=float),
    # State in:
    face_count: wp.array(dtype=int),
    # Out:
    extent: wp.array(dtype=float),
):
    f = wp.tid()  # one thread per face slot: extent[0] = max centroid–vertex distance, extent[1] = max depth
    if f >= face_count[0]:
        return
    n = face_nodes[f]
    a = node_ref_q[n[0]]
    b = node_ref_q[n[1]]
    c = node_ref_q[n[2]]
    centre = (a + b + c) / 3.0
    r = wp.max(wp.length(a - centre), wp.max(wp.length(b - centre), wp.length(c - centre)))
    wp.atomic_max(extent, 0, r)
    wp.atomic_max(extent, 1, face_depth[f])


# ----------------------------------------------------------------------------------------------------------------
# Candidate lists.


@wp.kernel
def flag_fem_rebuild_kernel(
    # State in:
    rebuild_total: wp.array(dtype=int),
    # State out:
    fem_sphere_builds_seen: wp.array(dtype=int),
    fem_rebuild_flag: wp.array(dtype=int),
):
    # One thread. A node that moved half the FEM skin raised the flag in its drift (kernels/integrate.py); the sphere
    # list rebuilt in this step is the other reason to rebuild, as the sphere–face candidates hang on it.
    if rebuild_total[0] != fem_sphere_builds_seen[0]:
        fem_rebuild_flag[0] = 1
        fem_sphere_builds_seen[0] = rebuild_total[0]  # the rebuild this flag triggers sees the new sphere list


@wp.kernel
def face_centers_kernel(
    # Model:
    face_nodes: wp.array(dtype=wp.vec3i),
    # State in:
    face_count: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    # Out:
    face_center: wp.array(dtype=wp.vec3),
    face_bound: wp.array(dtype=float),
):
    f = wp.tid()  # one thread per face slot: the centroid and the radius of the ball about it that holds the face
    if f >= face_count[0]:
        face_center[f] = wp.vec3(0.0)  # never reported: queries skip indices past the count
        face_bound[f] = 0.0
        return
    n = face_nodes[f]
    a = node_q[n[0]]
    b = node_q[n[1]]
    c = node_q[n[2]]
    centre = (a + b + c) / 3.0
    face_center[f] = centre
    face_bound[f] = wp.max(wp.length(a - centre), wp.max(wp.length(b - centre), wp.length(c - centre)))


@wp.func
def node_surface_normal(
    v: int,
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_face_nbr: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
) -> wp.vec3:
    """Outward unit normal of the surface at node v: the sum of the area vectors of its boundary faces (current
    positions), normalised; zero for a node inside the rock."""
    acc = wp.vec3(0.0)
    start = star_offset[v]
    for e in range(start, start + star_count[v]):
        t = star_tets[e]
        n = tet_nodes[t]
        for k in range(4):
            if n[k] == v or tet_face_nbr[4 * t + k] >= 0:
                continue
            f = tet_face(n, k)
            acc += triangle_area_vector(node_q[f[0]], node_q[f[1]], node_q[f[2]])
    length = wp.length(acc)
    if length > 0.0:
        return acc / length
    return acc


@wp.kernel
def rest_positions_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    # State in:
    node_count: wp.array(dtype=int),
    node_body: wp.array(dtype=int),
    node_rigid_u0: wp.array(dtype=wp.vec3),
    # Out:
    x_rest: wp.array(dtype=wp.vec3),
):
    """A rigid block's node where the switch left it, X + u0: the float32 sum the pose forms (kernels/rigid.py
    ``pose_nodes_kernel``, x = X + u), so a body that has not moved gets its star walk's normal bit for bit."""
    i = wp.tid()  # one thread per node slot
    if i >= node_count[0]:
        return
    if node_body[i] >= 0:
        x_rest[i] = node_ref_q[i] + node_rigid_u0[i]


@wp.kernel
def rest_normals_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_face_nbr: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # State in:
    node_count: wp.array(dtype=int),
    node_body: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    # In:
    x_rest: wp.array(dtype=wp.vec3),
    # Out:
    normal_body: wp.array(dtype=int),
    rest_normal: wp.array(dtype=wp.vec3),
):
    """Rigid normals: a node of a rigid block whose star holds rigid tets only (all of its block: a tet shares the
    node, so it is connected to it) moves with every face of its star rigidly, so n_v = R(q) n_v0 with n_v0 its
    :func:`node_surface_normal` at the switch positions X + u0; ``normal_body`` says which body turns it (-1: the
    star walk each evaluation, as for a deformable node or one next to a deformable tet, whose faces deform)."""
    v = wp.tid()  # one thread per node slot
    normal_body[v] = -1
    if v >= node_count[0]:
        return
    b = node_body[v]
    if b < 0:
        return
    start = star_offset[v]
    for e in range(start, start + star_count[v]):
        if tet_active[star_tets[e]] != TET_RIGID:
            return
    rest_normal[v] = node_surface_normal(v, tet_nodes, tet_face_nbr, star_offset, star_count, star_tets, x_rest)
    normal_body[v] = b


@wp.kernel
def face_normals_kernel(
    # Model:
    face_nodes: wp.array(dtype=wp.vec3i),
    # State in:
    face_count: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    # Out:
    face_normal: wp.array(dtype=wp.vec3),
    face_origin: wp.array(dtype=wp.vec3),
):
    f = wp.tid()  # one thread per face slot: the unit normal n_f at the current positions, once for all its nodes
    if f >= face_count[0]:
        return
    fn = face_nodes[f]
    a = node_q[fn[0]]
    b = node_q[fn[1]]
    c = node_q[fn[2]]
    face_normal[f] = wp.normalize(wp.cross(b - a, c - a))
    # Its first vertex x_a, the point the node–face depth tests measure from (-(x - x_a) · n_f): one load of a copy
    # instead of face_nodes[f] and then node_q at its first index, in the same arithmetic.
    face_origin[f] = a


@wp.kernel
def tet_face_slots_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    face_nodes: wp.array(dtype=wp.vec3i),
    face_tet: wp.array(dtype=int),
    # State in:
    face_count: wp.array(dtype=int),
    # Out:
    face_slot: wp.array(dtype=int),
):
    f = wp.tid()  # one thread per face slot: the tet-face slot 4t + k each boundary face is (before a split)
    face_slot[f] = -1
    if f >= face_count[0]:
        return
    face_slot[f] = face_tet_slot(f, tet_nodes, face_nodes, face_tet)


@wp.kernel
def remap_face_ids_kernel(
    # In:
    old_face_count: wp.array(dtype=int),
    face_slot: wp.array(dtype=int),
    slot_to_face: wp.array(dtype=int),
    # Out:
    ids: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per entry of a face-id array: old face → its tet-face slot → the new face of that slot
    f = ids[i]
    if f < 0 or f >= old_face_count[0]:
        return
    s = face_slot[f]
    if s < 0:
        ids[i] = -1
        return
    ids[i] = slot_to_face[s]
