"""The rock mesh of a scene's ``[mesh]`` section, and the face and node sets its loads and boundaries name.

Every mesh kind becomes a :class:`warpdem.build.geology.GeologyMesh`: ``"box"`` through the Kuhn box mesher
(:func:`warpdem.build.mesh.box_mesh`) with the six box faces picked by their outward normals, ``"geology"``,
``"cylinder"``, ``"ellipsoid"`` and ``"arch_dam"`` through Gmsh (:func:`warpdem.build.geology.mesh_geology`,
:func:`~warpdem.build.geology.mesh_cylinder`, :func:`~warpdem.build.geology.mesh_ellipsoid`,
:func:`warpdem.build.arch_dam.mesh_arch_dam`), ``"file"`` through meshio
(:func:`warpdem.build.geology.read_mesh`). The ``[[fracture.seed_cracks]]`` become joint faces of open, frictional joint
sets (:func:`seed_crack_faces`). Loads and boundaries select faces by name (``boundary_faces`` of the mesh) or by a
region (the outer faces whose three nodes lie inside it), and velocity loads select nodes the same way. Problems are
:class:`warpdem.scene.SceneError` lines naming the scene and the key path.

Host code, run once before the model is built.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..scene import (
    ARCH_FACE_NAMES,
    ArchMesh,
    BoxMesh,
    BrickMeshSpec,
    FileMesh,
    GeologyMeshSpec,
    JointProperties,
    Region,
    Scene,
    SceneError,
    SeedCrack,
)
from ..stages.tets import TetProps
from ..tables import BOX_FACE_NAMES
from .arch_dam import mesh_arch_dam
from .bricks import mesh_bricks
from .face_cover import face_cover_weights
from .geology import (
    Geology,
    GeologyMesh,
    JointSet,
    MeshImportError,
    Refinement,
    RockMass,
    Room,
    Shaft,
    Solid,
    Tunnel,
    interior_faces,
    mesh_cylinder,
    mesh_ellipsoid,
    mesh_geology_cached,
    read_mesh,
)
from .mesh import MeshError, MeshTooFarError, boundary_faces, box_mesh

if TYPE_CHECKING:
    from ..stages.joints import JointProps
    from .builder import ModelBuilder

__all__ = [
    "add_scene_mesh",
    "arch_mesh",
    "assign_material_regions",
    "box_face_sets",
    "face_normals",
    "joint_set_properties",
    "nodes_of_selection",
    "rock_mesh",
    "seed_crack_faces",
    "select_faces",
]

SEED_PLANE_TOLERANCE = 1e-9
"""A node lies on a seed crack's plane when its distance from it is within this fraction of the mesh's bounding-box
diagonal [-]: far above the float64 rounding of the coordinates (1e-16 relative), far below any tet's height."""

# A box mesh face lies on box face ±axis when its unit normal is within this of ±e_axis (Kuhn faces are exact).
_AXIS_COSINE = 1.0 - 1e-6


def face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area vectors of triangles [m²]: half the cross product, along the right-hand normal, shape (F, 3)."""
    p = np.asarray(points, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    return 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def box_face_sets(points: np.ndarray, tets: np.ndarray) -> dict[str, np.ndarray]:
    """The outer faces of a box mesh sorted onto the six box faces by their outward normals.

    Args:
        points: node positions [m], shape (N, 3). tets: positively oriented tets, shape (M, 4).

    Returns:
        :data:`warpdem.build.geology.BOX_FACE_NAMES` → outward-oriented triangles, shape (F, 3), int64.
    """
    faces = boundary_faces(tets).astype(np.int64)
    n = face_normals(points, faces)
    unit = n / np.linalg.norm(n, axis=1, keepdims=True)
    sets = {}
    for name in BOX_FACE_NAMES:
        axis = "xyz".index(name[0])
        sign = -1.0 if name[1] == "-" else 1.0
        sets[name] = faces[sign * unit[:, axis] >= _AXIS_COSINE]
    return sets


def _openings(spec: GeologyMeshSpec | BrickMeshSpec) -> list[Tunnel | Shaft | Room]:
    openings = []
    for o in spec.openings:
        if o.kind == "tunnel":
            openings.append(Tunnel(o.axis, o.center, o.shape, o.radius, o.width, o.height, o.span))
        elif o.kind == "shaft":
            openings.append(Shaft(o.center, o.radius, o.bottom, o.top))
        else:
            openings.append(Room(o.lo, o.hi))
    return openings


def _geology(spec: GeologyMeshSpec, seed: int) -> Geology:
    openings = _openings(spec)
    joint_sets = [
        JointSet(
            dip=js.dip,
            dip_direction=js.dip_direction,
            spacing=js.spacing,
            offset=js.offset,
            persistence=js.persistence,
            radius=js.radius,
            disc_spacing=js.disc_spacing,
            reference=js.reference,
            layers=js.layers,
            phase=js.phase,
            layers_max=js.layers_max,
            jitter_position=js.jitter_position,
            jitter_angle=js.jitter_angle,
            name=js.name,
        )
        for js in spec.joint_sets
    ]
    rock = RockMass(spec.lo, spec.hi, [(layer.z_top, layer.material) for layer in spec.layers], spec.material)
    solids = [
        Solid(
            s.name,
            s.lo,
            s.hi,
            None if s.cavity is None else s.cavity.lo,
            None if s.cavity is None else s.cavity.hi,
        )
        for s in spec.solids
    ]
    refinements = [Refinement(r.lo, r.hi, r.h) for r in spec.refinements]
    return Geology(rock, openings, joint_sets, spec.h, spec.h_opening, spec.refine_distance, seed, solids, refinements)


def _box(spec: BoxMesh) -> GeologyMesh:
    points, tets = box_mesh(spec.lo, spec.hi, spec.divisions)
    tets = tets.astype(np.int64)
    return GeologyMesh.single(points, tets, spec.material, box_face_sets(points, tets))


def arch_mesh(spec: ArchMesh) -> GeologyMesh:
    """The structured tet mesh of an arch (:class:`~warpdem.scene.ArchMesh`): the Kuhn mesh of the unit cube
    (:func:`warpdem.build.mesh.box_mesh`) in coordinates (s, w, ζ) mapped onto the annular sector

        θ = (s − ½) angle,  z = ζ H,  t(ζ) = thickness + (crest_thickness − thickness) ζ,
        r = radius + 4 bulge ζ (1 − ζ) − (1 − w) t(ζ),  x = c + (r sin θ, r cos θ, z).

    The map's Jacobian has a positive determinant (∂x/∂s along +θ, ∂x/∂w along +r, ∂x/∂ζ up: a right-handed frame
    as (x, y, z) at θ = 0), so the Kuhn tets stay positively oriented; the face sets are the unit cube's faces
    (:func:`box_face_sets` before the map) named :data:`~warpdem.scene.ARCH_FACE_NAMES`.
    """
    unit, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), spec.divisions)
    tets = tets.astype(np.int64)
    s, w, zeta = unit.T
    theta = (s - 0.5) * np.radians(spec.angle)
    crest = spec.crest_thickness if spec.crest_thickness is not None else spec.thickness
    r = (
        spec.radius
        + 4.0 * spec.bulge * zeta * (1.0 - zeta)
        - (1.0 - w) * (spec.thickness + (crest - spec.thickness) * zeta)
    )
    points = np.asarray(spec.center, dtype=np.float64) + np.stack(
        [r * np.sin(theta), r * np.cos(theta), zeta * spec.height], axis=1
    )
    sets = box_face_sets(unit, tets)
    return GeologyMesh.single(
        points,
        tets,
        spec.material,
        {name: sets[box] for name, box in zip(ARCH_FACE_NAMES, BOX_FACE_NAMES, strict=True)},
    )


def assign_material_regions(mesh: GeologyMesh, scene: Scene) -> GeologyMesh:
    """The mesh with the tets whose centroid lies in a ``[[material_regions]]`` entry's region made of its material
    (later entries win), the new materials appended to ``mesh.material_names``."""
    if not scene.material_regions:
        return mesh
    centroids = mesh.points[mesh.tets].mean(axis=1)
    names = list(mesh.material_names)
    material = mesh.tet_material.copy()
    for zone in scene.material_regions:
        if zone.material not in names:
            names.append(zone.material)
        material[zone.region.contains(centroids)] = names.index(zone.material)
    used = np.unique(material)  # a material no tet keeps is dropped, so the builder sees only the mesh's own
    mesh.tet_material = np.searchsorted(used, material).astype(np.int64)
    mesh.material_names = [names[i] for i in used]
    return mesh


def _file(spec: FileMesh, scene: Scene) -> GeologyMesh:
    source = scene.source
    # TOML keys are strings; a key of digits names a physical group by its number.
    material_map = {int(k) if k.isdigit() else k: v for k, v in spec.material_map.items()} or None
    joint_groups = None if spec.joint_groups is None else list(spec.joint_groups)
    try:
        mesh = read_mesh(spec.path, material_map=material_map, joint_groups=joint_groups)
    except MeshImportError as exc:
        raise SceneError(f"{source}: mesh.{exc.argument or 'path'}: {exc}") from None
    if spec.material is not None:
        mesh.tet_material = np.zeros(len(mesh.tets), np.int64)
        mesh.material_names = [spec.material]
        return mesh
    defined = scene.material_names()
    unknown = [name for name in mesh.material_names if name not in defined]
    if unknown:
        raise SceneError(
            f"{source}: mesh.material_map: tet group(s) {', '.join(repr(n) for n in unknown)} of {spec.path} are not "
            f"materials; map them in material_map or give one 'material' (defined materials: "
            f"{', '.join(repr(n) for n in defined)})"
        )
    return mesh


def rock_mesh(scene: Scene) -> GeologyMesh:
    """The tet mesh a scene's ``[mesh]`` describes, with its materials, joint faces and named face sets.

    Raises:
        SceneError: the scene has no mesh, Gmsh fails, or the mesh file cannot be used.
    """
    mesh = _rock_mesh(scene)
    return assign_material_regions(mesh, scene)


def _rock_mesh(scene: Scene) -> GeologyMesh:
    """The mesh of :func:`rock_mesh` before its material regions, at the scene's resolution."""
    spec = scene.scaled_mesh()
    source = scene.source
    if spec is None:
        raise SceneError(f"{source}: mesh: the scene has no [mesh]")
    try:
        if spec.kind == "box":
            return _box(spec)
        if spec.kind == "arch":
            return arch_mesh(spec)
        if spec.kind == "arch_dam":
            return mesh_arch_dam(spec)
        if spec.kind == "geology":
            seed = spec.seed if spec.seed is not None else scene.run.seed
            return mesh_geology_cached(_geology(spec, seed))
        if spec.kind == "cylinder":
            axis = np.eye(3)["xyz".index(spec.axis)]
            return mesh_cylinder(spec.center, axis, spec.radius, spec.height, spec.h, spec.material)
        if spec.kind == "ellipsoid":
            return mesh_ellipsoid(spec.center, spec.radii, spec.h, spec.material)
        if spec.kind == "bricks":
            return mesh_bricks(
                spec.lo,
                spec.hi,
                spec.brick,
                spec.h,
                spec.material,
                spec.stagger,
                _openings(spec),
                [o.min_piece for o in spec.openings],
            )
        return _file(spec, scene)
    except (ValueError, RuntimeError, MeshError) as exc:
        if isinstance(exc, SceneError):
            raise
        raise SceneError(f"{source}: mesh: {' '.join(str(exc).split())}") from None


def select_faces(mesh: GeologyMesh, faces: str | None, region: Region | None, where: str) -> np.ndarray:
    """Outer faces named by ``faces`` (a face set of the mesh) or lying inside ``region`` (all three nodes).

    Args:
        mesh: the rock mesh. faces: a face set name, or None. region: a region, or None (exactly one is given).
        where: ``"<scene>: <key path>"`` of the entry, for the error message.

    Returns:
        Outward-oriented triangles, node indices into ``mesh.points``, shape (F, 3), int64.

    Raises:
        SceneError: an unknown face set name, or a selection with no face.
    """
    if faces is not None:
        if faces not in mesh.boundary_faces:
            allowed = ", ".join(repr(n) for n in mesh.boundary_faces) or "(none)"
            raise SceneError(f"{where}.faces: unknown face set {faces!r}; the mesh has: {allowed}")
        selected = np.asarray(mesh.boundary_faces[faces], dtype=np.int64).reshape(-1, 3)
        if len(selected) == 0:
            raise SceneError(f"{where}.faces: face set {faces!r} of the mesh is empty")
        return selected
    assert region is not None  # guaranteed by the scene schema
    outer = boundary_faces(mesh.tets).astype(np.int64)
    inside = region.contains(mesh.points)
    selected = outer[np.all(inside[outer], axis=1)]
    if len(selected) == 0:
        raise SceneError(f"{where}.region: contains no outer face of the mesh (all three nodes inside)")
    return selected


def select_load_faces(
    mesh: GeologyMesh, faces: str | None, region: Region | None, where: str
) -> tuple[np.ndarray, np.ndarray | None]:
    """The outer faces a pressure load pushes on and each node's share of each face's push: a named face set whole
    (weights None: a third each), or every outer face a region covers at least in part, with the weights that make the
    load push on exactly the area the region covers (warpdem.build.face_cover).

    Args: as :func:`select_faces`.

    Returns:
        Outward-oriented triangles (F, 3), int64, and their weights (F, 3) or None.

    Raises:
        SceneError: an unknown face set name, or a selection with no face.
    """
    if faces is not None:
        return select_faces(mesh, faces, None, where), None
    assert region is not None  # guaranteed by the scene schema
    outer = boundary_faces(mesh.tets).astype(np.int64)
    weights = face_cover_weights(mesh.points, outer, region)
    hit = weights.sum(axis=1) > 0.0
    if not np.any(hit):
        raise SceneError(f"{where}.region: covers no outer face of the mesh")
    return outer[hit], weights[hit]


def seed_crack_faces(points: np.ndarray, tets: np.ndarray, crack: SeedCrack, where: str) -> np.ndarray:
    """The interior faces of a mesh that a seed crack cuts: all three nodes on its plane (within
    :data:`SEED_PLANE_TOLERANCE` of the mesh diagonal) and inside its region, with a tet on either side.

    Args:
        points: node positions [m], shape (N, 3). tets: node indices, shape (M, 4). crack: the seed crack.
        where: ``"<scene>: <key path>"`` of the crack, for the error message.

    Returns:
        Node triples (sorted), shape (F, 3), int64.

    Raises:
        SceneError: no interior face of the mesh lies on the plane inside the region.
    """
    points = np.asarray(points, dtype=np.float64)
    normal = np.asarray(crack.normal, dtype=np.float64)
    normal /= np.linalg.norm(normal)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    on_plane = np.abs((points - np.asarray(crack.point)) @ normal) <= SEED_PLANE_TOLERANCE * diagonal
    on_crack = on_plane & crack.region.contains(points)
    faces = interior_faces(tets)
    selected = faces[np.all(on_crack[faces], axis=1)]
    if len(selected) == 0:
        raise SceneError(
            f"{where}.region: no interior face of the mesh lies on the plane through {list(crack.point)} normal to "
            f"{list(crack.normal)} inside the region (the plane must hold mesh faces, e.g. a box mesh's grid plane)"
        )
    return selected


def nodes_of_selection(mesh: GeologyMesh, faces: str | None, region: Region | None, where: str) -> np.ndarray:
    """Nodes of the named face set, or every node inside ``region``, sorted, shape (K,), int64.

    Raises:
        SceneError: an unknown face set name, or a selection with no node.
    """
    if faces is not None:
        return np.unique(select_faces(mesh, faces, None, where))
    assert region is not None
    nodes = np.nonzero(region.contains(mesh.points))[0].astype(np.int64)
    if len(nodes) == 0:
        raise SceneError(f"{where}.region: contains no node of the mesh")
    return nodes


def add_scene_mesh(builder: ModelBuilder, scene: Scene) -> tuple[GeologyMesh, np.ndarray]:
    """Adds a scene's rock mesh, its joints, loads and boundaries to a builder.

    Each material's continuum properties (bulk viscosity, mass damping) go to
    :meth:`~warpdem.build.builder.ModelBuilder.set_tet_properties`; the mesh, with one material per tet, to
    :meth:`~warpdem.build.builder.ModelBuilder.add_tet_mesh`.

    Returns:
        The mesh and the builder's node id of each of its nodes, shape (N,).

    Raises:
        SceneError: the mesh cannot be built, a selection is empty or unknown, or the scene uses a stage this
            build does not have yet.
    """
    spec = scene.mesh
    assert spec is not None
    mesh = rock_mesh(scene)
    for name in mesh.material_names:
        m = scene.materials[name]
        builder.set_tet_properties(name, TetProps(m.bulk_viscosity_linear, m.bulk_viscosity_quadratic, m.mass_damping))
    per_tet = np.asarray(mesh.material_names)[mesh.tet_material]
    problems = scene.conversion_material_problems(mesh.material_names)
    if scene.fracture.enabled:
        problems += scene.fracture_material_problems(mesh.material_names)
    if problems:
        raise SceneError([f"{scene.source}: {key}: {message}" for key, message in problems])
    fixed = np.ones(len(mesh.points), dtype=bool) if spec.fixed else None
    joints = _joint_faces(builder, scene, mesh)
    try:
        nodes = builder.add_tet_mesh(
            mesh.points, mesh.tets, per_tet, fixed_nodes=fixed, velocity=spec.velocity, **joints
        )
    except MeshError as exc:
        # A degenerate tet of a mesh file is the file's fault; of a box or Gmsh mesh, that of the sizes that made it,
        # and a mesh too far from the origin for float32, that of its corner or centre.
        where = f"mesh.path: {spec.path}" if spec.kind == "file" else "mesh"
        if isinstance(exc, MeshTooFarError) and spec.kind != "file":
            where = "mesh.lo" if hasattr(spec, "lo") else "mesh.origin" if spec.kind == "arch_dam" else "mesh.center"
        raise SceneError(f"{scene.source}: {where}: {exc}") from None
    _add_loads(builder, scene, mesh, nodes)
    return mesh, nodes


def joint_set_properties(scene: Scene, mesh: GeologyMesh) -> list[JointProps]:
    """The properties of each joint set of the scene's mesh, in ``mesh.joint_set_names`` order.

    A geology joint set takes its own values from ``mesh.joint_sets[k]``, a joint group of a mesh file from
    ``mesh.joint_groups.<name>``; every value a set does not give comes from ``[joints]``.
    """
    from ..stages.joints import JointProps

    spec = scene.mesh
    own: list[JointProperties | None]
    if spec is not None and spec.kind == "geology":
        own = list(spec.joint_sets)  # mesh_geology names every set, in order
    elif spec is not None and spec.kind == "bricks":
        own = [spec.bedding, spec.head]
    elif spec is not None and spec.kind == "file" and spec.joint_groups is not None:
        own = [spec.joint_groups.get(name) for name in mesh.joint_set_names]
    else:
        own = [None] * len(mesh.joint_set_names)
    defaults = scene.joints
    props = []
    for entry in own:
        given = entry.model_dump(exclude_none=True) if entry is not None else {}
        merged = {key: given.get(key, getattr(defaults, key)) for key in JointProperties.model_fields}
        if _STIFFNESS_KEYS & given.keys():
            # The set's own stiffness (either key) replaces [joints]' choice whole: the two keys exclude each other.
            merged.update({key: given.get(key) for key in _STIFFNESS_KEYS})
        props.append(JointProps(**merged))
    return props


_STIFFNESS_KEYS = frozenset({"stiffness_factor", "normal_stiffness"})
"""The joint keys that set the normal spring, one of which a joint takes (warpdem.stages.joints.JointProps)."""


def _joint_faces(builder: ModelBuilder, scene: Scene, mesh: GeologyMesh) -> dict[str, np.ndarray]:
    """The ``joint_faces`` and ``joint_set`` arguments of :meth:`~warpdem.build.builder.ModelBuilder.add_tet_mesh`: the
    mesh's own joints (their sets added to the builder) and each seed crack's faces, a joint set of its own that is
    open from the start (no cohesion, no tensile strength: the pre-split faces only touch, with the crack's
    friction; stiffness and restitution from ``[joints]``). A face that is already a joint keeps its joint's set."""
    from ..stages.joints import JointProps

    faces, sets = [], []
    if len(mesh.joint_faces):
        set_ids = np.asarray(_add_joint_sets(builder, scene, mesh), dtype=np.int64)
        faces.append(np.asarray(mesh.joint_faces, dtype=np.int64))
        sets.append(set_ids[mesh.joint_face_set])
    defaults = scene.joints
    for k, crack in enumerate(scene.fracture.seed_cracks):
        cracked = seed_crack_faces(mesh.points, mesh.tets, crack, f"{scene.source}: fracture.seed_cracks[{k}]")
        props = JointProps(
            friction=crack.friction,
            stiffness_factor=defaults.stiffness_factor,
            normal_stiffness=defaults.normal_stiffness,
            restitution=defaults.restitution,
            shear_stiffness_ratio=defaults.shear_stiffness_ratio,
        )
        faces.append(cracked)
        sets.append(np.full(len(cracked), builder.add_joint_set(props, name=f"seed_crack{k}"), dtype=np.int64))
    if not faces:
        return {}
    all_faces, all_sets = np.concatenate(faces), np.concatenate(sets)
    _, first = np.unique(np.sort(all_faces, axis=1), axis=0, return_index=True)
    keep = np.sort(first)  # the first entry of a face listed twice: the mesh's joints come first
    return {"joint_faces": all_faces[keep], "joint_set": all_sets[keep]}


def _add_joint_sets(builder: ModelBuilder, scene: Scene, mesh: GeologyMesh) -> list[int]:
    """Adds the mesh's joint sets to the builder with their properties (:func:`joint_set_properties`); returns the
    builder's id of each."""
    props = joint_set_properties(scene, mesh)
    return [builder.add_joint_set(p, name=name) for p, name in zip(props, mesh.joint_set_names, strict=True)]


def _add_loads(builder: ModelBuilder, scene: Scene, mesh: GeologyMesh, nodes: np.ndarray) -> None:
    """Maps ``[[loads]]`` and ``[[boundaries]]`` onto the builder's loads (:mod:`warpdem.stages.loads`)."""
    source = scene.source
    if (scene.loads or scene.boundaries) and not hasattr(builder, "add_face_pressure"):
        section = "loads" if scene.loads else "boundaries"
        raise SceneError(f"{source}: {section}: not supported by this build yet (warpdem.stages.loads)")
    if not (scene.loads or scene.boundaries):
        return
    from ..stages.loads import roller_axis
    from ..stages.pressure import PressureHistory

    driven = np.full(len(mesh.points), -1, dtype=np.int64)  # the velocity load that drives each node
    for i, load in enumerate(scene.loads):
        where = f"{source}: loads[{i}]"
        try:
            if load.kind == "velocity":
                local = nodes_of_selection(mesh, load.faces, load.region, where)
                taken = local[driven[local] >= 0]
                if len(taken):
                    key = "faces" if load.faces is not None else "region"
                    raise SceneError(
                        f"{where}.{key}: selects nodes that loads[{driven[taken[0]]}] already drives (node "
                        f"{int(taken[0])}); a node takes one velocity load"
                    )
                driven[local] = i
                ids = nodes[local]
                end = load.end if load.end is not None else float("inf")
                builder.add_node_velocity(ids, load.velocity, start=load.start, end=end)
                continue
            local, weights = select_load_faces(mesh, load.faces, load.region, where)
            faces = nodes[local]
            if load.kind == "airblast":
                history = PressureHistory.friedlander(
                    load.peak,
                    load.positive_duration,
                    load.decay_coefficient,
                    load.source,
                    front_speed=load.front_speed,
                    start=load.t0,
                )
            else:
                h = load.history
                if h.kind == "blast":
                    history = PressureHistory.blast(h.peak, h.rise_time, h.decay_time, start=h.start)
                elif h.kind == "table":
                    history = PressureHistory.table(h.times, h.values)
                else:
                    history = PressureHistory.friedlander(
                        h.peak, h.positive_duration, h.decay_coefficient, (0.0, 0.0, 0.0), start=h.start
                    )
            builder.add_face_pressure(faces, history, name=f"loads[{i}]", weights=weights)
        except ValueError as exc:
            if isinstance(exc, SceneError):
                raise
            raise SceneError(f"{where}: {exc}") from None
    for i, boundary in enumerate(scene.boundaries):
        where = f"{source}: boundaries[{i}]"
        local = select_faces(mesh, boundary.faces, boundary.region, where)
        try:
            if boundary.kind == "roller" and boundary.normal is None:
                # Checked here rather than at finalize, so the message names the entry.
                roller_axis(mesh.points, local)
            builder.add_boundary(nodes[local], boundary.kind, normal=boundary.normal)
        except ValueError as exc:
            key = "faces" if boundary.faces is not None else "region"
            raise SceneError(f"{where}.{key}: {exc}") from None
