"""``plot`` and ``preview`` (warpdem/io/plot.py, warpdem/io/preview.py): pictures of a sphere, a mesh and a mixed run.

Oracles (pixel statistics, not golden images):
- every PNG has the requested size and is not blank: more than ``MIN_INK`` of its pixels differ from the background;
- a disc is as large as its sphere: one sphere of radius r drawn in a window of width W [m] over w pixels covers
  π (r w / W)² pixels, up to its anti-aliased rim (± the perimeter 2π r w / W, one pixel wide);
- a stage with more spheres than ``max_spheres`` is drawn with that many and says so; the GIF has one image per frame;
- bad input (missing stage, folder without a series) exits with status 2 and one line.
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
from warpdem.io.plot import plot_run
from warpdem.io.preview import _bounds, _fit, camera, draw_frame, read_frame, render
from warpdem.io.usd import UsdWriter
from warpdem.runner import RunOptions, run_scene
from warpdem.scene import parse_scene

MIN_INK = 0.01  # fraction of pixels that must differ from the background

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
