"""Cohesive elements between the daughters A, B of a split node (LDEC §2.2–2.3, eqs. 5–10): the weakening central
force, its history d_max, the break, and the energy books.

Force law. With r = x_B − x_A and d = |r| (eq. 5), the force on A is f e towards B, e = r / d, and −f e acts on B:

    f = f_c (1 − α δ_max/δ_c) (d/δ_max)                       (eq. 6)
    δ_max = min(d_max, δ_c)                                     (eq. 7)
    d_max = max(d_max, d), updated every step                   (eq. 8)

so the element loads along the weakening envelope f_env(δ) = f_c (1 − α δ/δ_c) and unloads and reloads along the line
to the origin f = k d with k = f_env(δ_max)/δ_max; the force vector is then simply k r (no division by d). Once
d_max ≥ δ_c the element is broken: it applies no force and waits for the compaction pass.

Before any opening. LDEC removes the singularity of eq. 6 at δ_max = 0 by d/δ_max := 1, and e is then undefined. The
daughters are born with equal X and u, so d = 0 exactly; afterwards d is at first only float32 round-off of the two
displacements (a spacing of 2⁻²³ |u| ≈ 1.2e-7 |u|), whose direction is noise and whose ratio d/δ_max would make the
force jump between 0 and f_c from step to step. So while δ_max < OPEN_FRACTION δ_c (1e-4 δ_c: above that round-off for
displacements up to ~10³ δ_c) the element is taken as not yet open: d/δ_max := 1 and e := cohesive_dir, the direction
the split gave it (from A's side to B's side; warpdem.fracture). The force is then f_env(δ_max) ≈ f_c along it,
which is what eqs. 3–4 need at the split (the daughters keep the parent's acceleration), and it meets eq. 6
continuously where δ_max passes the threshold while loading (d = δ_max there). The energy books below are those of
eq. 6 throughout; the regularised force differs from their gradient only below 1e-4 δ_c, by at most f_c × 1e-4 δ_c
≤ 2e-4 Γ A_f of work over the element's life.

Energy identity (what the books rest on). The work the nodes do on the element while it loads along the envelope to
δ_max is ∫₀^δmax f_c (1 − α δ/δ_c) dδ = f_c δ_max − ½ α f_c δ_max²/δ_c. Of it the element holds, on its unloading
line, the spring energy ½ k δ_max² = ½ f_c (1 − α δ_max/δ_c) δ_max, which unloading gives back; the difference,

    dissipated(δ_max) = f_c δ_max − ½ α f_c δ_max²/δ_c − ½ f_c (1 − α δ_max/δ_c) δ_max = ½ f_c δ_max,

is spent for good, independent of α. So at any time stored + dissipated = ½ k d² + ½ f_c δ_max equals the work done
on the element (exactly on the envelope and the line, whose pieces are linear in d), and every growth Δδ_max is booked
as ½ f_c Δδ_max into node_energy_cohesive, half on A and half on B. The element lets go at d = δ_c, still holding
½ k(δ_c) δ_c² = ½ (1 − α) f_c δ_c, which is released (booked as dissipated) at the break; its life total is then
½ f_c δ_c + ½ (1 − α) f_c δ_c = (1 − α/2) f_c δ_c = Γ A_f (eq. 9, with δ_c from eq. 10), exactly. The step that breaks
it overshoots δ_c by part of one step's opening Δd, over which velocity Verlet applies the force of the step before
instead of the envelope's: for α < 1 (a force that drops from (1 − α) f_c to 0) the energy balance sees up to
½ (1 − α) f_c Δd per break; for α = 1 the force reaches 0 continuously and the difference is second order in Δd.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

OPEN_FRACTION = wp.constant(1.0e-4)
"""δ_max/δ_c below which an element counts as not yet open (d is float32 round-off of the displacements there)."""


@wp.func
def envelope_force(fc: float, delta_max: float, delta_c: float, alpha: float) -> float:
    """Force on the weakening envelope at δ_max [N]: LDEC eq. 6 at d = δ_max, f_c (1 − α δ_max/δ_c)."""
    return fc * (1.0 - alpha * delta_max / delta_c)


@wp.func
def capped_opening(d_max: float, delta_c: float) -> float:
    """δ_max = min(d_max, δ_c) [m] (LDEC eq. 7)."""
    return wp.min(d_max, delta_c)


@wp.func
def unloading_stiffness(fc: float, delta_max: float, delta_c: float, alpha: float) -> float:
    """Slope k = f_env(δ_max)/δ_max [N/m] of the line to the origin that unloading and reloading follow (LDEC eqs.
    6–7: f = k d while d ≤ δ_max); 0 before any opening (δ_max = 0), where the element holds no spring energy."""
    if delta_max <= 0.0:
        return 0.0
    return envelope_force(fc, delta_max, delta_c, alpha) / delta_max


@wp.func
def cohesive_force(r: wp.vec3, d_max: float, fc: float, delta_c: float, alpha: float, direction: wp.vec3) -> wp.vec3:
    """Force of the element on A [N] (−it acts on B) at the opening r = x_B − x_A [m] and the history d_max ≥ |r|.

    LDEC eq. 6 (with eq. 7): f e = f_c (1 − α δ_max/δ_c) (d/δ_max) e = k r. Before any opening (δ_max below
    OPEN_FRACTION δ_c) d/δ_max := 1 and e := ``direction`` (module docstring), so f = f_env(δ_max) along it.
    """
    delta_max = capped_opening(d_max, delta_c)
    if delta_max < OPEN_FRACTION * delta_c:
        return envelope_force(fc, delta_max, delta_c, alpha) * direction
    return unloading_stiffness(fc, delta_max, delta_c, alpha) * r


@wp.func
def spring_energy(d: float, d_max: float, fc: float, delta_c: float, alpha: float) -> float:
    """Energy the element holds on its unloading line, ½ k d² [J] (k of eqs. 6–7; 0 before any opening)."""
    k = unloading_stiffness(fc, capped_opening(d_max, delta_c), delta_c, alpha)
    return 0.5 * k * d * d


@wp.func
def opening(a: int, b: int, node_ref_q: wp.array(dtype=wp.vec3), node_u: wp.array(dtype=wp.vec3)) -> wp.vec3:
    """r = x_B − x_A = (X_B − X_A) + (u_B − u_A) [m] (LDEC eq. 5). The daughters of a split share X, so the first
    difference is exact (0 for the two daughters of one node) and r keeps the displacements' float32 precision."""
    return (node_ref_q[b] - node_ref_q[a]) + (node_u[b] - node_u[a])


@wp.kernel
def eval_cohesive_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    dt: float,
    # State in:
    cohesive_count: wp.array(dtype=int),
    cohesive_a: wp.array(dtype=int),
    cohesive_b: wp.array(dtype=int),
    cohesive_fc: wp.array(dtype=float),
    cohesive_delta_c: wp.array(dtype=float),
    cohesive_alpha: wp.array(dtype=float),
    cohesive_area: wp.array(dtype=float),
    cohesive_dir: wp.array(dtype=wp.vec3),
    node_u: wp.array(dtype=wp.vec3),
    # In:
    track_energy: int,
    # State out:
    cohesive_d_max: wp.array(dtype=float),
    cohesive_broken: wp.array(dtype=int),
    cohesive_broken_total: wp.array(dtype=int),
    cohesive_area_broken: wp.array(dtype=wp.float64),
    cohesive_work_broken: wp.array(dtype=wp.float64),
    fem_rebuild_flag: wp.array(dtype=int),
    node_f: wp.array(dtype=wp.vec3),
    node_damage: wp.array(dtype=float),
    node_energy_cohesive: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per cohesive element slot
    if i >= cohesive_count[0] or cohesive_broken[i] != 0:
        return
    a = cohesive_a[i]
    b = cohesive_b[i]
    fc = cohesive_fc[i]
    delta_c = cohesive_delta_c[i]
    alpha = cohesive_alpha[i]
    r = opening(a, b, node_ref_q, node_u)
    d_max_old = cohesive_d_max[i]
    d_max = wp.max(d_max_old, wp.length(r))  # LDEC eq. 8
    # An intact element has d_max_old < δ_c, so δ_max before this step is d_max_old itself.
    if dt > 0.0 and d_max >= delta_c:
        # Broken: no force from now on. The books close on Γ A_f (eq. 9): ½ f_c of the last growth of δ_max up to
        # δ_c, and the spring energy ½ k(δ_c) δ_c² = ½ (1 − α) f_c δ_c held where the element let go.
        cohesive_d_max[i] = d_max
        cohesive_broken[i] = 1
        wp.atomic_add(cohesive_broken_total, 0, 1)
        fc64 = wp.float64(fc)
        dc64 = wp.float64(delta_c)
        wp.atomic_add(cohesive_area_broken, 0, wp.float64(cohesive_area[i]))
        wp.atomic_add(cohesive_work_broken, 0, (wp.float64(1.0) - wp.float64(0.5) * wp.float64(alpha)) * fc64 * dc64)
        fem_rebuild_flag[0] = 1  # the crack faces at A and B may now touch: rebuild the FEM contact lists
        wp.atomic_max(node_damage, a, 1.0)
        wp.atomic_max(node_damage, b, 1.0)
        if track_energy != 0:
            rest = (
                wp.float64(0.5) * fc64 * ((dc64 - wp.float64(d_max_old)) + (wp.float64(1.0) - wp.float64(alpha)) * dc64)
            )
            wp.atomic_add(node_energy_cohesive, a, wp.float64(0.5) * rest)
            wp.atomic_add(node_energy_cohesive, b, wp.float64(0.5) * rest)
        return
    # The set-up and post-split evaluation (dt = 0) sees the history including the present opening, but keeps none.
    f = cohesive_force(r, d_max, fc, delta_c, alpha, cohesive_dir[i])
    # Held nodes (inverse mass 0) take the force too: the integrator holds them, and the sums stay symmetric.
    wp.atomic_add(node_f, a, f)
    wp.atomic_add(node_f, b, -f)
    if dt <= 0.0 or d_max <= d_max_old:
        return
    cohesive_d_max[i] = d_max
    damage = d_max / delta_c  # δ_max/δ_c < 1 here
    wp.atomic_max(node_damage, a, damage)
    wp.atomic_max(node_damage, b, damage)
    if track_energy != 0:
        # ½ f_c Δδ_max (module docstring), in float64 from the float32 openings: the sum over steps telescopes.
        quarter = wp.float64(0.25) * wp.float64(fc) * (wp.float64(d_max) - wp.float64(d_max_old))
        wp.atomic_add(node_energy_cohesive, a, quarter)
        wp.atomic_add(node_energy_cohesive, b, quarter)


@wp.kernel
def cohesive_energy_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    # State in:
    cohesive_count: wp.array(dtype=int),
    cohesive_a: wp.array(dtype=int),
    cohesive_b: wp.array(dtype=int),
    cohesive_fc: wp.array(dtype=float),
    cohesive_delta_c: wp.array(dtype=float),
    cohesive_alpha: wp.array(dtype=float),
    cohesive_d_max: wp.array(dtype=float),
    cohesive_broken: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    # Out:
    energy: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per cohesive element slot
    if i >= cohesive_count[0] or cohesive_broken[i] != 0:
        return
    d = wp.length(opening(cohesive_a[i], cohesive_b[i], node_ref_q, node_u))
    # The same history as the force evaluation: d_max including the present opening (eq. 8).
    d_max = wp.max(cohesive_d_max[i], d)
    e = spring_energy(d, d_max, cohesive_fc[i], cohesive_delta_c[i], cohesive_alpha[i])
    wp.atomic_add(energy, 0, wp.float64(e))
