"""The continuum of a scene: the rock [mesh] (box, geology, file, cylinder, ellipsoid, arch, arch_dam, bricks), its
openings and its joints ([joints], [[mesh.joint_sets]])."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from fractions import Fraction
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BeforeValidator,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from ..tables import BOX_FACE_NAMES, OPENING_FACE_NAME
from .fields import Bool, FilePath, Float, Int, Name, Str, Vec3, _array_to_list, _Model
from .regions import Box, _hi_above_lo

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


def _min_piece_field() -> Any:
    return Field(
        default=0.0,
        ge=0,
        lt=1,
        description="Bricks meshes: a piece of a block this opening cuts that is left smaller than this fraction of a "
        "whole block goes with it (a charge's crushed zone) [-]; 0 keeps every piece.",
    )


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
    min_piece: Float = _min_piece_field()

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
    min_piece: Float = _min_piece_field()

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
    min_piece: Float = _min_piece_field()

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)


Opening = Annotated[TunnelOpening | ShaftOpening | RoomOpening, Field(discriminator="kind")]
"""One ``[[mesh.openings]]`` entry, selected by ``kind``."""


CAVITY_FLUSH_TOL = 1e-9
"""A cavity's face within this fraction of its solid's size of the solid's face is flush with it (passes through)."""


def cavity_flush(a: float, b: float, size: float) -> bool:
    """Whether a cavity's face at coordinate ``a`` [m] is flush with its solid's face at ``b`` [m] (a solid ``size``
    [m] across on that axis), within :data:`CAVITY_FLUSH_TOL` of the size."""
    return abs(a - b) <= CAVITY_FLUSH_TOL * size


def cavity_problem(
    lo: Sequence[float], hi: Sequence[float], cavity_lo: Sequence[float], cavity_hi: Sequence[float]
) -> str:
    """What is wrong with a cavity in the box [lo, hi] (all corners [m]), or ``""``: the cavity must have positive
    size and lie strictly inside the box on every axis but at most one, along which it may pass right through (flush
    with both faces; the thickness of a 2-D slice). A cavity flush with one face only would leave a notch; through on
    two axes, the box in pieces."""
    if any(ch <= cl for cl, ch in zip(cavity_lo, cavity_hi, strict=True)):
        return f"the cavity's hi {list(cavity_hi)} must exceed its lo {list(cavity_lo)} on every axis"
    through = 0
    for a in range(3):
        size = hi[a] - lo[a]
        flush_lo, flush_hi = cavity_flush(cavity_lo[a], lo[a], size), cavity_flush(cavity_hi[a], hi[a], size)
        if flush_lo and flush_hi:
            through += 1
            continue
        if flush_lo or flush_hi or not (lo[a] < cavity_lo[a] and cavity_hi[a] < hi[a]):
            return (
                f"the cavity [{cavity_lo[a]:g}, {cavity_hi[a]:g}] along {'xyz'[a]} is not inside the solid "
                f"[{lo[a]:g}, {hi[a]:g}] (allowed: strictly inside, or flush with both faces along one axis)"
            )
    if through > 1:
        return "the cavity passes right through the solid along more than one axis (it would cut it in pieces)"
    return ""


def _box_corners(lo: Sequence[float], hi: Sequence[float]) -> list[tuple[float, float, float]]:
    return [(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]


def _inside_opening(opening: Any, p: Sequence[float], box_lo: Sequence[float], box_hi: Sequence[float]) -> bool:
    """Whether point ``p`` [m] lies strictly inside an opening (one that spans the model: inside along its axis
    wherever it lies in the box [box_lo, box_hi])."""
    x, y, z = p
    if opening.kind == "room":
        return all(lo < c < hi for lo, c, hi in zip(opening.lo, p, opening.hi, strict=True))
    if opening.kind == "shaft":
        bottom = box_lo[2] - 1.0 if opening.bottom is None else opening.bottom
        top = box_hi[2] + 1.0 if opening.top is None else opening.top
        return math.hypot(x - opening.center[0], y - opening.center[1]) < opening.radius and bottom < z < top
    along, across = (x, y) if opening.axis == "x" else (y, x)
    a = 0 if opening.axis == "x" else 1
    s0, s1 = opening.span if opening.span is not None else (box_lo[a] - 1.0, box_hi[a] + 1.0)
    if not s0 < along < s1:
        return False
    c, zc = opening.center
    if opening.shape == "circular":
        return math.hypot(across - c, z - zc) < opening.radius
    half_w, half_h = 0.5 * opening.width, 0.5 * opening.height
    if opening.shape == "rectangular":
        return abs(across - c) < half_w and abs(z - zc) < half_h
    # Horseshoe: floor, walls up to the springing line, then a half circle of radius w/2 (warpdem.build.geology).
    z_spring = zc + half_h - half_w
    if not (abs(across - c) < half_w and z > zc - half_h):
        return False
    return z <= z_spring or math.hypot(across - c, z - z_spring) < half_w


class CavitySpec(Box):
    """The cavity of a solid: an axis-aligned box inside it (a region's box, the same fields and checks)."""


class RefinementSpec(Box):
    """A box of a geology mesh meshed finer than ``h`` (a wall that needs more elements through its thickness)."""

    h: Float = Field(gt=0, description="Tet edge length inside the box [m]; below the mesh's h.")


class SolidSpec(_Model):
    """A box put back inside an opening of a geology mesh (a concrete box in a tunnel): a body of its own, meshed with
    the rock but sharing no node with it, not cut by the joints, with an optional cavity (a charge chamber)."""

    name: Name = Field(
        description="Name of the solid: its walls are the face set '<name>', its cavity's walls '<name>_cavity'."
    )
    lo: Vec3 = Field(description="Lower corner [m]; the solid lies inside the model's box.")
    hi: Vec3 = Field(description="Upper corner [m]; greater than lo in every component.")
    cavity: CavitySpec | None = Field(
        default=None,
        description="A box-shaped cavity: strictly inside the solid, or flush with both its faces along one axis "
        "(through the thickness of a slice); omitted: a full box.",
    )

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)

    @model_validator(mode="after")
    def _check_cavity(self) -> SolidSpec:
        if self.cavity is not None:
            problem = cavity_problem(self.lo, self.hi, self.cavity.lo, self.cavity.hi)
            if problem:
                raise ValueError(f"cavity: {problem}")
        return self


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
    layers_max: Int | None = Field(
        default=None,
        ge=1,
        description="Randomized persistence (persistence 'layers'): each plane alternates runs of 'layers' to "
        "'layers_max' slabs with and without a joint piece, its own random draws ('phase' unused).",
    )
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
            for key, wanted in (
                ("radius", "disc"),
                ("disc_spacing", "disc"),
                ("reference", "layers"),
                ("layers_max", "layers"),
            )
            if getattr(self, key) is not None and self.persistence != wanted
        ]
        if unused:
            raise ValueError(f"{', '.join(repr(k) for k in unused)} not used with persistence {self.persistence!r}")
        if self.layers_max is not None and self.layers_max < self.layers:
            raise ValueError(f"'layers_max' ({self.layers_max}) must be at least 'layers' ({self.layers})")
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
    solids: list[SolidSpec] = Field(
        default_factory=list, description="Boxes put back inside the openings, each clear of the rock all round."
    )
    h: Float = Field(gt=0, description="Target tet edge length [m].")
    h_opening: Float | None = Field(default=None, gt=0, description="Edge length on the opening walls [m]; default h.")
    refine_distance: Float | None = Field(
        default=None, gt=0, description="Distance over which the size grows from h_opening to h [m]; default 4 h."
    )
    refinements: list[RefinementSpec] = Field(
        default_factory=list,
        description="Boxes meshed at an edge below h (Gmsh's Box size fields; the finest size wins where they meet).",
    )
    seed: Int | None = Field(
        default=None, ge=0, description="Seed of the joints' jitter and randomized persistence; default run.seed."
    )
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    @field_validator("hi")
    @classmethod
    def _check_hi(cls, value: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        return _hi_above_lo(value, info)

    @field_validator("refinements")
    @classmethod
    def _check_refinements(cls, value: list[RefinementSpec], info: ValidationInfo) -> list[RefinementSpec]:
        # Gmsh takes the finest size asked for, so a box coarser than h would change nothing: refused, not ignored.
        lo, hi, h = info.data.get("lo"), info.data.get("hi"), info.data.get("h")
        for i, r in enumerate(value):
            if h is not None and not r.h < h:
                raise ValueError(f"[{i}].h = {r.h:g} m must be below the mesh's h = {h:g} m (a finer edge)")
            if (
                lo is not None
                and hi is not None
                and not all(a < d and c < b for a, b, c, d in zip(r.lo, r.hi, lo, hi, strict=True))
            ):
                raise ValueError(
                    f"[{i}]: the box [{list(r.lo)}, {list(r.hi)}] does not overlap the model's box [{list(lo)}, "
                    f"{list(hi)}]"
                )
        return value

    @field_validator("openings")
    @classmethod
    def _check_openings(cls, value: list[Any]) -> list[Any]:
        # Gmsh conforms the tets to the joints, so no opening leaves cell-sized pieces to take.
        if any(o.min_piece > 0 for o in value):
            raise ValueError("'min_piece' is for bricks meshes only")
        return value

    @field_validator("solids")
    @classmethod
    def _check_solids(cls, value: list[SolidSpec], info: ValidationInfo) -> list[SolidSpec]:
        # A solid sits in the air of an opening: inside the model's box (its faces may lie on the box's, where the
        # box's boundaries act on it too), inside one opening with a gap all round (a solid touching the rock would
        # meet it on faces whose nodes do not match), and clear of the other solids.
        lo, hi, openings = info.data.get("lo"), info.data.get("hi"), info.data.get("openings")
        if lo is None or hi is None or openings is None:
            return value  # the box or the openings are already refused
        taken = {*BOX_FACE_NAMES, OPENING_FACE_NAME}
        for i, solid in enumerate(value):
            where = f"solids[{i}] ({solid.name!r})"
            for name in (solid.name, f"{solid.name}_cavity"):
                if name in taken:
                    raise ValueError(f"{where}: the face set name {name!r} is taken (by {sorted(taken)})")
                taken.add(name)
            if not all(m <= a and b <= n for m, a, b, n in zip(lo, solid.lo, solid.hi, hi, strict=True)):
                raise ValueError(
                    f"{where}: [{list(solid.lo)}, {list(solid.hi)}] is not inside the model's box [{list(lo)}, "
                    f"{list(hi)}]"
                )
            corners = _box_corners(solid.lo, solid.hi)
            if not any(all(_inside_opening(o, p, lo, hi) for p in corners) for o in openings):
                raise ValueError(
                    f"{where}: not inside any opening with a gap all round (allowed: a box within one tunnel, shaft "
                    "or room, clear of the rock)"
                )
            for j, other in enumerate(value[:i]):
                if all(a < d and c < b for a, b, c, d in zip(solid.lo, solid.hi, other.lo, other.hi, strict=True)):
                    raise ValueError(f"{where}: overlaps solids[{j}] ({other.name!r})")
        return value


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


ARCH_DAM_FACE_NAMES = ("upstream", "downstream", "crest", "charge", "foundation")
"""Face sets of an arch dam mesh: the convex (water) face, the concave face, the crest less the charge disc, the charge
disc on the crest, and the dam's contact with the valley (the floor and both abutments)."""

EM36_FOOT = 0.3048
"""One foot [m]: EM36's base-thickness rule has a factor (H/400)^(H/400) with H in feet."""

ARCH_DAM_RADIUS_RATIO = 0.6
"""Radius of every arch's downstream (intrados) face over the valley's width at its elevation [-]: a constant-angle
layout, each arch subtending 2 asin(1 / (2 · 0.6)) = 112.9° between the valley walls (EM36's crest arch: a radius of
0.6 L1 at the crest)."""

ARCH_DAM_SECTOR = 75.0
"""Half-angle of the arch sections Gmsh lofts [deg], beyond the valley walls (56.4° at ARCH_DAM_RADIUS_RATIO) so that
the valley, not the section's ends, cuts the abutments."""


class ArchDamMesh(_Model):
    """A whole double-curvature arch dam in a trapezoidal valley, laid out by the rules of the US Bureau of
    Reclamation's Engineering Monograph 36 (H. L. Boggs, *Guide for Preliminary Design of Arch Dams*, 1977) from its
    height H, the valley's width L1 at the crest and L2 at 0.15 H, and meshed with Gmsh, fine at a charge disc at the
    crest centre and coarse away from it (warpdem.build.arch_dam). ζ = z / H:

        crown cantilever thickness  T_C = 0.01 (H + 1.2 L1),  T_B = (0.0012 H L1 L2 (H'/400)^(H'/400))^(1/3)
        (H' = H in feet), T(ζ) the parabola through T_B at ζ = 0, 0.95 T_B at 0.45, T_C at 1;
        upstream face of the crown  u(ζ) the parabola through 0.67 T_B, 0.95 T_B, 0 (upstream of the crest's edge);
        arch at ζ: concentric circular arcs, downstream radius R_d = 0.6 L(ζ), upstream R_u = R_d + T(ζ), L(ζ) the
        valley's width (linear through L2 at 0.15 and L1 at 1), centred on the crown at x = 0.

    Upstream is +y (the arches' convex side); the valley runs along y with its floor at ``origin``'s z."""

    kind: Literal["arch_dam"] = Field(description="Mesh kind.")
    origin: Vec3 = Field(
        description="Point of the valley floor under the upstream edge of the crest at the crown [m]; x = origin.x "
        "is the valley's centre line."
    )
    height: Float = Field(gt=0, description="Height H from the valley floor to the crest [m].")
    crest_length: Float = Field(gt=0, description="Width L1 of the valley at the crest [m].")
    lower_length: Float = Field(gt=0, description="Width L2 of the valley 0.15 H above the floor [m].")
    charge_radius: Float = Field(
        gt=0, description="Radius of the charge disc on the crest centre [m], less than half the crest thickness."
    )
    h_charge: Float = Field(gt=0, description="Tet edge at the charge [m] (run.resolution divides it).")
    h: Float = Field(gt=0, description="Largest tet edge, far from the charge [m] (run.resolution divides it).")
    fine_distance: Float = Field(ge=0, description="Distance from the charge disc with tets of edge h_charge [m].")
    grading_distance: Float = Field(
        gt=0, description="Distance beyond fine_distance over which the edge grows linearly to h [m]."
    )
    material: Str = Field(description="Name of a material defined in [materials].")
    fixed: Bool = _fixed_field()
    velocity: Vec3 = _velocity_field()

    @model_validator(mode="after")
    def _layout(self) -> ArchDamMesh:
        if not self.lower_length < self.crest_length:
            raise ValueError(
                f"lower_length must be less than crest_length (the valley widens upwards): lower_length "
                f"{self.lower_length}, crest_length {self.crest_length}"
            )
        if not self.floor_width() > 0.0:
            raise ValueError(
                f"the valley's floor width L2 - 0.15/0.85 (L1 - L2) must be > 0: got {self.floor_width():.4g} m "
                f"(raise lower_length or lower crest_length)"
            )
        if not self.charge_radius < 0.5 * self.crest_thickness:
            raise ValueError(
                f"charge_radius must be less than half the crest thickness T_C = 0.01 (H + 1.2 L1) = "
                f"{self.crest_thickness:.4g} m: got {self.charge_radius}"
            )
        if not self.h_charge <= self.h:
            raise ValueError(f"h_charge must not exceed h: h_charge {self.h_charge}, h {self.h}")
        return self

    @property
    def crest_thickness(self) -> float:
        """T_C = 0.01 (H + 1.2 L1) [m] (EM36; homogeneous, so in metres as in feet)."""
        return 0.01 * (self.height + 1.2 * self.crest_length)

    @property
    def base_thickness(self) -> float:
        """T_B = (0.0012 H L1 L2 (H'/400)^(H'/400))^(1/3) [m], H' the height in feet (EM36)."""
        hf = self.height / EM36_FOOT / 400.0
        return (0.0012 * self.height * self.crest_length * self.lower_length * hf**hf) ** (1.0 / 3.0)

    def valley_width(self, zeta: Any) -> Any:
        """L(ζ) [m]: the valley's width at ζ = z / H, linear through L2 at 0.15 and L1 at 1; array or float."""
        slope = (self.crest_length - self.lower_length) / 0.85
        return self.crest_length - slope * (1.0 - zeta)

    def floor_width(self) -> float:
        """L(0) [m]: the valley floor's width."""
        return float(self.valley_width(0.0))

    def thickness(self, zeta: Any) -> Any:
        """T(ζ) [m]: the crown cantilever's (and every arch's) thickness, the parabola through T_B, 0.95 T_B, T_C at
        ζ = 0, 0.45, 1."""
        tb = self.base_thickness
        return _parabola(zeta, (tb, 0.95 * tb, self.crest_thickness))

    def upstream_offset(self, zeta: Any) -> Any:
        """u(ζ) [m]: how far upstream (+y) of the crest's upstream edge the crown's upstream face lies, the parabola
        through 0.67 T_B, 0.95 T_B, 0 at ζ = 0, 0.45, 1."""
        tb = self.base_thickness
        return _parabola(zeta, (0.67 * tb, 0.95 * tb, 0.0))

    def radii(self, zeta: Any) -> tuple[Any, Any]:
        """(R_u, R_d) [m]: the upstream and downstream radii of the arch at ζ."""
        inner = ARCH_DAM_RADIUS_RATIO * self.valley_width(zeta)
        return inner + self.thickness(zeta), inner

    def arch_center_y(self, zeta: Any) -> Any:
        """y of the centre of the arch at ζ [m]: its upstream face passes through the crown's upstream point."""
        return self.origin[1] + self.upstream_offset(zeta) - self.radii(zeta)[0]

    def charge_center(self) -> tuple[float, float, float]:
        """Centre of the charge disc [m]: the crest's centre at the crown."""
        return (self.origin[0], self.origin[1] - 0.5 * self.crest_thickness, self.origin[2] + self.height)

    def estimated_tets(self) -> float:
        """About how many tets Gmsh makes [-]: the dam at edge h, plus the graded zone about the charge as a half disc
        in the dam's plane, as thick as the dam at its deepest point, of tets of the threshold's edge e(d) (h_charge
        out to charge_radius + fine_distance from the centre, then linear to h over grading_distance), regular
        tetrahedra of volume e³ / (6√2): ∫ π d t / (e(d)³ / (6√2)) dd by the midpoint rule. An over-estimate, for the
        memory check: 2 to 4 times Gmsh's count on the shipped and test dams (tests/test_arch_dam.py)."""
        import numpy as np

        inner = self.charge_radius + self.fine_distance
        reach = inner + self.grading_distance
        d = (np.arange(400) + 0.5) * reach / 400
        edge = self.h_charge + (self.h - self.h_charge) * np.clip((d - inner) / self.grading_distance, 0.0, 1.0)
        depth = max(0.0, 1.0 - reach / self.height)
        thick = float(np.max(self.thickness(np.linspace(depth, 1.0, 32))))
        regular = 1.0 / (6.0 * math.sqrt(2.0))
        graded = float(np.sum(math.pi * d * thick / (regular * edge**3))) * reach / 400
        return self.volume() / (regular * self.h**3) + graded

    def volume(self) -> float:
        """The dam's volume [m³] by 64-point Gauss-Legendre over ζ of the arch section, the ring between R_d and R_u
        cut by the valley walls |x| <= L/2: A(R) − A(R_d), A(R) = a √(R² − a²) + R² asin(a / R), a = L / 2."""
        import numpy as np

        nodes, weights = np.polynomial.legendre.leggauss(64)
        zeta = 0.5 * (nodes + 1.0)
        a = 0.5 * self.valley_width(zeta)
        outer, inner = self.radii(zeta)

        def part(r: Any) -> Any:
            return a * np.sqrt(r * r - a * a) + r * r * np.arcsin(a / r)

        return float(0.5 * self.height * np.sum(weights * (part(outer) - part(inner))))


def _parabola(zeta: Any, values: tuple[float, float, float]) -> Any:
    """The parabola through values at ζ = 0, 0.45, 1 (Lagrange form); array or float."""
    z0, z1, z2 = 0.0, 0.45, 1.0
    v0, v1, v2 = values
    return (
        v0 * (zeta - z1) * (zeta - z2) / ((z0 - z1) * (z0 - z2))
        + v1 * (zeta - z0) * (zeta - z2) / ((z1 - z0) * (z1 - z2))
        + v2 * (zeta - z0) * (zeta - z1) / ((z2 - z0) * (z2 - z1))
    )


def brick_cells(length: float, stagger: float, h: float) -> int:
    """Cells along a block's length: at least length / h, and a multiple of the stagger's denominator so that every
    course's head joints lie on grid lines (stagger 0.5: even). A Python int, however long the block."""
    step = Fraction(stagger).limit_denominator(64).denominator
    return step * max(1, math.ceil(length / h / step - 1e-9))


def block_cells(brick: tuple[float, float, float], stagger: float, h: float) -> tuple[int, int, int]:
    """Cells along the length, depth and height of a block of a bricks mesh (warpdem.build.bricks): the length's
    from :func:`brick_cells`, the others at least size / h. Python ints, however large the block is against h."""
    return (
        brick_cells(brick[0], stagger, h),
        max(1, math.ceil(brick[1] / h - 1e-9)),
        max(1, math.ceil(brick[2] / h - 1e-9)),
    )


class BrickMeshSpec(_Model):
    """Rock laid in courses of equal blocks (warpdem.build.bricks): bedding joints between the courses, head joints
    between the blocks, every other course shifted (running bond), on a structured grid of cells no longer than h."""

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
    BoxMesh | GeologyMeshSpec | FileMesh | CylinderMesh | EllipsoidMesh | ArchMesh | ArchDamMesh | BrickMeshSpec,
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
