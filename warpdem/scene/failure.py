"""How the rock may fail or change mode: [fracture] (nodal splitting), [conversion] (FEM→DEM) and [rigid] (LDEC's
rigid blocks)."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    Field,
    field_validator,
    model_validator,
)

from ..limits import MAX_SUBSTEPS
from .fields import Bool, Float, Int, Name, Str, Vec3, _Model
from .regions import Region

# ----------------------------------------------------------------------------------------------------------------------
# Nodal fracture
# ----------------------------------------------------------------------------------------------------------------------


def _nonzero_vec3(value: tuple[float, float, float]) -> tuple[float, float, float]:
    if not math.hypot(*value) > 0.0:
        raise ValueError("must be a nonzero vector")
    return value


class SeedCrack(_Model):
    """An open, frictional pre-crack: the mesh faces on a plane inside a region, split at build time."""

    point: Vec3 = Field(description="A point on the crack plane [m].")
    normal: Annotated[Vec3, AfterValidator(_nonzero_vec3)] = Field(description="Normal of the crack plane [-].")
    region: Region = Field(description="The mesh faces on the plane with all three nodes inside are cracked.")
    friction: Float = Field(default=0.0, ge=0, description="Coulomb friction coefficient of the crack faces [-].")


class Fracture(_Model):
    """Nodal fracture of the rock mesh (LDEC §2.2–2.3): nodes whose averaged stress reaches the material's tensile
    strength split, joined by softening cohesive elements."""

    enabled: Bool = Field(default=False, description="Run the split pass (every mesh material needs T_f and Γ).")
    check_interval: Int = Field(default=1, ge=1, description="Steps between split passes [-].")
    region: Region | None = Field(default=None, description="Only nodes inside may split; omitted: every node.")
    cohesive_capacity: Int | None = Field(
        default=None, gt=0, description="Initial cohesive element slots (they grow); default chosen by the build."
    )
    cohesive_substeps: Int = Field(
        default=1,
        ge=1,
        le=MAX_SUBSTEPS,
        description=(
            "Sub-steps per step of the cohesive elements' nodes under the elements' forces [-]: 1 steps them with "
            "every other force; n > 1 resolves openings a blast drives through δ_c within a step (n ≥ √β)."
        ),
    )
    seed_cracks: list[SeedCrack] = Field(default_factory=list, description="Open pre-cracks made at build time.")


# ----------------------------------------------------------------------------------------------------------------------
# FEM→DEM conversion
# ----------------------------------------------------------------------------------------------------------------------

CONVERSION_STRENGTH = {"tresca": "tresca_strength", "rankine": "tensile_strength", "mohr_coulomb": "cohesion"}
"""The material key each conversion criterion reads (Tresca τ_f, Rankine T_f, Mohr–Coulomb c)."""


class Conversion(_Model):
    """Adaptive FEM→DEM conversion (CIMNE §4–5): tets whose stress reaches a fraction of their material's strength
    turn into bonded spheres, penalty-coupled to the intact tets around them."""

    enabled: Bool = Field(
        default=False,
        description="Run the conversion pass (every mesh material needs the strength its criterion reads).",
    )
    criterion: Literal["tresca", "rankine", "mohr_coulomb"] = Field(
        default="tresca",
        description="'tresca' ((σ1 − σ3)/2 ≥ f τ_f), 'rankine' (σ1 ≥ f T_f) or 'mohr_coulomb' (c and φ).",
    )
    fraction: Float = Field(
        default=0.9, gt=0, le=1, description="Fraction f of the strength at which a tet converts (CIMNE: 90 %) [-]."
    )
    check_interval: Int = Field(default=1, ge=1, description="Steps between conversion passes [-].")
    region: Region | None = Field(
        default=None, description="Only tets whose centroid is inside may convert; omitted: every tet."
    )
    start_as_spheres: Region | None = Field(
        default=None, description="Tets whose centroid is inside are converted at t = 0, whatever their stress."
    )
    spheres_per_tet: Int = Field(
        default=1,
        description="Spheres spawned per converted tet: 1 (at its centroid) or 4 (one per corner sub-tet) [-].",
    )
    part: Name = Field(
        default="converted", description="Part of the spawned spheres (created if [parts] does not name it)."
    )
    coupling: Literal["tie", "band"] = Field(
        default="band",
        description="How spheres meet the continuum: 'band' (a blended DEM/FEM overlap band, CIMNE eqs. 8–9: "
        "converted tets within band_width tet layers of the continuum keep α of their FEM element, their spheres "
        "1 − α, tied to the element by penalty springs; it reflects less) or 'tie' (each converted tet dropped, its "
        "spheres tied to the tets around). Default 'band' (benchmarks/overlap_band.py), 'tie' with spheres_per_tet = 4 "
        "(the band needs 1).",
    )
    band_width: Int = Field(
        default=3,
        ge=1,
        description="Tet layers of the band, counted through shared edges from the continuum; α steps from 1 to 0 "
        "in band_width + 1 equal steps [-].",
    )
    band_penalty: Float = Field(
        default=1.0, gt=0, description="Factor on the band's penalty stiffness over the coupling rule [-]."
    )

    @field_validator("spheres_per_tet")
    @classmethod
    def _check_spheres_per_tet(cls, value: int) -> int:
        # warpdem.stages.multisphere: the corner sub-tets of the 1:8 subdivision (8 is not offered; it says why).
        if value not in (1, 4):
            raise ValueError("must be 1 or 4")
        return value

    @model_validator(mode="after")
    def _band_needs_one_sphere(self) -> Conversion:
        if self.spheres_per_tet != 1 and self.coupling == "band":
            if "coupling" in self.model_fields_set:
                raise ValueError(
                    "coupling = 'band' needs spheres_per_tet = 1 (use coupling = 'tie' with four spheres per tet)"
                )
            object.__setattr__(self, "coupling", "tie")  # the default falls back to what four spheres support
        return self


class Rigid(_Model):
    """Rigid blocks (LDEC §2–§4): each connected set of tets (what joints, cracks and conversion left in one piece)
    turns into one rigid body whose nodes follow it; contacts and joints act between the blocks (warpdem.stages.rigid).
    At most one of ``enabled``, ``switch_time`` and ``energy_fraction``."""

    enabled: Bool = Field(default=False, description="Rigid blocks from the start (t = 0).")
    switch_time: Float | None = Field(
        default=None, ge=0, description="Switch from deformable tets to rigid blocks at this time [s]."
    )
    energy_fraction: Float | None = Field(
        default=None,
        gt=0,
        lt=1,
        description="Switch once the kinetic energy of the element modes (the nodes' beyond each block's rigid "
        "motion) is below this fraction of the nodes' kinetic energy [-].",
    )
    check_interval: Int = Field(default=100, ge=1, description="Steps between checks of energy_fraction [-].")
    region: Region | None = Field(
        default=None, description="Only tets whose centroid is inside turn rigid; omitted: every tet."
    )
    materials: list[Name] | None = Field(
        default=None, description="Only tets of these materials turn rigid; omitted: every material."
    )

    @model_validator(mode="after")
    def _one_trigger(self) -> Rigid:
        given = [k for k in ("enabled", "switch_time", "energy_fraction") if getattr(self, k) not in (None, False)]
        if len(given) > 1:
            raise ValueError(
                f"takes at most one of 'enabled', 'switch_time', 'energy_fraction' (got {', '.join(given)})"
            )
        return self

    @property
    def active(self) -> bool:
        """Whether the blocks turn rigid at some point of the run."""
        return self.enabled or self.switch_time is not None or self.energy_fraction is not None


class MaterialRegion(_Model):
    """Tets of the mesh whose centroid lies in a region take another material (a second body, a lining)."""

    region: Region = Field(description="Tets whose centroid is inside take the material; later entries win.")
    material: Str = Field(description="Name of a material defined in [materials].")
