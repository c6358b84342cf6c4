"""Command line (warpdem/cli.py, ``python -m warpdem``): bad input ends with readable lines and exit status 2 before
any output is written; a good scene writes a USD stage and a checkpoint.

Oracles:
- bad input: exit status 2, the key path (or option) and a phrase saying what is wrong on stderr, no
  "Traceback", and no .usd*/.h5 file anywhere under the output directory or the working directory. Most cases
  call ``warpdem.cli.main`` in-process; a few run ``python -m warpdem`` to see the real exit status and stderr;
- good scene: the stage read back with pxr has one time sample per frame (codes 0..3), widths = 2 r, upAxis Z,
  metersPerUnit 1, timeCodesPerSecond = framesPerSecond = 1 / (substeps dt) = the scene's output rate, and its last
  sample equals the positions of the final checkpoint (both float32, exact).
"""

from __future__ import annotations

import json
import re
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom
from stage_compare import assert_stages_equal

from warpdem.cli import main
from warpdem.io.checkpoint import read_checkpoint, write_checkpoint

OUTPUT_RATE = 100.0  # [frames/s]
FPS_RTOL = 1e-12  # 1 / (substeps · dt) with dt = period / substeps: a few float64 roundings
RADII = (0.01, 0.012, 0.008)  # [m]
CENTERS = ((0.0, 0.0, 0.05), (0.05, 0.0, 0.05), (0.0, 0.05, 0.08))  # [m]

GOOD_SCENE = (
    f"""\
schema_version = 1
name = "tiny"
[run]
end_time = 1.0
output_rate = {OUTPUT_RATE}
[materials.rock]
density = 2500.0
youngs_modulus = 1.0e7
poisson_ratio = 0.3
[parts.grains]
material = "rock"
"""
    + "".join(
        f"""[[particles]]
kind = "sphere"
part = "grains"
center = [{c[0]}, {c[1]}, {c[2]}]
radius = {r}
"""
        for c, r in zip(CENTERS, RADII, strict=True)
    )
    + """[[walls]]
kind = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "rock"
"""
)


def edit(old: str, new: str, base: str = GOOD_SCENE) -> str:
    """The good scene with one exact substring replaced (asserting it is there, so a case cannot go stale)."""
    assert old in base, old
    return base.replace(old, new)


def with_file_source_text(path: str) -> str:
    """The good scene plus a 4th particle source (particles[3]) reading sphere centres from ``path``."""
    return GOOD_SCENE + f'[[particles]]\nkind = "file"\npart = "grains"\npath = "{path}"\nradius = 0.01\n'


def with_file_source(lines: str) -> Callable[[Path], list[str]]:
    """A case whose scene adds spheres from a particle file holding ``lines``."""

    def setup(inputs: Path) -> list[str]:
        (inputs / "spheres.txt").write_text(lines)
        return [str(scene_file(inputs, with_file_source_text("spheres.txt")))]

    return setup


def scene_file(inputs: Path, text: str) -> Path:
    path = inputs / "scene.toml"
    path.write_text(text)
    return path


def scene_text(text: str) -> Callable[[Path], list[str]]:
    return lambda inputs: [str(scene_file(inputs, text))]


def good_scene_with(*options: str) -> Callable[[Path], list[str]]:
    return lambda inputs: [str(scene_file(inputs, GOOD_SCENE)), *options]


def restart_from_foreign_checkpoint(inputs: Path) -> list[str]:
    # A valid warpdem checkpoint that belongs to another scene (bond capacity 7, this scene builds none).
    arrays = {"state/particle_q": np.zeros((3, 3), np.float32)}
    path = write_checkpoint(inputs / "foreign.ckpt", arrays, {"bond_capacity": 7, "num_walls": 1})
    return [str(scene_file(inputs, GOOD_SCENE)), "--restart", str(path)]


def restart_from_checkpoint_of_another_scene(inputs: Path) -> list[str]:
    # A checkpoint that names its scene ("slab"): refused, naming both, before anything else is looked at.
    arrays = {"state/particle_q": np.zeros((3, 3), np.float32)}
    path = write_checkpoint(inputs / "slab.h5", arrays, {"scene": "slab", "bond_capacity": 0, "num_walls": 1})
    return [str(scene_file(inputs, GOOD_SCENE)), "--restart", str(path)]


def restart_from_text_file(inputs: Path) -> list[str]:
    (inputs / "notes.txt").write_text("not a checkpoint\n")
    return [str(scene_file(inputs, GOOD_SCENE)), "--restart", str(inputs / "notes.txt")]


# (id, argv builder (gets the input folder), phrases expected on stderr: key path / option first, then the problem)
BAD_INPUTS = [
    (
        "unknown_key",
        scene_text(edit("end_time = 1.0", "end_time = 1.0\nendtime = 2.0")),
        ["run.endtime", "unknown key"],
    ),
    (
        "negative_density",
        scene_text(edit("density = 2500.0", "density = -2500.0")),
        ["materials.rock.density", "greater than 0"],
    ),
    (
        "poisson_half",
        scene_text(edit("poisson_ratio = 0.3", "poisson_ratio = 0.5")),
        ["materials.rock.poisson_ratio", "< 0.5"],
    ),
    (
        "unknown_material",
        scene_text(edit('[parts.grains]\nmaterial = "rock"', '[parts.grains]\nmaterial = "granite"')),
        ["parts.grains.material", "unknown material 'granite'"],
    ),
    ("missing_scene_file", lambda inputs: [str(inputs / "absent.toml")], ["absent.toml", "file not found"]),
    ("malformed_toml", scene_text(GOOD_SCENE + "[run\n"), ["scene.toml", "invalid TOML"]),
    ("particle_file_two_columns", with_file_source("0.0 0.1\n0.2 0.3\n"), ["particles[3].path", "2 columns"]),
    ("particle_file_not_numbers", with_file_source("0.0 0.1 abc\n"), ["particles[3].path", "cannot read"]),
    (
        "particle_file_missing",
        lambda inputs: [str(scene_file(inputs, with_file_source_text("absent.txt")))],
        ["particles[3].path", "file not found"],
    ),
    (
        "bond_region_empty",
        scene_text(
            GOOD_SCENE + "[[bonds]]\nregion = { box = { lo = [1.0, 1.0, 1.0], hi = [2.0, 2.0, 2.0] } }\n"
            'material = "rock"\ntensile_strength = 1.0e5\nshear_strength = 1.0e5\n'
        ),
        ["bonds[0].region", "contains 0 sphere"],
    ),
    (
        "initial_overlap",  # a 4th sphere half a radius deep in the first (r = 0.01 m, centres 0.015 m apart)
        scene_text(
            GOOD_SCENE + '[[particles]]\nkind = "sphere"\npart = "grains"\ncenter = [0.015, 0.0, 0.05]\nradius = 0.01\n'
        ),
        ["scene.toml: run.allow_initial_overlap", "1 sphere pair(s) overlap, the worst by 50 %"],
    ),
    ("usd_suffix", good_scene_with("--usd", "run.txt"), ["--usd", "allowed suffixes"]),
    ("restart_missing", good_scene_with("--restart", "absent.h5"), ["--restart", "file not found"]),
    ("restart_not_hdf5", restart_from_text_file, ["notes.txt", "not an HDF5 file"]),
    ("restart_other_scene", restart_from_foreign_checkpoint, ["bond_capacity", "wrong scene"]),
    ("restart_named_scene", restart_from_checkpoint_of_another_scene, ["belongs to scene 'slab', not 'tiny'"]),
    ("device_absent", good_scene_with("--device", "cuda:7"), ["cuda:7", "not available"]),
    ("frames_zero", good_scene_with("--frames", "0"), ["--frames", "must be a positive integer"]),
    # Numbers valid in float64 that the device's float32 turns into inf or 0 (warpdem.limits).
    (
        "modulus_beyond_float32",
        scene_text(edit("youngs_modulus = 1.0e7", "youngs_modulus = 1.0e39")),
        ["materials.rock.youngs_modulus", "float32"],
    ),
    (
        "density_1e300",
        scene_text(edit("density = 2500.0", "density = 1.0e300")),
        ["materials.rock.density", "float32"],
    ),
    (
        "density_1e-300",
        scene_text(edit("density = 2500.0", "density = 1.0e-300")),
        ["materials.rock.density", "float32"],
    ),
    (
        "gravity_huge",
        scene_text(GOOD_SCENE + "[gravity]\nvector = [0.0, 0.0, -1.0e7]\n"),
        ["gravity.vector", "<= 1e+06"],
    ),
    # Sizes estimated before anything is packed or allocated.
    (
        "packing_exabytes",
        scene_text(
            GOOD_SCENE + '[[particles]]\nkind = "packing"\npart = "grains"\nradius = 1.0e-9\n'
            "region = { box = { lo = [0.0, 0.0, 0.0], hi = [1.0, 1.0, 1.0] } }\n"
        ),
        ["particles[3].radius", "would need", "spheres"],
    ),
    (
        "capacity_2_pow_40",
        scene_text(GOOD_SCENE + "[capacity]\nparticles = 1099511627776\n"),
        ["capacity.particles", "would need"],
    ),
    # dt = 1e-12 asks for 1e12 steps: refused before the first step instead of building a list of step indices.
    ("dt_1e-12", scene_text(edit("end_time = 1.0", "end_time = 1.0\ndt = 1.0e-12")), ["run.dt", "would need"]),
    ("name_with_nul", scene_text('name = "a\\u0000b"\n' + edit('name = "tiny"\n', "")), ["name", "control characters"]),
    (
        "usd_name_too_long",
        scene_text(GOOD_SCENE + f'[output]\nusd = "{"x" * 300}.usdc"\n'),
        ["output.usd", "305 bytes long"],
    ),
    # A sphere source given twice: coincident bonded spheres would have an infinite bond stiffness and dt = 0.
    (
        "coincident_bonded_spheres",
        scene_text(
            GOOD_SCENE + '[[particles]]\nkind = "sphere"\npart = "grains"\ncenter = [0.0, 0.0, 0.05]\nradius = 0.01\n'
            '[[bonds]]\nregion = { box = { lo = [-0.1, -0.1, 0.0], hi = [0.1, 0.1, 0.1] } }\nmaterial = "rock"\n'
            "tensile_strength = 1.0e5\nshear_strength = 1.0e5\n"
        ),
        ["bonds[0].region", "same centre"],
    ),
]
# These run as `python -m warpdem` subprocesses (real exit status and stderr); the rest call main() in-process.
SUBPROCESS_CASES = {"malformed_toml", "negative_density", "particle_file_two_columns", "usd_suffix"}


def matching_line(stderr: str, phrases: list[str]) -> str | None:
    """The first line of stderr holding every phrase (key path and problem on one line), or None."""
    return next((line for line in stderr.splitlines() if all(p in line for p in phrases)), None)


def output_files(*folders: Path) -> list[Path]:
    """USD stages (final or partial) and HDF5 files under the given folders."""
    found = []
    for folder in folders:
        if folder.exists():
            found += [p for p in folder.rglob("*") if p.is_file() and (".usd" in p.name or p.suffix == ".h5")]
    return found


@pytest.fixture
def folders(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Path, Path]:
    """(inputs, out, working directory): the scene's default output folder "out" would land in the last."""
    inputs, out, cwd = tmp_path / "in", tmp_path / "out", tmp_path / "cwd"
    inputs.mkdir()
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    return inputs, out, cwd


def full_argv(args: list[str], out: Path, device: str | None = None) -> list[str]:
    """A case's arguments plus --out, --quiet, and --frames 2 / --device unless the case sets them."""
    argv = [*args, "--out", str(out), "--quiet"]
    if "--frames" not in args:
        argv += ["--frames", "2"]
    if device is not None and "--device" not in args:
        argv += ["--device", device]
    return argv


@pytest.mark.parametrize(
    ("case", "make_argv", "phrases"),
    [pytest.param(c, a, p, id=c) for c, a, p in BAD_INPUTS if c not in SUBPROCESS_CASES],
)
def test_bad_input_in_process(device, folders, capsys, case, make_argv, phrases):
    inputs, out, cwd = folders
    argv = full_argv(make_argv(inputs), out, device)
    try:
        status = main(argv)
    except SystemExit as exc:  # argparse reports option errors by exiting
        status = exc.code
    captured = capsys.readouterr()
    assert status == 2, captured.err
    assert matching_line(captured.err, phrases), f"expected {phrases} in one line:\n{captured.err}"
    assert captured.out == ""
    assert output_files(out, cwd) == []


@pytest.mark.parametrize(
    ("case", "make_argv", "phrases"),
    [pytest.param(c, a, p, id=c) for c, a, p in BAD_INPUTS if c in SUBPROCESS_CASES],
)
def test_bad_input_subprocess(folders, case, make_argv, phrases):
    inputs, out, cwd = folders
    argv = full_argv(make_argv(inputs), out)
    result = subprocess.run(
        [sys.executable, "-m", "warpdem", *argv], capture_output=True, text=True, cwd=cwd, timeout=120
    )
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    line = matching_line(result.stderr, phrases)
    assert line is not None, f"expected {phrases} in one line:\n{result.stderr}"
    assert line.startswith("error: ")
    assert output_files(out, cwd) == []


def test_good_scene_writes_usd_and_checkpoint(device, folders, capsys):
    inputs, out, _ = folders
    frames = 3
    scene = scene_file(inputs, GOOD_SCENE)
    status = main([str(scene), "--out", str(out), "--frames", str(frames), "--quiet", "--device", device])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert captured.out == ""  # --quiet: no summary

    usd_path = out / "tiny.usdc"
    assert usd_path.is_file()
    assert [p.name for p in output_files(out) if ".partial" in p.name] == []
    stage = Usd.Stage.Open(str(usd_path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    checkpoints = sorted((out / "checkpoints").glob("*.h5"))
    assert len(checkpoints) == 1
    arrays, attrs = read_checkpoint(checkpoints[0])
    substeps, dt = int(attrs["substeps"]), float(attrs["dt"])
    assert attrs["frame"] == frames and attrs["step"] == frames * substeps
    assert checkpoints[0].name == f"tiny_checkpoint_{frames * substeps:010d}.h5"  # named by scene and step
    np.testing.assert_allclose(stage.GetTimeCodesPerSecond(), 1.0 / (substeps * dt), rtol=FPS_RTOL)
    np.testing.assert_allclose(stage.GetTimeCodesPerSecond(), OUTPUT_RATE, rtol=FPS_RTOL)
    assert stage.GetFramesPerSecond() == stage.GetTimeCodesPerSecond()
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, float(frames))

    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles"))
    assert points.GetPointsAttr().GetTimeSamples() == [float(c) for c in range(frames + 1)]
    ids = np.asarray(points.GetIdsAttr().Get(0.0))
    np.testing.assert_array_equal(np.sort(ids), np.arange(len(RADII)))  # ids are the creation order
    for code in range(frames + 1):
        widths = np.asarray(points.GetWidthsAttr().Get(float(code)))
        np.testing.assert_array_equal(widths, (2.0 * np.asarray(RADII, np.float32))[ids])
    start = np.asarray(points.GetPointsAttr().Get(0.0))
    np.testing.assert_array_equal(start, np.asarray(CENTERS, np.float32)[ids])
    n = int(arrays["state/particle_count"][0])
    end = np.asarray(points.GetPointsAttr().Get(float(frames)))
    np.testing.assert_array_equal(end, arrays["state/particle_q"][:n].astype(np.float32))  # USD points: float32
    assert np.all(end[:, 2] < start[:, 2])  # they fell under gravity


def test_quiet_run_prints_nothing(folders):
    """``--quiet``: a good run prints nothing at all, on stdout or stderr (no Warp banner, no "no CUDA driver" line
    on a CPU-only machine, no progress bar, no summary)."""
    inputs, out, cwd = folders
    scene = scene_file(inputs, GOOD_SCENE)
    result = subprocess.run(
        [sys.executable, "-m", "warpdem", str(scene), "--out", str(out), "--frames", "1", "--quiet"],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert (result.stdout, result.stderr) == ("", "")
    assert (out / "tiny.usdc").is_file()


def test_warp_start_drops_only_the_missing_driver_line(monkeypatch, capfd):
    """The start-up filter drops the native library's "no CUDA driver" line and passes on everything else it writes
    to file descriptor 2 (a real error must still show)."""
    import os

    import warp as wp

    from warpdem.api import CUDA_DRIVER_MISSING
    from warpdem.cli import init_warp

    real_error = "Warp CUDA error: Failed to get function cuGetProcAddress\n"

    def start_without_driver() -> None:  # what the native wp_init writes on a CPU-only machine, plus an error
        os.write(2, f"{CUDA_DRIVER_MISSING}. GPU execution will not be available.\n".encode())
        os.write(2, real_error.encode())

    monkeypatch.setattr(wp.config, "log_level", wp.config.log_level)  # restored after the test
    monkeypatch.setattr(wp, "init", start_without_driver)
    init_warp()
    assert capfd.readouterr().err == real_error


def test_bench_help():
    result = subprocess.run(
        [sys.executable, "-m", "warpdem", "bench", "--help"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert "usage" in result.stdout and "Traceback" not in result.stderr
    assert "bench tets" in result.stdout


def test_tet_bench_runs_the_kuhn_block(tmp_path):
    """``bench tets`` times a Kuhn-tet cube of about the requested size: n = round((600 / 6)^(1/3)) = 5 cells a side,
    6 n³ = 750 tets on (n + 1)³ = 216 nodes, and the vibrating block's energy stays finite. (Speed is not asserted:
    it belongs to the benchmark's own report.)"""
    out = tmp_path / "tets.json"
    assert main(["bench", "tets", "--sizes", "600", "--steps", "5", "--repeat", "1", "--json", str(out)]) == 0
    (row,) = json.loads(out.read_text())
    assert (row["tets"], row["nodes"], row["steps"]) == (750, 216, 5)
    assert row["finite"] and row["tet_steps_per_second"] > 0.0 and row["bytes_per_tet"] > 0.0


# ----------------------------------------------------------------------------------------------------------------
# Restart, interruption, end time (oracle: the uninterrupted run, bit for bit on the CPU; the stage sample by sample)


def tiny_run(out: Path, *options: str, scene: str = GOOD_SCENE, inputs: Path | None = None) -> int:
    """Runs the good scene (or ``scene``) into ``out``; returns the exit status."""
    inputs = inputs if inputs is not None else out.parent / "in"
    inputs.mkdir(exist_ok=True)
    return main([str(scene_file(inputs, scene)), "--out", str(out), "--quiet", "--device", "cpu", *options])


def final_checkpoint(out: Path) -> Path:
    return max((out / "checkpoints").glob("*.h5"))


def assert_same_run(out: Path, reference: Path) -> None:
    """The final checkpoint and the stage under ``out`` equal those of the uninterrupted run under ``reference``."""
    a, a_attrs = read_checkpoint(final_checkpoint(out))
    b, b_attrs = read_checkpoint(final_checkpoint(reference))
    assert sorted(a) == sorted(b)
    for key in sorted(a):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert (a_attrs["step"], a_attrs["time"], a_attrs["frame"]) == (b_attrs["step"], b_attrs["time"], b_attrs["frame"])
    assert_stages_equal(Usd.Stage.Open(str(out / "tiny.usdc")), Usd.Stage.Open(str(reference / "tiny.usdc")))


def test_restart_from_the_final_checkpoint_has_nothing_to_do_and_a_longer_end_continues(tmp_path, capsys):
    out, reference = tmp_path / "out", tmp_path / "reference"
    assert tiny_run(out, "--frames", "2") == 0
    assert tiny_run(reference, "--frames", "4") == 0
    final = final_checkpoint(out)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()

    assert tiny_run(out, "--frames", "2", "--restart", str(final)) == 0
    said = capsys.readouterr().out
    assert said.startswith("nothing to do: the checkpoint is at t = 0.02 s (frame 2), the run ends at t = 0.02 s")
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before  # nothing written or touched

    # A later end continues the same run and the same stage: frames 0..4 in one file, as if never stopped.
    assert tiny_run(out, "--frames", "4", "--restart", str(final)) == 0
    assert_same_run(out, reference)
    assert sorted(p.name for p in out.glob("*.usd*")) == ["tiny.usdc"]


def test_restart_refuses_to_extend_the_stage_of_another_run(tmp_path, capsys):
    """The stage at the restart's path was written by another run (same name and timing, one sphere 1 cm higher):
    exit 2 naming it, and the stage is left as it was."""
    out = tmp_path / "out"
    assert tiny_run(out, "--frames", "2", "--checkpoint-every", "0.01") == 0
    middle = min((out / "checkpoints").glob("*.h5"))
    other = edit("center = [0.0, 0.0, 0.05]", "center = [0.0, 0.0, 0.06]")
    stage = out / "tiny.usdc"
    other_run = ["--frames", "2", "--usd", str(stage)]
    assert tiny_run(tmp_path / "other", *other_run, scene=other, inputs=tmp_path / "in_other") == 0
    before = stage.read_bytes()
    capsys.readouterr()
    assert tiny_run(out, "--frames", "2", "--restart", str(middle)) == 2
    err = capsys.readouterr().err
    assert f"error: --restart: {stage} is not the stage of this checkpoint's run" in err
    assert "other sphere positions" in err
    assert stage.read_bytes() == before
    assert not list(out.glob("*.partial*"))


def test_two_scenes_share_an_output_folder(tmp_path):
    out = tmp_path / "out"
    assert tiny_run(out, "--frames", "1") == 0
    assert tiny_run(out, "--frames", "1", scene=edit('name = "tiny"', 'name = "tiny2"'), inputs=tmp_path / "in2") == 0
    names = sorted(p.name.split("_checkpoint_")[0] for p in (out / "checkpoints").glob("*.h5"))
    assert names == ["tiny", "tiny2"]  # same step numbers, two files
    for path in (out / "checkpoints").glob("*.h5"):
        assert read_checkpoint(path)[1]["scene"] == path.name.split("_checkpoint_")[0]


def test_end_time_between_frames_ends_with_a_short_frame(tmp_path, capsys):
    """2.5 frames of 1/100 s: frames 1 and 2 are whole, frame 3 is the half frame that ends at the time asked (to
    the nearest step: within dt/2, plus float64 round-off of the clock)."""
    out = tmp_path / "out"
    end_time = 0.025
    status = main(
        [str(scene_file(tmp_path, GOOD_SCENE)), "--out", str(out), "--device", "cpu", "--end-time", str(end_time)]
    )
    said = capsys.readouterr().out
    assert status == 0
    assert "end time 0.025 s is not a whole number of frames of 1/100 s: the last frame (3) will be short" in said
    _, attrs = read_checkpoint(final_checkpoint(out))
    substeps, dt = int(attrs["substeps"]), float(attrs["dt"])
    assert attrs["frame"] == 3 and attrs["step"] == round(end_time / dt)
    assert abs(attrs["time"] - end_time) <= 0.5 * dt + 1e-12
    assert 2 * substeps < attrs["step"] < 3 * substeps
    stage = Usd.Stage.Open(str(out / "tiny.usdc"))
    assert stage.GetEndTimeCode() == 3.0
    assert stage.GetPrimAtPath("/World").GetAttribute("warpdem:time").Get(3.0) == attrs["time"]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_checkpoints_publishes_and_the_resume_command_continues(tmp_path, signum):
    """A signal after the first frame: the run stops within a piece of steps (between two frames, or at one) with a
    checkpoint of that state and the frames so far published, exits 128 + signal, and the printed command resumes it
    into the uninterrupted run."""
    inputs, out, reference = tmp_path / "in", tmp_path / "out", tmp_path / "reference"
    inputs.mkdir()
    scene = scene_file(inputs, GOOD_SCENE)
    # Far more frames than run before the signal lands; a checkpoint every frame shows when frame 1 is done.
    argv = [str(scene), "--out", str(out), "--device", "cpu", "--frames", "100000", "--checkpoint-every", "0.01"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "warpdem", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        deadline = time.monotonic() + 300.0
        while not list((out / "checkpoints").glob("tiny_checkpoint_*.h5")) and proc.poll() is None:
            assert time.monotonic() < deadline, "no frame was written within 300 s"
            time.sleep(0.05)
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signum, err
    line = next(line for line in err.splitlines() if line.startswith("interrupted at t = "))
    frame = int(re.search(r", after frame (\d+)\); resume with: ", line).group(1))
    command = shlex.split(line.split("resume with: ")[1])
    assert command[:3] == ["python", "-m", "warpdem"] and "Traceback" not in err
    checkpoint = Path(command[command.index("--restart") + 1])
    assert read_checkpoint(checkpoint)[1]["frame"] == frame >= 1
    stage = Usd.Stage.Open(str(out / "tiny.usdc"))  # published: frames 0..frame
    assert stage.GetPrimAtPath("/World/Particles").GetAttribute("points").GetTimeSamples() == [
        float(c) for c in range(frame + 1)
    ]
    del stage

    # Resume (to two frames past the interruption, not 100000), and compare with a run never interrupted.
    resume = command[3:]
    resume[resume.index("--frames") + 1] = str(frame + 2)
    assert main([*resume, "--quiet"]) == 0
    assert main([str(scene), "--out", str(reference), "--device", "cpu", "--frames", str(frame + 2), "--quiet"]) == 0
    assert_same_run(out, reference)


def test_a_second_interrupt_publishes_the_frames_written(tmp_path, capsys, monkeypatch):
    """Ctrl-C that cannot wait (KeyboardInterrupt out of a step in frame 3): exit 130, one line saying that frames 0..2
    are published in the stage and no checkpoint was written of that state; the stage is there, with those frames."""
    from warpdem.simulation import Simulation

    advance = Simulation.advance

    def interrupted(self, n_steps, stop_at_switch=False):
        if self.time > 0.02 - 1e-9:  # frame 3 of 1/100 s
            raise KeyboardInterrupt
        return advance(self, n_steps, stop_at_switch)

    monkeypatch.setattr(Simulation, "advance", interrupted)
    out = tmp_path / "out"
    assert tiny_run(out, "--frames", "5") == 130
    err = capsys.readouterr().err
    assert err.startswith(f"interrupted at once: 3 frames published in {(out / 'tiny.usdc').resolve()}; no checkpoint")
    assert len(err.splitlines()) == 1
    stage = Usd.Stage.Open(str(out / "tiny.usdc"))
    assert stage.GetPrimAtPath("/World/Particles").GetAttribute("points").GetTimeSamples() == [0.0, 1.0, 2.0]
    assert not list(out.glob("*.partial*")) and not (out / "checkpoints").exists()


def test_frames_and_end_time_together_say_which_wins(tmp_path, capsys):
    out = tmp_path / "out"
    scene = scene_file(tmp_path, GOOD_SCENE)
    assert main([str(scene), "--out", str(out), "--device", "cpu", "--frames", "2", "--end-time", "0.5"]) == 0
    said = capsys.readouterr().out
    assert said.startswith("note: --frames 2 wins over --end-time 0.5: the run ends with frame 2")
    assert read_checkpoint(final_checkpoint(out))[1]["frame"] == 2


def test_summary_json_carries_the_compile_time_and_the_ejecta_count(tmp_path, capsys):
    """The summary's kernel compile time is its own field, left out of the wall time; the ejecta are counted."""
    out = tmp_path / "out"
    summary = tmp_path / "summary.json"
    assert tiny_run(out, "--frames", "1", "--summary-json", str(summary)) == 0
    data = json.loads(summary.read_text())
    assert data["compile_time"] >= 0.0 and data["wall_time"] > 0.0
    assert data["ejecta_count"] == 0 and data["fragment_count"] == 0  # three loose spheres: nothing to break


def test_summary_quotes_the_time_step_and_what_sets_the_critical_one(tmp_path, capsys):
    """Issue 30: the summary says the step and the critical step with its source, and the JSON carries both."""
    out, inputs = tmp_path / "out", tmp_path / "in"
    inputs.mkdir()
    summary = tmp_path / "summary.json"
    argv = [str(scene_file(inputs, GOOD_SCENE)), "--out", str(out), "--device", "cpu", "--frames", "1"]
    assert main([*argv, "--summary-json", str(summary)]) == 0
    data = json.loads(summary.read_text())
    assert 0.0 < data["time_step"] <= data["critical_dt"] and data["critical_dt_source"]
    printed = capsys.readouterr().out
    line = next(x for x in printed.splitlines() if x.startswith("time step "))
    assert f"set by {data['critical_dt_source']}" in line
