"""Bond stage (host side): bonded-particle forces and breakage, bond creation at build time, and removal of
broken bonds by the compaction helper."""

from __future__ import annotations

import numpy as np
import warp as wp

from .compaction import Compactor
from .contact import hash_grid_dims
from .kernels import bonds as kb
from .model import BOND_FIELDS, Model, State


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
            s.contact_f_normal,
            s.contact_f_tangential,
            s.contact_t_tangential,
            s.energy_damping,
            s.energy_friction,
            s.energy_bond_broken,
            s.particle_bonds_broken,
        ],
        device=m.device,
    )


def bond_energy(model: Model, state: State) -> tuple[float, int]:
    """Elastic energy of the intact bonds [J] and their number. Allocates and reads back: call between steps."""
    energy = wp.zeros(1, dtype=wp.float64, device=model.device)
    intact = wp.zeros(1, dtype=int, device=model.device)
    if model.bond_capacity:
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
    return float(energy.numpy()[0]), int(intact.numpy()[0])


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
