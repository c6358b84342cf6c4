"""``python -m warpdem plot RUN_DIR``: the plots a DEM user makes first, from a run's time series (matplotlib, Agg).

For every ``<name>_series.csv`` in the folder (warpdem.io.timeseries) it writes:

- ``<name>_energy.png``: the energy balance over time (:func:`energy_stack`). The lines that hold or dissipate
  energy are stacked: where a line is positive it is stacked upward from 0, where it is negative (a release booked
  below zero, a step change of the shadow term) downward from 0, so the stack's net, the top of the upward stack
  less the depth of the downward one, is the sum of the lines. The dashed line is what the balance says that net
  must be: the energy at the first frame plus the work put in by walls and loads minus the change of gravity
  potential (counted from the first frame, so its datum does not matter). The net is drawn as a broad grey line
  under the dashes: the gap between them is the balance's error, also drawn on a second axis (relative, as the
  summary prints it).
- ``<name>_counts.png``: spheres, contacts, bonds intact and broken, nodes, tets, joints over time, and the
  largest speed.
- ``<name>_forces.png``: the force on each wall and on each loaded face set over time (components and magnitude);
  only for runs that have walls or pressure loads.
- ``<name>_fracture.png``: the crack area made and opened (one face) with the node splits over time, and the
  energy the cohesive elements dissipated against Γ × the area of the broken ones; only for runs with fracture on.
- ``<name>_fragments.png``: the cumulative mass distribution of the fragments at the last frame (the share of the
  fragmented mass in pieces of at most a given mass, a sieve curve) and the largest fragment's mass over time; only
  where the run wrote ``<name>_fragments.h5`` (warpdem.stages.fragments: scenes that can break apart).
"""

from __future__ import annotations

import os
import pathlib
from dataclasses import dataclass

import numpy as np

from .timeseries import COUNT_COLUMNS, energy_signs, read_series


class PlotError(Exception):
    """A run folder that cannot be plotted (one readable line)."""


def _figure(size: tuple[int, int], rows: int = 1, sharex: bool = True):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(rows, 1, figsize=(size[0] / 100.0, size[1] / 100.0), dpi=100, sharex=sharex, squeeze=False)
    # Fixed margins (room for the labels of both y axes) instead of tight_layout, which draws every figure twice.
    fig.subplots_adjust(left=0.11, right=0.87, bottom=0.1, top=0.93, hspace=0.3)
    return fig, list(axes[:, 0])


def _save(fig, path: pathlib.Path) -> pathlib.Path:
    """Write a figure under a temporary name, then rename."""
    import matplotlib.pyplot as plt

    tmp = path.with_name(f"{path.stem}.partial.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
    return path


@dataclass
class EnergyStack:
    """The energy plot's stack (module docstring), every array shape (T,) [J].

    Attributes:
        up: the positive part of each stacked line (0 where it is negative), stacked upward from 0, in order.
        down: the negative part of each line that goes below 0 somewhere (0 where it is positive), stacked
            downward from 0, in order.
        target: what the balance says the net must be: initial energy + work put in − Δ gravity potential.
    """

    up: dict[str, np.ndarray]
    down: dict[str, np.ndarray]
    target: np.ndarray

    @property
    def net(self) -> np.ndarray:
        """The stack's net [J]: the top of the upward stack less the depth of the downward one."""
        return sum(self.up.values(), np.zeros_like(self.target)) + sum(self.down.values(), np.zeros_like(self.target))


def energy_stack(data: dict[str, np.ndarray]) -> EnergyStack:
    """Split a series' energy lines into the stack and its target (module docstring).

    Balance: Σ held(t) + potential(t) − Σ work(t) = total(t), so the net of the stack, Σ held(t), is
    total(0) − potential(t) + Σ work(t) (the target) plus total(t) − total(0), the books' error [J]. Lines that
    are 0 throughout are left out.

    Args:
        data: a time series (warpdem.io.timeseries.read_series): ``energy_<line>`` and ``energy_total`` columns.
    """
    target = np.full(len(data["energy_total"]), float(data["energy_total"][0]))
    held = {}
    for line, sign in energy_signs().items():
        values = data.get(f"energy_{line}")
        if values is None:
            continue
        if line == "gravity_potential":
            target -= values
        elif sign > 0:
            held[line] = values
        else:
            target += values
    up = {k: np.maximum(v, 0.0) for k, v in held.items() if np.any(v > 0.0)}
    down = {k: np.minimum(v, 0.0) for k, v in held.items() if np.any(v < 0.0)}
    return EnergyStack(up, down, target)


def draw_energy(ax, data: dict[str, np.ndarray]) -> EnergyStack:
    """Draw the stacked energy balance into ``ax`` (module docstring): the upward stack, the downward stack
    (hatched, in the colour of the same line), the net and the target. Returns the stack drawn."""
    from matplotlib import patheffects

    t = data["time"]
    stack = energy_stack(data)
    lines = list(dict.fromkeys([*stack.up, *stack.down]))
    colors = dict(zip(lines, _line_colors(len(lines)), strict=True))
    for parts, hatch in ((stack.up, None), (stack.down, "////")):
        base = np.zeros_like(t)
        for line, values in parts.items():
            label = line.replace("_", " ") + (" (below 0)" if hatch else "")
            ax.fill_between(
                t,
                base,
                base + values,
                facecolor=colors[line],
                alpha=0.85,
                hatch=hatch,
                edgecolor="white",
                linewidth=0.0,
                label=label,
            )
            base = base + values
    if stack.down:
        ax.axhline(0.0, color="0.2", lw=0.6)
    # The net as a white band edged in grey, the target's dashes on top: where they agree the dashes run inside it.
    outline = [patheffects.Stroke(linewidth=4.5, foreground="0.35"), patheffects.Normal()]
    ax.plot(t, stack.net, color="white", lw=3.0, path_effects=outline, label="net of the stack (up − down)")
    ax.plot(t, stack.target, "k--", lw=1.2, label="initial + work in − Δ potential")
    return stack


def _line_colors(n: int) -> list:
    """n distinct colours, the first ten as matplotlib's default cycle (tab10), then tab20's lighter ones."""
    import matplotlib

    tab10, tab20 = matplotlib.colormaps["tab10"], matplotlib.colormaps["tab20"]
    return [tab10(k) if k < 10 else tab20((2 * (k - 10) + 1) % 20) for k in range(n)]


def plot_energy(data: dict[str, np.ndarray], name: str, path: pathlib.Path, size: tuple[int, int]) -> pathlib.Path:
    """The stacked energy balance with its relative error on a second axis (module docstring)."""
    t = data["time"]
    fig, (ax,) = _figure(size)
    draw_energy(ax, data)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("energy [J]")
    ax.set_title(f"{name}: energy balance")
    err_ax = ax.twinx()
    err_ax.plot(t, data["energy_error"], color="crimson", lw=1.0, label="balance error")
    err_ax.set_ylabel("relative error [-]", color="crimson")
    err_ax.tick_params(axis="y", colors="crimson")
    handles, labels = ax.get_legend_handles_labels()
    h2, l2 = err_ax.get_legend_handles_labels()
    ax.legend(handles + h2, labels + l2, fontsize=7, loc="upper left", framealpha=0.8)
    return _save(fig, path)


def plot_counts(data: dict[str, np.ndarray], name: str, path: pathlib.Path, size: tuple[int, int]) -> pathlib.Path:
    """Counts over time (those that are not zero throughout) and the largest speed."""
    t = data["time"]
    fig, (ax, speed_ax) = _figure(size, rows=2)
    for column in COUNT_COLUMNS:
        values = data.get(column)
        if values is not None and np.any(values != 0):
            ax.plot(t, values, label=column.replace("_", " "))
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_ylabel("count [-]")
    ax.set_title(f"{name}: counts")
    ax.legend(fontsize=7, loc="best", framealpha=0.8)
    speed_ax.plot(t, data["max_speed"], color="k")
    speed_ax.set_ylabel("max speed [m/s]")
    speed_ax.set_xlabel("time [s]")
    return _save(fig, path)


def force_groups(data: dict[str, np.ndarray]) -> list[str]:
    """The walls and loads of a series (``wall0``, ``load2``, ...), in column order."""
    return list(dict.fromkeys(c[:-3] for c in data if c.endswith("_fx")))


def plot_forces(
    data: dict[str, np.ndarray], name: str, path: pathlib.Path, size: tuple[int, int]
) -> pathlib.Path | None:
    """Force components and magnitude of each wall and load over time; None when the run has neither."""
    groups = force_groups(data)
    if not groups:
        return None
    t = data["time"]
    kinds = [k for k in ("wall", "load") if any(g.startswith(k) for g in groups)]
    fig, axes = _figure(size, rows=len(kinds))
    for ax, kind in zip(axes, kinds, strict=True):
        for g in (g for g in groups if g.startswith(kind)):
            f = np.stack([data[f"{g}_f{a}"] for a in "xyz"], axis=1)
            (line,) = ax.plot(t, np.linalg.norm(f, axis=1), lw=1.4, label=f"{g} |F|")
            for a, style in zip("xyz", (":", "-.", "--"), strict=True):
                if np.any(data[f"{g}_f{a}"] != 0.0):
                    ax.plot(t, data[f"{g}_f{a}"], style, lw=0.8, color=line.get_color(), label=f"{g} F{a}")
        what = "force of the spheres on each wall" if kind == "wall" else "pressure force of each load"
        ax.set_title(f"{name}: {what}", fontsize=9)
        ax.set_ylabel("force [N]")
        ax.legend(fontsize=7, loc="best", framealpha=0.8, ncol=2)
    axes[-1].set_xlabel("time [s]")
    return _save(fig, path)


def plot_fracture(
    data: dict[str, np.ndarray], name: str, path: pathlib.Path, size: tuple[int, int]
) -> pathlib.Path | None:
    """Crack area and splits over time, and the cohesive energy books (module docstring); None without fracture."""
    if "crack_area" not in data:
        return None
    t = data["time"]
    fig, (ax, energy_ax) = _figure(size, rows=2)
    ax.plot(t, data["crack_area"], color="k", label="crack area made")
    ax.plot(t, data["crack_area_opened"], "k--", label="opened (cohesive elements broken)")
    ax.set_ylabel("area, one face [m²]")
    ax.set_title(f"{name}: fracture")
    splits_ax = ax.twinx()
    splits_ax.plot(t, data["splits"], color="crimson", lw=1.0, label="node splits")
    splits_ax.set_ylabel("node splits [-]", color="crimson")
    splits_ax.tick_params(axis="y", colors="crimson")
    handles, labels = ax.get_legend_handles_labels()
    h2, l2 = splits_ax.get_legend_handles_labels()
    ax.legend(handles + h2, labels + l2, fontsize=7, loc="upper left", framealpha=0.8)
    if "energy_dissipated_cohesive" in data:
        energy_ax.plot(t, data["energy_dissipated_cohesive"], color="k", label="dissipated by cohesive elements")
    energy_ax.plot(t, data["cohesive_work_broken"], "k--", label="Γ × area of the broken elements")
    energy_ax.set_ylabel("energy [J]")
    energy_ax.set_xlabel("time [s]")
    energy_ax.legend(fontsize=7, loc="upper left", framealpha=0.8)
    return _save(fig, path)


def plot_fragments(fragments_path: pathlib.Path, name: str, path: pathlib.Path, size: tuple[int, int]) -> pathlib.Path:
    """The cumulative mass distribution at the last frame and the largest fragment over time (module docstring).

    Raises:
        PlotError: the fragment file is unreadable or holds no frame.
    """
    from ..stages.fragments import read_fragments

    try:
        series = read_fragments(fragments_path)
    except (OSError, KeyError, ValueError) as exc:
        raise PlotError(f"{fragments_path}: unreadable fragment file ({exc})") from None
    if len(series.frame) == 0:
        raise PlotError(f"{fragments_path}: holds no frame")
    fig, (dist_ax, time_ax) = _figure(size, rows=2, sharex=False)  # mass on one axis, time on the other
    fig.subplots_adjust(hspace=0.45)
    masses = np.sort(series.masses[-1])
    if len(masses):
        # Share of the total in fragments of mass ≤ m: the sum of the masses up to m over the total (a sieve curve).
        passing = np.cumsum(masses) / masses.sum()
        dist_ax.step(masses, passing, where="post", color="k")
        dist_ax.set_xscale("log")
    dist_ax.set_xlabel("fragment mass m [kg]")
    dist_ax.set_ylabel("mass share in fragments ≤ m [-]")
    dist_ax.set_title(
        f"{name}: {len(masses)} fragments at t = {series.time[-1]:.4g} s (frame {series.frame[-1]})", fontsize=9
    )
    time_ax.plot(series.time, series.largest, color="k", label="largest fragment")
    time_ax.set_xlabel("time [s]")
    time_ax.set_ylabel("mass [kg]")
    count_ax = time_ax.twinx()
    count_ax.plot(series.time, series.count, color="crimson", lw=1.0, label="fragments")
    count_ax.set_ylabel("fragments [-]", color="crimson")
    count_ax.tick_params(axis="y", colors="crimson")
    handles, labels = time_ax.get_legend_handles_labels()
    h2, l2 = count_ax.get_legend_handles_labels()
    time_ax.legend(handles + h2, labels + l2, fontsize=7, loc="best", framealpha=0.8)
    return _save(fig, path)


def plot_run(
    run_dir: str | os.PathLike, out_dir: str | os.PathLike | None = None, size: tuple[int, int] = (800, 600)
) -> list[pathlib.Path]:
    """Plot every time series in a run folder (module docstring). Returns the PNG files written.

    Raises:
        PlotError: the folder does not exist, holds no series, or a series is unreadable.
    """
    run_dir = pathlib.Path(run_dir)
    if not run_dir.is_dir():
        raise PlotError(f"{run_dir}: no such folder")
    files = sorted(run_dir.glob("*_series.csv"))
    if not files:
        raise PlotError(f"{run_dir}: no *_series.csv here (the time series a run writes next to its USD stage)")
    out = pathlib.Path(out_dir) if out_dir is not None else run_dir
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for csv_path in files:
        name = csv_path.name.removesuffix("_series.csv")
        try:
            data = read_series(csv_path)
        except (OSError, ValueError) as exc:
            raise PlotError(f"{csv_path}: unreadable time series ({exc})") from None
        missing = [c for c in ("time", "energy_total", "energy_error", "max_speed") if c not in data]
        if missing:
            raise PlotError(f"{csv_path}: not a warpdem time series (no column {', '.join(missing)})")
        written.append(plot_energy(data, name, out / f"{name}_energy.png", size))
        written.append(plot_counts(data, name, out / f"{name}_counts.png", size))
        forces = plot_forces(data, name, out / f"{name}_forces.png", size)
        if forces is not None:
            written.append(forces)
        fracture = plot_fracture(data, name, out / f"{name}_fracture.png", size)
        if fracture is not None:
            written.append(fracture)
        fragments_path = run_dir / f"{name}_fragments.h5"
        if fragments_path.is_file():
            written.append(plot_fragments(fragments_path, name, out / f"{name}_fragments.png", size))
    return written
