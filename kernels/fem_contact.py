"""FEM contact (DESIGN.md stage 4): the boundary faces of the tet mesh, their skinned candidate lists from a hash
grid, and sphere–face, node–face and node–wall forces with tangential history.

Surface. The boundary faces are the faces of live, active tets that no other active tet shares (after joints are
pre-split, both faces of a joint are boundary faces), listed in outward order so that n_f, the right-hand unit
normal, points out of the rock. A node's penalty stiffness is Σ over its boundary faces of f E A / (3 h) [N/m]:
each face, of area A on a tet of modulus E and height h over it, is a spring f E / h per unit area shared by its
three nodes (f the face's stiffness factor: its joint set's, or the model's for other faces).

Sphere–face: the closest point c of the triangle to the sphere centre x (barycentric weights w); touching when
|x - c| < r with x in front of the face. The vertices are taken relative to the float64 centre (float64
differences rounded once), so the sphere's side of the arithmetic does not depend on the offset; the nodes' float32
positions do. The force is the sphere contact law of the model (kernels/contact.py,
``make_pair_laws``) with the face as a flat body (R* = r, as a wall), m* = 1 / (1/m_s + Σ w_i²/m_i), and the equal
and opposite force goes to the face's nodes with the weights w_i. A sphere may touch several faces; a contact at a
face's edge or vertex counts only if no other face is nearer (the same edge point seen from the two faces that share
the edge counts once, and a contact in a face's interior shadows its neighbours' edges).

Node–face: a node penetrates a face when the face faces it (n_f · n_v < 0, n_v the outward normal of the node's own
surface), it lies behind the face's plane (s = (x - x_a) · n_f < 0), less deep than half the tet's height over the
face, and it projects inside the triangle. Of the faces it penetrates it is pushed out of the shallowest (the
shortest way out; a vertex shared by coplanar faces goes to the lowest face index), by a linear spring–dashpot k δ
with k its penalty stiffness and ζ from the restitution (the laws linear_normal_force and coulomb_tangential of
kernels/contact.py). One spring of tangential history per node follows it from face to face.
The spring never gains energy that no force worked for (½ k δ² jumping up at an event is energy created; a jump down
is booked as dissipated): a node keeps its target while it still penetrates it (its projection may then stray
KEEP_EPS outside the triangle: a node on the rim of a joint sits on the edge of the face opposite); on a change of
target the new spring starts at no more than the old one's compression; a new contact starts at the depth gained in
the step, the depth the node already had behind the plane at the last positions (it slid in past an edge) carried as
an offset; the offset follows a node that backs out.
Candidates exclude every face with a vertex in the node's 1-ring (the node itself or a node it shares a tet with):
a node never touches a face of a tet holding it, nor a face that holds it, and near a crack tip the rock is still
continuous. An intact joint element's pair is excluded too (the element carries it).

Node–wall: as sphere–wall, with the node's penalty stiffness.

Rigid normals. A node of a rigid block whose star holds rigid tets only moves rigidly with every face of its star, so
its outward normal n_v is its normal at the switch turned by the body's rotation, R(q) n_v0 (``rest_normals_kernel``
computes n_v0 by the star walk at the switch positions X + u0, which the state keeps, so a restart computes the same
bits). It differs from the star walk at the posed positions by float32 rounding (~1e-6), and n_v enters only the sign
of the facing test n_f · n_v < 0, so the two paths decide alike unless a face is within that of perpendicular to the
node's normal. A node next to a deformable tet walks its star, as every node before the switch.

Held stiffness. A split or conversion pass moves no node, but the surface rebuild re-lumps the penalty stiffness of
every node whose faces changed (a daughter gains the crack faces, a converted tet's neighbours its inner faces): a
node pressed by δ into the ground or a face would gain ½ Δk δ² with no work done, and its contact force would jump.
So before a pass every surface node holds its stiffness per unit mass, ω² = k / m (``node_contact_hold``, float64),
and its springs use k = ω² m (the node's current mass) until it touches nothing; then, with no spring stretched,
the lumped stiffness takes over at no cost in energy. Why per unit mass:

- a split copies ω² into both daughters (the pass replicates every per-node array), so k_A + k_B = ω² (m_A + m_B)
  = k_K: the sum of the daughters' forces is the parent's, their springs' energy ½ (k_A + k_B) δ² the parent's,
  and each daughter has the parent's contact acceleration k δ / m, as eq. 3 asks of the element forces (the
  tangential springs ξ are copied too, so k_t ξ shares alike; node–wall dashpots too: c = 2ζ √(m k) = 2ζ ω m);
- a conversion pass that moves a tet's mass into a sphere leaves the node ω² m_new ≤ k: its springs' energy can
  only fall (the share of the node that left no longer presses), never rise;
- the contact's frequency ω is the parent's, so no pass raises a node's k / m above what the stable step
  (warpdem.fem_contact.contact_critical_step_at) was taken for; holding k itself on a node that lost most of its
  mass to spheres would.

Float64 makes the hold exact for a node whose mass the pass leaves alone: f32(f64(k) / m × m) = k, the two
float64 roundings (2.2e-16 relative) lying far inside half a float32 spacing. A node–face spring that first forms
at the re-evaluation after a pass (``born_relaxed``) starts relaxed, its depth carried as an offset: nothing moved,
so no depth was gained.

Skins: the lists are rebuilt when a node has moved half of ``fem_skin`` since the last build or the sphere list was
rebuilt (a sphere moved half its skin since the sphere build, which may precede the FEM build by another half: up
to a whole skin since the FEM build). A candidate is kept at a build when it is within r + skin + fem_skin/2
(sphere) or fem_skin (node), or already behind the face (node), so no pair can start touching between builds
without being in the list.
"""

from __future__ import annotations

import functools

import warp as wp

from .contact import (
    ContactPair,
    book_contact_force,
    coulomb_tangential,
    linear_normal_force,
    make_pair_laws,
    rotate_into_plane,
)
from .joints import JointMaterial, face_stiffness_per_area, joint_face_spring
from .neighbors import ListSpec, make_list_kernels
from .rigid import TET_RIGID
from .tets import TetMaterial
from .topology import local_index, tet_face, triangle_area_vector

wp.set_module_options({"enable_backward": False})

BARY_EPS = wp.constant(1.0e-5)
"""A barycentric weight above this is inside the triangle; a contact point with all three above it is in the
face's interior, otherwise on an edge or vertex [-]."""

KEEP_EPS = wp.constant(1.0e-3)
"""A node keeps its target face while its projection lies within this barycentric margin outside the triangle
(new targets need -BARY_EPS): a node on the rim of a joint sits on the edge of the face opposite, and float32 rounding
or a little shear would otherwise drop and restart its contact step after step [-]."""

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
    search), -1 if absent. An element's A may be the larger index once a split pass handed it over (warpdem.topology
    .sort_joint_elements keeps the order)."""
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
# Surface topology (after every topology pass): flag → scan → scatter through warpdem.compaction.


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


@wp.struct
class SphereFaceInputs:
    """What the sphere–face candidate test reads (kernels/neighbors.py ``ListSpec.inputs``): the Model/State arrays
    of those names; ``margin``, how far beyond its radius a sphere keeps a face (sphere skin + fem_skin / 2) [m]; and
    ``face_radius``, the largest centroid–vertex distance of a face [m] (the grid holds the faces' centroids)."""

    particle_radius: wp.array(dtype=float)
    face_nodes: wp.array(dtype=wp.vec3i)
    node_q: wp.array(dtype=wp.vec3)
    margin: float
    face_radius: float


@wp.struct
class SphereFaceHistory:
    """Per-slot history of the sphere–face list: ``sphere_face_shear`` (or its scratch copy)."""

    shear: wp.array(dtype=wp.vec3)


@wp.func
def sphere_face_search_radius(inputs: SphereFaceInputs, i: int) -> float:
    return inputs.particle_radius[i] + inputs.margin + inputs.face_radius


@wp.func
def is_sphere_face_candidate(inputs: SphereFaceInputs, i: int, x: wp.vec3d, f: int) -> bool:
    """The face's closest point within r + margin of the sphere centre (in coordinates relative to the centre)."""
    cutoff = inputs.particle_radius[i] + inputs.margin
    fn = inputs.face_nodes[f]
    a = relative_position(inputs.node_q[fn[0]], x)
    b = relative_position(inputs.node_q[fn[1]], x)
    c = relative_position(inputs.node_q[fn[2]], x)
    w = closest_point_barycentric(wp.vec3(0.0), a, b, c)
    d = -(w[0] * a + w[1] * b + w[2] * c)
    return not (wp.dot(d, d) >= cutoff * cutoff)  # not ≥ rather than <: a NaN distance keeps the pair


@wp.func
def copy_sphere_face_history(src: SphereFaceHistory, src_slot: int, dst: SphereFaceHistory, dst_slot: int):
    dst.shear[dst_slot] = src.shear[src_slot]


@wp.func
def fresh_sphere_face_history(inputs: SphereFaceInputs, history: SphereFaceHistory, slot: int, i: int, f: int):
    """A pair new to the list starts untouched."""
    history.shear[slot] = wp.vec3(0.0)


SPHERE_FACE_LIST = make_list_kernels(
    ListSpec(
        inputs=SphereFaceInputs,
        radius=sphere_face_search_radius,
        accept=is_sphere_face_candidate,
        history=SphereFaceHistory,
        copy=copy_sphere_face_history,
        fresh=fresh_sphere_face_history,
        owner_vec=wp.vec3d,
        grid_vec=wp.vec3,  # the grid of face centroids is float32, as the nodes are
    )
)
"""Build and commit kernels of the sphere–face lists."""


BOUND_SLACK = wp.constant(1.0e-3)
"""Relative slack on a face's bounding ball in the node–face prefilter [-]: the ball's radius, the barycentric
margin (4 BARY_EPS at most) and float32 rounding all fit well inside it."""


@wp.struct
class NodeFaceInputs:
    """What the node–face candidate test reads (kernels/neighbors.py ``ListSpec.inputs``): the Model/State arrays of
    those names, ``fem_skin`` [m], the query radius face_radius + max(fem_skin, largest face_depth) [m], each face's
    centroid and bounding radius about it at the build (``face_center``, ``face_bound`` [m], face_centers_kernel),
    and ``node_body`` (each node's rigid body, -1 for a deformable node; empty before any switch)."""

    node_contact_stiffness: wp.array(dtype=float)
    tet_nodes: wp.array(dtype=wp.vec4i)
    star_offset: wp.array(dtype=int)
    star_count: wp.array(dtype=int)
    star_tets: wp.array(dtype=int)
    face_nodes: wp.array(dtype=wp.vec3i)
    face_depth: wp.array(dtype=float)
    face_center: wp.array(dtype=wp.vec3)
    face_bound: wp.array(dtype=float)
    joint_a: wp.array(dtype=int)
    joint_b: wp.array(dtype=int)
    node_body: wp.array(dtype=int)
    node_q: wp.array(dtype=wp.vec3)
    joint_count: wp.array(dtype=int)
    joint_broken: wp.array(dtype=int)
    fem_skin: float
    search_radius: float


@wp.func
def node_face_search_radius(inputs: NodeFaceInputs, v: int) -> float:
    return inputs.search_radius


@wp.func
def on_surface(inputs: NodeFaceInputs, v: int) -> bool:
    """A node inside the rock is no contact point."""
    return inputs.node_contact_stiffness[v] != 0.0


@wp.func
def within_reach(inputs: NodeFaceInputs, x: wp.vec3, f: int) -> bool:
    """Whether x lies within max(fem_skin, face_depth) + (1 + BOUND_SLACK) × the face's bounding radius of its
    centroid: a necessary condition of the candidate test below, at the cost of one load and a dot product.

    Why necessary: a point p of the triangle lies within the bounding radius r_f of the centroid c, so a face whose
    closest point is within fem_skin of x has |x − c| < fem_skin + r_f; and a node behind the face, less deep than
    face_depth, whose projection p has barycentric weights w_i ≥ −BARY_EPS (Σ w_i = 1, so Σ |w_i| ≤ 1 + 4 BARY_EPS)
    has |p − c| = |Σ w_i (v_i − c)| ≤ (1 + 4 BARY_EPS) r_f and |x − c| < face_depth + (1 + 4 BARY_EPS) r_f. The grid
    hands over every face in the cells the query ball touches (about six times the ball's volume with cells as wide
    as its radius); this drops the ones outside the ball before the exact test's point–triangle arithmetic."""
    reach = (1.0 + BOUND_SLACK) * inputs.face_bound[f] + wp.max(inputs.fem_skin, inputs.face_depth[f])
    d = x - inputs.face_center[f]
    return wp.dot(d, d) <= reach * reach


@wp.func
def own_body_face(inputs: NodeFaceInputs, v: int, fn: wp.vec3i) -> bool:
    """Whether node v and all three nodes of the face follow the same rigid body: their relative positions never
    change, so the pair can never start or stop touching, and a force between them would be internal to the body
    (zero net force; with friction a torque from nothing). A face with a deformable node still moves against v."""
    if inputs.node_body.shape[0] == 0:
        return False
    b = inputs.node_body[v]
    if b < 0:
        return False
    return inputs.node_body[fn[0]] == b and inputs.node_body[fn[1]] == b and inputs.node_body[fn[2]] == b


@wp.func
def is_node_face_candidate(inputs: NodeFaceInputs, v: int, x: wp.vec3, f: int) -> bool:
    """Within reach of the face (:func:`within_reach`); no vertex of the face in the node's 1-ring or held to it by
    an intact joint element, the face not of the node's own rigid body (:func:`own_body_face`); the face's closest
    point within fem_skin, or the node already behind the face (a build during a contact)."""
    if not within_reach(inputs, x, f):
        return False
    fn = inputs.face_nodes[f]
    a = inputs.node_q[fn[0]]
    b = inputs.node_q[fn[1]]
    c = inputs.node_q[fn[2]]
    w = closest_point_barycentric(x, a, b, c)
    d = x - (w[0] * a + w[1] * b + w[2] * c)
    near = wp.dot(d, d) < inputs.fem_skin * inputs.fem_skin
    if not near:
        area2 = wp.cross(b - a, c - a)
        s = wp.dot(x - a, wp.normalize(area2))
        if s < 0.0 and -s < inputs.face_depth[f]:
            near = min3(projection_barycentric(x, a, b, c, area2)) >= -BARY_EPS
    if not near:
        # The distance test first: most faces the grid offers are far away, and the 1-ring and joint searches below
        # cost a star walk each (the list build of a cracked mesh took 3x longer with them first).
        return False
    if own_body_face(inputs, v, fn):
        return False
    n_joints = inputs.joint_count[0]
    for k in range(3):
        u = fn[k]
        if in_one_ring(v, u, inputs.tet_nodes, inputs.star_offset, inputs.star_count, inputs.star_tets):
            return False
        if held_by_joint(v, u, inputs.joint_a, inputs.joint_b, n_joints, inputs.joint_broken):
            return False
    return True


NODE_FACE_LIST = make_list_kernels(
    ListSpec(
        inputs=NodeFaceInputs,
        radius=node_face_search_radius,
        accept=is_node_face_candidate,
        active=on_surface,
    )
)
"""Build kernel of the node–face lists (no history: a node's spring follows the node, kernels below)."""


# ----------------------------------------------------------------------------------------------------------------
# Forces.


@wp.func
def sphere_face_contact(x: wp.vec3d, r: float, fn: wp.vec3i, node_q: wp.array(dtype=wp.vec3)):
    """Geometry of a sphere (centre x, radius r) against the triangle of nodes fn.

    The vertices are taken relative to the centre (float64 differences rounded once), so the arithmetic is the
    same wherever the pair is.

    Returns:
        (barycentric weights of the closest point, unit normal from it to x, distance [m], touching (r beyond the
        distance and x in front of the face), in the face's interior).
    """
    a = relative_position(node_q[fn[0]], x)
    b = relative_position(node_q[fn[1]], x)
    c = relative_position(node_q[fn[2]], x)
    w = closest_point_barycentric(wp.vec3(0.0), a, b, c)
    d = -(w[0] * a + w[1] * b + w[2] * c)
    dist = wp.length(d)
    nf = wp.cross(b - a, c - a)
    touching = dist < r and wp.dot(d, nf) > 0.0
    n = wp.vec3(0.0)
    if dist > 0.0:
        n = d / dist
    interior = min3(w) > BARY_EPS
    return w, n, dist, touching, interior


@functools.cache
def make_sphere_face_kernel(normal: str, tangential: str, rolling: str, track_energy: bool):
    """The sphere–face kernels for one choice of the sphere contact laws (kernels/contact.py).

    Energy books (``track_energy``) as for the sphere contacts (kernels/contact.py ``make_contact_kernels``): each
    pair books the half of its work that lies behind, ½ dt f·v_rel (with the rolling torque's ½ dt M·ω), and adds
    its forces to the sphere's sums (``contact_f_normal`` …) and to the face nodes' ``node_f_contact``, whose half
    ahead the integrator and ``book_half_ahead_kernel`` (kernels/integrate.py) book against v_{n+1/2} (the
    sphere's share to ``energy_damping`` / ``energy_friction``, the nodes' to ``node_energy_contact``). The
    dissipation is then
    D = -W - ΔU exactly, ΔU from the sphere's sphere–face spring energies at the last evaluation,
    ``sphere_face_energy_prev`` (normal → ``energy_damping``, tangential → ``energy_friction``; the change of a
    tangential spring's energy with k_t at fixed ξ → ``energy_stiffness_change``).

    Returns:
        (eval_sphere_faces_kernel, sphere_face_energy_kernel).
    """
    laws = make_pair_laws(normal, tangential, rolling)
    pair_interaction = laws.pair_interaction
    normal_force = laws.normal_force
    tangential_stiffness = laws.tangential_stiffness
    elastic_energy = laws.elastic_energy

    @wp.func
    def counted_face(
        i: int,
        x: wp.vec3d,
        r: float,
        face_radius: float,
        count: int,
        max_sphere_faces: int,
        sphere_face_index: wp.array(dtype=int),
        face_nodes: wp.array(dtype=wp.vec3i),
        node_q: wp.array(dtype=wp.vec3),
    ) -> int:
        """The nearest touching face of sphere i (an edge or vertex contact counts only if it is this one), -1.

        Ties are judged relative to the size of the coordinates the distances come from, the vertices relative to
        the centre: within r + 2 face_radius of it for a touching face.
        """
        tol = TIE_EPS * (r + 2.0 * face_radius)
        best_d = float(0.0)
        best_interior = int(0)
        best_f = int(-1)
        for s in range(count):
            f = sphere_face_index[i * max_sphere_faces + s]
            fn = face_nodes[f]
            _w, _n, dist, touching, interior = sphere_face_contact(x, r, fn, node_q)
            if touching:
                inside = int(interior)
                if nearer(dist, inside, f, best_d, best_interior, best_f, tol):
                    best_d = dist
                    best_interior = inside
                    best_f = f
        return best_f

    @wp.kernel(enable_backward=False, module="unique")
    def eval_sphere_faces_kernel(
        # Model:
        particle_radius: wp.array(dtype=float),
        particle_inv_mass: wp.array(dtype=float),
        particle_material: wp.array(dtype=int),
        pair_table: wp.array(dtype=ContactPair),
        num_materials: int,
        node_inv_mass: wp.array(dtype=float),
        tet_material: wp.array(dtype=int),
        face_nodes: wp.array(dtype=wp.vec3i),
        face_tet: wp.array(dtype=int),
        face_radius: float,
        max_sphere_faces: int,
        dt: float,
        # State in:
        particle_count: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        particle_qd: wp.array(dtype=wp.vec3),
        particle_omega: wp.array(dtype=wp.vec3),
        sphere_face_count: wp.array(dtype=int),
        sphere_face_index: wp.array(dtype=int),
        node_q: wp.array(dtype=wp.vec3),
        node_qd: wp.array(dtype=wp.vec3),
        # State out:
        sphere_face_shear: wp.array(dtype=wp.vec3),
        particle_f: wp.array(dtype=wp.vec3),
        particle_t: wp.array(dtype=wp.vec3),
        node_f: wp.array(dtype=wp.vec3),
        contact_f_normal: wp.array(dtype=wp.vec3),
        contact_f_tangential: wp.array(dtype=wp.vec3),
        contact_t_tangential: wp.array(dtype=wp.vec3),
        node_f_contact: wp.array(dtype=wp.vec3),
        sphere_face_energy_prev: wp.array(dtype=wp.vec2),
        energy_damping: wp.array(dtype=wp.float64),
        energy_friction: wp.array(dtype=wp.float64),
        energy_stiffness_change: wp.array(dtype=wp.float64),
    ):
        i = wp.tid()  # one thread per particle slot; it owns its sphere–face pairs
        if i >= particle_count[0]:
            return
        count = wp.min(sphere_face_count[i], max_sphere_faces)
        if count == 0:
            if wp.static(track_energy):
                prev = sphere_face_energy_prev[i]
                if prev[0] != 0.0 or prev[1] != 0.0:  # the last springs went with the lists: their energy dissipated
                    sphere_face_energy_prev[i] = wp.vec2(0.0)
                    if dt > 0.0:
                        energy_damping[i] = energy_damping[i] + wp.float64(prev[0])
                        energy_friction[i] = energy_friction[i] + wp.float64(prev[1])
            return
        x = particle_q[i]
        r = particle_radius[i]
        inv_mi = particle_inv_mass[i]
        # Pass 1: the nearest contact (an edge or vertex contact counts only if it is the nearest).
        best_f = counted_face(i, x, r, face_radius, count, max_sphere_faces, sphere_face_index, face_nodes, node_q)
        # Pass 2: springs of pairs that no longer count are handed to a pair that starts counting (the contact
        # point slid from one face onto the next).
        orphan = wp.vec3(0.0)
        a_t = float(0.0)  # the tangential springs' energy at their old ξ under the new stiffness, ½ k_t |ξ_n|² [J]
        a_orphan = float(0.0)  # the orphan's share of a_t, until a pair takes it over
        mat_i = particle_material[i]
        for s in range(count):
            slot = i * max_sphere_faces + s
            f = sphere_face_index[slot]
            fn = face_nodes[f]
            w, n, dist, touching, interior = sphere_face_contact(x, r, fn, node_q)
            if not (touching and (interior or f == best_f)):
                sh = sphere_face_shear[slot]
                if wp.static(track_energy):
                    # A spring let go of is released at k_t(0) (zero where k_t follows the overlap).
                    p = pair_table[mat_i * num_materials + tet_material[face_tet[f]]]
                    a = 0.5 * tangential_stiffness(0.0, r, normal_force(0.0, 0.0, r, r, r, 1.0, p)[2], p)
                    a = a * wp.dot(sh, sh)
                    a_t += a
                    if wp.dot(sh, sh) > wp.dot(orphan, orphan):
                        a_orphan = a
                if wp.dot(sh, sh) > wp.dot(orphan, orphan):
                    orphan = sh
                sphere_face_shear[slot] = wp.vec3(0.0)
        # Pass 3: forces.
        vi = particle_qd[i]
        wi = particle_omega[i]
        f_i = wp.vec3(0.0)
        t_i = wp.vec3(0.0)
        d_damp = float(0.0)  # minus the work behind [J]
        d_fric = float(0.0)  # the same, tangential and rolling [J]
        e_n = float(0.0)  # normal spring energy of the sphere's face pairs [J]
        e_t = float(0.0)  # tangential spring energy, ½ k_t(δ_{n+1}) |ξ_{n+1}|² [J]
        fn_i = wp.vec3(0.0)  # the sphere's contact force sums
        ft_i = wp.vec3(0.0)
        tt_i = wp.vec3(0.0)
        for s in range(count):
            slot = i * max_sphere_faces + s
            f = sphere_face_index[slot]
            fn = face_nodes[f]
            w, n, dist, touching, interior = sphere_face_contact(x, r, fn, node_q)
            if not (touching and (interior or f == best_f)):
                continue
            inv_sum = inv_mi
            inv_sum += w[0] * w[0] * node_inv_mass[fn[0]] + w[1] * w[1] * node_inv_mass[fn[1]]
            inv_sum += w[2] * w[2] * node_inv_mass[fn[2]]
            if inv_sum == 0.0:
                continue
            shear_old = sphere_face_shear[slot]
            if wp.dot(shear_old, shear_old) == 0.0:
                shear_old = orphan
                orphan = wp.vec3(0.0)
                a_t -= a_orphan  # handed over, not let go of
                a_orphan = 0.0
            delta = r - dist
            ci = r - delta  # lever arm to the contact point
            v_face = w[0] * node_qd[fn[0]] + w[1] * node_qd[fn[1]] + w[2] * node_qd[fn[2]]
            v_rel = (vi - ci * wp.cross(wi, n)) - v_face
            mstar = 1.0 / inv_sum
            p = pair_table[mat_i * num_materials + tet_material[face_tet[f]]]
            # A face is flat: R* = r, as for a wall.
            out = pair_interaction(n, delta, r, r, r, mstar, v_rel, wi, shear_old, p, dt)
            force = out[0]
            roll = out[1]
            sphere_face_shear[slot] = out[2]
            ft = force - wp.dot(force, n) * n
            f_i += force
            t_i += wp.cross(-ci * n, ft) + roll
            # Equal and opposite, spread over the face's nodes by the weights of the contact point.
            wp.atomic_add(node_f, fn[0], -w[0] * force)
            wp.atomic_add(node_f, fn[1], -w[1] * force)
            wp.atomic_add(node_f, fn[2], -w[2] * force)
            if wp.static(track_energy):
                fnv = normal_force(delta, 0.0, r, r, r, 1.0, p)
                kt = tangential_stiffness(delta, r, fnv[2], p)
                e_n += elastic_energy(delta, fnv[2])
                e_t += 0.5 * kt * wp.dot(out[2], out[2])
                a_t += 0.5 * kt * wp.dot(shear_old, shear_old)
                f_normal = wp.dot(force, n)
                d_damp -= 0.5 * dt * f_normal * wp.dot(v_rel, n)
                d_fric -= 0.5 * dt * (wp.dot(ft, v_rel) + wp.dot(roll, wi))
                fn_i += f_normal * n
                ft_i += ft
                tt_i += wp.cross(-ci * n, ft) + roll
                wp.atomic_add(node_f_contact, fn[0], -w[0] * force)
                wp.atomic_add(node_f_contact, fn[1], -w[1] * force)
                wp.atomic_add(node_f_contact, fn[2], -w[2] * force)
        wp.atomic_add(particle_f, i, f_i)
        wp.atomic_add(particle_t, i, t_i)
        if wp.static(track_energy):
            book_contact_force(i, fn_i, ft_i, tt_i, contact_f_normal, contact_f_tangential, contact_t_tangential)
            prev = sphere_face_energy_prev[i]
            sphere_face_energy_prev[i] = wp.vec2(e_n, e_t)
            if dt > 0.0:  # the set-up evaluation (dt = 0) only records the springs' energies
                d_n = wp.float64(d_damp) - (wp.float64(e_n) - wp.float64(prev[0]))
                d_t = wp.float64(d_fric) - (wp.float64(e_t) - wp.float64(a_t))
                energy_damping[i] = energy_damping[i] + d_n
                energy_friction[i] = energy_friction[i] + d_t
                energy_stiffness_change[i] = energy_stiffness_change[i] + (wp.float64(a_t) - wp.float64(prev[1]))

    @wp.kernel(enable_backward=False, module="unique")
    def sphere_face_energy_kernel(
        # Model:
        particle_radius: wp.array(dtype=float),
        particle_inv_mass: wp.array(dtype=float),
        particle_material: wp.array(dtype=int),
        pair_table: wp.array(dtype=ContactPair),
        num_materials: int,
        node_inv_mass: wp.array(dtype=float),
        tet_material: wp.array(dtype=int),
        face_nodes: wp.array(dtype=wp.vec3i),
        face_tet: wp.array(dtype=int),
        face_radius: float,
        max_sphere_faces: int,
        # State in:
        particle_count: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        sphere_face_count: wp.array(dtype=int),
        sphere_face_index: wp.array(dtype=int),
        sphere_face_shear: wp.array(dtype=wp.vec3),
        node_q: wp.array(dtype=wp.vec3),
        # Out:
        energy: wp.array(dtype=wp.float64),
    ):
        i = wp.tid()  # one thread per particle slot: elastic energy of its sphere–face springs
        energy[i] = wp.float64(0.0)
        if i >= particle_count[0]:
            return
        count = wp.min(sphere_face_count[i], max_sphere_faces)
        x = particle_q[i]
        r = particle_radius[i]
        best_f = counted_face(i, x, r, face_radius, count, max_sphere_faces, sphere_face_index, face_nodes, node_q)
        e = float(0.0)
        for s in range(count):
            slot = i * max_sphere_faces + s
            f = sphere_face_index[slot]
            fn = face_nodes[f]
            w, _n, dist, touching, interior = sphere_face_contact(x, r, fn, node_q)
            if not (touching and (interior or f == best_f)):
                continue
            inv_sum = particle_inv_mass[i] + w[0] * w[0] * node_inv_mass[fn[0]]
            inv_sum += w[1] * w[1] * node_inv_mass[fn[1]] + w[2] * w[2] * node_inv_mass[fn[2]]
            if inv_sum == 0.0:
                continue
            delta = r - dist
            p = pair_table[particle_material[i] * num_materials + tet_material[face_tet[f]]]
            fnv = normal_force(delta, 0.0, r, r, r, 1.0, p)
            kt = tangential_stiffness(delta, r, fnv[2], p)
            sh = sphere_face_shear[slot]
            e += elastic_energy(delta, fnv[2]) + 0.5 * kt * wp.dot(sh, sh)
        energy[i] = wp.float64(e)

    return eval_sphere_faces_kernel, sphere_face_energy_kernel


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


@wp.func
def node_normal(
    v: int,
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_face_nbr: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    normal_body: wp.array(dtype=int),
    rest_normal: wp.array(dtype=wp.vec3),
    body_q: wp.array(dtype=wp.quatd),
) -> wp.vec3:
    """n_v of node v: for a node of a rigid block whose star is all rigid (``normal_body`` its body, -1 otherwise) its
    normal at the switch turned with the body, R(q) n_v0 ("Rigid normals"); otherwise :func:`node_surface_normal`."""
    b = normal_body[v]
    if b >= 0:
        return wp.vec3(wp.quat_rotate(body_q[b], wp.vec3d(rest_normal[v])))
    return node_surface_normal(v, tet_nodes, tet_face_nbr, star_offset, star_count, star_tets, node_q)


@wp.func
def kept_face_holds(
    v: int,
    x: wp.vec3,
    keep: int,
    hint: int,
    max_node_faces: int,
    node_face_count: wp.array(dtype=int),
    node_face_index: wp.array(dtype=int),
    face_nodes: wp.array(dtype=wp.vec3i),
    face_depth: wp.array(dtype=float),
    face_normal: wp.array(dtype=wp.vec3),
    normal: wp.vec3,
    node_q: wp.array(dtype=wp.vec3),
):
    """Whether the kept face ``keep`` is still node v's target: a candidate of v that v lies behind (less deep than
    face_depth), that faces v's normal n_v (``normal``) and that v projects into within KEEP_EPS; the tests of
    :func:`node_face_target` for that face, in its arithmetic. Whether it is a candidate is read at the list slot
    ``hint`` where the last evaluation found it; only when it is not there (the list was rebuilt since, or no hint)
    is the list searched: the same answer, without a pass over some thirty slots for nearly every node.

    Returns:
        (holds, its list slot (-1 when not listed), depth δ [m], barycentric weights of the projection, the face's
        unit normal).
    """
    count = wp.min(node_face_count[v], max_node_faces)
    slot = int(-1)
    if hint >= 0 and hint < count:
        if node_face_index[v * max_node_faces + hint] == keep:
            slot = hint
    if slot < 0:
        for s in range(count):
            if node_face_index[v * max_node_faces + s] == keep:
                slot = s
                break
    if slot < 0:
        return False, -1, 0.0, wp.vec3(0.0), wp.vec3(0.0)
    fn = face_nodes[keep]
    a = node_q[fn[0]]
    nf = face_normal[keep]
    depth = -wp.dot(x - a, nf)
    if depth <= 0.0 or depth >= face_depth[keep] or wp.dot(nf, normal) >= 0.0:
        return False, slot, 0.0, wp.vec3(0.0), wp.vec3(0.0)
    b = node_q[fn[1]]
    c = node_q[fn[2]]
    w = projection_barycentric(x, a, b, c, wp.cross(b - a, c - a))
    if min3(w) < -KEEP_EPS:
        return False, slot, 0.0, wp.vec3(0.0), wp.vec3(0.0)
    return True, slot, depth, w, nf


@wp.func
def node_face_target(
    v: int,
    x: wp.vec3,
    max_node_faces: int,
    node_face_count: wp.array(dtype=int),
    node_face_index: wp.array(dtype=int),
    face_nodes: wp.array(dtype=wp.vec3i),
    face_depth: wp.array(dtype=float),
    face_normal: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_face_nbr: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    normal_body: wp.array(dtype=int),
    rest_normal: wp.array(dtype=wp.vec3),
    body_q: wp.array(dtype=wp.quatd),
    keep: int,
    hint: int,
):
    """The face node v (at x, its own surface's outward normal n_v) is pushed out of: of the candidate faces
    that face it (n_f · n_v < 0) and that it lies behind (less deep than face_depth) and projects into, the
    shallowest; an interior contact before an edge or vertex one, then the lowest face index. The face ``keep``
    (the node's target at the last evaluation, -1 for none) is kept while it stays one of those faces: the shallowest
    face jumps where two face planes meet, and a target held until it no longer holds the node switches less often.

    The facing test keeps a node on a convex edge of one body, which sits exactly on the edge of the body it rests
    on, from being pushed out through that body's side face (where it is "behind" the side plane by a rounding
    error): the side face's normal points along the node's own, the face it rests on against it.

    The tests run cheapest first and give the same decisions in any order: the depth test reads the face's unit
    normal from ``face_normal`` (face_normals_kernel, this step's positions), n_v is summed only for a node with a
    candidate it lies behind, and the projection only for a face that passes both.

    The kept face is tried first (:func:`kept_face_holds`): when it holds, the scan of all candidates would end on it
    with the same numbers (it replaces whatever came before it and nothing after it is looked at), so the scan is
    skipped. A node in a lasting contact, nearly every surface node of a block pile, then tests one face a step instead
    of all its candidates (some thirty in a lattice of blocks, each face touching a block corner is one): the same
    result bit for bit, at a fraction of the cost.

    Returns:
        (face or -1, its slot in v's candidate list (-1 with no face), depth δ [m], barycentric weights of the
        projection, the face's unit normal).
    """
    normal = wp.vec3(0.0)
    has_normal = int(0)
    if keep >= 0:
        normal = node_normal(
            v, tet_nodes, tet_face_nbr, star_offset, star_count, star_tets, node_q, normal_body, rest_normal, body_q
        )
        has_normal = 1
        holds, keep_slot, keep_d, keep_w, keep_n = kept_face_holds(
            v,
            x,
            keep,
            hint,
            max_node_faces,
            node_face_count,
            node_face_index,
            face_nodes,
            face_depth,
            face_normal,
            normal,
            node_q,
        )
        if holds:
            return keep, keep_slot, keep_d, keep_w, keep_n
    tol = TIE_EPS * wp.length(x)
    best_d = float(0.0)
    best_interior = int(0)
    best_f = int(-1)
    best_slot = int(-1)
    best_w = wp.vec3(0.0)
    best_n = wp.vec3(0.0)
    for s in range(wp.min(node_face_count[v], max_node_faces)):
        f = node_face_index[v * max_node_faces + s]
        if f == keep:
            continue  # it does not hold (above)
        fn = face_nodes[f]
        a = node_q[fn[0]]
        nf = face_normal[f]
        depth = -wp.dot(x - a, nf)
        if depth <= 0.0 or depth >= face_depth[f]:
            continue
        if has_normal == 0:
            normal = node_normal(
                v, tet_nodes, tet_face_nbr, star_offset, star_count, star_tets, node_q, normal_body, rest_normal, body_q
            )
            has_normal = 1
        if wp.dot(nf, normal) >= 0.0:
            continue
        b = node_q[fn[1]]
        c = node_q[fn[2]]
        w = projection_barycentric(x, a, b, c, wp.cross(b - a, c - a))
        if min3(w) < -BARY_EPS:
            continue
        inside = int(min3(w) > BARY_EPS)
        if nearer(depth, inside, f, best_d, best_interior, best_f, tol + TIE_EPS * depth):
            best_d = depth
            best_interior = inside
            best_f = f
            best_slot = s
            best_w = w
            best_n = nf
    return best_f, best_slot, best_d, best_w, best_n


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
):
    f = wp.tid()  # one thread per face slot: the unit normal n_f at the current positions, once for all its nodes
    if f >= face_count[0]:
        return
    fn = face_nodes[f]
    a = node_q[fn[0]]
    b = node_q[fn[1]]
    c = node_q[fn[2]]
    face_normal[f] = wp.normalize(wp.cross(b - a, c - a))


@wp.func
def plane_depth(x: wp.vec3, f: int, face_nodes: wp.array(dtype=wp.vec3i), node_q: wp.array(dtype=wp.vec3)) -> float:
    """Depth of x behind the plane of face f [m] (negative in front of it); 0 for a face index past the arrays."""
    if f < 0 or f >= face_nodes.shape[0]:
        return 0.0
    fn = face_nodes[f]
    a = node_q[fn[0]]
    return -wp.dot(x - a, wp.normalize(wp.cross(node_q[fn[1]] - a, node_q[fn[2]] - a)))


@wp.func
def moved_plane_depth(
    x: wp.vec3, fn: wp.vec3i, node_q: wp.array(dtype=wp.vec3), node_qd: wp.array(dtype=wp.vec3), dt: float
) -> float:
    """Depth of x behind the plane of the face with nodes fn at the last step's positions x_k - dt v_k [m]."""
    a = node_q[fn[0]] - dt * node_qd[fn[0]]
    b = node_q[fn[1]] - dt * node_qd[fn[1]]
    c = node_q[fn[2]] - dt * node_qd[fn[2]]
    return -wp.dot(x - a, wp.normalize(wp.cross(b - a, c - a)))


@wp.func
def spring_depth(
    x: wp.vec3, f: int, offset: float, face_nodes: wp.array(dtype=wp.vec3i), node_q: wp.array(dtype=wp.vec3)
):
    """Compression of a node's face spring [m]: its depth behind the target face f less the offset it carries
    (non-negative; 0 with no target)."""
    if f < 0:
        return 0.0
    return wp.max(plane_depth(x, f, face_nodes, node_q) - offset, 0.0)


@wp.func
def penalty_contact(
    n: wp.vec3,
    delta: float,
    kn: float,
    mstar: float,
    v_rel: wp.vec3,
    shear: wp.vec3,
    p: ContactPair,
    dt: float,
):
    """Linear penalty contact of a node (kernels/contact.py laws): normal k δ with the dashpot of ζ = p.damp_n,
    tangential spring k_t = kt_ratio k with Coulomb limit and ζ = p.damp_t.

    Returns:
        (force on the node [N], new tangential spring [m]); its dissipation is booked as Verlet does the work
        (``make_node_contact_kernel``).
    """
    vn = wp.dot(v_rel, n)
    fnv = linear_normal_force(delta, vn, kn, mstar, p)
    vt = v_rel - vn * n
    kt = p.kt_ratio * kn
    s_old = rotate_into_plane(shear, n)
    tang = coulomb_tangential(s_old, vt, kt, 2.0 * p.damp_t * wp.sqrt(mstar * kt), fnv[0], p.friction, dt)
    return fnv[0] * n + tang[0], tang[1]


@wp.func
def face_contact_pair(
    mat_v: int,
    f: int,
    face_tet: wp.array(dtype=int),
    face_joint: wp.array(dtype=int),
    tet_material: wp.array(dtype=int),
    fem_pair_table: wp.array(dtype=ContactPair),
    joint_material_table: wp.array(dtype=JointMaterial),
    num_materials: int,
) -> ContactPair:
    """The contact law of a node of material ``mat_v`` on face f: its joint set's where f is a joint face, else the
    pair of the two materials (the face's tet's material read only then: two loads fewer per joint contact)."""
    js = face_joint[f]
    if js >= 0:
        return joint_material_table[js].contact
    return fem_pair_table[mat_v * num_materials + tet_material[face_tet[f]]]


@wp.func
def node_spring_energy(
    v: int,
    x: wp.vec3,
    kn: float,
    mat_v: int,
    f: int,
    offset: float,
    face_nodes: wp.array(dtype=wp.vec3i),
    face_joint: wp.array(dtype=int),
    face_tet: wp.array(dtype=int),
    tet_material: wp.array(dtype=int),
    fem_pair_table: wp.array(dtype=ContactPair),
    joint_material_table: wp.array(dtype=JointMaterial),
    num_materials: int,
    wall_normal: wp.array(dtype=wp.vec3),
    wall_material: wp.array(dtype=int),
    num_walls: int,
    node_q: wp.array(dtype=wp.vec3),
    node_face_shear: wp.array(dtype=wp.vec3),
    node_wall_shear: wp.array(dtype=wp.vec3),
    wall_point: wp.array(dtype=wp.vec3d),
) -> float:
    """Elastic energy [J] of node v's springs at x: its face spring (target f, carrying ``offset``) and its wall
    springs, normal ½ k δ² and tangential ½ k_t |ξ|² (the same sum in the force evaluation and the energy books)."""
    e = float(0.0)
    if f >= 0 and f < face_nodes.shape[0]:
        p = face_contact_pair(
            mat_v, f, face_tet, face_joint, tet_material, fem_pair_table, joint_material_table, num_materials
        )
        d = spring_depth(x, f, offset, face_nodes, node_q)
        sh = node_face_shear[v]
        e += 0.5 * kn * d * d + 0.5 * p.kt_ratio * kn * wp.dot(sh, sh)
    for wall in range(num_walls):
        gap = wp.dot(wp.vec3(wp.vec3d(x) - wall_point[wall]), wall_normal[wall])
        if gap < 0.0:
            p = fem_pair_table[mat_v * num_materials + wall_material[wall]]
            sh = node_wall_shear[v * num_walls + wall]
            e += 0.5 * kn * gap * gap + 0.5 * p.kt_ratio * kn * wp.dot(sh, sh)
    return e


@functools.cache
def make_node_contact_kernel(track_energy: bool):
    """The node–face and node–wall force kernel.

    Energy books (``track_energy``), as for the sphere contacts (kernels/contact.py ``make_contact_kernels``):
    velocity Verlet works a force f_n over ½ dt f_n·(v_{n-1/2} + v_{n+1/2}), and v_{n-1/2} is the velocity during the
    evaluation of f_n. So each node books here the half of its springs' work that lies behind, ½ dt f·v_rel (against
    the face's velocity at the contact point, or the wall's), and adds its forces to ``node_f_contact`` of itself and
    of the face's nodes, which ``book_half_ahead_kernel`` (kernels/integrate.py) dots with v_{n+1/2} before the
    next evaluation (the half ahead). The dissipation is then D = -W - ΔU exactly (dashpots, friction, a spring let
    go of or handed to a shallower face), ΔU from the springs' energy at the last evaluation,
    ``node_contact_energy_prev``. An evaluation at dt = 0 (set-up, the re-evaluation after a topology pass) records the
    springs' energy and books what it lets go of at the same positions.
    """

    @wp.kernel(enable_backward=False, module="unique")
    def eval_node_contacts_kernel(
        # Model:
        node_inv_mass: wp.array(dtype=float),
        node_mass: wp.array(dtype=float),
        node_contact_stiffness: wp.array(dtype=float),
        node_contact_material: wp.array(dtype=int),
        tet_nodes: wp.array(dtype=wp.vec4i),
        tet_face_nbr: wp.array(dtype=int),
        star_offset: wp.array(dtype=int),
        star_count: wp.array(dtype=int),
        star_tets: wp.array(dtype=int),
        tet_material: wp.array(dtype=int),
        face_nodes: wp.array(dtype=wp.vec3i),
        face_tet: wp.array(dtype=int),
        face_joint: wp.array(dtype=int),
        face_depth: wp.array(dtype=float),
        fem_pair_table: wp.array(dtype=ContactPair),
        joint_material_table: wp.array(dtype=JointMaterial),
        num_materials: int,
        wall_normal: wp.array(dtype=wp.vec3),
        wall_velocity: wp.array(dtype=wp.vec3),
        wall_material: wp.array(dtype=int),
        num_walls: int,
        max_node_faces: int,
        dt: float,
        # State in:
        node_count: wp.array(dtype=int),
        node_q: wp.array(dtype=wp.vec3),
        node_qd: wp.array(dtype=wp.vec3),
        node_face_count: wp.array(dtype=int),
        node_face_index: wp.array(dtype=int),
        wall_point: wp.array(dtype=wp.vec3d),
        body_q: wp.array(dtype=wp.quatd),
        # In:
        face_normal: wp.array(dtype=wp.vec3),
        normal_body: wp.array(dtype=int),
        rest_normal: wp.array(dtype=wp.vec3),
        born_relaxed: int,
        # State out:
        node_face_spring: wp.array(dtype=int),
        node_face_offset: wp.array(dtype=float),
        node_face_shear: wp.array(dtype=wp.vec3),
        node_wall_shear: wp.array(dtype=wp.vec3),
        node_contact_hold: wp.array(dtype=wp.float64),
        node_f: wp.array(dtype=wp.vec3),
        node_f_contact: wp.array(dtype=wp.vec3),
        node_contact_energy_prev: wp.array(dtype=wp.float64),
        node_energy_contact: wp.array(dtype=wp.float64),
        node_energy_boundary_work: wp.array(dtype=wp.float64),
        # Out:
        node_target_slot: wp.array(dtype=int),  # read too: the last evaluation's slot, a hint (kept_face_holds)
    ):
        v = wp.tid()  # one thread per node slot
        if v >= node_count[0]:
            return
        if node_contact_stiffness[v] == 0.0:
            return  # a node inside the rock
        kn = held_stiffness(node_contact_stiffness[v], node_contact_hold[v], node_mass[v])
        x = node_q[v]
        xv = node_qd[v]
        inv_mv = node_inv_mass[v]
        mat_v = node_contact_material[v]
        best_f = int(-1)
        best_d = float(0.0)
        best_w = wp.vec3(0.0)
        best_n = wp.vec3(0.0)
        old_f = node_face_spring[v]
        best_slot = int(-1)
        if node_face_count[v] > 0:
            best_f, best_slot, best_d, best_w, best_n = node_face_target(
                v,
                x,
                max_node_faces,
                node_face_count,
                node_face_index,
                face_nodes,
                face_depth,
                face_normal,
                tet_nodes,
                tet_face_nbr,
                star_offset,
                star_count,
                star_tets,
                node_q,
                normal_body,
                rest_normal,
                body_q,
                old_f,
                node_target_slot[v],
            )
        node_target_slot[v] = best_slot
        f_v = wp.vec3(0.0)
        d_v = float(0.0)  # minus the work behind [J] (the wall's share of the work ahead included)
        # What a re-evaluation at dt = 0 lets go of at the same positions [J]: a spring handed to a shallower face,
        # one left with no target, tangential springs cut back to their Coulomb limit (its D = -ΔU, W = 0).
        r_v = float(0.0)
        # The spring is continuous across a change of target: the new face takes over the old spring's compression
        # at the current positions (at most its own depth: the excess is dissipated), and carries the rest of its
        # depth as an offset, so that ½ k δ² never jumps up without work. A spring left with no target is
        # dissipated with its tangential part.
        offset = node_face_offset[v]
        delta = float(0.0)
        if best_f != old_f:
            offset = float(0.0)
            delta = best_d
            if old_f >= 0:
                old_delta = spring_depth(x, old_f, node_face_offset[v], face_nodes, node_q)
                delta = wp.min(best_d, old_delta)
                offset = best_d - delta
                r_v += 0.5 * kn * (old_delta * old_delta - delta * delta)
            elif dt > 0.0:
                # A new spring takes only the depth gained in this step: a node that was already behind the face's
                # plane at the last positions x - dt v (it slid in past an edge, or the face turned towards it)
                # carries that depth as an offset instead of starting at ½ k δ² that no force worked for.
                before = moved_plane_depth(x - dt * xv, face_nodes[best_f], node_q, node_qd, dt)
                offset = wp.min(wp.max(before, 0.0), best_d)
                delta = best_d - offset
            elif born_relaxed != 0:
                # The re-evaluation after a topology pass: nothing moved, so no depth was gained. A node that finds
                # itself behind a face only now (a new crack face, or its own surface turned by the faces it gained)
                # carries that depth as its offset.
                offset = best_d
        elif best_f >= 0:
            # The relaxed depth follows a node that backs out (no work: the spring is slack meanwhile).
            offset = wp.min(offset, best_d)
            delta = best_d - offset
        node_face_spring[v] = best_f
        node_face_offset[v] = offset
        if best_f < 0:
            if old_f >= 0 and old_f < face_nodes.shape[0]:
                p_old = face_contact_pair(
                    mat_v,
                    old_f,
                    face_tet,
                    face_joint,
                    tet_material,
                    fem_pair_table,
                    joint_material_table,
                    num_materials,
                )
                sh = node_face_shear[v]
                r_v += 0.5 * p_old.kt_ratio * kn * wp.dot(sh, sh)
            node_face_shear[v] = wp.vec3(0.0)  # history lives only as long as the node touches
        else:
            fn = face_nodes[best_f]
            # Weights on the triangle (an edge or vertex contact has one slightly negative): clamp and normalise.
            w = wp.vec3(wp.max(best_w[0], 0.0), wp.max(best_w[1], 0.0), wp.max(best_w[2], 0.0))
            w = w / (w[0] + w[1] + w[2])
            inv_sum = inv_mv
            inv_sum += w[0] * w[0] * node_inv_mass[fn[0]] + w[1] * w[1] * node_inv_mass[fn[1]]
            inv_sum += w[2] * w[2] * node_inv_mass[fn[2]]
            if inv_sum > 0.0:
                p = face_contact_pair(
                    mat_v,
                    best_f,
                    face_tet,
                    face_joint,
                    tet_material,
                    fem_pair_table,
                    joint_material_table,
                    num_materials,
                )
                v_face = w[0] * node_qd[fn[0]] + w[1] * node_qd[fn[1]] + w[2] * node_qd[fn[2]]
                sh = node_face_shear[v]
                force, shear = penalty_contact(best_n, delta, kn, 1.0 / inv_sum, xv - v_face, sh, p, dt)
                node_face_shear[v] = shear
                r_v -= 0.5 * p.kt_ratio * kn * (wp.dot(shear, shear) - wp.dot(sh, sh))
                f_v += force
                wp.atomic_add(node_f, fn[0], -w[0] * force)
                wp.atomic_add(node_f, fn[1], -w[1] * force)
                wp.atomic_add(node_f, fn[2], -w[2] * force)
                if wp.static(track_energy):
                    d_v -= 0.5 * dt * wp.dot(force, xv - v_face)
                    wp.atomic_add(node_f_contact, fn[0], -w[0] * force)
                    wp.atomic_add(node_f_contact, fn[1], -w[1] * force)
                    wp.atomic_add(node_f_contact, fn[2], -w[2] * force)
        w_wall = float(0.0)
        touching = int(0)
        if best_f >= 0:
            touching = 1
        for wall in range(num_walls):
            nw = wall_normal[wall]
            slot = v * num_walls + wall
            gap = wp.dot(wp.vec3(wp.vec3d(x) - wall_point[wall]), nw)
            if gap < 0.0:
                touching = 1
            if gap >= 0.0 or inv_mv == 0.0:
                node_wall_shear[slot] = wp.vec3(0.0)
                continue
            vw = wall_velocity[wall]
            p = fem_pair_table[mat_v * num_materials + wall_material[wall]]
            sh = node_wall_shear[slot]
            force, shear = penalty_contact(nw, -gap, kn, 1.0 / inv_mv, xv - vw, sh, p, dt)
            node_wall_shear[slot] = shear
            r_v -= 0.5 * p.kt_ratio * kn * (wp.dot(shear, shear) - wp.dot(sh, sh))
            f_v += force
            # The half ahead is booked against the node's own velocity, -½ dt f·v_{n+1/2}; against the wall's it is
            # -½ dt f·(v_{n+1/2} - v_w): the wall's share, +½ dt f·v_w, is booked here (v_w is constant), with the
            # half behind against the relative velocity: -½ dt f·(xv - 2 v_w) in all (as for a sphere on a wall).
            d_v -= 0.5 * dt * wp.dot(force, xv - 2.0 * vw)
            w_wall += wp.dot(force, vw) * dt  # work of a moving wall on the node
        wp.atomic_add(node_f, v, f_v)
        if touching == 0:
            # No spring of the node is stretched now (its face spring was let go above, and no wall gap is
            # negative), so the lumped stiffness takes over from a held one without changing any energy.
            node_contact_hold[v] = wp.float64(0.0)
        if wp.static(track_energy):
            if wp.length_sq(f_v) > 0.0:
                wp.atomic_add(node_f_contact, v, f_v)
            e_now = node_spring_energy(
                v,
                x,
                kn,
                mat_v,
                best_f,
                offset,
                face_nodes,
                face_joint,
                face_tet,
                tet_material,
                fem_pair_table,
                joint_material_table,
                num_materials,
                wall_normal,
                wall_material,
                num_walls,
                node_q,
                node_face_shear,
                node_wall_shear,
                wall_point,
            )
            prev = node_contact_energy_prev[v]
            node_contact_energy_prev[v] = wp.float64(e_now)
            # ΔU in float64, so that its sum over the steps telescopes to U_now - U_start exactly. At dt = 0 the
            # springs' energy before is not at hand for a split node's daughters, whose slots are new: what the
            # evaluation lets go of is booked from the springs it changes (r_v) instead.
            dissipated = wp.float64(r_v)
            if dt > 0.0:
                dissipated = wp.float64(d_v) - (wp.float64(e_now) - prev)
            if dissipated != wp.float64(0.0):
                node_energy_contact[v] = node_energy_contact[v] + dissipated
            if w_wall != 0.0:
                node_energy_boundary_work[v] = node_energy_boundary_work[v] + wp.float64(w_wall)

    return eval_node_contacts_kernel


@wp.kernel
def fem_contact_energy_kernel(
    # Model:
    node_contact_stiffness: wp.array(dtype=float),
    node_mass: wp.array(dtype=float),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_face_nbr: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    face_nodes: wp.array(dtype=wp.vec3i),
    face_joint: wp.array(dtype=int),
    face_tet: wp.array(dtype=int),
    tet_material: wp.array(dtype=int),
    node_contact_material: wp.array(dtype=int),
    fem_pair_table: wp.array(dtype=ContactPair),
    joint_material_table: wp.array(dtype=JointMaterial),
    num_materials: int,
    wall_normal: wp.array(dtype=wp.vec3),
    wall_material: wp.array(dtype=int),
    num_walls: int,
    face_depth: wp.array(dtype=float),
    max_node_faces: int,
    # State in:
    node_count: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    node_face_spring: wp.array(dtype=int),
    node_face_offset: wp.array(dtype=float),
    node_face_shear: wp.array(dtype=wp.vec3),
    node_wall_shear: wp.array(dtype=wp.vec3),
    node_contact_hold: wp.array(dtype=wp.float64),
    wall_point: wp.array(dtype=wp.vec3d),
    # Out:
    energy: wp.array(dtype=wp.float64),
):
    v = wp.tid()  # one thread per node slot: elastic energy of its node–face and node–wall springs
    energy[v] = wp.float64(0.0)
    if v >= node_count[0]:
        return
    if node_contact_stiffness[v] == 0.0:
        return
    kn = held_stiffness(node_contact_stiffness[v], node_contact_hold[v], node_mass[v])
    e = node_spring_energy(
        v,
        node_q[v],
        kn,
        node_contact_material[v],
        node_face_spring[v],  # the target of the last force evaluation
        node_face_offset[v],
        face_nodes,
        face_joint,
        face_tet,
        tet_material,
        fem_pair_table,
        joint_material_table,
        num_materials,
        wall_normal,
        wall_material,
        num_walls,
        node_q,
        node_face_shear,
        node_wall_shear,
        wall_point,
    )
    energy[v] = wp.float64(e)


# ----------------------------------------------------------------------------------------------------------------
# Face ids across a surface rebuild (after a split pass).


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
    t = face_tet[f]
    n = face_nodes[f]
    from_k = int(-1)
    nodes = tet_nodes[t]
    for k in range(4):
        if nodes[k] != n[0] and nodes[k] != n[1] and nodes[k] != n[2]:
            from_k = k
    if from_k >= 0:
        face_slot[f] = 4 * t + from_k


@wp.kernel
def remap_face_ids_kernel(
    # In:
    old_face_count: int,
    face_slot: wp.array(dtype=int),
    slot_to_face: wp.array(dtype=int),
    # Out:
    ids: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per entry of a face-id array: old face → its tet-face slot → the new face of that slot
    f = ids[i]
    if f < 0 or f >= old_face_count:
        return
    s = face_slot[f]
    if s < 0:
        ids[i] = -1
        return
    ids[i] = slot_to_face[s]
