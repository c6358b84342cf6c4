"""The settling case side by side with LIGGGHTS 3.8, on one rank and on N MPI ranks (issue 25's speed target):
``python benchmarks/liggghts_settling.py [--sizes 100000] [--ranks 2]``.

The case is ``python -m warpdem bench``'s (warpdem/bench/settling.py): N spheres of r = 0.01 m, ρ = 2500 kg/m³,
E = 1e7 Pa, ν = 0.3, μ = 0.5, e = 0.5, Hertz–Mindlin with history, no rolling resistance, from the shipped centres at
rest in an open box (floor z = 0, side walls at x = 0, Lx and y = 0, Ly), gravity 9.81 m/s², dt = 5e-5 s, 2000
steps, nothing written while they run. LIGGGHTS gets the same centres through a data file, the same walls as
``wall/gran`` planes, a 4 mm skin as warpdem's (``neighbor 0.004 bin``), its ranks cutting the box across x or y
(``processors * * 1``: the spheres fill the lower half of its box, which a cut in z would leave to one rank), and its
own ``Loop time`` is its wall time;
warpdem's is the bench's timed part (kernels compiled and the step captured before the clock starts). Each code runs
``--repeat`` times and keeps its fastest.

Needs LIGGGHTS (``apt-get install liggghts``: its ``liggghts`` binary and the OpenMPI ``mpirun`` it is built with;
as root OpenMPI also wants OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1, which this script sets) and
warpdem's mpi extra. Prints a Markdown table; ``--json`` writes the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from warpdem.bench.settling import find_case  # noqa: E402

STEPS = 2000

INPUT = """\
atom_style granular
atom_modify map array
boundary f f f
newton off
communicate single vel yes
units si
processors * * 1
read_data {data}
neighbor 0.004 bin
neigh_modify delay 0
fix m1 all property/global youngsModulus peratomtype 1.0e7
fix m2 all property/global poissonsRatio peratomtype 0.3
fix m3 all property/global coefficientRestitution peratomtypepair 1 0.5
fix m4 all property/global coefficientFriction peratomtypepair 1 0.5
pair_style gran model hertz tangential history
pair_coeff * *
timestep 5.0e-5
fix gravi all gravity 9.81 vector 0.0 0.0 -1.0
fix floor all wall/gran model hertz tangential history primitive type 1 zplane 0.0
fix wx0 all wall/gran model hertz tangential history primitive type 1 xplane 0.0
fix wx1 all wall/gran model hertz tangential history primitive type 1 xplane {lx}
fix wy0 all wall/gran model hertz tangential history primitive type 1 yplane 0.0
fix wy1 all wall/gran model hertz tangential history primitive type 1 yplane {ly}
fix integr all nve/sphere
thermo 1000
thermo_style custom step atoms ke
run {steps}
"""


def write_data(path: Path, q, box: dict) -> None:
    """A LIGGGHTS data file of the case's spheres (atom_style granular: id type diameter density x y z)."""
    lo, hi = box["box_lo"], box["box_hi"]
    r, rho = box.get("r", 0.01), box.get("density", 2500.0)
    lines = [
        "settling case (warpdem/data/bench)",
        "",
        f"{len(q)} atoms",
        "1 atom types",
        "",
        f"{lo[0]} {hi[0]} xlo xhi",
        f"{lo[1]} {hi[1]} ylo yhi",
        f"{lo[2]} {hi[2] + 0.5} zlo zhi",
        "",
        "Atoms",
        "",
    ]
    lines += [f"{i + 1} 1 {2 * r!r} {rho!r} {x!r} {y!r} {z!r}" for i, (x, y, z) in enumerate(q.tolist())]
    path.write_text("\n".join(lines) + "\n")


def liggghts(n: int, ranks: int, folder: Path) -> float:
    """LIGGGHTS' loop time [s] of the case on ``ranks`` ranks."""
    q, box = find_case(n)
    data = folder / f"settling_{n}.data"
    if not data.exists():
        write_data(data, q, box)
    script = folder / f"in.settling_{n}"
    script.write_text(INPUT.format(data=data, lx=box["Lx"], ly=box["Ly"], steps=STEPS))
    env = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    command = ["liggghts", "-in", str(script), "-log", str(folder / "log.liggghts"), "-echo", "none"]
    if ranks > 1:
        command = ["/usr/bin/mpirun", "--oversubscribe", "-np", str(ranks), *command]
    done = subprocess.run(command, cwd=folder, capture_output=True, text=True, env=env, check=True)
    loop = re.search(r"Loop time of ([0-9.eE+-]+) on", done.stdout)
    if loop is None:
        raise RuntimeError(f"no loop time in LIGGGHTS' output:\n{done.stdout[-2000:]}")
    return float(loop.group(1))


def warpdem(n: int, ranks: int, folder: Path, repeat: int) -> float:
    """warpdem's timed part [s] of the case on ``ranks`` ranks, the fastest of the bench's ``repeat`` runs in one
    process (the bench's 2 warm-up steps excluded: scaled back to 2000 steps)."""
    out = folder / f"warpdem_{n}_{ranks}.json"
    command = [sys.executable, "-m", "warpdem", "bench", "--sizes", str(n), "--repeat", str(repeat), "--json", str(out)]
    if ranks > 1:
        command = [str(Path(sys.executable).parent / "mpiexec"), "-n", str(ranks), *command]
    subprocess.run(command, cwd=ROOT, capture_output=True, check=True)
    (row,) = json.loads(out.read_text())
    return row["wall_time"] * STEPS / (row["steps"] - 2)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[100000])
    p.add_argument("--ranks", type=int, nargs="+", default=[2])
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    if shutil.which("liggghts") is None:
        print("error: no liggghts on PATH (apt-get install liggghts)", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for n in args.sizes:
            for ranks in [1, *args.ranks]:
                lig = min(liggghts(n, ranks, folder) for _ in range(args.repeat))
                wd = warpdem(n, ranks, folder, args.repeat)
                rows.append({"spheres": n, "ranks": ranks, "liggghts_s": lig, "warpdem_s": wd, "ratio": lig / wd})
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    print(f"settling, {STEPS} steps, books on (warpdem at {commit.stdout.strip()}), fastest of {args.repeat}")
    print("| spheres | ranks | LIGGGHTS 3.8 [s] | warpdem [s] | warpdem / LIGGGHTS speed |")
    print("| ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['spheres']} | {r['ranks']} | {r['liggghts_s']:.2f} | {r['warpdem_s']:.2f} | {r['ratio']:.2f}× |")
    if args.json is not None:
        args.json.write_text(json.dumps({"commit": commit.stdout.strip(), "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
