"""The energy books reduced on the device (warpdem.stages.energy): every line of ``EnergyBalance`` summed into one
small float64 vector that the host reads once per frame, in place of some seventy whole arrays read back and summed
in NumPy.

Each line is a sum over spheres, nodes, bodies, joint elements or the per-item energies other kernels write. A sum
runs in two passes that fix its order on every device: ``stride`` threads each add items t, t + stride, t + 2 stride,
... into their own float64 partial (``partials[line, t]``, added to by every pass that feeds the line, one launch
after another), then :func:`finish_books_kernel` adds each line's partials in thread order. No float atomics: two runs
on one device give the same bits, and a line's error is that of a float64 sum of float64 terms (each term computed
in float64 from the float32 state, as the NumPy books did).
"""

from __future__ import annotations

import warp as wp

from .rigid import NODE_RIGID, allowed_rotation, allowed_translation, body_angular_velocity
from .tets import node_free_directions
from .topology import tet_face

# The lines, in the order of warpdem.stages.energy.EnergyBalance's fields (that module checks the two agree).
KINETIC_TRANSLATIONAL = wp.constant(0)
KINETIC_ROTATIONAL = wp.constant(1)
ELASTIC = wp.constant(2)
GRAVITY_POTENTIAL = wp.constant(3)
KINETIC_NODES = wp.constant(8)
SHADOW = wp.constant(15)
KINETIC_RIGID = wp.constant(20)
LINES = wp.constant(28)
"""Number of lines (fields of EnergyBalance)."""


@wp.kernel
def add_sum_kernel(
    values: wp.array(dtype=wp.float64),
    count: wp.array(dtype=int),
    counted: int,
    line: int,
    stride: int,
    # Out:
    partials: wp.array2d(dtype=wp.float64),
):
    """partials[line, t] += Σ values[i], i = t, t + stride, ... below the live count (``count[0]`` when ``counted``,
    else the array's length). One thread per partial."""
    t = wp.tid()
    n = values.shape[0]
    if counted != 0:
        n = wp.min(n, count[0])
    acc = wp.float64(0.0)
    for i in range(t, n, stride):
        acc += values[i]
    partials[line, t] = partials[line, t] + acc


@wp.kernel
def sphere_books_kernel(
    # Model:
    particle_mass: wp.array(dtype=float),
    particle_radius: wp.array(dtype=float),
    particle_motion: wp.array(dtype=int),
    particle_inv_inertia: wp.array(dtype=float),
    gravity: wp.vec3d,
    shadow_factor: wp.float64,
    # State in:
    particle_count: wp.array(dtype=int),
    particle_q: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    particle_f: wp.array(dtype=wp.vec3),
    particle_t: wp.array(dtype=wp.vec3),
    stride: int,
    # Out:
    partials: wp.array2d(dtype=wp.float64),
):
    """The spheres' kinetic energy ½ m v² and ½ I ω² (I = 2/5 m r², every live sphere), the free spheres' gravity
    potential −m x·g and their shadow term dt²/8 (|f + m g|²/m + |t|²/I) (``shadow_factor`` = dt²/8 [s²])."""
    t = wp.tid()
    translational = wp.float64(0.0)
    rotational = wp.float64(0.0)
    potential = wp.float64(0.0)
    shadow = wp.float64(0.0)
    for i in range(t, particle_count[0], stride):
        m = wp.float64(particle_mass[i])
        r = wp.float64(particle_radius[i])
        v = wp.vec3d(particle_qd[i])
        w = wp.vec3d(particle_omega[i])
        translational += wp.float64(0.5) * m * wp.dot(v, v)
        rotational += wp.float64(0.2) * m * r * r * wp.dot(w, w)
        if particle_motion[i] == 0:
            potential -= m * wp.dot(particle_q[i], gravity)
            f = wp.vec3d(particle_f[i]) + m * gravity
            torque = wp.vec3d(particle_t[i])
            shadow += shadow_factor * (wp.dot(f, f) / m + wp.float64(particle_inv_inertia[i]) * wp.dot(torque, torque))
    partials[KINETIC_TRANSLATIONAL, t] = partials[KINETIC_TRANSLATIONAL, t] + translational
    partials[KINETIC_ROTATIONAL, t] = partials[KINETIC_ROTATIONAL, t] + rotational
    partials[GRAVITY_POTENTIAL, t] = partials[GRAVITY_POTENTIAL, t] + potential
    partials[SHADOW, t] = partials[SHADOW, t] + shadow


@wp.kernel
def node_books_kernel(
    # Model:
    node_mass: wp.array(dtype=float),
    node_inv_mass: wp.array(dtype=float),
    node_motion: wp.array(dtype=int),
    node_ref_q: wp.array(dtype=wp.vec3),
    node_driver: wp.array(dtype=int),
    has_drivers: int,
    gravity: wp.vec3d,
    shadow_factor: wp.float64,
    substeps: int,
    # State in:
    node_count: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    node_f: wp.array(dtype=wp.vec3),
    node_f_fast: wp.array(dtype=wp.vec3),
    stride: int,
    # Out:
    partials: wp.array2d(dtype=wp.float64),
):
    """The FEM nodes' kinetic energy ½ m v² (a rigid body's nodes excluded: the body counts), the moving nodes'
    gravity potential −m (X + u)·g (X + u in float64, so the potential keeps the displacements' precision) and the
    shadow term m dt²/8 |a|² of the kicked components of the nodes' acceleration a = f/m + g (not those a velocity
    driver holds), and with ``substeps`` n > 1 that of the sub-steps, m (dt/n)²/8 |f_fast/m|² (warpdem.stages.substep;
    ``node_f_fast`` is zero without them)."""
    t = wp.tid()
    kinetic = wp.float64(0.0)
    potential = wp.float64(0.0)
    shadow = wp.float64(0.0)
    for i in range(t, node_count[0], stride):
        m = wp.float64(node_mass[i])
        motion = node_motion[i]
        if motion != NODE_RIGID:
            v = wp.vec3d(node_qd[i])
            kinetic += wp.float64(0.5) * m * wp.dot(v, v)
        inv_mass = node_inv_mass[i]
        if inv_mass > 0.0:
            potential -= m * wp.dot(wp.vec3d(node_ref_q[i]) + wp.vec3d(node_u[i]), gravity)
            kicked = True
            if has_drivers != 0:
                kicked = node_driver[i] < 0
            if kicked:
                a = wp.cw_mul(
                    wp.vec3d(node_f[i]) * wp.float64(inv_mass) + gravity, wp.vec3d(node_free_directions(motion))
                )
                shadow += shadow_factor * m * wp.dot(a, a)
                if substeps > 1:
                    free = wp.vec3d(node_free_directions(motion))
                    fast = wp.cw_mul(wp.vec3d(node_f_fast[i]) * wp.float64(inv_mass), free)
                    shadow += shadow_factor * m * wp.dot(fast, fast) / wp.float64(substeps * substeps)
    partials[KINETIC_NODES, t] = partials[KINETIC_NODES, t] + kinetic
    partials[GRAVITY_POTENTIAL, t] = partials[GRAVITY_POTENTIAL, t] + potential
    partials[SHADOW, t] = partials[SHADOW, t] + shadow


@wp.kernel
def body_books_kernel(
    # Model:
    gravity: wp.vec3d,
    shadow_factor: wp.float64,
    # State in:
    body_mass: wp.array(dtype=wp.float64),
    body_inertia: wp.array(dtype=wp.vec3d),
    body_axes: wp.array(dtype=wp.mat33d),
    body_fixed: wp.array(dtype=int),
    body_constraint: wp.array(dtype=int),
    body_axis: wp.array(dtype=wp.vec3d),
    body_v: wp.array(dtype=wp.vec3d),
    body_q: wp.array(dtype=wp.quatd),
    body_l: wp.array(dtype=wp.vec3d),
    body_f: wp.array(dtype=wp.vec3d),
    body_t: wp.array(dtype=wp.vec3d),
    stride: int,
    # Out:
    partials: wp.array2d(dtype=wp.float64),
):
    """The rigid bodies' kinetic energy ½ M v² + ½ L·ω and their shadow term dt²/8 (|F + M g|²/M + T·I⁻¹T), held
    bodies excluded; on roller constraints of the allowed motion (kernels/rigid.py ``allowed_translation``,
    ``allowed_rotation``, ``body_angular_velocity``), as warpdem.stages.rigid.body_energy has it."""
    t = wp.tid()
    kinetic = wp.float64(0.0)
    shadow = wp.float64(0.0)
    for b in range(t, body_mass.shape[0], stride):
        if body_fixed[b] != 0:
            continue
        mass = body_mass[b]
        c = body_constraint[b]
        axis = body_axis[b]
        v = body_v[b]
        spin = body_angular_velocity(c, axis, body_q[b], body_axes[b], body_inertia[b], body_l[b])
        kinetic += wp.float64(0.5) * (mass * wp.dot(v, v) + wp.dot(body_l[b], spin))
        f = allowed_translation(c, axis, body_f[b] + mass * gravity)
        torque = allowed_rotation(c, axis, body_t[b])
        turn = wp.dot(torque, body_angular_velocity(c, axis, body_q[b], body_axes[b], body_inertia[b], torque))
        shadow += shadow_factor * (wp.dot(f, f) / mass + turn)
    partials[KINETIC_RIGID, t] = partials[KINETIC_RIGID, t] + kinetic
    partials[SHADOW, t] = partials[SHADOW, t] + shadow


@wp.kernel
def joint_books_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    joint_a: wp.array(dtype=int),
    joint_b: wp.array(dtype=int),
    joint_kn: wp.array(dtype=float),
    joint_tet_face: wp.array(dtype=int),
    joint_set: wp.array(dtype=int),
    set_shear_ratio: wp.array(dtype=wp.float64),
    # State in:
    joint_count: wp.array(dtype=int),
    joint_broken: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    node_q: wp.array(dtype=wp.vec3),
    stride: int,
    # Out:
    partials: wp.array2d(dtype=wp.float64),
):
    """The intact joint elements' spring energy ½ k_n (g_n² + (k_t/k_n) |g_t|²) [J], g = u_B − u_A split along the
    normal of the joint's tet face (float64, from the float32 positions)."""
    t = wp.tid()
    elastic = wp.float64(0.0)
    for i in range(t, joint_count[0], stride):
        if joint_broken[i] != 0:
            continue
        tf = joint_tet_face[i]
        face = tet_face(tet_nodes[tf // 4], tf % 4)
        x0 = wp.vec3d(node_q[face[0]])
        n = wp.normalize(wp.cross(wp.vec3d(node_q[face[1]]) - x0, wp.vec3d(node_q[face[2]]) - x0))
        g = wp.vec3d(node_u[joint_b[i]]) - wp.vec3d(node_u[joint_a[i]])
        gn = wp.dot(g, n)
        gt = g - gn * n
        elastic += (
            wp.float64(0.5) * wp.float64(joint_kn[i]) * (gn * gn + set_shear_ratio[joint_set[i]] * wp.dot(gt, gt))
        )
    partials[ELASTIC, t] = partials[ELASTIC, t] + elastic


@wp.kernel
def finish_books_kernel(partials: wp.array2d(dtype=wp.float64), books: wp.array(dtype=wp.float64)):
    """books[line] = Σ_t partials[line, t], in thread order. One thread per line."""
    line = wp.tid()
    acc = wp.float64(0.0)
    for t in range(partials.shape[1]):
        acc += partials[line, t]
    books[line] = acc


@wp.func
def weighted_lines(books: wp.array(dtype=wp.float64), weights: wp.array(dtype=wp.float64)) -> wp.float64:
    """Σ weights[line] × books[line], in line order."""
    acc = wp.float64(0.0)
    for line in range(LINES):
        acc += weights[line] * books[line]
    return acc


@wp.kernel
def mark_books_kernel(
    books: wp.array(dtype=wp.float64),
    weights: wp.array(dtype=wp.float64),
    slot: int,
    # Out:
    marks: wp.array(dtype=wp.float64),
):
    """marks[slot] = Σ weights × books: the lines before a pass. One thread."""
    marks[slot] = weighted_lines(books, weights)


@wp.kernel
def book_change_kernel(
    books: wp.array(dtype=wp.float64),
    weights: wp.array(dtype=wp.float64),
    marks: wp.array(dtype=wp.float64),
    slot: int,
    # Out:
    into: wp.array(dtype=wp.float64),
):
    """into[0] += Σ weights × books − marks[slot]: what a pass changed the lines by, booked where the state keeps
    it. One thread."""
    into[0] = into[0] + (weighted_lines(books, weights) - marks[slot])
