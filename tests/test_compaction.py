"""Compaction pass (kernels/compaction.py, warpdem/stages/compaction.py): flag → exclusive scan → scatter → remap.

Oracles (exact equality; the pass only moves data):
- numpy boolean-mask compaction of the same arrays with the same dead flags;
- ``old_to_new`` is a bijection from the survivors (slot < count, dead == 0) onto 0..new_count-1 that keeps their
  order, and -1 for every other slot;
- remapped index arrays hold only -1 or indices in [0, new_count), and follow ``old_to_new``;
- on a bonded model (warpdem.stages.bonds.compact_bonds): every neighbour slot's ``nbr_bond`` that is not -1 names a
  live bond joining exactly that slot's pair, every surviving bond is still linked from its pair's slot, and the
  bond keys stay sorted (the neighbour build binary-searches them).
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from warpdem.build import packing
from warpdem.build.builder import ModelBuilder
from warpdem.model import BOND_FIELDS
from warpdem.simulation import Simulation
from warpdem.stages.bonds import compact_bonds
from warpdem.stages.compaction import Compactor

SEEDS = (0, 1, 2)
# (capacity, live count): the empty set, one slot (live or not), count < capacity, count == capacity.
SIZES = ((0, 0), (1, 0), (1, 1), (7, 5), (64, 64), (1000, 733))


def survivors(capacity: int, count: int, dead: np.ndarray) -> np.ndarray:
    return (np.arange(capacity) < count) & (dead == 0)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize(("capacity", "count"), SIZES)
def test_plan_scatter_remap(device, seed, capacity, count):
    rng = np.random.default_rng(seed)
    dead = (rng.random(capacity) < rng.uniform(0.0, 1.0)).astype(np.int32)
    keep = survivors(capacity, count, dead)
    new_count = int(keep.sum())

    compactor = Compactor(capacity, device)
    w_count = wp.array([count], dtype=int, device=device)
    w_dead = wp.array(dead, dtype=int, device=device)
    old_to_new = compactor.plan(w_count, w_dead).numpy().copy()
    assert int(compactor.new_count.numpy()[0]) == new_count

    # old_to_new: survivors → 0..new_count-1 in their original order; everything else → -1.
    assert old_to_new.shape == (capacity,)
    np.testing.assert_array_equal(old_to_new[keep], np.arange(new_count))
    np.testing.assert_array_equal(old_to_new[~keep], np.full(int((~keep).sum()), -1))

    # Scatter: every dtype equals numpy mask compaction of the live slots.
    ints = rng.integers(-(2**31), 2**31 - 1, size=capacity, dtype=np.int64).astype(np.int32)
    floats = rng.normal(size=capacity).astype(np.float32)
    vecs = rng.normal(size=(capacity, 3)).astype(np.float32)
    w_ints = wp.array(ints, dtype=int, device=device)
    w_floats = wp.array(floats, dtype=float, device=device)
    w_vecs = wp.array(vecs, dtype=wp.vec3, device=device)
    compactor.scatter(w_count, [w_ints, w_floats, w_vecs])
    assert w_ints.shape == (capacity,) and w_floats.shape == (capacity,) and w_vecs.shape == (capacity,)
    np.testing.assert_array_equal(w_ints.numpy()[:new_count], ints[keep])
    np.testing.assert_array_equal(w_floats.numpy()[:new_count], floats[keep])
    np.testing.assert_array_equal(w_vecs.numpy()[:new_count], vecs[keep])

    # Remap an index array pointing into the compacted set (with -1 entries): in range or -1, following the map.
    n_idx = 50
    idx = rng.integers(-1, max(capacity, 1), size=n_idx).astype(np.int32) if capacity else np.full(n_idx, -1)
    idx = idx.astype(np.int32)
    w_idx = wp.array(idx, dtype=int, device=device)
    compactor.remap(w_idx)
    got = w_idx.numpy()
    assert np.all((got == -1) | ((got >= 0) & (got < new_count)))
    expected = np.where(idx >= 0, old_to_new[np.maximum(idx, 0)] if capacity else -1, -1)
    np.testing.assert_array_equal(got, expected)
    # A removed slot's index becomes -1; a survivor's keeps pointing at the same item.
    np.testing.assert_array_equal(w_ints.numpy()[got[got >= 0]], ints[idx[got >= 0]])

    compactor.finish(w_count)
    assert int(w_count.numpy()[0]) == new_count


def test_plan_is_repeatable(device):
    # The compactor's buffers are reused: a second pass over different flags must not see the first one's data.
    rng = np.random.default_rng(5)
    capacity = 100
    compactor = Compactor(capacity, device)
    for count in (100, 40, 0, 77):
        dead = (rng.random(capacity) < 0.5).astype(np.int32)
        keep = survivors(capacity, count, dead)
        old_to_new = compactor.plan(
            wp.array([count], dtype=int, device=device), wp.array(dead, dtype=int, device=device)
        ).numpy()
        np.testing.assert_array_equal(old_to_new[keep], np.arange(int(keep.sum())))
        assert np.all(old_to_new[~keep] == -1)
        assert int(compactor.new_count.numpy()[0]) == int(keep.sum())


def bonded_block(device: str) -> Simulation:
    """An hcp block of ~60 bonded spheres on a floor; the neighbour list (with nbr_bond links) is built."""
    radius = 0.005
    q = packing.lattice_packing(packing.Box(np.zeros(3), np.array([0.04, 0.04, 0.02])), radius, "hcp")
    b = ModelBuilder()
    b.add_material("rock", 2600.0, 5.0e7, 0.25)
    ids = b.add_spheres(q, radius, "rock")
    b.add_bonded_group(ids, youngs_modulus=5.0e7, tensile_strength=1.0e5, shear_strength=2.0e5)
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "rock")
    model, state = b.finalize(device)
    return Simulation(model, state)


def linked_pairs(sim: Simulation) -> dict[tuple[int, int], int]:
    """(i, j) → nbr_bond of every used neighbour slot."""
    m, s = sim.model, sim.state
    n, k = sim.particle_count, m.max_neighbors
    counts = np.minimum(s.nbr_count.numpy()[:n], k)
    index = s.nbr_index.numpy().reshape(m.particle_capacity, k)
    bond = s.nbr_bond.numpy().reshape(m.particle_capacity, k)
    return {(i, int(index[i, c])): int(bond[i, c]) for i in range(n) for c in range(counts[i])}


def check_bond_links(sim: Simulation) -> None:
    """Every non-negative nbr_bond names a live bond of the slot's pair, unbonded slots hold -1, every live bond is
    linked."""
    s = sim.state
    nb = sim.bond_count
    bi, bj = s.bond_i.numpy()[:nb], s.bond_j.numpy()[:nb]
    key = s.bond_key.numpy()[:nb]
    np.testing.assert_array_equal(key, bi.astype(np.int64) * sim.model.particle_capacity + bj)
    assert np.all(np.diff(key) > 0), "bond keys must stay sorted and unique"
    links = linked_pairs(sim)
    for (i, j), b in links.items():
        if b >= 0:
            assert b < nb, f"slot ({i}, {j}) points at bond {b} >= bond_count {nb}"
            assert (int(bi[b]), int(bj[b])) == (i, j), f"slot ({i}, {j}) points at bond {b} = ({bi[b]}, {bj[b]})"
    bond_of_pair = {(int(i), int(j)): b for b, (i, j) in enumerate(zip(bi, bj, strict=True))}
    for pair, b in links.items():
        if pair not in bond_of_pair:
            assert b == -1, f"slot {pair} has no bond but links {b}"
    for pair, b in bond_of_pair.items():
        # Bonded spheres touch, so they are inside the neighbour cutoff: their slot must carry the bond.
        assert links.get(pair) == b, f"bond {b} {pair} is linked as {links.get(pair)}"


@pytest.mark.parametrize("seed", SEEDS)
def test_compact_bonds_keeps_neighbor_links(device, seed):
    sim = bonded_block(device)
    s = sim.state
    nb = sim.bond_count
    assert nb > 50
    check_bond_links(sim)
    rng = np.random.default_rng(seed)
    broken = (rng.random(nb) < 0.4).astype(np.int32) * rng.integers(1, 3, size=nb).astype(np.int32)
    before = {name: getattr(s, name).numpy()[:nb].copy() for name in BOND_FIELDS}
    links_before = linked_pairs(sim)
    flags = s.bond_broken.numpy().copy()
    flags[:nb] = broken
    s.bond_broken.assign(flags)

    compact_bonds(sim.model, s, Compactor(sim.model.bond_capacity, sim.model.device))

    keep = broken == 0
    assert sim.bond_count == int(keep.sum())
    for name in BOND_FIELDS:
        np.testing.assert_array_equal(getattr(s, name).numpy()[: sim.bond_count], before[name][keep], err_msg=name)
    check_bond_links(sim)
    # The slots of broken bonds are unlinked (-1): those pairs are ordinary contacts now.
    links = linked_pairs(sim)
    gone = {(int(i), int(j)) for i, j in zip(before["bond_i"][~keep], before["bond_j"][~keep], strict=True)}
    assert gone, "the random flags broke no bond"
    for pair in gone:
        assert pair in links_before and links[pair] == -1
