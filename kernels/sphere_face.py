"""Sphere–face contact (DESIGN.md stage 4): the spheres' candidate faces and their forces (kernels/fem_contact.py says
how the FEM contacts fit together).

Sphere–face: the closest point c of the triangle to the sphere centre x (barycentric weights w); touching when
|x - c| < r with x in front of the face. The vertices are taken relative to the float64 centre (float64
differences rounded once), so the sphere's side of the arithmetic does not depend on the offset; the nodes' float32
positions do. The force is the sphere contact law of the model (kernels/contact.py,
``make_pair_laws``) with the face as a flat body (R* = r, as a wall), m* = 1 / (1/m_s + Σ w_i²/m_i), and the equal
and opposite force goes to the face's nodes with the weights w_i. A sphere may touch several faces; a contact at a
face's edge or vertex counts only if no other face is nearer (the same edge point seen from the two faces that share
the edge counts once, and a contact in a face's interior shadows its neighbours' edges). A centre behind a face it
projects into has gone past the contact's reach (an overlap past r): the face is recorded for the stability guard,
which stops the run (warpdem.stages.guard).
"""

from __future__ import annotations

import functools

import warp as wp

from .contact import ContactPair, make_pair_laws
from .fem_surface import BARY_EPS, TIE_EPS, closest_point_barycentric, min3, nearer, relative_position
from .neighbors import ListSpec, make_list_kernels

wp.set_module_options({"enable_backward": False})


@wp.struct
class SphereFaceInputs:
    """What the sphere–face candidate test reads (kernels/neighbors.py ``ListSpec.inputs``): the Model/State arrays
    of those names; ``margin``, how far beyond its radius a sphere keeps a face (sphere skin + fem_skin / 2) [m]; and
    ``face_radius``, the largest centroid–vertex distance of a face [m] (the grid holds the faces' centroids)."""

    particle_radius: wp.array(dtype=float)
    face_nodes: wp.array(dtype=wp.vec3i)
    node_q: wp.array(dtype=wp.vec3)
    margin: float
    face_radius: float


@wp.struct
class SphereFaceHistory:
    """Per-slot history of the sphere–face list: ``sphere_face_shear`` (or its scratch copy)."""

    shear: wp.array(dtype=wp.vec3)


@wp.func
def sphere_face_search_radius(inputs: SphereFaceInputs, i: int) -> float:
    return inputs.particle_radius[i] + inputs.margin + inputs.face_radius


@wp.func
def is_sphere_face_candidate(inputs: SphereFaceInputs, i: int, x: wp.vec3d, f: int) -> bool:
    """The face's closest point within r + margin of the sphere centre (in coordinates relative to the centre)."""
    cutoff = inputs.particle_radius[i] + inputs.margin
    fn = inputs.face_nodes[f]
    a = relative_position(inputs.node_q[fn[0]], x)
    b = relative_position(inputs.node_q[fn[1]], x)
    c = relative_position(inputs.node_q[fn[2]], x)
    w = closest_point_barycentric(wp.vec3(0.0), a, b, c)
    d = -(w[0] * a + w[1] * b + w[2] * c)
    return not (wp.dot(d, d) >= cutoff * cutoff)  # not ≥ rather than <: a NaN distance keeps the pair


@wp.func
def copy_sphere_face_history(src: SphereFaceHistory, src_slot: int, dst: SphereFaceHistory, dst_slot: int):
    dst.shear[dst_slot] = src.shear[src_slot]


@wp.func
def fresh_sphere_face_history(inputs: SphereFaceInputs, history: SphereFaceHistory, slot: int, i: int, f: int):
    """A pair new to the list starts untouched."""
    history.shear[slot] = wp.vec3(0.0)


SPHERE_FACE_LIST = make_list_kernels(
    ListSpec(
        inputs=SphereFaceInputs,
        radius=sphere_face_search_radius,
        accept=is_sphere_face_candidate,
        history=SphereFaceHistory,
        copy=copy_sphere_face_history,
        fresh=fresh_sphere_face_history,
        owner_vec=wp.vec3d,
        grid_vec=wp.vec3,  # the grid of face centroids is float32, as the nodes are
    )
)
"""Build and commit kernels of the sphere–face lists."""


@wp.func
def sphere_face_contact(x: wp.vec3d, r: float, fn: wp.vec3i, node_q: wp.array(dtype=wp.vec3)):
    """Geometry of a sphere (centre x, radius r) against the triangle of nodes fn.

    The vertices are taken relative to the centre (float64 differences rounded once), so the arithmetic is the
    same wherever the pair is.

    Returns:
        (barycentric weights of the closest point, unit normal from it to x, distance [m], touching (r beyond the
        distance and x in front of the face), in the face's interior).
    """
    a = relative_position(node_q[fn[0]], x)
    b = relative_position(node_q[fn[1]], x)
    c = relative_position(node_q[fn[2]], x)
    w = closest_point_barycentric(wp.vec3(0.0), a, b, c)
    d = -(w[0] * a + w[1] * b + w[2] * c)
    dist = wp.length(d)
    nf = wp.cross(b - a, c - a)
    touching = dist < r and wp.dot(d, nf) > 0.0
    n = wp.vec3(0.0)
    if dist > 0.0:
        n = d / dist
    interior = min3(w) > BARY_EPS
    return w, n, dist, touching, interior


@functools.cache
def make_sphere_face_kernel(normal: str, tangential: str, rolling: str, track_energy: bool):
    """The sphere–face kernels for one choice of the sphere contact laws (kernels/contact.py).

    Energy books (``track_energy``), as velocity Verlet does the work (kernels/contact.py ``make_contact_kernels``):
    a force f_n works ½ dt f_n·(v_{n-1/2} + v_{n+1/2}) on each body it acts on, and v_{n-1/2} is the velocity during
    its evaluation. A contact's dissipation D = -W - ΔU is booked whole on the sphere–face line (the spheres'
    ``sphere_face_dissipated`` and the nodes' ``node_energy_sphere_face``, ``dissipated_sphere_face`` in the books),
    never split between lines of which only the sum would be a dissipation: the half of its work behind,
    -½ dt (f·v_rel + M·ω) (v_rel against the face's velocity at the contact point, M the rolling torque), and -ΔU,
    ΔU from the sphere's sphere–face spring energies at the last evaluation (``sphere_face_energy_prev``), are
    booked here on the sphere; its forces are kept, the sphere's sums in ``sphere_face_f`` / ``sphere_face_t`` and
    the face nodes' shares in ``node_f_sphere_face``, and the half ahead against v_{n+1/2} is booked at the next
    evaluation: the sphere's here, -½ dt (f·v + t·ω), the nodes' by ``book_half_ahead_kernel`` (kernels/integrate.py)
    before it. The change of a tangential spring's energy with k_t at fixed ξ is no dissipation: it goes to
    ``energy_stiffness_change``.

    Returns:
        (eval_sphere_faces_kernel, sphere_face_energy_kernel).
    """
    laws = make_pair_laws(normal, tangential, rolling)
    pair_interaction = laws.pair_interaction
    normal_force = laws.normal_force
    tangential_stiffness = laws.tangential_stiffness
    elastic_energy = laws.elastic_energy

    @wp.func
    def counted_face(
        i: int,
        x: wp.vec3d,
        r: float,
        face_radius: float,
        count: int,
        max_sphere_faces: int,
        sphere_face_index: wp.array(dtype=int),
        face_nodes: wp.array(dtype=wp.vec3i),
        node_q: wp.array(dtype=wp.vec3),
    ) -> int:
        """The nearest touching face of sphere i (an edge or vertex contact counts only if it is this one), -1.

        Ties are judged relative to the size of the coordinates the distances come from, the vertices relative to
        the centre: within r + 2 face_radius of it for a touching face.
        """
        tol = TIE_EPS * (r + 2.0 * face_radius)
        best_d = float(0.0)
        best_interior = int(0)
        best_f = int(-1)
        for s in range(count):
            f = sphere_face_index[i * max_sphere_faces + s]
            fn = face_nodes[f]
            _w, _n, dist, touching, interior = sphere_face_contact(x, r, fn, node_q)
            if touching:
                inside = int(interior)
                if nearer(dist, inside, f, best_d, best_interior, best_f, tol):
                    best_d = dist
                    best_interior = inside
                    best_f = f
        return best_f

    @wp.kernel(enable_backward=False, module="unique")
    def eval_sphere_faces_kernel(
        # Model:
        particle_radius: wp.array(dtype=float),
        particle_inv_mass: wp.array(dtype=float),
        particle_material: wp.array(dtype=int),
        pair_table: wp.array(dtype=ContactPair),
        num_materials: int,
        node_inv_mass: wp.array(dtype=float),
        tet_material: wp.array(dtype=int),
        face_nodes: wp.array(dtype=wp.vec3i),
        face_tet: wp.array(dtype=int),
        face_radius: float,
        max_sphere_faces: int,
        dt: float,
        # State in:
        particle_count: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        particle_qd: wp.array(dtype=wp.vec3),
        particle_omega: wp.array(dtype=wp.vec3),
        sphere_face_count: wp.array(dtype=int),
        sphere_face_index: wp.array(dtype=int),
        node_q: wp.array(dtype=wp.vec3),
        node_qd: wp.array(dtype=wp.vec3),
        # State out:
        sphere_face_shear: wp.array(dtype=wp.vec3),
        particle_f: wp.array(dtype=wp.vec3),
        particle_t: wp.array(dtype=wp.vec3),
        node_f: wp.array(dtype=wp.vec3),
        sphere_face_f: wp.array(dtype=wp.vec3),
        sphere_face_t: wp.array(dtype=wp.vec3),
        node_f_sphere_face: wp.array(dtype=wp.vec3),
        sphere_face_energy_prev: wp.array(dtype=wp.vec2),
        sphere_face_dissipated: wp.array(dtype=wp.float64),
        energy_stiffness_change: wp.array(dtype=wp.float64),
        # Out:
        sphere_passed_face: wp.array(dtype=int),  # a face whose reach the sphere went past (-1 none; the guard clears)
    ):
        i = wp.tid()  # one thread per particle slot; it owns its sphere–face pairs
        if i >= particle_count[0]:
            return
        vi = particle_qd[i]
        wi = particle_omega[i]
        if wp.static(track_energy):
            # The half ahead of the last evaluation's forces on the sphere, now that v_{n+1/2} is known; a set-up or
            # re-evaluation (dt = 0) replaces them: the next kick works with the forces evaluated now.
            f_last = sphere_face_f[i]
            t_last = sphere_face_t[i]
            if dt > 0.0 and (wp.length_sq(f_last) > 0.0 or wp.length_sq(t_last) > 0.0):
                ahead = 0.5 * dt * (wp.dot(f_last, vi) + wp.dot(t_last, wi))
                sphere_face_dissipated[i] = sphere_face_dissipated[i] - wp.float64(ahead)
            if wp.length_sq(f_last) > 0.0 or wp.length_sq(t_last) > 0.0:  # a sphere far from faces keeps its zeros
                sphere_face_f[i] = wp.vec3(0.0)
                sphere_face_t[i] = wp.vec3(0.0)
        count = wp.min(sphere_face_count[i], max_sphere_faces)
        if count == 0:
            if wp.static(track_energy):
                prev = sphere_face_energy_prev[i]
                if prev[0] != 0.0 or prev[1] != 0.0:  # the last springs went with the lists: their energy dissipated
                    sphere_face_energy_prev[i] = wp.vec2(0.0)
                    if dt > 0.0:
                        sphere_face_dissipated[i] = sphere_face_dissipated[i] + wp.float64(prev[0] + prev[1])
            return
        x = particle_q[i]
        r = particle_radius[i]
        inv_mi = particle_inv_mass[i]
        # Pass 1: the nearest contact (an edge or vertex contact counts only if it is the nearest).
        best_f = counted_face(i, x, r, face_radius, count, max_sphere_faces, sphere_face_index, face_nodes, node_q)
        # Pass 2: springs of pairs that no longer count are handed to a pair that starts counting (the contact
        # point slid from one face onto the next).
        orphan = wp.vec3(0.0)
        a_t = float(0.0)  # the tangential springs' energy at their old ξ under the new stiffness, ½ k_t |ξ_n|² [J]
        a_orphan = float(0.0)  # the orphan's share of a_t, until a pair takes it over
        mat_i = particle_material[i]
        for s in range(count):
            slot = i * max_sphere_faces + s
            f = sphere_face_index[slot]
            fn = face_nodes[f]
            w, n, dist, touching, interior = sphere_face_contact(x, r, fn, node_q)
            if not (touching and (interior or f == best_f)):
                sh = sphere_face_shear[slot]
                if wp.static(track_energy and laws.parting_spring):
                    # A spring let go of is released at k_t(0) (zero where k_t follows the overlap: left out).
                    p = pair_table[mat_i * num_materials + tet_material[face_tet[f]]]
                    a = 0.5 * tangential_stiffness(0.0, r, normal_force(0.0, 0.0, r, r, r, 1.0, p)[2], p)
                    a = a * wp.dot(sh, sh)
                    a_t += a
                    if wp.dot(sh, sh) > wp.dot(orphan, orphan):
                        a_orphan = a
                if wp.dot(sh, sh) > wp.dot(orphan, orphan):
                    orphan = sh
                sphere_face_shear[slot] = wp.vec3(0.0)
        # Pass 3: forces.
        f_i = wp.vec3(0.0)
        t_i = wp.vec3(0.0)
        d_behind = float(0.0)  # minus the work behind, normal, tangential and rolling [J]
        e_n = float(0.0)  # normal spring energy of the sphere's face pairs [J]
        e_t = float(0.0)  # tangential spring energy, ½ k_t(δ_{n+1}) |ξ_{n+1}|² [J]
        for s in range(count):
            slot = i * max_sphere_faces + s
            f = sphere_face_index[slot]
            fn = face_nodes[f]
            w, n, dist, touching, interior = sphere_face_contact(x, r, fn, node_q)
            if not (touching and (interior or f == best_f)):
                if dt > 0.0 and interior and dist < r and not touching:
                    # The centre lies behind a face it projects into, less than r deep: an overlap past the radius,
                    # the contact's reach. It acts only while the centre is in front, so nothing pushes the sphere
                    # back out of the rock (warpdem.stages.guard stops the run).
                    sphere_passed_face[i] = f
                continue
            inv_sum = inv_mi
            inv_sum += w[0] * w[0] * node_inv_mass[fn[0]] + w[1] * w[1] * node_inv_mass[fn[1]]
            inv_sum += w[2] * w[2] * node_inv_mass[fn[2]]
            if inv_sum == 0.0:
                continue
            shear_old = sphere_face_shear[slot]
            if wp.dot(shear_old, shear_old) == 0.0:
                shear_old = orphan
                orphan = wp.vec3(0.0)
                a_t -= a_orphan  # handed over, not let go of
                a_orphan = 0.0
            delta = r - dist
            ci = r - delta  # lever arm to the contact point
            v_face = w[0] * node_qd[fn[0]] + w[1] * node_qd[fn[1]] + w[2] * node_qd[fn[2]]
            v_rel = (vi - ci * wp.cross(wi, n)) - v_face
            mstar = 1.0 / inv_sum
            p = pair_table[mat_i * num_materials + tet_material[face_tet[f]]]
            # A face is flat: R* = r, as for a wall.
            out, k = pair_interaction(n, delta, r, r, r, mstar, v_rel, wi, shear_old, p, dt)
            force = out[0]
            roll = out[1]
            sphere_face_shear[slot] = out[2]
            ft = force - wp.dot(force, n) * n
            f_i += force
            t_i += wp.cross(-ci * n, ft) + roll
            # Equal and opposite, spread over the face's nodes by the weights of the contact point.
            wp.atomic_add(node_f, fn[0], -w[0] * force)
            wp.atomic_add(node_f, fn[1], -w[1] * force)
            wp.atomic_add(node_f, fn[2], -w[2] * force)
            if wp.static(track_energy):
                e_n += elastic_energy(delta, k[0])
                e_t += 0.5 * k[1] * wp.dot(out[2], out[2])
                a_t += 0.5 * k[1] * wp.dot(shear_old, shear_old)
                d_behind -= 0.5 * dt * (wp.dot(force, v_rel) + wp.dot(roll, wi))
                wp.atomic_add(node_f_sphere_face, fn[0], -w[0] * force)
                wp.atomic_add(node_f_sphere_face, fn[1], -w[1] * force)
                wp.atomic_add(node_f_sphere_face, fn[2], -w[2] * force)
        wp.atomic_add(particle_f, i, f_i)
        wp.atomic_add(particle_t, i, t_i)
        if wp.static(track_energy):
            sphere_face_f[i] = f_i
            sphere_face_t[i] = t_i
            prev = sphere_face_energy_prev[i]
            sphere_face_energy_prev[i] = wp.vec2(e_n, e_t)
            if dt > 0.0:  # the set-up evaluation (dt = 0) only records the springs' energies
                d = wp.float64(d_behind) - (wp.float64(e_n) - wp.float64(prev[0]))
                d -= wp.float64(e_t) - wp.float64(a_t)
                sphere_face_dissipated[i] = sphere_face_dissipated[i] + d
                energy_stiffness_change[i] = energy_stiffness_change[i] + (wp.float64(a_t) - wp.float64(prev[1]))

    @wp.kernel(enable_backward=False, module="unique")
    def sphere_face_energy_kernel(
        # Model:
        particle_radius: wp.array(dtype=float),
        particle_inv_mass: wp.array(dtype=float),
        particle_material: wp.array(dtype=int),
        pair_table: wp.array(dtype=ContactPair),
        num_materials: int,
        node_inv_mass: wp.array(dtype=float),
        tet_material: wp.array(dtype=int),
        face_nodes: wp.array(dtype=wp.vec3i),
        face_tet: wp.array(dtype=int),
        face_radius: float,
        max_sphere_faces: int,
        # State in:
        particle_count: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        sphere_face_count: wp.array(dtype=int),
        sphere_face_index: wp.array(dtype=int),
        sphere_face_shear: wp.array(dtype=wp.vec3),
        node_q: wp.array(dtype=wp.vec3),
        # Out:
        energy: wp.array(dtype=wp.float64),
    ):
        i = wp.tid()  # one thread per particle slot: elastic energy of its sphere–face springs
        energy[i] = wp.float64(0.0)
        if i >= particle_count[0]:
            return
        count = wp.min(sphere_face_count[i], max_sphere_faces)
        x = particle_q[i]
        r = particle_radius[i]
        best_f = counted_face(i, x, r, face_radius, count, max_sphere_faces, sphere_face_index, face_nodes, node_q)
        e = float(0.0)
        for s in range(count):
            slot = i * max_sphere_faces + s
            f = sphere_face_index[slot]
            fn = face_nodes[f]
            w, _n, dist, touching, interior = sphere_face_contact(x, r, fn, node_q)
            if not (touching and (interior or f == best_f)):
                continue
            inv_sum = particle_inv_mass[i] + w[0] * w[0] * node_inv_mass[fn[0]]
            inv_sum += w[1] * w[1] * node_inv_mass[fn[1]] + w[2] * w[2] * node_inv_mass[fn[2]]
            if inv_sum == 0.0:
                continue
            delta = r - dist
            p = pair_table[particle_material[i] * num_materials + tet_material[face_tet[f]]]
            fnv = normal_force(delta, 0.0, r, r, r, 1.0, p)
            kt = tangential_stiffness(delta, r, fnv[2], p)
            sh = sphere_face_shear[slot]
            e += elastic_energy(delta, fnv[2]) + 0.5 * kt * wp.dot(sh, sh)
        energy[i] = wp.float64(e)

    return eval_sphere_faces_kernel, sphere_face_energy_kernel
