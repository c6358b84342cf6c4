"""``plot`` and ``preview`` (warpdem/io/plot.py, warpdem/io/preview.py): pictures of a sphere, a mesh and a mixed run.

Oracles (pixel statistics, not golden images):
- every PNG has the requested size and is not blank: more than ``MIN_INK`` of its pixels differ from the background;
- a disc is as large as its sphere: one sphere of radius r drawn in a window of width W [m] over w pixels covers
  π (r w / W)² pixels, up to its anti-aliased rim (± the perimeter 2π r w / W, one pixel wide);
- a stage with more spheres than ``max_spheres`` is drawn with that many and says so; the GIF has one image per frame;
- bad input (missing stage, folder without a series) exits with status 2 and one line;
- the colour keys: the scale a key reads back from a frame's colours is the one the run coloured it with, the
  largest value so far in the run (recomputed here from the stage's own values, frame by frame), to ``SCALE_RTOL``;
  a stage coloured on a scale the test chose gets a key of that scale, whose bar runs from 0 to it (in the unit the
  title names) and whose end pixels in the PNG have the colours of the scale's ends, to ``PIXEL_TOL``.
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.image as mpimg
import numpy as np
import pytest
from PIL import Image

from warpdem.cli import main
from warpdem.io.output import damage_colors, ramp_colors
from warpdem.io.plot import plot_run
from warpdem.io.preview import (
    PART_PALETTE,
    ColorKey,
    PreviewError,
    _bounds,
    _fit,
    _font_size,
    bar_rect,
    camera,
    color_keys,
    draw_frame,
    draw_key,
    key_title,
    legend_height,
    read_frame,
    recolor,
    render,
)
from warpdem.io.usd import SurfaceFrame, UsdWriter
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import parse_scene

MIN_INK = 0.01  # fraction of pixels that must differ from the background
SCALE_RTOL = 1e-4  # float32 colours and values: value / t is good to ~1e-5 where t >= 0.02
PIXEL_TOL = 0.02  # 8-bit PNG (0.004) plus the bar's first and last bin (1/256 of the scale from its ends)

ROCK = {"density": 2600.0, "youngs_modulus": 5.0e7, "poisson_ratio": 0.25}
BEADS = {
    "kind": "packing",
    "part": "beads",
    "region": {"box": {"lo": [0.1, 0.1, 1.05], "hi": [0.4, 0.4, 1.15]}},
    "radius": 0.02,
    "arrangement": "hcp",
}
BOX = {"kind": "box", "lo": [0.0, 0.0, 0.0], "hi": [1.0, 0.5, 1.0], "divisions": [2, 1, 2], "material": "rock"}
SCENES = {
    "spheres": {
        "run": {"end_time": 1.0, "output_rate": 100.0},
        "materials": {"rock": ROCK},
        "parts": {"beads": {"material": "rock"}},
        "particles": [BEADS],
        "walls": [{"kind": "plane", "point": [0, 0, 1.0], "normal": [0, 0, 1], "material": "rock"}],
    },
    "mesh": {
        "run": {"end_time": 1.0, "output_rate": 1000.0},
        "materials": {"rock": ROCK},
        "mesh": {**BOX, "velocity": [0.0, 0.0, -0.5]},
        "boundaries": [{"faces": "z-", "kind": "fixed"}],
    },
    "mixed": {
        "run": {"end_time": 1.0, "output_rate": 100.0},
        "materials": {"rock": ROCK},
        "parts": {"beads": {"material": "rock"}},
        "particles": [BEADS],
        "mesh": BOX,
        "boundaries": [{"faces": "z-", "kind": "fixed"}],
    },
}


@pytest.fixture(scope="module", params=sorted(SCENES))
def run(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param)
    scene = parse_scene({"name": request.param, **SCENES[request.param]})
    return run_scene(scene, RunOptions(device="cpu", frames=2, out_dir=out, quiet=True)), out


def ink(path, size: tuple[int, int]) -> float:
    """Fraction of the pixels of a PNG that differ from its corner pixel (the background); checks the size."""
    image = mpimg.imread(path)
    assert image.shape[:2] == (size[1], size[0]), path
    rgb = image[..., :3]
    return float(np.mean(np.any(np.abs(rgb - rgb[0, 0]) > 0.02, axis=-1)))


def test_plot_writes_the_energy_counts_and_force_pictures(run):
    summary, out = run
    files = plot_run(out, size=(400, 300))
    names = {f.name.removeprefix(f"{out.name}_") for f in files}
    name = summary.usd_path.stem
    expected = {f"{name}_energy.png", f"{name}_counts.png"}
    if name == "spheres":  # the only one with a wall
        expected.add(f"{name}_forces.png")
    assert {f.name for f in files} == expected, names
    for f in files:
        assert ink(f, (400, 300)) > MIN_INK, f


@pytest.mark.parametrize("view", ["xz", "3d"])
def test_preview_draws_every_frame_asked(run, view):
    summary, out = run
    files = render(summary.usd_path, out / "pictures", frames=[0, -1], view=view, size=(320, 240))
    assert [f.name for f in files] == [f"{summary.usd_path.stem}_{view}_{k:06d}.png" for k in (0, 2)]
    for f in files:
        assert ink(f, (320, 240)) > 5 * MIN_INK, f


def test_the_command_line_draws_what_render_draws_with_the_same_options(run, tmp_path, capsys):
    """``preview --color-by --scale --window --no-legend`` forwards each option to render: the pictures are the same
    bytes as render's with those arguments (oracle: the function the command wraps); a window that is not
    LEFT < RIGHT, BOTTOM < TOP is refused by the parser, naming the option (exit 2)."""
    from warpdem.cli import main

    summary, _ = run
    options = {"color_by": "speed", "scale": 2.0, "window": (-0.5, 0.5, -0.5, 0.5), "legend": False}
    (direct,) = render(summary.usd_path, tmp_path / "direct", frames=[-1], view="xz", size=(200, 150), **options)
    argv = ["preview", str(summary.usd_path), "--frames", "-1", "--view", "xz", "--size", "200x150"]
    argv += ["--out", str(tmp_path / "cli"), "--color-by", "speed", "--scale", "2", "--window=-0.5,0.5,-0.5,0.5"]
    assert main([*argv, "--no-legend"]) == 0
    assert (tmp_path / "cli" / direct.name).read_bytes() == direct.read_bytes()
    with pytest.raises(SystemExit) as exc:
        main([*argv[:-1], "0.5,-0.5,-0.5,0.5"])
    assert exc.value.code == 2
    assert "--window" in capsys.readouterr().err


def test_disc_covers_the_area_of_its_sphere(tmp_path):
    radius = 0.1
    path = tmp_path / "one.usda"
    with UsdWriter(path, 10.0) as usd:
        # A red sphere at the origin and a tiny one 2 m away, which sets the window's width.
        usd.write_frame(
            time=0.0,
            positions=np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.5]]),
            radii=np.array([radius, 1e-4]),
            velocities=np.zeros((2, 3)),
            ids=np.array([0, 1]),
            colors=np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
        )
    (png,) = render(path, tmp_path, view="xz", size=(400, 300))
    image = mpimg.imread(png)[..., :3]
    red = np.sum((image[..., 0] > 0.5) & (image[..., 1] < 0.3) & (image[..., 2] < 0.3))
    from pxr import Usd

    u0, u1, _, _ = _fit(_bounds([read_frame(Usd.Stage.Open(str(path)), 0)], camera("xz")), 400 / 300)
    r_px = radius * 400 / (u1 - u0)
    assert r_px > 10.0  # large enough for the area to mean something
    assert abs(red - math.pi * r_px**2) < 2.0 * math.pi * r_px, (red, math.pi * r_px**2)


def test_large_stage_is_subsampled_and_says_so(tmp_path):
    import matplotlib.pyplot as plt

    n = 50
    path = tmp_path / "cloud.usdc"
    rng = np.random.default_rng(1)
    with UsdWriter(path, 10.0) as usd:
        for k in range(3):
            usd.write_frame(
                time=0.1 * k,
                positions=rng.random((n, 3)),
                radii=np.full(n, 0.01),
                velocities=np.zeros((n, 3)),
                ids=np.arange(n),
                colors=np.full((n, 3), 0.5),
            )
    from pxr import Usd

    frame = read_frame(Usd.Stage.Open(str(path)), 1)
    fig, ax = plt.subplots()
    note = draw_frame(ax, frame, camera("3d"), max_spheres=10)
    assert note == "showing 10 of 50 spheres (random subset)"
    assert len(ax.collections[0].get_offsets()) == 10
    plt.close(fig)
    files = render(path, tmp_path, gif=True, size=(200, 150), max_spheres=10)
    assert [f.suffix for f in files] == [".png"] * 3 + [".gif"]
    with Image.open(files[-1]) as gif:
        assert gif.n_frames == 3 and gif.size == (200, 150)


def test_bad_input_exits_with_status_2(tmp_path, capsys):
    (tmp_path / "text.usda").write_text("not usd\n")
    assert main(["preview", str(tmp_path / "absent.usdc")]) == 2
    assert main(["preview", str(tmp_path / "text.usda")]) == 2
    assert main(["plot", str(tmp_path)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [
        f"error: {tmp_path / 'absent.usdc'}: file not found",
        f"error: {tmp_path / 'text.usda'}: USD cannot open it (not a USD file, or a damaged one)",
        f"error: {tmp_path}: no *_series.csv here (the time series a run writes next to its USD stage)",
    ]
    assert not list(tmp_path.glob("*.png"))


def open_stage(path):
    from pxr import Usd

    return Usd.Stage.Open(str(path))


def test_keys_read_back_the_runs_scale(run):
    """The runs colour spheres by speed and the rock by von Mises stress, each on the largest value so far."""
    summary, _ = run
    stage = open_stage(summary.usd_path)
    top = {"spheres": 0.0, "rock": 0.0}
    for code in range(3):
        frame = read_frame(stage, code)
        keys = {k.body: k for k in color_keys(frame)}
        expected = {}
        if len(frame.centers):
            top["spheres"] = max(top["spheres"], float(frame.sphere_values["speed"].max()))
            expected["spheres"] = ("speed", top["spheres"])
        if len(frame.rock_faces):
            top["rock"] = max(top["rock"], float(frame.rock_values["vonMisesStress"].max()))
            expected["rock"] = ("stress", top["rock"])
        assert set(keys) == set(expected), (code, keys)
        for body, (quantity, scale) in expected.items():
            assert keys[body].quantity == quantity
            assert not keys[body].clipped
            np.testing.assert_allclose(keys[body].scale, scale, rtol=SCALE_RTOL, atol=1e-12)


def test_recolor_by_speed_uses_the_largest_speed_drawn(run):
    summary, _ = run
    stage = open_stage(summary.usd_path)
    frames = [read_frame(stage, code) for code in (1, 2)]
    # What is drawn: every sphere, the rock surface's vertices (not the nodes inside the rock).
    speeds = [f.sphere_values["speed"] for f in frames if len(f.centers)]
    speeds += [f.rock_values["speed"][np.unique(f.rock_faces)] for f in frames if len(f.rock_faces)]
    recolor(frames, "speed")
    for frame in frames:
        (key,) = color_keys(frame)  # one scale for both bodies: one key
        assert key.quantity == "speed"
        np.testing.assert_allclose(key.scale, max(float(v.max()) for v in speeds), rtol=SCALE_RTOL)
    if not any(len(f.rock_faces) for f in frames):
        with pytest.raises(PreviewError, match="hold no von Mises stress"):
            recolor(frames, "stress")


def write_stage(path, colors: np.ndarray, speed: np.ndarray, surface: SurfaceFrame | None = None) -> None:
    """One frame: spheres in a row along x moving along z at ``speed`` [m/s], in ``colors``, and ``surface``."""
    n = len(speed)
    with UsdWriter(path, 10.0) as usd:
        usd.write_frame(
            time=0.0,
            positions=np.stack([np.linspace(0.0, 1.0, n), np.zeros(n), np.zeros(n)], axis=1),
            radii=np.full(n, 0.5 / n),
            velocities=np.stack([np.zeros(n), np.zeros(n), speed], axis=1),
            ids=np.arange(n),
            colors=colors,
            surface=surface,
        )


def bar_ends(png, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The colours at the two ends of the colour bar of a one-key picture: the pixels 3 columns inside its ends,
    on the row through its middle (where render's layout, preview.bar_rect, puts it)."""
    image = mpimg.imread(png)[..., :3].astype(np.float64)
    width, height = size
    x, y, w, h = bar_rect((0.0, 0.0, 1.0, legend_height(size) / height), _font_size(size), height)
    row = height - 1 - round((y + 0.5 * h) * height)  # image rows run down, figure fractions up
    return image[row, math.ceil(x * width) + 3], image[row, math.floor((x + w) * width) - 4]


@pytest.mark.parametrize("quantity", ["speed", "damage"])
def test_legend_bar_spans_the_scale_of_the_colours(tmp_path, quantity):
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(3)
    if quantity == "speed":
        scale = 7.5  # the run's largest speed so far: above every speed of this frame
        speed = rng.uniform(0.0, 6.0, 40)
        colors, ends = ramp_colors(speed, scale), ramp_colors(np.array([0.0, scale]), scale)
    else:
        scale, speed = 1.0, rng.uniform(0.0, 3.0, 40)
        colors, ends = damage_colors(rng.uniform(0.0, 1.0, 40)), damage_colors(np.array([0.0, 1.0]))
    path = tmp_path / f"{quantity}.usda"
    write_stage(path, colors, speed)
    (key,) = color_keys(read_frame(open_stage(path), 0))
    assert (key.body, key.quantity) == ("spheres", quantity)
    np.testing.assert_allclose(key.scale, scale, rtol=SCALE_RTOL)
    size = (480, 360)
    (png,) = render(path, tmp_path, view="xz", size=size)
    left, right = bar_ends(png, size)
    np.testing.assert_allclose(left, ends[0], atol=PIXEL_TOL)
    np.testing.assert_allclose(right, ends[1], atol=PIXEL_TOL)
    fig = plt.figure(figsize=(4.8, 3.6), dpi=100)
    cax = draw_key(fig, key, (0.0, 0.0, 1.0, 0.2), 8.0)
    np.testing.assert_allclose(cax.get_xlim(), (0.0, scale), rtol=SCALE_RTOL)
    assert cax.get_xticklabels()[-1].get_text() == f"{scale:.3g}"
    plt.close(fig)


def test_recolor_in_a_window_scales_by_what_it_shows(tmp_path):
    speed = np.linspace(1.0, 8.0, 8)  # spheres along x from 0 to 1 m, the faster the further
    path = tmp_path / "row.usda"
    write_stage(path, ramp_colors(speed, 8.0), speed)
    frame = read_frame(open_stage(path), 0)
    recolor([frame], "speed", inside=lambda points: points[:, 0] < 0.5)
    (key,) = color_keys(frame)
    np.testing.assert_allclose(key.scale, speed[frame.centers[:, 0] < 0.5].max(), rtol=SCALE_RTOL)
    assert key.clipped  # the spheres outside are faster: the red end reads "≥"


def test_stress_key_in_megapascals(tmp_path):
    import matplotlib.pyplot as plt

    # A square of two triangles whose von Mises stresses were coloured on a 30 MPa scale.
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    von_mises = np.array([1.2e7, 2.4e7])
    surface = SurfaceFrame(
        points=points,
        faces=faces,
        velocities=np.zeros((4, 3)),
        von_mises=von_mises,
        max_principal=von_mises,
        colors=ramp_colors(von_mises, 3.0e7),
        fragment=np.array([0, 0, 1, 1]),  # per vertex, beside colours per triangle: not fragment colours
    )
    path = tmp_path / "stress.usda"
    write_stage(path, ramp_colors(np.array([0.0, 1.0]), 2.0), np.array([0.0, 1.0]), surface)
    keys = color_keys(read_frame(open_stage(path), 0))
    assert [(k.body, k.quantity) for k in keys] == [("spheres", "speed"), ("rock", "stress")]
    np.testing.assert_allclose([k.scale for k in keys], [2.0, 3.0e7], rtol=SCALE_RTOL)
    assert key_title(keys[1]) == ("rock: von Mises stress [MPa]", "MPa", 1e6)
    fig = plt.figure(figsize=(6.4, 4.8), dpi=100)
    cax = draw_key(fig, keys[1], (0.5, 0.0, 0.5, 0.1), 8.0)
    np.testing.assert_allclose(cax.get_xlim(), (0.0, 30.0), rtol=SCALE_RTOL)
    plt.close(fig)


def test_part_and_unknown_colours(tmp_path):
    path = tmp_path / "parts.usda"
    write_stage(path, PART_PALETTE[[0, 0, 0, 1]], np.zeros(4))
    (key,) = color_keys(read_frame(open_stage(path), 0), part_names=["slab", "ball"])
    assert key == ColorKey(
        "spheres", "part", swatches=[("slab", tuple(PART_PALETTE[0])), ("ball", tuple(PART_PALETTE[1]))], count=2
    )
    # Colours on none of warpdem's scales get no key, and the view fills the picture.
    write_stage(tmp_path / "odd.usda", np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.array([1.0, 2.0]))
    assert color_keys(read_frame(open_stage(tmp_path / "odd.usda"), 0)) == []
