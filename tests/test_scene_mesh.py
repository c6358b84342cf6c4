"""Scene meshes (warpdem/build/scene_mesh.py): the [mesh] kinds, face and node selections, and their mapping onto the
builder.

Oracles: box face sets against the analytic box (4 n_a n_b triangles per face, all nodes on the plane, outward unit
normals exactly ±e_axis); region selections against the named sets they coincide with; the builder's continuum
properties against the scene's material values; a mesh file written by warpdem.build.geology.write_mesh and read back
through a scene gives the same tets; layer materials by tet centroid height; per-group joint properties of a mesh
file on the device, each joint face identified by the plane it lies on (not by its set id) and checked against the
scene's value for that plane's group, or the [joints] default it does not set.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from warpdem.build.builder import NODE_MOTIONS
from warpdem.build.face_cover import SUBDIVISIONS, covered_area
from warpdem.build.geology import GeologyMesh, write_mesh
from warpdem.build.mesh import boundary_faces
from warpdem.build.scene_build import finalize_scene, scene_builder
from warpdem.build.scene_mesh import box_face_sets, face_normals, nodes_of_selection, rock_mesh, select_faces
from warpdem.scene import Material, Region, SceneError, parse_scene
from warpdem.stages.tets import TetProps
from warpdem.tables import TET_FACES

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


def test_geology_joint_sets_get_their_own_properties():
    """Each geology joint set's own values, the [joints] defaults for the rest, on the builder's joint sets."""
    sets = [
        {"name": "bedding", "dip": 0.0, "dip_direction": 0.0, "spacing": 5.0, "offset": 1.0, "stiffness_factor": 2.0},
        {"dip": 90.0, "dip_direction": 90.0, "spacing": 5.0, "offset": 1.0, "friction": 0.3, "restitution": 0.8},
    ]
    mesh = {"kind": "geology", "lo": [0.0, 0.0, 0.0], "hi": [2.0, 2.0, 2.0], "material": "rock", "h": 1.0}
    b = scene_builder(parse_scene(scene_with({**mesh, "joint_sets": sets}, joints={"friction": 0.7})))
    assert b.joint_set_names == ["bedding", "joint1"]
    bedding, steep = b.joint_sets
    assert (bedding.friction, bedding.stiffness_factor, bedding.restitution) == (0.7, 2.0, 0.5)
    assert (steep.friction, steep.stiffness_factor, steep.restitution) == (0.3, 1.0, 0.8)


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


CUBE = {"kind": "box", "lo": [0.0, 0.0, 0.0], "hi": [1.0, 1.0, 1.0], "divisions": [2, 2, 2], "material": "rock"}
# Joint groups of the mesh file: each is the plane {axis = 0.5} of the unit cube.
PLANES = {"bedding": 2, "fault": 0}


def two_joint_group_file(tmp_path: Path) -> Path:
    """A unit-cube mesh file whose triangle groups 'bedding' (z = 0.5) and 'fault' (x = 0.5) are the interior tet
    faces on those planes, with the six box faces as further groups."""
    cube = rock_mesh(parse_scene(scene_with(CUBE)))
    faces = np.unique(np.sort(cube.tets[:, TET_FACES].reshape(-1, 3), axis=1), axis=0)
    on = [np.all(cube.points[faces][:, :, axis] == 0.5, axis=1) for axis in PLANES.values()]
    mesh = GeologyMesh(
        points=cube.points,
        tets=cube.tets,
        tet_block=cube.tet_block,
        tet_material=cube.tet_material,
        material_names=["granite"],
        joint_faces=np.concatenate([faces[m] for m in on]),
        joint_face_set=np.concatenate([np.full(int(m.sum()), k) for k, m in enumerate(on)]),
        joint_set_names=list(PLANES),
        boundary_faces=cube.boundary_faces,
        num_blocks=1,
    )
    path = tmp_path / "jointed.msh"
    write_mesh(path, mesh)
    return path


def test_file_joint_groups_get_their_own_properties(tmp_path: Path):
    from warpdem.stages.restitution import restitution_linear

    path = two_joint_group_file(tmp_path)
    defaults = {"friction": 0.6, "cohesion": 0.0, "tensile_strength": 0.0, "stiffness_factor": 1.0}
    defaults |= {"restitution": 0.5, "shear_stiffness_ratio": 0.5}
    groups = {
        # A normal stiffness [Pa/m] replaces [joints]' stiffness_factor for this group (the keys exclude each other).
        "bedding": {
            "friction": 0.2,
            "cohesion": 1.0e5,
            "tensile_strength": 2.0e5,
            "restitution": 0.9,
            "normal_stiffness": 5e9,
        },
        "fault": {"friction": 0.9, "stiffness_factor": 2.0, "shear_stiffness_ratio": 0.3},
    }
    mesh = {"kind": "file", "path": str(path), "material": "rock", "joint_groups": groups}
    scene = parse_scene(scene_with(mesh, joints=defaults))
    model, state = finalize_scene(scene, scene_builder(scene), "cpu")

    # Every joint face on the device: the plane it lies on names its group; its set's properties are that group's.
    count = int(state.face_count.numpy()[0])
    face_set = model.face_joint.numpy()[:count]
    nodes = model.face_nodes.numpy()[:count][face_set >= 0]
    x = model.node_ref_q.numpy()[nodes]  # (F, 3 nodes, 3)
    table = model.joint_material_table.numpy()
    seen = set()
    for corners, k in zip(x, face_set[face_set >= 0], strict=True):
        group = [name for name, axis in PLANES.items() if np.all(corners[:, axis] == 0.5)]
        assert len(group) == 1, f"joint face at {corners.tolist()} is on no joint plane"
        want = defaults | groups[group[0]]
        got = table[k]
        np.testing.assert_allclose(got["contact"]["friction"], want["friction"], rtol=1e-6)
        np.testing.assert_allclose(got["contact"]["kt_ratio"], want["shear_stiffness_ratio"], rtol=1e-6)
        np.testing.assert_allclose(restitution_linear(float(got["contact"]["damp_n"])), want["restitution"], rtol=1e-5)
        np.testing.assert_allclose(got["cohesion"], want["cohesion"], rtol=1e-6)
        np.testing.assert_allclose(got["tensile_strength"], want["tensile_strength"], rtol=1e-6)
        own_kn = "normal_stiffness" in want
        np.testing.assert_allclose(got["stiffness_factor"], 0.0 if own_kn else want["stiffness_factor"], rtol=1e-6)
        np.testing.assert_allclose(got["face_normal_stiffness"], 0.5 * want.get("normal_stiffness", 0.0), rtol=1e-6)
        assert got["bonded"] == int(want["cohesion"] > 0 or want["tensile_strength"] > 0)
        seen.add(group[0])
    assert seen == set(PLANES)  # both sides of both joints are surface faces after the pre-split

    # Only the bonded bedding joint has interface elements: every one joins two copies of a node on z = 0.5.
    assert model.joint_capacity > 0
    a, b = model.joint_a.numpy(), model.joint_b.numpy()
    ref = model.node_ref_q.numpy()
    np.testing.assert_array_equal(ref[a][:, 2], 0.5)
    np.testing.assert_array_equal(ref[a], ref[b])
    for k in np.unique(model.joint_set.numpy()):
        np.testing.assert_allclose(table[k]["cohesion"], groups["bedding"]["cohesion"], rtol=1e-6)


def test_file_joint_group_selection_and_errors(tmp_path: Path):
    path = two_joint_group_file(tmp_path)

    def mesh(**extra) -> dict:
        return {"kind": "file", "path": str(path), "material": "rock", **extra}

    # The array form still selects groups (properties from [joints]); unlisted groups are face sets.
    listed = rock_mesh(parse_scene(scene_with(mesh(joint_groups=["fault"]))))
    assert listed.joint_set_names == ["fault"] and "bedding" in listed.boundary_faces
    np.testing.assert_array_equal(listed.points[listed.joint_faces][:, :, 0], 0.5)
    # Without joint_groups only names starting with 'joint' are joints: none here.
    assert rock_mesh(parse_scene(scene_with(mesh()))).joint_set_names == []

    with pytest.raises(SceneError) as excinfo:
        rock_mesh(parse_scene(scene_with(mesh(joint_groups={"bedding": {}, "faults": {"friction": 0.1}}))))
    message = str(excinfo.value)
    assert message.startswith("t: mesh.joint_groups: ") and str(path) in message, message
    assert "no triangle group 'faults'" in message and "'bedding', 'fault'" in message and "'z+'" in message, message
    with pytest.raises(SceneError, match=r"mesh.joint_groups.fault.friction: .*greater than or equal to 0"):
        parse_scene(scene_with(mesh(joint_groups={"fault": {"friction": -0.1}})))


def test_scene_without_spheres_or_mesh_is_refused():
    from warpdem.build.scene_build import build_scene

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

    (f0, h0, *_), (f1, h1, *_), (f2, h2, *_), (f3, h3, *_) = specs.pressures
    assert same_faces(f0, "z+") and (h0.kind, h0.peak, h0.decay_time, h0.rise_time) == ("blast", 1e6, 1e-3, 0.0)
    # The region holds the x+ face whole and a 0.01 m strip of the four faces around it: those faces it covers in part
    # (warpdem.build.face_cover), so it loads A = 1 × 3 + 0.01 × (2 × 3 + 2 × 1) m², to the midpoint rule's error,
    # at most the strips' edge (8 m) times a sub-triangle's size (the faces' 0.5 m legs / SUBDIVISIONS).
    w1 = specs.pressures[1].weights
    whole = np.isclose(w1.sum(axis=1), 1.0)
    assert same_faces(f1[whole], "x+") and h1.kind == "table" and h1.values == (0.0, 5e5)
    assert covered_area(mesh.points, f1, w1) == pytest.approx(3.08, abs=8.0 * 0.5 * np.sqrt(2.0) / SUBDIVISIONS)
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


def _arch_scene(**mesh) -> dict:
    spec = {
        "kind": "arch",
        "center": [1.0, -2.0, 0.5],
        "radius": 10.0,
        "thickness": 2.0,
        "height": 4.0,
        "angle": 60.0,
        "divisions": [6, 2, 4],
        "material": "rock",
        **mesh,
    }
    return {
        "run": {"end_time": 0.01},
        "materials": {"rock": {"density": 2400.0, "youngs_modulus": 3e10, "poisson_ratio": 0.2}},
        "mesh": spec,
    }


def test_arch_mesh_volume_orientation_and_face_sets():
    """A straight arch (constant thickness, no bulge) is a stack of right prisms over isosceles trapezoids, whose
    faces are planar: the tets' volumes sum to the polygonal annular sector's, n/2 sin(Δθ) (R² − r²) H, to float64
    round-off (ROUND). Every tet of a tapered, bulging arch (the dam's shape) is positively oriented; the face sets
    lie where the map puts them: upstream at r = R, downstream at r = R − t, crest at z = H, base at z = 0, the ends at
    θ = ∓angle/2."""
    from warpdem.build.mesh import tet_signed_volumes
    from warpdem.build.scene_mesh import arch_mesh

    ROUND = 1e-12
    scene = parse_scene(_arch_scene())
    mesh = arch_mesh(scene.mesh)
    n, r_out, r_in, height = 6, 10.0, 8.0, 4.0
    dtheta = np.radians(60.0) / n
    expected = 0.5 * n * np.sin(dtheta) * (r_out**2 - r_in**2) * height
    volumes = tet_signed_volumes(mesh.points, mesh.tets)
    np.testing.assert_allclose(volumes.sum(), expected, rtol=ROUND)
    assert len(mesh.tets) == 6 * 6 * 2 * 4 and np.all(volumes > 0.0)
    rel = mesh.points - np.array([1.0, -2.0, 0.5])
    radius = np.hypot(rel[:, 0], rel[:, 1])
    theta = np.arctan2(rel[:, 0], rel[:, 1])
    checks = {
        "upstream": (radius, r_out),
        "downstream": (radius, r_in),
        "crest": (rel[:, 2], height),
        "base": (rel[:, 2], 0.0),
        "left": (theta, -np.radians(30.0)),
        "right": (theta, np.radians(30.0)),
    }
    for name, (value, target) in checks.items():
        faces = mesh.boundary_faces[name]
        assert len(faces), name
        np.testing.assert_allclose(value[faces], target, atol=ROUND * 10.0, err_msg=name)
    assert sum(len(f) for f in mesh.boundary_faces.values()) == len(boundary_faces(mesh.tets))

    dam = parse_scene(_arch_scene(crest_thickness=1.0, bulge=0.5, divisions=[8, 3, 6]))
    bent = arch_mesh(dam.mesh)
    assert np.all(tet_signed_volumes(bent.points, bent.tets) > 0.0)


def test_material_regions_assign_tets_by_centroid():
    """Tets whose centroid lies in a [[material_regions]] entry's region take its material (later entries win):
    against a brute-force test of every centroid."""
    data = _arch_scene()
    data["mesh"] = {"kind": "box", "lo": [0, 0, 0], "hi": [2, 1, 1], "divisions": [4, 2, 2], "material": "rock"}
    data["materials"]["brick"] = {"density": 1900.0, "youngs_modulus": 5e9, "poisson_ratio": 0.2}
    data["materials"]["unused"] = {"density": 1000.0, "youngs_modulus": 1e9, "poisson_ratio": 0.2}
    left = {"box": {"lo": [-1, -1, -1], "hi": [1.0, 2, 2]}}
    corner = {"box": {"lo": [-1, -1, -1], "hi": [0.5, 0.5, 0.5]}}
    data["material_regions"] = [{"region": left, "material": "brick"}, {"region": corner, "material": "rock"}]
    scene = parse_scene(data)
    mesh = rock_mesh(scene)
    centroid = mesh.points[mesh.tets].mean(axis=1)
    expected = np.where(
        Region.model_validate(corner).contains(centroid),
        "rock",
        np.where(Region.model_validate(left).contains(centroid), "brick", "rock"),
    )
    np.testing.assert_array_equal(np.asarray(mesh.material_names)[mesh.tet_material], expected)
    assert sorted(mesh.material_names) == ["brick", "rock"]  # 'unused' is no tet's material
