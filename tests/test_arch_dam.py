"""The whole arch dam mesh (``[mesh] kind = "arch_dam"``, warpdem.build.arch_dam).

Oracles:
- volume: the tets' volumes sum to the layout's volume, integrated independently of Gmsh and OCC (64-point
  Gauss-Legendre over the height of the closed-form section area, :meth:`warpdem.scene.ArchDamMesh.volume`), within
  the faceting error of flat triangles on the curved faces: a chord of length l on a surface of curvature κ strays at
  most κ l² / 8 from it, so |ΔV| <= Σ_curved faces A l_max² κ_max / 8 (FACET_SAFETY for the loft's own interpolation);
- the charge: the loaded faces conform to the circle the scene names, so their area is that of the polygon of their
  boundary nodes on it, r²/2 Σ sin θ_i (float64 round-off), and falls short of π r² by r²/2 Σ (θ_i − sin θ_i) <=
  r²/2 Σ θ_i³ / 6 <= π r² θ_max² / 6 (the polygon error);
- determinism: the same parameters give identical arrays (single-threaded Gmsh, pinned options);
- grading: the edges at the charge are about h_charge, those far from it (beyond fine + grading distance) far longer;
- bad parameters: each rejected with its key and what is allowed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from warpdem.build.arch_dam import PLANE_TOLERANCE, mesh_arch_dam
from warpdem.build.mesh import boundary_faces, tet_signed_volumes
from warpdem.scene import ArchDamMesh, SceneError, load_scene, parse_scene

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "dam_crest_blast.toml"

ROUND = 1e-9
"""Relative float64 round-off of sums over ~10⁴ triangles and tets of coordinates ~10² m."""

FACET_SAFETY = 1.5
"""The faceting bound counts only the sagitta of flat triangles; the loft's B-splines through LOFT_SECTIONS sections
add far less (cubic interpolation of parabolas and lines), covered by this factor."""

GMSH_EDGE = (0.5, 1.6)
"""Gmsh's tets have edges within about this factor of the target size (its quality optimiser moves nodes)."""


def _small(**update) -> ArchDamMesh:
    """A 20 m dam, quick to mesh, with the shipped scene's proportions."""
    spec = {
        "kind": "arch_dam",
        "origin": [3.0, -5.0, 100.0],
        "height": 20.0,
        "crest_length": 50.0,
        "lower_length": 14.0,
        "charge_radius": 0.3,
        "h_charge": 0.2,
        "h": 1.5,
        "fine_distance": 0.5,
        "grading_distance": 6.0,
        "material": "concrete",
        **update,
    }
    return ArchDamMesh.model_validate(spec)


@pytest.fixture(scope="module")
def shipped():
    scene = load_scene(SCENE)
    return scene.mesh, mesh_arch_dam(scene.mesh)


def _curvature(spec: ArchDamMesh, faces: np.ndarray, points: np.ndarray, upstream: bool) -> np.ndarray:
    """Largest curvature of the face under each triangle [1/m]: its arch's 1/R (R_u upstream, R_d downstream, at the
    triangle's lowest node, where the radius is smallest) plus the crown profile's |u''| or |u'' − T''| over H²
    (parabolas: constant second derivatives)."""
    zeta = np.array([0.0, 0.45, 1.0])
    u2, t2 = (np.polyfit(zeta, f(zeta), 2)[0] * 2.0 for f in (spec.upstream_offset, spec.thickness))
    profile = (abs(u2) if upstream else abs(u2 - t2)) / spec.height**2
    low = (points[faces][..., 2].min(axis=1) - spec.origin[2]) / spec.height
    return 1.0 / spec.radii(np.clip(low, 0.0, 1.0))[0 if upstream else 1] + profile


@pytest.mark.parametrize("h", [1.5, 0.75])
def test_volume_matches_the_layout(h):
    """The small dam at two sizes (the shipped one's 8 m tets on its 12 m floor arch leave a 14 % bound)."""
    spec = _small(h=h)
    mesh = mesh_arch_dam(spec)
    volumes = tet_signed_volumes(mesh.points, mesh.tets)
    assert np.all(volumes > 0.0)
    bound = 0.0
    for name in ("upstream", "downstream"):
        faces = mesh.boundary_faces[name]
        p = mesh.points[faces]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        longest = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
        kappa = _curvature(spec, faces, mesh.points, name == "upstream")
        bound += FACET_SAFETY * float(np.sum(area * longest**2 * kappa)) / 8.0
    expected = spec.volume()
    assert abs(volumes.sum() - expected) <= bound, (volumes.sum(), expected, bound)
    print(h, volumes.sum() / expected - 1.0, bound / expected)
    assert bound < 0.05 * expected  # the bound itself is tight enough to catch a wrong layout


def test_charge_faces_are_the_named_disc(shipped):
    spec, mesh = shipped
    faces = mesh.boundary_faces["charge"]
    p = mesh.points[faces]
    area = float(np.sum(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)))
    centre = np.asarray(spec.charge_center())
    np.testing.assert_allclose(p[..., 2], centre[2], atol=PLANE_TOLERANCE * spec.height)
    # The disc's rim: edges of one charge triangle; their nodes lie on the circle.
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    rim = np.unique(unique[count == 1])
    r = spec.charge_radius
    rel = mesh.points[rim, :2] - centre[:2]
    np.testing.assert_allclose(np.hypot(rel[:, 0], rel[:, 1]), r, rtol=ROUND)
    angle = np.sort(np.arctan2(rel[:, 1], rel[:, 0]))
    theta = np.diff(np.append(angle, angle[0] + 2.0 * np.pi))
    polygon = 0.5 * r * r * np.sum(np.sin(theta))
    np.testing.assert_allclose(area, polygon, rtol=ROUND)
    disc = np.pi * r * r
    assert 0.0 < disc - area <= disc * theta.max() ** 2 / 6.0
    assert len(rim) >= 2.0 * np.pi * r / spec.h_charge / GMSH_EDGE[1]


def test_face_sets_cover_the_surface_once(shipped):
    spec, mesh = shipped
    sets = mesh.boundary_faces
    assert all(len(sets[name]) for name in ("upstream", "downstream", "crest", "charge", "foundation"))
    listed = np.sort(np.concatenate(list(sets.values())), axis=1)
    outer = np.sort(boundary_faces(mesh.tets), axis=1)
    assert len(np.unique(listed, axis=0)) == len(listed) == len(outer)
    rel = mesh.points - np.asarray(spec.origin)
    np.testing.assert_allclose(rel[sets["crest"], 2], spec.height, atol=PLANE_TOLERANCE * spec.height)
    # The upstream face at the crown is the crest's upstream edge (y = origin.y) up top, u(ζ) upstream of it below.
    up = np.unique(sets["upstream"])
    crown = up[np.abs(rel[up, 0]) < 1e-9 * spec.height]
    np.testing.assert_allclose(rel[crown, 1], spec.upstream_offset(rel[crown, 2] / spec.height), atol=1e-6)


def test_resolution_and_size_estimate(shipped):
    """run.resolution k divides both edges (h, h_charge) by k; the memory check's tet estimate
    (ArchDamMesh.estimated_tets, regular tetrahedra of the threshold's edge) is an upper bound on Gmsh's count,
    within a factor ESTIMATE_SLACK (Gmsh's tets are not regular: more of them fill a volume than edge³ / (6√2) says)."""
    ESTIMATE_SLACK = 5.0
    scene = load_scene(SCENE)
    fine = scene.model_copy(update={"run": scene.run.model_copy(update={"resolution": 2.0})}).scaled_mesh()
    assert (fine.h, fine.h_charge) == (scene.mesh.h / 2.0, scene.mesh.h_charge / 2.0)
    spec, mesh = shipped
    for dam, count in ((spec, len(mesh.tets)), (_small(), len(mesh_arch_dam(_small()).tets))):
        assert count <= dam.estimated_tets() <= ESTIMATE_SLACK * count


def test_mesh_is_deterministic():
    spec = _small()
    a, b = mesh_arch_dam(spec), mesh_arch_dam(spec)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.tets, b.tets)
    for name in a.boundary_faces:
        np.testing.assert_array_equal(a.boundary_faces[name], b.boundary_faces[name])


def test_mesh_is_graded(shipped):
    spec, mesh = shipped
    x = mesh.points[mesh.tets]
    edge = np.mean([np.linalg.norm(x[:, i] - x[:, j], axis=1) for i in range(4) for j in range(i)], axis=0)
    distance = np.linalg.norm(x.mean(axis=1) - np.asarray(spec.charge_center()), axis=1)
    near = np.median(edge[distance < spec.charge_radius + 0.5 * spec.fine_distance])
    far = np.median(edge[distance > spec.charge_radius + spec.fine_distance + spec.grading_distance])
    assert GMSH_EDGE[0] * spec.h_charge <= near <= GMSH_EDGE[1] * spec.h_charge
    # Far away the dam is thinner than h in places (the crest, 2.4 m): the edge is the smaller of h and the thickness.
    assert far >= GMSH_EDGE[0] * min(spec.h, spec.crest_thickness)
    assert far > 5.0 * near


def _scene(**mesh) -> dict:
    spec = _small().model_dump(mode="json")
    spec.update(mesh)
    for key in ("fixed", "velocity"):
        spec.pop(key)
    return {
        "run": {"end_time": 0.001},
        "materials": {"concrete": {"density": 2400.0, "youngs_modulus": 3e10, "poisson_ratio": 0.2}},
        "mesh": spec,
    }


@pytest.mark.parametrize(
    ("mesh", "pattern"),
    [
        ({"lower_length": 60.0}, r"mesh: .*lower_length must be less than crest_length"),
        ({"lower_length": 4.0}, r"mesh: .*floor width .* must be > 0"),
        (
            {"charge_radius": 0.5},
            r"mesh: .*charge_radius must be less than half the crest thickness T_C .* = 0\.8 m: got 0\.5",
        ),
        ({"h_charge": 4.0}, r"mesh: .*h_charge must not exceed h"),
        ({"h": 0.0}, r"mesh\.h: .*greater than 0"),
        ({"fine_distance": -1.0}, r"mesh\.fine_distance: .*greater than or equal to 0"),
        ({"heigth": 20.0}, r"mesh\.heigth"),
    ],
)
def test_bad_parameters_are_rejected(mesh, pattern):
    with pytest.raises(SceneError, match=pattern):
        parse_scene(_scene(**mesh))


def test_scene_names_the_dam_face_sets():
    scene = parse_scene(_scene())
    assert scene.face_set_names() == ["upstream", "downstream", "crest", "charge", "foundation"]
    data = _scene()
    data["loads"] = [
        {"kind": "pressure", "faces": "chrage", "history": {"kind": "blast", "peak": 1e6, "decay_time": 1e-4}}
    ]
    with pytest.raises(SceneError, match=r"loads\[0\]\.faces.*chrage"):
        parse_scene(data)
