"""Several spheres per converted tet (``spheres_per_tet`` = 4; scene key ``[conversion] spheres_per_tet``): the
sub-lattice's geometry, bonds and calibration, and the launches the conversion pass (warpdem.stages.conversion) makes in
place of its one-sphere kernels (kernels/multisphere.py).

Design. A tet converts into four spheres, one in each corner sub-tet of its 1:8 midpoint subdivision. Why these:

- The corner sub-tet at node a is the tet scaled by 1/2 about x_a, so its centroid s_a = (x_a + c) / 2 (c the
  tet's centroid) lies h_k / 8 from each of its faces (h_k the tet's heights). A sphere of radius min_k h_k / 8
  (less a float32 margin, as for one sphere) at s_a lies inside its corner sub-tet; the corner sub-tets of a tet have
  disjoint interiors and lie inside it, so no two spheres of one tet, of neighbouring tets (converted in the same
  pass or earlier, one or the other way) and no remaining tet face overlap at birth: no energy from spurious
  overlaps. Each sphere touches its sub-tet's nearest face (the 8-ulp margin apart), half the one-sphere radius.
- Mass: sphere a takes the lumped share ρ V₀ / 4 node a held of the tet (the lumped-mass model already splits the
  tet's mass that way), so the four sum to exactly the ρ V₀ the nodes lose (×0.25 is exact in binary).
- Velocity: the tet's (linear) velocity field at s_a, v(s_a) = (v_a + v̄) / 2 with v̄ the centroid's (the nodes'
  mean). The s_a average to c with equal weights, so Σ_a (m/4) v(s_a) = m v̄ = Σ_a (m/4) v_a: linear momentum
  is conserved exactly, as with one sphere (to float32 rounding of the stored velocities).
- Spin: ω, the axial vector of the antisymmetric part of the velocity gradient, on every sphere.
- Angular momentum. The orbital part m c × v̄ is conserved exactly. Of the tet's internal part about its centroid,
  H = Σ_a (m/4) r_a × (v_a − v̄) (r_a = x_a − c), the spheres' orbits carry exactly H / 4 (s_a − c = r_a / 2 and
  v(s_a) − v̄ = (v_a − v̄) / 2), their spins 4 · (2/5)(m/4) ρ_s² ω (ρ_s the sphere radius). A conversion therefore
  changes the angular momentum by ΔH = (3/4) H − (2/5) m ρ_s² ω, bounded by |ΔH| ≤ ((3/4) ‖J‖₂ + (2/5) m ρ_s²)
  |ω| for a rigidly spinning tet (H = J ω, J = Σ_a (m/4)(|r_a|² 1 − r_a r_aᵀ)): the orbits keep a quarter of the
  J ω that one sphere per tet loses (tests/test_multisphere.py checks the exact formula). The energy of the motion
  neither the orbits nor the spins carry, (m/8) Σ_a (3/4)|v_a − v̄|² less the spins', is booked as released.
- Eight (every sub-tet of the 1:8 subdivision, each ρ V₀ / 8 at its centroid, which would conserve momentum as
  well) is not offered: the central octahedron's four tets depend on which of its diagonals splits it, are not
  similar to the parent (smaller in-radii, so smaller spheres), and would need their own bond rule and calibration.

Bonds (the edge network of warpdem.stages.lattice carried to the sub-lattice). Sphere a of tet t is bonded to the other
three spheres of its tet (a rigid tetrahedron: 6 bonds, rest lengths the tet's edges / 2) and to sphere a' of every
converted tet t' that shares an edge through node a (t' holds that node as a'): the spheres around a node form a
cluster, whose bonds (c_t − c_t') / 2 are the one-sphere lattice's halved. As a body-bar framework each tet's four
spheres are one rigid body (6 degrees of freedom) with 3 bars to each face neighbour and 2 to each further edge
neighbour, 17 per tet in a 6³-cell Kuhn box (≥ 6 needed; Z_s = 11.5 bonds per sphere on average), so the network is
rigid with normal springs alone (k_s = 0); nothing crosses a crack (split nodes are different nodes). Stiffness k_b = κ₄
E V_b / L_b², V_b = V_s / Z_s + V_s' / Z_s' with V_s = V_t / 4 and Z_s = 3 + the tets sharing an edge through its node
(over all live tets, so a bond's stiffness does not depend on which neighbours have converted yet): Σ_b V_b = V, the
affine energy equivalence gives κ = 6 for isotropic bond directions (warpdem.stages.lattice), and κ₄ =
SUB_STIFFNESS_FACTOR is that over the measured E_net / E. Strength: a bond breaks at the stretch L_b T_f / (S₄ E),
tensile strength (κ₄ / S₄) T_f per unit area A_b = V_b / L_b. Both factors were measured on a fully converted bar of
cubic Kuhn cells, 12 long and 2 × 2 across (tests/test_coupling.py, parametrized by the spheres per tet): with κ = 6 the
bar-wave speed is 0.658 sqrt(E/ρ) (E_net = 0.432 E: the sub-lattice relaxes non-affinely more than the one-sphere
network's 0.615), so κ₄ = 6 / 0.432 = 13.88; with S = 1 the nominal stress at the first bond break is 0.768 T_f (the
cluster and in-tet bonds that carry the load stretch more than the bar), and S₄ = 0.775 puts it at T_f. Calibrated, that
bar measures 1.005 sqrt(E/ρ) and 1.002 T_f; 3 × 3 cells across, 1.033 sqrt(E/ρ) and 0.905 T_f (one sphere per tet there:
0.990 and 0.891). After the first bond breaks the four-sphere network still carries load through its other bonds, so the
strength is taken at the onset of breaking (tests/test_coupling.py says why the later peak is dynamic).
These are the reference factors (:func:`lattice_factors`); attach_conversion calibrates κ₄ and S₄ on the mesh's own
sub-lattice (:func:`mesh_lattice_factors`, warpdem.stages.lattice "Calibration on the mesh"): that Kuhn bar then
measures 0.978 sqrt(E/ρ) and 1.010 T_f.

Couplings (warpdem.stages.coupling): sphere a of a new tet is tied to every still-active tet sharing an edge through
node a (the tets it would bond to), at its barycentric coordinates there, with the stiffness rule k = k_n min(1, 2 / (1
+ m_s Σ N² / m_a)), k_n the bond it would have with that tet's sphere at the node, (x_a + c_t') / 2.

Stable step: the sub-spheres weigh a quarter and their bonds are half as long, so the step of the bonded spheres is
about half the one-sphere one (:func:`sub_critical_step`; attach_conversion refuses a larger dt).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import multisphere as kms
from ..model import Model, State
from ..tables import TET_EDGES
from .lattice import (
    STIFFNESS_FACTOR,
    STRENGTH_FACTOR,
    calibrated_factors,
    calibration_sample,
    edge_bond_lattice,
    edge_pairs,
    largest_body,
    network_tension,
)

SPHERES_PER_TET = (1, 4)
"""The values ``spheres_per_tet`` may take."""

SUB_STIFFNESS_FACTOR = 13.88
"""κ₄ of the sub-lattice's k_b = κ₄ E V_b / L_b² [-]: 6 over the measured E_net / E = 0.432 (module docstring)."""

SUB_STRENGTH_FACTOR = 0.775
"""S₄: sub-lattice bonds break at the stretch L_b T_f / (S₄ E) [-]; the measured stress at the first bond break with
S = 1, over T_f (0.768; 0.775 centres the calibrated bar on T_f, module docstring)."""


def lattice_factors(spheres_per_tet: int) -> tuple[float, float]:
    """(κ, S) of the bond network for ``spheres_per_tet`` spheres per tet (1: warpdem.stages.lattice; 4: this
    module)."""
    return (STIFFNESS_FACTOR, STRENGTH_FACTOR) if spheres_per_tet == 1 else (SUB_STIFFNESS_FACTOR, SUB_STRENGTH_FACTOR)


@dataclass
class SubLattice:
    """The sub-lattice of a set of tets (host reference; spheres numbered 4 t + a, a the local node).

    Attributes:
        centers: s_a = (x_a + c) / 2 [m], shape (4 M, 3) (rows of tets outside the set unused).
        pairs: sphere pairs (i < j) bonded, sorted, shape (B, 2), int64.
        volume: V_b = V_s / Z_s + V_s' / Z_s' [m³], shape (B,).
        length: centre distance L_b [m], shape (B,).
        degree: Z_s = 3 + the tets sharing an edge through the sphere's node, over ``live``, shape (4 M,).
    """

    centers: np.ndarray
    pairs: np.ndarray
    volume: np.ndarray
    length: np.ndarray
    degree: np.ndarray


def _inter_pairs(tets: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Sphere pairs (4 t + a, 4 t' + a') of tets in ``mask`` sharing an edge through their common node, shape (B, 2)."""
    tp = edge_pairs(tets, mask)
    same = tets[tp[:, 0]][:, :, None] == tets[tp[:, 1]][:, None, :]  # (B, 4, 4): node a of t is node a' of t'
    k, a, a2 = np.nonzero(same)
    return np.stack([4 * tp[k, 0] + a, 4 * tp[k, 1] + a2], axis=1)


def sub_lattice(tets: np.ndarray, points: np.ndarray, live: np.ndarray, bonded: np.ndarray) -> SubLattice:
    """The sub-lattice bonds among the spheres of the tets in ``bonded`` (module docstring), each sphere's Z_s counted
    over the tets in ``live`` (float64, the reference or any configuration ``points``).

    Args:
        tets: node ids, shape (M, 4). points: node positions [m], shape (N, 3).
        live: bool per tet, the network Z_s counts. bonded: bool per tet (a subset of ``live``), the spheres bonded.
    """
    tets = np.asarray(tets, dtype=np.int64)
    live, bonded = np.asarray(live, dtype=bool), np.asarray(bonded, dtype=bool)
    x = np.asarray(points, dtype=np.float64)[tets]
    centers = (0.5 * (x + x.mean(axis=1, keepdims=True))).reshape(-1, 3)
    vol = np.abs(np.linalg.det(x[:, 1:] - x[:, :1])) / 6.0
    degree = 3 + np.bincount(_inter_pairs(tets, live).ravel(), minlength=4 * len(tets))
    ids = np.nonzero(bonded)[0]
    intra = (4 * ids[:, None, None] + TET_EDGES[None]).reshape(-1, 2)
    pairs = np.unique(np.sort(np.concatenate([intra, _inter_pairs(tets, bonded)]), axis=1), axis=0)
    share = np.repeat(0.25 * vol, 4) / degree
    return SubLattice(
        centers=centers,
        pairs=pairs,
        volume=share[pairs[:, 0]] + share[pairs[:, 1]],
        length=np.linalg.norm(centers[pairs[:, 1]] - centers[pairs[:, 0]], axis=1),
        degree=degree,
    )


def sub_critical_step(
    tets: np.ndarray, points: np.ndarray, density: np.ndarray, modulus: np.ndarray, converts: np.ndarray
) -> tuple[float, int]:
    """Stable step [s] of the bonded sub-spheres of the tets that may convert, and the tet that sets it (-1: none):
    ω² = Σ_b k_b / m over each sphere's bonds (or couplings, k ≤ k_b) in the fully converted network, dt = 2 / ω
    (as warpdem.stages.conversion.conversion_critical_step does for one sphere).

    Args:
        tets: node ids of the live tets, shape (M, 4). points: reference node positions [m], shape (N, 3).
        density: ρ per tet [kg/m³], shape (M,). modulus: κ₄ E per tet (``bond_modulus``) [Pa], shape (M,).
        converts: bool per tet, those that may convert.
    """
    if not np.any(converts):
        return math.inf, -1
    m = len(tets)
    every = np.ones(m, dtype=bool)
    lat = sub_lattice(tets, points, every, every)
    owner = lat.pairs // 4
    kb = 0.5 * (modulus[owner[:, 0]] + modulus[owner[:, 1]]) * lat.volume / lat.length**2
    stiffness = np.bincount(lat.pairs.ravel(), weights=np.repeat(kb, 2), minlength=4 * m).reshape(m, 4).max(axis=1)
    x = np.asarray(points, dtype=np.float64)[np.asarray(tets, dtype=np.int64)]
    mass = 0.25 * density * np.abs(np.linalg.det(x[:, 1:] - x[:, :1])) / 6.0
    omega2 = np.where(converts, stiffness / mass, 0.0)
    k = int(np.argmax(omega2))
    return float(2.0 / math.sqrt(omega2[k])), k


# ----------------------------------------------------------------------------------------------------------------
# The pass's counts (warpdem.stages.conversion.ConversionPass calls this when model.spheres_per_tet == 4; ``work`` is
# the pass, whose scratch arrays it uses; the pass launches kernels/multisphere.py's spawn, bond and coupling kernels
# itself, with the same arguments as its one-sphere ones and ``sub_degree`` for ``degree``).


def count_sub_links(model: Model, state: State, work) -> None:
    """Each tet's Z per node over the stars of all live tets (``work.sub_degree``), and the bonds and couplings each
    converting tet's spheres will own (``work.bonds``, ``work.couplings``). Launches only."""
    m, s, d = model, state, model.device
    stars = work.full_stars.csr()
    wp.launch(
        kms.sub_edge_degree_kernel,
        dim=m.tet_capacity,
        inputs=[m.tet_nodes, s.tet_count, *stars],
        outputs=[work.sub_degree],
        device=d,
    )
    wp.launch(
        kms.count_sub_links_kernel,
        dim=m.tet_capacity,
        inputs=[m.tet_nodes, s.tet_count, s.tet_active, s.tet_sphere, work.flag, *stars],
        outputs=[work.bonds, work.couplings],
        device=d,
    )


def mesh_lattice_factors(
    tets: np.ndarray, points: np.ndarray, mask: np.ndarray, spheres_per_tet: int
) -> tuple[float, float, int]:
    """(κ, S) of ``spheres_per_tet`` spheres per tet calibrated on the mesh's own network (warpdem.stages.lattice's
    "Calibration on the mesh"), and the tets the virtual test took (0: none, the reference factors returned).

    The test takes the largest edge-connected body of the sample (warpdem.stages.lattice.calibration_sample) of the tets
    that may convert; when that body holds under half the sample (scattered tets, not a body to pull), the sample is
    drawn from every tet instead, the same mesh's network.

    Args:
        tets: node ids, shape (M, 4). points: reference node positions [m], shape (N, 3).
        mask: bool per tet, the tets that may convert.
    """
    tets = np.asarray(tets, dtype=np.int64)
    p = np.asarray(points, dtype=np.float64)
    centroids = p[tets].mean(axis=1)
    for region in (np.asarray(mask, dtype=bool), np.ones(len(tets), dtype=bool)):
        ids = calibration_sample(centroids, region)
        body = largest_body(edge_pairs(tets[ids], np.ones(len(ids), dtype=bool)), len(ids))
        if len(ids) >= 2 and 2 * body.sum() >= len(ids):
            ids = ids[body]
            break
    else:
        return (*lattice_factors(spheres_per_tet), 0)
    sample = tets[ids]
    every = np.ones(len(ids), dtype=bool)
    x = p[sample]
    volume = np.abs(np.linalg.det(x[:, 1:] - x[:, :1])) / 6.0
    if spheres_per_tet == 1:
        lat = edge_bond_lattice(sample, p, every, x.mean(axis=1), 1.0, 1.0, 1.0, 1.0)
        centers, pairs, weight = x.mean(axis=1), lat.pairs, lat.kn  # κ = E = 1: k_b = V_b / L_b²
    else:
        sub = sub_lattice(sample, p, every, every)
        centers, pairs, weight = sub.centers, sub.pairs, sub.volume / sub.length**2
    corners = x.reshape(-1, 3)
    bounds = np.stack([corners.min(axis=0), corners.max(axis=0)])
    cell = float(np.cbrt(6.0 * volume.mean()))
    tension = network_tension(centers, pairs, weight, float(volume.sum()), bounds, cell, group=spheres_per_tet)
    if tension is None:
        return (*lattice_factors(spheres_per_tet), 0)
    return (*calibrated_factors(tension), len(ids))
