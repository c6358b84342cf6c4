"""Every shipped scene (scenes/*.toml and the embedded default) is a 2-frame smoke test, a restart test, and its
energy balance closes at its time step and at half of it.

Oracles:
- smoke: the scene loads, builds and runs 2 frames (run_scene, frames=2); the final checkpoint holds only finite
  positions and velocities of the live spheres and FEM nodes, at frame 2 after 2 × substeps steps; the USD stage
  has exactly the time samples 0, 1, 2 of the particle positions, one point per live sphere (and no /World/Particles
  prim at all in a scene of rock alone; with FEM→DEM conversion a growing count, from an empty sample before the
  first spheres), and for a scene with a mesh the same samples of the /World/Rock points, the
  last equal to the checkpoint's node positions.
- balance: the relative energy error is within scene_balance_bound at the scene's time step and at half of it.
- restart: a run restarted from the checkpoint of frame 1 ends, on the CPU, in a final checkpoint equal to the
  uninterrupted run's array by array, bit for bit (same kernels, same order of float operations, every capacity as
  grown), and extends the uninterrupted run's stage into one equal to it sample by sample. The initial neighbour
  and FEM contact slots are cut to 1 so that every list with contacts grows before the checkpoint: the restart
  must rebuild the model with the grown capacities, not the scene's.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom
from stage_compare import assert_stages_equal

from warpdem.build.builder import ModelBuilder
from warpdem.io.checkpoint import read_checkpoint
from warpdem.runner import RunOptions, RunSummary, run_scene
from warpdem.scene import default_scene_path, load_scene

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
SCENES = [*sorted(SCENES_DIR.glob("*.toml")), default_scene_path()]
FRAMES = 2
INITIAL_SLOTS = 1  # neighbour and FEM contact slots per sphere / node before any growth
F32_EPS = float(np.finfo(np.float32).eps)
BOOK_ROUNDOFF = 16.0
"""float32 roundings per step relative to the energy in play (tests/test_energy_balance.py, where it is measured on
spheres)."""
MESH_BOUND = 5e-3
"""Bound on the balance of a scene with tets, relative to the energy in play: bulk viscosity, mass-proportional
damping, the non-reflecting dashpots and the FEM contacts still book their power at the half-step velocity, half a
step ahead (an O(dt) lead that does not accumulate: 1e-4 to 4e-4 over the scenes' first frames, halving with dt).
Issue 7's bound for every scene."""
DRIFT_SIGMAS = 4.0
"""A drift x ← x + dt v repeats almost the same increment, so float32 rounds it the same way step after step: after
n steps a sphere is off by n ulp(x)/√12 (one standard deviation, test_contact.py's momentum derivation), which moves
its potential by m |g| n ε₃₂ |z|/√12; four of those."""


def scene_balance_bound(summary: RunSummary) -> float:
    """The bound on a run's relative balance error: MESH_BOUND with tets; else the rounding of the booked work
    (BOOK_ROUNDOFF ε₃₂ per step, a random walk) and of the drifts against gravity (DRIFT_SIGMAS), which grows with
    the height of the spheres above z = 0 as long as positions are float32."""
    if summary.nodes:
        return MESH_BOUND
    n = summary.steps
    drift = DRIFT_SIGMAS * F32_EPS * n / np.sqrt(12.0) * abs(summary.energy_end.gravity_potential)
    return BOOK_ROUNDOFF * F32_EPS * np.sqrt(n) + drift / summary.energy_in_play


def test_scenes_are_found():
    assert len(SCENES) >= 7  # bonded_slab_impact, granular_pour, the four continuum scenes, the default
    assert default_scene_path().is_file()


@pytest.fixture
def small_lists(monkeypatch):
    """Every scene starts with INITIAL_SLOTS neighbour and FEM contact slots, so its lists grow at the first build."""
    finalize = ModelBuilder.finalize

    def finalize_small(self, *args, **kwargs):
        kwargs.update(max_neighbors=INITIAL_SLOTS, max_sphere_faces=INITIAL_SLOTS, max_node_faces=INITIAL_SLOTS)
        return finalize(self, *args, **kwargs)

    monkeypatch.setattr(ModelBuilder, "finalize", finalize_small)


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_scene_runs_two_frames_and_restarts_bit_for_bit(device, tmp_path, path, small_lists):
    scene = load_scene(path)
    period = 1.0 / scene.run.output_rate  # a checkpoint every frame: frames 1 and 2
    summary = run_scene(
        scene, RunOptions(device=device, frames=FRAMES, out_dir=tmp_path / "full", checkpoint_every=period, quiet=True)
    )

    # The energy balance closes (test_scene_balance_at_half_the_time_step: the same bound at half the time step).
    assert summary.energy_in_play > 0.0
    assert abs(summary.energy_error) <= scene_balance_bound(summary)

    middle, end = summary.checkpoints
    assert middle.name.startswith(f"{scene.name}_checkpoint_")
    arrays, attrs = read_checkpoint(end)
    n = int(arrays["state/particle_count"][0])
    nn = int(arrays["state/node_count"][0])
    assert n == summary.particles and nn == summary.nodes and n + nn > 0
    assert attrs["frame"] == FRAMES and attrs["step"] == FRAMES * int(attrs["substeps"])
    assert attrs["scene"] == scene.name
    for name in ("particle_q", "particle_qd", "particle_omega"):
        values = arrays[f"state/{name}"][:n]
        bad = np.nonzero(~np.isfinite(values).all(axis=1))[0]
        assert bad.size == 0, f"{path.name}: {name} non-finite for {bad.size} spheres (first {bad[:5]})"
    for name in ("node_q", "node_qd"):
        values = arrays[f"state/{name}"][:nn]
        bad = np.nonzero(~np.isfinite(values).all(axis=1))[0]
        assert bad.size == 0, f"{path.name}: {name} non-finite for {bad.size} nodes (first {bad[:5]})"

    stage = Usd.Stage.Open(str(summary.usd_path))
    particles = stage.GetPrimAtPath("/World/Particles")
    assert bool(particles) == (n > 0)  # a scene of rock alone has no empty Points prim (inverted extent)
    if n:
        points = UsdGeom.Points(particles).GetPointsAttr()
        counts = [len(points.Get(float(frame))) for frame in range(FRAMES + 1)]
        if scene.conversion.enabled:
            # FEM→DEM conversion adds spheres and never removes them: the count grows to n; the frames before the
            # first spheres hold one empty sample, the one before them (warpdem.io.usd).
            samples = points.GetTimeSamples()
            assert samples == [float(frame) for frame in range(int(samples[0]), FRAMES + 1)]
            assert counts == sorted(counts) and counts[-1] == n
        else:
            assert points.GetTimeSamples() == [float(frame) for frame in range(FRAMES + 1)]
            assert counts == [n] * (FRAMES + 1)
        # USD points are float32: the float64 centres rounded once, at the write.
        usd_points = np.asarray(points.Get(float(FRAMES))).reshape(-1, 3)
        np.testing.assert_array_equal(usd_points, arrays["state/particle_q"][:n].astype(np.float32))
    rock = stage.GetPrimAtPath("/World/Rock")
    assert bool(rock) == (nn > 0)
    if nn:
        rock_points = UsdGeom.Mesh(rock).GetPointsAttr()
        assert rock_points.GetTimeSamples() == [float(frame) for frame in range(FRAMES + 1)]
        np.testing.assert_array_equal(np.asarray(rock_points.Get(float(FRAMES))), arrays["state/node_q"][:nn])

    # Every list that holds contacts has grown past its initial slots before the middle checkpoint, and the checkpoint
    # holds the grown capacities (the restart below must rebuild the model with them).
    mid_arrays, mid_attrs = read_checkpoint(middle)
    for key, needed in (
        ("max_neighbors", mid_arrays["state/nbr_needed"][0]),
        ("max_sphere_faces", mid_arrays["state/sphere_face_needed"][0]),
        ("max_node_faces", mid_arrays["state/node_face_needed"][0]),
    ):
        assert mid_attrs[key] >= max(int(needed), INITIAL_SLOTS), key

    if device != "cpu":
        return  # bitwise restart identity is a CPU property (float atomics reorder on GPUs)
    # The restart extends the stage of the run it continues: a copy of it in the restart's folder.
    restart_dir = tmp_path / "restart"
    restart_dir.mkdir()
    shutil.copy(summary.usd_path, restart_dir / summary.usd_path.name)
    again = run_scene(
        load_scene(path), RunOptions(device=device, frames=FRAMES, out_dir=restart_dir, restart=middle, quiet=True)
    )
    b_arrays, b_attrs = read_checkpoint(again.checkpoints[-1])
    assert sorted(b_arrays) == sorted(arrays)
    for key in sorted(arrays):
        assert b_arrays[key].dtype == arrays[key].dtype, key
        np.testing.assert_array_equal(b_arrays[key], arrays[key], err_msg=f"{path.name}: {key}")
    assert {k: v for k, v in b_attrs.items() if k != "warpdem_version"} == {
        k: v for k, v in attrs.items() if k != "warpdem_version"
    }
    assert again.usd_path == summary.usd_path.parent.parent / "restart" / summary.usd_path.name
    assert_stages_equal(Usd.Stage.Open(str(again.usd_path)), stage)


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_scene_balance_at_half_the_time_step(device, tmp_path, path):
    """Each shipped scene at half its time step (the smoke test checks the same bound at its own): a scene of spheres
    books every force's work as Verlet does it, so its balance closes to the rounding bound (the pour's
    Hertz–Mindlin stiffness change is its own line), a scene with tets to MESH_BOUND.

    Measured over two frames (relative error, at dt and dt/2): pour 2e-5 and 9e-5 of 0.15 J in play, slab 1.5e-5 of
    57 J, default 1.9e-4 and 9.8e-5 of 5.3 J (the boulder's float32 drift against gravity), slope 3.7e-4 and 3.0e-4,
    tunnels 2.3e-4 → 1.0e-4 and 3.1e-4 → 1.1e-4, wave column 4.0e-4 → 2.0e-4."""
    scene = load_scene(path)
    # Half the time step over an eighth of the smoke test's time: a quarter of its steps.
    run = scene.run.model_copy(
        update={"safety_factor": 0.5 * scene.run.safety_factor, "output_rate": 4.0 * scene.run.output_rate}
    )
    summary = run_scene(
        scene.model_copy(update={"run": run}), RunOptions(device=device, frames=1, out_dir=tmp_path, quiet=True)
    )
    e0, e1 = summary.energy_start, summary.energy_end
    np.testing.assert_allclose(summary.energy_error, (e1.total - e0.total) / summary.energy_in_play)
    assert abs(summary.energy_error) <= scene_balance_bound(summary)
