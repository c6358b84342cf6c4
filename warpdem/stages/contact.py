"""Contact stage (host side): hash-grid neighbour list with a Verlet skin, and contact forces.

The neighbour list is rebuilt only when some sphere has moved more than half the skin since the last build (the
integrator raises ``State.rebuild_flag`` on the device). The rebuild is a conditional branch
(``wp.capture_if``), so the step stays one graph on CPU and CUDA and never reads the flag back to the host. The
builder is the generic skinned-list builder of :mod:`warpdem.stages.neighbors`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import warp as wp

from ..kernels import contact as kc
from ..model import Model, State
from .guard import CriticalStep
from .neighbors import SkinnedList, SlotArrays, finish_rebuild, make_struct


def hash_grid_dims(n: int) -> int:
    """Cells per axis of the hash grid: about one cell per particle, at least 16³ and at most 256³."""
    return int(min(256, max(16, round(n ** (1.0 / 3.0)))))


class NeighborList:
    """Builds the half neighbour list of a Model/State pair and holds its scratch buffers.

    Args:
        model: the model (radii, capacities).
        state: the state whose ``nbr_*`` arrays are rebuilt in place.
    """

    def __init__(self, model: Model, state: State) -> None:
        self.model = model
        self.state = state
        device = model.device
        cap = model.particle_capacity
        # A float64 grid over the float64 centres: no float32 copy to keep, and the same candidates at any offset.
        self.grid = wp.HashGrid(*(hash_grid_dims(model.grid_owners or cap),) * 3, device=device, dtype=wp.float64)
        # Reserve for every slot now, so that a rebuild inside a captured graph never allocates.
        self.grid.reserve(cap)
        self.cell = 2.0 * model.max_radius + model.skin
        history = {"shear": wp.vec3, "bond": int}
        self.list = SkinnedList(kc.NEIGHBOR_LIST, cap, model.max_neighbors, device, history)
        # The scratch list, by name (the benchmark counts its memory).
        self.new_count, self.new_index = self.list.new.count, self.list.new.index
        self.new_shear, self.new_bond = self.list.new.history.shear, self.list.new.history.bond

    def rebuild(self) -> None:
        """Rebuild the list now (launches only: usable inside a graph capture)."""
        m, s = self.model, self.state
        self.grid.build(s.particle_q, self.cell)
        inputs = make_struct(
            kc.NeighborInputs,
            particle_radius=m.particle_radius,
            particle_q=s.particle_q,
            skin=m.skin,
            search_radius=self.cell,
            bond_count=s.bond_count,
            bond_key=s.bond_key,
        )
        history = make_struct(kc.NeighborHistory, shear=s.nbr_shear, bond=s.nbr_bond)
        lists = SlotArrays(s.nbr_count, s.nbr_index, history)
        self.list.rebuild(inputs, self.grid, s.particle_count, s.particle_q, s.particle_count, lists, s.nbr_needed)
        finish_rebuild(s.particle_count, s.particle_q, s.particle_q_at_build, s.rebuild_flag, s.rebuild_total, m.device)

    def rebuild_if_needed(self) -> None:
        """Rebuild when the device flag says so: a conditional graph node under capture, a branch otherwise."""
        wp.capture_if(self.state.rebuild_flag, on_true=self.rebuild)


def eval_contacts(model: Model, state: State, track_energy: bool, dt: float | None = None) -> None:
    """Accumulate sphere–sphere and sphere–wall contact forces and torques into ``state.particle_f/t``.

    ``dt`` overrides the model step for the history increments; 0 evaluates forces without advancing any
    history (the initial evaluation, as LIGGGHTS does at set-up).
    """
    kernel, _ = kc.make_contact_kernels(model.normal_model, model.tangential_model, model.rolling_model, track_energy)
    m, s = model, state
    wp.launch(
        kernel,
        dim=m.particle_capacity,
        inputs=[
            # Model:
            m.particle_radius,
            m.particle_inv_mass,
            m.particle_material,
            m.pair_table,
            m.num_materials,
            m.wall_normal,
            m.wall_velocity,
            m.wall_material,
            m.num_walls,
            m.max_neighbors,
            m.dt if dt is None else dt,
            # State in:
            s.particle_count,
            s.particle_q,
            s.particle_qd,
            s.particle_omega,
            s.nbr_count,
            s.nbr_index,
            s.nbr_bond,
            s.bond_broken,
            s.wall_point,
        ],
        outputs=[
            s.nbr_shear,
            s.wall_shear,
            s.particle_f,
            s.particle_t,
            s.contact_sums,
            s.contact_energy_prev,
            s.energy_damping,
            s.energy_friction,
            s.energy_stiffness_change,
            s.energy_boundary_work,
        ],
        device=m.device,
    )


def launch_contact_energy(model: Model, state: State, energy: wp.array, count: wp.array) -> None:
    """Each live sphere's share of the elastic energy of its contacts [J] into ``energy`` (float64, shape
    (particle_capacity,)) and the number of touching sphere–sphere pairs added to ``count[0]`` (launch only)."""
    _, kernel = kc.make_contact_kernels(model.normal_model, model.tangential_model, model.rolling_model, False)
    m, s = model, state
    wp.launch(
        kernel,
        dim=m.particle_capacity,
        inputs=[
            m.particle_radius,
            m.particle_inv_mass,
            m.particle_material,
            m.pair_table,
            m.num_materials,
            m.wall_normal,
            m.wall_material,
            m.num_walls,
            m.max_neighbors,
            s.particle_count,
            s.particle_q,
            s.nbr_count,
            s.nbr_index,
            s.nbr_bond,
            s.bond_broken,
            s.nbr_shear,
            s.wall_point,
            s.wall_shear,
        ],
        outputs=[energy, count],
        device=m.device,
    )


def contact_energy(model: Model, state: State) -> tuple[float, int]:
    """Elastic energy stored in the contacts [J] (normal and tangential springs) and the number of touching
    sphere–sphere pairs. Allocates and reads back: call between steps."""
    energy = wp.zeros(model.particle_capacity, dtype=wp.float64, device=model.device)
    count = wp.zeros(1, dtype=int, device=model.device)
    launch_contact_energy(model, state, energy, count)
    return float(energy.numpy().sum()), int(count.numpy()[0])


def wall_forces(model: Model, state: State) -> np.ndarray:
    """Force of the spheres on each wall now [N], shape (num_walls, 3), float64: minus the sum of the sphere–wall
    contact forces, the step's law evaluated without advancing the springs. Allocates and reads back: call between
    steps."""
    out = wp.zeros(model.num_walls, dtype=wp.vec3d, device=model.device)
    if model.num_walls and model.max_radius > 0.0:
        m, s = model, state
        wp.launch(
            kc.make_wall_force_kernel(m.normal_model, m.tangential_model, m.rolling_model),
            dim=m.particle_capacity,
            inputs=[
                # Model:
                m.particle_radius,
                m.particle_inv_mass,
                m.particle_material,
                m.pair_table,
                m.num_materials,
                m.wall_normal,
                m.wall_velocity,
                m.wall_material,
                m.num_walls,
                # State in:
                s.particle_count,
                s.particle_q,
                s.particle_qd,
                s.particle_omega,
                s.wall_point,
                s.wall_shear,
            ],
            outputs=[out],
            device=m.device,
        )
    return out.numpy().reshape(model.num_walls, 3).astype(np.float64)


def neighbor_pairs(model: Model, state: State) -> np.ndarray:
    """The (i, j) pairs, i < j, held in the neighbour list, shape (P, 2), sorted (for tests and bond building)."""
    cap, k = model.particle_capacity, model.max_neighbors
    n = int(state.particle_count.numpy()[0])
    counts = np.minimum(state.nbr_count.numpy()[:n], k)
    index = state.nbr_index.numpy().reshape(cap, k)[:n]
    used = np.arange(k)[None, :] < counts[:, None]
    rows = np.broadcast_to(np.arange(n)[:, None], (n, k))
    pairs = np.stack([rows[used], index[used]], axis=1).astype(np.int64)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


def critical_time_step_hertz(radius, density, young, poisson):
    """Rayleigh time step of a sphere, π r sqrt(ρ/G) / (0.1631 ν + 0.8766) [s] (the usual Hertz DEM bound); floats
    or numpy arrays of one shape."""
    shear = young / (2.0 * (1.0 + poisson))
    return math.pi * radius * np.sqrt(density / shear) / (0.1631 * poisson + 0.8766)


def sphere_contact_steps(
    normal: str,
    radius: np.ndarray,
    mass: np.ndarray,
    young: np.ndarray,
    poisson: np.ndarray,
    estar: np.ndarray,
    speed: float,
    describe: Callable[[int], str],
    density: np.ndarray | None = None,
) -> list[CriticalStep]:
    """The critical steps of the spheres' contacts [s] before the safety factor, one per bound, each set by its
    smallest sphere.

    Hertz: the Rayleigh step (:func:`critical_time_step_hertz`; ρ = m / (4/3 π r³) unless ``density`` is given: a
    converted tet's sphere carries the tet's mass ρV in a smaller ball) and a tenth of the Hertz contact time of two
    such spheres at the approach ``speed``, 2.87 (m*² / (r* E*² v))^(1/5) with m* = m/2, r* = r/2 (none at rest).
    Linear: 2 sqrt(m* / k_n), k_n = E r of two such spheres (the linear law's 2 E_a r_a E_b r_b / (E_a r_a + E_b r_b)).

    Args:
        normal: the normal law, "hertz" or "linear".
        radius: [m], shape (N,).
        mass: [kg], shape (N,).
        young: E [Pa] of each sphere's material, shape (N,).
        poisson: ν [-] of each sphere's material, shape (N,).
        estar: E* [Pa] of each sphere's material with itself, shape (N,).
        speed: the fastest approach, twice the largest sphere speed [m/s].
        describe: the words for sphere k ("spheres of material … (r = …)").
        density: the material's density [kg/m³], shape (N,), where mass = ρ 4/3 π r³ (the builder's spheres).
    """
    if normal == "hertz":
        if density is None:
            density = mass / (4.0 / 3.0 * math.pi * radius**3)
        steps = {"the Rayleigh step of the smallest {}": critical_time_step_hertz(radius, density, young, poisson)}
        if speed > 0.0:
            mstar, rstar = 0.5 * mass, 0.5 * radius
            impact = 0.1 * 2.87 * (mstar**2 / (rstar * estar**2 * speed)) ** 0.2
            steps[f"a tenth of the Hertz contact of {{}} at {speed:.3g} m/s"] = impact
    else:
        steps = {"the linear contact of the smallest {}": 2.0 * np.sqrt(0.5 * mass / (young * radius))}
    found = []
    for words, values in steps.items():
        k = int(np.argmin(values))
        found.append(CriticalStep(float(values[k]), words.format(describe(k))))
    return found
