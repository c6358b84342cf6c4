"""Step pipeline and between-step work (warpdem/simulation.py, warpdem/runner/): neighbour-capacity overflow and
regrowth, restart from a checkpoint, the energy balance, and bond compaction during a run.

Oracles:
- overflow: a build with too few neighbour slots keeps counting (nbr_count = the O(N²) brute-force half-list count,
  nbr_needed = its maximum), writes only inside its slots, and after Simulation.advance has grown the capacity the
  run equals, bit for bit, a run that had enough slots from the start (CPU: deterministic launch order);
- restart: a run restarted from its middle checkpoint ends in a final checkpoint identical, bit for bit, to that
  of the uninterrupted run (every ``state/*`` and ``model/*`` array, step, time and frame);
- energy: kinetic − shadow + elastic + gravity potential + dissipated + released by bond breakage − work put in stays at
  its initial value up to float32 rounding (ROUNDING_PER_STEP);
- compaction during a run: every non-negative nbr_bond names a live, intact bond of the slot's own pair, and every
  live bond is linked from its pair's slot.
"""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest

from warpdem.build import packing
from warpdem.build.builder import ModelBuilder
from warpdem.build.scene_build import build_scene
from warpdem.io.checkpoint import read_checkpoint
from warpdem.model import BOND_FIELDS
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import load_scene, parse_scene
from warpdem.simulation import Simulation

RADIUS = 0.005  # [m]

# A bonded slab (hcp, 2 layers, ~130 spheres, ~490 bonds) in an open box, struck by a steel ball at 10 m/s that
# is 3.3 mm above it: contact after ~70 steps, bonds break from ~step 90 on. 5000 frames/s ≈ 41 steps a frame.
SLAB_SCENE = """\
schema_version = 1
name = "slab"
[run]
end_time = 0.0012
dt = "auto"
safety_factor = 0.2
output_rate = 5000.0
[materials.rock]
density = 2400.0
youngs_modulus = 5.0e7
poisson_ratio = 0.2
[materials.steel]
density = 7800.0
youngs_modulus = 2.0e8
poisson_ratio = 0.3
[interactions]
default = { friction = 0.5, restitution = 0.5 }
[parts.slab]
material = "rock"
[parts.ball]
material = "steel"
[[particles]]
kind = "packing"
part = "slab"
region = { box = { lo = [0.0, 0.0, 0.0], hi = [0.08, 0.08, 0.02] } }
radius = 0.005
arrangement = "hcp"
[[particles]]
kind = "sphere"
part = "ball"
center = [0.04, 0.04, 0.0365]
radius = 0.015
velocity = [0.0, 0.0, -10.0]
[[bonds]]
region = { box = { lo = [-0.01, -0.01, -0.01], hi = [0.09, 0.09, 0.025] } }
youngs_modulus = 5.0e7
tensile_strength = 1.0e5
shear_strength = 2.0e5
[[walls]]
kind = "box"
lo = [-0.001, -0.001, 0.0]
hi = [0.081, 0.081, 0.2]
material = "steel"
open_top = true
"""
SLAB_DURATION = 3.5e-3  # [s]: the ball has rebounded and the fragments have separated
ENERGY_FRAMES = 20

# Energy tolerance, relative to the initial total (≈ the ball's kinetic energy, 5.6 J). Contacts and bonds book their
# work as velocity Verlet does it, the energy the tangential springs gain as k_t follows the overlap is its own line,
# and the balance carries Verlet's shadow term (warpdem.stages.energy.EnergyBalance), so what is left at any dt is
# float32 rounding: a random walk of ROUNDING_PER_STEP ε₃₂ of the energy per step (measured on spheres in
# test_energy_balance.py). Before the exact books: 2.35 % with friction, and without it 0.55 % at safety factor 0.2
# and 0.29 % at 0.1 (first order in dt); now 1e-5 to 2e-5.
ROUNDING_PER_STEP = 16.0


def slab_scene_dict(**run_overrides) -> dict:
    data = tomllib.loads(SLAB_SCENE)
    data["run"].update(run_overrides)
    return data


# ----------------------------------------------------------------------------------------------------------------
# Neighbour-capacity overflow


def hcp_block_builder() -> tuple[ModelBuilder, int]:
    """196 spheres in an hcp block resting on a floor under gravity: up to 12 contacts each, far more than 1 or 2."""
    q = packing.lattice_packing(packing.Box(np.zeros(3), np.array([0.08, 0.08, 0.03])), RADIUS, "hcp")
    b = ModelBuilder()
    b.add_material("rock", 2600.0, 5.0e7, 0.25)
    b.add_spheres(q + np.array([0.0, 0.0, 0.0005]), RADIUS, "rock")
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "rock")
    return b, len(q)


def contracting_cloud_builder() -> tuple[ModelBuilder, int]:
    """~200 spheres of a loose random packing (solid fraction 0.2) given a velocity field v = -20 (x - c) toward the
    centre: the cloud's neighbour counts grow during the run, not at the first build."""
    rng = np.random.default_rng(3)
    box = packing.Box(np.zeros(3), np.full(3, 0.08))
    q, r = packing.random_packing(box, RADIUS, RADIUS, rng, volume_fraction=0.2, max_count=200)
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", 2600.0, 5.0e7, 0.25)
    b.add_spheres(q, r, "rock", velocity=-20.0 * (q - 0.04))
    return b, len(q)


PAD = 8  # particle slots past the live count: a write past a particle's neighbour slots would land in theirs
OVERFLOW_DT = 1.0e-5  # [s], fixed so that both builds step identically


def brute_force_half_counts(q: np.ndarray, radius: np.ndarray, skin: float) -> list[set[int]]:
    """For each i, the j > i with |x_i - x_j| < r_i + r_j + skin (the neighbour-list criterion)."""
    q = q.astype(np.float64)
    d = np.linalg.norm(q[:, None, :] - q[None, :, :], axis=2)
    cutoff = radius[:, None] + radius[None, :] + skin
    n = len(q)
    return [set(np.nonzero((d[i] < cutoff[i]) & (np.arange(n) > i))[0].tolist()) for i in range(n)]


def check_neighbor_slots(sim: Simulation, n: int, k_built: int) -> None:
    """The list holds what the brute force says, counts past the capacity, and wrote nothing out of bounds."""
    m, s = sim.model, sim.state
    cap, k = m.particle_capacity, m.max_neighbors
    assert k == k_built
    for name in ("nbr_index", "nbr_shear", "nbr_bond"):
        assert getattr(s, name).shape == (cap * k,), name
    q = s.particle_q_at_build.numpy()[:n]
    truth = brute_force_half_counts(q, m.particle_radius.numpy()[:n].astype(np.float64), m.skin)
    counts = s.nbr_count.numpy()
    np.testing.assert_array_equal(counts[:n], [len(t) for t in truth])
    assert int(s.nbr_needed.numpy()[0]) == max(len(t) for t in truth)
    index = s.nbr_index.numpy().reshape(cap, k)
    for i in range(n):
        stored = index[i, : min(counts[i], k)].tolist()
        assert len(set(stored)) == len(stored) and set(stored) <= truth[i], (i, stored, truth[i])
    # The padding particles' slots are as allocated: nothing spilled over from the last live particle.
    np.testing.assert_array_equal(counts[n:], 0)
    np.testing.assert_array_equal(index[n:], 0)
    np.testing.assert_array_equal(s.nbr_bond.numpy().reshape(cap, k)[n:], -1)
    np.testing.assert_array_equal(s.nbr_shear.numpy().reshape(cap, k, 3)[n:], 0.0)
    np.testing.assert_array_equal(s.particle_q.numpy()[n:], 0.0)


@pytest.mark.parametrize("max_neighbors", [1, 2])
def test_overflowing_build_counts_and_stays_in_bounds(device, max_neighbors):
    b, n = hcp_block_builder()
    model, state = b.finalize(device, dt=OVERFLOW_DT, max_neighbors=max_neighbors, particle_capacity=n + PAD)
    # primed: skip the set-up evaluation (which would grow the list) to look at the device side alone.
    sim = Simulation(model, state, primed=True)
    sim.neighbors.rebuild()  # the build overflows here: the device counter must say so
    assert int(sim.state.nbr_needed.numpy()[0]) > max_neighbors
    check_neighbor_slots(sim, n, max_neighbors)
    for _ in range(5):  # steps without the host check: the overflowing list stays in bounds
        sim.step()
    check_neighbor_slots(sim, n, max_neighbors)

    # The host's check at set-up grows the slots until the first list fits, and the list is then complete.
    model, state = b.finalize(device, dt=OVERFLOW_DT, max_neighbors=max_neighbors, particle_capacity=n + PAD)
    grown = Simulation(model, state)
    assert grown.growths >= 1
    assert int(grown.state.nbr_needed.numpy()[0]) <= grown.model.max_neighbors
    check_neighbor_slots(grown, n, grown.model.max_neighbors)


def run_to_end(
    builder: ModelBuilder, n: int, device: str, max_neighbors: int, chunks: int, steps: int, every: int = 0
) -> Simulation:
    """Run ``chunks`` calls of ``advance(steps)``; with ``every`` > 0 each call runs in chunks of that many steps
    with between-steps work that changes nothing (a rigid-switch check no sphere model can pass), so that a redo
    may go back past several of them to the call's snapshot (Simulation._advance_chunk)."""
    model, state = builder.finalize(device, dt=OVERFLOW_DT, max_neighbors=max_neighbors, particle_capacity=n + PAD)
    if every:
        model = dataclasses.replace(model, rigid_energy_fraction=1.0e-30, rigid_check_interval=every)
    sim = Simulation(model, state)
    sim.rewound = 0
    chunk = sim._advance_chunk

    def counting(n_steps: int) -> int:
        back = chunk(n_steps)
        sim.rewound += back
        return back

    sim._advance_chunk = counting
    for _ in range(chunks):
        sim.advance(steps)
    return sim


@pytest.mark.parametrize(
    ("case", "max_neighbors"),
    [("initial", 1), ("initial", 2), ("during_run", 3), ("chunked", 3)],
    ids=["initial-K1", "initial-K2", "during-run-K3", "chunked-K3"],
)
def test_overflow_regrowth_reproduces_large_capacity_run(device, case, max_neighbors):
    # "initial": a dense hcp block whose very first neighbour build (in Simulation.__init__) overflows.
    # "during_run": a contracting cloud that fits 3 slots at the start (checked) and overflows later.
    # "chunked": the same in chunks of 5 steps whose between-steps work changes nothing: they share one snapshot, so
    # a redo goes back past the chunks since it and runs them again.
    builder, n = hcp_block_builder() if case == "initial" else contracting_cloud_builder()
    chunks, steps = 10, 25
    every = 5 if case == "chunked" else 0
    reference = run_to_end(builder, n, device, 64, chunks, steps, every)
    needed = int(reference.state.nbr_needed.numpy()[0])
    assert reference.growths == 0 and needed <= 64
    if case != "initial":
        model0, state0 = builder.finalize(device, dt=OVERFLOW_DT, max_neighbors=64, particle_capacity=n + PAD)
        Simulation(model0, state0)  # builds the first neighbour list
        assert int(state0.nbr_needed.numpy()[0]) <= max_neighbors < needed

    grown = run_to_end(builder, n, device, max_neighbors, chunks, steps, every)
    assert grown.growths >= 1
    if case == "chunked":
        assert grown.rewound > 0  # some redo went back past a chunk
    assert grown.model.max_neighbors > max_neighbors
    assert int(grown.state.nbr_needed.numpy()[0]) <= grown.model.max_neighbors
    assert grown.step_count == reference.step_count
    for name in ("particle_q", "particle_qd", "particle_omega"):
        bad = np.nonzero(~np.isfinite(getattr(grown.state, name).numpy()[:n]).all(axis=1))[0]
        assert bad.size == 0, f"{name}: {bad.size} of {n} spheres non-finite after regrowth (first: {bad[:5]})"
    if device != "cpu":
        return  # float atomics make GPU runs order-dependent: bitwise identity is a CPU property
    for name in ("particle_q", "particle_qd", "particle_omega", "particle_f", "nbr_count"):
        np.testing.assert_array_equal(
            getattr(grown.state, name).numpy()[:n], getattr(reference.state, name).numpy()[:n], err_msg=name
        )
    # The padding particles were never touched by the overflowing passes either.
    np.testing.assert_array_equal(grown.state.particle_q.numpy()[n:], 0.0)
    np.testing.assert_array_equal(grown.state.nbr_count.numpy()[n:], 0)


# ----------------------------------------------------------------------------------------------------------------
# Restart


def test_restart_from_middle_checkpoint_is_bit_identical(device, tmp_path):
    if device != "cpu":
        pytest.skip("bitwise restart identity is a CPU property (float atomics reorder on GPUs)")
    scene_path = tmp_path / "slab.toml"
    scene_path.write_text(SLAB_SCENE)
    scene = load_scene(scene_path)
    frames, every = 6, 3
    period = every / scene.run.output_rate  # checkpoint period [s]: every 3 frames
    full = run_scene(
        scene, RunOptions(device=device, frames=frames, out_dir=tmp_path / "full", checkpoint_every=period, quiet=True)
    )
    assert len(full.checkpoints) == 2  # frame 3 and the final frame 6
    middle, end = full.checkpoints
    mid_arrays, mid_attrs = read_checkpoint(middle)
    assert mid_attrs["frame"] == every
    broken_middle = int(mid_arrays["state/bonds_broken_total"][0])
    assert broken_middle > 0, "no bond broke before the restart point: the test would not cover compaction"

    again = run_scene(
        load_scene(scene_path),
        RunOptions(device=device, frames=frames, out_dir=tmp_path / "restart", restart=middle, quiet=True),
    )
    a_arrays, a_attrs = read_checkpoint(end)
    b_arrays, b_attrs = read_checkpoint(again.checkpoints[-1])
    assert int(a_arrays["state/bonds_broken_total"][0]) > broken_middle, "no bond broke after the restart point"
    assert sorted(a_arrays) == sorted(b_arrays)
    assert any(key.startswith("state/") for key in a_arrays)
    # First the live part (what the physics reads: bond slots below bond_count), so that a failure below names
    # only the dead slots; then every array over its whole capacity, as written to the file.
    nb = int(a_arrays["state/bond_count"][0])
    bond_keys = [f"state/{name}" for name in BOND_FIELDS]
    for key in sorted(a_arrays):
        assert a_arrays[key].dtype == b_arrays[key].dtype, key
        live = slice(0, nb) if key in bond_keys else slice(None)
        np.testing.assert_array_equal(b_arrays[key][live], a_arrays[key][live], err_msg=f"{key} (live part)")
    for key in sorted(a_arrays):
        np.testing.assert_array_equal(b_arrays[key], a_arrays[key], err_msg=f"{key} (whole array)")
    for key in ("step", "time", "frame", "max_neighbors", "dt"):
        assert b_attrs[key] == a_attrs[key], key
    assert again.checkpoints[-1].name == end.name


# ----------------------------------------------------------------------------------------------------------------
# Energy


def slab_simulation(device: str, **run_overrides) -> Simulation:
    model, state = build_scene(parse_scene(slab_scene_dict(**run_overrides)), device)
    return Simulation(model, state)


def energy_errors(sim: Simulation) -> tuple[np.ndarray, float]:
    """Relative drift of EnergyBalance.total at ENERGY_FRAMES frames over SLAB_DURATION, and the initial total."""
    e0 = sim.energy()
    per_frame = max(1, round(SLAB_DURATION / ENERGY_FRAMES / sim.model.dt))
    errors = []
    for _ in range(ENERGY_FRAMES):
        sim.advance(per_frame)
        errors.append((sim.energy().total - e0.total) / e0.total)
    return np.asarray(errors), e0.total


def test_energy_balance_bonded_slab_impact(device):
    sim = slab_simulation(device)
    errors, total0 = energy_errors(sim)
    assert total0 > 5.0  # the ball's ½ m v² ≈ 5.5 J dominates
    broken = int(sim.state.bonds_broken_total.numpy()[0])
    assert broken > 100, "the impact should break a good part of the slab"
    end = sim.energy()
    assert end.released_by_bond_breakage > 0.0 and end.dissipated_damping > 0.0 and end.dissipated_friction > 0.0
    tol = ROUNDING_PER_STEP * float(np.finfo(np.float32).eps) * np.sqrt(SLAB_DURATION / sim.model.dt)
    np.testing.assert_allclose(errors, 0.0, atol=tol, err_msg="relative drift of EnergyBalance.total")


def test_energy_balance_frictionless_closes_at_any_dt(device):
    data = slab_scene_dict()
    data["interactions"]["default"]["friction"] = 0.0
    for safety in (0.2, 0.1):
        data["run"]["safety_factor"] = safety
        model, state = build_scene(parse_scene(data), device)
        errors, _ = energy_errors(Simulation(model, state))
        steps = SLAB_DURATION / model.dt
        tol = ROUNDING_PER_STEP * float(np.finfo(np.float32).eps) * np.sqrt(steps)
        np.testing.assert_allclose(errors, 0.0, atol=tol, err_msg=f"frictionless energy drift at safety {safety}")


# ----------------------------------------------------------------------------------------------------------------
# Bond compaction during a run


def check_bond_links(sim: Simulation) -> None:
    """Every neighbour slot links the live bond of its pair (or -1 if it has none); touching bonded pairs are listed."""
    m, s = sim.model, sim.state
    n, k, nb = sim.particle_count, m.max_neighbors, sim.bond_count
    bi, bj = s.bond_i.numpy()[:nb], s.bond_j.numpy()[:nb]
    np.testing.assert_array_equal(s.bond_broken.numpy()[:nb], 0)  # advance compacted every broken bond away
    key = s.bond_key.numpy()[:nb]
    np.testing.assert_array_equal(key, bi.astype(np.int64) * m.particle_capacity + bj)
    assert np.all(np.diff(key) > 0)
    bond_of_pair = {(int(i), int(j)): b for b, (i, j) in enumerate(zip(bi, bj, strict=True))}
    counts = np.minimum(s.nbr_count.numpy()[:n], k)
    index = s.nbr_index.numpy().reshape(m.particle_capacity, k)
    bond = s.nbr_bond.numpy().reshape(m.particle_capacity, k)
    listed = set()
    for i in range(n):
        for c in range(counts[i]):
            pair, b = (i, int(index[i, c])), int(bond[i, c])
            listed.add(pair)
            # A slot links exactly the live bond of its pair, or -1 when the pair has none (a plain contact).
            assert b == bond_of_pair.get(pair, -1), f"slot {pair} links bond {b}, expected {bond_of_pair.get(pair, -1)}"
    # Touching bonded pairs are inside the list's cutoff (the skin guarantees it), so their slot exists.
    q = s.particle_q.numpy().astype(np.float64)
    r = m.particle_radius.numpy()
    for (i, j), b in bond_of_pair.items():
        if np.linalg.norm(q[i] - q[j]) < r[i] + r[j]:
            assert (i, j) in listed, f"bond {b} ({i}, {j}) touches but has no neighbour slot"


def test_bond_compaction_during_run_keeps_neighbor_links(device):
    sim = slab_simulation(device)
    initial = sim.bond_count
    per_frame = max(1, round(SLAB_DURATION / ENERGY_FRAMES / sim.model.dt))
    compactions = 0
    for _ in range(ENERGY_FRAMES):
        before = sim.bond_count
        sim.advance(per_frame)
        compactions += sim.bond_count < before
        check_bond_links(sim)
        assert sim.bond_count + int(sim.state.bonds_broken_total.numpy()[0]) == initial
    assert compactions >= 3, "bonds should break (and be compacted) over several frames"
    assert 0 < sim.bond_count < initial


# ----------------------------------------------------------------------------------------------------------------
# A run of steps (head, fused bodies, tail) against separate steps


def _every_kind_of_motion(device: str):
    """Free, prescribed and fixed spheres over a moving wall and a tet block with a velocity driver that takes hold
    and lets go mid-run, mass-proportional damping, bulk viscosity, a blast on its top and gravity."""
    from warpdem.build.mesh import boundary_faces, box_mesh
    from warpdem.stages.loads import PressureHistory
    from warpdem.stages.tets import TetProps

    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("rock", 2600.0, 1.0e8, 0.25)
    b.set_tet_properties("rock", TetProps(damping_alpha=50.0))
    points, tets = box_mesh((0.0, 0.0, 0.0), (0.1, 0.1, 0.05), (3, 3, 2))
    b.add_tet_mesh(points, tets, "rock", velocity=(0.0, 0.0, -0.5))
    dt_guess = 2.0e-6
    b.add_node_velocity(points[:, 0] == 0.0, (0.2, 0.0, 0.0), start=5.5 * dt_guess, end=17.5 * dt_guess)
    faces = boundary_faces(tets)
    top = faces[np.all(points[faces][:, :, 2] == 0.05, axis=1)]
    b.add_face_pressure(top, PressureHistory.blast(1.0e5, 4 * dt_guess, 20 * dt_guess))
    b.add_sphere((0.05, 0.05, 0.0549), 0.005, "rock", velocity=(0.0, 0.0, -3.0))
    b.add_sphere(
        (0.02, 0.05, 0.0545), 0.005, "rock", velocity=(0.5, 0.0, -1.0), angular_velocity=(0, 9, 0), motion="prescribed"
    )
    b.add_sphere((0.08, 0.05, 0.0551), 0.005, "rock", motion="fixed")
    b.add_plane_wall((0.0, 0.0, -0.001), (0.0, 0.0, 1.0), "rock", velocity=(0.0, 0.0, 0.3))
    return b.finalize(device, dt=dt_guess)


def test_run_of_steps_equals_separate_steps(device):
    """Invariant: ``advance(n)`` (first half, n - 1 fused kick-drifts, second half; replayed graphs) is, bit for bit,
    n calls of ``step()`` (two separate halves each): the fused pass does the same float operations in the same order
    (warpdem/stages/integrate.py). The run covers a driver taking hold and letting go, contacts and a blast."""
    steps = 40
    runs = []
    for use_graph in (True, False):
        model, state = _every_kind_of_motion(device)
        sim = Simulation(model, state, use_graph=use_graph)
        if use_graph:
            sim.advance(steps // 2)
            sim.advance(steps - steps // 2)  # a second run replays the captured parts
        else:
            for _ in range(steps):
                sim.step()
        runs.append(sim.state.arrays())
    assert np.any(runs[0]["particle_f"].numpy() != 0.0)  # the spheres touched something
    assert np.any(runs[0]["node_energy_boundary_work"].numpy() != 0.0)  # the driver and the blast worked
    for name, fused in runs[0].items():
        if name == "tet_stress":  # refreshed by advance only
            continue
        np.testing.assert_array_equal(fused.numpy(), runs[1][name].numpy(), err_msg=name)
