"""The stable step of a model whose blocks turned rigid (warpdem.stages.rigid): the bodies' own, from their contact
springs and dashpots (:func:`rigid_critical_step`), and that of what the switch left deformable, tets, dashpots, surface
springs and spheres (:func:`deformable_critical_step`, :func:`sphere_critical_step`); the step after a switch is the
least (:func:`rigid_step_after_switch`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import warp as wp

from ..kernels import rigid as kr
from ..kernels.node_face_target import SPRING_BOUND
from ..kernels.tets import TET_ACTIVE
from ..model import Model, State
from .fragments import block_labels
from .guard import CriticalStep
from .loads import dashpot_critical_step
from .rigid import _rotations, body_frames, has_bodies, make_bodies
from .tets import reference_geometry, tet_stable_time_steps


def contact_damping_ratio(model: Model) -> float:
    """The largest damping ratio ζ of the FEM contacts and joints of a model [-] (0 without any)."""
    ratios = [0.0]
    if model.fem_pair_table is not None:
        ratios += model.fem_pair_table.numpy()["damp_n"].tolist()
    if model.joint_material_table is not None and model.joint_set_props:
        ratios += model.joint_material_table.numpy()["contact"]["damp_n"].tolist()
    return float(max(ratios))


def rigid_time_step(model: Model, state: State, safety_factor: float) -> Model:
    """The model with the time step of rigid blocks from the start: ``safety_factor`` × :func:`rigid_step_after_switch`
    of the bodies the switch will make (made on copies, so the model and state are left as they are), where that is
    finite; else the model as it is.
    """
    probe = dataclasses.replace(model, node_motion=wp.clone(model.node_motion))
    bodies, _ = make_bodies(probe, state.clone())
    step = rigid_step_after_switch(probe, bodies)
    if not math.isfinite(step.value):
        return model
    return dataclasses.replace(
        model,
        dt=safety_factor * step.value,
        critical_dt=step.value,
        critical_dt_source=step.source,
        deformable_critical_dt=model.critical_dt,
    )


def rigid_step_after_switch(model: Model, state: State) -> CriticalStep:
    """The critical step of a model whose blocks turned rigid [s], before the safety factor, and what sets it: the
    least of the bodies' own (:func:`rigid_critical_step`: their contact springs and dashpots) and that of what is
    left deformable (:func:`deformable_critical_step`: its tets, dashpots, contact springs and spheres). Reads back."""
    rigid = CriticalStep(
        rigid_critical_step(model, state, contact_damping_ratio(model)),
        "the contact springs and dashpots of the rigid blocks (warpdem.stages.rigid_step.rigid_critical_step)",
    )
    left = deformable_critical_step(model, state)
    return left if left.value < rigid.value else rigid


def deformable_critical_step(model: Model, state: State) -> CriticalStep:
    """The critical step of what a switch left deformable [s], before the safety factor, and what sets it (inf when
    nothing is left). Host, reference configuration; reads back.

    The builder's bounds (warpdem.build.builder.ModelBuilder.critical_step), restricted to the active tets that did not
    turn rigid (``tet_active`` = 1) and the nodes that follow no body — a node shared with a rigid tet moves with its
    block, whose step :func:`rigid_critical_step` bounds (a body's effective mass at a node is at least the node's own
    share, so the tets next to it are bounded by their own element steps):

    - each tet's element step (warpdem.stages.tets.tet_stable_time_steps, with its bulk viscosity and mass damping);
    - the nodes under non-reflecting dashpots (warpdem.stages.loads.dashpot_critical_step);
    - the contact springs of the deformable surface nodes, where contacts can engage (as the builder: walls, spheres,
      joints, cohesive elements, or more than one tet body): ω² = 4 SPRING_BOUND k/m with the node's penalty stiffness
      k = ``node_contact_stiffness`` and lumped mass m (two such nodes pressed together by both passes of the
      contact, each node's springs on several face planes no stiffer than SPRING_BOUND k = 2 k along any direction,
      warpdem.stages.fem_contact.contact_critical_step_at), dt = 2/ω (sqrt(1 + ζ²) − ζ). After the joints' split
      the side of each node is known, so k/m is the node's own, not the builder's bound over its tets;
    - spheres left (scene spheres, converted tets): their own step (:func:`sphere_critical_step`).
    """
    nt = int(state.tet_count.numpy()[0])
    nn = int(state.node_count.numpy()[0])
    deformable = state.tet_active.numpy()[:nt] == int(TET_ACTIVE)
    tets = model.tet_nodes.numpy()[:nt][deformable].astype(np.int64)
    steps = [CriticalStep(math.inf, "nothing deformable is left")]
    if int(state.particle_count.numpy()[0]) > 0:
        steps.append(sphere_critical_step(model, state))
    if len(tets):
        points = model.node_ref_q.numpy()[:nn].astype(np.float64)
        table = model.tet_material_table.numpy()
        material = model.tet_material.numpy()[:nt][deformable]
        props = {name: table[name].astype(np.float64)[material] for name in ("mu", "lam", "density", "c_lin", "alpha")}
        inv_ref, _ = reference_geometry(points, tets)
        per_tet = tet_stable_time_steps(
            inv_ref, props["mu"], props["lam"], props["density"], props["c_lin"], props["alpha"]
        )
        k = int(np.argmin(per_tet))
        tet = int(np.flatnonzero(deformable)[k])
        steps.append(CriticalStep(float(per_tet[k]), f"deformable tet {tet} left after the rigid switch"))
        moving = model.node_motion.numpy()[:nn] != int(kr.NODE_RIGID)
        dashpots = model.loads.dashpots if model.loads is not None else None
        if dashpots is not None:
            dashpot = dashpot_critical_step(
                points, tets, props, dashpots.nodes.numpy(), dashpots.impedance.numpy().astype(np.float64), moving
            )
            steps.append(CriticalStep(dashpot, "the non-reflecting dashpots on the deformable nodes left"))
        if model.node_contact_stiffness is not None and _contacts_can_engage(model, state):
            spring = model.node_contact_stiffness.numpy()[:nn].astype(np.float64)
            mass = model.node_mass.numpy()[:nn].astype(np.float64)
            ratio = np.where(moving & (spring > 0.0) & (mass > 0.0), spring / np.where(mass > 0.0, mass, 1.0), 0.0)
            node = int(np.argmax(ratio))
            if ratio[node] > 0.0:
                omega = 2.0 * math.sqrt(SPRING_BOUND * ratio[node])
                zeta = contact_damping_ratio(model)
                contact = 2.0 / omega * (math.sqrt(1.0 + zeta**2) - zeta)
                steps.append(CriticalStep(contact, f"the contact penalty springs of deformable node {node}"))
    return min(steps, key=lambda c: c.value)


def sphere_critical_step(model: Model, state: State) -> CriticalStep:
    """The critical step of the spheres [s], before the safety factor, and what sets it (inf without spheres): the
    builder's bounds on its spheres (warpdem.build.builder.ModelBuilder.critical_step) from what the model holds now.
    Host; reads back.

    - Their contacts (warpdem.stages.contact.sphere_contact_steps), with each sphere's own radius and mass (a converted
      tet's sphere carries the tet's mass ρV) and its material's E and ν from the material's pair with itself in
      ``pair_table`` (E = ``young_a``, 1 − ν² = E / (2 E*)), at twice the fastest sphere's speed now; sphere–face
      contacts take the same laws, with the face's material.
    - The live intact bonds between spheres that no tet became (warpdem.stages.bonds.bond_critical_step).
    - Spheres of converted tets (``tet_sphere`` + 0 … spheres_per_tet − 1): the bound of the converted lattice the
      conversion's attach checks the step against (warpdem.stages.conversion.conversion_critical_step over the tets that
      converted: the bonds and couplings on one sphere sum to no more than the fully bonded sphere's).
    """
    from ..host_data import BondData
    from .bonds import bond_critical_step
    from .contact import sphere_contact_steps
    from .conversion import conversion_critical_step

    n = int(state.particle_count.numpy()[0])
    nb = int(state.bond_count.numpy()[0])
    intact = np.flatnonzero(state.bond_broken.numpy()[:nb] == 0)
    free = model.particle_motion.numpy()[:n] == 0
    steps = [CriticalStep(math.inf, "no sphere")]
    if not (free.any() or len(intact)):
        return steps[0]
    radius = model.particle_radius.numpy()[:n].astype(np.float64)
    mass = model.particle_mass.numpy()[:n].astype(np.float64)
    material = model.particle_material.numpy()[:n]
    part = model.particle_part.numpy()[:n]
    pairs = model.pair_table.numpy()[:: model.num_materials + 1]  # each material with itself
    young = pairs["young_a"].astype(np.float64)[material]
    estar = pairs["estar"].astype(np.float64)[material]
    poisson = np.sqrt(np.maximum(1.0 - young / (2.0 * estar), 0.0))
    speed = 2.0 * float(np.linalg.norm(state.particle_qd.numpy()[:n].astype(np.float64), axis=1).max(initial=0.0))

    def describe(k: int) -> str:
        where = f"(r = {radius[k]:.3g} m, part {model.part_names[part[k]]})" if model.part_names else ""
        return f"spheres of material {model.material_names[material[k]]} {where}".rstrip()

    steps += sphere_contact_steps(model.normal_model, radius, mass, young, poisson, estar, speed, describe)
    converted = np.zeros(n, dtype=bool)
    if model.conversion_material_table is not None:
        nt = int(state.tet_count.numpy()[0])
        first = state.tet_sphere.numpy()[:nt]
        converted[(first[first >= 0, None] + np.arange(model.spheres_per_tet)).ravel()] = True
        if converted.any():
            lattice, tet = conversion_critical_step(model, state, first >= 0)
            words = f"the bonded spheres of converted tet {tet} (warpdem.stages.conversion.conversion_critical_step)"
            steps.append(CriticalStep(lattice, words))
    # The converted lattice's bonds are bounded above, as at the conversion's attach (its sum of the bonds on a
    # sphere, not bond_critical_step's most bonds times the stiffest).
    intact = intact[~converted[state.bond_i.numpy()[intact]]]
    if len(intact):
        fields = ("rest_length", "kn", "ks", "area", "tensile_strength", "shear_strength", "damping")
        bonds = BondData(
            np.stack([state.bond_i.numpy()[intact], state.bond_j.numpy()[intact]], axis=1),
            *(getattr(state, f"bond_{name}").numpy()[intact].astype(np.float64) for name in fields),
        )
        steps.append(bond_critical_step(mass, part, bonds, model.part_names))
    return min(steps, key=lambda c: c.value)


def _contacts_can_engage(model: Model, state: State) -> bool:
    """Whether the FEM contacts of a model can engage, as the builder decides it for its contact step
    (warpdem.build.builder.ModelBuilder.contact_critical_step): walls, spheres, joints or cohesive elements (cracks), or
    more than one tet body (rigid or not, connected through shared nodes; warpdem.stages.fragments.block_labels)."""
    if model.num_walls > 0 or model.max_radius > 0.0 or model.joint_set_props or model.cohesive_capacity > 0:
        return True
    nt = int(state.tet_count.numpy()[0])
    live = np.zeros(model.tet_capacity, dtype=np.int32)
    live[:nt] = state.tet_active.numpy()[:nt] != 0
    every = dataclasses.replace(model, tet_may_rigid=None)
    _, bodies = block_labels(
        every, dataclasses.replace(state, tet_active=wp.array(live, dtype=int, device=model.device))
    )
    return bodies > 1


def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors that span the plane normal to each unit n, shape (B, 3) each."""
    helper = np.where((np.abs(n[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def _allowed_basis(state: State, axes: np.ndarray, moments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The motions each body's rollers allow as columns of a (B, 6, 6) basis in body-frame coordinates (translation,
    rotation), zero columns where fewer than six are allowed, and the diagonal mass of those coordinates, shape
    (B, 6) (1 on the zero columns): M and the principal moments when free; M, M, I_n on a plane; M on a line."""
    count = len(moments)
    mass = state.body_mass.numpy()
    constraint, n = state.body_constraint.numpy(), state.body_axis.numpy()
    basis = np.zeros((count, 6, 6))
    diag = np.ones((count, 6))
    free = constraint == int(kr.BODY_FREE)
    basis[free] = np.eye(6)
    diag[free] = np.concatenate([np.repeat(mass[free, None], 3, axis=1), moments[free]], axis=1)
    to_body = np.swapaxes(axes, 1, 2)  # world → body frame: the principal axes now, as rows
    plane = np.flatnonzero(constraint == int(kr.BODY_PLANE))
    if len(plane):
        t1, t2 = _plane_basis(n[plane])
        basis[plane, :3, 0] = np.einsum("bij,bj->bi", to_body[plane], t1)
        basis[plane, :3, 1] = np.einsum("bij,bj->bi", to_body[plane], t2)
        nb = np.einsum("bij,bj->bi", to_body[plane], n[plane])
        basis[plane, 3:, 2] = nb
        diag[plane, :2] = mass[plane, None]
        diag[plane, 2] = np.sum(moments[plane] * nb * nb, axis=1)
    line = np.flatnonzero(constraint == int(kr.BODY_LINE))
    if len(line):
        basis[line, :3, 0] = np.einsum("bij,bj->bi", to_body[line], n[line])
        diag[line, 0] = mass[line]
    return basis, diag


def _body_jacobians(rb: np.ndarray) -> np.ndarray:
    """J = [1, −[r]×] of nodes at body-frame offsets r, shape (n, 3, 6): a node's velocity from its body's."""
    cross = np.zeros((len(rb), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -rb[:, 2], rb[:, 1], -rb[:, 0]
    cross[:, 1, 0], cross[:, 2, 0], cross[:, 2, 1] = rb[:, 2], -rb[:, 1], rb[:, 0]
    return np.concatenate([np.broadcast_to(np.eye(3), (len(rb), 3, 3)), -cross], axis=2)


def _dashpot_matrices(
    model: Model, state: State, axes: np.ndarray, frame_of: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The non-reflecting dashpots on the bodies' nodes (warpdem.stages.loads: a third of each face's area times ρ c_p
    along its normal and ρ c_s across it, at the faces' current positions): the node of each dashpot corner and its
    damping matrix in its body's frame [N s/m], shapes (k,) and (k, 3, 3); empty without dashpots or where no corner is
    a body's node."""
    loads = model.loads
    if loads is None or loads.dashpots is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3))
    d = loads.dashpots
    faces = d.nodes.numpy().astype(np.int64)
    impedance = d.impedance.numpy().astype(np.float64)
    x = model.node_ref_q.numpy().astype(np.float64) + state.node_u.numpy().astype(np.float64)
    xf = x[faces]
    a = 0.5 * np.cross(xf[:, 1] - xf[:, 0], xf[:, 2] - xf[:, 0])
    area = np.linalg.norm(a, axis=1)
    normal = a / np.maximum(area, 1e-300)[:, None]
    nn = np.einsum("fi,fj->fij", normal, normal)
    c = (area / 3.0)[:, None, None] * (
        impedance[:, 0, None, None] * nn + impedance[:, 1, None, None] * (np.eye(3) - nn)
    )
    nodes = faces.ravel()
    c = np.repeat(c, 3, axis=0)
    body = frame_of[nodes]
    keep = body >= 0
    nodes, c, body = nodes[keep], c[keep], body[keep]
    to_body = np.swapaxes(axes[body], 1, 2)
    return nodes, np.einsum("nia,nab,njb->nij", to_body, c, to_body)


def rigid_critical_step(model: Model, state: State, damping_ratio: float = 0.0) -> float:
    """Stable step of the rigid bodies on their contact springs and dashpots [s], before the safety factor (reads
    back).

    Every surface node i of a body (penalty stiffness k_i = ``node_contact_stiffness``, warpdem.stages.fem_contact)
    pressed by a contact at once gives the body the stiffness K = Σ k_i J_iᵀ J_i on its six velocities (J_i = [1,
    −[r_i]×], the node's velocity from the body's), against its mass matrix diag(M, M, M, I), with k_i = SPRING_BOUND ×
    the node's penalty stiffness: a node holds a spring per face plane it lies behind, k Σ_s n_s n_sᵀ, whose normals
    are pairwise |n_s · n_t| ≤ cos θ_g, so it is no stiffer than SPRING_BOUND k = 2 k along any direction
    (kernels/node_face_target.py ``PLANE_GROUP_COS``; three orthogonal springs are exactly k I). A spring between
    two bodies stores ½ k |u_A − u_B|² ≤ k (|u_A|² + |u_B|²), so no mode of the assembly exceeds
    ω² = 2 max_b λ_max(M_b⁻¹ K_b). The non-reflecting dashpots on its nodes (C_i, warpdem.stages.loads) give it
    D = Σ J_iᵀ C_i J_i, explicit at the half-step velocity: c = λ_max(M_b⁻¹ D_b), ζ = ζ_contact + c / (2ω). On roller
    constraints K, D and the mass are those of the allowed motions (:func:`_allowed_basis`).
    dt = min_b 2/ω (sqrt(1 + ζ²) − ζ) (2/c without springs), as for the nodes. Held bodies, and deformable nodes and
    tets (whose own steps still hold where some remain), are not counted.
    """
    if not has_bodies(state) or model.node_contact_stiffness is None:
        return math.inf
    free = np.flatnonzero(state.body_fixed.numpy() == 0)
    if len(free) == 0:
        return math.inf
    nodes = state.rigid_nodes.numpy()
    node_body = state.node_body.numpy()
    body = node_body[nodes].astype(np.int64)
    k = SPRING_BOUND * model.node_contact_stiffness.numpy()[nodes].astype(np.float64)
    axes, moments = body_frames(state)
    r0 = state.node_rigid_r0.numpy()
    rotations = _rotations(state.body_q.numpy())
    # Body-frame offsets, so that the rotational block of the mass matrix is diagonal.
    r = np.einsum("bij,bj->bi", rotations[body], r0[nodes])
    jac = _body_jacobians(np.einsum("nik,ni->nk", axes[body], r))  # (n, 3, 6)
    count = len(moments)
    stiff = np.zeros((count, 6, 6))
    np.add.at(stiff, body, k[:, None, None] * np.einsum("nia,nib->nab", jac, jac))
    damp_nodes, c = _dashpot_matrices(model, state, axes, node_body.astype(np.int64))
    damp = np.zeros((count, 6, 6))
    if len(damp_nodes):
        damp_body = node_body[damp_nodes].astype(np.int64)
        rd = np.einsum("bij,bj->bi", rotations[damp_body], r0[damp_nodes])
        jd = _body_jacobians(np.einsum("nik,ni->nk", axes[damp_body], rd))
        np.add.at(damp, damp_body, np.einsum("nia,nij,njb->nab", jd, c, jd))
    basis, diag = _allowed_basis(state, axes, moments)
    inv_sqrt = 1.0 / np.sqrt(diag)
    transform = basis * inv_sqrt[:, None, :]  # columns scaled: the allowed coordinates in the mass metric

    def largest(matrix: np.ndarray) -> np.ndarray:
        reduced = np.einsum("bia,bij,bjc->bac", transform[free], matrix[free], transform[free])
        return np.maximum(np.linalg.eigvalsh(reduced)[:, -1], 0.0)

    omega = np.sqrt(2.0 * largest(stiff))
    c_max = largest(damp)
    with np.errstate(divide="ignore", invalid="ignore"):
        zeta = damping_ratio + np.where(omega > 0.0, c_max / (2.0 * omega), 0.0)
        springs = 2.0 / omega * (np.sqrt(1.0 + zeta**2) - zeta)
        step = np.where(omega > 0.0, springs, np.where(c_max > 0.0, 2.0 / c_max, np.inf))
    return float(step.min())
