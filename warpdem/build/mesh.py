"""Tetrahedral meshes on the host: a structured box mesher, validation with a quality summary, boundary faces.

Conventions: ``points`` are node positions [m], shape (N, 3), float64; ``tets`` are node indices, shape (M, 4),
int32, positively oriented: ``det[x1 - x0, x2 - x0, x3 - x0] > 0`` (volume = det / 6). Face k of a tet is the face
opposite its node k, listed so that its right-hand normal points out of the tet (:data:`TET_FACES`).

Everything here is numpy on the host, run once before a model is built (a device version of the boundary
extraction belongs with the topology passes that split nodes).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..tables import TET_EDGES, TET_FACES

DEGENERATE_VOLUME = 1.0e-12
"""A tet is degenerate when |V| <= DEGENERATE_VOLUME · h³, h its longest edge [-]."""


FLOAT32_ROUNDING = 1.0e-3
"""Largest float32 rounding of a node coordinate, |x| 2⁻²⁴ (half a float32 step), as a fraction of the shortest tet
edge [-]. The device holds node positions in float32 (warpdem.model: node_ref_q, node_q): a mesh far from the origin
compared with its tets loses its shape there (at 1e8 m a float32 step is 8 m, and the faces of a 1 m tet collapse to
zero area, their depth to NaN), so such a mesh is refused before the build."""


class MeshError(ValueError):
    """A mesh that cannot be used: bad shapes or indices, non-finite points, or a degenerate tet."""


class MeshTooFarError(MeshError):
    """A mesh whose coordinates float32 cannot hold to :data:`FLOAT32_ROUNDING` of its shortest edge."""


@dataclass
class MeshQuality:
    """Quality summary of a tet mesh.

    Attributes:
        count: number of tets.
        volume_min: smallest tet volume [m³].
        volume_mean: mean tet volume [m³].
        volume_total: total tet volume [m³].
        radius_ratio_min: smallest radius ratio 3 r_in / r_circ (1 for a regular tet, → 0 for slivers) [-].
        radius_ratio_mean: mean radius ratio [-].
        dihedral_min: smallest dihedral angle over all tets [deg] (regular: 70.53°).
        dihedral_max: largest dihedral angle over all tets [deg].
        edge_min: shortest edge [m].
    """

    count: int
    volume_min: float
    volume_mean: float
    volume_total: float
    radius_ratio_min: float
    radius_ratio_mean: float
    dihedral_min: float
    dihedral_max: float
    edge_min: float

    def format(self) -> str:
        """A one-paragraph human-readable summary."""
        return (
            f"{self.count} tets, volume {self.volume_total:.6g} m³ "
            f"(min {self.volume_min:.3g}, mean {self.volume_mean:.3g} m³)\n"
            f"radius ratio min {self.radius_ratio_min:.3f}, mean {self.radius_ratio_mean:.3f}; "
            f"dihedral angles {self.dihedral_min:.1f}°–{self.dihedral_max:.1f}°; shortest edge {self.edge_min:.3g} m"
        )


def box_mesh(lo: Sequence[float], hi: Sequence[float], divisions: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """A structured tet mesh of the box [lo, hi]: each of the nx·ny·nz hex cells split into 6 Kuhn tets.

    The Kuhn (Freudenthal) split cuts a cell along its main diagonal: the 6 tets are the monotone paths
    corner 0 → e_a → e_a + e_b → corner 7 over the permutations (a, b, c) of the axes. Every cell is split the
    same way, so neighbouring cells cut their shared face along the same diagonal and the mesh is conforming.
    For a cubic cell the tets have dihedral angles of 45°, 60° and 90° (radius ratio 0.717); no slivers.

    Args:
        lo: lower corner [m], shape (3,).
        hi: upper corner [m], shape (3,), hi > lo.
        divisions: cells per axis (nx, ny, nz), each ≥ 1.

    Returns:
        points: node positions [m], shape ((nx+1)(ny+1)(nz+1), 3), float64, node (i, j, k) at
        index i + (nx+1)(j + (ny+1) k); tets: shape (6 nx ny nz, 4), int32, positively oriented, cell-major.
    """
    lo_a, hi_a = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    n = np.asarray(divisions, dtype=np.int64)
    if lo_a.shape != (3,) or hi_a.shape != (3,) or n.shape != (3,):
        raise MeshError("box_mesh: lo, hi and divisions need 3 entries each")
    if np.any(n < 1) or np.any(hi_a <= lo_a):
        raise MeshError(f"box_mesh: need divisions >= 1 and hi > lo, got {list(n)}, {list(lo_a)}, {list(hi_a)}")
    nx, ny, nz = (int(v) for v in n)
    axes = [np.linspace(lo_a[a], hi_a[a], n[a] + 1) for a in range(3)]
    gz, gy, gx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    points = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)

    def node(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        return i + (nx + 1) * (j + (ny + 1) * k)

    ck, cj, ci = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    ci, cj, ck = ci.ravel(), cj.ravel(), ck.ravel()
    tets = np.empty((nx * ny * nz, 6, 4), dtype=np.int64)
    for p, perm in enumerate(itertools.permutations(range(3))):
        corner = np.zeros(3, dtype=np.int64)
        path = [corner.copy()]
        for axis in perm:
            corner[axis] = 1
            path.append(corner.copy())
        # An odd permutation of the axes gives a negatively oriented path: swap two nodes to fix it.
        if _permutation_parity(perm):
            path[1], path[2] = path[2], path[1]
        for v, (di, dj, dk) in enumerate(path):
            tets[:, p, v] = node(ci + di, cj + dj, ck + dk)
    return points, tets.reshape(-1, 4).astype(np.int32)


def _permutation_parity(perm: Sequence[int]) -> int:
    """1 for an odd permutation, 0 for an even one."""
    inversions = sum(1 for a in range(len(perm)) for b in range(a + 1, len(perm)) if perm[a] > perm[b])
    return inversions % 2


def tet_signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes det[x1 - x0, x2 - x0, x3 - x0] / 6 [m³], shape (M,)."""
    x = points[tets]
    d = x[:, 1:] - x[:, :1]
    return np.einsum("ij,ij->i", d[:, 0], np.cross(d[:, 1], d[:, 2])) / 6.0


def _face_normals(x: np.ndarray) -> np.ndarray:
    """Area-weighted outward normals [m²] of the faces of positively oriented tets, shape (M, 4, 3)."""
    f = x[:, TET_FACES]
    return 0.5 * np.cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0])


def tet_quality(points: np.ndarray, tets: np.ndarray) -> MeshQuality:
    """Quality summary of positively oriented tets (see :class:`MeshQuality`)."""
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    if len(tets) == 0:
        return MeshQuality(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    x = points[tets]
    vol = tet_signed_volumes(points, tets)
    normals = _face_normals(x)
    areas = np.linalg.norm(normals, axis=2)
    r_in = 3.0 * vol / areas.sum(axis=1)
    # Circumcentre relative to x0: (|a|² b×c + |b|² c×a + |c|² a×b) / (2 a·(b×c)).
    a, b, c = (x[:, k] - x[:, 0] for k in (1, 2, 3))
    num = (
        np.sum(a * a, axis=1)[:, None] * np.cross(b, c)
        + np.sum(b * b, axis=1)[:, None] * np.cross(c, a)
        + np.sum(c * c, axis=1)[:, None] * np.cross(a, b)
    )
    r_circ = np.linalg.norm(num, axis=1) / (12.0 * vol)
    ratio = 3.0 * r_in / r_circ
    unit = normals / areas[:, :, None]
    pairs = np.array(list(itertools.combinations(range(4), 2)))
    cosines = np.einsum("mkj,mkj->mk", unit[:, pairs[:, 0]], unit[:, pairs[:, 1]])
    # The dihedral angle at the edge shared by two faces is π minus the angle between their outward normals.
    dihedral = 180.0 - np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))
    edges = np.linalg.norm(x[:, TET_EDGES[:, 1]] - x[:, TET_EDGES[:, 0]], axis=2)
    return MeshQuality(
        count=len(tets),
        volume_min=float(vol.min()),
        volume_mean=float(vol.mean()),
        volume_total=float(vol.sum()),
        radius_ratio_min=float(ratio.min()),
        radius_ratio_mean=float(ratio.mean()),
        dihedral_min=float(dihedral.min()),
        dihedral_max=float(dihedral.max()),
        edge_min=float(edges.min()),
    )


def check_tets(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, MeshQuality]:
    """Validate a tet mesh, re-orient inverted tets, and summarise its quality.

    Args:
        points: node positions [m], shape (N, 3).
        tets: node indices, shape (M, 4).

    Returns:
        tets with every one positively oriented (an inverted tet has its nodes 1 and 2 swapped), shape (M, 4),
        int32; and the :class:`MeshQuality` of the result.

    Raises:
        MeshError: wrong shapes, non-finite points, an index out of range, or a degenerate tet
            (|V| <= :data:`DEGENERATE_VOLUME` · h³, h its longest edge), named by its index; MeshTooFarError (a
            MeshError): coordinates so far from the origin, compared with the shortest edge, that the device's
            float32 cannot hold the tets' shape (:data:`FLOAT32_ROUNDING`).
    """
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"points must have shape (N, 3), got {points.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"tets must have shape (M, 4), got {tets.shape}")
    if not np.issubdtype(tets.dtype, np.integer) and len(tets):
        raise MeshError(f"tets must hold integer node indices, got {tets.dtype}")
    if not np.all(np.isfinite(points)):
        bad = int(np.nonzero(~np.all(np.isfinite(points), axis=1))[0][0])
        raise MeshError(f"point {bad} is not finite: {points[bad]}")
    tets = tets.astype(np.int64)
    out_of_range = np.nonzero(np.any((tets < 0) | (tets >= len(points)), axis=1))[0]
    if len(out_of_range):
        t = int(out_of_range[0])
        raise MeshError(f"tet {t} has a node index out of range [0, {len(points)}): {tets[t].tolist()}")
    if len(tets) == 0:
        return tets.astype(np.int32), tet_quality(points, tets)
    vol = tet_signed_volumes(points, tets)
    x = points[tets]
    edges = np.linalg.norm(x[:, TET_EDGES[:, 1]] - x[:, TET_EDGES[:, 0]], axis=2)
    h = edges.max(axis=1)
    degenerate = np.nonzero(np.abs(vol) <= DEGENERATE_VOLUME * h**3)[0]
    if len(degenerate):
        t = int(degenerate[0])
        more = f" (and {len(degenerate) - 1} more)" if len(degenerate) > 1 else ""
        raise MeshError(
            f"tet {t} is degenerate: volume {vol[t]:.3g} m³ with longest edge {h[t]:.3g} m, nodes "
            f"{tets[t].tolist()}{more}"
        )
    _check_float32_positions(points, float(edges.min()))
    oriented = tets.copy()
    inverted = vol < 0.0
    oriented[inverted, 1], oriented[inverted, 2] = tets[inverted, 2], tets[inverted, 1]
    return oriented.astype(np.int32), tet_quality(points, oriented)


def _check_float32_positions(points: np.ndarray, shortest: float) -> None:
    """Refuses a mesh whose farthest coordinate rounds in float32 by more than :data:`FLOAT32_ROUNDING` of its
    shortest edge [m] (:class:`MeshTooFarError`, naming the node and the distance allowed)."""
    far = np.abs(points).max(axis=1)
    node = int(np.argmax(far))
    allowed = FLOAT32_ROUNDING * shortest * 2.0**24
    if far[node] > allowed:
        raise MeshTooFarError(
            f"node {node} lies {far[node]:.3g} m from the origin (coordinates {points[node].tolist()}), where the "
            f"device's float32 positions round by {far[node] * 2.0**-24:.2g} m, more than {FLOAT32_ROUNDING:g} of the "
            f"shortest tet edge ({shortest:.3g} m); allowed: coordinates within {allowed:.3g} m of the origin for "
            "this mesh (move it nearer the origin)"
        )


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Faces used by exactly one tet, each with its nodes in outward (right-hand) order.

    Args:
        tets: positively oriented tets, shape (M, 4).

    Returns:
        Boundary triangles, shape (F, 3), int32, in the order of their tets.
    """
    tets = np.asarray(tets, dtype=np.int64)
    faces = tets[:, TET_FACES].reshape(-1, 3)
    if len(faces) == 0:
        return np.zeros((0, 3), dtype=np.int32)
    key = np.sort(faces, axis=1)
    order = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
    k = key[order]
    same_next = np.all(k[1:] == k[:-1], axis=1)
    unique_start = np.concatenate([[True], ~same_next])
    unique_end = np.concatenate([~same_next, [True]])
    single = order[unique_start & unique_end]
    return faces[np.sort(single)].astype(np.int32)


def smallest_heights(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Smallest height of each tet, 3 V / (largest face area) [m], shape (M,)."""
    x = np.asarray(points, dtype=np.float64)[np.asarray(tets, dtype=np.int64)]
    vol = np.abs(tet_signed_volumes(np.asarray(points, dtype=np.float64), np.asarray(tets, dtype=np.int64)))
    areas = np.linalg.norm(_face_normals(x), axis=2)
    return 3.0 * vol / areas.max(axis=1)
