"""FEM rock output (warpdem/io/output.py and the runner): boundary surface, stress measures, VTU/pvd series, checkpoints
of the mesh, and a box-mesh scene run end to end.

Oracles:
- surface: the faces used once by active tets, against :func:`warpdem.build.mesh.boundary_faces` of the active tets
  (exact); split faces hidden while closed and drawn once open, by construction;
- stress measures: hand values (uniaxial σ → von Mises |σ|, pure shear τ → √3 τ, hydrostatic → 0), to float64
  round-off (``STRESS_RTOL``);
- VTU/pvd: read back with meshio and ElementTree, equal to what was written (VTU stores float64 exactly);
- run: the last USD sample of /World/Rock equals the final checkpoint's node positions (both float32, exact), the
  triangle count of a box of nx·ny·nz Kuhn cells is 4 (nx ny + ny nz + nz nx); a restart from a middle checkpoint
  reproduces the uninterrupted run bit for bit on the CPU.
"""

from __future__ import annotations

import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpdem.build.mesh import boundary_faces, box_mesh
from warpdem.io.checkpoint import read_checkpoint
from warpdem.io.output import VtuSeries, max_principal_stress, surface_faces, von_mises_stress
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import parse_scene

STRESS_RTOL = 1e-12

DIVISIONS = (2, 2, 4)
BOX_SCENE = {
    "name": "column",
    "run": {"end_time": 1.0, "output_rate": 2000.0},
    "gravity": {"vector": [0.0, 0.0, -9.81]},
    "materials": {
        "granite": {
            "density": 2650.0,
            "youngs_modulus": 5.0e9,
            "poisson_ratio": 0.25,
            "tensile_strength": 1.0e7,
            "fracture_energy": 50.0,
            "mass_damping": 5.0,
        }
    },
    "mesh": {
        "kind": "box",
        "lo": [0.0, 0.0, 0.0],
        "hi": [1.0, 1.0, 2.0],
        "divisions": list(DIVISIONS),
        "material": "granite",
        "velocity": [0.0, 0.0, -0.5],
    },
    "boundaries": [{"faces": "z-", "kind": "fixed"}],
    "output": {"vtu": True},
}

# A block on a horizontal joint at z = 1 m; the upper half is pulled up at 1 m/s, the joint has no strength.
JOINT_Z = 1.0
PULL = 1.0  # [m/s]
JOINTED_SCENE = {
    "name": "pulled",
    "run": {"end_time": 1.0, "output_rate": 1000.0},
    "gravity": {"vector": [0.0, 0.0, 0.0]},
    "materials": {"rock": {"density": 2650.0, "youngs_modulus": 5.0e9, "poisson_ratio": 0.25}},
    "joints": {"friction": 0.5},
    "mesh": {
        "kind": "geology",
        "lo": [0.0, 0.0, 0.0],
        "hi": [1.0, 1.0, 2.0],
        "material": "rock",
        "h": 0.4,
        "joint_sets": [{"name": "bed", "dip": 0.0, "dip_direction": 0.0, "spacing": 10.0, "offset": JOINT_Z}],
    },
    "loads": [
        {
            "kind": "velocity",
            "region": {"box": {"lo": [-1.0, -1.0, JOINT_Z + 1e-6], "hi": [2.0, 2.0, 3.0]}},
            "velocity": [0.0, 0.0, PULL],
        }
    ],
    "boundaries": [{"faces": "z-", "kind": "fixed"}],
}


def sorted_rows(faces: np.ndarray) -> np.ndarray:
    """Faces as sorted node triples in lexicographic order (orientation-free set comparison)."""
    f = np.sort(np.asarray(faces), axis=1)
    return f[np.lexsort(f.T[::-1])]


# ----------------------------------------------------------------------------------------------------------------
# Surface


def test_surface_of_box_equals_boundary_faces_and_follows_active_tets():
    _, tets = box_mesh((0, 0, 0), (1, 1, 1), (2, 2, 2))
    active = np.ones(len(tets), dtype=bool)
    faces, owner = surface_faces(tets, active)
    np.testing.assert_array_equal(faces, boundary_faces(tets))  # same faces, same order and orientation
    assert len(faces) == 6 * 4 * 2  # 6 box faces of 2 × 2 cell faces, each cut into 2 triangles
    # Each face belongs to its owner tet: its three nodes are three of the owner's four.
    for face, t in zip(faces, owner, strict=True):
        assert set(face) <= set(tets[t])
    # A converted tet exposes the faces of its neighbours.
    active[7] = False
    faces, _ = surface_faces(tets, active)
    np.testing.assert_array_equal(sorted_rows(faces), sorted_rows(boundary_faces(tets[active])))


def test_split_faces_drawn_only_once_open():
    # Two tets sharing face (1, 2, 3); the second tet got its own copies 5, 6, 7 of those nodes (a joint).
    points = np.array(
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]], dtype=np.float64
    )
    q = np.concatenate([points, points[1:4]])
    root = np.array([0, 1, 2, 3, 4, 1, 2, 3])
    tets = np.array([[0, 1, 2, 3], [4, 7, 6, 5]])
    active = np.ones(2, dtype=bool)
    faces, _ = surface_faces(tets, active, node_root=root, node_q=q, closed_gap=1e-6)
    assert len(faces) == 6  # the split face is closed: only the outer faces
    opened = q.copy()
    opened[5:] += 1e-3 * np.array([1.0, 1.0, 1.0])  # the joint opens
    faces, owner = surface_faces(tets, active, node_root=root, node_q=opened, closed_gap=1e-6)
    assert len(faces) == 8
    np.testing.assert_array_equal(np.bincount(owner), [4, 4])
    unsplit, _ = surface_faces(tets, active)  # without node roots every face of a split node is drawn
    assert len(unsplit) == 8


def test_face_grouping_equals_numpy_unique_rows():
    """The packed-key grouping of the surface search against np.unique(rows, axis=0) (exact), below and above the
    largest node index a packed key holds."""
    from warpdem.tables import PACKED_ROW_LIMIT, row_groups

    rng = np.random.default_rng(3)
    for high in (1, 7, 1000, 3 * PACKED_ROW_LIMIT):
        for count in (0, 1, 2000):
            rows = np.sort(rng.integers(0, high, size=(count, 3)), axis=1)
            rows[count - count // 4 :] = rows[: count // 4]  # a quarter repeated: groups of one and of more
            group, size = row_groups(rows)
            if count == 0:
                assert len(group) == 0 and len(size) == 0
                continue
            _, expected_group, expected_size = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
            np.testing.assert_array_equal(group, expected_group.reshape(-1))
            np.testing.assert_array_equal(size, expected_size)


def test_stress_measures_hand_values():
    sigma, tau, p = 3.0e6, 2.0e6, -5.0e6
    uniaxial = np.diag([sigma, 0.0, 0.0])
    shear = np.array([[0.0, tau, 0.0], [tau, 0.0, 0.0], [0.0, 0.0, 0.0]])
    hydro = p * np.eye(3)
    stresses = np.stack([uniaxial, shear, hydro, -uniaxial])
    np.testing.assert_allclose(
        von_mises_stress(stresses), [sigma, np.sqrt(3.0) * tau, 0.0, sigma], rtol=STRESS_RTOL, atol=STRESS_RTOL * sigma
    )
    np.testing.assert_allclose(
        max_principal_stress(stresses), [sigma, tau, p, 0.0], rtol=STRESS_RTOL, atol=STRESS_RTOL * sigma
    )
    assert max_principal_stress(np.zeros((0, 3, 3))).shape == (0,)


# ----------------------------------------------------------------------------------------------------------------
# VTU series


def test_vtu_series_round_trip(tmp_path: Path):
    points, tets = box_mesh((0, 0, 0), (1, 1, 1), (1, 1, 1))
    series = VtuSeries(tmp_path / "out", "rock")
    rng = np.random.default_rng(0)
    written = []
    for frame, time in enumerate((0.0, 2.5e-4)):
        u = rng.normal(size=points.shape)
        stress = rng.normal(size=(len(tets), 3, 3))
        series.write(
            frame,
            time,
            points + u,
            tets,
            point_data={"displacement": u},
            cell_data={"stress": stress, "von_mises": von_mises_stress(stress)},
        )
        written.append((u, stress))
    assert series.pvd_path == tmp_path / "out" / "rock.pvd"
    assert [p.name for p in series.files] == ["rock_000000.vtu", "rock_000001.vtu"]
    leftovers = [p for p in (tmp_path / "out").rglob("*") if "partial" in p.name]
    assert leftovers == []

    root = ET.parse(series.pvd_path).getroot()
    assert root.get("type") == "Collection"
    datasets = root.find("Collection").findall("DataSet")
    assert [float(d.get("timestep")) for d in datasets] == [0.0, 2.5e-4]
    for d, (u, stress) in zip(datasets, written, strict=True):
        mesh = meshio.read(tmp_path / "out" / d.get("file"))
        np.testing.assert_array_equal(mesh.points, points + u)
        np.testing.assert_array_equal(mesh.cells_dict["tetra"], tets)
        np.testing.assert_array_equal(mesh.point_data["displacement"], u)
        np.testing.assert_array_equal(mesh.cell_data["stress"][0], stress.reshape(-1, 9))

    # A restart from frame 1 continues the collection: frame 0's entry stays, frame 1 is rewritten.
    restarted = VtuSeries(tmp_path / "out", "rock", first_frame=1)
    assert restarted.pvd_path == series.pvd_path
    restarted.write(1, 7.5e-4, points, tets, point_data={}, cell_data={})
    datasets = ET.parse(series.pvd_path).getroot().find("Collection").findall("DataSet")
    assert [(float(d.get("timestep")), d.get("file")) for d in datasets] == [
        (0.0, "rock_vtu/rock_000000.vtu"),
        (7.5e-4, "rock_vtu/rock_000001.vtu"),
    ]


def test_one_collection_lists_mesh_and_spheres_of_every_frame(tmp_path: Path):
    """The mesh is part 0 and the spheres part 1 of each timestep; the spheres read back as vertex cells."""
    points, tets = box_mesh((0, 0, 0), (1, 1, 1), (1, 1, 1))
    series = VtuSeries(tmp_path, "mixed")
    rng = np.random.default_rng(1)
    spheres = []
    for frame, time in enumerate((0.0, 1e-3, 2e-3)):
        series.write(frame, time, points, tets, point_data={}, cell_data={})
        centers, radius = rng.random((5 + frame, 3)), rng.random(5 + frame)
        series.write_particles(frame, time, centers, {"radius": radius, "velocity": rng.normal(size=(5 + frame, 3))})
        spheres.append((centers, radius))
    datasets = ET.parse(series.pvd_path).getroot().find("Collection").findall("DataSet")
    assert [(float(d.get("timestep")), d.get("part")) for d in datasets] == [
        (t, part) for t in (0.0, 1e-3, 2e-3) for part in ("0", "1")
    ]
    assert [p.name for p in series.particle_files] == [f"mixed_{k:06d}.vtu" for k in range(3)]
    for d, (centers, radius) in zip(datasets[1::2], spheres, strict=True):
        mesh = meshio.read(tmp_path / d.get("file"))
        np.testing.assert_array_equal(mesh.points, centers)
        np.testing.assert_array_equal(mesh.cells_dict["vertex"].reshape(-1), np.arange(len(centers)))
        np.testing.assert_array_equal(mesh.point_data["radius"], radius)


VTK_HEADER = {"UInt32": np.uint32, "UInt64": np.uint64}
VTK_TYPE = {"Float64": np.float64, "Float32": np.float32, "Int64": np.int64, "Int32": np.int32, "UInt8": np.uint8}


def read_vtu(path: Path) -> tuple[int, int, dict[str, np.ndarray]]:
    """(NumberOfPoints, NumberOfCells, section/name → array of shape (tuples, components)) of a VTU file, decoded by
    the VTK XML format's rules (binary DataArrays: base64 of a header of block sizes, then each zlib block).

    meshio 5.3.5 reads no VTU file without cells (nschloe/meshio#1412: it indexes the first cell type), which ParaView
    reads; this reader is the oracle there, and :func:`test_vtu_reader_agrees_with_meshio` holds it to meshio's
    arrays where both read."""
    import base64
    import zlib

    root = ET.parse(path).getroot()
    header_type = np.dtype(VTK_HEADER[root.get("header_type", "UInt32")]).newbyteorder("<")
    compressed = root.get("compressor") is not None
    piece = root.find("UnstructuredGrid").find("Piece")
    arrays = {}
    for section in piece:
        for array in section.iter("DataArray"):
            assert array.get("format") == "binary", array.attrib
            text = array.text.strip()
            size = header_type.itemsize
            if compressed:
                first = np.frombuffer(base64.b64decode(text[: 4 * -(-3 * size // 3)]), header_type)
                blocks = int(first[0])
                head_chars = 4 * -(-(3 + blocks) * size // 3)
                sizes = np.frombuffer(base64.b64decode(text[:head_chars]), header_type)[3:].astype(np.int64)
                raw = base64.b64decode(text[head_chars:])
                ends = np.cumsum(sizes)
                data = b"".join(zlib.decompress(raw[e - n : e]) for n, e in zip(sizes, ends, strict=True))
            else:
                head_chars = 4 * -(-size // 3)
                data = base64.b64decode(text[head_chars:])
            values = np.frombuffer(data, np.dtype(VTK_TYPE[array.get("type")]).newbyteorder("<"))
            arrays[f"{section.tag}/{array.get('Name')}"] = values.reshape(-1, int(array.get("NumberOfComponents", 1)))
    return int(piece.get("NumberOfPoints")), int(piece.get("NumberOfCells")), arrays


def test_vtu_reader_agrees_with_meshio(tmp_path: Path):
    """The oracle of the empty-series test: on a file meshio reads, the decoder gives meshio's arrays exactly."""
    points, tets = box_mesh((0, 0, 0), (1, 1, 1), (1, 1, 1))
    stress = np.random.default_rng(2).normal(size=(len(tets), 3, 3))
    path = VtuSeries(tmp_path, "rock").write(
        0, 0.0, points, tets, point_data={"displacement": points * 0.5}, cell_data={"stress": stress}
    )
    n_points, n_cells, arrays = read_vtu(path)
    mesh = meshio.read(path)
    assert (n_points, n_cells) == (len(points), len(tets))
    np.testing.assert_array_equal(arrays["Points/Points"], mesh.points)
    np.testing.assert_array_equal(arrays["PointData/displacement"], mesh.point_data["displacement"])
    np.testing.assert_array_equal(arrays["CellData/stress"], mesh.cell_data["stress"][0])
    np.testing.assert_array_equal(arrays["Cells/connectivity"].reshape(-1, 4), mesh.cells_dict["tetra"])


def test_vtu_series_with_no_tet_and_no_sphere(tmp_path: Path):
    """A frame after every tet converted (nodes left, no cell) and a frame without spheres are written with every
    field at 0 rows (tensors still 9 components) and listed in the collection: ParaView shows nothing there
    instead of the last frame that had tets. Oracle: :func:`read_vtu` (meshio reads no cell-less file)."""
    points, _ = box_mesh((0, 0, 0), (1, 1, 1), (1, 1, 1))
    series = VtuSeries(tmp_path, "empty")
    no_tets = np.zeros((0, 4), np.int64)
    stress = np.zeros((0, 3, 3))
    mesh_path = series.write(
        0,
        0.0,
        points,
        no_tets,
        point_data={"displacement": np.zeros_like(points), "velocity": np.zeros_like(points)},
        cell_data={
            "stress": stress.reshape(-1, 9),
            "von_mises": von_mises_stress(stress),
            "max_principal": max_principal_stress(stress),
            "material": np.zeros(0, np.int32),
        },
    )
    sphere_path = series.write_particles(0, 0.0, np.zeros((0, 3)), {"radius": np.zeros(0)})

    n_points, n_cells, arrays = read_vtu(mesh_path)
    assert (n_points, n_cells) == (len(points), 0)
    np.testing.assert_array_equal(arrays["Points/Points"], points)
    assert arrays["CellData/stress"].shape == (0, 9)
    for name in ("von_mises", "max_principal", "material"):
        assert arrays[f"CellData/{name}"].shape == (0, 1), name
    assert arrays["Cells/connectivity"].size == arrays["Cells/offsets"].size == arrays["Cells/types"].size == 0
    n_points, n_cells, arrays = read_vtu(sphere_path)
    assert (n_points, n_cells) == (0, 0)
    assert arrays["Points/Points"].shape == (0, 3) and arrays["PointData/radius"].shape == (0, 1)
    datasets = ET.parse(series.pvd_path).getroot().find("Collection").findall("DataSet")
    assert [d.get("file") for d in datasets] == ["empty_vtu/empty_000000.vtu", "empty_particles/empty_000000.vtu"]


def test_run_that_starts_as_spheres_writes_a_readable_vtu_series(tmp_path: Path, capsys):
    """A box whose every tet starts as spheres, with the mesh and sphere series on: exit 0 and every .vtu of the
    collection readable, the mesh with 0 cells and the spheres with one vertex per converted tet (6 Kuhn tets, one
    sphere each)."""
    import tomli_w

    from warpdem.cli import main

    scene = {
        "name": "all_spheres",
        "run": {"end_time": 0.002, "output_rate": 1000.0},
        "materials": {
            "rock": {"density": 2500.0, "youngs_modulus": 1.0e8, "poisson_ratio": 0.25, "tresca_strength": 1.0e6}
        },
        "mesh": {
            "kind": "box",
            "lo": [0.0, 0.0, 0.0],
            "hi": [0.2, 0.2, 0.2],
            "divisions": [1, 1, 1],
            "material": "rock",
        },
        "conversion": {"enabled": True, "start_as_spheres": {"box": {"lo": [-1.0, -1.0, -1.0], "hi": [1.0, 1.0, 1.0]}}},
        "output": {"vtu": True, "particles_vtu": True},
    }
    path = tmp_path / "all_spheres.toml"
    path.write_text(tomli_w.dumps(scene))
    status = main([str(path), "--quiet", "--out", str(tmp_path / "out")])
    assert status == 0, capsys.readouterr().err
    datasets = ET.parse(tmp_path / "out" / "all_spheres.pvd").getroot().find("Collection").findall("DataSet")
    assert [d.get("part") for d in datasets] == ["0", "1"] * 3  # frames 0, 1, 2
    for d in datasets:
        _, n_cells, _ = read_vtu(tmp_path / "out" / d.get("file"))
        assert n_cells == (0 if d.get("part") == "0" else 6), d.get("file")
        if d.get("part") == "1":
            assert meshio.read(tmp_path / "out" / d.get("file")).cells_dict["vertex"].shape == (6, 1)
    assert sorted(p.relative_to(tmp_path / "out").as_posix() for p in (tmp_path / "out").rglob("*.vtu")) == sorted(
        d.get("file") for d in datasets
    )


# ----------------------------------------------------------------------------------------------------------------
# Runs


def test_box_scene_writes_rock_surface_vtu_and_mesh_checkpoint(device, tmp_path, capsys):
    frames = 2
    scene = parse_scene(BOX_SCENE)
    summary = run_scene(scene, RunOptions(device=device, frames=frames, out_dir=tmp_path))
    out = capsys.readouterr().out
    assert out.startswith("mesh: 96 tets, volume 2 m³")  # 6 Kuhn tets per cell, 2 × 2 × 4 cells

    arrays, attrs = read_checkpoint(summary.checkpoints[-1])
    nn = int(arrays["state/node_count"][0])
    assert nn == summary.nodes == 3 * 3 * 5
    assert summary.tets == 96
    for name in ("node_ref_q", "node_mass", "node_inv_mass", "node_motion", "tet_nodes", "tet_inv_ref", "tet_volume"):
        assert f"model/{name}" in arrays, name
    assert attrs["node_capacity"] == nn and attrs["tet_capacity"] == 96
    node_q = arrays["state/node_q"][:nn]
    assert np.all(np.isfinite(node_q))

    stage = Usd.Stage.Open(str(summary.usd_path))
    rock = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Rock"))
    assert rock.GetPointsAttr().GetTimeSamples() == [float(c) for c in range(frames + 1)]
    assert rock.GetFaceVertexIndicesAttr().GetTimeSamples() == [0.0]  # no topology change
    nx, ny, nz = DIVISIONS
    assert len(rock.GetFaceVertexCountsAttr().Get(0.0)) == 4 * (nx * ny + ny * nz + nz * nx)
    np.testing.assert_array_equal(np.asarray(rock.GetPointsAttr().Get(float(frames))), node_q)
    nt = int(arrays["state/tet_count"][0])
    _, owner = surface_faces(arrays["model/tet_nodes"][:nt], arrays["state/tet_active"][:nt] == 1)
    expected = von_mises_stress(arrays["state/tet_stress"][owner].astype(np.float64))
    assert expected.max() > 0.0  # gravity and the initial velocity against the fixed base strain the rock
    stress = UsdGeom.PrimvarsAPI(rock.GetPrim()).GetPrimvar("vonMisesStress")
    np.testing.assert_allclose(np.asarray(stress.Get(float(frames))), expected, rtol=1e-6, atol=1e-6 * expected.max())

    assert summary.pvd_path == tmp_path / "column.pvd"
    datasets = ET.parse(summary.pvd_path).getroot().find("Collection").findall("DataSet")
    assert len(datasets) == frames + 1
    last = meshio.read(tmp_path / datasets[-1].get("file"))
    np.testing.assert_allclose(last.points, node_q, rtol=0, atol=0)
    assert len(last.cells_dict["tetra"]) == 96
    assert "strain" in summary.format() and "rock mesh        45 nodes, 96 tets" in summary.format()
    assert not summary.fracture and "fracture" not in summary.format()  # no fracture lines where it is off


def test_quiet_run_prints_no_mesh_quality(device, tmp_path, capsys):
    run_scene(
        parse_scene({**BOX_SCENE, "output": {}}), RunOptions(device=device, frames=1, out_dir=tmp_path, quiet=True)
    )
    assert capsys.readouterr().out == ""
    assert not list(tmp_path.glob("*.pvd"))


@pytest.mark.parametrize("data", [BOX_SCENE, JOINTED_SCENE], ids=["box", "jointed"])
def test_mesh_restart_from_middle_checkpoint_is_bit_identical(device, tmp_path, data):
    if device != "cpu":
        pytest.skip("bitwise restart identity is a CPU property (float atomics reorder on GPUs)")
    data = {**data, "output": {"vtu": True}}
    scene = parse_scene(data)
    frames, every = 4, 2
    period = every / scene.run.output_rate
    full = run_scene(
        scene, RunOptions(device=device, frames=frames, out_dir=tmp_path / "full", checkpoint_every=period, quiet=True)
    )
    middle, end = full.checkpoints
    shutil.copytree(tmp_path / "full", tmp_path / "restart")  # the restart continues the first run's outputs
    again = run_scene(
        parse_scene(data),
        RunOptions(device=device, frames=frames, out_dir=tmp_path / "restart", restart=middle, quiet=True),
    )
    a, a_attrs = read_checkpoint(end)
    b, b_attrs = read_checkpoint(again.checkpoints[-1])
    assert sorted(a) == sorted(b)
    assert float(np.abs(a["state/node_u"]).max()) > 0.0
    for key in sorted(a):
        np.testing.assert_array_equal(b[key], a[key], err_msg=key)
    for key in ("step", "time", "frame", "dt", "node_capacity", "tet_capacity"):
        assert b_attrs[key] == a_attrs[key], key
    # The restart continues the VTU collection it finds (a copy of the first run's here): one series of frames 0..4,
    # the same files at the same times.
    name = scene.name
    full_sets = ET.parse(tmp_path / "full" / f"{name}.pvd").getroot().find("Collection").findall("DataSet")
    again_sets = ET.parse(tmp_path / "restart" / f"{name}.pvd").getroot().find("Collection").findall("DataSet")
    assert [(d.get("timestep"), d.get("file")) for d in again_sets] == [
        (d.get("timestep"), d.get("file")) for d in full_sets
    ]
    assert len(full_sets) == frames + 1


def test_opened_joint_appears_in_the_rock_surface(device, tmp_path):
    """Frame 0: the joint is closed and only the outer surface is drawn; once the upper block has been pulled
    PULL / output_rate = 1 mm away, both sides of every joint face are drawn, and the triangles are re-authored
    at that frame only."""
    from warpdem.build.scene_mesh import rock_mesh

    scene = parse_scene(JOINTED_SCENE)
    geology = rock_mesh(scene)
    joint_faces = len(geology.joint_faces)
    assert joint_faces > 0
    outer = sum(len(f) for f in geology.boundary_faces.values())
    summary = run_scene(scene, RunOptions(device=device, frames=2, out_dir=tmp_path, quiet=True))
    stage = Usd.Stage.Open(str(summary.usd_path))
    rock = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Rock"))
    counts = [len(rock.GetFaceVertexCountsAttr().Get(float(c))) for c in range(3)]
    assert counts == [outer, outer + 2 * joint_faces, outer + 2 * joint_faces]
    assert rock.GetFaceVertexIndicesAttr().GetTimeSamples() == [0.0, 1.0]
    # Checkpoints hold the split topology and the joint elements, so a restart needs no pre-split.
    arrays, _ = read_checkpoint(summary.checkpoints[-1])
    assert int(arrays["state/node_count"][0]) > len(geology.points)
    assert any(key.startswith("model/joint_") or key == "model/tet_face_joint" for key in arrays)


def test_cli_reports_an_unusable_mesh_file(tmp_path, capsys):
    from warpdem.cli import main

    (tmp_path / "rock.msh").write_text("not a mesh\n")
    scene = tmp_path / "bad_mesh.toml"
    scene.write_text(
        "[run]\nend_time = 0.01\n[materials.rock]\ndensity = 2600.0\nyoungs_modulus = 5e10\npoisson_ratio = 0.25\n"
        '[mesh]\nkind = "file"\npath = "rock.msh"\nmaterial = "rock"\n'
    )
    status = main([str(scene), "--out", str(tmp_path / "out"), "--frames", "1", "--quiet"])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith(f"error: {scene}: mesh.path: ") and "cannot read as gmsh" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").rglob("*.usd*"))


# ----------------------------------------------------------------------------------------------------------------
# Run-time cracks (LDEC node splitting): daughters appended past the mesh's nodes, tets remapped to them. The split is
# made by hand here, as the split pass makes it (the + side of the plane z = z_K takes the new daughter B, which
# copies K's reference position, position and displacement), so the output is checked without the fracture pass.

CRACK_Z = 1.0  # [m] the crack plane, through the middle nodes of a 2 m cube of 2 × 2 × 2 cells
CRACK_SCENE = {
    "name": "cracked_cube",
    "run": {"end_time": 1.0, "output_rate": 1000.0},
    "gravity": {"vector": [0.0, 0.0, 0.0]},
    "materials": {"rock": {"density": 2650.0, "youngs_modulus": 5.0e9, "poisson_ratio": 0.25}},
    "mesh": {"kind": "box", "lo": [0.0, 0.0, 0.0], "hi": [2.0, 2.0, 2.0], "divisions": [2, 2, 2], "material": "rock"},
    "capacity": {"nodes": 27 + 2},
}
CENTRE, SIDE = 13, 12  # box_mesh node (i, j, k) = i + 3 (j + 3 k): (1, 1, 1) inside, (0, 1, 1) on the x = 0 face
OPENING = 0.05  # [m] z displacement of the + side daughters once the crack opens (CLOSED_GAP × size ~ 5e-4 m)
DELTA_C = 0.04  # [m] critical opening of the hand-made cohesive elements


def split_by_hand(model, state, k: int, damage: float) -> int:
    """Splits node k along the plane z = z_K (the + side tets take a new daughter B), adds a cohesive element K–B and
    sets both daughters' damage; returns B."""
    nn = int(state.node_count.numpy()[0])
    for array in (model.node_ref_q, state.node_q, state.node_u, state.node_qd):
        a = array.numpy()
        a[nn] = a[k]
        array.assign(a)
    nt = int(state.tet_count.numpy()[0])
    tets = model.tet_nodes.numpy()
    ref = model.node_ref_q.numpy()
    plus = np.any(tets[:nt] == k, axis=1) & (ref[tets[:nt]].mean(axis=1)[:, 2] > ref[k, 2])
    tets[:nt][plus] = np.where(tets[:nt][plus] == k, nn, tets[:nt][plus])
    model.tet_nodes.assign(tets)
    state.node_count.assign(np.array([nn + 1], np.int32))
    c = int(state.cohesive_count.numpy()[0])
    for array, value in ((state.cohesive_a, k), (state.cohesive_b, nn), (state.cohesive_delta_c, DELTA_C)):
        a = array.numpy()
        a[c] = value
        array.assign(a)
    state.cohesive_count.assign(np.array([c + 1], np.int32))
    state.node_splits_total.assign(state.node_splits_total.numpy() + 1)
    set_damage(state, [k, nn], damage)
    return nn


def set_damage(state, nodes: list[int], value: float) -> None:
    d = state.node_damage.numpy()
    d[nodes] = value
    state.node_damage.assign(d)


def cracking_cube(restart_frame: int | None = None):
    """A fresh model of CRACK_SCENE with fracture on and the story of its frames: 0 intact; 1 the centre node split
    (interior, closed); 2 the side node split (on the surface, closed); 3 the + side daughters moved up by OPENING (the
    crack opens) and the centre's element broken; 4 nothing moved but the velocities. Yields (frame, model, state)."""
    import dataclasses

    from warpdem.build.scene_build import finalize_scene, scene_builder
    from warpdem.model import fracture_state

    scene = parse_scene(CRACK_SCENE)
    model, state = finalize_scene(scene, scene_builder(scene), "cpu")
    model = dataclasses.replace(model, fracture_interval=1, cohesive_capacity=4)
    state = dataclasses.replace(state, **fracture_state(model))
    points, tets = box_mesh((0, 0, 0), (2, 2, 2), (2, 2, 2))  # the mesh the scene builds, in the same order
    np.testing.assert_array_equal(model.node_ref_q.numpy()[:27], points.astype(np.float32))
    np.testing.assert_array_equal(model.tet_nodes.numpy()[:48], tets)
    yield 0, model, state
    b_centre = split_by_hand(model, state, CENTRE, 0.25)
    yield 1, model, state
    b_side = split_by_hand(model, state, SIDE, 0.5)
    yield 2, model, state
    for array in (state.node_u, state.node_q):
        a = array.numpy()
        a[[b_centre, b_side], 2] += OPENING
        array.assign(a)
    set_damage(state, [CENTRE, b_centre], 1.0)
    state.cohesive_broken.assign(np.array([1, 0, 0, 0], np.int32))
    state.cohesive_broken_total.assign(np.array([1], np.int32))
    yield 3, model, state
    state.node_qd.assign(state.node_qd.numpy() + 1.0)
    yield 4, model, state


def write_cracking_cube(path: Path, rock, first_frame: int = 0) -> list[tuple]:
    """Writes the rock of :func:`cracking_cube` from ``first_frame`` on (a restart when above 0); returns, per frame
    written, (node damage, node positions, intact cohesive pairs)."""
    from warpdem.io.usd import UsdWriter

    held = []
    none = {
        "positions": np.zeros((0, 3)),
        "radii": np.zeros(0),
        "velocities": np.zeros((0, 3)),
        "colors": np.zeros((0, 3)),
    }
    with UsdWriter(path, 1000.0, first_frame=first_frame, append=first_frame > 0) as writer:
        for frame, model, state in cracking_cube():
            if frame < first_frame:
                continue
            nn, nc = int(state.node_count.numpy()[0]), int(state.cohesive_count.numpy()[0])
            intact = state.cohesive_broken.numpy()[:nc] == 0
            pairs = np.stack([state.cohesive_a.numpy()[:nc], state.cohesive_b.numpy()[:nc]], axis=1)[intact]
            held.append((state.node_damage.numpy()[:nn].copy(), state.node_q.numpy()[:nn].copy(), pairs))
            rock.write_vtu(frame, 1e-3 * frame, model, state)
            writer.write_frame(
                time=1e-3 * frame,
                ids=np.zeros(0, np.int64),
                **none,
                surface=rock.surface(model, state),
                cohesive=rock.cohesive_curves(model, state),
            )
    return held


def test_run_time_crack_faces_appear_as_they_open_with_damage(tmp_path):
    """Oracles: the triangles are re-authored exactly where the drawn surface changes (frame 2: the side node's outer
    faces now use its daughter; frame 3: the crack opens), never on a split that shows nothing (frame 1: an interior
    node, closed); the opened crack adds both sides of every mesh triangle in the plane z = CRACK_Z that has a split
    node (brute force over the tets' faces); damage primvar, damage colours, VTU point data and cohesive curves
    equal what the state holds at every frame (float32 storage: exact)."""
    from warpdem.io.output import RockFrames, VtuSeries, damage_colors

    path = tmp_path / "crack.usdc"
    rock = RockFrames("damage", VtuSeries(tmp_path, "crack"))
    held = write_cracking_cube(path, rock)

    points, tets = box_mesh((0, 0, 0), (2, 2, 2), (2, 2, 2))
    in_plane = {
        frozenset(f)
        for tet in tets
        for f in np.asarray(tet)[[[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]]
        if np.all(np.isclose(points[f, 2], CRACK_Z))
    }
    crack = [f for f in in_plane if CENTRE in f or SIDE in f]
    assert len(crack) > 0
    outer = len(boundary_faces(tets))

    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Rock"))
    assert mesh.GetFaceVertexIndicesAttr().GetTimeSamples() == [0.0, 2.0, 3.0]
    faces = [np.asarray(mesh.GetFaceVertexIndicesAttr().Get(float(c))).reshape(-1, 3) for c in range(5)]
    assert [len(f) for f in faces] == [outer] * 3 + [outer + 2 * len(crack)] * 2
    # The daughters' roots (27: the centre's, 28: the side's) map every frame's triangles back onto the mesh's.
    root = np.concatenate([np.arange(27), [CENTRE, SIDE]])
    np.testing.assert_array_equal(sorted_rows(root[faces[2]]), sorted_rows(faces[0]))
    opened = {tuple(r) for r in sorted_rows(faces[3])} - {tuple(r) for r in sorted_rows(faces[2])}
    new_rows = [tuple(sorted(root[r])) for r in faces[3] if tuple(sorted(r)) in opened]
    assert sorted(new_rows) == sorted(tuple(sorted(f)) for f in crack for _ in range(2))

    primvars = UsdGeom.PrimvarsAPI(mesh.GetPrim())
    cohesive = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Cohesive"))
    for code, (damage, q, pairs) in enumerate(held):
        np.testing.assert_array_equal(np.asarray(primvars.GetPrimvar("damage").Get(code)), damage)
        np.testing.assert_array_equal(
            np.asarray(mesh.GetDisplayColorPrimvar().Get(code)), damage_colors(damage).astype(np.float32)
        )
        ends = np.asarray(cohesive.GetPointsAttr().Get(code)).reshape(-1, 2, 3)
        np.testing.assert_array_equal(ends, q[pairs])
        assert len(pairs) == [0, 1, 2, 1, 1][code]
    assert mesh.GetDisplayColorPrimvar().GetInterpolation() == UsdGeom.Tokens.vertex
    vtu = meshio.read(rock.vtu.files[-1])
    np.testing.assert_array_equal(vtu.point_data["damage"], held[-1][0])
    assert len(vtu.points) == 29


@pytest.mark.parametrize("restart_frame", [3, 4])
def test_restart_extends_a_cracked_stage(tmp_path, restart_frame):
    """A restarted run (a new RockFrames, the stage extended from ``restart_frame``) leaves the stage of the
    uninterrupted one, damage primvar and cohesive curves included, sample by sample."""
    from stage_compare import assert_stages_equal

    from warpdem.io.output import RockFrames

    whole, pieces = tmp_path / "whole.usdc", tmp_path / "pieces.usdc"
    write_cracking_cube(whole, RockFrames("stress"))
    write_cracking_cube(pieces, RockFrames("stress"))
    write_cracking_cube(pieces, RockFrames("stress"), first_frame=restart_frame)
    assert_stages_equal(Usd.Stage.Open(str(pieces)), Usd.Stage.Open(str(whole)))


def test_a_run_past_usd_max_spheres_writes_a_subsample_and_says_so(tmp_path, capsys):
    """The default scene's first 40 ms (2 frames) with output.usd_max_spheres = 100: the stage's last frame holds
    exactly the spheres whose id is a multiple of the smallest power of two k with ceil(N / k) <= 100 (N and the ids
    from the end's checkpoint, brute force), /World/Particles.warpdem:sphereStride = k, and the summary says so; a
    restart from the middle checkpoint continues that stage (its check compares the spheres the stage holds) and ends
    with the same stage, sample by sample."""
    import tomllib

    import tomli_w
    from stage_compare import assert_stages_equal

    from warpdem.cli import main

    scene = tomllib.loads((Path(__file__).parents[1] / "warpdem" / "data" / "default.toml").read_text())
    scene["run"]["end_time"] = 0.04
    scene["output"] = {**scene.get("output", {}), "usd_max_spheres": 100, "checkpoint_every": 0.02}
    path = tmp_path / "many.toml"
    path.write_text(tomli_w.dumps(scene))
    out = tmp_path / "out"
    assert main([str(path), "--out", str(out)]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    middle, end = sorted((out / "checkpoints").glob("*.h5"))
    arrays, _ = read_checkpoint(end)
    ids = arrays["model/particle_id"][: int(arrays["state/particle_count"][0])]
    stride = 1
    while -(-len(ids) // stride) > 100:
        stride *= 2
    assert stride > 1
    (stage_path,) = out.glob("*.usdc")
    stage = Usd.Stage.Open(str(stage_path))
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    last = stage.GetEndTimeCode()
    assert last == 2.0
    np.testing.assert_array_equal(np.asarray(points.GetIdsAttr().Get(last)), ids[ids % stride == 0])
    assert points.GetPrim().GetAttribute("warpdem:sphereStride").Get(last) == stride
    assert f"spheres subsampled: those whose id is a multiple of {stride}" in printed

    shutil.copytree(out, tmp_path / "again")
    again = tmp_path / "again"
    assert main([str(path), "--out", str(again), "--restart", str(again / "checkpoints" / middle.name)]) == 0
    assert "new stage" not in capsys.readouterr().err
    assert_stages_equal(Usd.Stage.Open(str(again / stage_path.name)), Usd.Stage.Open(str(stage_path)))
