"""Initial overlaps (warpdem/build/overlap.py, kernels/overlap.py): spheres deep in each other or in the rock at build
time.

Oracles:
- sphere pairs: the O(N²) brute-force set of pairs with δ = r_i + r_j − |x_i − x_j| > ROUNDOFF · min(r_i, r_j), exact
  equality of the pair sets, δ to float64 round-off; the same pairs with the cloud moved 1 km from the origin;
- spheres and rock, against a Kuhn-tet cube [0, 1]³ (the rock is the cube): a centre inside the cube is in a tet and
  one outside is in none (points kept 1e-4 m from the faces, far beyond float32 rounding); outside, the depth is
  r − (distance to the cube) = r − |x − clamp(x, 0, 1)|, to float32 rounding of unit coordinates (DEPTH_ATOL);
- CUDA: the kernel module (which no shipped scene runs) generates CUDA source and compiles for sm_80 and sm_90 with
  Warp's NVRTC (as tests/test_cuda_codegen.py does for the scenes' kernels), on machines without a GPU too;
- scenes: a sphere placed inside a tet block, or two spheres overlapping by half a radius, are refused with a line
  naming run.allow_initial_overlap, the count and the worst overlap (δ / r = 0.5 exactly); the key lets them build;
  an overlap under the tolerance builds and is reported; every shipped scene with spheres starts clean;
- mesh nodes (warpdem.build.overlap.initial_node_overlap): two unit cubes of a mesh file, the upper one sunk by SINK
  into the lower one, start with node–face springs compressed by exactly SINK less the offset the set-up carries
  (float32 rounding of the extent; to DEPTH_ATOL), are refused by the runner with a line naming
  run.allow_initial_overlap, and run with it; the same cubes stacked exactly start with nothing compressed (every
  shipped scene with a mesh starts so: it stays at rest, tests/test_scenes_at_rest.py), and so do the cubes stacked
  with the upper one shifted over the lower's edge (a T-junction: nodes on one cube's face within half a tet of the
  other's side face, at its rim); and facility_nonpersistent's randomized joints at the [mesh] seeds whose meshes
  hold such T-junctions (seed 3: across two blocks' faces; seed 4: on a bedding plane at a node the block beneath
  shares through a joint element, half a tet from that block's lift-shaft wall), one geology whose blocks touch
  without penetrating, start with nothing pressed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import warp as wp
from warp._src import context
from warpdem.kernels import overlap as ko

from warpdem.build.geology import GeologyMesh, write_mesh
from warpdem.build.mesh import box_mesh
from warpdem.build.overlap import (
    OVERLAP_TOLERANCE,
    ROUNDOFF,
    initial_node_overlap,
    initial_overlap,
    sphere_pair_overlaps,
    sphere_rock_penetration,
)
from warpdem.build.scene_build import build_scene, finalize_scene, scene_builder
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import SceneError, default_scene_path, load_scene, parse_scene
from warpdem.simulation import Simulation

DEPTH_ATOL = 1e-6  # [m] float32 positions of order 1 m: ~1e-7 each, a few roundings
MARGIN = 1e-4  # [m] distance kept from the cube's faces by the inside/outside test points
SCENES = [*sorted((Path(__file__).resolve().parent.parent / "scenes").glob("*.toml")), default_scene_path()]
SPHERE_SCENES = [p for p in SCENES if "[[particles]]" in p.read_text()]
FACILITY = Path(__file__).resolve().parent.parent / "scenes" / "facility_nonpersistent.toml"


def brute_force_pairs(q: np.ndarray, r: np.ndarray) -> dict[tuple[int, int], float]:
    """Every pair (i < j) overlapping by more than ROUNDOFF of the smaller radius, with its overlap δ [m]."""
    found = {}
    for i in range(len(q)):
        for j in range(i + 1, len(q)):
            delta = r[i] + r[j] - float(np.linalg.norm(q[i] - q[j]))
            if delta > ROUNDOFF * min(r[i], r[j]):
                found[(i, j)] = delta
    return found


def test_sphere_pairs_equal_brute_force_anywhere(device):
    rng = np.random.default_rng(7)
    n = 300
    q = rng.uniform(0.0, 0.3, size=(n, 3))
    r = rng.uniform(0.005, 0.02, size=n)
    expected = brute_force_pairs(q, r)
    assert len(expected) > 50  # a dense cloud: many overlaps of every depth
    for offset in (np.zeros(3), np.array([1000.0, -2000.0, 500.0])):
        pairs, delta = sphere_pair_overlaps(q + offset, r, device)
        assert {tuple(p) for p in pairs.tolist()} == set(expected)
        # δ from coordinates of magnitude 2e3 m: float64 rounding ~2e3 · 1e-16 per coordinate.
        want = np.array([expected[tuple(p)] for p in pairs.tolist()])
        np.testing.assert_allclose(delta, want, rtol=0, atol=1e-11)


def test_touching_lattice_has_no_overlap(device):
    # Spheres of radius 0.5 on a unit cubic lattice touch exactly: δ = 0 up to float64 rounding, not an overlap.
    g = np.arange(6, dtype=np.float64)
    q = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) + 0.1
    pairs, _ = sphere_pair_overlaps(q, np.full(len(q), 0.5), device)
    assert len(pairs) == 0


def test_sphere_rock_depth_against_the_cube(device):
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (3, 3, 3))
    rng = np.random.default_rng(3)
    q = rng.uniform(-0.3, 1.3, size=(400, 3))
    clearance = np.minimum(np.abs(q), np.abs(q - 1.0)).min(axis=1)
    q = q[clearance > MARGIN]
    r = rng.uniform(0.05, 0.25, size=len(q))
    depth, tet = sphere_rock_penetration(q, r, points, tets, device)

    inside = np.all((q > 0.0) & (q < 1.0), axis=1)
    assert 0 < inside.sum() < len(q)
    np.testing.assert_array_equal(tet >= 0, inside)
    # The tet named holds the centre: its barycentric coordinates are all ≥ 0 (to float64 rounding).
    corners = points[tets[tet[inside]]]
    m = np.stack([corners[:, k] - corners[:, 0] for k in (1, 2, 3)], axis=2)
    lam = np.linalg.solve(m, (q[inside] - corners[:, 0])[..., None])[..., 0]
    assert np.all(lam >= -1e-12) and np.all(lam.sum(axis=1) <= 1.0 + 1e-12)
    np.testing.assert_allclose(depth[inside], r[inside], rtol=0, atol=DEPTH_ATOL)

    distance = np.linalg.norm(q - np.clip(q, 0.0, 1.0), axis=1)
    outside = ~inside
    want = r[outside] - np.minimum(distance[outside], r[outside])  # the kernel caps the search at r
    np.testing.assert_allclose(depth[outside], want, rtol=0, atol=DEPTH_ATOL)
    assert np.any(want > 0.0) and np.any(want == 0.0)


@pytest.mark.skipif(
    not context.runtime.is_cuda_enabled, reason="this Warp build has no CUDA compiler (CPU-only platform build)"
)
def test_rock_kernel_compiles_for_cuda(tmp_path):
    files = wp.compile_aot_module(
        ko.sphere_rock_penetration_kernel.module, arch=(80, 90), use_ptx=True, module_dir=tmp_path
    )
    assert sorted(p.suffixes[-2] for p in map(Path, files) if p.suffix == ".ptx") == [".sm80", ".sm90"]


def test_report_counts_the_worst_and_skips_held_pairs(device):
    r = 0.01
    # 0-1 overlap by 0.3 r (free), 2-3 by 0.6 r (both fixed: skipped), 4 alone; sphere 5 reaches 0.2 r into the cube
    # [0, 1]³ through its top face, sphere 6 sits in it.
    q = np.array(
        [
            [2.0, 0.0, 0.0],
            [2.0 + 2 * r - 0.3 * r, 0.0, 0.0],
            [3.0, 0.0, 0.0],
            [3.0 + 2 * r - 0.6 * r, 0.0, 0.0],
            [4.0, 0.0, 0.0],
            [0.5, 0.5, 1.0 + 0.8 * r],
            [0.5, 0.5, 0.5],
        ]
    )
    free = np.array([True, True, False, False, True, True, True])
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    report = initial_overlap(q, np.full(len(q), r), free, points, tets, device)
    assert (report.pairs, report.worst_pair) == (1, (0, 1))
    np.testing.assert_allclose(report.worst_pair_overlap, 0.3, rtol=1e-9)
    np.testing.assert_allclose(report.worst_pair_point, [2.0 + r - 0.15 * r, 0.0, 0.0], rtol=0, atol=1e-15)
    assert (report.inside, report.inside_sphere) == (1, 6)
    assert (report.penetrating, report.worst_penetrating) == (1, 5)
    np.testing.assert_allclose(report.worst_penetration, 0.2, rtol=0, atol=DEPTH_ATOL / r)
    assert report.exceeds(OVERLAP_TOLERANCE)
    line = report.format()
    assert "1 sphere pair(s) overlap, the worst by 30 %" in line and "spheres 0 and 1" in line
    assert "1 sphere(s) start with the centre inside the rock (sphere 6" in line
    assert "1 sphere(s) reach into the rock, the worst by 20 %" in line


# ----------------------------------------------------------------------------------------------------------------
# Scenes

ROCK = {"density": 2600.0, "youngs_modulus": 5.0e7, "poisson_ratio": 0.25}
BLOCK = {"kind": "box", "lo": [0.0, 0.0, 0.0], "hi": [1.0, 1.0, 1.0], "divisions": [2, 2, 2], "material": "rock"}


def sphere(center: list[float], radius: float = 0.05) -> dict:
    return {"kind": "sphere", "part": "grains", "center": center, "radius": radius}


def scene(spheres: list[dict], mesh: dict | None = None, allow: bool | None = None) -> dict:
    run = {"end_time": 0.01} | ({} if allow is None else {"allow_initial_overlap": allow})
    data = {
        "name": "overlapping",
        "run": run,
        "materials": {"rock": dict(ROCK)},
        "parts": {"grains": {"material": "rock"}},
        "particles": spheres,
    }
    return data | ({"mesh": mesh} if mesh is not None else {})


def test_sphere_inside_a_tet_block_is_refused_unless_allowed(device):
    data = scene([sphere([0.5, 0.5, 0.5]), sphere([0.5, 0.5, 1.5])], mesh=BLOCK)
    with pytest.raises(SceneError) as info:
        build_scene(parse_scene(data), device)
    (line,) = info.value.problems
    assert line.startswith("overlapping: run.allow_initial_overlap: ")
    assert "1 sphere(s) start with the centre inside the rock (sphere 0 at (0.5, 0.5, 0.5) m" in line

    model, _ = build_scene(parse_scene(scene(data["particles"], mesh=BLOCK, allow=True)), device)
    assert model.particle_capacity == 2 and model.tet_capacity == 6 * 8


def test_deeply_overlapping_spheres_are_refused_unless_allowed(device):
    r = 0.05
    spheres = [sphere([0.0, 0.0, 1.0], r), sphere([2 * r - 0.5 * r, 0.0, 1.0], r)]  # δ = 0.5 r
    with pytest.raises(SceneError, match=r"1 sphere pair\(s\) overlap, the worst by 50 % of the smaller radius"):
        build_scene(parse_scene(scene(spheres)), device)
    build_scene(parse_scene(scene(spheres, allow=True)), device)


def test_slight_overlap_builds_and_is_reported(device):
    r = 0.05
    spheres = [sphere([0.0, 0.0, 1.0], r), sphere([2 * r - 0.01 * r, 0.0, 1.0], r)]  # δ = 0.01 r < tolerance
    parsed = parse_scene(scene(spheres))
    b = scene_builder(parsed)
    finalize_scene(parsed, b, device)
    assert b.overlap.pairs == 1 and not b.overlap.exceeds(OVERLAP_TOLERANCE)
    np.testing.assert_allclose(b.overlap.worst_pair_overlap, 0.01, rtol=1e-9)


@pytest.mark.parametrize("path", SPHERE_SCENES, ids=[p.stem for p in SPHERE_SCENES])
def test_shipped_scenes_start_clean(path):
    # The scenes without spheres (a mesh only) have nothing to measure; every scene builds through finalize_scene,
    # which refuses overlaps, in test_scenes.py.
    report = scene_builder(load_scene(path)).measure_initial_overlap("cpu")
    assert not report.any, report.format()


def test_sphere_scenes_are_found():
    assert len(SPHERE_SCENES) >= 3  # granular_pour, bonded_slab_impact, the default


SINK = 0.05
"""How far the upper cube starts inside the lower one [m]: 20–40 % of the reach of the lower cube's top faces (half the
height of a 0.5 m Kuhn cell's tets over them), far past OVERLAP_TOLERANCE."""


def two_cubes_file(tmp_path: Path, sink: float, shift: float = 0.0) -> Path:
    """A mesh file of two unit cubes (Kuhn cells of 0.5 m), separate bodies, the upper one ``sink`` into the lower and
    ``shift`` along x."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    upper = points + np.array([shift, 0.0, 1.0 - sink])
    mesh = GeologyMesh(
        points=np.concatenate([points, upper]),
        tets=np.concatenate([tets, tets + len(points)]),
        tet_block=np.repeat([0, 1], len(tets)),
        tet_material=np.zeros(2 * len(tets), dtype=np.int32),
        material_names=["rock"],
        joint_faces=np.zeros((0, 3), dtype=np.int64),
        joint_face_set=np.zeros(0, dtype=np.int64),
        joint_set_names=[],
        boundary_faces={},
        num_blocks=2,
    )
    path = tmp_path / "cubes.msh"
    write_mesh(path, mesh)
    return path


def cubes_scene(path: Path, allow: bool | None = None) -> dict:
    run = {"end_time": 1e-4} | ({} if allow is None else {"allow_initial_overlap": allow})
    return {
        "name": "cubes",
        "run": run,
        "gravity": {"vector": [0.0, 0.0, 0.0]},
        "materials": {"rock": dict(ROCK)},
        "mesh": {"kind": "file", "path": str(path), "material": "rock"},
    }


def test_mesh_nodes_pressed_into_another_block_are_measured_and_refused_unless_allowed(tmp_path):
    sunk = parse_scene(cubes_scene(two_cubes_file(tmp_path, SINK)))
    model, state = build_scene(sunk, "cpu")
    assert initial_node_overlap(model, state).nodes == 0  # the built State has no spring yet: the set-up makes them
    sim = Simulation(model, state)
    overlap = initial_node_overlap(sim.model, sim.state)
    assert overlap.nodes > 0 and overlap.exceeds(OVERLAP_TOLERANCE)
    # The set-up carries a depth within float32 rounding of the model's extent as the spring's offset (noise_depth).
    np.testing.assert_allclose(overlap.worst_depth, SINK - sim.fem_contact.noise_depth, rtol=0.0, atol=DEPTH_ATOL)

    with pytest.raises(SceneError, match=r"run.allow_initial_overlap: \d+ mesh node\(s\) start pressed into a face"):
        run_scene(sunk, RunOptions(device="cpu", frames=1, out_dir=tmp_path / "refused", quiet=True))
    assert not (tmp_path / "refused").exists()  # refused before anything is written
    allowed = parse_scene(cubes_scene(two_cubes_file(tmp_path, SINK), allow=True))
    run_scene(allowed, RunOptions(device="cpu", frames=1, out_dir=tmp_path / "allowed", quiet=True))

    stacked = Simulation(*build_scene(parse_scene(cubes_scene(two_cubes_file(tmp_path, 0.0))), "cpu"))
    assert initial_node_overlap(stacked.model, stacked.state).nodes == 0


@pytest.mark.parametrize("shift", [0.77, 0.8, 0.9, 0.95])
def test_cube_resting_over_an_edge_starts_with_nothing_pressed(tmp_path, shift):
    """The upper cube rests on the lower one shifted by ``shift`` along x, over its edge: the upper cube's bottom
    edge at x = shift lies on the lower cube's top face, 1 − shift in from its side face x = 1 (within half the
    height of the tets over that face, 0.25 m), and the lower cube's top edge at x = 1 on the upper cube's bottom face,
    as far in from the upper's side face x = shift: each node projects onto the rim of the other cube's side face,
    behind it (a T-junction of a geology meshed on a lattice). Oracle: the cubes touch without penetrating, so no
    spring starts pressed (six nodes started 1 − shift deep before kernels/node_face_target.py
    exits_over_convex_edge), and the run is not refused."""
    scene = parse_scene(cubes_scene(two_cubes_file(tmp_path, 0.0, shift)))
    sim = Simulation(*build_scene(scene, "cpu"))
    assert initial_node_overlap(sim.model, sim.state).nodes == 0
    run_scene(scene, RunOptions(device="cpu", frames=1, out_dir=tmp_path / "run", quiet=True))


@pytest.mark.parametrize("seed", [3, 4])
def test_randomized_facility_starts_with_nothing_pressed(seed):
    """facility_nonpersistent's joints drawn at [mesh] ``seed`` (8 ships): a mesh of one geology puts no node inside
    another block, so no node–face spring may start pressed. Seed 3 started 17 nodes pressed by half a tet into the
    side face of a block whose top face they lie on, seed 4 two such nodes (at 4.5, 9.5, 16 m, 0.5 m behind the lift
    shaft's wall of the block beneath), whose face there is no candidate of theirs: its corner under them is their
    joint partner (kernels/node_face_target.py exits_over_convex_edge). Each draw is a new Gmsh mesh (~15 s)."""
    data = load_scene(FACILITY).model_dump(warnings=False)
    data["mesh"]["seed"] = seed
    sim = Simulation(*build_scene(parse_scene(data), "cpu"))
    overlap = initial_node_overlap(sim.model, sim.state)
    assert overlap.nodes == 0, overlap.format()
