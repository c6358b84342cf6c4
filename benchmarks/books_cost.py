"""What the energy books cost the step (issue 24, "Benchmarks that measure what users run"): the settling case of
``python -m warpdem bench`` with the books on and off, side by side in one process.

    python benchmarks/books_cost.py [--sizes 100000] [--steps 2000] [--window 100] [--json FILE]

This VM's speed wanders by ±20 % over minutes, more than the books cost, so two separate ``bench --books on`` and
``--books off`` runs cannot resolve the difference. Here both runs step in one process, window by window in turn
(``--window`` steps each, graphs captured, as the bench steps), so each pair of windows meets the machine in the
same state and covers the same stretch of the case (which goes first alternates); each run's time is the sum of its
windows, and the ratio is taken window by window (median and quartiles: a window the machine slowed shows as an
outlier, not as a bias).

Checked on every window: the books leave the physics alone, so both runs' positions and velocities are bit-identical
(the books only read the forces); a difference stops the script.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def books_cost(n: int, steps: int, window: int, device: str = "cpu") -> dict:
    """Both runs of the N-sphere settling case over ``steps`` steps in windows of ``window``; the window times [s]
    of each and the ratio books on / books off per window."""
    import warp as wp

    from warpdem.bench.settling import settling_case

    runs = {books: settling_case(n, device, track_energy=books) for books in (True, False)}
    for sim in runs.values():
        sim.advance(2)  # kernels compiled, graphs captured, outside the clock
    times: dict[bool, list[float]] = {True: [], False: []}
    for start in range(2, steps, window):
        count = min(window, steps - start)
        # Alternate which run goes first, so neither always meets the machine after the other.
        order = (True, False) if (start // window) % 2 == 0 else (False, True)
        for books in order:
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            runs[books].advance(count)
            wp.synchronize_device(device)
            times[books].append(time.perf_counter() - t0)
        on, off = (runs[b].state for b in (True, False))
        for name in ("particle_q", "particle_qd", "particle_omega"):
            if not np.array_equal(getattr(on, name).numpy(), getattr(off, name).numpy()):
                raise RuntimeError(f"the books changed the physics: {name} differs after step {start + count}")
    ratio = np.array(times[True]) / np.array(times[False])
    return {
        "spheres": n,
        "steps": steps,
        "window": window,
        "books_on_s": float(sum(times[True])),
        "books_off_s": float(sum(times[False])),
        "ratio_median": float(np.median(ratio)),
        "ratio_q1": float(np.percentile(ratio, 25)),
        "ratio_q3": float(np.percentile(ratio, 75)),
        "contacts_per_sphere": 2.0 * runs[True].contact_count() / n,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[100000])
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--window", type=int, default=100)
    p.add_argument("--device", default="cpu")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    rows = [books_cost(n, args.steps, args.window, args.device) for n in args.sizes]
    print("| spheres | steps | books on [s] | books off [s] | on / off per window: median (quartiles) |")
    print("| ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['spheres']} | {r['steps']} | {r['books_on_s']:.2f} | {r['books_off_s']:.2f} | "
            f"{r['ratio_median']:.3f} ({r['ratio_q1']:.3f}–{r['ratio_q3']:.3f}) |"
        )
    if args.json is not None:
        import subprocess

        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
        args.json.write_text(json.dumps({"commit": commit.stdout.strip(), "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
