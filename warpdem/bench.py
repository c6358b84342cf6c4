"""Benchmarks: ``python -m warpdem bench`` (DEM settling), ``python -m warpdem bench tets`` (tetrahedra),
``python -m warpdem bench fracture`` (the split pass and a cracking run), ``python -m warpdem bench conversion``
(the FEM→DEM conversion pass and a converting run) and ``python -m warpdem bench blocks`` (rigid blocks).

Settling, the case other DEM codes are measured on (issue "Foundation", §7): N spheres (r = 0.01 m,
ρ = 2500 kg/m³, E = 1e7 Pa, ν = 0.3, μ = 0.5, e = 0.5, Hertz–Mindlin with history) start at rest from the centres
in ``warpdem/data/bench/init_N*.txt.gz`` (shipped with the package) inside a box (floor z = 0, side walls x = 0,
Lx, y = 0, Ly) under gravity 9.81 m/s²; dt = 5e-5 s; 2000 steps; nothing is written inside the timed part.

Tetrahedra (issue "Cosserat point tetrahedra", §9): a granite block (E = 50 GPa, ν = 0.25, ρ = 2700 kg/m³, default
bulk viscosity) meshed by the Kuhn box mesher into about the requested number of tets, vibrating from a smooth
initial velocity field (about half the tets compress at any time, so the bulk-viscosity branch is exercised as in
wave problems), under gravity, at half the stable step. The timed part is ``Simulation.advance`` (captured graphs:
integration, tets, the surface's FEM contact), after compilation and capture.

Fracture (issue 9 §8): the cost of one split pass (``Simulation.fracture_pass``: nodal stresses, candidates, rounds
of claims, the splits, cohesive elements born, the surface and FEM contact lists rebuilt, forces re-evaluated) in
units of force steps of the same mesh, on a granite cube of Kuhn tets (about 0.2 M tets by default; the documented
figure is 1 M) stretched in uniaxial strain to 3 T_f with a seeded random 1 % of its nodes free to split
(:func:`stretched_block`); and the step rate of a cracking run, a smaller cube of grains of random strength pulled
apart at a constant strain rate with a pass every 1 or 10 steps (:func:`cracking_block`).

Conversion (issue 10 §8): the cost of one conversion pass (``Simulation.conversion_pass``: the criterion, spheres,
bonds and couplings written, nodes re-lumped, the surface and contact lists rebuilt, forces re-evaluated) in units
of force steps of the same mesh, on the same stretched cube with a seeded random 1 % of its tets, all above the
Tresca threshold, allowed to convert (:func:`converting_block`); and the step rate of a converting run, the pulled
cube of grains with its central slab allowed to convert, a pass every 1 or 10 steps (:func:`converting_run_block`).
The two pass benchmarks and the two runs share the block, the timing and the command line (:func:`run_pass_bench`).

Rigid blocks (issue 11 §5): block-steps/s of a jointed cube of 1 m granite blocks, one Kuhn cell (6 tets) each, on a
ground wall under gravity, rattling from seeded random velocities, in rigid mode at half the blocks' stable step
(:func:`jointed_cube`); the engaged node–face contacts, and the device memory of every array per block.
"""

from __future__ import annotations

import functools
import json
import resource
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import numpy as np

if TYPE_CHECKING:
    import warp as wp

    from .model import Model, State
    from .simulation import Simulation

DATA_DIR = Path(__file__).resolve().parent / "data" / "bench"
"""The settling cases shipped with the package: ``init_N<N>.txt.gz`` (centres [m], one ``x y z`` line per sphere,
gzip-compressed text, so the numbers read back are exactly those of the original case files) and ``box_N<N>.json``
(box, radius, density)."""

T = TypeVar("T")


@dataclass
class BenchResult:
    """One benchmark row: sizes, throughput [particle-steps/s], mean contacts per particle, memory [MB], and the
    physics at the end (kinetic energies [J], mean height [m]) for comparison with other codes."""

    device: str
    particles: int
    steps: int
    dt: float
    wall_time: float
    particle_steps_per_second: float
    mean_contacts_per_particle: float
    neighbor_rebuilds: int
    state_memory_mb: float
    peak_rss_mb: float
    kinetic_translational: float
    kinetic_rotational: float
    mean_height: float
    mean_height_initial: float


def find_case(n: int, data_dir: Path | None = None) -> tuple[np.ndarray, dict]:
    """Initial centres [m], shape (N, 3), and box description of the N-sphere case, from ``data_dir`` (default: the
    package's :data:`DATA_DIR`); the centres file may be plain (``init_N<N>.txt``) or gzip-compressed (``.txt.gz``).
    """
    folder = DATA_DIR if data_dir is None else data_dir
    box = folder / f"box_N{n}.json"
    for txt in (folder / f"init_N{n}.txt.gz", folder / f"init_N{n}.txt"):
        if txt.is_file() and box.is_file():
            return np.loadtxt(txt, dtype=np.float64).reshape(-1, 3), json.loads(box.read_text())
    shipped = sorted(int(p.name[len("box_N") : -len(".json")]) for p in folder.glob("box_N*.json"))
    raise FileNotFoundError(
        f"no benchmark case for N = {n}: {folder} needs init_N{n}.txt(.gz) and box_N{n}.json"
        + (f" (it has N = {', '.join(map(str, shipped))})" if shipped else "")
    )


def settling_case(n: int, device: str, track_energy: bool = False, data_dir: Path | None = None):
    """Model, state and Simulation of the settling case."""
    from .builder import InteractionProps, ModelBuilder
    from .simulation import Simulation

    q, box = find_case(n, data_dir)
    b = ModelBuilder(normal="hertz", tangential="mindlin", gravity=(0.0, 0.0, -9.81))
    b.add_material("glass", density=box.get("density", 2500.0), youngs_modulus=1.0e7, poisson_ratio=0.3)
    b.default_interaction = InteractionProps(friction=0.5, restitution=0.5)
    b.add_spheres(q, box.get("r", 0.01), "glass")
    lx, ly = box["Lx"], box["Ly"]
    b.add_plane_wall((0, 0, 0), (0, 0, 1), "glass")
    b.add_plane_wall((0, 0, 0), (1, 0, 0), "glass")
    b.add_plane_wall((lx, 0, 0), (-1, 0, 0), "glass")
    b.add_plane_wall((0, 0, 0), (0, 1, 0), "glass")
    b.add_plane_wall((0, ly, 0), (0, -1, 0), "glass")
    model, state = b.finalize(device, dt=5.0e-5, max_neighbors=8)
    return Simulation(model, state, track_energy=track_energy)


def bench_settling(
    n: int, steps: int = 2000, device: str = "cpu", data_dir: Path | None = None, repeat: int = 3
) -> BenchResult:
    """Run the settling case and measure it (compilation and graph capture happen before the clock starts).

    The case runs ``repeat`` times from its initial state and the fastest run counts, as ``timeit`` does: the
    slower ones measured whatever else the machine was doing.
    """
    import warp as wp

    wall = float("inf")
    for _ in range(repeat):
        sim = settling_case(n, device, data_dir=data_dir)
        z0 = float(sim.state.particle_q.numpy()[:n, 2].mean())
        sim.advance(2)  # compile kernels and capture the step graph outside the timed part
        rebuilds0 = int(sim.state.rebuild_total.numpy()[0])
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        sim.advance(steps - 2)
        wp.synchronize_device(device)
        wall = min(wall, time.perf_counter() - t0)
    m = sim.model
    e = sim.energy()
    pairs = sim.contact_count()
    q = sim.state.particle_q.numpy()[:n]
    mem = sum(a.capacity for a in (*sim.model.arrays().values(), *sim.state.arrays().values()))
    mem += sum(
        a.capacity
        for a in (sim.neighbors.new_count, sim.neighbors.new_index, sim.neighbors.new_shear, sim.neighbors.new_bond)
    )
    return BenchResult(
        device=str(device),
        particles=n,
        steps=steps,
        dt=m.dt,
        wall_time=wall,
        particle_steps_per_second=n * (steps - 2) / wall,
        mean_contacts_per_particle=2.0 * pairs / n,
        neighbor_rebuilds=int(sim.state.rebuild_total.numpy()[0]) - rebuilds0,
        state_memory_mb=mem / 2**20,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        kinetic_translational=e.kinetic_translational,
        kinetic_rotational=e.kinetic_rotational,
        mean_height=float(q[:, 2].mean()),
        mean_height_initial=z0,
    )


def format_table(rows: list[BenchResult]) -> str:
    head = (
        f"{'device':<8}{'N':>8}{'steps':>7}{'wall s':>9}{'M p-steps/s':>13}{'contacts/p':>11}"
        f"{'rebuilds':>9}{'mem MB':>9}{'RSS MB':>9}{'KE_t J':>11}{'KE_r J':>11}{'z_mean m':>10}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r.device:<8}{r.particles:>8}{r.steps:>7}{r.wall_time:>9.3f}{r.particle_steps_per_second / 1e6:>13.2f}"
            f"{r.mean_contacts_per_particle:>11.2f}{r.neighbor_rebuilds:>9}{r.state_memory_mb:>9.1f}{r.peak_rss_mb:>9.0f}"
            f"{r.kinetic_translational:>11.3e}{r.kinetic_rotational:>11.3e}{r.mean_height:>10.4f}"
        )
    return "\n".join(lines)


def run_bench(
    sizes: list[int],
    steps: int,
    device: str,
    json_path: Path | None = None,
    data_dir: Path | None = None,
    repeat: int = 3,
) -> int:
    """``python -m warpdem bench``: print the table; returns the exit status."""
    rows = []
    for n in sizes:
        try:
            rows.append(bench_settling(n, steps, device, data_dir, repeat))
        except FileNotFoundError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(format_table(rows[-1:]) if len(rows) == 1 else format_table(rows).splitlines()[-1], flush=True)
    if json_path is not None:
        json_path.write_text(json.dumps([asdict(r) for r in rows], indent=1))
    return 0


# ----------------------------------------------------------------------------------------------------------------
# Tetrahedra


@dataclass
class TetBenchResult:
    """One tet benchmark row: sizes, throughput [tet-steps/s], device memory of the node and tet arrays per tet [B],
    peak host RSS [MB], and whether the energy stayed finite."""

    device: str
    tets: int
    nodes: int
    steps: int
    dt: float
    build_time: float
    wall_time: float
    tet_steps_per_second: float
    bytes_per_tet: float
    peak_rss_mb: float
    finite: bool


def vibrating_block(tets_wanted: int, device: str):
    """A cubic granite block of about ``tets_wanted`` Kuhn tets (6 per cell), vibrating, as a Simulation."""
    import math

    from .builder import ModelBuilder
    from .mesh import box_mesh
    from .simulation import Simulation

    n = max(1, round((tets_wanted / 6.0) ** (1.0 / 3.0)))
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (n, n, n))
    amplitude = 1.0  # [m/s]
    velocity = amplitude * np.stack(
        [np.sin(math.pi * points[:, 2]), np.sin(math.pi * points[:, 0]), np.sin(math.pi * points[:, 1])], axis=1
    )
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("granite", density=2700.0, youngs_modulus=50.0e9, poisson_ratio=0.25)
    b.add_tet_mesh(points, tets, "granite", velocity=velocity)
    model, state = b.finalize(device, safety_factor=0.5)
    return Simulation(model, state, track_energy=False)


def bench_tets(tets_wanted: int, steps: int = 100, device: str = "cpu", repeat: int = 3) -> TetBenchResult:
    """Build the vibrating block once, then time ``repeat`` runs of ``steps`` steps; the fastest counts (as
    ``timeit``: the slower ones measured whatever else the machine was doing)."""
    import math

    import warp as wp

    t0 = time.perf_counter()
    sim = vibrating_block(tets_wanted, device)
    build = time.perf_counter() - t0
    sim.advance(2)  # compile and capture outside the clock
    wall = float("inf")
    for _ in range(repeat):
        wp.synchronize_device(sim.model.device)
        t0 = time.perf_counter()
        sim.advance(steps)
        wp.synchronize_device(sim.model.device)
        wall = min(wall, time.perf_counter() - t0)
    arrays = {**sim.model.arrays(), **sim.state.arrays()}
    fem_bytes = sum(a.capacity for name, a in arrays.items() if name.startswith(("node_", "tet_")))
    tets = sim.model.tet_capacity
    return TetBenchResult(
        device=str(device),
        tets=tets,
        nodes=sim.model.node_capacity,
        steps=steps,
        dt=sim.model.dt,
        build_time=build,
        wall_time=wall,
        tet_steps_per_second=tets * steps / wall,
        bytes_per_tet=fem_bytes / tets,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        finite=bool(math.isfinite(sim.energy().total)),
    )


def format_tet_row(r: TetBenchResult, header: bool) -> str:
    line = (
        f"{r.device:<8}{r.tets:>10}{r.nodes:>10}{r.steps:>7}{r.build_time:>9.2f}{r.wall_time:>9.3f}"
        f"{r.tet_steps_per_second / 1e6:>15.2f}{r.bytes_per_tet:>8.0f}{r.peak_rss_mb:>9.0f}"
        + ("" if r.finite else "   NON-FINITE ENERGY")
    )
    if not header:
        return line
    head = (
        f"{'device':<8}{'tets':>10}{'nodes':>10}{'steps':>7}{'build s':>9}{'wall s':>9}{'M tet-steps/s':>15}"
        f"{'B/tet':>8}{'RSS MB':>9}"
    )
    return "\n".join([head, "-" * len(head), line])


def run_tet_bench(sizes: list[int], steps: int, device: str, json_path: Path | None = None, repeat: int = 3) -> int:
    """``python -m warpdem bench tets``: print the table; returns the exit status."""
    rows = []
    for n in sizes:
        rows.append(bench_tets(n, steps, device, repeat))
        print(format_tet_row(rows[-1], header=len(rows) == 1), flush=True)
    if json_path is not None:
        json_path.write_text(json.dumps([asdict(r) for r in rows], indent=1))
    return 0 if all(r.finite for r in rows) else 1


# ----------------------------------------------------------------------------------------------------------------
# Fracture

GRANITE = {"density": 2700.0, "youngs_modulus": 50.0e9, "poisson_ratio": 0.25}
"""The rock of the fracture benchmark (the tetrahedra benchmark's granite): ρ [kg/m³], E [Pa], ν [-]."""

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

    from .builder import ModelBuilder
    from .mesh import box_mesh

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
    from .fracture import FractureProps, attach_fracture

    model, state = stretched_granite(cells, device, node_capacity=node_capacity)
    props = FractureProps(tensile_strength=TENSILE_STRENGTH, fracture_energy=FRACTURE_ENERGY)
    return attach_fracture(model, state, [props], check_interval=1, may_split=may_split)


def qualifying_nodes(model: Model, state: State, may_split: np.ndarray) -> int:
    """How many nodes the split pass must split, counted on the host by brute force (the rules of warpdem.fracture):
    nodes with ``may_split``, whose volume-weighted average of their tets' stresses (LDEC eq. 1) has σ1 ≥ the least
    T_f of their tets' materials, and whose star has tets on both sides of the plane through the node normal to p1.
    Nodes that share a tet are all counted: the pass's rounds split them one after another. (The pass also asks for a
    face between the two sides; a node's star in a conforming mesh such as the Kuhn box is face-connected around it,
    so tets on both sides imply one.)"""
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


def timed(device: str | wp.context.Device, fn: Callable[[], T]) -> tuple[float, T]:
    """Wall time [s] of ``fn()`` with the device synchronised before and after (launches are asynchronous), and what
    it returned."""
    import warp as wp

    wp.synchronize_device(device)
    t0 = time.perf_counter()
    out = fn()
    wp.synchronize_device(device)
    return time.perf_counter() - t0, out


def force_step_time(model: Model, state: State, steps: int, repeat: int) -> float:
    """The cost of one force step of a model [s]: the fastest of ``repeat`` runs of ``steps`` steps of
    ``Simulation.advance`` over steps, with the between-steps passes off (fracture_interval = conversion_interval
    = 0), after compilation and capture. ``state`` is left as it was given (the pass benchmarks time their pass on
    it next)."""
    import dataclasses

    from .simulation import Simulation

    snapshot = state.clone()
    plain = Simulation(
        dataclasses.replace(model, fracture_interval=0, conversion_interval=0), state, track_energy=False
    )
    plain.advance(2)  # compile and capture outside the clock
    wall = float("inf")
    for _ in range(repeat):
        wall = min(wall, timed(model.device, functools.partial(plain.advance, steps))[0])
    del plain  # its graphs and contact buffers; the pass builds its own Simulation
    state.assign(snapshot)
    return wall / steps


def bench_fracture_pass(
    tets_wanted: int, fraction: float = 0.01, steps: int = 50, device: str = "cpu", repeat: int = 3, seed: int = 0
) -> FracturePassResult:
    """Time one split pass (``Simulation.fracture_pass``) on the stretched block of about ``tets_wanted`` tets with
    ``fraction`` of its nodes splitting, against force steps of the same mesh with the pass off.

    The force steps are timed first (:func:`force_step_time`), then the state goes back to the stretch it was built
    with and the pass runs once; each further repeat rebuilds the block for another pass (a pass changes the mesh).
    The fastest of each counts (as ``timeit``). Node slots are reserved for the daughters, so the pass does not grow.
    """
    from .simulation import Simulation

    cells = cells_for(tets_wanted)
    may_split = spread_nodes(cells, fraction, seed)
    capacity = (cells + 1) ** 3 + int(np.count_nonzero(may_split))
    pass_time = float("inf")
    for r in range(repeat):
        build, (model, state) = timed(device, lambda: stretched_block(cells, device, may_split, node_capacity=capacity))
        if r == 0:
            step_time = force_step_time(model, state, steps, repeat)
            build_time = build
        sim = Simulation(model, state, track_energy=False)
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
    from .builder import ModelBuilder
    from .mesh import box_mesh
    from .model import BondData

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


def cracking_block(cells: int, device: str, steps: int, interval: int, seed: int = 0) -> Simulation:
    """The cracking run: :func:`pulled_granite` with every node but the driven ones free to split, a pass every
    ``interval`` steps (0: none, the reference), so the block cracks through most of the run. Returns a
    Simulation."""
    import dataclasses

    from .fracture import FractureProps, attach_fracture
    from .simulation import Simulation

    model, state, strengths, driven = pulled_granite(cells, device, steps, seed)
    props = [FractureProps(tensile_strength=float(t), fracture_energy=FRACTURE_ENERGY) for t in strengths]
    model, state = attach_fracture(model, state, props, check_interval=max(interval, 1), may_split=~driven)
    if interval == 0:  # the reference: the same model with the pass off
        model = dataclasses.replace(model, fracture_interval=0)
    return Simulation(model, state, track_energy=False)


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


def bench_cracking_run(
    tets_wanted: int, steps: int = 200, interval: int = 1, device: str = "cpu", seed: int = 0
) -> CrackingRunResult:
    """Time ``Simulation.advance(steps - 2)`` on the cracking block (:func:`cracking_block`), passes included, after
    its first two steps (graph capture; nothing splits before a quarter of the run)."""
    sim = cracking_block(cells_for(tets_wanted), device, steps, interval, seed)
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
        ["split pass (steps = pass in force steps of the same mesh; target < 20):", head, "-" * len(head), line]
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
    return "\n".join(["cracking run (passes included):", head, "-" * len(head), line])


def write_json(path: Path | None, data: dict) -> None:
    """Write ``data`` as JSON to ``path`` (nothing when None) through a temporary name, so a reader never sees a
    half-written file."""
    if path is None:
        return
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)


# ----------------------------------------------------------------------------------------------------------------
# Conversion

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
    from .conversion import ConversionProps, attach_conversion, regrow_bonds

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
    by the rules of warpdem.conversion: (bonds, one per pair of tets in the mask that share an edge
    (warpdem.lattice.edge_pairs); couplings, one per pair of a tet in the mask and an active tet outside it that share
    an edge)."""
    from .lattice import TET_EDGES, edge_pairs

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
    """The tets a conversion pass must convert, found on the host by brute force (the rules of warpdem.conversion):
    live, active tets with ``tet_may_convert`` of a material that converts, whose stress (``state.tet_stress``,
    brought up to date here) reaches the criterion of their material — Tresca (σ1 − σ3)/2 ≥ f τ_f or Rankine
    σ1 ≥ f T_f, principal stresses in float64. Returns a bool mask, shape (tet_count,)."""
    from .kernels.conversion import CRITERION_RANKINE, CRITERION_TRESCA
    from .tets import eval_tet_stresses

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


def bench_conversion_pass(
    tets_wanted: int, fraction: float = 0.01, steps: int = 50, device: str = "cpu", repeat: int = 3, seed: int = 0
) -> ConversionPassResult:
    """Time one conversion pass (``Simulation.conversion_pass``) on the stretched block of at least ``tets_wanted``
    tets with ``fraction`` of its tets converting, against force steps of the same mesh with the pass off, as
    :func:`bench_fracture_pass` times the split pass (each repeat rebuilds the block: a pass changes the mesh)."""
    from .simulation import Simulation

    cells = cells_for(tets_wanted)
    may_convert = spread_tets(6 * cells**3, fraction, seed)
    pass_time = float("inf")
    for r in range(repeat):
        build, (model, state) = timed(device, lambda: converting_block(cells, device, may_convert))
        if r == 0:
            due = due_tets(model, state)
            bonds_due, couplings_due = lattice_counts(model, state, due)
            step_time = force_step_time(model, state, steps, repeat)
            build_time = build
        setup, sim = timed(device, functools.partial(Simulation, model, state, track_energy=False))
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
    )


def converting_run_block(cells: int, device: str, steps: int, interval: int, seed: int = 0) -> Simulation:
    """The converting run: :func:`pulled_granite` with conversion on in its central slab (tets whose centroid lies
    within CONVERSION_SLAB / 2 of x = 0.5 m: the block fails at its centre), Tresca with τ_f = T_f / 2 of each grain
    (σ_xx ≈ E ε in uniaxial stress reaches 0.9 × 2 τ_f just before the grain's T_f), a pass every ``interval``
    steps (0: none, the reference). Returns a Simulation."""
    import dataclasses

    from .conversion import ConversionProps, attach_conversion
    from .simulation import Simulation

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
    return Simulation(model, state, track_energy=False)


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


def bench_converting_run(
    tets_wanted: int, steps: int = 200, interval: int = 1, device: str = "cpu", seed: int = 0
) -> ConvertingRunResult:
    """Time ``Simulation.advance(steps - 2)`` on the converting block (:func:`converting_run_block`), passes included,
    after its first two steps (graph capture; nothing converts before a fifth of the run)."""
    sim = converting_run_block(cells_for(tets_wanted), device, steps, interval, seed)
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
        ["conversion pass (steps = pass in force steps of the same mesh; target < 20):", head, "-" * len(head), line]
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
    return "\n".join(["converting run (passes included):", head, "-" * len(head), line])


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
) -> int:
    """``python -m warpdem bench fracture|conversion`` (``kind``): print the pass table and the run table; returns the
    exit status (1 when a pass changed other than the nodes or tets due)."""
    bench_pass, bench_run, format_pass, format_run, done = PASS_BENCHES[kind]
    # Compile every kernel of the pass and the step on a small block first, so no size pays for it.
    bench_pass(6 * 4**3, 0.05, 2, device, 1, seed)
    passes, runs = [], []
    for n in sizes:
        passes.append(bench_pass(n, fraction, steps, device, repeat, seed))
        print(format_pass(passes[-1], header=len(passes) == 1), flush=True)
    if passes and run_sizes:
        print()
    for n in run_sizes:
        for interval in intervals:
            runs.append(bench_run(n, run_steps, interval, device, seed))
            print(format_run(runs[-1], header=len(runs) == 1), flush=True)
    write_json(json_path, {"passes": [asdict(r) for r in passes], "runs": [asdict(r) for r in runs]})
    return 0 if all(getattr(r, done) == r.due for r in passes) else 1


# ----------------------------------------------------------------------------------------------------------------
# Rigid blocks (issue 11 §5)


@dataclass
class BlockBenchResult:
    """One rigid-block benchmark row: blocks, steps, throughput [block-steps/s] per second of wall time and per second
    of the process's CPU time (on the CPU device the steps run on one core, so the CPU time is what the steps cost
    whatever else shares the machine; a CUDA device's steps do not show in it), engaged contacts, the FEM contact-list
    builds during the timed steps (the hash-grid rebuild a node's half-skin move flags), device memory per block [B]
    (every Model and State array), the stable steps [s] and whether the energy stayed finite."""

    device: str
    blocks: int
    held: int
    nodes: int
    tets: int
    steps: int
    dt: float
    deformable_dt: float
    build_time: float
    wall_time: float
    block_steps_per_second: float
    cpu_time: float
    block_steps_per_cpu_second: float
    contacts: int
    list_builds: int
    bytes_per_block: float
    peak_rss_mb: float
    finite: bool


def jointed_cube(cells: int, device: str, node_order: str = "blocks") -> Simulation:
    """A cube of ``cells``³ granite blocks of 1 m, one Kuhn cell (6 tets) each: every cell face inside the cube is a
    frictional joint (μ = 0.5), so the blocks are the cells. It rests on a ground wall under gravity, each block with
    a seeded small random velocity (the blocks rattle, so the contacts work), in rigid mode from the start at half
    the blocks' stable step (warpdem.rigid.rigid_time_step), as a Simulation. ``node_order``: ModelBuilder.finalize's
    (the bench's, "blocks", numbers the nodes block by block; README, Benchmark, compares it with "split")."""
    from .builder import ModelBuilder
    from .joints import JointProps
    from .mesh import TET_FACES, box_mesh
    from .rigid import rigid_time_step
    from .simulation import Simulation

    points, tets = box_mesh((0.0, 0.0, 0.0), (float(cells),) * 3, (cells,) * 3)
    faces = tets[:, TET_FACES].reshape(-1, 3)
    xf = points[faces]  # (F, 3, 3)
    on_grid = np.zeros(len(faces), dtype=bool)
    for axis in range(3):
        c = xf[:, :, axis]
        flat = np.all(c == c[:, :1], axis=1)
        on_grid |= flat & (c[:, 0] > 0.0) & (c[:, 0] < cells) & (np.round(c[:, 0]) == c[:, 0])
    joint_faces = np.unique(np.sort(faces[on_grid], axis=1), axis=0)
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("granite", **GRANITE)
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "granite")
    js = b.add_joint_set(JointProps(friction=0.5, restitution=0.5))
    rng = np.random.default_rng(0)
    cell = np.floor(points[tets].mean(axis=1)).astype(np.int64)
    kick = rng.normal(scale=0.01, size=(cells**3, 3))[(cell[:, 0] * cells + cell[:, 1]) * cells + cell[:, 2]]
    velocity = np.zeros((len(points), 3))
    velocity[tets.ravel()] = np.repeat(kick, 4, axis=0)
    b.add_tet_mesh(points, tets, "granite", joint_faces=joint_faces, joint_set=js, velocity=velocity)
    # A block corner inside the cube is a corner of eight blocks: some thirty faces of the seven others touch it, all
    # node–face candidates. Slots for them from the start spare the set-up a list build that overflows and is redone.
    model, state = b.finalize(device, safety_factor=0.5, max_node_faces=32, node_order=node_order)
    sim = Simulation(rigid_time_step(model, state, 0.5), state, track_energy=False)
    sim.switch_to_rigid()
    return sim


def bench_blocks(blocks_wanted: int, steps: int = 50, device: str = "cpu", repeat: int = 3) -> BlockBenchResult:
    """Build the jointed cube of at least ``blocks_wanted`` blocks once, then time ``repeat`` runs of ``steps`` steps;
    the fastest counts."""
    import math

    import warp as wp

    cells = max(1, math.ceil(blocks_wanted ** (1.0 / 3.0) - 1e-9))
    t0 = time.perf_counter()
    sim = jointed_cube(cells, device)
    build = time.perf_counter() - t0
    sim.advance(2)  # compile and capture outside the clock
    builds = int(sim.state.fem_rebuild_total.numpy()[0])
    wall = cpu = float("inf")
    for _ in range(repeat):
        wp.synchronize_device(sim.model.device)
        t0, c0 = time.perf_counter(), time.process_time()
        sim.advance(steps)
        wp.synchronize_device(sim.model.device)
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    s = sim.state
    blocks = s.body_mass.shape[0]
    nn = sim.node_count
    total_bytes = sum(a.capacity for a in {**sim.model.arrays(), **s.arrays()}.values())
    return BlockBenchResult(
        device=str(device),
        blocks=blocks,
        held=int(s.body_fixed.numpy().sum()),
        nodes=nn,
        tets=int(s.tet_count.numpy()[0]),
        steps=steps,
        dt=sim.model.dt,
        deformable_dt=0.5 * sim.model.deformable_critical_dt,
        build_time=build,
        wall_time=wall,
        block_steps_per_second=blocks * steps / wall,
        cpu_time=cpu,
        block_steps_per_cpu_second=blocks * steps / cpu if cpu > 0.0 else math.inf,
        contacts=int(np.count_nonzero(s.node_face_spring.numpy()[:nn] >= 0)),
        list_builds=int(s.fem_rebuild_total.numpy()[0]) - builds,
        bytes_per_block=total_bytes / blocks,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        finite=bool(np.all(np.isfinite(s.body_v.numpy())) and np.all(np.isfinite(s.node_u.numpy()[:nn]))),
    )


def format_block_row(r: BlockBenchResult, header: bool) -> str:
    line = (
        f"{r.device:<8}{r.blocks:>9}{r.held:>7}{r.tets:>9}{r.steps:>7}{r.dt:>11.3g}{r.deformable_dt:>11.3g}"
        f"{r.build_time:>9.1f}{r.wall_time:>9.3f}{r.block_steps_per_second / 1e6:>17.3f}"
        f"{r.block_steps_per_cpu_second / 1e6:>13.3f}{r.contacts:>10}{r.list_builds:>8}"
        f"{r.bytes_per_block:>9.0f}{r.peak_rss_mb:>9.0f}" + ("" if r.finite else "   NON-FINITE")
    )
    if not header:
        return line
    head = (
        f"{'device':<8}{'blocks':>9}{'held':>7}{'tets':>9}{'steps':>7}{'dt s':>11}{'deform. dt':>11}{'build s':>9}"
        f"{'wall s':>9}{'M block-steps/s':>17}{'M per cpu-s':>13}{'contacts':>10}{'builds':>8}{'B/block':>9}"
        f"{'RSS MB':>9}"
    )
    return "\n".join([head, "-" * len(head), line])


def run_block_bench(sizes: list[int], steps: int, device: str, json_path: Path | None = None, repeat: int = 3) -> int:
    """``python -m warpdem bench blocks``: print the table; returns the exit status (1 on a non-finite state)."""
    rows = []
    for n in sizes:
        rows.append(bench_blocks(n, steps, device, repeat))
        print(format_block_row(rows[-1], header=len(rows) == 1), flush=True)
    write_json(json_path, {"blocks": [asdict(r) for r in rows]})
    return 0 if all(r.finite for r in rows) else 1
