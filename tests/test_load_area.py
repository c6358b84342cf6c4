"""A pressure patch loads exactly the area its region names, whatever the mesh (issue 27), and the run reports that area
and the impulse the load delivered.

Oracle: a disc of radius R = 1 m (a cylinder region through a flat surface) under a uniform pressure p pushes with
|F| = p π R² on any mesh. The weights of warpdem.build.face_cover count a face's sub-triangle when its centroid is
inside, so the loaded area is off by at most the disc's perimeter times a sub-triangle's diameter, 2π R · h√2 / n
(h the mesh's cell, n = SUBDIVISIONS), and the force is that area times p in float32 (a few ε₃₂ relative). The old
rule (a face loaded only when its three corners were inside) lost a band of about one cell around the edge: 20–66 % of
the disc on these meshes.

The impulse: each step's evaluation adds dt p(t_{n+1}) |a| Σw per face (kernels/loads.py, Impulse), so over a run the
load reports Σ_n dt p(t_n) × the loaded area, the exact sum of the pulse sampled at the steps, to float32 rounding.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from warpdem.build.face_cover import SUBDIVISIONS
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import parse_scene
from warpdem.stages.loads import load_forces

RADIUS = 1.0
PEAK = 1.0e6
DECAY = 5.0e-5
F32_EPS = float(np.finfo(np.float32).eps)


def patch_scene(divisions: int, shift: float, out_dir) -> dict:
    """A 4 × 4 × 1 m slab, ``divisions`` cells a side, its top at z = 0, the disc centred ``shift`` m off a node."""
    return {
        "name": f"patch{divisions}",
        "run": {"end_time": 1.0e-4, "dt": "auto", "output_rate": 1.0e4},
        "materials": {"rock": {"density": 2600.0, "youngs_modulus": 5.0e10, "poisson_ratio": 0.25}},
        "mesh": {
            "kind": "box",
            "lo": [-2.0, -2.0, -1.0],
            "hi": [2.0, 2.0, 0.0],
            "divisions": [divisions, divisions, 2],
            "material": "rock",
        },
        "loads": [
            {
                "kind": "pressure",
                "region": {"cylinder": {"center": [shift, 0.5 * shift, -0.5], "radius": RADIUS, "height": 1.0}},
                "history": {"kind": "blast", "peak": PEAK, "rise_time": 0.0, "decay_time": DECAY},
            }
        ],
        "output": {"directory": str(out_dir)},
    }


@pytest.mark.parametrize(("divisions", "shift"), [(5, 0.0), (8, 0.13), (13, 0.31)])
def test_disc_patch_loads_pi_r_squared_on_any_mesh(tmp_path, divisions, shift):
    from warpdem.build.scene_build import build_scene

    scene = parse_scene(patch_scene(divisions, shift, tmp_path))
    model, state = build_scene(scene, "cpu")
    cell = 4.0 / divisions
    area_error = 2.0 * math.pi * RADIUS * cell * math.sqrt(2.0) / SUBDIVISIONS
    exact = math.pi * RADIUS**2
    area = float(model.loads.loaded_areas()[0])
    assert area == pytest.approx(exact, abs=area_error)
    _, forces = load_forces(model, state)  # at t = 0: p = PEAK, pushing down into the slab
    assert forces[0, :2] == pytest.approx([0.0, 0.0], abs=8 * F32_EPS * PEAK * exact)
    assert -forces[0, 2] == pytest.approx(PEAK * area, rel=8 * F32_EPS)
    assert -forces[0, 2] == pytest.approx(PEAK * exact, abs=PEAK * area_error)


def test_run_reports_loaded_area_and_impulse(tmp_path):
    scene = parse_scene(patch_scene(8, 0.13, tmp_path))
    summary = run_scene(scene, RunOptions(device="cpu", out_dir=tmp_path, quiet=True))
    (name, area, impulse), *_ = summary.loads
    assert name == "loads[0]"
    dt = summary.time_step
    times = dt * np.arange(1, summary.steps + 1)
    expected = float(np.sum(dt * PEAK * np.exp(-times / DECAY))) * area  # blast with no rise: p = PEAK e^(-t/τ)
    # float32 pressures and areas summed in float64 over the steps: a few ε₃₂ of each term
    assert impulse == pytest.approx(expected, rel=16 * F32_EPS)
    assert f"{area:.6g} m² loaded" in summary.format()
