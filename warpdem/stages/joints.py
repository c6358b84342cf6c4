"""Joints (host side): joint-set properties, the device pass that pre-splits the nodes of joint faces, and the
cohesive joint interface elements.

A joint of the geology is a pre-split face made by the same code as nodal fracture (DESIGN.md stage 6): the nodes
on a joint are split so that the rock on either side is separate, meeting at the joint; the two sides then touch
through the FEM contact stage (penalty normal force, Coulomb friction with tangential history;
warpdem.stages.fem_contact). A *bonded* joint (cohesion c > 0 or tensile strength σ_t > 0) also ties each pair of
daughter nodes with an interface element that carries tension up to σ_t A and shear up to c A + μ σ_n A until it fails;
a failed element is purely frictional from then on (kernels/joints.py).

The pass (:class:`warpdem.stages.topology.NodeSplitter`, shared with nodal fracture) is a compaction pass on the device:

1. the node → tet adjacency (*star*): count → exclusive scan → fill → sort each node's list;
2. the face neighbours of every tet, and the joint faces tagged on the tet-face slots of both sides;
3. per node, its star grouped into connected components by faces that hold the node and are no joint faces;
   ``copies[n] = components - 1``;
4. :meth:`warpdem.stages.compaction.Compactor.plan_append` (exclusive scan → each node's first new slot), then
   :meth:`~warpdem.stages.compaction.Compactor.replicate` copies every per-node array into the new slots (positions,
   velocities, reference positions, motion kinds, ...), and the masses are re-lumped from each component's tets
   (Σ ρV₀/4, so the total mass is unchanged);
5. the tets' node indices remapped onto their component's node; face lists given in pre-split ids (loads) too.

Which nodes split: a node on a joint face splits into as many nodes as the joints cut its star into. A node inside
a joint surface, or on a joint that reaches the outer boundary of the mesh, gets one new node per extra side; a node
on the rim of a joint that ends inside the rock (a disc, a partial plane) is not split, since the rock around the
rim still connects the two sides; a node where two joints cross gets up to three new nodes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import joints as kj
from ..kernels.contact import ContactPair
from ..model import Model, State
from ..tables import TET_FACES
from .restitution import linear_damping_ratio
from .topology import NodeSplitter, NodeStars

__all__ = [
    "JointData",
    "JointElements",
    "JointFaceError",
    "JointProps",
    "NodeSplitter",
    "NodeStars",
    "build_joint_elements",
    "count_split_nodes",
    "eval_joints",
    "joint_energy",
    "joint_material",
    "joint_material_table",
    "load_face_arrays",
    "split_joints",
    "tag_joint_faces",
]


@dataclass
class JointProps:
    """Mechanical properties of a joint set.

    Attributes:
        friction: Coulomb friction coefficient μ of the joint faces [-].
        cohesion: cohesion c of the intact joint [Pa]; 0 with ``tensile_strength`` 0 gives a purely frictional
            joint from the start.
        tensile_strength: tensile strength σ_t of the intact joint [Pa].
        stiffness_factor: penalty factor f [-]: a joint face of a tet of Young's modulus E and height h over the
            face is a normal spring of f E / h per unit area, so the interface (both faces) is f (E_A/h_A + E_B/h_B),
            2 f E / h for equal sides. The default 1 makes the joint about as stiff as the elements behind it: the
            contact's stable step is then h / (2 c_bar sqrt(f)) with c_bar = sqrt(E/ρ), close to the tets' own
            (:func:`warpdem.stages.fem_contact.contact_critical_step_at`); a stiffer joint shortens the step by sqrt(f).
            None when ``normal_stiffness`` is given; 1 when neither is.
        normal_stiffness: joint normal stiffness k_n per unit area [Pa/m] (LDEC / UDEC / 3DEC style), instead of
            ``stiffness_factor``: the interface is a normal spring of k_n per unit area whatever the mesh, k_n / 2
            on each of its two faces (the node–face contact presses both ways at once), so a joint under a normal
            stress σ closes by σ / k_n, in deformable and rigid mode alike. The shear spring is
            ``shear_stiffness_ratio`` × k_n. None to use ``stiffness_factor``.
        restitution: coefficient of restitution (0, 1] of the joint's normal dashpot, as InteractionProps [-].
        shear_stiffness_ratio: tangential / normal stiffness k_t / k_n of the joint [-].
    """

    friction: float
    cohesion: float = 0.0
    tensile_strength: float = 0.0
    stiffness_factor: float | None = None
    restitution: float = 0.5
    shear_stiffness_ratio: float = 0.5
    normal_stiffness: float | None = None

    def __post_init__(self) -> None:
        if self.friction < 0.0 or self.cohesion < 0.0 or self.tensile_strength < 0.0:
            raise ValueError(f"JointProps: friction, cohesion and tensile_strength must be >= 0, got {self}")
        if self.stiffness_factor is not None and self.normal_stiffness is not None:
            raise ValueError(f"JointProps: give stiffness_factor or normal_stiffness, not both, got {self}")
        if self.normal_stiffness is None and self.stiffness_factor is None:
            self.stiffness_factor = 1.0
        spring = self.stiffness_factor if self.normal_stiffness is None else self.normal_stiffness
        if not spring > 0.0 or not 0.0 < self.restitution <= 1.0 or not self.shear_stiffness_ratio > 0:
            raise ValueError(
                "JointProps: need stiffness_factor > 0 (or normal_stiffness > 0 [Pa/m]), 0 < restitution <= 1, "
                f"k_t/k_n > 0, got {self}"
            )

    @property
    def penalty_factor(self) -> float:
        """f of the rock-relative part of a joint face's spring [-]: 0 when the joint has a ``normal_stiffness``."""
        return self.stiffness_factor if self.stiffness_factor is not None else 0.0

    @property
    def face_normal_stiffness(self) -> float:
        """The mesh-independent part of a joint face's spring per unit area, k_n / 2 [Pa/m] (0 without one)."""
        return 0.5 * self.normal_stiffness if self.normal_stiffness is not None else 0.0

    @property
    def bonded(self) -> bool:
        """Whether the joint starts intact (it has a cohesion or a tensile strength)."""
        return self.cohesion > 0.0 or self.tensile_strength > 0.0

    @property
    def damping_ratio(self) -> float:
        """ζ of the joint's dashpots, from the restitution (linear spring–dashpot) [-]."""
        return linear_damping_ratio(self.restitution)


def joint_material(props: JointProps) -> kj.JointMaterial:
    """The device-side JointMaterial of a joint set."""
    p = ContactPair()
    p.friction = props.friction
    p.kt_ratio = props.shear_stiffness_ratio
    zeta = props.damping_ratio
    p.damp_n = zeta
    p.damp_t = zeta
    m = kj.JointMaterial()
    m.contact = p
    m.cohesion = props.cohesion
    m.tensile_strength = props.tensile_strength
    m.stiffness_factor = props.penalty_factor
    m.face_normal_stiffness = props.face_normal_stiffness
    m.bonded = 1 if props.bonded else 0
    return m


def joint_material_table(props: list[JointProps], device: wp.context.Device) -> wp.array:
    """JointMaterial of every joint set, index = set id (one unused entry when there is no set, so kernels always
    get an array)."""
    table = [joint_material(p) for p in props] or [joint_material(JointProps(friction=0.0))]
    return wp.array(table, dtype=kj.JointMaterial, device=device)


@dataclass
class JointData:
    """Host-side joint faces to pre-split: node triples (J, 3) in the builder's node ids, joint set of each (J,)."""

    faces: np.ndarray
    face_set: np.ndarray

    def __len__(self) -> int:
        return len(self.faces)

    @staticmethod
    def empty() -> JointData:
        return JointData(np.zeros((0, 3), dtype=np.int32), np.zeros(0, dtype=np.int32))


class JointFaceError(ValueError):
    """Joint faces that are not interior faces of the tet mesh (each must be shared by exactly two tets)."""


def tag_joint_faces(
    stars: NodeStars, tet_nodes: wp.array, joints: JointData, tet_face_joint: wp.array
) -> tuple[wp.array, wp.array, wp.array]:
    """Tag the tet-face slots of both sides of every joint face with its set (others -1). Reads back a count.

    Returns:
        (joint face nodes, their sets, the two tets of each face (lower first)), on the device.

    Raises:
        JointFaceError: a joint face that is not shared by exactly two tets.
    """
    d = stars.device
    tet_face_joint.fill_(-1)
    nj = len(joints)
    faces = wp.array(np.asarray(joints.faces, dtype=np.int32).reshape(-1, 3), dtype=wp.vec3i, device=d)
    sets = wp.array(np.asarray(joints.face_set, dtype=np.int32), dtype=int, device=d)
    sides = wp.zeros(nj, dtype=wp.vec2i, device=d)
    if nj:
        unmatched = wp.zeros(1, dtype=int, device=d)
        wp.launch(
            kj.flag_joint_faces_kernel,
            dim=nj,
            inputs=[tet_nodes, faces, sets, *stars.csr()],
            outputs=[tet_face_joint, sides, unmatched],
            device=d,
        )
        bad = int(unmatched.numpy()[0])
        if bad:
            which = np.nonzero(np.any(sides.numpy() < 0, axis=1))[0]
            first = int(which[0]) if len(which) else -1
            raise JointFaceError(
                f"{bad} joint face(s) are not interior faces of the tet mesh (shared by two tets); first: face {first}"
                + (f" {joints.faces[first].tolist()}" if first >= 0 else "")
            )
    return faces, sets, sides


def count_split_nodes(points: np.ndarray, tets: np.ndarray, joints: JointData, device: wp.context.Device) -> int:
    """Node count after pre-splitting the joints of a host mesh (a device pass; reads back). Used to size the node
    arrays before the model is allocated."""
    nn, nt = len(points), len(tets)
    if nt == 0 or len(joints) == 0:
        return nn
    tet_nodes = wp.array(np.asarray(tets, dtype=np.int32), dtype=wp.vec4i, device=device)
    tet_count = wp.array([nt], dtype=int, device=device)
    node_count = wp.array([nn], dtype=int, device=device)
    active = wp.ones(nt, dtype=int, device=device)
    splitter = NodeSplitter(nn, nt, device)
    splitter.stars.build(tet_nodes, tet_count, active, node_count)
    tet_face_joint = wp.full(4 * nt, -1, dtype=int, device=device)
    tag_joint_faces(splitter.stars, tet_nodes, joints, tet_face_joint)
    splitter.plan(tet_nodes, tet_count, active, node_count, tet_face_joint)
    return splitter.new_node_count()


@dataclass
class JointElements:
    """The joint interface elements made by :func:`split_joints` (Model fields ``joint_*``), on the device."""

    capacity: int
    a: wp.array
    b: wp.array
    area: wp.array
    kn: wp.array
    tet_face: wp.array
    set: wp.array


def build_joint_elements(
    splitter: NodeSplitter,
    model: Model,
    faces: wp.array,
    sets: wp.array,
    sides: wp.array,
) -> JointElements:
    """One interface element per pair of daughter nodes across a bonded joint: emit one pair per joint-face vertex
    (area A/3), sort by (a, b), and sum each run of equal pairs in order (deterministic). Reads back the count."""
    d = splitter.device
    m = model
    nj = faces.shape[0]
    n_emit = 3 * nj
    # radix_sort_pairs needs twice the sorted length of scratch.
    key = wp.zeros(max(2 * n_emit, 1), dtype=wp.int64, device=d)
    value = wp.zeros(max(2 * n_emit, 1), dtype=int, device=d)
    area = wp.zeros(max(n_emit, 1), dtype=float, device=d)
    kn = wp.zeros(max(n_emit, 1), dtype=float, device=d)
    tet_face = wp.zeros(max(n_emit, 1), dtype=int, device=d)
    pset = wp.zeros(max(n_emit, 1), dtype=int, device=d)
    count = 0
    if nj:
        wp.launch(
            kj.emit_joint_pairs_kernel,
            dim=nj,
            inputs=[
                m.node_ref_q,
                m.tet_nodes,
                m.tet_volume,
                m.tet_material,
                m.tet_material_table,
                m.joint_material_table,
                faces,
                sets,
                sides,
                *splitter.split_args(),
            ],
            outputs=[key, value, area, kn, tet_face, pset],
            device=d,
        )
        wp.utils.radix_sort_pairs(key, value, n_emit)
        run_start = wp.zeros(n_emit, dtype=int, device=d)
        run_offset = wp.zeros(n_emit, dtype=int, device=d)
        wp.launch(kj.flag_pair_runs_kernel, dim=n_emit, inputs=[n_emit, key], outputs=[run_start], device=d)
        wp.utils.array_scan(run_start, run_offset, inclusive=False)
        count = int(run_offset.numpy()[-1] + run_start.numpy()[-1])
    out = JointElements(
        capacity=count,
        a=wp.zeros(count, dtype=int, device=d),
        b=wp.zeros(count, dtype=int, device=d),
        area=wp.zeros(count, dtype=float, device=d),
        kn=wp.zeros(count, dtype=float, device=d),
        tet_face=wp.zeros(count, dtype=int, device=d),
        set=wp.zeros(count, dtype=int, device=d),
    )
    if count:
        wp.launch(
            kj.reduce_joint_pairs_kernel,
            dim=n_emit,
            inputs=[n_emit, m.node_capacity, key, value, run_start, run_offset, area, kn, tet_face, pset],
            outputs=[out.a, out.b, out.area, out.kn, out.tet_face, out.set],
            device=d,
        )
    return out


def load_face_arrays(loads: object) -> list[wp.array]:
    """Face node lists (vec3i) of a warpdem.load_data.LoadModel: the pressure face sets and the dashpot faces."""
    if loads is None:
        return []
    sets = list(getattr(loads, "pressure", {}).values())
    if getattr(loads, "dashpots", None) is not None:
        sets.append(loads.dashpots)
    return [fs.nodes for fs in sets if getattr(fs, "nodes", None) is not None]


def split_joints(model: Model, state: State, joints: JointData) -> Model:
    """Pre-split the joint faces of a freshly built model on its device (module docstring) and make the interface
    elements of its bonded joints. Build time: reads back counts.

    The model's ``tet_face_joint`` is filled (joint set of each tet-face, -1 elsewhere) and ``joint_*`` hold the
    interface elements (the state's joint arrays are allocated from them: warpdem.stages.fem_contact.fem_contact_state).
    The node arrays of the model and state are split in place; the load model's faces and node drivers follow.

    Returns:
        The model with its joint elements.

    Raises:
        JointFaceError: a joint face is not an interior face of the mesh.
        ValueError: the node capacity cannot hold the split nodes (size it with :func:`count_split_nodes`).
    """
    m, s = model, state
    d = m.device
    splitter = NodeSplitter(m.node_capacity, m.tet_capacity, d)
    splitter.stars.build(m.tet_nodes, s.tet_count, s.tet_active, s.node_count)
    faces, sets, sides = tag_joint_faces(splitter.stars, m.tet_nodes, joints, m.tet_face_joint)
    splitter.plan(m.tet_nodes, s.tet_count, s.tet_active, s.node_count, m.tet_face_joint)
    needed = splitter.new_node_count()
    if needed > m.node_capacity:
        raise ValueError(f"split_joints: the split needs {needed} node slots, the model has {m.node_capacity}")
    elements = build_joint_elements(splitter, m, faces, sets, sides)
    for face_nodes in load_face_arrays(m.loads):
        splitter.remap_faces(m.tet_nodes, face_nodes)
    driver = getattr(m.loads, "node_driver", None)
    splitter.apply(m, s, [driver] if isinstance(driver, wp.array) else [])
    model = dataclasses.replace(
        m,
        joint_capacity=elements.capacity,
        joint_a=elements.a,
        joint_b=elements.b,
        joint_area=elements.area,
        joint_kn=elements.kn,
        joint_tet_face=elements.tet_face,
        joint_set=elements.set,
    )
    return model


def eval_joints(model: Model, state: State, dt: float | None = None) -> None:
    """Forces of the intact joint interface elements into ``state.node_f``; failures flagged (launches only).

    ``dt`` overrides the model step; 0 (the set-up evaluation) breaks nothing and books nothing.
    """
    if model.joint_capacity == 0:
        return
    m, s = model, state
    wp.launch(
        kj.eval_joints_kernel,
        dim=m.joint_capacity,
        inputs=[
            # Model:
            m.tet_nodes,
            m.node_inv_mass,
            m.joint_a,
            m.joint_b,
            m.joint_area,
            m.joint_kn,
            m.joint_tet_face,
            m.joint_set,
            m.joint_material_table,
            m.dt if dt is None else dt,
            # State in:
            s.joint_count,
            s.node_u,
            s.node_q,
            s.node_qd,
        ],
        outputs=[
            s.joint_broken,
            s.joints_broken_total,
            s.fem_rebuild_flag,
            s.node_f,
            s.node_f_contact,
            s.node_energy_contact,
        ],
        device=m.device,
    )


def joint_energy(model: Model, state: State) -> float:
    """Elastic energy of the intact joint elements [J] (reads back; between steps)."""
    if model.joint_capacity == 0:
        return 0.0
    m, s = model, state
    n = int(s.joint_count.numpy()[0])
    intact = s.joint_broken.numpy()[:n] == 0
    if not np.any(intact):
        return 0.0
    a, b = m.joint_a.numpy()[:n], m.joint_b.numpy()[:n]
    u = s.node_u.numpy().astype(np.float64)
    q = s.node_q.numpy().astype(np.float64)
    g = u[b] - u[a]
    tf = m.joint_tet_face.numpy()[:n]
    tets = m.tet_nodes.numpy()[tf // 4]
    face = np.take_along_axis(tets, TET_FACES[tf % 4], axis=1)
    x = q[face]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    gn = np.einsum("ij,ij->i", g, normal)
    gt = g - gn[:, None] * normal
    kt_ratio = np.array([p.shear_stiffness_ratio for p in m.joint_set_props] or [0.0])[m.joint_set.numpy()[:n]]
    kn = m.joint_kn.numpy()[:n].astype(np.float64)
    e = 0.5 * kn * (gn**2 + kt_ratio * np.sum(gt * gt, axis=1))
    return float(e[intact].sum())
