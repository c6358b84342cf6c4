"""Loads and boundaries of a scene: pressure histories, [[loads]] and [[boundaries]]."""

from __future__ import annotations

import itertools
from typing import Annotated, Any, Literal

from pydantic import (
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .fields import Float, Str, Vec3, _Model
from .regions import Region


def _faces_field() -> Any:
    return Field(
        default=None,
        description="Face set name: 'x-', 'x+', 'y-', 'y+', 'z-', 'z+', 'opening' or a triangle group of a mesh file.",
    )


def _region_field(what: str = "Boundary faces") -> Any:
    return Field(default=None, description=f"{what} inside this region (instead of 'faces').")


def _check_selection(model: Any) -> None:
    if (model.faces is None) == (model.region is None):
        given = "both" if model.faces is not None else "neither"
        raise ValueError(f"needs exactly one of 'faces' or 'region' (got {given})")


class BlastHistory(_Model):
    """Explosive pressure pulse: linear rise to the peak, then exponential decay."""

    kind: Literal["blast"] = Field(description="History kind.")
    peak: Float = Field(gt=0, description="Peak pressure [Pa].")
    rise_time: Float = Field(default=0.0, ge=0, description="Time from the start to the peak [s].")
    decay_time: Float = Field(gt=0, description="Exponential decay time after the peak [s].")
    start: Float = Field(default=0.0, ge=0, description="Arrival time [s].")


class TableHistory(_Model):
    """Pressure interpolated linearly in a table (0 before the first time and after the last)."""

    kind: Literal["table"] = Field(description="History kind.")
    times: list[Float] = Field(min_length=2, description="Times [s], strictly increasing.")
    values: list[Float] = Field(description="Pressures at those times [Pa].")

    @field_validator("times")
    @classmethod
    def _increasing(cls, value: list[float]) -> list[float]:
        if any(b <= a for a, b in itertools.pairwise(value)):
            raise ValueError("must be strictly increasing")
        return value

    @field_validator("values")
    @classmethod
    def _same_length(cls, value: list[float], info: ValidationInfo) -> list[float]:
        times = info.data.get("times")
        if times is not None and len(value) != len(times):
            raise ValueError(f"needs one value per time ({len(times)})")
        return value


class FriedlanderHistory(_Model):
    """Friedlander blast wave p(t) = peak (1 - τ) exp(-b τ), τ = (t - start) / positive_duration."""

    kind: Literal["friedlander"] = Field(description="History kind.")
    peak: Float = Field(gt=0, description="Peak overpressure [Pa].")
    positive_duration: Float = Field(gt=0, description="Duration of the positive phase [s].")
    decay_coefficient: Float = Field(default=1.0, gt=0, description="Decay coefficient b [-].")
    start: Float = Field(default=0.0, ge=0, description="Arrival time [s].")


PressureHistorySpec = Annotated[BlastHistory | TableHistory | FriedlanderHistory, Field(discriminator="kind")]
"""A pressure history, selected by ``kind``."""


class PressureLoad(_Model):
    """A pressure history on boundary faces (pushing along their inward normal)."""

    kind: Literal["pressure"] = Field(description="Load kind.")
    faces: Str | None = _faces_field()
    region: Region | None = _region_field()
    history: PressureHistorySpec = Field(description="Pressure history.")

    @model_validator(mode="after")
    def _selection(self) -> PressureLoad:
        _check_selection(self)
        return self


class AirblastLoad(_Model):
    """A surface airblast: Friedlander pulses arriving at each face when a front from ``source`` reaches it."""

    kind: Literal["airblast"] = Field(description="Load kind.")
    faces: Str | None = _faces_field()
    region: Region | None = _region_field()
    peak: Float = Field(gt=0, description="Peak overpressure [Pa].")
    positive_duration: Float = Field(gt=0, description="Duration of the positive phase [s].")
    decay_coefficient: Float = Field(default=1.0, gt=0, description="Friedlander decay coefficient b [-].")
    source: Vec3 = Field(description="Point the front starts from [m].")
    front_speed: Float = Field(gt=0, description="Speed of the front [m/s].")
    t0: Float = Field(default=0.0, ge=0, description="Time the front leaves the source [s].")

    @model_validator(mode="after")
    def _selection(self) -> AirblastLoad:
        _check_selection(self)
        return self


class VelocityLoad(_Model):
    """Prescribed velocity of nodes (of the named faces, or every node inside a region) between two times."""

    kind: Literal["velocity"] = Field(description="Load kind.")
    faces: Str | None = _faces_field()
    region: Region | None = _region_field("Nodes")
    velocity: Vec3 = Field(description="Prescribed velocity [m/s].")
    start: Float = Field(default=0.0, ge=0, description="Start time [s].")
    end: Float | None = Field(default=None, description="End time [s]; omitted: until the end of the run.")

    @field_validator("end")
    @classmethod
    def _after_start(cls, value: float | None, info: ValidationInfo) -> float | None:
        start = info.data.get("start")
        if value is not None and start is not None and not value > start:
            raise ValueError(f"must be > start = {start}")
        return value

    @model_validator(mode="after")
    def _selection(self) -> VelocityLoad:
        _check_selection(self)
        return self


Load = Annotated[PressureLoad | AirblastLoad | VelocityLoad, Field(discriminator="kind")]
"""One ``[[loads]]`` entry, selected by ``kind``."""


class Boundary(_Model):
    """A boundary condition on mesh faces."""

    faces: Str | None = _faces_field()
    region: Region | None = _region_field()
    kind: Literal["fixed", "roller", "non_reflecting"] = Field(
        description="'fixed' (held), 'roller' (no motion along the normal) or 'non_reflecting' (viscous dashpots "
        "that absorb waves leaving the model)."
    )
    normal: Vec3 | None = Field(
        default=None,
        description="Roller normal along x, y or z (e.g. [1, 0, 0]) [-]; omitted: the axis the faces' plane is "
        "normal to.",
    )

    @field_validator("normal")
    @classmethod
    def _axis_aligned(cls, value: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        # A roller holds one velocity component of its nodes (node_motion codes): only the coordinate axes exist.
        if value is not None and sum(1 for c in value if c != 0.0) != 1:
            raise ValueError("must be a nonzero vector along x, y or z")
        return value

    @model_validator(mode="after")
    def _selection(self) -> Boundary:
        _check_selection(self)
        if self.normal is not None and self.kind != "roller":
            raise ValueError(f"'normal' is only used by kind 'roller', not {self.kind!r}")
        return self
