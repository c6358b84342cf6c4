"""The counted budget (issue 24): what a piece of host code asks of the device, counted.

A GPU pays for what the host asks of it, not only for the kernels: every launch is a driver call (a few µs), every
read-back waits for the device to finish its queue (a synchronisation), every allocation may synchronise too, and a
graph capture costs as much as the launches it records. None of that shows as time on the CPU, where a launch is a
function call and a read-back an alias, so the CPU cannot time it; it can count it. :func:`counted` counts, for the
code inside it, what would cost on a GPU:

- ``launches``: kernel launches made eagerly (``wp.launch``; a scan ``wp.utils.array_scan`` counts as one), not
  those recorded while a graph is being captured, which cost nothing when the graph is replayed;
- ``graph_launches``: replays of captured graphs (``wp.capture_launch``);
- ``captures``: graphs captured (``wp.capture_begin``);
- ``readbacks``: arrays read back to the host (``array.numpy()``, ``.list()``): each waits for the device;
- ``copies``: array copies (``wp.copy``, ``array.assign``): a device-to-device copy is a launch, a host-device
  copy a transfer (and, from the device, a wait);
- ``allocations`` and ``allocated_bytes``: device buffers allocated (on the CPU device: host buffers Warp
  allocates; NumPy's own arrays are not counted);
- ``syncs``: explicit synchronisations (``wp.synchronize*``).

The counting wraps Warp's public functions while the context is open (one context at a time; not thread-safe) and
puts them back on exit. It is the measuring instrument of the budget tests (tests/test_budget.py) and of the
closing notes' figures, never on in a run.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import warp as wp


@dataclasses.dataclass
class Budget:
    """What the host asked of the device inside a :func:`counted` block (counts; bytes in ``allocated_bytes``)."""

    launches: int = 0
    graph_launches: int = 0
    captures: int = 0
    readbacks: int = 0
    copies: int = 0
    allocations: int = 0
    allocated_bytes: int = 0
    syncs: int = 0

    def __sub__(self, other: Budget) -> Budget:
        return Budget(*(a - b for a, b in zip(dataclasses.astuple(self), dataclasses.astuple(other), strict=True)))

    def copy(self) -> Budget:
        return dataclasses.replace(self)

    def line(self) -> str:
        """One line for a report: every count by name."""
        return ", ".join(f"{f.name} {getattr(self, f.name)}" for f in dataclasses.fields(self))


_ACTIVE: list[Budget] = []


def _allocators() -> list[type]:
    """Warp's allocator classes (each has ``allocate(size_in_bytes)``)."""
    from warp._src import context

    return [
        getattr(context, name)
        for name in dir(context)
        if name.endswith("Allocator")
        and isinstance(getattr(context, name), type)
        and callable(getattr(getattr(context, name), "allocate", None))
    ]


def _capturing() -> bool:
    """Whether any device is recording a graph now (a launch then costs nothing until the graph is replayed)."""
    try:
        return any(d.is_capturing for d in wp.get_cuda_devices()) or wp.get_device("cpu").is_capturing
    except Exception:  # a build of Warp without the attribute: count every launch
        return False


@contextmanager
def counted() -> Iterator[Budget]:
    """Count what the code inside asks of the device (module docstring). Yields the :class:`Budget` it fills in.

    Raises:
        RuntimeError: a :func:`counted` block is open already (the wrappers are global).
    """
    if _ACTIVE:
        raise RuntimeError("counted(): a counted block is open already; counting does not nest")
    from warp._src import types as wtypes

    budget = Budget()
    _ACTIVE.append(budget)
    saved: list[tuple[Any, str, Any]] = []

    def wrap(owner: Any, name: str, count: Callable[..., None]) -> None:
        original = getattr(owner, name)

        @functools.wraps(original)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            count(*args, **kwargs)
            return original(*args, **kwargs)

        saved.append((owner, name, original))
        setattr(owner, name, wrapper)

    def launch(*_a: Any, **_k: Any) -> None:
        if not _capturing():
            budget.launches += 1

    def bump(field: str) -> Callable[..., None]:
        def count(*_a: Any, **_k: Any) -> None:
            setattr(budget, field, getattr(budget, field) + 1)

        return count

    def allocate(_self: Any, size_in_bytes: int, *_a: Any, **_k: Any) -> None:
        budget.allocations += 1
        budget.allocated_bytes += int(size_in_bytes)

    try:
        wrap(wp, "launch", launch)
        wrap(wp.utils, "array_scan", launch)
        wrap(wp, "capture_launch", bump("graph_launches"))
        wrap(wp, "capture_begin", bump("captures"))
        wrap(wtypes.array, "numpy", bump("readbacks"))
        wrap(wtypes.array, "list", bump("readbacks"))
        wrap(wp, "copy", bump("copies"))
        for name in ("synchronize", "synchronize_device", "synchronize_stream"):
            wrap(wp, name, bump("syncs"))
        for cls in _allocators():
            wrap(cls, "allocate", allocate)
        yield budget
    finally:
        for owner, name, original in reversed(saved):
            setattr(owner, name, original)
        _ACTIVE.clear()
