"""What the scene report scripts share (benchmarks/conversion_scenes.py, facility_scenes.py, fracture_scenes.py):
their command line's common part and the scenes it picks.

The scripts are run as ``python benchmarks/<name>.py`` from the repository root, so this module is found beside them
(a script's own folder is the first entry of ``sys.path``)."""

from __future__ import annotations

import argparse
from collections.abc import Iterable


def scene_parser(doc: str | None, names: Iterable[str], every: str = "all") -> argparse.ArgumentParser:
    """The parser of a scene report script: SCENE ... (any of ``names``, default ``every`` of them), ``--device`` and
    ``--end-time``; the script adds its own options. ``doc`` is the script's docstring, whose first paragraph is the
    description."""
    parser = argparse.ArgumentParser(description=(doc or "").split("\n\n")[0])
    parser.add_argument("scenes", nargs="*", metavar="SCENE", help=f"one of {', '.join(names)} [{every}]")
    parser.add_argument("--device", default="cpu", help="Warp device [cpu]")
    parser.add_argument("--end-time", type=float, help="simulated end time [s] (default: the scene's)")
    return parser


def chosen_scenes(parser: argparse.ArgumentParser, args: argparse.Namespace, names: Iterable[str]) -> list[str]:
    """The scenes the command line asks for (every one of ``names`` when it names none), after the scene report
    scripts' one check: an unknown name ends the script with argparse's usage error (exit status 2), before Warp is
    initialised."""
    names = list(names)
    unknown = [name for name in args.scenes if name not in names]
    if unknown:
        parser.error(f"unknown scene {unknown[0]!r}; allowed: {', '.join(names)}")
    return list(args.scenes) or names
