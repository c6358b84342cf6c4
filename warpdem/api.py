"""The Python API: load or write a scene, edit it, build it, run it frame by frame, read and steer its state,
checkpoint and restart it, with the outputs ``python -m warpdem`` writes (the USD stage, VTU series, time series,
fragment record and checkpoints: both drive one :class:`~warpdem.runner.Run`).

Example::

    import warpdem as wd

    scene = wd.load_scene("scenes/boulder_impact.toml")  # or wd.parse_scene({...}), wd.Scene(...) in Python
    scene.run.end_time = 2e-3  # edit before building: build() validates the scene again
    sim = wd.build(scene, device="cpu")  # builds the model, writes frame 0 (out/boulder_impact.usdc, ...)
    for frame in sim.frames():  # steps to each output frame, writes it, yields it
        print(frame.time, frame.energy.error, frame.splits)
        x = sim.positions()  # sphere centres [m], a numpy copy
        if frame.index == 2:
            sim.checkpoint("run.h5")  # the run as it stands at frame 2
    print(sim.summary.format())  # the loop finished the run at its end: final checkpoint, stage published
    sim = wd.restart("run.h5")  # the same run again from frame 2: same scene, end, outputs
    sim.run()  # to the end: positions bit for bit those of the run above (on the CPU)

What the pieces do:

- :func:`build` validates the scene again (``scene.run.end_time = -1`` is an error naming ``run.end_time``), builds
  the model on the device, opens the outputs and writes frame 0. Options override the scene's run and output
  settings as the command line's do (``end_time``, ``frames``, ``out_dir``, ``usd``, ``checkpoint_every``).
- :meth:`Run.frames <warpdem.runner.Run.frames>` yields :class:`~warpdem.runner.Frame` objects: ``index`` (the USD
  time code), ``time`` [s], ``step``, ``energy`` (``energy.error`` the books' relative drift, ``energy.balance``
  every line in J), ``splits``, ``fragments`` and ``series`` (the time series row). At the end it finishes the run
  (final checkpoint, the stage published, ``sim.summary``); breaking out of the loop leaves the run where it is (a
  later ``frames()`` continues it; ``sim.finish()`` or ``with wd.build(...) as sim:`` ends it and publishes the stage).
  ``sim.on_frame(fn)`` calls ``fn(frame)`` for every frame; ``sim.run(callback)`` runs to the end.
- Reading the state: ``sim.positions()``, ``sim.velocities()``, ``sim.node_positions()``, ``sim.node_velocities()``
  are numpy copies of the live items. ``sim.array("node_q")`` is any state (or model) array by field name as numpy:
  a view of the run's own memory on the CPU (no copy; it changes as the run steps), a copy on a GPU.
  ``sim.warp_array(name)`` is the ``wp.array`` itself, for ``wp.to_torch`` or DLPack without a copy on any device.
  Both are sized by capacity, the live items first (field docstrings in :mod:`warpdem.model`).
- Steering: ``sim.set_load_scale(0, 0.5)`` halves the amplitude of pressure load ``[[loads]]`` 0 from the next step
  on; the energy books stay closed (the load kernels book the work of the forces they apply), and checkpoints keep
  the scales. ``sim.request_stop()`` ends ``frames()`` within about a second, between two pieces of steps.
- :func:`restart` continues a checkpoint's run: the checkpoint holds the scene (with the edits it was built with),
  the end of the run and where its outputs go, so nothing else is needed; the stage, series and VTU files continue
  on the same timeline. A run of this process still writing that stage is closed first (its frames published).

Everything is deterministic on the CPU: the same scene gives the same bits, however the run is cut into frames,
pieces, checkpoints and restarts.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from .io.checkpoint import CheckpointError, read_checkpoint_attrs
from .limits import MAX_STEPS
from .runner import Frame, FrameEnergy, NothingToDo, Run, RunInterrupted, RunOptions, RunSummary
from .scene import Scene, SceneError, load_scene, parse_scene

__all__ = [
    "CUDA_DRIVER_MISSING",
    "CheckpointError",
    "Frame",
    "FrameEnergy",
    "NothingToDo",
    "Run",
    "RunInterrupted",
    "RunSummary",
    "Scene",
    "SceneError",
    "build",
    "init_warp",
    "load_scene",
    "parse_scene",
    "restart",
    "validate",
]


CUDA_DRIVER_MISSING = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"
"""Start of the line Warp's native library prints on stderr when it finds no CUDA driver (a CPU-only machine)."""


def init_warp(quiet: bool = False) -> None:
    """Initialise Warp without its start-up chatter: no banner, and no warning that a CPU-only machine has no CUDA
    driver (the CPU is a supported device, not a fault; asking for ``--device cuda:0`` there still fails with a
    message). Everything else Warp writes to stderr while it starts is passed on, so real errors still show.

    Warp's native library prints the driver warning with C ``fprintf``, beyond Python's ``sys.stderr``, so the
    start is run with file descriptor 2 pointed at a temporary file that is replayed, less that one line, afterwards.

    Args:
        quiet: also drop Warp's info and warning messages after the start (log level ERROR): ``--quiet`` prints
            nothing but errors.
    """
    import warp as wp

    wp.config.log_level = logging.ERROR if quiet else logging.WARNING  # no init banner
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no file descriptor 2 (an embedding host): nothing to redirect, nothing to show either
        wp.init()
        return
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()  # returns at once when Warp has started already (and then prints nothing)
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        text = captured.read().decode(errors="replace")
    kept = [line for line in text.splitlines(keepends=True) if not line.startswith(CUDA_DRIVER_MISSING)]
    if kept:
        sys.stderr.write("".join(kept))
        sys.stderr.flush()


def _start_warp() -> None:
    """Start Warp as the command line does (:func:`init_warp`: no banner, no module-load lines; its warnings still
    show), unless this process has set Warp's log level itself (another than Warp's default, INFO): then its
    settings are its own."""
    import warp as wp

    if wp.config.log_level == logging.INFO:
        init_warp()


def validate(scene: Scene) -> Scene:
    """The scene validated again, as its values would be in a file: a scene edited in Python (pydantic does not
    check assignments) is held to every rule the loader applies, cross references and sizes included.

    Args:
        scene: a scene, possibly edited since it was loaded or made.

    Returns:
        A new, validated scene (the one given is left as it is).

    Raises:
        SceneError: one line per problem, each naming the key (``boulder_impact.toml: run.end_time: Input should be
            greater than 0 (got -1.0)``).
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"validate: expected a warpdem Scene, got {type(scene).__name__}")
    return parse_scene(scene.model_dump(warnings=False), source=scene.source)


def build(
    scene: Scene | str | os.PathLike,
    *,
    device: str | None = None,
    end_time: float | None = None,
    frames: int | None = None,
    out_dir: str | os.PathLike | None = None,
    usd: str | os.PathLike | None = None,
    checkpoint_every: float | None = None,
    quiet: bool = True,
    max_steps: int = MAX_STEPS,
) -> Run:
    """Validate a scene, build its model on a device, open its outputs and write frame 0.

    Args:
        scene: a scene (validated again: :func:`validate`), or the path of a TOML scene file.
        device: Warp device, ``"cpu"`` or ``"cuda:N"`` (None: the scene's ``run.device``).
        end_time: simulated end time [s] (None: the scene's ``run.end_time``).
        frames: number of frames after frame 0 (wins over ``end_time``).
        out_dir: output directory (None: the scene's ``output.directory``, relative to the working directory).
        usd: the USD stage's path (None: ``<out_dir>/<output.usd>``).
        checkpoint_every: checkpoint period [s], 0 = at the end only (None: the scene's).
        quiet: print nothing (mesh quality, notes, progress bar); False prints as the command line does.
        max_steps: most time steps the run may take (more is refused before the first step).

    Returns:
        The started run: iterate :meth:`Run.frames <warpdem.runner.Run.frames>`.

    Raises:
        SceneError: the scene is not valid, cannot be built, or cannot run as asked (one line per problem).
    """
    scene = validate(scene) if isinstance(scene, Scene) else load_scene(scene)
    _start_warp()
    return _started(
        scene,
        device=device,
        end_time=end_time,
        frames=frames,
        out_dir=out_dir,
        usd=usd,
        checkpoint_every=checkpoint_every,
        quiet=quiet,
        max_steps=max_steps,
    )


def restart(
    checkpoint: str | os.PathLike,
    scene: Scene | str | os.PathLike | None = None,
    *,
    device: str | None = None,
    end_time: float | None = None,
    frames: int | None = None,
    out_dir: str | os.PathLike | None = None,
    usd: str | os.PathLike | None = None,
    checkpoint_every: float | None = None,
    quiet: bool = True,
    max_steps: int = MAX_STEPS,
) -> Run:
    """Continue a run from one of its checkpoints (written by :meth:`Run.checkpoint <warpdem.runner.Run.checkpoint>`
    or the command line): the same scene, end and outputs as the run that wrote it, unless told otherwise. The
    next frames extend its USD stage and series on the same timeline (a checkpoint taken between two frames goes on
    to the next), and on the CPU they are bit for bit those of the run never stopped.

    Args:
        checkpoint: the HDF5 checkpoint.
        scene: the scene to continue with (None: the one the checkpoint holds); a scene object, or a TOML file.
        device: Warp device (None: the checkpoint's run's).
        end_time: simulated end time [s] (None, with ``frames`` None: where the checkpoint's run was to end).
        frames: number of frames to run to (overrides ``end_time``).
        out_dir: output folder (None: where the checkpoint's run wrote its outputs).
        usd: USD stage to extend (None: the checkpoint's run's).
        checkpoint_every: checkpoint period [s], as :func:`build`.
        quiet: no progress bar or summary, as :func:`build`.
        max_steps: most time steps the run may take, as :func:`build`.

    Returns:
        The started run. From a checkpoint taken at a frame, that frame is written again and is the first one
        ``frames()`` yields; from one taken between two frames (a stop request), the next frame is.

    Raises:
        CheckpointError: the file is not a usable checkpoint, or holds no scene and none is given.
        SceneError: the scene is not valid, or the stage to extend belongs to another run.
        NothingToDo: the checkpoint is at or past the end of the run.
    """
    path = Path(checkpoint)
    attrs = read_checkpoint_attrs(path)
    if scene is None:
        if "scene_json" not in attrs:
            raise CheckpointError(f"{path}: holds no scene (written by an older warpdem); pass the scene to restart")
        scene = parse_scene(json.loads(attrs["scene_json"]), source=str(attrs.get("scene_source", "<checkpoint>")))
    else:
        scene = validate(scene) if isinstance(scene, Scene) else load_scene(scene)
    _start_warp()
    held = attrs.get("run_options", {})
    if end_time is None and frames is None:
        end_time, frames = held.get("end_time"), held.get("frames")

    # The checkpoint holds its run's outputs relative to its own folder.
    out = out_dir if out_dir is not None else _beside(path, held.get("out_dir"))
    stage = usd if usd is not None else (_beside(path, held.get("usd")) if out_dir is None else None)
    return _started(
        scene,
        device=device if device is not None else held.get("device"),
        end_time=end_time,
        frames=frames,
        out_dir=out,
        usd=stage,
        checkpoint_every=checkpoint_every,
        restart=path,
        quiet=quiet,
        max_steps=max_steps,
    )


def _started(scene: Scene, out_dir: str | os.PathLike | None, usd: str | os.PathLike | None, **options: Any) -> Run:
    """A run of ``scene`` with these options (:class:`~warpdem.runner.RunOptions`; paths as given or None), started:
    its model built or restored and its first frame written."""
    run = Run(
        scene,
        RunOptions(
            out_dir=Path(out_dir) if out_dir is not None else None,
            usd=Path(usd) if usd is not None else None,
            **options,
        ),
    )
    run.start()
    return run


def _beside(checkpoint: Path, stored: str | None) -> Path | None:
    """A path a checkpoint holds (relative to its folder, or absolute), as a path here; None stays None."""
    return None if stored is None else checkpoint.parent / stored
