"""The DEM/FEM interface on a wave (issue 28 item 2): ``python benchmarks/overlap_band.py [--widths 1 2 3 4]
[--penalties 0.25 1 4] [--device cpu] [--out benchmarks/results/overlap_band.json]``.

A bar half FEM, half DEM (start_as_spheres), a bar pulse from the FEM side crossing the interface: the reflection
coefficient of the tie and of the blended overlap band at each width and penalty, beside the impedance mismatch's
(Z_D − Z_F)/(Z_D + Z_F). The case and the measures are described in warpdem.bench.overlap_band; the table is in
docs/physics.md ("The overlap zone").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import warp as wp

from warpdem.bench.common import write_json
from warpdem.bench.overlap_band import compare


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", type=int, nargs="+", default=[1, 2, 3, 4], help="band widths [tet layers]")
    parser.add_argument("--penalties", type=float, nargs="+", default=[0.25, 1.0, 4.0], help="penalty factors [-]")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "overlap_band.json")
    args = parser.parse_args()
    wp.config.quiet = True
    result = compare(args.device, args.widths, args.penalties)
    print(
        f"c_F = {result['c_fem_m_s']:.1f} m/s, c_D = {result['c_dem_m_s']:.1f} m/s, "
        f"impedance mismatch R = {result['r_impedance']:+.4f}"
    )
    print(f"{'coupling':8} {'width':>5} {'penalty':>7} {'R_energy':>8} {'R_gauge':>8} {'transm.':>7} {'books':>8}")
    for r in result["rows"]:
        print(
            f"{r['coupling']:8} {r['band_width']:5d} {r['penalty']:7.2f} {r['r_energy']:8.4f} {r['r_gauge']:+8.4f} "
            f"{r['transmitted']:7.4f} {r['books']:8.1e}"
        )
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
