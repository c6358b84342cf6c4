"""A meshed geology (:class:`GeologyMesh`): its named face sets, its topology helpers, and its files.

:func:`read_mesh` and :func:`write_mesh` move a :class:`GeologyMesh` through meshio (Gmsh ``.msh`` and VTU):
tetrahedra carry a physical group (the material) and a geometrical entity (the block), triangles a physical
group whose name makes it a joint set (``joint*``) or a named boundary/load set.
"""

from __future__ import annotations

import os
import pathlib
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import numpy as np

from ..limits import F32_MAX
from ..tables import BOX_FACE_NAMES, OPENING_FACE_NAME, TET_FACES
from .mesh import boundary_faces as outer_faces

_READ_SUFFIXES = {".msh": "gmsh", ".vtu": "vtu", ".vtk": "vtk"}
_LINEAR_VOLUME_CELLS = {"tetra"}
_SURFACE_CELLS = {"triangle"}


class MeshImportError(ValueError):
    """A mesh file cannot be used as a geology mesh; the message is one line naming the file and the problem.

    Attributes:
        argument: The :func:`read_mesh` argument the problem is about (``"material_map"``, ``"joint_groups"``), or
            None for a problem of the file itself.
    """

    def __init__(self, message: str, argument: str | None = None) -> None:
        super().__init__(message)
        self.argument = argument


# ---------------------------------------------------------------------------------------------------------------
# The mesh
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class GeologyMesh:
    """A tetrahedral rock mesh with its blocks, materials, joint faces and boundary sets.

    Attributes:
        points: Node positions [m], shape (N, 3), float64. Nodes are numbered 0..N-1 and all belong to tets.
        tets: Node indices of the tetrahedra, shape (M, 4), int64, positively oriented
            (``det[p1 - p0, p2 - p0, p3 - p0] > 0``).
        tet_block: Rock block (Gmsh volume) of each tet, shape (M,), int64, values 0..num_blocks-1.
        tet_material: Index into ``material_names`` of each tet, shape (M,), int64.
        material_names: Material names.
        joint_faces: Node triples of the mesh faces on joint surfaces, shape (J, 3), int64. Each face appears
            once and is shared by the two tets on either side. :func:`mesh_geology` orients each face so its
            right-hand normal points along the set's nominal normal (:func:`joint_normal`).
        joint_face_set: Joint set of each joint face, shape (J,), int64, index into ``joint_set_names``.
        joint_set_names: Joint set names.
        boundary_faces: Named face sets, name → node triples shape (F, 3), int64. :func:`mesh_geology` gives the
            outer box faces (:data:`BOX_FACE_NAMES`) and ``"opening"`` (tunnel, shaft and room walls), each face
            oriented with its normal pointing out of the rock.
        num_blocks: Number of rock blocks.
    """

    points: np.ndarray
    tets: np.ndarray
    tet_block: np.ndarray
    tet_material: np.ndarray
    material_names: list[str]
    joint_faces: np.ndarray
    joint_face_set: np.ndarray
    joint_set_names: list[str]
    boundary_faces: dict[str, np.ndarray]
    num_blocks: int

    @classmethod
    def single(
        cls, points: np.ndarray, tets: np.ndarray, material: str, boundary_faces: dict[str, np.ndarray]
    ) -> GeologyMesh:
        """One block of one material with no joints (a box, an arch, a dam, a solid): ``points`` shape (N, 3) [m],
        ``tets`` shape (M, 4), ``boundary_faces`` name → node triples shape (F, 3)."""
        return cls(
            points=points,
            tets=tets,
            tet_block=np.zeros(len(tets), np.int64),
            tet_material=np.zeros(len(tets), np.int64),
            material_names=[material],
            joint_faces=np.zeros((0, 3), np.int64),
            joint_face_set=np.zeros(0, np.int64),
            joint_set_names=[],
            boundary_faces=boundary_faces,
            num_blocks=1,
        )

    def tet_volumes(self) -> np.ndarray:
        """Volume of each tet [m³], shape (M,)."""
        p = self.points[self.tets]
        return np.linalg.det(p[:, 1:] - p[:, :1]) / 6.0


# ---------------------------------------------------------------------------------------------------------------
# Mesh topology helpers
# ---------------------------------------------------------------------------------------------------------------


def _orient_tets(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swaps two nodes of every negatively oriented tet."""
    p = points[tets]
    negative = np.linalg.det(p[:, 1:] - p[:, :1]) < 0.0
    tets = tets.astype(np.int64, copy=True)
    tets[negative] = tets[negative][:, [0, 2, 1, 3]]
    return tets


def _face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = points[faces]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def _tet_face_table(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All tet faces, outward oriented, shape (4M, 3) (row 4t + i is face i of tet t), with the unique sorted
    node triples, the index of each face's triple among them and how many tets share each triple."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    keys, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    return faces, keys, inverse.reshape(-1), counts


def interior_faces(tets: np.ndarray) -> np.ndarray:
    """Faces shared by two tets, as sorted node triples, shape (F, 3), int64, in lexicographic order."""
    _, keys, _, counts = _tet_face_table(np.asarray(tets, dtype=np.int64))
    return keys[counts == 2]


def _classify_boundary(
    points: np.ndarray, tets: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float
) -> dict[str, np.ndarray]:
    """Faces of exactly one tet, outward oriented, sorted onto the six box faces and the opening walls."""
    outer = outer_faces(tets).astype(np.int64)
    p = points[outer]
    remaining = np.ones(len(outer), dtype=bool)
    result: dict[str, np.ndarray] = {}
    for name in BOX_FACE_NAMES:
        axis = "xyz".index(name[0])
        value = lo[axis] if name[1] == "-" else hi[axis]
        on = remaining & np.all(np.abs(p[:, :, axis] - value) <= tol, axis=1)
        result[name] = outer[on]
        remaining &= ~on
    result[OPENING_FACE_NAME] = outer[remaining]
    return result


def _blocks_from_components(tets: np.ndarray, joint_faces: np.ndarray) -> np.ndarray:
    """Connected components of tets across shared faces that are not joint faces, numbered in tet order."""
    _, keys, inverse, counts = _tet_face_table(tets)
    is_joint = np.zeros(len(keys), dtype=bool)
    if len(joint_faces):
        pos = _row_lookup(keys, np.sort(joint_faces, axis=1))
        is_joint[pos[pos >= 0]] = True
    order = np.argsort(inverse, kind="stable")  # the two rows of a shared face become neighbours
    shared = (counts[inverse[order]] == 2) & ~is_joint[inverse[order]]
    pairs = order[shared].reshape(-1, 2) // 4
    return component_labels(len(tets), pairs[:, 0], pairs[:, 1])


def component_labels(count: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected components of the graph on ``count`` vertices with edges ``a[i]``–``b[i]``.

    Returns:
        The component of each vertex, shape (count,), int64, numbered 0, 1, ... in order of each component's lowest
        vertex.
    """
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    labels = np.arange(count)
    while True:  # min-label propagation with pointer jumping
        new = labels.copy()
        m = np.minimum(labels[a], labels[b])
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]
        if np.array_equal(new, labels):
            break
        labels = new
    _, block = np.unique(labels, return_inverse=True)
    return block.reshape(-1).astype(np.int64)


def _row_lookup(table: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Index of each row of ``rows`` in the lexicographically sorted unique ``table``, -1 where absent."""
    if len(table) == 0:
        return np.full(len(rows), -1, dtype=np.int64)
    dtype = np.dtype((np.void, table.dtype.itemsize * table.shape[1]))
    t = np.ascontiguousarray(table).view(dtype).reshape(-1)
    r = np.ascontiguousarray(rows.astype(table.dtype)).view(dtype).reshape(-1)
    order = np.argsort(t)
    pos = np.searchsorted(t[order], r)
    pos = np.clip(pos, 0, len(t) - 1)
    found = t[order][pos] == r
    return np.where(found, order[pos], -1)


# ---------------------------------------------------------------------------------------------------------------
# Import and export
# ---------------------------------------------------------------------------------------------------------------


def _import_error(path: pathlib.Path, problem: str, argument: str | None = None) -> MeshImportError:
    return MeshImportError(f"{path}: {' '.join(problem.split())}", argument)


def _check_cells(path: pathlib.Path, cells: np.ndarray, num_points: int, what: str) -> None:
    """Raises MeshImportError naming the first cell with a node index outside 0 .. num_points - 1 (numpy would wrap a
    negative one silently, and fail on a large one without naming the file)."""
    bad = np.nonzero(np.any((cells < 0) | (cells >= num_points), axis=1))[0]
    if len(bad):
        k = int(bad[0])
        raise _import_error(
            path, f"{what} {k} has node indices {cells[k].tolist()} outside 0..{num_points - 1} (the file's nodes)"
        )


def read_mesh(
    path: str | os.PathLike,
    *,
    material_map: Mapping[int | str, str] | None = None,
    material_array: str | None = None,
    joint_groups: Sequence[str] | None = None,
) -> GeologyMesh:
    """Reads a ready tetrahedral mesh (Gmsh ``.msh`` v2/v4, VTU, legacy VTK) through meshio.

    Tetrahedra: the material comes from the cell-data array ``material_array`` if given, else
    ``"gmsh:physical"``, ``"material"``, ``"MaterialIds"`` or ``"gmsh:geometrical"``, the first present; each
    distinct value is a group, named through ``field_data`` (Gmsh physical names) where possible. Without any
    such array every tet is ``"rock"``. The block is the ``"gmsh:geometrical"`` entity (or a ``"block"``
    array); failing both, blocks are the connected sets of tets across non-joint faces.

    Triangles: grouped by ``"gmsh:physical"`` and named through ``field_data`` (unnamed groups are named by
    their number). Groups in ``joint_groups`` (default: names starting with ``"joint"``) are joint sets, the
    rest go to ``boundary_faces`` under their names. Lines and points are ignored.

    Args:
        path: Mesh file.
        material_map: Group tag or group name → material name. When given, every tet group must appear in it.
        material_array: Name of the tet cell-data array holding the material groups.
        joint_groups: Names of the triangle groups that are joints; each must be a triangle group of the file.

    Returns:
        The mesh, with unused nodes dropped and tets positively oriented.

    Raises:
        MeshImportError: If the file is missing, of unknown format or unreadable, has no tetrahedra, has other
            volume cells (hexahedra, wedges, pyramids, quadratic tets), has triangles that are not tet faces,
            has a tet group missing from ``material_map``, or lacks a group named in ``joint_groups``.
    """
    import meshio

    path = pathlib.Path(path)
    if not path.is_file():
        raise _import_error(path, "no such file")
    file_format = _READ_SUFFIXES.get(path.suffix.lower())
    if file_format is None:
        raise _import_error(path, f"unknown mesh format {path.suffix!r}, expected one of {', '.join(_READ_SUFFIXES)}")
    # The format readers directly: meshio.read reports a failed read by printing and calling sys.exit.
    reader = {"gmsh": meshio.gmsh.read, "vtu": meshio.vtu.read, "vtk": meshio.vtk.read}[file_format]
    try:
        raw = reader(str(path))
    except Exception as exc:
        detail = str(exc) or type(exc).__name__
        raise _import_error(path, f"cannot read as {file_format}: {detail}") from exc

    volume_types = {c.type for c in raw.cells if c.dim == 3}
    unsupported = sorted(volume_types - _LINEAR_VOLUME_CELLS)
    if unsupported:
        counts = ", ".join(f"{sum(len(c.data) for c in raw.cells if c.type == t)} {t}" for t in unsupported)
        raise _import_error(path, f"has {counts} cells; only linear tetrahedra (tetra) are supported")
    tet_blocks = [i for i, c in enumerate(raw.cells) if c.type == "tetra"]
    tri_blocks = [i for i, c in enumerate(raw.cells) if c.type in _SURFACE_CELLS]
    if not tet_blocks or sum(len(raw.cells[i].data) for i in tet_blocks) == 0:
        found = ", ".join(sorted({c.type for c in raw.cells})) or "no cells"
        raise _import_error(path, f"has no tetrahedra (found {found})")

    def cell_array(name: str, blocks: list[int]) -> np.ndarray | None:
        data = raw.cell_data.get(name)
        if data is None:
            return None
        return np.concatenate([np.asarray(data[i]).reshape(len(raw.cells[i].data), -1)[:, 0] for i in blocks])

    names_by_dim: dict[int, dict[int, str]] = {2: {}, 3: {}}
    for name, value in raw.field_data.items():
        value = np.asarray(value).reshape(-1)
        if len(value) >= 2 and int(value[1]) in names_by_dim:
            names_by_dim[int(value[1])][int(value[0])] = str(name)

    tets = np.concatenate([np.asarray(raw.cells[i].data, dtype=np.int64) for i in tet_blocks])
    _check_cells(path, tets, len(raw.points), "tet")
    candidates = (
        [material_array] if material_array else ["gmsh:physical", "material", "MaterialIds", "gmsh:geometrical"]
    )
    groups = next((g for g in (cell_array(n, tet_blocks) for n in candidates) if g is not None), None)
    if material_array and groups is None:
        raise _import_error(path, f"has no tet cell-data array {material_array!r} (has {sorted(raw.cell_data)})")

    if groups is None:
        tet_material = np.zeros(len(tets), dtype=np.int64)
        material_names = ["rock"]
    else:
        groups = groups.astype(np.int64)
        tags, group_index = np.unique(groups, return_inverse=True)
        group_names = [names_by_dim[3].get(int(t)) for t in tags]
        if material_map is None:
            resolved = [name or f"material{t}" for t, name in zip(tags, group_names, strict=True)]
        else:
            resolved = []
            for t, name in zip(tags, group_names, strict=True):
                key: int | str | None = name if name in material_map else int(t) if int(t) in material_map else None
                if key is None:
                    label = f"{int(t)} ({name!r})" if name else f"{int(t)}"
                    raise _import_error(
                        path,
                        f"tet physical group {label} is not in material_map (keys: {sorted(map(str, material_map))})",
                        "material_map",
                    )
                resolved.append(material_map[key])
        material_names = list(dict.fromkeys(resolved))
        lookup = np.array([material_names.index(n) for n in resolved], dtype=np.int64)
        tet_material = lookup[group_index.reshape(-1)]

    joint_parts, joint_set_parts, boundary_parts = [], [], {}
    joint_set_names: list[str] = []
    tris = np.zeros((0, 3), np.int64)
    tri_groups = np.zeros(0, np.int64)
    if tri_blocks:
        tris = np.concatenate([np.asarray(raw.cells[i].data, dtype=np.int64) for i in tri_blocks])
        _check_cells(path, tris, len(raw.points), "triangle")
        tri_groups = cell_array("gmsh:physical", tri_blocks)
        tri_groups = np.zeros(len(tris), np.int64) if tri_groups is None else tri_groups.astype(np.int64)
    tri_names = [names_by_dim[2].get(int(t), str(int(t))) for t in np.unique(tri_groups)]
    missing = [name for name in joint_groups or [] if name not in tri_names]
    if missing:
        raise _import_error(
            path,
            f"has no triangle group {', '.join(repr(n) for n in missing)} named in joint_groups "
            f"(its triangle groups: {', '.join(repr(n) for n in tri_names) or 'none'})",
            "joint_groups",
        )
    for t, name in zip(np.unique(tri_groups), tri_names, strict=True):
        faces = tris[tri_groups == t]
        is_joint = name in joint_groups if joint_groups is not None else name.lower().startswith("joint")
        if is_joint:
            joint_parts.append(faces)
            joint_set_parts.append(np.full(len(faces), len(joint_set_names), dtype=np.int64))
            joint_set_names.append(name)
        else:
            boundary_parts[name] = faces

    used = np.unique(tets)
    renumber = np.full(len(raw.points), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    points = np.ascontiguousarray(np.asarray(raw.points, dtype=np.float64)[used])
    if points.shape[1] != 3:
        raise _import_error(path, f"has {points.shape[1]}-dimensional points; a tet mesh needs 3")
    # The device holds positions in float32: a coordinate it cannot represent is refused with the node that has it.
    bad = np.nonzero(~np.all(np.isfinite(points) & (np.abs(points) <= F32_MAX), axis=1))[0]
    if len(bad):
        node = int(used[bad[0]])
        raise _import_error(
            path, f"node {node} has coordinates {raw.points[node].tolist()}; allowed: finite, at most {F32_MAX:g} m"
        )
    tets = _orient_tets(points, renumber[tets])

    face_keys = np.unique(np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1), axis=0)
    for name, faces in [*zip(joint_set_names, joint_parts, strict=True), *boundary_parts.items()]:
        mapped = renumber[faces]
        if np.any(mapped < 0) or np.any(_row_lookup(face_keys, np.sort(mapped, axis=1)) < 0):
            raise _import_error(path, f"triangle group {name!r} has triangles that are not faces of the tets")
    joint_faces = renumber[np.concatenate(joint_parts)] if joint_parts else np.zeros((0, 3), np.int64)
    joint_face_set = np.concatenate(joint_set_parts) if joint_set_parts else np.zeros(0, np.int64)
    boundary_faces = {name: renumber[faces] for name, faces in boundary_parts.items()}

    block_ids = cell_array("gmsh:geometrical", tet_blocks)
    if block_ids is None:
        block_ids = cell_array("block", tet_blocks)
    if block_ids is None:
        tet_block = _blocks_from_components(tets, joint_faces)
    else:
        _, tet_block = np.unique(block_ids.astype(np.int64), return_inverse=True)
        tet_block = tet_block.reshape(-1).astype(np.int64)

    return GeologyMesh(
        points=points,
        tets=tets,
        tet_block=tet_block,
        tet_material=tet_material,
        material_names=material_names,
        joint_faces=joint_faces,
        joint_face_set=joint_face_set,
        joint_set_names=joint_set_names,
        boundary_faces=boundary_faces,
        num_blocks=int(tet_block.max()) + 1,
    )


def write_mesh(path: str | os.PathLike, mesh: GeologyMesh) -> None:
    """Writes a mesh that :func:`read_mesh` reads back unchanged (Gmsh MSH 2.2 ASCII or VTU), through meshio.

    Tets carry ``"gmsh:physical"`` = material index + 1 and ``"gmsh:geometrical"`` = block + 1; joint and
    boundary faces are triangles whose ``"gmsh:physical"`` tag follows the materials (joint sets first). Group
    names go to the Gmsh physical names (name → [tag, dim]); for VTU, whose meshio writer drops field data, they
    are added as a ``FieldData`` element of the same layout, which meshio and ParaView read. Empty face sets are
    not written. MSH 4.1 is not offered: meshio's 4.1 writer needs a node entity for every element entity.

    Args:
        path: Output file; the suffix picks the format: ``.msh`` or ``.vtu``. Parent directories are created.
        mesh: The mesh to write.

    Raises:
        ValueError: If the suffix is neither ``.msh`` nor ``.vtu``, or a group name is used twice.
    """
    import meshio

    path = pathlib.Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".msh", ".vtu"):
        raise ValueError(f"write_mesh {str(path)!r}: unsupported suffix {path.suffix!r}, expected .msh or .vtu")

    field_data: dict[str, np.ndarray] = {}
    for i, name in enumerate(mesh.material_names):
        field_data[name] = np.array([i + 1, 3])
    cells = [("tetra", mesh.tets)]
    physical = [mesh.tet_material + 1]
    geometrical = [mesh.tet_block + 1]
    face_sets = [
        (name, mesh.joint_faces[mesh.joint_face_set == k]) for k, name in enumerate(mesh.joint_set_names)
    ] + list(mesh.boundary_faces.items())
    tag = len(mesh.material_names)
    for name, faces in face_sets:
        if len(faces) == 0:
            continue
        if name in field_data:
            raise ValueError(f"write_mesh {str(path)!r}: group name {name!r} is used twice")
        tag += 1
        field_data[name] = np.array([tag, 2])
        cells.append(("triangle", np.asarray(faces, dtype=np.int64)))
        physical.append(np.full(len(faces), tag, dtype=np.int64))
        geometrical.append(np.full(len(faces), tag, dtype=np.int64))

    out = meshio.Mesh(
        mesh.points,
        cells,
        cell_data={"gmsh:physical": physical, "gmsh:geometrical": geometrical},
        field_data=field_data,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".msh":
        meshio.write(path, out, file_format="gmsh22", binary=False)
        return
    meshio.write(path, out, file_format="vtu")
    arrays = "".join(
        f'<DataArray type="Int64" Name={quoteattr(name)} NumberOfTuples="2" format="ascii">'
        f"{int(v[0])} {int(v[1])}</DataArray>\n"
        for name, v in field_data.items()
    )
    text = path.read_text()
    text = re.sub(
        r"(<UnstructuredGrid[^>]*>\s*)", lambda m: m.group(1) + f"<FieldData>\n{arrays}</FieldData>\n", text, count=1
    )
    path.write_text(text)
