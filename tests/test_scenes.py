"""Every shipped scene (scenes/*.toml and the embedded default) is a 2-frame smoke test.

Oracle: the scene loads, builds and runs 2 frames (run_scene, frames=2); the final checkpoint holds only finite
positions and velocities of the live spheres and FEM nodes, at frame 2 after 2 × substeps steps; the USD stage has
exactly the time samples 0, 1, 2 of the particle positions, one point per live sphere, and for a scene with a mesh
the same samples of the /World/Rock points, the last equal to the checkpoint's node positions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpdem.checkpoint import read_checkpoint
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import default_scene_path, load_scene

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
SCENES = [*sorted(SCENES_DIR.glob("*.toml")), default_scene_path()]
FRAMES = 2


def test_scenes_are_found():
    assert len(SCENES) >= 7  # bonded_slab_impact, granular_pour, the four continuum scenes, the default
    assert default_scene_path().is_file()


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_scene_runs_two_frames(device, tmp_path, path):
    scene = load_scene(path)
    summary = run_scene(scene, RunOptions(device=device, frames=FRAMES, out_dir=tmp_path, quiet=True))

    arrays, attrs = read_checkpoint(summary.checkpoints[-1])
    n = int(arrays["state/particle_count"][0])
    nn = int(arrays["state/node_count"][0])
    assert n == summary.particles and nn == summary.nodes and n + nn > 0
    assert attrs["frame"] == FRAMES and attrs["step"] == FRAMES * int(attrs["substeps"])
    for name in ("particle_q", "particle_qd", "particle_omega"):
        values = arrays[f"state/{name}"][:n]
        bad = np.nonzero(~np.isfinite(values).all(axis=1))[0]
        assert bad.size == 0, f"{path.name}: {name} non-finite for {bad.size} spheres (first {bad[:5]})"
    for name in ("node_q", "node_qd"):
        values = arrays[f"state/{name}"][:nn]
        bad = np.nonzero(~np.isfinite(values).all(axis=1))[0]
        assert bad.size == 0, f"{path.name}: {name} non-finite for {bad.size} nodes (first {bad[:5]})"

    stage = Usd.Stage.Open(str(summary.usd_path))
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles")).GetPointsAttr()
    assert points.GetTimeSamples() == [float(frame) for frame in range(FRAMES + 1)]
    for frame in range(FRAMES + 1):
        assert len(points.Get(float(frame))) == n
    # USD points are float32: the float64 centres rounded once, at the write.
    usd_points = np.asarray(points.Get(float(FRAMES))).reshape(-1, 3)
    np.testing.assert_array_equal(usd_points, arrays["state/particle_q"][:n].astype(np.float32))
    rock = stage.GetPrimAtPath("/World/Rock")
    assert bool(rock) == (nn > 0)
    if nn:
        rock_points = UsdGeom.Mesh(rock).GetPointsAttr()
        assert rock_points.GetTimeSamples() == [float(frame) for frame in range(FRAMES + 1)]
        np.testing.assert_array_equal(np.asarray(rock_points.Get(float(FRAMES))), arrays["state/node_q"][:nn])
