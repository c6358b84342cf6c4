"""What the device can represent and how large a run may grow: the bounds that scene validation and the set-up check
before anything is allocated or meshed.

- Numbers: the device computes in float32 (largest 3.4e38, smallest normal 1.2e-38). A scene number must be 0 or
  lie in [:data:`F32_MIN`, :data:`F32_MAX`] in magnitude; the margin of eight decades on each side leaves room for the
  products the physics forms from them (a mass is ρ r³, a stiffness E r), which the builder checks again once formed.
- Sizes: sphere, node and tet counts, neighbour slots and time steps are estimated from the scene before any array is
  allocated or any mesh is made, and refused above :data:`MAX_ELEMENTS` (int32 indices) or above the memory of this
  machine (:func:`memory_budget`) with the estimate in the message.

Pure host code; no warp import.
"""

from __future__ import annotations

import math
import os

__all__ = [
    "BYTES_PER_NEIGHBOR_SLOT",
    "BYTES_PER_NODE",
    "BYTES_PER_SPHERE",
    "BYTES_PER_TET",
    "F32_MAX",
    "F32_MIN",
    "MAX_ELEMENTS",
    "MAX_STEPS",
    "MAX_SUBSTEPS",
    "format_bytes",
    "memory_budget",
    "size_problem",
]

F32_MAX = 1e30
"""Largest magnitude of a scene number (float32 overflows at 3.4e38)."""

F32_MIN = 1e-30
"""Smallest nonzero magnitude of a scene number (float32 numbers below 1.2e-38 lose precision, then flush to 0)."""

MAX_ELEMENTS = 2**31 - 1
"""Most spheres, nodes, tets or neighbour slots of one run: the kernels index them with int32."""

MAX_STEPS = 10**9
"""Most time steps of one run by default (``--max-steps``): even at a microsecond a step, 10⁹ steps take 17 minutes,
and a step count far beyond it means a time step or end time that was not meant."""

MAX_SUBSTEPS = 64
"""Most sub-steps a step of the cohesive elements' nodes (``[fracture] cohesive_substeps``; warpdem.stages.substep):
β up to 4096 resolved, two launches a sub-step."""

# Memory of one item, host and device together, for the estimates. Measured on the shipped scenes by summing the
# Model and State arrays: 144-156 B a sphere slot, 36 B a neighbour slot, 136 B a tet and 176 B a node slot; the
# figures below add the scratch neighbour list (a second 36 B), the host arrays the build holds meanwhile (float64
# positions, radii, reference geometry) and what Gmsh holds while meshing, rounded up.
BYTES_PER_SPHERE = 400
"""Bytes per sphere slot: positions, velocities, forces, history, energy books, the build's host arrays."""

BYTES_PER_NEIGHBOR_SLOT = 80
"""Bytes per neighbour slot (candidate index, shear history, bond index; list and scratch list)."""

BYTES_PER_NODE = 300
"""Bytes per FEM node slot: reference position, displacement, velocity, force, mass, contact lists."""

BYTES_PER_TET = 400
"""Bytes per tet slot: nodes, reference inverse, stress, volume, material, topology and face lists, and what Gmsh or
the Kuhn mesher holds while meshing."""


def memory_budget() -> int:
    """Bytes a run may use: the physical memory of this machine (64 GiB where the platform does not say)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return 64 * 2**30


def format_bytes(n: float) -> str:
    """``n`` bytes as a short text with a binary unit (``1.5 GB``)."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB", "EB"):
        if abs(n) < 1024.0 or unit == "EB":
            return f"{n:.3g} {unit}"
        n /= 1024.0
    return f"{n:.3g} EB"  # pragma: no cover - the loop returns


def size_problem(counts: dict[str, float], bytes_each: dict[str, int], budget: int | None = None) -> str | None:
    """Why a run of this size cannot be allocated, or None when it fits.

    Args:
        counts: estimated number of each kind of item (``"spheres"``, ``"tets"``, ...); may be inf.
        bytes_each: bytes per item of each kind in ``counts``.
        budget: bytes allowed; default :func:`memory_budget`.

    Returns:
        ``"would need 3.1e+12 spheres (~1.2 PB); the limit is 2147483647 of each and 125 GB of memory"`` or None.
    """
    budget = memory_budget() if budget is None else budget
    total = sum(counts[k] * bytes_each[k] for k in counts)
    too_many = [k for k, n in counts.items() if not n <= MAX_ELEMENTS]
    if not too_many and total <= budget:
        return None
    listed = ", ".join(f"{_count(n)} {k}" for k, n in counts.items() if n > 0)
    return (
        f"would need {listed} (~{format_bytes(total)}); the limit is {MAX_ELEMENTS} of each "
        f"and {format_bytes(budget)} of memory"
    )


def _count(n: float) -> str:
    if not math.isfinite(n):
        return "infinitely many"
    return f"{n:.3g}" if n >= 1e6 else str(round(n))
