"""Command line: ``python -m warpdem [SCENE] [options]`` runs a scene; ``python -m warpdem bench`` benchmarks.

Bad input (scene, restart file, device) ends with one readable line per problem on stderr and exit status 2,
before any output file is opened.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from .limits import MAX_STEPS

EXIT_USAGE = 2
EXIT_INTERNAL = 1


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0 (got {text})")
    return value


def _non_negative_float(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0 (got {text})")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer (got {text})")
    return value


def run_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m warpdem",
        description="Run a warpdem scene (TOML). Without SCENE, runs the embedded default scene. "
        "'python -m warpdem bench' prints the settling benchmark table, 'python -m warpdem bench tets' the "
        "tetrahedra one.",
    )
    p.add_argument("scene", nargs="?", help="scene file (.toml); default: the embedded default scene")
    p.add_argument("--device", help="Warp device: cpu or cuda:N (default: the scene's run.device)")
    p.add_argument("--end-time", type=_positive_float, help="simulated end time [s]")
    p.add_argument("--frames", type=_positive_int, help="number of frames to simulate (overrides --end-time)")
    p.add_argument("--out", type=Path, help="output directory (default: the scene's output.directory)")
    p.add_argument("--usd", type=Path, help="USD file to write (.usdc, .usda or .usd)")
    p.add_argument("--checkpoint-every", type=_non_negative_float, help="checkpoint period [s]; 0 = only at the end")
    p.add_argument("--restart", type=Path, help="continue from this HDF5 checkpoint")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    p.add_argument("--summary-json", type=Path, help="also write the summary as JSON to this file")
    p.add_argument(
        "--max-steps",
        type=_positive_int,
        help=f"refuse (exit 2) a run that would need more time steps than this (default {MAX_STEPS:.0e})",
    )
    return p


def bench_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m warpdem bench", description="Settling benchmark (see benchmarks/).")
    p.add_argument("--sizes", type=_positive_int, nargs="+", default=[10000, 100000], help="sphere counts")
    p.add_argument("--steps", type=_positive_int, default=2000, help="time steps to time")
    p.add_argument("--device", default="cpu", help="Warp device")
    p.add_argument("--json", type=Path, help="also write the results as JSON")
    p.add_argument("--data", type=Path, help="folder with init_N*.txt and box_N*.json (default: benchmarks/data)")
    p.add_argument("--repeat", type=_positive_int, default=3, help="runs per size; the fastest counts")
    return p


def tet_bench_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m warpdem bench tets", description="Tetrahedra benchmark: a vibrating Kuhn-tet block."
    )
    p.add_argument("--sizes", type=_positive_int, nargs="+", default=[200_000, 1_000_000], help="tets wanted")
    p.add_argument("--steps", type=_positive_int, default=100, help="time steps per timed run")
    p.add_argument("--device", default="cpu", help="Warp device")
    p.add_argument("--json", type=Path, help="also write the results as JSON")
    p.add_argument("--repeat", type=_positive_int, default=3, help="timed runs per size; the fastest counts")
    return p


def _fail(lines: list[str] | str) -> int:
    for line in [lines] if isinstance(lines, str) else lines:
        print(f"error: {line}", file=sys.stderr)
    return EXIT_USAGE


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:2] == ["bench", "tets"]:
        from .bench import run_tet_bench

        args = tet_bench_parser().parse_args(argv[2:])
        return run_tet_bench(args.sizes, args.steps, args.device, args.json, args.repeat)
    if argv[:1] == ["bench"]:
        from .bench import run_bench

        args = bench_parser().parse_args(argv[1:])
        return run_bench(args.sizes, args.steps, args.device, args.json, args.data, args.repeat)
    args = run_parser().parse_args(argv)

    from .scene import SceneError, default_scene_path, load_scene

    try:
        scene = load_scene(args.scene if args.scene is not None else default_scene_path())
    except SceneError as exc:
        return _fail(exc.problems)

    import warp as wp

    wp.config.log_level = logging.WARNING  # no init banner; warnings still show
    from .checkpoint import CheckpointError
    from .runner import RunOptions, run_scene, summary_json

    options = RunOptions(
        device=args.device,
        end_time=args.end_time,
        frames=args.frames,
        out_dir=args.out,
        usd=args.usd,
        checkpoint_every=args.checkpoint_every,
        restart=args.restart,
        quiet=args.quiet,
        max_steps=args.max_steps if args.max_steps is not None else MAX_STEPS,
    )
    if args.usd is not None and args.usd.suffix not in (".usd", ".usda", ".usdc"):
        return _fail(f"--usd: {args.usd}: allowed suffixes: .usd, .usda, .usdc")
    if args.restart is not None and not args.restart.is_file():
        return _fail(f"--restart: {args.restart}: file not found")
    try:
        summary = run_scene(scene, options)
    except (SceneError, CheckpointError) as exc:
        return _fail(str(exc).splitlines())
    except KeyboardInterrupt:
        print("interrupted: the USD stage was not published; resume from the last checkpoint", file=sys.stderr)
        return 130
    except Exception as exc:
        # Every error about the user's input is a SceneError or CheckpointError raised where the key is known; what
        # reaches here is a bug. One line and exit 1 rather than a traceback, which WARPDEM_TRACEBACK=1 brings back.
        if os.environ.get("WARPDEM_TRACEBACK"):
            raise
        detail = " ".join(str(exc).split())[:300]
        print(
            f"internal error: {type(exc).__name__}: {detail} (please report it with the scene; WARPDEM_TRACEBACK=1 "
            "shows the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL
    if not args.quiet:
        print(summary.format())
    if args.summary_json is not None:
        try:
            args.summary_json.parent.mkdir(parents=True, exist_ok=True)
            args.summary_json.write_text(summary_json(summary))
        except OSError as exc:
            return _fail(f"--summary-json: cannot write {args.summary_json}: {exc.strerror or exc}")
    return 0
