"""Bond stage (host side): bonded-particle forces and breakage, bond creation at build time, removal of broken bonds
by the compaction helper, and the stable step of bonded spheres."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from ..host_data import BondData, ParticleData
from ..kernels import bonds as kb
from ..model import BOND_FIELDS, Model, State
from .compaction import Compactor
from .contact import hash_grid_dims
from .guard import CriticalStep

if TYPE_CHECKING:
    from ..materials import MaterialProps


def eval_bonds(model: Model, state: State, dt: float | None = None, track_energy: bool = True) -> None:
    """Accumulate the forces of intact bonds and break those at their strength (``dt`` as in eval_contacts); with
    ``track_energy`` book their dissipation (kernels/bonds.py)."""
    if model.bond_capacity == 0:
        return
    m, s = model, state
    wp.launch(
        kb.eval_bonds_kernel,
        dim=m.bond_capacity,
        inputs=[
            # Model:
            m.particle_radius,
            m.particle_inv_mass,
            m.dt if dt is None else dt,
            # State in:
            s.particle_q,
            s.particle_qd,
            s.particle_omega,
            s.bond_count,
            s.bond_i,
            s.bond_j,
            s.bond_rest_length,
            s.bond_kn,
            s.bond_ks,
            s.bond_area,
            s.bond_tensile_strength,
            s.bond_shear_strength,
            s.bond_damping,
            # In:
            int(track_energy),
        ],
        outputs=[
            s.bond_shear,
            s.bond_broken,
            s.bonds_broken_total,
            s.bond_energy_prev,
            s.particle_f,
            s.particle_t,
            s.contact_sums,
            s.energy_damping,
            s.energy_friction,
            s.energy_bond_broken,
            s.energy_bond_trapezoid,
            s.particle_bonds_broken,
        ],
        device=m.device,
    )


def launch_bond_energy(model: Model, state: State, energy: wp.array, intact: wp.array) -> None:
    """Each intact live bond's elastic energy [J] into ``energy`` (float64, shape (bond_capacity,); other slots left
    as they are: zero it first) and the number of intact bonds added to ``intact[0]`` (launch only)."""
    if model.bond_capacity == 0:
        return
    s = state
    wp.launch(
        kb.bond_energy_kernel,
        dim=model.bond_capacity,
        inputs=[
            s.particle_q,
            s.bond_count,
            s.bond_i,
            s.bond_j,
            s.bond_rest_length,
            s.bond_kn,
            s.bond_ks,
            s.bond_shear,
            s.bond_broken,
        ],
        outputs=[energy, intact],
        device=model.device,
    )


def bond_energy(model: Model, state: State) -> tuple[float, int]:
    """Elastic energy of the intact bonds [J] and their number. Allocates and reads back: call between steps."""
    energy = wp.zeros(model.bond_capacity, dtype=wp.float64, device=model.device)
    intact = wp.zeros(1, dtype=int, device=model.device)
    launch_bond_energy(model, state, energy, intact)
    return float(energy.numpy().sum()), int(intact.numpy()[0])


def compact_bonds(model: Model, state: State, compactor: Compactor) -> None:
    """Remove broken bonds: compact every bond array and remap the neighbour slots' bond indices."""
    if model.bond_capacity == 0:
        return
    compactor.remove(
        state.bond_count, state.bond_broken, [getattr(state, name) for name in BOND_FIELDS], remap=[state.nbr_bond]
    )


def find_bond_pairs(
    q: np.ndarray, radius: np.ndarray, group: np.ndarray, gap_tolerance: float, device: wp.context.Device
) -> np.ndarray:
    """Pairs (i < j) of spheres in the same bond group (> 0) whose gap is at most ``gap_tolerance * (r_i + r_j)``.

    A count → exclusive scan → fill pass over a hash grid.

    Args:
        q: centres [m], shape (N, 3).
        radius: radii [m], shape (N,).
        group: bond group of each sphere, 0 = not bonded, shape (N,).
        gap_tolerance: relative gap tolerance [-].
        device: Warp device.

    Returns:
        Sorted pairs, shape (M, 2), int32.
    """
    n = len(radius)
    if n == 0 or not np.any(group):
        return np.zeros((0, 2), dtype=np.int32)
    search = float(2.0 * radius.max() * (1.0 + gap_tolerance))
    wq = wp.array(np.asarray(q, dtype=np.float64), dtype=wp.vec3d, device=device)
    wr = wp.array(radius.astype(np.float32), dtype=float, device=device)
    wg = wp.array(group.astype(np.int32), dtype=int, device=device)
    grid = wp.HashGrid(*(hash_grid_dims(n),) * 3, device=device, dtype=wp.float64)
    grid.build(wq, search)
    counts = wp.zeros(n, dtype=int, device=device)
    common = [wr, float(gap_tolerance), search, grid.id, wq, wg]
    wp.launch(kb.count_bond_pairs_kernel, dim=n, inputs=common, outputs=[counts], device=device)
    offsets = wp.zeros(n, dtype=int, device=device)
    wp.utils.array_scan(counts, offsets, inclusive=False)
    total = int(offsets.numpy()[-1] + counts.numpy()[-1])
    pairs = wp.zeros(max(total, 1), dtype=wp.vec2i, device=device)
    wp.launch(kb.fill_bond_pairs_kernel, dim=n, inputs=[*common, offsets], outputs=[pairs], device=device)
    out = pairs.numpy()[:total].astype(np.int32)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


def sphere_masses(particles: ParticleData, materials: dict[str, MaterialProps]) -> np.ndarray:
    """Mass of each sphere, ρ (4/3) π r³ [kg], shape (N,)."""
    density = np.array([m.density for m in materials.values()])[particles.material]
    return density * 4.0 / 3.0 * math.pi * particles.radius**3


def bond_critical_step(
    mass: np.ndarray, part: np.ndarray, bonds: BondData, part_names: Sequence[str] = ()
) -> CriticalStep:
    """Stable step [s] of the bonded spheres, from the stiffest mode each sphere can have, and the bond that sets it.

    A sphere with Z bonds, mass m and I = (2/5) m r² has a translational mode ω² = Z k_n / m and a rotational one
    ω² = Z (k_s r²)·2 / I = 5 Z k_s / m (neighbours counter-rotating). Explicit central differences are stable for
    dt < (2/ω)(sqrt(1 + ζ²) - ζ), ζ the mode's damping ratio. The bond dashpot c = 2 ζ sqrt(m* k) with m* = m/2
    gives ζ/√2 in translation and sqrt(5/2) ζ ≈ 1.58 ζ in rotation, where the small moment of inertia makes the
    same dashpot relatively much stronger.

    Args:
        mass: the spheres' masses [kg], shape (N,); part: their part ids, shape (N,).
        bonds: the bonds (``pairs`` index the spheres), their ``kn``, ``ks`` [N/m] and ``damping`` ζ [-].
    """
    z = np.bincount(bonds.pairs.ravel(), minlength=len(mass)).astype(np.float64)
    i, j = bonds.pairs[:, 0], bonds.pairs[:, 1]
    m = np.minimum(mass[i], mass[j])
    zmax = np.maximum(z[i], z[j])
    zeta = np.asarray(bonds.damping, dtype=np.float64)

    def step(omega2: np.ndarray, damping_ratio: np.ndarray) -> np.ndarray:
        return 2.0 / np.sqrt(omega2) * (np.sqrt(1.0 + damping_ratio**2) - damping_ratio)

    modes = {
        "translational": step(zmax * bonds.kn / m, zeta / math.sqrt(2.0)),
        "rotational": step(5.0 * zmax * bonds.ks / m, 1.58 * zeta),
    }
    mode, steps = min(modes.items(), key=lambda item: float(item[1].min()))
    k = int(np.argmin(steps))
    owner = int(part[i[k]])
    name = f" of part {part_names[owner]}" if owner < len(part_names) else ""
    return CriticalStep(
        float(steps[k]), f"the bond between spheres{name} ({mode} mode, {int(zmax[k])} bonds on a sphere)"
    )


COINCIDENT = 1e-6
"""Two bonded spheres whose centres are closer than this times the sum of their radii coincide: their bond has no
direction and an infinite stiffness E A / L0."""


class CoincidentSpheresError(ValueError):
    """Two spheres of a bonded group have the same centre (a particle source given twice, usually).

    Attributes:
        group: index of the bonded group (the scene's ``bonds[group]``). i, j: sphere ids (creation order).
    """

    def __init__(self, group: int, i: int, j: int, center: np.ndarray) -> None:
        super().__init__(
            f"spheres {i} and {j} have the same centre {np.round(center, 9).tolist()} m; a bond needs two distinct "
            "centres (is a particle source given twice?)"
        )
        self.group, self.i, self.j = group, i, j


def bonded_group_bonds(groups: Sequence[tuple], particles: ParticleData, device: wp.context.Device) -> BondData:
    """Bonds of every bonded group (pairs found with the hash grid, :func:`find_bond_pairs`), with their springs and
    strengths: k_n = E_b A / L_0 with A = π (λ min(r_i, r_j))², k_s = k_n / ratio.

    Args:
        groups: (sphere ids, (E_b, σ_t, τ_c, k_n/k_s, λ, search tolerance, ζ)) per group, as
            :meth:`warpdem.build.builder.ModelBuilder.add_bonded_group` keeps them; a sphere belongs to the last group
            that names it.
        particles: the spheres. device: where the pairs are searched.

    Raises:
        CoincidentSpheresError: two spheres of a group share a centre.
    """
    parts: list[BondData] = []
    group = np.zeros(len(particles), dtype=np.int32)
    for k, (ids, _) in enumerate(groups):
        group[ids] = k + 1  # a sphere belongs to the last group that names it
    for k, (_, props) in enumerate(groups):
        e_b, sig_t, tau_c, ratio, lam, tol, zeta = props
        mine = np.where(group == k + 1, 1, 0)
        pairs = find_bond_pairs(particles.q, particles.radius, mine, tol, device)
        if len(pairs) == 0:
            continue
        i, j = pairs[:, 0], pairs[:, 1]
        length = np.linalg.norm(particles.q[i] - particles.q[j], axis=1)
        coincident = np.nonzero(length <= COINCIDENT * (particles.radius[i] + particles.radius[j]))[0]
        if len(coincident):
            a, b = int(i[coincident[0]]), int(j[coincident[0]])
            raise CoincidentSpheresError(k, a, b, particles.q[a])
        area = math.pi * (lam * np.minimum(particles.radius[i], particles.radius[j])) ** 2
        kn = e_b * area / length
        m = len(pairs)
        parts.append(
            BondData(
                pairs=pairs,
                rest_length=length,
                kn=kn,
                ks=kn / ratio,
                area=area,
                tensile_strength=np.full(m, sig_t),
                shear_strength=np.full(m, tau_c),
                damping=np.full(m, zeta),
            )
        )
    if not parts:
        return BondData.empty()
    return BondData(*(np.concatenate([getattr(p, f) for p in parts]) for f in BondData.__dataclass_fields__))
