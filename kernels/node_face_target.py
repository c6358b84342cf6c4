"""The face a node is pushed out of (kernels/fem_contact.py, "Node–face"): the node's outward normal (its star's, or
on a rigid block its normal at the switch turned with the body), the kept-face test and the scan of its candidates.
"""

from __future__ import annotations

import warp as wp

from .fem_surface import BARY_EPS, KEEP_EPS, TIE_EPS, min3, nearer, node_surface_normal, projection_barycentric

wp.set_module_options({"enable_backward": False})


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
