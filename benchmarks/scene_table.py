"""The shipped scenes' table (README.md and docs/scenes.md): the default scene and each scene of ``scenes/`` run to its
own end time as a user runs it (``python -m warpdem SCENE --summary-json ...``), with its wall time on this machine,
its steps, the energy books' error and what broke.

Run from the repository root::

    python benchmarks/scene_table.py [SCENE ...] [--device cpu] [--out benchmarks/results/scene_table.json]

Each scene is first run for one frame, so that its kernels are compiled and cached before the timed run (the table's
wall time is the run's, not first-use compiling). Every row is written with the commit and the machine it ran on;
``--markdown`` prints the table from an existing results file without running anything.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = "default"
"""The embedded default scene (``python -m warpdem`` without a scene file)."""
SCENES = [DEFAULT, *sorted(p.stem for p in (ROOT / "scenes").glob("*.toml"))]
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "scene_table.json"


def stamp() -> dict:
    """The commit and machine the figures come from."""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True)
        commit += "+dirty" if dirty.stdout.strip() else ""
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "commit": commit,
        "machine": f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "date": time.strftime("%Y-%m-%d"),
    }


def run_scene(name: str, device: str, work: Path, keep: Path | None = None) -> dict:
    """One scene to its end time: the CLI's summary plus the wall time of the process [s]; its outputs go to
    ``keep / name`` when given (else a scratch folder)."""
    scene = [] if name == DEFAULT else [str(ROOT / "scenes" / f"{name}.toml")]
    base = [sys.executable, "-m", "warpdem", *scene, "--device", device, "--quiet"]
    warm = subprocess.run([*base, "--frames", "1", "--out", str(work / "warm")], capture_output=True, text=True)
    if warm.returncode != 0:
        return {"scene": name, "error": warm.stderr.strip().splitlines()[-1:]}
    summary = work / f"{name}.json"
    start = time.perf_counter()
    run = subprocess.run(
        [*base, "--out", str((keep or work) / name), "--summary-json", str(summary)], capture_output=True, text=True
    )
    wall = time.perf_counter() - start
    if run.returncode != 0:
        return {"scene": name, "error": run.stderr.strip().splitlines()[-1:], "wall_s": wall}
    s = json.loads(summary.read_text())
    return {
        "scene": name,
        "wall_s": round(wall, 1),
        "simulated_s": s["simulated_time"],
        "steps": s["steps"],
        "spheres": s["particles"],
        "tets": s["tets"],
        "books": s["energy_error"],
        "energy_in_play_J": s["energy_in_play"],
        "splits": s["splits"],
        "bonds_broken": s["bonds_broken"],
        "fragments": s["fragment_count"],
        "usd": s["usd_path"] and Path(s["usd_path"]).name,
    }


def markdown(results: dict) -> str:
    """The table as Markdown, stamped."""
    lines = [
        "| scene | simulated | wall (2 CPU cores) | steps | spheres | tets | books | what broke |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in results["scenes"]:
        if "error" in r:
            lines.append(f"| `{r['scene']}` | failed: {' '.join(r['error'])} | | | | | | |")
            continue
        broke = []
        if r["splits"]:
            broke.append(f"{r['splits']} splits")
        if r["bonds_broken"]:
            broke.append(f"{r['bonds_broken']} bonds")
        if r["fragments"]:
            broke.append(f"{r['fragments']} fragments")
        lines.append(
            f"| `{r['scene']}` | {r['simulated_s']:.3g} s | {r['wall_s']:.0f} s | {r['steps']} | {r['spheres']} | "
            f"{r['tets']} | {r['books']:+.1e} | {', '.join(broke) or '-'} |"
        )
    lines.append("")
    stamps = sorted({(r["stamp"]["commit"], r["stamp"]["machine"], r["stamp"]["date"]) for r in results["scenes"]})
    for commit, machine, date in stamps:
        lines.append(f"*`python benchmarks/scene_table.py`: commit {commit}, {machine}, {date}.*")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="*", metavar="SCENE", help=f"one of {', '.join(SCENES)} [all]")
    parser.add_argument("--device", default="cpu", help="Warp device [cpu]")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="results file (JSON) [%(default)s]")
    parser.add_argument("--markdown", action="store_true", help="print the table of an existing results file")
    parser.add_argument(
        "--keep",
        type=Path,
        help="keep each run's outputs (stage, series) in KEEP/SCENE (the pictures are drawn from them)",
    )
    args = parser.parse_args(argv)
    if args.markdown:
        print(markdown(json.loads(args.out.read_text())))
        return 0
    unknown = [s for s in args.scenes if s not in SCENES]
    if unknown:
        parser.error(f"unknown scene {unknown[0]!r}; allowed: {', '.join(SCENES)}")
    results = {"scenes": []}
    here = stamp()
    previous = json.loads(args.out.read_text()) if args.out.is_file() else None
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes or SCENES:
            row = run_scene(name, args.device, Path(tmp), args.keep) | {"stamp": here}
            print(json.dumps(row), flush=True)
            results["scenes"].append(row)
    if previous and args.scenes:  # a partial run keeps the other scenes' rows, each with its own stamp
        kept = [r for r in previous["scenes"] if r["scene"] not in args.scenes]
        results["scenes"] = sorted(kept + results["scenes"], key=lambda r: r["scene"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp_out = args.out.with_suffix(".json.tmp")
    tmp_out.write_text(json.dumps(results, indent=1) + "\n")
    tmp_out.replace(args.out)
    print(markdown(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
