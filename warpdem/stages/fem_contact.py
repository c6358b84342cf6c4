"""FEM contact (host side): on the boundary faces of the tet mesh (:mod:`warpdem.stages.fem_surface` rebuilds them on
the device after topology passes), their hash-grid candidate lists with a Verlet skin, sphere–face, node–face and
node–wall forces, growth on overflow, the energy they store, and the stable time step they allow.

The laws and the geometric rules are in :mod:`warpdem.kernels.fem_contact`. The stage runs after the sphere
contacts in Simulation.step: flag a rebuild (a node moved half ``fem_skin``, flagged by its drift in
warpdem.stages.integrate, or the sphere list was rebuilt) →
rebuild the lists in a conditional graph node (``wp.capture_if``) → sphere–face forces → node–face and node–wall
forces → joint interface elements (:func:`warpdem.stages.joints.eval_joints`). It allocates nothing and reads nothing
back, so it is captured in the step's graph.

Grid. The faces get their own ``wp.HashGrid`` over their centroids rather than a share of the sphere grid: a
face's extent (the tet size h) is unrelated to the sphere radii that size the sphere grid's cells, the FEM lists
are rebuilt on node motion rather than sphere motion, and a model of tets alone has no sphere grid at all. The
mechanism is the sphere list's, and so is the builder (:mod:`warpdem.stages.neighbors`): skinned lists with capacities,
an overflow counter (the largest count seen), growth ×2 between steps with the step redone, and tangential history
carried across rebuilds by matching pairs.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import warp as wp

from ..kernels import fem_contact as kf
from ..kernels.contact import ContactPair
from ..model import Model, State
from ..tables import TET_FACES, row_groups
from .contact import hash_grid_dims
from .fem_surface import build_surface, smallest_face_depth
from .integrate import book_half_ahead
from .joints import (
    JointData,
    JointProps,
    eval_joints,
    joint_energy,
    joint_material_table,
    load_face_arrays,
    split_joints,
)
from .neighbors import SkinnedList, SlotArrays, finish_rebuild, make_struct
from .rigid import has_bodies
from .topology import renumber_nodes

DEFAULT_SKIN_FRACTION = 0.25
"""Default ``fem_skin`` as a fraction of the smallest tet height over a boundary face [-]."""
ROUNDING_ULPS = 8.0
"""The depth of a node lying on a face at set-up, in float32 spacings of the largest coordinate [-]: the depth is a
projection of float32 differences of a few float32 sums (X + u), each rounded by half a spacing."""
RELAXED_ALL = 3.0e38
"""The relaxed depth of the re-evaluation after a topology pass: every spring that starts then starts relaxed [m]."""


def sphere_face_rows(model: Model) -> int:
    """Spheres with sphere–face lists: every slot in a model with boundary faces, none without (there the lists
    would be 132 bytes per sphere that nothing reads)."""
    return model.particle_capacity if model.face_capacity else 0


def fem_contact_state(model: Model) -> dict[str, wp.array]:
    """The State fields of the FEM contact stage and the joint elements of a model: no contact yet, lists to be
    built (``fem_rebuild_flag`` = 1), every joint element intact."""
    d = model.device
    ncap, pcap = model.node_capacity, sphere_face_rows(model)

    def one(v: int = 0) -> wp.array:
        return wp.array([v], dtype=int, device=d)

    return {
        "face_count": one(),
        "fem_rebuild_flag": one(1),
        "fem_rebuild_total": one(),
        "fem_sphere_builds_seen": one(-1),
        "node_q_at_fem_build": wp.zeros(ncap, dtype=wp.vec3, device=d),
        "sphere_face_needed": one(),
        "sphere_face_count": wp.zeros(pcap, dtype=int, device=d),
        "sphere_face_index": wp.zeros(pcap * model.max_sphere_faces, dtype=int, device=d),
        "sphere_face_shear": wp.zeros(pcap * model.max_sphere_faces, dtype=wp.vec3, device=d),
        "sphere_face_energy_prev": wp.zeros(pcap, dtype=wp.vec2, device=d),
        "sphere_face_f": wp.zeros(pcap, dtype=wp.vec3, device=d),
        "sphere_face_t": wp.zeros(pcap, dtype=wp.vec3, device=d),
        "sphere_face_dissipated": wp.zeros(pcap, dtype=wp.float64, device=d),
        "node_face_needed": one(),
        "node_face_count": wp.zeros(ncap, dtype=int, device=d),
        "node_face_index": wp.zeros(ncap * model.max_node_faces, dtype=int, device=d),
        "node_face_spring": wp.full(ncap * model.node_springs, -1, dtype=int, device=d),
        "node_face_offset": wp.zeros(ncap * model.node_springs, dtype=float, device=d),
        "node_face_shear": wp.zeros(ncap * model.node_springs, dtype=wp.vec3, device=d),
        "node_wall_shear": wp.zeros(ncap * model.num_walls, dtype=wp.vec3, device=d),
        "node_contact_hold": wp.zeros(ncap, dtype=wp.float64, device=d),
        "node_f_contact": wp.zeros(ncap, dtype=wp.vec3, device=d),
        "node_contact_energy_prev": wp.zeros(ncap, dtype=wp.float64, device=d),
        "node_energy_contact": wp.zeros(ncap, dtype=wp.float64, device=d),
        "node_f_sphere_face": wp.zeros(ncap, dtype=wp.vec3, device=d),
        "node_energy_sphere_face": wp.zeros(ncap, dtype=wp.float64, device=d),
        "joint_count": one(model.joint_capacity),
        "joint_broken": wp.zeros(model.joint_capacity, dtype=int, device=d),
        "joints_broken_total": one(),
    }


def fem_pair_table(pairs: list[list[ContactPair]], device: wp.context.Device) -> wp.array:
    """The node–face / node–wall pair table: the sphere pair table with damp_n = damp_t, the linear damping ratio ζ
    of the restitution (node contacts are linear springs, whatever the sphere normal law)."""
    flat = []
    for row in pairs:
        for p in row:
            q = ContactPair()
            for name in ("estar", "gstar", "young_a", "young_b", "kt_ratio", "friction", "rolling", "damp_t"):
                setattr(q, name, getattr(p, name))
            q.damp_n = p.damp_t
            flat.append(q)
    return wp.array(flat, dtype=ContactPair, device=device)


def attach_fem_contact(
    model: Model,
    state: State,
    joints: JointData,
    joint_props: list[JointProps],
    pairs: list[list[ContactPair]],
    *,
    fem_skin: float | None = None,
    max_sphere_faces: int = 8,
    max_node_faces: int = 8,
    contact_stiffness_factor: float = 1.0,
    contact_face_normal_stiffness: float = 0.0,
    node_order: Callable[[Model, State], np.ndarray] | None = None,
) -> tuple[Model, State]:
    """Give a freshly built model its joints and FEM contact: pre-split the joint faces (warpdem.stages.joints),
    renumber the nodes if asked, build the surface, and allocate the contact lists. Build time.

    Args:
        joints: joint faces in the model's node ids and their sets.
        joint_props: properties of each joint set (index = set id).
        pairs: the sphere pair table (ModelBuilder.pair_table), for the node contacts' friction and restitution.
        fem_skin: Verlet skin of the FEM lists [m]; None = :data:`DEFAULT_SKIN_FRACTION` × the smallest tet height
            over a boundary face.
        max_sphere_faces: initial candidate slots per sphere (grown on overflow).
        max_node_faces: initial candidate slots per node (grown on overflow).
        contact_stiffness_factor: penalty factor of faces that are no joint faces [-].
        contact_face_normal_stiffness: mesh-independent spring of those faces, k_n / 2 per unit area [Pa/m].
        node_order: the node numbering after the pre-split, new node i = old node ``node_order(model, state)[i]``
            (warpdem.stages.topology.renumber_nodes; e.g. warpdem.stages.ordering.block_node_order); None keeps the
            split's own.
    """
    d = model.device
    nj = len(joints)
    if nj and (np.max(joints.face_set) >= len(joint_props) or np.min(joints.face_set) < 0):
        raise ValueError(f"joint face sets must lie in [0, {len(joint_props)}), the joint sets added")
    empty_int = wp.zeros(0, dtype=int, device=d)
    model = dataclasses.replace(
        model,
        max_sphere_faces=max_sphere_faces,
        max_node_faces=max_node_faces,
        contact_stiffness_factor=contact_stiffness_factor,
        contact_face_normal_stiffness=contact_face_normal_stiffness,
        tet_face_joint=wp.full(4 * model.tet_capacity, -1, dtype=int, device=d),
        fem_pair_table=fem_pair_table(pairs, d),
        joint_material_table=joint_material_table(joint_props, d),
        joint_set_props=list(joint_props),
        joint_capacity=0,
        joint_a=empty_int,
        joint_b=empty_int,
        joint_area=wp.zeros(0, dtype=float, device=d),
        joint_kn=wp.zeros(0, dtype=float, device=d),
        joint_tet_face=empty_int,
        joint_set=empty_int,
    )
    if nj:
        model = split_joints(model, state, joints)
    if node_order is not None:
        renumber_nodes(model, state, node_order(model, state), load_face_arrays(model.loads))
    model = build_surface(model, state)
    if fem_skin is None:
        fem_skin = 2.0 * DEFAULT_SKIN_FRACTION * smallest_face_depth(model, state)
    model = dataclasses.replace(model, fem_skin=float(fem_skin))
    state = dataclasses.replace(state, **{k: v for k, v in fem_contact_state(model).items() if k != "face_count"})
    return model, state


# ----------------------------------------------------------------------------------------------------------------
# The stage


class FemContact:
    """The FEM contact stage of a Model/State pair: hash grid, scratch buffers, rebuild and force launches.

    Args:
        model: the model it works on.
        state: the state it works on (its lists are rebuilt in place).
        has_spheres: whether the model has spheres (sphere–face contacts).
    """

    def __init__(self, model: Model, state: State, has_spheres: bool) -> None:
        self.model = model
        self.state = state
        self.has_spheres = has_spheres
        d = model.device
        fcap = max(model.face_capacity, 1)
        # A subdomain's grid has the whole run's buckets (Model.face_grid_owners): candidates come in the same order.
        self.grid = wp.HashGrid(*(hash_grid_dims(model.face_grid_owners or fcap),) * 3, device=d)
        self.grid.reserve(fcap)  # so that a rebuild inside a captured graph never allocates
        self.face_center = wp.zeros(fcap, dtype=wp.vec3, device=d)
        self.face_bound = wp.zeros(fcap, dtype=float, device=d)
        self.face_normal = wp.zeros(fcap, dtype=wp.vec3, device=d)
        self.face_origin = wp.zeros(fcap, dtype=wp.vec3, device=d)
        # A sphere moves at most its whole skin between FEM builds (kernels/fem_contact.py, "Skins"), a face half ours.
        self.sphere_margin = model.skin + 0.5 * model.fem_skin
        # A node–face candidate may project KEEP_EPS outside its face: within RIM_REACH face radii of its centroid.
        self.node_search = kf.RIM_REACH * model.face_radius + max(model.fem_skin, model.face_depth_max)
        self.sphere_search = model.face_radius + (model.max_radius + self.sphere_margin if has_spheres else 0.0)
        self.cell = max(self.node_search, self.sphere_search, 1.0e-6)
        # A node whose candidates a split may change lies within the query radius plus a face's extent of a daughter
        # (kernels/node_face_list.py mark_near_new_nodes_kernel); fem_skin covers float rounding and a face stretched
        # past its reference radius.
        self.near_radius = self.node_search + model.face_radius + model.fem_skin
        # refresh_near's marks (made here: a recording of it allocates nothing).
        self.near = wp.zeros(max(model.node_capacity, 1), dtype=int, device=d)
        self.every_node = wp.zeros(0, dtype=int, device=d)  # ``near`` of a full rebuild: every node builds its list
        self.sphere_faces = None
        if has_spheres:
            self.sphere_faces = SkinnedList(
                kf.SPHERE_FACE_LIST, model.particle_capacity, model.max_sphere_faces, d, {"shear": wp.vec3}
            )
        self.node_faces = SkinnedList(kf.NODE_FACE_LIST, model.node_capacity, model.max_node_faces, d)
        self.normal_body = wp.full(max(model.node_capacity, 1), -1, dtype=int, device=d)
        self.rest_normal = wp.zeros(max(model.node_capacity, 1), dtype=wp.vec3, device=d)
        # Where each spring slot found its target in its node's candidate list at the last evaluation (a hint only: a
        # stale one costs a search, never a different answer; kernels/node_face_target.py kept_face_holds).
        self.target_slot = wp.full(max(model.node_capacity, 1) * model.node_springs, -1, dtype=int, device=d)
        # -2: a node's later scans for a new plane test only the first scan's survivors; -1: each scans its whole
        # list (kernels/node_face_target.py new_plane_face; survivor_scans).
        self.first_scan = wp.full(1, -2, dtype=int, device=d)
        # The face each node and sphere went past the contact's reach of in a step since the stability guard last
        # looked (-1: none; kernels/fem_contact.py passed_face, kernels/sphere_face.py): written where the contact lets
        # go, since the body then moves on through the rock, read and cleared by warpdem.stages.guard between steps.
        self.node_passed = wp.full(max(model.node_capacity, 1), -1, dtype=int, device=d)
        self.sphere_passed = wp.full(max(sphere_face_rows(model), 1), -1, dtype=int, device=d)
        self.rigid_normals(True)
        # The depth float32 rounding gives a node lying on a face (the two sides of a pre-split joint, a block resting
        # on its base): a few ulp of the largest coordinate (set-up only: read back once).
        nn = model.node_capacity
        extent = float(np.abs(model.node_ref_q.numpy()[:nn]).max(initial=0.0)) if nn else 0.0
        self.noise_depth = ROUNDING_ULPS * float(np.finfo(np.float32).eps) * extent

    def seat_walls(self) -> None:
        """Seat each plane wall on the rock that lies on it: move the wall back along its normal (away from the model)
        by the deepest gap of a node behind it within ``noise_depth`` (float32 rounding, as a node lying on a face,
        the brazilian disc's nodes 3.7e-10 m behind its platens). Set-up only, before the first force evaluation and
        not at a restart (the checkpoint's walls are seated): a wall spring holds no offset, so a node meshed onto
        the wall would otherwise press on it with k δ at rest, energy that float32 positions cannot book (a
        displacement below a coordinate's spacing moves the node but not the gap). Nodes deeper than that are a real
        initial penetration and are left to push (less the shift, at most ``noise_depth``). Moving a wall away never
        starts a contact. Reads back a float per wall, one round or two."""
        m, s, d = self.model, self.state, self.model.device
        if m.num_walls == 0 or m.node_capacity == 0 or self.noise_depth <= 0.0:
            return
        deepest = wp.zeros(m.num_walls, dtype=float, device=d)
        normal = m.wall_normal.numpy().astype(np.float64)
        for _ in range(4):  # the float64 shift leaves the float32 gap at 0 or a spacing above; a second round checks
            deepest.zero_()
            wp.launch(
                kf.seat_walls_kernel,
                dim=m.node_capacity,
                inputs=[
                    m.node_contact_stiffness,
                    m.wall_normal,
                    m.num_walls,
                    s.node_count,
                    s.node_q,
                    s.wall_point,
                    float(self.noise_depth),
                ],
                outputs=[deepest],
                device=d,
            )
            gaps = deepest.numpy().astype(np.float64)
            if not np.any(gaps < 0.0):
                return
            s.wall_point.assign(s.wall_point.numpy() + gaps[:, None] * normal)

    def survivor_scans(self, on: bool) -> None:
        """Let a node's later scans for a new plane in one evaluation test only the faces that passed its first scan
        (``on``, the default) or scan its whole candidate list each time (the path it is tested against: the same
        decisions). An array fill, so a captured graph sees the choice."""
        self.first_scan.fill_(-2 if on else -1)

    def rigid_normals(self, on: bool) -> None:
        """Turn the nodes of rigid blocks by their bodies' pose instead of walking their stars each evaluation
        (kernels/fem_surface.py ``rest_normals_kernel``; ``on`` False: every node walks its star, the general path
        the fast one is tested against). A no-op before the blocks turned rigid. Launches only; the arrays keep
        their addresses, so a captured graph sees the choice."""
        m, s, d = self.model, self.state, self.model.device
        self.normal_body.fill_(-1)
        if not (on and has_bodies(s) and m.node_capacity):
            return
        x_rest = wp.zeros(m.node_capacity, dtype=wp.vec3, device=d)
        wp.launch(
            kf.rest_positions_kernel,
            dim=m.node_capacity,
            inputs=[m.node_ref_q, s.node_count, s.node_body, s.node_rigid_u0],
            outputs=[x_rest],
            device=d,
        )
        wp.launch(
            kf.rest_normals_kernel,
            dim=m.node_capacity,
            inputs=[
                # Model:
                m.tet_nodes,
                m.tet_face_nbr,
                m.star_offset,
                m.star_count,
                m.star_tets,
                # State in:
                s.node_count,
                s.node_body,
                s.tet_active,
                # In:
                x_rest,
            ],
            outputs=[self.normal_body, self.rest_normal],
            device=d,
        )

    def rebuild_sphere_faces(self) -> None:
        """Build the face grid and the sphere–face lists (the first part of :meth:`rebuild`; alone, it sizes the
        sphere–face slots through ``state.sphere_face_needed`` for a few spheres before the node lists are built).
        Launches only."""
        m, s = self.model, self.state
        self._build_face_grid(s.node_q)
        if self.sphere_faces is not None:
            inputs = make_struct(
                kf.SphereFaceInputs,
                particle_radius=m.particle_radius,
                face_nodes=m.face_nodes,
                node_q=s.node_q,
                margin=self.sphere_margin,
                face_radius=m.face_radius,
            )
            history = make_struct(kf.SphereFaceHistory, shear=s.sphere_face_shear)
            lists = SlotArrays(s.sphere_face_count, s.sphere_face_index, history)
            self.sphere_faces.rebuild(
                inputs, self.grid, s.particle_count, s.particle_q, s.face_count, lists, s.sphere_face_needed
            )

    def rebuild(self) -> None:
        """Rebuild the candidate lists now (launches only: usable inside a graph capture)."""
        m, s, d = self.model, self.state, self.model.device
        self.rebuild_sphere_faces()
        if m.node_capacity:
            self._build_node_faces(s.node_q, self.every_node)
        finish_rebuild(s.node_count, s.node_q, s.node_q_at_fem_build, s.fem_rebuild_flag, s.fem_rebuild_total, d)

    def _build_face_grid(self, node_q: wp.array) -> None:
        """Face centroids and bounding radii (``face_center``, ``face_bound``) with the nodes at ``node_q``, and the
        face grid over the centroids. Launches only."""
        m, s = self.model, self.state
        wp.launch(
            kf.face_centers_kernel,
            dim=self.face_center.shape[0],
            inputs=[m.face_nodes, s.face_count, node_q],
            outputs=[self.face_center, self.face_bound],
            device=m.device,
        )
        self.grid.build(self.face_center, self.cell)

    def _build_node_faces(self, node_q: wp.array, near: wp.array) -> None:
        """Build the node–face lists with the faces and nodes at ``node_q`` (the face grid and ``face_center`` /
        ``face_bound`` taken there already); ``near``: the nodes to build (empty: all). Launches only."""
        m, s = self.model, self.state
        inputs = make_struct(
            kf.NodeFaceInputs,
            node_contact_stiffness=m.node_contact_stiffness,
            tet_nodes=m.tet_nodes,
            star_offset=m.star_offset,
            star_count=m.star_count,
            star_tets=m.star_tets,
            face_nodes=m.face_nodes,
            face_depth=m.face_depth,
            face_center=self.face_center,
            face_bound=self.face_bound,
            joint_a=m.joint_a,
            joint_b=m.joint_b,
            node_body=s.node_body,
            node_q=node_q,
            joint_count=s.joint_count,
            joint_broken=s.joint_broken,
            near=near,
            fem_skin=m.fem_skin,
            search_radius=self.node_search,
        )
        lists = SlotArrays(s.node_face_count, s.node_face_index)
        self.node_faces.rebuild(inputs, self.grid, s.node_count, node_q, s.face_count, lists, s.node_face_needed)

    @property
    def refreshes_near(self) -> bool:
        """Whether :meth:`refresh_near` can bring the lists up to date (no spheres: their lists are rebuilt with the
        sphere list, at the current positions)."""
        return self.sphere_faces is None and self.model.node_capacity > 0

    def refresh_near(
        self, first_new: wp.array, face_slot: wp.array, old_faces: wp.array, slot_to_face: wp.array
    ) -> bool:
        """After a split pass that appended daughters from node ``first_new[0]`` on and rebuilt the surface
        (warpdem.stages.fem_surface.rebuild_surface, whose ``slot_to_face`` and the ``face_slot`` of the
        ``old_faces[0]`` faces before it carry face ids over; both counts on the device, shape (1,)): bring the
        node–face lists to what a full rebuild would have built where they
        were last built, rebuilding only the lists of the nodes near a daughter
        (kernels/node_face_list.py mark_near_new_nodes_kernel) and carrying the others' face ids over.

        Why where they were last built (``node_q_at_fem_build``, which a daughter copies from its parent): the Verlet
        criterion measures every node's drift from there, so lists built there with the new topology stay valid until
        the next rebuild exactly as a full rebuild's would, and no skin is spent. A full rebuild tests every node
        against the faces of ~27 grid cells (16 ms a pass on the 10 k-tet cracking block of ``bench fracture``); this
        one, the daughters' neighbourhoods.

        Returns whether it refreshed the lists; False where only a full rebuild will do (the model has spheres: the
        sphere–face lists are rebuilt at the current positions with the sphere list). Launches only."""
        m, s, d = self.model, self.state, self.model.device
        if not self.refreshes_near:
            return False
        # The kept lists' face ids, as remap_face_ids carries the springs' (a split removes no face).
        wp.launch(
            kf.remap_face_ids_kernel,
            dim=s.node_face_index.shape[0],
            inputs=[old_faces, face_slot, slot_to_face],
            outputs=[s.node_face_index],
            device=d,
        )
        q = s.node_q_at_fem_build
        self._build_face_grid(q)
        self.near.zero_()
        wp.launch(
            kf.mark_near_new_nodes_kernel,
            dim=m.node_capacity,
            inputs=[
                m.face_nodes,
                self.grid.id,
                first_new,
                self.near_radius,
                # reach: radius + a face's bounding radius, taken as twice the reference face radius so that a face
                # stretched to twice its reference extent is still offered (the cracking-run test in
                # tests/test_fracture.py holds the result to a brute force).
                self.near_radius + 2.0 * m.face_radius,
                s.node_count,
                s.face_count,
                q,
            ],
            outputs=[self.near],
            device=d,
        )
        self._build_node_faces(q, self.near)
        return True

    def rebuild_if_needed(self) -> None:
        """Rebuild when a node moved half the skin or the sphere list was rebuilt (conditional node under capture)."""
        m, s = self.model, self.state
        wp.launch(
            kf.flag_fem_rebuild_kernel,
            dim=1,
            inputs=[s.rebuild_total],
            outputs=[s.fem_sphere_builds_seen, s.fem_rebuild_flag],
            device=m.device,
        )
        wp.capture_if(s.fem_rebuild_flag, on_true=self.rebuild)

    def eval(self, track_energy: bool, dt: float | None = None, born_relaxed: bool = False) -> None:
        """Rebuild if needed, then accumulate sphere–face, node–face, node–wall and joint-element forces.

        ``dt`` overrides the model step for the history increments; 0 evaluates forces without advancing any (the
        set-up evaluation, where a spring whose depth is within float32 rounding, ``noise_depth``, starts relaxed:
        a state at rest stays at rest). ``born_relaxed``: node–face springs that start now start relaxed (the
        evaluation after a topology pass).
        """
        self.rebuild_if_needed()
        eval_fem_contacts(
            self.model,
            self.state,
            track_energy,
            self.has_spheres,
            dt,
            self.face_normal,
            born_relaxed,
            self.normal_body,
            self.rest_normal,
            self.target_slot,
            self.face_origin,
            self.first_scan,
            self.noise_depth if dt == 0.0 else 0.0,
            self.node_passed,
            self.sphere_passed,
        )
        eval_joints(self.model, self.state, dt)


def eval_fem_contacts(
    model: Model,
    state: State,
    track_energy: bool,
    has_spheres: bool,
    dt: float | None,
    face_normal: wp.array,
    born_relaxed: bool = False,
    normal_body: wp.array | None = None,
    rest_normal: wp.array | None = None,
    target_slot: wp.array | None = None,
    face_origin: wp.array | None = None,
    first_scan: wp.array | None = None,
    noise_depth: float = 0.0,
    node_passed: wp.array | None = None,
    sphere_passed: wp.array | None = None,
) -> None:
    """Sphere–face, node–face and node–wall forces into ``particle_f/t`` and ``node_f`` (launches only).

    ``normal_body``, ``rest_normal``, ``target_slot``, ``face_origin`` and ``first_scan`` are allocated here when None
    (a direct call outside a step; survivors on).

    Args:
        face_normal: scratch for the faces' unit normals of this evaluation, shape (face_capacity,), vec3
            (``FemContact`` holds one).
        born_relaxed: a node–face spring that starts in this evaluation starts relaxed, its depth carried as an
            offset: the re-evaluation after a topology pass, where nothing moved, so no depth was gained (at set-up
            an initial penetration pushes, and in a step a new spring takes the depth gained in it).
        noise_depth: where not ``born_relaxed``, a spring that starts in this evaluation carries up to this depth [m]
            as an offset: float32 rounding, not a penetration (``FemContact.noise_depth``, at set-up).
        normal_body: the body whose pose turns each node's normal, -1 where the node walks its star
            (``FemContact.rigid_normals``), shape (node_capacity,), int32; None: every node walks its star.
        rest_normal: each node's normal at the switch positions, turned by that body
            (``FemContact.rigid_normals``), shape (node_capacity,), vec3.
        target_slot: each spring slot's list slot of its target at the last evaluation, a hint (``FemContact``),
            shape (node_capacity * node_springs,), int32; None: none.
        face_origin: scratch for each face's first vertex x_a at this evaluation, shape (face_capacity,), vec3
            (``FemContact`` holds one; written with the normals, read by the node–face depth tests).
        first_scan: shape (1,), int32: -2, a node's later scans for a new plane test only its first scan's survivors;
            -1, each scans the whole list (``FemContact.survivor_scans``).
        node_passed: the face each node went past the reach of in a step (-1 none), written here and cleared by the
            stability guard (``FemContact.node_passed``), shape (node_capacity,), int32; None: a scratch array.
        sphere_passed: the same for the spheres' faces (``FemContact.sphere_passed``), shape (particle_capacity,).
    """
    m, s = model, state
    n = max(m.node_capacity, 1)
    if normal_body is None or rest_normal is None:
        normal_body = wp.full(n, -1, dtype=int, device=m.device)
        rest_normal = wp.zeros(n, dtype=wp.vec3, device=m.device)
    if target_slot is None:
        target_slot = wp.full(n * m.node_springs, -1, dtype=int, device=m.device)
    if face_origin is None:
        face_origin = wp.zeros(face_normal.shape[0], dtype=wp.vec3, device=m.device)
    if first_scan is None:
        first_scan = wp.full(1, -2, dtype=int, device=m.device)
    if node_passed is None:
        node_passed = wp.full(n, -1, dtype=int, device=m.device)
    if sphere_passed is None:
        sphere_passed = wp.full(max(sphere_face_rows(m), 1), -1, dtype=int, device=m.device)
    step = m.dt if dt is None else dt
    if m.node_capacity:
        if step > 0.0:
            # The half ahead of the last evaluation's node contact forces, at the velocities this one sees. Without
            # the books only the joint elements' dashpots (kernels/joints.py) put forces into node_f_contact: with
            # none, it stays zero and the launch over every node slot would book zeros (4-7 ns per node and step
            # of `bench blocks`).
            if track_energy or m.joint_capacity > 0:
                book_half_ahead(m, s, step, s.node_f_contact, s.node_energy_contact, -1.0)
            # The sphere–face contacts' share on the face nodes, on their own line (kernels/sphere_face.py).
            if track_energy and has_spheres and m.face_capacity:
                book_half_ahead(m, s, step, s.node_f_sphere_face, s.node_energy_sphere_face, -1.0)
        else:
            # Set-up or re-evaluation after a pass: the next kick works with the forces evaluated now, so the next
            # step books the half ahead of exactly these, whatever the forces before the pass were.
            s.node_f_contact.zero_()
            s.node_f_sphere_face.zero_()
    if has_spheres and m.face_capacity:
        kernel, _ = kf.make_sphere_face_kernel(m.normal_model, m.tangential_model, m.rolling_model, track_energy)
        wp.launch(
            kernel,
            dim=m.particle_capacity,
            inputs=[
                # Model:
                m.particle_radius,
                m.particle_inv_mass,
                m.particle_material,
                m.pair_table,
                m.num_materials,
                m.node_inv_mass,
                m.tet_material,
                m.face_nodes,
                m.face_tet,
                m.face_radius,
                m.max_sphere_faces,
                step,
                # State in:
                s.particle_count,
                s.particle_q,
                s.particle_qd,
                s.particle_omega,
                s.sphere_face_count,
                s.sphere_face_index,
                s.node_q,
                s.node_qd,
            ],
            outputs=[
                s.sphere_face_shear,
                s.particle_f,
                s.particle_t,
                s.node_f,
                s.sphere_face_f,
                s.sphere_face_t,
                s.node_f_sphere_face,
                s.sphere_face_energy_prev,
                s.sphere_face_dissipated,
                s.energy_stiffness_change,
                # Out:
                sphere_passed,
            ],
            device=m.device,
        )
    if m.node_capacity:
        wp.launch(
            kf.face_normals_kernel,
            dim=m.face_capacity,
            inputs=[m.face_nodes, s.face_count, s.node_q],
            outputs=[face_normal, face_origin],
            device=m.device,
        )
        wp.launch(
            kf.make_node_contact_kernel(track_energy),
            dim=m.node_capacity,
            inputs=[
                # Model:
                m.node_inv_mass,
                m.node_mass,
                m.node_contact_stiffness,
                m.node_contact_material,
                m.tet_nodes,
                m.tet_face_nbr,
                m.star_offset,
                m.star_count,
                m.star_tets,
                m.tet_material,
                m.face_nodes,
                m.face_tet,
                m.face_joint,
                m.face_depth,
                m.fem_pair_table,
                m.joint_material_table,
                m.num_materials,
                m.wall_normal,
                m.wall_velocity,
                m.wall_material,
                m.num_walls,
                m.max_node_faces,
                step,
                # State in:
                s.node_count,
                s.node_q,
                s.node_qd,
                s.node_face_count,
                s.node_face_index,
                s.wall_point,
                s.body_q,
                # In:
                face_normal,
                face_origin,
                normal_body,
                rest_normal,
                first_scan,
                RELAXED_ALL if born_relaxed else float(noise_depth),
                rim_faces(m),
            ],
            outputs=[
                s.node_face_spring,
                s.node_face_offset,
                s.node_face_shear,
                s.node_wall_shear,
                s.node_contact_hold,
                s.node_f,
                s.node_f_contact,
                s.node_contact_energy_prev,
                s.node_energy_contact,
                s.node_energy_boundary_work,
                # Out:
                target_slot,
                node_passed,
            ],
            device=m.device,
        )


# ----------------------------------------------------------------------------------------------------------------
# Growth, energy, time step


_NO_FACES: dict[str, wp.array] = {}
"""An empty int array per device: ``ref_tet_face_nbr`` of a model without fracture or conversion."""


def rim_faces(model: Model) -> kf.RimFaces:
    """What the node–face tests read to tell a crack's faces from the others (kernels/fem_surface.py ``rim_margins``),
    as the kernels take it: made at each launch, so that it holds the Model's arrays after any growth."""
    m = model
    ref = m.ref_tet_face_nbr
    if ref is None:
        ref = _NO_FACES.setdefault(str(m.device), wp.empty(0, dtype=int, device=m.device))
    return make_struct(
        kf.RimFaces,
        face_joint=m.face_joint,
        face_tet=m.face_tet,
        face_nodes=m.face_nodes,
        tet_nodes=m.tet_nodes,
        ref_tet_face_nbr=ref,
        tet_face_joint=m.tet_face_joint,
    )


def hold_contact_stiffness(model: Model, state: State) -> None:
    """Before a topology pass (split or conversion): every surface node that holds no stiffness yet holds the one in
    use as ω² = k / m, so that the pass changes neither the force nor the energy of its contact springs
    (kernels/fem_contact.py, "Held stiffness"); the force evaluation lets go of it once the node touches nothing.
    Launches only."""
    if model.node_capacity == 0 or model.node_contact_stiffness is None:
        return
    wp.launch(
        kf.hold_contact_stiffness_kernel,
        dim=model.node_capacity,
        inputs=[model.node_contact_stiffness, model.node_mass, state.node_count],
        outputs=[state.node_contact_hold],
        device=model.device,
    )


def contact_stiffness_in_use(model: Model, state: State) -> np.ndarray:
    """The penalty stiffness each live node's contact springs use now [N/m], shape (node_count,), float64: the
    stiffness per unit mass it holds times its mass where it holds one (since a split or conversion pass, until it
    touches nothing), else the lumped stiffness of its faces (kernels/fem_surface.py ``held_stiffness``). Reads back."""
    n = int(state.node_count.numpy()[0])
    lumped = model.node_contact_stiffness.numpy()[:n].astype(np.float64)
    hold = state.node_contact_hold.numpy()[:n]
    held = (hold * model.node_mass.numpy()[:n].astype(np.float64)).astype(np.float32).astype(np.float64)
    return np.where((hold > 0.0) & (lumped != 0.0), held, lumped)


def fem_contact_growth(
    model: Model, state: State, need_s: int | None = None, need_n: int | None = None
) -> tuple[int, int] | None:
    """New (max_sphere_faces, max_node_faces), ×2 until the largest counts seen fit, or None when both fit.
    ``need_s``, ``need_n``: those counts as already read back (None: read them from the state now)."""
    if model.node_capacity == 0:
        return None
    ks, kn = model.max_sphere_faces, model.max_node_faces
    if need_s is None:
        need_s = int(state.sphere_face_needed.numpy()[0])
    if need_n is None:
        need_n = int(state.node_face_needed.numpy()[0])
    if need_s <= ks and need_n <= kn:
        return None
    while ks < need_s:
        ks *= 2
    while kn < need_n:
        kn *= 2
    return ks, kn


def _regrow_rows(a: wp.array, rows: int, old_k: int, new_k: int) -> wp.array:
    host = a.numpy().reshape(rows, old_k, *a.numpy().shape[1:])
    pad = [(0, 0), (0, new_k - old_k)] + [(0, 0)] * (host.ndim - 2)
    return wp.array(np.pad(host, pad).reshape(rows * new_k, *host.shape[2:]), dtype=a.dtype, device=a.device)


def regrow_fem_contacts(model: Model, state: State, max_sphere_faces: int, max_node_faces: int) -> tuple[Model, State]:
    """A model and state with more candidate slots per sphere and node, the existing slots copied over."""
    pcap, ncap = sphere_face_rows(model), model.node_capacity
    ks, kn = model.max_sphere_faces, model.max_node_faces
    fields = {
        "sphere_face_index": _regrow_rows(state.sphere_face_index, pcap, ks, max_sphere_faces),
        "sphere_face_shear": _regrow_rows(state.sphere_face_shear, pcap, ks, max_sphere_faces),
        "node_face_index": _regrow_rows(state.node_face_index, ncap, kn, max_node_faces),
    }
    model = dataclasses.replace(model, max_sphere_faces=max_sphere_faces, max_node_faces=max_node_faces)
    return model, dataclasses.replace(state, **fields)


def launch_fem_contact_energy(model: Model, state: State, node_e: wp.array) -> None:
    """Each live node's share of the elastic energy of its node–face and node–wall contacts [J] into ``node_e``
    (float64, shape (node_capacity,); launch only; nothing without nodes or faces)."""
    m, s = model, state
    if m.node_capacity == 0 or m.face_capacity == 0:
        return
    d = m.device
    wp.launch(
        kf.fem_contact_energy_kernel,
        dim=m.node_capacity,
        inputs=[
            m.node_contact_stiffness,
            m.node_mass,
            m.tet_nodes,
            m.tet_face_nbr,
            m.star_offset,
            m.star_count,
            m.star_tets,
            m.face_nodes,
            m.face_joint,
            m.face_tet,
            m.tet_material,
            m.node_contact_material,
            m.fem_pair_table,
            m.joint_material_table,
            m.num_materials,
            m.wall_normal,
            m.wall_material,
            m.num_walls,
            m.face_depth,
            m.max_node_faces,
            s.node_count,
            s.node_q,
            s.node_face_spring,
            s.node_face_offset,
            s.node_face_shear,
            s.node_wall_shear,
            s.node_contact_hold,
            s.wall_point,
        ],
        outputs=[node_e],
        device=d,
    )


def has_sphere_face_energy(model: Model) -> bool:
    """Whether the model has sphere–face contacts whose springs hold energy: spheres and boundary faces (reads the
    radii back)."""
    return bool(model.face_capacity and model.particle_capacity and model.max_radius > 0.0)


def launch_sphere_face_energy(model: Model, state: State, sphere_e: wp.array) -> None:
    """Each live sphere's elastic energy of its sphere–face contacts [J] into ``sphere_e`` (float64, shape
    (particle_capacity,); launch only: call where :func:`has_sphere_face_energy` holds)."""
    m, s, d = model, state, model.device
    _, kernel = kf.make_sphere_face_kernel(m.normal_model, m.tangential_model, m.rolling_model, False)
    wp.launch(
        kernel,
        dim=m.particle_capacity,
        inputs=[
            m.particle_radius,
            m.particle_inv_mass,
            m.particle_material,
            m.pair_table,
            m.num_materials,
            m.node_inv_mass,
            m.tet_material,
            m.face_nodes,
            m.face_tet,
            m.face_radius,
            m.max_sphere_faces,
            s.particle_count,
            s.particle_q,
            s.sphere_face_count,
            s.sphere_face_index,
            s.sphere_face_shear,
            s.node_q,
        ],
        outputs=[sphere_e],
        device=d,
    )


def fem_contact_energy(model: Model, state: State) -> tuple[float, float]:
    """Elastic energy of the FEM contacts and intact joint elements [J], and the energy they dissipated [J].
    Allocates and reads back: call between steps."""
    m, s = model, state
    if m.node_capacity == 0 or m.face_capacity == 0:
        return 0.0, 0.0
    node_e = wp.zeros(m.node_capacity, dtype=wp.float64, device=m.device)
    launch_fem_contact_energy(m, s, node_e)
    elastic = float(node_e.numpy().sum()) + joint_energy(m, s)
    if has_sphere_face_energy(m):
        sphere_e = wp.zeros(m.particle_capacity, dtype=wp.float64, device=m.device)
        launch_sphere_face_energy(m, s, sphere_e)
        elastic += float(sphere_e.numpy().sum())
    dissipated = float(s.node_energy_contact.numpy()[: int(s.node_count.numpy()[0])].sum())
    return elastic, dissipated


def sphere_face_dissipated(model: Model, state: State) -> float:
    """What the sphere–face contacts dissipated [J]: the spheres' share (the half of the work behind each evaluation,
    the sphere's half ahead, minus the change of the springs' energy) and the face nodes' (their half ahead), one line
    (kernels/sphere_face.py). Reads back: call between steps."""
    m, s = model, state
    if m.face_capacity == 0:
        return 0.0
    n, nn = int(s.particle_count.numpy()[0]), int(s.node_count.numpy()[0])
    spheres = float(s.sphere_face_dissipated.numpy()[:n].sum()) if sphere_face_rows(m) else 0.0
    return spheres + float(s.node_energy_sphere_face.numpy()[:nn].sum())


def contact_critical_step_at(
    points: np.ndarray,
    tets: np.ndarray,
    young: np.ndarray,
    density: np.ndarray,
    joints: JointData,
    joint_props: list[JointProps],
    stiffness_factor: float,
    damping_ratio: float,
    face_normal_stiffness: float = 0.0,
) -> tuple[float, int, int]:
    """Stable step of the FEM contacts and joint elements [s] (before the safety factor), from the unsplit mesh, and
    the node that sets it with its joint set (-1 off the joints).

    A node on a surface (boundary faces and both sides of every joint) has the penalty stiffness
    k = Σ (f E / h + k_n / 2) A / 3 over its surface faces (h = 3 V₀ / A; a joint takes f or its normal stiffness
    k_n, kernels.joints.joint_face_spring) and mass m = Σ ρ V₀ / 4 over the tets on its side. Off
    the joints that is the whole star; on a joint the side is not known before the split, but by the mediant
    inequality k / m is at most the largest ratio, over the tets t at the node, of t's share of k to ρ V₀ / 4. Two
    such nodes pressed together by both passes of the contact (or a joint element, of the same stiffness) form the
    relative mode ω² = (k_A + k_B)(1/m_A + 1/m_B) = 4 k/m for equal sides; a node on a wall has ω² = k/m. A node
    holds a spring per face plane direction it lies behind (kernels/node_face_target.py), their normals pairwise
    |n_s · n_t| ≤ cos θ_g, so along any direction its springs are no stiffer than SPRING_BOUND k = 2 k (Gershgorin,
    ``PLANE_GROUP_COS``). Hence dt = 2/ω (sqrt(1 + ζ²) - ζ) with ω² = 4 SPRING_BOUND max k/m. For a regular mesh this
    is about h / (2 c_bar sqrt(2 f)), c_bar = sqrt(E/ρ).

    Args:
        points: (N, 3) [m].
        tets: (M, 4), positively oriented.
        young: E per tet [Pa], (M,).
        density: ρ per tet [kg/m³], (M,).
        joints: joint faces and sets.
        joint_props: per set.
        stiffness_factor: f of other faces.
        damping_ratio: the largest ζ of the contact dashpots [-].
        face_normal_stiffness: k_n / 2 of other faces [Pa/m] (Model.contact_face_normal_stiffness).

    Returns:
        The step [s] (inf without tets), the node of the mesh that sets it (-1 for none), its joint set (-1 for none).
    """
    tets = np.asarray(tets, dtype=np.int64)
    if len(tets) == 0:
        return math.inf, -1, -1
    x = np.asarray(points, dtype=np.float64)
    faces = tets[:, TET_FACES]  # (M, 4, 3)
    key = np.sort(faces, axis=2).reshape(-1, 3)
    group, size = row_groups(key)
    surface = size[group] == 1
    factor = np.full(len(key), float(stiffness_factor))
    per_area = np.full(len(key), float(face_normal_stiffness))  # k_n / 2 [Pa/m] (JointProps.normal_stiffness)
    if len(joints):
        jkey = np.sort(np.asarray(joints.faces, dtype=np.int64), axis=1)
        jfactor = np.array([joint_props[k].penalty_factor for k in joints.face_set], dtype=np.float64)
        jper_area = np.array([joint_props[k].face_normal_stiffness for k in joints.face_set], dtype=np.float64)
        both = np.concatenate([key, jkey])
        inv, _ = row_groups(both)
        lookup = np.full(inv.max() + 1, -1, dtype=np.int64)
        lookup[inv[len(key) :]] = np.arange(len(jkey))
        hit = lookup[inv[: len(key)]]
        surface |= hit >= 0
        factor = np.where(hit >= 0, jfactor[np.maximum(hit, 0)], factor)
        per_area = np.where(hit >= 0, jper_area[np.maximum(hit, 0)], per_area)
    xf = x[faces]
    area = 0.5 * np.linalg.norm(np.cross(xf[:, :, 1] - xf[:, :, 0], xf[:, :, 2] - xf[:, :, 0]), axis=2).reshape(-1)
    volume = np.abs(np.linalg.det(x[tets][:, 1:] - x[tets][:, :1])) / 6.0
    tet_of = np.repeat(np.arange(len(tets)), 4)
    spring = factor * young[tet_of] * area / (3.0 * volume[tet_of]) + per_area  # [Pa/m], kernels.joints
    k_face = np.where(surface, spring * area / 3.0, 0.0).reshape(-1, 4)
    # Node a of a tet lies on faces k != a: its share of the penalty is the sum of those faces' springs.
    share = k_face.sum(axis=1)[:, None] - k_face  # (M, 4): node a gets every face but the one opposite it
    quarter = 0.25 * density * volume
    n = len(x)
    k_node = np.bincount(tets.ravel(), weights=share.ravel(), minlength=n)
    m_node = np.bincount(tets.ravel(), weights=np.repeat(quarter, 4), minlength=n)
    ratio = np.divide(k_node, m_node, out=np.zeros(n), where=m_node > 0)
    joint_of = np.full(n, -1, dtype=np.int64)
    if len(joints):
        joint_of[np.asarray(joints.faces, dtype=np.int64).ravel()] = np.repeat(joints.face_set, 3)
        bound = np.zeros(n)
        np.maximum.at(bound, tets.ravel(), (share / quarter[:, None]).ravel())
        ratio = np.where(joint_of >= 0, bound, ratio)
    node = int(np.argmax(ratio))
    k_over_m = float(ratio[node])
    if k_over_m <= 0.0:
        return math.inf, -1, -1
    omega = math.sqrt(4.0 * kf.SPRING_BOUND * k_over_m)
    return 2.0 / omega * (math.sqrt(1.0 + damping_ratio**2) - damping_ratio), node, int(joint_of[node])
