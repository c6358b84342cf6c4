"""Running a scene: frames of captured steps, USD output, HDF5 checkpoints, restart, and the closing summary.

:class:`Run` (warpdem.runner.run) is the one code path: :func:`run_scene` (the command line, warpdem.cli) and the
Python API (warpdem.api) both drive it. Its options, frames and summary are in warpdem.runner.records, when its steps
fall (the frame grid, the rigid step's change, compile time) in warpdem.runner.timing, and what a script reads and
steers between frames in warpdem.runner.access.
"""

from .access import RunAccess, UnknownArrayError
from .records import (
    Frame,
    FrameEnergy,
    NothingToDo,
    RunInterrupted,
    RunOptions,
    RunSummary,
    ejecta_speeds,
    summary_json,
)
from .run import Run, run_scene
from .timing import FrameGrid, RigidStepChange, end_step, end_time_note, kernel_load_seconds, take_rigid_step

__all__ = [
    "Frame",
    "FrameEnergy",
    "FrameGrid",
    "NothingToDo",
    "RigidStepChange",
    "Run",
    "RunAccess",
    "RunInterrupted",
    "RunOptions",
    "RunSummary",
    "UnknownArrayError",
    "ejecta_speeds",
    "end_step",
    "end_time_note",
    "kernel_load_seconds",
    "run_scene",
    "summary_json",
    "take_rigid_step",
]
