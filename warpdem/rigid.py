"""Rigid blocks (host side): the switch from deformable tets to rigid bodies, the body stages of a step, their energy
and their stable step (LDEC's original mode, ldec_fem_dem_fracture.txt §2–§4; kernels/rigid.py has the physics).

What a block is. A block is a connected set of active tets that may turn rigid (``Model.tet_may_rigid``), connected
through shared nodes: the union–find labelling of the fragments (warpdem.fragments, kernels/fragments.py) over those
tets alone. Joint pre-splits, cracks and conversion have already cut the mesh where the rock is jointed or broken, so
a block is what is left in one piece. Intact joint and cohesive elements do not glue blocks together: they stay what
they are, forces between the nodes of two blocks, exactly like the node–face contacts, so joints behave the same in
both modes (cohesion, tensile strength and friction with history, warpdem.joints). A node shared by a rigid tet and
a deformable one (a rigid region next to a deformable one) belongs to the block; the deformable tet's force on it
becomes a force on the body.

The switch (:func:`make_bodies`, called by :meth:`warpdem.simulation.Simulation.switch_to_rigid`):

- mass M = Σ m_i over the block's nodes (their lumped masses, float64 sum), centre of mass C = Σ m_i x_i / M (for
  lumped masses ρV/4 this is the exact centre of mass of the tets), momentum P = Σ m_i v_i, angular momentum
  L = Σ m_i (x_i − C) × v_i: the body takes all of them exactly (v = P / M);
- inertia: exact for the tets, I = tr(J) 1 − J with J = Σ_t m_t/20 (Σ_a r_a r_aᵀ + s sᵀ), r_a the vertices from C,
  s = Σ_a r_a, m_t = ρ V₀ (the second moment of a uniform tet), plus, as point masses, whatever part of a node's
  mass its block's tets do not account for (the share of a neighbouring deformable tet). A box block gives
  M (b² + c²)/12 whatever its tet mesh. The principal axes come from numpy's ``eigh`` in float64;
- a block with a held node (fixed, roller, velocity driver, or no inverse mass) is held in place whole;
- the nodes get ``node_motion = NODE_RIGID`` (the node kernels leave them alone) and the tets ``tet_active =
  TET_RIGID`` (no elastic force, stress or strain energy; still surface, contact and fragment material);
- the strain energy of the block's tets and the kinetic energy of the element modes (the nodes' kinetic energy
  beyond the body's), with the switch's change of the shadow term, are booked as ``released_rigid_switch``.

The step (warpdem.simulation): after the node kernels' drift, :func:`drift_bodies` kicks, translates and rotates the
bodies and sets their nodes' displacements and velocities; after the forces, :func:`reduce_body_forces` sums the
nodes' forces into a force and torque per body; the second half kick is :func:`kick_bodies`. Fracture and
conversion passes stop at the switch: a rigid block neither splits nor converts.

Stable step (:func:`rigid_critical_step`): with no element modes left, the contact springs on the bodies set it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from .fragments import block_labels
from .kernels import rigid as kr
from .kernels.tets import NODE_FREE
from .model import RIGID_BODY_FIELDS, RIGID_NODE_FIELDS, Model, State

__all__ = [
    "RigidReport",
    "angular_velocities",
    "body_energy",
    "body_frames",
    "box_inertia",
    "contact_damping_ratio",
    "drift_bodies",
    "element_mode_energy",
    "has_bodies",
    "kick_bodies",
    "make_bodies",
    "pose_nodes",
    "reduce_body_forces",
    "rigid_critical_step",
    "rigid_time_step",
    "tet_inertia",
]


@dataclass
class RigidReport:
    """What a switch to rigid blocks did.

    Attributes:
        bodies: rigid bodies made; fixed: of which held in place; nodes: nodes that follow a body; tets: tets made
        rigid; released: energy booked as ``released_rigid_switch`` [J]; critical_dt: the stable step of the
        rigid blocks on their contacts (:func:`rigid_critical_step`, before the safety factor) [s]; deformable_dt:
        the builder's critical step of the deformable model (``Model.critical_dt`` at the switch) [s] (both set by
        the Simulation).
    """

    bodies: int
    fixed: int
    nodes: int
    tets: int
    released: float = 0.0
    critical_dt: float = math.inf
    deformable_dt: float = math.nan

    def format(self) -> str:
        return (
            f"rigid switch: {self.bodies} blocks ({self.fixed} held), {self.nodes} nodes, {self.tets} tets; "
            f"{self.released:.6g} J released; stable step {self.critical_dt:.4g} s rigid against "
            f"{self.deformable_dt:.4g} s deformable ({self.critical_dt / self.deformable_dt:.3g}×)"
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
    rigid_tet = (active == 1) & may
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

    motion = model.node_motion.numpy()[:nn]
    held = (motion != NODE_FREE) | (model.node_inv_mass.numpy()[:nn] <= 0.0)
    if model.loads is not None and model.loads.num_drivers:
        held |= model.loads.node_driver.numpy()[:nn] >= 0
    fixed = np.bincount(body_of, weights=held[in_body], minlength=count) > 0

    order = np.argsort(body_of, kind="stable")
    rigid_nodes = np.flatnonzero(in_body)[order].astype(np.int32)
    node_count = np.bincount(body_of, minlength=count).astype(np.int32)
    start = (np.cumsum(node_count) - node_count).astype(np.int32)
    velocity = np.where(fixed[:, None], 0.0, momentum / body_mass[:, None])
    angular = np.where(fixed[:, None], 0.0, angular)
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
        "body_dc": np.zeros((count, 3)),
        "body_v": velocity,
        "body_q": identity,
        "body_l": angular,
        "body_f": np.zeros((count, 3)),
        "body_t": np.zeros((count, 3)),
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
    report = RigidReport(count, int(fixed.sum()), int(in_body.sum()), int(rigid_tet.sum()))
    return state, report


def has_bodies(state: State) -> bool:
    """Whether the state holds rigid bodies (host: the body arrays' length)."""
    return state.body_mass.shape[0] > 0


def drift_bodies(model: Model, state: State, after_second_half: bool) -> None:
    """Kick the bodies by dt/2 (twice with ``after_second_half``: the second half of the step before), translate by
    dt, turn by the free rotor over dt, then set their nodes' displacements and velocities (launches only)."""
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
            s.body_f,
            s.body_t,
        ],
        outputs=[s.body_dc, s.body_v, s.body_q, s.body_l],
        device=m.device,
    )
    pose_nodes(m, s, move=True)


def kick_bodies(model: Model, state: State) -> None:
    """The second half kick of the bodies with the forces at the new positions, then their nodes' velocities."""
    m, s = model, state
    wp.launch(
        kr.kick_bodies_kernel,
        dim=s.body_mass.shape[0],
        inputs=[wp.vec3(*m.gravity), m.dt, s.body_mass, s.body_fixed, s.body_f, s.body_t],
        outputs=[s.body_v, s.body_l],
        device=m.device,
    )
    pose_nodes(m, s, move=False)


def pose_nodes(model: Model, state: State, move: bool) -> None:
    """Nodes from their bodies' pose: displacement and position when ``move``, and velocity (launches only)."""
    m, s = model, state
    wp.launch(
        kr.pose_nodes_kernel,
        dim=m.node_capacity,
        inputs=[
            m.node_ref_q,
            # Without FEM contact (half skin < 0) the stiffness is never read: any float array of the nodes stands in.
            m.node_contact_stiffness if m.node_contact_stiffness is not None else m.node_mass,
            0.5 * m.fem_skin if m.face_capacity else -1.0,
            s.node_count,
            s.node_body,
            s.node_rigid_r0,
            s.node_rigid_u0,
            s.body_inertia,
            s.body_axes,
            s.body_dc,
            s.body_v,
            s.body_q,
            s.body_l,
            s.node_q_at_fem_build,
            int(move),
        ],
        outputs=[s.node_u, s.node_q, s.node_qd, s.fem_rebuild_flag],
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


def angular_velocities(state: State) -> np.ndarray:
    """ω = R I⁻¹ Rᵀ L of every body [rad/s], shape (B, 3), float64 (reads back)."""
    axes, moments = body_frames(state)
    body_l = np.einsum("bik,bi->bk", axes, state.body_l.numpy())
    return np.einsum("bik,bk->bi", axes, body_l / moments)


def body_energy(model: Model, state: State) -> tuple[float, float]:
    """Kinetic energy of the bodies ½ M v² + ½ L·ω, and their Verlet shadow term dt²/8 (|F + M g|²/M + T·I⁻¹T)
    (as warpdem.simulation.EnergyBalance has it for spheres and nodes: kinetic − shadow is the leapfrog kinetic energy
    the translation conserves), held bodies excluded [J] (reads back)."""
    if not has_bodies(state):
        return 0.0, 0.0
    free = state.body_fixed.numpy() == 0
    mass = state.body_mass.numpy()[free]
    v = state.body_v.numpy()[free]
    axes, moments = body_frames(state)
    axes, moments = axes[free], moments[free]
    body_l = np.einsum("bik,bi->bk", axes, state.body_l.numpy()[free])
    kinetic = 0.5 * np.sum(mass * np.sum(v * v, axis=1)) + 0.5 * np.sum(body_l * body_l / moments)
    g = np.asarray(model.gravity, dtype=np.float64)
    f = state.body_f.numpy()[free] + mass[:, None] * g
    body_t = np.einsum("bik,bi->bk", axes, state.body_t.numpy()[free])
    shadow = model.dt**2 / 8.0 * (np.sum(np.sum(f * f, axis=1) / mass) + np.sum(body_t * body_t / moments))
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


def contact_damping_ratio(model: Model) -> float:
    """The largest damping ratio ζ of the FEM contacts and joints of a model [-] (0 without any)."""
    ratios = [0.0]
    if model.fem_pair_table is not None:
        ratios += model.fem_pair_table.numpy()["damp_n"].tolist()
    if model.joint_material_table is not None and model.joint_set_props:
        ratios += model.joint_material_table.numpy()["contact"]["damp_n"].tolist()
    return float(max(ratios))


def rigid_time_step(model: Model, state: State, safety_factor: float) -> Model:
    """The model with the time step of rigid blocks from the start: ``safety_factor`` × :func:`rigid_critical_step` of
    the bodies the switch will make (made on copies, so the model and state are left as they are). Only where the
    rigid bodies are all there is: every tet may turn rigid, no sphere and no non-reflecting dashpot (their own steps,
    which the builder folded into ``critical_dt``, would still hold); else the model as it is.
    """
    if model.tet_may_rigid is not None or model.max_radius > 0.0:
        return model
    if model.loads is not None and getattr(model.loads, "dashpots", None) is not None:
        return model
    probe = dataclasses.replace(model, node_motion=wp.clone(model.node_motion))
    bodies, _ = make_bodies(probe, state.clone())
    step = rigid_critical_step(probe, bodies, contact_damping_ratio(model))
    if not math.isfinite(step):
        return model
    return dataclasses.replace(
        model,
        dt=safety_factor * step,
        critical_dt=step,
        critical_dt_source="the contact springs of the rigid blocks (warpdem.rigid.rigid_critical_step)",
        deformable_critical_dt=model.critical_dt,
    )


def rigid_critical_step(model: Model, state: State, damping_ratio: float = 0.0) -> float:
    """Stable step of the rigid bodies on their contact springs [s], before the safety factor (reads back).

    Every surface node i of a body (penalty stiffness k_i = ``node_contact_stiffness``, warpdem.fem_contact) pressed
    by a contact at once gives the body the stiffness K = Σ k_i J_iᵀ J_i on its six velocities (J_i = [1, −[r_i]×],
    the node's velocity from the body's), against its mass matrix diag(M, M, M, I). A spring between two bodies
    stores ½ k |u_A − u_B|² ≤ k (|u_A|² + |u_B|²), so no mode of the assembly exceeds ω² = 2 max_b λ_max(M_b⁻¹ K_b),
    the largest over the bodies; dt = 2/ω (sqrt(1 + ζ²) − ζ) as for the nodes. Held bodies, and deformable nodes and
    tets (whose own steps still hold where some remain), are not counted.
    """
    if not has_bodies(state) or model.node_contact_stiffness is None:
        return math.inf
    free = np.flatnonzero(state.body_fixed.numpy() == 0)
    if len(free) == 0:
        return math.inf
    nodes = state.rigid_nodes.numpy()
    body = state.node_body.numpy()[nodes].astype(np.int64)
    k = model.node_contact_stiffness.numpy()[nodes].astype(np.float64)
    axes, moments = body_frames(state)
    r = np.einsum("bij,bj->bi", _rotations(state.body_q.numpy())[body], state.node_rigid_r0.numpy()[nodes])
    # Body-frame offsets, so that the rotational block of the mass matrix is diagonal.
    rb = np.einsum("nik,ni->nk", axes[body], r)
    cross = np.zeros((len(nodes), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -rb[:, 2], rb[:, 1], -rb[:, 0]
    cross[:, 1, 0], cross[:, 2, 0], cross[:, 2, 1] = rb[:, 2], -rb[:, 1], rb[:, 0]
    jac = np.concatenate([np.broadcast_to(np.eye(3), (len(nodes), 3, 3)), -cross], axis=2)  # (n, 3, 6)
    stiff = np.zeros((len(moments), 6, 6))
    np.add.at(stiff, body, k[:, None, None] * np.einsum("nia,nib->nab", jac, jac))
    mass = state.body_mass.numpy()
    inv_sqrt = 1.0 / np.sqrt(np.concatenate([np.repeat(mass[:, None], 3, axis=1), moments], axis=1))
    scaled = inv_sqrt[:, :, None] * stiff * inv_sqrt[:, None, :]
    lam = np.linalg.eigvalsh(scaled[free])[:, -1].max()
    if lam <= 0.0:
        return math.inf
    omega = math.sqrt(2.0 * lam)
    return 2.0 / omega * (math.sqrt(1.0 + damping_ratio**2) - damping_ratio)
