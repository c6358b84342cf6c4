"""Reading and steering a run between frames (the Python API's side of :class:`warpdem.runner.Run`): the live
items' positions and velocities, any Model or State array by name, and the pressure loads' amplitudes.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from ..stages.loads import scale_pressure_loads


class UnknownArrayError(KeyError):
    """:meth:`Run.array` was asked for an array the model and state do not have; the message lists those they do."""

    def __str__(self) -> str:
        return str(self.args[0])


class RunAccess:
    """The readers and steering of :class:`warpdem.runner.Run` (a mixin: ``self.sim`` is the run's Simulation)."""

    # ------------------------------------------------------------------------------------------------------------
    # Reading and steering the run (warpdem.api)

    @property
    def time(self) -> float:
        """Simulated time now [s]."""
        return self.sim.time

    @property
    def step(self) -> int:
        """Time steps taken since the start of the run's timeline."""
        return self.sim.step_count

    @property
    def model(self) -> Any:
        """The model now (warpdem.model.Model; a pass that grows a capacity replaces it)."""
        return self.sim.model

    @property
    def state(self) -> Any:
        """The state now (warpdem.model.State; a pass that grows a capacity replaces it)."""
        return self.sim.state

    @property
    def usd_path(self) -> Path:
        """The USD stage this run writes (published at :meth:`finish` or :meth:`close`)."""
        return self._usd_path

    @property
    def series_path(self) -> Path:
        """The time series CSV this run writes (rewritten at every frame; the HDF5 copy beside it)."""
        return self._series.csv_path

    def positions(self) -> np.ndarray:
        """Sphere centres now [m], shape (N,) live spheres × 3, float64: a copy, safe to keep."""
        return self.sim.state.particle_q.numpy()[: self.sim.particle_count].copy()

    def velocities(self) -> np.ndarray:
        """Sphere velocities now [m/s], shape (N, 3), float32: a copy."""
        return self.sim.state.particle_qd.numpy()[: self.sim.particle_count].copy()

    def node_positions(self) -> np.ndarray:
        """FEM node positions now [m], shape (N,) live nodes × 3, float32: a copy."""
        return self.sim.state.node_q.numpy()[: self.sim.node_count].copy()

    def node_velocities(self) -> np.ndarray:
        """FEM node velocities now [m/s], shape (N, 3), float32: a copy."""
        return self.sim.state.node_qd.numpy()[: self.sim.node_count].copy()

    def warp_array(self, name: str) -> wp.array:
        """A state (or else model) array by field name, as the Warp array the kernels use: no copy on any device.

        Hand it to ``wp.to_torch``, ``wp.to_jax`` or DLPack (``np.from_dlpack`` on the CPU) to read it without a copy.
        It is sized by capacity (the live items first: see the field's docstring in warpdem.model) and valid until
        the run grows a capacity (a later frame may replace it); writing to it changes the run.

        Raises:
            UnknownArrayError: no such array (the message lists the state's and the model's).
        """
        state, model = self.sim.state.arrays(), self.sim.model.arrays()
        if name in state:
            return state[name]
        if name in model:
            return model[name]
        import difflib

        close = difflib.get_close_matches(name, [*state, *model], n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise UnknownArrayError(
            f"no state or model array {name!r}{hint}; state arrays: {', '.join(sorted(state))}; model arrays: "
            f"{', '.join(sorted(model))}"
        )

    def array(self, name: str) -> np.ndarray:
        """A state (or else model) array by field name, as numpy: on the CPU a view of the run's own memory (no
        copy: it changes as the run steps, and writing to it changes the run), on a GPU a copy. Sized by capacity,
        the live items first (:meth:`warp_array`; vectors as trailing axes: vec3 → shape (capacity, 3)).

        Raises:
            UnknownArrayError: no such array (the message lists the state's and the model's).
        """
        return self.warp_array(name).numpy()

    @property
    def load_names(self) -> list[str]:
        """The scene's pressure loads that :meth:`set_load_scale` can scale, by name (``loads[i]``, i its
        ``[[loads]]`` entry)."""
        loads = self.sim.model.loads
        return list(loads.pressure_names) if loads is not None and loads.pressure_loads is not None else []

    @property
    def load_scales(self) -> dict[str, float]:
        """The scale of each pressure load now [-] (1: the scene's amplitude), by name."""
        return {name: float(s) for name, s in zip(self.load_names, self._load_scales, strict=True)}

    def set_load_scale(self, load: int | str, scale: float) -> None:
        """Scale a pressure load's amplitude (peak pressure, or a table's pressures) to ``scale`` times the scene's,
        from the next step on. The books stay closed: the load kernels book the work of the forces they apply
        (warpdem.stages.loads.scale_pressure_loads). Checkpoints hold the scales, so a restart continues with them.

        Args:
            load: the ``[[loads]]`` entry, by index (0, 1, ...) or name (``"loads[0]"``); a pressure or airblast load.
            scale: the factor [-], finite and >= 0.

        Raises:
            ValueError: no such pressure load (the message lists those there are), or a bad scale.
        """
        self._check_running("set_load_scale")
        names = self.load_names
        name = f"loads[{load}]" if isinstance(load, int | np.integer) else str(load)
        if name not in names:
            loads = self.scene.loads
            index = int(load) if isinstance(load, int | np.integer) else None
            why = ""
            if index is not None and 0 <= index < len(loads):
                why = f" ({name} is a {loads[index].kind} load: only pressure and airblast loads scale)"
            listed = ", ".join(names) if names else "none in this scene"
            raise ValueError(f"set_load_scale: no pressure load {load!r}{why}; pressure loads: {listed}")
        if not (math.isfinite(scale) and scale >= 0.0):
            raise ValueError(f"set_load_scale: the scale must be a finite number >= 0, got {scale!r}")
        self._load_scales[names.index(name)] = float(scale)
        scale_pressure_loads(self.sim.model, self._load_base, self._load_scales)
