"""Test helper: ``python -m warpdem ARGS`` with one fault injected at a chosen point (tests/test_fault_injection.py).

Usage::

    python tests/fault_run.py EVENT INDEX PHASE FAULT COUNTS -- ARGS...

The fault fires at the INDEX-th call (counted from 1) of EVENT, just ``before`` or just ``after`` the call:

- ``frame``: a frame's outputs are written (``Run._write_frame``: energy books, VTU, series, fragments, stage);
- ``stage_save``: the USD stage is saved to its partial file (``UsdWriter._save``);
- ``checkpoint``: a checkpoint is written (``save_checkpoint``, as the runner calls it);
- ``replace``: a file under the output folder is moved over its final name (``os.replace``: a checkpoint, the
  published stage, the time series, the fragment record) — ``before`` is the file complete under its temporary name.

FAULT is ``kill`` (SIGKILL: nothing runs after it, as the OOM killer or a power loss), ``sigint2`` (two SIGINTs at
once: a user pressing Ctrl-C twice; the second lands inside the call) or ``sigint`` (one). INDEX 0 injects nothing.
COUNTS is a JSON file the wrapper writes at exit with how many times each event happened (the fault-free run's counts
tell a test where the faults can go).
"""

from __future__ import annotations

import atexit
import json
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any


def main() -> int:
    event, index, phase, fault, counts_path = sys.argv[1:6]
    assert sys.argv[6] == "--"
    argv = sys.argv[7:]
    out = Path(argv[argv.index("--out") + 1]).resolve()
    target, hit_at = event, int(index)
    counts = {"frame": 0, "stage_save": 0, "checkpoint": 0, "replace": 0}
    atexit.register(lambda: Path(counts_path).write_text(json.dumps(counts)))

    def fire() -> None:
        if fault == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        else:  # the handler of the first asks the run to stop; the second's raises KeyboardInterrupt here
            os.kill(os.getpid(), signal.SIGINT)
            if fault == "sigint2":
                os.kill(os.getpid(), signal.SIGINT)

    def hook(name: str, original: Callable[..., Any], counted: Callable[..., bool] = lambda *a: True) -> Callable:
        def hooked(*args: Any, **kwargs: Any) -> Any:
            if not counted(*args):
                return original(*args, **kwargs)
            counts[name] += 1
            hit = name == target and counts[name] == hit_at
            if hit and phase == "before":
                fire()
            result = original(*args, **kwargs)
            if hit and phase == "after":
                fire()
            return result

        return hooked

    import warpdem.runner.run as run_module
    from warpdem.io.usd import UsdWriter

    run_module.Run._write_frame = hook("frame", run_module.Run._write_frame)
    UsdWriter._save = hook("stage_save", UsdWriter._save)
    run_module.save_checkpoint = hook("checkpoint", run_module.save_checkpoint)
    os.replace = hook("replace", os.replace, lambda src, dst: Path(dst).resolve().is_relative_to(out))

    from warpdem.cli import main as warpdem_main

    return warpdem_main(argv)


if __name__ == "__main__":
    sys.exit(main())
