"""Conversion (issue 10 §8): the cost of one conversion pass (``Simulation.conversion_pass``: the criterion, spheres,
bonds and couplings written, nodes re-lumped, the surface and contact lists rebuilt, forces re-evaluated) in units
of force steps of the same mesh, on the same stretched cube with a seeded random 1 % of its tets, all above the
Tresca threshold, allowed to convert (:func:`converting_block`); and the step rate of a converting run, the pulled
cube of grains with its central slab allowed to convert, a pass every 1 or 10 steps (:func:`converting_run_block`).
The two pass benchmarks and the two runs share the block, the timing and the command line (:func:`run_pass_bench`).
"""

from __future__ import annotations

import functools
import resource
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .common import timed, write_json
from .fracture import (
    STRETCH,
    TENSILE_STRENGTH,
    bench_cracking_run,
    bench_fracture_pass,
    cells_for,
    force_step_time,
    format_pass_row,
    format_run_row,
    pulled_granite,
    stretched_granite,
)

if TYPE_CHECKING:
    from ..model import Model, State
    from ..simulation import Simulation


TRESCA_STRENGTH = TENSILE_STRENGTH
"""τ_f of the conversion benchmark's granite [Pa]: under :func:`stretched_granite`'s stretch (σ_xx = 3 T_f, σ_yy =
σ_zz = T_f for ν = 0.25) a tet's Tresca stress (σ1 − σ3)/2 = T_f is 1/0.9 of the threshold 0.9 τ_f."""

CONVERSION_FRACTION = 0.9
"""The fraction of τ_f at which a tet converts (CIMNE's 90 %) [-]."""

CONVERSION_SLAB = 0.25
"""Width along x [m] of the central slab of the converting run's cube whose tets may convert."""


def spread_tets(tets: int, fraction: float, seed: int) -> np.ndarray:
    """A seeded random ``fraction`` of ``tets`` tets (spread over the whole mesh), as a mask, shape (tets,), bool;
    at least one tet."""
    mask = np.zeros(tets, dtype=bool)
    count = min(tets, max(1, round(fraction * tets)))
    mask[np.random.default_rng(seed).choice(tets, size=count, replace=False)] = True
    return mask


def converting_block(cells: int, device: str, may_convert: np.ndarray, stretch: float = STRETCH) -> tuple[Model, State]:
    """The conversion pass case: :func:`stretched_granite` at σ_xx = ``stretch`` × T_f with conversion on (Tresca,
    0.9 τ_f = 0.9 TRESCA_STRENGTH, a pass every step, one sphere per tet) and ``may_convert`` (bool per tet) the tets
    that may convert. Particle, bond and coupling slots are reserved for the case where every tet that may convert
    does (:func:`lattice_counts`), so the pass does not grow them. Returns (model, state)."""
    from ..stages.conversion import ConversionProps, attach_conversion, regrow_bonds

    flagged = int(np.count_nonzero(may_convert))
    model, state = stretched_granite(cells, device, stretch=stretch, particle_capacity=flagged)
    bonds, couplings = lattice_counts(model, state, may_convert)
    props = ConversionProps(criterion="tresca", fraction=CONVERSION_FRACTION, tresca_strength=TRESCA_STRENGTH)
    model, state = attach_conversion(
        model, state, [props], check_interval=1, may_convert=may_convert, coupling_capacity=max(couplings, 1)
    )
    return regrow_bonds(model, state, bonds)


def lattice_counts(model: Model, state: State, mask: np.ndarray) -> tuple[int, int]:
    """What a conversion of exactly the tets in ``mask`` (bool per tet, shape (tet_count,)) makes, counted on the host
    by the rules of warpdem.stages.conversion: (bonds, one per pair of tets in the mask that share an edge
    (warpdem.stages.lattice.edge_pairs); couplings, one per pair of a tet in the mask and an active tet outside it that
    share an edge)."""
    from ..stages.lattice import edge_pairs
    from ..tables import TET_EDGES

    count = len(mask)
    tets = model.tet_nodes.numpy()[:count].astype(np.int64)
    active = state.tet_active.numpy()[:count] != 0
    bonds = len(edge_pairs(tets, mask))
    # The tets that share an edge with one in the mask: edges keyed by their sorted node pair, grouped by key.
    ends = np.sort(tets[:, TET_EDGES], axis=2).reshape(-1, 2)
    key = ends[:, 0] * (int(tets.max()) + 1) + ends[:, 1]
    owner = np.repeat(np.arange(count), 6)
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    group = np.cumsum(np.r_[True, key[1:] != key[:-1]]) - 1
    touched = np.zeros(group[-1] + 1, dtype=bool)
    touched[group[mask[owner]]] = True
    near = np.zeros(count, dtype=bool)
    near[owner[touched[group]]] = True
    pairs = edge_pairs(tets, near)
    i, j = pairs[:, 0], pairs[:, 1]
    couplings = (mask[i] & ~mask[j] & active[j]) | (mask[j] & ~mask[i] & active[i])
    return bonds, int(np.count_nonzero(couplings))


def due_tets(model: Model, state: State) -> np.ndarray:
    """The tets a conversion pass must convert, found on the host by brute force (the rules of
    warpdem.stages.conversion): live, active tets with ``tet_may_convert`` of a material that converts, whose stress
    (``state.tet_stress``, brought up to date here) reaches the criterion of their material — Tresca (σ1 − σ3)/2 ≥ f τ_f
    or Rankine σ1 ≥ f T_f, principal stresses in float64. Returns a bool mask, shape (tet_count,)."""
    from ..kernels.conversion import CRITERION_RANKINE, CRITERION_TRESCA
    from ..stages.tets import eval_tet_stresses

    eval_tet_stresses(model, state)
    count = int(state.tet_count.numpy()[0])
    table = model.conversion_material_table.numpy()
    material = model.tet_material.numpy()[:count]
    criterion = table["criterion"][material]
    if not np.all(np.isin(criterion, (int(CRITERION_TRESCA), int(CRITERION_RANKINE)))):
        raise NotImplementedError("due_tets counts Tresca and Rankine tets only")
    sigma = np.linalg.eigvalsh(state.tet_stress.numpy()[:count].astype(np.float64))  # ascending: σ3, σ2, σ1
    fraction = table["fraction"][material].astype(np.float64)
    tresca = 0.5 * (sigma[:, 2] - sigma[:, 0]) >= fraction * table["tresca_strength"][material]
    rankine = sigma[:, 2] >= fraction * table["tensile_strength"][material]
    reached = np.where(criterion == int(CRITERION_TRESCA), tresca, rankine)
    live = (state.tet_active.numpy()[:count] != 0) & (model.tet_may_convert.numpy()[:count] != 0)
    return live & (table["converts"][material] != 0) & reached


@dataclass
class ConversionPassResult:
    """The conversion pass against the force step on one mesh: sizes, the tets that may convert and those due
    (:func:`due_tets`), what the pass did (tets converted, spheres spawned, bonds and couplings made against those the
    tets due make (:func:`lattice_counts`), whether a capacity grew), wall times [s] (build, the Simulation's set-up
    (contact lists, forces, the conversion pass's stars of all live tets), one force step = the fastest run of
    ``steps`` over steps, the fastest pass), the pass in force steps, and peak host RSS [MB]."""

    device: str
    tets: int
    nodes: int
    may_convert: int
    due: int
    converted: int
    spawned: int
    bonds_due: int
    bonds: int
    couplings_due: int
    couplings: int
    grew: bool
    build_time: float
    setup_time: float
    steps: int
    step_time: float
    pass_time: float
    pass_in_steps: float
    peak_rss_mb: float
    books: bool = True


def bench_conversion_pass(
    tets_wanted: int,
    fraction: float = 0.01,
    steps: int = 50,
    device: str = "cpu",
    repeat: int = 3,
    seed: int = 0,
    books: bool = True,
) -> ConversionPassResult:
    """Time one conversion pass (``Simulation.conversion_pass``) on the stretched block of at least ``tets_wanted``
    tets with ``fraction`` of its tets converting, against force steps of the same mesh with the pass off, as
    :func:`bench_fracture_pass` times the split pass (each repeat rebuilds the block: a pass changes the mesh), with
    the energy books kept (``books``) or not."""
    from ..simulation import Simulation

    cells = cells_for(tets_wanted)
    may_convert = spread_tets(6 * cells**3, fraction, seed)
    pass_time = float("inf")
    for r in range(repeat):
        build, (model, state) = timed(device, lambda: converting_block(cells, device, may_convert))
        if r == 0:
            due = due_tets(model, state)
            bonds_due, couplings_due = lattice_counts(model, state, due)
            step_time = force_step_time(model, state, steps, repeat, books)
            build_time = build
        setup, sim = timed(device, functools.partial(Simulation, model, state, track_energy=books))
        if r == 0:
            setup_time = setup
        seconds, report = timed(device, sim.conversion_pass)
        pass_time = min(pass_time, seconds)
    return ConversionPassResult(
        device=str(device),
        tets=int(sim.state.tet_count.numpy()[0]),
        nodes=int(sim.state.node_count.numpy()[0]),
        may_convert=int(np.count_nonzero(may_convert)),
        due=int(np.count_nonzero(due)),
        converted=report.converted,
        spawned=report.spawned,
        bonds_due=bonds_due,
        bonds=report.bonds,
        couplings_due=couplings_due,
        couplings=report.couplings,
        grew=report.grew,
        build_time=build_time,
        setup_time=setup_time,
        steps=steps,
        step_time=step_time,
        pass_time=pass_time,
        pass_in_steps=pass_time / step_time,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        books=books,
    )


def converting_run_block(
    cells: int, device: str, steps: int, interval: int, seed: int = 0, books: bool = False
) -> Simulation:
    """The converting run: :func:`pulled_granite` with conversion on in its central slab (tets whose centroid lies
    within CONVERSION_SLAB / 2 of x = 0.5 m: the block fails at its centre), Tresca with τ_f = T_f / 2 of each grain
    (σ_xx ≈ E ε in uniaxial stress reaches 0.9 × 2 τ_f just before the grain's T_f), a pass every ``interval``
    steps (0: none, the reference); the energy books kept with ``books``. Returns a Simulation."""
    import dataclasses

    from ..simulation import Simulation
    from ..stages.conversion import ConversionProps, attach_conversion

    model, state, strengths, _ = pulled_granite(cells, device, steps, seed)
    count = int(state.tet_count.numpy()[0])
    centroid_x = model.node_ref_q.numpy()[model.tet_nodes.numpy()[:count], 0].mean(axis=1)
    central = np.abs(centroid_x - 0.5) < 0.5 * CONVERSION_SLAB
    # A strength class no grain drew has no tets (and no elastic constants to calibrate bonds from): None.
    used = np.isin(np.arange(len(strengths)), model.tet_material.numpy()[:count])
    props = [
        ConversionProps(criterion="tresca", fraction=CONVERSION_FRACTION, tresca_strength=0.5 * float(t)) if u else None
        for t, u in zip(strengths, used, strict=True)
    ]
    model, state = attach_conversion(model, state, props, check_interval=max(interval, 1), may_convert=central)
    if interval == 0:  # the reference: the same model with the pass off
        model = dataclasses.replace(model, conversion_interval=0)
    return Simulation(model, state, track_energy=books)


@dataclass
class ConvertingRunResult:
    """A converting run: sizes at the start, the pass interval [steps], steps timed, wall time [s], step rate
    [steps/s] and throughput [tet-steps/s] with the passes included, and what converted (tets, spheres spawned;
    spheres, bonds and couplings at the end)."""

    device: str
    tets: int
    nodes: int
    may_convert: int
    interval: int
    steps: int
    wall_time: float
    steps_per_second: float
    tet_steps_per_second: float
    converted: int
    spawned: int
    spheres: int
    bonds: int
    couplings: int
    books: bool = True


def bench_converting_run(
    tets_wanted: int, steps: int = 200, interval: int = 1, device: str = "cpu", seed: int = 0, books: bool = True
) -> ConvertingRunResult:
    """Time ``Simulation.advance(steps - 2)`` on the converting block (:func:`converting_run_block`), passes included,
    after its first two steps (graph capture; nothing converts before a fifth of the run), with the energy books
    kept as a run keeps them (``books``)."""
    sim = converting_run_block(cells_for(tets_wanted), device, steps, interval, seed, books)
    sim.advance(2)  # capture outside the clock (the kernels were compiled by run_pass_bench's warm-up)
    wall = timed(sim.model.device, lambda: sim.advance(steps - 2))[0]
    tets = int(sim.state.tet_count.numpy()[0])
    s = sim.state
    return ConvertingRunResult(
        device=str(device),
        tets=tets,
        nodes=int(s.node_count.numpy()[0]),
        may_convert=int(np.count_nonzero(sim.model.tet_may_convert.numpy()[:tets])),
        interval=interval,
        steps=steps - 2,
        wall_time=wall,
        steps_per_second=(steps - 2) / wall,
        tet_steps_per_second=tets * (steps - 2) / wall,
        converted=int(s.tets_converted_total.numpy()[0]),
        spawned=int(s.spheres_spawned_total.numpy()[0]),
        spheres=int(s.particle_count.numpy()[0]),
        bonds=int(s.bond_count.numpy()[0]),
        couplings=int(s.coupling_count.numpy()[0]),
        books=books,
    )


def format_conversion_pass_row(r: ConversionPassResult, header: bool) -> str:
    line = (
        f"{r.device:<8}{r.tets:>10}{r.nodes:>9}{r.due:>7}{r.converted:>10}{r.spawned:>8}{r.bonds:>7}{r.couplings:>10}"
        f"{r.build_time:>9.2f}{r.setup_time:>9.2f}{r.step_time * 1e3:>10.2f}{r.pass_time * 1e3:>10.1f}"
        f"{r.pass_in_steps:>9.1f}{r.peak_rss_mb:>9.0f}"
        + ("   GREW" if r.grew else "")
        + ("" if r.converted == r.due else "   CONVERTED != DUE")
        + ("" if (r.bonds, r.couplings) == (r.bonds_due, r.couplings_due) else "   BONDS/COUPLINGS != DUE")
    )
    if not header:
        return line
    head = (
        f"{'device':<8}{'tets':>10}{'nodes':>9}{'due':>7}{'converted':>10}{'spheres':>8}{'bonds':>7}{'couplings':>10}"
        f"{'build s':>9}{'setup s':>9}{'step ms':>10}{'pass ms':>10}{'steps':>9}{'RSS MB':>9}"
    )
    return "\n".join(
        [
            f"conversion pass (books {'on' if r.books else 'off'}; steps = pass in force steps of the same mesh; "
            "target < 20):",
            head,
            "-" * len(head),
            line,
        ]
    )


def format_converting_run_row(r: ConvertingRunResult, header: bool) -> str:
    line = (
        f"{r.device:<8}{r.tets:>10}{r.may_convert:>9}{r.interval:>9}{r.steps:>7}{r.wall_time:>9.2f}"
        f"{r.steps_per_second:>9.1f}{r.tet_steps_per_second / 1e6:>15.2f}{r.converted:>10}{r.spheres:>8}{r.bonds:>7}"
        f"{r.couplings:>10}"
    )
    if not header:
        return line
    head = (
        f"{'device':<8}{'tets':>10}{'may':>9}{'interval':>9}{'steps':>7}{'wall s':>9}{'steps/s':>9}"
        f"{'M tet-steps/s':>15}{'converted':>10}{'spheres':>8}{'bonds':>7}{'couplings':>10}"
    )
    title = f"converting run (passes included; books {'on' if r.books else 'off'}):"
    return "\n".join([title, head, "-" * len(head), line])


PASS_BENCHES = {
    "fracture": (bench_fracture_pass, bench_cracking_run, format_pass_row, format_run_row, "splits"),
    "conversion": (
        bench_conversion_pass,
        bench_converting_run,
        format_conversion_pass_row,
        format_converting_run_row,
        "converted",
    ),
}
"""The benchmarks of a between-steps pass: the pass and run measurements, their row formats, and the field of a pass
result that must equal its ``due``."""


def run_pass_bench(
    kind: str,
    sizes: list[int],
    fraction: float,
    steps: int,
    run_sizes: list[int],
    run_steps: int,
    intervals: list[int],
    device: str,
    json_path: Path | None = None,
    repeat: int = 3,
    seed: int = 0,
    books: bool = True,
) -> int:
    """``python -m warpdem bench fracture|conversion`` (``kind``): print the pass table and the run table, the energy
    books kept (``books``) as a run keeps them; returns the exit status (1 when a pass changed other than the nodes or
    tets due)."""
    bench_pass, bench_run, format_pass, format_run, done = PASS_BENCHES[kind]
    # Compile every kernel of the pass and the step on a small block first, so no size pays for it.
    bench_pass(6 * 4**3, 0.05, 2, device, 1, seed, books)
    passes, runs = [], []
    for n in sizes:
        passes.append(bench_pass(n, fraction, steps, device, repeat, seed, books))
        print(format_pass(passes[-1], header=len(passes) == 1), flush=True)
    if passes and run_sizes:
        print()
    for n in run_sizes:
        for interval in intervals:
            runs.append(bench_run(n, run_steps, interval, device, seed, books))
            print(format_run(runs[-1], header=len(runs) == 1), flush=True)
    write_json(json_path, {"passes": [asdict(r) for r in passes], "runs": [asdict(r) for r in runs]})
    return 0 if all(getattr(r, done) == r.due for r in passes) else 1


# ----------------------------------------------------------------------------------------------------------------
# Rigid blocks (issue 11 §5)
