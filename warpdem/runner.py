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
from .limits import MAX_ELEMENTS, MAX_STEPS
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
        max_steps: most time steps the run may take; more is refused before the first step (SceneError).
    """

    device: str | None = None
    end_time: float | None = None
    frames: int | None = None
    out_dir: Path | None = None
    usd: Path | None = None
    checkpoint_every: float | None = None
    restart: Path | None = None
    quiet: bool = False
    max_steps: int = MAX_STEPS


@dataclass
class RunSummary:
    """What a run did: simulated time [s], steps, wall time [s], throughput [particle-steps/s], contacts now,
    bonds broken, the energy balance at start and end, and the files written; FEM nodes and live tets, throughput
    [tet-steps/s] and the VTU collection where the scene has a mesh."""

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

    def format(self) -> str:
        e0, e1 = self.energy_start, self.energy_end
        # Relative to the energy in play: stored now, or put in by walls and loads over the run.
        stored = e1.kinetic + e1.elastic + e1.strain + abs(e1.gravity_potential)
        scale = max(abs(e0.total), stored, abs(e1.boundary_work) + abs(e1.load_work), 1e-300)
        lines = [
            f"simulated time   {self.simulated_time:.6g} s in {self.steps} steps",
            f"wall time        {self.wall_time:.3f} s  ({self.particle_steps_per_second / 1e6:.3f} M particle-steps/s)",
            f"particles        {self.particles}   contacts {self.contacts}",
            f"bonds            {self.bonds_intact} intact, {self.bonds_broken} broken",
        ]
        if self.nodes:
            rate = self.tet_steps_per_second / 1e6
            lines.append(f"rock mesh        {self.nodes} nodes, {self.tets} tets  ({rate:.3f} M tet-steps/s)")
        lines += [
            "energy [J]       start          end",
            f"  kinetic        {e0.kinetic:<14.6g} {e1.kinetic:.6g}",
        ]
        if self.nodes:
            lines += [
                f"    of nodes     {e0.kinetic_nodes:<14.6g} {e1.kinetic_nodes:.6g}",
                f"  strain         {e0.strain:<14.6g} {e1.strain:.6g}",
                f"  viscous diss.  {e0.dissipated_viscous:<14.6g} {e1.dissipated_viscous:.6g}",
                f"  load work      {e0.load_work:<14.6g} {e1.load_work:.6g}",
                f"  contact diss.  {e0.dissipated_fem_contact:<14.6g} {e1.dissipated_fem_contact:.6g}",
            ]
        lines += [
            f"  elastic        {e0.elastic:<14.6g} {e1.elastic:.6g}",
            f"  gravity pot.   {e0.gravity_potential:<14.6g} {e1.gravity_potential:.6g}",
            f"  damping diss.  {e0.dissipated_damping:<14.6g} {e1.dissipated_damping:.6g}",
            f"  friction diss. {e0.dissipated_friction:<14.6g} {e1.dissipated_friction:.6g}",
            f"  bond breakage  {e0.released_by_bond_breakage:<14.6g} {e1.released_by_bond_breakage:.6g}",
            f"  wall work      {e0.boundary_work:<14.6g} {e1.boundary_work:.6g}",
            f"  balance        {e0.total:<14.6g} {e1.total:.6g}   (error {(e1.total - e0.total) / scale:+.2e})",
        ]
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


# Attributes a checkpoint must hold for a restart: name -> (type, smallest allowed value, whether it must exceed it).
_CHECKPOINT_ATTRS: dict[str, tuple[type, float, bool]] = {
    "step": (int, 0, False),
    "time": (float, 0.0, False),
    "frame": (int, 0, False),
    "dt": (float, 0.0, True),
    "particle_capacity": (int, 0, False),
    "max_neighbors": (int, 0, True),
    "bond_capacity": (int, 0, False),
    "num_walls": (int, 0, False),
}


def _check_attrs(path: Path, attrs: dict, capacities: list[str]) -> None:
    """Raises CheckpointError naming the first attribute that is missing, of the wrong type or out of range."""
    spec = {**_CHECKPOINT_ATTRS, **{name: (int, 0, False) for name in capacities}}
    for name, (kind, low, strict) in spec.items():
        value = attrs.get(name)
        if value is None:
            raise CheckpointError(f"{path}: attribute {name!r} is missing; not a checkpoint of a warpdem run?")
        ok_type = isinstance(value, int) if kind is int else isinstance(value, int | float)
        if isinstance(value, bool) or not ok_type:
            raise CheckpointError(
                f"{path}: attribute {name!r} is {value!r}; expected {'an integer' if kind is int else 'a number'}"
            )
        if not (math.isfinite(value) and (value > low if strict else value >= low)):
            raise CheckpointError(
                f"{path}: attribute {name!r} is {value!r}; expected a finite number {'>' if strict else '>='} {low}"
            )
    if attrs["max_neighbors"] > MAX_ELEMENTS or attrs["particle_capacity"] * attrs["max_neighbors"] > MAX_ELEMENTS:
        raise CheckpointError(f"{path}: particle_capacity × max_neighbors exceeds {MAX_ELEMENTS} slots")


def restore_checkpoint(path: Path, model: Model, template: State) -> tuple[Model, State, dict]:
    """Model and state of a checkpoint, on the device of ``model`` (built from the same scene; ``template`` is its
    initial state and gives each array's type).

    Raises:
        CheckpointError: unreadable file, or one that does not belong to this scene.
    """
    arrays, attrs = read_checkpoint(path)
    for key, expected in (("bond_capacity", model.bond_capacity), ("num_walls", model.num_walls)):
        if key in attrs and attrs[key] != expected:
            raise CheckpointError(f"{path}: {key} is {attrs.get(key)} but the scene builds {expected}; wrong scene?")
    _check_attrs(path, attrs, list(_capacities(model)))
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
    slots = {
        "particle_capacity": int(attrs["particle_capacity"]),
        "neighbor slots": int(attrs["particle_capacity"]) * int(attrs["max_neighbors"]),
    }

    def load(key: str, like: wp.array) -> wp.array:
        data = arrays[key]
        if data.dtype.kind in "fc" and not np.all(np.isfinite(data)):
            bad = int(np.count_nonzero(~np.isfinite(data)))
            raise CheckpointError(f"{path}: {key} holds {bad} non-finite value(s); the run it saved had already failed")
        # Arrays sized by the particle capacity (or its neighbour slots) must agree with the attributes, or the
        # kernels would index past their ends.
        if like.shape and like.shape[0] == template.particle_q.shape[0] and key.startswith(("state/", "model/")):
            expected = slots["particle_capacity"]
        elif like.shape and like.shape[0] == template.nbr_index.shape[0] and key.startswith("state/nbr_"):
            expected = slots["neighbor slots"]
        else:
            expected = None
        if expected is not None and (data.ndim == 0 or len(data) != expected):
            raise CheckpointError(f"{path}: {key} has shape {data.shape}, not {expected} items as its attributes say")
        try:
            return wp.array(data, dtype=like.dtype, device=device)
        except (ValueError, TypeError, RuntimeError) as exc:
            detail = " ".join(str(exc).split())
            raise CheckpointError(
                f"{path}: {key}: {data.dtype} {data.shape} is not a {like.dtype.__name__} array ({detail})"
            ) from None

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


def _output_error(where: str, path: Path, exc: BaseException) -> SceneError:
    """A one-line SceneError for an output file that cannot be written (name too long, no permission, disk full)."""
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else " ".join(str(exc).split())
    return SceneError(f"{where}: cannot write {path}: {reason}")


def _check_steps(scene: Scene, steps_per_frame: float, options: RunOptions, frames: int | None) -> None:
    """Refuses a run of more than ``options.max_steps`` steps (``frames`` frames; None: one frame) before it starts.

    Raises:
        SceneError: naming run.dt, with the step count it would take.
    """
    steps = steps_per_frame * (1 if frames is None else frames)
    if not steps <= options.max_steps:
        what = "one frame" if frames is None else f"the run ({frames} frames)"
        raise SceneError(
            f"{scene.source}: run.dt: {what} would need {steps:.3g} time steps, more than the limit of "
            f"{options.max_steps} (--max-steps); raise dt, the output_rate or the material numbers that make the "
            "critical step small, or shorten the run"
        )


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
        where = "--device" if options.device else f"{scene.source}: run.device"
        raise SceneError(f"{where}: device {device_name!r} is not available here ({exc})") from None
    builder = scene_builder(scene)
    if not options.quiet:
        for quality in builder.mesh_qualities:
            print(f"mesh: {quality.format()}")
    model, state = finalize_scene(scene, builder, device)

    fps = run.output_rate
    frame_period = 1.0 / fps
    if not (math.isfinite(model.dt) and model.dt > 0.0):
        raise SceneError(
            f"{scene.source}: run.dt: the time step is {model.dt!r} s; the critical step of this scene is not a "
            "positive number (coincident spheres, or material numbers out of proportion)"
        )
    _check_steps(scene, frame_period / model.dt, options, None)
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
    _check_steps(scene, float(substeps), options, frames_left)

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
    try:
        vtu = VtuSeries(out_dir, output_stem, first_frame) if scene.output.vtu and model.node_capacity else None
    except OSError as exc:
        raise _output_error(f"{scene.source}: output.vtu", out_dir, exc) from None
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
    progress = None
    if not options.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        progress = tqdm(
            total=round(frames_left * frame_period, 9), unit="s", unit_scale=False, desc=scene.name, file=sys.stderr
        )
    wall0 = time.perf_counter()
    steps0 = sim.step_count
    comment = f"warpdem {__version__}: {scene.name}"

    def checkpoint(frame: int) -> None:
        path = checkpoint_dir / checkpoint_name(sim.step_count)
        try:
            checkpoints.append(save_checkpoint(path, sim, frame, ckpt_extra))
        except OSError as exc:
            raise _output_error(f"{scene.source}: output.checkpoint_dir", path, exc) from None

    try:
        writer = UsdWriter(usd_path, 1.0 / frame_period, comment=comment, first_frame=first_frame)
    except (OSError, RuntimeError) as exc:  # pxr reports a layer it cannot create as a RuntimeError
        if options.usd is not None or options.out_dir is not None:
            where = "--usd" if options.usd is not None else "--out"
        else:
            where = f"{scene.source}: output.directory / output.usd"
        raise _output_error(where, usd_path, exc) from None
    with writer:
        write_frame(writer, first_frame)
        for k in range(frames_left):
            sim.advance(substeps)
            frame = first_frame + k + 1
            write_frame(writer, frame)
            if progress is not None:
                progress.update(round(frame_period, 9))
            if frames_per_checkpoint and frame % frames_per_checkpoint == 0 and k < frames_left - 1:
                checkpoint(frame)
        wall = time.perf_counter() - wall0
        checkpoint(first_frame + frames_left)
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
    )


def summary_json(summary: RunSummary) -> str:
    """The summary as JSON (for scripts)."""
    d = dataclasses.asdict(summary)
    d["usd_path"] = str(summary.usd_path) if summary.usd_path else None
    d["checkpoints"] = [str(p) for p in summary.checkpoints]
    d["pvd_path"] = str(summary.pvd_path) if summary.pvd_path else None
    return json.dumps(d, indent=1)
