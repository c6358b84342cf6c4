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
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpdem.checkpoint import read_checkpoint, write_checkpoint
from warpdem.cli import main

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
    ("usd_suffix", good_scene_with("--usd", "run.txt"), ["--usd", "allowed suffixes"]),
    ("restart_missing", good_scene_with("--restart", "absent.h5"), ["--restart", "file not found"]),
    ("restart_not_hdf5", restart_from_text_file, ["notes.txt", "not an HDF5 file"]),
    ("restart_other_scene", restart_from_foreign_checkpoint, ["bond_capacity", "wrong scene"]),
    ("device_absent", good_scene_with("--device", "cuda:7"), ["cuda:7", "not available"]),
    ("frames_zero", good_scene_with("--frames", "0"), ["--frames", "must be a positive integer"]),
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
    checkpoints = sorted((out / "checkpoints").glob("checkpoint_*.h5"))
    assert len(checkpoints) == 1
    arrays, attrs = read_checkpoint(checkpoints[0])
    substeps, dt = int(attrs["substeps"]), float(attrs["dt"])
    assert attrs["frame"] == frames and attrs["step"] == frames * substeps
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


def test_bench_help():
    result = subprocess.run(
        [sys.executable, "-m", "warpdem", "bench", "--help"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert "usage" in result.stdout and "Traceback" not in result.stderr


def test_tet_bench_runs_the_kuhn_block(tmp_path):
    """``bench tets`` times a Kuhn-tet cube of about the requested size: n = round((600 / 6)^(1/3)) = 5 cells a side,
    6 n³ = 750 tets on (n + 1)³ = 216 nodes, and the vibrating block's energy stays finite. (Speed is not asserted:
    it belongs to the benchmark's own report.)"""
    out = tmp_path / "tets.json"
    assert main(["bench", "tets", "--sizes", "600", "--steps", "5", "--repeat", "1", "--json", str(out)]) == 0
    (row,) = json.loads(out.read_text())
    assert (row["tets"], row["nodes"], row["steps"]) == (750, 216, 5)
    assert row["finite"] and row["tet_steps_per_second"] > 0.0 and row["bytes_per_tet"] > 0.0
