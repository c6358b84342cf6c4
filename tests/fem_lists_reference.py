"""The node–face candidate lists checked by brute force (tests/test_fem_contact.py, tests/test_fracture.py): every
node–face pair of the live surface tested in float64 NumPy, independently of the kernels' grid and prefilter.
"""

from __future__ import annotations

import math

import numpy as np

from warpdem.model import Model, State

BAND = 1.0e-4
"""Relative band around a cut-off inside which float32 may decide either way [-]."""


def point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> float:
    """Exact distance from p to a triangle (float64), by minimising over the face and its three edges."""
    a, b, c = tri
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    q = p - np.dot(p - a, n) * n
    w = [np.dot(np.cross(c - b, q - b), n), np.dot(np.cross(a - c, q - c), n), np.dot(np.cross(b - a, q - a), n)]
    if min(w) >= 0.0:
        return abs(float(np.dot(p - a, n)))
    best = math.inf
    for u, v in ((a, b), (b, c), (c, a)):
        t = np.clip(np.dot(p - u, v - u) / np.dot(v - u, v - u), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(p - (u + t * (v - u)))))
    return best


def point_triangle_distances(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Exact distances from p, shape (3,), to triangles, shape (F, 3, 3), float64, shape (F,): the distance to the
    plane where p projects inside, else the least distance to the three edges."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    h = np.einsum("ij,ij->i", p - a, n)
    q = p - h[:, None] * n
    inside = np.ones(len(tri), dtype=bool)
    edge = np.full(len(tri), math.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, q - u), n) >= 0.0
        e = v - u
        t = np.clip(np.einsum("ij,ij->i", p - u, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
        edge = np.minimum(edge, np.linalg.norm(p - (u + t[:, None] * e), axis=1))
    return np.where(inside, np.abs(h), edge)


def node_lists_hold_their_candidates(m: Model, s: State, tets: int) -> int:
    """Check every surface node's node–face list against an O(N F) brute force at the positions the lists were built
    at (``node_q_at_fem_build``): each face certainly within ``fem_skin`` of the node, or with the node certainly
    behind it less deep than its ``face_depth`` and projecting into it, is listed; no face certainly outside both is;
    no face of the node's 1-ring (a face with a vertex sharing a tet with it, over the first ``tets`` tets) is.
    Returns how many listed pairs the brute force required (a check that found none tested nothing)."""
    n_faces = int(s.face_count.numpy()[0])
    n_nodes = int(s.node_count.numpy()[0])
    faces = m.face_nodes.numpy()[:n_faces]
    face_depth = m.face_depth.numpy()[:n_faces].astype(np.float64)
    x_nodes = s.node_q_at_fem_build.numpy().astype(np.float64)
    tri = x_nodes[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    adjacent = np.zeros((n_nodes, n_nodes), dtype=bool)  # sharing a tet
    for tet in m.tet_nodes.numpy()[:tets]:
        adjacent[np.ix_(tet, tet)] = True
    stiff = m.node_contact_stiffness.numpy()
    k_nodes = m.max_node_faces
    index = s.node_face_index.numpy().reshape(-1, k_nodes)
    count = s.node_face_count.numpy()
    checked = 0
    for v in np.nonzero(stiff[:n_nodes] > 0)[0]:
        assert count[v] <= k_nodes
        listed = np.zeros(n_faces, dtype=bool)
        listed[index[v, : count[v]]] = True
        in_ring = adjacent[v][faces].any(axis=1)
        assert not (listed & in_ring).any(), f"node {v} listed against a face of its own 1-ring"
        d = point_triangle_distances(x_nodes[v], tri)
        depth = -np.einsum("ij,ij->i", x_nodes[v] - tri[:, 0], normal)
        behind = (depth > 0.0) & (depth < face_depth * (1 - BAND)) & (d <= depth * (1 + BAND))  # projects inside
        must = ~in_ring & ((d < m.fem_skin * (1 - BAND)) | behind)
        must_not = ~in_ring & (d > m.fem_skin * (1 + BAND)) & ~((depth > 0.0) & (depth < face_depth * (1 + BAND)))
        assert listed[must].all(), f"node {v} misses faces {np.nonzero(must & ~listed)[0]}"
        assert not listed[must_not].any(), f"node {v} lists faces {np.nonzero(must_not & listed)[0]}"
        checked += int(must.sum())
    return checked
