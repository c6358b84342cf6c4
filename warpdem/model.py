"""Model (what a step does not change) and State (what it does), as flat struct-of-arrays ``wp.array``s.

Every per-particle array is sized by ``particle_capacity``; the live count sits on the device
(``State.particle_count``) so kernels launch over capacity and return early past it, and a step never reads a
count back to the host. Neighbour slots are ``particle_capacity * max_neighbors`` long, wall histories
``particle_capacity * num_walls``, bond arrays ``bond_capacity``. FEM node arrays are ``node_capacity`` long and
tet arrays ``tet_capacity`` (live counts ``State.node_count`` / ``State.tet_count``); both exist, possibly empty,
in a model without tets.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import warp as wp

from .fused import copy_arrays
from .kernels.contact import ContactPair

if TYPE_CHECKING:
    from .load_data import LoadModel


def _array_fields(obj: object) -> dict[str, wp.array]:
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj) if isinstance(getattr(obj, f.name), wp.array)}


@dataclass
class Model:
    """Static description of a DEM system on one device.

    Attributes:
        device: Warp device the arrays live on.
        particle_capacity: slots per particle array.
        max_neighbors: neighbour slots per particle (grows ×2 on overflow between steps).
        num_materials: number of materials; ``pair_table`` has num_materials² entries.
        num_walls: number of planar walls.
        dt: time step [s].
        skin: Verlet skin of the neighbour list [m].
        gravity: gravitational acceleration [m/s²].
        normal_model: "hertz" or "linear".
        tangential_model: "mindlin" or "linear".
        rolling_model: "none" or "constant_torque".
        material_names: names of the materials, index = material id.
        part_names: names of the parts, index = part id.
        particle_radius: radii [m], shape (particle_capacity,), float32.
        particle_mass: masses [kg], shape (particle_capacity,), float32.
        particle_inv_mass: 1/m [1/kg], 0 for fixed and prescribed spheres, shape (particle_capacity,).
        particle_inv_inertia: 1/I = 1/(2/5 m r²) [1/(kg m²)], 0 for fixed and prescribed, shape (particle_capacity,).
        particle_material: material id, shape (particle_capacity,), int32.
        particle_motion: 0 free, 1 fixed, 2 prescribed velocity and spin, shape (particle_capacity,), int32.
        particle_part: part id, shape (particle_capacity,), int32.
        particle_id: stable id (order of creation), shape (particle_capacity,), int32.
        pair_table: interaction properties of material pairs, shape (num_materials²,), ContactPair.
        wall_normal: unit normals pointing into the domain, shape (num_walls,), vec3.
        wall_velocity: wall velocities [m/s], shape (num_walls,), vec3.
        wall_material: material id of each wall, shape (num_walls,), int32.
        node_capacity: FEM node slots.
        tet_capacity: tet slots.
        node_ref_q: reference positions X [m], shape (node_capacity,), vec3.
        node_mass: lumped mass Σ ρV₀/4 over the node's tets [kg], shape (node_capacity,), float32.
        node_inv_mass: 1/m [1/kg], 0 for fixed nodes, shape (node_capacity,), float32.
        node_motion: held velocity components: 0 free, 1 fixed, 2 z only (x, y held), 3/4/5 roller normal to x/y/z
            (that component held), 6 x only, 7 y only (kernels/tets.py), shape (node_capacity,), int32.
        node_damping: mass-proportional damping α of the node (mass-weighted over its tets) [1/s],
            shape (node_capacity,), float32.
        tet_nodes: node indices, positively oriented, shape (tet_capacity,), vec4i.
        tet_inv_ref: [D1 D2 D3]⁻¹ of the reference directors D_i = X_i - X_0 [1/m], shape (tet_capacity,), mat33.
        tet_volume: reference volume V₀ [m³], shape (tet_capacity,), float32.
        tet_length: characteristic length ℓ = 2 / sqrt(Σ_a |∇N_a|²) of the bulk viscosity (warpdem.stages.tets
            .characteristic_lengths) [m], shape (tet_capacity,), float32.
        tet_material: material id, shape (tet_capacity,), int32.
        tet_material_table: continuum properties per material id, shape (num_materials,), TetMaterial.
        loads: pressure loads, non-reflecting dashpots and node velocity drivers (warpdem.load_data.LoadModel), or
            None.
        critical_dt: the builder's estimate of the critical time step [s] (inf when nothing bounds it).
        critical_dt_source: what sets ``critical_dt``, in words (warpdem.stages.guard.CriticalStep).
        speed_limit: run-away bound on the speed of a sphere or node at t = 0 [m/s]; the guard adds |g| t
            (warpdem.stages.guard.run_away_speed; inf: only non-finite values are caught).
        contact_reach: the smallest contact reach [m]: the smallest sphere radius or shortest tet edge (inf when
            there is neither). No sphere or node may move more than REACH_FRACTION of it in one step, or a contact
            can be stepped over (warpdem.stages.guard.reach_step).
        contact_reach_source: what sets ``contact_reach``, in words.

    FEM contact and joints (warpdem.stages.fem_contact, warpdem.stages.joints; the surface topology is rebuilt on the
    device after every topology pass).

    Attributes:
        face_capacity: boundary face slots.
        max_sphere_faces: candidate faces per sphere (grows ×2 on overflow between steps).
        max_node_faces: candidate faces per FEM node (grows ×2 on overflow between steps).
        node_springs: node–face spring slots per FEM node, one per face plane direction the node lies behind
            (kernels/node_face_target.py NODE_SPRINGS, which the kernels are compiled for; the only value allowed).
        fem_skin: Verlet skin of the FEM contact lists [m] (rebuilt when a node has moved half of it).
        face_radius: largest distance from a boundary face's centroid to its vertices (reference) [m].
        face_depth_max: largest face_depth [m].
        contact_stiffness_factor: penalty factor f of faces that are no joint faces [-] (a face of a tet of modulus
            E and height h is a spring of f E / h per unit area).
        contact_face_normal_stiffness: the mesh-independent part of the spring of faces that are no joint faces,
            k_n / 2 per unit area for a surface normal stiffness k_n [Pa/m] (ModelBuilder.contact_normal_stiffness;
            ``contact_stiffness_factor`` is then 0); 0 otherwise.
        tet_face_joint: joint set of each tet-face slot 4t + k (face k opposite node k), -1 for none, shape
            (4 tet_capacity,), int32.
        star_offset: the node → tet adjacency: node n's tets are ``star_tets[star_offset[n] .. star_offset[n] +
            star_count[n])``, sorted, shape (node_capacity,), int32.
        star_count: the number of tets in each node's star, shape (node_capacity,), int32.
        star_tets: live active tets of every node's star, shape (4 tet_capacity,), int32.
        tet_face_nbr: the tet across each tet-face slot, -1 on the surface, shape (4 tet_capacity,), int32.
        face_nodes: boundary faces (faces of active tets used once), nodes in outward order, shape (face_capacity,),
            vec3i.
        face_tet: the tet behind each face, shape (face_capacity,), int32.
        face_joint: joint set of each face, -1 for none, shape (face_capacity,), int32.
        face_depth: deepest penetration a node may have into the face and still be pushed back out of it: half the
            tet's height over the face [m], shape (face_capacity,), float32.
        node_contact_stiffness: penalty stiffness of each node, Σ over its boundary faces of f E A / (3 h) [N/m]
            (k_n A / 6 on the faces of a joint given a normal stiffness k_n; 0 for a node inside the rock), shape
            (node_capacity,), float32.
        node_contact_material: material id of each node (of its lowest tet), shape (node_capacity,), int32.
        fem_pair_table: node–face and node–wall interaction of a material pair, as pair_table with damp_n the
            linear damping ratio ζ, shape (num_materials²,), ContactPair.
        joint_material_table: properties of each joint set, shape (max(num_joint_sets, 1),), JointMaterial.
        joint_set_props: the joint sets' warpdem.stages.joints.JointProps (host copies).
        joint_capacity: joint interface elements.
        joint_a: daughter node A of each element (a < b), shape (joint_capacity,), int32.
        joint_b: daughter node B of each element, shape (joint_capacity,), int32.
        joint_area: interface area of each element [m²].
        joint_kn: its normal stiffness [N/m].
        joint_tet_face: the tet-face slot of A's joint face (its outward normal is the element's).
        joint_set: its joint set.

    Nodal fracture (warpdem.stages.fracture, warpdem.stages.cohesive; LDEC §2.2–2.3).

    Attributes:
        fracture_interval: steps between two split passes; 0: no split pass (fracture off, or a rigid switch stopped
            the passes: :attr:`has_fracture` tells the two apart).
        cohesive_capacity: cohesive element slots (grows ×2 on overflow between steps).
        cohesive_substeps: sub-steps n of the cohesive elements' daughters per step (≥ 1): with n > 1 their nodes
            move under the elements' forces in n velocity-Verlet sub-steps of dt/n between the half kicks of every
            other force (a multiple-time-step integration, r-RESPA; warpdem.stages.substep), so that an opening
            crossed within a step is resolved; 1: one step for every force, as without fracture.
        node_may_split: 1 where a node may split (the scene's fracture region), else 0, shape (node_capacity,), int32
            (a daughter inherits its parent's flag).
        fracture_material_table: T_f, Γ and α of every material id, shape (num_materials,), FractureMaterial
            (kernels/fracture.py).
        ref_tet_face_nbr: the tet across each tet-face slot 4t + k in the unsplit mesh (faces matched by reference
            positions, so joints and cracks do not cut it), -1 on the outer surface, shape (4 tet_capacity,), int32
            (warpdem.stages.topology.reference_face_neighbors, set by attach_fracture and attach_conversion; tet slots
            never move, so it holds for the whole run).

    Adaptive FEM→DEM conversion (warpdem.stages.conversion, warpdem.stages.coupling; CIMNE §4–5).

    Attributes:
        conversion_interval: steps between two conversion passes; 0: conversion is off.
        spheres_per_tet: spheres spawned in place of one converted tet (1 or more, a scene option).
        conversion_part: part id of the spawned spheres.
        coupling_capacity: penalty coupling slots (grows ×2 on overflow between steps).
        tet_may_convert: 1 where a tet may convert (the scene's conversion region), else 0, shape (tet_capacity,),
            int32.
        conversion_material_table: criterion, fraction and strengths of every material id, shape (num_materials,),
            ConversionMaterial (kernels/conversion.py).
        band_width: tet layers of the blended DEM/FEM overlap band (CIMNE eq. 8, warpdem.stages.overlap_band); 0: no
            band, each converted tet is dropped and its spheres tied to the continuum around (the tie).
        band_penalty: factor on the band's penalty stiffness (eq. 9) over warpdem.stages.coupling's rule [-].
        tet_band_volume: α_t V₀ of each tet [m³], the volume its FEM forces, strain energy and lumped mass stand for
            (α = 1 on the continuum, 0 < α < 1 on a converted tet in the band, 0 on an inactive one), shape
            (tet_capacity,); None without a band (α = 1 wherever a tet is active).
        tet_edge_degree: Z_t, the live tets sharing an edge with each tet (converted or not: the bonds' V_b = V_t /
            Z_t + V_n / Z_n, warpdem.stages.lattice), 0 past the live tets, shape (tet_capacity,), int32; set at attach
            (the mesh's topology then; a conversion pass recomputes what it reads where nodes may split).

    Rigid blocks (warpdem.stages.rigid; LDEC §2–§4).

    Attributes:
        rigid_switch: whether the blocks turn rigid at ``rigid_switch_time``.
        rigid_switch_time: the time of that switch [s] (0: from the start); it falls on the first step at or after
            it (warpdem.simulation).
        rigid_energy_fraction: turn rigid once the kinetic energy of the element modes (the nodes' kinetic energy
            beyond each block's rigid motion) is below this fraction of the nodes' kinetic energy, checked every
            ``rigid_check_interval`` steps; 0: off.
        rigid_check_interval: steps between two checks of ``rigid_energy_fraction``.
        deformable_critical_dt: the builder's critical step of the deformable model where a rigid-from-start run took
            the rigid blocks' step instead (warpdem.stages.rigid_step.rigid_time_step) [s]; 0 otherwise (``critical_dt``
            is it; not nan, which a checkpoint's attributes could not compare equal).
        tet_may_rigid: 1 where a tet may turn rigid (the scene's region or materials), else 0, shape
            (tet_capacity,), int32; None: every tet.
        radius_bound: the largest sphere radius of the whole run [m] where this model is one rank's subdomain
            (warpdem.parallel), so that every rank's contact grid has the whole run's cells; 0: from the radii.
        grid_owners: the sphere capacity of the whole run where this model is a subdomain, which sizes the contact
            grid's hash table as the whole run's (the same cells share a bucket, so candidates come in the same
            order); 0: ``particle_capacity``.
        face_grid_owners: the boundary face capacity of the whole run where this model is a subdomain, which sizes the
            FEM contact grid's hash table as the whole run's; 0: ``face_capacity``.
    """

    device: wp.context.Device
    particle_capacity: int
    max_neighbors: int
    num_materials: int
    num_walls: int
    dt: float
    skin: float
    gravity: tuple[float, float, float]
    normal_model: str
    tangential_model: str
    rolling_model: str
    material_names: list[str]
    part_names: list[str]
    particle_radius: wp.array
    particle_mass: wp.array
    particle_inv_mass: wp.array
    particle_inv_inertia: wp.array
    particle_material: wp.array
    particle_motion: wp.array
    particle_part: wp.array
    particle_id: wp.array
    pair_table: wp.array
    wall_normal: wp.array
    wall_velocity: wp.array
    wall_material: wp.array
    node_capacity: int
    tet_capacity: int
    node_ref_q: wp.array
    node_mass: wp.array
    node_inv_mass: wp.array
    node_motion: wp.array
    node_damping: wp.array
    tet_nodes: wp.array
    tet_inv_ref: wp.array
    tet_volume: wp.array
    tet_length: wp.array
    tet_material: wp.array
    tet_material_table: wp.array
    walls_move: bool = False
    bond_capacity: int = 0
    loads: LoadModel | None = None
    critical_dt: float = math.inf
    critical_dt_source: str = ""
    speed_limit: float = math.inf
    contact_reach: float = math.inf
    contact_reach_source: str = ""
    face_capacity: int = 0
    max_sphere_faces: int = 8
    max_node_faces: int = 8
    node_springs: int = 3
    fem_skin: float = 0.0
    face_radius: float = 0.0
    face_depth_max: float = 0.0
    contact_stiffness_factor: float = 1.0
    contact_face_normal_stiffness: float = 0.0
    tet_face_joint: wp.array | None = None
    star_offset: wp.array | None = None
    star_count: wp.array | None = None
    star_tets: wp.array | None = None
    tet_face_nbr: wp.array | None = None
    face_nodes: wp.array | None = None
    face_tet: wp.array | None = None
    face_joint: wp.array | None = None
    face_depth: wp.array | None = None
    node_contact_stiffness: wp.array | None = None
    node_contact_material: wp.array | None = None
    fem_pair_table: wp.array | None = None
    joint_material_table: wp.array | None = None
    joint_set_props: list = field(default_factory=list)
    joint_capacity: int = 0
    joint_a: wp.array | None = None
    joint_b: wp.array | None = None
    joint_area: wp.array | None = None
    joint_kn: wp.array | None = None
    joint_tet_face: wp.array | None = None
    joint_set: wp.array | None = None
    fracture_interval: int = 0
    cohesive_capacity: int = 0
    cohesive_substeps: int = 1
    node_may_split: wp.array | None = None
    fracture_material_table: wp.array | None = None
    ref_tet_face_nbr: wp.array | None = None
    conversion_interval: int = 0
    spheres_per_tet: int = 1
    conversion_part: int = 0
    coupling_capacity: int = 0
    tet_may_convert: wp.array | None = None
    conversion_material_table: wp.array | None = None
    tet_edge_degree: wp.array | None = None
    band_width: int = 0
    band_penalty: float = 1.0
    tet_band_volume: wp.array | None = None
    rigid_switch: bool = False
    rigid_switch_time: float = 0.0
    rigid_energy_fraction: float = 0.0
    rigid_check_interval: int = 100
    deformable_critical_dt: float = 0.0
    tet_may_rigid: wp.array | None = None
    radius_bound: float = 0.0
    grid_owners: int = 0
    face_grid_owners: int = 0

    @property
    def max_radius(self) -> float:
        """Largest sphere radius [m] (host copy, for the grid cell size): ``radius_bound`` where set (a subdomain's,
        the whole run's largest), else the largest of the model's spheres."""
        if self.radius_bound > 0.0:
            return self.radius_bound
        r = self.particle_radius.numpy()
        return float(r.max()) if r.size else 0.0

    @property
    def has_fracture(self) -> bool:
        """Whether nodal fracture was attached (warpdem.stages.fracture.attach_fracture, which gives at least one
        cohesive slot): the cracks, cohesive elements, node damage and their counters exist. It stays true after a rigid
        switch, which stops the split passes (``fracture_interval`` = 0) but keeps what they made, so a run's outputs
        keep their fracture columns and fields from its first frame to its last."""
        return self.cohesive_capacity > 0

    def arrays(self) -> dict[str, wp.array]:
        """All per-item arrays of the model by field name."""
        return _array_fields(self)


@dataclass
class State:
    """Dynamic state of a DEM/FEM system: everything a restart needs besides the Model.

    Attributes:
        particle_count: live particles, shape (1,), int32.
        particle_q: centres [m], shape (particle_capacity,), vec3d (float64). The only float64 positions, with the
            wall points and ``particle_q_at_build``: a float32 coordinate of 10 m has a spacing of 1 µm, below the
            drift dt·v of a microsecond step, and rounds contact overlaps differently at every offset. Kernels form
            differences x_i - x_j (or x_i - wall point, x_i - FEM node) in float64 and round the small result to
            float32 once, so every contact, bond and wall law sees the same numbers wherever the model sits.
        particle_qd: velocities [m/s], shape (particle_capacity,), vec3.
        particle_qd_carry: what the float32 kicks of ``particle_qd`` rounded off [m/s], shape (particle_capacity,),
            vec3: each kick adds its increment to the velocity with compensated (Kahan) summation, carrying the
            rounding into the next kick, so that the increments are summed to float32 precision of the velocity.
            Without it a constant increment (gravity, dt g/2 a half kick) rounds the same way at every kick: a free
            fall's velocity was 1.2e-3 off g t after 0.1 s at dt = 1 µs, and worse the finer the step.
        particle_omega: angular velocities [rad/s], shape (particle_capacity,), vec3.
        particle_f: forces [N] (gravity excluded), shape (particle_capacity,), vec3.
        particle_t: torques [N m], shape (particle_capacity,), vec3.
        particle_q_at_build: centres when the neighbour list was built [m], shape (particle_capacity,), vec3d.
        rebuild_flag: 1 when the neighbour list must be rebuilt before the next force evaluation, shape (1,).
        rebuild_total: neighbour-list builds since the start, shape (1,).
        nbr_needed: the largest neighbour count seen at a build (overflow when > max_neighbors), shape (1,).
        nbr_count: neighbours of each particle in its half list, shape (particle_capacity,), int32.
        nbr_index: neighbour j > i in each slot, shape (particle_capacity * max_neighbors,), int32.
        nbr_shear: tangential spring of each slot [m], shape (particle_capacity * max_neighbors,), vec3.
        nbr_bond: bond between the slot's pair or -1, shape (particle_capacity * max_neighbors,), int32.
        wall_point: a point on each wall [m], shape (num_walls,), vec3d (float64, as the centres it is measured
            from).
        wall_shear: tangential spring of each sphere–wall pair [m], shape (particle_capacity * num_walls,), vec3.
        bond_count: live bonds (intact or broken but not yet compacted), shape (1,), int32.
        bond_i: the first bonded sphere (i < j), shape (bond_capacity,), int32.
        bond_j: the second bonded sphere, shape (bond_capacity,), int32.
        bond_key: i * particle_capacity + j, sorted ascending, shape (bond_capacity,), int64.
        bond_rest_length: L_0 [m], shape (bond_capacity,).
        bond_kn: normal stiffness [N/m], shape (bond_capacity,).
        bond_ks: shear stiffness [N/m], shape (bond_capacity,).
        bond_area: cross-section [m²], shape (bond_capacity,).
        bond_tensile_strength: [Pa], shape (bond_capacity,).
        bond_shear_strength: [Pa], shape (bond_capacity,).
        bond_damping: damping ratio ζ [-], shape (bond_capacity,).
        bond_shear: shear spring [m], shape (bond_capacity,), vec3.
        bond_broken: 0 intact, 1 broke in tension, 2 in shear, shape (bond_capacity,).
        bond_energy_prev: (normal, shear) spring energy at the last evaluation [J], shape (bond_capacity,), vec2 (for
            the energy books).
        bonds_broken_total: bonds broken since the start, shape (1,).
        particle_bonds_broken: bonds each sphere has lost since the start (a damage measure for output), shape
            (particle_capacity,), int32.
        energy_damping: energy dissipated by dashpots [J], per particle, shape (particle_capacity,), float64.
        energy_friction: energy dissipated by friction (and tangential dashpots) [J], per particle, shape
            (particle_capacity,), float64.
        energy_boundary_work: work done on the spheres by moving walls and driven spheres [J], per particle, shape
            (particle_capacity,), float64.
        energy_bond_broken: spring energy released by breaking bonds [J], per particle, shape (particle_capacity,),
            float64.
        energy_bond_trapezoid: the bonds' springs' -W - ΔU [J], their work as Verlet does it (the trapezoid) less the
            change of their energy: no dissipation, of either sign where a bond turns within a step (kernels/bonds.py),
            per particle, shape (particle_capacity,), float64.
        energy_stiffness_change: energy the contacts' tangential springs gained without work because k_t follows
            the overlap (Mindlin, or a linear k_t on a Hertz k_n) [J], per particle, shape (particle_capacity,),
            float64.
        contact_sums: sums of the sphere contacts' and bonds' forces on each sphere at the last evaluation, for the
            integrator's booking of the half of their work that lies ahead (kernels/contact.py), one record per
            sphere, its rows the normal forces [N], the tangential forces [N] and the tangential and rolling torques
            [N m], shape (particle_capacity,), mat33 (one record, so that a pair's other sphere costs one cache line
            of books, not three).
        contact_energy_prev: (normal, tangential) spring energy of the contacts each sphere owns (its half list and
            its walls) at the last evaluation [J], shape (particle_capacity,), vec2.
        node_count: live FEM nodes, shape (1,), int32.
        tet_count: live tet slots (active or not), shape (1,), int32.
        node_u: node displacements x - X [m], shape (node_capacity,), vec3. The integrator advances u and the tets
            read it: float32 then resolves strains to ε₃₂ |u|/h instead of ε₃₂ |x|/h, and a step's increment dt·v
            is not lost against the size of the coordinates.
        node_q: node positions x = X + u [m] (kept for contact and output), shape (node_capacity,), vec3 (float32:
            the contact geometry of nodes rounds to ulp(|x|)/2, e.g. 3.8 µm at 100 m; a sphere–face contact takes the
            float64 difference from the sphere's centre to these).
        node_qd: node velocities [m/s], shape (node_capacity,), vec3.
        node_qd_carry: what the float32 kicks of ``node_qd`` rounded off [m/s], shape (node_capacity,), vec3 (as
            ``particle_qd_carry``); zero where a driver sets the velocity, or a body (rigid nodes do not kick).
        node_f: node forces [N] (gravity excluded; starts each step at the damping force -α m v), shape
            (node_capacity,), vec3.
        node_energy_damping: energy dissipated by bulk viscosity and mass-proportional damping [J], per node, shape
            (node_capacity,), float64.
        node_f_viscous: the bulk-viscosity and mass-proportional damping forces on each node at the last evaluation
            [N] (part of ``node_f``), for the integrator's booking of the half of their work that lies ahead, as the
            sphere contacts' sums (kernels/integrate.py ``drift_node``; on a rigid block's node, the forces of the
            deformable tets next to it, booked after the body's drift: warpdem.stages.rigid.drift_bodies), shape
            (node_capacity,), vec3.
        node_energy_absorbed: energy the non-reflecting boundaries' dashpots took out of the model [J], per node,
            shape (node_capacity,), float64.
        node_f_absorbed: the non-reflecting boundaries' dashpot forces on each node at the last evaluation [N] (part
            of ``node_f``), whose work over the half step ahead the next evaluation books (kernels/integrate.py
            ``book_half_ahead_kernel``), shape (node_capacity,), vec3.
        node_f_load: the pressure loads' forces on each node at the last evaluation [N] (part of ``node_f``), whose
            work over the half step ahead the next evaluation books into ``node_energy_boundary_work``
            (kernels/integrate.py ``book_half_ahead_kernel``; the half behind: kernels/loads.py), shape
            (node_capacity,), vec3.
        tet_active: 1 for a tet that carries forces, 0 for one taken out (converted), shape (tet_capacity,), int32.
        tet_stress: Cauchy stress at the current displacements (elastic, without bulk viscosity; 0 for inactive
            tets) [Pa], tension positive, shape (tet_capacity,), mat33. Refreshed between steps (after every
            ``Simulation.advance`` and at set-up), not inside the step.
        time: simulated time [s], advanced on the device every step (time-dependent loads read it), shape (1,),
            float64.
        node_energy_boundary_work: work done on the nodes by pressure loads and velocity drivers [J], shape
            (node_capacity,), float64.
        load_face_force: the force -p a_c of each pressure face handed over to its converted tet's spheres, made by
            the last evaluation and kept for the half ahead of its work [N], shape (loaded faces,), vec3 (the faces of
            ``Model.loads.pressure`` in its order, each set from its ``first``; zero for a face not handed over).
        load_face_work: the work of that force on the spheres since the start [J], shape (loaded faces,), float64:
            a part of the load work line (kernels/loads.py, Hand-over).
        load_face_impulse: the normal impulse each pressure face delivered since the start, Σ dt p |a| Σ_k w_k
            [N s], shape (loaded faces,), float64 (kernels/loads.py, Impulse).
        face_count: live boundary faces, shape (1,), int32.
        fem_rebuild_flag: 1 when the FEM contact lists must be rebuilt, shape (1,), int32.
        fem_rebuild_total: FEM contact-list builds since the start, shape (1,), int32.
        fem_sphere_builds_seen: the sphere list's rebuild_total at the last FEM build (a sphere rebuild means a
            sphere moved half its skin, so the sphere–face lists are rebuilt too), shape (1,), int32.
        node_q_at_fem_build: node positions at the last FEM contact-list build [m], shape (node_capacity,), vec3.
        sphere_face_needed: the most candidate faces a sphere had at a build (overflow when > max_sphere_faces),
            shape (1,).
        sphere_face_count: candidate faces of each sphere, shape (particle_capacity,). In a model without boundary
            faces (face_capacity 0) this and the next six per-sphere arrays are empty
            (warpdem.stages.fem_contact.sphere_face_rows).
        sphere_face_index: candidate face of each slot, shape (particle_capacity * max_sphere_faces,), int32.
        sphere_face_shear: tangential spring of each slot [m], shape (particle_capacity * max_sphere_faces,), vec3.
        sphere_face_energy_prev: (normal, tangential) spring energy of each sphere's face contacts at the last
            evaluation [J] (ΔU of their dissipation D = -W - ΔU), shape (particle_capacity,), vec2.
        sphere_face_f: sum of the sphere–face contact forces on each sphere at the last evaluation [N], whose work over
            the half step ahead the next evaluation books into ``sphere_face_dissipated`` (kernels/sphere_face.py;
            zero without energy tracking), shape (particle_capacity,), vec3.
        sphere_face_t: the same for their torques [N m], shape (particle_capacity,), vec3.
        sphere_face_dissipated: energy dissipated by each sphere's face contacts [J]: the half of their work behind
            each evaluation and the sphere's half ahead, less the change of their springs' energy (the face nodes'
            half ahead: ``node_energy_sphere_face``), shape (particle_capacity,), float64.
        node_face_needed: the most candidate faces a node had at a build (overflow when > max_node_faces), shape
            (1,).
        node_face_count: candidate faces of each node, shape (node_capacity,).
        node_face_index: candidate face of each slot, shape (node_capacity * max_node_faces,), int32.
        node_face_spring: the face each node–face spring acts across, -1 for none, node_springs slots per node (one
            per face plane direction the node lies behind; each keeps its face while it still holds the node), shape
            (node_capacity * node_springs,), int32.
        node_face_offset: depth behind its target face at which each spring is relaxed [m] (what a change of target
            within its plane carried over without work), shape (node_capacity * node_springs,), float32.
        node_face_shear: tangential spring of each node–face spring [m] (it follows the node from face to face within
            its plane), shape (node_capacity * node_springs,), vec3.
        node_wall_shear: tangential spring of each node–wall pair [m], shape (node_capacity * num_walls,), vec3.
        node_contact_hold: penalty stiffness per unit mass [1/s²] that a node's contact springs keep across topology
            passes while it touches (k = hold × node_mass; 0: none held, k = ``node_contact_stiffness``), held at each
            split or conversion pass and let go once the node touches nothing (kernels/fem_contact.py, "Held
            stiffness"), shape (node_capacity,), float64.
        node_f_contact: the node–face and node–wall forces on each node at the last evaluation [N] (the node's own
            and its share as a face node; with the dashpot forces of the intact joint elements), whose work over the
            half step ahead the next evaluation books (kernels/integrate.py ``book_half_ahead_kernel``; the
            contacts' part is zero without energy tracking), shape (node_capacity,), vec3.
        node_contact_energy_prev: elastic energy of each node's face and wall springs at the last evaluation [J]
            (ΔU of the contact dissipation D = -W - ΔU), shape (node_capacity,), float64.
        node_energy_contact: energy dissipated by the FEM contacts and joint elements of each node [J] (dashpots,
            friction, released by failed joints), shape (node_capacity,), float64.
        node_f_sphere_face: the sphere–face contact forces on each node as a face node at the last evaluation [N],
            whose work over the half step ahead the next evaluation books into ``node_energy_sphere_face``
            (kernels/integrate.py ``book_half_ahead_kernel``; zero without energy tracking), shape (node_capacity,),
            vec3.
        node_energy_sphere_face: the face nodes' share of the sphere–face contacts' dissipation [J] (minus the half
            of their work on the node that lies ahead of each evaluation; with ``sphere_face_dissipated`` the
            contacts' D = -W - ΔU, kernels/sphere_face.py), shape (node_capacity,), float64.
        joint_count: joint interface elements, shape (1,), int32.
        joint_broken: 0 intact, 1 failed in tension, 2 failed in shear, shape (joint_capacity,), int32.
        joints_broken_total: joint elements failed since the start, shape (1,), int32.

    Cohesive elements between the daughters A, B of a split node (LDEC eqs. 4–10; arrays of shape
    (cohesive_capacity,) unless said).

    Attributes:
        cohesive_count: live elements (intact, or broken and not yet compacted), shape (1,), int32.
        cohesive_a: the daughter node A (the − side, keeps the parent's index at the split), int32.
        cohesive_b: the daughter node B (the + side), int32.
        cohesive_fc: f_c, the force at the onset of fracture (eq. 4) [N], float32.
        cohesive_delta_c: δ_c, the critical opening (eq. 10) [m], float32.
        cohesive_alpha: α of the weakening law (eq. 6) [-], float32.
        cohesive_area: A_f, the new crack area attributed to the node, both faces (eq. 9) [m²], float32.
        cohesive_dir: unit direction from A to B before any opening: that of eq. 4's force at the split (along the
            principal direction p1 in a pure tensile split; warpdem.stages.fracture says why), vec3.
        cohesive_d_max: d_max, the largest opening |x_B − x_A| so far (eq. 8) [m], float32.
        cohesive_f_prev: the element's force on A at its last evaluation (its birth force after a split) [N], vec3: the
            first half of the next step's trapezoid in the energy books (kernels/cohesive.py).
        cohesive_energy_prev: its spring energy ½ k d² at the last evaluation (0 at birth) [J], float32.
        cohesive_broken: 0 intact, 1 broken (d_max ≥ δ_c) and awaiting compaction, int32.
        cohesive_tet_face: the tet-face slot 4t + k, on A's side, of the largest crack face the element was born with:
            tet t is A's representative tet and the tet across the slot in the unsplit mesh (Model.ref_tet_face_nbr)
            B's; a later split of A or B hands the element to the daughter on its representative tet's side, int32.
        cohesive_broken_total: elements broken since the start, shape (1,), int32.
        cohesive_area_broken: Σ A_f of the broken elements [m²], shape (1,), float64.
        cohesive_work_broken: Σ Γ A_f = Σ (1 − α/2) f_c δ_c of the broken elements [J] (eq. 9), shape (1,), float64.
        node_damage: largest δ_max/δ_c of the node's cohesive elements so far, 1 once one broke [-], shape
            (node_capacity,), float32 (a daughter inherits its parent's).
        node_energy_cohesive: energy the node's cohesive elements dissipated by their law (½ f_c per unit growth of
            δ_max once open, up to Γ A_f at the break; kernels/cohesive.py ``law_dissipation``) [J], shape
            (node_capacity,), float64.
        node_energy_cohesive_trapezoid: the rest of what the node's cohesive elements spent, their work as Verlet does
            it (the trapezoid) less the change of their energy and the law's dissipation: 0 where the steps resolve
            the opening, of either sign where an element crosses δ_c in a step [J], shape (node_capacity,), float64.
        node_f_fast: the cohesive elements' forces on each node at the last evaluation [N], kept apart from
            ``node_f`` while their nodes are sub-stepped (``Model.cohesive_substeps`` > 1; zero otherwise), shape
            (node_capacity,), vec3.
        node_substepped: 1 where a node is sub-stepped (``Model.cohesive_substeps`` > 1): a node of an intact cohesive
            element at the last pass that split or converted (warpdem.stages.substep), shape (node_capacity,), int32.
        node_energy_substep: the work of the forces other than the cohesive ones over a sub-stepped node's motion
            that their lines, booked against the step's mean velocity, do not hold [J] (warpdem.stages.substep;
            either sign, 0 without sub-steps), shape (node_capacity,), float64.
        node_splits_total: node splits since the start, shape (1,), int32.
        crack_area_total: Σ A_f of every cohesive element born [m²] (both faces), shape (1,), float64.
        energy_contact_topology: energy the FEM contacts' springs gained without work at split and conversion passes
            [J] (the penalty stiffness k of a node re-lumped over its new faces at the depth it holds, springs of
            faces that appear inside an overlap), shape (1,), float64.

    Adaptive FEM→DEM conversion (arrays of shape (coupling_capacity,) unless said).

    Attributes:
        tets_converted_total: tets converted since the start, shape (1,), int32.
        spheres_spawned_total: spheres spawned by conversion since the start, shape (1,), int32.
        energy_released_conversion: energy that left the mechanical books at conversions [J] — the strain energy and
            the kinetic energy of the motion relative to the centroid (beyond the spheres' spin) that the converted
            tets held, less what the new bonds and coupling springs hold — shape (1,), float64.
        coupling_count: live penalty couplings (overlap zone, CIMNE eqs. 8–9), shape (1,), int32.
        coupling_particle: the sphere of each coupling, int32.
        coupling_tet: the still-continuous tet whose material point the sphere is tied to, int32.
        coupling_bary: the material point's barycentric coordinates in that tet's reference configuration (the
            shape functions N_a of eq. 9; may lie slightly outside the tet), vec4.
        coupling_k: penalty stiffness [N/m], float32.
        coupling_energy_prev: spring energy at the last evaluation [J] (for the Verlet books), float32.
        coupling_rest: the gap g₀ = Σ N_a x_a - x_p [m] at the coupling's birth, vec3: the rounding of N_a to
            float32 (~ε₃₂ × the tet's size), which the spring's rest state takes so that it is born relaxed.
        tet_sphere: the sphere spawned in place of each tet, -1 while it is a tet, shape (tet_capacity,), int32
            (the bonds of a later conversion find their partner spheres through it).

    Rigid blocks (warpdem.stages.rigid, kernels/rigid.py; body arrays of shape (bodies,), empty before the switch, all
    float64 but the ints).

    Attributes:
        rigid_switched: 1 once the blocks turned rigid, shape (1,), int32.
        energy_released_rigid: the strain energy of the tets and the kinetic energy of the element modes that left
            the mechanical books at the switch, with the switch's change of the shadow term [J], shape (1,), float64.
        energy_step_change: what changes of the time step between steps (the rigid step taken after a switch,
            warpdem.simulation.Simulation.set_time_step) changed Verlet's shadow term by, S(dt_new) − S(dt_old) at
            the forces then, and what split passes changed it by at the step, S(f_new) − S(f_old) (the forces the
            next kick uses, re-evaluated after the split) [J], shape (1,), float64 (a line of the books: no force
            works across either change).
        body_mass: M [kg].
        body_inertia: principal moments [kg m²], vec3d.
        body_axes: principal axes at the switch (columns, world), mat33d.
        body_fixed: 1 for a block held in place (a fixed or driven node, or rollers of three directions), int32.
        body_constraint: 0 free, 1 on a roller plane (moves in the plane, turns about its normal ``body_axis``), 2
            between two roller planes (moves along their line ``body_axis``), int32.
        body_axis: that normal or line, unit [-], vec3d (warpdem.stages.rigid: roller constraints).
        body_dc: displacement of the centre of mass since the switch [m], vec3d.
        body_v: the velocity of the centre of mass [m/s], vec3d.
        body_q: rotation since the switch, quatd.
        body_l: angular momentum about the centre of mass [kg m²/s], vec3d.
        body_f: force of the nodes' forces [N] (gravity excluded), vec3d.
        body_t: torque of the nodes' forces about the centre of mass [N m], vec3d.
        body_q_before: the rotation before the last drift's rotor, q_n (where the forces of the last evaluation were
            made), quatd. Scratch of a step, as ``body_omega_ahead``.
        body_omega_ahead: the angular velocity there after the drift's kick, ω(q_n, L_{n+1/2}) [rad/s] (rollers
            respected), vec3d. Scratch of a step: each drift writes it and ``body_q_before``, and the evaluation
            after it books the half ahead of the last forces' work with them (kernels/rigid.py
            ``node_velocity_ahead``); between steps nothing reads them (a restart needs them only as every State
            array is carried).
        body_node_start: the body's nodes are ``rigid_nodes[start .. start + count)``, int32.
        body_node_count: see ``body_node_start``, int32.
        rigid_nodes: the nodes of the bodies, grouped by body, ascending within one, shape (rigid nodes,), int32.
        node_body: the body of each node, -1 for a deformable node, shape (node_capacity,) after the switch, int32.
        node_rigid_r0: the node's offset from its body's centre of mass at the switch [m], shape (node_capacity,)
            after the switch, vec3d.
        node_rigid_u0: the node's displacement at the switch [m], shape (node_capacity,) after the switch, vec3.
    """

    particle_count: wp.array
    particle_q: wp.array
    particle_qd: wp.array
    particle_qd_carry: wp.array
    particle_omega: wp.array
    particle_f: wp.array
    particle_t: wp.array
    particle_q_at_build: wp.array
    rebuild_flag: wp.array
    rebuild_total: wp.array
    nbr_needed: wp.array
    nbr_count: wp.array
    nbr_index: wp.array
    nbr_shear: wp.array
    nbr_bond: wp.array
    wall_point: wp.array
    wall_shear: wp.array
    bond_count: wp.array
    bond_i: wp.array
    bond_j: wp.array
    bond_key: wp.array
    bond_rest_length: wp.array
    bond_kn: wp.array
    bond_ks: wp.array
    bond_area: wp.array
    bond_tensile_strength: wp.array
    bond_shear_strength: wp.array
    bond_damping: wp.array
    bond_shear: wp.array
    bond_broken: wp.array
    bond_energy_prev: wp.array
    bonds_broken_total: wp.array
    particle_bonds_broken: wp.array
    energy_damping: wp.array
    energy_friction: wp.array
    energy_boundary_work: wp.array
    energy_bond_broken: wp.array
    energy_bond_trapezoid: wp.array
    energy_stiffness_change: wp.array
    contact_sums: wp.array
    contact_energy_prev: wp.array
    node_count: wp.array
    tet_count: wp.array
    node_u: wp.array
    node_q: wp.array
    node_qd: wp.array
    node_qd_carry: wp.array
    node_f: wp.array
    node_energy_damping: wp.array
    node_f_viscous: wp.array
    node_energy_absorbed: wp.array
    node_f_absorbed: wp.array
    node_f_load: wp.array
    tet_active: wp.array
    tet_stress: wp.array
    time: wp.array
    node_energy_boundary_work: wp.array
    load_face_force: wp.array
    load_face_work: wp.array
    load_face_impulse: wp.array
    face_count: wp.array
    fem_rebuild_flag: wp.array
    fem_rebuild_total: wp.array
    fem_sphere_builds_seen: wp.array
    node_q_at_fem_build: wp.array
    sphere_face_needed: wp.array
    sphere_face_count: wp.array
    sphere_face_index: wp.array
    sphere_face_shear: wp.array
    sphere_face_energy_prev: wp.array
    sphere_face_f: wp.array
    sphere_face_t: wp.array
    sphere_face_dissipated: wp.array
    node_face_needed: wp.array
    node_face_count: wp.array
    node_face_index: wp.array
    node_face_spring: wp.array
    node_face_offset: wp.array
    node_face_shear: wp.array
    node_wall_shear: wp.array
    node_contact_hold: wp.array
    node_f_contact: wp.array
    node_contact_energy_prev: wp.array
    node_energy_contact: wp.array
    node_f_sphere_face: wp.array
    node_energy_sphere_face: wp.array
    joint_count: wp.array
    joint_broken: wp.array
    joints_broken_total: wp.array
    cohesive_count: wp.array
    cohesive_a: wp.array
    cohesive_b: wp.array
    cohesive_fc: wp.array
    cohesive_delta_c: wp.array
    cohesive_alpha: wp.array
    cohesive_area: wp.array
    cohesive_dir: wp.array
    cohesive_d_max: wp.array
    cohesive_f_prev: wp.array
    cohesive_energy_prev: wp.array
    cohesive_broken: wp.array
    cohesive_tet_face: wp.array
    cohesive_broken_total: wp.array
    cohesive_area_broken: wp.array
    cohesive_work_broken: wp.array
    node_damage: wp.array
    node_energy_cohesive: wp.array
    node_energy_cohesive_trapezoid: wp.array
    node_f_fast: wp.array
    node_substepped: wp.array
    node_energy_substep: wp.array
    node_splits_total: wp.array
    crack_area_total: wp.array
    energy_contact_topology: wp.array
    tets_converted_total: wp.array
    spheres_spawned_total: wp.array
    energy_released_conversion: wp.array
    coupling_count: wp.array
    coupling_particle: wp.array
    coupling_tet: wp.array
    coupling_bary: wp.array
    coupling_k: wp.array
    coupling_energy_prev: wp.array
    coupling_rest: wp.array
    tet_sphere: wp.array
    rigid_switched: wp.array
    energy_released_rigid: wp.array
    energy_step_change: wp.array
    body_mass: wp.array
    body_inertia: wp.array
    body_axes: wp.array
    body_fixed: wp.array
    body_constraint: wp.array
    body_axis: wp.array
    body_dc: wp.array
    body_v: wp.array
    body_q: wp.array
    body_l: wp.array
    body_f: wp.array
    body_t: wp.array
    body_q_before: wp.array
    body_omega_ahead: wp.array
    body_node_start: wp.array
    body_node_count: wp.array
    rigid_nodes: wp.array
    node_body: wp.array
    node_rigid_r0: wp.array
    node_rigid_u0: wp.array

    def arrays(self) -> dict[str, wp.array]:
        """All arrays of the state by field name."""
        return _array_fields(self)

    def clone(self) -> State:
        """A deep copy on the same device."""
        return State(**{name: wp.clone(a) for name, a in self.arrays().items()})

    def assign(self, other: State) -> None:
        """Copy another state of the same capacities into this one, bit for bit, in one launch for all its arrays
        (warpdem.fused.copy_arrays; no reallocation)."""
        mine = self.arrays()
        copy_arrays(list(mine.values()), [getattr(other, name) for name in mine])


BOND_FIELDS = (
    "bond_i",
    "bond_j",
    "bond_key",
    "bond_rest_length",
    "bond_kn",
    "bond_ks",
    "bond_area",
    "bond_tensile_strength",
    "bond_shear_strength",
    "bond_damping",
    "bond_shear",
    "bond_broken",
    "bond_energy_prev",
)
"""State fields indexed by bond (compacted together)."""

COHESIVE_FIELDS = (
    "cohesive_a",
    "cohesive_b",
    "cohesive_fc",
    "cohesive_delta_c",
    "cohesive_alpha",
    "cohesive_area",
    "cohesive_dir",
    "cohesive_d_max",
    "cohesive_f_prev",
    "cohesive_energy_prev",
    "cohesive_broken",
    "cohesive_tet_face",
)
"""State fields indexed by cohesive element (compacted and grown together)."""


def fracture_state(model: Model) -> dict[str, wp.array]:
    """The State fields of nodal fracture for a model: ``model.cohesive_capacity`` empty element slots, no damage."""
    d, cap, ncap = model.device, model.cohesive_capacity, model.node_capacity
    one = {"dtype": int, "device": d}
    return {
        "cohesive_count": wp.zeros(1, **one),
        "cohesive_a": wp.zeros(cap, **one),
        "cohesive_b": wp.zeros(cap, **one),
        "cohesive_fc": wp.zeros(cap, dtype=float, device=d),
        "cohesive_delta_c": wp.zeros(cap, dtype=float, device=d),
        "cohesive_alpha": wp.zeros(cap, dtype=float, device=d),
        "cohesive_area": wp.zeros(cap, dtype=float, device=d),
        "cohesive_dir": wp.zeros(cap, dtype=wp.vec3, device=d),
        "cohesive_d_max": wp.zeros(cap, dtype=float, device=d),
        "cohesive_f_prev": wp.zeros(cap, dtype=wp.vec3, device=d),
        "cohesive_energy_prev": wp.zeros(cap, dtype=float, device=d),
        "cohesive_broken": wp.zeros(cap, **one),
        "cohesive_tet_face": wp.full(cap, -1, **one),
        "cohesive_broken_total": wp.zeros(1, **one),
        "cohesive_area_broken": wp.zeros(1, dtype=wp.float64, device=d),
        "cohesive_work_broken": wp.zeros(1, dtype=wp.float64, device=d),
        "node_damage": wp.zeros(ncap, dtype=float, device=d),
        "node_energy_cohesive": wp.zeros(ncap, dtype=wp.float64, device=d),
        "node_energy_cohesive_trapezoid": wp.zeros(ncap, dtype=wp.float64, device=d),
        "node_f_fast": wp.zeros(ncap, dtype=wp.vec3, device=d),
        "node_substepped": wp.zeros(ncap, dtype=int, device=d),
        "node_energy_substep": wp.zeros(ncap, dtype=wp.float64, device=d),
        "node_splits_total": wp.zeros(1, **one),
        "crack_area_total": wp.zeros(1, dtype=wp.float64, device=d),
        "energy_contact_topology": wp.zeros(1, dtype=wp.float64, device=d),
    }


COUPLING_FIELDS = (
    "coupling_particle",
    "coupling_tet",
    "coupling_bary",
    "coupling_k",
    "coupling_energy_prev",
    "coupling_rest",
)
"""State fields indexed by penalty coupling (compacted and grown together)."""


def conversion_state(model: Model) -> dict[str, wp.array]:
    """The State fields of FEM→DEM conversion for a model: ``model.coupling_capacity`` empty coupling slots."""
    d, cap = model.device, model.coupling_capacity
    return {
        "tets_converted_total": wp.zeros(1, dtype=int, device=d),
        "spheres_spawned_total": wp.zeros(1, dtype=int, device=d),
        "energy_released_conversion": wp.zeros(1, dtype=wp.float64, device=d),
        "coupling_count": wp.zeros(1, dtype=int, device=d),
        "coupling_particle": wp.zeros(cap, dtype=int, device=d),
        "coupling_tet": wp.zeros(cap, dtype=int, device=d),
        "coupling_bary": wp.zeros(cap, dtype=wp.vec4, device=d),
        "coupling_k": wp.zeros(cap, dtype=float, device=d),
        "coupling_energy_prev": wp.zeros(cap, dtype=float, device=d),
        "coupling_rest": wp.zeros(cap, dtype=wp.vec3, device=d),
        "tet_sphere": wp.full(model.tet_capacity, -1, dtype=int, device=d),
    }


RIGID_BODY_FIELDS = {
    "body_mass": wp.float64,
    "body_inertia": wp.vec3d,
    "body_axes": wp.mat33d,
    "body_fixed": int,
    "body_constraint": int,
    "body_axis": wp.vec3d,
    "body_dc": wp.vec3d,
    "body_v": wp.vec3d,
    "body_q": wp.quatd,
    "body_l": wp.vec3d,
    "body_f": wp.vec3d,
    "body_t": wp.vec3d,
    "body_q_before": wp.quatd,
    "body_omega_ahead": wp.vec3d,
    "body_node_start": int,
    "body_node_count": int,
}
"""State fields indexed by rigid body, with their types."""

RIGID_NODE_FIELDS = {"node_body": int, "node_rigid_r0": wp.vec3d, "node_rigid_u0": wp.vec3}
"""State fields indexed by node that exist once the blocks turned rigid (empty before)."""


def rigid_state(model: Model) -> dict[str, wp.array]:
    """The State fields of rigid blocks before the switch: no body, no rigid node (warpdem.stages.rigid fills them)."""
    d = model.device
    fields = {
        name: wp.empty(0, dtype=dtype, device=d) for name, dtype in {**RIGID_BODY_FIELDS, **RIGID_NODE_FIELDS}.items()
    }
    return {
        "rigid_switched": wp.zeros(1, dtype=int, device=d),
        "energy_released_rigid": wp.zeros(1, dtype=wp.float64, device=d),
        "energy_step_change": wp.zeros(1, dtype=wp.float64, device=d),
        "rigid_nodes": wp.empty(0, dtype=int, device=d),
        **fields,
    }


PARTICLE_MODEL_FIELDS = {
    "particle_radius": 0,
    "particle_mass": 0,
    "particle_inv_mass": 0,
    "particle_inv_inertia": 0,
    "particle_material": 0,
    "particle_motion": 0,
    "particle_part": 0,
    "particle_id": -1,
}
"""Per-particle Model fields and the value of an empty slot."""

PARTICLE_STATE_FIELDS = (
    "particle_q",
    "particle_qd",
    "particle_qd_carry",
    "particle_omega",
    "particle_f",
    "particle_t",
    "particle_q_at_build",
    "nbr_count",
    "particle_bonds_broken",
    "energy_damping",
    "energy_friction",
    "energy_boundary_work",
    "energy_bond_broken",
    "energy_bond_trapezoid",
    "energy_stiffness_change",
    "contact_sums",
    "contact_energy_prev",
)
"""Per-particle State fields (empty slots 0)."""

NEIGHBOR_FIELDS = ("nbr_index", "nbr_shear", "nbr_bond")
"""State fields with max_neighbors slots per particle (regrown together)."""


def pair_table_array(pairs: list[list[ContactPair]], device: wp.context.Device) -> wp.array:
    """Flatten a num_materials × num_materials table of ContactPair into a device array (row-major)."""
    flat = [p for row in pairs for p in row]
    return wp.array(flat, dtype=ContactPair, device=device)
