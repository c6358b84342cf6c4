"""Cosserat point tetrahedra (ldec_fem_dem_fracture.txt §2.1; DESIGN.md stage 2): explicit, lumped mass.

Each tet is a homogeneously deformable Cosserat point. Its directors d_i = x_i - x_0 (i = 1..3) against the reference
directors D_i = X_i - X_0 give the deformation gradient F = [d1 d2 d3][D1 D2 D3]⁻¹; a hyperelastic law gives the
first Piola stress P(F); the director balance laws with the uncoupled (lumped) director inertia of LDEC reduce to
nodal forces f_i = -V₀ P D⁻ᵀ e_i on nodes 1..3 and f_0 = -(f_1 + f_2 + f_3), each node carrying ρV₀/4 of every
tet it belongs to. In a continuum region this is the constant-strain tet of standard FEM. The kernels read the
nodal displacements u = x - X, not the positions: F = I + [u_i - u_0] D⁻¹ keeps the float32 round-off of a strain
at ε₃₂ (1 + |u|/h) wherever the body sits, where differences of float32 coordinates would give ε₃₂ |x|/h.

Material law: compressible neo-Hookean, ψ(F) = μ/2 (tr FᵀF - 3) - μ ln J + λ/2 (J - 1)², so P = μ F + g(J) cof F
with g(J) = λ (J - 1) - μ/J and cof F = J F⁻ᵀ. It is chosen over the corotated law because (i) it is
frame-indifferent by construction (F = R gives P = μR - μR = 0 exactly, with no polar decomposition whose iterative
SVD would cost more than the rest of the element), (ii) it linearises to Hooke's law with the same λ, μ
(P ≈ 2με + λ tr ε I for F = I + ∇u), and (iii) its energy → ∞ as J → 0, so a blast-compressed tet resists collapse
instead of inverting at finite energy as a corotated tet can. The volumetric term λ/2 (J - 1)² rather than
λ/2 (ln J)² keeps a logarithm out of the force kernel (the two agree to second order in the strain). Below J_MIN the
volumetric energy is continued by its second-order Taylor expansion in J (the restoring force keeps growing), so a
crushed or inverted tet yields finite forces and never NaN (the inversion-safe idea of Irving et al. 2004).

Shock capture: a linear + quadratic bulk viscosity in compression (von Neumann–Richtmyer / Landshoff, as LS-DYNA and
other explicit shock codes), q = ρ₀ ℓ (c_quad ℓ ε̇_v² - c_lin c_p ε̇_v) for ε̇_v < 0, added to the stress as the
pressure q, with the reference density and a reference length of the tet; its work is booked as dissipated energy on
the tet's nodes, half at evaluation and half in the next kick (the trapezoid Verlet does), as the sphere contacts'.
"""

from __future__ import annotations

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

# Motion kinds of a node (``node_motion``): which velocity components are held at zero. Rollers (from
# warpdem.stages.loads) hold the one normal to their plane; a node on two roller planes moves along their common axis.
NODE_FREE = wp.constant(0)
NODE_FIXED = wp.constant(1)
NODE_Z_ONLY = wp.constant(2)
NODE_ROLLER_X = wp.constant(3)  # x held
NODE_ROLLER_Y = wp.constant(4)  # y held
NODE_ROLLER_Z = wp.constant(5)  # z held
NODE_X_ONLY = wp.constant(6)  # y, z held
NODE_Y_ONLY = wp.constant(7)  # x, z held

TET_ACTIVE = wp.constant(1)

J_MIN = wp.constant(0.1)
"""Volume ratio below which the volumetric energy is continued by its Taylor expansion (and Cauchy stress is
reported with J = J_MIN) [-]."""


@wp.struct
class TetMaterial:
    """Continuum properties of one material, one entry per material id.

    Attributes:
        mu: Lamé shear modulus μ = E / (2(1 + ν)) [Pa].
        lam: Lamé λ = E ν / ((1 + ν)(1 - 2ν)) [Pa].
        density: reference density ρ₀ [kg/m³].
        c_p: P-wave speed sqrt((λ + 2μ)/ρ₀) [m/s].
        c_lin: linear bulk-viscosity coefficient [-] (default 0.06).
        c_quad: quadratic bulk-viscosity coefficient [-] (default 1.2).
        alpha: mass-proportional (Rayleigh α) damping [1/s] (default 0).
    """

    mu: float
    lam: float
    density: float
    c_p: float
    c_lin: float
    c_quad: float
    alpha: float


# ----------------------------------------------------------------------------------------------------------------
# Element physics.


@wp.func
def node_free_directions(motion: int) -> wp.vec3:
    """Components of a node's velocity that move: 1 free, 0 held (free: all; fixed: none; z only: z; a roller: the
    two in its plane; x or y only: that one)."""
    if motion == NODE_FREE:
        return wp.vec3(1.0, 1.0, 1.0)
    if motion == NODE_Z_ONLY:
        return wp.vec3(0.0, 0.0, 1.0)
    if motion == NODE_ROLLER_X:
        return wp.vec3(0.0, 1.0, 1.0)
    if motion == NODE_ROLLER_Y:
        return wp.vec3(1.0, 0.0, 1.0)
    if motion == NODE_ROLLER_Z:
        return wp.vec3(1.0, 1.0, 0.0)
    if motion == NODE_X_ONLY:
        return wp.vec3(1.0, 0.0, 0.0)
    if motion == NODE_Y_ONLY:
        return wp.vec3(0.0, 1.0, 0.0)
    return wp.vec3(0.0)


@wp.func
def displacement_gradient(u0: wp.vec3, u1: wp.vec3, u2: wp.vec3, u3: wp.vec3, inv_ref: wp.mat33) -> wp.mat33:
    """H = F - I = [u1 - u0, u2 - u0, u3 - u0] D⁻¹ from the nodal displacements u_k = x_k - X_k (LDEC §2.1:
    directors d_i = x_i - x_0 = D_i + u_i - u_0, F = [d1 d2 d3] D⁻¹). Forming it from the displacements keeps float32
    round-off relative to |u| rather than to the coordinates."""
    return wp.matrix_from_cols(u1 - u0, u2 - u0, u3 - u0) * inv_ref


@wp.func
def cofactor(f: wp.mat33) -> wp.mat33:
    """cof F = det(F) F⁻ᵀ = ∂J/∂F, from the columns f_k of F: [f1 × f2, f2 × f0, f0 × f1]; defined for any F."""
    c0 = wp.vec3(f[0, 0], f[1, 0], f[2, 0])
    c1 = wp.vec3(f[0, 1], f[1, 1], f[2, 1])
    c2 = wp.vec3(f[0, 2], f[1, 2], f[2, 2])
    return wp.matrix_from_cols(wp.cross(c1, c2), wp.cross(c2, c0), wp.cross(c0, c1))


@wp.func
def det_minus_one(h: wp.mat33, cof_h: wp.mat33) -> float:
    """J - 1 = det(I + H) - 1 = tr H + tr cof H + det H (the three invariants of H), exactly, without forming the 1 that
    cancels: at rock strains (|H| ~ 1e-4) float32 det(F) - 1 keeps only about three significant digits of it."""
    return wp.trace(h) + wp.trace(cof_h) + wp.dot(h[0], cof_h[0])


@wp.func
def deformation_cofactor(h: wp.mat33, cof_h: wp.mat33) -> wp.mat33:
    """cof F = cof(I + H) = (1 + tr H) I - Hᵀ + cof H, exactly (each entry of cof F is a 2 × 2 minor of I + H)."""
    return wp.diag(wp.vec3(1.0 + wp.trace(h))) - wp.transpose(h) + cof_h


@wp.func
def volumetric_stress_and_slope(j: Any, mu: Any, lam: Any):
    """g(J) = dψ_v/dJ = λ (J - 1) - μ/J [Pa] and its slope g'(J) = λ + μ/J² [Pa], J > 0."""
    return lam * (j - type(j)(1.0)) - mu / j, lam + mu / (j * j)


@wp.func
def volumetric_stress(j: float, mu: float, lam: float) -> float:
    """g(J) = dψ_v/dJ [Pa], continued linearly below J_MIN (the derivative of the quadratic continuation of ψ_v)."""
    if j < J_MIN:
        g_min, slope = volumetric_stress_and_slope(J_MIN, mu, lam)
        return g_min + slope * (j - J_MIN)
    g, _slope = volumetric_stress_and_slope(j, mu, lam)
    return g


@wp.func
def volumetric_energy(j: wp.float64, mu: wp.float64, lam: wp.float64) -> wp.float64:
    """ψ_v(J) = -μ ln J + λ/2 (J - 1)² [J/m³], continued below J_MIN by its second-order Taylor expansion, float64."""
    half = wp.float64(0.5)
    one = wp.float64(1.0)
    if j < wp.float64(J_MIN):
        j_min = wp.float64(J_MIN)
        g_min, slope = volumetric_stress_and_slope(j_min, mu, lam)
        s = j - j_min
        return -mu * wp.log(j_min) + half * lam * (j_min - one) * (j_min - one) + g_min * s + half * slope * s * s
    return -mu * wp.log(j) + half * lam * (j - one) * (j - one)


@wp.func
def shifted_pressure(j_minus_one: float, mat: TetMaterial) -> float:
    """g(J) + μ [Pa]: the volumetric stress g = dψ_v/dJ (:func:`volumetric_stress`) plus μ, which is
    (J - 1) (λ + μ/J) for J ≥ J_MIN, formed from J - 1 so that it keeps float32 precision at rock strains (g alone is
    ≈ -μ there)."""
    j = 1.0 + j_minus_one
    if j < J_MIN:
        return volumetric_stress(j, mat.mu, mat.lam) + mat.mu
    return j_minus_one * (mat.lam + mat.mu / j)


@wp.func
def stretch_less_cofactor(h: wp.mat33, cof_h: wp.mat33) -> wp.mat33:
    """F - cof F = H + Hᵀ - (tr H) I - cof H at F = I + H (:func:`deformation_cofactor`): of the order of the strain,
    where F and cof F are each of order 1."""
    return h + wp.transpose(h) - wp.diag(wp.vec3(wp.trace(h))) - cof_h


@wp.func
def cauchy_stress(h: wp.mat33, j_minus_one: float, mat: TetMaterial) -> wp.mat33:
    """Cauchy stress σ = P Fᵀ / J [Pa] of the neo-Hookean P = μ F + g cof F at F = I + H:
    (μ (F Fᵀ - I) + λ (J - 1) J I) / J with F Fᵀ - I = H + Hᵀ + H Hᵀ (no cancellation); below J_MIN (μ F Fᵀ + g J I) / J
    with J clamped at J_MIN in the division."""
    j = 1.0 + j_minus_one
    if j < J_MIN:
        f = wp.identity(n=3, dtype=float) + h
        g = volumetric_stress(j, mat.mu, mat.lam)
        return (mat.mu / J_MIN) * (f * wp.transpose(f)) + wp.diag(wp.vec3(g * j / J_MIN))
    strain = h + wp.transpose(h) + h * wp.transpose(h)
    return (mat.mu / j) * strain + wp.diag(wp.vec3(mat.lam * j_minus_one))


@wp.func
def neo_hookean_energy_density(f: wp.mat33d, mat: TetMaterial) -> wp.float64:
    """Strain energy per reference volume ψ = μ/2 (tr FᵀF - 3) + ψ_v(J) [J/m³], in float64.

    At rock strains ε the two O(με) terms cancel to O(με²); float32 would leave only noise of order μ·1e-7.
    """
    mu = wp.float64(mat.mu)
    psi_v = volumetric_energy(wp.determinant(f), mu, wp.float64(mat.lam))
    return wp.float64(0.5) * mu * (wp.ddot(f, f) - wp.float64(3.0)) + psi_v


@wp.func
def bulk_viscosity_pressure(volume_rate: float, length: float, mat: TetMaterial) -> float:
    """Artificial bulk-viscosity pressure q ≥ 0 [Pa] (von Neumann–Richtmyer quadratic + Landshoff linear terms).

    q = ρ₀ ℓ (c_quad ℓ ε̇_v² - c_lin c_p ε̇_v) for ε̇_v < 0 (compression), 0 otherwise. Density and length are those
    of the reference configuration (a Lagrangian viscosity; rock stays within a few percent of J = 1).

    Args:
        volume_rate: volumetric strain rate ε̇_v = J̇/J [1/s].
        length: the tet's characteristic length ℓ = 2 / sqrt(Σ_a |∇N_a|²) [m]
        (warpdem.stages.tets.characteristic_lengths),
            stored per tet: it shrinks with the smallest height of a flat tet, so the viscosity damps the element's
            fastest mode by the same ratio whatever its shape.
    """
    if volume_rate >= 0.0:
        return 0.0
    return mat.density * length * (mat.c_quad * length * volume_rate * volume_rate - mat.c_lin * mat.c_p * volume_rate)


@wp.func
def director_forces(
    stretch: wp.mat33, a: wp.mat33, pressure: float, mu: float, volume0: float, inv_ref: wp.mat33
) -> wp.mat33:
    """Nodal forces of a tet of P = μ F + (g - q) cof F = μ (F - cof F) + (g + μ - q) cof F, the neo-Hookean law
    (∂ψ/∂F = μ F + g cof F) and a viscous pressure q: the rows of -V₀ D⁻¹ Pᵀ = -V₀ (μ D⁻¹ (F - cof F)ᵀ + pressure A)
    are the forces on nodes 1..3 [N] (node 0 takes minus their sum), with ``stretch`` = F - cof F
    (:func:`stretch_less_cofactor`), A = D⁻¹ cof Fᵀ and ``pressure`` = g + μ - q [Pa] (:func:`shifted_pressure`).

    Written as μ F + g cof F, its two O(μ) terms cancel to the stress (μ - μ = 0 at rest): in float32 that left an
    error of ε₃₂ μ in the force, ~1e-3 of it at rock strains, which did work the energy does not see (a floor in the
    books that does not shrink with dt). Both terms here are of the order of the strain."""
    return -volume0 * (mu * (inv_ref * wp.transpose(stretch)) + pressure * a)


@wp.func
def elastic_node_force(
    u0: wp.vec3, u1: wp.vec3, u2: wp.vec3, u3: wp.vec3, inv_ref: wp.mat33, volume0: float, mat: TetMaterial, k: int
) -> wp.vec3:
    """Elastic force of a tet on its node k (0..3) [N] at the displacements u_i [m] (no bulk viscosity): the force
    eval_tet_forces_kernel adds to that node when the tet is at rest."""
    h = displacement_gradient(u0, u1, u2, u3, inv_ref)
    cof_h = cofactor(h)
    a = inv_ref * wp.transpose(deformation_cofactor(h, cof_h))
    pressure = shifted_pressure(det_minus_one(h, cof_h), mat)
    forces = director_forces(stretch_less_cofactor(h, cof_h), a, pressure, mat.mu, volume0, inv_ref)
    if k == 0:
        return -(forces[0] + forces[1] + forces[2])
    return forces[k - 1]


# ----------------------------------------------------------------------------------------------------------------
# Kernels.


@wp.kernel
def eval_tet_forces_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_inv_ref: wp.array(dtype=wp.mat33),
    tet_volume: wp.array(dtype=float),
    tet_length: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    dt: float,
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    # State out:
    node_f: wp.array(dtype=wp.vec3),
    node_energy_damping: wp.array(dtype=wp.float64),
    node_f_viscous: wp.array(dtype=wp.vec3),
):
    t = wp.tid()  # one thread per tet slot
    if t >= tet_count[0]:
        return
    if tet_active[t] != TET_ACTIVE:
        return
    n = tet_nodes[t]
    inv_ref = tet_inv_ref[t]
    volume0 = tet_volume[t]
    mat = tet_material_table[tet_material[t]]
    h = displacement_gradient(node_u[n[0]], node_u[n[1]], node_u[n[2]], node_u[n[3]], inv_ref)
    cof_h = cofactor(h)
    cof = deformation_cofactor(h, cof_h)
    j_minus_one = det_minus_one(h, cof_h)
    j = 1.0 + j_minus_one
    # The Cauchy stress is not stored here (eval_tet_stress_kernel, between steps): its 36-byte store per tet would
    # be a third of the kernel's memory traffic, for a value no stage of the step reads.
    # A = D⁻¹ cof Fᵀ: row i is ∂J/∂d_i, so J̇ = Σ_i A_i · (v_i - v_0) (= cof F : Ḟ) and ε̇_v = J̇ / J.
    a = inv_ref * wp.transpose(cof)
    v0 = node_qd[n[0]]
    j_rate = wp.dot(a[0], node_qd[n[1]] - v0) + wp.dot(a[1], node_qd[n[2]] - v0) + wp.dot(a[2], node_qd[n[3]] - v0)
    q = bulk_viscosity_pressure(j_rate / wp.max(j, J_MIN), tet_length[t], mat)
    # P = μ F + (g - q) cof F: the elastic law plus the viscous pressure q as -q J F⁻ᵀ, formed as μ (F - cof F) +
    # (g + μ - q) cof F (director_forces says why). Nodal forces -V₀ P D⁻ᵀ e_i are the rows of
    # -V₀ (μ D⁻¹ (F - cof F)ᵀ + (g + μ - q) A) on nodes 1..3, minus their sum on node 0.
    pressure = shifted_pressure(j_minus_one, mat) - q
    forces = director_forces(stretch_less_cofactor(h, cof_h), a, pressure, mat.mu, volume0, inv_ref)
    f1 = forces[0]
    f2 = forces[1]
    f3 = forces[2]
    wp.atomic_add(node_f, n[0], -(f1 + f2 + f3))
    wp.atomic_add(node_f, n[1], f1)
    wp.atomic_add(node_f, n[2], f2)
    wp.atomic_add(node_f, n[3], f3)
    if q > 0.0:
        # Verlet does the viscous forces' work as the trapezoid ½ dt f_{n+1}·(v_{n+1/2} + v_{n+3/2}), as every force's
        # (warpdem.stages.energy.EnergyBalance). The half behind, ½ q (-J̇) V₀ dt ≥ 0 at v_{n+1/2}, is booked here, on
        # the tet's first node (only the sum over nodes is read: one float64 update instead of four); the forces
        # q V₀ A_i go to node_f_viscous, whose half ahead the integrator books once v_{n+3/2} is known. A tet that
        # stops carrying forces between steps (converted) then leaves nothing booked that Verlet did not do.
        wp.atomic_add(node_energy_damping, n[0], wp.float64(-0.5 * q * j_rate * volume0 * dt))
        fv = (q * volume0) * a
        wp.atomic_add(node_f_viscous, n[0], -(fv[0] + fv[1] + fv[2]))
        wp.atomic_add(node_f_viscous, n[1], fv[0])
        wp.atomic_add(node_f_viscous, n[2], fv[1])
        wp.atomic_add(node_f_viscous, n[3], fv[2])


@wp.kernel
def eval_tet_stress_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_inv_ref: wp.array(dtype=wp.mat33),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    # State out:
    tet_stress: wp.array(dtype=wp.mat33),
):
    t = wp.tid()  # one thread per tet slot
    if t >= tet_count[0]:
        return
    if tet_active[t] != TET_ACTIVE:
        tet_stress[t] = wp.mat33(0.0)
        return
    n = tet_nodes[t]
    mat = tet_material_table[tet_material[t]]
    h = displacement_gradient(node_u[n[0]], node_u[n[1]], node_u[n[2]], node_u[n[3]], tet_inv_ref[t])
    # The elastic stress: the bulk viscosity is a numerical device, not a rock stress.
    tet_stress[t] = cauchy_stress(h, det_minus_one(h, cofactor(h)), mat)


@wp.kernel
def eval_tet_energy_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_inv_ref: wp.array(dtype=wp.mat33),
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    # Out:
    tet_energy: wp.array(dtype=wp.float64),
):
    t = wp.tid()  # one thread per tet slot
    if t >= tet_count[0]:
        tet_energy[t] = wp.float64(0.0)
        return
    if tet_active[t] != TET_ACTIVE:
        tet_energy[t] = wp.float64(0.0)
        return
    n = tet_nodes[t]
    mat = tet_material_table[tet_material[t]]
    u0 = node_u[n[0]]
    # F = I + [u_i - u_0] D⁻¹ formed in float64, so the energy keeps the precision of the displacements.
    du = wp.matrix_from_cols(node_u[n[1]] - u0, node_u[n[2]] - u0, node_u[n[3]] - u0)
    f = wp.identity(n=3, dtype=wp.float64) + wp.mat33d(du) * wp.mat33d(tet_inv_ref[t])
    tet_energy[t] = wp.float64(tet_volume[t]) * neo_hookean_energy_density(f, mat)
