"""Fault injection (issue 29): a run killed (SIGKILL) or stopped by two Ctrl-C at any point, then resumed as its user
would, leaves every output exactly as the uninterrupted run does.

The run is tests/test_timeseries.py's struck bonded bar (bonds break in the first frames, so the fragment record
changes), with its VTU series, checkpointed every CHECKPOINT_FRAMES frames. A fault-free run through the wrapper
(tests/fault_run.py) counts the points where a fault can land: frames written, stage saves, checkpoints and files
moved over their final names. Each case fires one fault at one of them — just before or just after it — chosen with a
seeded generator so that each event and phase is hit and the set is the same on every run. The resume is what the
README tells a user: the newest checkpoint under ``--restart`` (none: the run again from the start).

Oracle: CPU runs and restarts are bit for bit (tests/test_api.py, test_cli.py), so the resumed outputs equal the
uninterrupted run's exactly: the USD stage sample by sample (tests/stage_compare.py), the time series and the fragment
record value by value, every VTU file byte by byte, the final checkpoint's arrays and position on the timeline; and no
temporary file is left.
"""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from pxr import Usd
from stage_compare import assert_stages_equal
from test_timeseries import SPHERE_SCENE

from warpdem.cli import main
from warpdem.io.checkpoint import latest_checkpoint, read_checkpoint
from warpdem.io.timeseries import read_series
from warpdem.stages.fragments import read_fragments

FRAMES = 6
OUTPUT_RATE = 200.0  # [frames/s], the scene's
CHECKPOINT_FRAMES = 2
EVENTS = ("frame", "stage_save", "checkpoint", "replace")
SEED = 29
WRAPPER = Path(__file__).resolve().parent / "fault_run.py"


def scene_file(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "struck_bar.toml"
    path.write_text(tomli_w.dumps(SPHERE_SCENE))
    return path


def argv(scene: Path, out: Path) -> list[str]:
    every = CHECKPOINT_FRAMES / OUTPUT_RATE
    return [str(scene), "--out", str(out), "--device", "cpu", "--frames", str(FRAMES), "--checkpoint-every", f"{every}"]


def wrapped(
    args: list[str], event: str, index: int, phase: str, fault: str, counts: Path, quiet: bool = True
) -> subprocess.CompletedProcess:
    """Runs the CLI in a subprocess with the fault injected (its exit status negative: killed)."""
    command = [sys.executable, str(WRAPPER), event, str(index), phase, fault, str(counts), "--", *args]
    command += ["--quiet"] if quiet else []
    return subprocess.run(command, capture_output=True, text=True, timeout=600, check=False)


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, dict[str, int]]:
    """The uninterrupted run (through the wrapper, no fault) and how many times each event happened in it."""
    root = tmp_path_factory.mktemp("reference")
    out = root / "out"
    counts = root / "counts.json"
    assert wrapped(argv(scene_file(root / "in"), out), "frame", 0, "before", "kill", counts).returncode == 0
    return out, json.loads(counts.read_text())


def cases() -> list[tuple[str, str, str, float]]:
    """(fault, event, phase, where): every event and phase with a kill, and three double Ctrl-C, at a seeded place
    ``where`` in [0, 1) along the event's occurrences; the last stage publish (the rename after the last frame) is
    always among them."""
    rng = random.Random(SEED)
    out = [("kill", event, phase, rng.random()) for event in EVENTS for phase in ("before", "after")]
    out.append(("kill", "replace", "before", 1.0))  # the stage's publish is the run's last rename
    out += [("sigint2", rng.choice(EVENTS), rng.choice(("before", "after")), rng.random()) for _ in range(3)]
    return out


def resume_argv(scene: Path, out: Path) -> list[str]:
    """The user's resume: the newest checkpoint, the same command (none: the run again from the start)."""
    checkpoint = latest_checkpoint(out / "checkpoints", "struck_bar")
    return [*argv(scene, out), *(["--restart", str(checkpoint)] if checkpoint is not None else [])]


def outputs(out: Path) -> dict[str, object]:
    """Everything a run leaves, in comparable form."""
    arrays, attrs = read_checkpoint(max((out / "checkpoints").glob("*.h5")))
    fragments = read_fragments(out / "struck_bar_fragments.h5")
    return {
        "checkpoint": (arrays, {k: attrs[k] for k in ("step", "time", "frame")}),
        "series": read_series(out / "struck_bar_series.csv"),
        "fragments": [fragments.frame, fragments.count, *fragments.masses, *fragments.speeds],
        "vtu": {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*.vt*")) if p.suffix in (".vtu", ".pvd")},
    }


@pytest.mark.parametrize("fault, event, phase, where", cases(), ids=lambda v: f"{v:.2f}" if isinstance(v, float) else v)
def test_resume_after_a_fault_equals_the_uninterrupted_run(reference, tmp_path, fault, event, phase, where):
    ref_out, counts = reference
    index = min(counts[event], 1 + int(where * counts[event]))
    scene = scene_file(tmp_path / "in")
    out = tmp_path / "out"
    status = wrapped(argv(scene, out), event, index, phase, fault, tmp_path / "counts.json").returncode
    stopped = {"kill": -signal.SIGKILL, "sigint2": 128 + signal.SIGINT}[fault]
    # A fault after the last event of the run may find it complete (exit 0); otherwise it stopped it.
    assert status in (stopped, 0), status

    assert main([*resume_argv(scene, out), "--quiet"]) == 0
    assert_same_outputs(out, ref_out)


def test_a_resume_killed_in_turn_is_resumed_again(reference, tmp_path):
    """Killed after the second stage save, its resume killed after writing its second frame (the partial stage it
    continues then holds frames of both runs), resumed again: the outputs are still the uninterrupted run's."""
    ref_out, _ = reference
    scene = scene_file(tmp_path / "in")
    out = tmp_path / "out"
    counts = tmp_path / "counts.json"
    assert wrapped(argv(scene, out), "stage_save", 3, "after", "kill", counts).returncode == -signal.SIGKILL
    assert wrapped(resume_argv(scene, out), "frame", 2, "after", "kill", counts).returncode == -signal.SIGKILL
    assert main([*resume_argv(scene, out), "--quiet"]) == 0
    assert_same_outputs(out, ref_out)


def assert_same_outputs(out: Path, ref_out: Path) -> None:
    """Every output under ``out`` equals the uninterrupted run's under ``ref_out`` (module docstring), and no
    temporary file is left."""
    assert_stages_equal(Usd.Stage.Open(str(out / "struck_bar.usdc")), Usd.Stage.Open(str(ref_out / "struck_bar.usdc")))
    got, want = outputs(out), outputs(ref_out)
    arrays, position = got["checkpoint"]
    ref_arrays, ref_position = want["checkpoint"]
    assert position == ref_position
    assert sorted(arrays) == sorted(ref_arrays)
    for key in ref_arrays:
        np.testing.assert_array_equal(arrays[key], ref_arrays[key], err_msg=key)
    assert sorted(got["series"]) == sorted(want["series"])
    for column, values in want["series"].items():
        np.testing.assert_array_equal(got["series"][column], values, err_msg=column)
    assert len(got["fragments"]) == len(want["fragments"])
    for a, b in zip(got["fragments"], want["fragments"], strict=True):
        np.testing.assert_array_equal(a, b)
    assert got["vtu"].keys() == want["vtu"].keys()
    for name, data in want["vtu"].items():
        assert got["vtu"][name] == data, name
    assert not [p for p in out.rglob("*") if ".partial" in p.name or ".tmp" in p.name]


def test_a_signal_during_the_last_frame_finds_the_run_finished(reference, tmp_path):
    """SIGINT while the last frame is written (its steps done): the run is complete, so it exits 0, says so, and
    leaves the uninterrupted run's stage — not "interrupted" with a resume that has nothing to do."""
    ref_out, counts = reference
    out = tmp_path / "out"
    last = counts["frame"]
    done = wrapped(
        argv(scene_file(tmp_path / "in"), out), "frame", last, "before", "sigint", tmp_path / "c", quiet=False
    )
    assert done.returncode == 0, done.stderr
    assert "the run finished: the stop came during its last frame" in done.stderr
    assert "interrupted" not in done.stderr
    assert_stages_equal(Usd.Stage.Open(str(out / "struck_bar.usdc")), Usd.Stage.Open(str(ref_out / "struck_bar.usdc")))
