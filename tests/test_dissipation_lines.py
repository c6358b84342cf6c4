"""Every dissipation line of the energy books runs forwards (issue 28): on every shipped scene, shortened, each
``energy_dissipated_*`` and ``energy_absorbed_*`` column of the time series is non-decreasing from frame to frame.

A dashpot, friction, a softening law and a non-reflecting boundary cannot give energy back; a line that runs
backwards books on the wrong line something that the books' total still closes on (a bond stretched in a step in which
it broke, booked as released and minus it as damping: -4.8 kJ on masonry_wall_blast before the fix, kernels/bonds.py).

Oracle: monotonicity up to rounding. The lines are float64 sums of float32 terms, each step's work and change of
stored energy rounded to a few ε₃₂ of the energy in play and the roundings of successive steps adding as a random walk:
a line may fall over a frame by at most BOOK_ROUNDOFF ε₃₂ √n of the energy in play (n the frame's steps), the bound of
tests/test_scenes.py on the whole balance.

Shortening: each scene runs FRAMES frames of 1/SPLIT of its own frame (output_rate × SPLIT), one frame of its own in
all: a blast scene's first conversion pass (masonry_tunnel_blast's lining), a charge crushing bonded spheres
(masonry_wall_blast's box, spheres from the start, under its handed-over push) and the first splits of limestone_tunnel
fall in it. Two lines are Verlet's work off a conservative law, of either sign, and are not checked here: the bonds'
springs' -W - ΔU, ``bond_trapezoid`` (on the damping line it fell by 65 J in a frame on masonry_tunnel_blast before its
concrete box, 1bc3e42, and 11.5 J on dam_crest_blast when it was a 10 m arch piece: lattice bonds crushed and turned in
their first steps after a conversion pass; kernels/bonds.py), and the cohesive elements' work beyond their law's
dissipation, ``cohesive_trapezoid`` (on the cohesive line it fell by 1.8 kJ in a frame on limestone_tunnel: elements
born in a split pass whose daughters cross by 40-100 δ_c in their first step and break in it; kernels/cohesive.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from warpdem.io.timeseries import read_series
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import load_scene

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
SCENES = sorted(SCENES_DIR.glob("*.toml"))
SPLIT = 4
FRAMES = 4
F32_EPS = float(np.finfo(np.float32).eps)
BOOK_ROUNDOFF = 16.0
"""float32 roundings per step relative to the energy in play (tests/test_scenes.py, tests/test_energy_balance.py)."""
LINE_PREFIXES = ("energy_dissipated_", "energy_absorbed_")


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_dissipation_lines_never_run_backwards(tmp_path, path):
    scene = load_scene(path)
    run = scene.run.model_copy(update={"output_rate": SPLIT * scene.run.output_rate})
    summary = run_scene(
        scene.model_copy(update={"run": run}),
        RunOptions(device="cpu", frames=FRAMES, out_dir=tmp_path, quiet=True),
    )
    series = read_series(next(tmp_path.glob("*_series.csv")))
    steps_per_frame = summary.steps / FRAMES
    tolerance = BOOK_ROUNDOFF * F32_EPS * np.sqrt(steps_per_frame) * summary.energy_in_play
    lines = [name for name in series if name.startswith(LINE_PREFIXES)]
    assert lines
    backwards = {}
    for name in lines:
        values = np.asarray(series[name], dtype=np.float64)
        assert values[0] == 0.0, name  # every line starts the books at zero
        fall = -float(np.min(np.diff(values)))
        if fall > tolerance:
            backwards[name] = fall
    assert not backwards, f"{path.stem}: lines fall by {backwards} J in a frame (tolerance {tolerance:.3g} J)"
