"""Benchmark cases (warpdem/bench.py): the settling cases ship with the package, so ``python -m warpdem bench`` runs
after a plain ``pip install .`` from any folder.

Oracles: the shipped centres of each case have the count and the mean height recorded with the case when it was made
(``N`` and ``mean_z0`` of box_N<N>.json, the latter to float64 rounding of a mean of N numbers); every sphere lies in
the case's box; a size without a case is refused with the sizes there are.
"""

from __future__ import annotations

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
