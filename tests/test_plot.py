"""The energy plot's stack (warpdem/io/plot.py): positive parts of the lines stacked upward from 0, negative parts
downward, and the stack's net against the dashed target.

Oracles:
- the balance itself: Σ held + potential − Σ work = total, so the stack's net less the target is the books' error
  total(t) − total(0), read from the series' own ``energy_total`` column, to ``ROUNDING`` of the largest line (the
  CSV holds every number by repr; the sums differ only in their order of addition);
- on a series built to balance exactly, with a negative dissipation, a line that changes sign and a potential that
  rises, the drawn stack's upper edge is the sum of the positive parts, its lower edge the sum of the negative ones,
  and the net line lies on the dashed target, to ``ROUNDING``.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pytest

from warpdem.io.plot import draw_energy, energy_stack, plot_run
from warpdem.io.timeseries import energy_lines, read_series
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import parse_scene
from warpdem.stages.energy import EnergyBalance

ROUNDING = 1e-12  # relative to the largest line: float64 sums of a dozen terms

ROCK = {"density": 2600.0, "youngs_modulus": 5.0e7, "poisson_ratio": 0.25}
# Bonded beads dropped onto a plane: gravity potential, kinetic, elastic, damping and friction lines, a wall.
BEADS = {
    "name": "beads",
    "run": {"end_time": 1.0, "output_rate": 50.0},
    "materials": {"rock": ROCK},
    "parts": {"beads": {"material": "rock"}},
    "particles": [
        {
            "kind": "packing",
            "part": "beads",
            "region": {"box": {"lo": [0.1, 0.1, 0.02], "hi": [0.3, 0.3, 0.1]}},
            "radius": 0.02,
            "arrangement": "hcp",
            "velocity": [0.0, 0.0, -1.0],
        }
    ],
    "walls": [{"kind": "plane", "point": [0, 0, 0.0], "normal": [0, 0, 1], "material": "rock"}],
}


def total_of(data: dict[str, np.ndarray]) -> np.ndarray:
    """EnergyBalance.total of every row of a series."""
    names = energy_lines()
    return np.array(
        [EnergyBalance(**{n: float(data[f"energy_{n}"][k]) for n in names}).total for k in range(len(data["time"]))]
    )


def test_stack_net_meets_the_target_within_the_books_error(tmp_path):
    scene = parse_scene(BEADS)
    summary = run_scene(scene, RunOptions(device="cpu", frames=3, out_dir=tmp_path, quiet=True))
    data = read_series(tmp_path / f"{summary.usd_path.stem}_series.csv")
    stack = energy_stack(data)
    books = data["energy_total"] - data["energy_total"][0]
    size = max(float(np.abs(v).max()) for k, v in data.items() if k.startswith("energy_") and k != "energy_error")
    assert {"kinetic_translational", "dissipated_damping"} <= set(stack.up)
    np.testing.assert_allclose(stack.net - stack.target, books, rtol=0.0, atol=ROUNDING * size)
    # The books' error is small in this run, so the net meets the target to it (the summary's figure, in J).
    assert np.abs(books).max() <= 1e-4 * size
    files = plot_run(tmp_path, size=(400, 300))
    assert any(f.name.endswith("_energy.png") for f in files)


def balanced_series() -> dict[str, np.ndarray]:
    """A series that balances exactly: kinetic is what the other lines leave of the initial energy and the work."""
    t = np.linspace(0.0, 1.0, 41)
    data = {"time": t} | {f"energy_{n}": np.zeros_like(t) for n in energy_lines()}
    data["energy_dissipated_damping"] = 4.0 * (1.0 - np.exp(-3.0 * t))
    data["energy_dissipated_cohesive"] = -1.5 * t  # a release booked below zero
    data["energy_step_change"] = 0.4 * np.sin(9.0 * t)  # changes sign
    data["energy_gravity_potential"] = 2.0 + 1.0 * t  # rises: the target falls by Δ potential
    data["energy_load_work"] = 6.0 * t
    initial = 10.0
    rest = total_of(data)  # everything but the kinetic energy
    data["energy_kinetic_translational"] = initial + data["energy_gravity_potential"][0] - rest
    assert np.all(data["energy_kinetic_translational"] > 0.0)
    data["energy_total"] = total_of(data)
    data["energy_error"] = (data["energy_total"] - data["energy_total"][0]) / initial
    return data


def edge(ax, t: np.ndarray, collections, upper: bool) -> np.ndarray:
    """The upper (or lower) edge of the drawn bands at each time: the extreme y of their outlines' vertices there."""
    out = np.zeros_like(t)
    for c in collections:
        for path in c.get_paths():
            x, y = path.vertices[:, 0], path.vertices[:, 1]
            for k, tk in enumerate(t):
                ys = y[x == tk]
                if len(ys):
                    out[k] = max(out[k], ys.max()) if upper else min(out[k], ys.min())
    return out


def test_negative_lines_stack_downward_and_the_net_meets_the_target():
    data = balanced_series()
    t = data["time"]
    stack = energy_stack(data)
    assert list(stack.down) == ["dissipated_cohesive", "step_change"]
    assert "step_change" in stack.up and "dissipated_cohesive" not in stack.up
    for line in ("step_change", "dissipated_cohesive"):
        parts = stack.up.get(line, 0.0) + stack.down[line]
        np.testing.assert_array_equal(parts, data[f"energy_{line}"])
    assert all(np.all(v >= 0.0) for v in stack.up.values()) and all(np.all(v <= 0.0) for v in stack.down.values())
    scale = 20.0
    np.testing.assert_allclose(stack.net, stack.target, rtol=0.0, atol=ROUNDING * scale)
    # Target: initial energy (total at the first frame) + work in − Δ potential.
    target = data["energy_total"][0] + 6.0 * t - data["energy_gravity_potential"]
    np.testing.assert_allclose(stack.target, target, rtol=0.0, atol=ROUNDING * scale)

    fig, ax = plt.subplots()
    draw_energy(ax, data)
    bands = ax.collections
    ups, downs = bands[: len(stack.up)], bands[len(stack.up) :]
    assert len(downs) == len(stack.down)
    np.testing.assert_allclose(edge(ax, t, ups, True), sum(stack.up.values()), atol=ROUNDING * scale)
    np.testing.assert_allclose(edge(ax, t, downs, False), sum(stack.down.values()), atol=ROUNDING * scale)
    lines = {line.get_label(): line for line in ax.lines}
    net = lines["net of the stack (up − down)"].get_ydata()
    dashed = lines["initial + work in − Δ potential"].get_ydata()
    np.testing.assert_allclose(net, dashed, rtol=0.0, atol=ROUNDING * scale)
    plt.close(fig)


@pytest.mark.parametrize("line", ["kinetic_translational", "dissipated_damping"])
def test_a_line_zero_throughout_is_left_out(line):
    data = balanced_series()
    data[f"energy_{line}"] = np.zeros_like(data["time"])
    stack = energy_stack(data)
    assert line not in stack.up and line not in stack.down
