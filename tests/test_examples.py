"""The scripts in examples/ run as a user runs them (a subprocess, its working directory a scratch folder that takes
the outputs), on short settings, and what they print holds.

Oracles:
- impact_speed_sweep: one row per speed; the edit of the ball's velocity took: the translational kinetic energy at
  the start goes as v² (20 against 10 m/s: 4×, to float32 rounding of the spheres' velocities, KINETIC_RTOL); every
  run breaks the slab into at least one fragment and its books close within tests/test_scenes.py's bound for it;
- custom_load: before the vent the load's force is the scene's blast pressure times the loaded area
  (-p(t) × 1 m², FORCE_RTOL: the face moves by micrometres); from the frame after the vent on it is exactly 0 and,
  once the half step of the last force is booked, the load work stays constant; the books close (MESH_BOUND);
- read_series: a PNG is written (its signature, a picture of some size), from the HDF5 and from the CSV alike, both
  reporting the same largest error, within MESH_BOUND.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from test_scenes import MESH_BOUND, scene_balance_bound

from warpdem.stages.pressure import PressureHistory

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
KINETIC_RTOL = 1e-6  # ½ m v² of float32 velocities against float64 masses, both runs the same masses
FORCE_RTOL = 1e-3  # the loaded face's area at its displaced nodes against its reference 1 m²
TIMEOUT = 300  # [s] each script on short settings takes seconds; a slow shared core, minutes


def run_example(name: str, *args: str, cwd: Path) -> str:
    """Runs ``examples/<name>`` with ``args`` in ``cwd``; returns its stdout (asserting exit status 0)."""
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args], capture_output=True, text=True, cwd=cwd, timeout=TIMEOUT
    )
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    return result.stdout


def as_summary(data: dict) -> SimpleNamespace:
    """A summary read back from JSON, with what scene_balance_bound reads."""
    return SimpleNamespace(**{**data, "energy_end": SimpleNamespace(**data["energy_end"])})


def test_impact_speed_sweep(tmp_path):
    out = run_example(
        "impact_speed_sweep.py", "--speeds", "10", "20", "--end-time", "0.004", "--json", "sweep.json", cwd=tmp_path
    )
    rows = [line.split() for line in out.splitlines() if line[:1] == " " or line[:1].isdigit()]
    assert [float(r[0]) for r in rows] == [10.0, 20.0]
    runs = json.loads((tmp_path / "sweep.json").read_text())
    assert sorted(runs) == ["10", "20"]
    slow, fast = runs["10"], runs["20"]
    np.testing.assert_allclose(
        fast["energy_start"]["kinetic_translational"],
        4.0 * slow["energy_start"]["kinetic_translational"],
        rtol=KINETIC_RTOL,
    )
    for speed, run in runs.items():
        assert run["fragment_count"] >= 1, speed
        assert abs(run["energy_error"]) <= scene_balance_bound(as_summary(run)), speed
        assert (tmp_path / "sweep" / speed / "bonded_slab_impact.usdc").is_file()


def test_custom_load(tmp_path):
    vent = 6e-4
    run_example("custom_load.py", "--vent", str(vent), "--end-time", "2e-3", "--json", "load.json", cwd=tmp_path)
    rows = json.loads((tmp_path / "load.json").read_text())
    time = np.array([r["time"] for r in rows])
    force = np.array([r["load_fz"] for r in rows])
    work = np.array([r["load_work"] for r in rows])
    assert len(rows) == 11 and np.all(np.abs([r["energy_error"] for r in rows]) <= MESH_BOUND)
    pulse = PressureHistory.blast(1.0e7, 2.0e-4, 4.0e-4)  # scenes/wave_column.toml [[loads]]
    before = time <= vent + 1e-12  # the frame at the vent still shows the force of the steps before it
    np.testing.assert_allclose(force[before], -pulse.pressure(time[before]) * 1.0, rtol=FORCE_RTOL)
    vented = np.flatnonzero(~before)
    assert np.all(force[vented] == 0.0)
    assert np.all(work[vented[1:]] == work[vented[0]]) and work[vented[0]] > work[vented[0] - 1]


def test_read_series(tmp_path):
    said = run_example("read_series.py", "--end-time", "1e-3", "--png", "h5.png", cwd=tmp_path)
    csv = tmp_path / "series_run" / "wave_column_series.csv"
    again = run_example("read_series.py", str(csv), "--png", "csv.png", cwd=tmp_path)
    for picture in ("h5.png", "csv.png"):
        data = (tmp_path / picture).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, picture
    largest = [line for line in said.splitlines() if line.startswith("largest |error|")]
    assert largest == [line for line in again.splitlines() if line.startswith("largest |error|")]
    assert float(largest[0].split()[-1]) <= MESH_BOUND
    assert "6 frames" in said  # 1 ms at 5000 frames/s, and frame 0
