"""What one frame of the USD stage carries (:mod:`warpdem.io.usd`): a triangulated surface (:class:`SurfaceFrame`) and a
set of two-point curves (:class:`CurveSet`), and the checks that turn them into the arrays the writer authors
(float32 points and values, int32 indices), raising a ValueError that names the array and the shape it needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class SurfaceFrame:
    """One frame of a triangulated surface (the boundary of the FEM rock, crack faces included).

    Attributes:
        points: vertex positions [m], shape (P, 3); may hold vertices no triangle uses.
        faces: triangles as vertex indices, shape (F, 3), integer, right-handed (normal out of the rock).
        velocities: vertex velocities [m/s], shape (P, 3).
        von_mises: von Mises stress of each triangle's tet [Pa], shape (F,).
        max_principal: largest principal stress (tension positive) of each triangle's tet [Pa], shape (F,).
        colors: display colours, linear RGB in [0, 1], shape (F, 3) (one per triangle) or (P, 3) (one per vertex,
            when ``vertex_colors``).
        vertex_colors: whether ``colors`` holds one colour per vertex instead of one per triangle.
        damage: optional damage of each vertex [-], shape (P,), in [0, 1] (written to ``primvars:damage``).
        fragment: fragment id of each vertex (-1 for none; warpdem.stages.fragments), shape (P,), integer, or None.
    """

    points: np.ndarray
    faces: np.ndarray
    velocities: np.ndarray
    von_mises: np.ndarray
    max_principal: np.ndarray
    colors: np.ndarray
    vertex_colors: bool = False
    damage: np.ndarray | None = None
    fragment: np.ndarray | None = None


@dataclass
class CurveSet:
    """One frame of straight two-point curves (the cohesive elements of the FEM rock).

    Attributes:
        endpoints: the two ends of each curve [m], shape (M, 2, 3).
        width: the width of every curve [m].
        damage: a value per curve [-], shape (M,) (``primvars:damage``).
        colors: display colour of each curve, linear RGB in [0, 1], shape (M, 3).
    """

    endpoints: np.ndarray
    width: float
    damage: np.ndarray
    colors: np.ndarray


def as_float32(values: np.ndarray, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """Converts an array to contiguous float32 and checks its shape.

    Args:
        values: Input array.
        name: Argument name for the error message.
        shape: Expected shape; ``-1`` accepts any length in that axis.

    Returns:
        C-contiguous float32 array.

    Raises:
        ValueError: If the shape does not match.
    """
    arr = np.asarray(values)
    if arr.ndim != len(shape) or any(want not in (-1, got) for want, got in zip(shape, arr.shape, strict=True)):
        expected = "(" + ", ".join("N" if s == -1 else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name}: expected shape {expected}, got {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float32)


def check_surface(surface: SurfaceFrame) -> tuple:
    """Checks a surface frame's shapes and converts its arrays for USD (float32, int32 indices).

    Raises:
        ValueError: If shapes disagree, the faces are not integers, or an index is out of range.
    """
    pts = as_float32(surface.points, "surface.points", (-1, 3))
    p = pts.shape[0]
    faces = np.asarray(surface.faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not (np.issubdtype(faces.dtype, np.integer) or faces.size == 0):
        raise ValueError(f"surface.faces: expected integer array of shape (F, 3), got {faces.dtype} {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= p):
        raise ValueError(f"surface.faces: indices must lie in [0, {p}), got range [{faces.min()}, {faces.max()}]")
    f = faces.shape[0]
    vel = as_float32(surface.velocities, "surface.velocities", (p, 3))
    von_mises = as_float32(surface.von_mises, "surface.von_mises", (f,))
    max_principal = as_float32(surface.max_principal, "surface.max_principal", (f,))
    colors = as_float32(surface.colors, "surface.colors", (p if surface.vertex_colors else f, 3))
    damage = as_float32(surface.damage, "surface.damage", (p,)) if surface.damage is not None else None
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    return pts, faces, vel, von_mises, max_principal, colors, bool(surface.vertex_colors), damage


def empty_surface() -> tuple:
    """The arrays of a surface without triangles (authored where the rock is gone or not there yet)."""
    z3 = np.zeros((0, 3), np.float32)
    z = np.zeros(0, np.float32)
    return z3, np.zeros((0, 3), np.int32), z3, z, z, z3


def check_curves(curves: CurveSet) -> tuple:
    """Checks a curve set's shapes and converts it for USD: endpoints as (2 M, 3) float32, width, damage and colours
    float32.

    Raises:
        ValueError: If shapes disagree or the width is not a finite number >= 0.
    """
    ends = as_float32(curves.endpoints, "cohesive.endpoints", (-1, 2, 3))
    m = ends.shape[0]
    width = float(curves.width)
    if not (math.isfinite(width) and width >= 0.0):
        raise ValueError(f"cohesive.width: expected a finite number >= 0, got {curves.width}")
    damage = as_float32(curves.damage, "cohesive.damage", (m,))
    colors = as_float32(curves.colors, "cohesive.colors", (m, 3))
    return ends.reshape(-1, 3), width, damage, colors


def empty_curves() -> tuple:
    """The arrays of a curve set without curves (checked form)."""
    return np.zeros((0, 3), np.float32), 0.0, np.zeros(0, np.float32), np.zeros((0, 3), np.float32)
