"""Tetrahedra (issue "Cosserat point tetrahedra", §9): a granite block (E = 50 GPa, ν = 0.25, ρ = 2700 kg/m³, default
bulk viscosity) meshed by the Kuhn box mesher into about the requested number of tets, vibrating from a smooth
initial velocity field (about half the tets compress at any time, so the bulk-viscosity branch is exercised as in
wave problems), under gravity, at half the stable step. The timed part is ``Simulation.advance`` (captured graphs:
integration, tets, the surface's FEM contact), after compilation and capture.
"""

from __future__ import annotations

import json
import resource
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    pass


@dataclass
class TetBenchResult:
    """One tet benchmark row: sizes, whether the energy books were kept, throughput [tet-steps/s], device memory of
    the node and tet arrays per tet [B], peak host RSS [MB], and whether the energy stayed finite."""

    device: str
    tets: int
    nodes: int
    steps: int
    dt: float
    books: bool
    build_time: float
    wall_time: float
    tet_steps_per_second: float
    bytes_per_tet: float
    peak_rss_mb: float
    finite: bool


def vibrating_block(tets_wanted: int, device: str, books: bool = False):
    """A cubic granite block of about ``tets_wanted`` Kuhn tets (6 per cell), vibrating, as a Simulation (keeping the
    energy books with ``books``)."""
    import math

    from ..build.builder import ModelBuilder
    from ..build.mesh import box_mesh
    from ..simulation import Simulation

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
    return Simulation(model, state, track_energy=books)


def bench_tets(
    tets_wanted: int, steps: int = 100, device: str = "cpu", repeat: int = 3, books: bool = True
) -> TetBenchResult:
    """Build the vibrating block once, then time ``repeat`` runs of ``steps`` steps; the fastest counts (as
    ``timeit``: the slower ones measured whatever else the machine was doing). ``books``: keep the energy books, as
    every run does (off: the step without them, for comparison)."""
    import math

    import warp as wp

    t0 = time.perf_counter()
    sim = vibrating_block(tets_wanted, device, books)
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
        books=books,
        build_time=build,
        wall_time=wall,
        tet_steps_per_second=tets * steps / wall,
        bytes_per_tet=fem_bytes / tets,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        finite=bool(math.isfinite(sim.energy().total)),
    )


def format_tet_row(r: TetBenchResult, header: bool) -> str:
    line = (
        f"{r.device:<8}{r.tets:>10}{r.nodes:>10}{r.steps:>7}{'on' if r.books else 'off':>6}{r.build_time:>9.2f}"
        f"{r.wall_time:>9.3f}"
        f"{r.tet_steps_per_second / 1e6:>15.2f}{r.bytes_per_tet:>8.0f}{r.peak_rss_mb:>9.0f}"
        + ("" if r.finite else "   NON-FINITE ENERGY")
    )
    if not header:
        return line
    head = (
        f"{'device':<8}{'tets':>10}{'nodes':>10}{'steps':>7}{'books':>6}{'build s':>9}{'wall s':>9}"
        f"{'M tet-steps/s':>15}"
        f"{'B/tet':>8}{'RSS MB':>9}"
    )
    return "\n".join([head, "-" * len(head), line])


def run_tet_bench(
    sizes: list[int],
    steps: int,
    device: str,
    json_path: Path | None = None,
    repeat: int = 3,
    books: bool = True,
) -> int:
    """``python -m warpdem bench tets``: print the table; returns the exit status."""
    rows = []
    for n in sizes:
        rows.append(bench_tets(n, steps, device, repeat, books))
        print(format_tet_row(rows[-1], header=len(rows) == 1), flush=True)
    if json_path is not None:
        json_path.write_text(json.dumps([asdict(r) for r in rows], indent=1))
    return 0 if all(r.finite for r in rows) else 1


# ----------------------------------------------------------------------------------------------------------------
# Fracture
