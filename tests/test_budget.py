"""The counted budget (issue 24; warpdem.budget) and the fused passes that keep it (warpdem.fused).

Oracles:
- invariants of a run that stays on the device, counted (warpdem.budget.counted wraps Warp's launch, read-back, copy,
  capture and allocation calls): a step replays captured graphs and asks nothing else of the host (0 eager launches,
  0 read-backs, 0 copies, 0 allocations); what the work between two chunks of steps asks is the same for a block of
  1 296 tets as for one of 6 000 (a fixed number of read-backs, whatever the body count); a split pass that splits
  nothing allocates nothing and captures nothing; a replicate pass is one launch whatever the number of arrays;
- brute-force references, exact (the passes only move bits): ``wp.copy`` array by array for the fused State copy,
  NumPy's append for the fused replicate on every field type (int32, float32, vec3, mat33, quat, float64, rows).
"""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
import warp as wp

from warpdem import fused
from warpdem.bench.fracture import cracking_block
from warpdem.budget import Budget, counted
from warpdem.simulation import Simulation
from warpdem.stages.compaction import Compactor
from warpdem.stages.energy import CONTACT, SHADOW

# Per-chunk read-backs (simulation.Simulation._advance_chunk and the pass after it) on a block with nodal fracture
# and FEM contact: the chunk status (warpdem.stages.status: the lists' counts, the clock, the guard's report, the broken
# bonds and cohesive elements) and the split pass's candidate count.
CHUNK_READBACKS = 2


def test_counting_counts_and_restores(device):
    """Each wrapped call is counted once, and Warp's functions are back as they were after the block."""
    launch, numpy_ = wp.launch, wp.array.numpy
    a = wp.zeros(4, dtype=float, device=device)
    with counted() as budget:
        b = wp.zeros(8, dtype=wp.vec3, device=device)
        wp.copy(a, wp.full(4, 2.0, dtype=float, device=device))
        a.numpy()
        with pytest.raises(RuntimeError, match="does not nest"), counted():
            pass
    assert wp.launch is launch and wp.array.numpy is numpy_
    assert budget.copies == 1 and budget.readbacks == 1
    assert budget.allocations == 2 and budget.allocated_bytes >= b.capacity + 4 * 4
    assert budget - budget == Budget()


@pytest.mark.parametrize("cells", [6, 10])
def test_steps_replay_graphs_and_ask_nothing_else(device, cells):
    sim = cracking_block(cells, device, steps=200, interval=1)
    sim.advance(2)  # compile and capture
    with counted() as budget:
        sim._run(5)
    # head, four bodies, tail: one graph replay each.
    assert budget == Budget(graph_launches=6)


def chunk_budget(cells: int, device: str) -> Budget:
    """What one step with its between-steps work (a split pass that finds nothing) asks of the device, on the
    cracking block of ``cells``³ cells, before anything splits."""
    sim = cracking_block(cells, device, steps=200, interval=1)
    sim.advance(2)
    sim.advance(1)  # the first snapshot copied into, not cloned: builds its word tables
    with counted() as budget:
        sim.advance(1)
    assert int(sim.state.node_splits_total.numpy()[0]) == 0  # a quarter of the run before the first split
    return budget


def test_work_between_chunks_does_not_grow_with_the_body_count(device):
    small, large = chunk_budget(6, device), chunk_budget(10, device)  # 1 296 and 6 000 tets
    assert small == large
    assert small.readbacks == CHUNK_READBACKS
    # The snapshot a redo starts from is one fused copy (warpdem.fused.copy_arrays), not one per State array.
    assert small.copies == 0 and small.allocations == 0 and small.captures == 0 and small.syncs == 0
    # The step (head and tail), the chunk's guard and status gathered and the split pass (recordings,
    # warpdem.recorded), replayed; two launches: the redo snapshot and the tet stresses.
    assert (small.graph_launches, small.launches) == (4, 2)


def test_a_pass_that_finds_nothing_allocates_and_captures_nothing(device):
    sim = cracking_block(6, device, steps=200, interval=1)
    sim.advance(2)
    with counted() as budget:
        report = sim.fracture_pass()
    assert report.splits == 0
    assert budget.allocations == 0 and budget.captures == 0 and budget.graph_launches == 0


FIELD_TYPES = (int, float, wp.vec3, wp.mat33, wp.quat, wp.float64)


def random_field(rng: np.random.Generator, dtype: type, entries: int, device: str) -> wp.array:
    """An array of ``entries`` of ``dtype`` holding random bits (any pattern: the passes move bits, not values)."""
    h = wp.zeros(entries, dtype=dtype, device="cpu").numpy()
    h.view(np.uint8)[...] = rng.integers(0, 256, size=h.view(np.uint8).shape, dtype=np.uint8)
    return wp.array(h, dtype=dtype, device=device)


@pytest.mark.parametrize("per_row", [1, 3])
def test_replicate_rows_is_one_launch_and_numpys_append(device, per_row):
    rng = np.random.default_rng(7)
    capacity, count = 40, 23
    copies = np.where(rng.random(capacity) < 0.3, rng.integers(1, 3, capacity), 0).astype(np.int32)
    copies[count:] = 0
    compactor = Compactor(capacity, device)
    w_count = wp.array([count], dtype=int, device=device)
    compactor.plan_append(w_count, wp.array(copies, dtype=int, device=device))
    arrays = [random_field(rng, t, capacity * per_row, device) for t in FIELD_TYPES]
    host = [a.numpy().copy() for a in arrays]
    rows = [(a, per_row) for a in arrays]
    compactor.replicate_rows(w_count, rows)  # builds the arrays' word table (kept for the next pass)
    with counted() as budget:
        compactor.replicate_rows(w_count, rows)  # the same pass again: parents unchanged, the same result
    assert budget == Budget(launches=1)
    # Reference: parent k's row goes to its appended slots first_new[k] + c, c < copies[k] (NumPy, slot by slot).
    first_new = count + np.concatenate([[0], np.cumsum(copies[:count])[:-1]])
    for h, a in zip(host, arrays, strict=True):
        want = h.copy().reshape(capacity, per_row, *h.shape[1:])
        for k in range(count):
            for c in range(copies[k]):
                if first_new[k] + c < capacity:
                    want[first_new[k] + c] = want[k]
        got = a.numpy().reshape(want.shape)
        assert np.array_equal(got.view(np.uint8), want.view(np.uint8)), a.dtype


def test_state_assign_is_wp_copy_bit_for_bit(device):
    sim = cracking_block(6, device, steps=200, interval=1)
    sim.advance(3)
    other = sim.state.clone()
    other.assign(sim.state)  # builds the pair's word tables (kept for the next copy between the same arrays)
    rng = np.random.default_rng(3)
    for a in other.arrays().values():  # every array scrambled: any bit pattern
        if a.size:
            h = a.numpy().copy()
            h.view(np.uint8)[...] = rng.integers(0, 256, size=h.view(np.uint8).shape, dtype=np.uint8)
            a.assign(h)
    with counted() as budget:
        other.assign(sim.state)
    assert budget == Budget(launches=1)
    for name, a in sim.state.arrays().items():
        b = getattr(other, name)
        assert np.array_equal(a.numpy().view(np.uint8), b.numpy().view(np.uint8)), name


def split_pass_budget(cells: int, device: str, books: bool = False) -> tuple[int, int, Budget]:
    """What one split pass that splits asks of the device (the stretched block of ``bench fracture``, 5 % of its
    nodes free to split, every one of them above T_f), with the splits and the rounds it made; ``books``: with the
    energy books kept, their scratch and marks made by an earlier pass (as in a run)."""
    from warpdem.bench.fracture import spread_nodes, stretched_block
    from warpdem.simulation import Simulation

    may_split = spread_nodes(cells, 0.05, 0)
    capacity = (cells + 1) ** 3 + int(np.count_nonzero(may_split))
    model, state = stretched_block(cells, device, may_split, node_capacity=capacity)
    sim = Simulation(model, state, track_energy=books)
    if books:
        sim._mark_books(SHADOW, 0)  # the scratch, the marks and the weights, made once in a run
        sim._book_change(SHADOW, 0, wp.zeros(1, dtype=wp.float64, device=device))
        sim._mark_books(CONTACT, 0)
    with counted() as budget:
        report = sim.fracture_pass()
    return report.splits, report.rounds, budget


def test_a_split_pass_books_its_energy_on_the_device(device):
    """Invariant: keeping the books costs a split pass launches only: the contact lines' and the shadow term's change
    across it are booked on the device (warpdem.stages.energy.DeviceBooks.mark / book), no read-back, copy or
    allocation more than without books (20 more read-backs when they were summed on the host)."""
    splits, rounds, off = split_pass_budget(4, device)
    splits_on, rounds_on, on = split_pass_budget(4, device, books=True)
    assert splits_on == splits > 0 and rounds_on == rounds
    assert (on.readbacks, on.copies, on.allocations, on.syncs) == (
        off.readbacks,
        off.copies,
        off.allocations,
        off.syncs,
    )


def test_a_split_pass_asks_the_same_of_a_larger_mesh(device):
    """Launches, read-backs, copies and allocations of a split pass do not grow with the mesh or with the splits (for
    the same number of rounds, each a fixed set of launches): the replicate of every node array is one launch
    (warpdem.fused), whatever their number."""
    (few, rounds_small, small), (more, rounds_large, large) = split_pass_budget(4, device), split_pass_budget(7, device)
    assert 0 < few < more  # 384 and 2 058 tets
    assert rounds_small == rounds_large
    assert (small.launches, small.readbacks, small.copies, small.allocations, small.captures) == (
        large.launches,
        large.readbacks,
        large.copies,
        large.allocations,
        large.captures,
    )


def cracking_pass_budgets(device: str, use_graph: bool) -> tuple[list[tuple[int, int, Budget]], Simulation]:
    """Every split pass that split nodes in the cracking block's run (6³ cells, 1 296 tets, a pass every step), as
    (splits, rounds, what ``FracturePass.find_and_split`` asked), and the simulation at the run's end."""
    from warpdem.stages import fracture

    sim = cracking_block(6, device, steps=200, interval=1)
    sim.use_graph = use_graph
    passes = []
    find_and_split = fracture.FracturePass.find_and_split

    def counted_pass(self, *args, **kwargs):
        with counted() as budget:
            status = find_and_split(self, *args, **kwargs)
        if status.after > status.before:
            passes.append((status.after - status.before, status.rounds, budget))
        return status

    try:
        fracture.FracturePass.find_and_split = counted_pass
        sim.advance(200)
    finally:
        fracture.FracturePass.find_and_split = find_and_split
    return passes, sim


def test_a_split_pass_replays_one_recorded_program_bit_for_bit(device):
    """Invariant: once recorded (the second pass with the same arrays), a whole split pass (the tension bound, the
    candidate search, the rounds: a device program with conditional branches and a device loop) is one graph replay
    and one read-back of its status, whatever it found and however many rounds it took; launched one by one, its
    branches and every round read their conditions back. Brute-force reference: the same run with every launch made
    one by one (``Simulation.use_graph`` off, steps and passes alike) ends in the same bits."""
    recorded, sim = cracking_pass_budgets(device, use_graph=True)
    eager, ref = cracking_pass_budgets(device, use_graph=False)
    assert [(n, r) for n, r, _ in recorded] == [(n, r) for n, r, _ in eager]
    replayed = [(r, b) for _, r, b in recorded if b.graph_launches]
    assert len(replayed) >= len(recorded) // 2, "most passes must replay the recorded program"
    assert {r for r, _ in replayed} != {1}, "the run must have passes of more than one round"
    for _, budget in replayed:
        # Inside advance the tet stresses are current: not even the bound is an eager launch.
        assert (budget.graph_launches, budget.launches, budget.readbacks, budget.allocations) == (1, 0, 1, 0)
        if budget.captures == 0:  # the pass that records the program counts the recording's copy too
            assert budget.copies == 0 and budget.syncs == 0
    for rounds, budget in ((r, b) for _, r, b in eager):
        # The status read back; the branches' and the rounds' conditions are read too, as copies out (wp.capture_if
        # and capture_while read them so when not recorded).
        assert (budget.readbacks, budget.graph_launches) == (1, 0) and budget.copies >= rounds
    for name in ("node_q", "node_qd", "node_mass", "cohesive_a", "cohesive_b", "cohesive_d_max", "crack_area_total"):
        a, b = getattr(sim.state, name, None), getattr(ref.state, name, None)
        if a is None:
            a, b = getattr(sim.model, name), getattr(ref.model, name)
        assert np.array_equal(a.numpy().view(np.uint8), b.numpy().view(np.uint8)), name
    assert np.array_equal(sim.model.tet_nodes.numpy(), ref.model.tet_nodes.numpy())


def test_chunks_that_change_nothing_share_one_snapshot(device):
    """Ten chunks of one step, each followed by a split pass that finds nothing, copy the State once (the redo
    snapshot of the advance call), not once per chunk: ten times one chunk's launches less nine snapshots."""
    sim = cracking_block(6, device, steps=200, interval=1)
    sim.advance(2)
    sim.advance(1)  # builds the snapshot's word tables
    with counted() as one:
        sim.advance(1)
    with counted() as ten:
        sim.advance(10)
    assert int(sim.state.node_splits_total.numpy()[0]) == 0
    assert ten.launches == 10 * one.launches - 9
    assert (ten.readbacks, ten.copies, ten.allocations) == (10 * one.readbacks, 0, 0)


def test_a_kept_pair_of_copy_tables_is_not_evicted(device):
    """Invariant: copying between arrays whose word tables are both kept builds nothing, however full the cache is
    (the fresh-clone CI caught a cache one short of full emptied before a pair it already held)."""
    fused._COPY_TABLES.clear()
    src, dst = [wp.zeros(8, dtype=float, device=device)], [wp.zeros(8, dtype=float, device=device)]
    fused.copy_arrays(dst, src)  # the pair's two tables
    others = [wp.zeros(4, dtype=float, device=device) for _ in range(fused.MAX_COPY_TABLES - 3)]
    for a in others:  # one short of full
        fused.cached_table(fused._COPY_TABLES, [a], [a.size], 1, a.device, fused.MAX_COPY_TABLES)
    assert len(fused._COPY_TABLES) == fused.MAX_COPY_TABLES - 1
    with counted() as budget:
        fused.copy_arrays(dst, src)
    assert budget == Budget(launches=1)


def energy_budget(cells: int, device: str) -> Budget:
    """What reading the energy books and the shadow term asks of the device once their scratch exists, on the
    cracking block of ``cells``³ cells."""
    sim = cracking_block(cells, device, steps=200, interval=1)
    sim.advance(2)
    sim.energy()  # makes the books' scratch
    with counted() as budget:
        sim.energy()
        sim.shadow()
    return budget


def test_energy_books_are_one_readback_whatever_the_body_count(device):
    small, large = energy_budget(6, device), energy_budget(10, device)  # 1 296 and 6 000 tets
    assert small == large
    # One read-back each of the books' vector (kernels/books.py); before it, energy() and shadow() read back 68
    # arrays and allocated 8 on this block.
    assert small.readbacks == 2
    assert small.allocations == 0 and small.copies == 0 and small.syncs == 0 and small.captures == 0


def frame_budget(scene, divisions: list[int], device: str, tmp_path) -> Budget:
    """What writing one frame of ``scene`` meshed with ``divisions`` asks of the device (``Run._write_frame``: the
    books, the USD frame, the time series, the VTU and fragment outputs the scene asks for), after its first frame."""
    from warpdem.api import build

    mesh = scene.mesh.model_copy(update={"divisions": divisions})
    run = build(scene.model_copy(update={"mesh": mesh}), device=device, frames=2, out_dir=tmp_path)
    try:
        next(iter(run.frames()))
        with counted() as budget:
            run._write_frame()
    finally:
        run.close()
    return budget


def test_a_frame_asks_the_same_of_a_larger_mesh(device, tmp_path):
    """Invariant: a frame reads back a fixed set of arrays, whatever the body count (the books one vector, each output
    array once: no read-back per body, per face or per line of the books). wave_column at 160 and 1 280 cells."""
    from warpdem.scene import load_scene

    scene = load_scene(pathlib.Path(__file__).resolve().parents[1] / "scenes" / "wave_column.toml")
    small = frame_budget(scene, [2, 2, 40], device, tmp_path / "small")
    large = frame_budget(scene, [4, 4, 80], device, tmp_path / "large")
    assert small.readbacks == large.readbacks and small.allocations == large.allocations
    assert small.copies == large.copies and small.syncs == 0 and small.captures == 0


def test_a_splitting_pass_allocates_nothing_once_running(device):
    """Invariant: once a run has split (the passes' scratch made: the fracture pass's, the surface rebuild's,
    warpdem.stages.fem_surface.SurfaceScratch), a chunk whose pass splits more nodes allocates nothing while the
    capacities hold (it allocated 12 arrays, the surface rebuild's, before the scratch was kept)."""
    sim = cracking_block(8, device, steps=200, interval=1)
    while int(sim.state.node_splits_total.numpy()[0]) == 0:
        sim.advance(5)
    for _ in range(50):
        before, capacity = int(sim.state.node_splits_total.numpy()[0]), sim.model.node_capacity
        with counted() as budget:
            sim.advance(1)
        split = int(sim.state.node_splits_total.numpy()[0]) > before
        if split and sim.model.node_capacity == capacity:
            assert budget.allocations == 0 and budget.captures == 0
            return
    pytest.fail("no chunk split within the capacities in 50 steps")
