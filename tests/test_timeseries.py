"""Per-frame outputs of a run (warpdem/io/timeseries.py, the sphere VTU series, the damage primvar, wall and load
forces).

Oracles:
- the CSV has one row per frame (0..F), its columns are the EnergyBalance fields, the counts, three components per
  wall and load and the largest speed; its last row equals the run's summary exactly (the same state read twice,
  written by repr); ``energy_total`` is the sum of the lines with the signs of ``EnergyBalance.total`` (to float64
  round-off, ``SUM_RTOL``) and ``energy_error`` is the summary's error (the same function on the same numbers);
- the HDF5 file holds the same numbers, with units;
- a restarted run (from a middle checkpoint, after an interrupted run had written a row past it) leaves the CSV of
  the uninterrupted run, byte for byte (CPU restarts are bit-identical);
- the sphere VTU files read back with meshio: one point per sphere, the fields finite, and the per-sphere bonds
  broken sum to twice the bonds broken (each broken bond is counted on both its spheres);
- wall force = minus the sum of the wall contact forces on the spheres (Newton's third law; the same float32 law
  evaluated twice, so to float32 round-off, ``F32_RTOL``); pressure load force = -p A n on a flat face of area A at
  rest (float32 area, ``F32_RTOL``);
- a bar pulled apart with nodal fracture on: every split appends one node and gives birth to one cohesive element, so
  in every row nodes − nodes at frame 0 = splits = cohesive elements intact + broken (exact counts); the bar breaks
  across one section, so the opened crack area is its cross-section W² and the stage gains both sides of the
  section's triangles (2 × 2 W/h × W/h); a broken element has dissipated Γ A_f (LDEC eq. 9), so where no element is
  intact the dissipated cohesive energy equals Γ × the broken area (float32 f_c, δ_c, A_f: ``F32_RTOL``) and
  exceeds it otherwise; the summary's
  fracture lines and JSON hold the last row's numbers; the stage's cohesive curves are the intact elements of each
  frame and its damage primvar (and the VTU point data) the checkpoint's node damage (float32: exact); a restart from
  a middle checkpoint leaves the stage and the series of the uninterrupted run (CPU restarts are bit-identical).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import xml.etree.ElementTree as ET

import h5py
import meshio
import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpdem.build.scene_build import finalize_scene, scene_builder
from warpdem.io.timeseries import COUNT_COLUMNS, FRACTURE_COLUMNS, energy_lines, energy_signs, read_series, unit
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import parse_scene
from warpdem.simulation import Simulation
from warpdem.stages.contact import wall_forces
from warpdem.stages.energy import EnergyBalance, balance_error
from warpdem.stages.loads import load_forces

SUM_RTOL = 1e-12  # a sum of ~15 float64 terms of one magnitude
F32_RTOL = 1e-5  # float32 forces and areas, a few roundings

FRAMES = 4
# A bonded bar resting on the ground, struck by a ball: bonds break within the first frames, the ground carries it.
SPHERE_SCENE = {
    "name": "struck_bar",
    "run": {"end_time": 1.0, "output_rate": 200.0},
    "materials": {"rock": {"density": 2600.0, "youngs_modulus": 5.0e7, "poisson_ratio": 0.25}},
    "interactions": {"default": {"friction": 0.5, "restitution": 0.3}},
    "parts": {"bar": {"material": "rock"}, "ball": {"material": "rock"}},
    "particles": [
        {
            "kind": "packing",
            "part": "bar",
            "region": {"box": {"lo": [0.0, 0.0, 0.0], "hi": [0.1, 0.02, 0.02]}},
            "radius": 0.005,
            "arrangement": "hcp",
        },
        {"kind": "sphere", "part": "ball", "center": [0.05, 0.01, 0.045], "radius": 0.012, "velocity": [0, 0, -4.0]},
    ],
    "bonds": [
        {
            "region": {"box": {"lo": [-0.01, -0.01, -0.01], "hi": [0.11, 0.03, 0.03]}},
            "material": "rock",
            "tensile_strength": 2.0e4,
            "shear_strength": 4.0e4,
        }
    ],
    "walls": [{"kind": "plane", "point": [0.0, 0.0, -0.0001], "normal": [0.0, 0.0, 1.0], "material": "rock"}],
    "output": {"color_by": "damage", "particles_vtu": True},
}

PRESSURE = 2.0e5  # [Pa]
MESH_SCENE = {
    "name": "pressed_block",
    "run": {"end_time": 1.0, "output_rate": 4000.0},
    "gravity": {"vector": [0.0, 0.0, 0.0]},
    "materials": {"granite": {"density": 2650.0, "youngs_modulus": 5.0e9, "poisson_ratio": 0.25}},
    "mesh": {
        "kind": "box",
        "lo": [0.0, 0.0, 0.0],
        "hi": [1.0, 0.5, 1.0],
        "divisions": [2, 1, 2],
        "material": "granite",
    },
    "loads": [
        {"kind": "pressure", "faces": "z+", "history": {"kind": "table", "times": [0.0, 1.0], "values": [PRESSURE] * 2}}
    ],
    "boundaries": [{"faces": "z-", "kind": "fixed"}],
}


@pytest.fixture(scope="module")
def sphere_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("spheres")
    summary = run_scene(parse_scene(SPHERE_SCENE), RunOptions(device="cpu", frames=FRAMES, out_dir=out, quiet=True))
    return summary, out


def energy_of(data: dict[str, np.ndarray], row: int) -> EnergyBalance:
    return EnergyBalance(**{n: float(data[f"energy_{n}"][row]) for n in energy_lines()})


def test_csv_rows_columns_and_the_summary(sphere_run):
    summary, out = sphere_run
    assert summary.series_path == out / "struck_bar_series.csv"
    data = read_series(summary.series_path)
    expected = ["frame", "time", *(f"energy_{n}" for n in energy_lines()), "energy_total", "energy_error"]
    expected += [*COUNT_COLUMNS, "wall0_fx", "wall0_fy", "wall0_fz", "max_speed"]
    assert list(data) == expected
    np.testing.assert_array_equal(data["frame"], np.arange(FRAMES + 1))
    assert data["time"][-1] == summary.simulated_time
    # The last row is the summary's end state, the first its start.
    for k, e in ((-1, summary.energy_end), (0, summary.energy_start)):
        for name in energy_lines():
            assert data[f"energy_{name}"][k] == getattr(e, name), name
    assert data["spheres"][-1] == summary.particles
    assert data["contacts"][-1] == summary.contacts
    assert data["bonds_intact"][-1] == summary.bonds_intact and data["bonds_broken"][-1] == summary.bonds_broken
    assert summary.bonds_broken > 0, "the ball should break bonds within the run"
    # The balance: total = Σ sign · line, and the error is the summary's.
    signs = energy_signs()
    total = sum(signs[n] * data[f"energy_{n}"] for n in energy_lines())
    np.testing.assert_allclose(data["energy_total"], total, rtol=SUM_RTOL)
    assert data["energy_error"][-1] == summary.energy_error
    in_play = max(energy_of(data, k).in_play for k in range(len(data["frame"])))
    assert data["energy_error"][-1] == balance_error(energy_of(data, 0), energy_of(data, -1), in_play)
    assert data["energy_error"][0] == 0.0
    # The ground carries the bar: the spheres push down on it.
    assert np.all(data["wall0_fz"][1:] < 0.0)
    assert np.all(np.isfinite(np.stack(list(data.values()))))

    with h5py.File(out / "struck_bar_series.h5") as f:
        assert list(f.attrs["columns"]) == expected
        for name in expected:
            np.testing.assert_array_equal(f[name][()], data[name], err_msg=name)
            assert f[name].attrs["unit"] == unit(name)
        assert f["time"].attrs["unit"] == "s" and f["energy_elastic"].attrs["unit"] == "J"
        assert f["wall0_fz"].attrs["unit"] == "N" and f["max_speed"].attrs["unit"] == "m/s"


def test_sphere_vtu_series_and_damage_primvar(sphere_run):
    summary, out = sphere_run
    root = ET.parse(summary.pvd_path).getroot()
    datasets = root.find("Collection").findall("DataSet")
    assert [int(d.get("part")) for d in datasets] == [1] * (FRAMES + 1)  # no mesh: the spheres alone
    assert [d.get("file") for d in datasets] == [f"struck_bar_particles/struck_bar_{k:06d}.vtu" for k in range(5)]
    last = meshio.read(out / datasets[-1].get("file"))
    assert len(last.points) == summary.particles
    assert len(last.cells_dict["vertex"]) == summary.particles
    for name, width in (("radius", 1), ("velocity", 3), ("spin", 3), ("part", 1), ("material", 1), ("damage", 1)):
        values = np.asarray(last.point_data[name])
        assert values.reshape(summary.particles, -1).shape[1] == width, name
        assert np.all(np.isfinite(values)), name
    broken = np.asarray(last.point_data["bonds_broken"])
    assert broken.sum() == 2 * summary.bonds_broken  # each broken bond counts on both of its spheres
    assert np.all((last.point_data["damage"] >= 0.0) & (last.point_data["damage"] <= 1.0))

    stage = Usd.Stage.Open(str(summary.usd_path))
    points = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/World/Particles"))
    np.testing.assert_array_equal(np.asarray(points.GetPrimvar("bondsBroken").Get(float(FRAMES))), broken)


def test_restarted_run_leaves_the_uninterrupted_series(sphere_run, tmp_path):
    summary, _ = sphere_run
    scene = parse_scene(SPHERE_SCENE)
    period = 2.0 / scene.run.output_rate
    # An interrupted run: three frames, checkpoints at frames 2 and 3; the restart from frame 2 replaces row 3.
    first = run_scene(scene, RunOptions(device="cpu", frames=3, out_dir=tmp_path, checkpoint_every=period, quiet=True))
    assert len(read_series(first.series_path)["frame"]) == 4
    again = run_scene(
        parse_scene(SPHERE_SCENE),
        RunOptions(device="cpu", frames=FRAMES, out_dir=tmp_path, restart=first.checkpoints[0], quiet=True),
    )
    assert again.series_path == first.series_path
    assert again.series_path.read_text() == summary.series_path.read_text()


def test_wall_force_is_minus_the_wall_contact_forces_on_the_spheres(device):
    """Two spheres, each pressed into its own wall, moving and spinning (so damping and tangential forces act)."""
    data = {
        "name": "pressed",
        "run": {"end_time": 1.0},
        "gravity": {"vector": [0.0, 0.0, 0.0]},
        "materials": {"rock": {"density": 2600.0, "youngs_modulus": 5.0e7, "poisson_ratio": 0.25}},
        "parts": {"a": {"material": "rock"}},
        "particles": [
            {"kind": "sphere", "part": "a", "center": [0.5, 0.5, 0.0095], "radius": 0.01, "velocity": [0.1, 0, -0.2]},
            {"kind": "sphere", "part": "a", "center": [0.0092, 0.5, 0.5], "radius": 0.01, "velocity": [-0.3, 0.2, 0]},
        ],
        "walls": [
            {"kind": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "rock"},
            {"kind": "plane", "point": [0, 0, 0], "normal": [1, 0, 0], "material": "rock"},
        ],
    }
    scene = parse_scene(data)
    model, state = finalize_scene(scene, scene_builder(scene), device)
    sim = Simulation(model, state)  # evaluates the forces at the start (dt = 0)
    f = sim.state.particle_f.numpy()[:2].astype(np.float64)
    forces = wall_forces(sim.model, sim.state)
    assert forces[0, 2] < 0.0 and forces[1, 0] < 0.0  # pushed into each wall
    np.testing.assert_allclose(forces, -f, rtol=F32_RTOL, atol=F32_RTOL * np.abs(f).max())


def test_load_force_is_pressure_times_area(device):
    scene = parse_scene(MESH_SCENE)
    model, state = finalize_scene(scene, scene_builder(scene), device)
    names, forces = load_forces(model, state)
    assert names == ["loads[0]"]
    # f = -p a, a the outward area vector of the z+ face: 1 m × 0.5 m, normal +z.
    np.testing.assert_allclose(forces, [[0.0, 0.0, -PRESSURE * 0.5]], rtol=F32_RTOL, atol=F32_RTOL * PRESSURE)


def test_mesh_run_series_has_nodes_tets_and_load_columns(tmp_path):
    summary = run_scene(parse_scene(MESH_SCENE), RunOptions(device="cpu", frames=2, out_dir=tmp_path, quiet=True))
    data = read_series(summary.series_path)
    assert data["nodes"][-1] == summary.nodes and data["tets"][-1] == summary.tets == 4 * 6
    assert data["spheres"][-1] == 0 and "wall0_fx" not in data
    np.testing.assert_allclose(data["load0_fz"][0], -PRESSURE * 0.5, rtol=F32_RTOL)
    assert data["energy_error"][-1] == summary.energy_error
    assert dataclasses.asdict(summary.energy_end)["strain"] == data["energy_strain"][-1] > 0.0


# ----------------------------------------------------------------------------------------------------------------
# Nodal fracture: a bar of 2 × 2 × 10 cells pulled at 2 m/s at the top, fixed at the bottom; T_f is reached within
# the first frames, so nodes split and crack faces open.

FRACTURE_FRAMES = 6
BAR_WIDTH, BAR_CELLS = 0.2, 2  # [m] the square section and the cells across it
BAR_SCENE = {
    "name": "pulled_bar",
    "run": {"end_time": 1.0, "output_rate": 20000.0},
    "gravity": {"vector": [0.0, 0.0, 0.0]},
    "materials": {"rock": {"density": 2650.0, "youngs_modulus": 5.0e9, "poisson_ratio": 0.25}},
    "mesh": {
        "kind": "box",
        "lo": [0.0, 0.0, 0.0],
        "hi": [BAR_WIDTH, BAR_WIDTH, 1.0],
        "divisions": [BAR_CELLS, BAR_CELLS, 10],
        "material": "rock",
    },
    "loads": [
        {"kind": "velocity", "region": {"box": {"lo": [-1, -1, 0.95], "hi": [1, 1, 2]}}, "velocity": [0.0, 0.0, 2.0]}
    ],
    "boundaries": [{"faces": "z-", "kind": "fixed"}],
    "output": {"vtu": True, "mesh_color_by": "damage", "cohesive_as_curves": True},
}
BAR_FRACTURE = {"tensile_strength": 2.0e6, "fracture_energy": 50.0, "alpha": 1.0}


def run_with_fracture(options: RunOptions):
    """run_scene of BAR_SCENE with nodal fracture attached to the built model (every node may split, a pass every
    step)."""
    import warpdem.runner.run as runner
    from warpdem.stages.fracture import FractureProps, attach_fracture

    build = runner.finalize_scene

    def finalize_with_fracture(scene, builder, device=None):
        model, state = build(scene, builder, device)
        return attach_fracture(model, state, [FractureProps(**BAR_FRACTURE)], check_interval=1)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(runner, "finalize_scene", finalize_with_fracture)
        return run_scene(parse_scene(BAR_SCENE), options)


@pytest.fixture(scope="module")
def fracture_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("fracture")
    period = 3.0 / BAR_SCENE["run"]["output_rate"]
    options = RunOptions(device="cpu", frames=FRACTURE_FRAMES, out_dir=out, checkpoint_every=period, quiet=True)
    return run_with_fracture(options), out


def test_fracture_run_counts_splits_elements_and_crack_area(fracture_run):
    from warpdem.io.checkpoint import read_checkpoint
    from warpdem.runner import summary_json

    summary, out = fracture_run
    data = read_series(summary.series_path)
    columns = list(data)
    assert columns[columns.index("joints_failed") + 1 :][: len(FRACTURE_COLUMNS)] == list(FRACTURE_COLUMNS)
    splits = data["splits"]
    assert splits[0] == 0 and splits[-1] > 0, "the pulled bar should crack within the run"
    np.testing.assert_array_equal(data["nodes"] - data["nodes"][0], splits)
    np.testing.assert_array_equal(data["cohesive_intact"] + data["cohesive_broken"], splits)
    assert np.all(np.diff(data["crack_area"]) >= 0.0) and data["crack_area"][-1] > 0.0
    assert np.all(data["crack_area_opened"] <= data["crack_area"])
    # Broken through one section by the end: the opened area is the section, its work Γ × both faces of it.
    gamma = BAR_FRACTURE["fracture_energy"]
    np.testing.assert_allclose(data["crack_area_opened"][-1], BAR_WIDTH**2, rtol=F32_RTOL)
    np.testing.assert_allclose(data["cohesive_work_broken"][-1], gamma * 2.0 * BAR_WIDTH**2, rtol=F32_RTOL)
    # Once every element has broken, nothing is left to work on: the dissipated line (the law's dissipation,
    # kernels/cohesive.py) stops changing and holds the law's Γ A of the broken elements, float32 f_c δ_c products
    # summed in float64 (the work the steps did beyond it is the trapezoid line; tests/test_fracture.py bounds it as
    # dt is refined).
    none_intact = (data["cohesive_intact"] == 0) & (data["cohesive_broken"] > 0)
    assert np.any(none_intact)
    done = data["energy_dissipated_cohesive"][none_intact]
    np.testing.assert_array_equal(done, done[0])
    np.testing.assert_allclose(done[0], data["cohesive_work_broken"][-1], rtol=F32_RTOL)

    # The summary is the last row.
    assert summary.fracture
    for name in FRACTURE_COLUMNS:
        assert getattr(summary, name) == data[name][-1], name
    assert summary.dissipated_cohesive == data["energy_dissipated_cohesive"][-1]
    text = summary.format()
    assert (
        f"fracture         {summary.splits} node splits; cohesive elements {summary.cohesive_intact} intact, "
        f"{summary.cohesive_broken} broken"
    ) in text
    assert f"crack area       {summary.crack_area:.6g} m² made, {summary.crack_area_opened:.6g} m² opened" in text
    assert f"cohesive energy  {summary.dissipated_cohesive:.6g} J dissipated" in text
    as_json = json.loads(summary_json(summary))
    for name in (*FRACTURE_COLUMNS, "fracture", "dissipated_cohesive"):
        assert as_json[name] == getattr(summary, name), name
    with h5py.File(out / "pulled_bar_series.h5") as f:
        assert f["crack_area"].attrs["unit"] == "m^2" and f["splits"].dtype == np.int64

    # The stage: one curve per intact element at every frame; damage as the checkpoint holds it at the end.
    arrays, _ = read_checkpoint(summary.checkpoints[-1])
    nn = int(arrays["state/node_count"][0])
    stage = Usd.Stage.Open(str(summary.usd_path))
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Cohesive"))
    counts = [len(curves.GetCurveVertexCountsAttr().Get(float(k))) for k in range(FRACTURE_FRAMES + 1)]
    np.testing.assert_array_equal(counts, data["cohesive_intact"])
    rock = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Rock"))
    # The opened section: both sides of its 2 triangles per cell face, beside the bar's outer triangles.
    outer = 4 * (BAR_CELLS * BAR_CELLS + 2 * BAR_CELLS * 10)
    first_open = int(np.argmax(none_intact))
    triangles = len(rock.GetFaceVertexCountsAttr().Get(float(first_open)))
    assert len(rock.GetFaceVertexCountsAttr().Get(0.0)) == outer
    assert triangles == outer + 2 * 2 * BAR_CELLS**2
    damage = UsdGeom.PrimvarsAPI(rock.GetPrim()).GetPrimvar("damage")
    np.testing.assert_array_equal(np.asarray(damage.Get(float(FRACTURE_FRAMES))), arrays["state/node_damage"][:nn])
    np.testing.assert_array_equal(
        np.asarray(rock.GetPointsAttr().Get(float(FRACTURE_FRAMES))), arrays["state/node_q"][:nn]
    )
    vtu = meshio.read(sorted((out / "pulled_bar_vtu").glob("*.vtu"))[-1])
    np.testing.assert_array_equal(vtu.point_data["damage"], arrays["state/node_damage"][:nn])


def test_fracture_run_plot_has_a_fracture_picture(fracture_run, tmp_path):
    import matplotlib.image as mpimg

    from warpdem.io.plot import plot_run

    _, out = fracture_run
    files = plot_run(out, tmp_path, size=(400, 300))
    # A run with fracture can break apart, so it also wrote a fragment file and gets its picture
    # (warpdem.stages.fragments).
    expected = [f"pulled_bar_{k}.png" for k in ("counts", "energy", "fracture", "fragments")]
    assert sorted(f.name for f in files) == expected
    image = mpimg.imread(tmp_path / "pulled_bar_fracture.png")[..., :3]
    assert image.shape[:2] == (300, 400)
    assert np.mean(np.any(np.abs(image - image[0, 0]) > 0.02, axis=-1)) > 0.01  # not blank


def test_restarted_fracture_run_leaves_the_uninterrupted_stage_and_series(fracture_run, tmp_path):
    from stage_compare import assert_stages_equal

    summary, out = fracture_run
    shutil.copytree(out, tmp_path / "restart")
    middle = tmp_path / "restart" / summary.checkpoints[0].relative_to(out)
    again = run_with_fracture(
        RunOptions(device="cpu", frames=FRACTURE_FRAMES, out_dir=tmp_path / "restart", restart=middle, quiet=True)
    )
    assert again.splits == summary.splits and again.crack_area == summary.crack_area
    assert again.series_path.read_text() == summary.series_path.read_text()
    assert_stages_equal(Usd.Stage.Open(str(again.usd_path)), Usd.Stage.Open(str(summary.usd_path)))


def test_fracture_outputs_run_on_across_a_rigid_switch(tmp_path):
    """The pulled bar cracks, then turns rigid at 3.5 frames ([rigid] switch_time): the switch stops the split passes
    but keeps the cracks. Oracles: one row per frame 0..F across the switch (the series had dropped every row before
    it); in every row nodes − nodes at frame 0 = splits = cohesive intact + broken (exact counts); no split after the
    switch (no pass runs); the stage carries the damage primvar at every frame, the checkpoint's at the end."""
    from warpdem.io.checkpoint import read_checkpoint

    period = 1.0 / BAR_SCENE["run"]["output_rate"]
    scene = {**BAR_SCENE, "rigid": {"switch_time": 3.5 * period}}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys.modules[__name__], "BAR_SCENE", scene)
        summary = run_with_fracture(RunOptions(device="cpu", frames=FRACTURE_FRAMES, out_dir=tmp_path, quiet=True))
    assert summary.rigid, "the bar should have turned rigid within the run"
    data = read_series(summary.series_path)
    np.testing.assert_array_equal(data["frame"], np.arange(FRACTURE_FRAMES + 1))
    splits = data["splits"]
    assert splits[3] > 0, "the bar should crack before the switch"
    np.testing.assert_array_equal(data["nodes"] - data["nodes"][0], splits)
    np.testing.assert_array_equal(data["cohesive_intact"] + data["cohesive_broken"], splits)
    np.testing.assert_array_equal(splits[4:], splits[3])
    assert summary.splits == splits[-1]  # the summary's are the last row's
    arrays, _ = read_checkpoint(summary.checkpoints[-1])
    nn = int(arrays["state/node_count"][0])
    stage = Usd.Stage.Open(str(summary.usd_path))
    rock = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Rock"))
    damage = UsdGeom.PrimvarsAPI(rock.GetPrim()).GetPrimvar("damage")
    assert all(damage.Get(float(k)) is not None for k in range(FRACTURE_FRAMES + 1))
    np.testing.assert_array_equal(np.asarray(damage.Get(float(FRACTURE_FRAMES))), arrays["state/node_damage"][:nn])


def test_a_column_some_frames_lack_keeps_every_row_with_nan(tmp_path, monkeypatch):
    """TimeSeries.record never drops a row this run wrote: a column in some frames only (a counter that appears
    mid-run) is NaN in the others, in the CSV and the HDF5 file (an integer column with NaN stored as float64), and a
    restart reading that CSV keeps the rows before it. Oracle: the values written, cell by cell."""
    import warpdem.io.timeseries as ts

    books = {f"energy_{n}": 0.0 for n in energy_lines()}  # every real row has the energy lines
    frames = [
        {"frame": 0, "time": 0.0, **books, "splits": 3, "max_speed": 1.0},
        {"frame": 1, "time": 0.5, **books, "max_speed": 2.0},
        {"frame": 2, "time": 1.0, **books, "splits": 5, "max_speed": 3.0, "extra": 7.0},
    ]
    monkeypatch.setattr(ts, "frame_values", lambda sim, frame, *a: frames[frame])
    energy = EnergyBalance(*[0.0] * 8)
    series = ts.TimeSeries(tmp_path, "mixed")
    for k in range(3):
        series.record(None, k, energy)
    data = read_series(series.csv_path)
    np.testing.assert_array_equal(data["frame"], [0, 1, 2])
    np.testing.assert_array_equal(data["splits"], [3, np.nan, 5])
    np.testing.assert_array_equal(data["max_speed"], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(data["extra"], [np.nan, np.nan, 7.0])
    with h5py.File(series.h5_path) as f:
        assert f["splits"].dtype == np.float64 and f["frame"].dtype == np.int64
        np.testing.assert_array_equal(f["splits"][...], [3, np.nan, 5])
    restart = ts.TimeSeries(tmp_path, "mixed", first_frame=2)
    assert [r[:2] for r in restart.rows] == [[0, 0.0], [1, 0.5]]
    assert np.isnan(restart.rows[1][restart.columns.index("splits")])
