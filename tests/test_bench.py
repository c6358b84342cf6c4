"""Benchmark cases (warpdem/bench.py): the settling cases ship with the package, so ``python -m warpdem bench`` runs
after a plain ``pip install .`` from any folder.

Oracles: the shipped centres of each case have the count and the mean height recorded with the case when it was made
(``N`` and ``mean_z0`` of box_N<N>.json, the latter to float64 rounding of a mean of N numbers); every sphere lies in
the case's box; a size without a case is refused with the sizes there are. The fracture benchmark's split pass splits
exactly the nodes its uniform stretch puts above T_f (see the test).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import warpdem
from warpdem.bench import DATA_DIR, find_case
from warpdem.cli import main

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
    σ_xx ≈ E ε = 2 T_f half way through it (``cracking_block``), so it must split nodes, one new node per split.
    """
    cells, fraction = 6, 0.05
    out = tmp_path / "fracture.json"
    argv = ["bench", "fracture", "--tets", str(6 * cells**3), "--fraction", str(fraction), "--steps", "2"]
    argv += ["--device", device]
    argv += [
        "--repeat",
        "1",
        "--run-tets",
        str(6 * cells**3),
        "--run-steps",
        "40",
        "--intervals",
        "1",
        "--json",
        str(out),
    ]
    assert main(argv) == 0
    data = json.loads(out.read_text())
    (p,) = data["passes"]
    assert p["nodes"] == (cells + 1) ** 3 and p["tets"] == 6 * cells**3
    assert p["may_split"] == round(fraction * (cells + 1) ** 3)
    assert p["due"] == p["may_split"] == p["splits"]
    assert p["nodes_after"] == p["nodes"] + p["splits"]
    assert not p["grew"]  # node slots were reserved for the daughters
    (r,) = data["runs"]
    assert r["splits"] > 0
    assert r["nodes_after"] == (cells + 1) ** 3 + r["splits"]
