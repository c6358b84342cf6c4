"""Cosserat point tetrahedra (kernels/tets.py, warpdem/stages/tets.py): element forces, stresses, waves, energy, time
step.

Oracles: a hand computation of one tet in float64 numpy (F = [d1 d2 d3] D⁻¹, P = μF + (λ (J - 1) J - μ) F⁻ᵀ,
f_i = -V₀ P D⁻ᵀ e_i); zero force under rigid motion; the patch test (a uniform affine deformation gives the uniform
stress in every tet and no net force inside); the 1D wave speeds c_p = sqrt((λ + 2μ)/ρ) (uniaxial strain) and
c_bar = sqrt(E/ρ) (thin bar); conservation of energy and momentum; the eigenvalues of the assembled lumped-mass
system for the stable time step.

Tolerances. Nodes hold float32 displacements u = x - X, so a difference u_i - u_0 carries about ε₃₂ |u| of rounding
and F = I + ∇u another ε₃₂: δF ≈ ε₃₂ (1 + |u|/h) (:func:`roundoff_strain`), and the stress δσ ≈ (3λ + 2μ) δF, the
largest modulus of the law (the bulk mode). A nodal force is V₀ |P| |∇N| ≈ h² |P| / 6 per tet, summed over up to
24 tets.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import box_mesh, smallest_heights
from warpdem.simulation import Simulation
from warpdem.stages.tets import (
    TetProps,
    eval_tet_stresses,
    eval_tets,
    lame_parameters,
    set_node_displacements,
    tet_energy,
)

YOUNG = 50.0e9  # [Pa] granite-like
POISSON = 0.25  # [-]
DENSITY = 2700.0  # [kg/m³]
MU, LAM = lame_parameters(YOUNG, POISSON)
C_P = math.sqrt((LAM + 2.0 * MU) / DENSITY)  # [m/s]
C_BAR = math.sqrt(YOUNG / DENSITY)  # [m/s]
BULK = 3.0 * LAM + 2.0 * MU  # [Pa] largest eigenvalue of the elasticity tensor (3 K)
F32_EPS = float(np.finfo(np.float32).eps)
NO_DAMPING = TetProps(bulk_viscosity_linear=0.0, bulk_viscosity_quadratic=0.0, damping_alpha=0.0)

# Stress and force errors of float32 (module docstring): δσ ≤ STRESS_ROUNDOFF (3λ+2μ) δF and
# |δf| ≤ FORCE_ROUNDOFF (3λ+2μ) h² δF (h²/6 per tet times √24 tets ≈ 1, with a factor of about 4 of margin).
STRESS_ROUNDOFF = 2.0
FORCE_ROUNDOFF = 4.0
# Small-strain patch test: neo-Hookean and Hooke's law differ at second order, |σ_NH - σ_Hooke| ≈ (λ + 2μ) |H|².
STRAIN = 5.0e-4
HOOKE_NONLINEAR = 3.0
# Wave speeds. For the lumped-mass chain integrated by central differences the group velocity is
# c cos(kh/2) / sqrt(1 - C² sin²(kh/2)) ≈ c (1 - (1 - C²)(kh)²/8) (C = c dt/h); a Gaussian pulse of width σ = 4h
# (≈ 25 elements per wavelength 2πσ) has its energy around kh = 1/4: under 0.8 % slow, inside the 2 % asked.
# The thin-bar speed carries Love's lateral-inertia correction ν² k² r_p²/2 with r_p² = a²/6 (a = h): 3e-4.
P_WAVE_RTOL = 0.02
BAR_WAVE_RTOL = 0.03
PULSE_CELLS = 4.0
# Energy: velocity Verlet conserves a shadow energy; the measured one oscillates by about (ω dt)²/4 of the energy
# in the fastest excited mode (here ω dt < 0.1 for a smooth velocity field at half the stable step).
ENERGY_RTOL = 0.005


# ----------------------------------------------------------------------------------------------------------------
# Helpers


def build(device: str, points: np.ndarray, tets: np.ndarray, *, props: TetProps = NO_DAMPING, gravity=(0, 0, 0), **kw):
    """Model and state of one tet body of the test material."""
    b = ModelBuilder(gravity=tuple(gravity))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.set_tet_properties("rock", props)
    b.add_tet_mesh(points, tets, "rock", **kw)
    return b.finalize(device, safety_factor=0.5)


def roundoff_strain(u: np.ndarray, h: float) -> float:
    """δF ≈ ε₃₂ (1 + |u|/h): float32 rounding of a deformation gradient built from displacements u [m] over h [m]."""
    return F32_EPS * (1.0 + np.abs(u).max() / h)


def reference_points(model) -> np.ndarray:
    """The reference positions X the device holds (float32 values), float64."""
    return model.node_ref_q.numpy().astype(np.float64)


def forces_at(model, state, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Node forces [N] and tet Cauchy stresses [Pa] with the nodes at x (float64 copies)."""
    set_node_displacements(model, state, x - reference_points(model))
    state.node_f.zero_()
    eval_tets(model, state, dt=0.0)
    eval_tet_stresses(model, state)
    return state.node_f.numpy().astype(np.float64), state.tet_stress.numpy().astype(np.float64)


def rotation(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * k @ k


def neo_hookean_energy(f: np.ndarray) -> float:
    """ψ = μ/2 (tr FᵀF - 3) - μ ln J + λ/2 (J - 1)² [J/m³], float64."""
    j = np.linalg.det(f)
    return 0.5 * MU * (np.sum(f * f) - 3.0) - MU * math.log(j) + 0.5 * LAM * (j - 1.0) ** 2


def neo_hookean_piola(f: np.ndarray) -> np.ndarray:
    """P = ∂ψ/∂F = μ F + (λ (J - 1) - μ/J) J F⁻ᵀ, float64."""
    j = np.linalg.det(f)
    return MU * f + (LAM * (j - 1.0) * j - MU) * np.linalg.inv(f).T


def neo_hookean_cauchy(f: np.ndarray) -> np.ndarray:
    """σ = P Fᵀ / J = μ/J (F Fᵀ - I) + λ (J - 1) I, float64."""
    j = np.linalg.det(f)
    return MU / j * (f @ f.T - np.eye(3)) + LAM * (j - 1.0) * np.eye(3)


def hooke(h: np.ndarray) -> np.ndarray:
    """σ = λ tr(ε) I + 2μ ε with ε = sym(∇u)."""
    eps = 0.5 * (h + h.T)
    return LAM * np.trace(eps) * np.eye(3) + 2.0 * MU * eps


def centered_block(divisions=(4, 4, 4), size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    half = 0.5 * size
    return box_mesh((-half, -half, -half), (half, half, half), divisions)


SINGLE_TET = np.array([[0.1, -0.05, 0.02], [0.42, 0.03, -0.01], [0.05, 0.38, 0.04], [0.08, 0.02, 0.33]])


# ----------------------------------------------------------------------------------------------------------------
# Element


def test_single_tet_forces_match_hand_computation(device):
    model, state = build(device, SINGLE_TET, np.array([[0, 1, 2, 3]]))
    rng = np.random.default_rng(7)
    grad = 2.0e-3 * rng.standard_normal((3, 3))
    x = SINGLE_TET + (SINGLE_TET - SINGLE_TET[0]) @ grad.T
    f, sigma = forces_at(model, state, x)

    # Hand computation in float64 from the reference geometry and the float32 displacements the device holds.
    u = state.node_u.numpy().astype(np.float64)
    dm = (SINGLE_TET[1:] - SINGLE_TET[0]).T
    dm_inv = np.linalg.inv(dm)
    v0 = np.linalg.det(dm) / 6.0
    ff = np.eye(3) + (u[1:] - u[0]).T @ dm_inv
    p = neo_hookean_piola(ff)
    h = -v0 * p @ dm_inv.T
    expected = np.vstack([-h.sum(axis=1), h.T])
    h_ref = np.linalg.norm(SINGLE_TET[1:] - SINGLE_TET[0], axis=1).min()
    delta_f = roundoff_strain(u, h_ref)
    force_tol = FORCE_ROUNDOFF * BULK * h_ref**2 * delta_f
    np.testing.assert_allclose(f[:4], expected, atol=force_tol)
    np.testing.assert_allclose(model.tet_volume.numpy()[0], v0, rtol=4 * F32_EPS)
    stress_tol = STRESS_ROUNDOFF * BULK * delta_f
    np.testing.assert_allclose(sigma[0], neo_hookean_cauchy(ff), atol=stress_tol)
    # And Hooke's law at this small strain, to second order in the displacement gradient.
    hooke_tol = HOOKE_NONLINEAR * (LAM + 2.0 * MU) * np.abs(grad).max() ** 2 * 9 + stress_tol
    np.testing.assert_allclose(sigma[0], hooke(grad), atol=hooke_tol)
    # Strain energy V₀ ψ(F), formed in float64 from the same displacements; the device's D⁻¹ and V₀ are rounded to
    # float32 (ε₃₂/2 each, entering ψ through F twice and V₀ once).
    np.testing.assert_allclose(tet_energy(model, state), v0 * neo_hookean_energy(ff), rtol=2.0 * F32_EPS)

    # A tet taken out of the model carries no force.
    state.tet_active.zero_()
    f_off, _ = forces_at(model, state, x)
    np.testing.assert_array_equal(f_off, 0.0)


@pytest.mark.parametrize("strain", [1.0e-6, 1.0e-4])
def test_small_strain_forces_keep_float32_precision_relative_to_the_strain(device, strain):
    """At rock strains the force and stress are of order μ |H|, while μ F and the volumetric -μ/J cof F are each of
    order μ: summed as such in float32 they cancel to an error of ε₃₂ μ, ε₃₂/|H| of the force (0.12 at |H| = 1e-6).
    kernels/tets.py forms every term at the order of the strain (director_forces, cauchy_stress), so the forces and
    stresses must match the float64 law, from the displacements the device holds, to a few ε₃₂ of their own size:
    H is a sum of three products (3 ε₃₂), D⁻¹ and V₀ are rounded (ε₃₂/2 each), P and D⁻¹ Pᵀ add a few more; 64 ε₃₂."""
    model, state = build(device, SINGLE_TET, np.array([[0, 1, 2, 3]]))
    grad = strain * np.array([[0.3, -0.7, 0.2], [0.5, 1.0, -0.4], [-0.6, 0.1, -0.9]])
    x = SINGLE_TET + (SINGLE_TET - SINGLE_TET[0]) @ grad.T
    f, sigma = forces_at(model, state, x)
    u = state.node_u.numpy().astype(np.float64)
    dm_inv = np.linalg.inv((SINGLE_TET[1:] - SINGLE_TET[0]).T)
    ff = np.eye(3) + (u[1:] - u[0]).T @ dm_inv
    h = -(np.linalg.det((SINGLE_TET[1:] - SINGLE_TET[0]).T) / 6.0) * neo_hookean_piola(ff) @ dm_inv.T
    expected = np.vstack([-h.sum(axis=1), h.T])
    np.testing.assert_allclose(f[:4], expected, atol=64.0 * F32_EPS * np.abs(expected).max())
    cauchy = neo_hookean_cauchy(ff)
    np.testing.assert_allclose(sigma[0], cauchy, atol=64.0 * F32_EPS * np.abs(cauchy).max())


def test_rigid_motion_gives_zero_force(device):
    points, tets = centered_block()
    model, state = build(device, points, tets)
    h = 0.25
    f, sigma = forces_at(model, state, points)
    np.testing.assert_array_equal(f, 0.0)
    for angle in (0.0, math.radians(60.0), math.radians(170.0)):
        x = points @ rotation((1.0, 1.0, 1.0), angle).T + np.array([0.3, -0.2, 0.1])
        f, sigma = forces_at(model, state, x)
        delta_f = roundoff_strain(x - points, h)
        np.testing.assert_allclose(f, 0.0, atol=FORCE_ROUNDOFF * BULK * h**2 * delta_f)
        np.testing.assert_allclose(sigma, 0.0, atol=STRESS_ROUNDOFF * BULK * delta_f)


def test_patch_test_uniform_affine_deformation(device):
    points, tets = box_mesh((-0.4, -0.3, -0.5), (0.4, 0.3, 0.5), (4, 3, 5))
    h = 0.2
    model, state = build(device, points, tets)
    rng = np.random.default_rng(3)
    grad = STRAIN * rng.standard_normal((3, 3))
    x = points + points @ grad.T + np.array([0.01, 0.02, -0.03])
    f, sigma = forces_at(model, state, x)
    delta_f = roundoff_strain(x - points, h)
    stress_tol = STRESS_ROUNDOFF * BULK * delta_f
    ff = np.eye(3) + grad
    # Every tet has the exact stress of the law...
    np.testing.assert_allclose(sigma, np.broadcast_to(neo_hookean_cauchy(ff), sigma.shape), atol=stress_tol)
    # ...which is Hooke's law up to second order in the displacement gradient.
    hooke_tol = HOOKE_NONLINEAR * (LAM + 2.0 * MU) * np.abs(grad).max() ** 2 * 9 + stress_tol
    np.testing.assert_allclose(sigma, np.broadcast_to(hooke(grad), sigma.shape), atol=hooke_tol)
    # A uniform stress is divergence-free: interior nodes feel no net force; all forces sum to zero.
    force_tol = FORCE_ROUNDOFF * BULK * h**2 * delta_f
    interior = np.all(np.abs(points) < np.array([0.4, 0.3, 0.5]) - 1e-9, axis=1)
    assert np.count_nonzero(interior) == 3 * 2 * 4
    np.testing.assert_allclose(f[interior], 0.0, atol=force_tol)
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=F32_EPS * np.abs(f).sum())
    assert np.abs(f).max() > 100.0 * force_tol  # the boundary nodes do carry the traction


def test_crushed_and_inverted_tets_push_back(device):
    """Below J_MIN the volumetric energy continues quadratically: forces stay finite, continuous, and restoring."""
    ref = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.2, 0.3, 1.0]])
    model, state = build(device, ref, np.array([[0, 1, 2, 3]]))

    def apex_force(j: float) -> np.ndarray:
        # Scaling the apex height by J scales the volume by J (F = diag(1, 1, J) plus a shear).
        x = ref.copy()
        x[3, 2] = j
        f, _ = forces_at(model, state, x)
        return f[3]

    above, below = apex_force(0.1 + 1e-4), apex_force(0.1 - 1e-4)
    np.testing.assert_allclose(below, above, rtol=2e-2)
    for j in (0.05, 0.0, -0.5):
        f = apex_force(j)
        assert np.all(np.isfinite(f))
        assert f[2] > 0.0  # pushes the apex back up, towards a positive volume
    assert apex_force(-0.5)[2] > apex_force(0.05)[2]


def test_bulk_viscosity_acts_in_compression_only(device):
    props = TetProps(bulk_viscosity_linear=0.06, bulk_viscosity_quadratic=1.2)
    model, state = build(device, SINGLE_TET, np.array([[0, 1, 2, 3]]), props=props)
    ref = SINGLE_TET.astype(np.float32).astype(np.float64)
    dm_inv = np.linalg.inv((ref[1:] - ref[0]).T)
    v0 = np.linalg.det((ref[1:] - ref[0]).T) / 6.0
    grads = np.vstack([-dm_inv.sum(axis=0), dm_inv])
    length = 2.0 / math.sqrt(np.sum(grads * grads))  # the element's characteristic length
    dt = 1.0e-6
    h_ref = np.linalg.norm(SINGLE_TET[1:] - SINGLE_TET[0], axis=1).min()
    elastic_tol = FORCE_ROUNDOFF * BULK * h_ref**2 * F32_EPS  # u = 0: F = I to float32 rounding
    for rate in (-200.0, 200.0):
        # Uniform dilatation v = r (X - X_c) at the reference configuration: ε̇_v = 3r, no elastic stress.
        state.node_qd.assign((rate * (SINGLE_TET - SINGLE_TET.mean(axis=0))).astype(np.float32))
        state.node_energy_damping.zero_()
        set_node_displacements(model, state, np.zeros((4, 3)))
        state.node_f.zero_()
        state.node_f_viscous.zero_()
        eval_tets(model, state, dt=dt)
        f = state.node_f.numpy().astype(np.float64)
        rate_v = 3.0 * rate
        q = DENSITY * length * (1.2 * length * rate_v**2 - 0.06 * C_P * rate_v) if rate_v < 0.0 else 0.0
        # P = -q cof F = -q I at F = I, so f_a = -V₀ P ∇N_a = q V₀ ∇N_a.
        expected = q * v0 * grads
        np.testing.assert_allclose(f, expected, rtol=1e-5, atol=elastic_tol)
        # The viscous forces alone are kept for the integrator's half ahead; the evaluation books the half behind of
        # Verlet's trapezoid, ½ q |ε̇_v| V₀ dt (the work of the viscous pressure at this velocity over half a step).
        np.testing.assert_allclose(state.node_f_viscous.numpy(), expected, rtol=1e-5, atol=elastic_tol)
        np.testing.assert_allclose(state.node_energy_damping.numpy().sum(), 0.5 * q * abs(rate_v) * v0 * dt, rtol=1e-4)


# ----------------------------------------------------------------------------------------------------------------
# Masses, constraints, gravity, mixed models


def test_lumped_masses_and_free_fall(device):
    points, tets = centered_block((3, 2, 2))
    model, state = build(device, points, tets, gravity=(0.0, 0.0, -9.81))
    mass = model.node_mass.numpy().astype(np.float64)
    np.testing.assert_allclose(mass.sum(), DENSITY * 1.0, rtol=1e-6)
    # Node (0, 0, 0) is corner 0 of its cell, in all six Kuhn tets: m = 6 ρ (V_cell/6) / 4.
    np.testing.assert_allclose(mass[0], DENSITY * (1.0 / 12.0) / 4.0, rtol=1e-6)
    sim = Simulation(model, state)
    steps = 50
    sim.advance(steps)
    t = steps * model.dt
    # Every node gets the same float32 increments, so the displacement differences stay exactly zero, F = I exactly
    # and the block falls as a rigid body: velocity Verlet is exact for a constant acceleration, up to the float32
    # rounding of 2 × 50 kicks and drifts.
    v = state.node_qd.numpy().astype(np.float64)
    u = state.node_u.numpy().astype(np.float64)
    np.testing.assert_array_equal(u, np.broadcast_to(u[0], u.shape))
    np.testing.assert_array_equal(state.tet_stress.numpy(), 0.0)
    np.testing.assert_allclose(v, np.broadcast_to([0.0, 0.0, -9.81 * t], v.shape), rtol=4 * steps * F32_EPS)
    np.testing.assert_allclose(u[:, 2], -0.5 * 9.81 * t**2, rtol=4 * steps * F32_EPS)
    q = state.node_q.numpy().astype(np.float64)
    np.testing.assert_allclose(q, reference_points(model) + u, atol=F32_EPS * np.abs(q).max())


def test_fixed_and_z_only_nodes(device):
    points, tets = box_mesh((0.0, 0.0, 0.0), (0.2, 0.2, 1.0), (1, 1, 5))
    bottom = np.nonzero(points[:, 2] == 0.0)[0]
    v0 = np.tile([1.0, -2.0, 0.5], (len(points), 1))
    model, state = build(
        device,
        points,
        tets,
        gravity=(1.0, 2.0, -9.81),
        fixed_nodes=bottom,
        z_only_nodes=np.arange(len(points)),
        velocity=v0,
    )
    np.testing.assert_array_equal(model.node_inv_mass.numpy()[bottom], 0.0)
    sim = Simulation(model, state)
    sim.advance(100)
    x = state.node_q.numpy()
    np.testing.assert_array_equal(x[bottom], points[bottom].astype(np.float32))
    np.testing.assert_array_equal(x[:, :2], points[:, :2].astype(np.float32))
    assert np.all(x[points[:, 2] > 0.0, 2] != points[points[:, 2] > 0.0, 2].astype(np.float32))


def test_spheres_and_tets_step_together(device):
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_sphere((5.0, 5.0, 5.0), 0.1, "rock")
    points, tets = centered_block((2, 2, 2))
    b.add_tet_mesh(points, tets, "rock")
    model, state = b.finalize(device, dt=1.0e-5)
    sim = Simulation(model, state)
    sim.advance(40)
    t = 40 * model.dt
    np.testing.assert_allclose(state.particle_qd.numpy()[0, 2], -9.81 * t, rtol=1e-5)
    np.testing.assert_allclose(state.node_qd.numpy()[:, 2], -9.81 * t, rtol=4 * 40 * F32_EPS)


def test_pure_dem_model_has_empty_fem_arrays(device):
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("glass", 2500.0, 1e7, 0.3)
    b.add_sphere((0.0, 0.0, 1.0), 0.01, "glass")
    model, state = b.finalize(device)
    assert model.node_capacity == 0 and model.tet_capacity == 0
    arrays = state.arrays()
    for name in ("node_u", "node_q", "node_qd", "node_f", "node_energy_damping", "tet_active", "tet_stress"):
        assert arrays[name].shape == (0,)
    np.testing.assert_array_equal([state.node_count.numpy()[0], state.tet_count.numpy()[0]], [0, 0])
    sim = Simulation(model, state)
    sim.advance(10)
    e = sim.energy()
    assert e.kinetic_nodes == 0.0 and e.strain == 0.0 and e.dissipated_viscous == 0.0


# ----------------------------------------------------------------------------------------------------------------
# Waves


def pulse_arrival_speed(device: str, confined: bool) -> tuple[float, float]:
    """Speed of a right-running Gaussian pulse between two stations of a 1-cell-wide column, from the times its
    displacement first reaches half its amplitude there (linear interpolation between steps).

    The initial condition u = A g(z - z0), v = -c A g'(z - z0) is d'Alembert's right-running wave (a thin bar also
    gets its Poisson contraction -ν ε_zz (x, y)). ``confined``: every node moves along z only (uniaxial strain,
    c = c_p); otherwise the lateral surfaces are free (uniaxial stress, c = c_bar).

    Returns:
        (measured speed, expected speed) [m/s].
    """
    h, cells = 0.05, 200
    length = h * cells
    points, tets = box_mesh((-h / 2, -h / 2, -length / 2), (h / 2, h / 2, length / 2), (1, 1, cells))
    c = C_P if confined else C_BAR
    sigma = PULSE_CELLS * h
    z0 = -0.3 * length
    amplitude = 1.0e-3 * sigma * math.exp(0.5)  # peak strain 1e-3
    dz = points[:, 2] - z0
    g = np.exp(-(dz**2) / (2 * sigma**2))
    g1 = -dz / sigma**2 * g
    g2 = (dz**2 / sigma**4 - 1.0 / sigma**2) * g
    u = np.zeros_like(points)
    v = np.zeros_like(points)
    u[:, 2], v[:, 2] = amplitude * g, -c * amplitude * g1
    if not confined:
        u[:, :2] = -POISSON * amplitude * g1[:, None] * points[:, :2]
        v[:, :2] = POISSON * c * amplitude * g2[:, None] * points[:, :2]
    constraint = {"z_only_nodes": np.arange(len(points))} if confined else {}
    model, state = build(device, points, tets, velocity=v, **constraint)
    set_node_displacements(model, state, u)
    sim = Simulation(model, state, use_graph=False)
    stations = np.array([-0.1 * length, 0.2 * length])
    ids = [
        int(np.argmin(np.abs(points[:, 2] - zs) + np.abs(points[:, 0] + h / 2) + np.abs(points[:, 1] + h / 2)))
        for zs in stations
    ]
    steps = int((stations[1] + 5 * sigma - z0) / c / model.dt)
    history = np.empty((steps + 1, 2))
    history[0] = u[ids, 2]
    for k in range(steps):
        sim.step()
        history[k + 1] = state.node_u.numpy()[ids, 2]
    arrival = []
    for j in range(2):
        k = int(np.nonzero(history[:, j] >= 0.5 * amplitude)[0][0])
        frac = (0.5 * amplitude - history[k - 1, j]) / (history[k, j] - history[k - 1, j])
        arrival.append((k - 1 + frac) * model.dt)
    return float((stations[1] - stations[0]) / (arrival[1] - arrival[0])), c


def test_p_wave_speed_in_a_confined_column(device):
    measured, expected = pulse_arrival_speed(device, confined=True)
    np.testing.assert_allclose(measured, expected, rtol=P_WAVE_RTOL)


def test_bar_wave_speed_in_a_thin_bar(device):
    measured, expected = pulse_arrival_speed(device, confined=False)
    np.testing.assert_allclose(measured, expected, rtol=BAR_WAVE_RTOL)


# ----------------------------------------------------------------------------------------------------------------
# Energy and the time step


def vibrating_block(device: str, props: TetProps):
    points, tets = centered_block((5, 5, 5))
    amplitude = 10.0  # [m/s]: strains ~ v/c ≈ 2e-3, far above the float32 floor
    v = amplitude * np.stack(
        [np.sin(np.pi * points[:, 2]), 0.5 * np.sin(np.pi * points[:, 0]), np.sin(np.pi * points[:, 1])], axis=1
    )
    model, state = build(device, points, tets, props=props, gravity=(0.0, 0.0, -9.81), velocity=v)
    return model, state, Simulation(model, state)


def test_energy_and_momentum_conserved_without_damping(device):
    model, state, sim = vibrating_block(device, NO_DAMPING)
    mass = model.node_mass.numpy().astype(np.float64)
    e0 = sim.energy()
    p0 = mass @ state.node_qd.numpy().astype(np.float64)
    errors = []
    for _ in range(20):
        sim.advance(20)
        e = sim.energy()
        assert e.strain > 0.01 * e0.kinetic  # the block does deform
        errors.append((e.total - e0.total) / e0.total)
    np.testing.assert_allclose(errors, 0.0, atol=ENERGY_RTOL)
    v = state.node_qd.numpy().astype(np.float64)
    gravity_impulse = mass.sum() * np.array([0.0, 0.0, -9.81]) * sim.time
    # The internal forces cancel exactly but for float32 rounding: each half kick rounds each velocity by about
    # ε₃₂ |v| / 2, a random walk over 2 × steps kicks and N nodes.
    steps = round(sim.time / model.dt)
    momentum_tol = 4.0 * F32_EPS * np.abs(v).max() * mass.mean() * math.sqrt(2.0 * steps * len(mass))
    np.testing.assert_allclose(mass @ v - p0, gravity_impulse, atol=momentum_tol)


def test_far_from_the_origin_behaves_the_same(device):
    """The tets see displacements, not coordinates: a block 2 km from the origin vibrates as the one at it (with
    float32 coordinates, ulp(2000 m) = 1.2e-4 m would otherwise swamp strains of 1e-3 over 0.2 m cells)."""
    points, tets = centered_block((3, 3, 3))
    velocity = 10.0 * np.stack([np.sin(np.pi * points[:, 2]), np.zeros(len(points)), np.sin(np.pi * points[:, 1])], 1)
    histories = []
    for offset in ((0.0, 0.0, 0.0), (1500.0, -500.0, 1200.0)):
        model, state = build(device, points + np.array(offset), tets, props=TetProps(), velocity=velocity)
        sim = Simulation(model, state)
        sim.advance(200)
        histories.append(state.node_u.numpy().astype(np.float64))
    # The two reference geometries differ in the last bits of D⁻¹, which flips single float32 roundings of
    # F = I + ∇u (δF = ε₃₂): relative to strains of about v/c_p, that is the agreement to expect.
    strain = 10.0 / C_P
    np.testing.assert_allclose(histories[1], histories[0], atol=F32_EPS / strain * np.abs(histories[0]).max())


def test_energy_balance_with_bulk_viscosity_and_damping(device):
    _, _, sim = vibrating_block(device, TetProps(damping_alpha=200.0))
    e0 = sim.energy()
    sim.advance(400)
    e = sim.energy()
    assert e.dissipated_viscous > 0.5 * e0.total  # most of the energy went
    np.testing.assert_allclose(e.total, e0.total, rtol=ENERGY_RTOL)


def assembled_stable_step(points: np.ndarray, tets: np.ndarray) -> float:
    """2/ω_max of the assembled linear-elastic stiffness with lumped mass ρV/4, float64 numpy (dense)."""
    n = len(points)
    k = np.zeros((3 * n, 3 * n))
    m = np.zeros(3 * n)
    eye = np.eye(3)
    c = LAM * np.einsum("ij,kl->ijkl", eye, eye) + MU * (
        np.einsum("ik,jl->ijkl", eye, eye) + np.einsum("il,jk->ijkl", eye, eye)
    )
    for tet in tets:
        d = (points[tet[1:]] - points[tet[0]]).T
        vol = np.linalg.det(d) / 6.0
        g = np.vstack([-np.linalg.inv(d).sum(axis=0), np.linalg.inv(d)])
        ke = vol * np.einsum("aj,ijkl,bl->aibk", g, c, g).reshape(12, 12)
        dofs = (3 * tet[:, None] + np.arange(3)).ravel()
        k[np.ix_(dofs, dofs)] += ke
        m[dofs] += DENSITY * vol / 4.0
    used = m > 0.0
    scaled = k[np.ix_(used, used)] / np.sqrt(np.outer(m[used], m[used]))
    return 2.0 / math.sqrt(np.linalg.eigvalsh(scaled)[-1])


@pytest.mark.parametrize(("jitter", "tightness"), [(0.0, 0.7), (0.02, 0.5), (0.06, 0.0)])
def test_critical_time_step_is_stable(jitter, tightness):
    """The element bound never exceeds the assembled system's 2/ω_max (Irons–Treharne); on good meshes it is within
    a factor ``tightness`` of it (a distorted tet makes it conservative: its neighbours' mass slows it down)."""
    rng = np.random.default_rng(11)
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 0.75, 0.75), (4, 3, 3))
    points = points + jitter * rng.uniform(-1.0, 1.0, points.shape)
    b = ModelBuilder()
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.set_tet_properties("rock", NO_DAMPING)
    b.add_tet_mesh(points, tets, "rock")
    mesh = b.tet_mesh_data()
    dt_elements = b.tet_critical_time_step(mesh)
    dt_system = assembled_stable_step(mesh.points, mesh.tets)
    assert tightness * dt_system <= dt_elements <= dt_system


def test_critical_time_step_of_a_regular_tet():
    """2/ω = (h/c_p) sqrt(3(λ+2μ) / (4(3λ+2μ))) in closed form, 33 % below the popular h_min/c_p, which would be
    unstable."""
    regular = np.array([[1.0, 1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, -1.0, -1.0], [-1.0, -1.0, 1.0]])
    one = np.array([[0, 1, 2, 3]])
    b = ModelBuilder()
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.set_tet_properties("rock", NO_DAMPING)
    b.add_tet_mesh(regular, one, "rock")
    height = smallest_heights(regular, one)[0]
    closed_form = height / C_P * math.sqrt(3.0 * (LAM + 2.0 * MU) / (4.0 * BULK))
    np.testing.assert_allclose(b.tet_critical_time_step(b.tet_mesh_data()), closed_form, rtol=1e-6)
    np.testing.assert_allclose(assembled_stable_step(regular, one), closed_form, rtol=1e-9)
    assert height / C_P > 1.4 * closed_form


def test_builder_time_step_includes_tets_and_viscosity():
    points, tets = centered_block((2, 2, 2))
    b = ModelBuilder()
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(points, tets, "rock")
    with_viscosity = b.critical_time_step(b.particle_data(), b.bond_data(b.particle_data(), wp.get_device("cpu")))
    b.set_tet_properties("rock", NO_DAMPING)
    without = b.tet_critical_time_step(b.tet_mesh_data())
    # The linear bulk viscosity (c_lin = 0.06) shortens the step by a few percent.
    assert 0.85 * without < with_viscosity < without
    model, _ = b.finalize("cpu", safety_factor=0.5)
    np.testing.assert_allclose(model.dt, 0.5 * without, rtol=1e-12)


@pytest.mark.parametrize("flip", [False, True])
def test_builder_reorients_inverted_input(device, flip):
    tets = np.array([[0, 1, 2, 3]])
    if flip:
        tets = tets[:, [0, 2, 1, 3]]
    model, _ = build(device, SINGLE_TET, tets)
    assert model.tet_volume.numpy()[0] > 0.0
