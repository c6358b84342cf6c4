"""FEM contact (DESIGN.md stage 4): the node–face and node–wall forces with tangential history, and the node–face
candidate lists from a hash grid. The pieces it stands on, re-exported here: the boundary faces, the nodes' penalty
stiffness and the point–triangle geometry (kernels/fem_surface.py), the sphere–face lists and forces
(kernels/sphere_face.py), the node–face candidate test and list build (kernels/node_face_list.py), and the faces a
node is pushed out of (kernels/node_face_target.py).

Node–face: a node penetrates a face when the face faces it (n_f · n_v < 0, n_v the outward normal of the node's own
surface), it lies behind the face's plane (s = (x - x_a) · n_f < 0), less deep than half the tet's height over the face,
and it projects into the triangle (within RIM_EPS of the edges of a joint face, kernels/fem_surface.py: where two joint
faces are one cell across, every node of each sits on the rim of the other; within BARY_EPS of another). The reaction
acts on the face's nodes at that projection, on the force's line. The faces it penetrates are grouped by plane direction
(unit normals with |n_f · n_f'| > cos θ_g, θ_g = 60°, are one plane: kernels/node_face_target.py PLANE_GROUP_COS), and
of each plane it is pushed out of the shallowest face (the shortest way out; a vertex shared by coplanar faces goes to
the lowest face index), by a linear spring–dashpot k δ with k its penalty stiffness and ζ from the restitution (the laws
linear_normal_force and coulomb_tangential of kernels/contact.py). A node has NODE_SPRINGS = 3 spring slots, one per
plane, each with its own tangential history that follows the node from face to face within its plane: a node in an
inside corner of two or three blocks (a block lattice's corners lie on three joint planes, a brick's head joint on the
bedding too) is held out of every plane it is pressed into, where one spring per node held it out of one only and left a
joint whose every node lies on another plane held by nothing. The slots' normals keep pairwise |n_s · n_t| ≤ cos θ_g, so
a node's springs are no stiffer than SPRING_BOUND k = 2 k along any direction (Gershgorin), which the stable steps take
(warpdem.stages.fem_contact.contact_critical_step_at, warpdem.stages.rigid_step). Each spring never gains energy that no
force worked for (½ k δ² jumping up at an event is energy created; a jump down is booked as dissipated): a slot keeps
its target while the node still penetrates it (its projection may then stray KEEP_EPS outside the triangle: a node on
the rim of a joint sits on the edge of the face opposite); on a change of target within its plane the new spring starts
at no more than the old one's compression; a spring whose plane no face holds is let go (dissipated); a new contact (a
new plane) starts at the depth gained in the step, the depth the node already had behind the plane at the last positions
(it slid in past an edge) carried as an offset; the offset follows a node that backs out. The springs' energy is their
sum, in the force evaluation and in the books alike. Candidates exclude every face with a vertex in the node's 1-ring
(the node itself or a node it shares a tet with): a node never touches a face of a tet holding it, nor a face that holds
it, and near a crack tip the rock is still continuous. An intact joint element's pair is excluded too (the element
carries it). A spring let go of because its node went through the face (``passed_face``) is recorded for the
stability guard, which stops the run (warpdem.stages.guard).

Node–wall: as sphere–wall, with the node's penalty stiffness. A wall the rock is meshed onto is seated on it at set-up
(``seat_walls_kernel``, warpdem.stages.fem_contact.FemContact.seat_walls): moved back by the deepest node behind it
within float32 rounding, as a node–face spring within it starts relaxed (a wall spring holds no offset).

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
  (warpdem.stages.fem_contact.contact_critical_step_at) was taken for; holding k itself on a node that lost most of its
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
    coulomb_tangential,
    linear_normal_force,
    rotate_into_plane,
)
from .fem_surface import (
    BARY_EPS,
    KEEP_EPS,
    TIE_EPS,
    RimFaces,
    closest_point_barycentric,
    count_tet_faces_kernel,
    face_centers_kernel,
    face_extent_kernel,
    face_normals_kernel,
    find_joint,
    flag_boundary_faces_kernel,
    flag_fem_rebuild_kernel,
    held_by_joint,
    held_stiffness,
    hold_contact_stiffness_kernel,
    in_one_ring,
    min3,
    nearer,
    node_contact_stiffness_kernel,
    node_surface_normal,
    projection_barycentric,
    relative_position,
    remap_face_ids_kernel,
    rest_normals_kernel,
    rest_positions_kernel,
    rim_margins,
    scatter_boundary_faces_kernel,
    tet_face_slots_kernel,
)
from .joints import JointMaterial
from .node_face_list import (
    BOUND_SLACK,
    NODE_FACE_LIST,
    RIM_REACH,
    NodeFaceInputs,
    is_node_face_candidate,
    mark_near_new_nodes_kernel,
    node_face_search_radius,
    on_surface,
    own_body_face,
    within_reach,
)
from .node_face_target import (
    NODE_SPRINGS,
    PLANE_GROUP_COS,
    SPRING_BOUND,
    kept_face_holds,
    new_plane_face,
    node_face_targets,
    node_normal,
    same_plane,
)
from .sphere_face import (
    SPHERE_FACE_LIST,
    SphereFaceHistory,
    SphereFaceInputs,
    copy_sphere_face_history,
    fresh_sphere_face_history,
    is_sphere_face_candidate,
    make_sphere_face_kernel,
    sphere_face_contact,
    sphere_face_search_radius,
)

wp.set_module_options({"enable_backward": False})

__all__ = [
    "BARY_EPS",
    "BOUND_SLACK",
    "KEEP_EPS",
    "NODE_FACE_LIST",
    "NODE_SPRINGS",
    "PASSED_COMPRESSION",
    "PLANE_GROUP_COS",
    "RIM_REACH",
    "SPHERE_FACE_LIST",
    "SPRING_BOUND",
    "TIE_EPS",
    "NodeFaceInputs",
    "RimFaces",
    "SphereFaceHistory",
    "SphereFaceInputs",
    "closest_point_barycentric",
    "copy_sphere_face_history",
    "count_tet_faces_kernel",
    "face_centers_kernel",
    "face_contact_pair",
    "face_extent_kernel",
    "face_normals_kernel",
    "fem_contact_energy_kernel",
    "find_joint",
    "flag_boundary_faces_kernel",
    "flag_fem_rebuild_kernel",
    "fresh_sphere_face_history",
    "held_by_joint",
    "held_stiffness",
    "hold_contact_stiffness_kernel",
    "in_one_ring",
    "is_node_face_candidate",
    "is_sphere_face_candidate",
    "kept_face_holds",
    "make_node_contact_kernel",
    "make_sphere_face_kernel",
    "mark_near_new_nodes_kernel",
    "min3",
    "moved_plane_depth",
    "nearer",
    "new_plane_face",
    "node_contact_stiffness_kernel",
    "node_face_search_radius",
    "node_face_targets",
    "node_normal",
    "node_spring_energy",
    "node_surface_normal",
    "on_surface",
    "own_body_face",
    "passed_face",
    "penalty_contact",
    "plane_depth",
    "projection_barycentric",
    "relative_position",
    "remap_face_ids_kernel",
    "rest_normals_kernel",
    "rest_positions_kernel",
    "same_plane",
    "scatter_boundary_faces_kernel",
    "seat_walls_kernel",
    "sphere_face_contact",
    "sphere_face_search_radius",
    "spring_depth",
    "tet_face_slots_kernel",
    "wall_gap",
    "within_reach",
]


# ----------------------------------------------------------------------------------------------------------------
# Forces.


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


SET_UP_RELAXED = wp.constant(1.0e38)
"""A ``relaxed_depth`` below this at dt = 0 is the set-up's (float32 rounding of the model's extent), above it the
re-evaluation's after a pass or a switch (RELAXED_ALL, warpdem.stages.fem_contact) [m]: only the set-up drops a node
lying on a body's surface from a face behind it across a convex edge (kernels/node_face_target.py
``exits_over_convex_edge``)."""

PASSED_COMPRESSION = wp.constant(0.5)
"""The compression of a spring let go of past its face's reach, as a fraction of that reach, from which the node has
gone through the face (:func:`passed_face`) [-]. A spring at its design load is compressed by σ / (f E) of the tet's
height, 1e-3 or less for rock; a relaxed one (its depth carried as an offset) carries nothing: a node lying on a
block's top next to a neighbour's side face holds one on that face at its whole depth, which a settling of a few µm
takes past the reach (facility_nonpersistent)."""


@wp.func
def passed_face(
    x: wp.vec3,
    f: int,
    offset: float,
    face_nodes: wp.array(dtype=wp.vec3i),
    face_depth: wp.array(dtype=float),
    node_q: wp.array(dtype=wp.vec3),
    rims: RimFaces,
) -> bool:
    """Whether a node at x, let go of by face f, went through it: at least ``face_depth[f]`` (half the height of the
    tet over f, the contact's reach) behind its plane with the spring (``offset`` its relaxed depth) compressed by at
    least PASSED_COMPRESSION of that, while it still projects into f within the margin a kept target has
    (``kept_face_holds``'s other tests). The spring was let go for its depth alone, after pushing back over half the
    reach, and nothing pushes the node back out of the rock it is in (warpdem.stages.guard stops the run)."""
    fn = face_nodes[f]
    a = node_q[fn[0]]
    b = node_q[fn[1]]
    c = node_q[fn[2]]
    area2 = wp.cross(b - a, c - a)
    depth = -wp.dot(x - a, wp.normalize(area2))
    if depth < face_depth[f] or depth - offset < PASSED_COMPRESSION * face_depth[f]:
        return False
    return min3(projection_barycentric(x, a, b, c, area2)) >= -rim_margins(f, rims)[1]


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
def wall_gap(x: wp.vec3, point: wp.vec3d, normal: wp.vec3) -> float:
    """Gap of a node at x in front of a plane wall through ``point`` with unit ``normal`` [m] (negative behind it):
    the difference in float64 (the wall's point moves by dt v_w a step), the dot in float32. The forces, the energy
    books and the set-up seating (``seat_walls_kernel``) read this one expression, so that they agree to the bit."""
    return wp.dot(wp.vec3(wp.vec3d(x) - point), normal)


@wp.func
def node_spring_energy(
    v: int,
    x: wp.vec3,
    kn: float,
    mat_v: int,
    node_face_spring: wp.array(dtype=int),
    node_face_offset: wp.array(dtype=float),
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
    """Elastic energy [J] of node v's springs at x: its face springs (slot i = v NODE_SPRINGS + s targets
    ``node_face_spring[i]``, carrying ``node_face_offset[i]``, tangential ``node_face_shear[i]``) and its wall
    springs, normal ½ k δ² and tangential ½ k_t |ξ|² (the same sum in the force evaluation and the energy books)."""
    e = float(0.0)
    for s in range(NODE_SPRINGS):
        i = v * NODE_SPRINGS + s
        f = node_face_spring[i]
        if f >= 0 and f < face_nodes.shape[0]:
            p = face_contact_pair(
                mat_v, f, face_tet, face_joint, tet_material, fem_pair_table, joint_material_table, num_materials
            )
            d = spring_depth(x, f, node_face_offset[i], face_nodes, node_q)
            sh = node_face_shear[i]
            e += 0.5 * kn * d * d + 0.5 * p.kt_ratio * kn * wp.dot(sh, sh)
    for wall in range(num_walls):
        gap = wall_gap(x, wall_point[wall], wall_normal[wall])
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
        face_origin: wp.array(dtype=wp.vec3),
        normal_body: wp.array(dtype=int),
        rest_normal: wp.array(dtype=wp.vec3),
        first_scan: wp.array(dtype=int),
        relaxed_depth: float,
        rims: RimFaces,
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
        node_passed_face: wp.array(dtype=int),  # the face a node went past the reach of (-1 none; the guard clears)
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
        base = v * NODE_SPRINGS
        old = wp.vec3i(node_face_spring[base], node_face_spring[base + 1], node_face_spring[base + 2])
        faces = wp.vec3i(-1, -1, -1)
        slots = wp.vec3i(-1, -1, -1)
        depths = wp.vec3(0.0)
        weights = wp.mat33(0.0)
        normals = wp.mat33(0.0)
        handed = wp.vec3i(0, 0, 0)
        if node_face_count[v] > 0:
            hints = wp.vec3i(node_target_slot[base], node_target_slot[base + 1], node_target_slot[base + 2])
            faces, slots, depths, weights, normals, handed = node_face_targets(
                v,
                x,
                max_node_faces,
                node_face_count,
                node_face_index,
                face_nodes,
                rims,
                face_depth,
                face_normal,
                face_origin,
                tet_nodes,
                tet_face_nbr,
                star_offset,
                star_count,
                star_tets,
                node_q,
                normal_body,
                rest_normal,
                body_q,
                old,
                hints,
                first_scan[0],
                int(dt <= 0.0) & int(relaxed_depth < SET_UP_RELAXED),
            )
        f_v = wp.vec3(0.0)
        d_v = float(0.0)  # minus the work behind [J] (the wall's share of the work ahead included)
        # What a re-evaluation at dt = 0 lets go of at the same positions [J]: a spring handed to a shallower face,
        # one left with no target, tangential springs cut back to their Coulomb limit (its D = -ΔU, W = 0).
        r_v = float(0.0)
        touching = int(0)
        for s in range(NODE_SPRINGS):
            i = base + s
            node_target_slot[i] = slots[s]
            old_f = old[s]
            best_f = faces[s]
            best_d = depths[s]
            # Each slot's spring is continuous across a change of target within its plane direction (``handed``):
            # the new face takes over the old spring's compression at the current positions (at most its own
            # depth: the excess is dissipated), and carries the rest of its depth as an offset, so that ½ k δ²
            # never jumps up without work. A spring whose plane no face holds any more is let go, dissipated with
            # its tangential part; a face of a new plane in the slot starts as a new contact.
            offset = node_face_offset[i]
            sh = node_face_shear[i]
            delta = float(0.0)
            if best_f >= 0 and best_f == old_f:
                # The relaxed depth follows a node that backs out (no work: the spring is slack meanwhile).
                offset = wp.min(offset, best_d)
                delta = best_d - offset
            elif handed[s] != 0:
                old_delta = spring_depth(x, old_f, offset, face_nodes, node_q)
                delta = wp.min(best_d, old_delta)
                offset = best_d - delta
                r_v += 0.5 * kn * (old_delta * old_delta - delta * delta)
            else:
                if old_f >= 0:
                    old_delta = spring_depth(x, old_f, offset, face_nodes, node_q)
                    r_v += 0.5 * kn * old_delta * old_delta
                    if old_f < face_nodes.shape[0]:
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
                        r_v += 0.5 * p_old.kt_ratio * kn * wp.dot(sh, sh)
                        if dt > 0.0:
                            if passed_face(x, old_f, offset, face_nodes, face_depth, node_q, rims):
                                node_passed_face[v] = old_f
                sh = wp.vec3(0.0)  # history lives only as long as the node touches the plane
                offset = float(0.0)
                delta = best_d
                if best_f >= 0:
                    if dt > 0.0:
                        # A new spring takes only the depth gained in this step: a node that was already behind the
                        # face's plane at the last positions x - dt v (it slid in past an edge, or the face turned
                        # towards it) carries that depth as an offset instead of starting at ½ k δ² that no force
                        # worked for.
                        before = moved_plane_depth(x - dt * xv, face_nodes[best_f], node_q, node_qd, dt)
                        offset = wp.min(wp.max(before, 0.0), best_d)
                        delta = best_d - offset
                    elif relaxed_depth > 0.0:
                        # The re-evaluation after a topology pass (relaxed_depth = RELAXED_ALL): nothing moved, so no
                        # depth was gained. A node that finds itself behind a face only now (a new crack face, or its
                        # own surface turned by the faces it gained) carries that depth as its offset. At set-up only
                        # a depth within float32 rounding (a node lying on a face) is carried. The spring pushes
                        # with what is left, as the energy books and every later evaluation read it: a force of the
                        # whole depth here, with ½ k (δ - offset)² = 0 booked, pushed a model at rest with a force
                        # that no stored energy paid for (a negative contact dissipation, issue 30).
                        offset = wp.min(best_d, relaxed_depth)
                        delta = best_d - offset
            node_face_spring[i] = best_f
            node_face_offset[i] = offset
            node_face_shear[i] = sh
            if best_f >= 0:
                touching = 1
                fn = face_nodes[best_f]
                # The reaction acts at the node's projection onto the face's plane, w the projection's barycentric
                # weights (Σ w = 1; one or two may be negative, down to -KEEP_EPS, for a node at the rim): the force
                # pair then lies on one line along n_f and has no torque. Weights clamped to the triangle put the
                # reaction up to KEEP_EPS of the face off that line, a torque from nothing (a frictionless pair of
                # rigid blocks gained angular momentum). −w_i n_f is also the gradient of the depth in face node i at a
                # fixed normal.
                w = weights[s]
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
                    force, shear = penalty_contact(normals[s], delta, kn, 1.0 / inv_sum, xv - v_face, sh, p, dt)
                    node_face_shear[i] = shear
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
        for wall in range(num_walls):
            nw = wall_normal[wall]
            slot = v * num_walls + wall
            gap = wall_gap(x, wall_point[wall], nw)
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
                node_face_spring,
                node_face_offset,
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
def seat_walls_kernel(
    # Model:
    node_contact_stiffness: wp.array(dtype=float),
    wall_normal: wp.array(dtype=wp.vec3),
    num_walls: int,
    # State in:
    node_count: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    wall_point: wp.array(dtype=wp.vec3d),
    # In:
    rounding_depth: float,
    # Out:
    deepest: wp.array(dtype=float),
):
    v = wp.tid()  # one thread per node slot: the deepest gap within rounding_depth behind each wall (atomic min)
    if v >= node_count[0] or node_contact_stiffness[v] == 0.0:
        return  # past the live nodes, or a node inside the rock (no wall spring)
    for wall in range(num_walls):
        gap = wall_gap(node_q[v], wall_point[wall], wall_normal[wall])
        if gap < 0.0 and gap >= -rounding_depth:
            wp.atomic_min(deepest, wall, gap)


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
        node_face_spring,  # the targets of the last force evaluation
        node_face_offset,
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
