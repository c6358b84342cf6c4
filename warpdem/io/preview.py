"""``python -m warpdem preview STAGE``: pictures of a warpdem USD stage without a USD viewer (matplotlib, Agg).

Spheres are drawn as discs of their true radius, the rock surface as triangles shaded by their angle to the light,
both in the colours of the stage (``primvars:displayColor``), back to front (painter's order) in an orthographic
view: ``xz`` (front, looking along +y), ``xy`` (top), ``yz`` (side, looking along -x) or ``3d`` (from azimuth -60°,
elevation 25°). The view window is the same for every frame of one call, so an animation does not jump. Stages
with more spheres than ``max_spheres`` are drawn with a fixed random subset, and the picture says so.

A strip under the view says what the colours mean (:func:`color_keys`), one key per body whose colours follow one of
warpdem's colour scales: a colour bar from blue (0) to red (the scale) for speed [m/s] and von Mises stress [Pa, kPa,
MPa or GPa], a bar from grey through orange to dark red for damage [-], swatches for fragments, parts and materials.
The stage holds colours, not the scale they were made with: each frame's key is read back from its colours and the
values beside them (``primvars:speed``, ``primvars:vonMisesStress``, ``primvars:damage``, ``primvars:fragment``).
A ramp's colour gives the fraction t = value / scale, so the scale is value / t, and that it is one number across
the body is the check that the colours do show that value. Runs colour by the largest value seen so far in the
run, so the scale is that, not the frame's largest value. ``color_by`` other than ``"stage"`` recolours a body from
those values instead, on one scale for every frame drawn (the largest value among them, or ``scale``).
"""

from __future__ import annotations

import math
import os
import pathlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .output import PART_PALETTE

VIEWS = ("xz", "xy", "yz", "3d")
DEFAULT_MAX_SPHERES = 200_000
COLOR_BY = ("stage", "speed", "stress", "damage", "fragment")
"""``render``'s colour modes: the stage's own colours, or a body recoloured from the values the stage holds."""

COLOR_TOL = 2e-4
"""How far [-] a stored colour may lie from a colour scale and still count as on it: float32 colours are exact to
1e-7; the swatches of the palettes lie 0.05 or more apart."""

RAMP_BAND = (0.02, 0.98)
"""The fractions t of a ramp that measure its scale: below, value / t loses digits to the colour's rounding; at 1 a
value may have been clipped."""

SCALE_SPREAD = 2e-3
"""Largest relative spread of value / t over a body for its colours to count as that value's ramp (float32 colours
give about 1e-5 at t = 0.02)."""


class PreviewError(Exception):
    """A stage or an option that cannot be rendered (one readable line)."""


@dataclass
class StageFrame:
    """What one time code of a stage holds: sphere centres [m] (N, 3), radii [m] (N,), colours (N, 3); rock
    vertices [m] (P, 3), triangles (F, 3), colours (F, 3), one per triangle; the simulated time [s].

    ``rock_point_colors`` holds the rock's colours per vertex (P, 3) where the stage stores them so (each triangle
    is drawn in their mean), else None. ``sphere_values`` (``speed`` [m/s], ``fragment`` [-]; N each) and
    ``rock_values`` (``speed`` [m/s], ``damage`` [-], ``fragment`` [-] per vertex; ``vonMisesStress`` [Pa] per
    triangle) are the primvars the stage holds for this time code."""

    code: int
    time: float
    centers: np.ndarray
    radii: np.ndarray
    sphere_colors: np.ndarray
    rock_points: np.ndarray
    rock_faces: np.ndarray
    rock_colors: np.ndarray
    rock_point_colors: np.ndarray | None = None
    sphere_values: dict[str, np.ndarray] = field(default_factory=dict)
    rock_values: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class ColorKey:
    """What the colours of one body (or of both, when they show the same thing on the same scale) mean.

    Attributes:
        body: ``"spheres"``, ``"rock"`` or ``"spheres and rock"``.
        quantity: ``"speed"`` or ``"stress"`` (ramps), ``"damage"``, or ``"fragment"``, ``"part"``, ``"material"``
            (swatches).
        scale: the value drawn red [m/s or Pa]; 1 for damage; 0 for swatches.
        clipped: some value of the frame lies above ``scale`` (drawn in the colour of the scale).
        swatches: (label, colour) of the categories present, largest first (swatch keys only).
        count: how many categories the body shows (fragments: distinct ids other than -1).
    """

    body: str
    quantity: str
    scale: float = 0.0
    clipped: bool = False
    swatches: list[tuple[str, tuple[float, float, float]]] = field(default_factory=list)
    count: int = 0


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

    def values_of(prim, name: str, dtype=np.float64) -> np.ndarray | None:
        attr = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name).GetAttr()
        value = attr.Get(code) if attr and attr.HasValue() else None
        return None if value is None else np.asarray(value, dtype=dtype).reshape(-1)

    world = stage.GetPrimAtPath("/World")
    time_attr = world.GetAttribute("warpdem:time") if world else None
    time = float(time_attr.Get(code)) if time_attr and time_attr.HasValue() else float(code)
    centers, radii, colors = np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3))
    sphere_values: dict[str, np.ndarray] = {}
    rock_values: dict[str, np.ndarray] = {}
    prim = stage.GetPrimAtPath("/World/Particles")
    if prim and prim.IsA(UsdGeom.Points):
        points = UsdGeom.Points(prim)
        centers = arr(points.GetPointsAttr(), (0, 3))
        radii = 0.5 * arr(points.GetWidthsAttr(), (0,))
        colors = arr(points.GetDisplayColorPrimvar().GetAttr(), (0, 3))
        if len(colors) != len(centers):
            colors = np.tile([0.6, 0.6, 0.65], (len(centers), 1))
        for name, dtype in (("speed", np.float64), ("fragment", np.int64)):
            values = values_of(prim, name, dtype)
            if values is not None and len(values) == len(centers):
                sphere_values[name] = values
    rock_points, faces, rock_colors = np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    point_colors = None
    prim = stage.GetPrimAtPath("/World/Rock")
    if prim and prim.IsA(UsdGeom.Mesh):
        mesh = UsdGeom.Mesh(prim)
        rock_points = arr(mesh.GetPointsAttr(), (0, 3))
        faces = arr(mesh.GetFaceVertexIndicesAttr(), (0, 3), np.int64)
        primvar = mesh.GetDisplayColorPrimvar()
        rock_colors = arr(primvar.GetAttr(), (0, 3))
        if primvar.GetInterpolation() == UsdGeom.Tokens.vertex and len(rock_colors) == len(rock_points):
            point_colors = rock_colors
            rock_colors = rock_colors[faces].mean(axis=1)  # per-vertex colours: each triangle gets their mean
        if len(rock_colors) != len(faces):
            rock_colors = np.tile([0.6, 0.6, 0.65], (len(faces), 1))
        for name, dtype, count in (
            ("speed", np.float64, len(rock_points)),
            ("damage", np.float64, len(rock_points)),
            ("fragment", np.int64, len(rock_points)),
            ("vonMisesStress", np.float64, len(faces)),
        ):
            values = values_of(prim, name, dtype)
            if values is not None and len(values) == count:
                rock_values[name] = values
    return StageFrame(
        code, time, centers, radii, colors, rock_points, faces, rock_colors, point_colors, sphere_values, rock_values
    )


def _ramp_ends() -> np.ndarray:
    """The colours of 0 and of the scale on warpdem's blue-to-red ramp (warpdem.io.output.ramp_colors; the runner's
    sphere speed colours are the same ramp), shape (2, 3)."""
    from .output import ramp_colors

    return ramp_colors(np.array([0.0, 1.0]), 1.0)


def _damage_stops() -> np.ndarray:
    """The colours of damage 0, 0.5 and 1 (warpdem.io.output.damage_colors, linear between them), shape (3, 3)."""
    from .output import damage_colors

    return damage_colors(np.array([0.0, 0.5, 1.0]))


def _on_segment(colors: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each colour's fraction along the segment a → b (clipped to [0, 1]) and its distance from the segment."""
    d = b - a
    t = np.clip((colors - a) @ d / (d @ d), 0.0, 1.0)
    return t, np.linalg.norm(colors - (a + t[:, None] * d), axis=1)


def ramp_scale(colors: np.ndarray, values: np.ndarray) -> float | None:
    """The scale of a blue-to-red ramp that coloured ``values`` with ``colors`` (module docstring), or None when the
    colours are not on the ramp or value / t is not one number across them; 0 when every value is 0 (any scale).

    Args:
        colors: linear RGB, shape (N, 3). values: what they show [any unit], shape (N,).
    """
    if len(colors) == 0 or len(colors) != len(values):
        return None
    blue, red = _ramp_ends()
    t, off = _on_segment(colors, blue, red)
    if off.max() > COLOR_TOL:
        return None
    band = (t > RAMP_BAND[0]) & (t < RAMP_BAND[1])
    if band.any():
        ratio = values[band] / t[band]
        scale = float(np.median(ratio))
        return scale if scale > 0.0 and np.ptp(ratio) <= SCALE_SPREAD * scale else None
    # No colour in the band. Every value 0 and blue: the scale is not known (0 here). Every value red or 0: a run's
    # scale is its largest value so far, at least the frame's largest, and a red value is at least the scale.
    top = float(values.max())
    if top == 0.0:
        return 0.0 if t.max() < RAMP_BAND[0] else None
    return top if np.all((t > RAMP_BAND[1]) | (values == 0.0)) and np.ptp(values[values > 0.0]) == 0.0 else None


def _on_damage_scale(colors: np.ndarray) -> bool:
    """Whether every colour lies on the grey-orange-dark red damage scale."""
    stops = _damage_stops()
    off = np.minimum(_on_segment(colors, stops[0], stops[1])[1], _on_segment(colors, stops[1], stops[2])[1])
    return len(colors) > 0 and off.max() <= COLOR_TOL


def _palette_index(colors: np.ndarray, palette: np.ndarray) -> np.ndarray | None:
    """The palette row of each colour, or None when a colour is none of them."""
    if len(colors) == 0:
        return None
    dist = np.linalg.norm(colors[:, None, :] - palette[None, :, :], axis=2)
    k = dist.argmin(axis=1)
    return k if dist[np.arange(len(k)), k].max() <= COLOR_TOL else None


def _fragment_key(body: str, labels: np.ndarray) -> ColorKey:
    ids, members = np.unique(labels[labels >= 0], return_counts=True)
    order = np.argsort(-members, kind="stable")
    from ..stages.fragments import fragment_colors

    swatches = [(f"#{i}", tuple(map(float, c))) for i, c in zip(ids[order], fragment_colors(ids[order]), strict=True)]
    return ColorKey(body, "fragment", swatches=swatches, count=len(ids))


def _swatch_key(body: str, quantity: str, index: np.ndarray, palette: np.ndarray, names: list[str] | None) -> ColorKey:
    ids, members = np.unique(index, return_counts=True)
    swatches = []
    for k in ids[np.argsort(-members, kind="stable")]:
        # Palettes cycle: row k is every id k, k + len(palette), ...
        labels = [names[j] for j in range(k, len(names), len(palette))] if names else []
        swatches.append((" / ".join(labels) or f"{quantity} {k}", tuple(map(float, palette[k]))))
    return ColorKey(body, quantity, swatches=swatches, count=len(ids))


def body_key(
    body: str, colors: np.ndarray, values: dict[str, np.ndarray], per_vertex: bool, part_names: list[str] | None = None
) -> ColorKey | None:
    """What one body's colours show (module docstring), or None when they follow none of warpdem's scales.

    Args:
        body: ``"spheres"`` or ``"rock"``. colors: its colours, linear RGB, one per sphere or rock vertex
            (``per_vertex``) or rock triangle, shape (N, 3). values: the primvars beside them (:class:`StageFrame`).
        per_vertex: whether the rock's colours are per vertex (speed, damage, fragment) or per triangle (stress,
            material). part_names: names of the part ids, for the spheres' part swatches.
    """
    from .output import MATERIAL_PALETTE

    if len(colors) == 0:
        return None
    if "fragment" in values and per_vertex:  # fragment colours are per sphere or rock vertex
        from ..stages.fragments import fragment_colors

        if np.abs(colors - fragment_colors(values["fragment"])).max() <= COLOR_TOL:
            return _fragment_key(body, values["fragment"])
    quantity = "speed" if body == "spheres" or per_vertex else "stress"
    column = values.get("speed" if quantity == "speed" else "vonMisesStress")
    if column is not None:
        scale = ramp_scale(colors, column)
        if scale is not None:
            return ColorKey(body, quantity, scale=scale, clipped=bool(column.max() > scale * (1.0 + SCALE_SPREAD)))
    if _on_damage_scale(colors) and (body == "spheres" or per_vertex):
        return ColorKey(body, "damage", scale=1.0)
    if body == "spheres":
        index = _palette_index(colors, PART_PALETTE)
        return None if index is None else _swatch_key(body, "part", index, PART_PALETTE, part_names)
    index = None if per_vertex else _palette_index(colors, MATERIAL_PALETTE)
    return None if index is None else _swatch_key(body, "material", index, MATERIAL_PALETTE, None)


def color_keys(frame: StageFrame, part_names: list[str] | None = None) -> list[ColorKey]:
    """The keys of a frame's colours: one per body drawn (spheres, then rock), merged into one where both show the
    same quantity on the same scale.

    Args:
        frame: the frame as drawn (after any recolouring). part_names: names of the part ids (spheres' swatches).
    """
    keys = []
    if len(frame.centers):
        keys.append(body_key("spheres", frame.sphere_colors, frame.sphere_values, True, part_names))
    if len(frame.rock_faces):
        used = np.unique(frame.rock_faces)
        if frame.rock_point_colors is not None:
            values = {k: v[used] for k, v in frame.rock_values.items() if k != "vonMisesStress"}
            keys.append(body_key("rock", frame.rock_point_colors[used], values, True))
        else:
            keys.append(body_key("rock", frame.rock_colors, frame.rock_values, False))
    keys = [k for k in keys if k is not None]
    if len(keys) == 2 and keys[0].quantity == keys[1].quantity:
        a, b = keys
        if a.quantity == "fragment":
            labels = [frame.sphere_values["fragment"], frame.rock_values["fragment"][np.unique(frame.rock_faces)]]
            return [_fragment_key("spheres and rock", np.concatenate(labels))]
        if abs(a.scale - b.scale) <= SCALE_SPREAD * max(a.scale, b.scale):
            return [ColorKey("spheres and rock", a.quantity, max(a.scale, b.scale), a.clipped or b.clipped)]
    return keys


def in_window(view: str, window: tuple[float, float, float, float]) -> Callable[[np.ndarray], np.ndarray]:
    """Which points [m], shape (N, 3), a view shows within ``window`` (left, right, bottom, top) [m] along its screen
    axes (:func:`camera`): bool, shape (N,)."""
    cam = camera(view)

    def inside(points: np.ndarray) -> np.ndarray:
        u, v = (points @ cam[:2].T).T
        return (u >= window[0]) & (u <= window[1]) & (v >= window[2]) & (v <= window[3])

    return inside


def _largest_drawn(
    frame: StageFrame,
    spheres: np.ndarray | None,
    rock: np.ndarray | None,
    rock_per_face: bool,
    inside: Callable[[np.ndarray], np.ndarray] | None,
) -> float:
    """The largest of a frame's values that are drawn: the spheres', the rock surface's (per vertex, or per triangle
    at its centroid), where ``inside`` says so. 0 when none is."""

    def keep(points: np.ndarray) -> np.ndarray:
        return np.ones(len(points), bool) if inside is None else inside(points)

    drawn = []
    if spheres is not None and len(spheres):
        drawn.append(spheres[keep(frame.centers)])
    if rock is not None and len(rock):
        if rock_per_face:
            drawn.append(rock[keep(frame.rock_points[frame.rock_faces].mean(axis=1))])
        else:
            used = np.unique(frame.rock_faces)
            drawn.append(rock[used][keep(frame.rock_points[used])])
    return max((float(v.max()) for v in drawn if len(v)), default=0.0)


def recolor(
    frames: list[StageFrame],
    color_by: str,
    scale: float | None = None,
    inside: Callable[[np.ndarray], np.ndarray] | None = None,
) -> None:
    """Recolour the frames from the values the stage holds (module docstring), in place.

    Args:
        frames: the frames to draw. color_by: one of :data:`COLOR_BY`; ``"stage"`` leaves the colours as stored.
        scale: the value drawn red [m/s or Pa] for speed and stress [the largest value drawn: of the spheres, the
            rock surface's vertices (speed) or triangles (stress) of the frames, those ``inside`` only].
        inside: which points [m], shape (N, 3), lie in the part of the view drawn (bool, shape (N,)) [all].

    Raises:
        PreviewError: an unknown mode, or a stage that holds no value to colour by.
    """
    from .output import damage_colors, ramp_colors

    if color_by not in COLOR_BY:
        raise PreviewError(f"--color-by: {color_by!r} is not one of {', '.join(COLOR_BY)}")
    if color_by == "stage":
        return
    # Which arrays of which body each mode recolours: the spheres hold speed and fragment ids only.
    sphere_column = {"speed": "speed", "fragment": "fragment"}.get(color_by)
    rock_column = {"speed": "speed", "stress": "vonMisesStress", "damage": "damage", "fragment": "fragment"}[color_by]
    sphere_data = [f.sphere_values.get(sphere_column) for f in frames] if sphere_column else [None] * len(frames)
    rock_data = [f.rock_values.get(rock_column) if len(f.rock_faces) else None for f in frames]
    present = [v for v in sphere_data + rock_data if v is not None and len(v)]
    if not present:
        what = {"stress": "von Mises stress (a rock surface)", "damage": "rock damage (fracture on)"}.get(
            color_by, color_by
        )
        raise PreviewError(f"--color-by {color_by}: the frames drawn hold no {what}")
    if scale is None and color_by in ("speed", "stress"):
        per_face = color_by == "stress"
        drawn = zip(frames, sphere_data, rock_data, strict=True)
        scale = max(_largest_drawn(f, spheres, rock, per_face, inside) for f, spheres, rock in drawn)
    if scale is not None and not scale > 0.0:
        scale = 1.0  # everything at rest or unloaded: blue on any scale

    def colors_of(values: np.ndarray) -> np.ndarray:
        if color_by == "fragment":
            from ..stages.fragments import fragment_colors

            return fragment_colors(values)
        if color_by == "damage":
            return damage_colors(values)
        return ramp_colors(values, scale)

    for f, spheres, rock in zip(frames, sphere_data, rock_data, strict=True):
        if spheres is not None:
            f.sphere_colors = colors_of(spheres)
        if rock is None:
            continue
        if color_by == "stress":
            f.rock_colors, f.rock_point_colors = colors_of(rock), None
        else:
            f.rock_point_colors = colors_of(rock)
            f.rock_colors = f.rock_point_colors[f.rock_faces].mean(axis=1)


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


def _font_size(size: tuple[int, int]) -> float:
    """Text size [pt] of a picture of ``size`` pixels: 8 pt up to 640 × 480, growing with the shorter side beyond, so
    the text of a large picture keeps its share of the picture."""
    return 8.0 * max(1.0, min(size) / 480.0)


def legend_height(size: tuple[int, int]) -> int:
    """Height [pixels] of the strip under the view that holds the colour keys: a title, a bar and its numbers."""
    return round(4.6 * _font_size(size) * 100.0 / 72.0)


def _stress_unit(scale: float) -> tuple[str, float]:
    """The unit a stress scale [Pa] reads best in, and its size in Pa."""
    for unit, size in (("GPa", 1e9), ("MPa", 1e6), ("kPa", 1e3)):
        if scale >= size:
            return unit, size
    return "Pa", 1.0


def key_title(key: ColorKey) -> tuple[str, str, float]:
    """The key's title (what the colours show, with its unit), the unit, and the unit's size in the stage's units
    (a stress scale of 3e7 Pa reads 30 MPa: unit "MPa", size 1e6)."""
    if key.quantity == "speed":
        return f"{key.body}: speed [m/s]", "m/s", 1.0
    if key.quantity == "stress":
        unit, size = _stress_unit(key.scale)
        return f"{key.body}: von Mises stress [{unit}]", unit, size
    if key.quantity == "damage":
        what = "share of bonds broken" if key.body == "spheres" else "cohesive damage δ_max/δ_c"
        return f"{key.body}: {what} [-]", "-", 1.0
    if key.quantity == "fragment":
        return f"{key.body}: {key.count} fragment{'s' * (key.count != 1)}, a colour each (grey: none)", "", 1.0
    return f"{key.body}: {key.quantity}", "", 1.0


def _bar_colors(key: ColorKey, n: int = 256) -> np.ndarray:
    """The key's colour scale at ``n`` evenly spaced values from 0 to its scale (bin centres), shape (n, 3)."""
    from .output import damage_colors, ramp_colors

    fraction = (np.arange(n) + 0.5) / n
    if key.quantity == "damage":
        return damage_colors(fraction)
    return ramp_colors(fraction, 1.0)


def bar_rect(rect: tuple[float, float, float, float], font: float, height: float) -> tuple[float, float, float, float]:
    """Where :func:`draw_key` puts a colour bar in its region ``rect`` (figure fractions) of a figure ``height``
    pixels high at render's 100 dpi: (x, y, width, height), figure fractions; room for the numbers below it and the
    title above."""
    x, y, w, _ = rect
    font_px = font * 100.0 / 72.0
    return x + 0.06 * w, y + 1.55 * font_px / height, 0.88 * w, 0.95 * font_px / height


def draw_key(fig, key: ColorKey, rect: tuple[float, float, float, float], font: float):
    """Draw one colour key into the figure region ``rect`` (x, y, width, height; figure fractions): a colour bar
    from 0 to the scale in the title's unit, or a row of swatches. Returns the bar's axes (x limits: 0 and the scale
    in that unit), or None for swatches."""
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import MaxNLocator

    _, _, w, h = rect
    title, _, size = key_title(key)
    width_px, height_px = fig.get_size_inches() * fig.dpi
    font_px = font * fig.dpi / 72.0
    if key.quantity in ("speed", "stress", "damage"):
        top = key.scale / size
        cax = fig.add_axes(bar_rect(rect, font, height_px))
        colors = _bar_colors(key)
        cax.imshow(
            colors[None], extent=(0.0, top if top > 0 else 1.0, 0.0, 1.0), aspect="auto", interpolation="nearest"
        )
        cax.set_yticks([])
        if top > 0.0:
            cax.set_xlim(0.0, top)
            ticks = [v for v in MaxNLocator(nbins=4).tick_values(0.0, top) if 0.0 <= v <= 0.78 * top]
            labels = [f"{v:.3g}" for v in ticks] + [f"{'≥ ' if key.clipped else ''}{top:.3g}"]
            cax.set_xticks([*ticks, top], labels)
        else:
            cax.set_xlim(0.0, 1.0)
            cax.set_xticks([0.0], ["0"])
            title += ": all 0"
        cax.tick_params(axis="x", labelsize=0.9 * font, length=2, pad=1)
        cax.set_title(title, fontsize=font, pad=2)
        for spine in cax.spines.values():
            spine.set_linewidth(0.5)
        return cax
    sax = fig.add_axes(rect)
    slot_w, slot_h = w * width_px, h * height_px
    sax.set_xlim(0.0, slot_w)
    sax.set_ylim(0.0, slot_h)
    sax.axis("off")
    sax.text(0.5 * slot_w, 2.55 * font_px, title, ha="center", va="bottom", fontsize=font)
    # Swatches in a row under the title, centred: as many as fit, the largest categories first; the rest counted.
    square = 0.95 * font_px
    widths = [square + 0.62 * font_px * (len(label) + 2) for label, _ in key.swatches]
    more = 5.0 * font_px  # room for "+N more"
    shown = 0
    while (
        shown < len(widths) and sum(widths[: shown + 1]) + (more if shown + 1 < len(widths) else 0.0) <= 0.92 * slot_w
    ):
        shown += 1
    row = sum(widths[:shown]) + (more if shown < len(widths) else 0.0)
    cursor, row_y = 0.5 * (slot_w - row), 1.55 * font_px
    for (label, color), width in zip(key.swatches[:shown], widths, strict=False):
        sax.add_patch(Rectangle((cursor, row_y), square, square, facecolor=color, edgecolor="0.3", linewidth=0.5))
        sax.text(cursor + 1.3 * square, row_y + 0.5 * square, label, va="center", fontsize=0.9 * font)
        cursor += width
    if shown < len(key.swatches):
        sax.text(cursor, row_y + 0.5 * square, f"+{len(key.swatches) - shown} more", va="center", fontsize=0.9 * font)
    return None


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
    color_by: str = "stage",
    scale: float | None = None,
    legend: bool = True,
    window: tuple[float, float, float, float] | None = None,
    part_names: list[str] | None = None,
) -> list[pathlib.Path]:
    """Render frames of a stage to PNG files (and an animated GIF of them).

    Args:
        stage_path: the USD stage.
        out_dir: where the pictures go (default: the stage's folder).
        frames: time codes, negative from the end (default: the last; with ``gif``, all, at most 100).
        view: one of :data:`VIEWS`.
        size: picture size (width, height) [pixels].
        gif: also write ``<stem>_<view>.gif``.
        max_spheres: draw at most this many spheres.
        fps: GIF frame rate [frames/s].
        color_by: one of :data:`COLOR_BY` (:func:`recolor`; default "stage": the stage's colours).
        scale: the value drawn red when recolouring by speed [m/s] or stress [Pa] (default: the largest drawn, in
            the window where one is given).
        legend: draw the colour keys under the view (:func:`color_keys`; only where the colours follow a known
            scale).
        window: the part of the view to draw, (left, right, bottom, top) [m] along the screen's axes
            (:func:`camera`), widened to the picture's shape (default: everything drawn, with a margin).
        part_names: the scene's part names by part id, for the swatches of ``color_by = "part"``.

    Returns:
        The files written: one ``<stem>_<view>_<code:06d>.png`` per frame, then the GIF.

    Raises:
        PreviewError: missing or unreadable stage, a frame it lacks, an unknown view or colour mode, a colour mode
            the stage holds no value for.
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
    recolor(data, color_by, scale, None if window is None else in_window(view, window))
    keys = [color_keys(frame, part_names) if legend else [] for frame in data]
    slots = max(map(len, keys), default=0)
    width, height = size
    font = _font_size(size)
    # The keys get a strip under the view, the same in every frame (an animation does not jump), so they hide
    # nothing of the scene; the view keeps one metre as long across as up in what is left.
    strip = legend_height(size) if slots else 0
    if strip > height // 2:
        raise PreviewError(f"--size: {width}x{height} leaves no room for the colour keys (at least 2 × {strip} high)")
    u0, u1, v0, v1 = _fit(window if window is not None else _bounds(data, cam), width / (height - strip))
    out = pathlib.Path(out_dir) if out_dir is not None else stage_path.parent
    out.mkdir(parents=True, exist_ok=True)
    stem = stage_path.stem
    written, images = [], []
    for frame, frame_keys in zip(data, keys, strict=True):
        fig = plt.figure(figsize=(width / 100.0, height / 100.0), dpi=100)
        below = strip / height
        ax = fig.add_axes((0.0, below, 1.0, 1.0 - below))
        ax.set_facecolor((0.97, 0.97, 0.98))
        note = draw_frame(ax, frame, cam, max_spheres)
        # The window has the axes' aspect: one metre is as long across as up.
        ax.set_xlim(u0, u1)
        ax.set_ylim(v0, v1)
        ax.set_xticks([])
        ax.set_yticks([])
        label = f"{stem}   frame {frame.code}   t = {frame.time:.4g} s   view {view}"
        ax.text(0.01, 0.99, label, transform=ax.transAxes, va="top", fontsize=font, color="0.15")
        if note:
            ax.text(0.01, 0.01, note, transform=ax.transAxes, va="bottom", fontsize=font, color="0.15")
        _scale_bar(ax, u0, u1, v0, font)
        for k, key in enumerate(frame_keys):
            draw_key(fig, key, (k / slots, 0.0, 1.0 / slots, below), font)
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


def _scale_bar(ax, u0: float, u1: float, v0: float, font: float = 8.0) -> None:
    """A bar of a round length (1, 2 or 5 × 10^k m) near the lower right corner."""
    span = u1 - u0
    target = 0.2 * span
    k = math.floor(math.log10(target))
    length = max(m * 10.0**k for m in (1, 2, 5) if m * 10.0**k <= target)
    x1 = u1 - 0.03 * span
    y = v0 + 0.03 * (ax.get_ylim()[1] - v0)
    ax.plot([x1 - length, x1], [y, y], color="0.15", lw=2, zorder=3)
    ax.text(x1 - 0.5 * length, y, f"{length:g} m", ha="center", va="bottom", fontsize=font, color="0.15", zorder=3)
