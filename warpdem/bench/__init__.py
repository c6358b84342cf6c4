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

from .blocks import BlockBenchResult, bench_blocks, format_block_row, jointed_cube, run_block_bench
from .common import GRANITE, timed, write_json
from .conversion import (
    CONVERSION_FRACTION,
    CONVERSION_SLAB,
    PASS_BENCHES,
    TRESCA_STRENGTH,
    ConversionPassResult,
    ConvertingRunResult,
    bench_conversion_pass,
    bench_converting_run,
    converting_block,
    converting_run_block,
    due_tets,
    format_conversion_pass_row,
    format_converting_run_row,
    lattice_counts,
    run_pass_bench,
    spread_tets,
)
from .fracture import (
    FRACTURE_ENERGY,
    GRAIN_CELLS,
    STRENGTH_CLASSES,
    STRETCH,
    TENSILE_STRENGTH,
    CrackingRunResult,
    FracturePassResult,
    bench_cracking_run,
    bench_fracture_pass,
    cells_for,
    cracking_block,
    force_step_time,
    format_pass_row,
    format_run_row,
    pulled_granite,
    qualifying_nodes,
    spread_nodes,
    stretched_block,
    stretched_granite,
    uniaxial_strain_modulus,
)
from .settling import DATA_DIR, BenchResult, bench_settling, find_case, format_table, run_bench, settling_case
from .tets import TetBenchResult, bench_tets, format_tet_row, run_tet_bench, vibrating_block

__all__ = [
    "CONVERSION_FRACTION",
    "CONVERSION_SLAB",
    "DATA_DIR",
    "FRACTURE_ENERGY",
    "GRAIN_CELLS",
    "GRANITE",
    "PASS_BENCHES",
    "STRENGTH_CLASSES",
    "STRETCH",
    "TENSILE_STRENGTH",
    "TRESCA_STRENGTH",
    "BenchResult",
    "BlockBenchResult",
    "ConversionPassResult",
    "ConvertingRunResult",
    "CrackingRunResult",
    "FracturePassResult",
    "TetBenchResult",
    "bench_blocks",
    "bench_conversion_pass",
    "bench_converting_run",
    "bench_cracking_run",
    "bench_fracture_pass",
    "bench_settling",
    "bench_tets",
    "cells_for",
    "converting_block",
    "converting_run_block",
    "cracking_block",
    "due_tets",
    "find_case",
    "force_step_time",
    "format_block_row",
    "format_conversion_pass_row",
    "format_converting_run_row",
    "format_pass_row",
    "format_run_row",
    "format_table",
    "format_tet_row",
    "jointed_cube",
    "lattice_counts",
    "pulled_granite",
    "qualifying_nodes",
    "run_bench",
    "run_block_bench",
    "run_pass_bench",
    "run_tet_bench",
    "settling_case",
    "spread_nodes",
    "spread_tets",
    "stretched_block",
    "stretched_granite",
    "timed",
    "uniaxial_strain_modulus",
    "vibrating_block",
    "write_json",
]
