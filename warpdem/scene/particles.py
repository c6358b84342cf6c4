"""Spheres, bonds and walls of a scene: [[particles]] sources (packings, single spheres, files), [[bonds]] and
[[walls]]."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import (
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .fields import Bool, FilePath, Float, Int, Str, Vec3, _Model
from .regions import Region, _hi_above_lo

# ----------------------------------------------------------------------------------------------------------------------
# Particle sources
# ----------------------------------------------------------------------------------------------------------------------


class PackingSource(_Model):
    """Fills a region with spheres."""

    kind: Literal["packing"] = Field(description="Source kind.")
    part: Str = Field(description="Name of a part defined in [parts].")
    region: Region = Field(description="Region to fill.")
    radius: Float = Field(gt=0, description="Sphere radius, or the smallest radius when radius_max is given [m].")
    radius_max: Float | None = Field(
        default=None, gt=0, description="Largest radius [m]; radii are uniform in [radius, radius_max]."
    )
    arrangement: Literal["hcp", "cubic", "random"] = Field(default="hcp", description="Lattice or random packing.")
    count: Int | None = Field(
        default=None, gt=0, description="At most this many spheres (random arrangement: the target count)."
    )
    volume_fraction: Float | None = Field(
        default=None,
        gt=0,
        le=0.74,
        description="Target solid fraction (0, 0.74] of a random packing; 0.5 when omitted.",
    )
    velocity: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Initial velocity [m/s].")

    @field_validator("radius_max")
    @classmethod
    def _check_radius_max(cls, value: float | None, info: ValidationInfo) -> float | None:
        radius = info.data.get("radius")
        if value is not None and radius is not None and value < radius:
            raise ValueError(f"must be >= radius = {radius}")
        return value

    @field_validator("volume_fraction")
    @classmethod
    def _check_volume_fraction(cls, value: float | None, info: ValidationInfo) -> float | None:
        # A lattice has a fixed solid fraction; accepting the key would silently ignore it.
        arrangement = info.data.get("arrangement")
        if value is not None and arrangement is not None and arrangement != "random":
            raise ValueError(f"only used with arrangement = 'random', not {arrangement!r}")
        return value

    @property
    def target_volume_fraction(self) -> float:
        """Solid fraction a random packing aims for [-]."""
        return 0.5 if self.volume_fraction is None else self.volume_fraction


class SphereSource(_Model):
    """One sphere."""

    kind: Literal["sphere"] = Field(description="Source kind.")
    part: Str = Field(description="Name of a part defined in [parts].")
    center: Vec3 = Field(description="Centre [m].")
    radius: Float = Field(gt=0, description="Radius [m].")
    velocity: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Initial velocity [m/s].")
    angular_velocity: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Initial angular velocity [rad/s].")
    motion: Literal["free", "fixed", "prescribed"] = Field(
        default="free",
        description="'free', 'fixed' (never moves) or 'prescribed' (keeps its initial velocity and spin).",
    )


class FileSource(_Model):
    """Sphere centres (and optionally radii) read from a text file of ``x y z [r]`` lines."""

    kind: Literal["file"] = Field(description="Source kind.")
    part: Str = Field(description="Name of a part defined in [parts].")
    path: FilePath = Field(
        description="Text file, relative to the scene file; absolute after loading. Lines 'x y z' or 'x y z r' [m]."
    )
    radius: Float | None = Field(default=None, gt=0, description="Radius for 3-column files [m].")
    velocity: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Initial velocity [m/s].")


ParticleSource = Annotated[PackingSource | SphereSource | FileSource, Field(discriminator="kind")]
"""One ``[[particles]]`` entry, selected by ``kind``."""


# ----------------------------------------------------------------------------------------------------------------------
# Bonds and walls
# ----------------------------------------------------------------------------------------------------------------------


class BondRegion(_Model):
    """Bonds every pair of touching (or nearly touching) particles whose centres lie in a region."""

    region: Region = Field(description="Particles with centres inside are bonded.")
    material: Str | None = Field(
        default=None, description="Material whose Young's modulus the bonds use when youngs_modulus is omitted."
    )
    youngs_modulus: Float | None = Field(default=None, gt=0, description="Bond Young's modulus [Pa].")
    stiffness_ratio: Float = Field(default=2.5, gt=0, description="Normal to shear stiffness ratio kn/ks [-].")
    tensile_strength: Float = Field(gt=0, description="Tensile strength [Pa].")
    shear_strength: Float = Field(gt=0, description="Shear strength [Pa].")
    radius_factor: Float = Field(
        default=1.0, gt=0, le=2, description="Bond radius divided by the smaller sphere radius (0, 2] [-]."
    )
    gap_tolerance: Float = Field(
        default=0.05, ge=0, description="Pairs with gap <= gap_tolerance * (r_i + r_j) are bonded [-]."
    )
    damping_ratio: Float = Field(
        default=0.05, ge=0, le=1, description="Damping ratio of the bond dashpots, c = 2 zeta sqrt(m* k) [-]."
    )

    @model_validator(mode="after")
    def _check_stiffness_source(self) -> BondRegion:
        if self.material is None and self.youngs_modulus is None:
            raise ValueError("needs 'material' or 'youngs_modulus' to set the bond stiffness")
        return self


class PlaneWall(_Model):
    """Infinite plane; particles are pushed to the side the normal points to."""

    kind: Literal["plane"] = Field(description="Wall kind.")
    point: Vec3 = Field(description="A point on the plane [m].")
    normal: Vec3 = Field(description="Normal [-]; any nonzero length, stored normalised.")
    material: Str = Field(description="Name of a material defined in [materials].")
    velocity: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Constant translation velocity [m/s].")

    @field_validator("normal")
    @classmethod
    def _normalise(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        length = math.sqrt(sum(c * c for c in value))
        if not length > 1e-12:
            raise ValueError("must be a nonzero vector")
        return (value[0] / length, value[1] / length, value[2] / length)


class BoxWall(_Model):
    """The six inner faces of an axis-aligned box (a container)."""

    kind: Literal["box"] = Field(description="Wall kind.")
    lo: Vec3 = Field(description="Lower corner [m].")
    hi: Vec3 = Field(description="Upper corner [m]; greater than lo in every component.")
    material: Str = Field(description="Name of a material defined in [materials].")
    open_top: Bool = Field(default=False, description="Drop the +z face.")

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)


Wall = Annotated[PlaneWall | BoxWall, Field(discriminator="kind")]
"""One ``[[walls]]`` entry, selected by ``kind``."""
