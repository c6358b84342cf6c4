"""The energy books summed on the host: the brute-force reference the device books (kernels/books.py,
warpdem.stages.energy.DeviceBooks) are tested against (tests/test_books.py). Every per-item array is read back whole
and summed by NumPy (pairwise summation in float64); the kinetic energies, the gravity potential, the shadow term
and the joints' springs are computed here in NumPy from the state's float32 values, independently of the kernels.
"""

from __future__ import annotations

import numpy as np
from warpdem.kernels import rigid as kernels_rigid

from warpdem.model import Model, State
from warpdem.stages.bonds import bond_energy
from warpdem.stages.cohesive import cohesive_stored
from warpdem.stages.contact import contact_energy
from warpdem.stages.coupling import coupling_energy
from warpdem.stages.energy import EnergyBalance
from warpdem.stages.fem_contact import fem_contact_energy, sphere_face_rows
from warpdem.stages.rigid import NODE_FREE_DIRECTIONS, body_energy
from warpdem.stages.tets import tet_energy

NODE_RIGID = int(kernels_rigid.NODE_RIGID)


def reference_balance(m: Model, s: State, absolute: bool = False) -> EnergyBalance:
    """The energy balance of a model and state now, every line read back whole and summed in NumPy in float64 (the
    books as warpdem computed them before kernels/books.py). ``absolute``: each line as the sum of its terms'
    magnitudes Σ|t| instead (the scale of a sum's rounding error; the stores' terms are ≥ 0 and unchanged)."""

    def add(x: np.ndarray) -> float:
        return float(np.abs(x).sum() if absolute else x.sum())

    n = int(s.particle_count.numpy()[0])
    mass = m.particle_mass.numpy()[:n].astype(np.float64)
    radius = m.particle_radius.numpy()[:n].astype(np.float64)
    free = m.particle_motion.numpy()[:n] == 0
    v = s.particle_qd.numpy()[:n].astype(np.float64)
    w = s.particle_omega.numpy()[:n].astype(np.float64)
    q = s.particle_q.numpy()[:n].astype(np.float64)
    inertia = 0.4 * mass * radius**2
    e_contact, _ = contact_energy(m, s)
    e_fem, _ = fem_contact_energy(m, s)
    e_bond, _ = bond_energy(m, s)
    g = np.asarray(m.gravity, dtype=np.float64)
    nn = int(s.node_count.numpy()[0])
    e_cohesive = cohesive_stored(m, s) if m.cohesive_capacity else 0.0
    node_mass = m.node_mass.numpy()[:nn].astype(np.float64)
    node_v = s.node_qd.numpy()[:nn].astype(np.float64)
    # The nodes of rigid bodies move with them: the bodies' own kinetic energy counts (kinetic_rigid).
    node_v[m.node_motion.numpy()[:nn] == NODE_RIGID] = 0.0
    kinetic_rigid, _ = body_energy(m, s)
    # X + u in float64 rather than the float32 sum node_q, so the potential keeps the displacements' precision.
    node_q = m.node_ref_q.numpy()[:nn].astype(np.float64) + s.node_u.numpy()[:nn].astype(np.float64)
    moving = m.node_inv_mass.numpy()[:nn] > 0.0
    return EnergyBalance(
        shadow=shadow_term(m, s, mass, free, g),
        kinetic_translational=float(0.5 * np.sum(mass * np.sum(v * v, axis=1))),
        kinetic_rotational=float(0.5 * np.sum(inertia * np.sum(w * w, axis=1))),
        elastic=e_contact + e_bond + e_fem,
        gravity_potential=-add(mass[free] * (q[free] @ g)) - add(node_mass[moving] * (node_q[moving] @ g)),
        dissipated_damping=add(s.energy_damping.numpy()[:n]),
        dissipated_friction=add(s.energy_friction.numpy()[:n]),
        released_by_bond_breakage=add(s.energy_bond_broken.numpy()[:n]),
        boundary_work=add(s.energy_boundary_work.numpy()[:n]),
        kinetic_nodes=float(0.5 * np.sum(node_mass * np.sum(node_v * node_v, axis=1))),
        strain=tet_energy(m, s),
        dissipated_viscous=add(s.node_energy_damping.numpy()[:nn]),
        # The pressure faces handed over to converted tets' spheres book their work per face, on the same line.
        load_work=add(s.node_energy_boundary_work.numpy()[:nn]) + add(s.load_face_work.numpy()),
        dissipated_fem_contact=add(s.node_energy_contact.numpy()[:nn]) if m.node_capacity and m.face_capacity else 0.0,
        absorbed_boundaries=add(s.node_energy_absorbed.numpy()[:nn]),
        stiffness_change=add(s.energy_stiffness_change.numpy()[:n]),
        cohesive_elastic=e_cohesive,
        dissipated_cohesive=add(s.node_energy_cohesive.numpy()[:nn]),
        cohesive_trapezoid=add(s.node_energy_cohesive_trapezoid.numpy()[:nn]),
        released_conversion=add(s.energy_released_conversion.numpy()[:1]),
        coupling_elastic=coupling_energy(m, s),
        kinetic_rigid=kinetic_rigid,
        released_rigid_switch=add(s.energy_released_rigid.numpy()[:1]),
        contact_topology=add(s.energy_contact_topology.numpy()[:1]),
        step_change=add(s.energy_step_change.numpy()[:1]),
        dissipated_sphere_face=(
            (add(s.sphere_face_dissipated.numpy()[:n]) if sphere_face_rows(m) else 0.0)
            + add(s.node_energy_sphere_face.numpy()[:nn])
            if m.face_capacity
            else 0.0
        ),
        bond_trapezoid=add(s.energy_bond_trapezoid.numpy()[:n]),
        substep_work=add(s.node_energy_substep.numpy()[:nn]),
    )


def shadow_term(m: Model, s: State, mass: np.ndarray, free: np.ndarray, g: np.ndarray) -> float:
    """Verlet's shadow term dt²/8 Σ (|f + m g|²/m + |t|²/I) [J] of the free spheres and the kicked velocity
    components of the FEM nodes (not those a velocity driver holds), at the forces held now; ``mass`` and
    ``free`` of the live spheres, ``g`` the gravity [m/s²]."""
    n, nn = int(s.particle_count.numpy()[0]), int(s.node_count.numpy()[0])
    f = s.particle_f.numpy()[:n].astype(np.float64)[free] + mass[free, None] * g
    t = s.particle_t.numpy()[:n].astype(np.float64)[free]
    inv_inertia = m.particle_inv_inertia.numpy()[:n].astype(np.float64)[free]
    total = np.sum(np.sum(f * f, axis=1) / mass[free]) + np.sum(inv_inertia * np.sum(t * t, axis=1))
    if nn:
        inv_mass = m.node_inv_mass.numpy()[:nn].astype(np.float64)
        kicked = inv_mass > 0.0
        if m.loads is not None and m.loads.num_drivers:
            kicked &= m.loads.node_driver.numpy()[:nn] < 0
        a = s.node_f.numpy()[:nn].astype(np.float64) * inv_mass[:, None] + g
        a *= NODE_FREE_DIRECTIONS[m.node_motion.numpy()[:nn]]
        node_mass = m.node_mass.numpy()[:nn].astype(np.float64)
        total += np.sum((node_mass * np.sum(a * a, axis=1))[kicked])
        # The sub-steps' part, (dt/n)²/8 |f_c|²/m of the cohesive forces kept apart (warpdem.stages.substep).
        fast = s.node_f_fast.numpy()[:nn].astype(np.float64) * inv_mass[:, None]
        fast *= NODE_FREE_DIRECTIONS[m.node_motion.numpy()[:nn]]
        total += np.sum((node_mass * np.sum(fast * fast, axis=1))[kicked]) / m.cohesive_substeps**2
    return float(m.dt**2 / 8.0 * total) + body_energy(m, s)[1]
