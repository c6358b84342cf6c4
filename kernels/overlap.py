"""Initial-state checks: how far each sphere reaches into the rock (the tets of the mesh), found through a BVH of the
tets' bounding boxes.

The distance from a point x to the rock is the smallest distance to one of its tets: zero when x lies in a tet, else
the distance to the tet's nearest face (the closest point of a triangle, Ericson §5.1.5). A sphere of radius r
penetrates the rock by r − distance; its centre lies in the rock when a tet contains it (barycentric coordinates
all ≥ 0).
"""

from __future__ import annotations

import warp as wp

from .fem_contact import closest_point_barycentric

wp.set_module_options({"enable_backward": False})


@wp.func
def distance_to_triangle(x: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """Distance [m] from x to the closest point of triangle abc."""
    w = closest_point_barycentric(x, a, b, c)
    return wp.length(x - (w[0] * a + w[1] * b + w[2] * c))


@wp.func
def contains_point(x: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3) -> bool:
    """Whether tet abcd (either orientation, not degenerate) contains x: its barycentric coordinates
    λ = [b − a, c − a, d − a]⁻¹ (x − a) and 1 − Σλ are all ≥ 0."""
    m = wp.matrix_from_cols(b - a, c - a, d - a)
    lam = wp.inverse(m) * (x - a)
    return wp.min(wp.min(lam[0], lam[1]), lam[2]) >= 0.0 and lam[0] + lam[1] + lam[2] <= 1.0


@wp.kernel
def sphere_rock_penetration_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    bvh: wp.uint64,
    # In:
    node_q: wp.array(dtype=wp.vec3),
    sphere_q: wp.array(dtype=wp.vec3),
    sphere_radius: wp.array(dtype=float),
    # Out:
    penetration: wp.array(dtype=float),
    containing_tet: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per sphere; visits the tets whose bounding box meets the sphere's
    x = sphere_q[i]
    r = sphere_radius[i]
    nearest = r  # distance to the rock, capped at r (no tet within r: no penetration)
    inside = int(-1)
    half = wp.vec3(r, r, r)
    query = wp.bvh_query_aabb(bvh, x - half, x + half)
    t = int(0)
    while wp.bvh_query_next(query, t):
        v = tet_nodes[t]
        a = node_q[v[0]]
        b = node_q[v[1]]
        c = node_q[v[2]]
        d = node_q[v[3]]
        if contains_point(x, a, b, c, d):
            nearest = 0.0
            if inside < 0:
                inside = t
        else:
            nearest = wp.min(nearest, distance_to_triangle(x, a, b, c))
            nearest = wp.min(nearest, distance_to_triangle(x, a, b, d))
            nearest = wp.min(nearest, distance_to_triangle(x, a, c, d))
            nearest = wp.min(nearest, distance_to_triangle(x, b, c, d))
    penetration[i] = r - nearest
    containing_tet[i] = inside
