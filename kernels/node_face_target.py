"""The faces a node is pushed out of (kernels/fem_contact.py, "Node–face"): the node's outward normal (its star's, or
on a rigid block its normal at the switch turned with the body), the kept-face test and the scan of its candidates,
one face per plane direction into each of its NODE_SPRINGS spring slots.
"""

from __future__ import annotations

import warp as wp

from .fem_surface import (
    BARY_EPS,
    TIE_EPS,
    RimFaces,
    min3,
    nearer,
    node_surface_normal,
    projection_barycentric,
    rim_margins,
)
from .topology import tet_face, triangle_area_vector

wp.set_module_options({"enable_backward": False})

NODE_SPRINGS = wp.constant(3)
"""Spring slots per node [-] (Model.node_springs): one per face plane direction the node lies behind, so a node in
the inside corner of three blocks (a block lattice's corner lies on three joint planes) is held by all three."""

PLANE_GROUP_COS = wp.constant(0.5)
"""cos θ_g of the plane groups [-], θ_g = 60°: two faces whose unit normals have |n_f · n_f'| > cos θ_g are one plane
direction, and only the shallowest of them holds a spring. The springs of a node then have pairwise |n_s · n_t| ≤
cos θ_g, so by Gershgorin on their Gram matrix λ_max(Σ_s n_s n_sᵀ) ≤ 1 + (NODE_SPRINGS − 1) cos θ_g = 2 = SPRING_BOUND:
the node's springs are no stiffer along any direction than 2 k (the stable steps take it,
warpdem.stages.fem_contact)."""

SPRING_BOUND = 1.0 + (NODE_SPRINGS - 1) * PLANE_GROUP_COS
"""λ_max(Σ_s n_s n_sᵀ) over a node's springs at most [-] (:data:`PLANE_GROUP_COS`); a Python float for the host."""

SURVIVORS = wp.constant(8)
"""List slots of the faces that pass every test of a node's first scan for a new plane that the scan keeps for the
later ones of the same evaluation [-] (:func:`new_plane_face`; with more, each later scan is a full one)."""


NEW_REACH = wp.constant(0.99)
"""A new target is taken less deep than NEW_REACH × face_depth (half the height of the tet over the face) [-]; a kept
one holds to the whole face_depth (:func:`kept_face_holds`). Why: on a geology meshed on a lattice (joints and
openings on whole and half metres) a node on a block's top or side face can sit exactly half a tet's height behind
the perpendicular outer face of the same block and project onto that face's rim; float32 rounding then put it inside
the reach about half the time, and it started a spring at the whole depth (facility_nonpersistent's randomized
joints: 7 to 32 such nodes per draw, 2e9 to 2e10 J of contact energy at the start). A node that touches a face in a
step gains far less depth than that in the step.
"""


class Survivors(wp.types.vector(length=SURVIVORS, dtype=wp.int32)):
    """The list slots a first scan keeps (:data:`SURVIVORS`)."""


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
    rims: RimFaces,
    face_depth: wp.array(dtype=float),
    face_normal: wp.array(dtype=wp.vec3),
    face_origin: wp.array(dtype=wp.vec3),
    normal: wp.vec3,
    node_q: wp.array(dtype=wp.vec3),
):
    """Whether the kept face ``keep`` is still node v's target: a candidate of v that v lies behind (less deep than
    face_depth), that faces v's normal n_v (``normal``) and that v projects into within KEEP_EPS; the tests of
    :func:`new_plane_face` for that face, in its arithmetic. Whether it is a candidate is read at the list slot
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
    a = face_origin[keep]
    nf = face_normal[keep]
    depth = -wp.dot(x - a, nf)
    # One branch for the three tests (their comparisons one by one), as in new_plane_face.
    if (int(depth <= 0.0) | int(depth >= face_depth[keep]) | int(wp.dot(nf, normal) >= 0.0)) != 0:
        return False, slot, 0.0, wp.vec3(0.0), wp.vec3(0.0)
    fn = face_nodes[keep]
    b = node_q[fn[1]]
    c = node_q[fn[2]]
    w = projection_barycentric(x, a, b, c, wp.cross(b - a, c - a))
    if min3(w) < -rim_margins(keep, rims)[1]:
        return False, slot, 0.0, wp.vec3(0.0), wp.vec3(0.0)
    return True, slot, depth, w, nf


@wp.func
def same_plane(n: wp.vec3, m: wp.vec3) -> bool:
    """Whether two unit face normals are one plane direction (:data:`PLANE_GROUP_COS`; opposite normals too: a
    spring's stiffness n nᵀ does not tell them apart)."""
    return wp.abs(wp.dot(n, m)) > PLANE_GROUP_COS


@wp.func
def held_rows(faces: wp.vec3i, normals: wp.mat33) -> wp.mat33:
    """The rows of ``normals`` whose slots hold a face (``faces`` >= 0), the others zero (|n_f · 0| > cos θ_g is
    false: no plane direction), for :func:`in_held_plane`."""
    rows = wp.mat33(0.0)
    for s in range(NODE_SPRINGS):
        if faces[s] >= 0:
            rows[s] = normals[s]
    return rows


@wp.func
def in_held_plane(nf: wp.vec3, rows: wp.mat33) -> int:
    """1 when the unit face normal nf is of a plane direction a slot holds (rows of :func:`held_rows`), else 0:
    :func:`same_plane` against each row in its arithmetic, combined without a branch."""
    return int(same_plane(nf, rows[0])) | int(same_plane(nf, rows[1])) | int(same_plane(nf, rows[2]))


@wp.func
def wholly_behind(fn: wp.vec3i, o: wp.vec3, n: wp.vec3, node_q: wp.array(dtype=wp.vec3), tol: float) -> bool:
    """Whether no vertex of the face with nodes ``fn`` lies in front of the plane through ``o`` with unit normal
    ``n`` by more than ``tol`` [m]."""
    behind = True
    for k in range(3):
        if wp.dot(node_q[fn[k]] - o, n) > tol:
            behind = False
    return behind


@wp.func
def exits_over_convex_edge(
    v: int,
    x: wp.vec3,
    f: int,
    fn: wp.vec3i,
    depth: float,
    max_node_faces: int,
    node_face_count: wp.array(dtype=int),
    node_face_index: wp.array(dtype=int),
    face_nodes: wp.array(dtype=wp.vec3i),
    face_normal: wp.array(dtype=wp.vec3),
    face_origin: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_face_nbr: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    rims: RimFaces,
    node_q: wp.array(dtype=wp.vec3),
    tol: float,
) -> bool:
    """Whether node v (at x), depth δ behind face f and projecting onto an edge or vertex of f, lies on or behind a
    face g of another plane direction, less deep by more than ``tol`` [m] and projecting into g (within BARY_EPS),
    with no vertex of f in front of g's plane by more than ``tol``: f meets g's body at a convex edge or corner,
    behind g. Then v lies on the surface there, not inside the body through f, and f is no target. Asked only at
    set-up (``at_set_up`` in :func:`new_plane_face`; kernels/fem_contact.py ``SET_UP_RELAXED``).

    Why: inside a body at a convex edge is behind every face there, and the way out is through the nearest. A node
    lying on the top face g of a block, less than half a tet's height in from the block's side plane, projects onto
    the rim of a side face f behind f (a T-junction of a geology meshed on a lattice: facility_nonpersistent's
    randomized joints at [mesh] seed 3). Taken as f's target at set-up, where a spring carries only a rounding depth
    as its offset, it started pressed by that whole depth (5e9 J of contact energy at t = 0). After a pass or a switch
    a new spring starts relaxed, and in a step at the depth gained in the step, so the rule is not asked there: a node
    pressed into f at a flush edge (on g's plane within rounding) keeps f. A node in front of g (past the edge, within
    the rim tolerance: tests/test_rim_contact.py) or on both planes within ``tol`` (flush blocks) presses f as before.

    The faces g are v's candidates, and the joint faces of v's own star seen from the block across the joint (the
    face's plane with its normal turned, ``rims.tet_face_joint``): a face of the block v rests on whose corner is v's
    joint partner is no candidate of v (kernels/node_face_list.py), and the node lies on it, at the partner, so
    depth 0 and inside it (facility_nonpersistent at [mesh] seed 4: two nodes on a bedding plane, half a tet in from
    the lift shaft's wall of the block under them, joint partners of that block's node there)."""
    n_f = face_normal[f]
    count = wp.min(node_face_count[v], max_node_faces)
    for s in range(count):
        g = node_face_index[v * max_node_faces + s]
        if g == f:
            continue
        gn = face_nodes[g]
        n_g = face_normal[g]
        if same_plane(n_f, n_g):
            continue
        o_g = face_origin[g]
        depth_g = -wp.dot(x - o_g, n_g)
        if depth_g < -tol or depth_g >= depth - tol:
            # In front of g: past the body's edge, on f's rim, where the rim tolerance lets it press f (a joint
            # whose nodes all lie past the edges of the faces opposite, tests/test_rim_contact.py). Not clearly less
            # deep: on both planes by rounding (flush blocks), f as before.
            continue
        if not wholly_behind(fn, o_g, n_g, node_q, tol):
            continue
        b = node_q[gn[1]]
        c = node_q[gn[2]]
        if min3(projection_barycentric(x, o_g, b, c, wp.cross(b - o_g, c - o_g))) >= -BARY_EPS:
            return True
    if depth <= tol:
        return False  # on f's plane within rounding: no face across a joint at v is clearly less deep
    start = star_offset[v]
    for e in range(start, start + star_count[v]):
        t = star_tets[e]
        tn = tet_nodes[t]
        for k in range(4):
            if tn[k] == v or tet_face_nbr[4 * t + k] >= 0 or rims.tet_face_joint[4 * t + k] < 0:
                continue
            h = tet_face(tn, k)
            # The face across the joint lies on h, at v (depth 0, v one of its corners), facing the other way.
            n_g = -wp.normalize(triangle_area_vector(node_q[h[0]], node_q[h[1]], node_q[h[2]]))
            if not same_plane(n_f, n_g) and wholly_behind(fn, x, n_g, node_q, tol):
                return True
    return False


@wp.func
def new_plane_face(
    v: int,
    x: wp.vec3,
    max_node_faces: int,
    node_face_count: wp.array(dtype=int),
    node_face_index: wp.array(dtype=int),
    face_nodes: wp.array(dtype=wp.vec3i),
    rims: RimFaces,
    face_depth: wp.array(dtype=float),
    face_normal: wp.array(dtype=wp.vec3),
    face_origin: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_face_nbr: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    normal_body: wp.array(dtype=int),
    rest_normal: wp.array(dtype=wp.vec3),
    body_q: wp.array(dtype=wp.quatd),
    faces: wp.vec3i,
    normals: wp.mat33,
    normal: wp.vec3,
    has_normal: int,
    survivors: Survivors,
    n_survivors: int,
    at_set_up: int,
):
    """The shallowest face node v (at x, its own surface's outward normal n_v) penetrates outside the plane
    directions its slots hold (``faces``, their normals ``normals``): of the candidate faces that face it
    (n_f · n_v < 0) and that it lies behind (less deep than face_depth) and projects into (within RIM_EPS of the
    triangle: a node on the rim of a joint whose faces are one cell across, kernels/fem_surface.py), the shallowest;
    an interior contact before an edge or vertex one, then the lowest face index (the rule of one spring per node
    before, now within the faces of the new planes).

    The facing test keeps a node on a convex edge of one body, which sits exactly on the edge of the body it rests
    on, from being pushed out through that body's side face (where it is "behind" the side plane by a rounding
    error): the side face's normal points along the node's own, the face it rests on against it.

    Every candidate takes the same arithmetic, combined into one branch: the held planes' test (three dot products
    with the unit normal from ``face_normal``, face_normals_kernel at this step's positions), the depth δ = -(x -
    x_a) · n_f (x_a from ``face_origin``, written with the normals) against 0 and face_depth, and the facing test.
    A node on a joint plane without pressure lies in front of or behind the faces of the blocks around it by
    rounding errors, so each test alone is a coin flip the processor mispredicts; taken together they fail for all
    but about one candidate in a thousand. n_v is summed only for a node with a candidate it lies behind in a new
    plane (``normal``/``has_normal``: the one summed already, handed back), and the projection only for a face that
    passes all those.

    The scans of one evaluation (one per slot a new plane fills, :func:`node_face_targets`) differ only in the held
    planes, which grow, and the held test only drops more faces as they do: a face that fails any other test in the
    first scan fails it in every later one. So the first scan (``n_survivors`` -2) lists the list slots of the faces
    that pass every test (``survivors``, their number handed back), and the later ones test only those, in the same
    order and arithmetic: the same face as a full scan, at a few tests instead of some thirty. A first scan with
    more than SURVIVORS of them hands back -1, and the later ones scan the whole list.

    ``at_set_up`` (1 in the set-up evaluation): a face the node projects onto the rim of from a surface it lies on,
    across that body's convex edge, is no target (:func:`exits_over_convex_edge`).

    Returns:
        (face or -1, its slot in v's candidate list (-1 with no face), depth δ [m], barycentric weights of the
        projection, the face's unit normal, n_v, whether n_v is summed, the survivors and their number).
    """
    tol = TIE_EPS * wp.length(x)
    best_d = float(0.0)
    best_interior = int(0)
    best_f = int(-1)
    best_slot = int(-1)
    best_w = wp.vec3(0.0)
    best_n = wp.vec3(0.0)
    held = held_rows(faces, normals)
    first = n_survivors == -2
    n = wp.min(node_face_count[v], max_node_faces)
    if n_survivors >= 0:
        n = n_survivors
    passed = int(0)  # survivors of a first scan; SURVIVORS + 1: too many to list
    for i in range(n):
        s = i
        if n_survivors >= 0:
            s = survivors[i]
        f = node_face_index[v * max_node_faces + s]
        nf = face_normal[f]
        a = face_origin[f]
        depth = -wp.dot(x - a, nf)
        # 0 for a face of a new plane the node lies behind (the comparisons of the tests one by one, NaN included).
        off = in_held_plane(nf, held) | int(depth <= 0.0) | int(depth >= NEW_REACH * face_depth[f])
        if (off | has_normal) == 0:
            normal = node_normal(
                v, tet_nodes, tet_face_nbr, star_offset, star_count, star_tets, node_q, normal_body, rest_normal, body_q
            )
            has_normal = 1
        if (off | int(wp.dot(nf, normal) >= 0.0)) != 0:
            continue
        fn = face_nodes[f]
        b = node_q[fn[1]]
        c = node_q[fn[2]]
        w = projection_barycentric(x, a, b, c, wp.cross(b - a, c - a))
        if min3(w) < -rim_margins(f, rims)[0]:
            continue
        if (at_set_up & int(min3(w) <= BARY_EPS)) != 0:
            if exits_over_convex_edge(
                v,
                x,
                f,
                fn,
                depth,
                max_node_faces,
                node_face_count,
                node_face_index,
                face_nodes,
                face_normal,
                face_origin,
                tet_nodes,
                tet_face_nbr,
                star_offset,
                star_count,
                star_tets,
                rims,
                node_q,
                tol,
            ):
                continue
        if first and passed < SURVIVORS:
            survivors[passed] = s
        passed = wp.min(passed + 1, SURVIVORS + 1)
        inside = int(min3(w) > BARY_EPS)
        if nearer(depth, inside, f, best_d, best_interior, best_f, tol + TIE_EPS * depth):
            best_d = depth
            best_interior = inside
            best_f = f
            best_slot = s
            best_w = w
            best_n = nf
    if first:
        n_survivors = passed
        if passed > SURVIVORS:
            n_survivors = -1
    return best_f, best_slot, best_d, best_w, best_n, normal, has_normal, survivors, n_survivors


@wp.func
def free_slot(faces: wp.vec3i, old: wp.vec3i, old_normal: wp.mat33, nf: wp.vec3) -> int:
    """The slot a face of a new plane (unit normal nf) goes into, of those that hold no face yet this evaluation
    (``faces`` < 0): the one whose last face (``old``, its normal a row of ``old_normal``) was of that plane (its
    spring is handed over); else one that held nothing; else one whose last face let go; -1 when none is free."""
    for s in range(NODE_SPRINGS):
        if faces[s] < 0 and old[s] >= 0:
            if same_plane(nf, old_normal[s]):
                return s
    for s in range(NODE_SPRINGS):
        if faces[s] < 0 and old[s] < 0:
            return s
    for s in range(NODE_SPRINGS):
        if faces[s] < 0:
            return s
    return -1


@wp.func
def node_face_targets(
    v: int,
    x: wp.vec3,
    max_node_faces: int,
    node_face_count: wp.array(dtype=int),
    node_face_index: wp.array(dtype=int),
    face_nodes: wp.array(dtype=wp.vec3i),
    rims: RimFaces,
    face_depth: wp.array(dtype=float),
    face_normal: wp.array(dtype=wp.vec3),
    face_origin: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_face_nbr: wp.array(dtype=int),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    normal_body: wp.array(dtype=int),
    rest_normal: wp.array(dtype=wp.vec3),
    body_q: wp.array(dtype=wp.quatd),
    old: wp.vec3i,
    hints: wp.vec3i,
    first_scan: int,
    at_set_up: int,
):
    """The faces node v (at x) is pushed out of, one per slot: ``old`` holds each slot's face at the last
    evaluation (-1 for none), ``hints`` their list slots then, ``first_scan`` -2 (the later scans for a new plane test
    only the first one's survivors, :func:`new_plane_face`) or -1 (each scans the whole list: the path they are
    tested against).

    1. Each slot keeps its face while it holds (:func:`kept_face_holds`, as with one spring per node: the shallowest
       face jumps where two face planes meet, and a target held until it no longer holds the node switches less
       often). Of two kept faces that came into one plane direction (a block turned), the shallower stays.
    2. Then, while a slot is free, the shallowest face of a plane direction no slot holds
       (:func:`new_plane_face`) takes one (:func:`free_slot`): the slot whose lost face was of that direction (its
       spring is handed over), else an empty one. A face of a held direction never opens a second slot, so the
       springs' normals keep pairwise |n_s · n_t| ≤ cos θ_g (:data:`PLANE_GROUP_COS`).

    A node whose slots all hold tests only its kept faces. One with a free slot scans its candidates for a new plane,
    once in full: each later scan (after a new plane took a slot) tests only the faces that passed the first
    (:func:`new_plane_face`), so a node resting on a joint pays one branch-free test per candidate a step for the
    chance of meeting a second plane.

    Returns:
        (face per slot (-1 for none), its candidate-list slot, depth δ [m] per slot, barycentric weights per slot
        (rows), the faces' unit normals (rows), whether each slot's face is of its last face's plane (a hand-over:
        the same face, or a new one of that direction)).
    """
    faces = wp.vec3i(-1, -1, -1)
    slots = wp.vec3i(-1, -1, -1)
    depths = wp.vec3(0.0)
    weights = wp.mat33(0.0)
    normals = wp.mat33(0.0)
    handed = wp.vec3i(0, 0, 0)
    old_normal = wp.mat33(0.0)
    normal = wp.vec3(0.0)
    has_normal = int(0)
    survivors = Survivors()
    n_survivors = first_scan
    for s in range(NODE_SPRINGS):
        keep = old[s]
        if keep >= 0 and keep < face_normal.shape[0]:
            old_normal[s] = face_normal[keep]
            if has_normal == 0:
                normal = node_normal(
                    v,
                    tet_nodes,
                    tet_face_nbr,
                    star_offset,
                    star_count,
                    star_tets,
                    node_q,
                    normal_body,
                    rest_normal,
                    body_q,
                )
                has_normal = 1
            holds, keep_slot, keep_d, keep_w, keep_n = kept_face_holds(
                v,
                x,
                keep,
                hints[s],
                max_node_faces,
                node_face_count,
                node_face_index,
                face_nodes,
                rims,
                face_depth,
                face_normal,
                face_origin,
                normal,
                node_q,
            )
            if holds:
                faces[s] = keep
                slots[s] = keep_slot
                depths[s] = keep_d
                weights[s] = keep_w
                normals[s] = keep_n
                handed[s] = 1
    for s in range(NODE_SPRINGS):
        for t in range(NODE_SPRINGS):
            if t > s and faces[s] >= 0 and faces[t] >= 0:
                if same_plane(normals[s], normals[t]):
                    drop = t
                    if depths[t] < depths[s]:
                        drop = s
                    faces[drop] = -1
                    slots[drop] = -1
                    depths[drop] = 0.0
                    handed[drop] = 0
    for _pass in range(NODE_SPRINGS):
        if faces[0] >= 0 and faces[1] >= 0 and faces[2] >= 0:
            break
        f, ls, d, w, nf, normal, has_normal, survivors, n_survivors = new_plane_face(
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
            faces,
            normals,
            normal,
            has_normal,
            survivors,
            n_survivors,
            at_set_up,
        )
        if f < 0:
            break
        s = free_slot(faces, old, old_normal, nf)
        if old[s] >= 0 and same_plane(nf, old_normal[s]):
            handed[s] = 1
        faces[s] = f
        slots[s] = ls
        depths[s] = d
        weights[s] = w
        normals[s] = nf
    return faces, slots, depths, weights, normals, handed
