"""The energy books (DESIGN.md, "Numerics that users trust"): :class:`EnergyBalance`, what every force's work and
every store of energy add up to, reduced on the device from a model and state (:class:`DeviceBooks`,
:func:`energy_balance`; kernels/books.py) with Verlet's shadow term among them, and the balance's relative error
(:func:`balance_error`). ``Simulation.energy`` and ``Simulation.shadow`` call these: one read-back of a few float64
values each.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import warp as wp

from ..kernels import books as kbk
from ..model import Model, State
from .bonds import launch_bond_energy
from .cohesive import launch_cohesive_stored
from .contact import launch_contact_energy
from .coupling import launch_coupling_energy
from .fem_contact import (
    launch_fem_contact_energy,
    launch_sphere_face_energy,
    sphere_face_rows,
)
from .guard import energy_from_nowhere
from .rigid import has_bodies
from .tets import tet_energies


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
    S(f_new) − S(f_old) goes to the same line. With the cohesive elements' daughters sub-stepped
    (``Model.cohesive_substeps`` n > 1; warpdem.stages.substep) the shadow term holds their sub-steps' part too,
    (dt/n)²/8 |f_c|²/m of the cohesive forces, and ``substep_work`` is the work the other forces did over those
    nodes' sub-stepped motion beyond what their lines book against the step's mean velocity (either sign; it enters
    the total like work put in).
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
    substep_work: float = 0.0

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
            - self.substep_work
        )


def balance_error(start: EnergyBalance, now: EnergyBalance, in_play: float) -> float:
    """Relative error of the energy balance [-]: the drift of ``total`` since ``start``, relative to ``in_play``, the
    largest :attr:`EnergyBalance.in_play` over the frames so far (no gravity potential, so no arbitrary datum scales
    it). The summary and the time series (warpdem.io.timeseries) both print this number."""
    return (now.total - start.total) / max(in_play, 1e-300)


LINE = {f.name: k for k, f in enumerate(fields(EnergyBalance))}
"""Index of each line of :class:`EnergyBalance` in the device books' vector (kernels/books.py)."""
assert len(LINE) == kbk.LINES and all(
    LINE[name] == int(index)
    for name, index in (
        ("kinetic_translational", kbk.KINETIC_TRANSLATIONAL),
        ("kinetic_rotational", kbk.KINETIC_ROTATIONAL),
        ("elastic", kbk.ELASTIC),
        ("gravity_potential", kbk.GRAVITY_POTENTIAL),
        ("kinetic_nodes", kbk.KINETIC_NODES),
        ("shadow", kbk.SHADOW),
        ("kinetic_rigid", kbk.KINETIC_RIGID),
    )
), "kernels/books.py's line indices must follow EnergyBalance's fields"

ALL_PARTS = frozenset({"motion", "stores", "booked"})
"""Every family of lines: the whole books. The others: "fem_contact" (the FEM contacts' springs and dissipation)
and "coupling" (the couplings' springs), each a subset of "stores" and "booked"."""


@dataclass(frozen=True)
class BookTerms:
    """A weighted sum of lines that a topology pass books the change of (:meth:`DeviceBooks.mark`,
    :meth:`DeviceBooks.book`): ``weights`` (line name, weight) pairs, ``parts`` the families that hold them."""

    parts: frozenset[str]
    weights: tuple[tuple[str, float], ...]


SHADOW = BookTerms(frozenset({"motion"}), (("shadow", 1.0),))
"""Verlet's shadow term."""
CONTACT = BookTerms(
    frozenset({"fem_contact"}),
    (("elastic", 1.0), ("dissipated_fem_contact", 1.0), ("dissipated_sphere_face", 1.0)),
)
"""The FEM contacts' lines: their springs (node–face, node–wall, sphere–face, joint elements) and what they
dissipated (Simulation._book_contact_topology)."""
CONVERSION = BookTerms(frozenset({"motion", "coupling"}), (("shadow", 1.0), ("coupling_elastic", -1.0)))
"""The shadow term less the couplings' springs (Simulation._convert books its change as released)."""

GPU_PARTIALS = 8192
"""Partial sums per line on a GPU (kernels/books.py): threads enough to fill one, each item read once."""


class DeviceBooks:
    """The energy books reduced on the device (kernels/books.py): every line of :class:`EnergyBalance` summed into
    one float64 vector of ``LINES`` values, read back once. Holds its scratch (a float64 per sphere, node, tet, bond,
    coupling and cohesive slot, and the partial sums), sized for one model's capacities (:meth:`fits`); evaluating
    allocates nothing.

    The order of every sum is fixed by the launch (``stride`` partials per line, added in thread order), so two
    evaluations of one state on one device give the same bits; the CPU (one partial) and a GPU add in different
    orders, which changes a line by float64 rounding only.
    """

    def __init__(self, model: Model, spheres: bool | None = None) -> None:
        """``spheres``: whether the model has spheres of non-zero radius (None: read the radii back), which decides
        whether sphere–face contacts hold energy; a simulation knows (``Simulation.has_spheres``)."""
        m, d = model, model.device
        self.device = d
        self.sphere_faces = bool(m.face_capacity and m.particle_capacity) and (
            m.max_radius > 0.0 if spheres is None else spheres
        )
        self.capacities = self._capacities(m, self.sphere_faces)
        self.stride = 1 if wp.get_device(d).is_cpu else GPU_PARTIALS
        self.partials = wp.zeros((kbk.LINES, self.stride), dtype=wp.float64, device=d)
        self.books = wp.zeros(kbk.LINES, dtype=wp.float64, device=d)
        f64 = dict(dtype=wp.float64, device=d)
        self.sphere_e = wp.zeros(m.particle_capacity, **f64)
        self.sphere_face_e = wp.zeros(m.particle_capacity if self.sphere_faces else 0, **f64)
        self.node_e = wp.zeros(m.node_capacity, **f64)
        self.tet_e = wp.zeros(m.tet_capacity, **f64)
        self.bond_e = wp.zeros(m.bond_capacity, **f64)
        self.coupling_e = wp.zeros(m.coupling_capacity, **f64)
        self.cohesive_e = wp.zeros(m.cohesive_capacity, **f64)
        self.touching = wp.zeros(2, dtype=int, device=d)  # scratch of the contact and bond counts
        self._term_weights: dict[BookTerms, wp.array] = {}
        ratios = [p.shear_stiffness_ratio for p in m.joint_set_props] or [0.0]
        self.shear_ratio = wp.array(np.asarray(ratios, dtype=np.float64), dtype=wp.float64, device=d)

    @staticmethod
    def _capacities(m: Model, sphere_faces: bool) -> tuple:
        return (
            m.particle_capacity,
            m.node_capacity,
            m.tet_capacity,
            m.bond_capacity,
            m.coupling_capacity,
            m.cohesive_capacity,
            m.face_capacity > 0,  # not the count: the surface grows at every split, the scratch does not depend on it
            sphere_faces,
            tuple(p.shear_stiffness_ratio for p in m.joint_set_props),
            str(m.device),
        )

    def fits(self, model: Model, spheres: bool) -> bool:
        """Whether this scratch serves ``model`` (same capacities, joint sets and device; ``spheres`` as for the
        constructor)."""
        return self._capacities(model, bool(model.face_capacity and model.particle_capacity) and spheres) == (
            self.capacities
        )

    def evaluate(self, model: Model, state: State, parts: frozenset[str] = ALL_PARTS) -> wp.array:
        """Launch the books of ``state`` into :attr:`books` (float64, shape (LINES,), indexed by :data:`LINE`) and
        return it. ``parts``: which families of lines to sum (:data:`ALL_PARTS` for the whole books; a line of a
        family left out reads 0 or a partial sum). Launches only: no read-back, no allocation."""
        m, s = model, state
        self.partials.zero_()
        if "motion" in parts:
            self._motion(m, s)
        if "stores" in parts:
            self._stores(m, s)
        if "fem_contact" in parts or "stores" in parts:
            self._fem_contact_stores(m, s)
        if "coupling" in parts or "stores" in parts:
            self._coupling_store(m, s)
        if "booked" in parts:
            self._booked_lines(m, s)
        if "fem_contact" in parts or "booked" in parts:
            self._fem_contact_booked(m, s)
        wp.launch(
            kbk.finish_books_kernel, dim=kbk.LINES, inputs=[self.partials], outputs=[self.books], device=self.device
        )
        return self.books

    def mark(self, model: Model, state: State, terms: BookTerms, marks: wp.array, slot: int) -> None:
        """Keep Σ weight × line of ``terms`` now in ``marks[slot]`` (float64, on the device; launches only): the
        "before" of a pass that :meth:`book` books the change of."""
        weights = self._weights(terms)
        self.evaluate(model, state, terms.parts)
        wp.launch(kbk.mark_books_kernel, dim=1, inputs=[self.books, weights, slot], outputs=[marks], device=self.device)

    def book(self, model: Model, state: State, terms: BookTerms, marks: wp.array, slot: int, into: wp.array) -> None:
        """Add Σ weight × line of ``terms`` now minus ``marks[slot]`` (:meth:`mark`) to ``into[0]`` (a float64
        accumulator of the state; launches only): what a pass changed the lines by, booked without a read-back."""
        weights = self._weights(terms)
        self.evaluate(model, state, terms.parts)
        wp.launch(
            kbk.book_change_kernel,
            dim=1,
            inputs=[self.books, weights, marks, slot],
            outputs=[into],
            device=self.device,
        )

    def prepare(self, *terms: BookTerms) -> None:
        """Make the weights of ``terms`` now (so that a recorded :meth:`mark` or :meth:`book` allocates nothing)."""
        for t in terms:
            self._weights(t)

    def _weights(self, terms: BookTerms) -> wp.array:
        """The device vector of ``terms``' weights by line, made once per set of terms."""
        weights = self._term_weights.get(terms)
        if weights is None:
            host = np.zeros(kbk.LINES, dtype=np.float64)
            for name, w in terms.weights:
                host[LINE[name]] += w
            weights = self._term_weights[terms] = wp.array(host, dtype=wp.float64, device=self.device)
        return weights

    def _motion(self, m: Model, s: State) -> None:
        """Kinetic energies, gravity potential and shadow term of the spheres, nodes and bodies."""
        g = wp.vec3d(*(float(c) for c in m.gravity))
        h = wp.float64(m.dt**2 / 8.0)
        launch = self._launch
        launch(
            kbk.sphere_books_kernel,
            [
                m.particle_mass,
                m.particle_radius,
                m.particle_motion,
                m.particle_inv_inertia,
                g,
                h,
                s.particle_count,
                s.particle_q,
                s.particle_qd,
                s.particle_omega,
                s.particle_f,
                s.particle_t,
            ],
        )
        drivers = m.loads.node_driver if m.loads is not None and m.loads.num_drivers else None
        launch(
            kbk.node_books_kernel,
            [
                m.node_mass,
                m.node_inv_mass,
                m.node_motion,
                m.node_ref_q,
                drivers if drivers is not None else s.node_count,
                int(drivers is not None),
                g,
                h,
                m.cohesive_substeps,
                s.node_count,
                s.node_u,
                s.node_qd,
                s.node_f,
                s.node_f_fast,
            ],
        )
        if has_bodies(s):
            launch(
                kbk.body_books_kernel,
                [
                    g,
                    h,
                    s.body_mass,
                    s.body_inertia,
                    s.body_axes,
                    s.body_fixed,
                    s.body_constraint,
                    s.body_axis,
                    s.body_v,
                    s.body_q,
                    s.body_l,
                    s.body_f,
                    s.body_t,
                ],
            )

    def read(self, model: Model, state: State) -> EnergyBalance:
        """:meth:`evaluate` and read the vector back (one read-back) as an :class:`EnergyBalance`."""
        values = self.evaluate(model, state).numpy()
        return EnergyBalance(**{name: float(values[k]) for name, k in LINE.items()})

    def shadow(self, model: Model, state: State) -> float:
        """Verlet's shadow term now [J] (:meth:`evaluate` with ``shadow_only``; one read-back)."""
        return float(self.evaluate(model, state, SHADOW.parts).numpy()[LINE["shadow"]])

    def _launch(self, kernel: wp.Kernel, inputs: list) -> None:
        wp.launch(kernel, dim=self.stride, inputs=[*inputs, self.stride], outputs=[self.partials], device=self.device)

    def _sum(self, values: wp.array, count: wp.array | None, line: str) -> None:
        """Add Σ values[:count[0]] (the whole array when ``count`` is None) to ``line``."""
        self._launch(
            kbk.add_sum_kernel,
            [values, count if count is not None else self.touching, int(count is not None), LINE[line]],
        )

    def _stores(self, m: Model, s: State) -> None:
        """The energy the sphere contacts, bonds, tets and cohesive elements hold now: each stage's per-item
        energies, then their sums (the FEM contacts' and couplings' are their own parts)."""
        launch_contact_energy(m, s, self.sphere_e, self.touching)
        self._sum(self.sphere_e, s.particle_count, "elastic")
        if m.bond_capacity:
            self.bond_e.zero_()
            launch_bond_energy(m, s, self.bond_e, self.touching)
            self._sum(self.bond_e, s.bond_count, "elastic")
        if m.tet_capacity:
            tet_energies(m, s, out=self.tet_e)
            self._sum(self.tet_e, s.tet_count, "strain")
        if m.cohesive_capacity:
            self.cohesive_e.zero_()
            launch_cohesive_stored(m, s, self.cohesive_e)
            self._sum(self.cohesive_e, s.cohesive_count, "cohesive_elastic")

    def _fem_contact_stores(self, m: Model, s: State) -> None:
        """The springs of the node–face, node–wall and sphere–face contacts and of the intact joint elements."""
        if m.node_capacity and m.face_capacity:
            launch_fem_contact_energy(m, s, self.node_e)
            self._sum(self.node_e, s.node_count, "elastic")
        if m.joint_capacity:
            self._launch(
                kbk.joint_books_kernel,
                [
                    m.tet_nodes,
                    m.joint_a,
                    m.joint_b,
                    m.joint_kn,
                    m.joint_tet_face,
                    m.joint_set,
                    self.shear_ratio,
                    s.joint_count,
                    s.joint_broken,
                    s.node_u,
                    s.node_q,
                ],
            )
        if self.sphere_faces:
            launch_sphere_face_energy(m, s, self.sphere_face_e)
            self._sum(self.sphere_face_e, s.particle_count, "elastic")

    def _coupling_store(self, m: Model, s: State) -> None:
        """The springs of the penalty couplings between converted spheres and the continuum."""
        if m.coupling_capacity:
            self.coupling_e.zero_()
            launch_coupling_energy(m, s, self.coupling_e)
            self._sum(self.coupling_e, s.coupling_count, "coupling_elastic")

    def _booked_lines(self, m: Model, s: State) -> None:
        """The lines the kernels book as they go: per-sphere, per-node, per-face and single accumulators."""
        n, nn = s.particle_count, s.node_count
        for values, count, line in (
            (s.energy_damping, n, "dissipated_damping"),
            (s.energy_friction, n, "dissipated_friction"),
            (s.energy_bond_broken, n, "released_by_bond_breakage"),
            (s.energy_boundary_work, n, "boundary_work"),
            (s.energy_stiffness_change, n, "stiffness_change"),
            (s.energy_bond_trapezoid, n, "bond_trapezoid"),
            (s.node_energy_damping, nn, "dissipated_viscous"),
            (s.node_energy_boundary_work, nn, "load_work"),
            # The pressure faces handed over to converted tets' spheres book their work per face, on the same line.
            (s.load_face_work, None, "load_work"),
            (s.node_energy_absorbed, nn, "absorbed_boundaries"),
            (s.node_energy_cohesive, nn, "dissipated_cohesive"),
            (s.node_energy_cohesive_trapezoid, nn, "cohesive_trapezoid"),
            (s.node_energy_substep, nn, "substep_work"),
            (s.energy_released_conversion, None, "released_conversion"),
            (s.energy_released_rigid, None, "released_rigid_switch"),
            (s.energy_contact_topology, None, "contact_topology"),
            (s.energy_step_change, None, "step_change"),
        ):
            self._sum(values, count, line)

    def _fem_contact_booked(self, m: Model, s: State) -> None:
        """What the FEM contacts' dashpots and friction and the sphere–face contacts dissipated."""
        n, nn = s.particle_count, s.node_count
        if m.node_capacity and m.face_capacity:
            self._sum(s.node_energy_contact, nn, "dissipated_fem_contact")
        if m.face_capacity:
            if sphere_face_rows(m):
                self._sum(s.sphere_face_dissipated, n, "dissipated_sphere_face")
            self._sum(s.node_energy_sphere_face, nn, "dissipated_sphere_face")


def energy_balance(m: Model, s: State, books: DeviceBooks | None = None) -> EnergyBalance:
    """The energy balance of a model and state now, reduced on the device (:class:`DeviceBooks`; ``books``: its
    scratch, made here when None or when it does not fit ``m``). One read-back: call between steps."""
    spheres = m.max_radius > 0.0
    if books is None or not books.fits(m, spheres):
        books = DeviceBooks(m, spheres)
    return books.read(m, s)


def books_from_nowhere(
    start: EnergyBalance, now: EnergyBalance, dt: float, critical_dt: float
) -> tuple[float, float] | None:
    """:func:`warpdem.stages.guard.energy_from_nowhere` between two states of the books: ``start``
    where the run began, ``now`` after it; the work put in, the load work and the stiffness and contact-topology gains
    taken as their changes since ``start``."""
    return energy_from_nowhere(
        (start.total, start.shadow, start.in_play, start.gravity_potential),
        (
            now.total,
            now.shadow,
            now.gravity_potential,
            now.boundary_work - start.boundary_work,
            now.load_work - start.load_work,
            now.stiffness_change - start.stiffness_change + now.contact_topology - start.contact_topology,
        ),
        dt,
        critical_dt,
    )
