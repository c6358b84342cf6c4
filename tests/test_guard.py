"""Stability guard (warpdem/stages/guard.py, kernels/guard.py): an explicit dt above the critical time step is refused
at set-up, and a run that goes non-finite or runs away stops with exit status 3, its good frames published.

Oracles:
- set-up: the critical step of three spheres at rest is their Rayleigh step π r sqrt(ρ/G) / (0.1631 ν + 0.8766) of
  the smallest radius (closed form); of a tet box, the smallest per-tet step (warpdem.stages.tets.tet_stable_time_steps,
  itself checked against closed forms in tests/test_tets.py), and the tet the refusal names has that step. The
  threshold is the estimate itself: dt = (1 ± REFUSAL_MARGIN) × estimate is accepted / refused;
- run-away bound: the P-wave speed sqrt(E (1 - ν) / ((1 + ν)(1 - 2ν) ρ)) of the only material (spheres at rest, no
  bonds): a sphere at (1 ± REFUSAL_MARGIN) × that speed passes / is stopped; a launch speed v raises it to
  SPEED_LIMIT_FACTOR v;
- injected NaN: isolated spheres (no contact) cannot spread it, so the first bad sphere is the poisoned one, found at
  the first step of the next advance, t = (steps + 1) dt on the device's float64 clock (TIME_RTOL);
- an unstable run (dt = UNSTABLE_FACTOR × estimate, allowed): exit status 3, one line on stderr naming time, step,
  sphere and cause, no traceback; the published stage holds the frames before the failing step, 1 + (step - 1) //
  substeps, all finite; no checkpoint of the bad state; a restart from the last good checkpoint replays the same
  steps bit for bit (CPU) and so stops with the same line.
- contact reach (issue 30): a sphere launched at v bounds the critical step by REACH_FRACTION r / v exactly, refused
  at (1 + REFUSAL_MARGIN) of it; a sphere coasting at (1 ∓ REFUSAL_MARGIN) × REACH_FRACTION r / dt passes / is
  stopped; a free sphere whose centre is behind a wall is stopped for penetration;
- penetration past the contact's reach (issue 30): of two spheres the smaller's centre at (1 ∓ REFUSAL_MARGIN) × the
  larger radius from the larger's passes / is reported (an overlap of the smaller radius); a sphere moved a tenth of its
  radius behind a slab's face it projects into stops the run at its next step, resting on it at a tenth of its radius
  in front it does not; two blocks thrown together at 20 m/s: with the default penalty the contact holds, with a
  hundredth of it they pass each other and the run stops naming the node, the face, the depth and the face's reach;
  a block moved (1 ∓ REFUSAL_MARGIN) × the node contact's largest reach behind a wall passes / is reported;
- energy from nowhere: energy_from_nowhere's allowance (a stable step's shadow, (dt/dt_c)² of what can flow, plus
  BOOKS_SLACK) at its edges; the unstable slab above is now stopped by it, before any speed runs away;
- the issue's edge runs, shortened: a 1e5 m/s ball, rigid_slope at dt = 0.01 s allowed and under 1e6 m/s² of gravity
  end with exit 3 and a message naming what went wrong (under 1e6 m/s², a node past a face of the base).
The guard never fires on the shipped scenes: tests/test_scenes.py runs each of them.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom
from warpdem.kernels import guard as kg

from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import box_mesh
from warpdem.build.scene_build import build_scene, scene_builder
from warpdem.cli import EXIT_UNSTABLE, main
from warpdem.io.checkpoint import read_checkpoint
from warpdem.scene import SceneError, load_scene
from warpdem.simulation import Simulation
from warpdem.stages.guard import BOOKS_SLACK, REACH_FRACTION, SPEED_LIMIT_FACTOR, UnstableRunError, energy_from_nowhere
from warpdem.stages.tets import reference_geometry, tet_stable_time_steps

REFUSAL_MARGIN = 1e-3  # relative; far above float64 rounding of dt and of the estimate (~1e-15)
TIME_RTOL = 1e-12  # the device clock sums dt in float64 a few times
UNSTABLE_FACTOR = 5.0  # dt / critical step of the unstable run: the stiffest bond mode grows ~(ω dt)² per step

DENSITY, YOUNG, POISSON = 2500.0, 1.0e7, 0.3  # [kg/m³], [Pa], [-] of the sphere scenes' rock
RADIUS = 0.01  # [m] of the isolated spheres
YOUNG_G = 6.0e10  # [Pa] of the tet scene's granite (ρ = 2650 kg/m³, ν = 0.25, c_lin = 0.06 by default)

SPHERES = """\
schema_version = 1
name = "three_spheres"
[run]
end_time = 1.0
dt = {dt}
output_rate = 100.0
{run_extra}
[materials.rock]
density = 2500.0
youngs_modulus = 1.0e7
poisson_ratio = 0.3
[parts.grains]
material = "rock"
[[particles]]
kind = "sphere"
part = "grains"
center = [0.0, 0.0, 0.05]
radius = 0.01
[[particles]]
kind = "sphere"
part = "grains"
center = [0.05, 0.0, 0.05]
radius = 0.008
[[particles]]
kind = "sphere"
part = "grains"
center = [0.0, 0.05, 0.08]
radius = 0.012
[[walls]]
kind = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "rock"
"""

TETS = """\
schema_version = 1
name = "tet_block"
[run]
end_time = 1.0e-3
dt = {dt}
output_rate = 1.0e4
{run_extra}
[gravity]
vector = [0.0, 0.0, 0.0]
[materials.granite]
density = 2650.0
youngs_modulus = 6.0e10
poisson_ratio = 0.25
[mesh]
kind = "box"
lo = [0.0, 0.0, 0.0]
hi = [1.0, 1.0, 2.0]
divisions = [1, 1, 3]
material = "granite"
"""

# A small bonded slab resting on the ground: gravity presses it into the wall, which excites the bond modes. The bonds
# cannot break, so an unstable mode grows without bound (breakable ones would all break and the spheres fly apart at
# about c_p, below the run-away bound: warpdem.stages.guard).
SLAB = """\
schema_version = 1
name = "slab"
[run]
end_time = 1.0
dt = {dt}
output_rate = {output_rate}
{run_extra}
[materials.rock]
density = 2600.0
youngs_modulus = 5.0e7
poisson_ratio = 0.25
[parts.slab]
material = "rock"
[[particles]]
kind = "packing"
part = "slab"
region = {{ box = {{ lo = [0.0, 0.0, 0.0], hi = [0.04, 0.03, 0.02] }} }}
radius = 0.005
arrangement = "hcp"
[[bonds]]
region = {{ box = {{ lo = [-0.01, -0.01, -0.01], hi = [0.05, 0.04, 0.03] }} }}
material = "rock"
tensile_strength = 1.0e12
shear_strength = 1.0e12
[[walls]]
kind = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "rock"
"""


def scene_file(folder: Path, template: str, dt: float | str, run_extra: str = "", **fields) -> Path:
    """A scene file from a template, dt [s] written exactly (repr) or "auto"."""
    path = folder / "scene.toml"
    value = '"auto"' if dt == "auto" else repr(float(dt))
    path.write_text(template.format(dt=value, run_extra=run_extra, **fields))
    return path


def rayleigh_step(radius: float) -> float:
    """Rayleigh time step π r sqrt(ρ/G) / (0.1631 ν + 0.8766) [s] of a sphere of the test material."""
    shear = YOUNG / (2.0 * (1.0 + POISSON))
    return math.pi * radius * math.sqrt(DENSITY / shear) / (0.1631 * POISSON + 0.8766)


# ----------------------------------------------------------------------------------------------------------------
# Set-up


def test_sphere_scene_refuses_dt_above_the_rayleigh_step(tmp_path):
    critical = rayleigh_step(0.008)  # the smallest sphere sets it
    model, _ = build_scene(load_scene(scene_file(tmp_path, SPHERES, (1.0 - REFUSAL_MARGIN) * critical)), "cpu")
    np.testing.assert_allclose(model.critical_dt, critical, rtol=1e-12)
    assert model.dt == (1.0 - REFUSAL_MARGIN) * critical
    for factor in (1.0 + REFUSAL_MARGIN, 10.0):
        path = scene_file(tmp_path, SPHERES, factor * critical)
        with pytest.raises(SceneError) as info:
            build_scene(load_scene(path), "cpu")
        (line,) = info.value.problems
        assert line.startswith(f"{path}: run.dt: dt = {factor * critical:.4g} s exceeds the critical time step ")
        assert f"{critical:.4g} s, set by the Rayleigh step of the smallest spheres of material rock" in line
        assert "r = 0.008 m" in line and "run.allow_unstable_dt = true" in line
    path = scene_file(tmp_path, SPHERES, 10.0 * critical, "allow_unstable_dt = true")
    model, _ = build_scene(load_scene(path), "cpu")
    assert model.dt == 10.0 * critical


def test_tet_scene_refuses_dt_above_the_smallest_tet_step(tmp_path):
    scene = load_scene(scene_file(tmp_path, TETS, "auto"))
    mesh = scene_builder(scene).tet_mesh_data()
    inv_ref, _ = reference_geometry(mesh.points, mesh.tets)
    mu = YOUNG_G / (2.0 * 1.25)
    lam = YOUNG_G * 0.25 / (1.25 * 0.5)
    steps = tet_stable_time_steps(inv_ref, *(np.full(len(inv_ref), v) for v in (mu, lam, 2650.0, 0.06)))
    critical = float(steps.min())
    path = scene_file(tmp_path, TETS, 1.0e-3)
    with pytest.raises(SceneError) as info:
        build_scene(load_scene(path), "cpu")
    (line,) = info.value.problems
    named = re.search(r"set by tet (\d+) of material granite;", line)
    assert named is not None, line
    assert steps[int(named.group(1))] == critical
    assert line.startswith(f"{path}: run.dt: dt = 0.001 s exceeds the critical time step {critical:.4g} s")
    build_scene(load_scene(scene_file(tmp_path, TETS, (1.0 - REFUSAL_MARGIN) * critical)), "cpu")
    with pytest.raises(SceneError):
        build_scene(load_scene(scene_file(tmp_path, TETS, (1.0 + REFUSAL_MARGIN) * critical)), "cpu")
    model, _ = build_scene(load_scene(scene_file(tmp_path, TETS, 1.0e-3, "allow_unstable_dt = true")), "cpu")
    assert model.dt == 1.0e-3


def test_cli_refusal_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    path = scene_file(tmp_path, SPHERES, 1.0e-2)
    out = tmp_path / "out"
    assert main([str(path), "--out", str(out), "--quiet", "--frames", "2"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "run.dt" in err and "Traceback" not in err
    assert not out.exists()


# ----------------------------------------------------------------------------------------------------------------
# Run time, Python API


def isolated_spheres(device: str, dt: float | None = None) -> tuple[ModelBuilder, Simulation]:
    """Four spheres far apart in zero gravity: nothing they do reaches another (``dt``: None for auto)."""
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    centers = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    b.add_spheres(centers, RADIUS, "rock", velocity=(0.0, 0.0, 0.0))
    model, state = b.finalize(device, dt=dt)
    return b, Simulation(model, state)


def poison(array, slot: int, value: np.ndarray) -> None:
    host = array.numpy()
    host[slot] = value
    array.assign(host)


@pytest.mark.parametrize("field", ["particle_qd", "particle_q", "particle_omega"])
def test_injected_nan_is_caught_on_the_next_advance(device, field):
    _, sim = isolated_spheres(device)
    sim.advance(3)
    slot = 2
    sphere_id = int(sim.model.particle_id.numpy()[slot])
    poison(getattr(sim.state, field), slot, np.array([0.0, np.nan, 0.0]))
    with pytest.raises(UnstableRunError) as info:
        sim.advance(5)
    err = info.value
    assert err.step == 4 and sim.step_count == 4
    np.testing.assert_allclose(err.time, 4 * sim.model.dt, rtol=TIME_RTOL)
    assert err.entity == f"sphere {sphere_id} (part default)"
    # A NaN position or velocity leaves the position NaN after the step's drift; a NaN spin stays in the spin.
    expected = "non-finite angular velocity" if field == "particle_omega" else "non-finite position"
    assert err.problem.startswith(expected) and "(1 spheres and 0 FEM nodes bad)" in err.problem
    assert "\n" not in str(err)


def test_sphere_of_an_unnamed_part_is_described_by_its_id(device):
    # Spheres a conversion pass makes in a model built without spheres carry a part id the model has no name for;
    # the error names it by id rather than failing on the description (an IndexError hid the real message).
    _, sim = isolated_spheres(device)
    sim.model.part_names.clear()
    sphere_id = int(sim.model.particle_id.numpy()[0])
    poison(sim.state.particle_q, 0, np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(UnstableRunError) as info:
        sim.advance(1)
    assert info.value.entity == f"sphere {sphere_id} (part #0)"


def test_speed_bound_is_the_p_wave_speed_or_ten_launch_speeds(device):
    # c_p = sqrt(E (1 - ν) / ((1 + ν)(1 - 2ν) ρ)): a material point that fast would be at 100 % strain.
    c_p = math.sqrt(YOUNG * (1.0 - POISSON) / ((1.0 + POISSON) * (1.0 - 2.0 * POISSON) * DENSITY))
    # A step short enough that c_p stays below the contact-reach speed 0.5 r / dt (2.5 c_p here).
    b, sim = isolated_spheres(device, dt=REACH_FRACTION * RADIUS / (2.5 * c_p))
    np.testing.assert_allclose(sim.model.speed_limit, c_p, rtol=1e-12)
    poison(sim.state.particle_qd, 1, np.array([(1.0 - REFUSAL_MARGIN) * c_p, 0.0, 0.0]))
    sim.advance(2)
    poison(sim.state.particle_qd, 3, np.array([0.0, (1.0 + REFUSAL_MARGIN) * c_p, 0.0]))
    with pytest.raises(UnstableRunError) as info:
        sim.advance(2)
    assert info.value.entity == f"sphere {int(sim.model.particle_id.numpy()[3])} (part default)"
    assert info.value.problem.startswith("speed ") and "above the run-away bound" in info.value.problem
    assert info.value.step == 3
    # A sphere launched at a tenth of c_p or faster raises the bound to SPEED_LIMIT_FACTOR times its speed.
    launch = 0.2 * c_p
    b.add_sphere((5.0, 5.0, 5.0), 0.01, "rock", velocity=(launch, 0.0, 0.0))
    model, _ = b.finalize(device)
    np.testing.assert_allclose(model.speed_limit, SPEED_LIMIT_FACTOR * launch, rtol=1e-12)


def test_injected_nan_in_a_node_is_caught(device, tmp_path):
    model, state = build_scene(load_scene(scene_file(tmp_path, TETS, "auto")), device)
    sim = Simulation(model, state)
    sim.advance(2)
    poison(sim.state.node_u, 0, np.array([np.inf, 0.0, 0.0]))
    with pytest.raises(UnstableRunError) as info:
        sim.advance(4)
    assert info.value.step == 3
    assert info.value.entity.startswith("FEM node 0 (of tet ") and info.value.entity.endswith("material granite)")
    assert info.value.problem.startswith("non-finite position")
    assert "dt = " in info.value.cause and "within the critical time step" in info.value.cause


# ----------------------------------------------------------------------------------------------------------------
# Run time, command line


def stage_frames(path: Path) -> np.ndarray:
    """Sphere positions of every frame of a published stage, shape (frames, N, 3)."""
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Points(stage.GetPrimAtPath("/World/Particles")).GetPointsAttr()
    return np.array([np.asarray(attr.Get(t)) for t in attr.GetTimeSamples()])


def test_unstable_run_stops_with_exit_3_and_keeps_the_good_output(tmp_path, capsys):
    critical = build_scene(load_scene(scene_file(tmp_path, SLAB, "auto", output_rate=100.0)), "cpu")[0].critical_dt
    dt = UNSTABLE_FACTOR * critical
    substeps = 2
    path = scene_file(tmp_path, SLAB, dt, "allow_unstable_dt = true", output_rate=repr(1.0 / (substeps * dt)))
    out = tmp_path / "out"
    argv = [str(path), "--out", str(out), "--quiet", "--frames", "50", "--checkpoint-every", repr(substeps * dt)]
    assert main(argv) == EXIT_UNSTABLE
    (line,) = capsys.readouterr().err.splitlines()
    found = re.fullmatch(
        r"error: unstable run stopped at t = (\S+) s \(step (\d+)\): "
        r"(?:sphere \d+ \(part slab\)|the energy books): (.*); likely cause: "
        r"time step too large: dt = (\S+) s is (\S+) x the critical time step (\S+) s set by the bond between "
        r"spheres of part slab .*; (\d+) good frames published in (\S+); last good checkpoint (\S+)",
        line,
    )
    assert found is not None, line
    step, frames = int(found.group(2)), int(found.group(7))
    np.testing.assert_allclose(float(found.group(1)), step * dt, rtol=1e-5)  # printed to 6 digits
    assert float(found.group(5)) == pytest.approx(UNSTABLE_FACTOR, rel=1e-3)
    assert frames == 1 + (step - 1) // substeps and frames >= 2  # some good frames before the blow-up
    positions = stage_frames(Path(found.group(8)))
    assert len(positions) == frames and np.all(np.isfinite(positions))
    assert not list(out.glob("*.partial.*"))
    checkpoints = sorted((out / "checkpoints").glob("*.h5"))
    steps = [int(read_checkpoint(p)[1]["step"]) for p in checkpoints]
    assert Path(found.group(9)) == checkpoints[-1].resolve() or Path(found.group(9)) == checkpoints[-1]
    assert steps == [substeps * f for f in range(1, frames)]  # one per good frame after the first, none of the bad
    arrays, _ = read_checkpoint(checkpoints[-1])
    assert all(np.all(np.isfinite(a)) for k, a in arrays.items() if a.dtype.kind == "f")
    # The last good checkpoint is whole: a restart from it runs the same steps and stops with the same line.
    assert main([*argv, "--restart", str(checkpoints[-1])]) == EXIT_UNSTABLE
    again = capsys.readouterr().err.splitlines()[0]
    # The same time, step and entity (the energy books of a restart start at its checkpoint: their numbers differ).
    assert again.split(": ")[:3] == line.split(": ")[:3]


# ----------------------------------------------------------------------------------------------------------------
# Contact reach (issue 30): a body may move at most REACH_FRACTION of the smallest contact reach per step.


def test_fast_launch_bounds_the_step_by_the_contact_reach(device):
    # reach step = REACH_FRACTION r / v (warpdem.stages.guard.reach_step): far below the Rayleigh step at this speed.
    speed = 1.0e4
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_sphere((0.0, 0.0, 0.0), RADIUS, "rock")
    b.add_sphere((1.0, 0.0, 0.0), RADIUS, "rock", velocity=(0.0, 0.0, -speed))
    model, _ = b.finalize(device)
    reach = REACH_FRACTION * RADIUS / speed
    assert reach < rayleigh_step(RADIUS)
    np.testing.assert_allclose(model.critical_dt, reach, rtol=1e-12)
    assert "the contact reach: a sphere of part default at 1e+04 m/s" in model.critical_dt_source
    np.testing.assert_allclose(model.contact_reach, RADIUS, rtol=1e-12)
    with pytest.raises(ValueError, match=r"exceeds the critical time step .* set by the contact reach: a sphere"):
        b.finalize(device, dt=(1.0 + REFUSAL_MARGIN) * reach)
    b.finalize(device, dt=(1.0 - REFUSAL_MARGIN) * reach)


def test_body_too_fast_for_the_contact_reach_is_stopped(device):
    # The guard's reach speed is REACH_FRACTION r / dt whatever the step's stability; the isolated spheres' auto step
    # keeps it below the run-away bound c_p, so a sphere between the two is stopped for the reach alone.
    _, sim = isolated_spheres(device)
    limit = REACH_FRACTION * RADIUS / sim.model.dt
    assert (1.0 + REFUSAL_MARGIN) * limit < sim.model.speed_limit
    # A sphere coasting for two steps adds no speed (no gravity, no contact): the speed checked is the one set.
    poison(sim.state.particle_qd, 1, np.array([(1.0 - REFUSAL_MARGIN) * limit, 0.0, 0.0]))
    sim.advance(2)
    poison(sim.state.particle_qd, 2, np.array([0.0, (1.0 + REFUSAL_MARGIN) * limit, 0.0]))
    with pytest.raises(UnstableRunError) as info:
        sim.advance(2)
    err = info.value
    assert err.entity == f"sphere {int(sim.model.particle_id.numpy()[2])} (part default)"
    assert "more than 0.5 x the smallest contact reach 0.01 m" in err.problem
    assert err.cause.startswith("a body too fast for the time step")


def test_sphere_through_a_wall_is_penetration_past_the_reach(device):
    # A free sphere's centre behind a plane wall has an overlap past its radius: the wall contact pushes it further
    # through. The same sphere with its centre just in front (gap = r / 2) is a resolved contact.
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_sphere((0.0, 0.0, 0.5 * RADIUS), RADIUS, "rock")
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "rock")
    model, state = b.finalize(device)
    sim = Simulation(model, state)
    sim.advance(1)
    host = sim.state.particle_q.numpy()
    host[0, 2] = -0.1 * RADIUS
    sim.state.particle_q.assign(host)
    with pytest.raises(UnstableRunError) as info:
        sim.advance(1)
    assert info.value.problem.startswith("penetration past the contact's reach: its centre")
    assert "behind wall 0" in info.value.problem


def test_sphere_centre_inside_another_is_penetration_past_the_reach(device):
    # Spheres of radii r and r/2 touching at set-up (their pair is in the neighbour list), then the small one moved
    # to d = (1 ∓ REFUSAL_MARGIN) r from the big one's centre: an overlap 3r/2 - d just below / above the smaller
    # radius r/2. The guard's pass alone decides (no step: the contact would throw them apart).
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_sphere((0.0, 0.0, 0.0), RADIUS, "rock")
    b.add_sphere((1.5 * RADIUS, 0.0, 0.0), 0.5 * RADIUS, "rock")
    sim = Simulation(*b.finalize(device))
    small = int(np.argmin(sim.model.particle_radius.numpy()[:2]))
    big = 1 - small

    def moved(d: float):
        q = sim.state.particle_q.numpy()
        q[small] = q[big] + np.array([d, 0.0, 0.0])
        sim.state.particle_q.assign(q)
        return sim.guard.check(sim.model, sim.state)

    assert moved((1.0 + REFUSAL_MARGIN) * RADIUS) is None
    report = moved((1.0 - REFUSAL_MARGIN) * RADIUS)
    assert report is not None and report.sphere == 0 and report.sphere_problem == kg.PROBLEM_OVERLAP
    err = str(sim.guard.error(sim.model, sim.state, report, 0, 0.0))
    assert "penetration past the contact's reach: its centre" in err
    assert f"overlap by {0.5 * RADIUS * (1 + 2 * REFUSAL_MARGIN):.3g} m, past the smaller radius 0.005 m" in err


def sphere_over_slab(device, height: float) -> Simulation:
    """A sphere of radius RADIUS at rest with its centre ``height`` over the top face (z = 0.2) of a fixed tet slab,
    over a face's interior, no gravity."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 0.2), (4, 4, 1))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(points, tets, "rock", fixed_nodes=np.arange(len(points)))
    b.add_sphere((0.43, 0.37, 0.2 + height), RADIUS, "rock")
    return Simulation(*b.finalize(device))


def test_sphere_behind_a_face_stops_the_run(device):
    # The sphere–face contact acts while the centre is in front of the face: resting a tenth of its radius deep it is
    # pushed out; moved a tenth of its radius behind the face, nothing pushes it back, and the step that sees it
    # records the face (kernels/sphere_face.py), which the guard reports.
    sim = sphere_over_slab(device, 0.9 * RADIUS)
    sim.advance(5)
    sim = sphere_over_slab(device, -0.1 * RADIUS)
    with pytest.raises(UnstableRunError) as info:
        sim.advance(5)
    err = info.value
    assert err.step == 1 and err.entity == "sphere 0 (part default)"
    assert re.search(
        r"its centre .* went 0.001 m behind face \d+ \(of tet \d+, material rock\), an overlap of "
        r"0.011 m past its radius 0.01 m",
        err.problem,
    ), err.problem


def test_node_deep_behind_a_wall_is_penetration_past_the_reach(device):
    # A tet block resting on a wall, moved down by (1 ∓ REFUSAL_MARGIN) × the node contact's largest reach
    # (face_depth_max, half the tallest tet over a boundary face): its bottom nodes are that deep behind the wall.
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 0.5), (2, 2, 1))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "rock")
    b.add_tet_mesh(points, tets, "rock")
    sim = Simulation(*b.finalize(device))
    reach = sim.model.face_depth_max
    np.testing.assert_allclose(reach, 0.25, rtol=1e-6)  # half a 0.5 m tall cell
    x_ref = sim.model.node_ref_q.numpy()

    def sunk(depth: float):
        u = np.zeros_like(x_ref)
        u[:, 2] = -depth
        sim.state.node_u.assign(u)
        sim.state.node_q.assign(x_ref + u)
        return sim.guard.check(sim.model, sim.state)

    assert sunk((1.0 - REFUSAL_MARGIN) * reach) is None
    report = sunk((1.0 + REFUSAL_MARGIN) * reach)
    assert report is not None and report.node >= 0 and report.node_problem == kg.PROBLEM_PENETRATION
    err = str(sim.guard.error(sim.model, sim.state, report, 0, 0.0))
    assert f"{(1.0 + REFUSAL_MARGIN) * reach:.3g} m behind wall 0, deeper than the node contact's largest reach" in err


def thrown_blocks(device, stiffness_factor: float) -> Simulation:
    """A 1 × 1 × 0.5 m block held at its base and a second one 1 cm over it thrown down at 20 m/s, no gravity, the
    contact's penalty factor ``stiffness_factor`` (2 × 2 × 1 cells: a face's reach is 0.25 m)."""
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0), contact_stiffness_factor=stiffness_factor)
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    lower, lower_tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 0.5), (2, 2, 1))
    upper, upper_tets = box_mesh((0.0, 0.0, 0.51), (1.0, 1.0, 1.01), (2, 2, 1))
    b.add_tet_mesh(lower, lower_tets, "rock", fixed_nodes=np.nonzero(lower[:, 2] == 0.0)[0])
    b.add_tet_mesh(upper, upper_tets, "rock", velocity=(0.0, 0.0, -20.0))
    return Simulation(*b.finalize(device, safety_factor=0.5))


def test_blocks_thrown_together_are_held_or_stopped(device):
    # Issue 30: "either the contact holds or the run stops saying the penetration exceeded what the contact
    # resolves". The default penalty stops the block within a few cm; a hundredth of it (the block's 1.2 kJ per
    # bottom node against ½ k (0.25 m)² ~ 0.2 kJ) lets the blocks pass each other: a node is let go of by a face it
    # went past the face's reach behind (kernels/fem_contact.py passed_face), and the run stops.
    thrown_blocks(device, 1.0).advance(400)
    with pytest.raises(UnstableRunError) as info:
        thrown_blocks(device, 0.01).advance(400)
    err = info.value
    assert err.entity.startswith("FEM node ")
    found = re.search(
        r"it is at .*, (\S+) m behind face \d+ \(of tet \d+, material rock\), past the face's reach "
        r"(\S+) m \(half the tet's height over it\)",
        err.problem,
    )
    assert found, err.problem
    assert float(found.group(1)) >= float(found.group(2)) == 0.25
    assert "likely cause: an impact or load the node–face contact cannot stop within its reach" in str(err)


SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"


def edge_scene(tmp_path: Path, name: str, replacements: dict[str, str]) -> Path:
    """A shipped scene with lines replaced (each old text must occur once)."""
    text = (SCENES_DIR / f"{name}.toml").read_text()
    for old, new in replacements.items():
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def run_edge(tmp_path: Path, path: Path, capsys) -> tuple[int, str, str]:
    code = main([str(path), "--out", str(tmp_path / "out"), "--device", "cpu"])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_ball_at_1e5_m_per_s_does_not_tunnel_silently(tmp_path, capsys):
    # Issue 30, case 1: at 1e5 m/s the ball's Hertz overlap against the ground, (15 m v² / (16 E* sqrt(R)))^(2/5)
    # ~ 6 m, is far past its 0.1 m radius: no step resolves it. The step now holds the ball to half the shortest
    # tet edge per step, and the run stops when the ball's centre passes the ground plane.
    path = edge_scene(
        tmp_path,
        "boulder_impact",
        {"velocity = [0.0, 0.0, -40.0]": "velocity = [0.0, 0.0, -1.0e5]", "end_time = 0.008": "end_time = 0.00002"},
    )
    code, out, err = run_edge(tmp_path, path, capsys)
    assert code == EXIT_UNSTABLE, out + err
    assert "sphere 0 (part ball): penetration past the contact's reach" in err
    # The step it ran at: t / step, at most REACH_FRACTION × the shortest edge (0.0569 m, printed) / 1e5 m/s.
    found = re.search(r"stopped at t = (\S+) s \(step (\d+)\)", err)
    edge = float(re.search(r"shortest edge (\S+) m", out).group(1))
    assert float(found.group(1)) / int(found.group(2)) <= REACH_FRACTION * edge / 1.0e5 * (1.0 + REFUSAL_MARGIN)


def test_rigid_slope_at_an_allowed_unstable_dt_is_stopped(tmp_path, capsys):
    # Issue 30, case 2: dt = 0.01 s (allowed) sends blocks off at hundreds of m/s, 2.9 m per step against a 0.18 m
    # shortest edge; the changed frame rate (40/s is 2.5 steps) is said.
    path = edge_scene(
        tmp_path,
        "rigid_slope",
        {'dt = "auto"': "dt = 0.01\nallow_unstable_dt = true", "end_time = 1.5": "end_time = 0.04"},
    )
    code, out, err = run_edge(tmp_path, path, capsys)
    assert code == EXIT_UNSTABLE, out + err
    assert "run.output_rate 40/s is not a whole number of steps of dt = 0.01 s: a frame every 2 steps" in out
    assert "more than 0.5 x the smallest contact reach" in err and "likely cause: time step too large" in err


def test_rigid_slope_under_1e6_gravity_is_stopped(tmp_path, capsys):
    # Issue 30, case 3: g = 1e6 m/s² drives the blocks through the fixed base ("853 of 1198 nodes fall through the
    # base to z = −309 m"); the run stops at the first node that goes past a face's reach (at ~0.6 ms, before any
    # node moves more than half the shortest edge in a step, g t dt > 0.09 m at t ~ 2 ms).
    path = edge_scene(
        tmp_path,
        "rigid_slope",
        {"vector = [0.0, 0.0, -9.81]": "vector = [0.0, 0.0, -1.0e6]", "end_time = 1.5": "end_time = 0.025"},
    )
    code, out, err = run_edge(tmp_path, path, capsys)
    assert code == EXIT_UNSTABLE, out + err
    assert "FEM node" in err and "penetration past the contact's reach: it is at" in err, err
    assert "behind face" in err and "past the face's reach" in err and err.count("\n") == 1


def test_energy_from_nowhere_allows_a_stable_steps_shadow_only():
    # A spring of energy U = 1 J at rest, no work, no gravity: at a stable step the shadow term S ≤ (dt/dt_c)² U
    # (S/U = (ω dt)²/4 per mode, 1 at ω dt = 2), so Δ(total + S) up to (dt/dt_c)² + BOOKS_SLACK of U passes.
    start = (1.0, 0.0, 1.0, 0.0)  # total, shadow, in play, gravity potential [J]
    half = 0.25 + BOOKS_SLACK  # allowed at dt = dt_c / 2
    assert energy_from_nowhere(start, (1.0, (1.0 - REFUSAL_MARGIN) * half, 0.0, 0.0, 0.0, 0.0), 0.5, 1.0) is None
    appeared, allowed = energy_from_nowhere(start, (1.0, (1.0 + REFUSAL_MARGIN) * half, 0.0, 0.0, 0.0, 0.0), 0.5, 1.0)
    np.testing.assert_allclose(allowed, half * 1.0 + 16.0 * float(np.finfo(np.float32).eps), rtol=1e-12)
    np.testing.assert_allclose(appeared, (1.0 + REFUSAL_MARGIN) * half, rtol=1e-12)
    # Work put in and gravity released (10 J each, booked in the total) enlarge what a stable shadow may hold:
    # 3 J of shadow passes with them ((0.25 + slack) × 21 J) and not without (× 1 J).
    assert energy_from_nowhere(start, (1.0, 3.0, -10.0, 10.0, 0.0, 0.0), 0.5, 1.0) is None
    assert energy_from_nowhere(start, (1.0, 3.0, 0.0, 0.0, 0.0, 0.0), 0.5, 1.0) is not None
    # Past the critical step the shadow may hold all of it, once: (1 + BOOKS_SLACK) × what can flow.
    assert energy_from_nowhere(start, (1.0, 1.0, 0.0, 0.0, 0.0, 0.0), 5.0, 1.0) is None
    assert energy_from_nowhere(start, (1.0, 1.0 + 2.0 * BOOKS_SLACK, 0.0, 0.0, 0.0, 0.0), 5.0, 1.0) is not None
