"""Jointed-rock geology: a rock mass with openings and joint sets, meshed with tetrahedra that conform to the joints.

The model follows the jointed geologies of LDEC (Morris et al., §3 and Fig. 6): regular persistent joint sets
that cut the whole model into polyhedral blocks, and non-persistent sets (finite discs, or planes that persist
only through a few layers between the planes of a persistent set). :func:`mesh_geology` builds the geometry
with the Gmsh OpenCASCADE kernel: the box minus the openings (boolean cut) is fragmented by the material layer
planes and by every joint surface, so each rock block is one Gmsh volume and the tetrahedral mesh conforms to
the joints: the two tetrahedra on either side of a joint share the face's three nodes. Splitting those nodes
into cohesive or contact interfaces is left to the FEM/DEM builder.

Coordinates: x east, y north, z up, all lengths in metres. Joint orientation uses the geological convention:
dip δ ∈ [0°, 90°] is the angle of the plane below the horizontal, dip direction α is the azimuth of the
steepest descent measured clockwise from north (+y). The upward unit normal of the plane is (see
:func:`joint_normal`)::

    n = (sin δ sin α, sin δ cos α, cos δ)

A joint set's planes are ``n · x = offset + k · spacing`` for every integer k whose plane cuts the box.

The modules below this one: :mod:`warpdem.build.jointing` (the description, :class:`Geology` and its parts, and the
joints' geometry in numpy) and :mod:`warpdem.build.mesh_io` (:class:`GeologyMesh`, its topology helpers and
:func:`read_mesh` / :func:`write_mesh` through meshio); their public names are re-exported here.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from ..tables import BOX_FACE_NAMES, OPENING_FACE_NAME, SURFACE_FACE_NAME
from .jointing import (
    _MARGIN,
    _REL_TOL,
    Geology,
    JointSet,
    Opening,
    Refinement,
    RockMass,
    Room,
    Shaft,
    Solid,
    Tunnel,
    _in_plane_axes,
    _joint_geometry,
    _JointPolygon,
    joint_normal,
)
from .mesh import boundary_faces as outer_faces
from .mesh_io import (
    GeologyMesh,
    MeshImportError,
    _classify_boundary,
    _face_normals,
    _orient_tets,
    component_labels,
    interior_faces,
    read_mesh,
    write_mesh,
)

__all__ = [
    "BOX_FACE_NAMES",
    "OPENING_FACE_NAME",
    "SURFACE_FACE_NAME",
    "Geology",
    "GeologyMesh",
    "JointSet",
    "MeshImportError",
    "Refinement",
    "RockMass",
    "Room",
    "Shaft",
    "Solid",
    "Tunnel",
    "component_labels",
    "interior_faces",
    "joint_normal",
    "mesh_cylinder",
    "mesh_ellipsoid",
    "mesh_geology",
    "mesh_geology_cached",
    "read_mesh",
    "write_mesh",
]

OPTIMIZE_THRESHOLD = 0.5
"""Gmsh optimises the tets whose quality gamma (inradius over longest edge, 1 for a regular tet) is below this.
Gmsh's default is 0.3; 0.5 raises the tets' stable time step of the non-persistent tunnel scene by 21 % and the
smallest dihedral angle of the slope scene from 13° to 18°."""

_GMSH_TET = 4  # Gmsh element type: 4-node tetrahedron
_GMSH_TRIANGLE = 2  # Gmsh element type: 3-node triangle


def _add_opening(occ: Any, opening: Opening, lo: np.ndarray, hi: np.ndarray, margin: float) -> int:
    """Adds the opening as an OCC volume; openings that span the model overshoot the box by the margin."""
    if isinstance(opening, Room):
        rlo, rhi = np.asarray(opening.lo, float), np.asarray(opening.hi, float)
        return occ.addBox(*rlo, *(rhi - rlo))
    if isinstance(opening, Shaft):
        z0 = lo[2] - margin if opening.bottom is None else opening.bottom
        z1 = hi[2] + margin if opening.top is None else opening.top
        return occ.addCylinder(opening.centre[0], opening.centre[1], z0, 0.0, 0.0, z1 - z0, opening.radius)
    along = 0 if opening.axis == "x" else 1
    across = 1 - along
    s0, s1 = opening.span if opening.span is not None else (lo[along] - margin, hi[along] + margin)
    length = s1 - s0
    c, zc = opening.centre

    def point(a: float, t: float, z: float) -> np.ndarray:
        p = np.zeros(3)
        p[along], p[across], p[2] = a, t, z
        return p

    axis_vec = point(length, 0.0, 0.0)
    if opening.shape == "circular":
        return occ.addCylinder(*point(s0, c, zc), *axis_vec, opening.radius)
    w, ht = opening.width, opening.height
    if opening.shape == "rectangular":
        corner = point(s0, c - 0.5 * w, zc - 0.5 * ht)
        return occ.addBox(*corner, *point(length, w, ht))
    # Horseshoe: extrude the profile (floor, walls, two quarter arcs of the crown) along the axis.
    z_floor, z_spring, r = zc - 0.5 * ht, zc + 0.5 * ht - 0.5 * w, 0.5 * w
    profile = [(c - r, z_floor), (c + r, z_floor), (c + r, z_spring), (c, z_spring + r), (c - r, z_spring)]
    p = [occ.addPoint(*point(s0, t, z)) for t, z in profile]
    o = occ.addPoint(*point(s0, c, z_spring))
    curves = [
        occ.addLine(p[0], p[1]),
        occ.addLine(p[1], p[2]),
        occ.addCircleArc(p[2], o, p[3]),
        occ.addCircleArc(p[3], o, p[4]),
        occ.addLine(p[4], p[0]),
    ]
    face = occ.addPlaneSurface([occ.addCurveLoop(curves)])
    out = occ.extrude([(2, face)], *axis_vec)
    occ.remove([(0, o)])
    return next(tag for dim, tag in out if dim == 3)


def _add_polygon(occ: Any, vertices: list[np.ndarray]) -> int:
    pts = [occ.addPoint(*v) for v in vertices]
    lines = [occ.addLine(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
    return occ.addPlaneSurface([occ.addCurveLoop(lines)])


def _on_box_face(bbox: Sequence[float], lo: np.ndarray, hi: np.ndarray, tol: float) -> bool:
    """Whether a Gmsh bounding box (xmin, ymin, zmin, xmax, ymax, zmax) lies flat on one of the box faces."""
    for axis in range(3):
        for value in (lo[axis], hi[axis]):
            if abs(bbox[axis] - value) <= tol and abs(bbox[axis + 3] - value) <= tol:
                return True
    return False


def _gmsh_options(h: float, refine: bool) -> dict[str, float]:
    """Every Gmsh option a mesh depends on, so that a caller's own Gmsh settings do not leak in.

    Args:
        h: target tet edge length [m]. refine: a background size field (opening refinement, refinement boxes) sets
            the sizes.
    """
    return {
        "General.Terminal": 0,
        "General.NumThreads": 1,  # single-threaded Delaunay: equal inputs, identical meshes
        "Mesh.Algorithm3D": 1,
        "Mesh.MeshSizeMin": 0.0,
        "Mesh.MeshSizeMax": h,
        "Mesh.MeshSizeFromCurvature": 0,
        "Mesh.MeshSizeExtendFromBoundary": 0 if refine else 1,
        "Mesh.MeshSizeFromPoints": 0 if refine else 1,
        "Mesh.Algorithm": 6,  # Frontal-Delaunay surfaces
        "Mesh.Smoothing": 1,
        "Mesh.QualityType": 2,  # gamma (inradius / longest edge): the quality the optimiser works on
        "Mesh.Optimize": 1,
        "Mesh.OptimizeThreshold": OPTIMIZE_THRESHOLD,
        "Mesh.OptimizeNetgen": 0,  # adds ~70 % tets and lowers the stable step on jointed models
    }


def _box_size_field(field_mesh: Any, refinement: Refinement, h: float) -> int:
    """Gmsh's Box field of a refinement box: ``refinement.h`` inside it (faces included), ``h`` outside; returns its
    tag."""
    tag = field_mesh.add("Box")
    for name, value in zip(("XMin", "YMin", "ZMin"), refinement.lo, strict=True):
        field_mesh.setNumber(tag, name, float(value))
    for name, value in zip(("XMax", "YMax", "ZMax"), refinement.hi, strict=True):
        field_mesh.setNumber(tag, name, float(value))
    field_mesh.setNumber(tag, "VIn", float(refinement.h))
    field_mesh.setNumber(tag, "VOut", float(h))
    return tag


@contextlib.contextmanager
def _gmsh_model(options: Mapping[str, float], model_name: str, what: str) -> Iterator[Any]:
    """A fresh Gmsh model with ``options`` set, yielding the ``gmsh`` module; afterwards Gmsh is finalized if this
    started it, else the caller's model and option values are restored. A Gmsh failure (a plain ``Exception`` with
    Gmsh's last error) becomes ``RuntimeError("<what>: Gmsh failed: ...")``."""
    import gmsh

    started = not gmsh.isInitialized()
    if started:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    saved = {} if started else {name: gmsh.option.getNumber(name) for name in options}
    current_model = None if started else gmsh.model.getCurrent()
    try:
        for name, value in options.items():
            gmsh.option.setNumber(name, value)
        gmsh.model.add(model_name)
        yield gmsh
    except Exception as exc:
        if type(exc) is Exception:  # the Gmsh API raises plain Exception with its last error message
            raise RuntimeError(f"{what}: Gmsh failed: {exc}") from exc
        raise
    finally:
        if started:
            gmsh.finalize()
        else:
            if model_name in gmsh.model.list():
                gmsh.model.setCurrent(model_name)
                gmsh.model.remove()
            if current_model in gmsh.model.list():
                gmsh.model.setCurrent(current_model)
            for name, value in saved.items():
                gmsh.option.setNumber(name, value)


def _gmsh_volume_tets(
    gmsh: Any, volume_tags: Sequence[int], what: str
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """The meshed nodes and the tets of each volume of the current Gmsh model.

    Returns:
        Node coordinates [m] (K, 3); Gmsh node tag → row of the coordinates (-1: none); the tets of each volume
        as rows into the coordinates (T_v, 4); the block index of each of those tets (its volume's position).
    """
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
    index[node_tags.astype(np.int64)] = np.arange(len(node_tags))
    tet_parts, block_parts = [], []
    for b, v in enumerate(volume_tags):
        for etype, _, enodes in zip(*gmsh.model.mesh.getElements(3, v), strict=True):
            if etype != _GMSH_TET:
                raise RuntimeError(f"{what}: Gmsh produced element type {etype} in volume {v}")
            tet_parts.append(index[enodes.astype(np.int64)].reshape(-1, 4))
            block_parts.append(np.full(len(tet_parts[-1]), b, dtype=np.int64))
    return coords.reshape(-1, 3), index, tet_parts, block_parts


def _used_nodes(coords: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contiguous numbering over the nodes the tets use: points (N, 3) float64, the positively oriented tets (M, 4)
    and the map old row → new node (-1 where unused), shape (K,)."""
    used = np.unique(tets)
    renumber = np.full(len(coords), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    points = np.ascontiguousarray(coords[used], dtype=np.float64)
    return points, _orient_tets(points, renumber[tets]), renumber


MESH_CACHE_SIZE = 16
"""Geology meshes :func:`mesh_geology_cached` keeps (the most recently used)."""

_mesh_cache: dict[str, GeologyMesh] = {}


def mesh_geology_cached(geology: Geology) -> GeologyMesh:
    """:func:`mesh_geology`, remembered for the process: a geology equal to one of the last MESH_CACHE_SIZE meshed
    (equal ``repr``: every field, floats exactly) gets a copy of that mesh without Gmsh. Equal inputs give identical
    meshes (single-threaded Delaunay, every Gmsh option pinned), so the copy is the mesh Gmsh would make. A shipped
    scene of a few thousand blocks takes Gmsh half a minute to a minute; its run, restart and half-step tests, and a
    report that builds it again, mesh it once.

    Returns:
        A fresh copy (its arrays and face-set dict are the caller's to change).
    """
    key = repr(geology)
    mesh = _mesh_cache.pop(key, None)
    if mesh is None:
        mesh = mesh_geology(geology)
    _mesh_cache[key] = mesh  # (re)inserted last: the dict's order is the order of use
    while len(_mesh_cache) > MESH_CACHE_SIZE:
        del _mesh_cache[next(iter(_mesh_cache))]
    return _copy_mesh(mesh)


def _copy_mesh(mesh: GeologyMesh) -> GeologyMesh:
    """A deep copy of a mesh: its arrays, names and face-set dict."""
    return GeologyMesh(
        points=mesh.points.copy(),
        tets=mesh.tets.copy(),
        tet_block=mesh.tet_block.copy(),
        tet_material=mesh.tet_material.copy(),
        material_names=list(mesh.material_names),
        joint_faces=mesh.joint_faces.copy(),
        joint_face_set=mesh.joint_face_set.copy(),
        joint_set_names=list(mesh.joint_set_names),
        boundary_faces={name: faces.copy() for name, faces in mesh.boundary_faces.items()},
        num_blocks=mesh.num_blocks,
    )


def mesh_geology(geology: Geology) -> GeologyMesh:
    """Meshes a jointed rock mass with first-order tetrahedra conforming to its joints, layers and openings.

    The Gmsh OCC model is the box minus the openings, fragmented by the layer tops and by every joint surface;
    joint pieces outside the box or inside an opening are removed. Each resulting volume is one rock block.
    Meshing is single-threaded Delaunay, so equal inputs give identical meshes. Gmsh's tetrahedral optimiser then
    improves every tet whose quality is below :data:`OPTIMIZE_THRESHOLD` by edge and face swaps and node
    relocation; nodes on joints, layers and walls stay on their surfaces, so the mesh still conforms. Without it,
    Delaunay leaves slivers (radius ratio down to 3e-4) that cut the tets' stable time step 20 to 240 times on the
    repository's jointed scenes. The worst tets that remain sit in geometric features smaller than ``h`` (joints
    crossing each other or a box face within a fraction of ``h`` of an edge), which no optimiser can remove: there
    the step is set by the feature's size.

    Args:
        geology: The rock mass, openings, joint sets, mesh size and seed.

    Solids (boxes put back inside the openings, :class:`Solid`) are added after the joints cut the rock, as
    volumes of their own: the joints do not cut them and they share no node with the rock; each is one block, after
    the rock's.

    Returns:
        The mesh; ``boundary_faces`` holds the six box faces, ``"opening"`` (the rock's walls inside the box) and, for
        each solid, its walls off the box faces (its name) and its cavity's (its name + ``"_cavity"``).

    Raises:
        ValueError: If the openings remove the whole box, or a solid overlaps the rock.
        RuntimeError: If Gmsh fails to build or mesh the model (its message included).
    """
    rock = geology.rock
    lo, hi = np.asarray(rock.lo, float), np.asarray(rock.hi, float)
    diag = float(np.linalg.norm(hi - lo))
    margin = _MARGIN * diag
    tol = _REL_TOL * diag
    joint_surfaces = _joint_geometry(geology)
    refine_openings = geology.h_opening is not None and bool(geology.openings)
    refine = refine_openings or bool(geology.refinements)
    with _gmsh_model(_gmsh_options(geology.h, refine), f"warpdem_geology_{id(geology)}", "mesh_geology") as gmsh:
        occ = gmsh.model.occ

        box = occ.addBox(*lo, *(hi - lo))
        volumes = [(3, box)]
        if geology.openings:
            tools = [(3, _add_opening(occ, o, lo, hi, margin)) for o in geology.openings]
            volumes, _ = occ.cut(volumes, tools)
            if not volumes:
                raise ValueError("mesh_geology: the openings remove the whole rock box")

        # Cutting surfaces in input order; kinds[i] is the joint set of surface i, or -1 for a layer top.
        cutters: list[tuple[int, int]] = []
        kinds: list[int] = []
        for z_top, _ in rock.layers:
            if lo[2] + tol < z_top < hi[2] - tol:
                size = hi - lo + 2.0 * margin
                cutters.append((2, occ.addRectangle(lo[0] - margin, lo[1] - margin, z_top, size[0], size[1])))
                kinds.append(-1)
        for s in joint_surfaces:
            if isinstance(s, _JointPolygon):
                cutters.append((2, _add_polygon(occ, s.vertices)))
            else:
                e1, _ = _in_plane_axes(s.normal)
                tag = occ.addDisk(*s.centre, s.radius, s.radius, zAxis=list(s.normal), xAxis=list(e1))
                cutters.append((2, tag))
            kinds.append(s.set_index)

        surface_set: dict[int, int] = {}
        if cutters:
            _, pieces = occ.fragment(volumes, cutters)
            # A piece that lies on several cutters (coplanar joints) belongs to the lowest joint set.
            for kind, out in zip(kinds, pieces[len(volumes) :], strict=True):
                for dim, tag in out:
                    if dim == 2 and kind >= 0:
                        surface_set[tag] = min(kind, surface_set.get(tag, kind))
        # The solids come after the fragment, so the joints do not cut them, and are not fragmented with the rock, so
        # they share no node with it (a box standing in a tunnel is a body of its own).
        rock_tags = sorted(tag for _, tag in occ.getEntities(3))
        solid_tags = [_add_solid(occ, solid, rock_tags, margin, tol) for solid in geology.solids]
        occ.synchronize()

        # Drop joint pieces that bound no block and are embedded in none: outside the box or inside openings.
        # Removing them from the Gmsh model only (the OCC shapes stay) is several times faster than
        # occ.remove + synchronize on models with hundreds of blocks.
        volume_tags = rock_tags + solid_tags  # blocks: the rock's, then one per solid in input order
        embedded = {tag for v in volume_tags for dim, tag in gmsh.model.mesh.getEmbedded(3, v) if dim == 2}
        free = [
            (2, s)
            for _, s in gmsh.model.getEntities(2)
            if len(gmsh.model.getAdjacencies(2, s)[0]) == 0 and s not in embedded
        ]
        if free:
            gmsh.model.removeEntities(free, recursive=True)
        surfaces = {tag for _, tag in gmsh.model.getEntities(2)}
        surface_set = {s: k for s, k in surface_set.items() if s in surfaces}

        if refine:
            field_mesh = gmsh.model.mesh.field
            fields = []
            if refine_openings:
                walls = [
                    s
                    for s in sorted(surfaces)
                    if len(gmsh.model.getAdjacencies(2, s)[0]) == 1
                    and not _on_box_face(gmsh.model.getBoundingBox(2, s), lo, hi, 1e3 * tol)
                ]
                distance = field_mesh.add("Distance")
                field_mesh.setNumbers(distance, "SurfacesList", walls)
                field_mesh.setNumber(distance, "Sampling", 30)
                threshold = field_mesh.add("Threshold")
                field_mesh.setNumber(threshold, "InField", distance)
                field_mesh.setNumber(threshold, "SizeMin", geology.h_opening)
                field_mesh.setNumber(threshold, "SizeMax", geology.h)
                field_mesh.setNumber(threshold, "DistMin", 0.0)
                field_mesh.setNumber(threshold, "DistMax", geology.refine_distance or 4.0 * geology.h)
                fields.append(threshold)
            for r in geology.refinements:
                fields.append(_box_size_field(field_mesh, r, geology.h))
            if len(fields) > 1:  # the finest size any field asks for at a point
                smallest = field_mesh.add("Min")
                field_mesh.setNumbers(smallest, "FieldsList", fields)
                fields = [smallest]
            field_mesh.setAsBackgroundMesh(fields[0])
        gmsh.model.mesh.generate(3)

        coords, index, tet_parts, block_parts = _gmsh_volume_tets(gmsh, volume_tags, "mesh_geology")
        face_parts, face_set_parts = [], []
        for s, k in sorted(surface_set.items(), key=lambda item: (item[1], item[0])):  # grouped by set
            for etype, _, enodes in zip(*gmsh.model.mesh.getElements(2, s), strict=True):
                if etype == _GMSH_TRIANGLE:
                    face_parts.append(index[enodes.astype(np.int64)].reshape(-1, 3))
                    face_set_parts.append(np.full(len(face_parts[-1]), k, dtype=np.int64))

    tets = np.concatenate(tet_parts) if tet_parts else np.zeros((0, 4), np.int64)
    if len(tets) == 0:
        raise RuntimeError("mesh_geology: Gmsh produced no tetrahedra")
    joint_faces = np.concatenate(face_parts) if face_parts else np.zeros((0, 3), np.int64)
    joint_face_set = np.concatenate(face_set_parts) if face_set_parts else np.zeros(0, np.int64)

    points, tets, renumber = _used_nodes(coords, tets)
    joint_faces = renumber[joint_faces]

    # Joint faces: normal along the set's nominal normal.
    nominal = np.array([joint_normal(js.dip, js.dip_direction) for js in geology.joint_sets]).reshape(-1, 3)
    if len(joint_faces):
        flip = np.einsum("ij,ij->i", _face_normals(points, joint_faces), nominal[joint_face_set]) < 0.0
        joint_faces[flip] = joint_faces[flip][:, [0, 2, 1]]

    centroid_z = points[tets][:, :, 2].mean(axis=1)
    block = np.concatenate(block_parts)
    boundary = _classify_boundary(points, tets, lo, hi, 1e3 * tol)
    _solid_face_sets(boundary, geology.solids, points, tets, block, len(rock_tags), 1e3 * tol)
    return GeologyMesh(
        points=points,
        tets=tets,
        tet_block=block,
        tet_material=rock.material_of_z(centroid_z),
        material_names=rock.material_names(),
        joint_faces=joint_faces,
        joint_face_set=joint_face_set,
        joint_set_names=geology.joint_set_names(),
        boundary_faces=boundary,
        num_blocks=len(volume_tags),
    )


def _add_solid(occ: Any, solid: Solid, rock_tags: Sequence[int], margin: float, tol: float) -> int:
    """Adds a solid (its box less its cavity) as an OCC volume and returns its tag.

    A cavity that passes right through the box is built ``margin`` [m] longer at both ends, so that the cut is
    transversal. The solid must not overlap the rock: the volume common to it and the rock volumes ``rock_tags``
    (measured on copies) must be below ``tol`` [m] cubed.

    Raises:
        ValueError: the solid overlaps the rock, or its cavity leaves it in pieces.
    """
    lo, hi = np.asarray(solid.lo, float), np.asarray(solid.hi, float)
    probe = occ.addBox(*lo, *(hi - lo))
    common, _ = occ.intersect(occ.copy([(3, t) for t in rock_tags]), [(3, probe)])
    overlap = sum(occ.getMass(dim, tag) for dim, tag in common if dim == 3)
    if common:
        occ.remove(common, recursive=True)
    if overlap > tol**3 + _REL_TOL * float(np.prod(hi - lo)):
        raise ValueError(
            f"mesh_geology: solid {solid.name!r} overlaps the rock by {overlap:.3g} m³: a solid must lie inside the "
            "openings, clear of the rock"
        )
    tag = occ.addBox(*lo, *(hi - lo))
    if solid.cavity_lo is None or solid.cavity_hi is None:
        return tag
    clo, chi = np.asarray(solid.cavity_lo, float), np.asarray(solid.cavity_hi, float)
    for axis in solid.through_axes():
        clo[axis], chi[axis] = lo[axis] - margin, hi[axis] + margin
    out, _ = occ.cut([(3, tag)], [(3, occ.addBox(*clo, *(chi - clo)))])
    pieces = [t for dim, t in out if dim == 3]
    if len(pieces) != 1:
        raise ValueError(f"mesh_geology: solid {solid.name!r} less its cavity is {len(pieces)} pieces, not one")
    return pieces[0]


def _solid_face_sets(
    boundary: dict[str, np.ndarray],
    solids: Sequence[Solid],
    points: np.ndarray,
    tets: np.ndarray,
    block: np.ndarray,
    first_block: int,
    tol: float,
) -> None:
    """Moves each solid's walls out of the ``"opening"`` face set into its own sets, in place: ``name`` (its outer
    walls off the model's box faces) and ``name + "_cavity"`` (its cavity's walls, with a cavity).

    Args:
        boundary: the face sets of :func:`_classify_boundary`, changed in place. solids: the geology's solids.
        points: node positions [m], shape (N, 3). tets: shape (M, 4). block: each tet's block, shape (M,); solid i
        is block ``first_block + i``. tol: distance under which a node counts as on a cavity wall [m].
    """
    walls = boundary[OPENING_FACE_NAME]
    for i, solid in enumerate(solids):
        node_in_solid = np.zeros(len(points), dtype=bool)
        node_in_solid[tets[block == first_block + i].ravel()] = True
        mine = np.all(node_in_solid[walls], axis=1)
        faces = walls[mine]
        walls = walls[~mine]
        if solid.cavity_lo is None or solid.cavity_hi is None:
            boundary[solid.name] = faces
            continue
        p = points[faces]
        # A cavity wall's nodes lie within the cavity's box, closed by the tolerance; the outer walls' do not.
        in_cavity = np.all(
            np.all((p >= np.asarray(solid.cavity_lo) - tol) & (p <= np.asarray(solid.cavity_hi) + tol), axis=2), axis=1
        )
        boundary[solid.name] = faces[~in_cavity]
        boundary[f"{solid.name}_cavity"] = faces[in_cavity]
    boundary[OPENING_FACE_NAME] = walls


def _mesh_solid(add: Callable[[Any], int], h: float, material: str, what: str) -> GeologyMesh:
    """One OCC solid (``add(occ)`` returns its volume tag) meshed with tets of edge about ``h`` [m], as one block
    of one material; ``boundary_faces`` holds its outer surface as :data:`SURFACE_FACE_NAME`."""
    with _gmsh_model(_gmsh_options(h, refine=False), f"warpdem_{what}_{id(add)}", what) as gmsh:
        volume = add(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        gmsh.model.mesh.generate(3)
        coords, _, tet_parts, _ = _gmsh_volume_tets(gmsh, [volume], what)
    if not tet_parts or not sum(len(t) for t in tet_parts):
        raise RuntimeError(f"{what}: Gmsh produced no tetrahedra")
    points, tets, _ = _used_nodes(coords, np.concatenate(tet_parts))
    return GeologyMesh.single(points, tets, material, {SURFACE_FACE_NAME: outer_faces(tets).astype(np.int64)})


def mesh_cylinder(
    center: Sequence[float], axis: Sequence[float], radius: float, height: float, h: float, material: str
) -> GeologyMesh:
    """A solid circular cylinder (a disc when ``height`` is small) meshed with Gmsh (the options of
    :func:`mesh_geology`, so equal inputs give identical meshes).

    Args:
        center: centre of the base disc [m], shape (3,). axis: direction of the axis (any length), shape (3,).
        radius: radius [m]. height: length along ``axis`` from the base disc [m]. h: target tet edge [m].
        material: the material name of every tet.

    Raises:
        RuntimeError: Gmsh fails.
    """
    direction = np.asarray(axis, dtype=np.float64)
    direction = height * direction / np.linalg.norm(direction)
    return _mesh_solid(lambda occ: occ.addCylinder(*center, *direction, radius), h, material, "mesh_cylinder")


def mesh_ellipsoid(center: Sequence[float], radii: Sequence[float], h: float, material: str) -> GeologyMesh:
    """A solid ellipsoid with semi-axes ``radii`` along x, y and z [m] (a unit OCC sphere scaled by them), meshed
    with Gmsh; see :func:`mesh_cylinder`."""

    def add(occ: Any) -> int:
        tag = occ.addSphere(*center, 1.0)
        occ.dilate([(3, tag)], *center, *radii)
        return tag

    return _mesh_solid(add, h, material, "mesh_ellipsoid")
