"""How the cohesive elements' sub-steps resolve a blast's openings: ``python benchmarks/cohesive_substeps.py
[--scene PATH] [--end-time T] [--runs N:S ...]``.

Runs the scene (a fracture scene; default scenes/limestone_tunnel.toml) to ``--end-time`` (default 4 ms, before its
rigid switch) through the runner, as ``warpdem run`` does, once per ``N:S`` pair: ``[fracture] cohesive_substeps`` =
N, ``[run] safety_factor`` = S (N alone: the scene's; default: 1, 2, 4, 8, 16 and 32 sub-steps at limestone_tunnel's
0.5, then 8 at 0.25 and 0.125). Prints per run, as a Markdown table: the node splits and broken elements, the law's line
(``energy_dissipated_cohesive``, Γ A_f of the broken elements and ½ f_c δ_max of the intact ones), the elements' work
off the law (``energy_cohesive_trapezoid``), the sub-step work line (``energy_substep_work``), the balance's relative
error and the wall time of the run (build included) on this machine.

What to read: the trapezoid line is what the steps make the elements do beyond their law (warpdem.stages.substep);
sub-steps shrink it without touching the rest of the model's step, where a smaller ``safety_factor`` shrinks it by
stepping everything. The splits themselves follow the step (a pass every 25 steps sees the stresses of another step),
so the law's line moves with S, not with N.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from warpdem.io.timeseries import read_series
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_RUNS = ("1:0.5", "2:0.5", "4:0.5", "8:0.5", "16:0.5", "32:0.5", "8:0.25", "8:0.125")


def run_once(path: Path, substeps: int, safety: float | None, end_time: float) -> dict[str, float]:
    """One run of the scene with ``substeps`` and ``safety`` (None: the scene's) to ``end_time`` [s]: the last
    frame's lines."""
    scene = load_scene(path)
    fracture = scene.fracture.model_copy(update={"cohesive_substeps": substeps})
    run = scene.run if safety is None else scene.run.model_copy(update={"safety_factor": safety})
    scene = scene.model_copy(update={"fracture": fracture, "run": run})
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        # The scene's own frames, so the steps are those of ``warpdem run`` to the same end.
        run_scene(scene, RunOptions(device="cpu", end_time=end_time, out_dir=Path(out), quiet=True))
        wall = time.perf_counter() - start
        series = read_series(next(Path(out).glob("*_series.csv")))
    row = {name: float(series[name][-1]) for name in series}
    row["wall"] = wall
    row["safety"] = scene.run.safety_factor
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, default=ROOT / "scenes" / "limestone_tunnel.toml")
    parser.add_argument("--end-time", type=float, default=0.004, help="simulated time [s] (default 4 ms)")
    parser.add_argument(
        "--runs", nargs="+", default=list(DEFAULT_RUNS), help="N:S pairs (sub-steps:safety), or N (the scene's safety)"
    )
    args = parser.parse_args(argv)
    print(f"{args.scene.stem}, {args.end_time * 1e3:g} ms")
    print()
    print(
        "| sub-steps | safety | splits | broken | law's line [J] | trapezoid [J] | sub-step work [J] | balance error "
        "| wall [s] |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for item in args.runs:
        n, _, s = item.partition(":")
        safety = float(s) if s else None
        r = run_once(args.scene, int(n), safety, args.end_time)
        print(
            f"| {int(n)} | {r['safety']:g} | {r['splits']:.0f} | {r['cohesive_broken']:.0f} "
            f"| {r['energy_dissipated_cohesive']:.4g} | {r['energy_cohesive_trapezoid']:.4g} "
            f"| {r['energy_substep_work']:.4g} | {r['energy_error']:.1e} | {r['wall']:.1f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
