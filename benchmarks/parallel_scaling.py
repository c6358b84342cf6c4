"""A run decomposed over MPI ranks against the same run in one process (issue 25): wall time, speed-up, and whether
the time series is the one process's bit for bit.

Each row also gives the bytes all ranks' halo messages carry in a step at the run's end (9 float64 a ghost sphere, 9
float32 a ghost node) and the ghosts over the items owned (the share of the owned state sent each step).

The spheres' case is a pour: ``--spheres`` beads (radius 4–5 mm, volume fraction 0.3) in a channel 0.2 m wide and
tall and as long as they need, dropped onto its floor for ``--end-time`` simulated seconds (Hertz–Mindlin with
rolling resistance, walls, gravity). The tets' case (``--tets``) is wave_column.toml made long: a granite column 2 m
square of about that many tets (h = 0.5 m), rollers on its sides, a blast pulse on its top and a non-reflecting base,
run for 400 steps. Both cases are longest along the axis the ranks cut. Wall time is the run's own (the summary's,
kernel compiling and start-up apart).

    python benchmarks/parallel_scaling.py                       # 8 000 and 40 000 spheres, 1 and 2 ranks
    python benchmarks/parallel_scaling.py --spheres 2000 --ranks 2 4 --json out.json
    python benchmarks/parallel_scaling.py --tets 40000 --json benchmarks/results/parallel_scaling_tets.json

Figures go to ``benchmarks/results/parallel_scaling.json`` (``--json`` elsewhere) and as a Markdown table to stdout.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MPIEXEC = Path(sys.executable).parent / "mpiexec"


def channel_pour(spheres: int, end_time: float, height: float = 0.2) -> str:
    """The scene of ``spheres`` beads in a channel 0.2 m wide, filled to ``height`` [m] and long enough to hold them
    at volume fraction 0.3 [TOML text] (tests/test_parallel.py runs a short, low one)."""
    mean_volume = 4.0 / 3.0 * 3.14159 * 0.0045**3
    length = max(0.1, spheres * mean_volume / 0.3 / (0.19 * (height - 0.01))) + 0.02
    return f"""
schema_version = 1
name = "channel_pour"
description = "Beads dropped into a long channel (benchmarks/parallel_scaling.py)"

[run]
end_time = {end_time}
dt = "auto"
safety_factor = 0.2
output_rate = 50.0
seed = 11

[gravity]
vector = [0.0, 0.0, -9.81]

[materials.glass]
density = 2500.0
youngs_modulus = 5.0e7
poisson_ratio = 0.25

[materials.steel]
density = 7800.0
youngs_modulus = 2.0e8
poisson_ratio = 0.3

[interactions]
default = {{ friction = 0.5, restitution = 0.5, rolling_friction = 0.05 }}

[contact]
normal = "hertz"
tangential = "mindlin"
rolling = "constant_torque"

[parts.beads]
material = "glass"

[[particles]]
kind = "packing"
part = "beads"
region = {{ box = {{ lo = [0.005, 0.005, 0.005], hi = [{length - 0.005:.4f}, 0.195, {height - 0.005:.4f}] }} }}
radius = 0.004
radius_max = 0.005
arrangement = "random"
volume_fraction = 0.3
count = {spheres}

[[walls]]
kind = "box"
lo = [0.0, 0.0, 0.0]
hi = [{length:.4f}, 0.2, 0.4]
material = "steel"
open_top = true
"""


def long_column(tets: int) -> str:
    """wave_column.toml made ``tets`` tets long (4 × 4 cells of 0.5 m across, 6 tets a cell) [TOML text], for 400
    steps of its own time step."""
    cells = max(1, round(tets / 96))
    return f"""
schema_version = 1
name = "long_column"
description = "A blast pulse down a long rock column (benchmarks/parallel_scaling.py)"

[run]
end_time = 0.0096
dt = 2.4e-5
output_rate = 500.0

[gravity]
vector = [0.0, 0.0, 0.0]

[materials.granite]
density = 2650.0
youngs_modulus = 6.0e10
poisson_ratio = 0.25
bulk_viscosity_linear = 0.06
bulk_viscosity_quadratic = 1.2

[mesh]
kind = "box"
lo = [0.0, 0.0, 0.0]
hi = [2.0, 2.0, {0.5 * cells}]
divisions = [4, 4, {cells}]
material = "granite"

[[loads]]
kind = "pressure"
faces = "z+"
history = {{ kind = "blast", peak = 1.0e7, rise_time = 2.0e-4, decay_time = 4.0e-4, start = 0.0 }}

[[boundaries]]
faces = "z-"
kind = "non_reflecting"

[[boundaries]]
faces = "x-"
kind = "roller"

[[boundaries]]
faces = "x+"
kind = "roller"

[[boundaries]]
faces = "y-"
kind = "roller"

[[boundaries]]
faces = "y+"
kind = "roller"
"""


def run(scene: Path, out: Path, ranks: int) -> dict:
    """One run of ``scene`` on ``ranks`` ranks (1: one process, no mpiexec); its summary."""
    summary = out / "summary.json"
    command = [
        sys.executable,
        "-m",
        "warpdem",
        str(scene),
        "--out",
        str(out),
        "--quiet",
        "--summary-json",
        str(summary),
    ]
    if ranks > 1:
        command = [str(MPIEXEC), "-n", str(ranks), *command]
    subprocess.run(command, check=True)
    return json.loads(summary.read_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--spheres", type=int, nargs="+", default=[8000, 40000])
    p.add_argument("--tets", type=int, nargs="+", help="run the tets' case at these sizes instead")
    p.add_argument("--ranks", type=int, nargs="+", default=[2])
    p.add_argument("--end-time", type=float, default=0.1, help="simulated seconds of the pour [s]")
    p.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "parallel_scaling.json")
    args = p.parse_args(argv)
    rows = []
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    # What a row counts and what the halo sends of each ghost: 9 float64 a sphere, 9 float32 a node.
    items, ghost_bytes = ("nodes", 36) if args.tets else ("particles", 72)
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.tets or args.spheres:
            stem = "long_column" if args.tets else "channel_pour"
            scene = Path(tmp) / f"{stem}_{n}.toml"
            scene.write_text(long_column(n) if args.tets else channel_pour(n, args.end_time))
            one = run(scene, Path(tmp) / f"{n}_1", 1)
            reference = (Path(tmp) / f"{n}_1" / f"{stem}_series.csv").read_text()
            rows.append({"items": one[items], "ranks": 1, "steps": one["steps"], "wall_s": one["wall_time"], "halo": 0})
            for ranks in args.ranks:
                many = run(scene, Path(tmp) / f"{n}_{ranks}", ranks)
                series = (Path(tmp) / f"{n}_{ranks}" / f"{stem}_series.csv").read_text()
                rows.append(
                    {
                        "items": many[items],
                        "ranks": ranks,
                        "steps": many["steps"],
                        "wall_s": many["wall_time"],
                        "halo": many["halo_bytes_per_step"],
                        "migrations": many["migrations"],
                        "speedup": one["wall_time"] / many["wall_time"],
                        "identical_series": series == reference,
                    }
                )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    record = {"commit": commit.stdout.strip(), "case": stem, "items": items, "rows": rows}
    args.json.write_text(json.dumps(record, indent=1) + "\n")
    header = "ranks | steps | wall time [s] | speed-up | halo [kB a step] | ghosts / owned | migrations | series"
    print(f"| {items} | {header} |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for r in rows:
        speedup = f"{r['speedup']:.2f}×" if "speedup" in r else "—"
        same = {True: "bit for bit", False: "DIFFERS"}.get(r.get("identical_series"), "(reference)")
        ghosts = r["halo"] / ghost_bytes / r["items"]
        print(
            f"| {r['items']} | {r['ranks']} | {r['steps']} | {r['wall_s']:.2f} | {speedup} | {r['halo'] / 1e3:.1f} "
            f"| {ghosts:.3f} | {r.get('migrations', 0)} | {same} |"
        )
    return 0 if all(r.get("identical_series", True) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
