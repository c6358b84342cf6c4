"""The node–face candidate lists (kernels/fem_contact.py, "Node–face" and "Skins"): the candidate test a list build
applies to each face the hash grid offers a surface node, and the build kernel it makes (kernels/neighbors.py).
"""

from __future__ import annotations

import warp as wp

from .fem_surface import KEEP_EPS, closest_point_barycentric, held_by_joint, in_one_ring, min3, projection_barycentric
from .neighbors import ListSpec, make_list_kernels

wp.set_module_options({"enable_backward": False})

BOUND_SLACK = wp.constant(1.0e-3)
"""Relative slack on a face's bounding ball in the node–face prefilter [-]: float32 rounding of the ball's radius and
of the distance fits well inside it."""

RIM_REACH = wp.constant(1.0 + 4.0 * KEEP_EPS + BOUND_SLACK)
"""How far a node–face candidate's projection may lie from the face's centroid, in bounding radii [-]
(:func:`within_reach`; the host's query radius takes it too, warpdem.stages.fem_contact)."""


@wp.struct
class NodeFaceInputs:
    """What the node–face candidate test reads (kernels/neighbors.py ``ListSpec.inputs``): the Model/State arrays of
    those names, ``fem_skin`` [m], the query radius face_radius + max(fem_skin, largest face_depth) [m], each face's
    centroid and bounding radius about it at the build (``face_center``, ``face_bound`` [m], face_centers_kernel),
    ``node_body`` (each node's rigid body, -1 for a deformable node; empty before any switch), and ``near`` (1 for a
    node whose list a partial rebuild refreshes, :func:`mark_near_new_nodes_kernel`; empty for a full rebuild)."""

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
    near: wp.array(dtype=int)
    fem_skin: float
    search_radius: float


@wp.func
def node_face_search_radius(inputs: NodeFaceInputs, v: int) -> float:
    return inputs.search_radius


@wp.func
def kept_list(inputs: NodeFaceInputs, v: int) -> bool:
    """In a partial rebuild, a node far from every new node keeps its list (:func:`mark_near_new_nodes_kernel`)."""
    if inputs.near.shape[0] == 0:
        return False
    return inputs.near[v] == 0


@wp.func
def on_surface(inputs: NodeFaceInputs, v: int) -> bool:
    """A node inside the rock is no contact point."""
    return inputs.node_contact_stiffness[v] != 0.0


@wp.func
def within_reach(inputs: NodeFaceInputs, x: wp.vec3, f: int) -> bool:
    """Whether x lies within max(fem_skin, face_depth) + RIM_REACH × the face's bounding radius of its centroid: a
    necessary condition of the candidate test below, at the cost of one load and a dot product.

    Why necessary: a point p of the triangle lies within the bounding radius r_f of the centroid c, so a face whose
    closest point is within fem_skin of x has |x − c| < fem_skin + r_f; and a node behind the face, less deep than
    face_depth, whose projection p has barycentric weights w_i ≥ −KEEP_EPS (the margin of a kept target, wider than
    the RIM_EPS of a new one: Σ w_i = 1, so the negative weights sum to no less than −2 KEEP_EPS and
    Σ |w_i| ≤ 1 + 4 KEEP_EPS) has |p − c| = |Σ w_i (v_i − c)| ≤ (1 + 4 KEEP_EPS) r_f and
    |x − c| < face_depth + (1 + 4 KEEP_EPS) r_f. The grid hands over every face in the cells the query ball touches
    (about six times the ball's volume with cells as wide as its radius); this drops the ones outside the ball before
    the exact test's point–triangle arithmetic."""
    reach = RIM_REACH * inputs.face_bound[f] + wp.max(inputs.fem_skin, inputs.face_depth[f])
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
    point within fem_skin, or the node already behind the face (a build during a contact) and projecting into it
    within KEEP_EPS: every face a kept target may hold (kernels/node_face_target.py ``kept_face_holds``), and so every
    face a new one may take (RIM_EPS < KEEP_EPS)."""
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
            near = min3(projection_barycentric(x, a, b, c, area2)) >= -KEEP_EPS
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
        kept=kept_list,
    )
)
"""Build kernel of the node–face lists (no history: a node's spring follows the node, kernels below)."""


@wp.kernel
def mark_near_new_nodes_kernel(
    # Model:
    face_nodes: wp.array(dtype=wp.vec3i),
    # In:
    grid: wp.uint64,
    first_new: wp.array(dtype=int),
    radius: float,
    reach: float,
    # State in:
    node_count: wp.array(dtype=int),
    face_count: wp.array(dtype=int),
    node_q_at_fem_build: wp.array(dtype=wp.vec3),
    # Out:
    near: wp.array(dtype=int),
):
    """Mark (``near`` = 1; zeroed before) the nodes a split pass may have changed the node–face candidates of
    (warpdem.stages.fem_contact ``FemContact.refresh_near``): the daughters, from slot ``first_new[0]`` on, and every
    surface node within ``radius`` of one of them, distances taken where the lists were built (``node_q_at_fem_build``;
    a daughter holds its parent's). ``grid`` holds the face centroids there; ``reach`` ≥ ``radius`` + the largest
    face's bounding radius, so every face with a vertex within ``radius`` is offered.

    Why these: a split adds crack faces and re-attaches faces and 1-rings to daughters, all at a split node's place p;
    a face with a vertex at p lies within its bounding radius of its centroid, and a node that may take the face lies
    within the query radius of that centroid, so within query radius + largest face radius of p (the host's
    ``radius``). Every other node's candidate set is what it was: the same faces at the same places. A node with a
    list is a vertex of a boundary face, so the faces near a daughter name every such node near it."""
    k = wp.tid()  # one thread per node slot from the first daughter's on (the count is on the device)
    v = first_new[0] + k
    if v >= node_count[0]:
        return
    near[v] = 1
    p = node_q_at_fem_build[v]
    n_faces = face_count[0]
    query = wp.hash_grid_query(grid, p, reach)
    for f in query:
        if f >= n_faces:
            continue
        fn = face_nodes[f]
        for j in range(3):
            u = fn[j]
            d = node_q_at_fem_build[u] - p
            if wp.dot(d, d) <= radius * radius:
                near[u] = 1  # a race between daughters writes the same value
