"""The scene report scripts (benchmarks/*_scenes.py) refuse an unknown scene as bad input: exit status 2 and one line
that names the scenes allowed, before any Warp work (benchmarks/scene_reports.py, which the three share)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    ("script", "allowed"),
    [
        ("facility_scenes.py", "facility_persistent, facility_nonpersistent"),
        ("conversion_scenes.py", "masonry_wall_blast, masonry_tunnel_blast, dam_crest_blast"),
        ("fracture_scenes.py", "pmma_plate, brazilian_disc, boulder_impact, pmma_plate_remote, pmma_plate_branching"),
    ],
)
def test_scene_report_refuses_an_unknown_scene(script: str, allowed: str) -> None:
    # Run from the repository root as the README says (python benchmarks/<script> ...).
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "no_such_scene"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    last = done.stderr.strip().splitlines()[-1]
    assert last == f"{script}: error: unknown scene 'no_such_scene'; allowed: {allowed}"
    assert "Traceback" not in done.stderr
