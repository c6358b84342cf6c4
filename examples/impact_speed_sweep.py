"""A parameter sweep from Python: the steel ball of ``scenes/bonded_slab_impact.toml`` dropped onto the bonded slab at
several speeds, one run per speed, and what each broke: bonds, fragments, the pieces thrown off and how fast.

    python examples/impact_speed_sweep.py                        # 5, 10, 20, 40 m/s, 20 ms each (about a minute)
    python examples/impact_speed_sweep.py --speeds 10 30 --end-time 0.01 --json sweep.json

Each run writes its own outputs (``sweep/<speed>/``: the USD stage, the time series, the fragment record). The scene
is loaded once and edited in Python before each build: ``scene.particles[1]`` is the ball, and ``wd.build`` validates
the edit as it would a file. ``--json`` writes every run's summary (the command line's ``--summary-json``), keyed by
speed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import warpdem as wd
from warpdem.runner import summary_json

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "bonded_slab_impact.toml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--speeds", type=float, nargs="+", default=[5.0, 10.0, 20.0, 40.0], help="impact speeds [m/s]")
    parser.add_argument("--end-time", type=float, default=0.02, help="simulated time of each run [s]")
    parser.add_argument("--out", type=Path, default=Path("sweep"), help="folder of the runs' outputs")
    parser.add_argument("--json", type=Path, help="also write every run's summary here, by speed")
    parser.add_argument("--device", default="cpu", help="Warp device")
    args = parser.parse_args()

    scene = wd.load_scene(SCENE)
    ball = scene.particles[1]
    assert ball.part == "ball", "the sweep edits the ball: particles[1] of the scene"
    print(f"{scene.name}: a {2 * ball.radius * 1000:.0f} mm steel ball on a bonded slab, {args.end_time * 1e3:g} ms")
    print("speed [m/s]  bonds broken  fragments  largest [%]  pieces off  fastest piece [m/s]  books")
    results = {}
    for speed in args.speeds:
        ball.velocity = (0.0, 0.0, -speed)  # straight down
        sim = wd.build(scene, device=args.device, end_time=args.end_time, out_dir=args.out / f"{speed:g}")
        summary = sim.run()
        share = summary.fragment_largest / summary.fragment_mass if summary.fragment_mass > 0 else 0.0
        print(
            f"{speed:11.4g}  {summary.bonds_broken:12d}  {summary.fragment_count:9d}  {100 * share:11.1f}  "
            f"{summary.ejecta_count:10d}  {summary.ejecta_speed_max:19.3g}  {summary.energy_error:+.1e}"
        )
        results[f"{speed:g}"] = json.loads(summary_json(summary))
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
