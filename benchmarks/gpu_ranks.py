"""Ranks on a GPU (issue 25: "1 vs 2 ranks on one GPU, just that it runs and agrees within tolerance"): the pour of
benchmarks/parallel_scaling.py in one process on ``cuda:0`` and on 2 ranks asking for ``cuda`` (each rank takes its
node's next GPU, warpdem.parallel.comm.rank_device; on a one-GPU machine both share it), the halo staged through
page-locked host buffers (warpdem.parallel.ranked.Channel).

    python benchmarks/gpu_ranks.py [--spheres 2000] [--end-time 0.05] [--json FILE] [--cpu]

``--cpu`` runs both on the CPU (a dry run of the script; there the two runs are bit for bit, which
tests/test_parallel.py checks).

On a GPU the contact forces sum with float atomics in no fixed order, so two runs, decomposed or not, part after a
few hundred steps of a pour (chaos): the checks are what must hold whatever the order. Both runs end; the same
spheres; the decomposed run says 2 ranks and its spheres migrated; each run's energy books close, the decomposed
run's relative error within ten times the one process's (or 1e-6): a ghost lost or refreshed late would put work
in the books that no force did. Exit status 0 when every check holds. Without ``mpiexec`` beside this Python or on
PATH the script says so and exits 3 (nothing to check).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from parallel_scaling import channel_pour  # beside this script (a script's folder is on sys.path)

ROOT = Path(__file__).resolve().parent.parent


def _run(command: list[str], out: Path) -> dict:
    done = subprocess.run(command, capture_output=True, text=True, timeout=400)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed ({done.returncode}):\n{done.stdout[-2000:]}{done.stderr[-3000:]}")
    return json.loads((out / "summary.json").read_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--spheres", type=int, default=2000)
    p.add_argument("--end-time", type=float, default=0.05, help="simulated seconds of the pour [s]")
    p.add_argument("--json", type=Path, help="the figures and checks as JSON")
    p.add_argument("--cpu", action="store_true", help="both runs on the CPU (a dry run of the script)")
    args = p.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from warpdem.parallel.comm import launcher

    mpiexec = launcher()
    if mpiexec is None:
        print("gpu_ranks: no mpiexec beside this Python or on PATH: nothing to check")
        return 3
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        scene = work / "channel_pour.toml"
        scene.write_text(channel_pour(args.spheres, args.end_time, height=0.05))
        runs = {}
        devices = ("cpu", "cpu") if args.cpu else ("cuda:0", "cuda")
        for name, prefix, device in (("one", [], devices[0]), ("two", [mpiexec, "-n", "2"], devices[1])):
            out = work / name
            command = [*prefix, sys.executable, "-m", "warpdem", str(scene), "--out", str(out), "--quiet"]
            command += ["--device", device, "--summary-json", str(out / "summary.json")]
            env_note = os.environ.get("CUDA_VISIBLE_DEVICES", "all")
            print(f"gpu_ranks: {name}: {' '.join(command)} (CUDA_VISIBLE_DEVICES {env_note})", flush=True)
            runs[name] = _run(command, out)
    one, two = runs["one"], runs["two"]
    checks = {
        "same spheres": one["particles"] == two["particles"],
        "2 ranks recorded": two.get("ranks") == 2,
        "spheres migrated": (two.get("migrations") or 0) > 0,
        "books close on 2 ranks": abs(two["energy_error"]) <= max(10.0 * abs(one["energy_error"]), 1e-6),
    }
    figures = {
        name: {k: run.get(k) for k in ("particles", "steps", "wall_time", "energy_error", "ranks", "migrations")}
        for name, run in runs.items()
    }
    figures["two"]["halo_bytes_per_step"] = two.get("halo_bytes_per_step")
    for name, ok in checks.items():
        print(f"gpu_ranks: {'ok  ' if ok else 'FAIL'} {name}")
    print(json.dumps(figures, indent=1))
    if args.json is not None:
        args.json.write_text(json.dumps({"checks": checks, "figures": figures}, indent=1))
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
