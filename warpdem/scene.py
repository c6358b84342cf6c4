"""Scene files: the validated TOML schema (SI units) that describes one simulation.

A scene file maps onto the pydantic models below (all ``extra="forbid"``). Every problem found while
loading is reported as one line ``<file>: <key.path>: <what is allowed> (got <value>)``, and all
problems of a file are reported together in one :class:`SceneError`, so a user fixes a file in one
pass instead of one error per run.

Loading happens in four passes:

1. TOML parsing (``tomllib``): syntax errors carry line and column.
2. Field validation (pydantic): types, ranges, unknown keys, unknown ``kind`` values.
3. Cross references and files: material / part names used before they are defined, duplicate
   interaction pairs, particle files that do not exist. These run only on a structurally valid scene,
   because they need the validated objects.
4. Sizes (:meth:`Scene.size_problems`): spheres, neighbour slots, nodes, tets and joint surfaces estimated from the
   scene and held against :mod:`warpdem.limits` before anything is packed, meshed or allocated. Every float is also
   held to the range the device's float32 represents (``Float``), so no scene number becomes inf or 0 on the device.

Python users build scenes without files through :func:`parse_scene`, which reports the same errors.
This module is pure host code: it must not import warp, so ``warpdem --help`` and scene checks stay fast.
"""

from __future__ import annotations

import itertools
import math
import os
import re
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    AllowInfNan,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PrivateAttr,
    Strict,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .geology import BOX_FACE_NAMES, OPENING_FACE_NAME, SURFACE_FACE_NAME
from .limits import (
    BYTES_PER_NEIGHBOR_SLOT,
    BYTES_PER_NODE,
    BYTES_PER_SPHERE,
    BYTES_PER_TET,
    F32_MAX,
    F32_MIN,
    size_problem,
)

__all__ = [
    "RESERVED_SECTIONS",
    "SCHEMA_VERSION",
    "AirblastLoad",
    "ArchMesh",
    "BlastHistory",
    "BondRegion",
    "Boundary",
    "Box",
    "BoxMesh",
    "BoxWall",
    "Capacity",
    "ContactSettings",
    "Conversion",
    "Cylinder",
    "FileMesh",
    "FileSource",
    "FriedlanderHistory",
    "GeologyMeshSpec",
    "Gravity",
    "InteractionPair",
    "InteractionProps",
    "Interactions",
    "JointDefaults",
    "JointSetSpec",
    "Layer",
    "Load",
    "Material",
    "MaterialRegion",
    "Mesh",
    "Opening",
    "Output",
    "PackingSource",
    "Part",
    "ParticleSource",
    "PlaneWall",
    "PressureLoad",
    "Region",
    "RoomOpening",
    "Run",
    "Scene",
    "SceneError",
    "ShaftOpening",
    "SphereSource",
    "TableHistory",
    "TunnelOpening",
    "Vec3",
    "VelocityLoad",
    "Wall",
    "default_scene_path",
    "load_scene",
    "parse_scene",
]

SCHEMA_VERSION = 1
"""The only scene schema version this release reads."""

RESERVED_SECTIONS = ("tets",)
"""Top-level sections planned for later schema versions; named explicitly so users are not told 'unknown key'."""

_NAME_PATTERN = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*")
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_DEVICE_PATTERN = re.compile(r"cpu|cuda(:\d+)?")
_USD_SUFFIXES = (".usd", ".usda", ".usdc")
_MAX_GOT_CHARS = 80
MAX_FILE_NAME_BYTES = 200
"""Longest file or folder name a scene may give (file systems allow 255 bytes; the writers add suffixes such as
``.partial.usdc``)."""
MAX_GRAVITY = 1e6
"""Largest gravity magnitude a scene may give [m/s²] (about 1e5 g)."""
MAX_JOINT_SURFACES = 5000
"""Most joint planes and discs a geology mesh may be fragmented by (Gmsh's boolean fragment grows faster than
linearly in their number)."""
_LATTICE_FRACTION = {"hcp": math.pi / (3.0 * math.sqrt(2.0)), "cubic": math.pi / 6.0}
_BYTES_EACH = {
    "spheres": BYTES_PER_SPHERE,
    "neighbor slots": BYTES_PER_NEIGHBOR_SLOT,
    "nodes": BYTES_PER_NODE,
    "tets": BYTES_PER_TET,
}


def _regular_tet_volume(edge: float) -> float:
    """Volume of a regular tetrahedron of edge ``edge`` [m³]: edge³ / (6√2)."""
    return edge**3 / (6.0 * math.sqrt(2.0))


# pydantic messages that speak Python where the user wrote TOML.
_PLAIN_MESSAGES = {
    "model_type": "must be a table",
    "model_attributes_type": "must be a table",
    "dict_type": "must be a table",
    "list_type": "must be an array",
    "tuple_type": "must be an array",
}


class SceneError(Exception):
    """A scene could not be loaded; carries one readable line per problem.

    Attributes:
        problems: One line per problem, ``<file>: <key.path>: <message>``.
    """

    def __init__(self, problems: list[str] | str) -> None:
        self.problems: list[str] = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(self.problems))

    def __str__(self) -> str:
        return "\n".join(self.problems)


# ----------------------------------------------------------------------------------------------------------------------
# Scalar and vector types
# ----------------------------------------------------------------------------------------------------------------------


def _check_float32(value: float) -> float:
    # The device computes in float32: a number it would turn into inf or 0 is refused here, naming the key, rather
    # than becoming NaN in the first frame (warpdem.limits).
    if value != 0.0 and not F32_MIN <= abs(value) <= F32_MAX:
        raise ValueError(
            f"must be 0 or between {F32_MIN:g} and {F32_MAX:g} in magnitude (the device computes in float32)"
        )
    return value


# Strict so that a quoted number ("1.0") or a boolean is reported instead of being silently converted;
# ints are still accepted for floats because TOML writers often drop the ".0". Every float of a scene lies in the
# range float32 represents (warpdem.limits.F32_MIN .. F32_MAX).
Float = Annotated[float, Strict(), AllowInfNan(False), AfterValidator(_check_float32)]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]


def _array_to_list(value: Any) -> Any:
    # Python users pass numpy vectors; TOML gives lists. Both must validate as the same tuple.
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


Vec3 = Annotated[tuple[Float, Float, Float], BeforeValidator(_array_to_list)]
"""Three finite floats; accepts a list, tuple or numpy array of length 3."""


def _check_name(value: str) -> str:
    if not _NAME_PATTERN.fullmatch(value):
        raise ValueError("invalid name; names start with a letter or '_' and contain only letters, digits, '_' and '-'")
    return value


def _check_path_text(value: Any) -> Any:
    # A file or folder name the operating system cannot take is refused here, naming the key, rather than failing
    # as an OSError when the first output file is opened after minutes of set-up.
    if isinstance(value, str | Path):
        text = str(value)
        if not text:
            raise ValueError("must not be empty")
        if any(ord(c) < 32 or ord(c) == 127 for c in text):
            raise ValueError("must not contain control characters (NUL, newline, ...)")
        longest = max((len(part.encode("utf-8", "surrogateescape")) for part in re.split(r"[/\\]", text)), default=0)
        if longest > MAX_FILE_NAME_BYTES:
            raise ValueError(f"a file or folder name is {longest} bytes long; allowed: at most {MAX_FILE_NAME_BYTES}")
    return value


PathText = Annotated[str, Strict(), AfterValidator(_check_path_text)]
"""A string that names a file or folder: no control characters, no name longer than MAX_FILE_NAME_BYTES."""

FilePath = Annotated[Path, BeforeValidator(_check_path_text)]
"""A path to an input file, checked like :data:`PathText`."""

Name = Annotated[str, Strict(), AfterValidator(_check_name)]
"""A material or part name: ``[A-Za-z_][A-Za-z0-9_-]*``."""


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _auto_or_positive(value: Any) -> Literal["auto"] | float:
    # Hand-written instead of a Literal | float union: a union reports one error per branch, and the
    # user should see a single line.
    if value == "auto":
        return "auto"
    if _is_number(value) and value > 0:
        return _check_float32(float(value))
    raise ValueError("must be 'auto' or a number > 0")


def _auto_or_non_negative(value: Any) -> Literal["auto"] | float:
    if value == "auto":
        return "auto"
    if _is_number(value) and value >= 0:
        return _check_float32(float(value))
    raise ValueError("must be 'auto' or a number >= 0")


AutoOrPositive = Annotated[Literal["auto"] | float, BeforeValidator(_auto_or_positive)]
AutoOrNonNegative = Annotated[Literal["auto"] | float, BeforeValidator(_auto_or_non_negative)]


class _Model(BaseModel):
    """Base of all scene models: unknown keys are errors, because a misspelt key silently ignored is a wrong run."""

    model_config = ConfigDict(extra="forbid")


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
    seed: Int = Field(default=0, ge=0, description="Seed of the random number generator (random packings) [-].")
    device: Str = Field(default="cpu", description="Warp device: 'cpu', 'cuda' or 'cuda:<index>'.")
    allow_initial_overlap: Bool = Field(
        default=False,
        description="Run even when spheres start overlapping each other or the rock by more than 5 % of a radius, "
        "or with a centre inside the rock (warpdem.overlap); otherwise such a scene is refused at build time.",
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
        description="Mesh refinement knob: tet edge lengths h (and h_opening) are divided by it, box and arch "
        "divisions multiplied by it (Scene.scaled_mesh); 1 is sized for two CPU cores, a GPU takes 4 or more [-].",
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


# ----------------------------------------------------------------------------------------------------------------------
# Continuum: the rock mesh, its joints, loads and boundaries
# ----------------------------------------------------------------------------------------------------------------------

PositiveInt = Annotated[Int, Field(gt=0)]
Vec2 = Annotated[tuple[Float, Float], BeforeValidator(_array_to_list)]
"""Two finite floats."""


def _fixed_field() -> Any:
    return Field(default=False, description="Hold every node of the mesh in place (an immobile rock body).")


def _velocity_field() -> Any:
    return Field(default=(0.0, 0.0, 0.0), description="Initial velocity of every node [m/s].")


class BoxMesh(_Model):
    """A structured tet mesh of an axis-aligned box (each cell split into 6 Kuhn tets)."""

    kind: Literal["box"] = Field(description="Mesh kind.")
    lo: Vec3 = Field(description="Lower corner [m].")
    hi: Vec3 = Field(description="Upper corner [m]; greater than lo in every component.")
    divisions: tuple[PositiveInt, PositiveInt, PositiveInt] = Field(description="Cells along x, y and z [-].")
    material: Str = Field(description="Name of a material defined in [materials].")
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)


class Layer(_Model):
    """A horizontal material layer of a geology mesh, from the previous layer top (or the box bottom) up."""

    z_top: Float = Field(description="Height of the top of the layer [m]; increasing from the bottom layer up.")
    material: Str = Field(description="Name of a material defined in [materials].")


class TunnelOpening(_Model):
    """A horizontal tunnel along x or y."""

    kind: Literal["tunnel"] = Field(description="Opening kind.")
    axis: Literal["x", "y"] = Field(description="Direction of the tunnel axis.")
    center: Vec2 = Field(
        description="Centre of the cross-section's bounding rectangle [m]: (x, z) for axis 'y', (y, z) for axis 'x'."
    )
    shape: Literal["circular", "horseshoe", "rectangular"] = Field(default="circular", description="Cross-section.")
    radius: Float | None = Field(default=None, gt=0, description="Radius of a circular tunnel [m].")
    width: Float | None = Field(default=None, gt=0, description="Span of a rectangular or horseshoe tunnel [m].")
    height: Float | None = Field(
        default=None, gt=0, description="Floor-to-crown height of a rectangular or horseshoe tunnel [m]."
    )
    span: Vec2 | None = Field(
        default=None, description="(start, end) along the axis [m]; omitted: through the whole model."
    )

    @model_validator(mode="after")
    def _check_shape(self) -> TunnelOpening:
        if self.shape == "circular":
            if self.radius is None:
                raise ValueError("a circular tunnel needs 'radius'")
            if self.width is not None or self.height is not None:
                raise ValueError("'width' and 'height' are only used by rectangular and horseshoe tunnels")
        else:
            if self.width is None or self.height is None:
                raise ValueError(f"a {self.shape} tunnel needs 'width' and 'height'")
            if self.radius is not None:
                raise ValueError("'radius' is only used by circular tunnels")
            if self.shape == "horseshoe" and not self.height > 0.5 * self.width:
                raise ValueError(f"a horseshoe tunnel needs height > width / 2 (got {self.height} <= {self.width}/2)")
        if self.span is not None and not self.span[1] > self.span[0]:
            raise ValueError(f"span: end must exceed start (got {list(self.span)})")
        return self


class ShaftOpening(_Model):
    """A vertical cylindrical shaft."""

    kind: Literal["shaft"] = Field(description="Opening kind.")
    center: Vec2 = Field(description="(x, y) of the shaft axis [m].")
    radius: Float = Field(gt=0, description="Shaft radius [m].")
    bottom: Float | None = Field(default=None, description="Height of the floor [m]; omitted: through the bottom.")
    top: Float | None = Field(default=None, description="Height of the top [m]; omitted: open to the surface.")

    @field_validator("top")
    @classmethod
    def _check_top(cls, value: float | None, info: ValidationInfo) -> float | None:
        bottom = info.data.get("bottom")
        if value is not None and bottom is not None and not value > bottom:
            raise ValueError(f"must be > bottom = {bottom}")
        return value


class RoomOpening(_Model):
    """An axis-aligned box-shaped excavation."""

    kind: Literal["room"] = Field(description="Opening kind.")
    lo: Vec3 = Field(description="Lower corner [m].")
    hi: Vec3 = Field(description="Upper corner [m]; greater than lo in every component.")

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)


Opening = Annotated[TunnelOpening | ShaftOpening | RoomOpening, Field(discriminator="kind")]
"""One ``[[mesh.openings]]`` entry, selected by ``kind``."""


def _check_one_stiffness(model: Any) -> None:
    # A joint's normal spring is either relative to the rock behind it or a physical k_n: both would be ambiguous.
    if model.stiffness_factor is not None and model.normal_stiffness is not None:
        raise ValueError("takes one of 'stiffness_factor' and 'normal_stiffness', not both")


class JointProperties(_Model):
    """Properties of the joints of one joint set (geology) or joint group (mesh file); omitted ones come from
    ``[joints]``."""

    friction: Float | None = Field(default=None, ge=0, description="Joint friction coefficient; default [joints].")
    cohesion: Float | None = Field(default=None, ge=0, description="Joint cohesion [Pa]; default [joints].")
    tensile_strength: Float | None = Field(
        default=None, ge=0, description="Joint tensile strength [Pa]; default [joints]."
    )
    stiffness_factor: Float | None = Field(
        default=None, gt=0, description="Joint penalty stiffness relative to the rock's (E / h) [-]; default [joints]."
    )
    normal_stiffness: Float | None = Field(
        default=None,
        gt=0,
        description="Joint normal stiffness k_n per unit area [Pa/m], independent of the mesh (instead of "
        "stiffness_factor); default [joints].",
    )
    restitution: Float | None = Field(
        default=None, gt=0, le=1, description="Restitution (0, 1] of the joint's normal dashpot [-]; default [joints]."
    )
    shear_stiffness_ratio: Float | None = Field(
        default=None, gt=0, description="Tangential to normal stiffness ratio k_t / k_n [-]; default [joints]."
    )

    @model_validator(mode="after")
    def _one_stiffness(self) -> JointProperties:
        _check_one_stiffness(self)
        return self


class JointSetSpec(JointProperties):
    """A set of parallel joints (geological dip / dip direction), and the properties of its joints."""

    name: Name | None = Field(default=None, description="Name of the set; default 'joint<index>'.")
    dip: Float = Field(ge=0, le=90, description="Dip: angle of the planes below the horizontal, [0, 90] [deg].")
    dip_direction: Float = Field(
        description="Dip direction: azimuth of steepest descent, clockwise from north (+y) [deg]."
    )
    spacing: Float = Field(gt=0, description="Distance between neighbouring planes along their normal [m].")
    offset: Float = Field(default=0.0, description="Signed distance of plane 0 from the origin along the normal [m].")
    persistence: Literal["persistent", "disc", "layers"] = Field(
        default="persistent",
        description="'persistent' (through the model), 'disc' (circular joints) or 'layers' (planes persisting "
        "through 'layers' slabs between the planes of the persistent set 'reference', alternately).",
    )
    radius: Float | None = Field(default=None, gt=0, description="Disc radius [m] (persistence 'disc').")
    disc_spacing: Float | None = Field(
        default=None, gt=0, description="Disc centre pitch within a plane [m] (persistence 'disc'); default 2.5 radius."
    )
    reference: Int | None = Field(
        default=None, ge=0, description="Index of the persistent joint set bounding the slabs (persistence 'layers')."
    )
    layers: Int = Field(default=1, ge=1, description="Slabs a plane persists through (persistence 'layers') [-].")
    phase: Literal[0, 1] = Field(default=0, description="Which alternation of slab groups holds joints (0 or 1).")
    jitter_position: Float = Field(default=0.0, ge=0, description="Uniform random shift of each plane [m].")
    jitter_angle: Float = Field(default=0.0, ge=0, description="Uniform random tilt of each plane's normal [deg].")

    @model_validator(mode="after")
    def _check_persistence(self) -> JointSetSpec:
        if self.persistence == "disc" and self.radius is None:
            raise ValueError("persistence 'disc' needs 'radius'")
        if self.persistence == "layers" and self.reference is None:
            raise ValueError("persistence 'layers' needs 'reference' (the index of a persistent joint set)")
        unused = [
            key
            for key, wanted in (("radius", "disc"), ("disc_spacing", "disc"), ("reference", "layers"))
            if getattr(self, key) is not None and self.persistence != wanted
        ]
        if unused:
            raise ValueError(f"{', '.join(repr(k) for k in unused)} not used with persistence {self.persistence!r}")
        return self


class GeologyMeshSpec(_Model):
    """A jointed, layered rock box with openings, meshed with Gmsh so that the tets conform to the joints."""

    kind: Literal["geology"] = Field(description="Mesh kind.")
    lo: Vec3 = Field(description="Lower corner of the rock box [m].")
    hi: Vec3 = Field(description="Upper corner of the rock box [m]; greater than lo in every component.")
    material: Str = Field(description="Material above the highest layer top (the whole box without layers).")
    layers: list[Layer] = Field(default_factory=list, description="Horizontal material layers, bottom up.")
    openings: list[Opening] = Field(default_factory=list, description="Tunnels, shafts and rooms.")
    joint_sets: list[JointSetSpec] = Field(default_factory=list, description="Joint sets.")
    h: Float = Field(gt=0, description="Target tet edge length [m].")
    h_opening: Float | None = Field(default=None, gt=0, description="Edge length on the opening walls [m]; default h.")
    refine_distance: Float | None = Field(
        default=None, gt=0, description="Distance over which the size grows from h_opening to h [m]; default 4 h."
    )
    seed: Int | None = Field(default=None, ge=0, description="Seed of the joint jitter; default run.seed.")
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)


def _joint_group_table(value: Any) -> Any:
    # The array form predates per-group properties; it stays valid and means "these groups, [joints] properties".
    if value is None or isinstance(value, Mapping):
        return value
    if isinstance(value, list | tuple):
        bad = [i for i, name in enumerate(value) if not isinstance(name, str)]
        if bad:
            raise ValueError(f"item {bad[0]} must be a group name (a string)")
        repeated = sorted({name for name in value if value.count(name) > 1})
        if repeated:
            raise ValueError(f"group {repeated[0]!r} is listed twice")
        return {name: {} for name in value}
    raise ValueError("must be an array of triangle group names or a table of group name -> joint properties")


class FileMesh(_Model):
    """A ready tetrahedral mesh file (Gmsh .msh, VTU or legacy VTK) read through meshio."""

    kind: Literal["file"] = Field(description="Mesh kind.")
    path: FilePath = Field(description="Mesh file, relative to the scene file; absolute after loading.")
    material_map: dict[Str, Str] = Field(
        default_factory=dict,
        description="Tet physical group (name or number) -> material; omitted: the group names are material names.",
    )
    material: Str | None = Field(
        default=None, description="One material for every tet, whatever the groups (instead of material_map)."
    )
    joint_groups: Annotated[dict[Str, JointProperties] | None, BeforeValidator(_joint_group_table)] = Field(
        default=None,
        description="Triangle groups that are joints: an array of group names (properties from [joints]) or a table "
        "group name -> joint properties; omitted: the groups whose names start with 'joint'.",
    )
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    @model_validator(mode="after")
    def _one_material_source(self) -> FileMesh:
        if self.material is not None and self.material_map:
            raise ValueError("give 'material' or 'material_map', not both")
        return self


def _positive_vec3(value: tuple[float, float, float]) -> tuple[float, float, float]:
    if not all(c > 0.0 for c in value):
        raise ValueError("every component must be > 0")
    return value


class CylinderMesh(_Model):
    """A solid circular cylinder (a disc when short) along a coordinate axis, meshed with Gmsh."""

    kind: Literal["cylinder"] = Field(description="Mesh kind.")
    center: Vec3 = Field(description="Centre of the base disc [m] (as a cylinder region's).")
    axis: Literal["x", "y", "z"] = Field(default="z", description="Coordinate axis of the cylinder.")
    radius: Float = Field(gt=0, description="Radius [m].")
    height: Float = Field(gt=0, description="Length along the axis from the base disc [m] (a disc's thickness).")
    h: Float = Field(gt=0, description="Target tet edge length [m].")
    material: Str = Field(description="Name of a material defined in [materials].")
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    def volume(self) -> float:
        """Volume π r² height [m³]."""
        return math.pi * self.radius**2 * self.height


class EllipsoidMesh(_Model):
    """A solid ellipsoid with axis-aligned semi-axes (a sphere when they are equal), meshed with Gmsh."""

    kind: Literal["ellipsoid"] = Field(description="Mesh kind.")
    center: Vec3 = Field(description="Centre [m].")
    radii: Annotated[Vec3, AfterValidator(_positive_vec3)] = Field(description="Semi-axes along x, y and z [m].")
    h: Float = Field(gt=0, description="Target tet edge length [m].")
    material: Str = Field(description="Name of a material defined in [materials].")
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    def volume(self) -> float:
        """Volume 4/3 π a b c [m³]."""
        return 4.0 / 3.0 * math.pi * math.prod(self.radii)


ARCH_FACE_NAMES = ("left", "right", "downstream", "upstream", "base", "crest")
"""Face sets of an arch mesh: the two abutment ends (angle − and +), the inner (concave) and outer (convex) faces, the
base and the crest."""


class ArchMesh(_Model):
    """A curved wall (an arch dam section): a structured tet mesh of an annular sector about a vertical axis, each
    cell split into 6 Kuhn tets. Curved in plan; with ``bulge`` also in section (a double-curvature dam)."""

    kind: Literal["arch"] = Field(description="Mesh kind.")
    center: Vec3 = Field(description="Point of the vertical axis at the base [m]; the arch opens towards -y.")
    radius: Float = Field(gt=0, description="Radius of the outer (upstream, convex) face at the base [m].")
    thickness: Float = Field(gt=0, description="Radial thickness at the base [m].")
    crest_thickness: Float | None = Field(
        default=None, gt=0, description="Radial thickness at the crest [m]; default the base thickness."
    )
    height: Float = Field(gt=0, description="Height from the base to the crest [m].")
    angle: Float = Field(gt=0, le=180, description="Central angle of the sector, symmetric about +y [deg].")
    bulge: Float = Field(
        default=0.0,
        description="Radial offset of the section at mid-height [m] (a parabola, 0 at base and crest): the second "
        "curvature of a double-curvature dam.",
    )
    divisions: tuple[PositiveInt, PositiveInt, PositiveInt] = Field(
        description="Cells along the arc, through the thickness and up the height [-]."
    )
    material: Str = Field(description="Name of a material defined in [materials].")
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    @model_validator(mode="after")
    def _inner_radius(self) -> ArchMesh:
        thickest = max(self.thickness, self.crest_thickness or self.thickness)
        if not self.radius - thickest - max(0.0, -self.bulge) > 0.0:
            raise ValueError(
                f"radius must exceed the thickness (and any inward bulge): radius {self.radius}, thickness {thickest}"
            )
        return self


class BrickMeshSpec(_Model):
    """Rock laid in courses of equal blocks (warpdem.bricks): bedding joints between the courses, head joints between
    the blocks, every other course shifted (running bond), on a structured grid of cells no longer than h."""

    kind: Literal["bricks"] = Field(description="Mesh kind.")
    lo: Vec3 = Field(description="Lower corner of the box [m].")
    hi: Vec3 = Field(description="Upper corner of the box [m] (rounded to whole cells); greater than lo.")
    material: Str = Field(description="Name of a material defined in [materials].")
    brick: Vec3 = Field(description="Block length along x, depth along y and height along z [m], each > 0.")
    stagger: Float = Field(
        default=0.5, ge=0, lt=1, description="Shift of each course against the one below, in block lengths [-]."
    )
    h: Float = Field(gt=0, description="Largest cell edge [m] (run.resolution divides it).")
    openings: list[Opening] = Field(
        default_factory=list, description="Tunnels, shafts and rooms: every cell whose centre is inside is removed."
    )
    bedding: JointProperties | None = Field(
        default=None, description="Properties of the joints between the courses; omitted ones from [joints]."
    )
    head: JointProperties | None = Field(
        default=None, description="Properties of the joints between the blocks of a course; omitted ones from [joints]."
    )
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)

    @field_validator("brick")
    @classmethod
    def _check_brick(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(v > 0 for v in value):
            raise ValueError("every size must be > 0")
        return value


Mesh = Annotated[
    BoxMesh | GeologyMeshSpec | FileMesh | CylinderMesh | EllipsoidMesh | ArchMesh | BrickMeshSpec,
    Field(discriminator="kind"),
]
"""The ``[mesh]`` section, selected by ``kind``."""


class JointDefaults(_Model):
    """Properties of joints that their joint set does not set."""

    friction: Float = Field(default=0.6, ge=0, description="Coulomb friction coefficient of the joints [-].")
    cohesion: Float = Field(default=0.0, ge=0, description="Cohesion of the joints [Pa].")
    tensile_strength: Float = Field(default=0.0, ge=0, description="Tensile strength of the joints [Pa].")
    stiffness_factor: Float | None = Field(
        default=None,
        gt=0,
        description="Joint contact stiffness relative to the rock's (E / h) [-]; 1 when neither it nor "
        "normal_stiffness is given.",
    )
    normal_stiffness: Float | None = Field(
        default=None,
        gt=0,
        description="Joint normal stiffness k_n per unit area [Pa/m], independent of the mesh (instead of "
        "stiffness_factor).",
    )
    restitution: Float = Field(
        default=0.5, gt=0, le=1, description="Coefficient of restitution (0, 1] of the joints' normal dashpot [-]."
    )
    shear_stiffness_ratio: Float = Field(
        default=0.5, gt=0, description="Tangential to normal stiffness ratio k_t / k_n of the joints [-]."
    )

    @model_validator(mode="after")
    def _one_stiffness(self) -> JointDefaults:
        _check_one_stiffness(self)
        return self


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

    @field_validator("spheres_per_tet")
    @classmethod
    def _check_spheres_per_tet(cls, value: int) -> int:
        # warpdem.multisphere: the corner sub-tets of the 1:8 subdivision (8 is not offered; it says why).
        if value not in (1, 4):
            raise ValueError("must be 1 or 4")
        return value


class Rigid(_Model):
    """Rigid blocks (LDEC §2–§4): each connected set of tets (what joints, cracks and conversion left in one piece)
    turns into one rigid body whose nodes follow it; contacts and joints act between the blocks (warpdem.rigid). At
    most one of ``enabled``, ``switch_time`` and ``energy_fraction``."""

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
        "fragment = a colour per fragment (warpdem.fragments).",
    )
    bonds_as_curves: Bool = Field(default=False, description="Write intact bonds as USD curves.")
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


# ----------------------------------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------------------------------


def _check_schema_version(value: int) -> int:
    if value != SCHEMA_VERSION:
        raise ValueError(f"unsupported schema version; supported: {SCHEMA_VERSION}")
    return value


def _check_scene_name(value: str) -> str:
    # The name becomes the default USD file name.
    if not value or "/" in value or "\\" in value:
        raise ValueError("must be a non-empty name without path separators")
    return _check_path_text(value)


def _check_materials(value: dict[str, Material]) -> dict[str, Material]:
    if not value:
        raise ValueError("at least one material is required")
    return value


class Scene(_Model):
    """A complete simulation description. Build it with :func:`load_scene` or :func:`parse_scene`."""

    schema_version: Annotated[Int, AfterValidator(_check_schema_version)] = Field(
        default=SCHEMA_VERSION, description="Scene schema version; this release reads 1."
    )
    name: Annotated[Str, AfterValidator(_check_scene_name)] = Field(
        default="scene", description="Scene name; defaults to the file stem."
    )
    description: Str = Field(default="", description="Free text.")
    run: Run = Field(description="Time integration and execution settings.")
    gravity: Gravity = Field(default_factory=Gravity, description="Uniform body acceleration.")
    materials: Annotated[dict[Name, Material], AfterValidator(_check_materials)] = Field(
        description="Materials by name."
    )
    interactions: Interactions = Field(default_factory=Interactions, description="Contact properties.")
    contact: ContactSettings = Field(default_factory=ContactSettings, description="Contact laws.")
    parts: dict[Name, Part] = Field(default_factory=dict, description="Parts by name.")
    particles: list[ParticleSource] = Field(default_factory=list, description="Particle sources.")
    bonds: list[BondRegion] = Field(default_factory=list, description="Bonded regions.")
    walls: list[Wall] = Field(default_factory=list, description="Rigid walls.")
    mesh: Mesh | None = Field(default=None, description="The rock mass as a tet mesh (continuum).")
    joints: JointDefaults = Field(
        default_factory=JointDefaults, description="Joint properties that a joint set does not set."
    )
    loads: list[Load] = Field(default_factory=list, description="Loads on the mesh.")
    boundaries: list[Boundary] = Field(default_factory=list, description="Boundary conditions of the mesh.")
    fracture: Fracture = Field(default_factory=Fracture, description="Nodal fracture of the rock mesh.")
    conversion: Conversion = Field(default_factory=Conversion, description="Adaptive FEM→DEM conversion.")
    rigid: Rigid = Field(default_factory=Rigid, description="Rigid blocks, from the start or by a switch.")
    material_regions: list[MaterialRegion] = Field(
        default_factory=list, description="Regions of the mesh made of another material than the mesh's."
    )
    output: Output = Field(default_factory=Output, description="Output settings.")
    capacity: Capacity = Field(default_factory=Capacity, description="Initial buffer capacities.")
    _source: str | None = PrivateAttr(default=None)

    @property
    def source(self) -> str:
        """What error messages name the scene by: the file it was loaded from, else its name."""
        return self._source if self._source is not None else self.name

    @model_validator(mode="before")
    @classmethod
    def _default_name(cls, data: Any, info: ValidationInfo) -> Any:
        # The default name depends on the file the scene came from, which only the loader knows.
        default = (info.context or {}).get("default_name")
        if default is not None and isinstance(data, Mapping) and "name" not in data:
            return {**data, "name": default}
        return data

    @model_validator(mode="after")
    def _check_rigid(self) -> Scene:
        unknown = [name for name in self.rigid.materials or [] if name not in self.materials]
        if unknown:
            raise ValueError(f"rigid.materials: {unknown[0]!r} is not a material of [materials]")
        if self.rigid.active and self.mesh is None:
            raise ValueError("rigid: rigid blocks need a [mesh] (they are made of its tets)")
        return self

    @model_validator(mode="after")
    def _default_usd(self) -> Scene:
        if self.output.usd is None:
            self.output.usd = f"{self.name}.usdc"
        return self

    def material_names(self) -> list[str]:
        """Material names in definition order; a material's position is its integer id."""
        return list(self.materials)

    def material_index(self, name: str) -> int:
        """Integer id of a material (its position in [materials]).

        Raises:
            KeyError: No such material.
        """
        try:
            return self.material_names().index(name)
        except ValueError:
            raise KeyError(name) from None

    def part_names(self) -> list[str]:
        """Part names in definition order; a part's position is its integer id."""
        return list(self.parts)

    def part_material(self, part: str) -> Material:
        """Material of a part."""
        return self.materials[self.parts[part].material]

    def interaction_for(self, a: str, b: str) -> InteractionProps:
        """Contact properties between materials ``a`` and ``b`` (order-free).

        Values a matching ``[[interactions.pairs]]`` entry sets take precedence; the rest come from
        ``interactions.default``.
        """
        default = self.interactions.default
        for pair in self.interactions.pairs:
            if sorted(pair.materials) == sorted((a, b)):
                overrides = {
                    key: getattr(pair, key) for key in InteractionProps.model_fields if getattr(pair, key) is not None
                }
                return default.model_copy(update=overrides)
        return default.model_copy()

    def bond_youngs_modulus(self, bond: BondRegion) -> float:
        """Young's modulus of the bonds of a bonded region [Pa]: its own, else its material's."""
        if bond.youngs_modulus is not None:
            return bond.youngs_modulus
        assert bond.material is not None  # guaranteed by the validator
        return self.materials[bond.material].youngs_modulus

    def reference_problems(self) -> list[tuple[str, str]]:
        """Cross-reference checks that need the whole validated scene.

        Returns:
            ``(key path, message)`` per problem: unknown material or part names, duplicate interaction pairs.
        """
        problems: list[tuple[str, str]] = []
        materials = self.material_names()
        parts = self.part_names()

        def check(path: str, name: str, defined: list[str], what: str) -> None:
            if name not in defined:
                listed = ", ".join(repr(n) for n in defined) or "(none)"
                problems.append((path, f"unknown {what} {name!r}; defined {what}s: {listed}"))

        for part_name, part in self.parts.items():
            check(f"parts.{_format_key(part_name)}.material", part.material, materials, "material")
        seen: dict[tuple[str, ...], int] = {}
        for i, pair in enumerate(self.interactions.pairs):
            for j, name in enumerate(pair.materials):
                check(f"interactions.pairs[{i}].materials[{j}]", name, materials, "material")
            key = tuple(sorted(pair.materials))
            if key in seen:
                problems.append(
                    (
                        f"interactions.pairs[{i}].materials",
                        f"duplicate pair {list(pair.materials)}; already defined at interactions.pairs[{seen[key]}]",
                    )
                )
            else:
                seen[key] = i
        for i, source in enumerate(self.particles):
            check(f"particles[{i}].part", source.part, parts, "part")
        for i, bond in enumerate(self.bonds):
            if bond.material is not None:
                check(f"bonds[{i}].material", bond.material, materials, "material")
        for i, wall in enumerate(self.walls):
            check(f"walls[{i}].material", wall.material, materials, "material")
        problems += self._mesh_problems(check)
        return problems

    def size_problems(self) -> list[tuple[str, str]]:
        """Sizes this scene would allocate, estimated before anything is packed, meshed or allocated.

        Spheres of a packing: region volume × solid fraction / sphere volume (hcp π/(3√2), cubic π/6, random its
        target), capped by ``count``; tets of a box mesh: 6 per cell, of a geology mesh: model volume / the volume of
        a regular tet of edge h, h³/(6√2) (and of edge h_opening, as if the refinement filled the model: an upper
        bound), a node per 4 tets; neighbour slots: sphere slots × neighbors_per_particle; explicit capacities as
        given. Spheres of files are counted when read (the builder).

        Returns:
            ``(key path, message)`` when the estimate exceeds :data:`warpdem.limits.MAX_ELEMENTS` of a kind or the
            memory of this machine (the key is that of the largest contributor); else an empty list.
        """
        contributions: list[tuple[str, str, float]] = []  # (key, kind, count)
        for i, src in enumerate(self.particles):
            if isinstance(src, PackingSource):
                fraction = _LATTICE_FRACTION.get(src.arrangement, src.target_volume_fraction)
                count = fraction * src.region.volume() / (4.0 / 3.0 * math.pi * src.radius**3)
                if src.count is not None:
                    count = min(count, src.count)
                contributions.append((f"particles[{i}].radius", "spheres", count))
            elif isinstance(src, SphereSource):
                contributions.append((f"particles[{i}]", "spheres", 1.0))
        spheres = sum(n for _, kind, n in contributions if kind == "spheres")
        if self.capacity.particles is not None and self.capacity.particles > spheres:
            contributions.append(("capacity.particles", "spheres", self.capacity.particles - spheres))
            spheres = float(self.capacity.particles)
        contributions.append(
            ("capacity.neighbors_per_particle", "neighbor slots", spheres * self.capacity.neighbors_per_particle)
        )
        mesh = self.scaled_mesh()
        tets = nodes = 0.0
        if isinstance(mesh, BoxMesh | ArchMesh):
            cells = math.prod(float(d) for d in mesh.divisions)
            tets, nodes = 6.0 * cells, math.prod(float(d) + 1.0 for d in mesh.divisions)
            key = "mesh.divisions"
        elif isinstance(mesh, GeologyMeshSpec):
            volume = math.prod(h - l for h, l in zip(mesh.hi, mesh.lo, strict=True))
            tets = volume / _regular_tet_volume(mesh.h)
            if mesh.openings and mesh.h_opening is not None and mesh.h_opening < mesh.h:
                tets += volume / _regular_tet_volume(mesh.h_opening)
            nodes = tets / 4.0
            key = "mesh.h"
        elif isinstance(mesh, CylinderMesh | EllipsoidMesh):
            tets = mesh.volume() / _regular_tet_volume(mesh.h)
            nodes = tets / 4.0
            key = "mesh.h"
        if tets:
            contributions += [(key, "tets", tets), (key, "nodes", nodes)]
        surfaces = self._joint_surface_problem()
        if surfaces is not None:
            return [surfaces]
        for name, kind in (("tets", "tets"), ("nodes", "nodes")):
            given = getattr(self.capacity, name)
            if given is not None:
                contributions.append((f"capacity.{name}", kind, float(given)))
        counts: dict[str, float] = {}
        for _, kind, n in contributions:
            counts[kind] = counts.get(kind, 0.0) + n
        problem = size_problem(counts, _BYTES_EACH)
        if problem is None:
            return []
        # Blame the key that asks for the most memory: a sphere source with its share of neighbour slots (at the
        # default count per sphere), or neighbors_per_particle for the slots it asks beyond that default.
        k = self.capacity.neighbors_per_particle
        default_k = Capacity.model_fields["neighbors_per_particle"].default
        sphere_bytes = BYTES_PER_SPHERE + min(k, default_k) * BYTES_PER_NEIGHBOR_SLOT

        def blame(c: tuple[str, str, float]) -> float:
            if c[1] == "spheres":
                return c[2] * sphere_bytes
            if c[1] == "neighbor slots":
                return spheres * max(k - default_k, 0) * BYTES_PER_NEIGHBOR_SLOT
            return c[2] * _BYTES_EACH[c[1]]

        worst = max(contributions, key=blame)
        return [(worst[0], problem)]

    def scaled_mesh(self) -> Mesh | None:
        """The ``[mesh]`` at ``run.resolution``: edge lengths h and h_opening divided by it, box and arch divisions
        multiplied by it (rounded, at least 1); a mesh file as it is. Resolution 1 gives the mesh as written."""
        mesh, k = self.mesh, self.run.resolution
        if mesh is None or k == 1.0 or mesh.kind == "file":
            return mesh
        if mesh.kind in ("box", "arch"):
            return mesh.model_copy(update={"divisions": tuple(max(1, round(d * k)) for d in mesh.divisions)})
        update = {"h": mesh.h / k}
        if mesh.kind == "geology" and mesh.h_opening is not None:
            update["h_opening"] = mesh.h_opening / k
        return mesh.model_copy(update=update)

    def _joint_surface_problem(self) -> tuple[str, str] | None:
        """Refuses joint sets that would hand Gmsh more than MAX_JOINT_SURFACES planes and discs to fragment the model
        by (a spacing far below the model size): the count is the model's diagonal / spacing + 1 planes per set, times
        (diagonal / disc pitch + 1)² discs per plane for disc joints."""
        mesh = self.mesh
        if not isinstance(mesh, GeologyMeshSpec):
            return None
        diagonal = math.dist(mesh.lo, mesh.hi)
        total, worst, worst_count = 0.0, "", -1.0
        for i, js in enumerate(mesh.joint_sets):
            count = diagonal / js.spacing + 1.0
            if js.persistence == "disc" and js.radius is not None:
                pitch = js.disc_spacing or 2.5 * js.radius
                count *= (diagonal / pitch + 1.0) ** 2
            total += count
            if count > worst_count:
                worst, worst_count = f"mesh.joint_sets[{i}].spacing", count
        if total <= MAX_JOINT_SURFACES:
            return None
        return worst, (
            f"would cut the model with {total:.3g} joint surfaces (planes and discs); the limit is "
            f"{MAX_JOINT_SURFACES}: make the spacing larger compared with the model ({diagonal:.3g} m across)"
        )

    def mesh_material_names(self) -> list[str] | None:
        """Materials the mesh's tets may take, known before it is built (None for a mesh file with neither
        ``material`` nor ``material_map``: its group names, read at build)."""
        mesh = self.mesh
        if mesh is None:
            return []
        if mesh.kind == "file":
            if mesh.material is not None:
                return [mesh.material]
            return list(dict.fromkeys(mesh.material_map.values())) or None
        names = [mesh.material]
        if mesh.kind == "geology":
            names += [layer.material for layer in mesh.layers]
        names += [zone.material for zone in self.material_regions]
        return list(dict.fromkeys(names))

    def fracture_material_problems(self, names: list[str]) -> list[tuple[str, str]]:
        """``(key path, message)`` for each of the named (defined) materials that nodal fracture cannot split: one
        without ``tensile_strength`` T_f or ``fracture_energy`` Γ (the split criterion and eq. 10's δ_c need both)."""
        problems = []
        for name in names:
            material = self.materials.get(name)
            if material is None:
                continue  # an unknown name is reported by the reference checks
            for key in ("tensile_strength", "fracture_energy"):
                if getattr(material, key) is None:
                    problems.append(
                        (
                            f"materials.{_format_key(name)}.{key}",
                            "required: [fracture] is enabled and the mesh is made of this material "
                            "(allowed: a number > 0)",
                        )
                    )
        return problems

    def conversion_material_problems(self, names: list[str]) -> list[tuple[str, str]]:
        """``(key path, message)`` for each of the named (defined) materials that lacks the strength the conversion
        criterion reads (:data:`CONVERSION_STRENGTH`), when ``[conversion]`` is enabled."""
        if not self.conversion.enabled:
            return []
        criterion = self.conversion.criterion
        key = CONVERSION_STRENGTH[criterion]
        return [
            (
                f"materials.{_format_key(name)}.{key}",
                f"required: [conversion] is enabled with criterion {criterion!r} and the mesh is made of this "
                "material (allowed: a number > 0)",
            )
            for name in names
            if name in self.materials and getattr(self.materials[name], key) is None
        ]

    def face_set_names(self) -> list[str] | None:
        """Face set names the mesh is known to have before it is built (None for a mesh file: read at build)."""
        mesh = self.mesh
        if mesh is None or mesh.kind == "file":
            return None
        if mesh.kind in ("cylinder", "ellipsoid"):
            return [SURFACE_FACE_NAME]
        if mesh.kind == "arch":
            return list(ARCH_FACE_NAMES)
        names = list(BOX_FACE_NAMES)
        if mesh.kind in ("geology", "bricks") and mesh.openings:
            names.append(OPENING_FACE_NAME)
        return names

    def _mesh_problems(self, check: Any) -> list[tuple[str, str]]:
        problems: list[tuple[str, str]] = []
        if self.conversion.start_as_spheres is not None and not self.conversion.enabled:
            problems.append(("conversion.start_as_spheres", "needs conversion.enabled = true"))
        mesh = self.mesh
        if mesh is None:
            for section, entries in (("loads", self.loads), ("boundaries", self.boundaries)):
                if entries:
                    problems.append((section, "needs a [mesh] to act on"))
            if self.fracture.enabled:
                problems.append(("fracture.enabled", "needs a [mesh] to split (nodal fracture acts on tets)"))
            if self.fracture.seed_cracks:
                problems.append(("fracture.seed_cracks", "needs a [mesh] to crack"))
            if self.conversion.enabled:
                problems.append(("conversion.enabled", "needs a [mesh] to convert (FEM→DEM conversion acts on tets)"))
            if self.material_regions:
                problems.append(("material_regions", "needs a [mesh] whose tets they assign"))
            return problems
        materials = self.material_names()
        for i, zone in enumerate(self.material_regions):
            check(f"material_regions[{i}].material", zone.material, materials, "material")
        if self.fracture.enabled:
            problems += self.fracture_material_problems(self.mesh_material_names() or [])
        problems += self.conversion_material_problems(self.mesh_material_names() or [])
        if mesh.kind in ("box", "geology", "cylinder", "ellipsoid", "arch", "bricks"):
            check("mesh.material", mesh.material, materials, "material")
        if mesh.kind == "file":
            if mesh.material is not None:
                check("mesh.material", mesh.material, materials, "material")
            for group, name in mesh.material_map.items():
                check(f"mesh.material_map.{_format_key(group)}", name, materials, "material")
        if mesh.kind == "geology":
            lo_z, hi_z = mesh.lo[2], mesh.hi[2]
            previous = lo_z
            for i, layer in enumerate(mesh.layers):
                check(f"mesh.layers[{i}].material", layer.material, materials, "material")
                if not previous < layer.z_top <= hi_z:
                    bound = "the box bottom" if i == 0 else f"mesh.layers[{i - 1}].z_top"
                    problems.append(
                        (
                            f"mesh.layers[{i}].z_top",
                            f"must be > {bound} = {previous} and <= the box top = {hi_z} (got {layer.z_top})",
                        )
                    )
                previous = max(previous, layer.z_top)
            names: dict[str, int] = {}
            for i, js in enumerate(mesh.joint_sets):
                if js.name is not None:
                    if js.name in names:
                        problems.append(
                            (
                                f"mesh.joint_sets[{i}].name",
                                f"duplicate name; already used by joint_sets[{names[js.name]}]",
                            )
                        )
                    names.setdefault(js.name, i)
                if js.persistence != "layers":
                    continue
                ref = js.reference
                count = len(mesh.joint_sets)
                if ref is not None and (ref >= count or ref == i):
                    problems.append(
                        (
                            f"mesh.joint_sets[{i}].reference",
                            f"must be the index of another joint set, 0..{count - 1} except {i} (got {ref})",
                        )
                    )
                elif ref is not None and mesh.joint_sets[ref].persistence != "persistent":
                    problems.append(
                        (f"mesh.joint_sets[{i}].reference", f"joint set {ref} is not persistent (got {ref})")
                    )
        known = self.face_set_names()
        if known is not None:
            entries = [("loads", i, e) for i, e in enumerate(self.loads)]
            entries += [("boundaries", i, e) for i, e in enumerate(self.boundaries)]
            for section, i, entry in entries:
                if entry.faces is not None and entry.faces not in known:
                    allowed = ", ".join(repr(n) for n in known)
                    problems.append(
                        (
                            f"{section}[{i}].faces",
                            f"unknown face set {entry.faces!r}; the {mesh.kind} mesh has: {allowed}",
                        )
                    )
        return problems


# ----------------------------------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------------------------------


def default_scene_path() -> Path:
    """Path of the scene shipped with the package (``warpdem/data/default.toml``)."""
    return Path(__file__).parent / "data" / "default.toml"


def load_scene(path: str | os.PathLike[str]) -> Scene:
    """Reads and validates a TOML scene file.

    Relative particle file paths are resolved against the scene file's directory.

    Args:
        path: Scene file.

    Returns:
        The validated scene; ``FileSource.path`` values are absolute.

    Raises:
        SceneError: The file is missing, unreadable, not TOML, or not a valid scene; lists every problem.
    """
    path = Path(path)
    source = str(path)
    if not path.exists():
        raise SceneError(f"{source}: file not found")
    if path.is_dir():
        raise SceneError(f"{source}: is a directory, expected a TOML scene file")
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as err:
        raise SceneError(f"{source}: invalid TOML: {err}") from None
    except UnicodeDecodeError as err:
        raise SceneError(f"{source}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    except OSError as err:
        raise SceneError(f"{source}: cannot read: {err.strerror or err}") from None
    return _parse(data, source, path.resolve().parent, default_name=path.stem or "scene")


def parse_scene(data: Mapping[str, Any], source: str = "<scene>", base_dir: Path | None = None) -> Scene:
    """Validates a scene given as a dict (the structure of the TOML file).

    Args:
        data: Scene tables and values, SI units.
        source: Name used at the start of every problem line.
        base_dir: Directory that relative particle file paths are resolved against; the current working
            directory when None.

    Returns:
        The validated scene.

    Raises:
        SceneError: Lists every problem, one line each.
    """
    default_name = "scene" if source.startswith("<") else (Path(source).stem or "scene")
    return _parse(data, source, base_dir, default_name=default_name)


def _parse(data: Any, source: str, base_dir: Path | None, default_name: str) -> Scene:
    if not isinstance(data, Mapping):
        raise SceneError(f"{source}: a scene must be a table (dict), got {type(data).__name__}")
    try:
        scene = Scene.model_validate(data, context={"default_name": default_name})
    except ValidationError as err:
        raise SceneError(_format_validation_error(err, source)) from None
    if not source.startswith("<"):
        scene._source = source
    problems = [f"{source}: {path}: {message}" for path, message in scene.reference_problems()]
    if not problems:
        # Sizes only of a scene whose references hold: the estimate reads the sources' parts and materials.
        problems = [f"{source}: {path}: {message}" for path, message in scene.size_problems()]
    problems += _resolve_files(scene, source, base_dir if base_dir is not None else Path.cwd())
    if problems:
        raise SceneError(problems)
    return scene


def _resolve_files(scene: Scene, source: str, base_dir: Path) -> list[str]:
    problems = []
    if scene.mesh is not None and scene.mesh.kind == "file":
        resolved = scene.mesh.path.expanduser()
        if not resolved.is_absolute():
            resolved = base_dir / resolved
        if not resolved.exists():
            problems.append(f"{source}: mesh.path: file not found: {resolved}")
        elif not resolved.is_file():
            problems.append(f"{source}: mesh.path: not a regular file: {resolved}")
        scene.mesh.path = resolved
    for i, particle_source in enumerate(scene.particles):
        if not isinstance(particle_source, FileSource):
            continue
        resolved = particle_source.path.expanduser()
        if not resolved.is_absolute():
            resolved = base_dir / resolved
        if not resolved.exists():
            problems.append(f"{source}: particles[{i}].path: file not found: {resolved}")
        elif not resolved.is_file():
            problems.append(f"{source}: particles[{i}].path: not a regular file: {resolved}")
        particle_source.path = resolved
    return problems


# ----------------------------------------------------------------------------------------------------------------------
# Validation error formatting
# ----------------------------------------------------------------------------------------------------------------------


def _format_key(key: str) -> str:
    # TOML quoting, so a path with odd characters can still be found in the file.
    return key if _BARE_KEY.fullmatch(key) else '"' + key.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _format_path(path: list[str | int]) -> str:
    text = ""
    for part in path:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += ("." if text else "") + _format_key(part)
    return text


def _unwrap(tp: Any) -> Any:
    """Strips Annotated and Optional wrappers from a type annotation."""
    while True:
        origin = typing.get_origin(tp)
        if origin is Annotated:
            tp = typing.get_args(tp)[0]
        elif origin in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) != 1:
                return tp
            tp = args[0]
        else:
            return tp


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _union_members(tp: Any) -> list[type[BaseModel]]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return [a for a in typing.get_args(tp) if _is_model(a)]
    return []


def _tags(members: list[type[BaseModel]], discriminator: str = "kind") -> list[str]:
    tags = []
    for member in members:
        field = member.model_fields.get(discriminator)
        if field is not None:
            tags += [str(v) for v in typing.get_args(_unwrap(field.annotation))]
    return tags


def _walk(loc: tuple[str | int, ...]) -> tuple[list[str | int], Any, Any]:
    """Follows a pydantic error location through the Scene type tree.

    Returns:
        The user-facing key path (union tags and validator labels removed), the annotation at the end of the
        path and the annotation of its parent (None where unknown).
    """
    path: list[str | int] = []
    tp: Any = Scene
    parent: Any = None
    for part in loc:
        tp = _unwrap(tp)
        members = _union_members(tp)
        if members:
            # pydantic inserts the tag of a discriminated union member into the location; the user never wrote it.
            chosen = [m for m in members if str(part) in _tags([m])]
            tp = chosen[0] if chosen else None
            continue
        if part == "[key]":  # dict key validation label: the key is already in the path
            continue
        parent = tp
        if isinstance(part, int):
            path.append(part)
            origin = typing.get_origin(tp)
            args = typing.get_args(tp)
            if origin is list and args:
                tp = args[0]
            elif origin is tuple and args:
                tp = args[0] if args[-1] is Ellipsis else (args[part] if part < len(args) else None)
            else:
                tp = None
        elif _is_model(tp):
            path.append(part)
            field = tp.model_fields.get(part)
            tp = field.annotation if field is not None else None
        elif typing.get_origin(tp) is dict:
            path.append(part)
            tp = typing.get_args(tp)[1]
        elif tp is None and _BARE_KEY.fullmatch(part):
            path.append(part)
        # Otherwise a validator label such as "function-after[...]": not part of the user's key path.
    return path, _unwrap(tp) if tp is not None else None, parent


def _got(value: Any) -> str:
    text = repr(value)
    if len(text) > _MAX_GOT_CHARS:
        text = text[: _MAX_GOT_CHARS - 3] + "..."
    return f" (got {text})"


def _format_error(error: Mapping[str, Any]) -> tuple[str, str]:
    """One pydantic error as ``(key path, message)``."""
    kind = error["type"]
    loc = tuple(error["loc"])
    ctx = error.get("ctx") or {}
    value = error.get("input")
    path, tp, parent = _walk(loc)

    if kind == "extra_forbidden":
        if len(path) == 1 and path[0] in RESERVED_SECTIONS:
            return _format_path(path), (
                f"section not supported by this version of warpdem (schema_version {SCHEMA_VERSION}) yet"
            )
        allowed = ", ".join(parent.model_fields) if _is_model(parent) else "see the documentation"
        return _format_path(path), f"unknown key; allowed keys: {allowed}"
    if kind == "missing":
        if path and isinstance(path[-1], int):
            expected = len(typing.get_args(parent)) if typing.get_origin(parent) is tuple else "more"
            return _format_path(path[:-1]), f"too few values; expected {expected}{_got(value)}"
        return _format_path(path), "required key is missing"
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        discriminator = str(ctx.get("discriminator", "kind")).strip("'")
        allowed = ", ".join(repr(t) for t in _tags(_union_members(tp), discriminator))
        path = [*path, discriminator]
        if kind == "union_tag_not_found":
            return _format_path(path), f"required key is missing; allowed: {allowed}"
        return _format_path(path), f"unknown value {ctx.get('tag')!r}; allowed: {allowed}"
    if kind == "literal_error":
        values = typing.get_args(tp) if typing.get_origin(tp) is Literal else ()
        allowed = ", ".join(repr(v) for v in values) if values else str(ctx.get("expected", ""))
        return _format_path(path), f"unknown value {value!r}; allowed: {allowed}"

    message = _PLAIN_MESSAGES.get(kind) or str(error["msg"])
    for prefix in ("Value error, ", "Assertion failed, "):
        message = message.removeprefix(prefix)
    # A whole table as 'got' is noise; the message of a table-level check already says what is wrong.
    if not isinstance(value, Mapping):
        message += _got(value)
    return _format_path(path), message


def _format_validation_error(err: ValidationError, source: str) -> list[str]:
    errors = err.errors(include_url=False)
    # A file written for another schema version produces errors everywhere; only the version matters then.
    version_errors = [e for e in errors if tuple(e["loc"]) == ("schema_version",)]
    if version_errors:
        errors = version_errors
    lines: list[str] = []
    for error in errors:
        path, message = _format_error(error)
        line = f"{source}: {path}: {message}" if path else f"{source}: {message}"
        if line not in lines:
            lines.append(line)
    return lines
