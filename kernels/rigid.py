"""Rigid blocks (LDEC's original mode, ldec_fem_dem_fracture.txt §2–§4): each joint-bounded block of tets is one rigid
body, its nodes follow it, and their forces reduce to a force and a torque on it.

A body holds, in float64 (few bodies, and the pose arithmetic must keep the displacements' precision):

- its mass M [kg], principal moments (I1, I2, I3) [kg m²] and the principal axes A at the switch (columns, world
  frame);
- the displacement of its centre of mass since the switch, dc [m], and its velocity v [m/s];
- its rotation since the switch as a unit quaternion q (world frame: the principal axes now are R(q) A);
- its angular momentum about the centre of mass L [kg m²/s] (world frame);
- the force F [N] (gravity excluded) and torque T [N m] about the centre of mass of its nodes' forces.

A node of a body keeps its offset from the centre of mass at the switch, r0 [m], and its displacement then, u0 [m];
its displacement now is u = u0 + dc + (R(q) r0 − r0), formed in float64 and rounded once, so a body at rest in a
1 km model has the same nodes, bit for bit, wherever the origin is, and an unrotated body keeps u0 exactly.

Integration: velocity Verlet for the translation (the same half kicks as the nodes, gravity added as to the nodes);
for the rotation, the torque kicks L by dt/2 on each side of a free-rotor flow over dt, split symmetrically over the
principal axes (Dullweber, Leimkuhler & McLachlan 1997, J. Chem. Phys. 107, 5840; the NO_SQUISH scheme of Miller et
al. 2002 is the same splitting in quaternion momenta): rotations about axis 1 by dt/2, axis 2 by dt/2, axis 3 by dt,
axis 2 by dt/2, axis 1 by dt/2, each the exact flow of H_k = L_k²/(2 I_k) (the body turns by φ = h L_k / I_k about
its current axis k; L is constant in the world frame during the free flow). The scheme is symplectic and
time-reversible, keeps |L| exactly, bounds the energy error at O(dt²) and carries the gyroscopic term of a body with
three different moments (the intermediate-axis instability) with O(dt²) error in ω(t); about a principal axis it is
leapfrog exactly.

Roller constraints (``body_constraint``, ``body_axis`` n): a body with nodes on one roller plane, or on two parallel
ones (a slice between two roller walls), moves in the plane and turns about its normal only; a body on two roller
planes that meet moves along their line d only (no rotation); rollers of three directions or a fixed node hold it
whole (``body_fixed``). The constrained motion is integrated in its own coordinates, exactly: in-plane translation
(velocity Verlet with F and g projected onto the plane: the mass matrix is isotropic, so the projection is its
orthogonal one) and the angle θ about n, whose Lagrangian ½ I_n θ̇² has the constant I_n = n·I n (a rotation about
n leaves n·R I₀ Rᵀ n unchanged), so I_n θ̈ = T·n: leapfrog on ℓ = I_n θ̇, the torque kicked by its n component, the
body turned by φ = dt ℓ / I_n about n. ``body_l`` then holds ℓ n, the momentum conjugate to θ (the body's own I ω
has components across n where I is not aligned with n; the rollers carry them). The dropped components of F and T
are the rollers' reactions: they do no work on the allowed motion, so the books need no line for them.
"""

from __future__ import annotations

import warp as wp

from .neighbors import flag_past_half_fem_skin

wp.set_module_options({"enable_backward": False})

NODE_RIGID = wp.constant(8)
"""``node_motion`` of a node that follows a rigid body (kernels/tets.py ``node_free_directions`` gives it no free
component, so the node kernels leave its velocity at zero and its displacement alone; the body kernels set both)."""

BODY_FREE = wp.constant(0)
"""``body_constraint`` of a body no roller touches."""

BODY_PLANE = wp.constant(1)
"""``body_constraint`` of a body on a roller plane of normal ``body_axis``: it moves in the plane, turns about n."""

BODY_LINE = wp.constant(2)
"""``body_constraint`` of a body on two roller planes that meet: it moves along their line ``body_axis`` only."""

TET_RIGID = wp.constant(2)
"""``tet_active`` of a tet in a rigid block: present (surface, contact, fragments: ``tet_active != 0``) but carrying
no elastic force, stress or strain energy (kernels/tets.py evaluates only ``tet_active == TET_ACTIVE``)."""


# ----------------------------------------------------------------------------------------------------------------
# Rigid-body physics.


@wp.func
def principal_axis_now(q: wp.quatd, axes: wp.mat33d, k: int) -> wp.vec3d:
    """Principal axis k of a body now, world frame: R(q) A e_k (A: the axes at the switch, columns)."""
    return wp.quat_rotate(q, wp.vec3d(axes[0, k], axes[1, k], axes[2, k]))


@wp.func
def angular_velocity(q: wp.quatd, axes: wp.mat33d, inertia: wp.vec3d, angular_momentum: wp.vec3d) -> wp.vec3d:
    """ω = R I⁻¹ Rᵀ L = Σ_k (L·a_k / I_k) a_k [rad/s], a_k the principal axes now."""
    w = wp.vec3d()
    for k in range(3):
        a = principal_axis_now(q, axes, k)
        w = w + (wp.dot(angular_momentum, a) / inertia[k]) * a
    return w


@wp.func
def allowed_translation(constraint: int, axis: wp.vec3d, x: wp.vec3d) -> wp.vec3d:
    """The part of a translation (velocity, acceleration) the body's rollers allow: all of it when free, x − (x·n) n
    on a plane (exactly zero along an axis-aligned n), (x·d) d on a line."""
    if constraint == BODY_PLANE:
        return x - wp.dot(x, axis) * axis
    if constraint == BODY_LINE:
        return wp.dot(x, axis) * axis
    return x


@wp.func
def allowed_rotation(constraint: int, axis: wp.vec3d, x: wp.vec3d) -> wp.vec3d:
    """The part of a torque or angular momentum the rollers allow: all of it when free, (x·n) n on a plane, none on a
    line."""
    if constraint == BODY_PLANE:
        return wp.dot(x, axis) * axis
    if constraint == BODY_LINE:
        return wp.vec3d()
    return x


@wp.func
def inertia_about(q: wp.quatd, axes: wp.mat33d, inertia: wp.vec3d, n: wp.vec3d) -> wp.float64:
    """I_n = n·I n = Σ_k I_k (n·a_k)² [kg m²], a_k the principal axes now (constant under rotation about n)."""
    s = wp.float64(0.0)
    for k in range(3):
        c = wp.dot(n, principal_axis_now(q, axes, k))
        s = s + inertia[k] * c * c
    return s


@wp.func
def body_angular_velocity(
    constraint: int, axis: wp.vec3d, q: wp.quatd, axes: wp.mat33d, inertia: wp.vec3d, angular_momentum: wp.vec3d
) -> wp.vec3d:
    """ω of a body [rad/s]: R I⁻¹ Rᵀ L when free, (L·n / I_n) n on a roller plane, zero on a line."""
    if constraint == BODY_PLANE:
        return (wp.dot(angular_momentum, axis) / inertia_about(q, axes, inertia, axis)) * axis
    if constraint == BODY_LINE:
        return wp.vec3d()
    return angular_velocity(q, axes, inertia, angular_momentum)


@wp.func
def rotate_about_axis(q: wp.quatd, axes: wp.mat33d, inertia: wp.vec3d, angular_momentum: wp.vec3d, k: int, h: float):
    """Exact flow of H_k = L_k²/(2 I_k) over h [s]: the body turns by φ = h L_k / I_k about its principal axis k.
    Body frame: Q ← Q R_k(φ); with Q = R(q) A that is q ← q ⊗ rot(A e_k, φ). Returns the normalised quaternion."""
    a = principal_axis_now(q, axes, k)
    phi = wp.float64(h) * wp.dot(angular_momentum, a) / inertia[k]
    axis0 = wp.vec3d(axes[0, k], axes[1, k], axes[2, k])
    return wp.normalize(q * wp.quat_from_axis_angle(axis0, phi))


@wp.func
def free_rotor(q: wp.quatd, axes: wp.mat33d, inertia: wp.vec3d, angular_momentum: wp.vec3d, dt: float) -> wp.quatd:
    """Free-rotor flow over dt by the symmetric splitting 1(dt/2) 2(dt/2) 3(dt) 2(dt/2) 1(dt/2) (module docstring)."""
    h = 0.5 * dt
    q = rotate_about_axis(q, axes, inertia, angular_momentum, 0, h)
    q = rotate_about_axis(q, axes, inertia, angular_momentum, 1, h)
    q = rotate_about_axis(q, axes, inertia, angular_momentum, 2, dt)
    q = rotate_about_axis(q, axes, inertia, angular_momentum, 1, h)
    q = rotate_about_axis(q, axes, inertia, angular_momentum, 0, h)
    return q


@wp.func
def turn_body(
    constraint: int,
    axis: wp.vec3d,
    q: wp.quatd,
    axes: wp.mat33d,
    inertia: wp.vec3d,
    angular_momentum: wp.vec3d,
    dt: float,
) -> wp.quatd:
    """The rotation of a body over dt: the free rotor when free; on a roller plane the exact turn by
    φ = dt (L·n) / I_n about the world normal n (q ← rot(n, φ) q); none on a line."""
    if constraint == BODY_PLANE:
        phi = wp.float64(dt) * wp.dot(angular_momentum, axis) / inertia_about(q, axes, inertia, axis)
        return wp.normalize(wp.quat_from_axis_angle(axis, phi) * q)
    if constraint == BODY_LINE:
        return q
    return free_rotor(q, axes, inertia, angular_momentum, dt)


@wp.func
def kick_body(
    b: int,
    dt: float,
    gravity: wp.vec3,
    body_mass: wp.array(dtype=wp.float64),
    body_constraint: wp.array(dtype=int),
    body_axis: wp.array(dtype=wp.vec3d),
    body_f: wp.array(dtype=wp.vec3d),
    body_t: wp.array(dtype=wp.vec3d),
    v: wp.vec3d,
    angular_momentum: wp.vec3d,
):
    """Half kick of a body: v + dt/2 (F/M + g) [m/s], L + dt/2 T [kg m²/s], each in the part its rollers allow
    (:func:`allowed_translation`, :func:`allowed_rotation`; the rest is the rollers' reaction)."""
    h = wp.float64(0.5 * dt)
    c = body_constraint[b]
    n = body_axis[b]
    v = allowed_translation(c, n, v + h * (body_f[b] / body_mass[b] + wp.vec3d(gravity)))
    return v, allowed_rotation(c, n, angular_momentum + h * body_t[b])


@wp.struct
class PoseAhead:
    """What the half ahead of a force's work is booked against (:func:`node_velocity_ahead`): the nodes' velocities
    v_{n+1/2} after the drift, and for the nodes of rigid bodies their body, offset R(0) r0 from its centre of mass,
    and the bodies' record of the pose q_n the force was made at and the spin ω(q_n, L_{n+1/2}) there (State arrays:
    ``node_qd``, ``node_body``, ``node_rigid_r0``, ``body_fixed``, ``body_v``, ``body_q_before``,
    ``body_omega_ahead``; ``node_body`` is empty before a switch: no node follows a body)."""

    node_qd: wp.array(dtype=wp.vec3)
    node_body: wp.array(dtype=int)
    node_rigid_r0: wp.array(dtype=wp.vec3d)
    body_fixed: wp.array(dtype=int)
    body_v: wp.array(dtype=wp.vec3d)
    body_q_before: wp.array(dtype=wp.quatd)
    body_omega_ahead: wp.array(dtype=wp.vec3d)


@wp.func
def node_velocity_ahead(i: int, ahead: PoseAhead) -> wp.vec3:
    """The velocity [m/s] that the half ahead of the work of a force made at the last evaluation is booked against,
    after the drift: v_{n+1/2} (``node_qd``) for a node of its own; for a node of a moving rigid body,
    V_{n+1/2} + ω(q_n, L_{n+1/2}) × R(q_n) r0, at the pose q_n the force was made at.

    Why that pose: the first half kick changes the body's kinetic energy by exactly ½ dt (F·V̄ + T·ω(q_n, L̄)), V̄ and
    L̄ the means before and after it (½ L·I⁻¹L is quadratic in L at a fixed pose), that is
    ½ dt Σ f_i·(V_{n+1/2} + ω(q_n, L_{n+1/2}) × R(q_n) r0_i) less the shadow term's share dt²/8 (|F|²/M + T·I⁻¹T),
    with T = Σ R(q_n) r0_i × f_i. The node's velocity after the pose, V + ω(q_{n+1}, L_{n+1/2}) × R(q_{n+1}) r0, is
    that of the next pose: it books the half behind of the next forces. ``body_q_before`` and ``body_omega_ahead``
    are the drift's record of q_n and ω(q_n, L_{n+1/2}) (:func:`make_body_drift_kernel`); a held body has neither,
    and its nodes stand still."""
    if ahead.node_body.shape[0] == 0:
        return ahead.node_qd[i]
    b = ahead.node_body[i]
    if b < 0:
        return ahead.node_qd[i]
    if ahead.body_fixed[b] != 0:
        return ahead.node_qd[i]
    r = wp.quat_rotate(ahead.body_q_before[b], ahead.node_rigid_r0[i])
    return wp.vec3(ahead.body_v[b] + wp.cross(ahead.body_omega_ahead[b], r))


# ----------------------------------------------------------------------------------------------------------------
# Kernels.


def make_body_drift_kernel(after_second_half: bool) -> wp.Kernel:
    """The body kernel that ends a half step in a drift: kick by dt/2, translate by dt, free rotor over dt; with
    ``after_second_half`` the second half kick of step n before it (the same forces twice, as the node kernels do),
    the choice made at code generation. Before the rotor it records the pose q_n and the spin ω(q_n, L_{n+1/2})
    (``body_q_before``, ``body_omega_ahead``), which the half ahead of the last forces' work is booked against
    (:func:`node_velocity_ahead`)."""

    @wp.kernel(enable_backward=False, module="unique")
    def drift_bodies_kernel(
        # Model:
        gravity: wp.vec3,
        dt: float,
        # State in:
        body_mass: wp.array(dtype=wp.float64),
        body_inertia: wp.array(dtype=wp.vec3d),
        body_axes: wp.array(dtype=wp.mat33d),
        body_fixed: wp.array(dtype=int),
        body_constraint: wp.array(dtype=int),
        body_axis: wp.array(dtype=wp.vec3d),
        body_f: wp.array(dtype=wp.vec3d),
        body_t: wp.array(dtype=wp.vec3d),
        # State out:
        body_dc: wp.array(dtype=wp.vec3d),
        body_v: wp.array(dtype=wp.vec3d),
        body_q: wp.array(dtype=wp.quatd),
        body_l: wp.array(dtype=wp.vec3d),
        body_q_before: wp.array(dtype=wp.quatd),
        body_omega_ahead: wp.array(dtype=wp.vec3d),
    ):
        b = wp.tid()  # one thread per body
        if body_fixed[b] != 0:
            return
        v = body_v[b]
        angular_momentum = body_l[b]
        c = body_constraint[b]
        n = body_axis[b]
        if wp.static(after_second_half):
            v, angular_momentum = kick_body(
                b, dt, gravity, body_mass, body_constraint, body_axis, body_f, body_t, v, angular_momentum
            )
        v, angular_momentum = kick_body(
            b, dt, gravity, body_mass, body_constraint, body_axis, body_f, body_t, v, angular_momentum
        )
        body_v[b] = v
        body_l[b] = angular_momentum
        body_dc[b] = body_dc[b] + wp.float64(dt) * v
        q = body_q[b]
        # The pose the last forces were made at and the spin the kick just gave it there: what the half ahead of
        # their work is booked against (node_velocity_ahead), before the rotor moves the pose on.
        body_q_before[b] = q
        body_omega_ahead[b] = body_angular_velocity(c, n, q, body_axes[b], body_inertia[b], angular_momentum)
        body_q[b] = turn_body(c, n, q, body_axes[b], body_inertia[b], angular_momentum, dt)

    return drift_bodies_kernel


drift_bodies_kernel = make_body_drift_kernel(after_second_half=False)
kick_drift_bodies_kernel = make_body_drift_kernel(after_second_half=True)


@wp.kernel
def kick_bodies_kernel(
    # Model:
    gravity: wp.vec3,
    dt: float,
    # State in:
    body_mass: wp.array(dtype=wp.float64),
    body_fixed: wp.array(dtype=int),
    body_constraint: wp.array(dtype=int),
    body_axis: wp.array(dtype=wp.vec3d),
    body_f: wp.array(dtype=wp.vec3d),
    body_t: wp.array(dtype=wp.vec3d),
    # State out:
    body_v: wp.array(dtype=wp.vec3d),
    body_l: wp.array(dtype=wp.vec3d),
):
    b = wp.tid()  # one thread per body
    if body_fixed[b] != 0:
        return
    v, angular_momentum = kick_body(
        b, dt, gravity, body_mass, body_constraint, body_axis, body_f, body_t, body_v[b], body_l[b]
    )
    body_v[b] = v
    body_l[b] = angular_momentum


@wp.kernel
def pose_nodes_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    node_contact_stiffness: wp.array(dtype=float),
    half_fem_skin: float,
    # State in:
    body_node_start: wp.array(dtype=int),
    body_node_count: wp.array(dtype=int),
    rigid_nodes: wp.array(dtype=int),
    node_rigid_r0: wp.array(dtype=wp.vec3d),
    node_rigid_u0: wp.array(dtype=wp.vec3),
    body_inertia: wp.array(dtype=wp.vec3d),
    body_axes: wp.array(dtype=wp.mat33d),
    body_constraint: wp.array(dtype=int),
    body_axis: wp.array(dtype=wp.vec3d),
    body_dc: wp.array(dtype=wp.vec3d),
    body_v: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.quatd),
    body_l: wp.array(dtype=wp.vec3d),
    node_q_at_fem_build: wp.array(dtype=wp.vec3),
    # In:
    move: int,
    # State out:
    node_u: wp.array(dtype=wp.vec3),
    node_q: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    node_f: wp.array(dtype=wp.vec3),
    fem_rebuild_flag: wp.array(dtype=int),
):
    """Nodes from their body's pose: with ``move`` the displacement u = u0 + dc + (R r0 − r0) and position X + u
    (flagging an FEM contact-list rebuild when a surface node moved half the FEM skin, as kernels/integrate.py
    ``drift_node`` does), and always the velocity v + ω × R r0. On a roller plane the normal component of R r0 − r0
    (zero but for rounding: the body turns about n) is dropped, so a node on the plane stays on it exactly. One
    thread per body: its ω (R I⁻¹ Rᵀ L) and pose are read once for all its nodes (``rigid_nodes``), each node's
    arithmetic is the same as a thread of its own would do.

    With ``move`` (the drift) the nodes' force accumulators start at zero, as the node kernels' drift starts those of
    a rigid node (kernels/integrate.py ``make_node_drift_kernel``: no damping force at v = 0 relative to the body):
    a model whose nodes are all rigid and undriven then skips that launch (warpdem.stages.rigid ``every_node_rigid``).
    The viscous forces of deformable tets on them (``node_f_viscous``) are left for their half ahead, booked and cleared
    after the pose (warpdem.stages.rigid ``drift_bodies``)."""
    b = wp.tid()  # one thread per body
    q = body_q[b]
    c = body_constraint[b]
    n = body_axis[b]
    dc = body_dc[b]
    w = body_angular_velocity(c, n, q, body_axes[b], body_inertia[b], body_l[b])
    vb = body_v[b]
    start = body_node_start[b]
    for k in range(body_node_count[b]):
        i = rigid_nodes[start + k]
        r0 = node_rigid_r0[i]
        r = wp.quat_rotate(q, r0)
        if move != 0:
            turn = r - r0
            if c == BODY_PLANE:
                turn = turn - wp.dot(turn, n) * n
            u = wp.vec3(wp.vec3d(node_rigid_u0[i]) + dc + turn)
            node_f[i] = wp.vec3(0.0)
            node_u[i] = u
            x = node_ref_q[i] + u
            node_q[i] = x
            flag_past_half_fem_skin(i, x, half_fem_skin, node_contact_stiffness, node_q_at_fem_build, fem_rebuild_flag)
        node_qd[i] = wp.vec3(vb + wp.cross(w, r))


@wp.kernel
def reduce_body_forces_kernel(
    # State in:
    body_fixed: wp.array(dtype=int),
    body_node_start: wp.array(dtype=int),
    body_node_count: wp.array(dtype=int),
    rigid_nodes: wp.array(dtype=int),
    node_rigid_r0: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.quatd),
    node_f: wp.array(dtype=wp.vec3),
    # State out:
    body_f: wp.array(dtype=wp.vec3d),
    body_t: wp.array(dtype=wp.vec3d),
):
    """F = Σ f_i and T = Σ r_i × f_i over the body's nodes (r_i = R r0_i, from the centre of mass, so the torque does
    not depend on the origin), summed in float64 in node order: the same numbers on every device (no atomics). The
    nodes' forces hold contacts, joint and cohesive elements, loads and any force of a neighbouring deformable tet,
    not gravity (added in the kick; its torque about the centre of mass is zero) and no force of the body's own tets
    (tet_active = TET_RIGID: not evaluated)."""
    b = wp.tid()  # one thread per body
    if body_fixed[b] != 0:
        return
    q = body_q[b]
    f = wp.vec3d()
    t = wp.vec3d()
    start = body_node_start[b]
    for k in range(body_node_count[b]):
        i = rigid_nodes[start + k]
        fi = wp.vec3d(node_f[i])
        f = f + fi
        t = t + wp.cross(wp.quat_rotate(q, node_rigid_r0[i]), fi)
    body_f[b] = f
    body_t[b] = t
