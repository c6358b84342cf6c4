"""The counted budget (issue 24): what a step, the work between two chunks of steps, a split pass, the energy books
and a frame of a shipped scene ask of the device — eager launches, graph replays, captures, read-backs, copies,
allocations — counted with warpdem.budget on the fracture benchmark's blocks, at two sizes (what does not grow with
the body count is the point), and the cracking run's throughput with a pass every 1 and 10 steps against none.

    python benchmarks/budget.py [--cells 6 10] [--split-cells 12 20] [--frame-scenes SCENE ...] [--no-run]

The counter is loaded from this checkout's ``warpdem/budget.py`` by path, and the simulation from whatever
``warpdem`` Python finds, so the same script counts an older checkout too (``PYTHONPATH=/path/to/old python
benchmarks/budget.py``: the figures "before" in docs/benchmarks.md came that way).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

_spec = importlib.util.spec_from_file_location(
    "warpdem_budget", Path(__file__).resolve().parent.parent / "warpdem" / "budget.py"
)
budget_module = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = budget_module  # its dataclass looks itself up there
_spec.loader.exec_module(budget_module)
counted = budget_module.counted


def step_and_chunk(cells: int) -> tuple[str, str, str]:
    """The counts of 5 steps (``Simulation._run``), of one step with its between-steps work (``advance(1)``: the
    chunk epilogue and a split pass that finds nothing) and of ten such chunks in one call (``advance(10)``), on the
    cracking block of ``cells``³ cells before it cracks."""
    from warpdem.bench.fracture import cracking_block

    sim = cracking_block(cells, "cpu", steps=200, interval=1)
    sim.advance(2)
    sim.advance(1)  # the snapshot's first copy builds its word tables (warpdem.fused), outside the count
    with counted() as steps:
        sim._run(5)
    with counted() as chunk:
        sim.advance(1)
    with counted() as chunks:
        sim.advance(10)
    return steps.line(), chunk.line(), chunks.line()


def split_pass(cells: int, books: bool = False) -> tuple[int, int, str]:
    """The counts of one split pass that splits (1 % of the nodes, the stretched block of ``bench fracture``), with
    the energy books kept (``books``: as every run keeps them) or not (as ``bench fracture`` times the pass)."""
    from warpdem.bench.fracture import spread_nodes, stretched_block
    from warpdem.simulation import Simulation

    may_split = spread_nodes(cells, 0.01, 0)
    capacity = (cells + 1) ** 3 + int(np.count_nonzero(may_split))
    model, state = stretched_block(cells, "cpu", may_split, node_capacity=capacity)
    sim = Simulation(model, state, track_energy=books)
    sim.fracture_pass()  # compiles; a second block is timed
    model, state = stretched_block(cells, "cpu", may_split, node_capacity=capacity)
    sim = Simulation(model, state, track_energy=books)
    sim.energy()  # the books' scratch, made before the pass (a run has made it at its first frame)
    with counted() as b:
        report = sim.fracture_pass()
    return 6 * cells**3, report.splits, b.line()


def passes_in_a_run(cells: int) -> tuple[str, str, int, int]:
    """The counts of the split passes of the cracking run (``cells``³ cells, a pass every step, books kept), each
    as ``Simulation.fracture_pass`` asks them inside ``advance``: the median of the passes that split and of those
    that did not, after the run's first three passes of each kind (the first runs eagerly; warpdem.recorded records
    the pass the second time it sees the same arrays), and how many of each were counted."""
    from warpdem.bench.fracture import cracking_block
    from warpdem.simulation import Simulation

    sim = cracking_block(cells, "cpu", steps=200, interval=1)
    sim.track_energy = True  # as a run keeps them (set so, an older checkout's block takes it too)
    fracture_pass = Simulation.fracture_pass
    seen: dict[bool, list] = {True: [], False: []}

    def counted_pass(self, *args, **kwargs):
        with counted() as b:
            report = fracture_pass(self, *args, **kwargs)
        seen[report.splits > 0].append(b)
        return report

    Simulation.fracture_pass = counted_pass
    try:
        sim.advance(200)
    finally:
        Simulation.fracture_pass = fracture_pass

    def median(budgets: list) -> str:
        later = budgets[3:] or budgets
        if not later:
            return "none"
        fields = later[0].__dataclass_fields__
        values = {f: int(np.median([getattr(b, f) for b in later])) for f in fields}
        return ", ".join(f"{k} {v}" for k, v in values.items())

    return median(seen[True]), median(seen[False]), len(seen[True]), len(seen[False])


def books(cells: int) -> str:
    """The counts of reading the energy books and the shadow term (``Simulation.energy()`` and ``shadow()``) on the
    cracking block of ``cells``³ cells, their scratch made."""
    from warpdem.bench.fracture import cracking_block

    sim = cracking_block(cells, "cpu", steps=200, interval=1)
    sim.advance(2)
    sim.energy()
    with counted() as b:
        sim.energy()
        sim.shadow()
    return b.line()


def frame(scene: str) -> str:
    """The counts of writing one frame of a shipped scene (``Run._write_frame``: the books, the USD frame, the time
    series, fragments, VTU as the scene asks), after its first frame; ``default`` is the embedded scene."""
    import tempfile

    from warpdem.api import build
    from warpdem.scene import default_scene_path

    root = Path(__file__).resolve().parent.parent
    path = default_scene_path() if scene == "default" else root / "scenes" / f"{scene}.toml"
    with tempfile.TemporaryDirectory() as out:
        run = build(path, device="cpu", frames=2, out_dir=out)
        try:
            next(iter(run.frames()))
            with counted() as b:
                run._write_frame()
        finally:
            run.close()
    return b.line()


def cracking(interval: int, repeat: int = 2) -> str:
    from warpdem.bench.fracture import bench_cracking_run

    best = min(
        (bench_cracking_run(10_000, steps=200, interval=interval) for _ in range(repeat)), key=lambda r: r.wall_time
    )
    return (
        f"cracking run, a pass every {interval:2d} steps: {best.tet_steps_per_second / 1e6:6.3f} M tet-steps/s "
        f"({best.wall_time:.2f} s for {best.steps} steps, {best.splits} splits)"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cells", type=int, nargs="+", default=[6, 10], help="cracking blocks' cells per side")
    p.add_argument("--split-cells", type=int, nargs="+", default=[12, 20], help="stretched blocks' cells per side")
    p.add_argument("--frame-scenes", nargs="*", default=["default", "pmma_plate", "masonry_wall_blast"])
    p.add_argument("--no-run", action="store_true", help="skip the cracking run's throughput")
    a = p.parse_args()
    from warpdem.cli import init_warp

    init_warp()
    for cells in a.cells:
        steps, chunk, chunks = step_and_chunk(cells)
        print(f"{6 * cells**3:>7} tets  5 steps:                  {steps}")
        print(f"{6 * cells**3:>7} tets  1 step + between-steps:   {chunk}")
        print(f"{6 * cells**3:>7} tets  10 steps + between-steps: {chunks}")
        print(f"{6 * cells**3:>7} tets  energy() + shadow():       {books(cells)}")
    for cells in a.cells:
        split, idle, n_split, n_idle = passes_in_a_run(cells)
        print(f"{6 * cells**3:>7} tets  a pass that splits, in a run ({n_split}; median):      {split}")
        print(f"{6 * cells**3:>7} tets  a pass that splits nothing, in a run ({n_idle}; median): {idle}")
    for keep in (False, True):
        for cells in a.split_cells:
            tets, splits, line = split_pass(cells, keep)
            print(f"{tets:>7} tets  split pass ({splits} splits), books {'on ' if keep else 'off'}:  {line}")
    for scene in a.frame_scenes:
        print(f"a frame of {scene}: {frame(scene)}", flush=True)
    if not a.no_run:
        for interval in (0, 1, 10):
            t = time.perf_counter()
            print(cracking(interval), f"[{time.perf_counter() - t:.0f} s]", flush=True)


if __name__ == "__main__":
    main()
