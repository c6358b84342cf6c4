"""The scene itself: the :class:`Scene` model that holds every table, its cross references and its size checks."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Annotated, Any

from pydantic import (
    AfterValidator,
    Field,
    PrivateAttr,
    ValidationInfo,
    model_validator,
)

from ..limits import (
    BYTES_PER_NEIGHBOR_SLOT,
    BYTES_PER_SPHERE,
    MAX_ELEMENTS,
    size_problem,
)
from ..tables import BOX_FACE_NAMES, OPENING_FACE_NAME, SURFACE_FACE_NAME
from .continuum import (
    ARCH_DAM_FACE_NAMES,
    ARCH_FACE_NAMES,
    ArchDamMesh,
    ArchMesh,
    BoxMesh,
    BrickMeshSpec,
    CylinderMesh,
    EllipsoidMesh,
    GeologyMeshSpec,
    JointDefaults,
    Mesh,
    block_cells,
)
from .failure import CONVERSION_STRENGTH, Conversion, Fracture, MaterialRegion, Rigid
from .fields import (
    _BYTES_EACH,
    _LATTICE_FRACTION,
    MAX_JOINT_SURFACES,
    SCHEMA_VERSION,
    Int,
    Name,
    Str,
    _check_path_text,
    _format_key,
    _Model,
    _regular_tet_volume,
)
from .loads import Boundary, Load
from .particles import BondRegion, PackingSource, ParticleSource, SphereSource, Wall
from .run import Capacity, ContactSettings, Gravity, InteractionProps, Interactions, Material, Output, Part, Run

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
        target), capped by ``count``; tets of a box mesh: 6 per cell, of a bricks mesh: 6 per cell of its grid (the
        box in whole cells of a block's, warpdem.build.bricks), of a geology mesh: model volume / the volume of a
        regular tet of edge e, e³/(6√2), e the smaller of h and the closest joint spacing (Gmsh conforms the tets to
        every joint plane; with planes closer than h it makes tets of their spacing or flat ones it cannot finish),
        and of edge h_opening, as if the refinement filled the model: an upper bound, plus each refinement box's part
        of the model at its edge, a node per 4 tets; neighbour
        slots: sphere slots (at least the one the builder always makes) × neighbors_per_particle; explicit
        capacities as given. Spheres of files are counted when read (the builder).

        Returns:
            ``(key path, message)`` when the estimate exceeds :data:`warpdem.limits.MAX_ELEMENTS` of a kind or the
            memory of this machine (the key is that of the largest contributor), or when a block of a bricks mesh
            spans more than MAX_ELEMENTS cells along an edge; else an empty list.
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
        # The builder allocates one sphere slot even without spheres (conversion may add some), each with its slots.
        slots = max(spheres, 1.0)
        contributions.append(
            ("capacity.neighbors_per_particle", "neighbor slots", slots * self.capacity.neighbors_per_particle)
        )
        mesh = self.scaled_mesh()
        tets = nodes = 0.0
        key, why = "", ""
        if isinstance(mesh, BoxMesh | ArchMesh):
            cells = math.prod(float(d) for d in mesh.divisions)
            tets, nodes = 6.0 * cells, math.prod(float(d) + 1.0 for d in mesh.divisions)
            key = "mesh.divisions"
        elif isinstance(mesh, BrickMeshSpec):
            grid = block_cells(mesh.brick, mesh.stagger, mesh.h)
            if max(grid) > MAX_ELEMENTS:
                axis = max(range(3), key=lambda a: grid[a])
                return [
                    (
                        f"mesh.brick[{axis}]",
                        f"a block {mesh.brick[axis]:g} m {('long', 'deep', 'high')[axis]} spans {grid[axis]:.3g} cells "
                        f"of h = {mesh.h:g} m; allowed: at most {MAX_ELEMENTS} cells along a block "
                        f"(mesh.brick[{axis}] <= {MAX_ELEMENTS * mesh.h:.3g} m at this h)",
                    )
                ]
            # The box is a whole number of cells of the block's grid (warpdem.build.bricks.mesh_bricks).
            sides = zip(mesh.lo, mesh.hi, mesh.brick, grid, strict=True)
            counts = [max(1.0, float(round((hi - lo) / (b / n)))) for lo, hi, b, n in sides]
            tets, nodes = 6.0 * math.prod(counts), math.prod(c + 1.0 for c in counts)
            key = "mesh.h"
        elif isinstance(mesh, GeologyMeshSpec):
            volume = math.prod(h - l for h, l in zip(mesh.hi, mesh.lo, strict=True))
            # Gmsh conforms the tets to every joint plane, so the blocks between planes closer than h get tets of
            # about their spacing (or flat ones it cannot finish): the edge is the smaller of h and the spacing.
            edge, key = mesh.h, "mesh.h"
            for i, js in enumerate(mesh.joint_sets):
                if js.spacing < edge:
                    edge, key = js.spacing, f"mesh.joint_sets[{i}].spacing"
            tets = volume / _regular_tet_volume(edge)
            if mesh.openings and mesh.h_opening is not None and mesh.h_opening < edge:
                tets += volume / _regular_tet_volume(mesh.h_opening)
            for r in mesh.refinements:  # the box's part of the model at its edge, on top of the whole at h
                sides = zip(r.lo, r.hi, mesh.lo, mesh.hi, strict=True)
                inside = math.prod(max(0.0, min(b, n) - max(a, m)) for a, b, m, n in sides)
                tets += inside / _regular_tet_volume(r.h)
            nodes = tets / 4.0
            if key != "mesh.h":
                why = (
                    f" (the mesh conforms to the joints: tets of about the spacing, {edge:g} m, where it is below "
                    f"h = {mesh.h:g} m); make the spacing larger compared with the model"
                )
        elif isinstance(mesh, CylinderMesh | EllipsoidMesh):
            tets = mesh.volume() / _regular_tet_volume(mesh.h)
            nodes = tets / 4.0
            key = "mesh.h"
        elif isinstance(mesh, ArchDamMesh):
            tets = mesh.estimated_tets()
            nodes = tets / 4.0
            key = "mesh.h_charge"
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
                return slots * max(k - default_k, 0) * BYTES_PER_NEIGHBOR_SLOT
            return c[2] * _BYTES_EACH[c[1]]

        worst = max(contributions, key=blame)
        return [(worst[0], problem + (why if worst[0] == key else ""))]

    def scaled_mesh(self) -> Mesh | None:
        """The ``[mesh]`` at ``run.resolution``: edge lengths h, h_opening and the refinements' h divided by it, box and
        arch divisions multiplied by it (rounded, at least 1); a mesh file as it is. Resolution 1 gives the mesh as
        written."""
        mesh, k = self.mesh, self.run.resolution
        if mesh is None or k == 1.0 or mesh.kind == "file":
            return mesh
        if mesh.kind in ("box", "arch"):
            return mesh.model_copy(update={"divisions": tuple(max(1, round(d * k)) for d in mesh.divisions)})
        update = {"h": mesh.h / k}
        if mesh.kind == "arch_dam":
            update["h_charge"] = mesh.h_charge / k
        if mesh.kind == "geology" and mesh.h_opening is not None:
            update["h_opening"] = mesh.h_opening / k
        if mesh.kind == "geology" and mesh.refinements:
            update["refinements"] = [r.model_copy(update={"h": r.h / k}) for r in mesh.refinements]
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
        if mesh.kind == "arch_dam":
            return list(ARCH_DAM_FACE_NAMES)
        names = list(BOX_FACE_NAMES)
        if mesh.kind in ("geology", "bricks") and mesh.openings:
            names.append(OPENING_FACE_NAME)
        if mesh.kind == "geology":
            for solid in mesh.solids:
                names += [solid.name] + ([f"{solid.name}_cavity"] if solid.cavity is not None else [])
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
        if mesh.kind in ("box", "geology", "cylinder", "ellipsoid", "arch", "arch_dam", "bricks"):
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
