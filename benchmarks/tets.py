"""Tetrahedra benchmark (issue "Cosserat point tetrahedra" §9): ``python benchmarks/tets.py [--sizes 200000 1000000]
[--steps 100] [--repeat 3] [--device cpu]``.

The same as ``python -m warpdem bench tets`` (the case is described in warpdem/bench/tets.py).
"""

from __future__ import annotations

from warpdem.cli import main

if __name__ == "__main__":
    raise SystemExit(main(["bench", "tets", *__import__("sys").argv[1:]]))
