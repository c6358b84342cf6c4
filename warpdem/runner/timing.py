"""When a run's steps fall: the frame grid (:class:`FrameGrid`), the rigid blocks' step taken on it, the end step and
its note, the step count refused before a run starts, and the time spent compiling kernels, which the summary keeps
apart from the run's wall time.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from typing import Any

from ..scene import Scene, SceneError
from ..simulation import Simulation
from ..stages.rigid_step import rigid_step_after_switch
from .records import RunOptions

_KERNEL_LOADS = {"seconds": 0.0, "depth": 0}


def _warp_module_class() -> type | None:
    """Warp's module class (whose ``load`` compiles or loads a module's kernels), None if this Warp hides it."""
    for where in ("warp._src.context", "warp.context"):
        try:
            module = __import__(where, fromlist=["Module"])
        except ImportError:
            continue
        cls = getattr(module, "Module", None)
        if isinstance(cls, type) and callable(getattr(cls, "load", None)):
            return cls
    return None


def kernel_load_seconds() -> float:
    """Seconds Warp has spent so far in this process building kernel modules for a device: compiling one on its
    first use or loading it from the kernel cache (the first call starts the clock).

    Warp compiles a module when one of its kernels is first launched, which lands in whatever step or pass launches
    it; it has no public counter of that time, so ``Module.load`` is wrapped once, timing the calls that made a new
    executable (the launches of a loaded module pass through in microseconds and are not counted). Without that
    method (another Warp), the clock stays at 0.
    """
    cls = _warp_module_class()
    if cls is not None and not getattr(cls.load, "_warpdem_clock", False):
        original = cls.load

        @functools.wraps(original)
        def load(self: Any, *args: Any, **kwargs: Any) -> Any:
            if _KERNEL_LOADS["depth"]:
                return original(self, *args, **kwargs)
            execs = getattr(self, "execs", None)
            before = dict(execs) if isinstance(execs, dict) else None
            start = time.perf_counter()
            _KERNEL_LOADS["depth"] += 1
            try:
                return original(self, *args, **kwargs)
            finally:
                _KERNEL_LOADS["depth"] -= 1
                if before is None or getattr(self, "execs", None) != before:
                    _KERNEL_LOADS["seconds"] += time.perf_counter() - start

        load._warpdem_clock = True
        cls.load = load
    return _KERNEL_LOADS["seconds"]


# ----------------------------------------------------------------------------------------------------------------
# Fragments thrown off


@dataclass
class FrameGrid:
    """Where the frames end, in steps: frame k ≥ ``frame`` ends at step ``step`` + (k − ``frame``) × ``substeps``.

    A run starts on one grid (frame 0 at step 0). A change of the time step (the rigid step taken at a switch,
    :func:`take_rigid_step`) starts a new grid at the frame boundary where the new step takes over: the frames keep
    their period (substeps × dt = frame period, dt = period / substeps), so frame k still falls at k × period, to the
    rounding of the device clock's sum of steps. Checkpoints hold the grid (``substeps``, ``grid_step``,
    ``grid_frame``, ``grid_time``), so a restart continues on it.

    Attributes:
        substeps: steps per frame. step, frame: the step at which frame ``frame`` ends (the grid's anchor).
        time: the simulated time then [s].
    """

    substeps: int
    step: int = 0
    frame: int = 0
    time: float = 0.0

    def end_step(self, frame: int) -> int:
        """The step frame ``frame`` ends at."""
        return self.step + (frame - self.frame) * self.substeps

    def last_step(self, end_time: float, frames: int | None, dt: float) -> int:
        """The run's last step: the end of frame ``frames``, or the step nearest ``end_time`` [s] (:func:`end_step`,
        counted in steps of ``dt`` [s] from the grid's anchor)."""
        if frames is not None:
            return self.end_step(frames)
        return self.step + end_step(end_time - self.time, dt)

    def frames(self, last_step: int) -> int:
        """The frames a run that ends at ``last_step`` writes (the last one short when it is not a whole frame)."""
        return self.frame + -(-(last_step - self.step) // self.substeps)

    def attrs(self) -> dict[str, int | float]:
        """The checkpoint attributes of the grid."""
        return {"substeps": self.substeps, "grid_step": self.step, "grid_frame": self.frame, "grid_time": self.time}

    @staticmethod
    def from_attrs(attrs: dict, substeps: int) -> FrameGrid:
        """The grid a checkpoint holds (one written before grids were kept: frame 0 at step 0 with its ``substeps``,
        else ``substeps``)."""
        return FrameGrid(
            int(attrs.get("substeps", substeps)),
            int(attrs.get("grid_step", 0)),
            int(attrs.get("grid_frame", 0)),
            float(attrs.get("grid_time", 0.0)),
        )


@dataclass
class RigidStepChange:
    """The rigid step taken at a switch (:func:`take_rigid_step`).

    Attributes:
        grid: the frame grid from the next frame boundary on (anchored there).
        dt: the time step of that grid, period / substeps [s]; ``pending``: whether it is still to be set at that
            boundary (a switch inside a frame runs the rest of the frame at a bridge step first).
    """

    grid: FrameGrid
    dt: float
    pending: bool


def take_rigid_step(
    sim: Simulation, safety_factor: float, frame_period: float, grid: FrameGrid, frame: int, end: int
) -> RigidStepChange | None:
    """The rigid step, taken at the step of the switch (a run with ``dt = "auto"``; the blocks turned rigid at
    ``sim.step_count``, inside frame ``frame`` or at its end, ``end``: the step that frame ends at on ``grid``).

    From the next frame boundary on, the step is period / n for the fewest n steps per frame that keep it within
    ``safety_factor`` × the critical step after the switch (warpdem.stages.rigid_step.rigid_step_after_switch; larger or
    smaller than the step before), so frames keep landing on k × period. A switch inside a frame leaves the time
    r = (end − step) × dt_old to the frame's end: it is run as m = ⌈r / dt_new⌉ steps of r / m ≤ dt_new (the bridge),
    so the rigid step holds from the switch itself and the frame still ends on its time, to the rounding of the
    device clock. Each change is :meth:`warpdem.simulation.Simulation.set_time_step` (which books the shadow term's
    change): the bridge step now, the grid's step at the boundary (by the caller, ``pending``).

    Returns:
        The new grid, anchored at ``end`` (moved to step + m), and its step; None when the step per frame does not
        change (nothing is changed) or the critical step is not a positive number.
    """
    critical = rigid_step_after_switch(sim.model, sim.state)
    if not (math.isfinite(critical.value) and critical.value > 0.0):
        return None
    substeps = max(1, math.ceil(frame_period / (safety_factor * critical.value)))
    if substeps == grid.substeps:
        return None
    dt = frame_period / substeps
    left = (end - sim.step_count) * sim.model.dt
    if end == sim.step_count:
        sim.set_time_step(dt, critical)
        return RigidStepChange(FrameGrid(substeps, sim.step_count, frame, sim.time), dt, pending=False)
    # The 1e-9 of slack keeps a remainder that is a whole number of new steps from gaining one by rounding.
    bridge = max(1, math.ceil(left / dt * (1.0 - 1e-9)))
    sim.set_time_step(left / bridge, critical)
    return RigidStepChange(FrameGrid(substeps, sim.step_count + bridge, frame, sim.time + left), dt, pending=True)


def frame_step(dt: float, frame_period: float) -> tuple[int, float]:
    """The steps per frame and the step [s] of a run with ``dt = "auto"``: the whole number of steps no longer than
    ``dt`` that fills a frame period [s] (a step at most ``dt``, so the frames land on steps)."""
    substeps = max(1, math.ceil(frame_period / dt))
    return substeps, frame_period / substeps


def end_step(end_time: float, dt: float) -> int:
    """The step a run to ``end_time`` [s] ends at: the nearest one (at least 1), so it ends within dt/2 of the time
    asked, never a frame beyond."""
    return max(1, round(end_time / dt))


def end_time_note(end_time: float, fps: float, dt: float, substeps: int, last: int) -> str | None:
    """What a run to ``end_time`` does when that is not a whole number of frames (or of steps), or None.

    Args:
        end_time: time asked [s]; fps: output rate [frames/s]; dt: time step [s]; substeps: steps per frame;
        last: the run's end step (:func:`end_step`).
    """
    short = last % substeps
    ends = last * dt
    off_step = abs(ends - end_time) > 1e-9 * end_time
    if not short and not off_step:
        return None
    note = f"end time {end_time:g} s"
    if short:
        frame = -(-last // substeps)
        note += (
            f" is not a whole number of frames of 1/{fps:g} s: the last frame ({frame}) will be short, "
            f"{short} of {substeps} steps ({short * dt:.6g} s)"
        )
    else:
        note += f" is not a whole number of steps of {dt:.6g} s"
    if off_step:
        note += f"; the run ends at the step nearest to it, t = {ends:.9g} s"
    return note


def _check_steps(scene: Scene, steps_per_frame: float, options: RunOptions, frames: int | None) -> None:
    """Refuses a run of more than ``options.max_steps`` steps (``frames`` frames; None: one frame) before it starts.

    Raises:
        SceneError: naming run.dt, with the step count it would take.
    """
    steps = steps_per_frame * (1 if frames is None else frames)
    if not steps <= options.max_steps:
        what = "one frame" if frames is None else f"the run ({frames} frames)"
        raise SceneError(
            f"{scene.source}: run.dt: {what} would need {steps:.3g} time steps, more than the limit of "
            f"{options.max_steps} (--max-steps); raise dt, the output_rate or the material numbers that make the "
            "critical step small, or shorten the run"
        )
