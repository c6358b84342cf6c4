"""``python -m warpdem preview STAGE``: pictures of a warpdem USD stage without a USD viewer (matplotlib, Agg).

Spheres are drawn as discs of their true radius, the rock surface as triangles shaded by their angle to the light,
both in the colours of the stage (``primvars:displayColor``), back to front (painter's order) in an orthographic
view: ``xz`` (front, looking along +y), ``xy`` (top), ``yz`` (side, looking along -x) or ``3d`` (from azimuth -60°,
elevation 25°). The view window is the same for every frame of one call, so an animation does not jump. Stages
with more spheres than ``max_spheres`` are drawn with a fixed random subset, and the picture says so.
"""

from __future__ import annotations

import math
import os
import pathlib
from dataclasses import dataclass

import numpy as np

VIEWS = ("xz", "xy", "yz", "3d")
DEFAULT_MAX_SPHERES = 200_000


class PreviewError(Exception):
    """A stage or an option that cannot be rendered (one readable line)."""


@dataclass
class StageFrame:
    """What one time code of a stage holds: sphere centres [m] (N, 3), radii [m] (N,), colours (N, 3); rock
    vertices [m] (P, 3), triangles (F, 3), colours (F, 3), one per triangle; the simulated time [s]."""

    code: int
    time: float
    centers: np.ndarray
    radii: np.ndarray
    sphere_colors: np.ndarray
    rock_points: np.ndarray
    rock_faces: np.ndarray
    rock_colors: np.ndarray


def camera(view: str) -> np.ndarray:
    """Rows: screen right, screen up, and toward the viewer (unit vectors), shape (3, 3)."""
    if view == "xz":
        return np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    if view == "xy":
        return np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    if view == "yz":
        return np.array([[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    az, el = math.radians(-60.0), math.radians(25.0)
    toward = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    right = np.array([-math.sin(az), math.cos(az), 0.0])
    return np.array([right, np.cross(toward, right), toward])


def open_stage(path: str | os.PathLike):
    """The stage at ``path``; PreviewError when it is missing or not USD."""
    from pxr import Usd

    if not pathlib.Path(path).is_file():
        raise PreviewError(f"{path}: file not found")
    if pathlib.Path(path).suffix.lower() not in (".usd", ".usda", ".usdc"):
        raise PreviewError(f"{path}: allowed suffixes: .usd, .usda, .usdc")
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception:  # pxr raises Tf.ErrorException, which has no stable import path; its text is C++ detail
        raise PreviewError(f"{path}: USD cannot open it (not a USD file, or a damaged one)") from None
    if stage is None:
        raise PreviewError(f"{path}: not a USD stage")
    return stage


def stage_frames(stage) -> list[int]:
    """Time codes of the stage, first to last."""
    return list(range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1))


def read_frame(stage, code: int) -> StageFrame:
    """The spheres and rock surface of one time code."""
    from pxr import UsdGeom

    def arr(attr, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        value = attr.Get(code) if attr and attr.HasValue() else None
        return np.zeros(shape, dtype) if value is None else np.asarray(value, dtype=dtype).reshape(-1, *shape[1:])

    world = stage.GetPrimAtPath("/World")
    time_attr = world.GetAttribute("warpdem:time") if world else None
    time = float(time_attr.Get(code)) if time_attr and time_attr.HasValue() else float(code)
    centers, radii, colors = np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3))
    prim = stage.GetPrimAtPath("/World/Particles")
    if prim and prim.IsA(UsdGeom.Points):
        points = UsdGeom.Points(prim)
        centers = arr(points.GetPointsAttr(), (0, 3))
        radii = 0.5 * arr(points.GetWidthsAttr(), (0,))
        colors = arr(points.GetDisplayColorPrimvar().GetAttr(), (0, 3))
        if len(colors) != len(centers):
            colors = np.tile([0.6, 0.6, 0.65], (len(centers), 1))
    rock_points, faces, rock_colors = np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    prim = stage.GetPrimAtPath("/World/Rock")
    if prim and prim.IsA(UsdGeom.Mesh):
        mesh = UsdGeom.Mesh(prim)
        rock_points = arr(mesh.GetPointsAttr(), (0, 3))
        faces = arr(mesh.GetFaceVertexIndicesAttr(), (0, 3), np.int64)
        primvar = mesh.GetDisplayColorPrimvar()
        rock_colors = arr(primvar.GetAttr(), (0, 3))
        if primvar.GetInterpolation() == UsdGeom.Tokens.vertex and len(rock_colors) == len(rock_points):
            rock_colors = rock_colors[faces].mean(axis=1)  # per-vertex colours: each triangle gets their mean
        if len(rock_colors) != len(faces):
            rock_colors = np.tile([0.6, 0.6, 0.65], (len(faces), 1))
    return StageFrame(code, time, centers, radii, colors, rock_points, faces, rock_colors)


def pick_frames(available: list[int], wanted: list[int] | None, default_all: bool) -> list[int]:
    """The time codes to draw: ``wanted`` (negative counts from the end, as Python indices), else all frames (at
    most 100, evenly spread) or the last one."""
    if not available:
        raise PreviewError("the stage has no frames")
    if wanted is None:
        if not default_all:
            return [available[-1]]
        picks = np.unique(np.linspace(0, len(available) - 1, min(100, len(available))).round().astype(int))
        return [available[k] for k in picks]
    out = []
    for w in wanted:
        code = available[w] if w < 0 and -w <= len(available) else w
        if code not in available:
            raise PreviewError(f"--frames: frame {w} is not in the stage (frames {available[0]}..{available[-1]})")
        out.append(code)
    return out


def _subset(n: int, max_spheres: int) -> np.ndarray:
    """Indices of the spheres to draw: all, or a fixed random subset of ``max_spheres`` (the same every frame)."""
    if n <= max_spheres:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, size=max_spheres, replace=False))


def _bounds(frames: list[StageFrame], cam: np.ndarray) -> tuple[float, float, float, float]:
    """The screen window (u0, u1, v0, v1) [m] that holds every drawn body of every frame, with a margin."""
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for f in frames:
        if len(f.centers):
            uv = f.centers @ cam[:2].T
            lo = np.minimum(lo, (uv - f.radii[:, None]).min(axis=0))
            hi = np.maximum(hi, (uv + f.radii[:, None]).max(axis=0))
        if len(f.rock_faces):
            uv = f.rock_points[np.unique(f.rock_faces)] @ cam[:2].T
            lo, hi = np.minimum(lo, uv.min(axis=0)), np.maximum(hi, uv.max(axis=0))
    if not np.all(np.isfinite(lo)):
        lo, hi = np.zeros(2), np.ones(2)
    span = np.maximum(hi - lo, 1e-9)
    lo, hi = lo - 0.04 * span, hi + 0.04 * span
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _fit(window: tuple[float, float, float, float], aspect: float) -> tuple[float, float, float, float]:
    """The window widened in one direction, about its centre, to the picture's aspect (width / height)."""
    u0, u1, v0, v1 = window
    du, dv = u1 - u0, v1 - v0
    if du / dv < aspect:
        grow = 0.5 * (dv * aspect - du)
        return u0 - grow, u1 + grow, v0, v1
    grow = 0.5 * (du / aspect - dv)
    return u0, u1, v0 - grow, v1 + grow


def draw_frame(ax, frame: StageFrame, cam: np.ndarray, max_spheres: int) -> str | None:
    """Draw one frame into a matplotlib axes. Returns the note on subsampling, or None."""
    from matplotlib.collections import EllipseCollection, PolyCollection

    toward = cam[2]
    if len(frame.rock_faces):
        p = frame.rock_points
        tri = p[frame.rock_faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normal, axis=1)
        # Faces point out of the rock: those turned away from the viewer are hidden behind the front ones.
        front = (normal @ toward > 0.0) & (length > 0.0)
        colors = frame.rock_colors
        light = toward + 0.6 * cam[1] - 0.3 * cam[0]
        light /= np.linalg.norm(light)
        shade = 0.35 + 0.65 * np.clip((normal[front] / length[front, None]) @ light, 0.0, 1.0)
        depth = tri[front].mean(axis=1) @ toward
        order = np.argsort(depth)
        polys = (tri[front] @ cam[:2].T)[order]
        face_colors = np.clip(colors[front] * shade[:, None], 0.0, 1.0)[order]
        ax.add_collection(
            PolyCollection(polys, facecolors=face_colors, edgecolors=face_colors, linewidths=0.2, zorder=1)
        )
    note = None
    n = len(frame.centers)
    if n:
        keep = _subset(n, max_spheres)
        if len(keep) < n:
            note = f"showing {len(keep):,} of {n:,} spheres (random subset)"
        centers, radii, colors = frame.centers[keep], frame.radii[keep], frame.sphere_colors[keep]
        order = np.argsort(centers @ toward)
        uv = (centers @ cam[:2].T)[order]
        d = 2.0 * radii[order]
        c = np.clip(colors[order], 0.0, 1.0)
        ax.add_collection(
            EllipseCollection(
                d,
                d,
                np.zeros(len(d)),
                units="xy",
                offsets=uv,
                offset_transform=ax.transData,
                facecolors=c,
                edgecolors=0.55 * c,
                linewidths=0.3,
                zorder=2,
            )
        )
    return note


def parse_size(text: str) -> tuple[int, int]:
    """``"640x480"`` → (640, 480); PreviewError otherwise."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise PreviewError(f"--size: expected WIDTHxHEIGHT in pixels, e.g. 640x480 (got {text!r})") from None
    if not (16 <= w <= 8000 and 16 <= h <= 8000):
        raise PreviewError(f"--size: each side must be 16..8000 pixels (got {text!r})")
    return w, h


def render(
    stage_path: str | os.PathLike,
    out_dir: str | os.PathLike | None = None,
    frames: list[int] | None = None,
    view: str = "3d",
    size: tuple[int, int] = (640, 480),
    gif: bool = False,
    max_spheres: int = DEFAULT_MAX_SPHERES,
    fps: float = 10.0,
) -> list[pathlib.Path]:
    """Render frames of a stage to PNG files (and an animated GIF of them).

    Args:
        stage_path: the USD stage. out_dir: where the pictures go [the stage's folder]. frames: time codes
            (negative from the end) [the last; with ``gif``, all, at most 100]. view: one of :data:`VIEWS`.
            size: picture size (width, height) [pixels]. gif: also write ``<stem>_<view>.gif``.
            max_spheres: draw at most this many spheres. fps: GIF frame rate [frames/s].

    Returns:
        The files written: one ``<stem>_<view>_<code:06d>.png`` per frame, then the GIF.

    Raises:
        PreviewError: missing or unreadable stage, a frame it lacks, an unknown view.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if view not in VIEWS:
        raise PreviewError(f"--view: {view!r} is not one of {', '.join(VIEWS)}")
    stage_path = pathlib.Path(stage_path)
    stage = open_stage(stage_path)
    codes = pick_frames(stage_frames(stage), frames, gif)
    data = [read_frame(stage, code) for code in codes]
    cam = camera(view)
    width, height = size
    u0, u1, v0, v1 = _fit(_bounds(data, cam), width / height)
    out = pathlib.Path(out_dir) if out_dir is not None else stage_path.parent
    out.mkdir(parents=True, exist_ok=True)
    stem = stage_path.stem
    written, images = [], []
    for frame in data:
        fig = plt.figure(figsize=(width / 100.0, height / 100.0), dpi=100)
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.set_facecolor((0.97, 0.97, 0.98))
        note = draw_frame(ax, frame, cam, max_spheres)
        # The axes fill the picture and the window has its aspect: one metre is as long across as up.
        ax.set_xlim(u0, u1)
        ax.set_ylim(v0, v1)
        ax.set_xticks([])
        ax.set_yticks([])
        label = f"{stem}   frame {frame.code}   t = {frame.time:.4g} s   view {view}"
        ax.text(0.01, 0.99, label, transform=ax.transAxes, va="top", fontsize=8, color="0.15")
        if note:
            ax.text(0.01, 0.01, note, transform=ax.transAxes, va="bottom", fontsize=8, color="0.15")
        _scale_bar(ax, u0, u1, v0)
        path = out / f"{stem}_{view}_{frame.code:06d}.png"
        tmp = path.with_name(f"{path.stem}.partial.png")
        fig.savefig(tmp, dpi=100)
        os.replace(tmp, path)
        written.append(path)
        if gif:
            fig.canvas.draw()
            images.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
    if gif:
        from PIL import Image

        path = out / f"{stem}_{view}.gif"
        tmp = path.with_name(f"{path.stem}.partial.gif")
        first, *rest = [Image.fromarray(im).quantize(colors=128) for im in images]
        first.save(tmp, save_all=True, append_images=rest, duration=int(1000 / fps), loop=0)
        os.replace(tmp, path)
        written.append(path)
    return written


def _scale_bar(ax, u0: float, u1: float, v0: float) -> None:
    """A bar of a round length (1, 2 or 5 × 10^k m) near the lower right corner."""
    span = u1 - u0
    target = 0.2 * span
    k = math.floor(math.log10(target))
    length = max(m * 10.0**k for m in (1, 2, 5) if m * 10.0**k <= target)
    x1 = u1 - 0.03 * span
    y = v0 + 0.03 * (ax.get_ylim()[1] - v0)
    ax.plot([x1 - length, x1], [y, y], color="0.15", lw=2, zorder=3)
    ax.text(x1 - 0.5 * length, y, f"{length:g} m", ha="center", va="bottom", fontsize=8, color="0.15", zorder=3)
