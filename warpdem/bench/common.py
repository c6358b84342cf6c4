"""What the benchmarks share: the granite they build, the timing of a device call and the JSON they write."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    import warp as wp


T = TypeVar("T")


GRANITE = {"density": 2700.0, "youngs_modulus": 50.0e9, "poisson_ratio": 0.25}
"""The rock of the fracture benchmark (the tetrahedra benchmark's granite): ρ [kg/m³], E [Pa], ν [-]."""


def timed(device: str | wp.context.Device, fn: Callable[[], T]) -> tuple[float, T]:
    """Wall time [s] of ``fn()`` with the device synchronised before and after (launches are asynchronous), and what
    it returned."""
    import warp as wp

    wp.synchronize_device(device)
    t0 = time.perf_counter()
    out = fn()
    wp.synchronize_device(device)
    return time.perf_counter() - t0, out


def write_json(path: Path | None, data: dict) -> None:
    """Write ``data`` as JSON to ``path`` (nothing when None) through a temporary name, so a reader never sees a
    half-written file."""
    if path is None:
        return
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)


# ----------------------------------------------------------------------------------------------------------------
# Conversion
