"""Per-frame time series of a run: the energy balance, counts, wall and load forces, the largest speed.

One row per output frame, written as ``<directory>/<name>_series.csv`` (``<name>`` the stem of the run's USD
stage) and, with the same columns, ``<directory>/<name>_series.h5`` (one dataset per column, with ``unit`` and
``description`` attributes, for h5py). Both are rewritten whole at every frame under a temporary name and renamed,
so a reader never sees half a file. A restart from frame M keeps the rows before M and continues the same file on
the same timeline, so a restarted run leaves the rows of the uninterrupted one.

Columns (units in :data:`UNITS` and the HDF5 attributes):

- ``frame`` [-], ``time`` [s];
- ``energy_<line>`` [J] for every field of :class:`warpdem.stages.energy.EnergyBalance` (taken from the dataclass, so a
  line added there appears here), ``energy_total`` [J] and ``energy_error`` [-] (:func:`balance_error` against
  the first frame of the timeline, relative to the largest energy in play so far: the number the summary prints);
- counts [-]: ``spheres``, ``contacts`` (touching sphere pairs), ``bonds_intact``, ``bonds_broken``, ``nodes``,
  ``tets`` (active), ``joints_intact``, ``joints_failed``;
- with fracture attached (``model.has_fracture``, from the first frame to the last, a rigid switch between them;
  :data:`FRACTURE_COLUMNS`): ``splits``, ``cohesive_intact``, ``cohesive_broken`` [-], ``crack_area`` and
  ``crack_area_opened`` [m²] (one face), ``cohesive_work_broken`` [J] (Γ A_f of the broken elements, what the
  dissipated energy ``energy_dissipated_cohesive`` must reach for them);
- ``wall<w>_fx``, ``_fy``, ``_fz`` [N]: force of the spheres on wall w (in the order the scene makes walls);
- ``load<i>_fx``, ``_fy``, ``_fz`` [N]: total force of pressure load ``[[loads]]`` entry i on the rock, -∫ p dA;
- ``max_speed`` [m/s]: the largest speed of any sphere or FEM node.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import pathlib
import re
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..model import Model, State
    from ..simulation import Simulation
    from ..stages.energy import EnergyBalance

COUNT_COLUMNS = {
    "spheres": "live spheres",
    "contacts": "touching sphere–sphere pairs",
    "bonds_intact": "intact sphere bonds",
    "bonds_broken": "sphere bonds broken since the start",
    "nodes": "live FEM nodes",
    "tets": "active tets",
    "joints_intact": "intact joint elements",
    "joints_failed": "joint elements failed since the start",
}
"""Integer columns and what they count."""

FRACTURE_COLUMNS = {
    "splits": ("-", "node splits since the start"),
    "cohesive_intact": ("-", "intact cohesive elements"),
    "cohesive_broken": ("-", "cohesive elements broken since the start"),
    "crack_area": ("m^2", "area of the crack surface made so far, one face (half of Σ A_f of every element born)"),
    "crack_area_opened": ("m^2", "area of the fully opened crack surface, one face (half of Σ A_f of the broken)"),
    "cohesive_work_broken": (
        "J",
        "Γ A_f summed over the broken cohesive elements (fracture energy of the opened area)",
    ),
}
"""Columns of a run with fracture on: unit and what each holds."""

INTEGER_COLUMNS = frozenset({"frame", *COUNT_COLUMNS, "splits", "cohesive_intact", "cohesive_broken"})
"""Columns that hold whole numbers (read back and stored as integers)."""


def fracture_values(model: Model, state: State) -> dict[str, int | float]:
    """The fracture counters now (reads back; call between steps), by :data:`FRACTURE_COLUMNS` name; empty when
    fracture is off. Alive elements are the live slots (``cohesive_count``) less those broken and not yet
    compacted; the crack areas are half of the A_f sums, which count both faces (LDEC eq. 9)."""
    if not model.has_fracture:
        return {}
    nc = int(state.cohesive_count.numpy()[0])
    return {
        "splits": int(state.node_splits_total.numpy()[0]),
        "cohesive_intact": int(np.count_nonzero(state.cohesive_broken.numpy()[:nc] == 0)),
        "cohesive_broken": int(state.cohesive_broken_total.numpy()[0]),
        "crack_area": 0.5 * float(state.crack_area_total.numpy()[0]),
        "crack_area_opened": 0.5 * float(state.cohesive_area_broken.numpy()[0]),
        "cohesive_work_broken": float(state.cohesive_work_broken.numpy()[0]),
    }


def energy_lines() -> list[str]:
    """The fields of :class:`~warpdem.stages.energy.EnergyBalance`, in declaration order."""
    from ..stages.energy import EnergyBalance

    return [f.name for f in dataclasses.fields(EnergyBalance)]


def energy_signs() -> dict[str, float]:
    """Sign of each energy line in the balance's ``total``: +1 for energy held or dissipated, -1 for work put in
    (read off ``EnergyBalance.total`` itself, so a new line is classified without a list here)."""
    from ..stages.energy import EnergyBalance

    names = energy_lines()
    return {n: EnergyBalance(**{m: float(m == n) for m in names}).total for n in names}


def unit(column: str) -> str:
    """Unit of a column: ``s``, ``J``, ``N``, ``m/s``, ``m^2`` or ``-``."""
    if column in FRACTURE_COLUMNS:
        return FRACTURE_COLUMNS[column][0]
    if column == "time":
        return "s"
    if column == "energy_error":
        return "-"
    if column.startswith("energy_"):
        return "J"
    if re.fullmatch(r"(wall|load)\d+_f[xyz]", column):
        return "N"
    if column == "max_speed":
        return "m/s"
    return "-"


def description(column: str) -> str:
    """One line on what a column holds."""
    if column == "frame":
        return "output frame number (the USD time code)"
    if column == "time":
        return "simulated time"
    if column == "energy_total":
        return "sum of the balance's lines (constant up to discretisation error)"
    if column == "energy_error":
        return "relative error of the energy balance since the first frame (as the summary)"
    if column.startswith("energy_"):
        return f"energy balance line {column.removeprefix('energy_')}"
    if column in COUNT_COLUMNS:
        return COUNT_COLUMNS[column]
    if column in FRACTURE_COLUMNS:
        return FRACTURE_COLUMNS[column][1]
    if match := re.fullmatch(r"(wall|load)(\d+)_f([xyz])", column):
        kind, index, axis = match.groups()
        what = "force of the spheres on wall" if kind == "wall" else "pressure force of [[loads]] entry"
        return f"{what} {index}, {axis} component"
    if column == "max_speed":
        return "largest speed of a sphere or FEM node"
    return column


def _load_index(name: str, k: int) -> int:
    """The ``[[loads]]`` index of a pressure load named ``loads[i]`` by the scene, else its pressure-load index."""
    match = re.fullmatch(r"loads\[(\d+)\]", name)
    return int(match.group(1)) if match else k


def frame_values(
    sim: Simulation, frame: int, energy: EnergyBalance, start: EnergyBalance, in_play: float
) -> dict[str, float]:
    """One row of the series: column → value (reads back; call between steps).

    Args:
        sim: the simulation. frame: output frame number. energy: its energy balance now (``sim.energy()``).
        start: the balance at the first frame of the timeline (the error's reference). in_play: the largest
            :attr:`~warpdem.stages.energy.EnergyBalance.in_play` of the timeline so far [J] (the error's scale).
    """
    from ..stages.contact import wall_forces
    from ..stages.energy import balance_error
    from ..stages.loads import load_forces

    m, s = sim.model, sim.state
    row: dict[str, float] = {"frame": frame, "time": sim.time}
    row |= {f"energy_{name}": getattr(energy, name) for name in energy_lines()}
    row["energy_total"] = energy.total
    row["energy_error"] = balance_error(start, energy, in_play)
    n, nn = sim.particle_count, sim.node_count
    nt = int(s.tet_count.numpy()[0])
    nj = int(s.joint_count.numpy()[0]) if m.joint_capacity else 0
    row |= {
        "spheres": n,
        "contacts": sim.contact_count() if sim.has_spheres else 0,
        "bonds_intact": sim.bond_count,
        "bonds_broken": int(s.bonds_broken_total.numpy()[0]),
        "nodes": nn,
        "tets": int(np.count_nonzero(s.tet_active.numpy()[:nt])),
        "joints_intact": int(np.count_nonzero(s.joint_broken.numpy()[:nj] == 0)),
        "joints_failed": int(s.joints_broken_total.numpy()[0]),
    }
    row |= fracture_values(m, s)
    for w, force in enumerate(wall_forces(m, s)):
        row |= {f"wall{w}_f{axis}": float(f) for axis, f in zip("xyz", force, strict=True)}
    names, forces = load_forces(m, s)
    for k, (name, force) in enumerate(zip(names, forces, strict=True)):
        i = _load_index(name, k)
        row |= {f"load{i}_f{axis}": float(f) for axis, f in zip("xyz", force, strict=True)}
    speeds = [np.linalg.norm(s.particle_qd.numpy()[:n].astype(np.float64), axis=1)]
    speeds.append(np.linalg.norm(s.node_qd.numpy()[:nn].astype(np.float64), axis=1))
    row["max_speed"] = float(np.concatenate(speeds).max(initial=0.0))
    return row


def _text(value: float) -> str:
    """A CSV cell that reads back to the same number (integers as integers, floats by repr)."""
    return str(value) if isinstance(value, int | np.integer) else repr(float(value))


def read_series(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A series CSV as column → array (float64; the count columns hold whole numbers)."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return {}
    header, body = rows[0], rows[1:]
    data = np.array(body, dtype=np.float64).reshape(len(body), len(header))
    return {name: data[:, k] for k, name in enumerate(header)}


class TimeSeries:
    """The per-frame series of one run (module docstring), in CSV and HDF5.

    Args:
        directory: output directory (created). name: stem of the files. first_frame: the frame this run starts at;
            above 0 (a restart), the rows of an existing series before it are kept, and the energy of its frame 0
            stays the error's reference (without that file, the restart's first frame is the reference, as in the
            restart's own summary).
    """

    def __init__(self, directory: str | os.PathLike, name: str, first_frame: int = 0) -> None:
        self.directory = pathlib.Path(directory)
        self.csv_path = self.directory / f"{name}_series.csv"
        self.h5_path = self.directory / f"{name}_series.h5"
        self.columns: list[str] = []
        self.rows: list[list[float]] = []
        self.energy_start: EnergyBalance | None = None
        self.in_play = 0.0
        """The largest energy in play over the rows so far [J] (the error's scale)."""
        self._recorded = False
        """Whether this run recorded a row yet (rows before that were read from an earlier run's file)."""
        if first_frame > 0 and self.csv_path.is_file():
            old = read_series(self.csv_path)
            if old and "frame" in old:
                keep = old["frame"] < first_frame
                self.columns = list(old)
                self.rows = [
                    [
                        int(old[c][r]) if c in INTEGER_COLUMNS and np.isfinite(old[c][r]) else float(old[c][r])
                        for c in self.columns
                    ]
                    for r in np.flatnonzero(keep)
                ]
                if self.rows and old["frame"][keep][0] == 0:
                    from ..stages.energy import EnergyBalance

                    kept = [
                        EnergyBalance(
                            **{n: float(old[f"energy_{n}"][r]) for n in energy_lines() if f"energy_{n}" in old}
                        )
                        for r in np.flatnonzero(keep)
                    ]
                    self.energy_start = kept[0]
                    self.in_play = max(e.in_play for e in kept)

    def record(self, sim: Simulation, frame: int, energy: EnergyBalance | None = None) -> dict[str, float]:
        """Appends the row of this frame (replacing a row of the same frame) and rewrites both files.

        Args:
            sim: the simulation. frame: output frame number. energy: its balance now, when the caller has read it
                back already (None: ``sim.energy()``).
        """
        energy = sim.energy() if energy is None else energy
        if self.energy_start is None:
            self.energy_start = energy
        self.in_play = max(self.in_play, self.energy_start.in_play, energy.in_play)
        row = frame_values(sim, frame, energy, self.energy_start, self.in_play)
        if self.columns and list(row) != self.columns and not self._recorded:
            self.columns, self.rows = [], []  # a different scene wrote the rows a restart found: they cannot share
        self._recorded = True
        # This run's own rows are never dropped: were a column in some of its frames only, the others hold NaN.
        old = [dict(zip(self.columns, r, strict=True)) for r in self.rows if r[0] != frame]
        self.columns = list(row) + [c for c in self.columns if c not in row]
        self.rows = [[r.get(c, math.nan) for c in self.columns] for r in [*old, row]]
        self._write_csv()
        self._write_hdf5()
        return row

    def _write_csv(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = self.csv_path.with_name(f"{self.csv_path.name}.partial")
        lines = [",".join(self.columns)] + [",".join(_text(v) for v in r) for r in self.rows]
        tmp.write_text("\n".join(lines) + "\n")
        os.replace(tmp, self.csv_path)

    def _write_hdf5(self) -> None:
        import h5py

        tmp = self.h5_path.with_name(f"{self.h5_path.stem}.partial.h5")
        try:
            with h5py.File(tmp, "w") as f:
                f.attrs["columns"] = self.columns
                table = np.array(self.rows, dtype=np.float64).reshape(len(self.rows), len(self.columns))
                for k, name in enumerate(self.columns):
                    integer = name in INTEGER_COLUMNS and bool(np.all(np.isfinite(table[:, k])))  # NaN: not recorded
                    data = f.create_dataset(name, data=table[:, k].astype(np.int64 if integer else np.float64))
                    data.attrs["unit"] = unit(name)
                    data.attrs["description"] = description(name)
            os.replace(tmp, self.h5_path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
