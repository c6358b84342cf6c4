"""Rigid blocks (host side): the switch from deformable tets to rigid bodies, the body stages of a step and their energy
(their stable step: warpdem.stages.rigid_step; LDEC's original mode, ldec_fem_dem_fracture.txt §2–§4; kernels/rigid.py
has the physics).

What a block is. A block is a connected set of active tets that may turn rigid (``Model.tet_may_rigid``), connected
through shared nodes: the union–find labelling of the fragments (warpdem.stages.fragments, kernels/fragments.py) over
those tets alone. Joint pre-splits, cracks and conversion have already cut the mesh where the rock is jointed or broken,
so a block is what is left in one piece. Intact joint and cohesive elements do not glue blocks together: they stay what
they are, forces between the nodes of two blocks, exactly like the node–face contacts, so joints behave the same in
both modes (cohesion, tensile strength and friction with history, warpdem.stages.joints). A node shared by a rigid tet
and a deformable one (a rigid region next to a deformable one) belongs to the block; the deformable tet's force on it
becomes a force on the body.

The switch (:func:`make_bodies`, called by :meth:`warpdem.simulation.Simulation.switch_to_rigid`):

- mass M = Σ m_i over the block's nodes (their lumped masses, float64 sum), centre of mass C = Σ m_i x_i / M (for
  lumped masses ρV/4 this is the exact centre of mass of the tets), momentum P = Σ m_i v_i, angular momentum
  L = Σ m_i (x_i − C) × v_i: the body takes all of them exactly (v = P / M);
- inertia: exact for the tets, I = tr(J) 1 − J with J = Σ_t m_t/20 (Σ_a r_a r_aᵀ + s sᵀ), r_a the vertices from C,
  s = Σ_a r_a, m_t = ρ V₀ (the second moment of a uniform tet), plus, as point masses, whatever part of a node's
  mass its block's tets do not account for (the share of a neighbouring deformable tet). A box block gives
  M (b² + c²)/12 whatever its tet mesh. The principal axes come from numpy's ``eigh`` in float64;
- roller constraints: the held components of its nodes (``node_motion``: a roller holds the component along its
  normal, an edge of two rollers two, a fixed node all three), joined over the block, say how it may move: none held,
  free; one direction n (nodes on one roller plane, or on two parallel ones: a slice between two roller walls), in
  the plane and about n (kernels/rigid.py integrates that motion exactly, I_n = n·I n); two, along the line of the
  third axis, without turning; three, or a fixed or driven node (or one without inverse mass), held in place whole.
  The body keeps the allowed part of its nodes' momentum (P less its held components, L·n about the plane's normal);
  the rest goes to the rollers, and the kinetic energy it took is booked with the switch's release. A block that
  touches a plane at one node or along one edge is held to it as if a face lay on it (the subspace above, rather
  than the larger one that a point or edge on a bilateral roller would leave, which changes as the block turns);
- the nodes get ``node_motion = NODE_RIGID`` (the node kernels leave them alone) and the tets ``tet_active =
  TET_RIGID`` (no elastic force, stress or strain energy; still surface, contact and fragment material);
- the strain energy of the block's tets and the kinetic energy of the element modes (the nodes' kinetic energy
  beyond the body's), with the switch's change of the shadow term, are booked as ``released_rigid_switch``.

The step (warpdem.simulation): after the node kernels' drift, :func:`drift_bodies` kicks, translates and rotates the
bodies and sets their nodes' displacements and velocities; after the forces, :func:`reduce_body_forces` sums the
nodes' forces into a force and torque per body; the second half kick is :func:`kick_bodies`. Fracture and
conversion passes stop at the switch: a rigid block neither splits nor converts.

Stable step (:func:`rigid_critical_step`): with no element modes left, the contact springs and the non-reflecting
dashpots on the bodies set it; :func:`rigid_step_after_switch` adds what still bounds the deformable parts left.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import rigid as kr
from ..kernels.tets import TET_ACTIVE
from ..model import RIGID_BODY_FIELDS, RIGID_NODE_FIELDS, Model, State
from .fragments import block_labels
from .integrate import book_half_ahead

__all__ = [
    "NODE_FREE_DIRECTIONS",
    "RigidReport",
    "angular_velocities",
    "body_energy",
    "body_frames",
    "box_inertia",
    "drift_bodies",
    "element_mode_energy",
    "has_bodies",
    "kick_bodies",
    "make_bodies",
    "pose_nodes",
    "reduce_body_forces",
    "roller_constraints",
    "tet_inertia",
]


NODE_FREE_DIRECTIONS = np.array(
    [[1, 1, 1], [0, 0, 0], [0, 0, 1], [0, 1, 1], [1, 0, 1], [1, 1, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0]],
    dtype=np.float64,
)
"""Components of a node's velocity that move, by ``node_motion`` (kernels/tets.py ``node_free_directions``; the last
row: a node of a rigid body, which the body moves, kernels/rigid.py ``NODE_RIGID``)."""


@dataclass
class RigidReport:
    """What a switch to rigid blocks did.

    Attributes:
        bodies: rigid bodies made.
        fixed: of which held in place.
        planar: of which on a roller plane (moving in it).
        lines: of which between two roller planes (moving along their line).
        nodes: nodes that follow a body.
        tets: tets made rigid.
        released: energy booked as ``released_rigid_switch`` [J].
        shadow: of which the change of Verlet's shadow term (the forces re-made on the bodies' masses: a switch at
            rest releases no strain or element kinetic energy, only this) [J].
        critical_dt: the stable step after the switch (:func:`rigid_step_after_switch`, before the safety factor)
            [s].
        deformable_dt: the builder's critical step of the deformable model (``Model.critical_dt`` at the switch)
            [s]; set by the Simulation.
        dt_before: the run's time step at the switch [s]; set by the Simulation and the runner.
        dt_after: the run's time step after the switch (with ``dt = "auto"`` the runner takes the rigid step at the
            switch, warpdem.runner.take_rigid_step; an explicit dt is kept) [s]; set by the Simulation and the
            runner.
    """

    bodies: int
    fixed: int
    nodes: int
    tets: int
    planar: int = 0
    lines: int = 0
    released: float = 0.0
    shadow: float = 0.0
    critical_dt: float = math.inf
    deformable_dt: float = math.nan
    dt_before: float = math.nan
    dt_after: float = math.nan

    def format(self) -> str:
        rollers = f", {self.planar} on a roller plane, {self.lines} on two" if self.planar or self.lines else ""
        text = (
            f"rigid switch: {self.bodies} blocks ({self.fixed} held{rollers}), {self.nodes} nodes, {self.tets} tets; "
            f"{self.released:.6g} J released{self._shadow_part()}; stable step {self.critical_dt:.4g} s rigid against "
            f"{self.deformable_dt:.4g} s deformable ({self.critical_dt / self.deformable_dt:.3g}×)"
        )
        if math.isfinite(self.dt_after) and self.dt_after != self.dt_before:
            text += (
                f"; time step {self.dt_after:.4g} s after the switch ({self.dt_after / self.dt_before:.3g}× "
                f"the {self.dt_before:.4g} s before)"
            )
        elif math.isfinite(self.dt_before):
            text += f"; time step kept at {self.dt_before:.4g} s"
            if self.dt_before > self.critical_dt:
                # An explicit run.dt is kept as the user set it; say so where it is past the new stable step.
                text += ' (above the stable step after the switch: lower run.dt or use dt = "auto")'
        return text

    def _shadow_part(self) -> str:
        """The shadow term's share of the release, said where there is one: without it a switch at rest would read as
        a negative release of strain energy."""
        if self.shadow == 0.0:
            return ""
        return (
            f" ({self.released - self.shadow:.6g} J strain and element modes, {self.shadow:.6g} J Verlet's shadow term)"
        )


def tet_inertia(vertices: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Second moment J = ∫ r rᵀ dm of uniform tets about the origin of ``vertices``: m/20 (Σ_a r_a r_aᵀ + s sᵀ),
    s = Σ_a r_a [kg m²].

    Args:
        vertices: (M, 4, 3) [m], relative to the point the moment is taken about. mass: (M,) [kg].

    Returns:
        (M, 3, 3) float64.
    """
    r = np.asarray(vertices, dtype=np.float64)
    s = r.sum(axis=1)
    outer = np.einsum("tai,taj->tij", r, r) + np.einsum("ti,tj->tij", s, s)
    return (np.asarray(mass, dtype=np.float64) / 20.0)[:, None, None] * outer


def box_inertia(mass: float, size: tuple[float, float, float]) -> np.ndarray:
    """Principal moments of a uniform box about its centre, M (b² + c²)/12 etc. [kg m²], shape (3,)."""
    a, b, c = (float(x) for x in size)
    return mass / 12.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])


def make_bodies(model: Model, state: State) -> tuple[State, RigidReport]:
    """Turn every block (module docstring) into a rigid body: the body arrays of the state filled, the nodes' motion
    set to ``NODE_RIGID`` (a Model array, changed in place) and the tets' ``tet_active`` to ``TET_RIGID``. Positions
    do not move; the nodes' velocities become the body's rigid field at the next pose (:func:`pose_nodes`). Between
    steps; reads back.

    Returns:
        The state with its rigid fields, and what was done.
    """
    device = model.device
    nn = int(state.node_count.numpy()[0])
    nt = int(state.tet_count.numpy()[0])
    label, count = block_labels(model, state)
    tets = model.tet_nodes.numpy()[:nt].astype(np.int64)
    active = state.tet_active.numpy()[:nt]
    may = model.tet_may_rigid.numpy()[:nt] != 0 if model.tet_may_rigid is not None else np.ones(nt, dtype=bool)
    rigid_tet = (active == int(TET_ACTIVE)) & may
    node_body = np.full(model.node_capacity, -1, dtype=np.int32)
    node_body[:nn] = label
    mass = model.node_mass.numpy()[:nn].astype(np.float64)
    x = model.node_ref_q.numpy()[:nn].astype(np.float64) + state.node_u.numpy()[:nn].astype(np.float64)
    v = state.node_qd.numpy()[:nn].astype(np.float64)
    in_body = label >= 0
    body_of = label[in_body].astype(np.int64)

    def per_body(values: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(body_of, weights=values[:, k], minlength=count) for k in range(3)], axis=1)

    m_i = mass[in_body]
    body_mass = np.bincount(body_of, weights=m_i, minlength=count)
    com = per_body(m_i[:, None] * x[in_body]) / body_mass[:, None]
    momentum = per_body(m_i[:, None] * v[in_body])
    r = x[in_body] - com[body_of]
    angular = per_body(m_i[:, None] * np.cross(r, v[in_body]))

    # Inertia: the block's tets exactly, each node's mass its tets do not account for as a point mass.
    tet_body = label[tets[rigid_tet, 0]].astype(np.int64)
    density = model.tet_material_table.numpy()["density"].astype(np.float64)
    tet_mass = density[model.tet_material.numpy()[:nt][rigid_tet]] * model.tet_volume.numpy()[:nt][rigid_tet]
    rt = x[tets[rigid_tet]] - com[tet_body][:, None, :]
    second = np.zeros((count, 3, 3))
    np.add.at(second, tet_body, tet_inertia(rt, tet_mass))
    share = np.bincount(tets[rigid_tet].ravel(), weights=np.repeat(0.25 * tet_mass, 4), minlength=nn)
    rest = np.maximum(mass - share, 0.0)[in_body]
    np.add.at(second, body_of, rest[:, None, None] * np.einsum("ni,nj->nij", r, r))
    inertia_tensor = np.trace(second, axis1=1, axis2=2)[:, None, None] * np.eye(3) - second
    moments, axes = np.linalg.eigh(inertia_tensor)
    # Right-handed axes, so that a body's frame is a rotation of the world's.
    axes[:, :, 2] *= np.sign(np.linalg.det(axes))[:, None]

    constraint, axis, fixed = roller_constraints(model, label, count)

    order = np.argsort(body_of, kind="stable")
    rigid_nodes = np.flatnonzero(in_body)[order].astype(np.int32)
    node_count = np.bincount(body_of, minlength=count).astype(np.int32)
    start = (np.cumsum(node_count) - node_count).astype(np.int32)
    # The allowed part of the nodes' momentum (the rest is the rollers' impulse at the switch).
    velocity = np.where(fixed[:, None], 0.0, _allowed(constraint, axis, momentum / body_mass[:, None], False))
    angular = np.where(fixed[:, None], 0.0, _allowed(constraint, axis, angular, True))
    r0 = np.zeros((model.node_capacity, 3))
    r0[:nn][in_body] = r
    u0 = np.zeros((model.node_capacity, 3), dtype=np.float32)
    u0[:nn] = state.node_u.numpy()[:nn]
    identity = np.zeros((count, 4))
    identity[:, 3] = 1.0
    host = {
        "body_mass": body_mass,
        "body_inertia": moments,
        "body_axes": axes,
        "body_fixed": fixed.astype(np.int32),
        "body_constraint": constraint,
        "body_axis": axis,
        "body_dc": np.zeros((count, 3)),
        "body_v": velocity,
        "body_q": identity,
        "body_l": angular,
        "body_f": np.zeros((count, 3)),
        "body_t": np.zeros((count, 3)),
        # The drift's scratch (kernels/rigid.py node_velocity_ahead): written by each drift before it is read.
        "body_q_before": identity,
        "body_omega_ahead": np.zeros((count, 3)),
        "body_node_start": start,
        "body_node_count": node_count,
        "node_body": node_body,
        "node_rigid_r0": r0,
        "node_rigid_u0": u0,
    }
    types = {**RIGID_BODY_FIELDS, **RIGID_NODE_FIELDS}
    fields = {name: wp.array(values, dtype=types[name], device=device) for name, values in host.items()}
    fields["rigid_nodes"] = wp.array(rigid_nodes, dtype=int, device=device)
    new_motion = model.node_motion.numpy()
    new_motion[:nn][in_body] = int(kr.NODE_RIGID)
    model.node_motion.assign(new_motion)
    tet_active = state.tet_active.numpy()
    tet_active[:nt][rigid_tet] = int(kr.TET_RIGID)
    state.tet_active.assign(tet_active)
    state.rigid_switched.fill_(1)
    state = dataclasses.replace(state, **fields)
    free = ~fixed
    report = RigidReport(
        count,
        int(fixed.sum()),
        int(in_body.sum()),
        int(rigid_tet.sum()),
        planar=int(np.sum(free & (constraint == int(kr.BODY_PLANE)))),
        lines=int(np.sum(free & (constraint == int(kr.BODY_LINE)))),
    )
    return state, report


def roller_constraints(model: Model, label: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How each block may move under the held components of its nodes (module docstring): the held axes of its nodes
    joined (``NODE_FREE_DIRECTIONS``), a node without inverse mass or with a velocity driver holding all three.

    Args:
        label: block of each live node, -1 for none, shape (node_count,). count: blocks.

    Returns:
        ``body_constraint`` (0 free, 1 plane, 2 line), shape (count,), int32; ``body_axis`` (the plane's normal or
        the line, a unit axis; zero when free), shape (count, 3), float64; held whole, shape (count,), bool.
    """
    nn = len(label)
    held_axes = 1.0 - NODE_FREE_DIRECTIONS[model.node_motion.numpy()[:nn]]
    pinned = model.node_inv_mass.numpy()[:nn] <= 0.0
    if model.loads is not None and model.loads.num_drivers:
        pinned |= model.loads.node_driver.numpy()[:nn] >= 0
    held_axes[pinned] = 1.0
    mine = label >= 0
    body_of = label[mine].astype(np.int64)
    union = np.stack([np.bincount(body_of, weights=held_axes[mine, k], minlength=count) > 0 for k in range(3)], axis=1)
    held = union.sum(axis=1)
    constraint = np.where(held == 1, int(kr.BODY_PLANE), np.where(held == 2, int(kr.BODY_LINE), int(kr.BODY_FREE)))
    # The plane's normal is its held axis; the line is the one axis left free.
    axis = np.where((held == 1)[:, None], union, np.where((held == 2)[:, None], ~union, False)).astype(np.float64)
    return constraint.astype(np.int32), axis, held == 3


def _allowed(constraint: np.ndarray, axis: np.ndarray, x: np.ndarray, rotation: bool) -> np.ndarray:
    """The part of per-body vectors x, shape (B, 3), the rollers allow (kernels/rigid.py ``allowed_translation`` and
    ``allowed_rotation``, float64)."""
    along = np.sum(x * axis, axis=1, keepdims=True) * axis
    plane = constraint[:, None] == int(kr.BODY_PLANE)
    line = constraint[:, None] == int(kr.BODY_LINE)
    if rotation:
        return np.where(plane, along, np.where(line, 0.0, x))
    return np.where(plane, x - along, np.where(line, along, x))


def has_bodies(state: State) -> bool:
    """Whether the state holds rigid bodies (host: the body arrays' length)."""
    return state.body_mass.shape[0] > 0


def every_node_rigid(model: Model, state: State) -> bool:
    """Whether every live FEM node is a rigid body's node with no velocity driver (host: reads back). Then the node
    kernels' drift has nothing to do that the bodies' pose does not (it starts their accumulators,
    kernels/rigid.py ``pose_nodes_kernel``), and the step skips it (warpdem.stages.integrate ``kick_drift``)."""
    if not has_bodies(state):
        return False
    nn = int(state.node_count.numpy()[0])
    rigid = model.node_motion.numpy()[:nn] == int(kr.NODE_RIGID)
    driver = getattr(model.loads, "node_driver", None)
    driven = driver.numpy()[:nn] >= 0 if isinstance(driver, wp.array) else np.zeros(nn, dtype=bool)
    return bool(np.all(rigid & ~driven))


def drift_bodies(model: Model, state: State, after_second_half: bool, deformable: bool = True) -> None:
    """Kick the bodies by dt/2 (twice with ``after_second_half``: the second half of the step before), translate by
    dt, turn by the free rotor over dt (recording the pose before it and the spin there, which the half ahead of the
    last forces' work is booked against: kernels/rigid.py ``node_velocity_ahead``), then set their nodes'
    displacements and velocities, and book the half ahead of the viscous forces of deformable tets on those nodes
    (launches only). ``deformable`` = False (no tet is left deformable, so no viscous force acts on a body's node)
    skips that booking pass over the node slots."""
    m, s = model, state
    kernel = kr.kick_drift_bodies_kernel if after_second_half else kr.drift_bodies_kernel
    wp.launch(
        kernel,
        dim=s.body_mass.shape[0],
        inputs=[
            wp.vec3(*m.gravity),
            m.dt,
            s.body_mass,
            s.body_inertia,
            s.body_axes,
            s.body_fixed,
            s.body_constraint,
            s.body_axis,
            s.body_f,
            s.body_t,
        ],
        outputs=[s.body_dc, s.body_v, s.body_q, s.body_l, s.body_q_before, s.body_omega_ahead],
        device=m.device,
    )
    pose_nodes(m, s, move=True)
    if not deformable:
        return
    # The viscous forces of deformable tets on the bodies' nodes (the node drift leaves them): their half ahead.
    book_half_ahead(m, s, m.dt, s.node_f_viscous, s.node_energy_damping, -1.0, rigid_only=True)


def kick_bodies(model: Model, state: State) -> None:
    """The second half kick of the bodies with the forces at the new positions, then their nodes' velocities."""
    m, s = model, state
    wp.launch(
        kr.kick_bodies_kernel,
        dim=s.body_mass.shape[0],
        inputs=[
            wp.vec3(*m.gravity),
            m.dt,
            s.body_mass,
            s.body_fixed,
            s.body_constraint,
            s.body_axis,
            s.body_f,
            s.body_t,
        ],
        outputs=[s.body_v, s.body_l],
        device=m.device,
    )
    pose_nodes(m, s, move=False)


def pose_nodes(model: Model, state: State, move: bool) -> None:
    """Nodes from their bodies' pose: displacement and position when ``move``, and velocity (launches only)."""
    m, s = model, state
    wp.launch(
        kr.pose_nodes_kernel,
        dim=s.body_mass.shape[0],
        inputs=[
            m.node_ref_q,
            # Without FEM contact (half skin < 0) the stiffness is never read: any float array of the nodes stands in.
            m.node_contact_stiffness if m.node_contact_stiffness is not None else m.node_mass,
            0.5 * m.fem_skin if m.face_capacity else -1.0,
            s.body_node_start,
            s.body_node_count,
            s.rigid_nodes,
            s.node_rigid_r0,
            s.node_rigid_u0,
            s.body_inertia,
            s.body_axes,
            s.body_constraint,
            s.body_axis,
            s.body_dc,
            s.body_v,
            s.body_q,
            s.body_l,
            s.node_q_at_fem_build,
            int(move),
        ],
        outputs=[s.node_u, s.node_q, s.node_qd, s.node_f, s.fem_rebuild_flag],
        device=m.device,
    )


def reduce_body_forces(model: Model, state: State) -> None:
    """Sum the nodes' forces into each body's force and torque about its centre of mass (launches only)."""
    s = state
    wp.launch(
        kr.reduce_body_forces_kernel,
        dim=s.body_mass.shape[0],
        inputs=[s.body_fixed, s.body_node_start, s.body_node_count, s.rigid_nodes, s.node_rigid_r0, s.body_q, s.node_f],
        outputs=[s.body_f, s.body_t],
        device=model.device,
    )


def _rotations(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions (x, y, z, w), shape (B, 3, 3)."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )


def body_frames(state: State) -> tuple[np.ndarray, np.ndarray]:
    """Principal axes now (columns, world frame), shape (B, 3, 3), and the principal moments, shape (B, 3) [kg m²]
    (reads back)."""
    axes = _rotations(state.body_q.numpy()) @ state.body_axes.numpy()
    return axes, state.body_inertia.numpy()


def _about_axis(state: State, axes: np.ndarray, moments: np.ndarray) -> np.ndarray:
    """I_n = n·I n of every body about its ``body_axis`` [kg m²], shape (B,) (nan where the axis is zero)."""
    n = state.body_axis.numpy()
    along = np.einsum("bik,bi->bk", axes, n)
    with np.errstate(invalid="ignore"):
        return np.where(np.sum(n * n, axis=1) > 0.0, np.sum(moments * along * along, axis=1), np.nan)


def _inverse_inertia_times(state: State, axes: np.ndarray, moments: np.ndarray, x: np.ndarray) -> np.ndarray:
    """I⁻¹ x of every body in the metric of its allowed rotations [rad/s per kg m²/s], shape (B, 3): R I⁻¹ Rᵀ x when
    free, (x·n / I_n) n on a roller plane, zero on a line (kernels/rigid.py ``body_angular_velocity``)."""
    body_x = np.einsum("bik,bi->bk", axes, x)
    free = np.einsum("bik,bk->bi", axes, body_x / moments)
    n = state.body_axis.numpy()
    constraint = state.body_constraint.numpy()
    with np.errstate(invalid="ignore", divide="ignore"):
        plane = (np.sum(x * n, axis=1) / _about_axis(state, axes, moments))[:, None] * n
    return np.where(
        (constraint == int(kr.BODY_PLANE))[:, None],
        plane,
        np.where((constraint == int(kr.BODY_LINE))[:, None], 0.0, free),
    )


def angular_velocities(state: State) -> np.ndarray:
    """ω of every body [rad/s], shape (B, 3), float64 (reads back): R I⁻¹ Rᵀ L, or on roller constraints what
    kernels/rigid.py ``body_angular_velocity`` gives."""
    axes, moments = body_frames(state)
    return _inverse_inertia_times(state, axes, moments, state.body_l.numpy())


def body_energy(model: Model, state: State) -> tuple[float, float]:
    """Kinetic energy of the bodies ½ M v² + ½ L·ω, and their Verlet shadow term dt²/8 (|F + M g|²/M + T·I⁻¹T)
    (as warpdem.stages.energy.EnergyBalance has it for spheres and nodes: kinetic − shadow is the leapfrog kinetic
    energy the translation conserves), held bodies excluded [J] (reads back). On roller constraints, of the allowed
    motion: F + M g and T projected as the kicks project them, ω and I⁻¹ of the allowed rotation."""
    if not has_bodies(state):
        return 0.0, 0.0
    free = state.body_fixed.numpy() == 0
    mass = state.body_mass.numpy()
    v = state.body_v.numpy()
    axes, moments = body_frames(state)
    constraint, axis = state.body_constraint.numpy(), state.body_axis.numpy()
    omega = _inverse_inertia_times(state, axes, moments, state.body_l.numpy())
    spin = np.sum(state.body_l.numpy() * omega, axis=1)
    kinetic = 0.5 * np.sum((mass * np.sum(v * v, axis=1) + spin)[free])
    g = np.asarray(model.gravity, dtype=np.float64)
    f = _allowed(constraint, axis, state.body_f.numpy() + mass[:, None] * g, False)
    t = _allowed(constraint, axis, state.body_t.numpy(), True)
    turn = np.sum(t * _inverse_inertia_times(state, axes, moments, t), axis=1)
    shadow = model.dt**2 / 8.0 * np.sum((np.sum(f * f, axis=1) / mass + turn)[free])
    return float(kinetic), float(shadow)


def element_mode_energy(model: Model, state: State) -> tuple[float, float]:
    """Kinetic energy of the element modes of the blocks that may turn rigid, and the nodes' whole kinetic energy
    [J] (reads back): per block, Σ ½ m_i v_i² − ½ |P|²/M − ½ L·I_n⁻¹L with the nodes' own (lumped) inertia I_n,
    what is left of the nodes' kinetic energy beyond the block's rigid motion (the criterion of
    ``rigid_energy_fraction``)."""
    nn = int(state.node_count.numpy()[0])
    label, count = block_labels(model, state)
    mass = model.node_mass.numpy()[:nn].astype(np.float64)
    v = state.node_qd.numpy()[:nn].astype(np.float64)
    total = 0.5 * float(np.sum(mass * np.sum(v * v, axis=1)))
    if count == 0:
        return 0.0, total
    x = model.node_ref_q.numpy()[:nn].astype(np.float64) + state.node_u.numpy()[:nn].astype(np.float64)
    keep = label >= 0
    b, m, x, v = label[keep].astype(np.int64), mass[keep], x[keep], v[keep]

    def per_body(values: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(b, weights=values[:, k], minlength=count) for k in range(3)], axis=1)

    body_mass = np.bincount(b, weights=m, minlength=count)
    com = per_body(m[:, None] * x) / body_mass[:, None]
    r = x - com[b]
    p = per_body(m[:, None] * v)
    angular = per_body(m[:, None] * np.cross(r, v))
    second = np.zeros((count, 3, 3))
    np.add.at(second, b, m[:, None, None] * np.einsum("ni,nj->nij", r, r))
    inertia = np.trace(second, axis1=1, axis2=2)[:, None, None] * np.eye(3) - second
    # The pseudo-inverse: a block whose nodes lie on a line has no inertia about it (and no momentum there).
    spin = np.einsum("bi,bij,bj->b", angular, np.linalg.pinv(inertia), angular)
    rigid = 0.5 * np.sum(np.sum(p * p, axis=1) / body_mass) + 0.5 * np.sum(spin)
    nodes = 0.5 * float(np.sum(m * np.sum(v * v, axis=1)))
    return max(nodes - float(rigid), 0.0), total
