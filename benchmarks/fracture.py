"""Fracture benchmark (issue 9 §8): ``python benchmarks/fracture.py [--tets 1000000] [--fraction 0.01] [--steps 50]
[--run-tets 10000] [--run-steps 200] [--intervals 0 1 10] [--repeat 3] [--device cpu]``.

The same as ``python -m warpdem bench fracture`` (the cases are described in the package warpdem.bench).
"""

from __future__ import annotations

from warpdem.cli import main

if __name__ == "__main__":
    raise SystemExit(main(["bench", "fracture", *__import__("sys").argv[1:]]))
