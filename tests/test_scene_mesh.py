"""Scene meshes (warpdem/scene_mesh.py): the [mesh] kinds, face and node selections, and their mapping onto the
builder.

Oracles: box face sets against the analytic box (4 n_a n_b triangles per face, all nodes on the plane, outward unit
normals exactly ±e_axis); region selections against the named sets they coincide with; the builder's continuum
properties against the scene's material values; a mesh file written by warpdem.geology.write_mesh and read back
through a scene gives the same tets; layer materials by tet centroid height.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from warpdem.builder import NODE_MOTIONS, scene_builder
from warpdem.geology import write_mesh
from warpdem.mesh import boundary_faces
from warpdem.scene import Material, Region, SceneError, parse_scene
from warpdem.scene_mesh import box_face_sets, face_normals, nodes_of_selection, rock_mesh, select_faces
from warpdem.tets import TetProps

ROCK = {"density": 2600.0, "youngs_modulus": 5.0e10, "poisson_ratio": 0.25}
BOX = {"kind": "box", "lo": [0.0, 0.0, 0.0], "hi": [2.0, 1.0, 3.0], "divisions": [4, 2, 3], "material": "rock"}


def scene_with(mesh: dict, **extra) -> dict:
    return {"name": "t", "run": {"end_time": 0.01}, "materials": {"rock": dict(ROCK)}, "mesh": mesh, **extra}


def test_material_continuum_defaults_are_the_tet_defaults():
    # The scene schema cannot import warp (tets.py), so it repeats the defaults: they must agree.
    m = Material(**ROCK)
    d = TetProps()
    assert (m.bulk_viscosity_linear, m.bulk_viscosity_quadratic, m.mass_damping) == (
        d.bulk_viscosity_linear,
        d.bulk_viscosity_quadratic,
        d.damping_alpha,
    )


def test_box_face_sets_by_outward_normal():
    scene = parse_scene(scene_with(BOX))
    mesh = rock_mesh(scene)
    n = dict(zip("xyz", BOX["divisions"], strict=True))
    lo, hi = np.asarray(BOX["lo"]), np.asarray(BOX["hi"])
    total = 0
    for name, faces in mesh.boundary_faces.items():
        axis = "xyz".index(name[0])
        others = [a for a in "xyz" if a != name[0]]
        assert len(faces) == 2 * n[others[0]] * n[others[1]], name  # two triangles per cell face
        plane = lo[axis] if name[1] == "-" else hi[axis]
        np.testing.assert_array_equal(mesh.points[faces][:, :, axis], plane)
        normals = face_normals(mesh.points, faces)
        unit = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        np.testing.assert_allclose(unit[:, axis], -1.0 if name[1] == "-" else 1.0, rtol=0, atol=1e-12)
        total += len(faces)
    assert total == len(boundary_faces(mesh.tets)) == 4 * (4 * 2 + 2 * 3 + 3 * 4)  # each outer face in one set
    assert mesh.material_names == ["rock"] and mesh.num_blocks == 1 and len(mesh.joint_faces) == 0
    assert set(box_face_sets(mesh.points, mesh.tets)) == {"x-", "x+", "y-", "y+", "z-", "z+"}


def test_region_selection_matches_named_sets():
    scene = parse_scene(scene_with(BOX))
    mesh = rock_mesh(scene)
    top = Region.model_validate({"box": {"lo": [-1.0, -1.0, 2.99], "hi": [3.0, 2.0, 4.0]}})
    by_region = select_faces(mesh, None, top, "t: loads[0]")
    by_name = select_faces(mesh, "z+", None, "t: loads[0]")
    np.testing.assert_array_equal(
        np.sort(np.sort(by_region, axis=1), axis=0), np.sort(np.sort(by_name, axis=1), axis=0)
    )
    nodes = nodes_of_selection(mesh, None, top, "t: loads[0]")
    np.testing.assert_array_equal(nodes, np.unique(by_name))
    assert np.all(mesh.points[nodes][:, 2] == 3.0)
    np.testing.assert_array_equal(nodes_of_selection(mesh, "z+", None, "t: loads[0]"), nodes)

    nowhere = Region.model_validate({"box": {"lo": [10.0, 10.0, 10.0], "hi": [11.0, 11.0, 11.0]}})
    with pytest.raises(SceneError, match=r"t: loads\[0\].region: contains no outer face"):
        select_faces(mesh, None, nowhere, "t: loads[0]")
    with pytest.raises(SceneError, match=r"t: loads\[0\].region: contains no node"):
        nodes_of_selection(mesh, None, nowhere, "t: loads[0]")
    with pytest.raises(SceneError, match=r"t: boundaries\[1\].faces: unknown face set 'top'; the mesh has: 'x-'"):
        select_faces(mesh, "top", None, "t: boundaries[1]")


def test_builder_gets_continuum_properties_motion_and_velocity():
    rock = {**ROCK, "bulk_viscosity_linear": 0.1, "bulk_viscosity_quadratic": 2.0, "mass_damping": 3.0}
    data = scene_with({**BOX, "velocity": [0.0, 0.0, -2.0]})
    data["materials"] = {"rock": rock, "unused": dict(ROCK)}
    b = scene_builder(parse_scene(data))
    assert b.tet_props["rock"] == TetProps(0.1, 2.0, 3.0)
    mesh = b.tet_mesh_data()
    assert len(mesh.tets) == 6 * 4 * 2 * 3 and np.all(mesh.material == 0)
    np.testing.assert_array_equal(mesh.velocity, np.tile([0.0, 0.0, -2.0], (len(mesh.points), 1)))
    assert np.all(mesh.motion == NODE_MOTIONS["free"])
    assert len(b.mesh_qualities) == 1

    fixed = scene_builder(parse_scene(scene_with({**BOX, "fixed": True, "velocity": [1.0, 0.0, 0.0]})))
    mesh = fixed.tet_mesh_data()
    assert np.all(mesh.motion == NODE_MOTIONS["fixed"]) and np.all(mesh.velocity == 0.0)


def test_layered_geology_materials_by_height():
    data = scene_with(
        {
            "kind": "geology",
            "lo": [0.0, 0.0, 0.0],
            "hi": [4.0, 2.0, 4.0],
            "material": "rock",
            "layers": [{"z_top": 1.5, "material": "soft"}],
            "h": 1.0,
        }
    )
    data["materials"]["soft"] = {"density": 2000.0, "youngs_modulus": 1.0e9, "poisson_ratio": 0.3}
    scene = parse_scene(data)
    b = scene_builder(scene)
    mesh = b.tet_mesh_data()
    z = mesh.points[mesh.tets][:, :, 2].mean(axis=1)
    names = scene.material_names()
    np.testing.assert_array_equal(mesh.material, np.where(z < 1.5, names.index("soft"), names.index("rock")))
    assert set(b.tet_props) == {"rock", "soft"}
    volume = sum(q.volume_total for q in b.mesh_qualities)
    np.testing.assert_allclose(volume, 32.0, rtol=1e-9)


def test_file_mesh_through_a_scene(tmp_path: Path):
    box = rock_mesh(parse_scene(scene_with(BOX)))
    box.material_names = ["granite"]
    path = tmp_path / "rock.msh"
    write_mesh(path, box)

    mapped = rock_mesh(
        parse_scene(scene_with({"kind": "file", "path": str(path), "material_map": {"granite": "rock"}}))
    )
    assert mapped.material_names == ["rock"]
    np.testing.assert_array_equal(mapped.tets, box.tets)
    np.testing.assert_allclose(mapped.points, box.points, rtol=0, atol=1e-12)
    assert sorted(mapped.boundary_faces) == sorted(box.boundary_faces)  # the box faces are named groups in the file
    by_number = rock_mesh(parse_scene(scene_with({"kind": "file", "path": str(path), "material_map": {"1": "rock"}})))
    assert by_number.material_names == ["rock"]
    one = rock_mesh(parse_scene(scene_with({"kind": "file", "path": str(path), "material": "rock"})))
    assert one.material_names == ["rock"] and np.all(one.tet_material == 0)

    with pytest.raises(SceneError, match=r"t: mesh.material_map: tet group\(s\) 'granite' .* are not materials"):
        rock_mesh(parse_scene(scene_with({"kind": "file", "path": str(path)})))
    broken = tmp_path / "broken.msh"
    broken.write_text("not a mesh\n")
    with pytest.raises(SceneError, match=r"^t: mesh.path: .*broken.msh: cannot read as gmsh"):
        rock_mesh(parse_scene(scene_with({"kind": "file", "path": str(broken), "material": "rock"})))


def test_scene_without_spheres_or_mesh_is_refused():
    from warpdem.builder import build_scene

    data = {"name": "empty", "run": {"end_time": 0.01}, "materials": {"rock": dict(ROCK)}}
    with pytest.raises(SceneError, match="empty: particles: the scene creates no sphere"):
        build_scene(parse_scene(data), "cpu")


def test_loads_and_boundaries_map_onto_the_builder():
    import math

    data = scene_with(
        BOX,
        loads=[
            {"kind": "pressure", "faces": "z+", "history": {"kind": "blast", "peak": 1e6, "decay_time": 1e-3}},
            {
                "kind": "pressure",
                "region": {"box": {"lo": [1.99, -1.0, -1.0], "hi": [3.0, 2.0, 4.0]}},
                "history": {"kind": "table", "times": [0.0, 1e-3], "values": [0.0, 5e5]},
            },
            {
                "kind": "pressure",
                "faces": "y-",
                "history": {"kind": "friedlander", "peak": 2e5, "positive_duration": 1e-3, "start": 1e-4},
            },
            {
                "kind": "airblast",
                "faces": "z+",
                "peak": 3e5,
                "positive_duration": 2e-3,
                "decay_coefficient": 1.5,
                "source": [1.0, 0.5, 10.0],
                "front_speed": 400.0,
                "t0": 1e-3,
            },
            {"kind": "velocity", "faces": "x-", "velocity": [1.0, 0.0, 0.0], "start": 0.0, "end": 2e-3},
            {
                "kind": "velocity",
                "region": {"box": {"lo": [0.9, -1.0, -1.0], "hi": [1.1, 2.0, 4.0]}},
                "velocity": [0.0, 0.0, -1.0],
            },
        ],
        boundaries=[
            {"faces": "z-", "kind": "fixed"},
            {"faces": "y+", "kind": "roller"},
            {"region": {"box": {"lo": [-1.0, -1.0, -1.0], "hi": [0.01, 2.0, 4.0]}}, "kind": "non_reflecting"},
        ],
    )
    scene = parse_scene(data)
    b = scene_builder(scene)
    mesh = rock_mesh(scene)
    specs = b.load_specs
    faces_of = {name: {tuple(sorted(f)) for f in faces.tolist()} for name, faces in mesh.boundary_faces.items()}

    def same_faces(faces: np.ndarray, name: str) -> bool:
        return {tuple(sorted(f)) for f in faces.tolist()} == faces_of[name]

    (f0, h0, _), (f1, h1, _), (f2, h2, _), (f3, h3, _) = specs.pressures
    assert same_faces(f0, "z+") and (h0.kind, h0.peak, h0.decay_time, h0.rise_time) == ("blast", 1e6, 1e-3, 0.0)
    assert same_faces(f1, "x+") and h1.kind == "table" and h1.values == (0.0, 5e5)
    assert same_faces(f2, "y-") and (h2.kind, h2.duration, h2.start, h2.front_speed) == (
        "friedlander",
        1e-3,
        1e-4,
        math.inf,
    )
    assert same_faces(f3, "z+")
    assert (h3.kind, h3.peak, h3.duration, h3.decay_coefficient, h3.source, h3.front_speed, h3.start) == (
        "friedlander",
        3e5,
        2e-3,
        1.5,
        (1.0, 0.5, 10.0),
        400.0,
        1e-3,
    )
    (n0, v0, s0, e0), (n1, v1, _, e1) = specs.drivers
    np.testing.assert_array_equal(np.sort(n0), np.unique(mesh.boundary_faces["x-"]))
    assert v0.tolist() == [1.0, 0.0, 0.0] and (s0, e0) == (0.0, 2e-3)
    np.testing.assert_array_equal(np.sort(n1), np.nonzero(np.abs(mesh.points[:, 0] - 1.0) < 1e-12)[0])
    assert e1 == math.inf and v1.tolist() == [0.0, 0.0, -1.0]
    kinds = [(kind, items) for kind, items, _ in specs.boundaries]
    assert [k for k, _ in kinds] == ["fixed", "roller", "non_reflecting"]
    assert same_faces(kinds[0][1], "z-") and same_faces(kinds[1][1], "y+") and same_faces(kinds[2][1], "x-")


def test_load_problems_name_the_entry():
    nowhere = {"box": {"lo": [5.0, 5.0, 5.0], "hi": [6.0, 6.0, 6.0]}}
    corner = {"box": {"lo": [-1.0, -1.0, -1.0], "hi": [0.51, 2.0, 1.01]}}  # faces of x-, y±, z- at a corner cell
    cases = [
        ({"boundaries": [{"region": nowhere, "kind": "fixed"}]}, r"^t: boundaries\[0\].region: contains no outer face"),
        (
            {"loads": [{"kind": "velocity", "region": nowhere, "velocity": [0, 0, 1]}]},
            r"^t: loads\[0\].region: contains no node",
        ),
        (
            {"boundaries": [{"faces": "z-", "kind": "fixed"}, {"region": corner, "kind": "roller"}]},
            r"^t: boundaries\[1\].region: roller boundary: its faces are not all normal to one axis",
        ),
    ]
    for extra, pattern in cases:
        with pytest.raises(SceneError, match=pattern):
            scene_builder(parse_scene(scene_with(BOX, **extra)))
