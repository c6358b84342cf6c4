"""Host tet meshes (warpdem/build/mesh.py): the Kuhn box mesher, validation, quality and boundary faces.

Oracles: exact geometry of the box (volume, surface area, ∮ x·n dA = 3V by the divergence theorem), the face
incidence of a conforming mesh (every face shared by one tet on the boundary, two inside), and the closed-form
quality of the Kuhn tet (dihedral angles 45°/60°/90°, radius ratio √3/(1+√2)) and of the regular tet.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from warpdem.build.mesh import MeshError, boundary_faces, box_mesh, check_tets, smallest_heights, tet_quality

# Float64 geometry of a few hundred tets: sums are exact to a few ulps of the total.
GEOMETRY_RTOL = 1.0e-12

LO = (-0.3, 0.1, 2.0)
HI = (0.9, 0.6, 3.5)
DIVISIONS = (4, 3, 5)


def box_dimensions() -> np.ndarray:
    return np.subtract(HI, LO)


def face_keys(tets: np.ndarray) -> np.ndarray:
    """Sorted node triples of every face of every tet, shape (4M, 3)."""
    faces = tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3)
    return np.sort(faces, axis=1)


def triangle_area_vectors(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    x = points[faces]
    return 0.5 * np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])


def test_box_mesh_volumes_sum_to_the_box_and_are_positive():
    points, tets = box_mesh(LO, HI, DIVISIONS)
    nx, ny, nz = DIVISIONS
    assert points.shape == ((nx + 1) * (ny + 1) * (nz + 1), 3)
    assert tets.shape == (6 * nx * ny * nz, 4)
    x = points[tets]
    vol = np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6.0
    cell = np.prod(box_dimensions() / DIVISIONS)
    # Every Kuhn tet is one sixth of its cell.
    np.testing.assert_allclose(vol, cell / 6.0, rtol=GEOMETRY_RTOL)
    np.testing.assert_allclose(vol.sum(), np.prod(box_dimensions()), rtol=GEOMETRY_RTOL)
    np.testing.assert_allclose(points.min(axis=0), LO, rtol=GEOMETRY_RTOL)
    np.testing.assert_allclose(points.max(axis=0), HI, rtol=GEOMETRY_RTOL)


def test_box_mesh_is_conforming():
    _, tets = box_mesh(LO, HI, DIVISIONS)
    _, counts = np.unique(face_keys(tets), axis=0, return_counts=True)
    nx, ny, nz = DIVISIONS
    # Two triangles per boundary cell face; every other face is shared by exactly two tets.
    boundary = 2 * 2 * (nx * ny + ny * nz + nz * nx)
    assert counts.max() == 2
    assert np.count_nonzero(counts == 1) == boundary
    assert np.count_nonzero(counts == 2) == (4 * len(tets) - boundary) // 2


def test_boundary_faces_cover_the_box_surface_facing_outward():
    points, tets = box_mesh(LO, HI, DIVISIONS)
    faces = boundary_faces(tets)
    d = box_dimensions()
    assert len(faces) == 2 * 2 * (
        DIVISIONS[0] * DIVISIONS[1] + DIVISIONS[1] * DIVISIONS[2] + DIVISIONS[2] * DIVISIONS[0]
    )
    area_vectors = triangle_area_vectors(points, faces)
    surface = 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
    np.testing.assert_allclose(np.linalg.norm(area_vectors, axis=1).sum(), surface, rtol=GEOMETRY_RTOL)
    # Divergence theorem: ∮ x·n dA = 3 V only if every normal points out (x·n is linear, so the centroid is exact).
    centroids = points[faces].mean(axis=1)
    np.testing.assert_allclose(np.einsum("ij,ij->", centroids, area_vectors), 3.0 * np.prod(d), rtol=GEOMETRY_RTOL)
    # Every boundary face lies on a face of the box.
    on_box = np.isclose(points[faces], LO) | np.isclose(points[faces], HI)
    assert np.all(np.any(np.all(on_box, axis=1), axis=1))


def test_kuhn_tet_quality_is_the_closed_form():
    points, tets = box_mesh((0.0, 0.0, 0.0), (2.0, 2.0, 2.0), (2, 2, 2))
    q = tet_quality(points, tets)
    assert q.count == 48
    np.testing.assert_allclose([q.dihedral_min, q.dihedral_max], [45.0, 90.0], rtol=GEOMETRY_RTOL)
    # r_in = 3V/A = (1/2)/(1 + √2), r_circ = √3/2 (the cube's circumsphere): 3 r_in / r_circ = √3/(1 + √2).
    np.testing.assert_allclose(q.radius_ratio_min, math.sqrt(3.0) / (1.0 + math.sqrt(2.0)), rtol=GEOMETRY_RTOL)
    np.testing.assert_allclose([q.volume_total, q.volume_min, q.edge_min], [8.0, 1.0 / 6.0, 1.0], rtol=GEOMETRY_RTOL)
    # Smallest height 3V / A_max = 3 (1/6) / (√2/2) = 1/√2.
    np.testing.assert_allclose(smallest_heights(points, tets), 1.0 / math.sqrt(2.0), rtol=GEOMETRY_RTOL)
    assert "48 tets" in q.format()


def test_regular_tet_quality():
    points = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])
    _, q = check_tets(points, np.array([[0, 1, 2, 3]]))
    np.testing.assert_allclose(q.radius_ratio_min, 1.0, rtol=GEOMETRY_RTOL)
    np.testing.assert_allclose([q.dihedral_min, q.dihedral_max], math.degrees(math.acos(1.0 / 3.0)), rtol=1e-9)


def test_check_tets_reorients_inverted_tets():
    points, tets = box_mesh(LO, HI, (2, 2, 2))
    flipped = tets.copy()
    flipped[[3, 7]] = flipped[[3, 7]][:, [0, 2, 1, 3]]
    oriented, quality = check_tets(points, flipped)
    np.testing.assert_array_equal(oriented, tets)
    np.testing.assert_allclose(quality.volume_total, np.prod(box_dimensions()), rtol=GEOMETRY_RTOL)


def test_check_tets_rejects_a_degenerate_tet_by_index():
    points, tets = box_mesh(LO, HI, (2, 2, 2))
    # Four coplanar nodes of the bottom face.
    flat = np.array([[0, 1, 3, 4]])
    with pytest.raises(MeshError, match=r"tet 5 is degenerate"):
        check_tets(points, np.concatenate([tets[:5], flat, tets[5:]]))
    # Two equal nodes.
    with pytest.raises(MeshError, match=r"tet 2 is degenerate"):
        check_tets(points, np.concatenate([tets[:2], [[0, 1, 1, 4]]]))


def test_check_tets_rejects_bad_input():
    points, tets = box_mesh(LO, HI, (1, 1, 1))
    with pytest.raises(MeshError, match=r"tet 4 has a node index out of range"):
        check_tets(points, np.concatenate([tets[:4], [[0, 1, 2, 99]]]))
    with pytest.raises(MeshError, match=r"shape"):
        check_tets(points, tets[:, :3])
    bad = points.copy()
    bad[2, 1] = np.nan
    with pytest.raises(MeshError, match=r"point 2 is not finite"):
        check_tets(bad, tets)
