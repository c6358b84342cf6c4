"""The blended DEM/FEM overlap band of the CIMNE adaptive scheme (adaptive_dem_fem_blast.txt §4, eqs. 8–9, after
Xiao & Belytschko 2004): an option of FEM→DEM conversion (``Model.band_width`` ≥ 1) beside the tie of
warpdem.stages.coupling. A host pass between steps, run by ``Simulation`` right after each conversion pass (and so
after ``start_as_spheres``).

Eq. 8 blends the virtual work, δW = α δW_F + (1 − α) δW_D, α = 1 on the continuum, 0 in the DEM region, linear across
the band. Here α is constant per tet, from its layer d = 1, 2, ... (edge neighbours: the adjacency of the bonds and
of the tie) counted from the still-continuous tets:

    α_t = 1 − d / (w + 1) for d ≤ w (the band, w = ``band_width`` tet layers), 0 for d > w,

so a band of w layers steps α through w + 1 equal steps between the continuum (1) and the DEM region (0).

What a band tet is. A converted tet with α > 0 stays an active FEM element whose forces, strain energy and lumped mass
stand for the volume α V₀ (``Model.tet_band_volume``: the tet kernels read it in place of V₀, so the Cosserat point
forces, the bulk viscosity and the strain energy all scale by α, and its nodes hold α ρ V₀ / 4); its sphere holds
(1 − α) ρ V₀, and each bond k_n, k_s and area (so a bond still breaks at the same stretch) is scaled by
1 − (α_i + α_j) / 2, eq. 8's weight at the bond's midpoint. So Σ α m_F + (1 − α) m_D = ρ V₀ for every tet: mass is
conserved. The band's spheres are tied to their own tet's interpolation, eq. 9's u_D − N_F u_F = 0, by the penalty
springs of warpdem.stages.coupling (one per sphere, at its current barycentric coordinates, born relaxed: its
float32 gap at birth is its rest, kernels/coupling.py ``coupling_rest_kernel``), of
stiffness ``band_penalty`` × the coupling rule (coupling_stiffness) at the weighted masses. A tet deeper than w
(α = 0) is dropped as the tie drops every converted tet: inactive, its tie released. As the continuum shrinks, a tet's
layer only grows, so α only falls: a pass only moves mass from nodes to spheres.

Conservation. The pass moves (α_old − α_new) ρ V₀ / 4 from each node of a tet to its sphere with the node's velocity
(the node keeps its own; the sphere's is the mass-weighted mean): linear momentum is conserved exactly, in float64
before the float32 stores. What the pass changes without work — the kinetic energy of the moved mass about the
sphere's velocity, the strain energy of the weights that fell, the bonds' stored energy at their new stiffness — is
booked on ``released_conversion`` with the rest of the conversion pass (its coupling springs and shadow term are
booked by ``Simulation._convert`` around the whole pass), so the books close across it.

Limits. One sphere per tet (``spheres_per_tet`` = 1). Pressure faces of band tets keep their full load on nodes that
hold α of their mass. Nodal fracture reads the tets' forces at V₀, not α V₀, in eq. 4's f_c (the band and fracture
together are not checked).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import coupling as kcp
from ..model import COUPLING_FIELDS, Model, State
from ..tables import TET_EDGES
from .coupling import coupling_stiffness, material_point
from .energy import energy_balance


@dataclass
class BandSnapshot:
    """What the band pass needs of the state before a conversion pass (host copies).

    Attributes:
        alpha: α of every live tet before the pass (1 unconverted, 0 inactive), shape (tet_count,), float64.
        node_qd: node velocities [m/s], shape (node_capacity, 3).
        node_motion: node motion flags, shape (node_capacity,).
        node_inv_mass: 1/m [1/kg] (0 where held), shape (node_capacity,).
        particle_count: live spheres before the pass.
    """

    alpha: np.ndarray
    node_qd: np.ndarray
    node_motion: np.ndarray
    node_inv_mass: np.ndarray
    particle_count: int


def tet_alpha(model: Model, state: State) -> np.ndarray:
    """α of every live tet now [-], shape (tet_count,), float64: tet_band_volume / V₀ where active, 0 where not."""
    nt = int(state.tet_count.numpy()[0])
    active = state.tet_active.numpy()[:nt] != 0
    v0 = model.tet_volume.numpy()[:nt].astype(np.float64)
    if model.tet_band_volume is None:
        return active.astype(np.float64)
    return np.where(active, model.tet_band_volume.numpy()[:nt].astype(np.float64) / v0, 0.0)


def snapshot(model: Model, state: State) -> BandSnapshot:
    """The :class:`BandSnapshot` of the state now (call before the conversion pass)."""
    return BandSnapshot(
        alpha=tet_alpha(model, state),
        node_qd=state.node_qd.numpy().astype(np.float64),
        node_motion=model.node_motion.numpy().copy(),
        node_inv_mass=model.node_inv_mass.numpy().copy(),
        particle_count=int(state.particle_count.numpy()[0]),
    )


def edge_incidence(tet_nodes: np.ndarray) -> np.ndarray:
    """Edge id of each of the six edges of each tet, shape (T, 6), int64: tets that share an edge (two nodes) share
    its id."""
    pairs = np.sort(tet_nodes[:, np.asarray(TET_EDGES)], axis=2).reshape(-1, 2).astype(np.int64)
    _, ids = np.unique(pairs[:, 0] * (int(pairs.max(initial=0)) + 1) + pairs[:, 1], return_inverse=True)
    return ids.reshape(-1, 6)


def band_layers(incidence: np.ndarray, continuum: np.ndarray, converted: np.ndarray, width: int) -> np.ndarray:
    """Layer d of each converted tet counted from the continuum through edge neighbours (1: shares an edge with a
    continuum tet), up to ``width``; 0 on the continuum, width + 1 beyond (and where no path of converted tets leads).

    Args:
        incidence: :func:`edge_incidence`, shape (T, 6).
        continuum: bool per tet, the still-continuous tets, shape (T,).
        converted: bool per tet, shape (T,).
        width: w, the band's layers (>= 1).
    """
    layer = np.full(len(continuum), width + 1, dtype=np.int64)
    layer[continuum] = 0
    frontier = continuum.copy()
    edges = int(incidence.max(initial=-1)) + 1
    for d in range(1, width + 1):
        hit = np.zeros(edges, dtype=bool)
        hit[incidence[frontier].ravel()] = True
        frontier = hit[incidence].any(axis=1) & converted & (layer > width)
        layer[frontier] = d
    return layer


def band_alpha(layer: np.ndarray, converted: np.ndarray, width: int) -> np.ndarray:
    """α = 1 − d / (w + 1) on the band (d ≤ w), 0 deeper, 1 on the unconverted tets [-] (eq. 8, linear in layers)."""
    alpha = np.where(layer <= width, 1.0 - layer / (width + 1.0), 0.0)
    return np.where(converted, alpha, 1.0)


def apply_band(model: Model, state: State, before: BandSnapshot, incidence: np.ndarray) -> float:
    """Re-weight the band after a conversion pass (module docstring): α of every converted tet from its layer, the
    tets' volumes, node masses, spheres' masses and velocities, the bonds' stiffness and the band's couplings. Books
    what it changes without work on ``energy_released_conversion`` and returns it [J]. Host side; reads back and
    writes the arrays in place (between steps).

    Args:
        before: the snapshot taken before the pass.
        incidence: :func:`edge_incidence` of the live tets.

    Raises:
        ValueError: the coupling slots cannot hold the band's couplings (Simulation grows them first to the live
            couplings plus one per new sphere, which always holds them).
    """
    m, s = model, state
    nt = int(s.tet_count.numpy()[0])
    npart = int(s.particle_count.numpy()[0])
    nn = int(s.node_count.numpy()[0])
    width = m.band_width

    tet_nodes = m.tet_nodes.numpy()[:nt]
    v0 = m.tet_volume.numpy()[:nt].astype(np.float64)
    tet_sphere = s.tet_sphere.numpy()[:nt]
    converted = tet_sphere >= 0
    active = s.tet_active.numpy()[:nt] != 0
    continuum = ~converted & active
    fresh = converted & (tet_sphere >= before.particle_count)
    old_alpha = before.alpha.copy()
    old_alpha[fresh] = 1.0  # converted in this pass: the FEM held all of it before
    alpha = band_alpha(band_layers(incidence, continuum, converted, width), converted, width)
    alpha = np.where(converted | active, alpha, 0.0)  # an inactive unconverted tet (never here) stays out
    alpha = np.minimum(alpha, old_alpha)  # α only falls (a layer only grows); guards rounding of the stored ratio

    table = m.tet_material_table.numpy()
    mat = m.tet_material.numpy()[:nt]
    full = table["density"][mat].astype(np.float64) * v0  # ρ V₀ [kg]
    damping = table["alpha"][mat].astype(np.float64)
    live = np.arange(m.node_capacity) < nn

    # The state the conversion pass booked: its new tets' ρ V₀ / 4 gone from their nodes, the band as it was (its
    # re-lumping counted the active band tets at V₀, which nothing booked).
    booked = np.zeros(m.node_capacity)
    np.add.at(booked, tet_nodes.ravel(), np.repeat(0.25 * np.where(fresh, 0.0, before.alpha) * full, 4))
    m.node_mass.assign(np.where(live, booked, m.node_mass.numpy()).astype(np.float32))
    e_before = _mechanical(m, s)

    # Nodes: Σ α ρ V₀ / 4 over the tets; they keep the velocity they had (mass only leaves them).
    node_mass = np.zeros(m.node_capacity)
    node_damp = np.zeros(m.node_capacity)
    np.add.at(node_mass, tet_nodes.ravel(), np.repeat(0.25 * alpha * full, 4))
    np.add.at(node_damp, tet_nodes.ravel(), np.repeat(0.25 * alpha * full * damping, 4))
    has = live & (node_mass > 0.0)
    qd = np.where(has[:, None], before.node_qd, 0.0)
    held = before.node_inv_mass == 0.0
    inv = np.where(has & ~held, 1.0 / np.where(has, node_mass, 1.0), 0.0)
    motion = np.where(has, before.node_motion, np.where(live, 1, before.node_motion))
    m.node_mass.assign(np.where(live, node_mass, m.node_mass.numpy()).astype(np.float32))
    m.node_inv_mass.assign(np.where(live, inv, m.node_inv_mass.numpy()).astype(np.float32))
    m.node_damping.assign(np.where(has, node_damp / np.where(has, node_mass, 1.0), 0.0).astype(np.float32))
    m.node_motion.assign(motion.astype(np.int32))
    s.node_qd.assign(np.where(live[:, None], qd, s.node_qd.numpy()).astype(np.float32))

    # Spheres: (1 − α) ρ V₀, momentum (1 − α_old) ρ V₀ v_s + (α_old − α) ρ V₀ / 4 Σ_a v_a.
    pm = m.particle_mass.numpy().astype(np.float64)
    pinv = m.particle_inv_mass.numpy()
    pinert = m.particle_inv_inertia.numpy().astype(np.float64)
    pqd = s.particle_qd.numpy().astype(np.float64)
    tets = np.flatnonzero(converted)
    sph = tet_sphere[tets]
    moved = (old_alpha[tets] - alpha[tets]) * full[tets]
    new_mass = (1.0 - alpha[tets]) * full[tets]
    held_mass = np.where(fresh[tets], 0.0, (1.0 - old_alpha[tets]) * full[tets])
    node_v = before.node_qd[tet_nodes[tets]].mean(axis=1)
    momentum = held_mass[:, None] * pqd[sph] + moved[:, None] * node_v
    pqd[sph] = momentum / new_mass[:, None]
    pinert[sph] *= pm[sph] / new_mass  # I = 2/5 m r²: 1/I scales as 1/m
    pm[sph] = new_mass
    pinv = pinv.astype(np.float64)
    pinv[sph] = np.where(pinv[sph] != 0.0, 1.0 / new_mass, 0.0)
    m.particle_mass.assign(pm.astype(np.float32))
    m.particle_inv_mass.assign(pinv.astype(np.float32))
    m.particle_inv_inertia.assign(pinert.astype(np.float32))
    s.particle_qd.assign(pqd.astype(np.float32))

    # Bonds: k_n, k_s, area and held energy × (1 − ᾱ_new) / (1 − ᾱ_old), ᾱ the mean of the two spheres' α.
    sphere_alpha = np.zeros(max(npart, 1))
    sphere_old = np.zeros(max(npart, 1))
    sphere_alpha[sph] = alpha[tets]
    sphere_old[sph] = np.where(fresh[tets], 1.0, old_alpha[tets])
    nb = int(s.bond_count.numpy()[0])
    if nb:
        bi, bj = s.bond_i.numpy()[:nb], s.bond_j.numpy()[:nb]
        born = (bi >= before.particle_count) | (bj >= before.particle_count)
        weight_old = np.where(born, 1.0, 1.0 - 0.5 * (sphere_old[bi] + sphere_old[bj]))
        weight = 1.0 - 0.5 * (sphere_alpha[bi] + sphere_alpha[bj])
        ratio = np.ones(m.bond_capacity)
        ratio[:nb] = weight / weight_old
        for name in ("bond_kn", "bond_ks", "bond_area"):
            a = getattr(s, name)
            a.assign((a.numpy() * ratio).astype(np.float32))
        prev = s.bond_energy_prev.numpy()
        s.bond_energy_prev.assign((prev * ratio[:, None]).astype(np.float32))

    # Tets: active where α > 0, α V₀ for the FEM forces; a band tet never converts again.
    tet_active = s.tet_active.numpy()
    tet_active[:nt] = np.where(converted, (alpha > 0.0).astype(np.int32), tet_active[:nt])
    s.tet_active.assign(tet_active)
    vol = np.zeros(m.tet_capacity, dtype=np.float32)
    vol[:nt] = alpha * v0
    m.tet_band_volume.assign(vol)
    may = m.tet_may_convert.numpy()
    may[:nt] = np.where(converted, 0, may[:nt])
    m.tet_may_convert.assign(may)

    _write_band_couplings(m, s, tets[alpha[tets] > 0.0], alpha)
    released = e_before - _mechanical(m, s)
    s.energy_released_conversion.assign(s.energy_released_conversion.numpy() + released)
    return released


def _write_band_couplings(m: Model, s: State, band_tets: np.ndarray, alpha: np.ndarray) -> None:
    """The couplings after the pass: each band tet's sphere tied to its own tet (eq. 9); ties that hold on from an
    earlier pass keep their state, new ones are born relaxed; the tie's couplings the conversion kernels wrote (to
    edge neighbours) and those of dropped tets go."""
    n = int(s.coupling_count.numpy()[0])
    host = {name: getattr(s, name).numpy()[:n] for name in COUPLING_FIELDS}
    tet_sphere = s.tet_sphere.numpy()
    own = host["coupling_particle"] == tet_sphere[host["coupling_tet"]]
    keep = own & np.isin(host["coupling_tet"], band_tets)
    new = np.setdiff1d(band_tets, host["coupling_tet"][keep])
    count = int(keep.sum()) + len(new)
    if count > m.coupling_capacity:
        raise ValueError(f"apply_band: {count} band couplings for {m.coupling_capacity} slots")
    particle = tet_sphere[new]
    if len(new):
        bary = np.atleast_2d(material_point(m, new, s.particle_q.numpy()[particle], s))
        nodes = m.tet_nodes.numpy()[new]
        k = m.band_penalty * coupling_stiffness(
            m.particle_mass.numpy()[particle].astype(np.float64),
            _reference_kn(m, s, particle, alpha, new),
            m.node_mass.numpy()[nodes].astype(np.float64),
            bary,
        )
    else:
        bary = np.zeros((0, 4))
        k = np.zeros(0)
    rows = {
        "coupling_particle": np.concatenate([host["coupling_particle"][keep], particle]),
        "coupling_tet": np.concatenate([host["coupling_tet"][keep], new]),
        "coupling_bary": np.concatenate([host["coupling_bary"][keep], bary]),
        "coupling_k": np.concatenate([host["coupling_k"][keep], k]),
        "coupling_energy_prev": np.concatenate([host["coupling_energy_prev"][keep], np.zeros(len(new))]),
        "coupling_rest": np.concatenate([host["coupling_rest"][keep], np.zeros((len(new), 3))]),
    }
    for name in COUPLING_FIELDS:
        a = getattr(s, name)
        a.zero_()
        if count:
            wp.copy(a, wp.array(rows[name].astype(a.numpy().dtype), dtype=a.dtype, device=m.device), count=count)
    s.coupling_count.fill_(count)
    if len(new):
        wp.launch(
            kcp.coupling_rest_kernel,
            dim=m.coupling_capacity,
            inputs=[
                m.tet_nodes,
                m.node_ref_q,
                s.particle_q,
                s.node_u,
                s.coupling_count,
                s.coupling_particle,
                s.coupling_tet,
                s.coupling_bary,
                count - len(new),
            ],
            outputs=[s.coupling_rest],
            device=m.device,
        )


def _reference_kn(m: Model, s: State, particle: np.ndarray, alpha: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """k_n of a full-weight bond of each sphere [N/m]: the mean over its bonds of k_n / (1 − ᾱ) (the coupling rule's
    reference, as the tie takes the bond its sphere would have); a sphere with no bond takes κ E V₀^(1/3) of its tet
    (k_b = κ E V_b / L_b² with V_b ~ V₀, L_b ~ V₀^(1/3))."""
    nb = int(s.bond_count.numpy()[0])
    npart = int(s.particle_count.numpy()[0])
    total = np.zeros(npart)
    count = np.zeros(npart)
    if nb:
        bi, bj = s.bond_i.numpy()[:nb], s.bond_j.numpy()[:nb]
        sphere_alpha = np.zeros(npart)
        tet_sphere = s.tet_sphere.numpy()[: len(alpha)]
        conv = tet_sphere >= 0
        sphere_alpha[tet_sphere[conv]] = alpha[conv]
        full = s.bond_kn.numpy()[:nb] / (1.0 - 0.5 * (sphere_alpha[bi] + sphere_alpha[bj]))
        intact = s.bond_broken.numpy()[:nb] == 0
        for ends in (bi, bj):
            np.add.at(total, ends[intact], full[intact])
            np.add.at(count, ends[intact], 1.0)
    table = m.conversion_material_table.numpy()
    fallback = table["bond_modulus"][m.tet_material.numpy()[tets]] * np.cbrt(m.tet_volume.numpy()[tets])
    return np.where(count[particle] > 0, total[particle] / np.maximum(count[particle], 1.0), fallback)


def _mechanical(m: Model, s: State) -> float:
    """The lines the band pass moves [J]: kinetic (nodes, spheres' translation and spin), strain, the springs'
    elastic energy (bonds among them) and the gravity potential (mass moves from the nodes to the sphere, which need
    not sit at their centroid). The shadow term and the couplings are booked around the whole conversion pass."""
    b = energy_balance(m, s)
    return b.kinetic + b.strain + b.elastic + b.gravity_potential
