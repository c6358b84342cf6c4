"""Settling, the case other DEM codes are measured on (issue "Foundation", §7): N spheres (r = 0.01 m,
ρ = 2500 kg/m³, E = 1e7 Pa, ν = 0.3, μ = 0.5, e = 0.5, Hertz–Mindlin with history) start at rest from the centres
in ``warpdem/data/bench/init_N*.txt.gz`` (shipped with the package) inside a box (floor z = 0, side walls x = 0,
Lx, y = 0, Ly) under gravity 9.81 m/s²; dt = 5e-5 s; 2000 steps; nothing is written inside the timed part.
"""

from __future__ import annotations

import json
import resource
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    pass


DATA_DIR = Path(__file__).resolve().parent.parent / "data" / "bench"
"""The settling cases shipped with the package: ``init_N<N>.txt.gz`` (centres [m], one ``x y z`` line per sphere,
gzip-compressed text, so the numbers read back are exactly those of the original case files) and ``box_N<N>.json``
(box, radius, density)."""


@dataclass
class BenchResult:
    """One benchmark row: sizes, whether the energy books were kept, throughput [particle-steps/s], mean contacts per
    particle, memory [MB], and the physics at the end (kinetic energies [J], mean height [m]) for comparison with
    other codes."""

    device: str
    particles: int
    steps: int
    dt: float
    books: bool
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
    ranks: int = 1
    rank_step_ms: list[dict[str, float]] | None = None
    """Under ranks: where each rank's timed steps went, ms a step (warpdem.parallel.ranked.STEP_TIMES, with
    ``between``: the exchange less the halo, i.e. list rebuilds and migrations); None in one process."""


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
    """The settling case's stepper: a Simulation, or under mpiexec rank 0's view of it decomposed over the ranks
    (warpdem.parallel.run.make_simulation; another rank steps its part inside this call and leaves it with
    WorkerDone when rank 0 releases it)."""
    from ..build.builder import InteractionProps, ModelBuilder
    from ..parallel.run import make_simulation

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
    return make_simulation(model, state, track_energy=track_energy)


def bench_settling(
    n: int, steps: int = 2000, device: str = "cpu", data_dir: Path | None = None, repeat: int = 3, books: bool = True
) -> BenchResult | None:
    """Run the settling case and measure it (compilation and graph capture happen before the clock starts), with the
    energy books kept as every run keeps them (``books``; off: the step without them, for comparison).

    The case runs ``repeat`` times from its initial state and the fastest run counts, as ``timeit`` does: the
    slower ones measured whatever else the machine was doing.

    Under mpiexec the case runs decomposed over the ranks (warpdem.parallel); rank 0 returns the result, another rank
    None (it stepped its part of each repeat).
    """
    import warp as wp

    from ..parallel.run import WorkerDone, release_ranks

    wall = float("inf")
    sim = None
    rank_ms = None
    for k in range(repeat):
        try:
            sim = settling_case(n, device, track_energy=books, data_dir=data_dir)
        except WorkerDone:
            continue  # a follower rank: rank 0's repeat is over
        z0 = float(sim.state.particle_q.numpy()[:n, 2].mean())
        sim.advance(2)  # compile kernels and capture the step graph outside the timed part
        rebuilds0 = int(sim.state.rebuild_total.numpy()[0])
        times0 = sim.step_times() if hasattr(sim, "step_times") else None  # a decomposed run's (a gather: untimed)
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        sim.advance(steps - 2)
        wp.synchronize_device(device)
        elapsed = time.perf_counter() - t0
        if elapsed < wall:
            wall = elapsed
            rank_ms = None if times0 is None else _per_step(times0, sim.step_times(), steps - 2)
        if k < repeat - 1:
            release_ranks(sim)
    if sim is None:
        return None
    m = sim.model
    e = sim.energy()
    pairs = sim.contact_count()
    q = sim.state.particle_q.numpy()[:n]
    ranks = getattr(sim, "ranks", 1)
    rebuilds = int(sim.state.rebuild_total.numpy()[0]) - rebuilds0
    release_ranks(sim)
    # Memory of the stepping arrays: rank 0's subdomain on ranks (the whole state it gathers into is output's).
    stepper = getattr(sim, "local", sim)
    mem = sum(a.capacity for a in (*stepper.model.arrays().values(), *stepper.state.arrays().values()))
    nbr = stepper.neighbors
    mem += sum(a.capacity for a in (nbr.new_count, nbr.new_index, nbr.new_shear, nbr.new_bond))
    return BenchResult(
        device=str(device),
        particles=n,
        steps=steps,
        dt=m.dt,
        books=books,
        wall_time=wall,
        particle_steps_per_second=n * (steps - 2) / wall,
        mean_contacts_per_particle=2.0 * pairs / n,
        neighbor_rebuilds=rebuilds,
        state_memory_mb=mem / 2**20,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        kinetic_translational=e.kinetic_translational,
        kinetic_rotational=e.kinetic_rotational,
        mean_height=float(q[:, 2].mean()),
        mean_height_initial=z0,
        ranks=ranks,
        rank_step_ms=rank_ms,
    )


def _per_step(before: list[dict[str, float]], after: list[dict[str, float]], steps: int) -> list[dict[str, float]]:
    """Each rank's step time between two reads of ``Decomposed.step_times`` [s], as ms a step, with ``between``."""
    out = []
    for b, a in zip(before, after, strict=True):
        ms = {name: 1e3 * (a[name] - b[name]) / steps for name in a}
        ms["between"] = ms["exchange"] - ms["pack"] - ms["post"] - ms["wait"] - ms["unpack"]
        out.append(ms)
    return out


def format_rank_times(rows: list[BenchResult]) -> str:
    """Where each rank's timed steps went, ms a step, for the rows run on ranks (empty where none was)."""
    names = ("kernels", "pack", "post", "wait", "unpack", "between")
    head = f"{'N':>8}{'rank':>6}" + "".join(f"{name:>9}" for name in names)
    lines = []
    for r in rows:
        for rank, ms in enumerate(r.rank_step_ms or []):
            lines.append(f"{r.particles:>8}{rank:>6}" + "".join(f"{ms[name]:>9.3f}" for name in names))
    if not lines:
        return ""
    title = "ms a step by rank: own kernels, halo (pack, post, wait, unpack), list rebuilds and migrations (between)"
    return "\n".join([title, head, "-" * len(head), *lines])


def format_table(rows: list[BenchResult]) -> str:
    head = (
        f"{'device':<8}{'ranks':>6}{'N':>8}{'steps':>7}{'books':>6}{'wall s':>9}{'M p-steps/s':>13}{'contacts/p':>11}"
        f"{'rebuilds':>9}{'mem MB':>9}{'RSS MB':>9}{'KE_t J':>11}{'KE_r J':>11}{'z_mean m':>10}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r.device:<8}{r.ranks:>6}{r.particles:>8}{r.steps:>7}{'on' if r.books else 'off':>6}{r.wall_time:>9.3f}"
            f"{r.particle_steps_per_second / 1e6:>13.2f}"
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
    books: bool = True,
) -> int:
    """``python -m warpdem bench``: print the table; returns the exit status."""
    rows = []
    for n in sizes:
        try:
            row = bench_settling(n, steps, device, data_dir, repeat, books)
        except FileNotFoundError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if row is None:
            continue  # a follower rank of a decomposed bench: rank 0 reports
        rows.append(row)
        print(format_table(rows[-1:]) if len(rows) == 1 else format_table(rows).splitlines()[-1], flush=True)
    by_rank = format_rank_times(rows)
    if by_rank:
        print(by_rank, flush=True)
    if json_path is not None and rows:
        json_path.write_text(json.dumps([asdict(r) for r in rows], indent=1))
    return 0


# ----------------------------------------------------------------------------------------------------------------
# Tetrahedra
