"""Running a scene: frames of captured steps, USD output, HDF5 checkpoints, restart, and the closing summary."""

from __future__ import annotations

import dataclasses
import json
import math
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

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
from .stages.rigid_step import rigid_step_after_switch, rigid_time_step


class NothingToDo(Exception):
    """A restart from a checkpoint at or past the end of the run: nothing is simulated and nothing is written."""


@dataclass
class RunOptions:
    """Command-line overrides of a scene's run and output settings (None = the scene's value).

    Attributes:
        device: Warp device. end_time: simulated end time [s]. frames: number of output frames after the first
        (overrides end_time). out_dir: output directory. usd: USD file path. checkpoint_every: checkpoint period
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
    interrupted_by: int | None = None
    """The signal (SIGINT, SIGTERM) that stopped the run at ``frame``, after its checkpoint and stage were written."""
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
    ejecta_speed_max: float = 0.0
    ejecta_speed_median: float = 0.0
    """Largest and median centre-of-mass speed of the fragments other than the largest at the last frame [m/s]
    (0 with one fragment)."""
    rigid: str = ""
    """What the switch to rigid blocks did in this run (warpdem.stages.rigid.RigidReport.format), empty without one."""

    def format(self) -> str:
        e0, e1 = self.energy_start, self.energy_end
        spheres = self.particles > 0
        lines = [f"simulated time   {self.simulated_time:.6g} s in {self.steps} steps"]
        if spheres:
            rate = self.particle_steps_per_second / 1e6
            lines += [
                f"wall time        {self.wall_time:.3f} s  ({rate:.3f} M particle-steps/s)",
                f"particles        {self.particles}   contacts {self.contacts}",
                f"bonds            {self.bonds_intact} intact, {self.bonds_broken} broken",
            ]
        else:
            lines.append(f"wall time        {self.wall_time:.3f} s")
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
            if self.fragment_count > 1:
                lines.append(
                    f"ejecta speed     max {self.ejecta_speed_max:.6g} m/s, median {self.ejecta_speed_median:.6g} m/s "
                    "(fragments but the largest)"
                )
        if self.series_path is not None:
            lines.append(f"time series      {self.series_path}")
        if self.fragments_path is not None:
            lines.append(f"fragment record  {self.fragments_path}")
        if self.checkpoints:
            lines.append(f"checkpoint       {self.checkpoints[-1]}")
        return "\n".join(lines)


def speed_colors(speed: np.ndarray, scale: float) -> np.ndarray:
    """Blue (at rest) → red (at ``scale`` m/s and above), shape (N, 3)."""
    t = np.clip(speed / max(scale, 1e-12), 0.0, 1.0)[:, None]
    return (1.0 - t) * np.array([0.15, 0.3, 0.85]) + t * np.array([0.95, 0.25, 0.1])


PART_PALETTE = np.array(
    [[0.55, 0.55, 0.6], [0.85, 0.45, 0.2], [0.2, 0.6, 0.85], [0.4, 0.75, 0.3], [0.8, 0.3, 0.5], [0.9, 0.8, 0.3]]
)


class _StopRequest:
    """SIGINT and SIGTERM during a run: the first is remembered and acted on at the next frame boundary (the frame's
    checkpoint is written and the stage published); a second stops at once (KeyboardInterrupt, nothing published).
    Handlers are installed only in the main thread, and the previous ones put back on exit."""

    def __init__(self, quiet: bool) -> None:
        self.signum: int | None = None
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
        if not self._quiet:
            print(
                f"\n{signal.Signals(signum).name}: stopping after this frame (again to stop at once, without a "
                "checkpoint)",
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


def run_scene(scene: Scene, options: RunOptions | None = None) -> RunSummary:
    """Run a validated scene to its end time, writing USD frames and checkpoints.

    Raises:
        SceneError: the scene cannot be built (for example a particle file that cannot be read).
        CheckpointError: the restart file cannot be used.
        UnstableRunError: the run blew up (warpdem.stages.guard); the stage holds the good frames and is published, the
            checkpoints written before stay, none is written of the bad state.
    """
    options = options or RunOptions()
    run = scene.run
    device_name = options.device or run.device
    try:
        device = wp.get_device(device_name)
    except (ValueError, RuntimeError) as exc:
        where = "--device" if options.device else f"{scene.source}: run.device"
        raise SceneError(f"{where}: device {device_name!r} is not available here ({exc})") from None
    builder = scene_builder(scene)
    if not options.quiet:
        for quality in builder.mesh_qualities:
            print(f"mesh: {quality.format()}")
    model, state = finalize_scene(scene, builder, device)
    if not options.quiet and builder.overlap is not None and builder.overlap.any:
        print(f"initial overlap: {builder.overlap.format()}")

    if scene.rigid.enabled and run.dt == "auto":
        # Rigid blocks from the start: no element modes, the contacts on the bodies set the step (warpdem.stages.rigid).
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

    step, sim_time, first_frame, primed, attrs = 0, 0.0, 0, False, {}
    grid = FrameGrid(substeps)
    if options.restart is not None:
        model, state, attrs = restore_checkpoint(Path(options.restart), model, state, scene.name)
        step, sim_time, first_frame, primed = int(attrs["step"]), float(attrs["time"]), int(attrs["frame"]), True
        # The frames end on the original run's grid, whatever the scene says now (its step is the checkpoint's).
        grid = FrameGrid.from_attrs(attrs, substeps)
        substeps = grid.substeps
    # The frame period stays that of the first grid (a later one divides it into other steps, to rounding).
    frame_period = float(attrs.get("frame_period", substeps * model.dt))

    # The run ends at last_step (a short last frame when that is not a multiple of the frame's steps).
    end_time = options.end_time if options.end_time is not None else run.end_time
    last_step = grid.last_step(end_time, options.frames, model.dt)
    total_frames = grid.frames(last_step)
    if step >= last_step:
        raise NothingToDo(
            f"nothing to do: the checkpoint is at t = {sim_time:.9g} s (frame {first_frame}), the run ends at "
            f"t = {grid.time + (last_step - grid.step) * model.dt:.9g} s (frame {total_frames})"
        )
    # The note counts frames from step 0: on the first grid only.
    note = (
        end_time_note(end_time, fps, model.dt, substeps, last_step)
        if options.frames is None and grid.step == 0
        else None
    )
    if note is not None and not options.quiet:
        print(note)
    sim = Simulation(model, state, primed=primed, step=step, time=sim_time)
    if options.restart is None:
        # A new run converts its start_as_spheres region here, before frame 0; a restart's checkpoint holds them.
        start_as_spheres(scene, sim)
    # With dt = "auto" a run takes the rigid blocks' step at the step of the switch (a switch from the start took it
    # above: the same step, no change); a restart knows from its checkpoint whether it did (one written at a run's
    # end by an earlier warpdem, which took it at the next frame boundary, may not have). An explicit dt is the
    # user's: it is kept across the switch.
    rigid_step_due = run.dt == "auto" and not bool(attrs.get("rigid_step_taken", primed and sim.rigid))
    pending_dt: float | None = None  # the grid's step, set at the frame boundary that ends a bridge (take_rigid_step)

    def adopt_rigid_step(frame: int) -> None:
        """Takes the rigid step now if it is due (the blocks are rigid), ``frame`` being the frame in progress: the
        one whose end on the grid is the next frame boundary at or after the current step."""
        nonlocal grid, last_step, total_frames, rigid_step_due, pending_dt
        end = grid.end_step(frame)
        if not (rigid_step_due and sim.rigid) or end > last_step:
            # A switch in the run's short last frame: the frames after it would leave the grid (k × period), so the
            # rigid step waits for a restart that continues the run, which takes it at its start (to the next
            # boundary on the grid); the checkpoint says it is not taken.
            return
        rigid_step_due = False
        change = take_rigid_step(sim, run.safety_factor, frame_period, grid, frame, end)
        if change is None:
            return
        runs_on = end != last_step  # a bridge to the run's last step ends the run: no step is added past it
        grid = change.grid
        if change.pending:
            pending_dt = change.dt
        last_step = grid.last_step(end_time, options.frames, change.dt) if runs_on else grid.step
        total_frames = grid.frames(last_step)

    def advance_frame(frame: int) -> None:
        """Runs the steps of frame ``frame`` (to its end on the grid, or the run's last step), taking the rigid step
        at a switch inside it, then the grid's step at its end after a bridge."""
        nonlocal pending_dt
        while True:
            end = min(grid.end_step(frame), last_step)
            if sim.step_count >= end:
                break
            rigid = sim.rigid
            sim.advance(end - sim.step_count, stop_at_switch=rigid_step_due)
            if sim.rigid and not rigid:
                adopt_rigid_step(frame)
        if pending_dt is not None:
            sim.set_time_step(pending_dt)
            pending_dt = None

    _check_steps(scene, float(substeps), options, total_frames - first_frame)

    out_dir = Path(options.out_dir) if options.out_dir is not None else Path(scene.output.directory)
    usd_path = Path(options.usd) if options.usd is not None else out_dir / scene.output.usd
    output_stem = usd_path.stem  # VTU files are named like the stage; a restart continues both
    if options.restart is not None:
        _check_stage_continues(usd_path, 1.0 / frame_period, first_frame, sim, options.quiet)
    checkpoint_every = (
        options.checkpoint_every if options.checkpoint_every is not None else scene.output.checkpoint_every
    )
    checkpoint_dir = out_dir / scene.output.checkpoint_dir
    frames_per_checkpoint = max(1, round(checkpoint_every / frame_period)) if checkpoint_every > 0 else 0

    from .io.output import RockFrames, VtuSeries, damage_colors, sphere_damage, sphere_point_data
    from .io.timeseries import TimeSeries, fracture_values
    from .io.usd import UsdWriter
    from .stages.fragments import FragmentFile, FragmentStats, can_fragment, fragment_colors, label_fragments

    # Colour scales are the largest values seen so far in the run: a restart continues them from its checkpoint.
    speed_scale = [float(attrs.get("speed_scale", 1e-12))]
    checkpoints: list[Path] = []
    mesh_vtu = scene.output.vtu and model.node_capacity > 0
    try:
        vtu = VtuSeries(out_dir, output_stem, first_frame) if mesh_vtu or scene.output.particles_vtu else None
        series = TimeSeries(out_dir, output_stem, first_frame)
        # Only a scene that can break apart gets a fragment record: elsewhere it would count the same pieces.
        fragment_file = FragmentFile(out_dir, output_stem, first_frame) if can_fragment(model) else None
    except OSError as exc:
        raise _output_error(f"{scene.source}: output.directory", out_dir, exc) from None
    rock = RockFrames(scene.output.mesh_color_by, vtu if mesh_vtu else None)
    rock.color_scale = float(attrs.get("rock_color_scale", 0.0))
    cohesive_as_curves = bool(getattr(scene.output, "cohesive_as_curves", False))
    by_fragment = fragment_file is not None or "fragment" in (scene.output.color_by, scene.output.mesh_color_by)
    last_fragments: list[FragmentStats] = []

    def checkpoint(frame: int) -> None:
        extra = {
            "scene": scene.name,
            **grid.attrs(),
            "frame_period": frame_period,
            "rigid_step_taken": not rigid_step_due,
            "seed": run.seed,
            "speed_scale": speed_scale[0],
            "rock_color_scale": rock.color_scale,
        }
        path = checkpoint_dir / checkpoint_name(sim.step_count, scene.name)
        try:
            checkpoints.append(save_checkpoint(path, sim, frame, extra))
        except OSError as exc:
            raise _output_error(f"{scene.source}: output.checkpoint_dir", path, exc) from None

    def write_frame(writer: UsdWriter, frame: int) -> EnergyBalance:
        """Writes every output of one frame; returns its energy balance (read back once, for the series and the
        summary)."""
        energy = sim.energy()
        rock.write_vtu(frame, sim.time, sim.model, sim.state)
        n = sim.particle_count
        q = sim.state.particle_q.numpy()[:n]
        v = sim.state.particle_qd.numpy()[:n]
        if scene.output.particles_vtu and n:
            vtu.write_particles(frame, sim.time, q, sphere_point_data(sim.model, sim.state))
        series.record(sim, frame, energy)
        fragments = label_fragments(sim.model, sim.state) if by_fragment else None
        if fragments is not None:
            last_fragments[:] = [fragments]
            if fragment_file is not None:
                try:
                    fragment_file.record(frame, sim.time, fragments)
                except OSError as exc:
                    raise _output_error(f"{scene.source}: output.directory", fragment_file.path, exc) from None
        speed = np.linalg.norm(v, axis=1)
        broken, damage = sphere_damage(sim.model, sim.state)
        if scene.output.color_by == "part":
            colors = PART_PALETTE[sim.model.particle_part.numpy()[:n] % len(PART_PALETTE)]
        elif scene.output.color_by == "damage":
            colors = damage_colors(damage)
        elif scene.output.color_by == "fragment":
            colors = fragment_colors(fragments.particle_label)
        else:
            speed_scale[0] = max(speed_scale[0], float(speed.max(initial=0.0)))
            colors = speed_colors(speed, speed_scale[0])
        bonds = None
        if scene.output.bonds_as_curves and sim.model.bond_capacity:
            nb = sim.bond_count
            intact = sim.state.bond_broken.numpy()[:nb] == 0
            bonds = np.stack([sim.state.bond_i.numpy()[:nb][intact], sim.state.bond_j.numpy()[:nb][intact]], axis=1)
        writer.write_frame(
            time=sim.time,
            positions=q,
            radii=sim.model.particle_radius.numpy()[:n],
            velocities=v,
            ids=sim.model.particle_id.numpy()[:n].astype(np.int64),
            colors=colors,
            bonds=bonds,
            surface=rock.surface(sim.model, sim.state, fragments.node_label if fragments is not None else None),
            bonds_broken=broken if sim.model.bond_capacity else None,
            cohesive=rock.cohesive_curves(sim.model, sim.state) if cohesive_as_curves else None,
            fragments=fragments.particle_label if fragments is not None else None,
        )
        return energy

    progress = None
    if not options.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        progress = tqdm(
            total=round(grid.time + (last_step - grid.step) * model.dt - sim_time, 9),
            unit="s",
            unit_scale=False,
            desc=scene.name,
            file=sys.stderr,
        )
    wall0 = time.perf_counter()
    steps0 = sim.step_count
    comment = f"warpdem {__version__}: {scene.name}"
    unstable: UnstableRunError | None = None
    frame = first_frame
    stop = _StopRequest(options.quiet)
    # A restart extends the stage of the run it continues (checked above); a new run replaces whatever was there.
    restart = options.restart is not None

    try:
        writer = UsdWriter(usd_path, 1.0 / frame_period, comment=comment, first_frame=first_frame, append=restart)
    except (OSError, RuntimeError) as exc:  # pxr reports a layer it cannot create as a RuntimeError
        if options.usd is not None or options.out_dir is not None:
            where = "--usd" if options.usd is not None else "--out"
        else:
            where = f"{scene.source}: output.directory / output.usd"
        raise _output_error(where, usd_path, exc) from None
    with stop, writer:
        # Blocks rigid from the start, or a restart that did not take the step (from a short last frame: to the end
        # of the next frame on the grid).
        adopt_rigid_step(frame if sim.step_count == grid.end_step(frame) else frame + 1)
        energy_start = energy_end = write_frame(writer, frame)
        in_play = energy_start.in_play
        while frame < total_frames and stop.signum is None:
            time_before = sim.time
            try:
                advance_frame(frame + 1)
            except UnstableRunError as exc:
                # The bad state is neither written nor checkpointed; the good frames are published below.
                unstable = exc
                break
            frame += 1
            energy_end = write_frame(writer, frame)
            in_play = max(in_play, energy_end.in_play)
            if progress is not None:
                progress.update(round(sim.time - time_before, 9))
            if frames_per_checkpoint and frame % frames_per_checkpoint == 0 and frame < total_frames:
                checkpoint(frame)
        wall = time.perf_counter() - wall0
        if unstable is None and (
            not checkpoints or checkpoints[-1] != checkpoint_dir / checkpoint_name(sim.step_count, scene.name)
        ):
            checkpoint(frame)
    if progress is not None:
        progress.close()
    if unstable is not None:
        last = f"last good checkpoint {checkpoints[-1]}" if checkpoints else "no checkpoint written"
        frames = f"{writer.frame_count} good frame{'s' if writer.frame_count != 1 else ''}"
        unstable.outputs = f"{frames} published in {writer.path}; {last}"
        raise unstable
    steps = sim.step_count - steps0
    n = sim.particle_count
    tets = int(np.count_nonzero(sim.state.tet_active.numpy()[: int(sim.state.tet_count.numpy()[0])]))
    fracture = fracture_values(sim.model, sim.state)
    fragments = last_fragments[0] if fragment_file is not None and last_fragments else None
    ejecta = fragments.ejecta_speeds if fragments is not None else np.zeros(0)
    return RunSummary(
        simulated_time=sim.time,
        steps=sim.step_count,
        wall_time=wall,
        particle_steps_per_second=n * steps / wall if wall > 0 else 0.0,
        particles=n,
        contacts=sim.contact_count(),
        bonds_broken=int(sim.state.bonds_broken_total.numpy()[0]),
        bonds_intact=sim.bond_count,
        energy_start=energy_start,
        energy_end=energy_end,
        usd_path=writer.path if hasattr(writer, "path") else usd_path,
        checkpoints=checkpoints,
        nodes=sim.node_count,
        tets=tets,
        tet_steps_per_second=tets * steps / wall if wall > 0 else 0.0,
        pvd_path=vtu.pvd_path if vtu is not None else None,
        frame=frame,
        interrupted_by=stop.signum,
        series_path=series.csv_path,
        energy_in_play=in_play,
        energy_error=balance_error(energy_start, energy_end, in_play),
        fracture=bool(fracture),
        **fracture,
        dissipated_cohesive=energy_end.dissipated_cohesive,
        fragments_path=fragment_file.path if fragments is not None else None,
        fragment_count=fragments.count if fragments is not None else 0,
        fragment_largest=fragments.largest if fragments is not None else 0.0,
        fragment_mass=fragments.total_mass if fragments is not None else 0.0,
        ejecta_speed_max=float(ejecta.max(initial=0.0)),
        ejecta_speed_median=float(np.median(ejecta)) if len(ejecta) else 0.0,
        rigid=sim.rigid_report.format() if sim.rigid_report is not None else "",
    )


def _check_stage_continues(usd_path: Path, fps: float, frame: int, sim: Simulation, quiet: bool) -> None:
    """Before a restart writes anything: the stage it extends must hold the checkpoint's frame, at the checkpoint's
    time and frame rate and with its sphere centres (float32, as the stage stores them), so that the frames it keeps
    are this run's own. Without a stage, a new one starts at the restart frame.

    Raises:
        SceneError: the stage at ``usd_path`` belongs to another run (nothing is written).
    """
    from .io.usd import stage_frame

    if not usd_path.exists():
        if not quiet:
            print(f"restart: {usd_path} is not there; writing a new stage whose timeline starts at frame {frame}")
        return
    try:
        rate, held_time, held_points = stage_frame(usd_path, frame)
    except ValueError as exc:
        raise SceneError(f"--restart: cannot extend {exc}") from None
    n = sim.particle_count
    points = sim.state.particle_q.numpy()[:n].astype(np.float32) if n else None
    same_points = (held_points is None) == (points is None) and (points is None or np.array_equal(held_points, points))
    if rate != fps or held_time != sim.time or not same_points:
        held = f"frame {frame} at t = {held_time:.9g} s" if held_time is not None else f"no frame {frame}"
        why = "" if same_points else ", other sphere positions"
        raise SceneError(
            f"--restart: {usd_path} is not the stage of this checkpoint's run (it holds {held}{why}, {rate:g} "
            f"frames/s; the checkpoint is frame {frame} at t = {sim.time:.9g} s, {fps:g} frames/s); move it away or "
            "pass --usd"
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
