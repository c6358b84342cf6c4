"""The generic skinned-list builder (warpdem.kernels.neighbors, warpdem.stages.neighbors) on a toy kind of list: points
listing the other points within a cut-off, owners switched off by a flag, and an integer tag per slot as history.

Oracles:
- lists: the O(N²) brute-force set per owner in the builder's float32 arithmetic, exact equality where the count
  fits K; every slot distinct; the count of an inactive owner is 0; nothing is written past an owner's filled slots
  nor for owners past the live count;
- overflow: with too few slots the count is still the brute-force count, ``needed`` is its maximum, and the filled
  slots are a subset of the brute-force set;
- history: after the points move and the list is rebuilt, a pair that was listed before keeps its tag and a new one
  gets the fresh value; the list without history, built in place, holds the same candidates in the same order;
- partial rebuild (``ListSpec.kept``): after the points move, an owner flagged kept holds its old row slot for slot and
  every other owner the brute-force set at the new positions; a kept function on a list with history is refused.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from warpdem.kernels.neighbors import ListSpec, make_list_kernels

from warpdem.stages.neighbors import SkinnedList, SlotArrays, make_struct

CAPACITY = 300  # owner slots
LIVE = 260  # live owners and candidates
CUTOFF = 0.12  # [m]
UNTOUCHED = -7  # sentinel of slots the builder must not write


@wp.struct
class PointInputs:
    q: wp.array(dtype=wp.vec3)
    on: wp.array(dtype=int)
    keep: wp.array(dtype=int)  # owners a partial rebuild keeps (test_partial_rebuild_keeps_flagged_rows only)
    cutoff: float


@wp.struct
class PointHistory:
    tag: wp.array(dtype=int)


@wp.func
def point_radius(inputs: PointInputs, i: int) -> float:
    return inputs.cutoff


@wp.func
def point_active(inputs: PointInputs, i: int) -> bool:
    return inputs.on[i] != 0


@wp.func
def point_accept(inputs: PointInputs, i: int, x: wp.vec3, j: int) -> bool:
    d = x - inputs.q[j]
    return j != i and wp.dot(d, d) < inputs.cutoff * inputs.cutoff


@wp.func
def copy_tag(src: PointHistory, src_slot: int, dst: PointHistory, dst_slot: int):
    dst.tag[dst_slot] = src.tag[src_slot]


@wp.func
def fresh_tag(inputs: PointInputs, history: PointHistory, slot: int, i: int, j: int):
    history.tag[slot] = -1 - j


WITH_HISTORY = make_list_kernels(
    ListSpec(PointInputs, point_radius, point_accept, point_active, PointHistory, copy_tag, fresh_tag)
)
WITHOUT_HISTORY = make_list_kernels(ListSpec(PointInputs, point_radius, point_accept, point_active))


@wp.func
def point_kept(inputs: PointInputs, i: int) -> bool:
    return inputs.keep[i] != 0


PARTIAL = make_list_kernels(ListSpec(PointInputs, point_radius, point_accept, point_active, kept=point_kept))


def brute_force(q: np.ndarray, on: np.ndarray) -> list[set[int]]:
    """Candidates of each live owner in the kernel's float32 arithmetic: d = x_i − x_j, d·d < cutoff²."""
    x = q[:LIVE].astype(np.float32)
    d = x[:, None, :] - x[None, :, :]
    d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
    near = (d2 < np.float32(CUTOFF) * np.float32(CUTOFF)) & ~np.eye(LIVE, dtype=bool)
    return [set(np.nonzero(row)[0].tolist()) if on[i] else set() for i, row in enumerate(near)]


class Points:
    """Random points, their grid and both kinds of list, with K slots per owner."""

    def __init__(self, device: str, k: int, seed: int = 5) -> None:
        rng = np.random.default_rng(seed)
        self.device, self.k = device, k
        self.q_host = rng.uniform(0.0, 1.0, (CAPACITY, 3)).astype(np.float32)
        self.on = (rng.uniform(size=CAPACITY) > 0.1).astype(np.int32)
        self.q = wp.array(self.q_host, dtype=wp.vec3, device=device)
        self.live = wp.array([LIVE], dtype=int, device=device)
        self.grid = wp.HashGrid(16, 16, 16, device=device)
        self.lists = {
            "history": self.empty_lists(with_tag=True),
            "in_place": self.empty_lists(with_tag=False),
        }
        self.builders = {
            "history": SkinnedList(WITH_HISTORY, CAPACITY, k, device, {"tag": int}),
            "in_place": SkinnedList(WITHOUT_HISTORY, CAPACITY, k, device),
        }
        self.needed = {name: wp.zeros(1, dtype=int, device=device) for name in self.lists}

    def empty_lists(self, with_tag: bool) -> SlotArrays:
        full = wp.full(CAPACITY * self.k, UNTOUCHED, dtype=int, device=self.device)
        history = make_struct(PointHistory, tag=wp.clone(full)) if with_tag else None
        return SlotArrays(wp.full(CAPACITY, UNTOUCHED, dtype=int, device=self.device), full, history)

    def rebuild(self) -> None:
        self.q.assign(self.q_host)
        self.grid.build(self.q, CUTOFF)
        inputs = make_struct(PointInputs, q=self.q, on=wp.array(self.on, dtype=int, device=self.device), cutoff=CUTOFF)
        for name, builder in self.builders.items():
            builder.rebuild(inputs, self.grid, self.live, self.q, self.live, self.lists[name], self.needed[name])

    def rows(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        lists = self.lists[name]
        return lists.count.numpy(), lists.index.numpy().reshape(CAPACITY, self.k)


@pytest.mark.parametrize("k", [64, 3], ids=["fits", "overflows"])
def test_lists_match_brute_force(device: str, k: int) -> None:
    points = Points(device, k)
    points.rebuild()
    expected = brute_force(points.q_host, points.on)
    largest = max(len(s) for s in expected)
    assert (largest <= k) == (k == 64), "the case does not exercise what its id says"
    for name in points.lists:
        count, index = points.rows(name)
        assert np.all(count[LIVE:] == UNTOUCHED) and np.all(index[LIVE:] == UNTOUCHED)
        assert int(points.needed[name].numpy()[0]) == largest
        for i in range(LIVE):
            assert count[i] == len(expected[i])
            filled = index[i, : min(count[i], k)].tolist()
            assert len(set(filled)) == len(filled)
            assert set(filled) <= expected[i]
            if count[i] <= k:
                assert set(filled) == expected[i]
            assert np.all(index[i, min(count[i], k) :] == UNTOUCHED)


def test_history_follows_pairs_across_rebuild(device: str) -> None:
    points = Points(device, 64)
    points.rebuild()
    count, index = points.rows("history")
    tags = points.lists["history"].history.tag
    np.testing.assert_array_equal(
        tags.numpy().reshape(CAPACITY, 64)[:LIVE][index[:LIVE] >= 0], -1 - index[:LIVE][index[:LIVE] >= 0]
    )
    # Tag every listed pair with its own code, move the points, rebuild.
    before = {(i, j) for i in range(LIVE) for j in index[i, : count[i]].tolist()}
    code = np.arange(CAPACITY)[:, None] * CAPACITY + index
    tags.assign(np.where(index >= 0, code, UNTOUCHED).reshape(-1).astype(np.int32))
    rng = np.random.default_rng(11)
    points.q_host += rng.normal(0.0, 0.02, points.q_host.shape).astype(np.float32)
    points.rebuild()
    count, index = points.rows("history")
    tag = tags.numpy().reshape(CAPACITY, 64)
    expected = brute_force(points.q_host, points.on)
    kept = fresh = 0
    for i in range(LIVE):
        assert set(index[i, : count[i]].tolist()) == expected[i]
        for s, j in enumerate(index[i, : count[i]].tolist()):
            if (i, j) in before:
                assert tag[i, s] == i * CAPACITY + j
                kept += 1
            else:
                assert tag[i, s] == -1 - j
                fresh += 1
    assert kept > 0 and fresh > 0, "the move neither kept nor made pairs: the carry-over was not exercised"
    # The list built in place holds the same candidates in the same order.
    count_in_place, index_in_place = points.rows("in_place")
    np.testing.assert_array_equal(count_in_place[:LIVE], count[:LIVE])
    for i in range(LIVE):
        np.testing.assert_array_equal(index_in_place[i, : count[i]], index[i, : count[i]])


def test_partial_rebuild_keeps_flagged_rows(device: str) -> None:
    k = 64
    rng = np.random.default_rng(3)
    q_host = rng.uniform(0.0, 1.0, (CAPACITY, 3)).astype(np.float32)
    on = (rng.uniform(size=CAPACITY) > 0.1).astype(np.int32)
    keep = (rng.uniform(size=CAPACITY) > 0.5).astype(np.int32)
    q = wp.array(q_host, dtype=wp.vec3, device=device)
    live = wp.array([LIVE], dtype=int, device=device)
    grid = wp.HashGrid(16, 16, 16, device=device)
    lists = SlotArrays(
        wp.full(CAPACITY, UNTOUCHED, dtype=int, device=device),
        wp.full(CAPACITY * k, UNTOUCHED, dtype=int, device=device),
    )
    needed = wp.zeros(1, dtype=int, device=device)
    builder = SkinnedList(PARTIAL, CAPACITY, k, device)

    def build(keep_flags: np.ndarray) -> None:
        grid.build(q, CUTOFF)
        inputs = make_struct(
            PointInputs,
            q=q,
            on=wp.array(on, dtype=int, device=device),
            keep=wp.array(keep_flags, dtype=int, device=device),
            cutoff=CUTOFF,
        )
        builder.rebuild(inputs, grid, live, q, live, lists, needed)

    build(np.zeros(CAPACITY, dtype=np.int32))  # a full build first
    count_before, index_before = lists.count.numpy(), lists.index.numpy().reshape(CAPACITY, k)
    q_host = q_host + rng.normal(0.0, 0.03, q_host.shape).astype(np.float32)
    q.assign(q_host)
    build(keep)
    count, index = lists.count.numpy(), lists.index.numpy().reshape(CAPACITY, k)
    expected = brute_force(q_host, on)
    moved = 0
    for i in range(LIVE):
        if keep[i]:
            assert count[i] == count_before[i]
            np.testing.assert_array_equal(index[i], index_before[i])
        else:
            assert count[i] == len(expected[i]) and set(index[i, : count[i]].tolist()) == expected[i]
        moved += set(index_before[i, : count_before[i]].tolist()) != expected[i]
    assert moved > 0, "the move changed no owner's set: the kept rows were not told apart from rebuilt ones"
    with pytest.raises(ValueError, match="partial rebuild"):
        make_list_kernels(
            ListSpec(
                PointInputs,
                point_radius,
                point_accept,
                point_active,
                PointHistory,
                copy_tag,
                fresh_tag,
                kept=point_kept,
            )
        )
