"""Tet stage (host side): Cosserat point tetrahedra forces, strain energy, and the set-up of their reference
geometry, lumped masses and stable time step.

The element itself is in :mod:`warpdem.kernels.tets` (material law and bulk viscosity are documented there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import tets as kt
from ..model import Model, State


@dataclass
class TetProps:
    """Continuum-only properties of a material (its density, E and ν come from the material itself).

    Attributes:
        bulk_viscosity_linear: c_lin of the linear bulk viscosity [-] (LS-DYNA's default 0.06).
        bulk_viscosity_quadratic: c_quad of the quadratic bulk viscosity [-] (LS-DYNA uses 1.5).
        damping_alpha: mass-proportional (Rayleigh α) damping [1/s]; 0 = none.
    """

    bulk_viscosity_linear: float = 0.06
    bulk_viscosity_quadratic: float = 1.2
    damping_alpha: float = 0.0


def lame_parameters(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """Lamé μ = E / (2(1 + ν)) and λ = E ν / ((1 + ν)(1 - 2ν)) [Pa].

    Raises:
        ValueError: E ≤ 0 or ν outside (-1, 0.5).
    """
    e, nu = youngs_modulus, poisson_ratio
    if not (e > 0.0 and -1.0 < nu < 0.5):
        raise ValueError(f"need E > 0 and -1 < ν < 0.5 for a solid, got E = {e}, ν = {nu}")
    return e / (2.0 * (1.0 + nu)), e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def tet_material(density: float, youngs_modulus: float, poisson_ratio: float, props: TetProps) -> kt.TetMaterial:
    """The device-side TetMaterial of a material: Lamé parameters, density [kg/m³], P-wave speed [m/s], viscosity.

    Raises:
        ValueError: a density ≤ 0, E ≤ 0 or ν outside (-1, 0.5).
    """
    mu, lam = lame_parameters(youngs_modulus, poisson_ratio)
    if not density > 0.0:
        raise ValueError(f"need a density > 0, got {density}")
    m = kt.TetMaterial()
    m.mu = mu
    m.lam = lam
    m.density = density
    m.c_p = math.sqrt((lam + 2.0 * mu) / density)
    m.c_lin = props.bulk_viscosity_linear
    m.c_quad = props.bulk_viscosity_quadratic
    m.alpha = props.damping_alpha
    return m


def reference_geometry(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse reference director matrices and reference volumes of positively oriented tets, in float64.

    The elements see the nodes through their displacements (F = I + [u_i - u_0] D⁻¹), so the reference geometry
    is taken from the exact points, not from their float32 rounding: a mesh far from the origin keeps its shape.

    Args:
        points: node positions [m], shape (N, 3).
        tets: node indices, shape (M, 4).

    Returns:
        D⁻¹ with D = ``[X1 - X0, X2 - X0, X3 - X0]`` [1/m], shape (M, 3, 3); V₀ = det D / 6 [m³], shape (M,).
    """
    x = np.asarray(points, dtype=np.float64)[np.asarray(tets, dtype=np.int64)]
    d = np.transpose(x[:, 1:] - x[:, :1], (0, 2, 1))
    return np.linalg.inv(d), np.linalg.det(d) / 6.0


def shape_gradients(inv_ref: np.ndarray) -> np.ndarray:
    """Gradients of the four linear shape functions ∇N_a [1/m], shape (M, 4, 3): rows of D⁻¹, and minus their sum
    for node 0."""
    g = np.empty((len(inv_ref), 4, 3))
    g[:, 1:] = inv_ref
    g[:, 0] = -inv_ref.sum(axis=1)
    return g


def characteristic_lengths(inv_ref: np.ndarray) -> np.ndarray:
    """Reference length of each tet, ℓ = 2 / sqrt(Σ_a |∇N_a|²) = 2 / sqrt(tr Q) [m], shape (M,): the height of a
    regular tet, 0.82 of the cell edge for a Kuhn tet. Unlike V^{1/3} it shrinks with the smallest height of a flat
    tet, so the bulk viscosity built on it (kernels/tets.py) damps the element's fastest mode by the same ratio
    whatever its shape (:func:`tet_stable_time_steps`).

    Args:
        inv_ref: D⁻¹ [1/m], shape (M, 3, 3).
    """
    g = shape_gradients(inv_ref)
    return 2.0 / np.sqrt(np.einsum("mai,mai->m", g, g))


def tet_stable_time_steps(
    inv_ref: np.ndarray,
    mu: np.ndarray,
    lam: np.ndarray,
    density: np.ndarray,
    bulk_viscosity_linear: np.ndarray,
    damping_alpha: np.ndarray | None = None,
) -> np.ndarray:
    """Stable explicit time step of each tet with its lumped mass [s], shape (M,).

    The largest eigenvalue of the assembled M⁻¹K is at most the largest of the element ones (Irons & Treharne), so
    dt = 2/ω_e,max per element is a guaranteed bound. With lumped mass ρV₀/4 per node, the element eigenproblem
    ω² u_a = (4/ρ) σ(∇u) ∇N_a reduces, through ∇u = Σ u_a ⊗ ∇N_a, to ω² H = (4/ρ) σ(H) Q with Q = Σ_a ∇N_a ∇N_aᵀ.
    In the eigenbasis of Q (eigenvalues q_i) shear pairs give (4μ/ρ)(q_i + q_j) and the diagonal block the
    eigenvalues of (4/ρ)(2μ diag(q) + λ √q √qᵀ), which always holds the largest: ω_e,max² = (4/ρ) λ_max of that
    3×3 matrix. For a regular tet of height h this is 2/ω = (h/c_p) sqrt(3(λ+2μ) / (4(3λ+2μ))), 33 % below the
    popular h_min/c_p at ν = 0.25: h_min/c_p is not a stable step for tets (tests/test_tets.py checks both).

    The linear bulk viscosity is a dashpot η = ρ ℓ c_lin c_p on the volumetric mode, ℓ = 2 / sqrt(tr Q) the
    element's characteristic length (:func:`characteristic_lengths`); its damping ratio is at most
    ζ = (4/ρ) η tr Q / (2ω) = 4 c_lin c_p sqrt(tr Q) / ω; mass-proportional damping adds α / (2ω). A damped
    oscillator is stable for dt ≤ (2/ω)(sqrt(1 + ζ²) - ζ).

    Args:
        inv_ref: D⁻¹ [1/m], shape (M, 3, 3). mu, lam: Lamé parameters [Pa], (M,). density: [kg/m³], (M,).
        bulk_viscosity_linear: c_lin [-], (M,). damping_alpha: α [1/s], (M,), default 0.
    """
    if len(inv_ref) == 0:
        return np.zeros(0)
    g = shape_gradients(inv_ref)
    qmat = np.einsum("mai,maj->mij", g, g)
    q = np.clip(np.linalg.eigvalsh(qmat), 0.0, None)
    s = np.sqrt(q)
    a = 2.0 * mu[:, None, None] * np.eye(3) * q[:, None, :] + lam[:, None, None] * s[:, :, None] * s[:, None, :]
    omega = np.sqrt(4.0 / density * np.linalg.eigvalsh(a)[:, -1])
    c_p = np.sqrt((lam + 2.0 * mu) / density)
    zeta = 4.0 * bulk_viscosity_linear * c_p * np.sqrt(q.sum(axis=1)) / omega
    if damping_alpha is not None:
        zeta = zeta + 0.5 * damping_alpha / omega
    return 2.0 / omega * (np.sqrt(1.0 + zeta**2) - zeta)


def lumped_node_masses(
    num_nodes: int, tets: np.ndarray, volume: np.ndarray, density: np.ndarray, alpha: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Lumped node masses Σ ρV₀/4 [kg] (LDEC's uncoupled director inertia) and the mass-weighted damping α [1/s].

    Args:
        num_nodes: N. tets: (M, 4). volume: V₀ [m³], (M,). density: ρ [kg/m³], (M,). alpha: α [1/s], (M,).

    Returns:
        masses, shape (N,); α per node, shape (N,) (0 for a node without tets).
    """
    quarter = np.repeat(0.25 * density * volume, 4)
    nodes = np.asarray(tets, dtype=np.int64).ravel()
    mass = np.bincount(nodes, weights=quarter, minlength=num_nodes)
    damping = np.bincount(nodes, weights=quarter * np.repeat(alpha, 4), minlength=num_nodes)
    return mass, np.divide(damping, mass, out=np.zeros(num_nodes), where=mass > 0)


def set_node_displacements(model: Model, state: State, displacement: np.ndarray) -> None:
    """Move the live nodes to x = X + u (an initial condition; between steps): sets ``node_u`` and ``node_q``.

    Args:
        displacement: u [m], shape (node_count, 3), float64 preferred (u is rounded once, to float32).
    """
    u = np.asarray(displacement, dtype=np.float64)
    n = len(u)
    node_u = state.node_u.numpy()
    node_u[:n] = u
    node_q = state.node_q.numpy()
    node_q[:n] = model.node_ref_q.numpy()[:n].astype(np.float64) + u
    state.node_u.assign(node_u)
    state.node_q.assign(node_q)


def eval_tets(model: Model, state: State, dt: float | None = None) -> None:
    """Accumulate the forces of the live tets into ``state.node_f`` (the step's tet stage; the Cauchy stresses are
    :func:`eval_tet_stresses`'s).

    ``dt`` overrides the model step for the dissipation bookkeeping; 0 evaluates forces without booking any. The
    bulk-viscosity forces also go to ``state.node_f_viscous`` (the integrator books the half of their work ahead).
    """
    if model.tet_capacity == 0:
        return
    m, s = model, state
    wp.launch(
        kt.eval_tet_forces_kernel,
        dim=m.tet_capacity,
        inputs=[
            # Model:
            m.tet_nodes,
            m.tet_inv_ref,
            m.tet_volume if m.tet_band_volume is None else m.tet_band_volume,
            m.tet_length,
            m.tet_material,
            m.tet_material_table,
            m.dt if dt is None else dt,
            # State in:
            s.tet_count,
            s.tet_active,
            s.node_u,
            s.node_qd,
        ],
        outputs=[s.node_f, s.node_energy_damping, s.node_f_viscous],
        device=m.device,
    )


def eval_tet_stresses(model: Model, state: State) -> None:
    """Store the elastic Cauchy stress of every live tet at the current displacements in ``state.tet_stress`` [Pa]
    (zero for inactive tets). Launches only; :class:`warpdem.simulation.Simulation` calls it after every advance."""
    if model.tet_capacity == 0:
        return
    m, s = model, state
    wp.launch(
        kt.eval_tet_stress_kernel,
        dim=m.tet_capacity,
        inputs=[
            # Model:
            m.tet_nodes,
            m.tet_inv_ref,
            m.tet_material,
            m.tet_material_table,
            # State in:
            s.tet_count,
            s.tet_active,
            s.node_u,
        ],
        outputs=[s.tet_stress],
        device=m.device,
    )


def tet_energies(model: Model, state: State, active: wp.array | None = None, out: wp.array | None = None) -> wp.array:
    """Strain energy of every tet slot [J] (0 past the count and for inactive tets), shape (tet_capacity,), float64.
    ``active``: the tets to evaluate, 1 where wanted (int per tet slot; None: ``state.tet_active``); ``out``: where to
    write (None: allocated here, so call between steps)."""
    if out is None:
        out = wp.zeros(model.tet_capacity, dtype=wp.float64, device=model.device)
    if model.tet_capacity:
        m, s = model, state
        wp.launch(
            kt.eval_tet_energy_kernel,
            dim=m.tet_capacity,
            inputs=[
                # Model:
                m.tet_nodes,
                m.tet_inv_ref,
                m.tet_volume if m.tet_band_volume is None else m.tet_band_volume,
                m.tet_material,
                m.tet_material_table,
                # State in:
                s.tet_count,
                s.tet_active if active is None else active,
                s.node_u,
            ],
            outputs=[out],
            device=m.device,
        )
    return out


def tet_energy(model: Model, state: State) -> float:
    """Total strain energy of the live tets [J] (reads back: call between steps)."""
    return float(tet_energies(model, state).numpy().sum())
