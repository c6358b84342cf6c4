"""Index tables and names that every layer shares: a tet's faces and edges, the grouping of face rows, the names of a
meshed solid's boundary face sets.

Pure numpy, below everything else in the package, so that the scene schema, the stages, the builder and the outputs
can all use one definition (tests/test_layers.py keeps it a leaf).

Conventions: a tet's nodes are positively oriented, ``det[x1 - x0, x2 - x0, x3 - x0] > 0`` (volume = det / 6); face k
is the face opposite its node k, listed so that its right-hand normal points out of the tet.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "BOX_FACE_NAMES",
    "OPENING_FACE_NAME",
    "PACKED_ROW_LIMIT",
    "SURFACE_FACE_NAME",
    "TET_EDGES",
    "TET_FACES",
    "row_groups",
]

TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)
"""Local node indices of the faces of a positively oriented tet, face k opposite node k, normals outward."""

TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
"""Local node indices of the six edges of a tet."""


BOX_FACE_NAMES = ("x-", "x+", "y-", "y+", "z-", "z+")
"""Names of the outer box faces in :attr:`GeologyMesh.boundary_faces`, in (axis, low/high) order."""

OPENING_FACE_NAME = "opening"
"""Name of the tunnel, shaft and room walls in :attr:`GeologyMesh.boundary_faces`."""

SURFACE_FACE_NAME = "surface"
"""Name of the whole outer surface of a solid meshed by :func:`mesh_cylinder` or :func:`mesh_ellipsoid`."""


def row_groups(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Groups equal rows of non-negative integer triples, shape (F, 3): the group of each row, shape (F,), and the
    size of each group, groups numbered in the lexicographic order of their rows (as ``np.unique(rows, axis=0)``).

    A row is packed into one int64 key (a b c in base n, n the largest entry + 1) where n³ fits, so the sort is one
    of F integers rather than ``np.unique``'s sort of F row records, about ten times slower: this runs on every frame
    in which a crack grows (warpdem.io.output), and on the faces of every tet when a model is built
    (warpdem.stages.fem_contact.contact_critical_step_at)."""
    rows = np.asarray(rows, dtype=np.int64).reshape(-1, 3)
    n = int(rows.max()) + 1 if len(rows) else 1
    if n > PACKED_ROW_LIMIT:
        _, group, size = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
        return group.reshape(-1), size
    key = (rows[:, 0] * n + rows[:, 1]) * n + rows[:, 2]
    # np.unique's inverse costs a stable sort and an unsort; equal keys need no stable order, so group by hand.
    order = np.argsort(key)
    sorted_key = key[order]
    first = np.ones(len(key), dtype=bool)  # the first row of each group in sorted order
    first[1:] = sorted_key[1:] != sorted_key[:-1]
    group = np.empty(len(key), dtype=np.int64)
    group[order] = np.cumsum(first) - 1
    return group, np.diff(np.append(np.flatnonzero(first), len(key)))


PACKED_ROW_LIMIT = 2_000_000
"""Largest entry + 1 of rows packed into one int64 key by :func:`row_groups`: 2e6³ = 8e18 < 2⁶³ ≈ 9.2e18."""
