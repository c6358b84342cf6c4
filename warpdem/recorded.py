"""Host code recorded once and replayed (issue 24): a between-steps stage made of launches only (a whole split pass,
the surface rebuilt after it, the forces re-evaluated, the chunk's guard and status) pays Warp's Python
launch path (~30 µs a launch on the CPU, a driver call each on a GPU) every time it runs eagerly. :class:`Recorded`
records it into a graph (a CUDA graph on GPUs, Warp's recorded graph on the CPU) the second time it runs with the
same arrays and replays it from then on; the first run, eager, compiles the kernels and builds what the stage caches
(word tables, scratch), so that nothing is allocated inside a recording.

What a recording depends on is its *key*: the address and shape of every array of the model, its loads and the state
(:func:`arrays_key`), and whatever else the caller's launches bake in (flags, the stage objects whose scratch they
read). A growth or a rebuild that reallocates an array changes the key, and the next run is eager again. A replay
gives the bits the eager launches give: the same launches in the same order (tests/test_budget.py).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import warp as wp

_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def _field_names(obj: object) -> tuple[str, ...]:
    """The dataclass field names of ``obj``'s class, looked up once per class."""
    cls = type(obj)
    names = _FIELD_NAMES.get(cls)
    if names is None:
        names = _FIELD_NAMES[cls] = tuple(f.name for f in dataclasses.fields(obj))
    return names


def arrays_key(*objs: Any) -> tuple:
    """What launches over these dataclasses (a Model, its LoadModel, a State) bake into a recording: the address and
    shape of every array field, the scalars (capacities, counts of walls and slots, the extents launches take as
    arguments), and the face sets of a dict field (the pressure loads), in field order. ~80 µs for a Model and State."""
    key: list[Any] = []
    for obj in objs:
        if obj is None or not dataclasses.is_dataclass(obj):
            key.append(None)
            continue
        for name in _field_names(obj):
            a = getattr(obj, name)
            if isinstance(a, wp.array):
                key.append((a.ptr, a.shape))
            elif isinstance(a, (int, float, str)):
                key.append(a)
            elif isinstance(a, np.ndarray) and a.size <= 16:  # a small vector launches take as values (gravity)
                key.append(tuple(a.ravel().tolist()))
            elif isinstance(a, tuple) and all(isinstance(x, (int, float)) for x in a):
                key.append(a)
            elif isinstance(a, dict):
                key.extend(
                    (k, v.nodes.ptr if isinstance(getattr(v, "nodes", None), wp.array) else None) for k, v in a.items()
                )
    return tuple(key)


class Recorded:
    """One stage's recording: run eagerly, recorded the second time the same key comes, replayed after.

    Args:
        device: Warp device of the stage's arrays.
        use_graph: False: always run eagerly (as ``Simulation(use_graph=False)``).
    """

    def __init__(self, device: wp.context.Device, use_graph: bool = True) -> None:
        self.device = device
        self.use_graph = use_graph
        self.key: tuple | None = None
        self.graph: Any = None
        self._retained: tuple = ()

    def run(self, key: tuple, body: Callable[[], None], retain: Sequence[object] = ()) -> bool:
        """Run ``body`` (launches only; its ``wp.capture_if`` / ``capture_while`` read their conditions back when it
        runs eagerly), or replay its recording. ``retain``: objects whose device memory the recording reads but the
        key does not hold (word tables of a cache that may drop them), kept alive while the recording is. Returns
        whether it replayed."""
        if self.use_graph and key == self.key:
            if self.graph is None:
                try:
                    with wp.ScopedCapture(device=self.device) as capture:
                        body()
                except (RuntimeError, NotImplementedError) as exc:
                    # Conditional graph nodes (wp.capture_while / capture_if) need CUDA 12.4+; without them the stage
                    # runs launch by launch.
                    warnings.warn(f"graph capture unavailable ({exc}); running without a graph", stacklevel=3)
                    self.use_graph = False
                else:
                    self.graph, self._retained = capture.graph, tuple(retain)
            if self.graph is not None:
                wp.capture_launch(self.graph)
                return True
        elif key != self.key:
            self.key, self.graph, self._retained = key, None, ()
        body()
        return False
