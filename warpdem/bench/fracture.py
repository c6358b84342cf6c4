"""Fracture (issue 9 §8): the cost of one split pass (``Simulation.fracture_pass``: nodal stresses, candidates, rounds
of claims, the splits, cohesive elements born, the surface and FEM contact lists rebuilt, forces re-evaluated) in
units of force steps of the same mesh, on a granite cube of Kuhn tets (about 0.2 M tets by default; the documented
figure is 1 M) stretched in uniaxial strain to 3 T_f with a seeded random 1 % of its nodes free to split
(:func:`stretched_block`); and the step rate of a cracking run, a smaller cube of grains of random strength pulled
apart at a constant strain rate with a pass every 1 or 10 steps (:func:`cracking_block`).
"""

from __future__ import annotations

import functools
import resource
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .common import GRANITE, timed

if TYPE_CHECKING:
    from ..model import Model, State
    from ..simulation import Simulation


TENSILE_STRENGTH = 10.0e6
"""T_f of the fracture benchmark's granite [Pa] (granite: 5–25 MPa)."""

FRACTURE_ENERGY = 100.0
"""Γ of the fracture benchmark's granite [J/m²] (granite: ~50–200 J/m²)."""

STRETCH = 3.0
"""σ_xx of the stretched block over T_f [-]. The block is stretched in uniaxial strain (σ_xx = (λ + 2μ) ε) with its
x-faces held: as its free lateral faces relax towards uniaxial stress (σ_xx = E ε, 5/6 of it for ν = 0.25) and
overshoot, σ_xx stays above 2/3 of the initial value, so every node stays above T_f while force steps are timed."""


def uniaxial_strain_modulus(youngs_modulus: float, poisson_ratio: float) -> float:
    """The P-wave modulus λ + 2μ = E (1 − ν) / ((1 + ν)(1 − 2ν)) [Pa]: σ_xx / ε_xx in uniaxial strain."""
    e, nu = youngs_modulus, poisson_ratio
    return e * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))


def spread_nodes(cells: int, fraction: float, seed: int) -> np.ndarray:
    """A seeded random ``fraction`` of the nodes of a ``cells``³ Kuhn box mesh that lie strictly inside it along x
    (their stars have tets on both sides of every plane x = const through them), as a mask over the nodes, shape
    ((cells + 1)³,), bool; at least one node."""
    side = cells + 1
    i = np.arange(side**3) % side
    inner = np.flatnonzero((i > 0) & (i < cells))
    count = min(len(inner), max(1, round(fraction * side**3)))
    mask = np.zeros(side**3, dtype=bool)
    mask[np.random.default_rng(seed).choice(inner, size=count, replace=False)] = True
    return mask


def stretched_granite(
    cells: int,
    device: str,
    *,
    stretch: float = STRETCH,
    node_capacity: int | None = None,
    particle_capacity: int | None = None,
) -> tuple[Model, State]:
    """The block of the pass benchmarks (fracture, conversion): a granite cube of side 1 m, ``cells``³ cells of 6
    Kuhn tets, stretched along x in uniaxial strain to σ_xx = ``stretch`` × T_f (displacement u = ε X, x-faces held,
    at rest, no gravity). Returns (model, state) with the stretch in ``state.node_u``/``node_q``; ``node_capacity``
    leaves room for split daughters, ``particle_capacity`` for spheres spawned by conversion.

    Every tet reproduces the linear displacement exactly (the patch test), so each holds σ_xx = (λ + 2μ) ε = stretch ×
    T_f and σ_yy = σ_zz = λ ε = stretch × T_f ν / (1 − ν) (= stretch × T_f / 3 for ν = 0.25)."""
    import warp as wp

    from ..build.builder import ModelBuilder
    from ..build.mesh import box_mesh

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (cells, cells, cells))
    held = (points[:, 0] == 0.0) | (points[:, 0] == 1.0)
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("granite", **GRANITE)
    b.add_tet_mesh(points, tets, "granite", fixed_nodes=held)
    model, state = b.finalize(
        device, safety_factor=0.5, node_capacity=node_capacity, particle_capacity=particle_capacity
    )
    strain = stretch * TENSILE_STRENGTH / uniaxial_strain_modulus(GRANITE["youngs_modulus"], GRANITE["poisson_ratio"])
    u = np.zeros((model.node_capacity, 3), dtype=np.float32)
    u[: len(points), 0] = strain * points[:, 0]
    q = model.node_ref_q.numpy() + u
    state.node_u.assign(wp.array(u, dtype=wp.vec3, device=model.device))
    state.node_q.assign(wp.array(q, dtype=wp.vec3, device=model.device))
    return model, state


def stretched_block(
    cells: int, device: str, may_split: np.ndarray, node_capacity: int | None = None
) -> tuple[Model, State]:
    """The fracture pass case: :func:`stretched_granite` at σ_xx = STRETCH × T_f with fracture on, a pass every step
    and ``may_split`` (bool per node) the nodes that may split. Returns (model, state); ``node_capacity`` leaves room
    for the daughters."""
    from ..stages.fracture import FractureProps, attach_fracture

    model, state = stretched_granite(cells, device, node_capacity=node_capacity)
    props = FractureProps(tensile_strength=TENSILE_STRENGTH, fracture_energy=FRACTURE_ENERGY)
    return attach_fracture(model, state, [props], check_interval=1, may_split=may_split)


def qualifying_nodes(model: Model, state: State, may_split: np.ndarray) -> int:
    """How many nodes the split pass must split, counted on the host by brute force (the rules of
    warpdem.stages.fracture): nodes with ``may_split``, whose volume-weighted average of their tets' stresses (LDEC eq.
    1) has σ1 ≥ the least T_f of their tets' materials, and whose star has tets on both sides of the plane through the
    node normal to p1. Nodes that share a tet are all counted: the pass's rounds split them one after another. (The pass
    also asks for a face between the two sides; a node's star in a conforming mesh such as the Kuhn box is
    face-connected around it, so tets on both sides imply one.)"""
    nodes = int(state.node_count.numpy()[0])
    tcount = int(state.tet_count.numpy()[0])
    tets = model.tet_nodes.numpy()[:tcount].astype(np.int64)
    live = state.tet_active.numpy()[:tcount] != 0
    tets = tets[live]
    sigma = state.tet_stress.numpy()[:tcount][live].astype(np.float64)
    volume = model.tet_volume.numpy()[:tcount][live].astype(np.float64)
    strength = model.fracture_material_table.numpy()["tensile_strength"].astype(np.float64)
    tet_tf = strength[model.tet_material.numpy()[:tcount][live]]
    q = state.node_q.numpy()[:nodes].astype(np.float64)
    chosen = np.asarray(may_split, dtype=bool)[:nodes]
    # The incidences (tet, corner) of the nodes that may split.
    tet_of, corner = np.nonzero(chosen[tets])
    node_of = tets[tet_of, corner]
    weight_sum = np.zeros(nodes)
    stress_sum = np.zeros((nodes, 3, 3))
    tf = np.full(nodes, np.inf)
    np.add.at(weight_sum, node_of, volume[tet_of])
    np.add.at(stress_sum, node_of, volume[tet_of, None, None] * sigma[tet_of])
    np.minimum.at(tf, node_of, tet_tf[tet_of])
    ids = np.flatnonzero(chosen & (weight_sum > 0.0))
    values, vectors = np.linalg.eigh(stress_sum[ids] / weight_sum[ids, None, None])
    p1 = np.zeros((nodes, 3))
    p1[ids] = vectors[:, :, -1]
    above = np.zeros(nodes, dtype=bool)
    above[ids] = values[:, -1] >= tf[ids]
    side = np.einsum("ij,ij->i", q[tets[tet_of]].mean(axis=1) - q[node_of], p1[node_of]) > 0.0
    plus = np.zeros(nodes, dtype=bool)
    minus = np.zeros(nodes, dtype=bool)
    plus[node_of[side]] = True
    minus[node_of[~side]] = True
    return int(np.count_nonzero(above & plus & minus))


def cells_for(tets_wanted: int) -> int:
    """Cells per side of the smallest Kuhn cube (6 tets per cell) with at least ``tets_wanted`` tets; at least 2
    (1 000 000 tets: 56³ cells, 1 053 696 tets, 185 193 nodes)."""
    cells = max(2, round((tets_wanted / 6.0) ** (1.0 / 3.0)))
    while 6 * cells**3 < tets_wanted:
        cells += 1
    while cells > 2 and 6 * (cells - 1) ** 3 >= tets_wanted:
        cells -= 1
    return cells


@dataclass
class FracturePassResult:
    """The split pass against the force step on one mesh: sizes before and after, the splits done against those due
    (:func:`qualifying_nodes`), wall times [s] (build, one force step = the fastest run of ``steps`` over steps, the
    fastest pass), the pass in force steps, and peak host RSS [MB]."""

    device: str
    tets: int
    nodes: int
    nodes_after: int
    may_split: int
    due: int
    splits: int
    rounds: int
    grew: bool
    build_time: float
    steps: int
    step_time: float
    pass_time: float
    pass_in_steps: float
    peak_rss_mb: float
    books: bool = True


def force_step_time(model: Model, state: State, steps: int, repeat: int, books: bool = True) -> float:
    """The cost of one force step of a model [s]: the fastest of ``repeat`` runs of ``steps`` steps of
    ``Simulation.advance`` over steps, with the between-steps passes off (fracture_interval = conversion_interval
    = 0), after compilation and capture, with the energy books kept (``books``, as every run keeps them) or not.
    ``state`` is left as it was given (the pass benchmarks time their pass on it next)."""
    import dataclasses

    from ..simulation import Simulation

    snapshot = state.clone()
    plain = Simulation(
        dataclasses.replace(model, fracture_interval=0, conversion_interval=0), state, track_energy=books
    )
    plain.advance(2)  # compile and capture outside the clock
    wall = float("inf")
    for _ in range(repeat):
        wall = min(wall, timed(model.device, functools.partial(plain.advance, steps))[0])
    del plain  # its graphs and contact buffers; the pass builds its own Simulation
    state.assign(snapshot)
    return wall / steps


def bench_fracture_pass(
    tets_wanted: int,
    fraction: float = 0.01,
    steps: int = 50,
    device: str = "cpu",
    repeat: int = 3,
    seed: int = 0,
    books: bool = True,
) -> FracturePassResult:
    """Time one split pass (``Simulation.fracture_pass``) on the stretched block of about ``tets_wanted`` tets with
    ``fraction`` of its nodes splitting, against force steps of the same mesh with the pass off.

    The force steps are timed first (:func:`force_step_time`), then the state goes back to the stretch it was built
    with and the pass runs once; each further repeat rebuilds the block for another pass (a pass changes the mesh).
    The fastest of each counts (as ``timeit``). Node slots are reserved for the daughters, so the pass does not grow.
    ``books``: steps and pass keep the energy books, as a run does (False: both without them).
    """
    from ..simulation import Simulation

    cells = cells_for(tets_wanted)
    may_split = spread_nodes(cells, fraction, seed)
    capacity = (cells + 1) ** 3 + int(np.count_nonzero(may_split))
    pass_time = float("inf")
    for r in range(repeat):
        build, (model, state) = timed(device, lambda: stretched_block(cells, device, may_split, node_capacity=capacity))
        if r == 0:
            step_time = force_step_time(model, state, steps, repeat, books)
            build_time = build
        sim = Simulation(model, state, track_energy=books)
        if r == 0:
            due = qualifying_nodes(sim.model, sim.state, may_split)  # the stresses the Simulation evaluated
        nodes = int(sim.state.node_count.numpy()[0])
        seconds, report = timed(device, sim.fracture_pass)
        pass_time = min(pass_time, seconds)
    return FracturePassResult(
        device=str(device),
        tets=int(sim.state.tet_count.numpy()[0]),
        nodes=nodes,
        nodes_after=int(sim.state.node_count.numpy()[0]),
        may_split=int(np.count_nonzero(may_split)),
        due=due,
        splits=report.splits,
        rounds=report.rounds,
        grew=report.grew,
        build_time=build_time,
        steps=steps,
        step_time=step_time,
        pass_time=pass_time,
        pass_in_steps=pass_time / step_time,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        books=books,
    )


GRAIN_CELLS = 4
"""Cells per side of a grain of the cracking block (one strength per grain)."""

STRENGTH_CLASSES = 8
"""Tensile strengths of the cracking block's grains: T_f × (1, …, 2) in this many even steps."""


def pulled_granite(cells: int, device: str, steps: int, seed: int = 0) -> tuple[Model, State, np.ndarray, np.ndarray]:
    """The block of the run benchmarks (cracking, converting): the granite cube of :func:`stretched_granite`, made of
    grains of GRAIN_CELLS³ cells with seeded random strengths T_f … 2 T_f (one material per strength class, named
    ``granite<k>``), pulled apart along x at a constant strain rate (x-faces driven at ∓v, the rest starting with
    the matching velocity v_x = v (2x − 1), so there is no shock). The rate takes the weakest grains to T_f a quarter
    of the way through ``steps`` steps at half the critical step and the strongest by half way (σ_xx ≈ E ε in
    uniaxial stress). Returns (model, state, strengths [Pa] of the classes in material order, shape
    (STRENGTH_CLASSES,), the driven nodes as a bool mask, shape (nodes,))."""
    from ..build.builder import ModelBuilder
    from ..build.mesh import box_mesh
    from ..host_data import BondData

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (cells, cells, cells))
    cell = np.arange(len(tets)) // 6
    ci, cj, ck = cell % cells, (cell // cells) % cells, cell // cells**2
    grains = -(-cells // GRAIN_CELLS)
    grain = (ci // GRAIN_CELLS) + grains * ((cj // GRAIN_CELLS) + grains * (ck // GRAIN_CELLS))
    strength_class = np.random.default_rng(seed).integers(0, STRENGTH_CLASSES, size=grains**3)[grain]
    strengths = TENSILE_STRENGTH * np.linspace(1.0, 2.0, STRENGTH_CLASSES)
    names = [f"granite{k}" for k in strength_class]
    left, right = points[:, 0] == 0.0, points[:, 0] == 1.0

    def builder(velocity: np.ndarray | tuple) -> ModelBuilder:
        b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
        for k in range(STRENGTH_CLASSES):
            b.add_material(f"granite{k}", **GRANITE)
        b.add_tet_mesh(points, tets, names, velocity=velocity)
        return b

    # The loading rate follows from the time step, which the mesh sets (the tets' critical step).
    probe = builder((0.0, 0.0, 0.0))
    dt = 0.5 * probe.critical_step(probe.particle_data(), BondData.empty()).value
    rate = TENSILE_STRENGTH / (GRANITE["youngs_modulus"] * 0.25 * steps * dt)  # [1/s]
    speed = 0.5 * rate  # [m/s] of each x-face of the 1 m cube
    velocity = np.zeros_like(points)
    velocity[:, 0] = speed * (2.0 * points[:, 0] - 1.0)
    b = builder(velocity)
    b.add_node_velocity(left, (-speed, 0.0, 0.0))
    b.add_node_velocity(right, (speed, 0.0, 0.0))
    model, state = b.finalize(device, dt=dt)
    return model, state, strengths, left | right


def cracking_block(
    cells: int, device: str, steps: int, interval: int, seed: int = 0, books: bool = False
) -> Simulation:
    """The cracking run: :func:`pulled_granite` with every node but the driven ones free to split, a pass every
    ``interval`` steps (0: none, the reference), so the block cracks through most of the run; the energy books kept
    with ``books``. Returns a Simulation."""
    import dataclasses

    from ..simulation import Simulation
    from ..stages.fracture import FractureProps, attach_fracture

    model, state, strengths, driven = pulled_granite(cells, device, steps, seed)
    props = [FractureProps(tensile_strength=float(t), fracture_energy=FRACTURE_ENERGY) for t in strengths]
    model, state = attach_fracture(model, state, props, check_interval=max(interval, 1), may_split=~driven)
    if interval == 0:  # the reference: the same model with the pass off
        model = dataclasses.replace(model, fracture_interval=0)
    return Simulation(model, state, track_energy=books)


@dataclass
class CrackingRunResult:
    """A cracking run: sizes at the start and the end, the pass interval [steps], steps timed, wall time [s], step
    rate [steps/s] and throughput [tet-steps/s] with the passes included, and what cracked (splits, cohesive
    elements broken)."""

    device: str
    tets: int
    nodes: int
    nodes_after: int
    interval: int
    steps: int
    wall_time: float
    steps_per_second: float
    tet_steps_per_second: float
    splits: int
    cohesive_broken: int
    books: bool = True


def bench_cracking_run(
    tets_wanted: int, steps: int = 200, interval: int = 1, device: str = "cpu", seed: int = 0, books: bool = True
) -> CrackingRunResult:
    """Time ``Simulation.advance(steps - 2)`` on the cracking block (:func:`cracking_block`), passes included, after
    its first two steps (graph capture; nothing splits before a quarter of the run), with the energy books kept as a
    run keeps them (``books``; False: without)."""
    sim = cracking_block(cells_for(tets_wanted), device, steps, interval, seed, books)
    sim.advance(2)  # capture outside the clock (the kernels were compiled by run_pass_bench's warm-up)
    nodes = int(sim.state.node_count.numpy()[0])
    wall = timed(sim.model.device, lambda: sim.advance(steps - 2))[0]
    tets = int(sim.state.tet_count.numpy()[0])
    return CrackingRunResult(
        device=str(device),
        tets=tets,
        nodes=nodes,
        nodes_after=int(sim.state.node_count.numpy()[0]),
        interval=interval,
        steps=steps - 2,
        wall_time=wall,
        steps_per_second=(steps - 2) / wall,
        tet_steps_per_second=tets * (steps - 2) / wall,
        splits=int(sim.state.node_splits_total.numpy()[0]),
        cohesive_broken=int(sim.state.cohesive_broken_total.numpy()[0]),
        books=books,
    )


def format_pass_row(r: FracturePassResult, header: bool) -> str:
    line = (
        f"{r.device:<8}{r.tets:>10}{r.nodes:>9}{r.nodes_after:>9}{r.due:>7}{r.splits:>8}{r.rounds:>7}"
        f"{r.build_time:>9.2f}{r.step_time * 1e3:>10.2f}{r.pass_time * 1e3:>10.1f}{r.pass_in_steps:>9.1f}"
        f"{r.peak_rss_mb:>9.0f}" + ("   GREW" if r.grew else "") + ("" if r.splits == r.due else "   SPLITS != DUE")
    )
    if not header:
        return line
    head = (
        f"{'device':<8}{'tets':>10}{'nodes':>9}{'after':>9}{'due':>7}{'splits':>8}{'rounds':>7}{'build s':>9}"
        f"{'step ms':>10}{'pass ms':>10}{'steps':>9}{'RSS MB':>9}"
    )
    return "\n".join(
        [
            f"split pass (books {'on' if r.books else 'off'}; steps = pass in force steps of the same mesh; "
            "target < 20):",
            head,
            "-" * len(head),
            line,
        ]
    )


def format_run_row(r: CrackingRunResult, header: bool) -> str:
    line = (
        f"{r.device:<8}{r.tets:>10}{r.nodes:>9}{r.nodes_after:>9}{r.interval:>9}{r.steps:>7}{r.wall_time:>9.2f}"
        f"{r.steps_per_second:>9.1f}{r.tet_steps_per_second / 1e6:>15.2f}{r.splits:>8}{r.cohesive_broken:>8}"
    )
    if not header:
        return line
    head = (
        f"{'device':<8}{'tets':>10}{'nodes':>9}{'after':>9}{'interval':>9}{'steps':>7}{'wall s':>9}{'steps/s':>9}"
        f"{'M tet-steps/s':>15}{'splits':>8}{'broken':>8}"
    )
    title = f"cracking run (passes included; books {'on' if r.books else 'off'}):"
    return "\n".join([title, head, "-" * len(head), line])
