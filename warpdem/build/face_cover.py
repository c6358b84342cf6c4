"""How much of each boundary face a load's region covers: the weights that make a pressure patch load exactly the
area it names, whatever the mesh (issue 27).

A face whose three corners lie in a convex region (a box or a cylinder, the only regions a scene has) lies in it
whole: weights (1/3, 1/3, 1/3), the lumped load of a whole face. A face the region's edge crosses carries the share of
the pressure that falls on its covered part, lumped onto its nodes by the linear shape functions N_k:

    w_k = (1/A) ∫_{face ∩ region} N_k dA,          Σ_k w_k = A_covered / A ∈ [0, 1],

so the force -p a w_k on node k sums to -p a (A_covered/A), the pressure times the covered area, with its centre
where the covered part's is. The integral is a midpoint rule on the n² congruent sub-triangles of the face (n
:data:`SUBDIVISIONS` per edge): a sub-triangle counts whole when its centroid is inside. Only the sub-triangles the
region's edge crosses can be miscounted, so the covered area is off by at most (edge length inside the face) ×
(sub-triangle diameter), i.e. the patch's perimeter × h/n over the whole load, h the faces' longest edge; the
miscounts of a smooth edge fall on either side and mostly cancel. The quadrature points are formed as
X0 + s (X1 − X0) + t (X2 − X0), so a face in a coordinate plane (a box's face, a flat surface) keeps that
coordinate exactly and a region bounded by the same plane counts it inside, as it counts the corners.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..load_data import covered_areas

SUBDIVISIONS = 32
"""Sub-triangles per face edge of the midpoint rule (n² = 1024 per crossed face)."""


class ConvexRegion(Protocol):
    """A region that tells which points it holds, boundary included (warpdem.scene.regions.Region)."""

    def contains(self, points: np.ndarray) -> np.ndarray: ...

    def bounds(self) -> tuple[np.ndarray, np.ndarray]: ...


def sub_triangle_centroids(n: int) -> np.ndarray:
    """Barycentric coordinates (s, t) of the centroids of the n² congruent sub-triangles of a triangle, each with
    area A/n², shape (n², 2), float64: the n(n+1)/2 upright ones and the n(n−1)/2 inverted ones."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = (i + j) <= n - 1
    down = (i + j) <= n - 2
    upright = np.stack([(i[up] + 1.0 / 3.0), (j[up] + 1.0 / 3.0)], axis=1)
    inverted = np.stack([(i[down] + 2.0 / 3.0), (j[down] + 2.0 / 3.0)], axis=1)
    return np.concatenate([upright, inverted]) / n


def face_cover_weights(
    points: np.ndarray, faces: np.ndarray, region: ConvexRegion, subdivisions: int = SUBDIVISIONS
) -> np.ndarray:
    """The nodal weights w_k = (1/A) ∫_{face ∩ region} N_k dA of each face (module docstring).

    Args:
        points: node positions [m], shape (N, 3).
        faces: node triples, shape (F, 3).
        region: a convex region.
        subdivisions: sub-triangles per edge of the midpoint rule.

    Returns:
        Weights [-], shape (F, 3), float64: (1/3, 1/3, 1/3) for a face inside, zeros for one the region misses.
    """
    x = np.asarray(points, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]  # (F, 3, 3)
    weights = np.zeros((len(x), 3))
    corners_in = region.contains(x)  # (F, 3)
    whole = np.all(corners_in, axis=1)
    weights[whole] = 1.0 / 3.0
    lo, hi = region.bounds()
    near = ~whole & np.all(x.max(axis=1) >= lo, axis=1) & np.all(x.min(axis=1) <= hi, axis=1)
    st = sub_triangle_centroids(subdivisions)
    shape = np.stack([1.0 - st[:, 0] - st[:, 1], st[:, 0], st[:, 1]], axis=1)  # N_k at the centroids, (Q, 3)
    for f in np.nonzero(near)[0]:
        x0, e1, e2 = x[f, 0], x[f, 1] - x[f, 0], x[f, 2] - x[f, 0]
        q = x0 + st[:, :1] * e1 + st[:, 1:] * e2
        inside = region.contains(q)
        weights[f] = shape[inside].sum(axis=0) / len(st)
    return weights


def covered_area(points: np.ndarray, faces: np.ndarray, weights: np.ndarray) -> float:
    """The area the weights load [m²]: Σ_f A_f Σ_k w_fk over the faces at ``points`` (shape (N, 3))."""
    x = np.asarray(points, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    return float(np.sum(covered_areas(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], np.asarray(weights).sum(axis=1))))
