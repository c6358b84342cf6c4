"""Adaptive FEM→DEM conversion (host side; CIMNE §4–5, DESIGN.md stage 7): tets close to failure turn into bonded
spheres in a between-steps pass on the device (:class:`ConversionPass`, run by ``Simulation.conversion_pass`` every
``model.conversion_interval`` steps, and by ``Simulation.convert_tets`` for a given set).

Rules of the conversion pass (others rely on them):

- Criterion (kernels/conversion.py ``conversion_measure``), on the elastic ``tet_stress`` refreshed at the pass's
  start: Tresca (σ1 − σ3)/2 ≥ f τ_f, Rankine σ1 ≥ f T_f or Mohr–Coulomb (σ1 (1 + sin φ) − σ3 (1 − sin φ)) ≥ f 2 c
  cos φ (tension positive), f the material's ``fraction`` (0.9: CIMNE's 90 % of the Tresca stress); only active tets
  with ``tet_may_convert`` = 1 and a material that converts. A tet converts in the first pass that sees it there.
- Slots: the flags' exclusive scan in tet order gives each converting tet its sphere slot ``particle_count +
  offset`` and ``particle_id`` = slot: deterministic. The bonds' scan gives their slots; the bond arrays are then
  re-sorted by ``bond_key`` = i · particle_capacity + j (a radix sort of the keys, every bond array gathered in that
  order, the neighbour slots' bond indices remapped), the order the contact stage's binary search needs.
- Capacities: the pass reads back how many spheres and bonds it will write, and the particle and bond capacities are
  grown ×2 until they hold them (:func:`regrow_particles`, :func:`regrow_bonds`) before anything is written, so a
  pass never overflows half way and a grown run equals a large-capacity one.
- The sphere (one per tet): at the centroid (float64 X + u), mass exactly ρ V₀ (the four ρ V₀ / 4 the nodes held),
  radius the smallest distance from the centroid to a face (h_min / 4) less 8 float32 ulps of the larger of
  |centroid| and the tet's size, so it touches its own tet's nearest face and overlaps no neighbouring tet or sphere
  at birth; velocity the mean of the nodes' (each node held ρ V₀ / 4 of the tet: mass and linear momentum are
  conserved exactly, to float32 round-off of the re-lumped masses); spin ω = axial vector of the antisymmetric part
  of the velocity gradient L = ``[v_a − v_0][x_a − x_0]⁻¹``; material the tet's, part ``model.conversion_part``.
- Four spheres per tet (``spheres_per_tet`` = 4, warpdem.stages.multisphere): one in each corner sub-tet of the 1:8
  midpoint subdivision, at (x_a + c) / 2 with node a's lumped mass ρ V₀ / 4, the velocity field there and the same
  spin; radius h_min / 8 (less the float32 margin); slots ``tet_sphere`` + a; bonds to the other three and to the
  spheres at the same node of the converted tets sharing an edge through it; couplings to the active ones; κ and S of
  the sub-lattice. The rules below are those of one sphere; warpdem.stages.multisphere says how each carries over.
- Angular momentum: the orbital part m c × v̄ is conserved exactly (Σ m_a x_a = m c, Σ m_a v_a = m v̄). The tet's
  internal part about its centroid is H = Σ_a (m/4) (x_a − c) × (v_a − v̄); for a rigid rotation v_a − v̄ = ω ×
  (x_a − c) it is J ω with J = Σ (m/4) (|r_a|² 1 − r_a r_aᵀ) the nodes' inertia tensor, while the sphere holds
  (2/5) m r² ω. So a conversion changes the angular momentum by ΔH = H − (2/5) m r² ω, bounded by |ΔH| ≤ (‖J‖₂ +
  (2/5) m r²) |ω| (J ω exactly for a rigidly spinning tet); the spin (sphere) inertia is about 1/20 of J for a
  regular tet, and the spin energy lost with it is booked in ``energy_released_conversion``.
- Nodes: each loses ρ V₀ / 4 of every converted tet (its mass re-lumped from its remaining active tets, summed in
  ascending tet order); a node left without active tets is deactivated: mass 0, inv_mass 0, held (motion 1), at
  rest; its penalty stiffness is 0 after the surface rebuild, so contact skips it.
- Bonds: the edge network of warpdem.stages.lattice — between the spheres of converted tets that share an edge (two
  nodes; so never across a crack or a joint, whose nodes are split). One sphere per tet bonded across faces alone
  has Z ≤ 4 and is a mechanism (Maxwell: 3 Z / 2 < 6); edge neighbours give Z ≈ 12 and a network rigid with normal
  springs alone. k_b = κ E V_b / L_b² (V_b = V_t / Z_t + V_n / Z_n, Z over all live tets, so a bond's stiffness does
  not depend on which of its neighbours have converted yet: counted once at attach, ``Model.tet_edge_degree``, and
  where nodes may split (fracture attached) found again at each pass for the converting tets and their edge
  neighbours; L_b the centres' distance), k_s = 0, area V_b / L_b, tensile strength (κ / S) T_f, no dashpot, born
  relaxed (rest length = L_b). κ and S are calibrated at attach on the mesh's own network (a static virtual tension
  test of the tets that may convert, warpdem.stages.lattice "Calibration on the mesh"): fully converted bars measure
  0.99 to 1.00 sqrt(E/ρ) and 0.99 to 1.00 T_f on Kuhn and Gmsh meshes (tests/test_coupling.py).
- Couplings (warpdem.stages.coupling, CIMNE eqs. 8–9): each new sphere is tied to every still-active tet sharing an edge
  with its tet (the adjacency of the bonds; ccoupling measured 4.3 % reflection at the first interface this way
  against 10.5 % with face neighbours alone) at its current barycentric coordinates there (born relaxed), with
  warpdem.stages.coupling.coupling_stiffness's rule k = k_b min(1, 2 / (1 + m_s Σ N_a² / m_a)), k_b the bond the sphere
  would have with a sphere at that tet's centroid; couplings to the tets converting now are released first
  (compact_coupling). With the blended overlap band (``Model.band_width`` ≥ 1) Simulation re-weights the pass's
  result right after it (warpdem.stages.overlap_band.apply_band): converted tets within the band stay FEM elements
  of weight α, their spheres take 1 − α, and the tie's couplings are replaced by one per band sphere to its own tet.
- Energy: ``energy_released_conversion`` += strain energy + kinetic energy of the tet's nodes' shares − the sphere's
  translational and spin energy (bonds and couplings are born relaxed, so they hold nothing), + the springs of the
  released couplings, + the change of Verlet's shadow term over the pass (Simulation: the scheme conserves kinetic −
  shadow, and the pass changes the forces and masses without work). A pass therefore closes the books
  (EnergyBalance, line ``released_conversion``) exactly, to the float64 rounding of the sums.
- After a pass (Simulation): boundary faces rebuilt on the device (the faces of converted tets' neighbours become
  contact faces for the spheres), the face ids of the contact state carried over, pressure and dashpot faces of
  converted tets dropped (:func:`drop_converted_load_faces`: collapsed to zero area, so the nodes lose that load;
  a pressure face's push is handed over to its tet's spheres, with the face's area vector at that moment, for the
  rest of the history, its work booked on the load line: kernels/loads.py, Hand-over; a face that a crack only
  split stays, on the daughters of its tet's side), the stages set up again (sphere
  contact comes alive after the first conversion) and the forces re-evaluated at dt = 0.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import compaction as kc
from ..kernels import conversion as kcv
from ..kernels import conversion_bonds as kcb
from ..kernels import multisphere as kms
from ..kernels import topology as kt
from ..model import (
    BOND_FIELDS,
    COUPLING_FIELDS,
    NEIGHBOR_FIELDS,
    PARTICLE_MODEL_FIELDS,
    PARTICLE_STATE_FIELDS,
    Model,
    State,
    conversion_state,
)
from . import multisphere
from .compaction import Compactor
from .coupling import compact_coupling
from .lattice import edge_pairs
from .tets import eval_tet_stresses, tet_energies
from .topology import NodeStars, live_flags, reference_face_neighbors

CRITERIA = {"tresca": 0, "rankine": 1, "mohr_coulomb": 2}
"""Criterion names and their kernel constants (kernels/conversion.py CRITERION_*)."""


@dataclass
class ConversionProps:
    """Conversion properties of one material (host side); None for a material that never converts.

    Attributes:
        criterion: "tresca" | "rankine" | "mohr_coulomb".
        fraction: f, the fraction of the strength at which a tet converts (CIMNE's 90 %) [-].
        tresca_strength: τ_f [Pa] (Tresca).
        tensile_strength: T_f [Pa] (Rankine; the bonds' tensile strength for every criterion).
        cohesion: c [Pa] (Mohr–Coulomb).
        friction_angle: φ [degrees] (Mohr–Coulomb).
    """

    criterion: str = "tresca"
    fraction: float = 0.9
    tresca_strength: float | None = None
    tensile_strength: float | None = None
    cohesion: float | None = None
    friction_angle: float = 30.0

    def check(self, where: str) -> None:
        """Raise ValueError naming ``where`` when the values are not usable."""
        if self.criterion not in CRITERIA:
            raise ValueError(f"{where}: criterion must be one of {sorted(CRITERIA)}, got {self.criterion!r}")
        if not (math.isfinite(self.fraction) and 0.0 < self.fraction <= 1.0):
            raise ValueError(f"{where}: fraction must lie in (0, 1], got {self.fraction}")
        needed = {"tresca": "tresca_strength", "rankine": "tensile_strength", "mohr_coulomb": "cohesion"}
        for name in ("tresca_strength", "tensile_strength", "cohesion"):
            value = getattr(self, name)
            if value is None:
                if name == needed[self.criterion]:
                    raise ValueError(f"{where}: criterion {self.criterion!r} needs {name} [Pa]")
                continue
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{where}: {name} must be a finite number > 0 [Pa], got {value}")
        if not (math.isfinite(self.friction_angle) and 0.0 <= self.friction_angle < 90.0):
            raise ValueError(f"{where}: friction_angle must lie in [0, 90) degrees, got {self.friction_angle}")

    def bond_strengths(self) -> tuple[float, float]:
        """Tensile and shear strength of the material the bonds stand for [Pa], before the lattice factor κ / S:
        T_f (else the Mohr–Coulomb tensile strength 2 c cos φ / (1 + sin φ), else τ_f), and τ_f (else c, else
        T_f)."""
        phi = math.radians(self.friction_angle)
        tensile = self.tensile_strength
        if tensile is None and self.cohesion is not None:
            tensile = 2.0 * self.cohesion * math.cos(phi) / (1.0 + math.sin(phi))
        if tensile is None:
            tensile = self.tresca_strength
        shear = self.tresca_strength or self.cohesion or tensile
        return float(tensile), float(shear)


@dataclass
class ConversionReport:
    """What one conversion pass did.

    Attributes:
        converted: tets converted. spawned: spheres spawned. bonds: bonds created. couplings: couplings created.
        grew: a capacity grew (particles, bonds or couplings), so the stages were set up again.
    """

    converted: int
    spawned: int
    bonds: int
    couplings: int
    grew: bool


def conversion_material_table(
    model: Model,
    materials: Sequence[ConversionProps | None],
    device: wp.context.Device,
    spheres_per_tet: int = 1,
    factors: tuple[float, float] | None = None,
) -> wp.array:
    """ConversionMaterial of every material id (``converts`` = 0 for None), with the bond calibration from the
    model's continuum properties (E, ν from the Lamé constants of ``tet_material_table``) and the lattice factors
    ``factors`` = (κ, S) (attach_conversion: calibrated on the mesh, warpdem.stages.multisphere.mesh_lattice_factors;
    None: the reference ones of ``spheres_per_tet`` spheres per tet, warpdem.stages.multisphere.lattice_factors)."""
    stiffness_factor, strength_factor = factors if factors is not None else multisphere.lattice_factors(spheres_per_tet)
    continuum = model.tet_material_table.numpy()
    table = []
    for mid, p in enumerate(materials):
        m = kcv.ConversionMaterial()
        m.criterion = 0
        m.fraction = 1.0
        m.tresca_strength = m.tensile_strength = m.cohesion = float(kcv.NEVER)
        m.friction_angle = 0.0
        m.bond_modulus = 1.0
        m.bond_shear_ratio = 0.0
        m.bond_tensile_strength = m.bond_shear_strength = float(kcv.NEVER)
        m.converts = 0
        mu, lam = float(continuum["mu"][mid]), float(continuum["lam"][mid])
        if p is not None and lam + mu > 0.0:  # a material no tet uses has no continuum row (and nothing to convert)
            young = mu * (3.0 * lam + 2.0 * mu) / (lam + mu)
            tensile, shear = p.bond_strengths()
            m.criterion = CRITERIA[p.criterion]
            m.fraction = float(p.fraction)
            for name in ("tresca_strength", "tensile_strength", "cohesion"):
                value = getattr(p, name)
                setattr(m, name, float(value) if value is not None else float(kcv.NEVER))
            m.friction_angle = math.radians(p.friction_angle)
            m.bond_modulus = stiffness_factor * young
            m.bond_shear_ratio = 0.0
            m.bond_tensile_strength = stiffness_factor / strength_factor * tensile
            m.bond_shear_strength = stiffness_factor / strength_factor * shear
            m.converts = 1
        table.append(m)
    return wp.array(table, dtype=kcv.ConversionMaterial, device=device)


def _is_count(value: object, low: int) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, np.integer)) and value >= low


def attach_conversion(
    model: Model,
    state: State,
    materials: Sequence[ConversionProps | None],
    *,
    check_interval: int = 1,
    may_convert: np.ndarray | None = None,
    spheres_per_tet: int = 1,
    part: int = 0,
    coupling_capacity: int | None = None,
    band_width: int = 0,
    band_penalty: float = 1.0,
    safety_factor: float | None = None,
) -> tuple[Model, State]:
    """Turn FEM→DEM conversion on for a built model (before its Simulation is made).

    A model built without spheres can spawn them: its particle capacity grows at the first pass, and when its
    Verlet skin is 0 (nothing set it) it gets 0.4 × the smallest radius a converted tet can give (h_min / 4).

    Args:
        materials: conversion properties per material id, in order (None: the material never converts).
        check_interval: steps between conversion passes (>= 1).
        may_convert: bool per live tet, True where a tet may convert (the scene's region); None: every tet.
        spheres_per_tet: spheres spawned per converted tet: 1 (at the centroid) or 4 (one per corner sub-tet;
            warpdem.stages.multisphere).
        part: part id of the spawned spheres (< len(model.part_names) when the model names parts).
        coupling_capacity: initial penalty coupling slots (grown ×2 on demand); None: max(64, tet_count // 8).
        band_width: tet layers of the blended overlap band (warpdem.stages.overlap_band; CIMNE eq. 8); 0: the tie
            (each converted tet dropped, its spheres tied to the continuum around, warpdem.stages.coupling).
        band_penalty: factor on the band's penalty stiffness over the coupling rule (> 0) [-].
        safety_factor: the fraction of the critical step the model's dt was built at (``dt = "auto"``), in (0, 1]:
            the bonded spheres' step (:func:`conversion_critical_step`) joins the critical step, and dt becomes
            ``safety_factor`` × the smaller where that is below it. None: dt was given, and is refused when above the
            spheres' step.

    Returns:
        The model (``conversion_interval``, ``spheres_per_tet``, ``conversion_part``, ``coupling_capacity``,
        ``tet_may_convert``, ``conversion_material_table``, ``tet_edge_degree``, ``ref_tet_face_nbr`` (kept when
        set), ``critical_dt`` set, ``dt`` lowered as ``safety_factor`` says) and the state with the conversion fields
        allocated.

    Raises:
        ValueError: a bad argument (the message says which and what is allowed).
    """
    if len(materials) != model.num_materials:
        raise ValueError(
            f"attach_conversion: need one ConversionProps (or None) per material ({model.num_materials}), got "
            f"{len(materials)}"
        )
    for i, p in enumerate(materials):
        if p is not None:
            name = model.material_names[i] if i < len(model.material_names) else str(i)
            p.check(f"attach_conversion: material {name!r}")
    if not _is_count(check_interval, 1):
        raise ValueError(f"attach_conversion: check_interval must be an integer >= 1, got {check_interval!r}")
    if isinstance(spheres_per_tet, bool) or spheres_per_tet not in multisphere.SPHERES_PER_TET:
        raise ValueError(
            f"attach_conversion: spheres_per_tet must be 1 (one sphere per tet) or 4 (one per corner sub-tet), got "
            f"{spheres_per_tet!r}"
        )
    if not _is_count(part, 0) or (model.part_names and part >= len(model.part_names)):
        raise ValueError(f"attach_conversion: part must be a part id in [0, {len(model.part_names)}), got {part!r}")
    if model.tet_capacity == 0:
        raise ValueError("attach_conversion: the model has no tets to convert")
    if not _is_count(band_width, 0):
        raise ValueError(f"attach_conversion: band_width must be an integer >= 0 (tet layers), got {band_width!r}")
    if band_width and spheres_per_tet != 1:
        raise ValueError(
            f"attach_conversion: the overlap band (band_width = {band_width}) needs spheres_per_tet = 1, got "
            f"{spheres_per_tet}"
        )
    if isinstance(band_penalty, bool) or not (math.isfinite(band_penalty) and band_penalty > 0.0):
        raise ValueError(f"attach_conversion: band_penalty must be a finite number > 0, got {band_penalty!r}")
    if safety_factor is not None and (isinstance(safety_factor, bool) or not 0.0 < safety_factor <= 1.0):
        raise ValueError(f"attach_conversion: safety_factor must be a number in (0, 1] or None, got {safety_factor!r}")
    nt = int(state.tet_count.numpy()[0])
    flags = live_flags(may_convert, nt, model.tet_capacity, "attach_conversion", "may_convert", "tet")
    if coupling_capacity is None:
        coupling_capacity = max(64, nt // 8)
    if not _is_count(coupling_capacity, 1):
        raise ValueError(f"attach_conversion: coupling_capacity must be an integer >= 1, got {coupling_capacity!r}")
    d = model.device
    # κ and S from a virtual tension test of the convertible tets' own network (warpdem.stages.lattice, "Calibration").
    converts = flags[:nt].astype(bool) & np.array([p is not None for p in materials])[model.tet_material.numpy()[:nt]]
    tets = model.tet_nodes.numpy()[:nt]
    kappa, strength, _ = multisphere.mesh_lattice_factors(tets, model.node_ref_q.numpy(), converts, spheres_per_tet)
    table = conversion_material_table(model, materials, d, spheres_per_tet, (kappa, strength))
    pairs = edge_pairs(tets, np.ones(nt, dtype=bool))
    critical, tet = conversion_critical_step(
        dataclasses.replace(model, conversion_material_table=table, spheres_per_tet=int(spheres_per_tet)),
        state,
        flags[:nt].astype(bool),
        pairs,
    )
    dt = model.dt
    if safety_factor is not None:
        # dt = "auto": the spheres the tets become are part of the model whose critical step it takes a fraction of.
        # Checked against the bound itself instead, a step up to that bound passed (at safety 0.5, 0.96 of it on
        # tests/test_loads_handover.py's block), where the bound (Σ k_b / m_s) is an estimate, not a ceiling: the
        # bonds and couplings of a converted layer on light nodes have a faster mode, and the layer ran away.
        dt = min(dt, safety_factor * critical)
    elif model.dt > critical:
        raise ValueError(
            f"attach_conversion: the time step {model.dt:.3g} s exceeds the stable step {critical:.3g} s of the bonded "
            f"spheres that tet {tet} would become (warpdem.stages.conversion.conversion_critical_step); build with a "
            "smaller dt or safety factor"
        )
    skin = model.skin
    if skin <= 0.0:
        skin = 0.4 * smallest_converted_radius(model, state) / (2.0 if spheres_per_tet == 4 else 1.0)
    model = dataclasses.replace(
        model,
        skin=float(skin),
        conversion_interval=int(check_interval),
        spheres_per_tet=int(spheres_per_tet),
        conversion_part=int(part),
        coupling_capacity=int(coupling_capacity),
        tet_may_convert=wp.array(flags, dtype=int, device=d),
        # The surface rebuild after each pass finds the tets' face neighbours in the unsplit adjacency (four lookups
        # per tet) rather than by star searches (warpdem.stages.topology.NodeStars.build); fracture builds the same
        # array.
        ref_tet_face_nbr=model.ref_tet_face_nbr
        if model.ref_tet_face_nbr is not None
        else reference_face_neighbors(model, state),
        conversion_material_table=table,
        band_width=int(band_width),
        band_penalty=float(band_penalty),
        tet_band_volume=wp.clone(model.tet_volume) if band_width else None,
        tet_edge_degree=wp.array(
            np.bincount(pairs.ravel(), minlength=model.tet_capacity).astype(np.int32), dtype=int, device=d
        ),
        dt=dt,
        critical_dt=min(model.critical_dt, critical),
        critical_dt_source=model.critical_dt_source
        if model.critical_dt <= critical
        else f"the bonded spheres of tet {tet}",
    )
    return model, dataclasses.replace(state, **conversion_state(model))


def smallest_converted_radius(model: Model, state: State) -> float:
    """Smallest sphere radius a live tet would convert into as one sphere, h_min / 4 over its faces, in the reference
    configuration [m] (host; build time; four spheres per tet get half of it)."""
    nt = int(state.tet_count.numpy()[0])
    if nt == 0:
        return 0.0
    x = model.node_ref_q.numpy().astype(np.float64)[model.tet_nodes.numpy()[:nt]]  # (M, 4, 3)
    volume = np.abs(np.linalg.det(x[:, 1:] - x[:, :1])) / 6.0
    faces = x[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]]  # (M, 4, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(faces[:, :, 1] - faces[:, :, 0], faces[:, :, 2] - faces[:, :, 0]), axis=2)
    return float(np.min(3.0 * volume / area.max(axis=1)) / 4.0)


def conversion_critical_step(
    model: Model, state: State, may_convert: np.ndarray, pairs: np.ndarray | None = None
) -> tuple[float, int]:
    """Stable step [s] of the bonded spheres the tets that may convert become, and the tet that sets it (-1: none).
    Build time (host, reference configuration).

    A sphere of mass m = ρ V has a bond of the edge network (k_b = κ E V_b / L_b², :mod:`warpdem.stages.lattice`) or a
    coupling (k ≤ k_b, warpdem.stages.coupling) to each tet sharing an edge with its tet; L_b the distance of the two
    centroids. Its stiffest translational mode is bounded by ω² = Σ_b k_b / m (every spring along the motion, as
    warpdem.stages.bonds.bond_critical_step's Z k_n / m); the bonds have no shear springs or dashpots, so dt = 2 / ω.

    Four spheres per tet: warpdem.stages.multisphere.sub_critical_step, the same bound on the sub-lattice.

    Args:
        may_convert: bool per live tet.
        pairs: the pairs of live tets that share an edge (warpdem.stages.lattice.edge_pairs over all of them), when the
            caller has them; None: found here.
    """
    nt = int(state.tet_count.numpy()[0])
    table = model.conversion_material_table.numpy()
    mats = model.tet_material.numpy()[:nt]
    converts = np.asarray(may_convert, dtype=bool) & (table["converts"][mats] != 0)
    if not converts.any():
        return math.inf, -1
    tets = model.tet_nodes.numpy()[:nt]
    if model.spheres_per_tet == 4:
        density = model.tet_material_table.numpy()["density"][mats].astype(np.float64)
        modulus = table["bond_modulus"][mats].astype(np.float64)
        return multisphere.sub_critical_step(tets, model.node_ref_q.numpy(), density, modulus, converts)
    x = model.node_ref_q.numpy().astype(np.float64)[tets]
    volume = np.abs(np.linalg.det(x[:, 1:] - x[:, :1])) / 6.0
    if pairs is None:
        pairs = edge_pairs(tets, np.ones(nt, dtype=bool))
    degree = np.bincount(pairs.ravel(), minlength=nt).astype(np.float64)
    i, j = pairs[:, 0], pairs[:, 1]
    centroid = x.mean(axis=1)
    length = np.linalg.norm(centroid[i] - centroid[j], axis=1)
    modulus = table["bond_modulus"][mats].astype(np.float64)
    kb = 0.5 * (modulus[i] + modulus[j]) * (volume[i] / degree[i] + volume[j] / degree[j]) / length**2
    stiffness = np.bincount(pairs.ravel(), weights=np.repeat(kb, 2), minlength=nt)
    mass = model.tet_material_table.numpy()["density"][mats] * volume
    omega2 = np.where(converts, stiffness / mass, 0.0)
    k = int(np.argmax(omega2))
    if omega2[k] <= 0.0:
        return math.inf, -1
    return float(2.0 / math.sqrt(omega2[k])), k


# ----------------------------------------------------------------------------------------------------------------
# Capacity growth


def _grow_rows(a: wp.array, rows: int, per_row: int, capacity: int, fill: int = 0) -> wp.array:
    host = a.numpy()
    grown = np.full((capacity * per_row, *host.shape[1:]), fill, dtype=host.dtype)
    grown[: rows * per_row] = host[: rows * per_row]
    return wp.array(grown, dtype=a.dtype, device=a.device)


def regrow_particles(model: Model, state: State, capacity: int) -> tuple[Model, State]:
    """Copies of a model and state with ``capacity`` particle slots: every per-particle array of the Model and the
    State, the neighbour slots (× max_neighbors), the wall histories (× num_walls) and the sphere–face slots (×
    max_sphere_faces, where the model has boundary faces) grown, the live slots copied, new slots empty; the bond
    keys recomputed as i · capacity + j (the order of i · old + j, so the bonds stay sorted). Between steps; the
    stages must be set up again and graphs re-captured."""
    old = model.particle_capacity
    if capacity <= old:
        return model, state
    mfields = {
        name: _grow_rows(getattr(model, name), old, 1, capacity, fill) for name, fill in PARTICLE_MODEL_FIELDS.items()
    }
    sfields = {name: _grow_rows(getattr(state, name), old, 1, capacity) for name in PARTICLE_STATE_FIELDS}
    for name in NEIGHBOR_FIELDS:
        sfields[name] = _grow_rows(
            getattr(state, name), old, model.max_neighbors, capacity, -1 if name == "nbr_bond" else 0
        )
    sfields["wall_shear"] = _grow_rows(state.wall_shear, old, model.num_walls, capacity)
    if model.face_capacity:  # warpdem.stages.fem_contact.sphere_face_rows: per-sphere FEM lists only with faces
        for name in (
            "sphere_face_count",
            "sphere_face_energy_prev",
            "sphere_face_f",
            "sphere_face_t",
            "sphere_face_dissipated",
        ):
            sfields[name] = _grow_rows(getattr(state, name), old, 1, capacity)
        for name in ("sphere_face_index", "sphere_face_shear"):
            sfields[name] = _grow_rows(getattr(state, name), old, model.max_sphere_faces, capacity)
    if model.bond_capacity:
        keys = state.bond_key.numpy().copy()
        n = int(state.bond_count.numpy()[0])
        i, j = state.bond_i.numpy()[:n].astype(np.int64), state.bond_j.numpy()[:n].astype(np.int64)
        keys[:n] = i * capacity + j
        sfields["bond_key"] = wp.array(keys, dtype=wp.int64, device=model.device)
    return dataclasses.replace(model, particle_capacity=capacity, **mfields), dataclasses.replace(state, **sfields)


def regrow_bonds(model: Model, state: State, capacity: int) -> tuple[Model, State]:
    """Copies of a model and state with ``capacity`` bond slots, the live bonds copied, new slots empty. Between
    steps; the stages must be set up again."""
    old = model.bond_capacity
    if capacity <= old:
        return model, state
    n = int(state.bond_count.numpy()[0])
    fields = {name: _grow_rows(getattr(state, name), n, 1, capacity) for name in BOND_FIELDS}
    return dataclasses.replace(model, bond_capacity=capacity), dataclasses.replace(state, **fields)


def grown(capacity: int, needed: int) -> int:
    """``capacity`` doubled (from at least 1) until it holds ``needed``."""
    cap = max(capacity, 1)
    while cap < needed:
        cap *= 2
    return cap


# ----------------------------------------------------------------------------------------------------------------
# The pass


class ConversionPass:
    """The scratch buffers and launches of a conversion pass for one tet and node capacity (module docstring). A
    Simulation keeps one for its life (a new one when the capacities change), with the stars of all live tets.

    Args:
        model: the model (its tet and node capacities size the buffers).
    """

    def __init__(self, model: Model) -> None:
        d = model.device
        tcap, ncap = model.tet_capacity, model.node_capacity
        self.device = d
        self.tet_capacity = tcap
        self.node_capacity = ncap
        t1 = max(tcap, 1)
        self.flag = wp.zeros(t1, dtype=int, device=d)
        self.offset = wp.zeros(t1, dtype=int, device=d)
        self.bonds = wp.zeros(t1, dtype=int, device=d)
        self.bond_offset = wp.zeros(t1, dtype=int, device=d)
        self.was_sphere = wp.zeros(t1, dtype=int, device=d)
        self.released = wp.zeros(t1, dtype=wp.float64, device=d)
        self.released_total = wp.zeros(1, dtype=wp.float64, device=d)
        self.forced = wp.zeros(t1, dtype=int, device=d)
        self.couplings = wp.zeros(t1, dtype=int, device=d)
        self.coupling_offset = wp.zeros(t1, dtype=int, device=d)
        self.counts = wp.zeros(3, dtype=int, device=d)  # converting tets, new bonds, new couplings
        self.node_touched = wp.zeros(max(ncap, 1), dtype=int, device=d)
        self.strain_energy = wp.zeros(t1, dtype=wp.float64, device=d)  # of the converting tets
        # The stars of all live tets, converted or not (the edge network; their active tets re-lump the nodes). They
        # change only where nodes split: built once while the model cannot split nodes, else at every pass.
        self.full_stars = NodeStars(ncap, tcap, d)
        self.full_stars_built = False
        self.all_live = wp.ones(t1, dtype=int, device=d)
        self.found_degree = wp.zeros(t1, dtype=int, device=d)  # Z_t found by the pass (where nodes may split)
        self.degree = self.found_degree  # the Z_t the pass reads: the model's, or found_degree
        self.needed = wp.zeros(t1, dtype=int, device=d)  # tets whose Z the pass reads
        self.sub_degree = wp.zeros(4 * t1, dtype=int, device=d)  # four spheres per tet: Z per (tet, node)
        self.spawned = wp.zeros(1, dtype=int, device=d)

    def fits(self, model: Model) -> bool:
        """Whether the buffers match the model's capacities."""
        return self.tet_capacity == model.tet_capacity and self.node_capacity == model.node_capacity

    def build_stars(self, model: Model, state: State) -> None:
        """Build the stars of all live tets unless they still hold: built before and the model cannot split nodes
        (no fracture attached; tets are never added, so nothing else changes them). Launches only."""
        m, s = model, state
        if self.full_stars_built and m.fracture_material_table is None:
            return
        self.full_stars.build(m.tet_nodes, s.tet_count, self.all_live, s.node_count, face_neighbors=False)
        self.full_stars_built = True

    def find(
        self, model: Model, state: State, forced: np.ndarray | None = None, stresses_current: bool = False
    ) -> tuple[int, int, int]:
        """Refresh the tet stresses (unless ``stresses_current``: the caller has just evaluated them at the current
        positions), flag the converting tets (the criterion, or ``forced``: bool per tet slot), scan the flags, the
        bonds each new sphere will own and its couplings. Reads back (tets, bonds, couplings)."""
        m, s, d = model, state, self.device
        if m.tet_capacity == 0:
            return 0, 0, 0
        if not stresses_current:
            eval_tet_stresses(m, s)
        if forced is not None:
            self.forced.assign(np.asarray(forced, dtype=np.int32))
        wp.launch(
            kcv.flag_conversion_kernel,
            dim=m.tet_capacity,
            inputs=[
                m.tet_material,
                m.conversion_material_table,
                m.tet_may_convert,
                s.tet_count,
                s.tet_active,
                s.tet_stress,
                self.forced,
                int(forced is not None),
            ],
            outputs=[self.flag],
            device=d,
        )
        wp.utils.array_scan(self.flag, self.offset, inclusive=False)
        self.build_stars(m, s)  # the edge network over every live tet, converted or not
        self.needed.zero_()
        wp.launch(
            kcv.count_conversion_links_kernel,
            dim=m.tet_capacity,
            inputs=[m.tet_nodes, s.tet_count, s.tet_active, s.tet_sphere, self.flag, *self.full_stars.csr()],
            outputs=[self.bonds, self.couplings, self.needed],
            device=d,
        )
        self.degree = m.tet_edge_degree
        if m.fracture_material_table is not None or m.tet_edge_degree is None:
            # Split nodes cut edges, so Z_t may have changed since attach: found again, but only where a bond or
            # coupling of this pass reads it (the converting tets and their edge neighbours; a star search from
            # every live tet was half the pass).
            self.degree = self.found_degree
            wp.launch(
                kcv.edge_degree_kernel,
                dim=m.tet_capacity,
                inputs=[m.tet_nodes, s.tet_count, self.needed, *self.full_stars.csr()],
                outputs=[self.degree],
                device=d,
            )
        if m.spheres_per_tet == 4:  # the sub-lattice's links replace the counts (warpdem.stages.multisphere)
            multisphere.count_sub_links(m, s, self)
        wp.utils.array_scan(self.bonds, self.bond_offset, inclusive=False)
        wp.utils.array_scan(self.couplings, self.coupling_offset, inclusive=False)
        for k, (items, offset) in enumerate(
            ((self.flag, self.offset), (self.bonds, self.bond_offset), (self.couplings, self.coupling_offset))
        ):
            wp.launch(kcv.scan_total_kernel, dim=1, inputs=[items, offset], outputs=[self.counts[k : k + 1]], device=d)
        tets, bonds, couplings = (int(v) for v in self.counts.numpy())
        return tets, bonds, couplings

    def convert(self, model: Model, state: State, coupling_compactor: Compactor | None = None) -> None:
        """Carry out the flagged conversions in place (after :meth:`find`; the particle, bond and coupling
        capacities must hold what it found): spheres, tets deactivated, bonds appended and re-sorted, nodes re-lumped,
        the couplings of converted tets released and the new spheres' couplings written (with
        ``coupling_compactor``, a Compactor of ``model.coupling_capacity`` slots). Reads back the coupling count."""
        m, s, d = model, state, self.device
        sub = m.spheres_per_tet == 4  # four spheres per tet: warpdem.stages.multisphere's kernels, same arguments
        # Strain energies of the converting tets alone (they are active), before they are deactivated.
        energies = tet_energies(m, s, active=self.flag, out=self.strain_energy)
        wp.copy(self.was_sphere, s.tet_sphere)
        self.node_touched.zero_()
        wp.launch(
            kcv.spawn_spheres_kernel,
            dim=m.tet_capacity,
            inputs=[
                m.node_ref_q,
                m.tet_nodes,
                m.tet_volume,
                m.tet_material,
                m.tet_material_table,
                m.conversion_part,
                m.spheres_per_tet,
                s.tet_count,
                s.particle_count,
                s.node_u,
                s.node_qd,
                self.flag,
                self.offset,
                energies,
            ],
            outputs=[
                m.particle_radius,
                m.particle_mass,
                m.particle_inv_mass,
                m.particle_inv_inertia,
                m.particle_material,
                m.particle_motion,
                m.particle_part,
                m.particle_id,
                s.particle_q,
                s.particle_qd,
                s.particle_omega,
                s.particle_q_at_build,
                s.tet_active,
                s.tet_sphere,
                self.node_touched,
                self.released,
            ],
            device=d,
        )
        if m.bond_capacity:
            wp.launch(
                kms.write_sub_bonds_kernel if sub else kcb.write_conversion_bonds_kernel,
                dim=m.tet_capacity,
                inputs=[
                    m.tet_nodes,
                    m.tet_volume,
                    m.tet_material,
                    m.conversion_material_table,
                    m.particle_capacity,
                    s.tet_count,
                    s.bond_count,
                    s.particle_q,
                    s.tet_sphere,
                    self.flag,
                    self.was_sphere,
                    self.bond_offset,
                    self.sub_degree if sub else self.degree,
                    *self.full_stars.csr(),
                ],
                outputs=[getattr(s, name) for name in BOND_FIELDS],
                device=d,
            )
            wp.launch(kcv.add_bond_count_kernel, dim=1, inputs=[self.counts], outputs=[s.bond_count], device=d)
            sort_bonds(m, s)
        wp.launch(
            kcv.relump_converted_nodes_kernel,
            dim=m.node_capacity,
            inputs=[
                m.tet_volume,
                m.tet_material,
                m.tet_material_table,
                s.node_count,
                s.tet_active,
                self.node_touched,
                *self.full_stars.csr(),
            ],
            outputs=[m.node_mass, m.node_inv_mass, m.node_damping, m.node_motion, s.node_qd],
            device=d,
        )
        if m.coupling_capacity and coupling_compactor is not None:
            # Couplings to the tets that converted now are released (their spheres bond instead), then the new
            # spheres are tied to their still-continuous face neighbours (at the re-lumped node masses).
            compact_coupling(m, s, coupling_compactor)
            wp.launch(
                kms.write_sub_couplings_kernel if sub else kcv.write_conversion_couplings_kernel,
                dim=m.tet_capacity,
                inputs=[
                    m.node_ref_q,
                    m.tet_nodes,
                    m.tet_volume,
                    m.tet_material,
                    m.conversion_material_table,
                    m.particle_mass,
                    m.node_mass,
                    s.tet_count,
                    s.coupling_count,
                    s.particle_q,
                    s.node_u,
                    s.tet_active,
                    s.tet_sphere,
                    self.flag,
                    self.coupling_offset,
                    self.sub_degree if sub else self.degree,
                    *self.full_stars.csr(),
                ],
                outputs=[getattr(s, name) for name in COUPLING_FIELDS],
                device=d,
            )
            wp.launch(
                kcv.add_coupling_count_kernel, dim=1, inputs=[self.counts[2:3]], outputs=[s.coupling_count], device=d
            )
        wp.utils.array_sum(self.released, out=self.released_total)
        spawned = self.counts[0:1]
        if sub:
            wp.launch(kms.scale_count_kernel, dim=1, inputs=[self.counts[0:1], 4], outputs=[self.spawned], device=d)
            spawned = self.spawned
        wp.launch(
            kcv.add_released_kernel,
            dim=1,
            inputs=[self.released_total, self.counts[0:1], spawned],
            outputs=[s.energy_released_conversion, s.tets_converted_total, s.spheres_spawned_total, s.particle_count],
            device=d,
        )


def sort_bonds(model: Model, state: State) -> None:
    """Re-sort the bonds by ``bond_key`` in place (a stable radix sort of the keys on the device, every bond array
    gathered in that order) and remap the bond indices the neighbour slots hold. Launches only."""
    m, s, d = model, state, model.device
    n = m.bond_capacity
    keys = wp.zeros(2 * n, dtype=wp.int64, device=d)  # radix_sort_pairs needs twice the length as scratch
    order = wp.zeros(2 * n, dtype=int, device=d)
    # Slots past the count sort last (largest key) and keep their place.
    keys.fill_(np.iinfo(np.int64).max)
    wp.launch(kcv.iota_kernel, dim=n, inputs=[], outputs=[order], device=d)
    wp.launch(kcb.bond_sort_keys_kernel, dim=n, inputs=[s.bond_count, s.bond_key], outputs=[keys, order], device=d)
    wp.utils.radix_sort_pairs(keys, order, n)
    for name in BOND_FIELDS:
        a = getattr(s, name)
        src = wp.clone(a)
        wp.launch(kt.gather_kernel, dim=n, inputs=[order, src], outputs=[a], device=d)
    old_to_new = wp.zeros(n, dtype=int, device=d)
    wp.launch(kcb.inverse_order_kernel, dim=n, inputs=[s.bond_count, order], outputs=[old_to_new], device=d)
    if s.nbr_bond.shape[0]:
        wp.launch(kc.remap_indices_kernel, dim=s.nbr_bond.shape[0], inputs=[old_to_new], outputs=[s.nbr_bond], device=d)


def drop_converted_load_faces(model: Model, state: State) -> None:
    """Drop the pressure and dashpot faces of converted tets (those no active tet holds any more): each is collapsed
    to zero area on its first node, so it stops acting on the nodes; a pressure face whose tet turned into spheres is
    handed over to them first, its area vector now recorded (``handed_area``; kernels/loads.py, Hand-over), so the
    charge's push goes on there. Reads the model's star CSR (valid after a surface rebuild). Launches only;
    idempotent."""
    loads = model.loads
    if loads is None or model.star_offset is None:
        return
    sets = list(loads.pressure.values()) + ([loads.dashpots] if loads.dashpots is not None else [])
    for faces in sets:
        if faces.count:
            pressure = faces.handed_area is not None
            unused = wp.zeros(0, dtype=int, device=model.device)
            wp.launch(
                kcv.drop_converted_faces_kernel,
                dim=faces.count,
                inputs=[
                    model.tet_nodes,
                    model.star_offset,
                    model.star_count,
                    model.star_tets,
                    faces.tet if pressure else unused,
                    int(pressure),
                    state.node_u,
                    state.tet_sphere,
                ],
                outputs=[
                    faces.nodes,
                    faces.edge_a,
                    faces.edge_b,
                    faces.handed_area if pressure else wp.zeros(0, dtype=wp.vec3, device=model.device),
                ],
                device=model.device,
            )
