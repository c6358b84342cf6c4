"""Loads and boundaries (host side, DESIGN.md stage 8): pressure histories on face sets, prescribed node velocities,
fixed, roller and non-reflecting boundaries.

A user describes them on the :class:`~warpdem.build.builder.ModelBuilder` (``add_face_pressure``, ``add_node_velocity``,
``add_boundary``), which collects them in a :class:`LoadSpecs`; ``finalize`` turns that into node constraints (the
``node_motion`` codes) and a :class:`LoadModel` of device arrays, and the step applies the loads with
:func:`eval_loads` after the other forces and before the second half kick. The kernels and the physics are in
:mod:`warpdem.kernels.loads`; velocity drivers and constraints are applied by the integrator. The pressure histories
themselves are :class:`warpdem.stages.pressure.PressureHistory` (re-exported here:
``warpdem.stages.loads.PressureHistory``).

Node indices are the ids :meth:`~warpdem.build.builder.ModelBuilder.add_tet_mesh` returns. Faces are node triples; the
faces of a pressure load or of a non-reflecting boundary must each be the face of exactly one tet (a boundary
face) and are re-ordered so that their normal points out of that tet.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import warp as wp

from ..host_data import TetMeshData
from ..kernels import loads as kl
from ..kernels import tets as kt
from ..load_data import FaceSet, LoadModel
from ..model import Model, State
from ..tables import TET_FACES
from .integrate import book_half_ahead
from .pressure import PressureHistory
from .tets import lumped_node_masses, reference_geometry, tet_stable_time_steps

BOUNDARY_KINDS = ("fixed", "roller", "non_reflecting")

# node_motion codes (kernels/tets.py) by held axes, bits x = 1, y = 2, z = 4, and back.
MOTION_OF_HELD = np.array(
    [
        kt.NODE_FREE,
        kt.NODE_ROLLER_X,
        kt.NODE_ROLLER_Y,
        kt.NODE_Z_ONLY,
        kt.NODE_ROLLER_Z,
        kt.NODE_Y_ONLY,
        kt.NODE_X_ONLY,
        kt.NODE_FIXED,
    ],
    dtype=np.int32,
)
HELD_OF_MOTION = np.argsort(MOTION_OF_HELD).astype(np.int32)


# ----------------------------------------------------------------------------------------------------------------
# What a builder collects


class PressureSpec(NamedTuple):
    """A pressure load as given: ``faces`` node triples (F, 3), its ``history``, a ``name`` for reports, and the share
    of the face's force each node takes, ``weights`` (F, 3) in the faces' node order (None: a third each; fewer where
    the load's region covers part of a face, warpdem.build.face_cover)."""

    faces: np.ndarray
    history: PressureHistory
    name: str
    weights: np.ndarray | None = None


def oriented_weights(faces: np.ndarray, oriented: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``weights`` (F, 3) of ``faces`` (F, 3) re-ordered as the same faces' nodes are in ``oriented`` (F, 3)
    (:func:`boundary_face_owners` turns each face to point out of its tet)."""
    faces, oriented = np.asarray(faces), np.asarray(oriented)
    position = np.argmax(oriented[:, :, None] == faces[:, None, :], axis=2)  # oriented k sits at input position[k]
    return np.take_along_axis(np.asarray(weights, dtype=np.float64), position, axis=1)


def node_indices(nodes: np.ndarray | Sequence[int], what: str) -> np.ndarray:
    """Node ids from indices or a boolean mask, shape (K,), int64.

    Raises:
        ValueError: not a 1-D integer or boolean array, or a negative index.
    """
    a = np.asarray(nodes)
    if a.dtype == bool:
        return np.nonzero(a)[0]
    if a.ndim != 1 or (len(a) and not np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{what}: node ids must be a 1-D integer array or a boolean mask, got {a.dtype} {a.shape}")
    if len(a) and a.min() < 0:
        raise ValueError(f"{what}: negative node id {int(a.min())}")
    return a.astype(np.int64)


def face_indices(faces: np.ndarray | Sequence[Sequence[int]], what: str) -> np.ndarray:
    """Faces as node triples, shape (F, 3), int64.

    Raises:
        ValueError: not an (F, 3) integer array, a negative id, or a face with a repeated node.
    """
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or (len(f) and not np.issubdtype(f.dtype, np.integer)):
        raise ValueError(f"{what}: faces must be an (F, 3) integer array of node ids, got {f.dtype} {f.shape}")
    if len(f) == 0:
        raise ValueError(f"{what}: no faces")
    if f.min() < 0:
        raise ValueError(f"{what}: negative node id {int(f.min())}")
    s = np.sort(f, axis=1)
    if np.any(s[:, 1:] == s[:, :-1]):
        bad = int(np.nonzero(np.any(s[:, 1:] == s[:, :-1], axis=1))[0][0])
        raise ValueError(f"{what}: face {bad} repeats a node: {f[bad].tolist()}")
    return f.astype(np.int64)


def axis_of(normal: Sequence[float], what: str) -> int:
    """The coordinate axis (0, 1, 2) a normal is parallel to.

    Raises:
        ValueError: a normal that is zero, not finite or not axis-aligned.
    """
    n = np.asarray(normal, dtype=np.float64)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.any(n != 0.0):
        raise ValueError(f"{what}: normal must be a finite non-zero 3-vector, got {normal}")
    axis = int(np.argmax(np.abs(n)))
    if np.count_nonzero(n) != 1:
        raise ValueError(f"{what}: a roller needs an axis-aligned normal (±x, ±y or ±z), got {normal}")
    return axis


@dataclass
class LoadSpecs:
    """The loads and boundaries a builder has been given, validated as they come (node ranges at finalize).

    Attributes:
        pressures: a :class:`PressureSpec` per pressure load.
        drivers: (nodes (K,), velocity [m/s] (3,), start [s], end [s]) per velocity driver.
        boundaries: (kind, nodes (K,) or faces (F, 3), axis or None) per boundary.
    """

    pressures: list[PressureSpec] = field(default_factory=list)
    drivers: list[tuple[np.ndarray, np.ndarray, float, float]] = field(default_factory=list)
    boundaries: list[tuple[str, np.ndarray, int | None]] = field(default_factory=list)

    def add_face_pressure(
        self, faces: np.ndarray, history: PressureHistory, name: str = "", weights: np.ndarray | None = None
    ) -> None:
        """See :meth:`warpdem.build.builder.ModelBuilder.add_face_pressure`."""
        if not isinstance(history, PressureHistory):
            raise ValueError(f"history must be a PressureHistory, got {type(history).__name__}")
        name = name or f"{history.kind}{len(self.pressures)}"
        what = f"pressure {name!r}"
        f = face_indices(faces, what)
        if weights is not None:
            weights = np.asarray(weights, dtype=np.float64)
            if weights.shape != f.shape:
                raise ValueError(f"{what}: weights must have the faces' shape {f.shape}, got {weights.shape}")
            if np.any(weights < 0.0) or np.any(weights.sum(axis=1) > 1.0 + 1e-9):
                raise ValueError(f"{what}: each face's weights must be ≥ 0 and sum to at most 1 (its covered share)")
        self.pressures.append(PressureSpec(f, history, name, weights))

    def add_node_velocity(
        self, nodes: np.ndarray, velocity: Sequence[float], start: float = 0.0, end: float = math.inf
    ) -> None:
        """See :meth:`warpdem.build.builder.ModelBuilder.add_node_velocity`."""
        what = f"node velocity {len(self.drivers)}"
        ids = node_indices(nodes, what)
        v = np.asarray(velocity, dtype=np.float64)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f"{what}: velocity must be a finite 3-vector [m/s], got {velocity}")
        if not (math.isfinite(start) and end > start):
            raise ValueError(f"{what}: need a finite start < end, got start = {start}, end = {end}")
        self.drivers.append((ids, v, float(start), float(end)))

    def add_boundary(self, faces_or_nodes: np.ndarray, kind: str, normal: Sequence[float] | None = None) -> None:
        """See :meth:`warpdem.build.builder.ModelBuilder.add_boundary`."""
        what = f"{kind} boundary {len(self.boundaries)}"
        if kind not in BOUNDARY_KINDS:
            raise ValueError(f"boundary kind {kind!r}; allowed: {', '.join(BOUNDARY_KINDS)}")
        a = np.asarray(faces_or_nodes)
        items = face_indices(a, what) if a.ndim == 2 else node_indices(a, what)
        if len(items) == 0:
            raise ValueError(f"{what}: no nodes")
        axis = None
        if kind == "non_reflecting":
            if items.ndim != 2:
                raise ValueError(f"{what}: a non-reflecting boundary needs faces (F, 3), got node ids")
            if normal is not None:
                raise ValueError(f"{what}: takes its normals from its faces; do not pass normal")
        elif kind == "roller":
            if normal is not None:
                axis = axis_of(normal, what)
            elif items.ndim != 2:
                raise ValueError(f"{what}: a roller on nodes needs its normal")
        elif normal is not None:
            raise ValueError(f"{what}: a fixed boundary takes no normal")
        self.boundaries.append((kind, items, axis))

    def __bool__(self) -> bool:
        return bool(self.pressures or self.drivers or self.boundaries)

    # -- finalize --------------------------------------------------------------------------------------------
    def check_nodes(self, num_nodes: int) -> None:
        """Raise ValueError if a load or boundary names a node past the ``num_nodes`` of the meshes."""
        named = [(f"pressure {p.name!r}", p.faces) for p in self.pressures]
        named += [(f"node velocity {k}", d[0]) for k, d in enumerate(self.drivers)]
        named += [(f"{b[0]} boundary {k}", b[1]) for k, b in enumerate(self.boundaries)]
        for what, ids in named:
            if ids.size and ids.max() >= num_nodes:
                raise ValueError(f"{what}: node id {int(ids.max())} but the tet meshes have {num_nodes} nodes")

    def constrain(self, mesh: TetMeshData) -> TetMeshData:
        """The mesh with the fixed and roller boundaries folded into its ``motion`` codes (held axes add up: a
        node on two roller planes moves along their common line) and its initial velocity zeroed on held axes.

        Raises:
            ValueError: an id past the mesh, or a roller on faces that do not lie in one axis-aligned plane.
        """
        if not self.boundaries:
            return mesh
        self.check_nodes(len(mesh.points))
        held = HELD_OF_MOTION[mesh.motion]
        for kind, items, axis in self.boundaries:
            if kind == "non_reflecting":
                continue
            nodes = np.unique(items)
            if kind == "fixed":
                held[nodes] |= 7
                continue
            if axis is None:
                axis = roller_axis(mesh.points, items)
            held[nodes] |= 1 << axis
        bits = (held[:, None] >> np.arange(3)) & 1
        return TetMeshData(
            points=mesh.points,
            velocity=np.where(bits == 1, 0.0, mesh.velocity),
            motion=MOTION_OF_HELD[held],
            tets=mesh.tets,
            material=mesh.material,
        )

    def build(
        self,
        mesh: TetMeshData,
        table: list[kt.TetMaterial],
        node_capacity: int,
        device: wp.context.Device,
    ) -> LoadModel:
        """The device-side :class:`LoadModel` (empty when nothing was given).

        Args:
            mesh: the constrained mesh (:meth:`constrain`). table: TetMaterial per material id.
            node_capacity: node slots. device: Warp device.

        Raises:
            ValueError: an id past the mesh, a face that is no boundary face of a tet, or a node driven twice (a
                dashpot too stiff for dt is refused by ModelBuilder.finalize, warpdem.stages.guard.check_time_step).
        """
        self.check_nodes(len(mesh.points))
        loads, faces, owners, weights, face_load, kinds, table_times, table_values = [], [], [], [], [], [], [], []
        for k, (f, history, name, w) in enumerate(self.pressures):
            oriented, owner = boundary_face_owners(mesh.tets, f, f"pressure {name!r}")
            owners.append(owner)
            weights.append(np.full(oriented.shape, 1.0 / 3.0) if w is None else oriented_weights(f, oriented, w))
            loads.append(history.device_load(sum(len(t) for t in table_times)))
            table_times.append(np.asarray(history.times, dtype=np.float64))
            table_values.append(np.asarray(history.values, dtype=np.float64))
            faces.append(oriented)
            face_load.append(np.full(len(oriented), k))
            kinds.append(np.full(len(oriented), kl.PRESSURE_KINDS.index(history.kind)))
        pressure: dict[str, FaceSet] = {}
        if loads:
            all_faces, all_load, all_kind = np.concatenate(faces), np.concatenate(face_load), np.concatenate(kinds)
            all_owner, all_weight = np.concatenate(owners), np.concatenate(weights)
            first = 0
            for i, kind in enumerate(kl.PRESSURE_KINDS):
                mine = all_kind == i
                if np.any(mine):
                    pressure[kind] = FaceSet.create(
                        mesh.points,
                        all_faces[mine],
                        device,
                        index=all_load[mine],
                        tet=all_owner[mine],
                        first=first,
                        weight=all_weight[mine],
                    )
                    first += int(np.count_nonzero(mine))
        dashpots = self.build_dashpots(mesh, table, device)
        node_driver, drivers = self.build_drivers(len(mesh.points), node_capacity, device)
        return LoadModel(
            pressure=pressure,
            pressure_loads=wp.array(loads, dtype=kl.PressureLoad, device=device) if loads else None,
            pressure_names=[p.name for p in self.pressures],
            table_times=wp.array(np.concatenate([np.zeros(0), *table_times]), dtype=wp.float64, device=device),
            table_values=wp.array(np.concatenate([np.zeros(0), *table_values]), dtype=float, device=device),
            dashpots=dashpots,
            node_driver=node_driver,
            drivers=drivers,
        )

    def dashpot_faces(self, mesh: TetMeshData, table: list[kt.TetMaterial]) -> tuple[np.ndarray, np.ndarray] | None:
        """The non-reflecting faces, oriented out of their tets, (F, 3), and the impedances (ρ c_p, ρ c_s) of those
        tets [Pa s/m], (F, 2); None without any."""
        faces, impedance = [], []
        for k, (kind, items, _) in enumerate(self.boundaries):
            if kind != "non_reflecting":
                continue
            oriented, owner = boundary_face_owners(mesh.tets, items, f"non_reflecting boundary {k}")
            mats = [table[m] for m in mesh.material[owner]]
            # Lysmer–Kuhlemeyer: ρ c_p and ρ c_s of the tet behind each face.
            impedance.append([[m.density * m.c_p, math.sqrt(m.mu * m.density)] for m in mats])
            faces.append(oriented)
        if not faces:
            return None
        return np.concatenate(faces), np.asarray(np.concatenate(impedance), dtype=np.float64)

    def critical_time_step(self, mesh: TetMeshData, table: list[kt.TetMaterial]) -> float:
        """Stable step [s] of the nodes with dashpots (inf without any), before the safety factor
        (:func:`dashpot_critical_step` on the scene's non-reflecting faces)."""
        dashpots = self.dashpot_faces(mesh, table)
        if dashpots is None or len(mesh.tets) == 0:
            return math.inf

        def per_tet(attr: str) -> np.ndarray:
            return np.array([getattr(m, attr) for m in table], dtype=np.float64)[mesh.material]

        faces, impedance = dashpots
        return dashpot_critical_step(
            mesh.points,
            mesh.tets,
            {name: per_tet(name) for name in ("mu", "lam", "density", "c_lin", "alpha")},
            faces,
            impedance,
        )

    def build_dashpots(self, mesh: TetMeshData, table: list[kt.TetMaterial], device) -> FaceSet | None:
        dashpots = self.dashpot_faces(mesh, table)
        if dashpots is None:
            return None
        faces, impedance = dashpots
        return FaceSet.create(mesh.points, faces, device, impedance=impedance)

    def build_drivers(self, num_nodes: int, node_capacity: int, device) -> tuple[wp.array | None, wp.array | None]:
        if not self.drivers:
            return None, None
        node_driver = np.full(node_capacity, -1, dtype=np.int32)
        drivers = []
        for k, (ids, v, start, end) in enumerate(self.drivers):
            taken = ids[node_driver[ids] >= 0]
            if len(taken):
                raise ValueError(
                    f"node velocity {k}: node {int(taken[0])} already has node velocity {node_driver[taken[0]]}; "
                    "a node takes one driver"
                )
            node_driver[ids] = k
            d = kl.NodeDriver()
            d.velocity = wp.vec3(*v)
            d.start = start
            d.end = end
            drivers.append(d)
        return (
            wp.array(node_driver, dtype=int, device=device),
            wp.array(drivers, dtype=kl.NodeDriver, device=device),
        )


def roller_axis(points: np.ndarray, faces: np.ndarray) -> int:
    """The axis normal to a set of faces lying in one axis-aligned plane.

    Raises:
        ValueError: the faces do not share one axis-aligned normal.
    """
    x = points[faces]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    axis = int(np.argmax(np.abs(n).sum(axis=0)))
    if not np.allclose(np.abs(n[:, axis]), 1.0, atol=1e-9):
        raise ValueError("roller boundary: its faces are not all normal to one axis; pass normal=")
    return axis


def boundary_face_owners(tets: np.ndarray, faces: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """The tet behind each face, and the face re-ordered so that its normal points out of that tet.

    Args:
        tets: positively oriented tets, (M, 4). faces: node triples, (F, 3).

    Returns:
        oriented faces (F, 3), int32; owner tet of each, (F,).

    Raises:
        ValueError: a face that belongs to no tet, or to two (an interior face).
    """
    tets = np.asarray(tets, dtype=np.int64)
    all_faces = tets[:, TET_FACES].reshape(-1, 3)
    keys = np.concatenate([np.sort(all_faces, axis=1), np.sort(faces, axis=1)])
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    of_tets, of_faces = inverse[: len(all_faces)], inverse[len(all_faces) :]
    count = np.bincount(of_tets, minlength=inverse.max() + 1)
    owner = np.full(len(count), -1, dtype=np.int64)
    owner[of_tets] = np.arange(len(all_faces))
    c = count[of_faces]
    for bad, word in ((c == 0, "is no face of a tet"), (c > 1, "is an interior face (shared by two tets)")):
        if np.any(bad):
            k = int(np.nonzero(bad)[0][0])
            raise ValueError(f"{what}: face {k} {faces[k].tolist()} {word}; a load or boundary needs boundary faces")
    slot = owner[of_faces]
    return all_faces[slot].astype(np.int32), slot // 4


# ----------------------------------------------------------------------------------------------------------------
# Device side


def eval_loads(model: Model, state: State, dt: float | None = None) -> None:
    """Stage 8: add the pressure loads at the state's time and the non-reflecting dashpots at the half-step
    velocity to ``node_f``, booking the load work and the dashpots' dissipation as Verlet does their work: first the
    half ahead of the last evaluation's forces (``node_f_load``, ``node_f_absorbed``; warpdem.stages.integrate
    ``book_half_ahead``), then the half behind the new ones (launches only).

    ``dt`` overrides the model step for the bookkeeping; 0 (the set-up evaluation, or after a pass) books nothing and
    leaves the dashpots out, as the set-up leaves out the integrator's mass-proportional damping; the next step then
    books the half ahead of exactly the forces made here.
    """
    loads = model.loads
    if loads is None:
        return
    m, s = model, state
    dt = m.dt if dt is None else dt
    if loads.pressure:
        if dt > 0.0:
            book_half_ahead(m, s, dt, s.node_f_load, s.node_energy_boundary_work, 1.0)
        else:
            s.node_f_load.zero_()
        add_pressure_forces(
            m,
            s.time,
            s.node_u,
            s.node_q,
            s.node_qd,
            s.node_f,
            s.node_f_load,
            s.node_energy_boundary_work,
            dt,
            SphereArrays(
                s.tet_sphere,
                s.particle_q,
                s.particle_qd,
                s.particle_f,
                s.load_face_force,
                s.load_face_work,
                s.load_face_impulse,
            ),
        )
    if loads.dashpots is not None and dt == 0.0:
        # Set-up or re-evaluation after a pass: the dashpots are left out of these forces, so the next kick does no
        # part of the last ones' work ahead.
        s.node_f_absorbed.zero_()
    if loads.dashpots is not None and dt > 0.0:
        d = loads.dashpots
        book_half_ahead(m, s, dt, s.node_f_absorbed, s.node_energy_absorbed, -1.0)
        wp.launch(
            kl.apply_dashpots_kernel,
            dim=d.count,
            inputs=[
                # Model:
                d.nodes,
                d.edge_a,
                d.edge_b,
                d.impedance,
                dt,
                # State in:
                s.node_u,
                s.node_qd,
            ],
            outputs=[s.node_f, s.node_f_absorbed, s.node_energy_absorbed],
            device=m.device,
        )


def _pressure_face_inputs(model: Model, faces: FaceSet) -> list:
    """The Model inputs every pressure kernel of one history kind starts with (kernels/loads.py): the loaded faces'
    nodes, reference edges and load index, the loads and their tables, the tet behind each face, the area vectors
    handed over to converted tets' spheres and the spheres per tet."""
    loads = model.loads
    return [
        faces.nodes,
        faces.edge_a,
        faces.edge_b,
        faces.index,
        loads.pressure_loads,
        loads.table_times,
        loads.table_values,
        faces.tet,
        faces.handed_area,
        faces.weight,
        faces.first,
        int(model.spheres_per_tet),
    ]


@dataclass
class SphereArrays:
    """The sphere arrays a pressure load's handed-over faces read and push (kernels/loads.py, Hand-over).

    Attributes:
        tet_sphere: first sphere of each converted tet or -1, shape (tet_capacity,), int32 (all -1: no face is
            handed over, the nodes' loads alone).
        particle_q: sphere positions [m], shape (particle_capacity,), vec3d.
        particle_qd: sphere velocities v_{n+1/2} [m/s], vec3.
        particle_f: sphere forces [N], vec3 (written).
        face_force: the handed-over faces' forces kept from the last evaluation [N], shape (loaded faces,), vec3
            (State ``load_face_force``; rewritten).
        face_work: their work [J], shape (loaded faces,), float64 (State ``load_face_work``; added to).
        face_impulse: every loaded face's impulse ∫ p |a| Σw dt [N s], shape (loaded faces,), float64 (State
            ``load_face_impulse``; added to).
    """

    tet_sphere: wp.array
    particle_q: wp.array
    particle_qd: wp.array
    particle_f: wp.array
    face_force: wp.array
    face_work: wp.array
    face_impulse: wp.array


def add_pressure_forces(
    model: Model,
    time: wp.array,
    node_u: wp.array,
    node_q: wp.array,
    node_qd: wp.array,
    node_f: wp.array,
    node_f_load: wp.array,
    node_energy_boundary_work: wp.array,
    dt: float,
    spheres: SphereArrays,
) -> None:
    """Add every pressure load's force at time[0] + dt and the displacements ``node_u`` (positions ``node_q``) to
    ``node_f`` and ``node_f_load`` [N], booking the half of its work behind it against ``node_qd`` into
    ``node_energy_boundary_work`` [J] (none at dt = 0); the handed-over faces' force to ``spheres.particle_f``, kept in
    ``spheres.face_force`` and its work booked into ``spheres.face_work``; arrays shaped as the State's (launches
    only)."""
    loads = model.loads
    for kind, faces in loads.pressure.items():
        wp.launch(
            kl.make_face_pressure_kernel(kind),
            dim=faces.count,
            inputs=[
                # Model:
                *_pressure_face_inputs(model, faces),
                dt,
                # The float64 step, so that t_n + dt is the clock's own next value (kernels/integrate.py).
                wp.float64(dt),
                # State in:
                time,
                node_u,
                node_q,
                node_qd,
                spheres.tet_sphere,
                spheres.particle_q,
                spheres.particle_qd,
            ],
            outputs=[
                node_f,
                node_f_load,
                node_energy_boundary_work,
                spheres.particle_f,
                spheres.face_force,
                spheres.face_work,
                spheres.face_impulse,
            ],
            device=model.device,
        )


def pressure_node_forces(model: Model, time: float, node_u: np.ndarray, node_q: np.ndarray) -> np.ndarray:
    """The pressure loads' forces on each node [N], shape (node_capacity, 3), float32, at ``time`` [s] and the
    displacements ``node_u`` and positions ``node_q`` (shape (node_capacity, 3)): what an evaluation there keeps in
    ``node_f_load``, accumulated in the same order (allocates and reads back; a restart from a checkpoint that lacks
    them, warpdem.runner). Faces handed over to spheres are left out (no tet has spheres here): such a checkpoint's
    run had no hand-over."""
    d = model.device
    n = model.node_capacity
    f_load = wp.zeros(n, dtype=wp.vec3, device=d)
    if model.loads is not None and model.loads.pressure:
        one = wp.zeros(1, dtype=wp.vec3, device=d)
        no_tet_spheres = wp.full(max(model.tet_capacity, 1), -1, dtype=int, device=d)
        faces = sum(f.count for f in model.loads.pressure.values())
        no_spheres = SphereArrays(
            no_tet_spheres,
            wp.zeros(1, dtype=wp.vec3d, device=d),
            one,
            one,
            wp.zeros(faces, dtype=wp.vec3, device=d),
            wp.zeros(faces, dtype=wp.float64, device=d),
            wp.zeros(faces, dtype=wp.float64, device=d),
        )
        add_pressure_forces(
            model,
            wp.array([time], dtype=wp.float64, device=d),
            wp.array(np.asarray(node_u, dtype=np.float32), dtype=wp.vec3, device=d),
            wp.array(np.asarray(node_q, dtype=np.float32), dtype=wp.vec3, device=d),
            wp.zeros(n, dtype=wp.vec3, device=d),
            wp.zeros(n, dtype=wp.vec3, device=d),
            f_load,
            wp.zeros(n, dtype=wp.float64, device=d),
            0.0,
            no_spheres,
        )
    return f_load.numpy()


def load_forces(model: Model, state: State) -> tuple[list[str], np.ndarray]:
    """Names and total forces of the pressure loads now [N], shape (L, 3), float64: -p a summed over each load's
    faces at the state's time and positions. Allocates and reads back: call between steps."""
    loads = model.loads
    if loads is None or loads.pressure_loads is None:
        return [], np.zeros((0, 3))
    out = wp.zeros(len(loads.pressure_names), dtype=wp.vec3d, device=model.device)
    for kind, faces in loads.pressure.items():
        wp.launch(
            kl.make_load_force_kernel(kind),
            dim=faces.count,
            inputs=[
                # Model:
                *_pressure_face_inputs(model, faces),
                # State in:
                state.time,
                state.node_u,
                state.node_q,
                state.tet_sphere,
                state.particle_q,
            ],
            outputs=[out],
            device=model.device,
        )
    return list(loads.pressure_names), out.numpy().reshape(-1, 3).astype(np.float64)


@dataclass(frozen=True)
class PressureAmplitudes:
    """The amplitudes of a model's pressure loads, as :func:`scale_pressure_loads` scales them.

    Attributes:
        peak: each load's peak pressure [Pa] (blast, Friedlander; unused by a table), shape (L,), float32.
        table_values: the pressures of every table [Pa], concatenated, float32.
        table_slices: the (first, count) of each load's entries in ``table_values`` (count 0 but for a table).
    """

    peak: np.ndarray
    table_values: np.ndarray
    table_slices: tuple[tuple[int, int], ...]


def pressure_amplitudes(model: Model) -> PressureAmplitudes | None:
    """The amplitudes of the model's pressure loads now (reads back), None without pressure loads."""
    loads = model.loads
    if loads is None or loads.pressure_loads is None:
        return None
    params = loads.pressure_loads.numpy()
    return PressureAmplitudes(
        peak=params["peak"].copy(),
        table_values=loads.table_values.numpy().copy(),
        table_slices=tuple((int(a), int(b)) for a, b in zip(params["table_first"], params["table_count"], strict=True)),
    )


def scale_pressure_loads(model: Model, base: PressureAmplitudes, scales: Sequence[float]) -> None:
    """Set every pressure load's amplitude to its ``scales`` [-] times ``base``, from the next step on (between
    steps). The arrays are written in place, so a captured step reads the new values without a re-capture.

    The books stay exact: the load kernels book the work of the forces they apply (the half behind each new force,
    the half ahead of the kept one, kernels/loads.py), so a force made at the old amplitude is booked at it and the
    next at the new one. Each scaled value is rounded to float32 once from the base (a power-of-two scale is exact).

    Args:
        model: the model whose ``loads`` are changed.
        base: the amplitudes the scales refer to (:func:`pressure_amplitudes` of the model as built).
        scales: one scale per pressure load, index = load id (``loads.pressure_names``).

    Raises:
        ValueError: the model has no pressure loads, or not one scale per load.
    """
    loads = model.loads
    if loads is None or loads.pressure_loads is None:
        raise ValueError("scale_pressure_loads: the model has no pressure loads")
    scales = np.asarray(scales, dtype=np.float64)
    if scales.shape != base.peak.shape:
        raise ValueError(f"scale_pressure_loads: {len(base.peak)} loads, got {scales.shape} scales")
    params = loads.pressure_loads.numpy().copy()
    params["peak"] = (base.peak.astype(np.float64) * scales).astype(np.float32)
    values = base.table_values.astype(np.float64)
    for k, (first, count) in enumerate(base.table_slices):
        values[first : first + count] *= scales[k]
    loads.pressure_loads.assign(params)
    if len(values):
        loads.table_values.assign(values.astype(np.float32))


def load_work(state: State) -> float:
    """Work done since the start by pressure loads and velocity drivers on the FEM nodes, and by the pressure loads
    handed over to converted tets' spheres [J] (reads back)."""
    return float(state.node_energy_boundary_work.numpy().sum()) + float(state.load_face_work.numpy().sum())


# ----------------------------------------------------------------------------------------------------------------
# Geostatic initial state


def default_relaxation_damping(model: Model) -> float:
    """Mass-proportional damping α [1/s] for dynamic relaxation: 2ω₁ (critical) for ω₁ = π c_s / (2 L), the
    lowest shear mode of a body of the model's largest extent L [m] fixed at one end, c_s the slowest shear speed of
    its tet materials."""
    table = model.tet_material_table.numpy()
    used = np.unique(model.tet_material.numpy()[: model.tet_capacity])
    speeds = [math.sqrt(table[m]["mu"] / table[m]["density"]) for m in used if table[m]["density"] > 0.0]
    x = model.node_ref_q.numpy()[: model.node_capacity]
    extent = float(np.ptp(x, axis=0).max()) if len(x) else 0.0
    if not speeds or extent <= 0.0:
        raise ValueError("dynamic relaxation needs tets with a material and a body of non-zero extent")
    return math.pi * min(speeds) / extent


def relax_to_equilibrium(
    sim,
    *,
    damping: float | None = None,
    tolerance: float = 1.0e-6,
    max_steps: int = 100_000,
    check_every: int = 100,
) -> int:
    """Bring the FEM nodes to static equilibrium under gravity and their supports by damped dynamic relaxation, so
    that dynamics starts from the geostatic stress.

    The step runs with mass-proportional damping α on every node and without the loads of this stage (pressures,
    velocity drivers, dashpots: they are time-dependent or would let the body sink), so the model needs its fixed or
    roller supports. It stops when the nodes' kinetic energy has fallen below ``tolerance`` times the strain energy.
    Then the model's damping and loads are restored, the node velocities zeroed, the dissipation booked meanwhile
    forgotten, the clock set back and the forces evaluated afresh: the energy balance starts from the relaxed state.
    The relaxation steps do not count as simulated time. Spheres, if any, step along undamped (this is a relaxation
    of the continuum). Between steps only; reads back every ``check_every`` steps.

    Args:
        sim (warpdem.simulation.Simulation): the Simulation to relax (its state changes in place).
        damping: α [1/s]; default :func:`default_relaxation_damping`.
        tolerance: kinetic / strain energy at which it stops [-].
        max_steps: the most steps it runs.
        check_every: steps between convergence checks.

    Returns:
        The number of relaxation steps run.

    Raises:
        RuntimeError: no convergence within ``max_steps``.
    """
    m, s = sim.model, sim.state
    if m.node_capacity == 0:
        return 0
    alpha = default_relaxation_damping(m) if damping is None else float(damping)
    saved_damping = wp.clone(m.node_damping)
    saved_loads = m.loads
    m.node_damping.fill_(alpha)
    m.loads = None
    steps = 0
    mass = m.node_mass.numpy().astype(np.float64)
    try:
        while True:
            # One by one, not through the captured graph: the graph holds the loads this relaxation leaves out.
            for _ in range(check_every):
                sim.step()
            steps += check_every
            v = s.node_qd.numpy().astype(np.float64)
            kinetic = 0.5 * float(mass @ np.sum(v * v, axis=1))
            strain = sim.energy().strain
            if kinetic <= tolerance * strain:
                break
            if steps >= max_steps:
                raise RuntimeError(
                    f"dynamic relaxation did not converge in {steps} steps: kinetic / strain energy "
                    f"{kinetic / max(strain, 1e-300):.3g} > {tolerance} (raise max_steps or damping = {alpha:.4g} 1/s)"
                )
    finally:
        wp.copy(m.node_damping, saved_damping)
        m.loads = saved_loads
    s.node_qd.zero_()
    s.node_energy_damping.zero_()
    s.node_energy_absorbed.zero_()
    s.node_f_absorbed.zero_()
    s.time.fill_(sim.time)
    sim.evaluate_forces()
    return steps


def dashpot_critical_step(
    points: np.ndarray,
    tets: np.ndarray,
    tet_props: dict[str, np.ndarray],
    faces: np.ndarray,
    impedance: np.ndarray,
    moving: np.ndarray | None = None,
) -> float:
    """Stable step [s] of the nodes with dashpots (inf without any), before the safety factor.

    A node of mass m under a dashpot C (Σ a third of each adjacent face's area times ρ c_p) and the stiffness of
    its tets is a damped oscillator; the explicit dashpot (at the half-step velocity) is stable for
    dt ≤ (2/ω)(sqrt(1 + ζ²) - ζ). ω is bounded by the largest element frequency of its tets (2/dt_e without
    viscosity, warpdem.stages.tets.tet_stable_time_steps), and ζ = C / (2 m ω) plus the largest viscous damping ratio
    of those tets. On a Kuhn box mesh the corner nodes of the faces (mass ρ V_cell / 24) set the step; the
    bound was found about 20 % below the step at which a dashpot column starts to blow up.

    Args:
        points: reference node positions [m], (N, 3).
        tets: the tets that give the nodes their mass and stiffness, (M, 4).
        tet_props: ``mu``, ``lam`` [Pa], ``density`` [kg/m³], ``c_lin`` [-] and ``alpha`` [1/s] per tet, (M,) each
            (kernels/tets.py TetMaterial).
        faces: the dashpot faces' nodes, (F, 3).
        impedance: their ρ c_p and ρ c_s [Pa s/m], (F, 2).
        moving: bool per node, the nodes whose step counts (None: every node; the nodes of rigid blocks have the
            bodies' step instead, warpdem.stages.rigid).
    """
    if len(faces) == 0 or len(tets) == 0:
        return math.inf
    points = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(points)
    x = points[faces]
    third = np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1) / 6.0
    coefficient = np.bincount(faces.ravel(), weights=np.repeat(third * impedance.max(axis=1), 3), minlength=n)
    inv_ref, volume = reference_geometry(points, tets)
    mu, lam, density = tet_props["mu"], tet_props["lam"], tet_props["density"]
    undamped = tet_stable_time_steps(inv_ref, mu, lam, density, np.zeros(len(mu)))
    damped = tet_stable_time_steps(inv_ref, mu, lam, density, tet_props["c_lin"], tet_props["alpha"])
    # Back from (2/ω)(sqrt(1 + ζ²) - ζ) = r (2/ω) to the element's damping ratio ζ = (1 - r²) / (2r).
    r = damped / undamped
    nodes = np.asarray(tets, dtype=np.int64).ravel()
    omega, zeta_tets = np.zeros(n), np.zeros(n)
    np.maximum.at(omega, nodes, np.repeat(2.0 / undamped, 4))
    np.maximum.at(zeta_tets, nodes, np.repeat((1.0 - r**2) / (2.0 * r), 4))
    mass, _ = lumped_node_masses(n, tets, volume, density, np.zeros(len(mu)))
    held = (coefficient > 0.0) & (mass > 0.0) & (omega > 0.0)
    if moving is not None:
        held &= np.asarray(moving, dtype=bool)
    if not held.any():
        return math.inf
    w = omega[held]
    zeta = coefficient[held] / (2.0 * mass[held] * w) + zeta_tets[held]
    return float(np.min(2.0 / w * (np.sqrt(1.0 + zeta**2) - zeta)))
