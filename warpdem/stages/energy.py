"""The energy books (DESIGN.md, "Numerics that users trust"): :class:`EnergyBalance`, what every force's work and
every store of energy add up to, read from a model and state (:func:`energy_balance`), with Verlet's shadow term
(:func:`shadow_term`) and the balance's relative error (:func:`balance_error`). ``Simulation.energy`` calls these.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels import rigid as kernels_rigid
from ..model import Model, State
from .bonds import bond_energy
from .cohesive import cohesive_stored
from .contact import contact_energy
from .coupling import coupling_energy
from .fem_contact import fem_contact_energy, sphere_face_dissipated
from .rigid import NODE_FREE_DIRECTIONS, body_energy
from .tets import tet_energy

NODE_RIGID = int(kernels_rigid.NODE_RIGID)


@dataclass
class EnergyBalance:
    """Energy bookkeeping of a DEM/FEM system [J].

    ``total`` = kinetic − shadow + elastic + strain + gravity potential + dissipated + absorbed − work put in.
    Velocity Verlet changes a body's kinetic energy over a step by the trapezoid ½ dt (f_n + f_{n+1})·v_{n+1/2} plus
    the change of its shadow term S = dt²/8 (|f|²/m + |t|²/I) (f the total force with gravity): ``shadow`` is S summed
    over the moving spheres and nodes at the forces held now, so that kinetic − shadow = Σ ½ m v_{n-1/2}·v_{n+1/2},
    the leapfrog kinetic energy, and where every force books the trapezoid the total is constant up to rounding. The
    sphere
    contacts book their dissipation as the scheme does their work (kernels/contact.py): ``dissipated_damping`` (normal
    dashpots, bond dashpots), ``dissipated_friction`` (tangential springs and dashpots, rolling resistance),
    ``bond_trapezoid`` the bonds' springs' -W - ΔU (no dissipation: Verlet's trapezoid work of a spring that turns
    within a step is not its energy change, and the difference has either sign; kernels/bonds.py) and
    ``stiffness_change``, the energy their tangential springs gained without work because k_t follows the overlap
    (Mindlin's k_t = 8 G* sqrt(R* δ); zero for linear laws), which enters the total like work put in. Spheres and FEM
    nodes share the gravity potential; ``kinetic_nodes`` is the FEM nodes' kinetic energy, ``strain`` the tets'
    strain energy, ``dissipated_viscous`` what bulk viscosity and mass-proportional damping took from the continuum,
    ``absorbed_boundaries`` what the non-reflecting boundaries' dashpots took out of the model, ``load_work`` the work
    of pressure loads and velocity drivers on the FEM nodes, and of the pressure loads handed over to the spheres of
    converted tets (kernels/loads.py, Hand-over). ``elastic`` is the energy of the springs of the sphere
    contacts, the bonds, the FEM contacts and intact joint elements; ``dissipated_fem_contact`` is what the node–face
    and node–wall contacts' dashpots and friction took (as Verlet does their work, kernels/fem_contact.py), and the
    springs of failed joints; ``dissipated_sphere_face`` what the sphere–face contacts took, each contact's -W - ΔU
    whole (its work on the sphere and on the face's nodes; kernels/sphere_face.py). ``cohesive_elastic`` is the spring
    energy stored in the intact cohesive elements of split nodes (½ k d², counted in ``in_play``) and
    ``dissipated_cohesive`` what their law dissipated (½ f_c per unit growth of δ_max once open, up to Γ A_f at the
    break), ``cohesive_trapezoid`` the rest of their -W - ΔU: Verlet's work off the law where an element crosses δ_c
    (or its daughters cross each other) within a step, of either sign, 0 where the steps resolve the opening
    (kernels/cohesive.py; warpdem.stages.cohesive). ``released_conversion`` is what left the mechanical books when
    tets turned into spheres (their strain energy and the kinetic energy of their motion about the centroid beyond the
    spheres' spin, the springs of released couplings and the pass's change of the shadow term;
    warpdem.stages.conversion) and
    ``coupling_elastic`` the spring energy of the penalty couplings between converted spheres and the continuum (in
    ``in_play``; warpdem.stages.coupling). ``kinetic_rigid`` is the rigid blocks' kinetic energy ½ M v² + ½ L·ω (their
    nodes are not counted in ``kinetic_nodes``) and ``released_rigid_switch`` what left the books when blocks turned
    rigid: the strain energy of their tets and the kinetic energy of the element modes, with the switch's change of the
    shadow term (warpdem.stages.rigid). ``contact_topology`` is the energy the FEM contacts' springs gained without work
    at split and conversion passes (Simulation._book_contact_topology), which enters the total like work put in.
    ``step_change`` is what changes of the time step between steps changed the shadow term by, S(dt_new) − S(dt_old)
    (:meth:`Simulation.set_time_step`): each step books its own trapezoid and shadow term at its own dt, so the
    leapfrog kinetic energy of the steps before a change (kinetic − S(dt_old)) and after it (kinetic − S(dt_new))
    differ by that, with no force working. A split pass changes the forces instead (lighter daughters, a face's
    share of a contact force on one daughter, the re-evaluation at dt = 0) at the same velocities: its
    S(f_new) − S(f_old) goes to the same line.
    """

    kinetic_translational: float
    kinetic_rotational: float
    elastic: float
    gravity_potential: float
    dissipated_damping: float
    dissipated_friction: float
    released_by_bond_breakage: float
    boundary_work: float
    kinetic_nodes: float = 0.0
    strain: float = 0.0
    dissipated_viscous: float = 0.0
    load_work: float = 0.0
    dissipated_fem_contact: float = 0.0
    absorbed_boundaries: float = 0.0
    stiffness_change: float = 0.0
    shadow: float = 0.0
    cohesive_elastic: float = 0.0
    dissipated_cohesive: float = 0.0
    released_conversion: float = 0.0
    coupling_elastic: float = 0.0
    kinetic_rigid: float = 0.0
    released_rigid_switch: float = 0.0
    contact_topology: float = 0.0
    step_change: float = 0.0
    dissipated_sphere_face: float = 0.0
    bond_trapezoid: float = 0.0
    cohesive_trapezoid: float = 0.0

    @property
    def kinetic(self) -> float:
        return self.kinetic_translational + self.kinetic_rotational + self.kinetic_nodes + self.kinetic_rigid

    @property
    def in_play(self) -> float:
        """Energy in play [J]: the larger of kinetic + elastic + strain and the work put in so far by walls, driven
        spheres and loads. It holds no gravity potential, whose datum (where z = 0 is) is arbitrary: the balance's
        error is scaled by its largest value over a run."""
        stored = self.kinetic + self.elastic + self.strain + self.cohesive_elastic + self.coupling_elastic
        return max(stored, abs(self.boundary_work) + abs(self.load_work))

    @property
    def total(self) -> float:
        return (
            self.kinetic
            - self.shadow
            + self.elastic
            + self.gravity_potential
            + self.dissipated_damping
            + self.dissipated_friction
            + self.released_by_bond_breakage
            - self.boundary_work
            + self.strain
            + self.dissipated_viscous
            - self.load_work
            + self.dissipated_fem_contact
            + self.absorbed_boundaries
            - self.stiffness_change
            + self.cohesive_elastic
            + self.dissipated_cohesive
            + self.released_conversion
            + self.coupling_elastic
            + self.released_rigid_switch
            - self.contact_topology
            + self.step_change
            + self.dissipated_sphere_face
            + self.bond_trapezoid
            + self.cohesive_trapezoid
        )


def balance_error(start: EnergyBalance, now: EnergyBalance, in_play: float) -> float:
    """Relative error of the energy balance [-]: the drift of ``total`` since ``start``, relative to ``in_play``, the
    largest :attr:`EnergyBalance.in_play` over the frames so far (no gravity potential, so no arbitrary datum scales
    it). The summary and the time series (warpdem.io.timeseries) both print this number."""
    return (now.total - start.total) / max(in_play, 1e-300)


def energy_balance(m: Model, s: State) -> EnergyBalance:
    """The energy balance of a model and state now (reads back; call between steps)."""
    n = int(s.particle_count.numpy()[0])
    mass = m.particle_mass.numpy()[:n].astype(np.float64)
    radius = m.particle_radius.numpy()[:n].astype(np.float64)
    free = m.particle_motion.numpy()[:n] == 0
    v = s.particle_qd.numpy()[:n].astype(np.float64)
    w = s.particle_omega.numpy()[:n].astype(np.float64)
    q = s.particle_q.numpy()[:n].astype(np.float64)
    inertia = 0.4 * mass * radius**2
    e_contact, _ = contact_energy(m, s)
    e_fem, d_fem = fem_contact_energy(m, s)
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
        gravity_potential=float(-np.sum(mass[free] * (q[free] @ g)) - np.sum(node_mass[moving] * (node_q[moving] @ g))),
        dissipated_damping=float(s.energy_damping.numpy()[:n].sum()),
        dissipated_friction=float(s.energy_friction.numpy()[:n].sum()),
        released_by_bond_breakage=float(s.energy_bond_broken.numpy()[:n].sum()),
        boundary_work=float(s.energy_boundary_work.numpy()[:n].sum()),
        kinetic_nodes=float(0.5 * np.sum(node_mass * np.sum(node_v * node_v, axis=1))),
        strain=tet_energy(m, s),
        dissipated_viscous=float(s.node_energy_damping.numpy()[:nn].sum()),
        # The pressure faces handed over to converted tets' spheres book their work per face, on the same line.
        load_work=float(s.node_energy_boundary_work.numpy()[:nn].sum()) + float(s.load_face_work.numpy().sum()),
        dissipated_fem_contact=d_fem,
        absorbed_boundaries=float(s.node_energy_absorbed.numpy()[:nn].sum()),
        stiffness_change=float(s.energy_stiffness_change.numpy()[:n].sum()),
        cohesive_elastic=e_cohesive,
        dissipated_cohesive=float(s.node_energy_cohesive.numpy()[:nn].sum()),
        cohesive_trapezoid=float(s.node_energy_cohesive_trapezoid.numpy()[:nn].sum()),
        released_conversion=float(s.energy_released_conversion.numpy()[0]),
        coupling_elastic=coupling_energy(m, s),
        kinetic_rigid=kinetic_rigid,
        released_rigid_switch=float(s.energy_released_rigid.numpy()[0]),
        contact_topology=float(s.energy_contact_topology.numpy()[0]),
        step_change=float(s.energy_step_change.numpy()[0]),
        dissipated_sphere_face=sphere_face_dissipated(m, s),
        bond_trapezoid=float(s.energy_bond_trapezoid.numpy()[:n].sum()),
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
    return float(m.dt**2 / 8.0 * total) + body_energy(m, s)[1]
