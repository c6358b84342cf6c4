"""Command line: ``python -m warpdem [SCENE] [options]`` runs a scene; ``python -m warpdem bench`` benchmarks;
``python -m warpdem plot RUN_DIR`` plots a run's time series; ``python -m warpdem preview STAGE`` renders a stage.

Bad input (scene, restart file, device) ends with one readable line per problem on stderr and exit status 2,
before any output file is opened. A run that blows up ends with one line on stderr and exit status 3, its good
frames published.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from .limits import MAX_STEPS

EXIT_USAGE = 2
EXIT_UNSTABLE = 3
"""Exit status of a run stopped by the stability guard (warpdem.stages.guard): non-finite or run-away state."""


def init_warp(quiet: bool = False) -> None:
    """Start Warp without its start-up chatter (:func:`warpdem.api.init_warp`, imported when called: ``--help`` and
    bad input need no Warp)."""
    from .api import init_warp as start_warp

    start_warp(quiet)


EXIT_SIGNAL_BASE = 128
"""A run stopped by a signal exits with 128 + its number, as a shell reports it: 130 for SIGINT, 143 for SIGTERM."""

EXIT_INTERNAL = 1
"""Exit status of an unexpected internal error (a bug), reported in one line."""


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


def _non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0 (got {text})")
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
        "tetrahedra one, 'python -m warpdem bench fracture' the fracture one, 'python -m warpdem bench conversion' "
        "the conversion one, 'python -m warpdem bench blocks' the rigid-block one; 'python -m warpdem plot RUN_DIR' "
        "plots a run's time series, 'python -m warpdem preview "
        "STAGE' renders frames of its USD stage to PNG.",
    )
    p.add_argument("scene", nargs="?", help="scene file (.toml); default: the embedded default scene")
    p.add_argument("--device", help="Warp device: cpu or cuda:N (default: the scene's run.device)")
    p.add_argument("--end-time", type=_positive_float, help="simulated end time [s]")
    p.add_argument(
        "--frames",
        type=_positive_int,
        help="number of frames to simulate (wins over --end-time, with a note, when both are given)",
    )
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
    p = argparse.ArgumentParser(
        prog="python -m warpdem bench",
        description="Settling benchmark: N spheres dropped into a box (see benchmarks/README.md). "
        "'python -m warpdem bench tets' runs the tetrahedra benchmark instead (see 'python -m warpdem bench tets "
        "--help'), 'python -m warpdem bench fracture' the fracture one, 'python -m warpdem bench conversion' the "
        "conversion one.",
    )
    p.add_argument("--sizes", type=_positive_int, nargs="+", default=[10000, 100000], help="sphere counts")
    p.add_argument("--steps", type=_positive_int, default=2000, help="time steps to time")
    p.add_argument("--device", default="cpu", help="Warp device")
    p.add_argument("--json", type=Path, help="also write the results as JSON")
    p.add_argument(
        "--data",
        type=Path,
        help="folder with init_N*.txt(.gz) and box_N*.json (default: the cases shipped in warpdem/data/bench)",
    )
    p.add_argument("--repeat", type=_positive_int, default=3, help="runs per size; the fastest counts")
    p.add_argument(
        "--ranks",
        type=_positive_int,
        default=1,
        help="run the case decomposed over this many MPI ranks (the same as mpiexec -n N python -m warpdem bench)",
    )
    _books_option(p)
    return p


def _without_option(argv: list[str], option: str) -> list[str]:
    """``argv`` without ``option`` and its value (``--option VALUE`` or ``--option=VALUE``)."""
    out, skip = [], False
    for word in argv:
        if skip:
            skip = False
        elif word == option:
            skip = True
        elif not word.startswith(f"{option}="):
            out.append(word)
    return out


def _books_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--books",
        choices=("on", "off"),
        default="on",
        help="keep the energy books in the timed steps, as every run does [on]; off: the step without them",
    )


def tet_bench_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m warpdem bench tets", description="Tetrahedra benchmark: a vibrating Kuhn-tet block."
    )
    p.add_argument("--sizes", type=_positive_int, nargs="+", default=[200_000, 1_000_000], help="tets wanted")
    p.add_argument("--steps", type=_positive_int, default=100, help="time steps per timed run")
    p.add_argument("--device", default="cpu", help="Warp device")
    p.add_argument("--json", type=Path, help="also write the results as JSON")
    p.add_argument("--repeat", type=_positive_int, default=3, help="timed runs per size; the fastest counts")
    _books_option(p)
    return p


def block_bench_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m warpdem bench blocks",
        description="Rigid-block benchmark: a jointed cube of 1 m blocks (one Kuhn cell, 6 tets, each) on the ground, "
        "in rigid mode (see benchmarks/README.md). The documented figure is '--blocks 100000'.",
    )
    p.add_argument(
        "--blocks", type=_positive_int, nargs="+", default=[4096], help="blocks wanted (rounded up to a cube)"
    )
    p.add_argument("--steps", type=_positive_int, default=50, help="time steps per timed run")
    p.add_argument("--device", default="cpu", help="Warp device")
    p.add_argument("--json", type=Path, help="also write the results as JSON")
    p.add_argument("--repeat", type=_positive_int, default=3, help="timed runs per size; the fastest counts")
    return p


def _fraction(text: str) -> float:
    value = float(text)
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1] (got {text})")
    return value


PASS_BENCH_TEXT = {
    "fracture": (
        "Fracture benchmark: one split pass on a stretched Kuhn-tet block with a fraction of its nodes splitting, in "
        "force steps of the same mesh (target < 20), and the step rate of a cracking run",
        "nodes that split",
        "cracking",
    ),
    "conversion": (
        "Conversion benchmark: one FEM-to-DEM conversion pass on a stretched Kuhn-tet block with a fraction of its "
        "tets converting into bonded spheres, in force steps of the same mesh (target < 20), and the step rate of a "
        "run whose centre converts as it fails",
        "tets that convert",
        "converting",
    ),
}
"""The benchmarks of a between-steps pass (``bench fracture``, ``bench conversion``): description, what the
fraction counts, the name of the run."""


def pass_bench_parser(kind: str) -> argparse.ArgumentParser:
    """The options of ``python -m warpdem bench fracture|conversion`` (both time a pass and a run the same way)."""
    description, fraction_of, run = PASS_BENCH_TEXT[kind]
    p = argparse.ArgumentParser(
        prog=f"python -m warpdem bench {kind}",
        description=f"{description} (see benchmarks/README.md). The documented figure is '--tets 1000000'.",
    )
    p.add_argument("--tets", type=_positive_int, nargs="+", default=[200_000], help="tets wanted for the pass")
    p.add_argument("--fraction", type=_fraction, default=0.01, help=f"fraction of the {fraction_of} [0.01]")
    p.add_argument("--steps", type=_positive_int, default=50, help="force steps per timed run [50]")
    p.add_argument(
        "--run-tets",
        type=_positive_int,
        nargs="*",
        default=[10_000],
        help=f"tets wanted for the {run} run (none: skip it)",
    )
    p.add_argument("--run-steps", type=_positive_int, default=200, help=f"steps of the {run} run [200]")
    p.add_argument(
        "--intervals",
        type=_non_negative_int,
        nargs="+",
        default=[0, 1, 10],
        help=f"steps between passes in the {run} run (0: the pass off, the reference)",
    )
    p.add_argument("--seed", type=int, default=0, help=f"seed of the {fraction_of} and of the grain strengths")
    p.add_argument("--device", default="cpu", help="Warp device")
    p.add_argument("--json", type=Path, help="also write the results as JSON")
    p.add_argument("--repeat", type=_positive_int, default=3, help="timed runs and passes per size; the fastest counts")
    _books_option(p)
    return p


def _size(text: str) -> tuple[int, int]:
    from .io.preview import PreviewError, parse_size

    try:
        return parse_size(text)
    except PreviewError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--size: ")) from None


def plot_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m warpdem plot",
        description="PNG plots of a run's time series (<name>_series.csv in RUN_DIR): energy balance, counts, wall "
        "and load forces.",
    )
    p.add_argument("run_dir", type=Path, help="output folder of a run (the scene's output.directory or --out)")
    p.add_argument("--out", type=Path, help="folder for the PNG files (default: RUN_DIR)")
    p.add_argument("--size", type=_size, default=(800, 600), help="picture size WIDTHxHEIGHT in pixels [800x600]")
    return p


def preview_parser() -> argparse.ArgumentParser:
    from .io.preview import COLOR_BY, DEFAULT_MAX_SPHERES, VIEWS

    p = argparse.ArgumentParser(
        prog="python -m warpdem preview",
        description="Render frames of a warpdem USD stage to PNG (spheres as discs of their radius, the rock "
        "surface as shaded triangles, in the stage's colours), optionally an animated GIF; no USD viewer needed.",
    )
    p.add_argument("stage", type=Path, help="USD stage written by a run (.usdc, .usda, .usd)")
    p.add_argument(
        "--frames", type=int, nargs="+", help="frames (time codes) to draw; negative counts from the end [last]"
    )
    p.add_argument("--gif", action="store_true", help="also write an animated GIF (of all frames without --frames)")
    p.add_argument("--view", choices=VIEWS, default="3d", help="projection: xz front, xy top, yz side, 3d [3d]")
    p.add_argument("--size", type=_size, default=(640, 480), help="picture size WIDTHxHEIGHT in pixels [640x480]")
    p.add_argument("--out", type=Path, help="folder for the pictures (default: the stage's folder)")
    p.add_argument(
        "--max-spheres", type=_positive_int, default=DEFAULT_MAX_SPHERES, help="draw at most this many spheres"
    )
    p.add_argument(
        "--color-by",
        choices=COLOR_BY,
        default="stage",
        help="colours: the stage's own, or a body recoloured from the values the stage holds [stage]",
    )
    p.add_argument(
        "--scale", type=_positive_float, help="value drawn red with --color-by speed [m/s] or stress [Pa] [the largest]"
    )
    p.add_argument(
        "--window",
        type=_window,
        metavar="LEFT,RIGHT,BOTTOM,TOP",
        help="draw only this part of the view [m] along the screen's axes [everything]",
    )
    p.add_argument("--no-legend", action="store_true", help="leave out the colour keys under the view")
    return p


def _window(text: str) -> tuple[float, float, float, float]:
    """``LEFT,RIGHT,BOTTOM,TOP`` [m], each pair increasing."""
    try:
        left, right, bottom, top = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not four numbers LEFT,RIGHT,BOTTOM,TOP") from None
    if not (left < right and bottom < top):
        raise argparse.ArgumentTypeError(f"{text!r}: need LEFT < RIGHT and BOTTOM < TOP")
    return left, right, bottom, top


def _fail(lines: list[str] | str) -> int:
    for line in [lines] if isinstance(lines, str) else lines:
        print(f"error: {line}", file=sys.stderr)
    return EXIT_USAGE


def _naming_file(line: str, scene_name: str, path: Path) -> str:
    """A build-time problem names the scene by its name (a scene may come from Python, without a file); on the
    command line, name the file instead."""
    prefix = f"{scene_name}: "
    return f"{path}: {line[len(prefix) :]}" if line.startswith(prefix) else line


def _quiet_follower() -> bool:
    """Under mpiexec every rank runs the command and rank 0 speaks for it (its errors are every rank's): another
    rank's output goes nowhere. Returns whether this is such a rank."""
    from .parallel.run import rank_is_follower

    if not rank_is_follower():
        return False
    sys.stdout = open(os.devnull, "w")  # noqa: SIM115 (for the life of the process)
    sys.stderr = sys.stdout
    return True


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:2] == ["bench", "tets"]:
        from .bench import run_tet_bench

        args = tet_bench_parser().parse_args(argv[2:])
        init_warp()
        return run_tet_bench(args.sizes, args.steps, args.device, args.json, args.repeat, args.books == "on")
    if argv[:2] == ["bench", "blocks"]:
        from .bench import run_block_bench

        args = block_bench_parser().parse_args(argv[2:])
        init_warp()
        return run_block_bench(args.blocks, args.steps, args.device, args.json, args.repeat)
    if argv[:1] == ["bench"] and argv[1:2] and argv[1] in PASS_BENCH_TEXT:
        from .bench import run_pass_bench

        args = pass_bench_parser(argv[1]).parse_args(argv[2:])
        init_warp()
        return run_pass_bench(
            argv[1],
            args.tets,
            args.fraction,
            args.steps,
            args.run_tets,
            args.run_steps,
            args.intervals,
            args.device,
            args.json,
            args.repeat,
            args.seed,
            args.books == "on",
        )
    if argv[:1] == ["bench"]:
        from .bench import run_bench

        args = bench_parser().parse_args(argv[1:])
        if args.ranks > 1:
            from .parallel.comm import run_on_ranks

            return run_on_ranks(args.ranks, _without_option(argv, "--ranks"))
        _quiet_follower()
        init_warp()
        return run_bench(args.sizes, args.steps, args.device, args.json, args.data, args.repeat, args.books == "on")
    if argv[:1] == ["plot"]:
        from .io.plot import PlotError, plot_run

        args = plot_parser().parse_args(argv[1:])
        try:
            files = plot_run(args.run_dir, args.out, args.size)
        except PlotError as exc:
            return _fail(str(exc))
        print("\n".join(str(f) for f in files))
        return 0
    if argv[:1] == ["preview"]:
        from .io.preview import PreviewError, render

        args = preview_parser().parse_args(argv[1:])
        try:
            files = render(
                args.stage,
                args.out,
                args.frames,
                args.view,
                args.size,
                args.gif,
                args.max_spheres,
                color_by=args.color_by,
                scale=args.scale,
                legend=not args.no_legend,
                window=args.window,
            )
        except PreviewError as exc:
            return _fail(str(exc))
        print("\n".join(str(f) for f in files))
        return 0
    args = run_parser().parse_args(argv)
    if _quiet_follower():
        args.quiet = True

    from .scene import SceneError, default_scene_path, load_scene

    scene_path = Path(args.scene) if args.scene is not None else default_scene_path()
    try:
        scene = load_scene(scene_path)
    except SceneError as exc:
        return _fail(exc.problems)

    init_warp(quiet=args.quiet)
    from .io.checkpoint import CheckpointError
    from .runner import NothingToDo, RunInterrupted, RunOptions, run_scene, summary_json
    from .stages.guard import UnstableRunError

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
    if args.frames is not None and args.end_time is not None and not args.quiet:
        print(
            f"note: --frames {args.frames} wins over --end-time {args.end_time:g}: the run ends with frame "
            f"{args.frames}, at {args.frames} / output_rate"
        )
    try:
        summary = run_scene(scene, options)
    except (SceneError, CheckpointError) as exc:
        return _fail([_naming_file(line, scene.name, scene_path) for line in str(exc).splitlines()])
    except UnstableRunError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_UNSTABLE
    except NothingToDo as exc:
        print(exc)
        return 0
    except RunInterrupted as exc:
        # A second signal while the run stopped: what was written is kept, the state it stopped in is not.
        print(f"interrupted at once: {exc.outputs}", file=sys.stderr)
        return EXIT_SIGNAL_BASE + 2
    except KeyboardInterrupt:
        # A signal before the run had written anything (while it was built).
        print("interrupted before the first frame: nothing was written", file=sys.stderr)
        return EXIT_SIGNAL_BASE + 2
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
    if summary.interrupted_by is not None:
        print(
            f"interrupted at t = {summary.simulated_time:.9g} s (step {summary.steps}, after frame {summary.frame}); "
            f"resume with: {resume_command(argv, summary.checkpoints[-1])}",
            file=sys.stderr,
        )
        return EXIT_SIGNAL_BASE + summary.interrupted_by
    return 0


def resume_command(argv: list[str], checkpoint: Path) -> str:
    """The command line that continues a run: the same arguments, ``--restart`` the given checkpoint."""
    args = _without_option(argv, "--restart")
    return shlex.join(["python", "-m", "warpdem", *args, "--restart", str(checkpoint)])
