"""A run decomposed over MPI ranks against the same run in one process (issue 25): wall time, speed-up, and whether
the time series is the one process's bit for bit.

Each row also gives the bytes all ranks' halo messages carry in a step at the run's end (9 float64 a ghost) and the
ghosts over the spheres owned (the share of the owned state sent each step).

The case is a pour: ``--spheres`` beads (radius 4–5 mm, volume fraction 0.3) in a channel 0.2 m wide and tall and as
long as they need, dropped onto its floor for ``--end-time`` simulated seconds (Hertz–Mindlin with rolling
resistance, walls, gravity: what decomposes so far). The channel's length is its longest extent, so the ranks get
slabs across it. Wall time is the run's own (the summary's, kernel compiling and start-up apart).

    python benchmarks/parallel_scaling.py                       # 8 000 and 40 000 spheres, 1 and 2 ranks
    python benchmarks/parallel_scaling.py --spheres 2000 --ranks 2 4 --json out.json

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
    p.add_argument("--ranks", type=int, nargs="+", default=[2])
    p.add_argument("--end-time", type=float, default=0.1, help="simulated seconds [s]")
    p.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "parallel_scaling.json")
    args = p.parse_args(argv)
    rows = []
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.spheres:
            scene = Path(tmp) / f"channel_pour_{n}.toml"
            scene.write_text(channel_pour(n, args.end_time))
            one = run(scene, Path(tmp) / f"{n}_1", 1)
            reference = (Path(tmp) / f"{n}_1" / "channel_pour_series.csv").read_text()
            rows.append(
                {"spheres": one["particles"], "ranks": 1, "steps": one["steps"], "wall_s": one["wall_time"], "halo": 0}
            )
            for ranks in args.ranks:
                many = run(scene, Path(tmp) / f"{n}_{ranks}", ranks)
                series = (Path(tmp) / f"{n}_{ranks}" / "channel_pour_series.csv").read_text()
                rows.append(
                    {
                        "spheres": many["particles"],
                        "ranks": ranks,
                        "steps": many["steps"],
                        "wall_s": many["wall_time"],
                        "halo": many["halo_bytes_per_step"],
                        "speedup": one["wall_time"] / many["wall_time"],
                        "identical_series": series == reference,
                    }
                )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"commit": commit.stdout.strip(), "rows": rows}, indent=1) + "\n")
    print("| spheres | ranks | steps | wall time [s] | speed-up | halo [kB a step] | ghosts / owned | series |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for r in rows:
        speedup = f"{r['speedup']:.2f}×" if "speedup" in r else "—"
        same = {True: "bit for bit", False: "DIFFERS"}.get(r.get("identical_series"), "(reference)")
        # A ghost is fed 9 float64 a step; its owner steps the same 9 values for each sphere it owns.
        ghosts = r["halo"] / 72 / r["spheres"]
        print(
            f"| {r['spheres']} | {r['ranks']} | {r['steps']} | {r['wall_s']:.2f} | {speedup} | {r['halo'] / 1e3:.1f} "
            f"| {ghosts:.3f} | {same} |"
        )
    return 0 if all(r.get("identical_series", True) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
