"""Building a scene: a validated :class:`~warpdem.scene.Scene` (TOML) turned into a :class:`ModelBuilder` and then a
Model and its initial State, with the checks that need the built geometry (representable numbers, initial overlaps,
the explicit time step against the critical one).

Everything here runs once, on the host, before the first step; errors about the user's input are SceneErrors that
name the scene file and the key.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import warp as wp

from ..limits import F32_MAX
from ..model import Model, State
from ..scene import Scene, SceneError
from ..stages.bonds import CoincidentSpheresError
from ..stages.guard import UnstableTimeStepError
from . import packing
from .builder import InteractionProps, ModelBuilder
from .mesh import tet_signed_volumes
from .overlap import OVERLAP_TOLERANCE, InitialOverlap


def packing_region(region) -> packing.Box | packing.Cylinder:
    """The packing module's region for a scene Region."""
    if region.box is not None:
        return packing.Box(np.asarray(region.box.lo, float), np.asarray(region.box.hi, float))
    c = region.cylinder
    return packing.Cylinder(np.asarray(c.center, float), float(c.radius), float(c.height), "xyz".index(c.axis))


def read_particle_file(path: Path, radius: float | None, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 3) [m] and radii (N,) [m] from a text file of ``x y z`` or ``x y z r`` lines."""
    try:
        data = np.loadtxt(path, comments="#", ndmin=2, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise SceneError(f"{where}.path: cannot read particle file {path}: {exc}") from None
    if data.size == 0:
        raise SceneError(f"{where}.path: particle file {path} has no spheres")
    if data.shape[1] not in (3, 4):
        raise SceneError(f"{where}.path: {path} has {data.shape[1]} columns; allowed: 3 (x y z) or 4 (x y z r)")
    if not np.all(np.isfinite(data) & (np.abs(data) <= F32_MAX)):
        raise SceneError(f"{where}.path: {path} contains non-finite numbers or numbers beyond {F32_MAX:g}")
    if data.shape[1] == 4:
        if np.any(data[:, 3] <= 0):
            raise SceneError(f"{where}.path: {path} has radii <= 0")
        return data[:, :3], data[:, 3]
    if radius is None:
        raise SceneError(f"{where}.radius: required because {path} has 3 columns (x y z)")
    return data, np.full(len(data), radius)


def scene_builder(scene: Scene) -> ModelBuilder:
    """A ModelBuilder holding everything a validated scene describes.

    Raises:
        SceneError: a particle file cannot be read, or a region holds no sphere.
    """
    source = scene.source
    c = scene.contact
    b = ModelBuilder(
        normal=c.normal,
        tangential=c.tangential,
        rolling=c.rolling,
        gravity=tuple(scene.gravity.vector),
        contact_normal_stiffness=c.surface_normal_stiffness,
    )
    for name, mat in scene.materials.items():
        b.add_material(name, mat.density, mat.youngs_modulus, mat.poisson_ratio)
    names = scene.material_names()
    for ia, a in enumerate(names):
        for bname in names[ia:]:
            it = scene.interaction_for(a, bname)
            b.set_interaction(a, bname, InteractionProps(it.friction, it.restitution, it.rolling_friction))
    rng = np.random.default_rng(scene.run.seed)
    for k, src in enumerate(scene.particles):
        where = f"particles[{k}]"
        material = scene.parts[src.part].material
        if src.kind == "packing":
            region = packing_region(src.region)
            if src.arrangement == "random":
                q, r = packing.random_packing(
                    region,
                    src.radius,
                    src.radius_max or src.radius,
                    rng,
                    volume_fraction=src.target_volume_fraction,
                    max_count=src.count,
                )
            else:
                q = packing.lattice_packing(region, src.radius, src.arrangement, max_count=src.count)
                r = np.full(len(q), src.radius)
            if len(q) == 0:
                raise SceneError(f"{source}: {where}.region: no sphere of radius {src.radius} fits in the region")
            b.add_spheres(q, r, material, velocity=src.velocity, part=src.part)
        elif src.kind == "sphere":
            b.add_sphere(
                src.center,
                src.radius,
                material,
                velocity=src.velocity,
                angular_velocity=src.angular_velocity,
                motion=src.motion,
                part=src.part,
            )
        else:
            q, r = read_particle_file(Path(src.path), src.radius, f"{source}: {where}")
            b.add_spheres(q, r, material, velocity=src.velocity, part=src.part)
    q_all = b.particle_data().q
    for k, bond in enumerate(scene.bonds):
        ids = np.nonzero(bond.region.contains(q_all))[0] if len(q_all) else np.zeros(0, int)
        if len(ids) < 2:
            raise SceneError(f"{source}: bonds[{k}].region: contains {len(ids)} sphere(s); a bond needs two")
        b.add_bonded_group(
            ids,
            youngs_modulus=scene.bond_youngs_modulus(bond),
            tensile_strength=bond.tensile_strength,
            shear_strength=bond.shear_strength,
            stiffness_ratio=bond.stiffness_ratio,
            radius_factor=bond.radius_factor,
            gap_tolerance=bond.gap_tolerance,
            damping_ratio=bond.damping_ratio,
        )
    for wall in scene.walls:
        if wall.kind == "plane":
            b.add_plane_wall(wall.point, wall.normal, wall.material, wall.velocity)
        else:
            b.add_box_walls(wall.lo, wall.hi, wall.material, open_top=wall.open_top)
    if scene.mesh is not None:
        from .scene_mesh import add_scene_mesh

        add_scene_mesh(b, scene)
    if scene.conversion.enabled:
        b.part_id(scene.conversion.part)  # the spawned spheres' part, named in the model like the sources' parts
    return b


def build_scene(scene: Scene, device: wp.context.DeviceLike = None) -> tuple[Model, State]:
    """Model and initial state of a validated scene on ``device`` (default: the scene's run.device)."""
    return finalize_scene(scene, scene_builder(scene), device)


FLOAT32_TINY = float(np.finfo(np.float32).tiny)
"""Smallest normal float32 [-]: a mass or moment of inertia below it has no finite inverse on the device."""


def _check_representable(scene: Scene, b: ModelBuilder) -> None:
    """Refuses sphere masses and moments of inertia (ρ 4/3 π r³, 2/5 m r²) and tet node masses (ρ V / 4) that the
    device's float32 cannot hold with a finite inverse: each scene number is in range (warpdem.limits), but their
    products need not be.

    Raises:
        SceneError: naming the material's density, with the range of the offending quantity.
    """
    names = list(b.materials)
    quantities: list[tuple[int, str, np.ndarray]] = []
    if b.sphere_count:
        particles = b.particle_data()
        mass = np.array([b.materials[names[m]].density for m in particles.material]) * (
            4.0 / 3.0 * math.pi * particles.radius**3
        )
        quantities += [(m, "sphere mass [kg]", mass[particles.material == m]) for m in np.unique(particles.material)]
        inertia = 0.4 * mass * particles.radius**2
        quantities += [
            (m, "sphere moment of inertia [kg m²]", inertia[particles.material == m])
            for m in np.unique(particles.material)
        ]
    if b.node_count:
        mesh = b.tet_mesh_data()
        density = np.array([b.materials[n].density for n in names])[mesh.material]
        node_mass = density * np.abs(tet_signed_volumes(mesh.points, mesh.tets)) / 4.0
        quantities += [(m, "tet node mass [kg]", node_mass[mesh.material == m]) for m in np.unique(mesh.material)]
    for m, what, values in quantities:
        lo, hi = float(values.min()), float(values.max())
        if not (lo >= FLOAT32_TINY and hi <= F32_MAX):
            raise SceneError(
                f"{scene.source}: materials.{names[m]}.density: gives a {what} from {lo:.3g} to {hi:.3g}, outside "
                f"what the device's float32 holds ({FLOAT32_TINY:.3g} to {F32_MAX:g}); check the density and the sizes"
            )


def finalize_scene(scene: Scene, b: ModelBuilder, device: wp.context.DeviceLike = None) -> tuple[Model, State]:
    """Model and initial state from the builder of a scene (:func:`scene_builder`), with the scene's run settings.

    The initial overlaps are measured first (``b.overlap``, :meth:`ModelBuilder.measure_initial_overlap`).

    Raises:
        SceneError: the scene creates neither a sphere nor a tet, a mesh file's joint faces are not interior faces, or
            spheres start overlapping each other or the rock beyond OVERLAP_TOLERANCE (or with a centre inside the
            rock) and ``run.allow_initial_overlap`` is off,
            or an explicit run.dt exceeds the critical time step and run.allow_unstable_dt is off.
    """
    from ..stages.joints import JointFaceError

    if b.sphere_count == 0 and b.node_count == 0:
        raise SceneError(f"{scene.source}: particles: the scene creates no sphere (and has no [mesh])")
    _check_representable(scene, b)
    run = scene.run
    overlap = b.measure_initial_overlap(device if device is not None else run.device)
    overlapping = overlap.exceeds(OVERLAP_TOLERANCE) and not run.allow_initial_overlap
    skin = None if scene.contact.skin == "auto" else float(scene.contact.skin)
    try:
        built = b.finalize(
            device if device is not None else run.device,
            dt=None if run.dt == "auto" else float(run.dt),
            safety_factor=run.safety_factor,
            skin=skin,
            max_neighbors=scene.capacity.neighbors_per_particle,
            particle_capacity=scene.capacity.particles,
            node_capacity=scene.capacity.nodes,
            tet_capacity=scene.capacity.tets,
            allow_unstable_dt=run.allow_unstable_dt,
        )
    except JointFaceError as exc:
        raise SceneError(f"{scene.source}: mesh: {exc}") from None
    except CoincidentSpheresError as exc:
        raise SceneError(f"{scene.source}: bonds[{exc.group}].region: {exc}") from None
    except UnstableTimeStepError as exc:
        if overlapping:  # deep initial overlaps set the critical step: name the cause, not the symptom
            raise _overlap_error(scene, overlap) from None
        raise SceneError(
            f"{scene.source}: run.dt: {exc}; allowed: dt <= {exc.critical.value:.4g} s, dt = 'auto' "
            f"(run.safety_factor x the critical step), or run.allow_unstable_dt = true to run it anyway"
        ) from None
    # Coincident bonded spheres (the more specific error, naming the source) were refused by finalize first.
    if overlapping:
        raise _overlap_error(scene, overlap)
    return attach_scene_rigid(scene, *attach_scene_conversion(scene, *attach_scene_fracture(scene, *built)))


def tet_centroids(model: Model, state: State) -> np.ndarray:
    """Centroids of the live tets at the current node positions [m], shape (tet_count, 3), float64."""
    count = int(state.tet_count.numpy()[0])
    tets = model.tet_nodes.numpy()[:count]
    return state.node_q.numpy()[tets].astype(np.float64).mean(axis=1)


def attach_scene_conversion(scene: Scene, model: Model, state: State) -> tuple[Model, State]:
    """Turns FEM→DEM conversion on for a built scene with ``[conversion] enabled`` (else returns model and state as
    they are): each material's criterion strengths in material-id order
    (:func:`warpdem.stages.conversion.attach_conversion`; a material no tet is made of never converts), the check
    interval, the spawned spheres' part, and the tets that may convert: those whose centroid lies in
    ``[conversion].region`` at the built positions.

    Raises:
        SceneError: the conversion pass refuses the settings (its message, naming [conversion]).
    """
    conversion = scene.conversion
    if not conversion.enabled:
        return model, state
    from ..stages.conversion import ConversionProps, attach_conversion

    # Every material a tet is made of has the strength its criterion reads (checked at load and at the mesh build); a
    # sphere or wall material gets None and never converts.
    count = int(state.tet_count.numpy()[0])
    used = set(np.unique(model.tet_material.numpy()[:count]).tolist())
    props = [
        ConversionProps(
            criterion=conversion.criterion,
            fraction=conversion.fraction,
            tresca_strength=m.tresca_strength,
            tensile_strength=m.tensile_strength,
            cohesion=m.cohesion,
            friction_angle=m.friction_angle,
        )
        if mid in used
        else None
        for mid, m in enumerate(scene.materials.values())
    ]
    may_convert = None if conversion.region is None else conversion.region.contains(tet_centroids(model, state))
    try:
        return attach_conversion(
            model,
            state,
            props,
            check_interval=conversion.check_interval,
            may_convert=may_convert,
            spheres_per_tet=conversion.spheres_per_tet,
            part=model.part_names.index(conversion.part),
            band_width=conversion.band_width if conversion.coupling == "band" else 0,
            band_penalty=conversion.band_penalty,
            safety_factor=scene.run.safety_factor if scene.run.dt == "auto" else None,
        )
    except ValueError as exc:
        # Values the schema already checks; a direct caller's mistake still names the key.
        key = "conversion.spheres_per_tet" if "spheres_per_tet" in str(exc) else "conversion"
        raise SceneError(f"{scene.source}: {key}: {exc}") from None


def attach_scene_rigid(scene: Scene, model: Model, state: State) -> tuple[Model, State]:
    """The model with the scene's ``[rigid]`` settings (else as it is): when the blocks turn rigid (from the start, at
    ``switch_time``, or by ``energy_fraction`` checked every ``check_interval`` steps) and which tets may (centroid in
    ``region`` at the built positions, material among ``materials``). The switch itself is the Simulation's
    (warpdem.simulation.Simulation.switch_to_rigid).

    Raises:
        SceneError: no tet lies in the region and materials given.
    """
    rigid = scene.rigid
    if not rigid.active:
        return model, state
    count = int(state.tet_count.numpy()[0])
    may = np.ones(count, dtype=bool)
    if rigid.region is not None:
        may &= rigid.region.contains(tet_centroids(model, state))
    if rigid.materials is not None:
        ids = [scene.material_index(name) for name in rigid.materials]
        may &= np.isin(model.tet_material.numpy()[:count], ids)
    if not may.any():
        raise SceneError(f"{scene.source}: rigid: no tet of the mesh lies in the region and materials given")
    flags = np.zeros(model.tet_capacity, dtype=np.int32)
    flags[:count] = may
    model = dataclasses.replace(
        model,
        rigid_switch=rigid.energy_fraction is None,
        rigid_switch_time=0.0 if rigid.enabled else float(rigid.switch_time or 0.0),
        rigid_energy_fraction=float(rigid.energy_fraction or 0.0),
        rigid_check_interval=rigid.check_interval,
        tet_may_rigid=None if may.all() else wp.array(flags, dtype=int, device=model.device),
    )
    return model, state


def start_as_spheres(scene: Scene, sim) -> int:
    """Converts the tets whose centroid lies in ``[conversion].start_as_spheres`` (Simulation.convert_tets), once,
    on a new run's Simulation before its first step (a restart's checkpoint already holds them as spheres).

    Returns:
        The number of tets converted (0 without the key).
    """
    region = scene.conversion.start_as_spheres
    if not scene.conversion.enabled or region is None:
        return 0
    mask = region.contains(tet_centroids(sim.model, sim.state))
    if not mask.any():
        raise SceneError(f"{scene.source}: conversion.start_as_spheres: contains no tet centroid of the mesh")
    return int(sim.convert_tets(mask).converted)


def attach_scene_fracture(scene: Scene, model: Model, state: State) -> tuple[Model, State]:
    """Turns nodal fracture on for a built scene with ``[fracture] enabled`` (else returns model and state as they
    are): T_f, Γ and α of every material in material-id order (:func:`warpdem.stages.fracture.attach_fracture`), the
    check interval, the initial cohesive slots, and the nodes that may split: those inside ``[fracture].region`` at
    their built positions (after the seed cracks' pre-split, so both copies of a crack node are judged alike).

    Raises:
        SceneError: the split pass refuses the settings (its message, naming [fracture]).
    """
    fracture = scene.fracture
    if not fracture.enabled:
        return model, state
    from ..stages.fracture import FractureProps, attach_fracture

    # A material needs both T_f and Γ to split (the mesh's were checked at load and build); one with only one of
    # them (a sphere or wall material, say) never splits.
    props = [
        FractureProps(m.tensile_strength, m.fracture_energy, m.cohesive_alpha)
        if m.tensile_strength is not None and m.fracture_energy is not None
        else FractureProps(None, None, m.cohesive_alpha)
        for m in scene.materials.values()
    ]
    may_split = None
    if fracture.region is not None:
        count = int(state.node_count.numpy()[0])
        may_split = fracture.region.contains(state.node_q.numpy()[:count])
    try:
        return attach_fracture(
            model,
            state,
            props,
            check_interval=fracture.check_interval,
            may_split=may_split,
            cohesive_capacity=fracture.cohesive_capacity,
            cohesive_substeps=fracture.cohesive_substeps,
        )
    except ValueError as exc:
        raise SceneError(f"{scene.source}: fracture: {exc}") from None


def _overlap_error(scene: Scene, overlap: InitialOverlap) -> SceneError:
    """The refusal of spheres that start overlapping each other or the rock beyond :data:`OVERLAP_TOLERANCE`."""
    return SceneError(
        f"{scene.source}: run.allow_initial_overlap: spheres start overlapping beyond the tolerance "
        f"({100.0 * OVERLAP_TOLERANCE:g} % of a radius, no centre in the rock): {overlap.format()}; move them "
        "apart (or out of the rock), or set allow_initial_overlap = true in [run] to start from this state anyway"
    )
