"""Settling benchmark (issue "Foundation" §7): ``python benchmarks/settling.py [--sizes 10000 100000] [--device cpu]``.

The same as ``python -m warpdem bench``; the initial centres and box of each case ship in
warpdem/data/bench/.
"""

from __future__ import annotations

from warpdem.cli import main

if __name__ == "__main__":
    raise SystemExit(main(["bench", *__import__("sys").argv[1:]]))
