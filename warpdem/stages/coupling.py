"""The overlap zone of adaptive FEM→DEM conversion (CIMNE, adaptive_dem_fem_blast.txt §4, eqs. 8–9): a sphere born
from a converted tet is tied by a penalty spring to its material point in a still-continuous face neighbour.

Blending (eq. 8, δW_Ω = α δW_F + (1 - α) δW_D, α = 1 on Ω_F, 0 on Ω_D). Here α is piecewise constant per tet: 1 on
every active tet, 0 on a converted one. Converting a tet moves its virtual work from the FEM term to the DEM term —
its Cosserat point element stops (tet_active = 0), its mass ρV leaves its nodes and rides on its sphere, and the
stiffness it held between its faces passes to the bonds between its sphere and those of converted face neighbours.
The overlap region Ω_DF is the band of converted tets next to the continuum: the sphere of such a tet sits inside the
support of the remaining tet's shape functions extended past its face, and eq. 9's constraint u_D - N_F u_F = 0
(with N_F the neighbour's barycentric coordinates of the sphere's material point, ``coupling_bary``) ties it to the
continuum's kinematics. The constraint is imposed by a penalty, as CIMNE do (after Rojek & Oñate 2007):
U = ½ k |g|², g = Σ_a N_a x_a - x_p; the sphere feels k g and node a feels -N_a k g. A coupling is released (its
slot removed by :func:`compact_coupling`) when its tet converts too; the sphere is then bonded to the new sphere
instead. This is the tie: nothing blends α linearly through a band of several tets, and the gradual hand-over of
stiffness that eq. 8's linear α gives is replaced by one interface spring per sphere–tet pair. The blended band
(``Model.band_width`` ≥ 1, the scenes' default) is warpdem.stages.overlap_band: it uses these springs to tie each band
sphere to its own, α-weighted tet, and reflects less (benchmarks/overlap_band.py).

What holds. Σ forces = k g (1 - Σ_a N_a) = 0 (Σ N_a = 1; in float32 to a few ε₃₂ |k g|). The forces are a
collinear pair: k g at x_p and -k g at x_mp (node a's share -N_a k g at x_a has the same moment as -k g at x_mp,
Σ N_a x_a × f = x_mp × f), so their moment about any point is (x_p - x_mp) × k g = -g × k g = 0, and no torque acts on
the sphere: the coupling conserves linear and angular momentum. A rigid motion of the tet carries x_mp with it
(barycentric interpolation is affine), so a sphere that moves rigidly with its tet feels no force.

Energy. U is quadratic in the positions (g is linear in x_p and x_a, N_a fixed), so the coupling is booked as a
potential, as the tets' strain energy is: :func:`coupling_energy` is the ``coupling_elastic`` line (in ``in_play``),
and nothing is booked per step. Velocity Verlet with the shadow term (warpdem.stages.energy.EnergyBalance) conserves
Σ ½ m v_{n-1/2}·v_{n+1/2} + U(x_n) exactly for a quadratic U: with v_{n+1/2} = v_{n-1/2} + dt M⁻¹ f_n,
x_{n+1} = x_n + dt v_{n+1/2} and f = -K x, the change over a step is ½ dt v_{n+1/2}·(f_n + f_{n+1}) + U(x_{n+1})
- U(x_n) = 0 term by term. The coupling therefore closes the books with no dissipation line, to rounding where the
rest of the system is linear and to the tets' own O((ω dt)²) where it is not; the sphere bonds' trapezoid scheme
(kernels/bonds.py) would need the nodes' forces summed for the work ahead, which the FEM side does not keep.
``coupling_energy_prev`` records U at the last evaluation (output and restarts), not a book.

Stiffness (:func:`coupling_stiffness`). k = k_n min(1, 2 / (1 + m_s Σ_a N_a² / m_a)): no stiffer than the bonds
it joins, and its own mode no faster than a bond's — derivation in the function. What the penalty does to waves: the
spring is an interface of stiffness κ ≈ k / A per unit area in series with the lattice; a plane wave of angular
frequency ω meeting a spring interface between media of impedance Z = ρ c reflects |R| = ω Z / sqrt(ω² Z² + 4 κ²)
of its amplitude. With k ~ k_n = E A / L (L the centre spacing), 2 κ / (ω Z) = 2 / (q L) (q the wavenumber): a wave
of length λ reflects |R| ≈ π L / λ of its amplitude (for k summed over the couplings of a face of area A), so a
wave resolved by ~10 spheres keeps a few per cent of its energy at a penalty interface, and a stiffer penalty would
shrink |R| only at the price of a smaller stable step. Measured (tests/test_coupling.py: a bar pulse 12 cells long,
2 × 2 cubic cells across, through an 8-cell converted band and back into tets; energy fractions): as the conversion
pass builds it — the edge-bond network of warpdem.stages.lattice, each sphere coupled to every active tet that shares an
edge with its tet — the first interface reflects 5.5 %, the band 7.7 % in all, 91 % goes through (a bar without a
band: 0.5 % and 99 %). With couplings to face neighbours only (16 instead of 104): 10.5 %, 17 %, 81 %; those 4×
stiffer than the rule: 7.9 %, 12 %, 86 %; 4× softer: 21 %, 33 %, 63 %. The number of tied points matters more than
k, and the rule's cap (stable step, no stiffer than the bonds) costs little.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from ..kernels import coupling as kcp
from ..model import COUPLING_FIELDS, Model, State
from .compaction import Compactor, grow_live_slots


def _coupling_inputs(model: Model, state: State) -> list:
    """The Model and State-in arrays the coupling kernels share, in their order."""
    m, s = model, state
    return [
        # Model:
        m.tet_nodes,
        m.node_ref_q,
        # State in:
        s.particle_q,
        s.node_u,
        s.tet_active,
        s.coupling_count,
        s.coupling_particle,
        s.coupling_tet,
        s.coupling_bary,
        s.coupling_k,
        s.coupling_rest,
    ]


def eval_coupling(model: Model, state: State, dt: float | None = None, track_energy: bool = True) -> None:
    """Add the penalty coupling forces (CIMNE eqs. 8–9) to ``particle_f`` and ``node_f`` [N]: k g on each coupled
    sphere, -N_a k g on node a of its tet, g = Σ N_a x_a - x_p [m]. Couplings whose tet is inactive apply nothing.

    Args:
        model: the system's model; launches over ``model.coupling_capacity``.
        state: the system's state; returns past its ``coupling_count``.
        dt: the step [s]; unused (the spring is a potential: nothing is booked per step, at dt = 0 or otherwise).
            Kept so every force stage has the same call.
        track_energy: record each spring's energy ½ k |g|² [J] in ``coupling_energy_prev``.
    """
    del dt  # booked as a potential (module docstring): the step does not enter
    if model.coupling_capacity == 0:
        return
    wp.launch(
        kcp.eval_coupling_kernel,
        dim=model.coupling_capacity,
        inputs=[*_coupling_inputs(model, state), int(track_energy)],
        outputs=[state.coupling_energy_prev, state.particle_f, state.node_f],
        device=model.device,
    )


def launch_coupling_energy(model: Model, state: State, energy: wp.array) -> None:
    """Each live coupling's spring energy ½ k |g|² [J] where its tet is active, into ``energy`` (float64, shape
    (coupling_capacity,); other slots left as they are: zero it first; launch only)."""
    if model.coupling_capacity:
        wp.launch(
            kcp.coupling_energy_kernel,
            dim=model.coupling_capacity,
            inputs=_coupling_inputs(model, state),
            outputs=[energy],
            device=model.device,
        )


def coupling_energy(model: Model, state: State) -> float:
    """Σ ½ k |g|² over the live couplings whose tet is active [J], at the current positions (the ``coupling_elastic``
    line of the energy books). Allocates and reads back: call between steps."""
    energy = wp.zeros(model.coupling_capacity, dtype=wp.float64, device=model.device)
    launch_coupling_energy(model, state, energy)
    return float(energy.numpy().sum())


def compact_coupling(model: Model, state: State, compactor: Compactor) -> int:
    """Remove the couplings whose tet is no longer active (it converted: the sphere is now bonded to its sphere),
    keeping the others in order (a topology pass between steps). Returns the live coupling count (read back).

    Args:
        compactor: a :class:`warpdem.stages.compaction.Compactor` of ``model.coupling_capacity`` slots.
    """
    if model.coupling_capacity == 0:
        return 0
    if compactor.capacity != model.coupling_capacity:
        raise ValueError(
            f"compact_coupling: compactor of {compactor.capacity} slots for {model.coupling_capacity} couplings"
        )
    dead = wp.zeros(model.coupling_capacity, dtype=int, device=model.device)
    wp.launch(
        kcp.flag_released_couplings_kernel,
        dim=model.coupling_capacity,
        inputs=[state.tet_active, state.coupling_count, state.coupling_tet],
        outputs=[dead],
        device=model.device,
    )
    compactor.remove(state.coupling_count, dead, [getattr(state, name) for name in COUPLING_FIELDS])
    return int(state.coupling_count.numpy()[0])


def regrow_coupling(model: Model, state: State, capacity: int) -> tuple[Model, State]:
    """Copies of ``model`` and ``state`` with ``capacity`` coupling slots: the live couplings (slots below
    ``coupling_count``) copied in place, the other slots zero; every other array is shared. Reads the count back:
    call between steps.

    Raises:
        ValueError: ``capacity`` is below the live coupling count.
    """
    live = int(state.coupling_count.numpy()[0])
    if capacity < live:
        raise ValueError(f"regrow_coupling: capacity {capacity} is below the {live} live couplings")
    fields = grow_live_slots(state, COUPLING_FIELDS, live, capacity)
    return dataclasses.replace(model, coupling_capacity=capacity), dataclasses.replace(state, **fields)


def coupling_stiffness(
    sphere_mass: float | np.ndarray,
    bond_kn: float | np.ndarray,
    node_mass: np.ndarray,
    bary: np.ndarray,
) -> float | np.ndarray:
    """Penalty stiffness of a coupling [N/m]: k = k_n min(1, 2 / (1 + m_s Σ_a N_a² / m_a)).

    Derivation. The coupling alone is a two-body spring between the sphere (mass m_s) and its material point, whose
    effective mass along g is m_mp = 1 / Σ_a N_a² / m_a (node a takes -N_a f, and x_mp = Σ N_a x_a accelerates by
    Σ N_a² f / m_a): its mode is ω_c² = k (1 / m_s + Σ_a N_a² / m_a). The bonds the coupling joins have stiffness
    k_n; a bond between two spheres of mass m_s has ω_b² = 2 k_n / m_s, and the step is chosen stable for the bonds
    (warpdem.stages.bonds.bond_critical_step: Z k_n / m_s with Z bonds on a sphere). Requiring

    - ω_c ≤ ω_b: k ≤ 2 k_n / (1 + m_s Σ N_a² / m_a) — the coupling's own mode does not lower the critical step below
      a bond's; on the FEM side the stiffness it adds to node a's diagonal, k N_a² / m_a ≤ ω_c², is no more than a
      bond's mode either;
    - k ≤ k_n: no stiffer than the bonds it joins. A sphere has one bond or one coupling per tet sharing an edge
      with its tet (warpdem.stages.lattice), each coupling no stiffer than the bond it stands for, so the springs on it
      sum to no more than the fully bonded sphere's, Σ k_n, whose translational mode Σ k_n / m_s the step must
      cover once the whole region has converted (the conversion's stable step).

    Where the nodes are heavy (m_s Σ N_a² / m_a ≤ 1, the usual case while the continuum around is intact) the cap is
    k_n; next to a node that has lost most of its tets k falls so the coupling's mode stays at the bond's.

    Args:
        sphere_mass: m_s [kg], scalar or shape (K,).
        bond_kn: normal stiffness of the sphere's bonds k_n [N/m], scalar or shape (K,).
        node_mass: masses of the tet's four nodes m_a [kg], shape (4,) or (K, 4).
        bary: the material point's barycentric coordinates N_a [-], shape (4,) or (K, 4).

    Returns:
        k [N/m], scalar or shape (K,).

    Raises:
        ValueError: a mass or stiffness is not positive.
    """
    ms = np.asarray(sphere_mass, dtype=np.float64)
    kn = np.asarray(bond_kn, dtype=np.float64)
    mn = np.asarray(node_mass, dtype=np.float64)
    n = np.asarray(bary, dtype=np.float64)
    if np.any(ms <= 0.0) or np.any(kn <= 0.0) or np.any(mn <= 0.0):
        raise ValueError("coupling_stiffness: sphere_mass, bond_kn and node_mass must be positive")
    ratio = ms * np.sum(n * n / mn, axis=-1)
    k = kn * np.minimum(1.0, 2.0 / (1.0 + ratio))
    return float(k) if k.ndim == 0 else k


def material_point(model: Model, tet: int | np.ndarray, x: np.ndarray, state: State | None = None) -> np.ndarray:
    """Barycentric coordinates N_a of points in tets [-] (the shape functions of eq. 9 at the material point).

    With ``state`` the points are current positions and the tets are taken at their current node positions X + u,
    so Σ N_a x_a = x: a coupling made with them starts with no gap (no spurious spring energy). An affine map keeps
    barycentric coordinates, so they are also those of the material point in the tet's reference configuration,
    where they stay fixed while the tet deforms. Without ``state`` the points are reference positions and the tets
    are taken at X. A point outside the tet (a sphere centre beyond the face it shares) gets some N_a < 0.

    Args:
        model: the model (``tet_nodes``, ``node_ref_q``).
        tet: tet index, scalar or shape (K,).
        x: positions [m], shape (3,) or (K, 3) (float64).
        state: the state whose node displacements apply; None: the reference configuration.

    Returns:
        N, shape (4,) or (K, 4), float32 (as ``coupling_bary`` stores them).
    """
    tets = np.atleast_1d(np.asarray(tet, dtype=np.int32))
    pts = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    if len(tets) != len(pts):
        raise ValueError(f"material_point: {len(tets)} tets for {len(pts)} points")
    d = model.device
    u = state.node_u if state is not None else wp.zeros_like(model.node_ref_q)
    out = wp.zeros(len(tets), dtype=wp.vec4, device=d)
    if len(tets):
        wp.launch(
            kcp.material_point_kernel,
            dim=len(tets),
            inputs=[
                model.tet_nodes,
                model.node_ref_q,
                u,
                wp.array(tets, dtype=int, device=d),
                wp.array(pts, dtype=wp.vec3d, device=d),
            ],
            outputs=[out],
            device=d,
        )
    bary = out.numpy()
    return bary[0] if np.ndim(tet) == 0 and np.ndim(x) == 1 else bary


def set_couplings(
    model: Model, state: State, particle: np.ndarray, tet: np.ndarray, bary: np.ndarray, k: np.ndarray
) -> None:
    """Write couplings into slots 0..K-1 and set ``coupling_count`` = K (host side: tests, scenes, restarts).

    Args:
        particle: sphere of each coupling, shape (K,).
        tet: its tet, shape (K,).
        bary: N_a of its material point, shape (K, 4).
        k: penalty stiffness [N/m], shape (K,).

    Raises:
        ValueError: K exceeds ``model.coupling_capacity`` (grow first with :func:`regrow_coupling`).
    """
    particle = np.asarray(particle, dtype=np.int32).reshape(-1)
    count = len(particle)
    if count > model.coupling_capacity:
        raise ValueError(f"set_couplings: {count} couplings for {model.coupling_capacity} slots")
    host = {
        "coupling_particle": particle,
        "coupling_tet": np.asarray(tet, dtype=np.int32).reshape(count),
        "coupling_bary": np.asarray(bary, dtype=np.float32).reshape(count, 4),
        "coupling_k": np.asarray(k, dtype=np.float32).reshape(count),
        "coupling_energy_prev": np.zeros(count, dtype=np.float32),
        "coupling_rest": np.zeros((count, 3), dtype=np.float32),
    }
    for name in COUPLING_FIELDS:
        arr = getattr(state, name)
        arr.zero_()
        if count:
            wp.copy(arr, wp.array(host[name], dtype=arr.dtype, device=model.device), count=count)
    state.coupling_count.fill_(count)
