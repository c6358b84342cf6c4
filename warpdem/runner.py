"""Running a scene: frames of captured steps, USD output, HDF5 checkpoints, restart, and the closing summary.

:class:`Run` is the one code path: :func:`run_scene` (the command line, warpdem.cli) and the Python API
(warpdem.api) both drive it, ``start()`` → ``frames()`` → ``finish()``. A frame is advanced in pieces of about
:attr:`Run.piece_seconds` of wall time (bit for bit the same steps as one piece: the passes fall on their own
multiples of steps), so that a stop request, Ctrl-C on the command line, is answered within one piece: the run
checkpoints where it stands, mid-frame if need be, and publishes the frames written; a restart from that checkpoint
continues the same run.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import functools
import json
import math
import os
import signal
import sys
import threading
import time
import weakref
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from ._version import __version__
from .build.scene_build import finalize_scene, scene_builder, start_as_spheres
from .io.checkpoint import checkpoint_name
from .io.restart import restore_checkpoint, save_checkpoint
from .limits import MAX_STEPS
from .scene import Scene, SceneError
from .simulation import Simulation
from .stages.energy import EnergyBalance, balance_error
from .stages.guard import UnstableRunError
from .stages.loads import PressureAmplitudes, pressure_amplitudes, scale_pressure_loads
from .stages.rigid_step import rigid_step_after_switch, rigid_time_step


class NothingToDo(Exception):
    """A restart from a checkpoint at or past the end of the run: nothing is simulated and nothing is written."""


class RunInterrupted(KeyboardInterrupt):
    """A run stopped at once (a second Ctrl-C, or Ctrl-C in a script): the frames written so far are published in
    the USD stage, no checkpoint is written of the state the stop found.

    Attributes:
        outputs: what the run left behind, in words (the stage and its frames, the last checkpoint written).
    """

    def __init__(self, outputs: str) -> None:
        super().__init__(outputs)
        self.outputs = outputs


@dataclass
class RunOptions:
    """Command-line overrides of a scene's run and output settings (None = the scene's value).

    Attributes:
        device: Warp device. end_time: simulated end time [s]. frames: number of output frames after the first
        (wins over end_time). out_dir: output directory. usd: USD file path. checkpoint_every: checkpoint period
        [s] (0 = at the end only). restart: checkpoint file to continue from. quiet: no progress bar or summary.
        max_steps: most time steps the run may take; more is refused before the first step (SceneError).
    """

    device: str | None = None
    end_time: float | None = None
    frames: int | None = None
    out_dir: Path | None = None
    usd: Path | None = None
    checkpoint_every: float | None = None
    restart: Path | None = None
    quiet: bool = False
    max_steps: int = MAX_STEPS


@dataclass
class RunSummary:
    """What a run did: simulated time [s], steps, wall time [s], throughput [particle-steps/s], contacts now,
    bonds broken, the energy balance at start and end, and the files written; FEM nodes and live tets, throughput
    [tet-steps/s] and the VTU collection where the scene has a mesh (or writes its spheres as VTU); the time series
    CSV (warpdem.io.timeseries).

    ``wall_time`` is the time spent stepping and writing the frames, less the time Warp took to compile (or load from
    its kernel cache) the kernel modules the run used for the first time: that is ``compile_time``, counted over the
    whole run (the build included), and the throughputs leave it out too.

    ``energy_in_play`` [J] is the largest :attr:`EnergyBalance.in_play` (kinetic + elastic + strain, or the work put
    in so far; no gravity potential) over the run's frames, and ``energy_error`` the balance's change over the run
    relative to it: a scale with no arbitrary datum, so the error does not depend on where z = 0 is.

    With fracture on (``fracture``; warpdem.io.timeseries.fracture_values): node ``splits``, cohesive elements
    ``cohesive_intact`` and ``cohesive_broken``, the crack area made (``crack_area``, one face [m²]) and fully
    opened (``crack_area_opened``), the energy the cohesive elements dissipated (``dissipated_cohesive`` [J]) and,
    to compare, Γ A_f of the broken ones (``cohesive_work_broken`` [J]: a broken element has dissipated exactly that,
    LDEC eq. 9; the intact ones add ½ f_c δ_max each)."""

    simulated_time: float
    steps: int
    wall_time: float
    particle_steps_per_second: float
    particles: int
    contacts: int
    bonds_broken: int
    bonds_intact: int
    energy_start: EnergyBalance
    energy_end: EnergyBalance
    usd_path: Path | None
    checkpoints: list[Path]
    nodes: int = 0
    tets: int = 0
    tet_steps_per_second: float = 0.0
    pvd_path: Path | None = None
    frame: int = 0
    """The last frame written (a run stopped between two frames ends after it, at ``simulated_time``)."""
    interrupted_by: int | None = None
    """The signal (SIGINT, SIGTERM) that stopped the run after ``frame``, once its checkpoint and stage were written."""
    series_path: Path | None = None
    energy_in_play: float = 0.0
    energy_error: float = 0.0
    fracture: bool = False
    splits: int = 0
    cohesive_intact: int = 0
    cohesive_broken: int = 0
    crack_area: float = 0.0
    crack_area_opened: float = 0.0
    dissipated_cohesive: float = 0.0
    cohesive_work_broken: float = 0.0
    fragments_path: Path | None = None
    """The per-frame fragment record (warpdem.stages.fragments), for scenes that can break apart; None otherwise."""
    fragment_count: int = 0
    fragment_largest: float = 0.0
    """Mass of the largest fragment at the last frame [kg]."""
    fragment_mass: float = 0.0
    """Mass of all fragments at the last frame [kg]."""
    ejecta_count: int = 0
    ejecta_speed_max: float = 0.0
    ejecta_speed_median: float = 0.0
    """The pieces broken off at the last frame (:func:`ejecta_speeds`: every fragment but the largest breakable one
    and the loose spheres, such as an impactor), their number and the largest and median speed of their centres of
    mass [m/s] (0 without any)."""
    rigid: str = ""
    """What the switch to rigid blocks did in this run (warpdem.stages.rigid.RigidReport.format), empty without one."""
    compile_time: float = 0.0
    """Time Warp spent compiling kernel modules on their first use, or loading them from its kernel cache [s]
    (:func:`kernel_load_seconds`), over the whole run; not part of ``wall_time``."""

    def format(self) -> str:
        e0, e1 = self.energy_start, self.energy_end
        spheres = self.particles > 0
        lines = [f"simulated time   {self.simulated_time:.6g} s in {self.steps} steps"]
        wall = f"wall time        {self.wall_time:.3f} s"
        if spheres:
            wall += f"  ({self.particle_steps_per_second / 1e6:.3f} M particle-steps/s)"
        if self.compile_time > 0.0:
            wall += f"; kernel compiling {self.compile_time:.2f} s more (first use, not counted)"
        lines.append(wall)
        if spheres:
            lines += [
                f"particles        {self.particles}   contacts {self.contacts}",
                f"bonds            {self.bonds_intact} intact, {self.bonds_broken} broken",
            ]
        if self.nodes:
            rate = self.tet_steps_per_second / 1e6
            lines.append(f"rock mesh        {self.nodes} nodes, {self.tets} tets  ({rate:.3f} M tet-steps/s)")
        if self.rigid:
            lines.append(f"rigid blocks     {self.rigid.removeprefix('rigid switch: ')}")
        if self.fracture:
            lines += [
                f"fracture         {self.splits} node splits; cohesive elements {self.cohesive_intact} intact, "
                f"{self.cohesive_broken} broken",
                f"crack area       {self.crack_area:.6g} m² made, {self.crack_area_opened:.6g} m² opened (one face)",
                f"cohesive energy  {self.dissipated_cohesive:.6g} J dissipated; Γ × area of the broken elements "
                f"{self.cohesive_work_broken:.6g} J",
            ]

        def row(label: str, a: float, b: float) -> str:
            return f"  {label:<15}{a:<14.6g} {b:.6g}"

        lines += ["energy [J]       start          end", row("kinetic", e0.kinetic, e1.kinetic)]
        if self.nodes:
            lines.append(row("  of nodes", e0.kinetic_nodes, e1.kinetic_nodes))
        if e0.kinetic_rigid or e1.kinetic_rigid:
            lines.append(row("  of rigid bl.", e0.kinetic_rigid, e1.kinetic_rigid))
        lines.append(row("Verlet shadow", e0.shadow, e1.shadow))
        if e1.released_rigid_switch:
            lines.append(row("rigid switch", e0.released_rigid_switch, e1.released_rigid_switch))
        if e0.step_change or e1.step_change:
            # What taking another time step, or the forces of a split pass, changed Verlet's shadow term by
            # (Simulation.set_time_step, Simulation.fracture_pass).
            lines.append(row("step change", e0.step_change, e1.step_change))
        if self.nodes:
            lines += [
                row("strain", e0.strain, e1.strain),
                row("viscous diss.", e0.dissipated_viscous, e1.dissipated_viscous),
                row("non-refl. abs.", e0.absorbed_boundaries, e1.absorbed_boundaries),
                row("load work", e0.load_work, e1.load_work),
                row("contact diss.", e0.dissipated_fem_contact, e1.dissipated_fem_contact),
            ]
        if self.fracture:
            lines += [
                row("cohesive el.", e0.cohesive_elastic, e1.cohesive_elastic),
                row("cohesive diss.", e0.dissipated_cohesive, e1.dissipated_cohesive),
            ]
        if self.fracture or e1.contact_topology != 0.0:
            # What split and conversion passes put into the FEM contact springs (Simulation._book_contact_topology).
            lines.append(row("contact gain", e0.contact_topology, e1.contact_topology))
        lines.append(row("elastic", e0.elastic, e1.elastic))
        if e0.gravity_potential != 0.0 or e1.gravity_potential != 0.0:
            lines.append(row("gravity pot.", e0.gravity_potential, e1.gravity_potential))
        if spheres:
            lines += [
                row("damping diss.", e0.dissipated_damping, e1.dissipated_damping),
                row("friction diss.", e0.dissipated_friction, e1.dissipated_friction),
                row("k_t(δ) change", e0.stiffness_change, e1.stiffness_change),
                row("bond breakage", e0.released_by_bond_breakage, e1.released_by_bond_breakage),
                row("wall work", e0.boundary_work, e1.boundary_work),
            ]
        lines.append(
            f"  balance        {e0.total:<14.6g} {e1.total:.6g}   "
            f"(error {self.energy_error:+.2e} of {self.energy_in_play:.3g} J in play)"
        )
        if self.usd_path is not None:
            lines.append(f"USD              {self.usd_path}")
        if self.pvd_path is not None:
            lines.append(f"VTU series       {self.pvd_path}")
        if self.fragments_path is not None:
            share = self.fragment_largest / self.fragment_mass if self.fragment_mass > 0.0 else 0.0
            lines.append(
                f"fragments        {self.fragment_count}, largest {self.fragment_largest:.6g} kg ({share:.1%} of "
                f"{self.fragment_mass:.6g} kg)"
            )
            if self.ejecta_count:
                pieces = f"{self.ejecta_count} piece{'s' if self.ejecta_count != 1 else ''}"
                lines.append(
                    f"ejecta speed     max {self.ejecta_speed_max:.6g} m/s, median {self.ejecta_speed_median:.6g} m/s "
                    f"of the {pieces} broken off (fragments but the largest; loose spheres such as an impactor "
                    "left out)"
                )
        if self.series_path is not None:
            lines.append(f"time series      {self.series_path}")
        if self.fragments_path is not None:
            lines.append(f"fragment record  {self.fragments_path}")
        if self.checkpoints:
            lines.append(f"checkpoint       {self.checkpoints[-1]}")
        return "\n".join(lines)


@dataclass(frozen=True)
class FrameEnergy:
    """The energy books at an output frame.

    Attributes:
        balance: every line of the books [J] (warpdem.stages.energy.EnergyBalance); its fields read through this
            object too (``frame.energy.kinetic``).
        error: the balance's drift since the first frame of the run's timeline, relative to ``in_play`` [-] (the
            time series' ``energy_error``, the number the summary prints).
        in_play: the largest energy in play over the timeline so far [J] (the error's scale).
    """

    balance: EnergyBalance
    error: float
    in_play: float

    def __getattr__(self, name: str) -> Any:
        if name == "balance":  # not set yet (copy, unpickling): no recursion through the delegation below
            raise AttributeError(name)
        return getattr(self.balance, name)


@dataclass(frozen=True)
class Frame:
    """An output frame, as :meth:`Run.frames` yields it once its outputs are written.

    Attributes:
        index: frame number (the USD time code; 0 is the initial state). time: simulated time [s]. step: time steps
            taken so far.
        energy: the energy books (:class:`FrameEnergy`; ``energy.error`` is the balance's relative drift).
        splits: node splits so far (0 without nodal fracture).
        fragments: the number of fragments, where the run labels them (None elsewhere).
        series: the frame's row of the time series, column → value (warpdem.io.timeseries: counts, wall and load
            forces, every energy line).
    """

    index: int
    time: float
    step: int
    energy: FrameEnergy
    splits: int = 0
    fragments: int | None = None
    series: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------------------
# Kernel compile time

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


def ejecta_speeds(model: Any, state: Any, fragments: Any) -> np.ndarray:
    """Centre-of-mass speeds of the pieces broken off [m/s], shape (K,), float64: every fragment but the largest
    breakable one, leaving out the loose spheres (reads back; call between steps).

    A loose sphere is one that never had a bond (none intact, none broken) and was not made by conversion: an
    impactor, a grain poured in. A fragment of loose spheres alone was never part of anything that could break,
    so its speed (an impactor's own) says nothing about what the impact threw off.

    Args:
        model, state: the run's model and state, as labelled. fragments: their fragments
            (warpdem.stages.fragments.FragmentStats).
    """
    from .io.output import sphere_damage

    count = fragments.count
    if count == 0:
        return np.zeros(0)
    breakable = np.zeros(count, dtype=bool)
    nodes = fragments.node_label[fragments.node_label >= 0]
    breakable[nodes] = True
    label = fragments.particle_label
    if len(label):
        broken, _ = sphere_damage(model, state)
        n = len(label)
        nb = int(state.bond_count.numpy()[0]) if model.bond_capacity else 0
        intact = state.bond_broken.numpy()[:nb] == 0
        ends = np.concatenate([state.bond_i.numpy()[:nb][intact], state.bond_j.numpy()[:nb][intact]])
        bonded = (broken > 0) | (np.bincount(ends, minlength=n)[:n] > 0)
        if model.conversion_interval > 0 or model.tet_may_convert is not None:
            bonded |= model.particle_part.numpy()[:n] == model.conversion_part
        breakable[label[(label >= 0) & bonded]] = True
    kept = np.flatnonzero(breakable)
    if len(kept) == 0:
        return np.zeros(0)
    # The largest of them is the body they broke from; ties keep the id order, as the fragment listing does.
    largest = kept[np.argsort(-fragments.fragment_mass[kept], kind="stable")[0]]
    others = kept[kept != largest]
    return np.linalg.norm(fragments.fragment_velocity[others], axis=1)


def speed_colors(speed: np.ndarray, scale: float) -> np.ndarray:
    """Blue (at rest) → red (at ``scale`` m/s and above), shape (N, 3)."""
    t = np.clip(speed / max(scale, 1e-12), 0.0, 1.0)[:, None]
    return (1.0 - t) * np.array([0.15, 0.3, 0.85]) + t * np.array([0.95, 0.25, 0.1])


PART_PALETTE = np.array(
    [[0.55, 0.55, 0.6], [0.85, 0.45, 0.2], [0.2, 0.6, 0.85], [0.4, 0.75, 0.3], [0.8, 0.3, 0.5], [0.9, 0.8, 0.3]]
)


class _StopRequest:
    """SIGINT and SIGTERM during a run: the first asks the run to stop at the next piece of steps (within about a
    second, :attr:`Run.piece_seconds`), where it writes a checkpoint of that state and publishes the stage; a second
    stops at once (KeyboardInterrupt: the frames written so far are published, no checkpoint is written). Handlers are
    installed only in the main thread, and the previous ones put back on exit."""

    def __init__(self, run: Run, quiet: bool) -> None:
        self.signum: int | None = None
        self._run = run
        self._quiet = quiet
        self._previous: dict[int, object] = {}

    def __enter__(self) -> _StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _handle(self, signum: int, _frame: object) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum
        self._run.request_stop(signum)
        if not self._quiet:
            print(
                f"\n{signal.Signals(signum).name}: stopping within a second, with a checkpoint and the stage published "
                "(again to stop at once: the frames written are published, no checkpoint)",
                file=sys.stderr,
            )


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


def _output_error(where: str, path: Path, exc: BaseException) -> SceneError:
    """A one-line SceneError for an output file that cannot be written (name too long, no permission, disk full)."""
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else " ".join(str(exc).split())
    return SceneError(f"{where}: cannot write {path}: {reason}")


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


_OPEN_RUNS: weakref.WeakSet[Run] = weakref.WeakSet()
"""Runs of this process whose USD stage is still being written (a restart into the same stage takes it over)."""


@atexit.register
def _close_open_runs() -> None:
    """At the interpreter's exit, publish the stage of every run left open (a script that stopped iterating, or
    ended in an error of its own), so that the frames it wrote are not left in a partial file."""
    for run in list(_OPEN_RUNS):
        with contextlib.suppress(Exception):
            run.close()


class UnknownArrayError(KeyError):
    """:meth:`Run.array` was asked for an array the model and state do not have; the message lists those they do."""

    def __str__(self) -> str:
        return str(self.args[0])


class Run:
    """One run of a scene: the model built (or restored from a checkpoint), stepped frame by frame, with every
    output a frame writes (USD stage, VTU series, time series, fragment record), checkpoints, and the summary.

    ``start()`` builds and writes the first frame; ``frames()`` steps to each output frame in turn, writes it and
    yields it (a :class:`Frame`); ``finish()`` writes the final checkpoint, publishes the USD stage and returns the
    :class:`RunSummary` (``frames()`` calls it itself when the run reaches its end). :func:`run_scene` and the Python
    API (warpdem.api, which documents the user's side) drive this class alike, so a script writes what the command
    line writes.

    Args:
        scene: a validated scene.
        options: overrides of the scene's run and output settings (None: the scene's own).

    Attributes:
        scene, options: as given. sim: the stepper (warpdem.simulation.Simulation) once started.
        frame: the last frame written (None before the first, or right after a restart from between two frames).
        checkpoints: the checkpoints written, oldest first. summary: the summary, once finished.
        piece_seconds: wall time of the pieces of steps a frame is run in [s]: a stop request
            (:meth:`request_stop`) is answered between two; any value gives the same steps, bit for bit.
    """

    piece_seconds: float = 0.25

    def __init__(self, scene: Scene, options: RunOptions | None = None) -> None:
        self.scene = scene
        self.options = options if options is not None else RunOptions()
        self.sim: Simulation | None = None
        self.frame: Frame | None = None
        self.checkpoints: list[Path] = []
        self.summary: RunSummary | None = None
        self.stop_signal: int | None = None
        self._stop = False
        self._phase = "new"  # new → running → finished (summary made) or closed (outputs released, no summary)
        self._callbacks: list[Callable[[Frame], None]] = []
        self._unyielded: Frame | None = None  # the first frame, written by start() and not yet yielded
        self._wall = 0.0  # [s] stepping and writing frames, kernel compiling left out
        self._stepping_since = 0.0  # perf_counter at the start of the frame being stepped (the progress rate)
        self._time_at_start = 0.0  # [s] simulated time when the run started
        self._in_play = 0.0  # [J] the largest energy in play over this run's frames
        self._compile = 0.0  # [s] kernel compiling and loading in this run's calls
        self._steps_per_piece = 1
        self._writer: Any = None
        self._progress: Any = None

    # ------------------------------------------------------------------------------------------------------------
    # Start

    def start(self) -> None:
        """Build the model (or restore the checkpoint of ``options.restart``), open the outputs and write the first
        frame (none after a restart from between two frames: the next is the first this run writes).

        Raises:
            SceneError: the scene cannot be built or run as asked (a device that is not there, an output that cannot
                be written, more steps than ``options.max_steps``), before any output is written.
            CheckpointError: the restart file cannot be used.
            NothingToDo: the restart's checkpoint is at or past the end of the run (nothing is written).
            RuntimeError: the run has started already.
        """
        if self._phase != "new":
            raise RuntimeError("Run.start: this run has started already")
        with self._clock(stepping=False):
            try:
                self._start()
            except BaseException:
                self._abort()
                raise

    def _start(self) -> None:
        scene, options = self.scene, self.options
        run = scene.run
        device_name = options.device or run.device
        try:
            device = wp.get_device(device_name)
        except (ValueError, RuntimeError) as exc:
            where = "--device" if options.device else f"{scene.source}: run.device"
            raise SceneError(f"{where}: device {device_name!r} is not available here ({exc})") from None
        self._device_name = str(device)
        builder = scene_builder(scene)
        for quality in builder.mesh_qualities:
            self._say(f"mesh: {quality.format()}")
        # Looked up in this module at call time (tests attach passes to the built model by replacing it).
        model, state = finalize_scene(scene, builder, device)
        if builder.overlap is not None and builder.overlap.any:
            self._say(f"initial overlap: {builder.overlap.format()}")

        if scene.rigid.enabled and run.dt == "auto":
            # Rigid blocks from the start: no element modes, the contacts on the bodies set the step
            # (warpdem.stages.rigid).
            model = rigid_time_step(model, state, run.safety_factor)
        fps = run.output_rate
        frame_period = 1.0 / fps
        if not (math.isfinite(model.dt) and model.dt > 0.0):
            raise SceneError(
                f"{scene.source}: run.dt: the time step is {model.dt!r} s; the critical step of this scene is not a "
                "positive number (coincident spheres, or material numbers out of proportion)"
            )
        _check_steps(scene, frame_period / model.dt, options, None)
        if run.dt == "auto":
            substeps = max(1, math.ceil(frame_period / model.dt))
            model = dataclasses.replace(model, dt=frame_period / substeps)
        else:
            substeps = max(1, round(frame_period / model.dt))

        # The amplitudes the load scales refer to: the scene's, whatever a checkpoint's run had set them to.
        self._load_base: PressureAmplitudes | None = pressure_amplitudes(model)
        self._load_scales = np.ones(0 if self._load_base is None else len(self._load_base.peak))
        step, sim_time, first_frame, primed, attrs = 0, 0.0, 0, False, {}
        grid = FrameGrid(substeps)
        restart = options.restart is not None
        if restart:
            model, state, attrs = restore_checkpoint(Path(options.restart), model, state, scene.name)
            step, sim_time, first_frame, primed = int(attrs["step"]), float(attrs["time"]), int(attrs["frame"]), True
            # The frames end on the original run's grid, whatever the scene says now (its step is the checkpoint's).
            grid = FrameGrid.from_attrs(attrs, substeps)
            substeps = grid.substeps
            held = attrs.get("load_scales", {})
            if held and self._load_base is not None:
                names = model.loads.pressure_names
                self._load_scales = np.array([float(held.get(name, 1.0)) for name in names])
                scale_pressure_loads(model, self._load_base, self._load_scales)
        # The frame period stays that of the first grid (a later one divides it into other steps, to rounding).
        self._frame_period = frame_period = float(attrs.get("frame_period", substeps * model.dt))

        # The run ends at last_step (a short last frame when that is not a multiple of the frame's steps).
        self._end_time = end_time = options.end_time if options.end_time is not None else run.end_time
        last_step = grid.last_step(end_time, options.frames, model.dt)
        total_frames = grid.frames(last_step)
        if step >= last_step:
            raise NothingToDo(
                f"nothing to do: the checkpoint is at t = {sim_time:.9g} s (frame {first_frame}), the run ends at "
                f"t = {grid.time + (last_step - grid.step) * model.dt:.9g} s (frame {total_frames})"
            )
        # The note counts frames from step 0: on the first grid only.
        if options.frames is None and grid.step == 0:
            note = end_time_note(end_time, fps, model.dt, substeps, last_step)
            if note is not None:
                self._say(note)
        self.sim = sim = Simulation(model, state, primed=primed, step=step, time=sim_time)
        if not restart:
            # A new run converts its start_as_spheres region here, before frame 0; a restart's checkpoint holds them.
            start_as_spheres(scene, sim)
        self._grid, self._last_step, self._total_frames = grid, last_step, total_frames
        # With dt = "auto" a run takes the rigid blocks' step at the step of the switch (a switch from the start took
        # it above: the same step, no change); a restart knows from its checkpoint whether it did (one written at a
        # run's end by an earlier warpdem, which took it at the next frame boundary, may not have). An explicit dt is
        # the user's: it is kept across the switch.
        self._rigid_step_due = run.dt == "auto" and not bool(attrs.get("rigid_step_taken", primed and sim.rigid))
        # The grid's step, set at the frame boundary that ends a bridge (take_rigid_step); a checkpoint taken inside
        # the bridge holds it.
        pending = attrs.get("pending_dt")
        self._pending_dt: float | None = float(pending) if pending is not None else None

        _check_steps(scene, float(substeps), options, total_frames - first_frame)

        # Where the last frame was written: a checkpoint taken between two frames (a stop request) holds it; the
        # next frame is then the first this run writes.
        self._frame_index = first_frame
        self._frame_step = int(attrs.get("frame_step", step))
        self._frame_time = float(attrs.get("frame_time", sim_time))
        crc = attrs.get("frame_points_crc32")
        self._frame_crc: int | None = int(crc) if crc is not None else None
        between = restart and self._frame_step != step
        first_written = first_frame + 1 if between else first_frame

        self._out_dir = out_dir = Path(options.out_dir) if options.out_dir is not None else Path(scene.output.directory)
        usd_path = Path(options.usd) if options.usd is not None else out_dir / scene.output.usd
        output_stem = usd_path.stem  # VTU files are named like the stage; a restart continues both
        _take_over(usd_path)
        if restart:
            _check_stage_continues(
                usd_path, 1.0 / frame_period, first_frame, sim, options.quiet, self._frame_time, self._frame_crc
            )
        checkpoint_every = (
            options.checkpoint_every if options.checkpoint_every is not None else scene.output.checkpoint_every
        )
        self._checkpoint_dir = out_dir / scene.output.checkpoint_dir
        self._frames_per_checkpoint = max(1, round(checkpoint_every / frame_period)) if checkpoint_every > 0 else 0

        from .io.output import RockFrames, VtuSeries
        from .io.timeseries import TimeSeries
        from .io.usd import UsdWriter
        from .stages.fragments import FragmentFile, can_fragment

        # Colour scales are the largest values seen so far in the run: a restart continues them from its checkpoint.
        self._speed_scale = float(attrs.get("speed_scale", 1e-12))
        mesh_vtu = scene.output.vtu and model.node_capacity > 0
        try:
            self._vtu = (
                VtuSeries(out_dir, output_stem, first_written) if mesh_vtu or scene.output.particles_vtu else None
            )
            self._series = TimeSeries(out_dir, output_stem, first_written)
            # Only a scene that can break apart gets a fragment record: elsewhere it would count the same pieces.
            self._fragment_file = FragmentFile(out_dir, output_stem, first_written) if can_fragment(model) else None
        except OSError as exc:
            raise _output_error(f"{scene.source}: output.directory", out_dir, exc) from None
        self._rock = RockFrames(scene.output.mesh_color_by, self._vtu if mesh_vtu else None)
        self._rock.color_scale = float(attrs.get("rock_color_scale", 0.0))
        self._cohesive_as_curves = bool(getattr(scene.output, "cohesive_as_curves", False))
        self._by_fragment = self._fragment_file is not None or "fragment" in (
            scene.output.color_by,
            scene.output.mesh_color_by,
        )
        self._last_fragments: Any = None
        self._ejecta = np.zeros(0)

        try:
            # A restart extends the stage of the run it continues (checked above); a new run replaces what was there.
            self._writer = UsdWriter(
                usd_path,
                1.0 / frame_period,
                comment=f"warpdem {__version__}: {scene.name}",
                first_frame=first_written,
                append=restart,
            )
        except (OSError, RuntimeError) as exc:  # pxr reports a layer it cannot create as a RuntimeError
            if options.usd is not None or options.out_dir is not None:
                where = "--usd" if options.usd is not None else "--out"
            else:
                where = f"{scene.source}: output.directory / output.usd"
            raise _output_error(where, usd_path, exc) from None
        self._usd_path = self._writer.path
        self._phase = "running"
        _OPEN_RUNS.add(self)
        self._steps_start, self._time_at_start = sim.step_count, sim.time
        if not options.quiet and sys.stderr.isatty():
            from tqdm import tqdm

            self._progress = tqdm(
                total=round(grid.time + (last_step - grid.step) * model.dt - sim_time, 9),
                desc=scene.name,
                file=sys.stderr,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}{postfix}]",
            )
        # Blocks rigid from the start, or a restart that did not take the step (from a short last frame, or from
        # between two frames: to the end of the next frame on the grid).
        frame = self._frame_index
        self._adopt_rigid_step(frame if sim.step_count == grid.end_step(frame) else frame + 1)
        if between:
            self._energy_start = self._energy_end = sim.energy()
            self._in_play = self._energy_start.in_play
        else:
            self._unyielded = self._write_frame()
            self._energy_start = self._unyielded.energy.balance

    # ------------------------------------------------------------------------------------------------------------
    # Frames

    def frames(self) -> Iterator[Frame]:
        """Step to each output frame in turn, write its outputs, call the :meth:`on_frame` callbacks and yield it.

        The first frame (the initial state, written by :meth:`start`) comes first, once. At the end of the run the
        iterator calls :meth:`finish` and stops; a stop request (:meth:`request_stop`) stops it early, without
        finishing. Leaving the loop early leaves the run where it is: ``frames()`` again continues it.

        Raises:
            UnstableRunError: the run blew up (warpdem.stages.guard); the stage holds the good frames and is
                published, the checkpoints written before stay, none is written of the bad state.
            RunInterrupted: Ctrl-C (KeyboardInterrupt) while stepping; the frames written are published.
        """
        self._check_running("frames")
        while True:
            if self._unyielded is not None:
                frame, self._unyielded = self._unyielded, None
            else:
                if self._stop or self._frame_index >= self._total_frames:
                    break
                frame = self._next_frame()
                if frame is None:
                    break  # stopped between two frames
            for callback in self._callbacks:
                callback(frame)
            yield frame
        if not self._stop and self._frame_index >= self._total_frames and self._phase == "running":
            self.finish()

    def _next_frame(self) -> Frame | None:
        """Advance to the next frame and write it (None: a stop request came first)."""
        try:
            with self._clock(stepping=True):
                if not self._advance_frame(self._frame_index + 1):
                    return None
                self._frame_index += 1
                frame = self._write_frame()
                k = self._frames_per_checkpoint
                if k and self._frame_index % k == 0 and self._frame_index < self._total_frames:
                    self.checkpoint()
                return frame
        except UnstableRunError as exc:
            # The bad state is neither written nor checkpointed; the good frames are published.
            last = f"last good checkpoint {self.checkpoints[-1]}" if self.checkpoints else "no checkpoint written"
            count = self._writer.frame_count
            exc.outputs = f"{count} good frame{'s' if count != 1 else ''} published in {self._usd_path}; {last}"
            self.close()
            raise
        except KeyboardInterrupt:
            raise self._interrupted() from None
        except BaseException:
            self._abort()
            raise

    def _advance_frame(self, frame: int) -> bool:
        """Run the steps of frame ``frame`` (to its end on the grid, or the run's last step) in pieces, taking the
        rigid step at a switch inside it, then the grid's step at its end after a bridge. Returns False when a stop
        request ended it between two pieces (the frame unfinished)."""
        sim = self.sim
        while True:
            end = min(self._grid.end_step(frame), self._last_step)
            if sim.step_count >= end:
                break
            if self._stop:
                return False
            rigid = sim.rigid
            start, loads = time.perf_counter(), kernel_load_seconds()
            done = sim.advance(min(end - sim.step_count, self._steps_per_piece), stop_at_switch=self._rigid_step_due)
            self._pace(done, time.perf_counter() - start - (kernel_load_seconds() - loads))
            if sim.rigid and not rigid:
                self._adopt_rigid_step(frame)
        if self._pending_dt is not None:
            sim.set_time_step(self._pending_dt)
            self._pending_dt = None
        return True

    def _pace(self, steps: int, seconds: float) -> None:
        """Size the next piece to :attr:`piece_seconds` at the rate of the last (growing at most ×4 a piece, so that
        a slow piece after a fast one cannot run long), and show the progress."""
        if steps > 0:
            rate = steps / max(seconds, 1e-9)
            self._steps_per_piece = max(1, min(int(rate * self.piece_seconds), 4 * self._steps_per_piece))
        if self._progress is not None:
            now = self.sim.time
            wall = self._wall + time.perf_counter() - self._stepping_since
            rate = (now - self._time_at_start) / wall if wall > 0 else 0.0
            bar = self._progress
            bar.set_postfix_str(f"t = {now:.4g} s, {rate:.3g} simulated s per wall s", refresh=False)
            bar.n = min(round(now - self._time_at_start, 9), bar.total)  # the clock's sum may pass the total by ulps
            bar.refresh()  # a piece is about piece_seconds: a redraw each is few

    def _adopt_rigid_step(self, frame: int) -> None:
        """Take the rigid step now if it is due (the blocks are rigid), ``frame`` being the frame in progress: the one
        whose end on the grid is the next frame boundary at or after the current step."""
        sim, grid = self.sim, self._grid
        end = grid.end_step(frame)
        if not (self._rigid_step_due and sim.rigid) or end > self._last_step:
            # A switch in the run's short last frame: the frames after it would leave the grid (k × period), so the
            # rigid step waits for a restart that continues the run, which takes it at its start (to the next
            # boundary on the grid); the checkpoint says it is not taken.
            return
        self._rigid_step_due = False
        change = take_rigid_step(sim, self.scene.run.safety_factor, self._frame_period, grid, frame, end)
        if change is None:
            return
        runs_on = end != self._last_step  # a bridge to the run's last step ends the run: no step is added past it
        self._grid = change.grid
        if change.pending:
            self._pending_dt = change.dt
        self._last_step = (
            change.grid.last_step(self._end_time, self.options.frames, change.dt) if runs_on else change.grid.step
        )
        self._total_frames = change.grid.frames(self._last_step)

    def _write_frame(self) -> Frame:
        """Write every output of the frame the run is at; returns it, with its energy balance (read back once, for
        the series, the frame and the summary)."""
        from .io.output import damage_colors, sphere_damage, sphere_point_data
        from .stages.fragments import fragment_colors, label_fragments

        sim, scene, frame = self.sim, self.scene, self._frame_index
        energy = sim.energy()
        self._rock.write_vtu(frame, sim.time, sim.model, sim.state)
        n = sim.particle_count
        q = sim.state.particle_q.numpy()[:n]
        v = sim.state.particle_qd.numpy()[:n]
        if scene.output.particles_vtu and n:
            self._vtu.write_particles(frame, sim.time, q, sphere_point_data(sim.model, sim.state))
        row = self._series.record(sim, frame, energy)
        fragments = label_fragments(sim.model, sim.state) if self._by_fragment else None
        if fragments is not None:
            self._last_fragments = fragments
            if self._fragment_file is not None:
                try:
                    self._fragment_file.record(frame, sim.time, fragments)
                except OSError as exc:
                    path = self._fragment_file.path
                    raise _output_error(f"{scene.source}: output.directory", path, exc) from None
                self._ejecta = ejecta_speeds(sim.model, sim.state, fragments)
        speed = np.linalg.norm(v, axis=1)
        broken, damage = sphere_damage(sim.model, sim.state)
        if scene.output.color_by == "part":
            colors = PART_PALETTE[sim.model.particle_part.numpy()[:n] % len(PART_PALETTE)]
        elif scene.output.color_by == "damage":
            colors = damage_colors(damage)
        elif scene.output.color_by == "fragment":
            colors = fragment_colors(fragments.particle_label)
        else:
            self._speed_scale = max(self._speed_scale, float(speed.max(initial=0.0)))
            colors = speed_colors(speed, self._speed_scale)
        bonds = None
        if scene.output.bonds_as_curves and sim.model.bond_capacity:
            nb = sim.bond_count
            intact = sim.state.bond_broken.numpy()[:nb] == 0
            bonds = np.stack([sim.state.bond_i.numpy()[:nb][intact], sim.state.bond_j.numpy()[:nb][intact]], axis=1)
        rock = self._rock
        self._writer.write_frame(
            time=sim.time,
            positions=q,
            radii=sim.model.particle_radius.numpy()[:n],
            velocities=v,
            ids=sim.model.particle_id.numpy()[:n].astype(np.int64),
            colors=colors,
            bonds=bonds,
            surface=rock.surface(sim.model, sim.state, fragments.node_label if fragments is not None else None),
            bonds_broken=broken if sim.model.bond_capacity else None,
            cohesive=rock.cohesive_curves(sim.model, sim.state) if self._cohesive_as_curves else None,
            fragments=fragments.particle_label if fragments is not None else None,
        )
        # What a restart from between this frame and the next checks the stage against (the points as stored).
        self._frame_step, self._frame_time = sim.step_count, sim.time
        self._frame_crc = zlib.crc32(np.ascontiguousarray(q, dtype=np.float32).tobytes()) if n else None
        self._energy_end = energy
        self._in_play = max(self._in_play, energy.in_play)
        self.frame = Frame(
            index=frame,
            time=sim.time,
            step=sim.step_count,
            energy=FrameEnergy(energy, float(row["energy_error"]), self._series.in_play),
            splits=int(row.get("splits", 0)),
            fragments=fragments.count if fragments is not None else None,
            series=row,
        )
        return self.frame

    # ------------------------------------------------------------------------------------------------------------
    # Stop, checkpoint, finish

    def request_stop(self, signum: int | None = None) -> None:
        """Ask the run to stop at the next piece of steps (within about :attr:`piece_seconds`): ``frames()`` then
        ends without finishing the frame in progress; :meth:`finish` checkpoints the state there and publishes the
        stage, and a restart from that checkpoint continues the run bit for bit. Safe to call from a signal handler
        or another thread.

        Args:
            signum: the signal that asked (reported as the summary's ``interrupted_by``), or None.
        """
        self._stop = True
        if signum is not None:
            self.stop_signal = signum

    def checkpoint(self, path: str | os.PathLike | None = None) -> Path:
        """Write a checkpoint of the run now: the complete state, the frame grid, the load scales, the scene and the
        run's output settings, so that :func:`warpdem.api.restart` (or ``--restart``) continues the same run with
        the same outputs. Also after the run ended (of its final state).

        Args:
            path: the HDF5 file (None: ``<checkpoint_dir>/<scene>_checkpoint_<step>.h5`` under the output
                directory).

        Returns:
            The file written.

        Raises:
            SceneError: the file cannot be written.
        """
        if self.sim is None:
            raise RuntimeError("Run.checkpoint: the run has not started (call start(), or build it with warpdem.build)")
        sim, scene, options = self.sim, self.scene, self.options
        target = Path(path) if path is not None else self._checkpoint_dir / checkpoint_name(sim.step_count, scene.name)
        extra: dict[str, Any] = {
            "scene": scene.name,
            **self._grid.attrs(),
            "frame_period": self._frame_period,
            "rigid_step_taken": not self._rigid_step_due,
            "seed": scene.run.seed,
            "speed_scale": self._speed_scale,
            "rock_color_scale": self._rock.color_scale,
            "frame_step": self._frame_step,
            "frame_time": self._frame_time,
            "scene_json": scene.model_dump_json(warnings=False),
            "scene_source": scene.source,
            "run_options": {
                "device": self._device_name,
                "end_time": options.end_time,
                "frames": options.frames,
                # Relative to the checkpoint's folder: the outputs are found beside it wherever the two are moved
                # together, and a run restarted into another folder writes the same checkpoint as the original.
                "out_dir": _relative_to(self._out_dir, target.parent),
                "usd": _relative_to(self._usd_path, target.parent),
            },
        }
        if self._frame_crc is not None:
            extra["frame_points_crc32"] = self._frame_crc
        if self._pending_dt is not None:
            extra["pending_dt"] = self._pending_dt
        if len(self._load_scales):
            names = sim.model.loads.pressure_names
            extra["load_scales"] = {name: float(s) for name, s in zip(names, self._load_scales, strict=True)}
        try:
            written = save_checkpoint(target, sim, self._frame_index, extra)
        except OSError as exc:
            where = f"{scene.source}: output.checkpoint_dir" if path is None else "checkpoint"
            raise _output_error(where, target, exc) from None
        self.checkpoints.append(written)
        return written

    def finish(self) -> RunSummary:
        """End the run: write the final checkpoint (unless one of this state was just written), publish the USD stage
        and make the summary. Called again, returns the same summary.

        Raises:
            RunInterrupted: Ctrl-C while finishing; the frames written are published.
        """
        if self.summary is not None:
            return self.summary
        self._check_running("finish")
        try:
            with self._clock(stepping=False):
                sim = self.sim
                if sim.step_count != self._frame_step:
                    # Stopped between two frames: the books where it stopped, not at the last frame.
                    self._energy_end = sim.energy()
                    self._in_play = max(self._in_play, self._energy_end.in_play)
                default = self._checkpoint_dir / checkpoint_name(sim.step_count, self.scene.name)
                if not self.checkpoints or self.checkpoints[-1] != default:
                    self.checkpoint()
                self._release(publish=True)
        except KeyboardInterrupt:
            raise self._interrupted() from None
        except BaseException:
            self._abort()
            raise
        self.summary = self._summarize()
        self._phase = "finished"
        return self.summary

    def close(self) -> None:
        """Publish the USD stage with the frames written so far and release the outputs, without a checkpoint or a
        summary (a run left part way; :meth:`finish` ends one properly). Does nothing to a run that has ended."""
        if self._phase == "running":
            self._release(publish=True)
            self._phase = "closed"

    def run(self, callback: Callable[[Frame], None] | None = None) -> RunSummary:
        """Start (if not started), run every frame to the end (or a stop request) and finish.

        Args:
            callback: called with each frame as it is written, after the :meth:`on_frame` callbacks.

        Returns:
            The summary.
        """
        if self._phase == "new":
            self.start()
        try:
            for frame in self.frames():
                if callback is not None:
                    callback(frame)
            return self.finish()
        except RunInterrupted:
            raise
        except KeyboardInterrupt:
            # Between the pieces the frames and finish() guard (a callback, the iterator's own lines).
            raise self._interrupted() from None

    def on_frame(self, callback: Callable[[Frame], None]) -> None:
        """Call ``callback(frame)`` for every frame :meth:`frames` yields from now on (before it yields it)."""
        self._callbacks.append(callback)

    def _interrupted(self) -> RunInterrupted:
        """Publish what was written after an interrupt that could not wait (the state is left as it was, unchecked),
        and say so."""
        count = self._writer.frame_count if self._writer is not None else 0
        published = f"{count} frame{'s' if count != 1 else ''} published in {self._usd_path}"
        try:
            self.close()
        except Exception as exc:  # the interrupt is what to report; the stage is then lost
            published = f"the stage could not be published ({' '.join(str(exc).split())})"
        last = f"; the last one written is {self.checkpoints[-1]}" if self.checkpoints else ""
        return RunInterrupted(f"{published}; no checkpoint written of the state it stopped in{last}")

    def _release(self, publish: bool) -> None:
        """Publish (or drop) the stage and close the progress bar."""
        _OPEN_RUNS.discard(self)
        if self._progress is not None:
            self._progress.close()
            self._progress = None
        writer, self._writer = self._writer, None
        if writer is not None:
            if publish:
                writer.close()
            else:
                writer.abort()

    def _abort(self) -> None:
        """Drop the partial stage after an error (the final path is left as it was)."""
        if self._phase in ("new", "running"):
            self._release(publish=False)
            self._phase = "closed"

    def _check_running(self, what: str) -> None:
        if self._phase == "new":
            raise RuntimeError(f"Run.{what}: the run has not started (call start(), or build it with warpdem.build)")
        if self._phase != "running":
            raise RuntimeError(f"Run.{what}: the run has ended ({self._phase}); restart it from a checkpoint")

    @contextlib.contextmanager
    def _clock(self, stepping: bool) -> Iterator[None]:
        """Count the wall time of a block (``stepping``: into the wall time) and the kernel compiling in it."""
        start, loads = time.perf_counter(), kernel_load_seconds()
        if stepping:
            self._stepping_since = start
        try:
            yield
        finally:
            compiling = kernel_load_seconds() - loads
            self._compile += compiling
            if stepping:
                self._wall += time.perf_counter() - start - compiling

    def _summarize(self) -> RunSummary:
        from .io.timeseries import fracture_values

        sim = self.sim
        wall = self._wall
        steps = sim.step_count - self._steps_start
        n = sim.particle_count
        tets = int(np.count_nonzero(sim.state.tet_active.numpy()[: int(sim.state.tet_count.numpy()[0])]))
        fracture = fracture_values(sim.model, sim.state)
        fragments = self._last_fragments if self._fragment_file is not None else None
        ejecta = self._ejecta if fragments is not None else np.zeros(0)
        end = self._energy_end
        return RunSummary(
            simulated_time=sim.time,
            steps=sim.step_count,
            wall_time=wall,
            particle_steps_per_second=n * steps / wall if wall > 0 else 0.0,
            particles=n,
            contacts=sim.contact_count(),
            bonds_broken=int(sim.state.bonds_broken_total.numpy()[0]),
            bonds_intact=sim.bond_count,
            energy_start=self._energy_start,
            energy_end=end,
            usd_path=self._usd_path,
            checkpoints=list(self.checkpoints),
            nodes=sim.node_count,
            tets=tets,
            tet_steps_per_second=tets * steps / wall if wall > 0 else 0.0,
            pvd_path=self._vtu.pvd_path if self._vtu is not None else None,
            frame=self._frame_index,
            interrupted_by=self.stop_signal if self._stop else None,
            series_path=self._series.csv_path,
            energy_in_play=self._in_play,
            energy_error=balance_error(self._energy_start, end, self._in_play),
            fracture=bool(fracture),
            **fracture,
            dissipated_cohesive=end.dissipated_cohesive,
            fragments_path=self._fragment_file.path if fragments is not None else None,
            fragment_count=fragments.count if fragments is not None else 0,
            fragment_largest=fragments.largest if fragments is not None else 0.0,
            fragment_mass=fragments.total_mass if fragments is not None else 0.0,
            ejecta_count=len(ejecta),
            ejecta_speed_max=float(ejecta.max(initial=0.0)),
            ejecta_speed_median=float(np.median(ejecta)) if len(ejecta) else 0.0,
            rigid=sim.rigid_report.format() if sim.rigid_report is not None else "",
            compile_time=self._compile,
        )

    def _say(self, line: str) -> None:
        if not self.options.quiet:
            print(line)

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

    def __enter__(self) -> Run:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *_: object) -> None:
        if exc_type is None and self._phase == "running":
            self.finish()
        else:
            self.close()


def _relative_to(path: Path, folder: Path) -> str:
    """``path`` relative to ``folder`` (both made absolute), or absolute where no relative path leads there."""
    try:
        return os.path.relpath(path.resolve(), folder.resolve())
    except ValueError:  # another drive (Windows)
        return str(path.resolve())


def _take_over(usd_path: Path) -> None:
    """Close (publishing its frames) any run of this process that still writes the stage at ``usd_path``: a restart
    from its checkpoint, or a new run, takes the stage over."""
    target = usd_path.resolve()
    for other in list(_OPEN_RUNS):
        if other._phase == "running" and other._usd_path == target:
            other.close()


def run_scene(scene: Scene, options: RunOptions | None = None) -> RunSummary:
    """Run a validated scene to its end time, writing USD frames and checkpoints (:class:`Run`). SIGINT and SIGTERM
    stop it within about a second, with a checkpoint of that state and the stage published (the summary's
    ``interrupted_by`` says which); a second one stops at once (:class:`RunInterrupted`).

    Raises:
        SceneError: the scene cannot be built (for example a particle file that cannot be read).
        CheckpointError: the restart file cannot be used.
        NothingToDo: the restart's checkpoint is at or past the end of the run.
        UnstableRunError: the run blew up (warpdem.stages.guard); the stage holds the good frames and is published, the
            checkpoints written before stay, none is written of the bad state.
        RunInterrupted: stopped at once by a second signal; the frames written are published.
    """
    options = options or RunOptions()
    run = Run(scene, options)
    with _StopRequest(run, options.quiet):
        return run.run()


def _check_stage_continues(
    usd_path: Path,
    fps: float,
    frame: int,
    sim: Simulation,
    quiet: bool,
    frame_time: float | None = None,
    frame_crc: int | None = None,
) -> None:
    """Before a restart writes anything: the stage it extends must hold the checkpoint's frame, at that frame's time
    and the checkpoint's frame rate and with its sphere centres (float32, as the stage stores them), so that the
    frames it keeps are this run's own. Without a stage, a new one starts at the restart frame.

    A checkpoint taken between two frames (a stop request) says where its last frame was: ``frame_time`` [s] and
    ``frame_crc`` (CRC-32 of its float32 sphere centres; None: no spheres, or an older checkpoint). One taken at a
    frame is compared with the state itself.

    Raises:
        SceneError: the stage at ``usd_path`` belongs to another run (nothing is written).
    """
    from .io.usd import stage_frame

    at_frame = frame_time is None or frame_time == sim.time
    if not usd_path.exists():
        if not quiet:
            first = frame if at_frame else frame + 1
            print(f"restart: {usd_path} is not there; writing a new stage whose timeline starts at frame {first}")
        return
    try:
        rate, held_time, held_points = stage_frame(usd_path, frame)
    except ValueError as exc:
        raise SceneError(f"--restart: cannot extend {exc}") from None
    expected_time = sim.time if frame_time is None else frame_time
    if at_frame:
        n = sim.particle_count
        points = sim.state.particle_q.numpy()[:n].astype(np.float32) if n else None
        same_points = (held_points is None) == (points is None) and (
            points is None or np.array_equal(held_points, points)
        )
    else:
        held_crc = zlib.crc32(np.ascontiguousarray(held_points).tobytes()) if held_points is not None else None
        same_points = frame_crc is None or held_crc == frame_crc
    if rate != fps or held_time != expected_time or not same_points:
        held = f"frame {frame} at t = {held_time:.9g} s" if held_time is not None else f"no frame {frame}"
        why = "" if same_points else ", other sphere positions"
        raise SceneError(
            f"--restart: {usd_path} is not the stage of this checkpoint's run (it holds {held}{why}, {rate:g} "
            f"frames/s; the checkpoint's frame {frame} is at t = {expected_time:.9g} s, {fps:g} frames/s); move it "
            "away or pass --usd"
        )


def summary_json(summary: RunSummary) -> str:
    """The summary as JSON (for scripts)."""
    d = dataclasses.asdict(summary)
    d["usd_path"] = str(summary.usd_path) if summary.usd_path else None
    d["checkpoints"] = [str(p) for p in summary.checkpoints]
    d["pvd_path"] = str(summary.pvd_path) if summary.pvd_path else None
    d["series_path"] = str(summary.series_path) if summary.series_path else None
    d["fragments_path"] = str(summary.fragments_path) if summary.fragments_path else None
    return json.dumps(d, indent=1)
