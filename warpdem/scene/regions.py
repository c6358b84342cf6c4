"""Regions of a scene: boxes and cylinders, alone or joined, that select spheres, nodes, tets and faces."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import (
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .fields import Float, Vec3, _Model

# ----------------------------------------------------------------------------------------------------------------------
# Regions
# ----------------------------------------------------------------------------------------------------------------------


def _hi_above_lo(hi: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
    lo = info.data.get("lo")
    # lo failed its own validation: that error is already reported, do not add a second one.
    if lo is not None and not all(h > l for h, l in zip(hi, lo, strict=True)):
        raise ValueError(f"must be > lo = {list(lo)} in every component")
    return hi


class Box(_Model):
    """Axis-aligned box."""

    lo: Vec3 = Field(description="Lower corner [m].")
    hi: Vec3 = Field(description="Upper corner [m]; greater than lo in every component.")

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)


_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


class Cylinder(_Model):
    """Solid circular cylinder along a coordinate axis."""

    center: Vec3 = Field(description="Centre of the base disc [m].")
    radius: Float = Field(gt=0, description="Radius [m].")
    height: Float = Field(gt=0, description="Height along the axis, measured from the base disc [m].")
    axis: Literal["x", "y", "z"] = Field(default="z", description="Coordinate axis of the cylinder.")


class Region(_Model):
    """A region of space: exactly one of ``box`` or ``cylinder``."""

    box: Box | None = Field(default=None, description="Axis-aligned box region.")
    cylinder: Cylinder | None = Field(default=None, description="Cylinder region.")

    @model_validator(mode="after")
    def _exactly_one(self) -> Region:
        given = [name for name in ("box", "cylinder") if getattr(self, name) is not None]
        if len(given) != 1:
            raise ValueError(f"needs exactly one of 'box' or 'cylinder' (got {', '.join(given) or 'none'})")
        return self

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Tests which points lie inside the region (boundary included).

        Args:
            points: Positions [m], shape (..., 3).

        Returns:
            Boolean array of shape (...,): True where the point is inside.
        """
        p = np.asarray(points, dtype=np.float64)
        if self.box is not None:
            lo = np.asarray(self.box.lo)
            hi = np.asarray(self.box.hi)
            return np.all((p >= lo) & (p <= hi), axis=-1)
        cyl = self.cylinder
        assert cyl is not None  # guaranteed by the validator
        a = _AXIS_INDEX[cyl.axis]
        d = p - np.asarray(cyl.center)
        along = d[..., a]
        radial_sq = np.sum(d * d, axis=-1) - along * along
        return (along >= 0.0) & (along <= cyl.height) & (radial_sq <= cyl.radius * cyl.radius)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box of the region.

        Returns:
            ``(lo, hi)`` corners [m], each a float64 array of shape (3,).
        """
        if self.box is not None:
            return np.asarray(self.box.lo, dtype=np.float64), np.asarray(self.box.hi, dtype=np.float64)
        cyl = self.cylinder
        assert cyl is not None
        a = _AXIS_INDEX[cyl.axis]
        c = np.asarray(cyl.center, dtype=np.float64)
        half = np.full(3, cyl.radius)
        half[a] = 0.0
        lo = c - half
        hi = c + half
        hi[a] += cyl.height
        return lo, hi

    def volume(self) -> float:
        """Volume of the region [m^3]."""
        if self.box is not None:
            return float(np.prod(np.subtract(self.box.hi, self.box.lo)))
        cyl = self.cylinder
        assert cyl is not None
        return math.pi * cyl.radius**2 * cyl.height
