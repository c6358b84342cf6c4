"""Sphere contact: neighbour-list build from a hash grid, and contact forces with tangential history.

Conventions (as in LIGGGHTS' ``pair gran``): for a pair (i, j) the unit normal ``n = (x_i - x_j) / |x_i - x_j|``
points from j to i, the overlap is ``delta = r_i + r_j - |x_i - x_j|`` and the normal speed
``v_n = (v_i - v_j) . n`` is negative while the spheres approach. A positive normal force pushes i along +n.
Centres (and wall points) are float64; ``x_i - x_j`` is formed in float64 and rounded to float32 once, so the contact
arithmetic sees the same small vector wherever the pair is (warpdem.model, State.particle_q).

The neighbour list is a *half* list: particle i stores the j > i within ``r_i + r_j + skin``, in fixed slots
``i * K .. i * K + K - 1``. Each slot carries the tangential spring of that pair (``shear``, [m], in the
current contact plane) and the bond between the pair, if any (``bond``, index into the bond arrays or -1).
"""

from __future__ import annotations

import dataclasses
import functools

import warp as wp

from .neighbors import ListSpec, make_list_kernels

wp.set_module_options({"enable_backward": False})

# Motion kinds of a particle (``particle_motion``).
MOTION_FREE = wp.constant(0)
MOTION_FIXED = wp.constant(1)
MOTION_PRESCRIBED = wp.constant(2)


@wp.struct
class ContactPair:
    """Interaction properties of one (material a, material b) pair; a table of n_mat² entries.

    Attributes:
        estar: effective Young's modulus E* = 1 / ((1 - ν_a²)/E_a + (1 - ν_b²)/E_b) [Pa].
        gstar: effective shear modulus G* = 1 / (2(2 - ν_a)(1 + ν_a)/E_a + 2(2 - ν_b)(1 + ν_b)/E_b) [Pa].
        young_a: Young's modulus of material a [Pa] (linear stiffness k_n = 2 E_a r_a E_b r_b / (E_a r_a + E_b r_b)).
        young_b: Young's modulus of material b [Pa].
        kt_ratio: k_t / k_n of the linear tangential spring, 2(1 - ν)/(2 - ν) with ν the mean Poisson ratio [-].
        friction: Coulomb coefficient μ [-].
        rolling: rolling-resistance coefficient μ_r [-] (torque μ_r R* F_n).
        damp_n: normal damping: ζ of the linear model or c of the Hertz model, from the restitution [-].
        damp_t: tangential damping ratio ζ_t (damping 2 ζ_t sqrt(m* k_t)) [-].
    """

    estar: float
    gstar: float
    young_a: float
    young_b: float
    kt_ratio: float
    friction: float
    rolling: float
    damp_n: float
    damp_t: float


# ----------------------------------------------------------------------------------------------------------------
# Contact laws. Each normal law returns (total normal force, elastic part, stiffness k_n = dF_el/dδ-secant) so
# that the tangential laws and the energy bookkeeping can be composed with any of them.


@wp.func
def hertz_normal_force(delta: float, vn: float, rstar: float, mstar: float, p: ContactPair) -> wp.vec3:
    """Hertz normal force with Tsuji-type damping, clamped non-negative.

    F_el = (4/3) E* sqrt(R*) δ^{3/2} (Hertz); F = max(0, F_el - c sqrt(m* k) δ^{1/4} v_n) with
    k = (4/3) E* sqrt(R*) and c from the restitution (warpdem.stages.restitution.hertz_damping_coefficient), which makes
    the restitution exact and independent of the impact speed.

    Returns:
        (F [N], F_el [N], k_n = F_el / δ [N/m]).
    """
    k = 4.0 / 3.0 * p.estar * wp.sqrt(rstar)
    sqrt_delta = wp.sqrt(delta)
    f_el = k * delta * sqrt_delta
    eta = p.damp_n * wp.sqrt(mstar * k) * wp.sqrt(sqrt_delta)
    f = wp.max(f_el - eta * vn, 0.0)
    return wp.vec3(f, f_el, k * sqrt_delta)


@wp.func
def linear_normal_force(delta: float, vn: float, kn: float, mstar: float, p: ContactPair) -> wp.vec3:
    """Linear spring–dashpot normal force, clamped non-negative: F = max(0, k_n δ - 2 ζ sqrt(m* k_n) v_n).

    Returns:
        (F [N], F_el [N], k_n [N/m]).
    """
    f_el = kn * delta
    f = wp.max(f_el - 2.0 * p.damp_n * wp.sqrt(mstar * kn) * vn, 0.0)
    return wp.vec3(f, f_el, kn)


@wp.func
def linear_stiffness(ra: float, rb: float, p: ContactPair) -> float:
    """Normal stiffness of the linear model, k_n = 2 E_a r_a E_b r_b / (E_a r_a + E_b r_b) [N/m] (YADE FrictPhys)."""
    ka = p.young_a * ra
    kb = p.young_b * rb
    return 2.0 * ka * kb / (ka + kb)


@wp.func
def mindlin_stiffness(delta: float, rstar: float, kn: float, p: ContactPair) -> float:
    """Mindlin no-slip tangential stiffness k_t = 8 G* sqrt(R* δ) [N/m]."""
    return 8.0 * p.gstar * wp.sqrt(rstar * delta)


@wp.func
def linear_tangential_stiffness(delta: float, rstar: float, kn: float, p: ContactPair) -> float:
    """Linear tangential stiffness k_t = (k_t/k_n) k_n [N/m]."""
    return p.kt_ratio * kn


@wp.func
def rotate_into_plane(shear: wp.vec3, n: wp.vec3) -> wp.vec3:
    """Project a tangential spring onto the plane normal to n, keeping its length (the contact plane rotates)."""
    length = wp.length(shear)
    projected = shear - wp.dot(shear, n) * n
    plen = wp.length(projected)
    if plen > 0.0:
        return projected * (length / plen)
    return wp.vec3(0.0)


@wp.func
def coulomb_tangential(
    shear: wp.vec3, vt: wp.vec3, kt: float, gamma_t: float, fn: float, mu: float, dt: float
) -> wp.mat33:
    """Tangential spring with a Coulomb limit and a dashpot while sticking (Cundall & Strack; LIGGGHTS history).

    ξ ← ξ + v_t dt and F_s = -k_t ξ. Sliding (|F_s| > μ F_n): F_t = μ F_n F_s/|F_s| and the spring is cut back to
    ξ = -F_t / k_t, so a sliding contact stores no more than (μ F_n)² / (2 k_t). Sticking: F_t = F_s - γ_t v_t,
    itself capped at μ F_n (Coulomb bounds the whole tangential force; the spring keeps its length, so the cap
    does not feed the 1/k_t blow-up of the dashpot term at first touch).

    Returns:
        Rows: (F_t on body a [N], new spring ξ [m], zero row).
    """
    s = shear + vt * dt
    ft = -kt * s
    limit = mu * fn
    ft_len = wp.length(ft)
    if ft_len > limit:
        if ft_len > 0.0:
            ft = ft * (limit / ft_len)
        if kt > 0.0:
            s = -ft / kt
        else:
            s = wp.vec3(0.0)
    else:
        ft = ft - gamma_t * vt
        ft_len = wp.length(ft)
        if ft_len > limit:
            ft = ft * (limit / ft_len)
    return wp.mat33(ft[0], ft[1], ft[2], s[0], s[1], s[2], 0.0, 0.0, 0.0)


@wp.func
def kept_spring(out: wp.mat33, shear_old: wp.vec3, dt: float) -> wp.vec3:
    """The tangential spring a pair keeps after an evaluation [m]: the updated one (``out``'s third row) in a step;
    the one it had in an evaluation at dt = 0 (the set-up, or the re-evaluation after a topology pass). Nothing moves
    there, and no line books a change: the Coulomb limit it is cut back to takes the normal dashpot at the velocity
    between steps, not at the half step the step used, so a sliding spring cut there lost its energy from the books
    (up to 8.9 J in one pass on masonry_tunnel_blast, −77 J over its run). The force of that evaluation is still
    capped; the next step cuts the spring, and books what it loses as friction."""
    if dt > 0.0:
        return wp.vec3(out[2, 0], out[2, 1], out[2, 2])
    return shear_old


@wp.func
def constant_rolling_torque(omega_rel: wp.vec3, fn: float, rstar: float, p: ContactPair) -> wp.vec3:
    """Constant directional torque rolling resistance (model A of Ai et al. 2011): M = -μ_r R* F_n ω_r/|ω_r| on i."""
    w = wp.length(omega_rel)
    if w > 1.0e-12:
        return -p.rolling * rstar * fn * omega_rel / w
    return wp.vec3(0.0)


@wp.func
def no_rolling_torque(omega_rel: wp.vec3, fn: float, rstar: float, p: ContactPair) -> wp.vec3:
    """No rolling resistance."""
    return wp.vec3(0.0)


@wp.func
def hertz_elastic_energy(delta: float, kn: float) -> float:
    """Hertz contact energy U = (2/5) k_n δ² with k_n = F_el/δ, i.e. ∫F dδ = (2/5)(4/3)E* sqrt(R*) δ^{5/2} [J]."""
    return 0.4 * kn * delta * delta


@wp.func
def linear_elastic_energy(delta: float, kn: float) -> float:
    """Linear spring energy U = k_n δ² / 2 [J]."""
    return 0.5 * kn * delta * delta


@wp.func
def carried_by_bond(bond: int, bond_broken: wp.array(dtype=int)) -> bool:
    """Whether a neighbour slot's pair is held by an intact bond (then it is no contact)."""
    if bond >= 0:
        return bond_broken[bond] == 0
    return False


@wp.func
def book_contact_force(
    i: int,
    fn_vec: wp.vec3,
    ft: wp.vec3,
    torque: wp.vec3,
    contact_sums: wp.array(dtype=wp.mat33),
):
    """Add a contact's normal force, tangential force and tangential + rolling torque on sphere i [N, N, N m] to its
    sums, the rows of ``contact_sums[i]``, which the integrator dots with v_{n+1/2} and ω_{n+1/2} for the half of the
    force's work that lies ahead (kernels/integrate.py ``book_contact_work_ahead``). The three sums are one record so
    that a pair's other sphere, reached at random, costs one cache line, not three (warpdem.model.State
    ``contact_sums``); each row adds as its own vec3 would, bit for bit."""
    wp.atomic_add(contact_sums, i, wp.matrix_from_rows(fn_vec, ft, torque))


NORMAL_MODELS = ("hertz", "linear")
TANGENTIAL_MODELS = ("mindlin", "linear")
ROLLING_MODELS = ("none", "constant_torque")


@dataclasses.dataclass(frozen=True)
class PairLaws:
    """The contact laws of one choice of models, composed as wp.funcs (:func:`make_pair_laws`).

    Attributes:
        normal_force: (δ, v_n, r_a, r_b, R*, m*, p) → (F [N], F_el [N], k_n [N/m]).
        tangential_stiffness: (δ, R*, k_n, p) → k_t [N/m].
        elastic_energy: (δ, k_n) → normal spring energy [J].
        stiffnesses: (δ, r_a, r_b, R*, p) → (k_n, k_t) [N/m] of the springs at overlap δ ≥ 0.
        pair_interaction: force and rolling torque on body a of a touching pair and its new tangential spring.
        pair_dissipation: energy a touching pair dissipated during the step (normal, tangential) [J].
        parting_spring: whether k_t(0) can be nonzero (a linear tangential spring on a linear normal one), so that a
            pair that parts lets go of ½ k_t(0) |ξ|²; otherwise that term is an exact zero and the kernels leave it
            out at code generation (else every parted pair and every wall out of reach tests its spring each step).
    """

    normal_force: wp.Function
    tangential_stiffness: wp.Function
    elastic_energy: wp.Function
    stiffnesses: wp.Function
    pair_interaction: wp.Function
    pair_dissipation: wp.Function
    parting_spring: bool


@functools.cache
def make_pair_laws(normal: str, tangential: str, rolling: str) -> PairLaws:
    """Compose the contact laws of one choice of models (shared by the sphere–sphere and sphere–wall kernels here
    and the sphere–FEM-face kernel of kernels/fem_contact.py, so a face is hit exactly as a wall is).

    Args:
        normal: "hertz" or "linear".
        tangential: "mindlin" or "linear".
        rolling: "none" or "constant_torque".
    """
    if normal not in NORMAL_MODELS or tangential not in TANGENTIAL_MODELS or rolling not in ROLLING_MODELS:
        raise ValueError(f"unknown contact model {normal!r}/{tangential!r}/{rolling!r}")
    hertz = normal == "hertz"
    tangential_stiffness = mindlin_stiffness if tangential == "mindlin" else linear_tangential_stiffness
    rolling_torque = constant_rolling_torque if rolling == "constant_torque" else no_rolling_torque
    elastic_energy = hertz_elastic_energy if hertz else linear_elastic_energy

    @wp.func
    def normal_force(delta: float, vn: float, ra: float, rb: float, rstar: float, mstar: float, p: ContactPair):
        if wp.static(hertz):
            return hertz_normal_force(delta, vn, rstar, mstar, p)
        else:
            return linear_normal_force(delta, vn, linear_stiffness(ra, rb, p), mstar, p)

    @wp.func
    def stiffnesses(delta: float, ra: float, rb: float, rstar: float, p: ContactPair) -> wp.vec2:
        kn = normal_force(delta, 0.0, ra, rb, rstar, 1.0, p)[2]
        return wp.vec2(kn, tangential_stiffness(delta, rstar, kn, p))

    @wp.func
    def pair_interaction(
        n: wp.vec3,
        delta: float,
        ra: float,
        rb: float,
        rstar: float,
        mstar: float,
        v_rel: wp.vec3,
        omega_rel: wp.vec3,
        shear: wp.vec3,
        p: ContactPair,
        dt: float,
    ):
        """Force and torque on body a of a touching pair, and the updated tangential spring.

        v_rel is the velocity of a's contact point relative to b's. Returns rows: (force on a [N],
        rolling torque on a [N m], new spring ξ [m]), the caller adding the moment of the tangential force; and the
        springs' stiffnesses (k_n, k_t) [N/m] at δ, as :func:`stiffnesses` gives them, for the energy books.
        """
        vn = wp.dot(v_rel, n)
        fnv = normal_force(delta, vn, ra, rb, rstar, mstar, p)
        fn = fnv[0]
        kn = fnv[2]
        vt = v_rel - vn * n
        kt = tangential_stiffness(delta, rstar, kn, p)
        gamma_t = 2.0 * p.damp_t * wp.sqrt(mstar * kt)
        tang = coulomb_tangential(rotate_into_plane(shear, n), vt, kt, gamma_t, fn, p.friction, dt)
        ft = tang[0]
        force = fn * n + ft
        torque = rolling_torque(omega_rel, fn, rstar, p)
        rows = wp.mat33(
            force[0], force[1], force[2], torque[0], torque[1], torque[2], tang[1, 0], tang[1, 1], tang[1, 2]
        )
        return rows, wp.vec2(kn, kt)

    @wp.func
    def pair_dissipation(
        n: wp.vec3,
        delta: float,
        ra: float,
        rb: float,
        rstar: float,
        mstar: float,
        v_rel: wp.vec3,
        omega_rel: wp.vec3,
        shear_old: wp.vec3,
        shear_new: wp.vec3,
        force: wp.vec3,
        rolling_t: wp.vec3,
        p: ContactPair,
        dt: float,
    ) -> wp.vec2:
        """Energy dissipated by this pair during this step [J]: (normal damping, friction + tangential damping).

        Normal: -(F_n - F_el) v_n dt, which is the dashpot's work and, while the clamp holds F_n at 0, the
        elastic energy released without doing work. Tangential: the work of F_t on the sliding minus the change
        of the spring's energy k_t |ξ|²/2. Rolling torque work counts as friction.
        """
        vn = wp.dot(v_rel, n)
        fnv = normal_force(delta, vn, ra, rb, rstar, mstar, p)
        d_n = -(fnv[0] - fnv[1]) * vn * dt
        kt = tangential_stiffness(delta, rstar, fnv[2], p)
        vt = v_rel - vn * n
        ft = force - fnv[0] * n
        s_old = rotate_into_plane(shear_old, n)
        d_t = -wp.dot(ft, vt) * dt - 0.5 * kt * (wp.dot(shear_new, shear_new) - wp.dot(s_old, s_old))
        d_t = d_t - wp.dot(rolling_t, omega_rel) * dt
        return wp.vec2(d_n, d_t)

    return PairLaws(
        normal_force,
        tangential_stiffness,
        elastic_energy,
        stiffnesses,
        pair_interaction,
        pair_dissipation,
        parting_spring=not hertz and tangential == "linear",
    )


@functools.cache
def make_contact_kernels(normal: str, tangential: str, rolling: str, track_energy: bool):
    """Build the contact kernels for one choice of laws, specialised at code-generation time.

    Args:
        normal: "hertz" or "linear".
        tangential: "mindlin" or "linear".
        rolling: "none" or "constant_torque".
        track_energy: book damping/friction dissipation, the tangential springs' stiffness change and wall work
            per particle (float64), as velocity Verlet does the work (below).

    Energy books (``track_energy``). Velocity Verlet changes the kinetic energy over a step by the trapezoid
    ΔKE = ½ dt Σ (f_n + f_{n+1})·v_{n+1/2} (plus the shadow term dt²/8 Δ(|f|²/m), which does not accumulate), and
    v_{n+1/2} is the velocity during the evaluation of f_{n+1}. So each pair books here the half of its work that
    lies behind, ½ dt f_{n+1}·v_rel (with the rolling torque's ½ dt M·ω_rel), and adds its forces and torques to
    the sphere's sums, which the integrator dots with v_{n+3/2} once it is known (the half ahead). A pair's
    dissipation is then D = -W - ΔU exactly, normal part → ``energy_damping``, tangential and rolling part →
    ``energy_friction``; ΔU comes from the energies of the pairs each sphere owns (its half list and its walls),
    kept from the last evaluation in ``contact_energy_prev``, so a pair that parts books what its springs held.
    The tangential spring's ½ k_t |ξ|² also changes where k_t follows the overlap (Mindlin; a linear k_t on a
    Hertz k_n) at fixed ξ: that change is no work and no dissipation, and goes to ``energy_stiffness_change``.

    Returns:
        (eval_contacts_kernel, contact_energy_kernel).
    """
    laws = make_pair_laws(normal, tangential, rolling)
    normal_force = laws.normal_force
    tangential_stiffness = laws.tangential_stiffness
    elastic_energy = laws.elastic_energy
    stiffnesses = laws.stiffnesses
    pair_interaction = laws.pair_interaction
    book_parting = track_energy and laws.parting_spring

    @wp.kernel(enable_backward=False, module="unique")
    def eval_contacts_kernel(
        # Model:
        particle_radius: wp.array(dtype=float),
        particle_inv_mass: wp.array(dtype=float),
        particle_material: wp.array(dtype=int),
        pair_table: wp.array(dtype=ContactPair),
        num_materials: int,
        wall_normal: wp.array(dtype=wp.vec3),
        wall_velocity: wp.array(dtype=wp.vec3),
        wall_material: wp.array(dtype=int),
        num_walls: int,
        max_neighbors: int,
        dt: float,
        # State in:
        particle_count: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        particle_qd: wp.array(dtype=wp.vec3),
        particle_omega: wp.array(dtype=wp.vec3),
        nbr_count: wp.array(dtype=int),
        nbr_index: wp.array(dtype=int),
        nbr_bond: wp.array(dtype=int),
        bond_broken: wp.array(dtype=int),
        wall_point: wp.array(dtype=wp.vec3d),
        # State out:
        nbr_shear: wp.array(dtype=wp.vec3),
        wall_shear: wp.array(dtype=wp.vec3),
        particle_f: wp.array(dtype=wp.vec3),
        particle_t: wp.array(dtype=wp.vec3),
        contact_sums: wp.array(dtype=wp.mat33),
        contact_energy_prev: wp.array(dtype=wp.vec2),
        energy_damping: wp.array(dtype=wp.float64),
        energy_friction: wp.array(dtype=wp.float64),
        energy_stiffness_change: wp.array(dtype=wp.float64),
        energy_wall_work: wp.array(dtype=wp.float64),
    ):
        i = wp.tid()  # one thread per particle slot; it owns the pairs (i, j > i) of its half list
        if i >= particle_count[0]:
            return
        xi = particle_q[i]
        vi = particle_qd[i]
        wi = particle_omega[i]
        ri = particle_radius[i]
        inv_mi = particle_inv_mass[i]
        mat_i = particle_material[i]
        f_i = wp.vec3(0.0)
        t_i = wp.vec3(0.0)
        d_damp = float(0.0)  # minus the work behind (and the wall's share of the work ahead) [J]
        d_fric = float(0.0)  # the same, tangential and rolling [J]
        w_wall = float(0.0)
        e_n = float(0.0)  # normal spring energy of the pairs i owns [J]
        e_t = float(0.0)  # tangential spring energy, ½ k_t(δ_{n+1}) |ξ_{n+1}|² [J]
        a_t = float(0.0)  # the same at the old springs, ½ k_t(δ_{n+1}) |ξ_n|² [J]
        fn_i = wp.vec3(0.0)  # this thread's share of i's contact force sums
        ft_i = wp.vec3(0.0)
        touched = int(0)
        count = wp.min(nbr_count[i], max_neighbors)
        for s in range(count):
            slot = i * max_neighbors + s
            if carried_by_bond(nbr_bond[slot], bond_broken):
                continue  # the bonds stage handles this pair
            j = nbr_index[slot]
            rj = particle_radius[j]
            d = wp.vec3(xi - particle_q[j])  # float64 difference, exact or nearly: the same at any offset
            dist2 = wp.dot(d, d)
            rsum = ri + rj
            if dist2 >= rsum * rsum:
                if wp.static(book_parting):
                    # The pair parted: its tangential spring goes, ½ k_t(0) |ξ|² to friction (zero where k_t(0) = 0;
                    # the change from k_t(δ_n) to k_t(0) is the stiffness change): it counts in a_t, not in e_t.
                    sh = nbr_shear[slot]
                    if wp.dot(sh, sh) > 0.0:
                        p = pair_table[mat_i * num_materials + particle_material[j]]
                        a_t += 0.5 * stiffnesses(0.0, ri, rj, ri * rj / rsum, p)[1] * wp.dot(sh, sh)
                nbr_shear[slot] = wp.vec3(0.0)  # history lives only as long as the pair touches
                continue
            inv_mj = particle_inv_mass[j]
            inv_sum = inv_mi + inv_mj
            if inv_sum == 0.0:
                continue  # two immovable bodies exchange no force
            dist = wp.sqrt(dist2)
            # Coincident centres have no normal; +z (i up, j down) keeps the force finite and equal and opposite.
            n = wp.vec3(0.0, 0.0, 1.0)
            if dist > 0.0:
                n = d / dist
            delta = rsum - dist
            ci = ri - 0.5 * delta  # lever arms to the contact point
            cj = rj - 0.5 * delta
            vj = particle_qd[j]
            wj = particle_omega[j]
            v_rel = (vi - ci * wp.cross(wi, n)) - (vj + cj * wp.cross(wj, n))
            omega_rel = wi - wj
            rstar = ri * rj / rsum
            mstar = 1.0 / inv_sum
            p = pair_table[mat_i * num_materials + particle_material[j]]
            shear_old = nbr_shear[slot]
            out, k = pair_interaction(n, delta, ri, rj, rstar, mstar, v_rel, omega_rel, shear_old, p, dt)
            force = out[0]
            roll = out[1]
            spring = kept_spring(out, shear_old, dt)
            nbr_shear[slot] = spring
            ft = force - wp.dot(force, n) * n
            f_i += force
            t_i += wp.cross(-ci * n, ft) + roll
            t_j = wp.cross(cj * n, -ft) - roll
            wp.atomic_add(particle_f, j, -force)
            wp.atomic_add(particle_t, j, t_j)
            if wp.static(track_energy):
                touched = 1
                fn = wp.dot(force, n)
                e_n += elastic_energy(delta, k[0])
                e_t += 0.5 * k[1] * wp.dot(spring, spring)
                a_t += 0.5 * k[1] * wp.dot(shear_old, shear_old)
                d_damp -= 0.5 * dt * fn * wp.dot(v_rel, n)
                d_fric -= 0.5 * dt * (wp.dot(ft, v_rel) + wp.dot(roll, omega_rel))
                fn_i += fn * n
                ft_i += ft
                book_contact_force(
                    j,
                    -fn * n,
                    -ft,
                    t_j,
                    contact_sums,
                )
        for w in range(num_walls):
            nw = wall_normal[w]
            gap = wp.dot(wp.vec3(xi - wall_point[w]), nw)
            slot = i * num_walls + w
            if gap >= ri:
                if wp.static(book_parting):
                    sh = wall_shear[slot]
                    if wp.dot(sh, sh) > 0.0:
                        p = pair_table[mat_i * num_materials + wall_material[w]]
                        a_t += 0.5 * stiffnesses(0.0, ri, ri, ri, p)[1] * wp.dot(sh, sh)
                wall_shear[slot] = wp.vec3(0.0)
                continue
            if inv_mi == 0.0:
                continue
            delta = ri - gap
            ci = ri - delta
            vw = wall_velocity[w]
            v_rel = (vi - ci * wp.cross(wi, nw)) - vw
            p = pair_table[mat_i * num_materials + wall_material[w]]
            mstar = 1.0 / inv_mi
            shear_old = wall_shear[slot]
            # A flat wall is a sphere of infinite radius: R* = r_i, and the linear stiffness uses r_wall = r_i.
            out, k = pair_interaction(nw, delta, ri, ri, ri, mstar, v_rel, wi, shear_old, p, dt)
            force = out[0]
            roll = out[1]
            spring = kept_spring(out, shear_old, dt)
            wall_shear[slot] = spring
            ft = force - wp.dot(force, nw) * nw
            f_i += force
            t_i += wp.cross(-ci * nw, ft) + roll
            if wp.static(track_energy):
                touched = 1
                # The integrator books the half ahead against the sphere's own velocity, -½ dt f·v_{n+3/2}; against
                # the wall's it is -½ dt f·(v_{n+3/2} - v_w): the wall's share, +½ dt f·v_w, is booked here (v_w is
                # constant), with the half behind against the relative velocity: -½ dt f·(v_rel - v_w) in all.
                fn = wp.dot(force, nw)
                e_n += elastic_energy(delta, k[0])
                e_t += 0.5 * k[1] * wp.dot(spring, spring)
                a_t += 0.5 * k[1] * wp.dot(shear_old, shear_old)
                d_damp -= 0.5 * dt * fn * wp.dot(v_rel - vw, nw)
                d_fric -= 0.5 * dt * (wp.dot(ft, v_rel - vw) + wp.dot(roll, wi))
                fn_i += fn * nw
                ft_i += ft
                w_wall += wp.dot(force, vw) * dt  # work of the moving wall on the sphere over the step (both halves)
        wp.atomic_add(particle_f, i, f_i)
        wp.atomic_add(particle_t, i, t_i)
        if wp.static(track_energy):
            prev = contact_energy_prev[i]
            # A sphere that touched nothing, now or at the last evaluation, and had no spring to let go has nothing
            # to book: every term below is an exact zero, so skipping it changes no bit (most spheres of a loose
            # packing, and its cost with the books on).
            if touched != 0 or prev[0] != 0.0 or prev[1] != 0.0 or a_t != 0.0:
                # t_i is all contact torque: its tangential and rolling parts are the books' torque sum.
                book_contact_force(i, fn_i, ft_i, t_i, contact_sums)
                contact_energy_prev[i] = wp.vec2(e_n, e_t)
                if dt > 0.0:  # the set-up evaluation (dt = 0) only records the springs' energies
                    # ΔU in float64 so that its sum over the steps telescopes to U_now - U_start exactly. The
                    # tangential springs' change splits at the old springs under the new stiffness, a_t: ξ's change
                    # (friction: a parting pair's spring goes there) and k_t's (the stiffness change).
                    d_n = wp.float64(d_damp) - (wp.float64(e_n) - wp.float64(prev[0]))
                    d_t = wp.float64(d_fric) - (wp.float64(e_t) - wp.float64(a_t))
                    d_k = wp.float64(a_t) - wp.float64(prev[1])
                    # An exact zero adds nothing to a line, so it is not stored (walls at rest do no work; linear
                    # laws change no stiffness): each store is a line of its own array, what the books cost here.
                    energy_damping[i] = energy_damping[i] + d_n
                    if d_t != wp.float64(0.0):
                        energy_friction[i] = energy_friction[i] + d_t
                    if d_k != wp.float64(0.0):
                        energy_stiffness_change[i] = energy_stiffness_change[i] + d_k
                    if w_wall != 0.0:
                        energy_wall_work[i] = energy_wall_work[i] + wp.float64(w_wall)

    @wp.kernel(enable_backward=False, module="unique")
    def contact_energy_kernel(
        # Model:
        particle_radius: wp.array(dtype=float),
        particle_inv_mass: wp.array(dtype=float),
        particle_material: wp.array(dtype=int),
        pair_table: wp.array(dtype=ContactPair),
        num_materials: int,
        wall_normal: wp.array(dtype=wp.vec3),
        wall_material: wp.array(dtype=int),
        num_walls: int,
        max_neighbors: int,
        # State in:
        particle_count: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        nbr_count: wp.array(dtype=int),
        nbr_index: wp.array(dtype=int),
        nbr_bond: wp.array(dtype=int),
        bond_broken: wp.array(dtype=int),
        nbr_shear: wp.array(dtype=wp.vec3),
        wall_point: wp.array(dtype=wp.vec3d),
        wall_shear: wp.array(dtype=wp.vec3),
        # Out:
        energy_elastic: wp.array(dtype=wp.float64),
        contact_count: wp.array(dtype=int),
    ):
        i = wp.tid()  # one thread per particle slot
        if i >= particle_count[0]:
            return
        xi = particle_q[i]
        ri = particle_radius[i]
        mat_i = particle_material[i]
        e = float(0.0)
        touching = int(0)
        count = wp.min(nbr_count[i], max_neighbors)
        for s in range(count):
            slot = i * max_neighbors + s
            if carried_by_bond(nbr_bond[slot], bond_broken):
                continue
            j = nbr_index[slot]
            rj = particle_radius[j]
            delta = ri + rj - wp.length(wp.vec3(xi - particle_q[j]))
            if delta <= 0.0:
                continue
            if particle_inv_mass[i] + particle_inv_mass[j] == 0.0:
                continue
            p = pair_table[mat_i * num_materials + particle_material[j]]
            rstar = ri * rj / (ri + rj)
            fnv = normal_force(delta, 0.0, ri, rj, rstar, 1.0, p)
            kt = tangential_stiffness(delta, rstar, fnv[2], p)
            sh = nbr_shear[slot]
            e += elastic_energy(delta, fnv[2]) + 0.5 * kt * wp.dot(sh, sh)
            touching += 1
        for w in range(num_walls):
            delta = ri - wp.dot(wp.vec3(xi - wall_point[w]), wall_normal[w])
            if delta <= 0.0 or particle_inv_mass[i] == 0.0:
                continue
            p = pair_table[mat_i * num_materials + wall_material[w]]
            fnv = normal_force(delta, 0.0, ri, ri, ri, 1.0, p)
            kt = tangential_stiffness(delta, ri, fnv[2], p)
            sh = wall_shear[i * num_walls + w]
            e += elastic_energy(delta, fnv[2]) + 0.5 * kt * wp.dot(sh, sh)
        energy_elastic[i] = wp.float64(e)
        wp.atomic_add(contact_count, 0, touching)

    return eval_contacts_kernel, contact_energy_kernel


@functools.cache
def make_wall_force_kernel(normal: str, tangential: str, rolling: str) -> wp.Kernel:
    """The kernel that sums the sphere–wall contact forces on each wall, for output between frames.

    It evaluates the same pair law as the step (``pair_interaction`` of :func:`make_pair_laws`) with dt = 0, which
    leaves the tangential springs as they are: the force on wall w is -Σ_i F_iw at the current positions,
    velocities and springs. Run between steps only, so the atomic sums onto a handful of walls cost the step nothing.
    """
    pair_interaction = make_pair_laws(normal, tangential, rolling).pair_interaction

    @wp.kernel(enable_backward=False, module="unique")
    def sum_wall_forces_kernel(
        # Model:
        particle_radius: wp.array(dtype=float),
        particle_inv_mass: wp.array(dtype=float),
        particle_material: wp.array(dtype=int),
        pair_table: wp.array(dtype=ContactPair),
        num_materials: int,
        wall_normal: wp.array(dtype=wp.vec3),
        wall_velocity: wp.array(dtype=wp.vec3),
        wall_material: wp.array(dtype=int),
        num_walls: int,
        # State in:
        particle_count: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        particle_qd: wp.array(dtype=wp.vec3),
        particle_omega: wp.array(dtype=wp.vec3),
        wall_point: wp.array(dtype=wp.vec3d),
        wall_shear: wp.array(dtype=wp.vec3),
        # Out:
        wall_force: wp.array(dtype=wp.vec3d),
    ):
        i = wp.tid()  # one thread per particle slot
        if i >= particle_count[0]:
            return
        inv_mi = particle_inv_mass[i]
        if inv_mi == 0.0:
            return  # the step applies no wall force to an immovable sphere
        xi = particle_q[i]
        ri = particle_radius[i]
        wi = particle_omega[i]
        for w in range(num_walls):
            nw = wall_normal[w]
            delta = ri - wp.dot(wp.vec3(xi - wall_point[w]), nw)
            if delta <= 0.0:
                continue
            # As eval_contacts_kernel: a wall is a sphere of infinite radius, R* = r_i, m* = m_i.
            v_rel = (particle_qd[i] - (ri - delta) * wp.cross(wi, nw)) - wall_velocity[w]
            p = pair_table[particle_material[i] * num_materials + wall_material[w]]
            out, _k = pair_interaction(
                nw, delta, ri, ri, ri, 1.0 / inv_mi, v_rel, wi, wall_shear[i * num_walls + w], p, 0.0
            )
            f = out[0]
            wp.atomic_sub(wall_force, w, wp.vec3d(wp.float64(f[0]), wp.float64(f[1]), wp.float64(f[2])))

    return sum_wall_forces_kernel


# ----------------------------------------------------------------------------------------------------------------
# Neighbour list with a Verlet skin.


@wp.func
def find_bond(bond_key: wp.array(dtype=wp.int64), bond_count: int, key: wp.int64) -> int:
    """Binary search of a sorted bond-key array (key = i * capacity + j, i < j); -1 when absent."""
    lo = int(0)
    hi = bond_count
    while lo < hi:
        mid = (lo + hi) // 2
        if bond_key[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if lo < bond_count:
        if bond_key[lo] == key:
            return lo
    return -1


@wp.struct
class NeighborInputs:
    """What the sphere–sphere candidate test and the bond look-up read (kernels/neighbors.py ``ListSpec.inputs``):
    the Model/State arrays of those names, the skin [m] and the query radius 2 r_max + skin [m]."""

    particle_radius: wp.array(dtype=float)
    particle_q: wp.array(dtype=wp.vec3d)
    skin: float
    search_radius: float
    bond_count: wp.array(dtype=int)
    bond_key: wp.array(dtype=wp.int64)


@wp.struct
class NeighborHistory:
    """Per-slot history of the sphere–sphere list: ``nbr_shear`` and ``nbr_bond`` (or their scratch copies)."""

    shear: wp.array(dtype=wp.vec3)
    bond: wp.array(dtype=int)


@wp.func
def neighbor_search_radius(inputs: NeighborInputs, i: int) -> float:
    return inputs.search_radius


@wp.func
def is_neighbor_candidate(inputs: NeighborInputs, i: int, xi: wp.vec3d, j: int) -> bool:
    """Half list: j > i, within r_i + r_j + skin."""
    if j <= i:
        return False
    cutoff = inputs.particle_radius[i] + inputs.particle_radius[j] + inputs.skin
    d = wp.vec3(xi - inputs.particle_q[j])
    return not (wp.dot(d, d) >= cutoff * cutoff)  # not ≥ rather than <: a NaN distance keeps the pair


@wp.func
def copy_neighbor_history(src: NeighborHistory, src_slot: int, dst: NeighborHistory, dst_slot: int):
    dst.shear[dst_slot] = src.shear[src_slot]
    dst.bond[dst_slot] = src.bond[src_slot]


@wp.func
def fresh_neighbor_history(inputs: NeighborInputs, history: NeighborHistory, slot: int, i: int, j: int):
    """A pair new to the list starts untouched, with its bond if it has one."""
    history.shear[slot] = wp.vec3(0.0)
    key = wp.int64(i) * wp.int64(inputs.particle_q.shape[0]) + wp.int64(j)
    history.bond[slot] = find_bond(inputs.bond_key, inputs.bond_count[0], key)


NEIGHBOR_LIST = make_list_kernels(
    ListSpec(
        inputs=NeighborInputs,
        radius=neighbor_search_radius,
        accept=is_neighbor_candidate,
        history=NeighborHistory,
        copy=copy_neighbor_history,
        fresh=fresh_neighbor_history,
        owner_vec=wp.vec3d,
        grid_vec=wp.vec3d,
    )
)
"""Build and commit kernels of the sphere–sphere half list."""
