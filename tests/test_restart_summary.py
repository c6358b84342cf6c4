"""A restarted run's summary equals the uninterrupted run's, every field (issue 29): the rigid report, the fracture and
conversion counts, the energy books from the timeline's first frame, the fragments.

Oracle: CPU restarts are bit for bit (tests/test_api.py), and the summary is a function of the final state and of the
timeline's first frame, both of which the checkpoint holds; so ``--summary-json`` of a run restarted from a checkpoint
in its middle equals that of the run never stopped, field by field — all but the wall-clock measures (wall time, the
rates made of it, kernel compiling) and the list of checkpoints, of which the restart wrote only its own (the last,
the one a later restart uses, is the same file name).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from warpdem.io.checkpoint import read_checkpoint_attrs
from warpdem.runner import RunOptions, run_scene, summary_json
from warpdem.scene import load_scene

SCENES = Path(__file__).resolve().parent.parent / "scenes"
CLOCK_FIELDS = {"wall_time", "particle_steps_per_second", "tet_steps_per_second", "compile_time"}


@pytest.mark.parametrize(
    "scene_name, frames, restart_at",
    [
        ("rigid_slope", 4, 2),  # rigid blocks from the start: the report is made at the build, not after the restart
        ("pmma_plate", 4, 2),  # nodal fracture: splits, cohesive elements, crack area, cohesive work
        ("masonry_wall_blast", 4, 2),  # FEM → DEM conversion, bonds, fragments and ejecta
        # Splits, then the deformable → rigid switch at 10 ms, restarted at 12 ms: the rigid report and the step's
        # source (the blocks' contact springs, not the tet the model was built with) come from the checkpoint.
        ("limestone_tunnel", 4, 3),
    ],
)
def test_restarted_summary_equals_the_uninterrupted_one(tmp_path, scene_name, frames, restart_at):
    scene = load_scene(SCENES / f"{scene_name}.toml")
    period = 1.0 / scene.run.output_rate
    whole = run_scene(
        scene, RunOptions(device="cpu", frames=frames, out_dir=tmp_path / "whole", quiet=True, checkpoint_every=period)
    )
    middle = next(p for p in whole.checkpoints if read_checkpoint_attrs(p)["frame"] == restart_at)
    cut = run_scene(
        scene, RunOptions(device="cpu", frames=frames, out_dir=tmp_path / "whole", quiet=True, restart=middle)
    )

    a, b = json.loads(summary_json(cut)), json.loads(summary_json(whole))
    assert sorted(a) == sorted(b)
    for field in sorted(set(b) - CLOCK_FIELDS - {"checkpoints"}):
        assert a[field] == b[field], field
    assert Path(a["checkpoints"][-1]).name == Path(b["checkpoints"][-1]).name
    if scene_name in ("rigid_slope", "limestone_tunnel"):
        assert b["rigid"].startswith("rigid switch: ")
    # Every printed line but the wall time's, and the rates made of it.
    assert printed(cut) == printed(whole)


def printed(summary: object) -> list[str]:
    """The summary's lines without the wall-clock measures."""
    lines = [line for line in summary.format().splitlines() if not line.startswith("wall time")]
    return [re.sub(r"\([\d.]+ M [a-z]+-steps/s\)", "(rate)", line) for line in lines]
