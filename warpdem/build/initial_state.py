"""The initial State of a model (ModelBuilder.finalize): spheres and FEM nodes at their initial positions and
velocities, bonds intact, tets active."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..host_data import BondData, ParticleData, TetMeshData, WallData
from ..model import Model, State, conversion_state, fracture_state, rigid_state
from ..stages.fem_contact import fem_contact_state


def new_state(
    model: Model, particles: ParticleData, walls: WallData, bonds: BondData, mesh: TetMeshData | None = None
) -> State:
    """Allocate the initial State of a model: spheres and FEM nodes at their initial positions and velocities,
    bonds intact, tets active."""
    device, cap, k = model.device, model.particle_capacity, model.max_neighbors
    n, nb = len(particles), len(bonds)
    mesh = mesh if mesh is not None else TetMeshData.empty()
    nn, nt = len(mesh.points), len(mesh.tets)
    loaded_faces = sum(f.count for f in model.loads.pressure.values()) if model.loads is not None else 0

    def vec(a: np.ndarray | None, size: int, dtype=wp.vec3) -> wp.array:
        out = np.zeros((size, 3), dtype=np.float64 if dtype == wp.vec3d else np.float32)
        if a is not None:
            out[: len(a)] = a
        return wp.array(out, dtype=dtype, device=device)

    def arr(a: np.ndarray, dtype, size: int, fill=0) -> wp.array:
        out = np.full(size, fill, dtype={int: np.int32, float: np.float32, wp.int64: np.int64}[dtype])
        out[: len(a)] = a
        return wp.array(out, dtype=dtype, device=device)

    def scalar(v: int) -> wp.array:
        return wp.array([v], dtype=int, device=device)

    pairs = bonds.pairs.astype(np.int64)
    q = particles.q
    return State(
        particle_count=scalar(n),
        # Absolute positions of spheres and walls are float64 (State.particle_q); everything else float32.
        particle_q=vec(q, cap, wp.vec3d),
        particle_qd=vec(particles.qd, cap),
        particle_qd_carry=vec(None, cap),
        particle_omega=vec(particles.omega, cap),
        particle_f=vec(None, cap),
        particle_t=vec(None, cap),
        particle_q_at_build=vec(q, cap, wp.vec3d),
        rebuild_flag=scalar(1),
        rebuild_total=scalar(0),
        nbr_needed=scalar(0),
        nbr_count=wp.zeros(cap, dtype=int, device=device),
        nbr_index=wp.zeros(cap * k, dtype=int, device=device),
        nbr_shear=wp.zeros(cap * k, dtype=wp.vec3, device=device),
        nbr_bond=wp.full(cap * k, -1, dtype=int, device=device),
        wall_point=vec(walls.point, len(walls), wp.vec3d),
        wall_shear=wp.zeros(cap * len(walls), dtype=wp.vec3, device=device),
        bond_count=scalar(nb),
        bond_i=arr(pairs[:, 0], int, nb),
        bond_j=arr(pairs[:, 1], int, nb),
        bond_key=arr(pairs[:, 0] * cap + pairs[:, 1], wp.int64, nb),
        bond_rest_length=arr(bonds.rest_length, float, nb),
        bond_kn=arr(bonds.kn, float, nb),
        bond_ks=arr(bonds.ks, float, nb),
        bond_area=arr(bonds.area, float, nb),
        bond_tensile_strength=arr(bonds.tensile_strength, float, nb),
        bond_shear_strength=arr(bonds.shear_strength, float, nb),
        bond_damping=arr(bonds.damping, float, nb),
        bond_shear=vec(None, nb),
        bond_broken=arr(np.zeros(nb), int, nb),
        bond_energy_prev=wp.zeros(nb, dtype=wp.vec2, device=device),
        bonds_broken_total=scalar(0),
        particle_bonds_broken=wp.zeros(cap, dtype=int, device=device),
        energy_damping=wp.zeros(cap, dtype=wp.float64, device=device),
        energy_friction=wp.zeros(cap, dtype=wp.float64, device=device),
        energy_boundary_work=wp.zeros(cap, dtype=wp.float64, device=device),
        energy_bond_broken=wp.zeros(cap, dtype=wp.float64, device=device),
        energy_bond_trapezoid=wp.zeros(cap, dtype=wp.float64, device=device),
        energy_stiffness_change=wp.zeros(cap, dtype=wp.float64, device=device),
        contact_sums=wp.zeros(cap, dtype=wp.mat33, device=device),
        contact_energy_prev=wp.zeros(cap, dtype=wp.vec2, device=device),
        node_count=scalar(nn),
        tet_count=scalar(nt),
        node_u=vec(None, model.node_capacity),
        node_q=vec(mesh.points, model.node_capacity),
        node_qd=vec(mesh.velocity, model.node_capacity),
        node_qd_carry=vec(None, model.node_capacity),
        node_f=vec(None, model.node_capacity),
        node_energy_damping=wp.zeros(model.node_capacity, dtype=wp.float64, device=device),
        node_f_viscous=vec(None, model.node_capacity),
        node_energy_absorbed=wp.zeros(model.node_capacity, dtype=wp.float64, device=device),
        node_f_absorbed=vec(None, model.node_capacity),
        node_f_load=vec(None, model.node_capacity),
        tet_active=arr(np.ones(nt), int, model.tet_capacity),
        tet_stress=wp.zeros(model.tet_capacity, dtype=wp.mat33, device=device),
        time=wp.zeros(1, dtype=wp.float64, device=device),
        node_energy_boundary_work=wp.zeros(model.node_capacity, dtype=wp.float64, device=device),
        load_face_force=wp.zeros(loaded_faces, dtype=wp.vec3, device=device),
        load_face_work=wp.zeros(loaded_faces, dtype=wp.float64, device=device),
        load_face_impulse=wp.zeros(loaded_faces, dtype=wp.float64, device=device),
        **fem_contact_state(model),
        **fracture_state(model),
        **conversion_state(model),
        **rigid_state(model),
    )
