"""The check script's helpers (``benchmarks/gpu_check.sh``, issue 24): settling cases the package does not ship,
and the script's ``summary.json`` (each step's checks recorded as it ends, the human summary at the end).

    python benchmarks/gpu_record.py settling-cases N [N ...] --data DIR
    python benchmarks/gpu_record.py record --summary FILE --name NAME --kind KIND [--rc RC --wall S --log F --json F]
    python benchmarks/gpu_record.py summary FILE

``settling-cases`` writes ``init_N*.txt`` and ``box_N*.json`` for ``python -m warpdem bench --data DIR`` (the package
has N = 10 000 and 100 000); ``record`` adds a step's result to ``summary.json``; ``summary`` prints it and exits 1
when a check failed.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


def check(name: str, passed: bool, figures: dict[str, Any], message: str = "", expected: bool = False) -> dict:
    """One check as summary.json holds it."""
    out = {"name": name, "passed": bool(passed), "figures": figures, "message": message}
    if expected:
        out["expected_failure"] = True
    return out


# ----------------------------------------------------------------------------------------------------------------
# Settling cases beyond the shipped ones


SETTLING_SPACING = 0.022
"""Lattice spacing of the settling cases' initial centres [m] (the shipped cases': 2.2 radii)."""

SETTLING_JITTER = 0.0005
"""Half-width of the uniform jitter added to each coordinate [m] (the shipped cases')."""


def _format_rows(rows: np.ndarray) -> str:
    """``x y z`` lines of centres [m], as the shipped case files write them."""
    text = io.StringIO()
    np.savetxt(text, rows, fmt="%.10e")
    return text.getvalue()


def write_settling_case(n: int, folder: Path, workers: int) -> None:
    """The settling case of N = k³ spheres in ``folder``: ``init_N<N>.txt`` (centres on a k × k × k lattice of spacing
    SETTLING_SPACING [m], each coordinate jittered by ± SETTLING_JITTER, seed 12345, x fastest) and ``box_N<N>.json``
    (box side L = k × spacing [m], radius 0.01 m, density 2500 kg/m³), the recipe of the shipped cases (whose centres
    came from another generator: the same lattice, not the same jitter). The text is formatted by ``workers``
    processes (8 M lines take ~40 s on one core)."""
    from multiprocessing import Pool

    k = round(n ** (1.0 / 3.0))
    if k**3 != n:
        raise ValueError(f"a settling case needs a cube number of spheres (got {n})")
    rng = np.random.default_rng(12345)
    i = np.arange(n)
    lattice = np.stack([i % k, (i // k) % k, i // (k * k)], axis=1).astype(np.float64)
    centres = SETTLING_SPACING * (lattice + 0.5) + rng.uniform(-SETTLING_JITTER, SETTLING_JITTER, size=(n, 3))
    chunks = np.array_split(centres, max(1, min(workers * 4, n // 10000)))
    with Pool(max(1, min(workers, len(chunks)))) as pool:
        parts = pool.map(_format_rows, chunks)
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f"init_N{n}.txt.tmp"
    with tmp.open("w") as f:
        f.writelines(parts)
    tmp.replace(folder / f"init_N{n}.txt")
    side = k * SETTLING_SPACING
    box = {
        "N": n,
        "nx": k,
        "ny": k,
        "nz": k,
        "Lx": side,
        "Ly": side,
        "r": 0.01,
        "density": 2500.0,
        "spacing": SETTLING_SPACING,
        "jitter": SETTLING_JITTER,
        "seed": 12345,
        "mean_z0": float(centres[:, 2].mean()),
        "note": "written by benchmarks/gpu_compare.py settling-cases (the shipped cases' recipe)",
    }
    write_json(folder / f"box_N{n}.json", box)


# ----------------------------------------------------------------------------------------------------------------
# summary.json


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` as JSON through a temporary name (a reader never sees half a file)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)


def _finite(*values: Any) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


GPU_TARGETS = {"settling": 2.0e9, "tets": 8.0e9, "pass_in_steps": 20.0}
"""Issue 24's targets on a GPU (docs/benchmarks.md; reported with the figures, not checked: speed is no
correctness): particle-steps/s of settling at N ≥ 1 M with the books on, tet-steps/s of the tets, a split or
conversion pass at 1 M tets in force steps."""


def bench_figures(kind: str, data: Any) -> tuple[bool, dict[str, Any], str]:
    """The main figures of a benchmark's JSON, whether they are sane, and a message when not; on a GPU, with the
    targets of :data:`GPU_TARGETS` (``meets_target``)."""
    if kind == "settling":
        rows = [
            {
                k: r[k]
                for k in (
                    "device",
                    "particles",
                    "steps",
                    "wall_time",
                    "particle_steps_per_second",
                    "mean_contacts_per_particle",
                    "neighbor_rebuilds",
                    "state_memory_mb",
                    "kinetic_translational",
                    "mean_height",
                    "mean_height_initial",
                )
            }
            for r in data
        ]
        for r in rows:
            if r["device"].startswith("cuda") and r["particles"] >= 1_000_000:
                r["meets_target"] = r["particle_steps_per_second"] >= GPU_TARGETS["settling"]
        # The spheres start at rest under gravity: after any steps their mean height is lower, their energy finite.
        sane = bool(rows) and all(
            _finite(r["kinetic_translational"], r["mean_height"]) and r["mean_height"] < r["mean_height_initial"]
            for r in rows
        )
        return sane, {"rows": rows}, "" if sane else "non-finite energy, or the spheres did not fall"
    if kind == "tets":
        rows = [
            {
                k: r[k]
                for k in ("device", "tets", "steps", "build_time", "wall_time", "tet_steps_per_second", "bytes_per_tet")
            }
            | {"finite": r["finite"]}
            for r in data
        ]
        for r in rows:
            if r["device"].startswith("cuda"):
                r["meets_target"] = r["tet_steps_per_second"] >= GPU_TARGETS["tets"]
        sane = bool(rows) and all(r["finite"] for r in rows)
        return sane, {"rows": rows}, "" if sane else "non-finite energy"
    if kind in ("fracture", "conversion"):
        done = "splits" if kind == "fracture" else "converted"
        passes = [
            {k: p[k] for k in ("tets", "nodes", "due", done, "build_time", "step_time", "pass_time", "pass_in_steps")}
            for p in data["passes"]
        ]
        for p, raw in zip(passes, data["passes"], strict=True):
            if raw["device"].startswith("cuda"):
                p["meets_target"] = p["pass_in_steps"] < GPU_TARGETS["pass_in_steps"]
        runs = [
            {k: r[k] for k in ("tets", "interval", "steps", "steps_per_second", "tet_steps_per_second", done)}
            for r in data["runs"]
        ]
        # The pass must do exactly what is due (the command exits 1 otherwise); a run with its pass on must crack.
        sane = all(p[done] == p["due"] for p in passes) and all(r[done] > 0 for r in runs if r["interval"] > 0)
        message = "" if sane else f"the pass did other than the {done} due, or a run with passes did not crack"
        return sane, {"passes": passes, "runs": runs}, message
    raise ValueError(f"unknown benchmark kind {kind!r}")


PYTEST_COUNTS = re.compile(r"(\d+) (passed|failed|skipped|deselected|errors?|xfailed|xpassed)")


def pytest_figures(log: Path) -> dict[str, Any]:
    """The counts of pytest's last summary line ("12 passed, 40 deselected in 61.2s") in its log."""
    lines = [x for x in log.read_text(errors="replace").splitlines() if re.search(r" in [\d.]+s", x)]
    if not lines:
        return {}
    figures: dict[str, Any] = {name: int(n) for n, name in PYTEST_COUNTS.findall(lines[-1])}
    seconds = re.search(r" in ([\d.]+)s", lines[-1])
    if seconds:
        figures["seconds"] = float(seconds.group(1))
    return figures


def record(args: argparse.Namespace) -> int:
    """Add one step's checks to summary.json (made with ``--mode`` and ``--device`` when it does not exist)."""
    summary_path: Path = args.summary
    if summary_path.is_file():
        summary = json.loads(summary_path.read_text())
    else:
        summary = {"mode": args.mode, "device": args.device, "checks": []}
    base = {"wall_s": args.wall, "exit_status": args.rc}
    status = "" if args.rc == 0 else f"exit status {args.rc}" + (" (timed out)" if args.rc in (124, 137) else "")
    new: list[dict] = []
    if args.kind == "skipped":
        new.append(check(args.name, False, base, args.note or "not run"))
    elif args.kind == "compare":
        path = args.json
        if path is not None and path.is_file():
            data = json.loads(path.read_text())
            new += data["checks"]
        else:
            new.append(check(args.name, False, base, f"{status}: no compare.json (see the step's log)"))
    elif args.kind == "command":
        # A script that checks by its exit status (benchmarks/gather_forces.py asserts): its last lines as figures.
        tail = args.log.read_text(errors="replace").splitlines()[-4:] if args.log and args.log.is_file() else []
        new.append(check(args.name, args.rc == 0, base | {"output_tail": tail}, status))
    elif args.kind == "pytest":
        figures = base | pytest_figures(args.log)
        ran = figures.get("passed", 0) + figures.get("failed", 0)
        # Exit 5 (nothing collected) or no CUDA case run at all is a failure: the step exists to run them.
        passed = args.rc == 0 and ran > 0
        new.append(check(args.name, passed, figures, status or ("" if ran else "no test ran")))
    else:
        if args.json is not None and args.json.is_file():
            sane, figures, message = bench_figures(args.kind, json.loads(args.json.read_text()))
        else:
            sane, figures, message = False, {}, "no JSON written"
        new.append(
            check(args.name, args.rc == 0 and sane, base | figures, "; ".join(x for x in (status, message) if x))
        )
    if args.note:
        for c in new:
            c["note"] = args.note
    summary["checks"] = [c for c in summary["checks"] if c["name"] not in {n["name"] for n in new}] + new
    step = {"name": args.name, "kind": args.kind, "exit_status": args.rc, "wall_s": args.wall}
    summary.setdefault("steps", []).append(step | ({"log": str(args.log)} if args.log else {}))
    failed = [c["name"] for c in summary["checks"] if not c["passed"]]
    summary["failed"] = failed
    summary["unexpected_failures"] = [
        c["name"] for c in summary["checks"] if not c["passed"] and not c.get("expected_failure")
    ]
    summary["passed"] = not failed
    write_json(summary_path, summary)
    for c in new:
        print(f"{'PASS' if c['passed'] else 'FAIL'}  {c['name']}  {c.get('message', '')}", flush=True)
    return 0


def print_summary(path: Path) -> int:
    """The human summary of summary.json; 1 when a check failed (or none ran), else 0."""
    summary = json.loads(path.read_text())
    checks = summary.get("checks", [])
    print(f"GPU check summary ({summary.get('mode')} mode, device {summary.get('device')}): {path}")
    for c in checks:
        mark = "PASS" if c["passed"] else ("FAIL (expected)" if c.get("expected_failure") else "FAIL")
        print(f"  {mark:<16}{c['name']}" + (f"  [{c['message']}]" if c.get("message") else ""))
        for line in _main_figures(c["figures"]):
            print(f"  {'':<16}  {line}")
    failed = [c for c in checks if not c["passed"]]
    unexpected = [c for c in failed if not c.get("expected_failure")]
    print(
        f"{len(checks) - len(failed)} of {len(checks)} checks passed; {len(failed)} failed "
        f"({len(unexpected)} unexpectedly)"
    )
    return 1 if failed or not checks else 0


def _main_figures(figures: dict[str, Any]) -> list[str]:
    """A line or two of a check's figures for the human summary (the rest is in summary.json)."""
    out = []
    for row in figures.get("rows", []):
        if "particle_steps_per_second" in row:
            out.append(
                f"{row['particles']} spheres: {row['particle_steps_per_second'] / 1e6:.1f} M particle-steps/s "
                f"(books on), {row['mean_contacts_per_particle']:.2f} contacts/particle" + _target(row)
            )
        else:
            out.append(
                f"{row['tets']} tets: {row['tet_steps_per_second'] / 1e6:.1f} M tet-steps/s, build "
                f"{row['build_time']:.1f} s" + _target(row)
            )
    for p in figures.get("passes", []):
        out.append(
            f"pass on {p['tets']} tets: {p['pass_in_steps']:.1f} force steps ({p['pass_time'] * 1e3:.1f} ms)"
            + _target(p)
        )
    for r in figures.get("runs", []):
        out.append(f"run of {r['tets']} tets, pass every {r['interval']}: {r['steps_per_second']:.1f} steps/s")
    out += [str(line) for line in figures.get("output_tail", [])]
    after = figures.get("after_cracking_reported_not_checked")
    if after:
        out.append(
            f"after cracking (reported): max |dq|/h {after['max_dq_over_h_original_nodes']:.2g}, splits "
            f"{after['splits_cpu']}/{after['splits_device']}, converted {after['converted_cpu']}/"
            f"{after['converted_device']}, first event at step {after['first_event_cpu']}/{after['first_event_device']}"
            " (cpu/device)"
        )
    short = {k: v for k, v in figures.items() if isinstance(v, int | float | bool) and k not in ("exit_status",)}
    if short and not any(k in figures for k in ("rows", "passes", "runs", "output_tail")):
        out.insert(0, ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in short.items()))
    return out


def _target(row: dict[str, Any]) -> str:
    """ ", target met" or ", target missed" where a row was measured against one."""
    if "meets_target" not in row:
        return ""
    return ", target met" if row["meets_target"] else ", target missed"


# ----------------------------------------------------------------------------------------------------------------
# Command line


def positive_int(text: str) -> int:
    """An argparse type: an integer > 0."""
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0 (got {text})")
    return value


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python benchmarks/gpu_record.py",
        description="The GPU check script's helpers: settling cases, and its summary.json.",
    )
    sub = p.add_subparsers(dest="command", metavar="{settling-cases,record,summary}", required=True)
    s = sub.add_parser("settling-cases", help="write settling cases (cube numbers of spheres) for bench --data")
    s.add_argument("sizes", type=positive_int, nargs="+", help="sphere counts, each a cube number (1000000)")
    s.add_argument("--data", type=Path, required=True, help="folder to write init_N*.txt and box_N*.json to")
    s.add_argument("--workers", type=positive_int, default=os.cpu_count() or 1, help="formatting processes")
    r = sub.add_parser("record", help="add a step's result to summary.json")
    r.add_argument("--summary", type=Path, required=True, help="summary.json")
    r.add_argument("--name", required=True, help="the check's name")
    r.add_argument(
        "--kind",
        required=True,
        choices=("pytest", "compare", "command", "settling", "tets", "fracture", "conversion", "skipped"),
    )
    r.add_argument("--rc", type=int, default=0, help="the step's exit status")
    r.add_argument("--wall", type=float, default=0.0, help="the step's wall time [s]")
    r.add_argument("--log", type=Path, help="the step's log")
    r.add_argument("--json", type=Path, help="the step's JSON")
    r.add_argument("--note", default="", help="a note kept with the check")
    r.add_argument("--mode", default="", help="cpu or cuda (when summary.json is made)")
    r.add_argument("--device", dest="summary_device", default="", help="the device (when summary.json is made)")
    m = sub.add_parser("summary", help="print summary.json; exit 1 when a check failed")
    m.add_argument("file", type=Path)
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.command == "record":
        args.device = args.summary_device
        return record(args)
    if args.command == "summary":
        return print_summary(args.file)
    if args.command == "settling-cases":
        for n in args.sizes:
            t0 = time.perf_counter()
            write_settling_case(n, args.data, args.workers)
            print(f"settling case N = {n} written to {args.data} in {time.perf_counter() - t0:.1f} s", flush=True)
        return 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
