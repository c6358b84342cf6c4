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
import math
import os
import signal
import sys
import threading
import time
import weakref
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from .._version import __version__
from ..build.overlap import OVERLAP_TOLERANCE, initial_node_overlap
from ..build.scene_build import finalize_scene, scene_builder, start_as_spheres
from ..io.checkpoint import checkpoint_name
from ..io.output import PART_PALETTE, ramp_colors
from ..io.restart import restore_checkpoint, save_checkpoint
from ..parallel.comm import rank_device
from ..parallel.run import NotDecomposable, make_simulation, release_ranks
from ..scene import Scene, SceneError
from ..simulation import Simulation
from ..stages.energy import EnergyBalance, balance_error, books_from_nowhere
from ..stages.guard import UnstableRunError, likely_cause
from ..stages.loads import PressureAmplitudes, pressure_amplitudes, scale_pressure_loads
from ..stages.rigid import RigidReport
from ..stages.rigid_step import rigid_time_step
from .access import RunAccess
from .records import (
    Frame,
    FrameEnergy,
    NothingToDo,
    RunInterrupted,
    RunOptions,
    RunSummary,
    ejecta_speeds,
)
from .timing import (
    FrameGrid,
    _check_steps,
    end_time_note,
    frame_step,
    kernel_load_seconds,
    take_rigid_step,
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


def _output_error(where: str, path: Path, exc: BaseException) -> SceneError:
    """A one-line SceneError for an output file that cannot be written (name too long, no permission, disk full)."""
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else " ".join(str(exc).split())
    return SceneError(f"{where}: cannot write {path}: {reason}")


_OPEN_RUNS: weakref.WeakSet[Run] = weakref.WeakSet()
"""Runs of this process whose USD stage is still being written (a restart into the same stage takes it over)."""


@atexit.register
def _close_open_runs() -> None:
    """At the interpreter's exit, publish the stage of every run left open (a script that stopped iterating, or
    ended in an error of its own), so that the frames it wrote are not left in a partial file."""
    for run in list(_OPEN_RUNS):
        with contextlib.suppress(Exception):
            run.close()


class Run(RunAccess):
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
        scene: the scene, as given.
        options: the options, as given.
        sim: the stepper (warpdem.simulation.Simulation) once started.
        frame: the last frame written (None before the first, or right after a restart from between two frames).
        checkpoints: the checkpoints written, oldest first.
        summary: the summary, once finished.
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
        self._in_play = 0.0  # [J] the largest energy in play over the timeline's frames
        self._energy_start: EnergyBalance | None = None  # the books at the timeline's first frame
        self._energy_end: EnergyBalance | None = None  # the books at the last frame written (or where it stopped)
        self._compile = 0.0  # [s] kernel compiling and loading in this run's calls
        self._steps_per_piece = 1
        self._writer: Any = None
        self._usd_stride = 1  # the stride of the spheres the stage holds (UsdWriter.sphere_stride), kept past it
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

    def _check_node_overlap(self, sim: Simulation) -> None:
        """Mesh nodes pressed into other blocks at the start (warpdem.build.overlap.initial_node_overlap): a note, and
        a refusal beyond OVERLAP_TOLERANCE of a face's reach unless ``run.allow_initial_overlap``, as for spheres."""
        scene = self.scene
        overlap = initial_node_overlap(sim.model, sim.state)
        if not overlap.nodes:
            return
        if overlap.exceeds(OVERLAP_TOLERANCE) and not scene.run.allow_initial_overlap:
            raise SceneError(
                f"{scene.source}: run.allow_initial_overlap: {overlap.format()}; the first steps throw them apart. "
                "Either two bodies are meshed into each other (move one out), or, in a mesh of one geology, which puts "
                "no node inside another block, this is a false contact of the set-up where a joint ends on another "
                "(docs/physics.md, node–face springs): draw other joints ([mesh] seed) or move a joint set's offset. "
                "Or set allow_initial_overlap = true in [run] to start from this state anyway"
            )
        self._say(f"initial overlap: {overlap.format()}")

    def _start(self) -> None:
        scene, options = self.scene, self.options
        run = scene.run
        # "cuda" on several ranks: each rank its node's next GPU (warpdem.parallel.comm.rank_device).
        device_name = rank_device(options.device or run.device)
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
            substeps, dt = frame_step(model.dt, frame_period)
            model = dataclasses.replace(model, dt=dt)
        else:
            substeps = max(1, round(frame_period / model.dt))
            if abs(substeps * model.dt - frame_period) > 1e-9 * frame_period:
                # An explicit dt is kept, so the frames take a whole number of its steps: a changed frame rate.
                self._say(
                    f"run.output_rate {fps:g}/s is not a whole number of steps of dt = {model.dt:.6g} s: a frame "
                    f"every {substeps} steps ({substeps * model.dt:.6g} s), {1.0 / (substeps * model.dt):.6g} "
                    "frames/s"
                )

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
        self._out_dir = out_dir = Path(options.out_dir) if options.out_dir is not None else Path(scene.output.directory)
        usd_path = Path(options.usd) if options.usd is not None else out_dir / scene.output.usd
        if step >= last_step:
            held = _StageCheck(1.0 / frame_period, first_frame, state, attrs, model.particle_id)
            published = _publish_left_stage(usd_path, held)
            raise NothingToDo(
                f"nothing to do: the checkpoint is at t = {sim_time:.9g} s (frame {first_frame}), the run ends at "
                f"t = {grid.time + (last_step - grid.step) * model.dt:.9g} s (frame {total_frames}){published}"
            )
        # The note counts frames from step 0: on the first grid only.
        if options.frames is None and grid.step == 0:
            note = end_time_note(end_time, fps, model.dt, substeps, last_step)
            if note is not None:
                self._say(note)
        try:
            # One process, or under mpiexec rank 0's view of a run decomposed over the ranks (warpdem.parallel); the
            # other ranks follow it inside this call and leave the process from it.
            self.sim = sim = make_simulation(model, state, primed=primed, step=step, time=sim_time)
        except NotDecomposable as exc:
            raise SceneError(f"{scene.source}: {exc}") from None
        if not restart:
            # A new run converts its start_as_spheres region here, before frame 0; a restart's checkpoint holds them.
            start_as_spheres(scene, sim)
            if isinstance(sim, Simulation):  # a decomposed run's state lives on its ranks; one process checks it
                self._check_node_overlap(sim)
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

        output_stem = usd_path.stem  # VTU files are named like the stage; a restart continues both
        _take_over(usd_path)
        continue_partial = restart and _stage_to_continue(
            usd_path, _StageCheck(1.0 / frame_period, first_frame, sim.state, attrs, sim.model.particle_id)
        )
        checkpoint_every = (
            options.checkpoint_every if options.checkpoint_every is not None else scene.output.checkpoint_every
        )
        self._checkpoint_dir = out_dir / scene.output.checkpoint_dir
        self._frames_per_checkpoint = max(1, round(checkpoint_every / frame_period)) if checkpoint_every > 0 else 0

        from ..io.output import RockFrames, VtuSeries
        from ..io.timeseries import TimeSeries
        from ..io.usd import UsdWriter
        from ..stages.fragments import FragmentFile, can_fragment

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
                continue_partial=continue_partial,
                max_spheres=scene.output.usd_max_spheres,
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
        if "rigid_report" in attrs:
            sim.rigid_report = RigidReport(**attrs["rigid_report"])
        if "energy_start" in attrs:
            # The timeline's first frame (a checkpoint of an older format: the restart's first frame, as before).
            self._energy_start = EnergyBalance(**attrs["energy_start"])
            self._in_play = float(attrs.get("energy_in_play", 0.0))
            if self._series.energy_start is None:  # the series file was not found: the checkpoint's reference
                self._series.energy_start, self._series.in_play = self._energy_start, self._in_play
        if between:
            self._energy_end = sim.energy()
            self._energy_start = self._energy_start or self._energy_end
            self._in_play = max(self._in_play, self._energy_end.in_play)
        else:
            self._unyielded = self._write_frame()
            self._energy_start = self._energy_start or self._unyielded.energy.balance

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
        if self._reached_end() and self._phase == "running":
            self.finish()  # also when a stop request came during the last frame: the run is complete

    def _reached_end(self) -> bool:
        """Whether the run has written its last frame (the end it was asked to reach)."""
        return self._frame_index >= self._total_frames and self.sim.step_count >= self._last_step

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
            self._keep_written()
            raise

    def _check_energy(self, energy: EnergyBalance) -> None:
        """Stop the run (warpdem.stages.guard.UnstableRunError) when energy appeared from nowhere since its start
        (warpdem.stages.energy.books_from_nowhere): the books close for Verlet at any step, so an unstable step
        allowed by allow_unstable_dt shows here, not in the balance."""
        s0, sim = self._energy_start, self.sim
        if s0 is None:  # frame 0: the books start here
            return
        found = books_from_nowhere(s0, energy, sim.model.dt, sim.model.critical_dt)
        if found is not None:
            appeared, allowed = found
            problem = (
                f"{appeared:.4g} J of energy appeared from nowhere (kinetic {energy.kinetic:.4g} J; more than the "
                f"{allowed:.4g} J the work put in, the gravity released and a stable step's shadow term allow), "
                f"while the books close only through Verlet's shadow term {energy.shadow:.4g} J"
            )
            raise UnstableRunError(sim.time, sim.step_count, "the energy books", problem, likely_cause(sim.model))

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
        from ..io.output import damage_colors, sphere_damage, sphere_point_data
        from ..stages.fragments import fragment_colors, label_fragments

        sim, scene, frame = self.sim, self.scene, self._frame_index
        energy = sim.energy()
        self._check_energy(energy)
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
            colors = ramp_colors(speed, self._speed_scale)
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
        stored = (
            q
            if self._writer.sphere_stride == 1
            else q[sim.model.particle_id.numpy()[:n] % self._writer.sphere_stride == 0]
        )
        self._frame_crc = zlib.crc32(np.ascontiguousarray(stored, dtype=np.float32).tobytes()) if n else None
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
        # The books of the timeline's first frame and its largest energy in play: a restart's summary, series and
        # energy-from-nowhere check measure from the run's start, as the uninterrupted run's do.
        extra["energy_start"] = dataclasses.asdict(self._energy_start)
        extra["energy_in_play"] = self._in_play
        if sim.rigid_report is not None:
            extra["rigid_report"] = dataclasses.asdict(sim.rigid_report)
        if len(self._load_scales):
            names = sim.model.loads.pressure_names
            extra["load_scales"] = {name: float(s) for name, s in zip(names, self._load_scales, strict=True)}
        try:
            if self._writer is not None:
                # The stage on disk holds the checkpoint's frame before the checkpoint exists, so that a restart from
                # it always finds the frames it continues, whenever the process is killed.
                self._writer.flush(sync=True)
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
                if self._stop and self._reached_end() and not self.options.quiet:
                    print("the run finished: the stop came during its last frame (nothing to resume)", file=sys.stderr)
                default = self._checkpoint_dir / checkpoint_name(sim.step_count, self.scene.name)
                if not self.checkpoints or self.checkpoints[-1] != default:
                    self.checkpoint()
                self._release(publish=True)
        except KeyboardInterrupt:
            raise self._interrupted() from None
        except BaseException:
            self._keep_written()
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
            self._usd_stride = writer.sphere_stride
            if publish:
                writer.close()
            else:
                writer.abort()

    def _keep_written(self) -> None:
        """After an error while running: publish the complete frames written (a frame the error cut short is
        dropped), or drop the stage where even that fails; the error is what to report."""
        try:
            self.close()
        except Exception:
            self._abort()

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
        from ..io.timeseries import fracture_values

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
            usd_sphere_stride=self._writer.sphere_stride if self._writer is not None else self._usd_stride,
            checkpoints=list(self.checkpoints),
            nodes=sim.node_count,
            tets=tets,
            tet_steps_per_second=tets * steps / wall if wall > 0 else 0.0,
            pvd_path=self._vtu.pvd_path if self._vtu is not None else None,
            frame=self._frame_index,
            # A stop request during the last frame came too late to stop anything: the run is complete.
            interrupted_by=self.stop_signal if self._stop and not self._reached_end() else None,
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
            time_step=sim.model.dt,
            critical_dt=sim.model.critical_dt,
            critical_dt_source=sim.model.critical_dt_source,
            loads=self._load_records(),
            ranks=getattr(sim, "ranks", 1),
            halo_bytes_per_step=getattr(sim, "halo_bytes", 0),
            migrations=getattr(sim, "migrations", 0),
        )

    def _load_records(self) -> list[tuple[str, float, float]]:
        """Each pressure load's name, loaded area [m²] and delivered impulse [N s] (reads back)."""
        loads = self.sim.model.loads
        if loads is None or loads.pressure_loads is None:
            return []
        areas, impulses = loads.loaded_areas(), loads.impulses(self.sim.state.load_face_impulse.numpy())
        return [(n, float(a), float(j)) for n, a, j in zip(loads.pressure_names, areas, impulses, strict=True)]

    def _say(self, line: str) -> None:
        if not self.options.quiet:
            print(line)

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
    try:
        with _StopRequest(run, options.quiet):
            return run.run()
    finally:
        release_ranks(run.sim)


@dataclasses.dataclass(frozen=True)
class _StageCheck:
    """What a restart's checkpoint says the stage it continues must hold: its frame ``frame`` at the frame rate
    ``fps`` [frames/s], at the frame's simulated time and with its sphere centres (float32, as the stage stores them).

    A checkpoint taken at a frame is compared with its state itself; one taken between two frames (a stop request)
    says where its last frame was: ``frame_time`` [s] and ``frame_points_crc32`` (CRC-32 of its float32 sphere
    centres as the stage stores them; absent: no spheres, or an older checkpoint). A stage that holds a subsample
    of the spheres (``[output] usd_max_spheres``) is compared on the spheres it holds.

    Args:
        fps: the run's frame rate [frames/s].
        frame: the checkpoint's frame.
        state: the restored state.
        attrs: the checkpoint's attributes.
        particle_id: the restored model's sphere ids (a wp.array).
    """

    fps: float
    frame: int
    state: Any
    attrs: dict
    particle_id: Any

    @property
    def between(self) -> bool:
        """Whether the checkpoint was taken between two frames (its next frame is the first the restart writes)."""
        return float(self.attrs.get("frame_time", self.attrs["time"])) != float(self.attrs["time"])

    def mismatch(self, path: Path) -> str | None:
        """None when the stage at ``path`` holds the checkpoint's frame; otherwise what it holds instead."""
        from ..io.usd import stage_frame

        try:
            rate, held_time, held_points, stride = stage_frame(path, self.frame)
        except ValueError as exc:
            return " ".join(str(exc).split())
        frame_time = float(self.attrs.get("frame_time", self.attrs["time"]))
        if not self.between:
            n = int(self.state.particle_count.numpy()[0])
            points = self.state.particle_q.numpy()[:n].astype(np.float32) if n else None
            if points is not None and stride > 1:
                points = points[self.particle_id.numpy()[:n] % stride == 0]
            same_points = (held_points is None) == (points is None) and (
                points is None or np.array_equal(held_points, points)
            )
        else:
            crc = self.attrs.get("frame_points_crc32")
            held_crc = zlib.crc32(np.ascontiguousarray(held_points).tobytes()) if held_points is not None else None
            same_points = crc is None or held_crc == int(crc)
        if rate == self.fps and held_time == frame_time and same_points:
            return None
        held = f"frame {self.frame} at t = {held_time:.9g} s" if held_time is not None else f"no frame {self.frame}"
        why = "" if same_points else ", other sphere positions"
        return (
            f"it holds {held}{why}, {rate:g} frames/s; the checkpoint's frame {self.frame} is at t = {frame_time:.9g} "
            f"s, {self.fps:g} frames/s"
        )


def _warn(line: str) -> None:
    """A line about frames kept or lost: on stderr, also with --quiet (a user must not lose frames silently)."""
    print(line, file=sys.stderr)


def _stage_to_continue(usd_path: Path, check: _StageCheck) -> bool:
    """Before a restart writes anything, pick the stage it continues, so that the frames it keeps are this run's own:
    the partial file a killed or stopped run left (it holds every frame that run wrote, saved frame by frame; True),
    else the published stage (False). Without either, a new stage starts at the restart frame, said on stderr.

    Raises:
        SceneError: the published stage belongs to another run and no partial one continues this (nothing is
            written).
    """
    from ..io.usd import partial_stage_path

    partial = partial_stage_path(usd_path)
    if partial.exists():
        why = check.mismatch(partial)
        if why is None:
            _warn(f"restart: continuing {partial}, the stage a stopped run left (every frame it wrote is kept)")
            return True
        _warn(f"restart: {partial}, left by a stopped run, does not continue this checkpoint ({why}); it is replaced")
    if not usd_path.exists():
        _warn(
            f"restart: {usd_path} is not there; writing a new stage whose timeline starts at frame "
            f"{check.frame + check.between} (the frames before it are not in it)"
        )
        return False
    why = check.mismatch(usd_path)
    if why is not None:
        raise SceneError(
            f"--restart: {usd_path} is not the stage of this checkpoint's run ({why}); move it away or pass --usd"
        )
    return False


def _publish_left_stage(usd_path: Path, check: _StageCheck) -> str:
    """A restart with nothing left to run: publish the stage a run killed after its last frame left in the partial
    file (when it holds the checkpoint's frame). Returns what was done, for the message ("" when nothing)."""
    from ..io.usd import partial_stage_path

    partial = partial_stage_path(usd_path)
    if not partial.exists() or check.mismatch(partial) is not None:
        return ""
    os.replace(partial, usd_path)
    return f"; published {usd_path}, which the run had left complete in {partial.name}"
