"""Bonds between the spheres of converted tets that make a rigid network with the continuum's bar-wave speed and
tensile strength (measured in tests/test_coupling.py; a calibration the conversion pass can call).

Why not face bonds alone. One sphere per tet bonded across shared faces has Z ≤ 4 bonds (3.3 on average in a bar).
A sphere has 6 degrees of freedom and a bond without bending or twisting moments removes 3 (normal and two shear
springs) or 1 (normal only, k_s = 0): 3 Z / 2 < 6, so the network is a mechanism (Maxwell's count) — a fully converted
bar carries neither a bar wave nor a tensile load. Bonding every pair of converted tets that share an edge gives
Z ≈ 12 > 6 (in 3D a central-force network needs Z ≥ 6), and the network is rigid with normal springs alone.

Stiffness. Energy equivalence under an affine strain ε: Σ_b ½ k_b (L_b n_b·ε·n_b)² = ½ V ε:C:ε. For isotropic bond
directions ⟨n_i n_j n_k n_l⟩ = (δ_ij δ_kl + δ_ik δ_jl + δ_il δ_jk)/15, so a central-force network has λ = μ =
Σ k L² / (15 V) (ν = 1/4) and E_net = 5 μ / 2 = Σ k L² / (6 V): k_b = 6 E V_b / L_b² with Σ_b V_b = V
(V_b = V_i / Z_i + V_j / Z_j). The edge network of Kuhn tets relaxes non-affinely and is not isotropic: with the factor
6 its bar-wave speed is 0.784 sqrt(E/ρ) (cubic cells; 2×2 and 3×3 cross-sections alike), E_net = 0.615 E, so the
factor is STIFFNESS_FACTOR = 6 / 0.615 = 9.76 (measured; other meshes need their own: cells stretched 1.5× along
the bar gave 1.03 sqrt(E/ρ) at the factor 6).

Strength. A bond breaks when its stretch reaches L_b T_f / (S E): the load-carrying bonds of a bar lie oblique to it
and stretch less than the bar, and with S = 1 a bar measured a peak nominal stress 1.126 T_f; STRENGTH_FACTOR = 1.126
brings it to T_f. As bond arrays hold a strength per unit area: area A_b = V_b / L_b, tensile strength
k_b L_b T_f / (S E A_b) = (κ / S) T_f. The shear springs are off (k_s = 0), so the shear strength never acts.

Open: κ and S hold for Kuhn cells 2 across, not for every mesh (tests/test_coupling.py, the same 12 × 2 × 2 cell bar,
0.6 × 0.1 × 0.1 m). An unstructured Gmsh mesh's edge network relaxes less (E_net = 0.77 to 0.91 of the affine
κ E / 6, against 0.615): at h = 0.04 m (2.5 tets across) it measured 1.12 sqrt(E/ρ) and 0.89 T_f, at 0.035 m 1.22
and 0.96, at 0.03 m 1.17 and 0.88, at 0.025 m 1.07 and 0.80. The strength also falls as the cross-section is
resolved more finely: Kuhn cells 4 across keep 0.999 sqrt(E/ρ) but reach only 0.869 T_f. Meeting the 10 % on any
mesh needs κ and S measured on the mesh's own network (e.g. its relaxation under an affine strain when conversion
is attached), not one constant each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STIFFNESS_FACTOR = 9.76
"""κ of k_b = κ E V_b / L_b² [-]: the affine 6 over the measured E_net / E = 0.615 of cubic Kuhn cells."""

STRENGTH_FACTOR = 1.126
"""S: bonds break at stretch L_b T_f / (S E) [-]; the measured peak stress of a bar with S = 1, in units of T_f."""

TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
"""Local node pairs of a tet's six edges."""


@dataclass
class LatticeBonds:
    """Bonds between converted tets' spheres, indexed by tet (map to sphere ids with the conversion's slots).

    Attributes:
        pairs: tet pairs (i < j) sharing an edge, shape (B, 2), int64.
        rest_length: centre distance L_b [m], shape (B,).
        kn: normal stiffness κ E V_b / L_b² [N/m], shape (B,).
        ks: shear stiffness [N/m] (0), shape (B,).
        area: A_b = V_b / L_b [m²], shape (B,).
        tensile_strength: (κ / S) T_f [Pa], shape (B,).
        shear_strength: the same [Pa] (unused with k_s = 0), shape (B,).
    """

    pairs: np.ndarray
    rest_length: np.ndarray
    kn: np.ndarray
    ks: np.ndarray
    area: np.ndarray
    tensile_strength: np.ndarray
    shear_strength: np.ndarray


def edge_pairs(tets: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Pairs (i < j) of tets in ``mask`` that share at least an edge, sorted, shape (B, 2), int64."""
    tets = np.asarray(tets, dtype=np.int64)
    ids = np.nonzero(np.asarray(mask, dtype=bool))[0]
    if len(ids) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    ends = np.sort(tets[ids][:, TET_EDGES], axis=2).reshape(-1, 2)
    owner = np.repeat(ids, 6)
    key = ends[:, 0] * (int(tets.max()) + 1) + ends[:, 1]
    order = np.lexsort((owner, key))
    key, owner = key[order], owner[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    sizes = np.diff(np.r_[starts, len(key)])
    found = []
    for g in np.unique(sizes[sizes > 1]):
        groups = owner[starts[sizes == g][:, None] + np.arange(g)]
        a, b = np.triu_indices(g, 1)
        found.append(np.stack([groups[:, a].ravel(), groups[:, b].ravel()], axis=1))
    if not found:
        return np.zeros((0, 2), dtype=np.int64)
    return np.unique(np.concatenate(found), axis=0)


def edge_bond_lattice(
    tets: np.ndarray,
    points: np.ndarray,
    mask: np.ndarray,
    centers: np.ndarray,
    youngs_modulus: float | np.ndarray,
    tensile_strength: float | np.ndarray,
    stiffness_factor: float = STIFFNESS_FACTOR,
    strength_factor: float = STRENGTH_FACTOR,
) -> LatticeBonds:
    """The bonds of the converted tets in ``mask`` (module docstring).

    Args:
        tets: node ids of every tet, shape (M, 4).
        points: reference node positions [m], shape (N, 3) (volumes V_i).
        mask: True for the converted tets, shape (M,).
        centers: each tet's sphere centre [m], shape (M, 3) (rows outside ``mask`` unused).
        youngs_modulus: E per tet [Pa], scalar or shape (M,) (a bond takes the mean of its two tets').
        tensile_strength: T_f per tet [Pa], scalar or shape (M,) (a bond takes the smaller).
        stiffness_factor: κ [-]. strength_factor: S [-].

    Returns:
        The bonds, by tet pair.
    """
    tets = np.asarray(tets, dtype=np.int64)
    p = np.asarray(points, dtype=np.float64)
    pairs = edge_pairs(tets, mask)
    m = len(tets)
    young = np.broadcast_to(np.asarray(youngs_modulus, dtype=np.float64), (m,))
    strength = np.broadcast_to(np.asarray(tensile_strength, dtype=np.float64), (m,))
    x = p[tets]
    vol = np.abs(np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]))) / 6.0
    z = np.bincount(pairs.ravel(), minlength=m).astype(np.float64)
    i, j = pairs[:, 0], pairs[:, 1]
    vb = vol[i] / z[i] + vol[j] / z[j]
    c = np.asarray(centers, dtype=np.float64)
    length = np.linalg.norm(c[j] - c[i], axis=1)
    e = 0.5 * (young[i] + young[j])
    kn = stiffness_factor * e * vb / length**2
    area = vb / length
    tensile = kn * length * np.minimum(strength[i], strength[j]) / (strength_factor * e * area)
    return LatticeBonds(pairs, length, kn, np.zeros_like(kn), area, tensile, tensile.copy())
