"""A load history from Python: the blast pulse of ``scenes/wave_column.toml`` (a granite column, 20 m tall, loaded on
its top face) vented at a time chosen here: from then on the cavity's gas is gone and the pressure is zero. Between
two frames the script sets the load's amplitude, ``sim.set_load_scale(0, s)``, from a function of time; any history
that is piecewise constant over frames can be written the same way.

    python examples/custom_load.py                     # vented at 0.6 ms, 4 ms of the wave (a few seconds)
    python examples/custom_load.py --vent 3e-4 --end-time 2e-3 --json load.json

Printed per frame: the amplitude the next frame runs at, the load's force on the rock (-∫ p dA, the time series'
``load0_fz``), the work it has done and the relative error of the energy books, which stay closed: the load kernels
book the work of the forces they apply, whatever amplitude they apply them at. ``--json`` writes the rows.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import warpdem as wd

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "wave_column.toml"


def amplitude(time: float, vent: float) -> float:
    """The load's amplitude at ``time`` [s], relative to the scene's blast: whole until the vent, then none."""
    return 1.0 if time < vent else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vent", type=float, default=6e-4, help="time the cavity vents [s]")
    parser.add_argument("--end-time", type=float, default=4e-3, help="simulated time [s]")
    parser.add_argument("--out", type=Path, default=Path("custom_load"), help="output folder")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    parser.add_argument("--device", default="cpu", help="Warp device")
    args = parser.parse_args()

    sim = wd.build(SCENE, device=args.device, end_time=args.end_time, out_dir=args.out)
    print(f"{sim.scene.name}: blast on the top face, vented at {args.vent * 1e3:g} ms")
    print("frame  t [ms]  amplitude  load force z [MN]  load work [J]  books")
    rows = []
    for frame in sim.frames():
        scale = amplitude(frame.time, args.vent)
        sim.set_load_scale(0, scale)  # from the next step on: the steps to the next frame run at it
        row = {
            "frame": frame.index,
            "time": frame.time,
            "amplitude": scale,
            "load_fz": frame.series["load0_fz"],
            "load_work": frame.energy.load_work,
            "energy_error": frame.energy.error,
        }
        rows.append(row)
        print(
            f"{frame.index:5d}  {frame.time * 1e3:6.2f}  {scale:9.2f}  {row['load_fz'] / 1e6:17.4f}  "
            f"{row['load_work']:13.5g}  {frame.energy.error:+.1e}"
        )
    print(sim.summary.format().splitlines()[0])
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
