"""Running a scene: frames of captured steps, USD output, HDF5 checkpoints, restart, and the closing summary."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from . import __version__
from .builder import finalize_scene, scene_builder
from .checkpoint import CheckpointError, checkpoint_name, read_checkpoint, write_checkpoint
from .model import Model, State
from .scene import Scene, SceneError
from .simulation import EnergyBalance, Simulation

# Model fields that describe spheres (saved with a checkpoint so a restart never depends on rebuilding them).
MODEL_PARTICLE_FIELDS = (
    "particle_radius",
    "particle_mass",
    "particle_inv_mass",
    "particle_inv_inertia",
    "particle_material",
    "particle_motion",
    "particle_part",
    "particle_id",
)

MODEL_MESH_PREFIXES = ("node_", "tet_", "joint_")
"""Model fields of the FEM nodes, tets and joint elements (saved with a checkpoint so a restart never depends on
re-meshing or on the joint pre-split): every array whose name starts with one of these, except tables of structs,
which the scene's materials give."""


def mesh_model_fields(model: Model) -> list[str]:
    """Names of the Model arrays of the mesh (:data:`MODEL_MESH_PREFIXES`) that a checkpoint holds."""
    return [
        name
        for name, a in model.arrays().items()
        if name.startswith(MODEL_MESH_PREFIXES) and not wp.types.type_is_struct(a.dtype)
    ]


def _capacities(model: Model) -> dict[str, int]:
    """The mesh capacities of a model (``node_capacity``, ``tet_capacity``, ``joint_capacity`` where present)."""
    return {
        f.name: int(getattr(model, f.name))
        for f in dataclasses.fields(model)
        if f.name in ("node_capacity", "tet_capacity", "joint_capacity")
    }


@dataclass
class RunOptions:
    """Command-line overrides of a scene's run and output settings (None = the scene's value).

    Attributes:
        device: Warp device. end_time: simulated end time [s]. frames: number of output frames after the first
        (overrides end_time). out_dir: output directory. usd: USD file path. checkpoint_every: checkpoint period
        [s] (0 = at the end only). restart: checkpoint file to continue from. quiet: no progress bar or summary.
    """

    device: str | None = None
    end_time: float | None = None
    frames: int | None = None
    out_dir: Path | None = None
    usd: Path | None = None
    checkpoint_every: float | None = None
    restart: Path | None = None
    quiet: bool = False


@dataclass
class RunSummary:
    """What a run did: simulated time [s], steps, wall time [s], throughput [particle-steps/s], contacts now,
    bonds broken, the energy balance at start and end, and the files written; FEM nodes and live tets, throughput
    [tet-steps/s] and the VTU collection where the scene has a mesh.

    ``energy_in_play`` [J] is the largest :attr:`EnergyBalance.in_play` (kinetic + elastic + strain, or the work put
    in so far; no gravity potential) over the run's frames, and ``energy_error`` the balance's change over the run
    relative to it: a scale with no arbitrary datum, so the error does not depend on where z = 0 is."""

    simulated_time: float
    steps: int
    wall_time: float
    particle_steps_per_second: float
    particles: int
    contacts: int
    bonds_broken: int
    bonds_intact: int
    energy_start: EnergyBalance
    energy_end: EnergyBalance
    usd_path: Path | None
    checkpoints: list[Path]
    nodes: int = 0
    tets: int = 0
    tet_steps_per_second: float = 0.0
    pvd_path: Path | None = None
    energy_in_play: float = 0.0
    energy_error: float = 0.0

    def format(self) -> str:
        e0, e1 = self.energy_start, self.energy_end
        spheres = self.particles > 0
        lines = [f"simulated time   {self.simulated_time:.6g} s in {self.steps} steps"]
        if spheres:
            rate = self.particle_steps_per_second / 1e6
            lines += [
                f"wall time        {self.wall_time:.3f} s  ({rate:.3f} M particle-steps/s)",
                f"particles        {self.particles}   contacts {self.contacts}",
                f"bonds            {self.bonds_intact} intact, {self.bonds_broken} broken",
            ]
        else:
            lines.append(f"wall time        {self.wall_time:.3f} s")
        if self.nodes:
            rate = self.tet_steps_per_second / 1e6
            lines.append(f"rock mesh        {self.nodes} nodes, {self.tets} tets  ({rate:.3f} M tet-steps/s)")

        def row(label: str, a: float, b: float) -> str:
            return f"  {label:<15}{a:<14.6g} {b:.6g}"

        lines += ["energy [J]       start          end", row("kinetic", e0.kinetic, e1.kinetic)]
        if self.nodes:
            lines.append(row("  of nodes", e0.kinetic_nodes, e1.kinetic_nodes))
        lines.append(row("Verlet shadow", e0.shadow, e1.shadow))
        if self.nodes:
            lines += [
                row("strain", e0.strain, e1.strain),
                row("viscous diss.", e0.dissipated_viscous, e1.dissipated_viscous),
                row("non-refl. abs.", e0.absorbed_boundaries, e1.absorbed_boundaries),
                row("load work", e0.load_work, e1.load_work),
                row("contact diss.", e0.dissipated_fem_contact, e1.dissipated_fem_contact),
            ]
        lines.append(row("elastic", e0.elastic, e1.elastic))
        if e0.gravity_potential != 0.0 or e1.gravity_potential != 0.0:
            lines.append(row("gravity pot.", e0.gravity_potential, e1.gravity_potential))
        if spheres:
            lines += [
                row("damping diss.", e0.dissipated_damping, e1.dissipated_damping),
                row("friction diss.", e0.dissipated_friction, e1.dissipated_friction),
                row("k_t(δ) change", e0.stiffness_change, e1.stiffness_change),
                row("bond breakage", e0.released_by_bond_breakage, e1.released_by_bond_breakage),
                row("wall work", e0.boundary_work, e1.boundary_work),
            ]
        lines.append(
            f"  balance        {e0.total:<14.6g} {e1.total:.6g}   "
            f"(error {self.energy_error:+.2e} of {self.energy_in_play:.3g} J in play)"
        )
        if self.usd_path is not None:
            lines.append(f"USD              {self.usd_path}")
        if self.pvd_path is not None:
            lines.append(f"VTU series       {self.pvd_path}")
        if self.checkpoints:
            lines.append(f"checkpoint       {self.checkpoints[-1]}")
        return "\n".join(lines)


def speed_colors(speed: np.ndarray, scale: float) -> np.ndarray:
    """Blue (at rest) → red (at ``scale`` m/s and above), shape (N, 3)."""
    t = np.clip(speed / max(scale, 1e-12), 0.0, 1.0)[:, None]
    return (1.0 - t) * np.array([0.15, 0.3, 0.85]) + t * np.array([0.95, 0.25, 0.1])


PART_PALETTE = np.array(
    [[0.55, 0.55, 0.6], [0.85, 0.45, 0.2], [0.2, 0.6, 0.85], [0.4, 0.75, 0.3], [0.8, 0.3, 0.5], [0.9, 0.8, 0.3]]
)


def save_checkpoint(path: Path, sim: Simulation, frame: int, extra: dict) -> Path:
    """Write the complete state of a simulation (and the sphere and mesh parts of its model) to an HDF5 checkpoint."""
    arrays = {f"state/{name}": a.numpy() for name, a in sim.state.arrays().items()}
    for name in [*MODEL_PARTICLE_FIELDS, *mesh_model_fields(sim.model)]:
        arrays[f"model/{name}"] = getattr(sim.model, name).numpy()
    attrs = {
        "step": sim.step_count,
        "time": sim.time,
        "frame": frame,
        "dt": sim.model.dt,
        "particle_capacity": sim.model.particle_capacity,
        "max_neighbors": sim.model.max_neighbors,
        "bond_capacity": sim.model.bond_capacity,
        "num_walls": sim.model.num_walls,
        **_capacities(sim.model),
        "warpdem_version": __version__,
        **extra,
    }
    return write_checkpoint(path, arrays, attrs)


def restore_checkpoint(path: Path, model: Model, template: State) -> tuple[Model, State, dict]:
    """Model and state of a checkpoint, on the device of ``model`` (built from the same scene; ``template`` is its
    initial state and gives each array's type).

    Raises:
        CheckpointError: unreadable file, or one that does not belong to this scene.
    """
    arrays, attrs = read_checkpoint(path)
    for key, expected in (("bond_capacity", model.bond_capacity), ("num_walls", model.num_walls)):
        if int(attrs.get(key, -1)) != expected:
            raise CheckpointError(f"{path}: {key} is {attrs.get(key)} but the scene builds {expected}; wrong scene?")
    missing = [
        k
        for k in [f"model/{n}" for n in [*MODEL_PARTICLE_FIELDS, *mesh_model_fields(model)]]
        + [f"state/{n}" for n in template.arrays()]
        + [f"attrs/{n}" for n in _capacities(model) if n not in attrs]
        if k not in arrays
    ]
    if missing:
        raise CheckpointError(f"{path}: missing arrays {', '.join(missing)}")
    device = model.device

    def load(key: str, like: wp.array) -> wp.array:
        return wp.array(arrays[key], dtype=like.dtype, device=device)

    model = dataclasses.replace(
        model,
        particle_capacity=int(attrs["particle_capacity"]),
        max_neighbors=int(attrs["max_neighbors"]),
        dt=float(attrs["dt"]),
        **{name: int(attrs[name]) for name in _capacities(model)},
        **{
            name: load(f"model/{name}", getattr(model, name))
            for name in [*MODEL_PARTICLE_FIELDS, *mesh_model_fields(model)]
        },
    )
    state = State(**{name: load(f"state/{name}", a) for name, a in template.arrays().items()})
    return model, state, attrs


def run_scene(scene: Scene, options: RunOptions | None = None) -> RunSummary:
    """Run a validated scene to its end time, writing USD frames and checkpoints.

    Raises:
        SceneError: the scene cannot be built (for example a particle file that cannot be read).
        CheckpointError: the restart file cannot be used.
    """
    options = options or RunOptions()
    run = scene.run
    device_name = options.device or run.device
    try:
        device = wp.get_device(device_name)
    except (ValueError, RuntimeError) as exc:
        where = "--device" if options.device else f"{scene.name}: run.device"
        raise SceneError(f"{where}: device {device_name!r} is not available here ({exc})") from None
    builder = scene_builder(scene)
    if not options.quiet:
        for quality in builder.mesh_qualities:
            print(f"mesh: {quality.format()}")
    model, state = finalize_scene(scene, builder, device)

    fps = run.output_rate
    frame_period = 1.0 / fps
    if run.dt == "auto":
        substeps = max(1, math.ceil(frame_period / model.dt))
        model = dataclasses.replace(model, dt=frame_period / substeps)
    else:
        substeps = max(1, round(frame_period / model.dt))
    frame_period = substeps * model.dt

    step, sim_time, first_frame, primed = 0, 0.0, 0, False
    if options.restart is not None:
        model, state, attrs = restore_checkpoint(Path(options.restart), model, state)
        step, sim_time, first_frame, primed = int(attrs["step"]), float(attrs["time"]), int(attrs["frame"]), True
        if abs(model.dt * substeps - frame_period) > 1e-12 * frame_period:
            substeps = max(1, round(frame_period / model.dt))
    sim = Simulation(model, state, primed=primed, step=step, time=sim_time)

    end_time = options.end_time if options.end_time is not None else run.end_time
    total_frames = options.frames if options.frames is not None else max(1, math.ceil(end_time / frame_period - 1e-9))
    frames_left = max(0, total_frames - first_frame)

    out_dir = Path(options.out_dir) if options.out_dir is not None else Path(scene.output.directory)
    usd_path = Path(options.usd) if options.usd is not None else out_dir / scene.output.usd
    output_stem = usd_path.stem  # VTU files are named like the stage; a restart's collection gets its own name
    if options.restart is not None and options.usd is None:
        # A restart gets its own stage, on the original timeline, instead of replacing the first run's stage.
        usd_path = usd_path.with_name(f"{usd_path.stem}_from{first_frame:06d}{usd_path.suffix}")
    checkpoint_every = (
        options.checkpoint_every if options.checkpoint_every is not None else scene.output.checkpoint_every
    )
    checkpoint_dir = out_dir / scene.output.checkpoint_dir
    frames_per_checkpoint = max(1, round(checkpoint_every / frame_period)) if checkpoint_every > 0 else 0
    ckpt_extra = {"scene": scene.name, "substeps": substeps, "seed": run.seed}

    from .output import RockFrames, VtuSeries
    from .usd import UsdWriter

    speed_scale = [1e-12]
    checkpoints: list[Path] = []
    vtu = VtuSeries(out_dir, output_stem, first_frame) if scene.output.vtu and model.node_capacity else None
    rock = RockFrames(scene.output.mesh_color_by, vtu)

    def write_frame(writer: UsdWriter, frame: int) -> None:
        rock.write_vtu(frame, sim.time, sim.model, sim.state)
        n = sim.particle_count
        q = sim.state.particle_q.numpy()[:n]
        v = sim.state.particle_qd.numpy()[:n]
        speed = np.linalg.norm(v, axis=1)
        if scene.output.color_by == "part":
            colors = PART_PALETTE[sim.model.particle_part.numpy()[:n] % len(PART_PALETTE)]
        else:
            speed_scale[0] = max(speed_scale[0], float(speed.max(initial=0.0)))
            colors = speed_colors(speed, speed_scale[0])
        bonds = None
        if scene.output.bonds_as_curves and sim.model.bond_capacity:
            nb = sim.bond_count
            intact = sim.state.bond_broken.numpy()[:nb] == 0
            bonds = np.stack([sim.state.bond_i.numpy()[:nb][intact], sim.state.bond_j.numpy()[:nb][intact]], axis=1)
        writer.write_frame(
            time=sim.time,
            positions=q,
            radii=sim.model.particle_radius.numpy()[:n],
            velocities=v,
            ids=sim.model.particle_id.numpy()[:n].astype(np.int64),
            colors=colors,
            bonds=bonds,
            surface=rock.surface(sim.model, sim.state),
        )

    energy_start = sim.energy()
    in_play = energy_start.in_play
    progress = None
    if not options.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        progress = tqdm(
            total=round(frames_left * frame_period, 9), unit="s", unit_scale=False, desc=scene.name, file=sys.stderr
        )
    wall0 = time.perf_counter()
    steps0 = sim.step_count
    comment = f"warpdem {__version__}: {scene.name}"
    with UsdWriter(usd_path, 1.0 / frame_period, comment=comment, first_frame=first_frame) as writer:
        write_frame(writer, first_frame)
        for k in range(frames_left):
            sim.advance(substeps)
            frame = first_frame + k + 1
            write_frame(writer, frame)
            in_play = max(in_play, sim.energy().in_play)
            if progress is not None:
                progress.update(round(frame_period, 9))
            if frames_per_checkpoint and frame % frames_per_checkpoint == 0 and k < frames_left - 1:
                checkpoints.append(
                    save_checkpoint(checkpoint_dir / checkpoint_name(sim.step_count), sim, frame, ckpt_extra)
                )
        wall = time.perf_counter() - wall0
        checkpoints.append(
            save_checkpoint(
                checkpoint_dir / checkpoint_name(sim.step_count), sim, first_frame + frames_left, ckpt_extra
            )
        )
    if progress is not None:
        progress.close()
    steps = sim.step_count - steps0
    n = sim.particle_count
    tets = int(np.count_nonzero(sim.state.tet_active.numpy()[: int(sim.state.tet_count.numpy()[0])]))
    energy_end = sim.energy()
    return RunSummary(
        simulated_time=sim.time,
        steps=sim.step_count,
        wall_time=wall,
        particle_steps_per_second=n * steps / wall if wall > 0 else 0.0,
        particles=n,
        contacts=sim.contact_count(),
        bonds_broken=int(sim.state.bonds_broken_total.numpy()[0]),
        bonds_intact=sim.bond_count,
        energy_start=energy_start,
        energy_end=energy_end,
        usd_path=writer.path if hasattr(writer, "path") else usd_path,
        checkpoints=checkpoints,
        nodes=sim.node_count,
        tets=tets,
        tet_steps_per_second=tets * steps / wall if wall > 0 else 0.0,
        pvd_path=vtu.pvd_path if vtu is not None else None,
        energy_in_play=in_play,
        energy_error=(energy_end.total - energy_start.total) / max(in_play, 1e-300),
    )


def summary_json(summary: RunSummary) -> str:
    """The summary as JSON (for scripts)."""
    d = dataclasses.asdict(summary)
    d["usd_path"] = str(summary.usd_path) if summary.usd_path else None
    d["checkpoints"] = [str(p) for p in summary.checkpoints]
    d["pvd_path"] = str(summary.pvd_path) if summary.pvd_path else None
    return json.dumps(d, indent=1)
