"""PLACEHOLDER (branch fcore only) until the cohesive helper's warpdem.cohesive merges: the API of
FRACTURE_CONTRACT.md with a constant force f_c along cohesive_dir on intact elements, so the split pass can be
exercised. Replaced wholesale by `git merge fcohesive`."""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from .compaction import Compactor
from .model import COHESIVE_FIELDS, Model, State


@wp.kernel
def _placeholder_cohesive_kernel(
    count: wp.array(dtype=int),
    a: wp.array(dtype=int),
    b: wp.array(dtype=int),
    fc: wp.array(dtype=float),
    direction: wp.array(dtype=wp.vec3),
    broken: wp.array(dtype=int),
    node_f: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    if i >= count[0] or broken[i] != 0:
        return
    f = fc[i] * direction[i]
    wp.atomic_add(node_f, a[i], f)
    wp.atomic_sub(node_f, b[i], f)


def eval_cohesive(model: Model, state: State, dt: float | None = None, track_energy: bool = True) -> None:
    if model.cohesive_capacity == 0:
        return
    s = state
    wp.launch(
        _placeholder_cohesive_kernel,
        dim=model.cohesive_capacity,
        inputs=[s.cohesive_count, s.cohesive_a, s.cohesive_b, s.cohesive_fc, s.cohesive_dir, s.cohesive_broken],
        outputs=[s.node_f],
        device=model.device,
    )


def cohesive_energy(model: Model, state: State) -> tuple[float, float]:
    n = int(state.node_count.numpy()[0])
    return 0.0, float(state.node_energy_cohesive.numpy()[:n].sum())


def compact_cohesive(model: Model, state: State, compactor: Compactor) -> int:
    s = state
    compactor.plan(s.cohesive_count, s.cohesive_broken)
    compactor.scatter(s.cohesive_count, [getattr(s, f) for f in COHESIVE_FIELDS])
    compactor.finish(s.cohesive_count)
    return int(s.cohesive_count.numpy()[0])


def regrow_cohesive(model: Model, state: State, capacity: int) -> tuple[Model, State]:
    fields = {}
    for name in COHESIVE_FIELDS:
        old = getattr(state, name)
        host = old.numpy()
        pad = np.zeros((capacity, *host.shape[1:]), dtype=host.dtype)
        pad[: len(host)] = host
        fields[name] = wp.array(pad, dtype=old.dtype, device=old.device)
    return dataclasses.replace(model, cohesive_capacity=capacity), dataclasses.replace(state, **fields)
