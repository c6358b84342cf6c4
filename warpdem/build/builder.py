"""Building a Model and its initial State from Python (:class:`ModelBuilder`); a scene file goes through
:func:`warpdem.build.scene_build.build_scene`, which fills a ModelBuilder.

Everything here runs once, on the host, before the first step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..host_data import BondData, ParticleData, TetMeshData, WallData
from ..kernels.contact import ContactPair
from ..kernels.tets import TetMaterial
from ..load_data import LoadModel
from ..materials import InteractionProps, MaterialProps, effective_moduli
from ..model import Model, State, pair_table_array
from ..stages.bonds import bond_critical_step, bonded_group_bonds, sphere_masses
from ..stages.contact import sphere_contact_steps
from ..stages.fem_contact import attach_fem_contact, contact_critical_step_at
from ..stages.guard import CriticalStep, check_time_step, p_wave_speed, reach_step, run_away_speed
from ..stages.joints import JointData, JointProps, count_split_nodes
from ..stages.loads import LoadSpecs
from ..stages.ordering import NODE_ORDERS, morton_order
from ..stages.pressure import PressureHistory
from ..stages.restitution import hertz_damping_coefficient, linear_damping_ratio
from ..stages.tets import (
    TetProps,
    characteristic_lengths,
    lumped_node_masses,
    reference_geometry,
    tet_material,
    tet_stable_time_steps,
)
from .initial_state import new_state
from .mesh import MeshQuality, check_tets
from .overlap import InitialOverlap, initial_overlap

MOTIONS = {"free": 0, "fixed": 1, "prescribed": 2}
NODE_MOTIONS = {"free": 0, "fixed": 1, "z_only": 2}


@dataclass
class ModelBuilder:
    """Collects materials, spheres, walls and bonds, then allocates a Model and State on a device.

    Args:
        normal: normal contact law, "hertz" or "linear".
        tangential: tangential law, "mindlin" or "linear".
        rolling: rolling resistance, "none" or "constant_torque".
        gravity: gravitational acceleration [m/s²].
        contact_stiffness_factor: penalty factor f of the FEM contact faces that are no joint faces [-] (a spring of
            f E / h per unit area, E and h of the tet behind the face).
        contact_normal_stiffness: instead, a normal stiffness k_n per unit area of those faces [Pa/m], independent of
            the mesh (k_n / 2 on each face: two of them pressed together close by σ / k_n, as a joint's
            ``normal_stiffness``); None to use ``contact_stiffness_factor``.
    """

    normal: str = "hertz"
    tangential: str = "mindlin"
    rolling: str = "none"
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    materials: dict[str, MaterialProps] = field(default_factory=dict)
    interactions: dict[tuple[str, str], InteractionProps] = field(default_factory=dict)
    default_interaction: InteractionProps = field(default_factory=InteractionProps)
    parts: list[str] = field(default_factory=list)
    _spheres: list[tuple] = field(default_factory=list)
    _walls: list[tuple] = field(default_factory=list)
    _bond_groups: list[tuple] = field(default_factory=list)
    tet_props: dict[str, TetProps] = field(default_factory=dict)
    mesh_qualities: list[MeshQuality] = field(default_factory=list)
    _tet_meshes: list[tuple] = field(default_factory=list)
    joint_sets: list[JointProps] = field(default_factory=list)
    joint_set_names: list[str] = field(default_factory=list)
    _joint_faces: list[tuple] = field(default_factory=list)
    contact_stiffness_factor: float = 1.0
    contact_normal_stiffness: float | None = None
    load_specs: LoadSpecs = field(default_factory=LoadSpecs)
    overlap: InitialOverlap | None = None

    # -- materials and interactions ---------------------------------------------------------------------------
    def add_material(self, name: str, density: float, youngs_modulus: float, poisson_ratio: float) -> int:
        """Add a material; returns its id."""
        self.materials[name] = MaterialProps(density, youngs_modulus, poisson_ratio)
        return list(self.materials).index(name)

    def set_tet_properties(self, material: str, props: TetProps) -> None:
        """Continuum properties (bulk viscosity, mass-proportional damping) of a material's tets; default TetProps."""
        if material not in self.materials:
            raise KeyError(f"unknown material {material!r}")
        self.tet_props[material] = props

    def set_interaction(self, a: str, b: str, props: InteractionProps) -> None:
        """Contact properties of the pair (a, b), order-free."""
        self.interactions[tuple(sorted((a, b)))] = props

    def interaction(self, a: str, b: str) -> InteractionProps:
        return self.interactions.get(tuple(sorted((a, b))), self.default_interaction)

    def part_id(self, part: str) -> int:
        if part not in self.parts:
            self.parts.append(part)
        return self.parts.index(part)

    # -- bodies ------------------------------------------------------------------------------------------------
    def add_spheres(
        self,
        centers: np.ndarray,
        radii: np.ndarray | float,
        material: str,
        *,
        velocity: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
        angular_velocity: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
        motion: str = "free",
        part: str = "default",
    ) -> np.ndarray:
        """Add spheres; returns their ids.

        Args:
            centers: [m], shape (N, 3).
            radii: [m], scalar or (N,).
            material: material name.
            velocity: [m/s], shape (3,) or (N, 3).
            angular_velocity: [rad/s], shape (3,) or (N, 3).
            motion: "free", "fixed" (never moves; velocity and spin are ignored) or "prescribed" (keeps its
                velocity and spin).
            part: part name (for colouring and output).
        """
        centers = np.atleast_2d(np.asarray(centers, dtype=np.float64))
        n = len(centers)
        radii = np.broadcast_to(np.asarray(radii, dtype=np.float64), (n,))
        vel = np.broadcast_to(np.asarray(velocity, dtype=np.float64), (n, 3))
        omega = np.broadcast_to(np.asarray(angular_velocity, dtype=np.float64), (n, 3))
        if motion == "fixed":
            # A fixed sphere never moves: whatever velocity it was given is dropped (use "prescribed" to drive it).
            vel, omega = np.zeros((n, 3)), np.zeros((n, 3))
        if material not in self.materials:
            raise KeyError(f"unknown material {material!r}")
        first = self.sphere_count
        self._spheres.append(
            (centers, radii.copy(), vel.copy(), omega.copy(), material, MOTIONS[motion], self.part_id(part))
        )
        return np.arange(first, first + n)

    def add_sphere(self, center: Sequence[float], radius: float, material: str, **kwargs) -> int:
        """Add one sphere (keyword arguments as :meth:`add_spheres`); returns its id."""
        return int(self.add_spheres(np.asarray([center]), radius, material, **kwargs)[0])

    @property
    def sphere_count(self) -> int:
        return sum(len(s[0]) for s in self._spheres)

    def add_tet_mesh(
        self,
        points: np.ndarray,
        tets: np.ndarray,
        material: str | Sequence[str],
        *,
        fixed_nodes: np.ndarray | None = None,
        z_only_nodes: np.ndarray | None = None,
        velocity: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
        joint_faces: np.ndarray | None = None,
        joint_set: int | np.ndarray = 0,
    ) -> np.ndarray:
        """Add a body of Cosserat point tetrahedra; returns the ids of its nodes.

        The mesh is checked first (:func:`warpdem.build.mesh.check_tets`): inverted tets are re-oriented, degenerate
        ones rejected; its quality summary is appended to ``mesh_qualities``.

        Args:
            points: node positions [m], shape (N, 3).
            tets: node indices into ``points``, shape (M, 4).
            material: material name (density, E, ν; bulk viscosity from :meth:`set_tet_properties`), or one name
                per tet (a layered rock mass).
            fixed_nodes: indices (or a boolean mask) of nodes held in place.
            z_only_nodes: indices (or a boolean mask) of nodes that move along z only (x and y held).
            velocity: initial node velocities [m/s], shape (3,) or (N, 3); held components are zeroed.
            joint_faces: faces of the mesh that lie on joints, node triples into ``points``, shape (J, 3) (e.g.
                warpdem.build.geology.GeologyMesh.joint_faces): their nodes are split at :meth:`finalize` so that the
                rock on either side is separate, touching through the joint (warpdem.stages.joints). A split node's
                copies keep its motion kind (a fixed node is fixed on every side).
            joint_set: joint set of the faces (:meth:`add_joint_set`), one id or one per face, shape (J,).

        Raises:
            KeyError: unknown material or joint set. warpdem.build.mesh.MeshError: a bad mesh.
        """
        per_tet = np.asarray([material] * len(tets) if isinstance(material, str) else material, dtype=str)
        unknown = sorted(set(per_tet.tolist()) - set(self.materials))
        if unknown or len(per_tet) != len(tets):
            raise KeyError(f"unknown material {unknown[0]!r}" if unknown else "need one material name per tet")
        points = np.asarray(points, dtype=np.float64)
        oriented, quality = check_tets(points, tets)
        n = len(points)
        motion = np.zeros(n, dtype=np.int32)
        for kind, nodes in (("z_only", z_only_nodes), ("fixed", fixed_nodes)):
            if nodes is not None:
                motion[np.arange(n)[np.asarray(nodes)]] = NODE_MOTIONS[kind]
        vel = np.broadcast_to(np.asarray(velocity, dtype=np.float64), (n, 3)).copy()
        vel[motion == NODE_MOTIONS["fixed"]] = 0.0
        vel[motion == NODE_MOTIONS["z_only"], :2] = 0.0
        first = self.node_count
        if joint_faces is not None and len(joint_faces):
            faces = np.asarray(joint_faces, dtype=np.int64).reshape(-1, 3)
            sets = np.broadcast_to(np.asarray(joint_set, dtype=np.int64), (len(faces),)).copy()
            if np.any((sets < 0) | (sets >= len(self.joint_sets))):
                raise KeyError(f"unknown joint set in {np.unique(sets).tolist()}: add it with add_joint_set first")
            if np.any((faces < 0) | (faces >= n)):
                raise KeyError("joint_faces: a node index is out of range")
            self._joint_faces.append((faces + first, sets))
        self._tet_meshes.append((points.copy(), vel, motion, oriented, per_tet))
        self.mesh_qualities.append(quality)
        return np.arange(first, first + n)

    @property
    def node_count(self) -> int:
        return sum(len(m[0]) for m in self._tet_meshes)

    def add_joint_set(self, props: JointProps, name: str | None = None) -> int:
        """A joint set (friction, cohesion, tensile strength, penalty stiffness); returns its id for
        :meth:`add_tet_mesh`'s ``joint_set``."""
        self.joint_sets.append(props)
        self.joint_set_names.append(name or f"joint{len(self.joint_sets) - 1}")
        return len(self.joint_sets) - 1

    def joint_data(self) -> JointData:
        """The joint faces of every mesh added, in global node ids, with their joint sets."""
        if not self._joint_faces:
            return JointData.empty()
        return JointData(
            faces=np.concatenate([f for f, _ in self._joint_faces]).astype(np.int32),
            face_set=np.concatenate([k for _, k in self._joint_faces]).astype(np.int32),
        )

    def _surface_spring(self) -> tuple[float, float]:
        """(penalty factor f, k_n / 2 [Pa/m]) of the faces that are no joint faces: ``contact_normal_stiffness`` k_n,
        when given, replaces ``contact_stiffness_factor`` (the spring is then k_n / 2 per unit area on each face, as a
        joint's: warpdem.stages.joints.JointProps.normal_stiffness)."""
        if self.contact_normal_stiffness is None:
            return self.contact_stiffness_factor, 0.0
        if not self.contact_normal_stiffness > 0.0:
            raise ValueError(
                f"ModelBuilder.contact_normal_stiffness must be > 0 [Pa/m], got {self.contact_normal_stiffness}"
            )
        return 0.0, 0.5 * self.contact_normal_stiffness

    def contact_critical_time_step(self, mesh: TetMeshData) -> float:
        """Stable step of the FEM contacts and joints [s] before the safety factor (:meth:`contact_critical_step`)."""
        return self.contact_critical_step(mesh).value

    def contact_critical_step(self, mesh: TetMeshData) -> CriticalStep:
        """Stable step of the FEM contacts and joints [s] before the safety factor
        (:func:`warpdem.stages.fem_contact.contact_critical_step_at`), and the node that sets it. inf where no FEM
        contact can engage at the start: no tets, or one tet body without joints, walls or spheres (a crack opened at
        run time brings its own contacts, and the fracture stage its own step)."""
        joints = self.joint_data()
        if len(mesh.tets) == 0 or not (len(joints) or self._walls or self._spheres or len(self._tet_meshes) > 1):
            return CriticalStep(math.inf, "no FEM contact")
        table = self.tet_material_table()
        young = np.array([m.mu * (3.0 * m.lam + 2.0 * m.mu) / max(m.lam + m.mu, 1e-30) for m in table])
        density = np.array([m.density for m in table], dtype=np.float64)
        zeta = [p.damping_ratio for p in self.joint_sets]
        names = list(self.materials)
        zeta += [linear_damping_ratio(self.interaction(a, b).restitution) for a in names for b in names]
        factor, face_normal_stiffness = self._surface_spring()
        step, node, joint_set = contact_critical_step_at(
            mesh.points,
            mesh.tets,
            young[mesh.material],
            density[mesh.material],
            joints,
            self.joint_sets,
            factor,
            max(zeta),
            face_normal_stiffness,
        )
        where = f"joint set {self.joint_set_names[joint_set]}" if joint_set >= 0 else "the rock surface"
        return CriticalStep(step, f"the contact penalty springs of {where} at mesh node {node}")

    def tet_mesh_data(self) -> TetMeshData:
        """All tet meshes added so far, concatenated (node indices offset accordingly)."""
        if not self._tet_meshes:
            return TetMeshData.empty()
        names = list(self.materials)
        offsets = np.cumsum([0] + [len(m[0]) for m in self._tet_meshes])[:-1]
        mesh = TetMeshData(
            points=np.concatenate([m[0] for m in self._tet_meshes]),
            velocity=np.concatenate([m[1] for m in self._tet_meshes]),
            motion=np.concatenate([m[2] for m in self._tet_meshes]),
            tets=np.concatenate([m[3] + off for m, off in zip(self._tet_meshes, offsets, strict=True)]),
            material=np.concatenate(
                [np.array([names.index(n) for n in m[4]], dtype=np.int32) for m in self._tet_meshes]
            ),
        )
        # Fixed and roller boundaries (add_boundary) add to the held axes of their nodes.
        return self.load_specs.constrain(mesh)

    def tet_material_table(self) -> list[TetMaterial]:
        """The TetMaterial of every material, index = material id (zeros for materials no tet uses)."""
        used = {name for m in self._tet_meshes for name in np.unique(m[4]).tolist()}
        return [
            tet_material(p.density, p.youngs_modulus, p.poisson_ratio, self.tet_props.get(name, TetProps()))
            if name in used
            else TetMaterial()
            for name, p in self.materials.items()
        ]

    def tet_critical_time_step(self, mesh: TetMeshData) -> float:
        """Critical time step of the tets [s] before the safety factor (:meth:`tet_critical_step`)."""
        return self.tet_critical_step(mesh).value

    def tet_critical_step(self, mesh: TetMeshData) -> CriticalStep:
        """Critical time step of the tets [s] before the safety factor
        (:func:`warpdem.stages.tets.tet_stable_time_steps`; inf without tets), and the tet that sets it."""
        if len(mesh.tets) == 0:
            return CriticalStep(math.inf, "no tet")
        table = self.tet_material_table()
        inv_ref, _ = reference_geometry(mesh.points, mesh.tets)

        def per_tet(attr: str) -> np.ndarray:
            return np.array([getattr(table[m], attr) for m in range(len(table))], dtype=np.float64)[mesh.material]

        steps = tet_stable_time_steps(
            inv_ref, per_tet("mu"), per_tet("lam"), per_tet("density"), per_tet("c_lin"), per_tet("alpha")
        )
        k = int(np.argmin(steps))
        return CriticalStep(float(steps[k]), f"tet {k} of material {list(self.materials)[mesh.material[k]]}")

    def add_plane_wall(
        self, point: Sequence[float], normal: Sequence[float], material: str, velocity: Sequence[float] = (0, 0, 0)
    ) -> None:
        """A rigid plane; ``normal`` points into the domain (spheres live on its + side)."""
        n = np.asarray(normal, dtype=np.float64)
        self._walls.append(
            (np.asarray(point, dtype=np.float64), n / np.linalg.norm(n), np.asarray(velocity, float), material)
        )

    def add_box_walls(self, lo: Sequence[float], hi: Sequence[float], material: str, open_top: bool = False) -> None:
        """The inner faces of an axis-aligned box (without the +z face if ``open_top``)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        for axis in range(3):
            e = np.eye(3)[axis]
            self.add_plane_wall(lo, e, material)
            if not (open_top and axis == 2):
                self.add_plane_wall(hi, -e, material)

    def add_bonded_group(
        self,
        ids: np.ndarray,
        *,
        youngs_modulus: float,
        tensile_strength: float,
        shear_strength: float,
        stiffness_ratio: float = 2.5,
        radius_factor: float = 1.0,
        gap_tolerance: float = 0.05,
        damping_ratio: float = 0.0,
    ) -> None:
        """Bond every pair of the given spheres whose gap is at most ``gap_tolerance (r_i + r_j)`` (at finalize).

        Bond stiffness k_n = E_b A / L_0 with A = π (radius_factor · min(r_i, r_j))², k_s = k_n / stiffness_ratio;
        strengths in [Pa]; ``damping_ratio`` ζ of the bond dashpots.
        """
        props = (
            youngs_modulus,
            tensile_strength,
            shear_strength,
            stiffness_ratio,
            radius_factor,
            gap_tolerance,
            damping_ratio,
        )
        self._bond_groups.append((np.asarray(ids, dtype=np.int64), props))

    # -- loads and boundaries ----------------------------------------------------------------------------------
    def add_face_pressure(
        self, faces: np.ndarray, history: PressureHistory, name: str = "", weights: np.ndarray | None = None
    ) -> None:
        """A pressure history on a set of boundary faces (stage 8, :mod:`warpdem.stages.loads`).

        Args:
            faces: node ids (as returned by :meth:`add_tet_mesh`) of the loaded faces, shape (F, 3); each must be a
                boundary face of one tet, and is re-ordered to point out of it. The pressure pushes into the rock.
            history: p(t, x), e.g. ``PressureHistory.blast(peak, rise_time, decay_time)``.
            name: a name for reports (default: kind and index).
            weights: the share of each face's force -p a each of its nodes takes [-], shape (F, 3), in ``faces``'
                node order, each row ≥ 0 and summing to the share of the face loaded (None: a third each, the whole
                face; :func:`warpdem.build.face_cover.face_cover_weights` makes them for a region that covers part of
                a face).

        Raises:
            ValueError: bad faces or history (faces that are no boundary faces are found at :meth:`finalize`).
        """
        self.load_specs.add_face_pressure(faces, history, name, weights)

    def add_node_velocity(
        self, nodes: np.ndarray, velocity: Sequence[float], start: float = 0.0, end: float = math.inf
    ) -> None:
        """Prescribe the velocity of a node set [m/s] while start ≤ t < end [s] (an impact, a moving support); the
        nodes are free (or as constrained) outside that window. The driver's work is booked in the energy balance.

        Args:
            nodes: node ids or a boolean mask over them, shape (K,). velocity: shape (3,).

        Raises:
            ValueError: bad ids, velocity or window; a node with two drivers (at :meth:`finalize`).
        """
        self.load_specs.add_node_velocity(nodes, velocity, start, end)

    def add_boundary(self, faces_or_nodes: np.ndarray, kind: str, *, normal: Sequence[float] | None = None) -> None:
        """A boundary condition on faces (F, 3) or nodes (K,) (ids or a mask) of the tet meshes.

        Args:
            faces_or_nodes: node ids of faces, shape (F, 3), or of nodes, shape (K,).
            kind: "fixed" (the nodes never move), "roller" (the nodes move only in the plane normal to ``normal``,
                an axis; on faces it defaults to their common normal) or "non_reflecting" (Lysmer–Kuhlemeyer
                dashpots on boundary faces, with ρ, c_p, c_s of the tet behind each: outgoing waves leave the model).
            normal: roller only: ±x, ±y or ±z as a 3-vector.

        Raises:
            ValueError: an unknown kind, a normal that is not axis-aligned, non-reflecting nodes without faces.
        """
        self.load_specs.add_boundary(faces_or_nodes, kind, normal)

    def load_model(self, mesh: TetMeshData, tet_arrays: dict, device: wp.context.Device) -> LoadModel | None:
        """The device-side loads and dashpots (None when none were added); ``tet_arrays`` from
        :meth:`tet_model_arrays`."""
        if not self.load_specs:
            return None
        return self.load_specs.build(mesh, self.tet_material_table(), tet_arrays["node_capacity"], device)

    # -- finalize ----------------------------------------------------------------------------------------------
    def measure_initial_overlap(self, device: wp.context.DeviceLike = None) -> InitialOverlap:
        """Spheres that start overlapping each other or the rock (:func:`warpdem.build.overlap.initial_overlap`), sphere
        ids in creation order; also kept as ``overlap``. :meth:`finalize` does not refuse overlaps (tests and scripts
        start contacts pre-loaded on purpose); scenes do (:func:`warpdem.build.scene_build.finalize_scene`)."""
        particles, mesh = self.particle_data(), self.tet_mesh_data()
        free = particles.motion == MOTIONS["free"]
        self.overlap = initial_overlap(particles.q, particles.radius, free, mesh.points, mesh.tets, device)
        return self.overlap

    def particle_data(self) -> ParticleData:
        if not self._spheres:
            z = np.zeros((0, 3))
            return ParticleData(z, z, z, np.zeros(0), np.zeros(0, int), np.zeros(0, int), np.zeros(0, int))
        names = list(self.materials)
        return ParticleData(
            q=np.concatenate([s[0] for s in self._spheres]),
            qd=np.concatenate([s[2] for s in self._spheres]),
            omega=np.concatenate([s[3] for s in self._spheres]),
            radius=np.concatenate([s[1] for s in self._spheres]),
            material=np.concatenate([np.full(len(s[0]), names.index(s[4])) for s in self._spheres]),
            motion=np.concatenate([np.full(len(s[0]), s[5]) for s in self._spheres]),
            part=np.concatenate([np.full(len(s[0]), s[6]) for s in self._spheres]),
        )

    def wall_data(self) -> WallData:
        names = list(self.materials)
        w = self._walls
        return WallData(
            point=np.array([x[0] for x in w]).reshape(-1, 3),
            normal=np.array([x[1] for x in w]).reshape(-1, 3),
            velocity=np.array([x[2] for x in w]).reshape(-1, 3),
            material=np.array([names.index(x[3]) for x in w], dtype=np.int32),
        )

    def pair_table(self) -> list[list[ContactPair]]:
        names = list(self.materials)
        table = []
        for a in names:
            row = []
            for b in names:
                ma, mb = self.materials[a], self.materials[b]
                inter = self.interaction(a, b)
                estar, gstar = effective_moduli(ma, mb)
                nu = 0.5 * (ma.poisson_ratio + mb.poisson_ratio)
                p = ContactPair()
                p.estar = estar
                p.gstar = gstar
                p.young_a = ma.youngs_modulus
                p.young_b = mb.youngs_modulus
                p.kt_ratio = 2.0 * (1.0 - nu) / (2.0 - nu)
                p.friction = inter.friction
                p.rolling = inter.rolling_friction
                e = inter.restitution
                p.damp_n = hertz_damping_coefficient(e) if self.normal == "hertz" else linear_damping_ratio(e)
                p.damp_t = linear_damping_ratio(e)
                row.append(p)
            table.append(row)
        return table

    def bond_data(self, particles: ParticleData, device: wp.context.Device) -> BondData:
        """Bonds of every bonded group (:func:`warpdem.stages.bonds.bonded_group_bonds`)."""
        return bonded_group_bonds(self._bond_groups, particles, device)

    def critical_time_step(self, particles: ParticleData, bonds: BondData, mesh: TetMeshData | None = None) -> float:
        """Critical time step [s] before the safety factor (:meth:`critical_step`)."""
        return self.critical_step(particles, bonds, mesh).value

    def critical_step(self, particles: ParticleData, bonds: BondData, mesh: TetMeshData | None = None) -> CriticalStep:
        """Critical time step [s] before the safety factor, and what sets it: the smallest of the Rayleigh step
        (Hertz) or 2 sqrt(m*/k_n) (linear) of every sphere size and material, the Hertz contact time at the fastest
        initial approach / 10, the bond step (:func:`bond_critical_step`), the tet step (:meth:`tet_critical_step`,
        of ``mesh`` or of the meshes added), the step of the nodes under non-reflecting dashpots
        (:meth:`warpdem.stages.loads.LoadSpecs.critical_time_step`), the step of the FEM contact and joint penalty
        springs (:meth:`contact_critical_step`) and the step at which the fastest launched body moves REACH_FRACTION
        of the smallest contact reach (:func:`warpdem.stages.guard.reach_step`)."""
        names = list(self.materials)
        free = particles.motion == 0
        mesh = mesh if mesh is not None else self.tet_mesh_data()
        # Non-reflecting dashpots on light boundary nodes can be stiffer than the tets themselves
        # (warpdem.stages.loads).
        dashpots = self.load_specs.critical_time_step(mesh, self.tet_material_table())
        steps = [
            self.tet_critical_step(mesh),
            CriticalStep(dashpots, "the non-reflecting boundary dashpots"),
            self.contact_critical_step(mesh),
            reach_step(*self.contact_reach(particles, mesh), *self.fastest_launch(particles, mesh)),
        ]
        if np.any(free) or len(bonds):
            props = [self.materials[name] for name in names]
            material = particles.material

            def per_sphere(value: Callable[[MaterialProps], float]) -> np.ndarray:
                return np.array([value(p) for p in props], dtype=np.float64)[material]

            def describe(k: int) -> str:
                where = f"(r = {float(particles.radius[k]):.3g} m, part {self.parts[particles.part[k]]})"
                return f"spheres of material {names[material[k]]} {where}"

            steps += sphere_contact_steps(
                self.normal,
                particles.radius,
                sphere_masses(particles, self.materials),
                per_sphere(lambda p: p.youngs_modulus),
                per_sphere(lambda p: p.poisson_ratio),
                per_sphere(lambda p: effective_moduli(p, p)[0]),
                2.0 * float(np.linalg.norm(particles.qd, axis=1).max(initial=0.0)),
                describe,
                density=per_sphere(lambda p: p.density),
            )
            if len(bonds):
                steps.append(
                    bond_critical_step(sphere_masses(particles, self.materials), particles.part, bonds, self.parts)
                )
        return min(steps, key=lambda c: c.value)

    def contact_reach(self, particles: ParticleData, mesh: TetMeshData) -> tuple[float, str]:
        """The smallest contact reach [m] and what sets it: the smallest sphere radius or the shortest tet edge (inf
        when there is neither; ``Model.contact_reach``)."""
        reach, source = math.inf, ""
        if len(particles):
            k = int(np.argmin(particles.radius))
            reach = float(particles.radius[k])
            source = f"the radius of the spheres of part {self.parts[particles.part[k]]}"
        if len(mesh.tets):
            corners = mesh.points[mesh.tets]
            edges = [corners[:, a] - corners[:, b] for a, b in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))]
            edge = float(np.sqrt(min(np.einsum("ij,ij->i", e, e).min() for e in edges)))
            if edge < reach:
                reach, source = edge, "the shortest tet edge"
        return reach, source

    def fastest_launch(self, particles: ParticleData, mesh: TetMeshData) -> tuple[float, str]:
        """The fastest initial speed of a sphere, FEM node, wall or node velocity driver [m/s], and which it is."""
        found = [(0.0, "")]
        if len(particles):
            speed = np.linalg.norm(particles.qd, axis=1)
            k = int(np.argmax(speed))
            found.append((float(speed[k]), f"a sphere of part {self.parts[particles.part[k]]}"))
        if len(mesh.points):
            found.append((float(np.linalg.norm(mesh.velocity, axis=1).max()), "a FEM node"))
        walls = self.wall_data()
        if len(walls):
            found.append((float(np.linalg.norm(walls.velocity, axis=1).max()), "a wall"))
        for _, v, _, _ in self.load_specs.drivers:
            found.append((float(np.linalg.norm(v)), "a node velocity driver"))
        return max(found, key=lambda f: f[0])

    def run_away_speed(self, particles: ParticleData, bonds: BondData, mesh: TetMeshData, walls: WallData) -> float:
        """The guard's run-away speed bound at t = 0 [m/s] (:func:`warpdem.stages.guard.run_away_speed`): from the
        P-wave speeds of the materials and of the bond chains (L_0 sqrt(k_n / m)), and the initial, wall and driver
        speeds and the particle velocity of the strongest pressure load."""
        waves = [p_wave_speed(m.density, m.youngs_modulus, m.poisson_ratio) for m in self.materials.values()]
        if len(bonds):
            mass = sphere_masses(particles, self.materials)
            m = np.minimum(mass[bonds.pairs[:, 0]], mass[bonds.pairs[:, 1]])
            waves.append(float(np.max(bonds.rest_length * np.sqrt(bonds.kn / m))))
        velocities = (particles.qd, mesh.velocity, walls.velocity, *(d[1] for d in self.load_specs.drivers))
        speeds = [
            float(np.linalg.norm(np.asarray(v, dtype=np.float64).reshape(-1, 3), axis=1).max(initial=0.0))
            for v in velocities
        ]
        if self.load_specs.pressures and len(mesh.tets):
            # A pressure p launches the rock at p / (ρ c_p), twice that where the pulse reflects from a free face.
            impedance = min(m.density * m.c_p for m in self.tet_material_table() if m.density > 0.0)
            peak = max(max([abs(p.history.peak), *map(abs, p.history.values)]) for p in self.load_specs.pressures)
            speeds.append(2.0 * peak / impedance)
        return run_away_speed(waves, speeds)

    def finalize(
        self,
        device: wp.context.DeviceLike = None,
        *,
        dt: float | None = None,
        safety_factor: float = 0.2,
        skin: float | None = None,
        max_neighbors: int = 8,
        particle_capacity: int | None = None,
        sort: bool = True,
        node_capacity: int | None = None,
        tet_capacity: int | None = None,
        fem_skin: float | None = None,
        max_sphere_faces: int = 8,
        max_node_faces: int = 8,
        allow_unstable_dt: bool = False,
        node_order: str = "split",
    ) -> tuple[Model, State]:
        """Allocate the model and initial state; pre-split the joints and build the FEM contact surface.

        Args:
            device: Warp device.
            dt: time step [s]; None = ``safety_factor`` × critical time step.
            safety_factor: fraction of the critical step used when dt is None.
            skin: Verlet skin [m]; None = 0.4 × the smallest radius.
            max_neighbors: initial neighbour slots per particle (grown on overflow).
            particle_capacity: particle slots (default: the sphere count).
            sort: reorder spheres along a Z-order curve for memory locality (ids keep the creation order).
            node_capacity: FEM node slots (default: the node count after splitting the joints).
            tet_capacity: tet slots (default: the tet count).
            fem_skin: Verlet skin of the FEM contact lists [m] (default: warpdem.stages.fem_contact.attach_fem_contact).
            max_sphere_faces: initial FEM contact candidates per sphere (grown on overflow).
            max_node_faces: initial FEM contact candidates per node (grown on overflow).
            allow_unstable_dt: accept an explicit dt above the critical time step (the run-time guard still stops a
                run that blows up, warpdem.stages.guard).
            node_order: FEM node numbering: ``"split"`` (the mesh's nodes, then the daughters the joints' pre-split
                appends) or ``"blocks"`` (:func:`block_node_order`: block by block, for memory locality).

        Raises:
            warpdem.stages.guard.UnstableTimeStepError: an explicit dt above the critical time step
                (:meth:`critical_step`) and not allow_unstable_dt.
        """
        if node_order not in NODE_ORDERS:
            raise ValueError(f"finalize: node_order must be one of {sorted(NODE_ORDERS)}, not {node_order!r}")
        device = wp.get_device(device)
        particles = self.particle_data()
        n = len(particles)
        bonds = self.bond_data(particles, device)
        if sort and n:
            perm = morton_order(particles.q, 2.0 * float(particles.radius.max()))
            particles = ParticleData(*(getattr(particles, f)[perm] for f in ParticleData.__dataclass_fields__))
            ids = perm
            if len(bonds):
                inv = np.empty_like(perm)
                inv[perm] = np.arange(n)
                p = inv[bonds.pairs]
                p.sort(axis=1)
                order = np.lexsort((p[:, 1], p[:, 0]))
                bonds = BondData(p[order], *(getattr(bonds, f)[order] for f in list(BondData.__dataclass_fields__)[1:]))
        else:
            ids = np.arange(n)
        mesh = self.tet_mesh_data()
        critical = self.critical_step(particles, bonds, mesh)
        if dt is None:
            dt = safety_factor * critical.value
            if not math.isfinite(dt):
                dt = 1.0e-4
        else:
            check_time_step(float(dt), critical, allow_unstable_dt)
        if skin is None:
            skin = 0.4 * float(particles.radius.min()) if n else 0.0
        walls = self.wall_data()
        cap = max(particle_capacity or n, n, 1)
        names = list(self.materials)
        mass = sphere_masses(particles, self.materials)
        free = particles.motion == 0
        inv_mass = np.where(free, 1.0 / np.where(mass > 0, mass, 1.0), 0.0)
        inertia = 0.4 * mass * particles.radius**2
        inv_inertia = np.where(free, 1.0 / np.where(inertia > 0, inertia, 1.0), 0.0)

        def f32(a: np.ndarray, width: int | None = None) -> wp.array:
            out = np.zeros((cap, width) if width else cap, dtype=np.float32)
            out[:n] = a
            return wp.array(out, dtype=wp.vec3 if width else float, device=device)

        def i32(a: np.ndarray, fill: int = 0) -> wp.array:
            out = np.full(cap, fill, dtype=np.int32)
            out[:n] = a
            return wp.array(out, dtype=int, device=device)

        nw = len(walls)
        reach, reach_source = self.contact_reach(particles, mesh)
        joints = self.joint_data()
        # Room for the nodes the joints split off (counted by the same device pass that splits them below).
        split_count = count_split_nodes(mesh.points, mesh.tets, joints, device)
        tet_arrays = self.tet_model_arrays(mesh, device, max(node_capacity or 0, split_count), tet_capacity)
        model = Model(
            device=device,
            particle_capacity=cap,
            max_neighbors=max_neighbors,
            num_materials=len(names),
            num_walls=nw,
            dt=float(dt),
            skin=float(skin),
            gravity=tuple(float(g) for g in self.gravity),
            normal_model=self.normal,
            tangential_model=self.tangential,
            rolling_model=self.rolling,
            material_names=names,
            part_names=list(self.parts),
            particle_radius=f32(particles.radius),
            particle_mass=f32(mass),
            particle_inv_mass=f32(inv_mass),
            particle_inv_inertia=f32(inv_inertia),
            particle_material=i32(particles.material),
            particle_motion=i32(particles.motion),
            particle_part=i32(particles.part),
            particle_id=i32(ids, fill=-1),
            pair_table=pair_table_array(self.pair_table(), device),
            wall_normal=wp.array(walls.normal.astype(np.float32), dtype=wp.vec3, device=device),
            wall_velocity=wp.array(walls.velocity.astype(np.float32), dtype=wp.vec3, device=device),
            wall_material=wp.array(walls.material, dtype=int, device=device),
            walls_move=bool(nw and np.any(walls.velocity != 0.0)),
            bond_capacity=len(bonds),
            **tet_arrays,
            loads=self.load_model(mesh, tet_arrays, device),
            critical_dt=critical.value,
            critical_dt_source=critical.source,
            speed_limit=self.run_away_speed(particles, bonds, mesh, walls),
            contact_reach=reach,
            contact_reach_source=reach_source,
        )
        state = new_state(model, particles, walls, bonds, mesh)
        model, state = attach_fem_contact(
            model,
            state,
            joints,
            self.joint_sets,
            self.pair_table(),
            fem_skin=fem_skin,
            max_sphere_faces=max_sphere_faces,
            max_node_faces=max_node_faces,
            contact_stiffness_factor=self._surface_spring()[0],
            contact_face_normal_stiffness=self._surface_spring()[1],
            node_order=NODE_ORDERS[node_order],
        )
        return model, state

    def tet_model_arrays(
        self, mesh: TetMeshData, device: wp.context.Device, node_capacity: int | None, tet_capacity: int | None
    ) -> dict:
        """The Model fields of the FEM nodes and tets (capacities, masses, reference geometry, materials)."""
        nn, nt = len(mesh.points), len(mesh.tets)
        ncap, tcap = max(node_capacity or nn, nn), max(tet_capacity or nt, nt)
        table = self.tet_material_table()
        inv_ref, volume = reference_geometry(mesh.points, mesh.tets)
        density = np.array([m.density for m in table], dtype=np.float64)[mesh.material]
        alpha = np.array([m.alpha for m in table], dtype=np.float64)[mesh.material]
        mass, damping = lumped_node_masses(nn, mesh.tets, volume, density, alpha)
        held = (mesh.motion == NODE_MOTIONS["fixed"]) | (mass <= 0.0)
        inv_mass = np.where(held, 0.0, 1.0 / np.where(mass > 0.0, mass, 1.0))

        def padded(a: np.ndarray, cap: int, dtype, np_dtype) -> wp.array:
            out = np.zeros((cap, *a.shape[1:]), dtype=np_dtype)
            out[: len(a)] = a
            return wp.array(out, dtype=dtype, device=device)

        return {
            "node_capacity": ncap,
            "tet_capacity": tcap,
            "node_ref_q": padded(mesh.points, ncap, wp.vec3, np.float32),
            "node_mass": padded(mass, ncap, float, np.float32),
            "node_inv_mass": padded(inv_mass, ncap, float, np.float32),
            "node_motion": padded(mesh.motion, ncap, int, np.int32),
            "node_damping": padded(damping, ncap, float, np.float32),
            "tet_nodes": padded(mesh.tets, tcap, wp.vec4i, np.int32),
            "tet_inv_ref": padded(inv_ref, tcap, wp.mat33, np.float32),
            "tet_volume": padded(volume, tcap, float, np.float32),
            "tet_length": padded(characteristic_lengths(inv_ref), tcap, float, np.float32),
            "tet_material": padded(mesh.material, tcap, int, np.int32),
            "tet_material_table": wp.array(table, dtype=TetMaterial, device=device),
        }


# ----------------------------------------------------------------------------------------------------------------
# Scenes
