"""Run control and the global tables of a scene: [run], [gravity], [materials], [interactions], [contact], [parts],
[output] and [capacity]."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    Field,
    field_validator,
)

from .fields import (
    _DEVICE_PATTERN,
    _USD_SUFFIXES,
    MAX_GRAVITY,
    AutoOrNonNegative,
    AutoOrPositive,
    Bool,
    Float,
    Int,
    PathText,
    Str,
    Vec3,
    _Model,
)

# ----------------------------------------------------------------------------------------------------------------------
# Run control and global fields
# ----------------------------------------------------------------------------------------------------------------------


class Run(_Model):
    """Time integration and execution settings."""

    end_time: Float = Field(gt=0, description="Simulated end time [s].")
    dt: AutoOrPositive = Field(
        default="auto",
        description="Time step [s], or 'auto' for safety_factor times the critical (Rayleigh / Hertz) time step.",
    )
    safety_factor: Float = Field(
        default=0.2, gt=0, le=1, description="Fraction (0, 1] of the critical time step used when dt = 'auto' [-]."
    )
    output_rate: Float = Field(default=50.0, gt=0, description="Output frames per simulated second [Hz].")
    seed: Int = Field(
        default=0,
        ge=0,
        description="Seed of the random number generator (random packings; the joints' draws unless [mesh] seed) [-].",
    )
    device: Str = Field(default="cpu", description="Warp device: 'cpu', 'cuda' or 'cuda:<index>'.")
    allow_initial_overlap: Bool = Field(
        default=False,
        description="Run even when spheres start overlapping each other or the rock by more than 5 % of a radius, "
        "or with a centre inside the rock, or mesh nodes start pressed into another block by more than 5 % of a "
        "face's reach (warpdem.build.overlap); otherwise such a scene is refused before its first step.",
    )
    allow_unstable_dt: Bool = Field(
        default=False,
        description="Run an explicit dt above the critical time step (refused otherwise); the run-time guard still "
        "stops a run that blows up.",
    )
    resolution: Float = Field(
        default=1.0,
        gt=0,
        le=1000,
        description="Mesh refinement knob: tet edge lengths h (h_opening, the refinements' h, h_charge) are divided "
        "by it, box and arch divisions multiplied by it (Scene.scaled_mesh); 1 is sized for two CPU cores, a GPU takes "
        "4 or more [-].",
    )

    @field_validator("device")
    @classmethod
    def _check_device(cls, value: str) -> str:
        if not _DEVICE_PATTERN.fullmatch(value):
            raise ValueError("must be 'cpu', 'cuda' or 'cuda:<index>'")
        return value


class Gravity(_Model):
    """Uniform body acceleration."""

    vector: Vec3 = Field(default=(0.0, 0.0, -9.81), description="Gravitational acceleration [m/s^2].")

    @field_validator("vector")
    @classmethod
    def _bounded(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        # Beyond 1e5 g a frame's drift leaves any model (and float32 positions lose the step); no rock problem needs it.
        if not math.hypot(*value) <= MAX_GRAVITY:
            raise ValueError(f"magnitude must be <= {MAX_GRAVITY:g} m/s^2")
        return value


def _check_poisson(value: float) -> float:
    # nu = 0.5 makes the bulk modulus infinite and nu <= -1 the shear modulus non-positive.
    if not -1.0 < value < 0.5:
        raise ValueError("must be > -1 and < 0.5")
    return value


class Material(_Model):
    """Elastic solid material of particles, bonds and walls."""

    density: Float = Field(gt=0, description="Mass density [kg/m^3].")
    youngs_modulus: Float = Field(gt=0, description="Young's modulus [Pa].")
    poisson_ratio: Annotated[Float, AfterValidator(_check_poisson)] = Field(
        description="Poisson's ratio (-1, 0.5) [-]."
    )
    tensile_strength: Float | None = Field(
        default=None, gt=0, description="Tensile strength T_f of the continuum (nodal fracture, LDEC §2.2) [Pa]."
    )
    fracture_energy: Float | None = Field(
        default=None, gt=0, description="Fracture energy Γ of new cracks (cohesive elements, LDEC eq. 10) [J/m^2]."
    )
    cohesive_alpha: Float = Field(
        default=1.0,
        ge=0,
        le=1,
        description="Softening parameter α in [0, 1] of the cohesive elements (LDEC eq. 6): 1 a linear drop from f_c "
        "to 0 over δ_c, 0 a constant f_c until δ_c [-].",
    )
    tresca_strength: Float | None = Field(
        default=None, gt=0, description="Tresca (shear) strength for the FEM-to-DEM conversion (CIMNE §5) [Pa]."
    )
    cohesion: Float | None = Field(
        default=None, gt=0, description="Cohesion c of the Mohr–Coulomb conversion criterion [Pa]."
    )
    friction_angle: Float = Field(
        default=30.0, ge=0, lt=90, description="Friction angle φ of the Mohr–Coulomb conversion criterion [deg]."
    )
    bulk_viscosity_linear: Float = Field(
        default=0.06, ge=0, description="Linear bulk-viscosity coefficient c_lin of the tets (shock capture) [-]."
    )
    bulk_viscosity_quadratic: Float = Field(
        default=1.2, ge=0, description="Quadratic bulk-viscosity coefficient c_quad of the tets (shock capture) [-]."
    )
    mass_damping: Float = Field(
        default=0.0, ge=0, description="Mass-proportional (Rayleigh alpha) damping of the tets' nodes [1/s]."
    )

    @property
    def shear_modulus(self) -> float:
        """Shear modulus G = E / (2 (1 + nu)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))


class InteractionProps(_Model):
    """Contact properties between two materials."""

    friction: Float = Field(default=0.5, ge=0, description="Coulomb sliding friction coefficient [-].")
    restitution: Float = Field(default=0.5, gt=0, le=1, description="Normal coefficient of restitution (0, 1] [-].")
    rolling_friction: Float = Field(
        default=0.0, ge=0, description="Dimensionless rolling resistance coefficient (torque / (F_n R)) [-]."
    )


class InteractionPair(_Model):
    """Contact properties for one pair of materials; omitted values come from ``interactions.default``."""

    materials: tuple[Str, Str] = Field(description="The two material names (order-free; may be equal).")
    friction: Float | None = Field(default=None, ge=0, description="Coulomb sliding friction coefficient [-].")
    restitution: Float | None = Field(
        default=None, gt=0, le=1, description="Normal coefficient of restitution (0, 1] [-]."
    )
    rolling_friction: Float | None = Field(
        default=None, ge=0, description="Dimensionless rolling resistance coefficient [-]."
    )


class Interactions(_Model):
    """Default contact properties and per-pair overrides."""

    default: InteractionProps = Field(
        default_factory=InteractionProps, description="Properties for every material pair not listed in pairs."
    )
    pairs: list[InteractionPair] = Field(default_factory=list, description="Per material pair overrides.")


class ContactSettings(_Model):
    """Choice of contact laws and neighbour-list skin."""

    normal: Literal["hertz", "linear"] = Field(default="hertz", description="Normal force law.")
    tangential: Literal["mindlin", "linear"] = Field(default="mindlin", description="Tangential force law.")
    rolling: Literal["none", "constant_torque"] = Field(default="none", description="Rolling resistance law.")
    skin: AutoOrNonNegative = Field(
        default="auto", description="Verlet skin of the neighbour list [m], or 'auto' (chosen from the radii)."
    )
    surface_normal_stiffness: Float | None = Field(
        default=None,
        gt=0,
        description="Normal stiffness k_n per unit area [Pa/m] of the FEM contacts between faces that are no joint "
        "faces (outer surfaces, cracks), as a joint's normal_stiffness; omitted: the rock's E / h behind each face.",
    )


class Part(_Model):
    """A named group of particles sharing one material."""

    material: Str = Field(description="Name of a material defined in [materials].")


# ----------------------------------------------------------------------------------------------------------------------
# Output and capacity
# ----------------------------------------------------------------------------------------------------------------------


class Output(_Model):
    """What is written and where."""

    directory: PathText = Field(default="out", description="Output directory.")
    usd: PathText | None = Field(
        default=None, description="USD file inside directory (.usd, .usda or .usdc); '<name>.usdc' after loading."
    )
    color_by: Literal["speed", "part", "damage", "fragment"] = Field(
        default="speed",
        description="Particle colouring in the USD file; damage = the fraction of each sphere's bonds broken so far; "
        "fragment = a colour per fragment (warpdem.stages.fragments).",
    )
    bonds_as_curves: Bool = Field(default=False, description="Write intact bonds as USD curves.")
    usd_max_spheres: Int = Field(
        default=2_000_000,
        ge=1,
        description="Past this many spheres in a frame the USD file holds a subsample: the spheres whose id is a "
        "multiple of a power of two, the smallest that brings the frame within the limit, kept for the rest of the run "
        "(authored as /World/Particles.warpdem:sphereStride; the summary says it). The checkpoints and the VTU "
        "spheres keep all [-].",
    )
    cohesive_as_curves: Bool = Field(
        default=False,
        description="Write the intact cohesive elements of the crack tips (nodal fracture) as USD curves.",
    )
    checkpoint_every: Float = Field(
        default=0.0, ge=0, description="Checkpoint interval in simulated time [s]; 0 = only at the end."
    )
    checkpoint_dir: PathText = Field(default="checkpoints", description="Checkpoint directory, relative to directory.")
    mesh_color_by: Literal["stress", "speed", "material", "damage", "fragment"] = Field(
        default="stress",
        description="Colouring of the rock surface /World/Rock in the USD file; damage = each node's cohesive damage "
        "(fracture); fragment = a colour per fragment.",
    )
    vtu: Bool = Field(
        default=False,
        description="Also write the tet mesh of every frame as VTU (<stem>_vtu/ in directory, <stem> that of the USD "
        "file) with a <stem>.pvd collection for ParaView.",
    )
    particles_vtu: Bool = Field(
        default=False,
        description="Also write the spheres of every frame as VTU vertex cells (<stem>_particles/ in directory) "
        "listed in the same <stem>.pvd as the mesh.",
    )

    @field_validator("usd")
    @classmethod
    def _check_usd(cls, value: str | None) -> str | None:
        # Path's suffix, not the text's ending: ".usdc" alone is a hidden file without a suffix.
        if value is not None and Path(value).suffix.lower() not in _USD_SUFFIXES:
            raise ValueError("must be a file name ending with .usd, .usda or .usdc")
        return value


class Capacity(_Model):
    """Initial buffer sizes; buffers still grow on overflow, these only avoid the first regrowths."""

    particles: Int | None = Field(default=None, gt=0, description="Particle slots; default chosen by the builder.")
    neighbors_per_particle: Int = Field(default=8, gt=0, description="Contact candidate slots per particle.")
    nodes: Int | None = Field(default=None, gt=0, description="FEM node slots; default: the mesh's node count.")
    tets: Int | None = Field(default=None, gt=0, description="Tet slots; default: the mesh's tet count.")
