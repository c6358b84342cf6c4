"""Frame output of the FEM rock: its boundary surface, stress measures and colours, and ParaView VTU series.

The surface of the rock is every face used by exactly one active tet, so the faces of a converted (inactive) tet's
neighbours, and both faces of a crack or joint whose nodes have been split, appear by themselves. A split face
whose two sides have not separated yet (every pair of daughter nodes closer than a gap) is hidden, so a closed joint
does not draw inside the rock; a run-time crack (nodes split by the fracture pass) is drawn the same way, and its
cohesive elements can be drawn as curves. Host code (numpy), run between steps.

VTU series: one ``.vtu`` file per frame (the active tets, with displacement and velocity per node, its damage with
fracture on, and the stress per tet) plus a ``.pvd`` collection that ParaView opens as one time series. Every file
is written under a temporary name and moved over the final one with ``os.replace``, and the collection is rewritten
after every frame, so a run that stops part way leaves a valid series of the frames it finished.
"""

from __future__ import annotations

import math
import os
import pathlib
from typing import TYPE_CHECKING
from xml.sax.saxutils import quoteattr

import numpy as np

from ..stages.fragments import fragment_colors
from ..tables import TET_FACES, row_groups
from .usd_frames import CurveSet, SurfaceFrame

if TYPE_CHECKING:
    from ..model import Model, State

__all__ = [
    "MATERIAL_PALETTE",
    "PART_PALETTE",
    "RockFrames",
    "VtuSeries",
    "max_principal_stress",
    "node_damage",
    "open_faces",
    "ramp_colors",
    "split_face_pairs",
    "surface_faces",
    "von_mises_stress",
]

MATERIAL_PALETTE = np.array(
    [[0.62, 0.6, 0.56], [0.75, 0.5, 0.3], [0.45, 0.55, 0.7], [0.5, 0.65, 0.4], [0.7, 0.45, 0.55], [0.8, 0.75, 0.45]]
)
"""Display colours of material ids (cycled), linear RGB."""

COHESIVE_WIDTH = 0.05
"""Width of the cohesive element curves as a fraction of the mesh size: visible beside the tets, not hiding them."""

CLOSED_GAP = 1e-3
"""A split face counts as closed while its daughter nodes are closer than this times the mesh size (the cube root
of the mean tet volume): well above the elastic overlap of a loaded joint (~σ h / E) and well below what shows."""


def ramp_colors(values: np.ndarray, scale: float) -> np.ndarray:
    """Blue (0) → red (``scale`` and above), linear RGB, shape (N, 3)."""
    t = np.clip(np.asarray(values, dtype=np.float64) / max(scale, 1e-300), 0.0, 1.0)[:, None]
    return (1.0 - t) * np.array([0.15, 0.3, 0.85]) + t * np.array([0.95, 0.25, 0.1])


def sphere_damage(model: Model, state: State) -> tuple[np.ndarray, np.ndarray]:
    """Damage of the live spheres (reads back; call between steps): the bonds each has lost so far, shape (N,),
    int, and the fraction of its bonds that broke, shape (N,), in [0, 1] (0 for a sphere that never had a bond).
    A sphere's bonds are those it lost plus its intact ones now."""
    n = int(state.particle_count.numpy()[0])
    broken = state.particle_bonds_broken.numpy()[:n].astype(np.int64)
    nb = int(state.bond_count.numpy()[0]) if model.bond_capacity else 0
    intact = state.bond_broken.numpy()[:nb] == 0
    ends = np.concatenate([state.bond_i.numpy()[:nb][intact], state.bond_j.numpy()[:nb][intact]])
    total = broken + np.bincount(ends, minlength=n)[:n]
    return broken, np.where(total > 0, broken / np.maximum(total, 1), 0.0)


PART_PALETTE = np.array(
    [[0.55, 0.55, 0.6], [0.85, 0.45, 0.2], [0.2, 0.6, 0.85], [0.4, 0.75, 0.3], [0.8, 0.3, 0.5], [0.9, 0.8, 0.3]]
)
"""The sphere colours of ``color_by = "part"``, one per part in order (cycled), shape (6, 3)."""


def damage_colors(fraction: np.ndarray) -> np.ndarray:
    """Light grey (no bond broken) → orange → dark red (every bond broken), linear RGB, shape (N, 3)."""
    stops = np.array([[0.72, 0.72, 0.75], [0.95, 0.55, 0.1], [0.6, 0.05, 0.05]])
    t = np.clip(np.asarray(fraction, dtype=np.float64), 0.0, 1.0) * 2.0
    k = np.minimum(t.astype(int), 1)
    w = (t - k)[:, None]
    return (1.0 - w) * stops[k] + w * stops[k + 1]


def node_damage(model: Model, state: State) -> np.ndarray | None:
    """Damage of the live FEM nodes (reads back; call between steps): the largest δ_max/δ_c of each node's cohesive
    elements so far, 1 once one broke, shape (N,), float32 in [0, 1]; None when fracture is off."""
    if not model.has_fracture:
        return None
    return state.node_damage.numpy()[: int(state.node_count.numpy()[0])]


def sphere_point_data(model: Model, state: State) -> dict[str, np.ndarray]:
    """Per-sphere fields for the ParaView series (reads back): radius [m], velocity [m/s], spin [rad/s], id, part,
    material, bonds_broken (bonds lost so far) and damage (their fraction of the sphere's bonds)."""
    n = int(state.particle_count.numpy()[0])
    broken, fraction = sphere_damage(model, state)
    return {
        "radius": model.particle_radius.numpy()[:n].astype(np.float64),
        "velocity": state.particle_qd.numpy()[:n].astype(np.float64),
        "spin": state.particle_omega.numpy()[:n].astype(np.float64),
        "id": model.particle_id.numpy()[:n].astype(np.int64),
        "part": model.particle_part.numpy()[:n].astype(np.int32),
        "material": model.particle_material.numpy()[:n].astype(np.int32),
        "bonds_broken": broken.astype(np.int32),
        "damage": fraction,
    }


def von_mises_stress(stress: np.ndarray) -> np.ndarray:
    """von Mises stress sqrt(3/2 s:s) of symmetric stress tensors [Pa], s the deviator; shape (M, 3, 3) → (M,)."""
    sigma = np.asarray(stress, dtype=np.float64).reshape(-1, 3, 3)
    s = sigma - np.trace(sigma, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("mij,mij->m", s, s))


def max_principal_stress(stress: np.ndarray) -> np.ndarray:
    """Largest principal stress σ1 (tension positive) [Pa]; shape (M, 3, 3) → (M,)."""
    sigma = np.asarray(stress, dtype=np.float64).reshape(-1, 3, 3)
    if len(sigma) == 0:
        return np.zeros(0)
    return np.linalg.eigvalsh(0.5 * (sigma + np.transpose(sigma, (0, 2, 1))))[:, -1]


def surface_faces(
    tet_nodes: np.ndarray,
    active: np.ndarray,
    *,
    node_root: np.ndarray | None = None,
    node_q: np.ndarray | None = None,
    closed_gap: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The boundary triangles of the active tets, outward oriented, and the tet each belongs to.

    Args:
        tet_nodes: positively oriented tets, shape (M, 4).
        active: which tets are active, shape (M,), bool.
        node_root: for split nodes, the node each one was split from (the original mesh node; itself for a node
            never split), shape (N,). Two faces whose nodes share their roots are the two sides of a split face;
            they are drawn only once they have opened. None: no node was split.
        node_q: node positions [m], shape (N, 3), needed with ``node_root``; displacements do as well (only
            differences between daughters of one node, which share their reference position, are used).
        closed_gap: the two sides of a split face count as closed while every pair of daughter nodes is closer
            than this [m].

    Returns:
        faces: shape (F, 3), int32, right-handed with the normal out of the tet; owner: the tet of each face,
        shape (F,), int64. Faces come in the order of their tets.
    """
    faces, owner = _single_faces(tet_nodes, active)
    if node_root is None or len(faces) == 0:
        return faces, owner
    pairs, side_a, side_b = split_face_pairs(faces, node_root)
    keep = open_faces(len(faces), pairs, side_a, side_b, node_q, closed_gap)
    return faces[keep], owner[keep]


def _single_faces(tet_nodes: np.ndarray, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces used by exactly one active tet (int32, outward) and their tets (int64), in tet order."""
    tet_nodes = np.asarray(tet_nodes, dtype=np.int64).reshape(-1, 4)
    owner_tets = np.nonzero(np.asarray(active, dtype=bool))[0]
    faces = tet_nodes[owner_tets][:, TET_FACES].reshape(-1, 3)
    owner = np.repeat(owner_tets, 4)
    if len(faces) == 0:
        return np.zeros((0, 3), np.int32), np.zeros(0, np.int64)
    # Each face's nodes in increasing order (min, middle, max: cheaper than np.sort along rows of three).
    lo, hi = faces.min(axis=1), faces.max(axis=1)
    group, size = row_groups(np.stack([lo, faces.sum(axis=1) - lo - hi, hi], axis=1))
    single = size[group] == 1
    return faces[single].astype(np.int32), owner[single]


def split_face_pairs(faces: np.ndarray, node_root: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two sides of every split face among boundary faces: faces whose nodes have the same roots.

    Args:
        faces: boundary triangles, shape (F, 3). node_root: the node each node was split from, shape (N,).

    Returns:
        pairs: indices into ``faces`` of the two sides, shape (P, 2); side_a, side_b: their nodes matched by root
        (side_a[p, k] and side_b[p, k] are daughters of one node), shape (P, 3) each.
    """
    roots = np.asarray(node_root, dtype=np.int64)[faces]
    order = np.argsort(roots, axis=1)
    sorted_roots = np.take_along_axis(roots, order, axis=1)
    sorted_nodes = np.take_along_axis(np.asarray(faces, dtype=np.int64), order, axis=1)
    if len(faces) == 0:
        empty = np.zeros((0, 3), np.int64)
        return np.zeros((0, 2), np.int64), empty, empty
    group, group_size = row_groups(sorted_roots)
    twins = np.nonzero(group_size[group] == 2)[0]
    pairs = twins[np.argsort(group[twins], kind="stable")].reshape(-1, 2)
    return pairs, sorted_nodes[pairs[:, 0]], sorted_nodes[pairs[:, 1]]


def open_faces(
    count: int, pairs: np.ndarray, side_a: np.ndarray, side_b: np.ndarray, node_q: np.ndarray, closed_gap: float
) -> np.ndarray:
    """Which of ``count`` boundary faces to draw: all but both sides of each split face whose daughter nodes are all
    closer than ``closed_gap`` [m] (positions or displacements ``node_q``, shape (N, 3)). Boolean, shape (count,)."""
    keep = np.ones(count, dtype=bool)
    if len(pairs):
        q = np.asarray(node_q, dtype=np.float64)
        gap = np.linalg.norm(q[side_a] - q[side_b], axis=2).max(axis=1)
        keep[pairs[gap < closed_gap].reshape(-1)] = False
    return keep


class VtuSeries:
    """Per-frame VTU files of a tet mesh and of the spheres, and the one ``.pvd`` collection that lists both.

    Files: ``<directory>/<name>_vtu/<name>_<frame:06d>.vtu`` (the mesh, part 0 of the collection),
    ``<directory>/<name>_particles/<name>_<frame:06d>.vtu`` (the spheres as vertex cells, part 1; VTK's PolyData
    files would hold the same, but meshio neither writes nor reads them) and ``<directory>/<name>.pvd``. A restarted
    run (with ``first_frame`` > 0) continues the collection, as it continues its USD stage: the entries of the frames
    before ``first_frame`` stay, the later ones are replaced by the frames it writes. ParaView opens the collection
    as one time series of both; draw the spheres with the Point Gaussian representation scaled by ``radius``.

    Args:
        directory: output directory (created). name: base name of the files. first_frame: frame number of the
            first frame this series writes.
    """

    def __init__(self, directory: str | os.PathLike, name: str, first_frame: int = 0) -> None:
        self.directory = pathlib.Path(directory)
        self.name = name
        self.frame_dir = self.directory / f"{name}_vtu"
        self.pvd_path = self.directory / f"{name}.pvd"
        self.particle_dir = self.directory / f"{name}_particles"
        self._entries: list[tuple[float, int, str]] = self._entries_before(first_frame) if first_frame > 0 else []

    def _entries_before(self, first_frame: int) -> list[tuple[float, int, str]]:
        """(time, part, file) of the collection's frames before ``first_frame`` (none without a readable
        collection)."""
        import xml.etree.ElementTree as ET

        try:
            datasets = ET.parse(self.pvd_path).getroot().iter("DataSet")
            entries = [(float(d.get("timestep")), int(d.get("part", "0")), d.get("file")) for d in datasets]
            return [
                (t, part, rel)
                for t, part, rel in entries
                if int(pathlib.PurePosixPath(rel).stem.rsplit("_", 1)[1]) < first_frame
            ]
        except (OSError, ET.ParseError, TypeError, ValueError, IndexError):
            return []

    @property
    def files(self) -> list[pathlib.Path]:
        """The mesh VTU files written so far, in frame order."""
        return [self.directory / rel for _, part, rel in self._entries if part == 0]

    @property
    def particle_files(self) -> list[pathlib.Path]:
        """The sphere VTU files written so far, in frame order."""
        return [self.directory / rel for _, part, rel in self._entries if part == 1]

    def write(
        self,
        frame: int,
        time: float,
        points: np.ndarray,
        tets: np.ndarray,
        point_data: dict[str, np.ndarray],
        cell_data: dict[str, np.ndarray],
    ) -> pathlib.Path:
        """Writes one frame and rewrites the collection.

        Args:
            frame: frame number (names the file). time: simulated time [s] (the collection's timestep).
            points: node positions [m], shape (N, 3). tets: node indices, shape (M, 4).
            point_data: name → array with N rows. cell_data: name → array with M rows (tensors are flattened to
                M × 9 components, as ParaView reads them).

        Returns:
            The VTU file.
        """
        return self._write(
            0, frame, time, points, "tetra", np.asarray(tets, dtype=np.int64).reshape(-1, 4), point_data, cell_data
        )

    def write_particles(
        self, frame: int, time: float, centers: np.ndarray, point_data: dict[str, np.ndarray]
    ) -> pathlib.Path:
        """Writes the spheres of one frame (one vertex cell each) and rewrites the collection.

        Args:
            frame: frame number. time: simulated time [s]. centers: sphere centres [m], shape (N, 3).
            point_data: name → array with N rows (radius, velocity, ...).

        Returns:
            The VTU file.
        """
        n = len(centers)
        return self._write(
            1, frame, time, centers, "vertex", np.arange(n, dtype=np.int64).reshape(n, 1), point_data, {}
        )

    def _write(
        self,
        part: int,
        frame: int,
        time: float,
        points: np.ndarray,
        cell_type: str,
        cells: np.ndarray,
        point_data: dict[str, np.ndarray],
        cell_data: dict[str, np.ndarray],
    ) -> pathlib.Path:
        """Writes one file of collection part ``part`` (0 mesh, 1 spheres) and rewrites the collection."""
        import meshio

        folder = self.frame_dir if part == 0 else self.particle_dir
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{self.name}_{frame:06d}.vtu"
        flat_cells = {}
        for name, a in cell_data.items():
            # The components per cell from the trailing shape, not by -1: a frame may have no cell left (every tet
            # converted, or none to begin with), and numpy cannot infer -1 from an empty array.
            a = np.asarray(a)
            flat = a.reshape(len(cells), math.prod(a.shape[1:]))
            flat_cells[name] = flat[:, 0] if flat.shape[1] == 1 else flat
        mesh = meshio.Mesh(
            np.asarray(points, dtype=np.float64),
            [(cell_type, cells)],
            point_data={name: np.asarray(a) for name, a in point_data.items()},
            cell_data={name: [a] for name, a in flat_cells.items()},
        )
        tmp = path.with_name(f"{path.stem}.partial.vtu")
        try:
            meshio.write(tmp, mesh, file_format="vtu")
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        rel = path.relative_to(self.directory).as_posix()
        self._entries = [e for e in self._entries if e[2] != rel] + [(float(time), part, rel)]
        self._write_collection()
        return path

    def _write_collection(self) -> None:
        lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">']
        lines.append("  <Collection>")
        for time, part, rel in sorted(self._entries):
            lines.append(f'    <DataSet timestep="{time!r}" group="" part="{part}" file={quoteattr(rel)}/>')
        lines += ["  </Collection>", "</VTKFile>", ""]
        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = self.pvd_path.with_name(f"{self.pvd_path.name}.partial")
        tmp.write_text("\n".join(lines))
        os.replace(tmp, self.pvd_path)


class RockFrames:
    """Per-frame output of the FEM rock of a simulation: the USD surface and, optionally, a VTU series.

    The surface is recomputed only when the live tets or their nodes change (a topology pass ran: the joint
    pre-split, or a run-time split that appends daughter nodes and remaps tets to them), and which split faces are
    open every frame: daughters of one node share their reference position, which identifies the two sides of a split
    face, drawn once their daughters are more than :data:`CLOSED_GAP` of the mesh size apart. Colours scale with the
    largest value seen so far in the run, so a colour means the same in every later frame. With fracture on
    (``model.has_fracture``) the surface carries each node's damage (``state.node_damage``) and the VTU
    files a ``damage`` point field.

    Args:
        color_by: ``"stress"`` (von Mises, per triangle), ``"speed"`` (per vertex), ``"material"`` (per triangle) or
            ``"damage"`` (per vertex: the largest δ_max/δ_c of the node's cohesive elements, 1 once one broke;
            :func:`damage_colors`, the ramp of the spheres' damage) or ``"fragment"`` (per vertex, by the fragment id
            :meth:`surface` is given; warpdem.stages.fragments).
        vtu: the VTU series to write, or None.
    """

    COLOR_BY = ("stress", "speed", "material", "damage", "fragment")

    def __init__(self, color_by: str = "stress", vtu: VtuSeries | None = None) -> None:
        if color_by not in self.COLOR_BY:
            raise ValueError(f"color_by: expected one of {', '.join(map(repr, self.COLOR_BY))}, got {color_by!r}")
        self.color_by = color_by
        self.vtu = vtu
        self._key: tuple[np.ndarray, np.ndarray, int] | None = None
        self._pairs: tuple[np.ndarray, np.ndarray, np.ndarray] = split_face_pairs(np.zeros((0, 3), np.int64), [])
        self._size = 0.0
        self._gap = 0.0
        self._faces = np.zeros((0, 3), np.int32)
        self._owner = np.zeros(0, np.int64)
        self._scale = 0.0

    @property
    def color_scale(self) -> float:
        """The largest colour value seen so far in the run [Pa or m/s]; checkpoints keep it, so that a restarted run
        colours its frames as the uninterrupted one."""
        return self._scale

    @color_scale.setter
    def color_scale(self, value: float) -> None:
        self._scale = float(value)

    def _live(self, model: Model, state: State) -> tuple[int, np.ndarray, np.ndarray]:
        nn = int(state.node_count.numpy()[0])
        nt = int(state.tet_count.numpy()[0])
        return nn, model.tet_nodes.numpy()[:nt], state.tet_active.numpy()[:nt] != 0  # rigid tets (2) too

    def surface(self, model: Model, state: State, fragment: np.ndarray | None = None) -> SurfaceFrame | None:
        """The rock surface now (reads back; call between steps), or None for a model without tets.

        Args:
            model: the simulation's model.
            state: the simulation's state.
            fragment: the fragment id of each live node (FragmentStats.node_label), shape (node_count,), or None;
                carried as the surface's ``fragment`` primvar and, with color_by "fragment", its colours (grey
                without it).
        """
        nn, tet_nodes, active = self._live(model, state)
        if nn == 0:
            return None
        key = self._key
        if key is None or not (key[2] == nn and np.array_equal(key[0], tet_nodes) and np.array_equal(key[1], active)):
            # Topology changed: the boundary faces and the pairs of split faces are found again (the slow part).
            self._faces, self._owner = _single_faces(tet_nodes, active)
            _, root = np.unique(model.node_ref_q.numpy()[:nn], axis=0, return_inverse=True)
            self._pairs = split_face_pairs(self._faces, root.reshape(-1))
            volume = model.tet_volume.numpy()[: len(active)][active]
            self._size = float(np.cbrt(volume.mean())) if len(volume) else 0.0
            self._gap = CLOSED_GAP * self._size
            self._key = (tet_nodes.copy(), active.copy(), nn)
        # Every frame: which split faces are open (daughters share X, so displacements give the gaps).
        keep = open_faces(len(self._faces), *self._pairs, state.node_u.numpy()[:nn], self._gap)
        faces, owner = self._faces[keep], self._owner[keep]
        stress = state.tet_stress.numpy()[owner]
        von_mises = von_mises_stress(stress)
        q = state.node_q.numpy()[:nn]
        v = state.node_qd.numpy()[:nn]
        damage = node_damage(model, state)
        vertex_colors = self.color_by in ("speed", "damage", "fragment")
        if self.color_by == "fragment":
            colors = fragment_colors(fragment if fragment is not None else np.full(nn, -1))
        elif self.color_by == "material":
            colors = MATERIAL_PALETTE[model.tet_material.numpy()[owner] % len(MATERIAL_PALETTE)]
        elif self.color_by == "damage":
            colors = damage_colors(damage if damage is not None else np.zeros(nn))
        else:
            values = np.linalg.norm(v, axis=1) if vertex_colors else von_mises
            self._scale = max(self._scale, float(values.max(initial=0.0)))
            colors = ramp_colors(values, self._scale)
        return SurfaceFrame(
            points=q,
            faces=faces,
            velocities=v,
            von_mises=von_mises,
            max_principal=max_principal_stress(stress),
            colors=colors,
            vertex_colors=vertex_colors,
            damage=damage,
            fragment=fragment,
        )

    def cohesive_curves(self, model: Model, state: State) -> CurveSet | None:
        """The intact cohesive elements now as curves from daughter A to daughter B (reads back; call between
        steps), each with its damage δ_max/δ_c; None when fracture is off. The width is :data:`COHESIVE_WIDTH` of
        the mesh size (measured by the last :meth:`surface`, else here)."""
        if not model.has_fracture:
            return None
        if self._size == 0.0:
            nt = int(state.tet_count.numpy()[0])
            volume = model.tet_volume.numpy()[:nt][state.tet_active.numpy()[:nt] != 0]
            self._size = float(np.cbrt(volume.mean())) if len(volume) else 0.0
        nc = int(state.cohesive_count.numpy()[0])
        intact = state.cohesive_broken.numpy()[:nc] == 0
        a, b = state.cohesive_a.numpy()[:nc][intact], state.cohesive_b.numpy()[:nc][intact]
        q = state.node_q.numpy()
        delta_c = state.cohesive_delta_c.numpy()[:nc][intact].astype(np.float64)
        d_max = state.cohesive_d_max.numpy()[:nc][intact].astype(np.float64)
        damage = np.clip(d_max / np.maximum(delta_c, 1e-300), 0.0, 1.0)
        return CurveSet(
            endpoints=np.stack([q[a], q[b]], axis=1).reshape(-1, 2, 3),
            width=COHESIVE_WIDTH * self._size,
            damage=damage,
            colors=damage_colors(damage),
        )

    def write_vtu(self, frame: int, time: float, model: Model, state: State) -> pathlib.Path | None:
        """Writes the active tets of this frame to the VTU series (if any); returns the file."""
        nn, tet_nodes, active = self._live(model, state)
        if self.vtu is None or nn == 0:
            return None
        stress = state.tet_stress.numpy()[: len(active)][active].astype(np.float64)
        point_data = {"displacement": state.node_u.numpy()[:nn], "velocity": state.node_qd.numpy()[:nn]}
        damage = node_damage(model, state)
        if damage is not None:
            point_data["damage"] = damage
        return self.vtu.write(
            frame,
            time,
            state.node_q.numpy()[:nn],
            tet_nodes[active],
            point_data=point_data,
            cell_data={
                "stress": stress.reshape(-1, 9),
                "von_mises": von_mises_stress(stress),
                "max_principal": max_principal_stress(stress),
                "material": model.tet_material.numpy()[: len(active)][active],
            },
        )
