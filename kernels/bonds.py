"""Cohesive bonds between spheres: the bonded-particle model of the CIMNE paper (adaptive_dem_fem_blast.txt §2).

A bond joins spheres i < j with normal and shear springs of stiffness k_n = E_b A / L_0 and k_s = k_n / κ, A the
bond cross-section. It carries tension and compression. It breaks when its normal stress k_n (L - L_0) / A reaches
the tensile strength or its shear stress k_s |u_s| / A reaches the shear strength; a broken bond applies no force,
and the pair is then an ordinary frictional contact (contact stage). Broken bonds are removed between steps by a
compaction pass.

Energy books, as velocity Verlet does the work (the same scheme as the sphere contacts, kernels/contact.py
``make_contact_kernels``): a bond books the half of its work behind its evaluation, ½ dt f_{n+1}·v_rel, and adds its
forces to the spheres' sums, whose half ahead the integrator books on the damping (normal) and friction (shear) lines.
The dashpots' work goes to those lines: ``energy_damping`` (normal) and ``energy_friction`` (shear, with the contacts'
tangential dashpots). The springs' work and their energy change go together to ``energy_bond_trapezoid``: at each
evaluation a bond books there its springs' -W - ΔU (the half ahead of its last evaluation, recovered to rounding by
:func:`spring_half_step` and handed back to the damping and friction lines, the half behind, and ΔU from the
springs' energies at the last evaluation, ``bond_energy_prev``). That is no dissipation: a spring that turns by θ in a
step does the trapezoid work along n_n and n_{n+1}, which differs from ½ k Δ(s²) by ½ k (1 - cos θ)(s_{n+1} L_n -
s_n L_{n+1}), of either sign (negative while it is compressed: the lattice bonds of a blast's first conversion pass,
born relaxed and crushed and turned in their first steps, booked -33 J in one step on masonry_tunnel_blast as
"damping"). A bond that breaks applies no force at that evaluation: it releases what its springs hold half a step
past their last evaluation (:func:`spring_half_step`) to ``energy_bond_broken``, hands their work over that
half step back to the two dissipation lines, and books what they held at the evaluation less that work and less the
release, Verlet's error over the half step, on the trapezoid line, so the springs leave no trace on the dissipation
lines and the release is never negative.
"""

from __future__ import annotations

import warp as wp

from .contact import book_contact_force, rotate_into_plane

wp.set_module_options({"enable_backward": False})

BOND_INTACT = wp.constant(0)
BOND_BROKEN_TENSION = wp.constant(1)
BOND_BROKEN_SHEAR = wp.constant(2)


@wp.func
def bond_arms(ri: float, rj: float, dist: float) -> wp.vec2:
    """Lever arms from the centres to the bond's mid-plane, splitting the distance in proportion to the radii."""
    s = dist / (ri + rj)
    return wp.vec2(ri * s, rj * s)


@wp.func
def spring_half_step(
    xi: wp.vec3d,
    xj: wp.vec3d,
    dt: float,
    vi: wp.vec3,
    vj: wp.vec3,
    wi: wp.vec3,
    wj: wp.vec3,
    ri: float,
    rj: float,
    rest_length: float,
    kn: float,
    ks: float,
    shear: wp.vec3,
    breaks: int,
) -> wp.vec4d:
    """A bond's springs over the half step ahead of their last evaluation, called at the next evaluation, where the
    velocities are v_{n+1/2} (``vi``, ``vj``, spins ``wi``, ``wj``) and the centres ``xi``, ``xj`` have drifted by
    dt v_{n+1/2} (kernels/integrate.py ``drift_particle``: x + dt v in float64, which x - dt v undoes to float64
    rounding); ``shear`` is the shear spring of the last evaluation (in its contact plane); ``breaks`` 1 where the bond
    breaks at this evaluation (the energy is needed only there: 0 skips it; for every bond it made the default
    scene's run 33 % slower).

    - Their work [J] over that half step, ½ dt f_n·v_{n+1/2} (normal; shear with the moments of its force:
      ½ dt f_s·v_rel), which the integrator booked as minus it on the damping and friction lines (kernels/integrate.py
      ``book_contact_work_ahead``): the last evaluation's centres and shear spring give its forces as it made them,
      to float64 rounding of the centres.
    - The energy [J] they hold at the end of it, (½ k_n s², ½ k_s |u_s|²) at the centres x - ½ dt v, the shear spring
      turned into that contact plane and grown by half a step of sliding: where a bond that breaks at the next
      evaluation lets go. Never negative; what the springs held at their last evaluation less their work over the
      half step differs from it by Verlet's error, the same to O(dt²) where the step resolves the motion, negative
      where it overshoots (a bond crushed by a blast and pulled past its strength in the next step).

    Returns:
        (normal work, shear work, normal energy, shear energy) [J]; the energies 0 unless ``breaks``.
    """
    work_n = wp.float64(0.0)
    work_s = wp.float64(0.0)
    d_old = wp.vec3((xi - wp.vec3d(dt * vi)) - (xj - wp.vec3d(dt * vj)))  # as the evaluation formed x_i - x_j
    dv = vi - vj
    dist_old = wp.length(d_old)
    if dist_old > 0.0:
        n_old = d_old / dist_old
        arms_old = bond_arms(ri, rj, dist_old)
        fn = -kn * (dist_old - rest_length)
        fs = -ks * shear
        v_rel_old = (dv - arms_old[0] * wp.cross(wi, n_old)) - arms_old[1] * wp.cross(wj, n_old)
        work_n = wp.float64(0.5 * dt * fn * wp.dot(n_old, dv))
        work_s = wp.float64(0.5 * dt * wp.dot(fs, v_rel_old))
    energy_n = wp.float64(0.0)
    energy_s = wp.float64(0.0)
    if breaks == 0:
        return wp.vec4d(work_n, work_s, energy_n, energy_s)
    half = wp.float64(0.5 * dt)
    d = wp.vec3((xi - half * wp.vec3d(vi)) - (xj - half * wp.vec3d(vj)))
    dist = wp.length(d)
    if dist > 0.0:
        n = d / dist
        arms = bond_arms(ri, rj, dist)
        v_rel = (vi - arms[0] * wp.cross(wi, n)) - (vj + arms[1] * wp.cross(wj, n))
        vt = v_rel - wp.dot(v_rel, n) * n
        us = rotate_into_plane(shear, n) + vt * (0.5 * dt)
        stretch = dist - rest_length
        energy_n = wp.float64(0.5 * kn * stretch * stretch)
        energy_s = wp.float64(0.5 * ks * wp.dot(us, us))
    return wp.vec4d(work_n, work_s, energy_n, energy_s)


@wp.kernel
def eval_bonds_kernel(
    # Model:
    particle_radius: wp.array(dtype=float),
    particle_inv_mass: wp.array(dtype=float),
    dt: float,
    # State in:
    particle_q: wp.array(dtype=wp.vec3d),
    particle_qd: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    bond_count: wp.array(dtype=int),
    bond_i: wp.array(dtype=int),
    bond_j: wp.array(dtype=int),
    bond_rest_length: wp.array(dtype=float),
    bond_kn: wp.array(dtype=float),
    bond_ks: wp.array(dtype=float),
    bond_area: wp.array(dtype=float),
    bond_tensile_strength: wp.array(dtype=float),
    bond_shear_strength: wp.array(dtype=float),
    bond_damping: wp.array(dtype=float),
    # In:
    track_energy: int,
    # State out:
    bond_shear: wp.array(dtype=wp.vec3),
    bond_broken: wp.array(dtype=int),
    bonds_broken_total: wp.array(dtype=int),
    bond_energy_prev: wp.array(dtype=wp.vec2),
    particle_f: wp.array(dtype=wp.vec3),
    particle_t: wp.array(dtype=wp.vec3),
    contact_sums: wp.array(dtype=wp.mat33),
    energy_damping: wp.array(dtype=wp.float64),
    energy_friction: wp.array(dtype=wp.float64),
    energy_bond_broken: wp.array(dtype=wp.float64),
    energy_bond_trapezoid: wp.array(dtype=wp.float64),
    particle_bonds_broken: wp.array(dtype=int),
):
    b = wp.tid()  # one thread per bond slot
    if b >= bond_count[0]:
        return
    if bond_broken[b] != BOND_INTACT:
        return
    i = bond_i[b]
    j = bond_j[b]
    ri = particle_radius[i]
    rj = particle_radius[j]
    d = wp.vec3(particle_q[i] - particle_q[j])  # float64 difference of the centres, then float32
    dist = wp.length(d)
    n = d / dist
    arms = bond_arms(ri, rj, dist)
    wi = particle_omega[i]
    wj = particle_omega[j]
    v_rel = (particle_qd[i] - arms[0] * wp.cross(wi, n)) - (particle_qd[j] + arms[1] * wp.cross(wj, n))
    vn = wp.dot(v_rel, n)
    vt = v_rel - vn * n
    stretch = dist - bond_rest_length[b]
    kn = bond_kn[b]
    ks = bond_ks[b]
    us = rotate_into_plane(bond_shear[b], n) + vt * dt
    area = bond_area[b]
    # Strength check on the elastic (spring) forces, before they are applied: the bond fails within one step's
    # load increment of its strength.
    mode = BOND_INTACT
    if kn * stretch >= bond_tensile_strength[b] * area:
        mode = BOND_BROKEN_TENSION
    elif ks * wp.length(us) >= bond_shear_strength[b] * area:
        mode = BOND_BROKEN_SHEAR
    e_n = 0.5 * kn * stretch * stretch
    e_s = 0.5 * ks * wp.dot(us, us)
    prev = bond_energy_prev[b]
    # The springs over the half step ahead of their last evaluation, with its shear spring (still in bond_shear):
    # their work, handed back to the dissipation lines either way (0 at the set-up evaluation, dt = 0, which books
    # nothing else), and the energy they hold at its end, released at a break.
    half_step = wp.vec4d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    breaks = int(0)
    if mode != BOND_INTACT:
        breaks = 1
    if track_energy != 0:
        half_step = spring_half_step(
            particle_q[i],
            particle_q[j],
            dt,
            particle_qd[i],
            particle_qd[j],
            wi,
            wj,
            ri,
            rj,
            bond_rest_length[b],
            kn,
            ks,
            bond_shear[b],
            breaks,
        )
    w = wp.vec2d(half_step[0], half_step[1])
    if mode != BOND_INTACT:
        bond_broken[b] = mode
        wp.atomic_add(bonds_broken_total, 0, 1)
        # Damage of each sphere (bonds lost so far), for output: the break path runs once per bond, so it is cheap.
        wp.atomic_add(particle_bonds_broken, i, 1)
        wp.atomic_add(particle_bonds_broken, j, 1)
        # A broken bond applies no force now: its springs did work only over the half step after their last
        # evaluation, which the integrator booked from the spheres' force sums as minus that work on the dissipation
        # lines; that work is handed back to them, so only the dashpots' work stays there. Released is what the
        # springs hold at the end of that half step, where they let go (:func:`spring_half_step`; never negative):
        # not their energy at the new positions, a stretch no force worked for (-4.8 kJ on masonry_wall_blast, where
        # lattice bonds born relaxed break in the first step after a conversion), nor what they held less their work
        # since, which overshoots where a crushed bond is pulled past its strength in one step (-6.1 kJ "released" on
        # masonry_tunnel_blast). That difference, Verlet's error over the half step, goes to the trapezoid line.
        if track_energy != 0:
            released = half_step[2] + half_step[3]
            if dt <= 0.0:  # the set-up evaluation: no step was taken, what the springs held is what they had
                released = wp.float64(prev[0]) + wp.float64(prev[1])
            wp.atomic_add(energy_bond_broken, i, released)
            wp.atomic_add(energy_bond_trapezoid, i, wp.float64(prev[0]) + wp.float64(prev[1]) - w[0] - w[1] - released)
            wp.atomic_add(energy_damping, i, w[0])
            wp.atomic_add(energy_friction, i, w[1])
        return
    bond_shear[b] = us
    bond_energy_prev[b] = wp.vec2(e_n, e_s)
    inv_sum = particle_inv_mass[i] + particle_inv_mass[j]
    mstar = float(0.0)
    if inv_sum > 0.0:
        mstar = 1.0 / inv_sum
    zeta = bond_damping[b]
    gn = 2.0 * zeta * wp.sqrt(mstar * kn)
    gs = 2.0 * zeta * wp.sqrt(mstar * ks)
    fn = -kn * stretch - gn * vn
    ft = -ks * us - gs * vt
    force = fn * n + ft
    wp.atomic_add(particle_f, i, force)
    wp.atomic_add(particle_f, j, -force)
    wp.atomic_add(particle_t, i, wp.cross(-arms[0] * n, ft))
    wp.atomic_add(particle_t, j, wp.cross(arms[1] * n, -ft))
    if track_energy == 0:
        return
    book_contact_force(i, fn * n, ft, wp.cross(-arms[0] * n, ft), contact_sums)
    book_contact_force(j, -fn * n, -ft, wp.cross(arms[1] * n, -ft), contact_sums)
    if dt > 0.0:  # the set-up evaluation (dt = 0) only records the springs' energies
        # The half of the work behind, ½ dt f·v_rel, as one float32 product per spring and dashpot pair (so the books'
        # total is the same sum, to float64 rounding, as with both on one line), split in float64: the dashpots' part,
        # ½ dt γ v², to the dissipation lines; the springs' -W - ΔU to the trapezoid line: their half behind (the
        # rest), their half ahead of the last evaluation (which the integrator booked on the dissipation lines: handed
        # back there, so those keep the dashpots' work alone, to rounding) and ΔU in float64 (its sum telescopes).
        behind_n = wp.float64(-0.5 * dt * fn * vn)
        behind_s = wp.float64(-0.5 * dt * wp.dot(ft, vt))
        dash_n = wp.float64(0.5 * dt * gn * vn * vn)
        dash_s = wp.float64(0.5 * dt * gs * wp.dot(vt, vt))
        t_n = (behind_n - dash_n) - (wp.float64(e_n) - wp.float64(prev[0])) - w[0]
        t_s = (behind_s - dash_s) - (wp.float64(e_s) - wp.float64(prev[1])) - w[1]
        wp.atomic_add(energy_damping, i, dash_n + w[0])
        wp.atomic_add(energy_friction, i, dash_s + w[1])
        wp.atomic_add(energy_bond_trapezoid, i, t_n + t_s)


@wp.kernel
def bond_energy_kernel(
    # State in:
    particle_q: wp.array(dtype=wp.vec3d),
    bond_count: wp.array(dtype=int),
    bond_i: wp.array(dtype=int),
    bond_j: wp.array(dtype=int),
    bond_rest_length: wp.array(dtype=float),
    bond_kn: wp.array(dtype=float),
    bond_ks: wp.array(dtype=float),
    bond_shear: wp.array(dtype=wp.vec3),
    bond_broken: wp.array(dtype=int),
    # Out:
    energy: wp.array(dtype=wp.float64),
    intact: wp.array(dtype=int),
):
    """Each intact live bond's spring energy ½ k_n (|x_i − x_j| − L)² + ½ k_s |u_s|² [J] into ``energy[b]`` (other
    slots are not written), and the count of intact bonds into ``intact[0]``."""
    b = wp.tid()  # one thread per bond slot
    if b >= bond_count[0]:
        return
    if bond_broken[b] != BOND_INTACT:
        return
    stretch = wp.length(wp.vec3(particle_q[bond_i[b]] - particle_q[bond_j[b]])) - bond_rest_length[b]
    us = bond_shear[b]
    e = 0.5 * bond_kn[b] * stretch * stretch + 0.5 * bond_ks[b] * wp.dot(us, us)
    energy[b] = wp.float64(e)
    wp.atomic_add(intact, 0, 1)


@wp.func
def within_bond_gap(xi: wp.vec3d, ri: float, xj: wp.vec3d, rj: float, gap_tolerance: float) -> bool:
    """Whether two spheres are close enough to bond: gap ≤ gap_tolerance (r_i + r_j)."""
    return wp.length(wp.vec3(xi - xj)) <= (ri + rj) * (1.0 + gap_tolerance)


@wp.kernel
def count_bond_pairs_kernel(
    # Model:
    particle_radius: wp.array(dtype=float),
    gap_tolerance: float,
    search_radius: float,
    # In:
    grid: wp.uint64,
    particle_q: wp.array(dtype=wp.vec3d),
    bondable: wp.array(dtype=int),
    # Out:
    pair_count: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per particle; counts the j > i it bonds to
    pair_count[i] = 0
    if bondable[i] == 0:
        return
    xi = particle_q[i]
    ri = particle_radius[i]
    n = int(0)
    for j in wp.hash_grid_query(grid, xi, wp.float64(search_radius)):
        if j > i and bondable[j] == bondable[i]:
            if within_bond_gap(xi, ri, particle_q[j], particle_radius[j], gap_tolerance):
                n += 1
    pair_count[i] = n


@wp.kernel
def fill_bond_pairs_kernel(
    # Model:
    particle_radius: wp.array(dtype=float),
    gap_tolerance: float,
    search_radius: float,
    # In:
    grid: wp.uint64,
    particle_q: wp.array(dtype=wp.vec3d),
    bondable: wp.array(dtype=int),
    pair_offset: wp.array(dtype=int),
    # Out:
    pairs: wp.array(dtype=wp.vec2i),
):
    i = wp.tid()  # one thread per particle; writes its pairs from its scanned offset (order within a particle is
    # the grid's, and is sorted on the host)
    if bondable[i] == 0:
        return
    xi = particle_q[i]
    ri = particle_radius[i]
    slot = pair_offset[i]
    for j in wp.hash_grid_query(grid, xi, wp.float64(search_radius)):
        if j > i and bondable[j] == bondable[i]:
            if within_bond_gap(xi, ri, particle_q[j], particle_radius[j], gap_tolerance):
                pairs[slot] = wp.vec2i(i, j)
                slot += 1
