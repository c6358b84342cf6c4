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
the split gave it (from A's side to B's side; warpdem.stages.fracture). The force is then f_env(δ_max) ≈ f_c along it,
which is what eqs. 3–4 need at the split (the daughters keep the parent's acceleration), and it meets eq. 6
continuously where δ_max passes the threshold while loading (d = δ_max there). The books below take the work this
force does, whatever its direction.

An opening the step resolves. Eq. 6 with e = r/d is a spring of stiffness f/d across r, and of k = f_env/δ_max along
it on the unloading line; both grow without bound as the opening starts. Below d ≈ f_c dt²/m* (m* the daughters'
reduced mass) their period is shorter than the step, and velocity Verlet turns the slightest sliding of the daughters
across p1 into an oscillation that feeds on itself: on the PMMA plate the openings swung across the plane every step
while the crack ran, the elements did net work on the nodes (−0.04 J "dissipated" against Γ A = 0.27 J) and the
balance drifted by 4.5 % in 70 µs. So the opening threshold follows the step: an element counts as not yet open while
δ_max < s = max(OPEN_FRACTION δ_c, min(δ_c, f_c dt²/m*)) (:func:`open_length`). Below s its force acts along
cohesive_dir, with no stiffness across it, and unloads on the line of slope f_env(δ_max)/s,
f = f_env(δ_max) max(0, 1 − (δ_max − d)/s), which meets eq. 6 where δ_max reaches s; above s every stiffness of the
element is at most f_c/s ≤ m*/dt², so the pair alone keeps ω dt ≤ 1 (Verlet's limit is 2). s shrinks like dt², so
the law converges to eq. 6 as the step is refined (tests/test_fracture.py: the work of a cracking bar's elements
converges to Γ A). A held daughter (inverse mass 0) counts with the other's mass alone.

Energy identity (the law's). The work the nodes do on the element while it loads along the envelope to δ_max is
∫₀^δmax f_c (1 − α δ/δ_c) dδ = f_c δ_max − ½ α f_c δ_max²/δ_c. Of it the element holds, on its unloading line, the
spring energy U = ½ k δ_max² = ½ f_c (1 − α δ_max/δ_c) δ_max, which unloading gives back; the difference,

    dissipated(δ_max) = f_c δ_max − ½ α f_c δ_max²/δ_c − ½ f_c (1 − α δ_max/δ_c) δ_max = ½ f_c δ_max,

is spent for good, independent of α. The element lets go at d = δ_c, still holding ½ k(δ_c) δ_c² = ½ (1 − α) f_c δ_c,
which is released at the break; its life total is ½ f_c δ_c + ½ (1 − α) f_c δ_c = (1 − α/2) f_c δ_c = Γ A_f (eq. 9,
with δ_c from eq. 10). ``cohesive_work_broken`` counts this Γ A_f of every broken element, for the summary.

Energy books (as the scheme does the work). An element opens through δ_c in a few steps once a crack runs, and its
force is not smooth in time: it is born at f_c, turns with the first openings and drops to zero at the break. The
discrete work then differs from the law's integral by a fraction of f_c Δd per event, which closes no balance. So
each element books what velocity Verlet makes its force do, like the sphere contacts and bonds (kernels/contact.py):
over a step the nodes do on it the trapezoid

    ΔW = ½ dt (f_n + f_{n+1}) · (v_B − v_A)_{n+1/2}                       (x_{n+1} − x_n = dt v_{n+1/2})

(f the force on A, −f on B, v_{n+1/2} the velocities during the evaluation of f_{n+1}; for a node of a rigid block
the half of f_n is taken at the pose f_n was made at, as the body's kick works it: kernels/rigid.py
``node_velocity_ahead``), of which its spring now holds
U_{n+1} = ½ k d²; spent += ΔW − (U_{n+1} − U_n), half on A and half on B, with f_n and U_n kept per element
(``cohesive_f_prev``, ``cohesive_energy_prev``). Stored + spent is then the work done on the element exactly, and the
energy balance closes however coarsely the step resolves δ_c. Of what is spent, the law's dissipation over the step,
the growth of G(δ_max) (:func:`law_dissipation`: ½ f_c δ_max once open) and at the break what is left of Γ A_f, goes
to the cohesive line (``node_energy_cohesive``): it never falls and ends at Γ A_f. The rest, Verlet's work off the
law, goes to a line of its own (``node_energy_cohesive_trapezoid``): on a resolved opening the trapezoid equals the
law's integral (exactly on its linear pieces) and it holds rounding (tests/test_cohesive.py); where a blast moves the
daughters past δ_c, or through each other, in a step it holds what the force did off the law, of either sign (on
limestone_tunnel: elements born in a split pass whose daughters cross by 40–100 δ_c in their first step; issue 28).
Sub-stepping the elements' nodes (``Model.cohesive_substeps`` n, warpdem.stages.substep) evaluates the elements n
times a step at dt/n: ``step`` and ``dt`` below are then the sub-step's, s shrinks by n², and the trapezoid line
with it.
The break step books ½ dt f_n · v_rel + U_n: the element applies no force from then on, so nothing is left ahead. A
split gives the new element f_prev = its force at birth (f_c along ``cohesive_dir``) and U = 0; a hand-over keeps
both.
"""

from __future__ import annotations

import warp as wp

from .rigid import PoseAhead, node_velocity_ahead

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
def open_length(fc: float, delta_c: float, dt: float, inv_mass_a: float, inv_mass_b: float) -> float:
    """s [m]: the element counts as open once δ_max ≥ s = max(OPEN_FRACTION δ_c, min(δ_c, f_c dt² (1/m_A + 1/m_B)))
    (module docstring; ``dt`` the model's step [s], inverse masses [1/kg]); above s its stiffness is at most f_c/s."""
    return wp.max(OPEN_FRACTION * delta_c, wp.min(delta_c, fc * dt * dt * (inv_mass_a + inv_mass_b)))


@wp.func
def cohesive_force(
    r: wp.vec3, d_max: float, fc: float, delta_c: float, alpha: float, direction: wp.vec3, s: float
) -> wp.vec3:
    """Force of the element on A [N] (−it acts on B) at the opening r = x_B − x_A [m] and the history d_max ≥ |r|.

    LDEC eq. 6 (with eq. 7): f e = f_c (1 − α δ_max/δ_c) (d/δ_max) e = k r. Before the element opens (δ_max below
    ``s``, :func:`open_length`) e := ``direction`` and f = f_env(δ_max) max(0, 1 − (δ_max − d)/s) (module docstring):
    f_env(δ_max) while loading, as eqs. 3–4 need at the split.
    """
    delta_max = capped_opening(d_max, delta_c)
    if delta_max < s:
        return (
            envelope_force(fc, delta_max, delta_c, alpha)
            * wp.max(0.0, 1.0 - (delta_max - wp.length(r)) / s)
            * direction
        )
    return unloading_stiffness(fc, delta_max, delta_c, alpha) * r


@wp.func
def spring_energy(d: float, d_max: float, fc: float, delta_c: float, alpha: float, s: float) -> float:
    """Energy the element holds on its unloading line [J]: what it gives back closing to d = 0 along the force of
    :func:`cohesive_force`, ½ k d² (k of eqs. 6–7) once open, f_env(δ_max) (d (1 − δ_max/s) + d²/(2 s)) below s
    (both ½ f_env d²/s where δ_max = s)."""
    delta_max = capped_opening(d_max, delta_c)
    if delta_max < s:
        return envelope_force(fc, delta_max, delta_c, alpha) * (d * (1.0 - delta_max / s) + 0.5 * d * d / s)
    k = unloading_stiffness(fc, delta_max, delta_c, alpha)
    return 0.5 * k * d * d


@wp.func
def law_dissipation(d_max: float, fc: float, delta_c: float, alpha: float, s: float) -> float:
    """G(δ_max) [J]: what the law spends for good loading along its envelope to δ_max = min(d_max, δ_c), the envelope's
    work less what :func:`spring_energy` holds at d = δ_max (module docstring): ½ f_c δ_max once open (δ_max ≥ s),
    f_c δ_max²/(2 s) (1 + α (s − δ_max)/δ_c) below s (the same at s, increasing in δ_max, at most ½ f_c δ_max)."""
    delta_max = capped_opening(d_max, delta_c)
    if delta_max >= s:
        return 0.5 * fc * delta_max
    return fc * delta_max * delta_max / (2.0 * s) * (1.0 + alpha * (s - delta_max) / delta_c)


@wp.func
def opening(a: int, b: int, node_ref_q: wp.array(dtype=wp.vec3), node_u: wp.array(dtype=wp.vec3)) -> wp.vec3:
    """r = x_B − x_A = (X_B − X_A) + (u_B − u_A) [m] (LDEC eq. 5). The daughters of a split share X, so the first
    difference is exact (0 for the two daughters of one node) and r keeps the displacements' float32 precision."""
    return (node_ref_q[b] - node_ref_q[a]) + (node_u[b] - node_u[a])


@wp.func
def book_step(
    i: int,
    a: int,
    b: int,
    dt: float,
    f: wp.vec3,
    energy: float,
    track_energy: int,
    node_qd: wp.array(dtype=wp.vec3),
    v_rel_ahead: wp.vec3,
    law: float,
    cohesive_f_prev: wp.array(dtype=wp.vec3),
    cohesive_energy_prev: wp.array(dtype=float),
    node_energy_cohesive: wp.array(dtype=wp.float64),
    node_energy_cohesive_trapezoid: wp.array(dtype=wp.float64),
):
    """Book element i's step that made its force ``f`` [N] (on A) and spring energy ``energy`` [J]: of the trapezoid
    ΔW = ½ dt (f_n·(v_B − v_A)_ahead + f·(v_B − v_A)_{n+1/2}) the nodes did on it, less the change of its spring
    energy, the law's dissipation over the step ``law`` [J] (≥ 0: the growth of :func:`law_dissipation`, or what is
    left of Γ A_f at the break) goes to the cohesive line and the rest, Verlet's work off the law, to the trapezoid
    line, each half on A and half on B (module docstring); then keep f and the energy for the next step.
    ``v_rel_ahead`` is the relative velocity the half ahead of f_n is booked against: v_{n+1/2} for nodes of their
    own, a rigid body's velocity at the pose f_n was made at for its nodes (:func:`relative_velocity_ahead`)."""
    v_rel = node_qd[b] - node_qd[a]
    work = wp.float64(0.5 * dt * (wp.dot(cohesive_f_prev[i], v_rel_ahead) + wp.dot(f, v_rel)))
    spent = work - (wp.float64(energy) - wp.float64(cohesive_energy_prev[i]))
    half_law = wp.float64(0.0)  # without the books (track_energy 0) the law's line stays as it is too
    if track_energy != 0:
        half_law = wp.float64(0.5) * wp.float64(law)
    half_rest = wp.float64(0.5) * spent - half_law
    wp.atomic_add(node_energy_cohesive, a, half_law)
    wp.atomic_add(node_energy_cohesive, b, half_law)
    wp.atomic_add(node_energy_cohesive_trapezoid, a, half_rest)
    wp.atomic_add(node_energy_cohesive_trapezoid, b, half_rest)
    cohesive_f_prev[i] = f
    cohesive_energy_prev[i] = energy


@wp.func
def relative_velocity_ahead(a: int, b: int, ahead: PoseAhead) -> wp.vec3:
    """(v_B − v_A) [m/s] over the half step ahead of the last evaluation: v_{n+1/2} of the nodes, or for a node of a
    rigid body its velocity at the pose the last force was made at (kernels/rigid.py ``node_velocity_ahead``;
    ``node_body`` is empty before a switch)."""
    return node_velocity_ahead(b, ahead) - node_velocity_ahead(a, ahead)


@wp.kernel
def eval_cohesive_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    node_inv_mass: wp.array(dtype=float),
    step: float,
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
    node_qd: wp.array(dtype=wp.vec3),
    ahead: PoseAhead,
    # In:
    track_energy: int,
    # State out:
    cohesive_d_max: wp.array(dtype=float),
    cohesive_f_prev: wp.array(dtype=wp.vec3),
    cohesive_energy_prev: wp.array(dtype=float),
    cohesive_broken: wp.array(dtype=int),
    cohesive_broken_total: wp.array(dtype=int),
    cohesive_area_broken: wp.array(dtype=wp.float64),
    cohesive_work_broken: wp.array(dtype=wp.float64),
    node_f: wp.array(dtype=wp.vec3),
    node_damage: wp.array(dtype=float),
    node_energy_cohesive: wp.array(dtype=wp.float64),
    node_energy_cohesive_trapezoid: wp.array(dtype=wp.float64),
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
    v_rel_ahead = wp.vec3(0.0)
    if dt > 0.0:
        v_rel_ahead = relative_velocity_ahead(a, b, ahead)
    d_max_old = cohesive_d_max[i]
    d_max = wp.max(d_max_old, wp.length(r))  # LDEC eq. 8
    s = open_length(fc, delta_c, step, node_inv_mass[a], node_inv_mass[b])
    spent_before = law_dissipation(d_max_old, fc, delta_c, alpha, s)
    # An intact element has d_max_old < δ_c, so δ_max before this step is d_max_old itself.
    if dt > 0.0 and d_max >= delta_c:
        # Broken: no force from now on. The books take the last trapezoid ½ dt f_n·v_rel and release what the spring
        # held (module docstring); the summary's Γ A_f (eq. 9) goes to cohesive_work_broken.
        cohesive_d_max[i] = d_max
        cohesive_broken[i] = 1
        wp.atomic_add(cohesive_broken_total, 0, 1)
        wp.atomic_add(cohesive_area_broken, 0, wp.float64(cohesive_area[i]))
        wp.atomic_add(
            cohesive_work_broken,
            0,
            (wp.float64(1.0) - wp.float64(0.5) * wp.float64(alpha)) * wp.float64(fc) * wp.float64(delta_c),
        )
        # No FEM list rebuild: the node–face candidate test does not read the cohesive elements, so the crack faces
        # at A and B were candidates of each other's nodes since the split (a break changes no list; a joint element's
        # break does, kernels/joints.py, as held_by_joint excludes an intact joint's pair).
        wp.atomic_max(node_damage, a, 1.0)
        wp.atomic_max(node_damage, b, 1.0)
        # The law's dissipation ends at its life total Γ A_f = (1 − α/2) f_c δ_c (eq. 9): what the spring still held
        # and the rest of the envelope a step past δ_c skipped.
        book_step(
            i,
            a,
            b,
            dt,
            wp.vec3(0.0),
            0.0,
            track_energy,
            node_qd,
            v_rel_ahead,
            (1.0 - 0.5 * alpha) * fc * delta_c - spent_before,
            cohesive_f_prev,
            cohesive_energy_prev,
            node_energy_cohesive,
            node_energy_cohesive_trapezoid,
        )
        return
    # The set-up and post-split evaluation (dt = 0) sees the history including the present opening, but keeps none.
    f = cohesive_force(r, d_max, fc, delta_c, alpha, cohesive_dir[i], s)
    # Held nodes (inverse mass 0) take the force too: the integrator holds them, and the sums stay symmetric.
    wp.atomic_add(node_f, a, f)
    wp.atomic_add(node_f, b, -f)
    if dt <= 0.0:
        return
    if d_max > d_max_old:
        cohesive_d_max[i] = d_max
        damage = d_max / delta_c  # δ_max/δ_c < 1 here
        wp.atomic_max(node_damage, a, damage)
        wp.atomic_max(node_damage, b, damage)
    u = spring_energy(wp.length(r), d_max, fc, delta_c, alpha, s)
    book_step(
        i,
        a,
        b,
        dt,
        f,
        u,
        track_energy,
        node_qd,
        v_rel_ahead,
        law_dissipation(d_max, fc, delta_c, alpha, s) - spent_before,
        cohesive_f_prev,
        cohesive_energy_prev,
        node_energy_cohesive,
        node_energy_cohesive_trapezoid,
    )


@wp.kernel
def cohesive_energy_kernel(
    # State in:
    cohesive_count: wp.array(dtype=int),
    cohesive_energy_prev: wp.array(dtype=float),
    cohesive_broken: wp.array(dtype=int),
    # Out:
    energy: wp.array(dtype=wp.float64),
):
    i = wp.tid()  # one thread per cohesive element slot
    if i >= cohesive_count[0] or cohesive_broken[i] != 0:
        return
    # The spring energy of the last evaluation, at the positions the state holds between steps: the very figure the
    # books subtracted (eval_cohesive_kernel), so stored + dissipated is the work done on the elements exactly.
    energy[i] = wp.float64(cohesive_energy_prev[i])
