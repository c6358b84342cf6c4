"""Bonds between the spheres of converted tets that make a rigid network with the continuum's bar-wave speed and
tensile strength (measured in tests/test_coupling.py), and their calibration on the mesh's own network.

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

Calibration on the mesh (what attach_conversion uses; the two constants above are the reference, kept where no test can
run). κ and S measured on Kuhn cells 2 across do not hold for every mesh: an unstructured Gmsh mesh's edge network
relaxes less (E_net = 0.77 to 0.91 of the affine κ E / 6, against 0.615), and with the Kuhn constants a fully converted
bar measured 1.07 to 1.22 sqrt(E/ρ) and 0.80 to 0.96 T_f (h = 0.025 to 0.04 m across 0.1 m); Kuhn cells 4 across gave
0.869 T_f. The affine stiffness is about the same on both meshes; what differs is the non-affine relaxation, so it is
measured on the mesh's own network: attach_conversion (warpdem.stages.multisphere.mesh_lattice_factors) pulls the bond
network of the tets that may convert (one or four spheres per tet, as the scene asks) in a virtual uniaxial test solved
statically (:func:`network_tension`: float64 matrix-free conjugate gradients, the ends held over max(L / 12, one cell)
as the bar test holds them, the sides free). Per unit κ E it gives the modulus m = σ / ε (σ the reaction over the
nominal cross-section volume / L, ε the strain of the middle half) and the largest bond strain per unit stress p, so
(:func:`calibrated_factors`) κ = 1 / m makes E_net = E and S = κ / p puts the first bond break at the nominal stress
T_f. A region of at most CALIBRATION_WHOLE tets is tested whole (a converted bar: its own network, ends and surface
included); a larger one through a bar of CALIBRATION_SAMPLE tets, 6 × 1 × 1 along its longest side, about its centre
(:func:`calibration_sample`), so attach stays fast at 1 M tets; the test takes the sample's largest edge-connected body
(:func:`largest_body`), and the whole mesh's network where the region's tets are scattered and make no body. Measured on
the 0.6 × 0.1 × 0.1 m bar (tests/test_coupling.py), calibrated: Kuhn cells 2 across 0.992 sqrt(E/ρ) and 0.987 T_f (0.978
and 1.010 with four spheres per tet), 4 across 0.995 and 1.001; Gmsh h = 0.04 m 1.001 and 0.997, 0.035 m 0.999 and
1.002, 0.03 m 0.986 and 0.999, 0.025 m 0.991 and 1.000 (four spheres per tet at 0.04 m: 1.005 and 0.996). The static
figures agree with the dynamic ones to about 2 %: the Kuhn constants above, measured dynamically, come back as κ = 9.63,
S = 1.108 (tests/test_lattice.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..tables import TET_EDGES

STIFFNESS_FACTOR = 9.76
"""Reference κ of k_b = κ E V_b / L_b² [-]: the affine 6 over the measured E_net / E = 0.615 of cubic Kuhn cells (attach
calibrates κ on the mesh; this one where no virtual test can run)."""

STRENGTH_FACTOR = 1.126
"""Reference S: bonds break at stretch L_b T_f / (S E) [-]; the measured peak stress of a Kuhn bar with S = 1, in units
of T_f (attach calibrates S on the mesh)."""


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


# ----------------------------------------------------------------------------------------------------------------
# Calibration on the mesh's own network (a virtual uniaxial test, solved statically)

CALIBRATION_WHOLE = 4_000
"""Regions of at most this many tets are tested whole, larger ones through a bar-shaped sample (calibration_sample)."""

CALIBRATION_SAMPLE = 2_304
"""Tets of the bar-shaped sample of a larger region: as many as a bar of 24 × 4 × 4 Kuhn cells."""

CALIBRATION_ASPECT = 6.0
"""Length over width of the bar-shaped sample (the converted-bar test's 12 × 2 × 2 cells)."""

CALIBRATION_RTOL = 1.0e-8
"""Relative residual ‖r‖ / ‖r₀‖ at which the virtual test's conjugate gradients stop [-] (float64)."""


@dataclass
class NetworkTension:
    """A bond network's response to a virtual uniaxial tension (:func:`network_tension`), per unit κ E.

    Attributes:
        modulus: E_net / (κ E), the nominal stress over the strain of the bar's middle half [-].
        peak_strain: the largest bond strain Δ_b / L_b over the nominal stress, times κ E [-].
        iterations: conjugate-gradient iterations taken.
    """

    modulus: float
    peak_strain: float
    iterations: int


def network_tension(
    centers: np.ndarray,
    pairs: np.ndarray,
    weight: np.ndarray,
    volume: float,
    bounds: np.ndarray,
    cell: float,
    strain: float = 1.0e-3,
    group: int = 1,
) -> NetworkTension | None:
    """Pull a bonded network statically along the longest side of its bounding box, as tests/test_coupling.py pulls
    a fully converted bar: the spheres within ``slab`` of either end are held (every component) and moved rigidly
    apart, the rest relax to equilibrium (normal springs k_b = weight_b per unit κ E; matrix-free conjugate
    gradients with a block-Jacobi preconditioner, float64; small strain, so linear).
    The modulus is the nominal stress (the reaction over volume / L) over the strain of the middle half (the slope
    of the displacement along the pull there, away from the held ends); the peak strain is over every bond.

    Args:
        centers: sphere centres [m], shape (n, 3). pairs: bonded sphere pairs, shape (B, 2).
        weight: k_b / (κ E) = V_b / L_b² [m], shape (B,). volume: the network's material volume [m³].
        bounds: the material's bounding box (low and high corner) [m], shape (2, 3): the pull is along its longest
            side, length L; the nominal cross-section is volume / L.
        cell: the tets' size (6 V̄)^(1/3) [m]; the held slabs are max(L / 12, cell) thick (the bar test holds its
            first and last of 12 cells).
        strain: the pull, the held ends' separation over L [-] (linear: the response does not depend on it).
        group: spheres g k … g k + g − 1 form one block of the preconditioner (4: a tet's four spheres, whose short
            in-tet bonds are the stiffest; n a multiple of g).

    Returns:
        The response, or None where there is no bar to pull (an end or the middle without spheres, no bond
        between them, or no equilibrium found).
    """
    c = np.asarray(centers, dtype=np.float64)
    i, j = pairs[:, 0], pairs[:, 1]
    lo, hi = np.asarray(bounds, dtype=np.float64)
    axis = int(np.argmax(hi - lo))
    x = c[:, axis] - lo[axis]  # measured from the material's end, as the bar test's held cell x < CELL
    span = float(hi[axis] - lo[axis])
    slab = max(span / 12.0, cell)
    held, pulled = x < slab, x > span - slab
    free = ~(held | pulled)
    middle = np.abs(x - 0.5 * span) < 0.25 * span
    if not (held.any() and pulled.any() and (middle & free).sum() >= 2) or len(pairs) == 0:
        return None
    length = np.linalg.norm(c[j] - c[i], axis=1)
    normal = (c[j] - c[i]) / length[:, None]
    n = len(c)

    def force(u: np.ndarray) -> np.ndarray:
        """Spring forces on the spheres of displacement u, −K u, shape (n, 3)."""
        f = (weight * np.einsum("bk,bk->b", u[j] - u[i], normal))[:, None] * normal
        return np.stack([np.bincount(i, f[:, k], n) - np.bincount(j, f[:, k], n) for k in range(3)], axis=1)

    # Block-Jacobi preconditioner: the stiffness of each group's free spheres among themselves (Σ_b k_b n_b n_bᵀ on
    # the diagonal, −k_b n_b n_bᵀ between two of a group); the held spheres' rows are the identity (their residual
    # is 0), and a small ridge keeps a loose sphere's block invertible.
    g = group
    size = 3 * g
    ab = np.arange(3)
    outer = (weight[:, None, None] * normal[:, :, None] * normal[:, None, :]).reshape(-1, 9)

    def entries(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Flat indices of the 3 × 3 sub-blocks (sphere a's rows, sphere b's columns) in (n / g) blocks."""
        rows = 3 * (a % g)[:, None, None] + ab[None, :, None]
        cols = 3 * (b % g)[:, None, None] + ab[None, None, :]
        return ((a // g)[:, None, None] * size * size + rows * size + cols).reshape(-1, 9)

    same = (i // g == j // g) & free[i] & free[j]
    index = np.concatenate([entries(i, i), entries(j, j), entries(i[same], j[same]), entries(j[same], i[same])])
    value = np.concatenate([outer, outer, -outer[same], -outer[same]])
    keep = np.concatenate([free[i], free[j], np.ones(2 * int(same.sum()), dtype=bool)])
    block = np.bincount(index[keep].ravel(), value[keep].ravel(), n // g * size * size).reshape(n // g, size, size)
    diagonal = np.einsum("kii->ki", block)  # a view: the ridge and the held spheres' identity are written through it
    scale = diagonal.mean(axis=1, keepdims=True)
    diagonal += 1e-9 * (scale + scale.max())
    diagonal[~free.reshape(-1, g).repeat(3, axis=1)] = 1.0
    inverse = np.linalg.inv(block)

    def precondition(residual: np.ndarray) -> np.ndarray:
        return np.einsum("kij,kj->ki", inverse, residual.reshape(-1, size)).reshape(n, 3)

    u = np.zeros((n, 3))
    u[pulled, axis] = strain * span
    r = force(u)
    r[~free] = 0.0
    z = precondition(r)
    p, rz = z.copy(), float(np.sum(r * z))
    r0 = float(np.sqrt(np.sum(r * r)))
    du = np.zeros((n, 3))
    iterations = 0
    while r0 > 0.0 and float(np.sqrt(np.sum(r * r))) > CALIBRATION_RTOL * r0:
        if iterations >= 20 * n + 100:
            return None
        kp = -force(p)
        kp[~free] = 0.0
        alpha = rz / float(np.sum(p * kp))
        du += alpha * p
        r -= alpha * kp
        z = precondition(r)
        rz, rz_old = float(np.sum(r * z)), rz
        p = z + (rz / rz_old) * p
        iterations += 1
    u += du
    stress = -float(force(u)[pulled, axis].sum()) / (volume / span)  # the pull's reaction / nominal cross-section
    inner = middle & free
    slope = np.polyfit(x[inner], u[inner, axis], 1)[0]  # the strain of the middle half, away from the held ends
    strain = np.einsum("bk,bk->b", u[j] - u[i], normal) / length
    if not (stress > 0.0 and slope > 0.0):
        return None
    return NetworkTension(modulus=stress / slope, peak_strain=float(strain.max()) / stress, iterations=iterations)


def calibration_sample(
    centroids: np.ndarray, mask: np.ndarray, whole: int = CALIBRATION_WHOLE, size: int = CALIBRATION_SAMPLE
) -> np.ndarray:
    """The tets the virtual tension test takes, ids ascending, int64: all of ``mask`` when they are at most
    ``whole``; else a bar along the longest side of their bounding box, about its centre: the ``size`` tets of
    ``mask`` nearest that centre in the distance max(|d_long| / CALIBRATION_ASPECT, |d_other|) (a box 6 × 1 × 1;
    nearest, so a region that is not convex still gives ``size`` tets)."""
    ids = np.nonzero(np.asarray(mask, dtype=bool))[0]
    if len(ids) <= whole:
        return ids
    c = np.asarray(centroids, dtype=np.float64)[ids]
    lo, hi = c.min(axis=0), c.max(axis=0)
    scale = np.ones(3)
    scale[int(np.argmax(hi - lo))] = 1.0 / CALIBRATION_ASPECT
    distance = np.max(np.abs(c - 0.5 * (lo + hi)) * scale, axis=1)
    return np.sort(ids[np.argpartition(distance, size - 1)[:size]])


def largest_body(pairs: np.ndarray, n: int) -> np.ndarray:
    """True for the items of the largest connected component of the graph ``pairs`` on ``n`` items (an item without
    pairs is a component of its own), shape (n,), bool. Labels by repeated minimum over the pairs (as many sweeps as
    the graph's diameter; the calibration's samples are a few dozen across)."""
    label = np.arange(n)
    if n == 0:
        return np.zeros(0, dtype=bool)
    i, j = pairs[:, 0], pairs[:, 1]
    while True:
        low = np.minimum(label[i], label[j])
        new = label.copy()
        np.minimum.at(new, i, low)
        np.minimum.at(new, j, low)
        new = new[new]  # jump to the label's own label: fewer sweeps
        if np.array_equal(new, label):
            return label == np.argmax(np.bincount(label, minlength=n))
        label = new


def calibrated_factors(tension: NetworkTension) -> tuple[float, float]:
    """(κ, S) that give a network with ``tension``'s response the continuum's E and make its first bond break at the
    nominal stress T_f: κ = 1 / modulus (E_net = κ E modulus = E) and S = κ / peak_strain (a bond breaks at the strain
    T_f / (S E), reached at the nominal stress σ = κ E T_f / (S E peak_strain) = T_f)."""
    kappa = 1.0 / tension.modulus
    return kappa, kappa / tension.peak_strain
