"""The Python API (warpdem/api.py, warpdem.runner.Run): a script runs the command line's run, frame by frame.

Oracles:
- the same run: the API's frames write, bit for bit on the CPU, what ``run_scene`` (the command line) writes: the time
  series CSV byte for byte, the final checkpoint array by array, the USD stage sample by sample;
- restart: a run restarted from an API checkpoint (at a frame, or between two frames after a stop request) ends in
  the uninterrupted run's state and stage, bit for bit on the CPU;
- loads: a pressure load scaled by ½ from the start is the scene with half the peak, bit for bit (½ is exact in
  float32); scaled between steps, the load work the kernels book equals the work of the applied forces summed on the
  host, ½ (f_n + f_{n+1})·(u_{n+1} − u_n) per step (Verlet's trapezoid, kernels/loads.py), to LOAD_WORK_RTOL, and the
  books close within MESH_BOUND;
- errors name what is wrong: the edited key, the array asked for and those there are, the load;
- ejecta: a loose impactor is no piece broken off (the summary counted its speed as ejecta before).
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd
from stage_compare import assert_stages_equal
from test_cli import GOOD_SCENE

import warpdem as wd
from warpdem.io.checkpoint import read_checkpoint
from warpdem.io.timeseries import read_series
from warpdem.runner import RunOptions, run_scene

REPO = Path(__file__).resolve().parent.parent
WAVE = REPO / "scenes" / "wave_column.toml"  # 960 tets, a blast pulse on the top: 16 steps a frame
STEPS_PER_WAVE_FRAME = 16

TINY = GOOD_SCENE
"""Three spheres falling onto the ground (73 steps a frame): tests/test_cli.py's good scene."""

MESH_BOUND = 5e-3
"""The balance bound of a scene with tets, relative to the energy in play (tests/test_scenes.py MESH_BOUND)."""
LOAD_WORK_RTOL = 2e-6
"""Booked against host-summed load work over n = 24 steps: the host's increments u_{n+1} − u_n are differences of
float32 displacements, off the kernels' dt·v_{n+1/2} by ε₃₂ |u| / |Δu| ≤ ε₃₂ n (u grows by at most n increments),
random in sign; the forces are the same float32 values in both. (Measured: 1.4e-8.)"""


def tiny_scene() -> wd.Scene:
    return wd.parse_scene(tomllib.loads(TINY))


def scene_named(name: str) -> wd.Scene:
    return tiny_scene() if name == "tiny" else wd.load_scene(WAVE)


def final_checkpoint(out: Path) -> Path:
    return max((out / "checkpoints").glob("*.h5"))


def assert_same_checkpoint(a: Path, b: Path) -> None:
    arrays_a, attrs_a = read_checkpoint(a)
    arrays_b, attrs_b = read_checkpoint(b)
    assert sorted(arrays_a) == sorted(arrays_b)
    for key in sorted(arrays_a):
        np.testing.assert_array_equal(arrays_a[key], arrays_b[key], err_msg=key)
    for key in ("step", "time", "frame"):
        assert attrs_a[key] == attrs_b[key], key


def stage(path: Path) -> Usd.Stage:
    return Usd.Stage.Open(str(path))


def frame_codes(path: Path) -> list[float]:
    """The time codes of the frames a stage holds (``/World.warpdem:time`` samples)."""
    opened = stage(path)
    return list(opened.GetPrimAtPath("/World").GetAttribute("warpdem:time").GetTimeSamples())


# ----------------------------------------------------------------------------------------------------------------
# The package and its names


def test_import_stays_light_and_the_api_names_are_the_packages():
    """``import warpdem`` loads no Warp and no USD; the names come on first use and are the scene package's own;
    ``wd.build`` is a function to call and still the package of the build layer for the import system."""
    code = (
        "import sys, warpdem as wd; assert 'warp' not in sys.modules and 'pxr' not in sys.modules, 'heavy import'; "
        "import warpdem.scene as s; assert wd.Scene is s.Scene and wd.load_scene is s.load_scene; "
        "assert 'warp' not in sys.modules; import warpdem.api as api; assert wd.restart is api.restart; "
        "import warpdem.build.geology as g; assert callable(wd.build) and wd.build.__name__ == 'warpdem.build'"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


# ----------------------------------------------------------------------------------------------------------------
# The API's run is the command line's


def test_api_frames_write_what_the_command_line_writes(tmp_path):
    """wave_column, 3 frames, once through run_scene and once through wd.build + frames(): the same series file, final
    checkpoint and stage; the frames yielded are 0..3 with the series' error and load work."""
    cli = run_scene(wd.load_scene(WAVE), RunOptions(device="cpu", frames=3, out_dir=tmp_path / "cli", quiet=True))
    seen = []
    sim = wd.build(WAVE, device="cpu", frames=3, out_dir=tmp_path / "api")
    sim.on_frame(seen.append)
    frames = list(sim.frames())
    assert sim.summary is not None  # the iterator finished the run at its end
    assert [f.index for f in frames] == [0, 1, 2, 3] and frames == seen
    assert [f.step for f in frames] == [k * STEPS_PER_WAVE_FRAME for k in range(4)]

    assert (tmp_path / "api" / "wave_column_series.csv").read_bytes() == cli.series_path.read_bytes()
    assert_same_checkpoint(final_checkpoint(tmp_path / "api"), final_checkpoint(tmp_path / "cli"))
    assert_stages_equal(stage(sim.usd_path), stage(cli.usd_path))
    series = read_series(cli.series_path)
    np.testing.assert_array_equal([f.energy.error for f in frames], series["energy_error"])
    np.testing.assert_array_equal([f.energy.load_work for f in frames], series["energy_load_work"])
    assert sim.summary.energy_error == cli.energy_error and sim.summary.steps == cli.steps


# ----------------------------------------------------------------------------------------------------------------
# Checkpoint and restart


@pytest.mark.parametrize("name", ["tiny", "wave"])
def test_restart_from_an_api_checkpoint_continues_the_same_run(tmp_path, name):
    """A run checkpointed by the API at frame 2 of 4 and restarted from that file alone (the scene, the end and the
    outputs come from it) ends where the uninterrupted run ends, with the same stage."""
    whole = wd.build(scene_named(name), device="cpu", frames=4, out_dir=tmp_path / "whole")
    whole.run()

    sim = wd.build(scene_named(name), device="cpu", frames=4, out_dir=tmp_path / "cut")
    for frame in sim.frames():
        if frame.index == 2:
            sim.checkpoint(tmp_path / "run.h5")
            break
    again = wd.restart(tmp_path / "run.h5")  # takes the stage over from the run still open
    assert [f.index for f in again.frames()] == [2, 3, 4]  # frame 2 written again, then the rest
    np.testing.assert_array_equal(again.positions(), whole.positions())
    np.testing.assert_array_equal(again.node_positions(), whole.node_positions())
    assert again.usd_path == (tmp_path / "cut" / whole.usd_path.name).resolve()
    assert_same_checkpoint(final_checkpoint(tmp_path / "cut"), final_checkpoint(tmp_path / "whole"))
    assert_stages_equal(stage(again.usd_path), stage(whole.usd_path))


@pytest.mark.parametrize("name", ["tiny", "wave"])
def test_a_stop_between_frames_checkpoints_there_and_the_restart_continues(tmp_path, name):
    """A stop request inside frame 2 (after 5 one-step pieces) ends frames() there; finish() checkpoints that state,
    between two frames, and publishes frames 0 and 1; the restart goes on to frame 2 and ends in the uninterrupted
    run's state and stage."""
    whole = wd.build(scene_named(name), device="cpu", frames=3, out_dir=tmp_path / "whole")
    whole.run()
    per_frame = whole.summary.steps // 3

    sim = wd.build(scene_named(name), device="cpu", frames=3, out_dir=tmp_path / "cut")
    sim.piece_seconds = 0.0  # pieces of one step
    advance, pieces = sim.sim.advance, []

    def counting(*args, **kwargs):
        done = advance(*args, **kwargs)
        pieces.append(done)
        if len(pieces) == per_frame + 5:
            sim.request_stop()
        return done

    sim.sim.advance = counting
    assert [f.index for f in sim.frames()] == [0, 1]
    summary = sim.finish()
    assert set(pieces) == {1}
    assert summary.frame == 1 and summary.steps == per_frame + 5  # between frames 1 and 2
    assert summary.interrupted_by is None  # asked from Python, not by a signal
    assert frame_codes(sim.usd_path) == [0.0, 1.0]
    assert not list((tmp_path / "cut").glob("*.partial*"))

    again = wd.restart(summary.checkpoints[-1])
    assert [f.index for f in again.frames()] == [2, 3]
    assert_same_checkpoint(final_checkpoint(tmp_path / "cut"), final_checkpoint(tmp_path / "whole"))
    assert_stages_equal(stage(again.usd_path), stage(whole.usd_path))
    cut, ref = read_series(again.series_path), read_series(whole.series_path)
    assert sorted(cut) == sorted(ref)
    for column in ref:
        np.testing.assert_array_equal(cut[column], ref[column], err_msg=column)


def test_an_interrupt_that_cannot_wait_publishes_the_frames_written(tmp_path):
    """Ctrl-C inside a step (KeyboardInterrupt out of the stepper) in frame 3: RunInterrupted says what was kept; the
    stage holds frames 0..2 and is published; no checkpoint is written of the state it stopped in."""
    sim = wd.build(WAVE, device="cpu", frames=5, out_dir=tmp_path)
    advance = sim.sim.advance

    def interrupted(*args, **kwargs):
        if sim.step >= 2 * STEPS_PER_WAVE_FRAME:
            raise KeyboardInterrupt
        return advance(*args, **kwargs)

    sim.sim.advance = interrupted
    with pytest.raises(wd.RunInterrupted, match=r"3 frames published in .*wave_column\.usdc; no checkpoint"):
        sim.run()
    assert frame_codes(sim.usd_path) == [0.0, 1.0, 2.0]
    assert not list(tmp_path.glob("*.partial*")) and not (tmp_path / "checkpoints").exists()
    with pytest.raises(RuntimeError, match="the run has ended"):
        next(sim.frames())


def test_leaving_a_with_block_early_publishes_the_stage(tmp_path):
    with wd.build(tiny_scene(), device="cpu", frames=5, out_dir=tmp_path) as sim:
        for frame in sim.frames():
            if frame.index == 1:
                break
    assert stage(sim.usd_path).GetEndTimeCode() == 1.0 and sim.summary is not None
    assert read_checkpoint(sim.summary.checkpoints[-1])[1]["frame"] == 1


# ----------------------------------------------------------------------------------------------------------------
# Loads from Python


def test_a_load_halved_from_the_start_is_the_scene_with_half_the_peak(tmp_path):
    """½ × the scene's peak, set before the first step, against the scene written with that peak: the same run."""
    scaled = wd.build(WAVE, device="cpu", frames=2, out_dir=tmp_path / "scaled")
    scaled.set_load_scale(0, 0.5)
    assert scaled.load_scales == {"loads[0]": 0.5}
    scaled.run()
    scene = wd.load_scene(WAVE)
    scene.loads[0].history.peak *= 0.5
    written = wd.build(scene, device="cpu", frames=2, out_dir=tmp_path / "written")
    written.run()
    np.testing.assert_array_equal(scaled.array("node_u"), written.array("node_u"))
    assert scaled.summary.energy_end.load_work == written.summary.energy_end.load_work


def test_load_work_booked_is_the_work_of_the_scaled_forces(device, tmp_path):
    """wave_column stepped one step at a time, its blast scaled to ½ at step 6 and to 1.5 at step 11 (on the pulse's
    rise): the load work booked equals Σ ½ (f_n + f_{n+1})·Δu of the forces the loads applied (``node_f_load``), and
    differs from the unscaled run's; the books close."""
    sim = wd.build(WAVE, device=device, out_dir=tmp_path / "scaled")
    plain = wd.build(WAVE, device=device, out_dir=tmp_path / "plain")
    host_work = 0.0
    u = sim.array("node_u").astype(np.float64)
    f = sim.array("node_f_load").astype(np.float64)
    for step in range(1, 25):
        if step in (6, 11):
            sim.set_load_scale("loads[0]", 0.5 if step == 6 else 1.5)
        sim.sim.advance(1)
        plain.sim.advance(1)
        u_next = sim.array("node_u").astype(np.float64)
        f_next = sim.array("node_f_load").astype(np.float64)
        host_work += 0.5 * float(np.sum((f + f_next) * (u_next - u)))
        u, f = u_next, f_next
    booked = sim.sim.energy()
    assert host_work > 0.0
    np.testing.assert_allclose(booked.load_work, host_work, rtol=LOAD_WORK_RTOL)
    unscaled = plain.sim.energy().load_work
    assert abs(booked.load_work - unscaled) > 0.1 * unscaled
    start = sim.frame.energy.balance
    error = (booked.total - start.total) / max(booked.in_play, start.in_play)
    assert abs(error) <= MESH_BOUND


def test_load_scales_travel_with_the_checkpoint(tmp_path):
    """A blast scaled by ¾ at frame 1, checkpointed at frame 2, restarted: the restart keeps ¾ and ends where the
    uninterrupted run does."""
    whole = wd.build(WAVE, device="cpu", frames=3, out_dir=tmp_path / "whole")
    cut = wd.build(WAVE, device="cpu", frames=3, out_dir=tmp_path / "cut")
    for run in (whole, cut):
        for frame in run.frames():
            if frame.index == 1:
                run.set_load_scale(0, 0.75)
            if run is cut and frame.index == 2:
                run.checkpoint(tmp_path / "run.h5")
                break
    again = wd.restart(tmp_path / "run.h5")
    assert again.load_scales == {"loads[0]": 0.75}
    again.run()
    np.testing.assert_array_equal(again.node_positions(), whole.node_positions())


def test_set_load_scale_names_the_loads_there_are(tmp_path):
    data = tomllib.loads(WAVE.read_text())
    data["loads"].append(
        {"kind": "velocity", "region": {"box": {"lo": [-1, -1, 9.9], "hi": [2, 2, 10.1]}}, "velocity": [0, 0, 0]}
    )
    sim = wd.build(wd.parse_scene(data), device="cpu", frames=1, out_dir=tmp_path)
    with pytest.raises(ValueError, match=r"no pressure load 'blast'; pressure loads: loads\[0\]"):
        sim.set_load_scale("blast", 2.0)
    with pytest.raises(ValueError, match=r"no pressure load 1 \(loads\[1\] is a velocity load: only pressure and "):
        sim.set_load_scale(1, 2.0)
    with pytest.raises(ValueError, match="finite number >= 0"):
        sim.set_load_scale(0, -1.0)
    tiny = wd.build(tiny_scene(), device="cpu", frames=1, out_dir=tmp_path / "tiny")
    with pytest.raises(ValueError, match="pressure loads: none in this scene"):
        tiny.set_load_scale(0, 2.0)


# ----------------------------------------------------------------------------------------------------------------
# Errors and arrays


def test_an_invalid_edit_is_an_error_naming_the_key(tmp_path):
    scene = wd.load_scene(WAVE)
    scene.run.end_time = -1.0  # pydantic takes it; build() validates again
    with pytest.raises(wd.SceneError, match=r"wave_column\.toml: run\.end_time: Input should be greater than 0"):
        wd.build(scene, out_dir=tmp_path)
    scene.run.end_time = "soon"
    with pytest.raises(wd.SceneError, match=r"run\.end_time: Input should be a valid number"):
        wd.build(scene, out_dir=tmp_path)
    assert not tmp_path.joinpath("checkpoints").exists() and not list(tmp_path.glob("*.usd*"))


def test_arrays_by_name_view_or_copy_and_an_unknown_name_lists_them(device, tmp_path):
    sim = wd.build(tiny_scene(), device=device, frames=2, out_dir=tmp_path)
    q = sim.array("particle_q")
    wq = sim.warp_array("particle_q")
    assert q.shape == (wq.shape[0], 3) and wq.device == sim.model.device
    first = sim.positions()
    np.testing.assert_array_equal(first, q[:3])
    next(sim.frames())  # frame 0
    next(sim.frames())  # frame 1: the spheres fell
    if device == "cpu":
        assert q.ctypes.data == wq.ptr  # a view of the run's memory: it moved with the run
        np.testing.assert_array_equal(q[:3], sim.positions())
    else:
        np.testing.assert_array_equal(q[:3], first)  # a copy, as it was
    assert np.all(sim.positions()[:, 2] < first[:, 2]) and np.all(first == sim.array("particle_q_at_build")[:3])
    with pytest.raises(KeyError) as caught:
        sim.array("node_x")
    message = str(caught.value)
    assert message.startswith("no state or model array 'node_x' (did you mean node_")
    assert "state arrays: " in message and "particle_q" in message and "model arrays: " in message
    assert "particle_radius" in message


# ----------------------------------------------------------------------------------------------------------------
# What the summary calls ejecta


EJECTA_SCENE = """\
schema_version = 1
name = "slab_and_ball"
[run]
end_time = 1.0
output_rate = 200.0
[materials.rock]
density = 2400.0
youngs_modulus = 5.0e7
poisson_ratio = 0.2
[parts.slab]
material = "rock"
[parts.ball]
material = "rock"
[[particles]]
kind = "packing"
part = "slab"
region = { box = { lo = [0.0, 0.0, 0.0], hi = [0.04, 0.04, 0.02] } }
radius = 0.005
arrangement = "hcp"
[[particles]]
kind = "sphere"
part = "ball"
center = [0.02, 0.02, 0.5]
radius = 0.01
velocity = [3.0, 0.0, 0.0]
[[bonds]]
region = { box = { lo = [-0.01, -0.01, -0.01], hi = [0.05, 0.05, 0.03] } }
tensile_strength = 1.0e6
shear_strength = 2.0e6
material = "rock"
[[walls]]
kind = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "rock"
"""


def test_a_loose_impactor_is_not_ejecta(tmp_path):
    """A bonded slab on the ground and a ball flying far above it: two fragments, and nothing broken off (the ball
    was never part of anything that could break; the summary used to report its speed as ejecta)."""
    sim = wd.build(wd.parse_scene(tomllib.loads(EJECTA_SCENE)), device="cpu", frames=1, out_dir=tmp_path)
    summary = sim.run()
    assert summary.fragment_count == 2 and summary.bonds_broken == 0
    assert summary.ejecta_count == 0 and summary.ejecta_speed_max == 0.0
    assert "ejecta" not in summary.format()


def test_a_script_that_ends_without_finishing_leaves_its_stage_published(tmp_path):
    """A script leaves the loop at frame 2 and ends: at exit the stage is published with frames 0..2, no partial
    file is left."""
    code = (
        "import warpdem as wd\n"
        f"sim = wd.build({str(WAVE)!r}, device='cpu', frames=5, out_dir='out')\n"
        "for frame in sim.frames():\n"
        "    if frame.index == 2:\n"
        "        break\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr
    assert frame_codes(tmp_path / "out" / "wave_column.usdc") == [0.0, 1.0, 2.0]
    assert not list((tmp_path / "out").glob("*.partial*"))
