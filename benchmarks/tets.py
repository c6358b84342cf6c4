"""Tet throughput benchmark: ``python benchmarks/tets.py [--sizes 200000 1000000] [--steps 100] [--device cpu]``.

A granite block (E = 50 GPa, ν = 0.25, ρ = 2700 kg/m³, default bulk viscosity) meshed with the Kuhn box mesher into
about the requested number of tets, vibrating from a smooth initial velocity field (about half the tets compress at
any time, so the bulk-viscosity branch is exercised as in wave problems), under gravity, at half the stable step.
The timed part is ``Simulation.advance`` (a captured graph: integrate, tets, integrate), after compilation and
capture. Reports tet-steps/s, the device memory of the node and tet arrays per tet, and the peak host RSS.
"""

from __future__ import annotations

import argparse
import logging
import math
import resource
import time

import numpy as np
import warp as wp

from warpdem.builder import ModelBuilder
from warpdem.mesh import box_mesh
from warpdem.simulation import Simulation


def block(tets_wanted: int, device: str) -> Simulation:
    """A cubic block of about ``tets_wanted`` Kuhn tets (6 per cell), vibrating, as a Simulation."""
    n = max(1, round((tets_wanted / 6.0) ** (1.0 / 3.0)))
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (n, n, n))
    amplitude = 1.0  # [m/s]
    velocity = amplitude * np.stack(
        [np.sin(np.pi * points[:, 2]), np.sin(np.pi * points[:, 0]), np.sin(np.pi * points[:, 1])], axis=1
    )
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("granite", density=2700.0, youngs_modulus=50.0e9, poisson_ratio=0.25)
    b.add_tet_mesh(points, tets, "granite", velocity=velocity)
    model, state = b.finalize(device, safety_factor=0.5)
    return Simulation(model, state, track_energy=False)


def fem_bytes(sim: Simulation) -> int:
    """Device bytes of every node and tet array of the model and state."""
    arrays = {**sim.model.arrays(), **sim.state.arrays()}
    return sum(a.capacity for name, a in arrays.items() if name.startswith(("node_", "tet_")))


def run(tets_wanted: int, steps: int, device: str) -> dict:
    t0 = time.perf_counter()
    sim = block(tets_wanted, device)
    build = time.perf_counter() - t0
    sim.advance(2)  # compile and capture outside the clock
    wp.synchronize_device(sim.model.device)
    t0 = time.perf_counter()
    sim.advance(steps)
    wp.synchronize_device(sim.model.device)
    wall = time.perf_counter() - t0
    tets = sim.model.tet_capacity
    energy = sim.energy()
    return {
        "tets": tets,
        "nodes": sim.model.node_capacity,
        "steps": steps,
        "dt": sim.model.dt,
        "build_s": build,
        "wall_s": wall,
        "tet_steps_per_s": tets * steps / wall,
        "bytes_per_tet": fem_bytes(sim) / tets,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "finite": bool(math.isfinite(energy.total)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[200_000, 1_000_000], help="tets wanted")
    parser.add_argument("--steps", type=int, default=100, help="timed steps per size")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    wp.config.log_level = logging.WARNING
    wp.init()
    header = ("tets", 10), ("nodes", 10), ("steps", 7), ("build s", 9), ("wall s", 9), ("M tet-steps/s", 15)
    print("".join(f"{name:>{width}}" for name, width in (*header, ("B/tet", 8), ("RSS MB", 9))))
    for size in args.sizes:
        r = run(size, args.steps, args.device)
        print(
            f"{r['tets']:>10}{r['nodes']:>10}{r['steps']:>7}{r['build_s']:>9.2f}{r['wall_s']:>9.2f}"
            f"{r['tet_steps_per_s'] / 1e6:>15.2f}{r['bytes_per_tet']:>8.0f}{r['peak_rss_mb']:>9.0f}"
            + ("" if r["finite"] else "   NON-FINITE ENERGY")
        )


if __name__ == "__main__":
    main()
