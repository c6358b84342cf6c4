"""CPU against a device, and a device against itself (issue 24), for ``benchmarks/gpu_check.sh``.

``python benchmarks/gpu_compare.py --device cuda:0 --out DIR`` runs two short runs that change their mesh, on the CPU
once and on the device twice, and writes ``DIR/compare.json``; it exits 1 when a check failed:

- the cracking block (``warpdem.bench.fracture.cracking_block``: a cube of grains pulled apart along x, a split pass
  every step) and the converting block (``warpdem.bench.conversion.converting_run_block``: the same cube with its
  central slab converting to spheres, a conversion pass every step), ``--cells``³ cells, ``--steps`` steps (the
  builders set the pulling rate from that length, so that the weakest grains fail a quarter of the way through);
- on every run: the total mass (nodes and spheres) is kept; the momentum changes by the impulse of the velocity
  drivers (the only external forces: no gravity, no walls); the energy books close within the bound the tests use;
  the block cracks (or converts);
- device against CPU: the same energy lines and node positions over an early window (before anything splits or
  converts, where the runs differ by rounding only); after that chaotic cracking makes them diverge, so the
  positions, split counts and energy totals are reported there, not checked;
- device against itself: the same run twice must leave every State and Model array and the energy books bit for bit
  equal. On CUDA this fails today (the force kernels scatter with float atomics, whose order changes from run to
  run): the check says so and is flagged as an expected failure.

On the CPU (``--device cpu``, CI's CPU mode) the "device" is the CPU too: the comparison is then CPU against CPU, and
the determinism check means what it says.

``--reference FILE reference`` runs only the CPU runs and saves them to FILE (the check script runs them in the
background while the CUDA tests run); ``--reference FILE`` without the subcommand loads them instead of running them
again, when they were run with the same parameters and versions. The check script's other helpers (settling cases,
summary.json) are in ``benchmarks/gpu_record.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from gpu_record import check, positive_int, write_json

if TYPE_CHECKING:
    from warpdem.simulation import Simulation

EPS32 = float(np.finfo(np.float32).eps)
"""Machine epsilon of float32 [-] (1.19e-7): the unit of every tolerance below."""

ENERGY_BOUNDS = {"fracture": 5.0e-3, "conversion": 5.0e-5}
"""Bounds on the worst energy balance error of each run, relative to the largest energy in play [-]: the tests' own
(tests/test_fracture.py ENERGY_BOUND for a cracking bar; tests/test_conversion.py ENERGY_BOUND for a bar converting
its middle, which carries a margin of 8 for the order of float32 atomics on a GPU). Measured on this block on the CPU:
5e-6 for both."""

CHECK_EVERY = 10
"""Steps between two readings of the energy books, the mass and the momentum [-] (as the tests read the books every
few steps: the worst error over a run is what they bound)."""

EXPECTED_CUDA_NONDETERMINISM = "force kernels still scatter with float atomics (issue 24, deterministic forces)"
"""Why two identical CUDA runs differ today: the expected failure of the determinism check on a GPU."""

SCENARIOS = ("fracture", "conversion")


# ----------------------------------------------------------------------------------------------------------------
# One run


@dataclass
class CaseRun:
    """One run of a scenario on one device: figures (JSON) and the arrays the comparisons need.

    ``window_*`` are taken after ``window`` steps (positions [m], energy lines [J], events = splits + conversions,
    the energy in play [J]),
    ``start_energy``/``end_energy`` at the start and the end [J], ``end_q`` the positions of the nodes the mesh started
    with [m] (their indices do not change when nodes split or tets convert), ``arrays`` every State and Model array
    at the end (device runs only, for the determinism check)."""

    device: str
    figures: dict[str, Any]
    window_q: np.ndarray
    window_energy: np.ndarray
    window_events: int
    window_in_play: float
    start_energy: np.ndarray
    end_energy: np.ndarray
    end_q: np.ndarray
    in_play: float
    arrays: dict[str, np.ndarray] = field(default_factory=dict)


def build(scenario: str, cells: int, steps: int, device: str) -> Simulation:
    """The scenario's block of ``cells``³ cells, its pulling rate set for a run of ``steps`` steps, a pass every
    step, as a Simulation that keeps the energy books."""
    from warpdem.bench.conversion import converting_run_block
    from warpdem.bench.fracture import cracking_block
    from warpdem.simulation import Simulation

    make = cracking_block if scenario == "fracture" else converting_run_block
    bare = make(cells, device, steps=steps, interval=1)
    # The builders make their Simulation without the energy books (a benchmark times the bare step): the same model
    # and state are set up again with the books on, as every run keeps them (the set-up evaluates the forces again).
    return Simulation(bare.model, bare.state)


def count(array: Any) -> int:
    """The int held by a one-entry device counter (reads back)."""
    return int(array.numpy()[0])


def events(sim: Simulation) -> int:
    """Node splits and tets converted since the start."""
    return count(sim.state.node_splits_total) + count(sim.state.tets_converted_total)


def mass(sim: Simulation) -> float:
    """Total mass of the live nodes and spheres [kg], summed in float64."""
    m, s = sim.model, sim.state
    n, p = count(s.node_count), count(s.particle_count)
    return float(
        m.node_mass.numpy()[:n].astype(np.float64).sum() + m.particle_mass.numpy()[:p].astype(np.float64).sum()
    )


def momentum(sim: Simulation) -> tuple[np.ndarray, float]:
    """Linear momentum Σ m v of the live nodes and spheres [kg m/s], shape (3,), and Σ |m v| (the scale its float32
    rounding is measured against) [kg m/s]; float64 sums of the float32 masses and velocities."""
    m, s = sim.model, sim.state
    n, p = count(s.node_count), count(s.particle_count)
    nodes = m.node_mass.numpy()[:n, None].astype(np.float64) * s.node_qd.numpy()[:n]
    spheres = m.particle_mass.numpy()[:p, None].astype(np.float64) * s.particle_qd.numpy()[:p]
    return nodes.sum(axis=0) + spheres.sum(axis=0), float(np.abs(nodes).sum() + np.abs(spheres).sum())


def driven_force(sim: Simulation) -> np.ndarray:
    """Σ node_f over the driven nodes [N], shape (3,): the forces of the rest of the model on them at the last
    evaluation. A driver holds its nodes' velocity, so it pushes with minus that; the rest of the model's forces on
    itself cancel (Newton's third law), so the driven nodes' forces are minus the impulse rate of the drivers on
    everything else."""
    m, s = sim.model, sim.state
    n = count(s.node_count)
    driven = m.loads.node_driver.numpy()[:n] >= 0
    return s.node_f.numpy()[:n][driven].astype(np.float64).sum(axis=0)


def gross_tet_force(sim: Simulation) -> float:
    """Σ over the live tets of Σ_a |f_a| ≤ 4 V |σ|_F / ℓ [N]: what the tets scatter onto their nodes in one force
    evaluation, before the contributions cancel in the nodes' sums. A tet's force on its node a is f_a = −V σ ∇N_a,
    and Σ_a |∇N_a| ≤ 2 (Σ_a |∇N_a|²)^½ = 4/ℓ (ℓ the tet's characteristic length, warpdem.stages.tets). Float32
    rounds each contribution and each sum by at most EPS32 of this."""
    m, s = sim.model, sim.state
    t = count(s.tet_count)
    sigma = np.linalg.norm(s.tet_stress.numpy()[:t].astype(np.float64).reshape(t, 9), axis=1)
    volume = m.tet_volume.numpy()[:t].astype(np.float64)
    length = m.tet_length.numpy()[:t].astype(np.float64)
    return float(np.sum(4.0 * volume * sigma / length))


def energy_lines(sim: Simulation) -> tuple[np.ndarray, float]:
    """Every line of the energy books [J] (warpdem.stages.energy.EnergyBalance, in field order) and the energy in
    play [J]."""
    e = sim.energy()
    return np.array(dataclasses.astuple(e), dtype=np.float64), e.in_play


def total(lines: np.ndarray) -> float:
    """EnergyBalance.total of a vector of lines [J]."""
    from warpdem.stages.energy import EnergyBalance

    return EnergyBalance(*lines.tolist()).total


def star_max(sim: Simulation) -> int:
    """The most tets around one node of the mesh [-] (24 in a Kuhn box mesh): how many float32 contributions a node's
    mass and force sums hold at most."""
    t = count(sim.state.tet_count)
    return int(np.bincount(sim.model.tet_nodes.numpy()[:t].ravel()).max())


def run_case(scenario: str, cells: int, steps: int, window: int, device: str, keep_arrays: bool) -> CaseRun:
    """Run the scenario for ``steps`` steps, one ``Simulation.advance(1)`` (one step and its pass) at a time, reading
    the driven nodes' forces around every pass, and check what every run must keep (mass, momentum, energy books).
    """
    t0 = time.perf_counter()
    sim = build(scenario, cells, steps, device)
    build_time = time.perf_counter() - t0
    dt = sim.model.dt
    stars = star_max(sim)
    original = (cells + 1) ** 3

    # A pass re-evaluates the forces (dt = 0) between the step's second half kick and the next step's first: each
    # half kick's impulse takes the forces it used, so the forces are read before the pass as well as after it.
    before_pass: list[np.ndarray] = []
    for name in ("fracture_pass", "conversion_pass"):
        method = getattr(sim, name)

        def recorded(*args: Any, method: Any = method, **kwargs: Any) -> Any:
            before_pass.append(driven_force(sim))
            return method(*args, **kwargs)

        setattr(sim, name, recorded)  # Simulation.advance calls self.<pass>()

    mass0 = mass(sim)
    p0, p_abs = momentum(sim)
    start, in_play = energy_lines(sim)
    # Velocity Verlet: Δ(Σ m v) over a step is ½ dt (F_n + F_{n+1}) of the net external force; the drivers' is minus
    # the driven nodes' forces. The first half kick uses the set-up's forces.
    impulse = -0.5 * dt * driven_force(sim)
    gross = 0.5 * dt * gross_tet_force(sim)
    worst = {"mass": 0.0, "momentum": 0.0, "momentum_ratio": 0.0, "balance": 0.0}
    momentum_tolerance = 0.0
    first_event = None
    window_q = window_energy = None
    window_events, window_in_play, window_u_max = 0, 0.0, 0.0
    t_run = time.perf_counter()
    for k in range(1, steps + 1):
        before_pass.clear()
        sim.advance(1)
        after = driven_force(sim)
        impulse_now = impulse - 0.5 * dt * (before_pass[0] if before_pass else after)
        impulse = impulse_now - 0.5 * dt * after
        step_gross = gross_tet_force(sim)
        gross_now = gross + 0.5 * dt * step_gross
        gross = gross_now + 0.5 * dt * step_gross
        n_events = events(sim)
        if n_events and first_event is None:
            first_event = k
        if k == window:
            live = count(sim.state.node_count)
            window_q = sim.state.node_q.numpy()[:live].astype(np.float64)
            window_u_max = float(np.abs(window_q - sim.model.node_ref_q.numpy()[:live]).max())
            window_energy, window_in_play = energy_lines(sim)
            window_events = n_events
        if k % CHECK_EVERY == 0 or k == steps:
            p, p_abs_now = momentum(sim)
            p_abs = max(p_abs, p_abs_now)
            # The tolerance of Σ m v - Σ m v(0) = impulse, from float32 rounding:
            # - the host's sums of float32 m and v at both ends: EPS32 Σ|m v| each;
            # - masses re-lumped at splits and conversions (each node's mass a float32 sum of ≤ `stars` tets' ρV/4,
            #   each rounded by EPS32/2): (stars/2) EPS32 Σ|m v| of momentum, with the velocities kept;
            # - the forces: each evaluation scatters the tets' contributions (Σ|f_a| = `gross`) into float32 nodal
            #   sums whose internal forces cancel only to EPS32 of what they sum; the contacts and cohesive elements
            #   carry at most the stress of the tets behind them: a factor 2. Over the run: EPS32 × 2 ∫ gross dt.
            momentum_tolerance = EPS32 * ((2.0 + 0.5 * stars) * p_abs + 2.0 * gross_now)
            residual = float(np.abs(p - p0 - impulse_now).max())
            worst["momentum"] = max(worst["momentum"], residual)
            worst["momentum_ratio"] = max(worst["momentum_ratio"], residual / momentum_tolerance)
            worst["mass"] = max(worst["mass"], abs(mass(sim) - mass0) / mass0)
            lines, now_in_play = energy_lines(sim)
            in_play = max(in_play, now_in_play)
            worst["balance"] = max(worst["balance"], abs(total(lines) - total(start)) / in_play)
    run_time = time.perf_counter() - t_run
    end, _ = energy_lines(sim)
    if window_q is None or window_energy is None:
        raise ValueError(f"the window ({window} steps) must lie within the run ({steps} steps)")
    figures = {
        "device": str(device),
        "tets": count(sim.state.tet_count),
        "nodes_start": original,
        "nodes_end": count(sim.state.node_count),
        "spheres_end": count(sim.state.particle_count),
        "splits": count(sim.state.node_splits_total),
        "converted": count(sim.state.tets_converted_total),
        "first_event_step": first_event,
        "events_at_window": window_events,
        "window_u_max": window_u_max,
        "dt": dt,
        "build_s": build_time,
        "run_s": run_time,
        "mass_rel_change": worst["mass"],
        # Each node's mass is a float32 sum of ≤ `stars` tets' ρV/4, rounded by ≤ (stars/2) EPS32 of it, at the start
        # and after any re-lumping: |ΔM|/M ≤ stars EPS32 (2.9e-6 for 24 tets; a lost tet weighs 1/(6 cells³)).
        "mass_tolerance": stars * EPS32,
        "momentum_residual": worst["momentum"],
        "momentum_tolerance": momentum_tolerance,
        "momentum_residual_over_tolerance": worst["momentum_ratio"],
        "driver_impulse": impulse.tolist(),
        "balance_error": worst["balance"],
        "balance_bound": ENERGY_BOUNDS[scenario],
        "energy_total_start": total(start),
        "energy_total_end": total(end),
        "in_play_max": in_play,
    }
    arrays = {}
    if keep_arrays:
        for prefix, obj in (("state.", sim.state), ("model.", sim.model)):
            arrays.update({prefix + name: a.numpy() for name, a in obj.arrays().items()})
    return CaseRun(
        device=str(device),
        figures=figures,
        window_q=window_q,
        window_energy=window_energy,
        window_events=window_events,
        window_in_play=window_in_play,
        start_energy=start,
        end_energy=end,
        end_q=sim.state.node_q.numpy()[:original].astype(np.float64),
        in_play=in_play,
        arrays=arrays,
    )


# ----------------------------------------------------------------------------------------------------------------
# Checks


def run_checks(scenario: str, run: CaseRun, label: str) -> list[dict]:
    """What every run must keep, checked on one run (``label``: which, in the checks' names): mass, momentum, energy
    books, and the block cracking."""
    f, tag = run.figures, f"{scenario} {label}"
    kind = "splits" if scenario == "fracture" else "converted"
    return [
        check(
            f"{tag}: total mass kept",
            f["mass_rel_change"] <= f["mass_tolerance"],
            {k: f[k] for k in ("mass_rel_change", "mass_tolerance")},
        ),
        check(
            f"{tag}: momentum change = the drivers' impulse",
            # Each reading against the tolerance at its time (the tolerance grows over the run).
            f["momentum_residual_over_tolerance"] <= 1.0,
            {
                k: f[k]
                for k in (
                    "momentum_residual",
                    "momentum_tolerance",
                    "momentum_residual_over_tolerance",
                    "driver_impulse",
                )
            },
        ),
        check(
            f"{tag}: energy books close",
            f["balance_error"] <= f["balance_bound"],
            {k: f[k] for k in ("balance_error", "balance_bound", "energy_total_start", "energy_total_end")},
        ),
        check(
            f"{tag}: the block {'cracks' if scenario == 'fracture' else 'converts'} after the window",
            f["events_at_window"] == 0 and f[kind] > 0,
            {k: f[k] for k in ("events_at_window", kind, "first_event_step")},
            "" if f["events_at_window"] == 0 else "events before the window: it is too long to compare states in",
        ),
    ]


def compare_checks(scenario: str, ref: CaseRun, dev: CaseRun, cells: int, window: int) -> list[dict]:
    """Device against the CPU: the early window checked, the end reported with it."""
    h = 1.0 / cells  # mesh size [m]: the cube's side is 1 m
    # The early window: both runs start from the same host-built state and, before anything splits or converts, are
    # a driven linear elastic body, so they differ by rounding that adds up step by step without growing (stable
    # Verlet steps: ω dt ≤ 2): each step a node's force is a float32 sum of ≤ 24 contributions (a Kuhn node's tets)
    # in another order (float atomics) and with other fused multiply-adds, off by ≤ 24 EPS32 of what it sums, and
    # the displacements follow: ≤ 2 × 24 EPS32 × steps of the largest displacement. Positions x = X + u are rounded
    # to float32 on each device: two ulps (2 EPS32 |x|) more. Energies (quadratic in the state): twice that of the
    # energy in play, each line, with one step more for the set-up's evaluation.
    n = min(len(ref.window_q), len(dev.window_q))
    u_max = max(ref.figures["window_u_max"], dev.figures["window_u_max"])  # the largest displacement [m]
    q_max = float(np.abs(ref.window_q).max())
    dq = float(np.abs(ref.window_q[:n] - dev.window_q[:n]).max()) if n else math.inf
    q_tolerance = 2 * 24 * EPS32 * window * u_max + 2 * EPS32 * q_max
    e_tolerance = 2 * 24 * EPS32 * (window + 1) * max(ref.window_in_play, dev.window_in_play)
    de_start = float(np.abs(ref.start_energy - dev.start_energy).max())
    de_window = float(np.abs(ref.window_energy - dev.window_energy).max())
    same_nodes = len(ref.window_q) == len(dev.window_q)
    # After cracking the runs diverge (which node splits first decides the rest): reported with the window's check,
    # not checked. Each run's books close within its bound (checked on each run), so their totals may differ by the
    # sum of both bounds' worth of energy in play.
    after = {
        "max_dq_over_h_original_nodes": float(np.abs(ref.end_q - dev.end_q).max()) / h,
        "splits_cpu": ref.figures["splits"],
        "splits_device": dev.figures["splits"],
        "converted_cpu": ref.figures["converted"],
        "converted_device": dev.figures["converted"],
        "first_event_cpu": ref.figures["first_event_step"],
        "first_event_device": dev.figures["first_event_step"],
        "energy_total_cpu_J": total(ref.end_energy),
        "energy_total_device_J": total(dev.end_energy),
        "closure_bound_J": ENERGY_BOUNDS[scenario] * (ref.in_play + dev.in_play),
    }
    tag = f"{scenario} {dev.device} vs cpu"
    return [
        check(
            f"{tag}: positions in the early window ({window} steps)",
            same_nodes and ref.window_events == dev.window_events and dq <= q_tolerance,
            {
                "max_dq_over_h": dq / h,
                "tolerance_over_h": q_tolerance / h,
                "events_cpu": ref.window_events,
                "events_device": dev.window_events,
                "nodes_cpu": len(ref.window_q),
                "nodes_device": len(dev.window_q),
                "after_cracking_reported_not_checked": after,
            },
        ),
        check(
            f"{tag}: energy lines at the start and in the early window",
            de_start <= e_tolerance and de_window <= e_tolerance,
            {"max_dE_start_J": de_start, "max_dE_window_J": de_window, "tolerance_J": e_tolerance},
        ),
    ]


def determinism_check(scenario: str, one: CaseRun, two: CaseRun) -> dict:
    """The same run twice on one device: every State and Model array and the energy books bit for bit equal."""
    differ = []
    for name, a in one.arrays.items():
        b = two.arrays.get(name)
        # Bytes, not values: NaN patterns and signed zeros count, and NaN == NaN.
        if b is None or a.shape != b.shape or a.dtype != b.dtype or a.tobytes() != b.tobytes():
            differ.append(name)
    energy_same = one.end_energy.tobytes() == two.end_energy.tobytes()
    passed = not differ and energy_same and set(one.arrays) == set(two.arrays)
    on_cuda = one.device.startswith("cuda")
    if passed:
        message = ""
    elif on_cuda:
        message = f"expected on CUDA: {EXPECTED_CUDA_NONDETERMINISM}"
    else:
        message = "two runs on the CPU differ: the CPU path must be deterministic"
    return check(
        f"{scenario} on {one.device}: determinism (same run twice, bit for bit)",
        passed,
        {
            "arrays_compared": len(one.arrays),
            "arrays_differing": len(differ),
            "first_differing": differ[:8],
            "energy_books_equal": energy_same,
        },
        message,
        expected=on_cuda and not passed,
    )


# ----------------------------------------------------------------------------------------------------------------
# The CPU reference, saved and loaded


def save_reference(path: Path, params: dict, runs: dict[str, CaseRun]) -> None:
    """Write the CPU runs (without their end arrays) to ``path`` (.npz), with the parameters they were run with."""
    data: dict[str, Any] = {"params": np.array(json.dumps(params))}
    for scenario, r in runs.items():
        data[f"{scenario}.figures"] = np.array(json.dumps(r.figures))
        data[f"{scenario}.scalars"] = np.array([r.window_events, r.window_in_play, r.in_play], dtype=np.float64)
        for name in ("window_q", "window_energy", "start_energy", "end_energy", "end_q"):
            data[f"{scenario}.{name}"] = getattr(r, name)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **data)
    tmp.replace(path)


def load_reference(path: Path, params: dict) -> dict[str, CaseRun] | None:
    """The CPU runs saved by :func:`save_reference`, or None when there is no such file or it was run with other
    parameters."""
    if not path.is_file():
        return None
    with np.load(path) as data:
        if json.loads(str(data["params"])) != params:
            return None
        runs = {}
        for scenario in params["scenarios"]:
            events_, window_in_play, in_play = data[f"{scenario}.scalars"]
            runs[scenario] = CaseRun(
                device="cpu",
                figures=json.loads(str(data[f"{scenario}.figures"])),
                window_q=data[f"{scenario}.window_q"],
                window_energy=data[f"{scenario}.window_energy"],
                window_events=int(events_),
                window_in_play=float(window_in_play),
                start_energy=data[f"{scenario}.start_energy"],
                end_energy=data[f"{scenario}.end_energy"],
                end_q=data[f"{scenario}.end_q"],
                in_play=float(in_play),
            )
    return runs


def reference_params(args: argparse.Namespace) -> dict:
    """What a saved CPU reference must have been run with to be used."""
    import warp as wp

    return {
        "scenarios": list(args.scenarios),
        "cells": args.cells,
        "steps": args.steps,
        "window": window_of(args),
        "warp": wp.config.version,
        "numpy": np.__version__,
    }


def window_of(args: argparse.Namespace) -> int:
    """The early window [steps]: ``--window``, or an eighth of the run (the builders' rate makes the weakest grains
    fail a quarter of the way through: nothing splits or converts before; measured: the first split at step 35 of
    160, the first conversion at 32 of 160)."""
    return args.window if args.window else max(1, args.steps // 8)


def cpu_reference(args: argparse.Namespace) -> dict[str, CaseRun]:
    """The CPU runs: loaded from ``--reference`` when it holds runs with these parameters, else run (and saved
    there when given)."""
    params = reference_params(args)
    if args.reference is not None:
        runs = load_reference(args.reference, params)
        if runs is not None:
            print(f"CPU reference loaded from {args.reference}", flush=True)
            return runs
    runs = {}
    for scenario in args.scenarios:
        runs[scenario] = run_case(scenario, args.cells, args.steps, window_of(args), "cpu", keep_arrays=False)
        print(f"CPU reference {scenario}: {json.dumps(runs[scenario].figures)}", flush=True)
    if args.reference is not None:
        save_reference(args.reference, params, runs)
    return runs


def compare(args: argparse.Namespace) -> int:
    """The comparison: the CPU reference, two runs on the device, the checks; writes OUT/compare.json."""
    from warpdem.cli import init_warp

    init_warp()
    window = window_of(args)
    started = time.perf_counter()
    ref = cpu_reference(args)
    checks: list[dict] = []
    figures: dict[str, Any] = {}
    for scenario in args.scenarios:
        first = len(checks)
        one = run_case(scenario, args.cells, args.steps, window, args.device, keep_arrays=True)
        two = run_case(scenario, args.cells, args.steps, window, args.device, keep_arrays=True)
        figures[scenario] = {"cpu": ref[scenario].figures, "device_1": one.figures, "device_2": two.figures}
        checks += run_checks(scenario, ref[scenario], "CPU reference")
        checks += run_checks(scenario, one, f"on {args.device}")
        checks += compare_checks(scenario, ref[scenario], one, args.cells, window)
        checks.append(determinism_check(scenario, one, two))
        for c in checks[first:]:
            print(f"{'PASS' if c['passed'] else 'FAIL'}  {c['name']}  {c['message']}", flush=True)
    result = {
        "device": args.device,
        "cells": args.cells,
        "steps": args.steps,
        "window": window,
        "wall_s": time.perf_counter() - started,
        "runs": figures,
        "checks": checks,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "compare.json", result)
    return 0 if all(c["passed"] for c in checks) else 1


# ----------------------------------------------------------------------------------------------------------------
# Command line


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python benchmarks/gpu_compare.py",
        description="CPU against a device and a device against itself on a cracking and a converting block "
        "(writes OUT/compare.json; exit 1 when a check failed).",
    )
    p.add_argument("--device", default="cuda:0", help="Warp device to compare with the CPU [cuda:0]")
    p.add_argument("--out", type=Path, default=Path("out/gpu_check"), help="output folder [out/gpu_check]")
    p.add_argument("--cells", type=positive_int, default=6, help="cells per side of the blocks [6: 1 296 tets]")
    p.add_argument("--steps", type=positive_int, default=160, help="steps of each run [160]")
    p.add_argument("--window", type=positive_int, help="steps of the early window [steps/8]")
    p.add_argument("--scenarios", nargs="+", choices=SCENARIOS, default=list(SCENARIOS), help="runs to do [both]")
    p.add_argument(
        "--reference", type=Path, help="CPU reference file (.npz): loaded when it matches, else written after the runs"
    )
    sub = p.add_subparsers(dest="command", metavar="{reference}")
    sub.add_parser("reference", help="only the CPU runs, saved to --reference")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.command == "reference":
        if args.reference is None:
            parser().error("reference needs --reference FILE (before the subcommand)")
        from warpdem.cli import init_warp

        init_warp()
        cpu_reference(args)
        return 0
    return compare(args)


if __name__ == "__main__":
    sys.exit(main())
