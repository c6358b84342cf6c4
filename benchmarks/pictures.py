"""Redraw the pictures of docs/ that show a scene, and the default scene's energy plot, from the runs' USD stages and
time series: ``python benchmarks/pictures.py [PICTURE ...] [--runs DIR ...] [--work DIR] [--docs DIR]``.

Every picture is one :class:`Picture` in :data:`PICTURES`, which records how it is drawn: the scene, the frame (time
code) of its stage, the view, the colour mode, the size and the part of the view drawn, with the preview options of
warpdem.io.preview.render (``python -m warpdem preview STAGE --frames F --view V --size WxH`` draws the same frame in
the stage's colours). The colour keys a picture must show are recorded too, and checked before it is written, so a
stage coloured otherwise (a default-scene stage coloured by part) is refused rather than drawn under a caption that
says damage.

The stages: ``RUNS/<scene>/<scene>.usdc`` for each ``--runs`` folder in turn (``python benchmarks/scene_table.py --keep
DIR`` lays its runs out so, each scene run to its end as a user runs it). A scene whose stage is in none of them, or
ends before the frame drawn, is run here, one scene at a time: ``python -m warpdem scenes/<scene>.toml --frames F
--out WORK/<scene>``, F the last frame any of its pictures draws (frames of a run do not depend on where it stops).
The default scene's pictures need ``color_by = "damage"``: its run uses a copy of the embedded scene
(warpdem/data/default.toml) with that one line changed, which changes the colours only, and runs to its end
(``python -m warpdem WORK/default_beam_impact.toml --out WORK/default_beam_impact``), since the energy plot covers the
whole run. ``docs/facility_sections.png`` is drawn by ``benchmarks/facility_scenes.py --picture`` (sections of the
rigid blocks, not a stage) and is left alone here.

For each picture written, one line says what it shows: the frame, its simulated time and the colour keys with their
scales (the facts a caption quotes).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = "default_beam_impact"
"""The embedded default scene (warpdem/data/default.toml), named as its stage is."""


@dataclass(frozen=True)
class Picture:
    """How one picture of docs/ is drawn.

    Attributes:
        name: the file, ``docs/<name>.png``.
        scene: the scene (``scenes/<scene>.toml``, or :data:`DEFAULT_SCENE`).
        frame: the time code of the stage drawn; None for the energy plot (the whole series).
        view: preview's view (``xz``, ``xy``, ``yz``, ``3d``).
        size: picture size (width, height) [pixels].
        color_by: preview's colour mode (``stage``: the run's own colours, on its largest value so far).
        keys: the colour keys the picture must show, as (body, quantity) in preview's order (spheres, then rock).
        window: the part of the view drawn, (left, right, bottom, top) [m] along the view's screen axes; None draws
            everything, with a margin.
        part_names: the scene's part names by part id (the order of first use in ``[[particles]]``), for the
            swatches of ``color_by = "part"``.
    """

    name: str
    scene: str
    frame: int | None
    view: str = "3d"
    size: tuple[int, int] = (640, 480)
    color_by: str = "stage"
    keys: tuple[tuple[str, str], ...] = ()
    window: tuple[float, float, float, float] | None = None
    part_names: tuple[str, ...] | None = None


PICTURES = [
    Picture("default_beam_impact", DEFAULT_SCENE, 4, "xz", keys=(("spheres", "damage"),)),
    Picture("default_beam_impact_energy", DEFAULT_SCENE, None, size=(800, 600)),
    Picture("granular_pour", "granular_pour", 15, keys=(("spheres", "speed"),)),
    Picture("bonded_slab_impact", "bonded_slab_impact", 10, keys=(("spheres", "part"),), part_names=("slab", "ball")),
    Picture("wave_column", "wave_column", 12, keys=(("rock", "stress"),)),
    Picture("jointed_slope", "jointed_slope", 16, keys=(("rock", "speed"),)),
    Picture("tunnel_jointed_rock", "tunnel_jointed_rock", 5, keys=(("rock", "stress"),)),
    Picture("tunnel_jointed_rock_nonpersistent", "tunnel_jointed_rock_nonpersistent", 5, keys=(("rock", "stress"),)),
    Picture("pmma_plate", "pmma_plate", 7, "xy", keys=(("rock", "stress"),)),
    Picture("pmma_plate_remote", "pmma_plate_remote", 17, "xy", color_by="damage", keys=(("rock", "damage"),)),
    Picture("pmma_plate_branching", "pmma_plate_branching", 11, "xy", keys=(("rock", "damage"),)),
    Picture("brazilian_disc", "brazilian_disc", 15, "xz", keys=(("rock", "damage"),)),
    Picture("boulder_impact", "boulder_impact", 9, "xz", keys=(("spheres", "speed"), ("rock", "stress"))),
    # The last frame, 1 s, recoloured on the largest speed in the window (faster pieces above it are drawn red):
    # the run's own colours are on the blast's speeds of the first milliseconds, on which everything at 1 s is
    # blue. The window: the slab (x -0.3 .. 11 m, z 0 .. 15 m) and up to 20 m above its foot; the courses thrown
    # higher would shrink the slab to a strip.
    Picture(
        "limestone_tunnel",
        "limestone_tunnel",
        250,
        "xz",
        size=(640, 1150),
        color_by="speed",
        keys=(("rock", "speed"),),
        window=(-0.8, 11.5, -0.5, 20.5),
    ),
    Picture("masonry_wall_blast", "masonry_wall_blast", 30, "xz", keys=(("spheres", "speed"), ("rock", "stress"))),
    Picture("masonry_tunnel_blast", "masonry_tunnel_blast", 12, "xz", keys=(("spheres", "speed"), ("rock", "stress"))),
    Picture("dam_crest_blast", "dam_crest_blast", 10, keys=(("spheres", "speed"), ("rock", "stress"))),
    Picture(
        "dam_crest_blast_crater",
        "dam_crest_blast",
        10,
        "xz",
        keys=(("spheres", "speed"), ("rock", "stress")),
        window=(-9.0, 9.0, 50.0, 64.0),
    ),
]

NOT_FROM_STAGES = {
    "facility_sections": "benchmarks/facility_scenes.py --end-time 0.2 --picture docs/facility_sections.png"
}


def default_scene_copy(work: Path) -> Path:
    """The embedded default scene with ``color_by = "damage"`` instead of ``"part"`` (colours only), in ``work``."""
    from warpdem.scene import default_scene_path

    text = default_scene_path().read_text()
    line = 'color_by = "part"\n'
    if text.count(line) != 1:
        raise SystemExit(f"{default_scene_path()}: expected one line {line.strip()!r} to change to damage")
    path = work / f"{DEFAULT_SCENE}.toml"
    work.mkdir(parents=True, exist_ok=True)
    path.write_text(text.replace(line, 'color_by = "damage"\n'))
    return path


def stage_frames(path: Path) -> int:
    """The last time code of a stage (-1 when it cannot be opened)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    return int(stage.GetEndTimeCode()) if stage else -1


def find_run(scene: str, runs: list[Path], frame: int | None) -> Path | None:
    """The first run folder that holds the scene's stage up to ``frame`` (to its end for None: a series is
    needed, with a summary.json beside it as scene_table's kept runs have, or the stage's own end)."""
    for base in runs:
        folder = base / scene
        stage = folder / f"{scene}.usdc"
        if not stage.is_file():
            continue
        if frame is None:
            if (folder / f"{scene}_series.csv").is_file():
                return folder
        elif stage_frames(stage) >= frame:
            return folder
    return None


def run_scene(scene: str, frame: int | None, work: Path) -> Path:
    """Run a scene here to ``frame`` (to its end for None) into ``work/<scene>``; returns that folder."""
    out = work / scene
    path = default_scene_copy(work) if scene == DEFAULT_SCENE else ROOT / "scenes" / f"{scene}.toml"
    command = [sys.executable, "-m", "warpdem", str(path), "--out", str(out), "--quiet"]
    if frame is not None:
        command += ["--frames", str(frame)]
    print(f"running: {' '.join(command)}", flush=True)
    subprocess.run(command, cwd=ROOT, check=True)
    return out


def draw(picture: Picture, folder: Path, docs: Path) -> str:
    """Draw one picture from a run folder into ``docs``; returns the line saying what it shows."""
    from warpdem.io.plot import plot_energy
    from warpdem.io.preview import color_keys, in_window, key_title, open_stage, read_frame, recolor, render
    from warpdem.io.timeseries import read_series

    target = docs / f"{picture.name}.png"
    if picture.frame is None:
        data = read_series(folder / f"{picture.scene}_series.csv")
        plot_energy(data, picture.scene, target, picture.size)
        books = data["energy_error"]
        return (
            f"{target}: energy of {folder}, t = 0 .. {data['time'][-1]:.4g} s, books {books[-1]:+.2g} at the end, "
            f"largest {books[abs(books).argmax()]:+.2g}"
        )
    stage_path = folder / f"{picture.scene}.usdc"
    frame = read_frame(open_stage(stage_path), picture.frame)
    # The keys as render makes them (the same recolouring, in the same window), to check and report them.
    recolor(
        [frame], picture.color_by, None, None if picture.window is None else in_window(picture.view, picture.window)
    )
    names = list(picture.part_names) if picture.part_names else None
    keys = color_keys(frame, names)
    found = tuple((k.body, k.quantity) for k in keys)
    if found != picture.keys:
        raise SystemExit(
            f"{picture.name}: the stage {stage_path} frame {picture.frame} shows {found or 'no known colour scale'}, "
            f"the picture needs {picture.keys}"
        )
    with tempfile.TemporaryDirectory() as tmp:
        (png,) = render(
            stage_path,
            tmp,
            frames=[picture.frame],
            view=picture.view,
            size=picture.size,
            color_by=picture.color_by,
            window=picture.window,
            part_names=names,
        )
        shutil.copyfile(png, target)
    shown = []
    for key in keys:
        title, unit, size = key_title(key)
        if key.quantity in ("speed", "stress"):
            top = f"{'≥ ' if key.clipped else ''}{key.scale / size:.3g}"
            shown.append(f"{title.split(' [')[0]} 0 .. {top} {unit}")
        elif key.quantity == "damage":
            shown.append(f"{title.split(' [')[0]} 0 .. 1")
        else:
            shown.append(f"{title} ({', '.join(label for label, _ in key.swatches[:6])})")
    return f"{target}: {stage_path} frame {picture.frame}, t = {frame.time:.4g} s, view {picture.view}; " + "; ".join(
        shown
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    names = [p.name for p in PICTURES]
    parser.add_argument("pictures", nargs="*", metavar="PICTURE", help=f"one of {', '.join(names)} [all]")
    parser.add_argument(
        "--runs", type=Path, nargs="+", default=[], help="folders holding <scene>/<scene>.usdc (scene_table --keep)"
    )
    parser.add_argument(
        "--work", type=Path, default=ROOT / "out" / "pictures", help="where scenes run here go [%(default)s]"
    )
    parser.add_argument("--docs", type=Path, default=ROOT / "docs", help="where the pictures go [%(default)s]")
    args = parser.parse_args(argv)
    unknown = [p for p in args.pictures if p not in names]
    if unknown:
        extra = f" ({NOT_FROM_STAGES[unknown[0]]} draws it)" if unknown[0] in NOT_FROM_STAGES else ""
        parser.error(f"unknown picture {unknown[0]!r}{extra}; allowed: {', '.join(names)}")
    chosen = [p for p in PICTURES if not args.pictures or p.name in args.pictures]
    args.docs.mkdir(parents=True, exist_ok=True)
    # A scene runs here once, to the last frame its pictures need (to its end if one needs the whole series).
    need: dict[str, int | None] = {}
    for p in chosen:
        if p.scene not in need:
            need[p.scene] = p.frame
        elif need[p.scene] is None or p.frame is None:
            need[p.scene] = None
        else:
            need[p.scene] = max(need[p.scene], p.frame)
    folders = {}
    for scene, frame in need.items():
        folder = find_run(scene, [*args.runs, args.work], frame)
        folders[scene] = folder if folder is not None else run_scene(scene, frame, args.work)
    for p in chosen:
        print(draw(p, folders[p.scene], args.docs), flush=True)
    if not args.pictures:
        for name, command in NOT_FROM_STAGES.items():
            print(f"{args.docs / name}.png: not from a stage; drawn by {command}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "Agg")
    raise SystemExit(main())
