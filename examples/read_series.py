"""Reading a run's time series and plotting it with matplotlib: the energy books of every frame, line by line, and
their relative error.

    python examples/read_series.py                                  # runs wave_column for 4 ms first, then plots
    python examples/read_series.py out/boulder_impact_series.h5     # a run's series (.h5 or .csv), as written
    python examples/read_series.py --end-time 1e-3 --png books.png

A run writes its series twice, with the same columns (warpdem.io.timeseries): ``<stem>_series.csv`` (one row per
frame) and ``<stem>_series.h5`` (one dataset per column, with ``unit`` and ``description`` attributes). This script
reads either: the CSV with ``warpdem.io.timeseries.read_series``, the HDF5 with h5py (and its units for the labels).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def read(path: Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The columns of a series file and their units (from the HDF5 attributes; the CSV holds none)."""
    if path.suffix == ".h5":
        import h5py

        with h5py.File(path, "r") as f:
            columns = list(f.attrs["columns"])
            return {c: np.asarray(f[c][()], dtype=np.float64) for c in columns}, {
                c: f[c].attrs["unit"] for c in columns
            }
    from warpdem.io.timeseries import read_series, unit

    data = read_series(path)
    return data, {c: unit(c) for c in data}


def plot(data: dict[str, np.ndarray], units: dict[str, str], title: str, png: Path) -> None:
    """Every energy line that is not zero throughout, the books' total, and their relative error below."""
    import matplotlib

    matplotlib.use("Agg")  # files only: no display needed
    import matplotlib.pyplot as plt

    t = data["time"] * 1e3
    lines = [c for c in data if c.startswith("energy_") and c not in ("energy_total", "energy_error")]
    lines = [c for c in lines if np.any(data[c] != 0.0)]
    fig, (top, bottom) = plt.subplots(2, 1, sharex=True, figsize=(8, 6), height_ratios=(3, 1))
    for c in lines:
        top.plot(t, data[c], label=c.removeprefix("energy_").replace("_", " "))
    top.plot(t, data["energy_total"], "k--", label="total (books)")
    top.set_ylabel(f"energy [{units.get('energy_total', 'J')}]")
    top.legend(fontsize=7, ncol=2)
    top.set_title(title)
    bottom.plot(t, data["energy_error"], "k")
    bottom.set_ylabel("relative error [-]")
    bottom.set_xlabel("time [ms]")
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("series", type=Path, nargs="?", help="a run's <stem>_series.h5 or .csv (default: run one)")
    parser.add_argument(
        "--end-time", type=float, default=4e-3, help="simulated time of the run made without SERIES [s]"
    )
    parser.add_argument("--out", type=Path, default=Path("series_run"), help="output folder of that run")
    parser.add_argument("--png", type=Path, default=Path("series.png"), help="the picture to write")
    args = parser.parse_args()

    series = args.series
    if series is None:
        import warpdem as wd

        scene = Path(__file__).resolve().parent.parent / "scenes" / "wave_column.toml"
        summary = wd.build(scene, end_time=args.end_time, out_dir=args.out).run()
        series = summary.series_path.with_suffix(".h5")  # written beside the CSV, same columns
    data, units = read(series)
    print(
        f"{series}: {len(data['frame'])} frames, {len(data)} columns, t = {data['time'][0]:g} .. {data['time'][-1]:g} s"
    )
    print(f"largest |error| of the books {np.max(np.abs(data['energy_error'])):.2e}")
    plot(data, units, series.name, args.png)
    print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
