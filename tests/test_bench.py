"""Benchmark cases (warpdem.bench): the settling cases ship with the package, so ``python -m warpdem bench`` runs
after a plain ``pip install .`` from any folder.

Oracles: the shipped centres of each case have the count and the mean height recorded with the case when it was made
(``N`` and ``mean_z0`` of box_N<N>.json, the latter to float64 rounding of a mean of N numbers); every sphere lies in
the case's box; a size without a case is refused with the sizes there are. The fracture benchmark's split pass splits
exactly the nodes its uniform stretch puts above T_f, and the conversion benchmark's pass converts exactly the tets
that may convert and are above the Tresca threshold (see the tests).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import warpdem
from warpdem.bench import (
    CONVERSION_FRACTION,
    DATA_DIR,
    STRETCH,
    TENSILE_STRENGTH,
    TRESCA_STRENGTH,
    converting_block,
    due_tets,
    find_case,
    lattice_counts,
    spread_tets,
)
from warpdem.cli import main
from warpdem.simulation import Simulation

MEAN_RTOL = 1e-12  # a float64 mean of 1e5 numbers of order 0.3: rounding ~1e-16 · sqrt(N)


@pytest.mark.parametrize("n", [10000, 100000])
def test_shipped_case_is_the_recorded_one(n):
    q, box = find_case(n)
    assert DATA_DIR.is_relative_to(Path(warpdem.__file__).parent)  # inside the package: installed with it
    assert q.shape == (box["N"], 3) == (n, 3)
    np.testing.assert_allclose(q[:, 2].mean(), box["mean_z0"], rtol=MEAN_RTOL)
    lo, hi = np.asarray(box["box_lo"]), np.asarray(box["box_hi"])
    assert np.all((q > lo) & (q < hi))


def test_unknown_size_is_refused(capsys):
    assert main(["bench", "--sizes", "500", "--steps", "2", "--repeat", "1"]) == 2
    err = capsys.readouterr().err
    assert "no benchmark case for N = 500" in err and "it has N = 10000, 100000" in err


def test_fracture_bench_splits_the_nodes_due(tmp_path, device):
    """``bench fracture`` at a tiny size: the pass splits exactly the nodes due, and the cracking run cracks.

    Oracle: the block is stretched by the linear displacement u_x = ε X, which every tet reproduces exactly (the patch
    test), so each tet holds the uniaxial-strain stress σ_xx = (λ + 2μ) ε = 3 T_f, σ_yy = σ_zz = λ ε = T_f (ν = 0.25),
    and so does every node's volume average (LDEC eq. 1): σ1 = 3 T_f ≥ T_f along p1 = x. Every node that may split
    lies strictly inside the block along x, so its star has tets on both sides of the plane x = X: all of them are
    due, the pass splits them all (its rounds split neighbours one after another) and adds one node each. The host
    count (``due``, brute force over the tets) must agree. The cracking run's grains (T_f … 2 T_f) are strained to
    σ_xx ≈ E ε = 2 T_f half way through it (``cracking_block``), so it must split nodes, one new node per split; the
    same run with the pass off (interval 0) splits none.
    """
    cells, fraction = 6, 0.05
    out = tmp_path / "fracture.json"
    tets = str(6 * cells**3)
    argv = ["bench", "fracture", "--tets", tets, "--fraction", str(fraction), "--steps", "2", "--repeat", "1"]
    argv += ["--run-tets", tets, "--run-steps", "40", "--intervals", "0", "1", "--device", device, "--json", str(out)]
    assert main(argv) == 0
    data = json.loads(out.read_text())
    (p,) = data["passes"]
    assert p["nodes"] == (cells + 1) ** 3 and p["tets"] == 6 * cells**3
    assert p["may_split"] == round(fraction * (cells + 1) ** 3)
    assert p["due"] == p["may_split"] == p["splits"]
    assert p["nodes_after"] == p["nodes"] + p["splits"]
    assert not p["grew"]  # node slots were reserved for the daughters
    off, r = data["runs"]
    assert off["interval"] == 0 and off["splits"] == 0 and off["nodes_after"] == (cells + 1) ** 3  # the pass off
    assert r["splits"] > 0
    assert r["nodes_after"] == (cells + 1) ** 3 + r["splits"]


@pytest.mark.parametrize("stretch", [STRETCH, 2.5])
def test_conversion_pass_converts_the_flagged_tets_above_the_threshold(device, stretch):
    """The conversion benchmark's block converts exactly the tets that may convert and are above the threshold.

    Oracle: u_x = ε X is reproduced exactly by every tet (the patch test), so each holds σ_xx = s T_f and σ_yy = σ_zz
    = s T_f ν / (1 − ν) = s T_f / 3 (ν = 0.25) for a stretch s: the Tresca stress (σ1 − σ3)/2 = s T_f / 3. With
    τ_f = T_f and f = 0.9, s = 3 puts every tet at T_f ≥ 0.9 τ_f (11 % above the threshold, far beyond float32
    round-off ~1e-7), s = 2.5 at 0.83 τ_f (7 % below it): the tets due are the flagged ones, or none. The host's
    brute-force count (``due_tets``) must say the same, and the pass must convert exactly that set (tet_active = 0),
    one sphere per tet, one bond per pair of them that shares an edge and one coupling per pair of one of them and a
    tet that stays continuous sharing an edge (warpdem.stages.lattice's network, counted on the host by sorting edges).
    """
    cells = 4
    may_convert = spread_tets(6 * cells**3, 0.05, seed=3)
    model, state = converting_block(cells, device, may_convert, stretch=stretch)
    sim = Simulation(model, state, track_energy=False)
    due = due_tets(sim.model, sim.state)
    above = stretch * TENSILE_STRENGTH / 3.0 >= CONVERSION_FRACTION * TRESCA_STRENGTH
    expected = may_convert & above
    np.testing.assert_array_equal(due, expected)
    bonds, couplings = lattice_counts(sim.model, sim.state, expected)
    report = sim.conversion_pass()
    converted = sim.state.tet_active.numpy()[: 6 * cells**3] == 0
    np.testing.assert_array_equal(converted, expected)
    assert report.converted == report.spawned == int(np.count_nonzero(expected))
    assert int(sim.state.particle_count.numpy()[0]) == report.spawned
    assert report.bonds == int(sim.state.bond_count.numpy()[0]) == bonds
    assert report.couplings == int(sim.state.coupling_count.numpy()[0]) == couplings
    assert not report.grew  # particle, bond and coupling slots were reserved


def test_conversion_bench_converts_the_tets_due(tmp_path, device):
    """``bench conversion`` at a tiny size: the pass converts exactly the tets due, and the converting run converts.

    Oracle: as above, every tet of the stretched block is 11 % above the Tresca threshold, so the tets due (counted
    on the host by brute force) are exactly the flagged ones, and the pass converts them all, one sphere each. The
    converting run's central slab (τ_f = T_f/2 … T_f per grain) is strained to a Tresca stress σ_xx/2 ≈ E ε/2 = T_f
    half way through the run (``pulled_granite``), past every grain's 0.9 τ_f, so it must convert tets, one sphere
    each; the same run with the pass off (interval 0) converts none.
    """
    cells, fraction = 6, 0.05
    out = tmp_path / "conversion.json"
    tets = str(6 * cells**3)
    argv = ["bench", "conversion", "--tets", tets, "--fraction", str(fraction), "--steps", "2", "--repeat", "1"]
    argv += ["--run-tets", tets, "--run-steps", "40", "--intervals", "0", "1", "--device", device, "--json", str(out)]
    assert main(argv) == 0
    data = json.loads(out.read_text())
    (p,) = data["passes"]
    assert p["tets"] == 6 * cells**3 and p["nodes"] == (cells + 1) ** 3
    assert p["may_convert"] == round(fraction * 6 * cells**3)
    assert p["due"] == p["may_convert"] == p["converted"] == p["spawned"]
    assert p["bonds"] == p["bonds_due"] and p["couplings"] == p["couplings_due"]
    assert not p["grew"]  # particle and coupling slots were reserved
    off, r = data["runs"]
    assert off["interval"] == 0 and off["converted"] == 0 and off["spheres"] == 0  # the pass off
    assert 0 < r["converted"] <= r["may_convert"]
    assert r["spawned"] == r["spheres"] == r["converted"]


def test_block_bench_makes_one_body_per_cell(tmp_path, device):
    """``bench blocks`` at a tiny size: every cell of the jointed cube is one free rigid block of 6 tets, with the
    mass ρ (1 m)³ and the moments ρ (1 m)⁵/6 of a unit cube (the exact tet inertia; float32 node masses), and the
    command runs and writes its JSON."""
    from warpdem.bench import GRANITE, jointed_cube
    from warpdem.stages.rigid import box_inertia

    sim = jointed_cube(2, device)
    s = sim.state
    assert s.body_mass.shape[0] == 8 and int(s.body_fixed.numpy().sum()) == 0
    np.testing.assert_array_equal(s.body_node_count.numpy(), 8)  # 8 corners each: the joints split every node
    rho = GRANITE["density"]
    np.testing.assert_allclose(s.body_mass.numpy(), rho, rtol=1e-6)
    np.testing.assert_allclose(s.body_inertia.numpy(), np.tile(box_inertia(rho, (1, 1, 1)), (8, 1)), rtol=1e-6)
    out = tmp_path / "blocks.json"
    assert main(["bench", "blocks", "--blocks", "8", "--steps", "2", "--repeat", "1", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["blocks"][0]["blocks"] == 8


def test_bench_ranks_2_runs_the_case_decomposed_and_ends_where_one_process_does(tmp_path):
    # `bench --ranks 2` is `mpiexec -n 2 python -m warpdem bench`: the oracle is the decomposed run's bit-identity
    # with one process on the CPU (tests/test_parallel.py), so the kinetic energies, the mean height, the contacts
    # and the list rebuilds after 1000 steps (spheres falling onto each other: contacts and a rebuild) are equal,
    # not close, and the record says 2 ranks.
    runs = {}
    for ranks in (1, 2):
        out = tmp_path / f"ranks{ranks}.json"
        args = ["bench", "--sizes", "10000", "--steps", "1000", "--repeat", "1", "--json", str(out)]
        assert main([*args, "--ranks", str(ranks)]) == 0
        (runs[ranks],) = json.loads(out.read_text())
    assert runs[1]["ranks"] == 1 and runs[2]["ranks"] == 2
    assert runs[1]["mean_contacts_per_particle"] > 0 and runs[1]["neighbor_rebuilds"] > 0
    for key in ("kinetic_translational", "kinetic_rotational", "mean_height", "mean_contacts_per_particle"):
        assert runs[2][key] == runs[1][key], key
    assert runs[2]["neighbor_rebuilds"] == runs[1]["neighbor_rebuilds"]
    # Where each rank's timed steps went: parts of the wall time, so each is >= 0 and a rank's parts (its kernels
    # and its exchange, which holds the halo's four and the rebuilds) sum to no more than the wall time a step; the
    # between part is the exchange less the halo, >= 0 up to the clock's resolution (1 us a call at most).
    assert runs[1]["rank_step_ms"] is None
    wall_ms = 1e3 * runs[2]["wall_time"] / (runs[2]["steps"] - 2)
    for ms in runs[2]["rank_step_ms"]:
        assert all(ms[k] >= 0.0 for k in ("kernels", "pack", "post", "wait", "unpack")), ms
        assert ms["between"] >= -1e-3, ms
        assert ms["kernels"] + ms["exchange"] <= wall_ms, (ms, wall_ms)
