"""What a checkpoint holds of a run, and how a run resumes from one (the HDF5 file layer is warpdem.io.checkpoint).

:func:`save_checkpoint` writes the State's arrays, the Model's arrays a run may change (:func:`model_checkpoint_arrays`)
and its scalars (:func:`model_scalars`: capacities as grown by the run); :func:`restore_checkpoint` reads them back onto
a model built from the same scene, refusing a file of another scene. A file of an older format lacks the fields
added since: :data:`FIELD_MIGRATIONS` says, per field, from which format on it is written and how an older file's
value is filled exactly, or why it cannot be (then the restart is refused, naming the file and the field). Before any
array reaches the device, warpdem.io.restart_check checks that the kernels can trust the file: every array as long as
its capacities say, every count within its capacity, every index within the count it indexes, the run's attributes in
range.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from .._version import __version__
from ..limits import MAX_ELEMENTS
from ..model import RIGID_BODY_FIELDS, RIGID_NODE_FIELDS, Model, State
from ..simulation import Simulation
from ..stages.loads import pressure_node_forces
from .checkpoint import CheckpointError, read_checkpoint_version, write_checkpoint
from .restart_check import check_restart


def model_checkpoint_arrays(model: Model) -> list[str]:
    """Names of the Model arrays a checkpoint holds: every one but the tables of structs, which the scene's materials
    give. Sphere, mesh (after the joint pre-split), joint, surface and wall arrays all come from the checkpoint, so a
    restart never depends on re-meshing or on rebuilding what a run grew."""
    return [name for name, a in model.arrays().items() if not wp.types.type_is_struct(a.dtype)]


def model_scalars(model: Model) -> dict[str, int | float]:
    """The int and float fields of a model: capacities (particles, neighbour slots, nodes, tets, faces, FEM contact
    slots per sphere and per node, joints, bonds), the time step and the lengths its surface build measured. A
    checkpoint holds them all, grown as they were when it was taken."""
    return {
        f.name: value
        for f in dataclasses.fields(model)
        if type(value := getattr(model, f.name)) in (int, float)  # not bool: flags come from the scene
    }


MODEL_TEXTS = ("critical_dt_source", "contact_reach_source")
"""The text fields of a model that a run may change (the rigid switch sets the step's source): a checkpoint holds
them, so a restart's summary and the guard's messages say what the uninterrupted run's do. One without them (an older
format) keeps the built model's."""


def model_texts(model: Model) -> dict[str, str]:
    """The :data:`MODEL_TEXTS` of a model."""
    return {name: getattr(model, name) for name in MODEL_TEXTS}


def load_checkpoint_arrays(model: Model) -> dict[str, wp.array]:
    """The arrays of the model's LoadModel that a run changes, by checkpoint name: the node drivers (per node, grown
    with the node capacity by a split pass) and the node triples of the loaded and dashpot faces (remapped onto the
    daughters of split nodes), and the area vectors of the pressure faces handed over to converted tets' spheres
    (kernels/loads.py, Hand-over; format 11: the forces kept and their work are State fields). The rest of the loads
    comes from the scene. An older checkpoint lacks the area vectors: its faces keep the fresh zeros, exactly that
    run's state (it handed nothing over: its dropped faces stay dropped)."""
    loads = model.loads
    if loads is None:
        return {}
    out = {f"pressure_{kind}_nodes": faces.nodes for kind, faces in loads.pressure.items()}
    for kind, faces in loads.pressure.items():
        if faces.handed_area is not None:
            out[f"pressure_{kind}_handed_area"] = faces.handed_area
    if loads.dashpots is not None:
        out["dashpots_nodes"] = loads.dashpots.nodes
    if isinstance(loads.node_driver, wp.array):
        out["node_driver"] = loads.node_driver
    return out


def _restore_loads(model: Model, arrays: dict[str, np.ndarray]) -> Model:
    """The model with its load arrays (:func:`load_checkpoint_arrays`) taken from a checkpoint where it holds them."""
    held = load_checkpoint_arrays(model)
    for name, a in held.items():
        key = f"loads/{name}"
        if key not in arrays:
            continue
        if name == "node_driver":
            driver = wp.array(arrays[key], dtype=a.dtype, device=model.device)
            model = dataclasses.replace(model, loads=dataclasses.replace(model.loads, node_driver=driver))
        elif arrays[key].shape == a.numpy().shape:
            a.assign(arrays[key])
    return model


SCENE_FIXED_SCALARS = ("bond_capacity", "num_walls", "num_materials")
"""Model scalars that no run changes: a checkpoint whose values differ was taken of another scene."""


def save_checkpoint(path: Path, sim: Simulation, frame: int, extra: dict) -> Path:
    """Write the complete state of a simulation, its model's arrays (:func:`model_checkpoint_arrays`) and scalars
    (:func:`model_scalars`) to an HDF5 checkpoint."""
    arrays = {f"state/{name}": a.numpy() for name, a in sim.state.arrays().items()}
    for name in model_checkpoint_arrays(sim.model):
        arrays[f"model/{name}"] = getattr(sim.model, name).numpy()
    for name, a in load_checkpoint_arrays(sim.model).items():
        arrays[f"loads/{name}"] = a.numpy()
    attrs = {
        **model_scalars(sim.model),
        **model_texts(sim.model),
        "step": sim.step_count,
        "time": sim.time,
        "frame": frame,
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


def _total(arrays: dict[str, np.ndarray], name: str) -> int:
    """A counter of the checkpoint's state (shape (1,)); 0 where it does not hold it."""
    held = arrays.get(f"state/{name}")
    return int(held.reshape(-1)[0]) if held is not None and held.size else 0


def _no_pass(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where no split or conversion pass changed anything (what such passes book and hold is then zero)."""
    if _total(arrays, "node_splits_total") or _total(arrays, "tets_converted_total"):
        return "split or conversion passes had run, and what they booked is not in it"
    return None


def _no_band_needed(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where the restarted model has no overlap band (the older run had none either), or no tet had converted
    (the band's α is then 1 on every tet, its volumes the tets')."""
    if model.band_width and _total(arrays, "tets_converted_total"):
        return (
            "the older run tied its converted spheres without an overlap band; restart it with [conversion] "
            "coupling = 'tie'"
        )
    return None


def _no_bodies(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where the blocks have not turned rigid (the rigid fields are then empty, their lines zero)."""
    bodies = arrays.get("state/body_mass")
    if (bodies is not None and len(bodies)) or _total(arrays, "rigid_switched"):
        return "its blocks had turned rigid, and their state is not all in it"
    return None


def _no_node_contact(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where no node's contact spring held a face (``node_face_spring`` all -1), there are no walls, and after
    step 0 no joint element is intact (their dashpot forces join ``node_f_contact``): the nodes' contact forces and
    spring energies at the last evaluation were then zero."""
    spring = arrays.get("state/node_face_spring")
    if spring is None or np.any(spring >= 0):
        return "nodes were touching faces, and their contact forces at the last step are not in it"
    if int(attrs.get("num_walls", 0)):
        return "the scene has walls, and whether nodes touched them at the last step is not in it"
    broken = arrays.get("state/joint_broken")
    if int(attrs.get("step", 0)) > 0 and broken is not None and np.any(broken[: _total(arrays, "joint_count")] == 0):
        return "intact joint elements' dashpots acted, and their forces at the last step are not in it"
    return None


def _no_dashpot_force(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where the model has no non-reflecting boundary, or at step 0: the dashpots' forces at the last evaluation
    were then zero (the set-up evaluation leaves them out)."""
    if model.loads is not None and model.loads.dashpots is not None and int(attrs.get("step", 0)) > 0:
        return "non-reflecting dashpots acted, and their forces at the last step are not in it"
    return None


def _no_sphere_face(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where no sphere had a candidate face (so none touched one) or there are no spheres."""
    candidates = arrays.get("state/sphere_face_count")
    if _total(arrays, "particle_count") and (candidates is None or np.any(candidates > 0)):
        return "spheres were near faces, and their contact energies at the last step are not in it"
    return None


def _no_sphere_face_books(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where no sphere could have touched a face: no spheres, or no boundary faces (empty sphere–face rows).
    An older run booked the sphere–face contacts' dissipation on the damping, friction and FEM contact lines, and kept
    the half ahead of their forces in the sphere contacts' and the node contacts' sums."""
    rows = arrays.get("state/sphere_face_count")
    if _total(arrays, "particle_count") and (rows is None or len(rows)):
        return "spheres and faces were in it, and it booked their contacts on the damping, friction and contact lines"
    return None


def _no_cohesive(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where no cohesive element was ever born (none alive, none broken and removed)."""
    if _total(arrays, "cohesive_count") or _total(arrays, "cohesive_broken_total"):
        return "cohesive elements had been born, and their forces at the last evaluation are not in it"
    return None


def _no_viscous_force(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where no material has bulk viscosity or mass damping (c_lin, c_quad, alpha all 0), or at step 0: the
    viscous forces at the last evaluation were then zero."""
    table = model.tet_material_table.numpy() if model.tet_material_table is not None else None
    damped = table is not None and any(np.any(table[name] != 0.0) for name in ("c_lin", "c_quad", "alpha"))
    if damped and int(attrs.get("step", 0)) > 0:
        return "bulk viscosity or mass damping acted, and their forces at the last step are not in it"
    return None


def _no_step_change(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """Exact where the time step never changed (the frame grid never moved: ``grid_step`` 0) and no pass ran (a split
    pass books its change of the shadow term as a step change too)."""
    if int(attrs.get("grid_step", 0)):
        return "the time step had changed, and the shadow term it booked is not in it"
    return _no_pass(arrays, attrs, model)


def _pressure_forces(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> np.ndarray:
    """The pressure loads' forces per node at the checkpoint's time and positions: what the evaluation before it kept
    in ``node_f_load`` (the same faces, time, displacements and order: bit for bit on the CPU)."""
    return pressure_node_forces(model, float(arrays["state/time"][0]), arrays["state/node_u"], arrays["state/node_q"])


def _drift_scratch(width: int) -> Callable[[dict[str, np.ndarray], dict, Model], np.ndarray]:
    """Zeros of ``width`` components per body of the checkpoint: a body scratch array the next drift writes before
    anything reads it (warpdem.model.State ``body_q_before``, ``body_omega_ahead``)."""

    def make(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> np.ndarray:
        return np.zeros((len(arrays.get("state/body_mass", ())), width))

    return make


def _always(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> str | None:
    """A scene setting no run changes: the scene's value is the run's."""
    return None


@dataclass(frozen=True)
class FieldMigration:
    """How a restart fills a field that a checkpoint of an older format lacks (:func:`restore_checkpoint`).

    Attributes:
        since: the first format version whose files hold it (warpdem.io.checkpoint.FORMAT_VERSION); a file of that
            version or newer that lacks it is refused as incomplete.
        exact: (arrays, attrs, fresh model) -> None where the fresh model's or state's value (a constant per item,
            sized as the checkpoint's other arrays of its kind, ``like``) is exactly what the run would hold, else
            why not (one clause).
        like: the checkpoint key whose length the filled array takes (None: the fresh value's own length).
        make: (arrays, attrs, fresh model) -> the value made from the checkpoint's own arrays, where ``exact``
            allows it (None: the fresh value).
    """

    since: int
    exact: Callable[[dict[str, np.ndarray], dict, Model], str | None]
    like: str | None = None
    make: Callable[[dict[str, np.ndarray], dict, Model], np.ndarray] | None = None


def _contact_sums(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> np.ndarray:
    """The one record per sphere of an older checkpoint's three contact force sums (format 13: warpdem.model.State
    ``contact_sums``), its rows the normal force, tangential force and torque sums, the same values."""
    rows = [arrays[f"state/{name}"] for name in ("contact_f_normal", "contact_f_tangential", "contact_t_tangential")]
    return np.stack(rows, axis=1)


_RIGID_FIELDS = ("rigid_nodes", *RIGID_BODY_FIELDS, *RIGID_NODE_FIELDS)
FIELD_MIGRATIONS: dict[str, FieldMigration] = {
    # Bulk viscosity and mass damping book Verlet's trapezoid (cea7fdb).
    "state/node_f_viscous": FieldMigration(2, _no_viscous_force, "state/node_u"),
    # Non-reflecting dashpots and joint dashpots book Verlet's trapezoid (lead4: node_f_absorbed, node_f_contact).
    "state/node_f_absorbed": FieldMigration(2, _no_dashpot_force, "state/node_u"),
    # FEM node and sphere–face contacts book Verlet's trapezoid (1e8395f, d830a52); held stiffness (6e2930a).
    "state/node_f_contact": FieldMigration(2, _no_node_contact, "state/node_u"),
    "state/node_contact_energy_prev": FieldMigration(2, _no_node_contact, "state/node_u"),
    "state/node_contact_hold": FieldMigration(2, _no_pass, "state/node_u"),
    "state/sphere_face_energy_prev": FieldMigration(2, _no_sphere_face, "state/sphere_face_count"),
    # Cohesive elements book Verlet's trapezoid (bd9f694).
    "state/cohesive_f_prev": FieldMigration(2, _no_cohesive, "state/cohesive_a"),
    "state/cohesive_energy_prev": FieldMigration(2, _no_cohesive, "state/cohesive_a"),
    # Energy lines of split and conversion passes and of changes of the step (f56645e, 5aa6f7b, 7241212).
    "state/energy_contact_topology": FieldMigration(2, _no_pass),
    "state/energy_step_change": FieldMigration(2, _no_step_change),
    # Rigid blocks (498b672, 5aa6f7b): empty before a switch.
    "state/rigid_switched": FieldMigration(2, _no_bodies),
    "state/energy_released_rigid": FieldMigration(2, _no_bodies),
    **{f"state/{name}": FieldMigration(2, _no_bodies) for name in _RIGID_FIELDS},
    "model/tet_may_rigid": FieldMigration(2, _always, "model/tet_nodes"),
    # Pressure loads book the half ahead of their work from the forces kept per node, and rigid nodes book it at the
    # pose the forces were made at (format 3): the forces are made again from the checkpoint's state where no pass
    # changed the loaded faces; the drift's scratch is rewritten before it is read.
    "state/node_f_load": FieldMigration(3, _no_pass, "state/node_u", _pressure_forces),
    "state/body_q_before": FieldMigration(3, _always, "state/body_mass", _drift_scratch(4)),
    "state/body_omega_ahead": FieldMigration(3, _always, "state/body_mass", _drift_scratch(3)),
    # Conversion's edge degree (19e0e61): as attached until a pass converts or splits.
    "model/tet_edge_degree": FieldMigration(2, _no_pass, "model/tet_nodes"),
    # Model scalars (attributes): scene settings, and the deformable step kept by a change of step.
    "attribute contact_face_normal_stiffness": FieldMigration(2, _always),
    "attribute rigid_switch_time": FieldMigration(2, _always),
    "attribute rigid_energy_fraction": FieldMigration(2, _always),
    "attribute rigid_check_interval": FieldMigration(2, _always),
    "attribute deformable_critical_dt": FieldMigration(2, _no_step_change),
    # A node–face spring per face plane (format 4): older files held one per node, which is slot 0 of the rows
    # (FIELD_RESHAPES), the other slots empty.
    "attribute node_springs": FieldMigration(4, _always),
    # The kicks sum the velocities with a carry (format 5): an older run's velocity was its float32 value, carry 0.
    "state/particle_qd_carry": FieldMigration(5, _always, "state/particle_qd"),
    "state/node_qd_carry": FieldMigration(5, _always, "state/node_qd"),
    # Coupling springs are born relaxed with a rest gap (format 6): an older run's springs had none (zero).
    "state/coupling_rest": FieldMigration(6, _always, "state/coupling_particle"),
    # The sphere–face contacts' dissipation on a line of its own (format 7), their forces' half ahead kept apart.
    **{
        f"state/{name}": FieldMigration(7, _no_sphere_face_books, "state/sphere_face_count")
        for name in ("sphere_face_f", "sphere_face_t", "sphere_face_dissipated")
    },
    **{
        f"state/{name}": FieldMigration(7, _no_sphere_face_books, "state/node_u")
        for name in ("node_f_sphere_face", "node_energy_sphere_face")
    },
    # The bonds' springs' -W - ΔU on a line of its own (format 8): an older run booked it on the damping and friction
    # lines, which keep it; the books close with the new line from zero.
    "state/energy_bond_trapezoid": FieldMigration(8, _always, "state/energy_damping"),
    # The cohesive elements' work off their law on a line of its own (format 9): an older run booked it on the
    # cohesive line, which keeps it; the books close with the new line from zero.
    "state/node_energy_cohesive_trapezoid": FieldMigration(9, _always, "state/node_energy_cohesive"),
    # The blended overlap band (format 10): an older run tied its spheres (band_width 0); a band model takes it where
    # nothing had converted yet.
    "attribute band_width": FieldMigration(10, _no_band_needed),
    "attribute band_penalty": FieldMigration(10, _always),
    "model/tet_band_volume": FieldMigration(10, _no_band_needed, "model/tet_volume"),
    # The pressure loads' hand-over to converted tets' spheres (format 11): an older run handed nothing over (its
    # dropped faces pushed nothing), so its kept forces and their work are zero.
    "state/load_face_force": FieldMigration(11, _always),
    "state/load_face_work": FieldMigration(11, _always),
    # The impulse each pressure face delivered (format 12): a report's counter, not a part of the books or of the
    # motion; an older run's restart counts it from the restart.
    "state/load_face_impulse": FieldMigration(12, _always),
    # The sphere contacts' three force sums as one record per sphere (format 13): an older file held them as three
    # arrays, the record's rows.
    "state/contact_sums": FieldMigration(13, _always, "state/particle_qd", _contact_sums),
    # The cohesive elements' daughters sub-stepped (format 14): an older run took one step for every force, so its
    # cohesive forces were part of node_f, none kept apart, and no sub-step work was booked.
    "attribute cohesive_substeps": FieldMigration(14, _always),
    "state/node_f_fast": FieldMigration(14, _always, "state/node_f"),
    "state/node_substepped": FieldMigration(14, _always, "state/node_damage"),
    "state/node_energy_substep": FieldMigration(14, _always, "state/node_energy_cohesive"),
}
"""The fields added since checkpoint format 1, by checkpoint key (``state/<name>``, ``model/<name>``, ``attribute
<name>`` for a model scalar), and when a restart may fill them from the fresh model and state
(warpdem.io.checkpoint, "Versions")."""


def _spring_rows(name: str, empty: float) -> Callable[[dict[str, np.ndarray], dict, Model], np.ndarray]:
    """The node_springs rows per node of a per-node spring field of an older checkpoint: its one spring into slot 0,
    the other slots ``empty`` (no face, no offset, no shear): exactly the state a run with these rows holds after the
    same steps, since the one spring was then a node's only one (warpdem.model.State ``node_face_spring``)."""

    def make(arrays: dict[str, np.ndarray], attrs: dict, model: Model) -> np.ndarray:
        old = arrays[f"state/{name}"]
        if len(old) != int(attrs.get("node_capacity", len(old))):
            return old  # rows already (a file whose version was set back by hand, as the tests make old files)
        rows = np.full((len(old), model.node_springs, *old.shape[1:]), empty, dtype=old.dtype)
        rows[:, 0] = old
        return rows.reshape(len(old) * model.node_springs, *old.shape[1:])

    return make


FIELD_RESHAPES: dict[str, FieldMigration] = {
    f"state/{name}": FieldMigration(4, _always, make=_spring_rows(name, empty))
    for name, empty in (("node_face_spring", -1), ("node_face_offset", 0.0), ("node_face_shear", 0.0))
}
"""Fields an older checkpoint holds in another shape, by checkpoint key: a file of a format before ``since`` has its
value made anew (``make``) before the restart reads it."""


def _migrate(
    path: Path,
    version: int,
    arrays: dict[str, np.ndarray],
    attrs: dict,
    missing: list[str],
    fresh: Callable[[str], object],
    model: Model,
) -> list[str]:
    """Fills, in ``arrays`` and ``attrs``, the fields of :data:`FIELD_MIGRATIONS` that a checkpoint of format
    ``version`` lacks, with the fresh value (``fresh``: key -> the fresh model's or state's value) where that is exact.

    Returns:
        The keys still missing: not in the table, or lacking in a file whose version should hold them.

    Raises:
        CheckpointError: one line naming the file, the field and why the fresh value would not be the run's.
    """
    left = []
    for key in missing:
        rule = FIELD_MIGRATIONS.get(key)
        if rule is None or version >= rule.since:
            left.append(key)
            continue
        why = rule.exact(arrays, attrs, model)
        value = rule.make(arrays, attrs, model) if rule.make is not None and why is None else fresh(key)
        if why is None and key.startswith("attribute "):
            attrs[key.removeprefix("attribute ")] = value
            continue
        if why is None:
            size = len(arrays[rule.like]) if rule.like is not None and rule.like in arrays else len(value)
            if size != len(value):
                # A grown capacity: the fresh value is one constant per item (an empty slot) or it cannot be resized.
                flat = value.reshape(len(value), -1)
                if len(value) == 0 or np.any(flat != flat[:1]):
                    why = f"its fresh value is not one constant to resize to the checkpoint's {size} items"
                else:
                    value = np.repeat(value[:1], size, axis=0)
        if why is not None:
            name = key.removeprefix("attribute ")
            raise CheckpointError(
                f"{path}: {name} is missing (format version {version}, before {rule.since}) and cannot be filled "
                f"exactly: {why}; restart from an earlier checkpoint of this run, or run it again with this warpdem"
            )
        arrays[key] = value
    return left


def restore_checkpoint(
    path: Path, model: Model, template: State, scene: str | None = None
) -> tuple[Model, State, dict]:
    """Model and state of a checkpoint, on the device of ``model`` (built from the same scene; ``template`` is its
    initial state and gives each array's type). Every model array but the struct tables and every model scalar
    (:func:`model_scalars`: capacities as grown by the run) come from the checkpoint. A checkpoint of an older format
    that lacks fields added since has them filled from the fresh model and state where that is exact
    (:data:`FIELD_MIGRATIONS`), so a run can always be resumed from its last checkpoint, or is refused saying why.

    Raises:
        CheckpointError: unreadable file, one that belongs to another scene (``scene``: this scene's name), one
            that lacks a field that cannot be filled exactly, or one a kernel could not safely read: a length, count,
            index or attribute out of range (warpdem.io.restart_check.check_restart). One line: the file, the field,
            what was found or why.
    """
    arrays, attrs, version = read_checkpoint_version(path)
    if scene is not None and "scene" in attrs and attrs["scene"] != scene:
        raise CheckpointError(f"checkpoint {path} belongs to scene {attrs['scene']!r}, not {scene!r}")
    for key in SCENE_FIXED_SCALARS:
        if key == "bond_capacity" and model.tet_may_convert is not None:
            continue  # conversion appends bonds: the capacity grows with the run
        expected = getattr(model, key)
        if key in attrs and attrs[key] != expected:
            raise CheckpointError(f"{path}: {key} is {attrs[key]} but the scene builds {expected}; wrong scene?")
    for key, rule in FIELD_RESHAPES.items():
        if version < rule.since and key in arrays and rule.make is not None:
            arrays[key] = rule.make(arrays, attrs, model)
    scalars = model_scalars(model)
    missing = [
        k
        for k in [f"model/{n}" for n in model_checkpoint_arrays(model)] + [f"state/{n}" for n in template.arrays()]
        if k not in arrays
    ] + [f"attribute {n}" for n in scalars if n not in attrs]

    def fresh(key: str) -> object:
        """The fresh model's or state's value of a checkpoint key."""
        kind, name = key.split("/", 1) if "/" in key else ("attribute", key.removeprefix("attribute "))
        if kind == "attribute":
            return scalars[name]
        return (getattr(model, name) if kind == "model" else getattr(template, name)).numpy()

    missing = _migrate(path, version, arrays, attrs, missing, fresh, model)
    _check_attrs(path, attrs, [name for name, value in scalars.items() if isinstance(value, int)])
    if missing:
        raise CheckpointError(f"{path}: missing {', '.join(missing)} (written by an older warpdem?)")
    check_restart(path, arrays, attrs, model, template)
    device = model.device

    def load(key: str, like: wp.array) -> wp.array:
        data = arrays[key]
        if data.dtype.kind in "fc" and not np.all(np.isfinite(data)):
            bad = int(np.count_nonzero(~np.isfinite(data)))
            raise CheckpointError(f"{path}: {key} holds {bad} non-finite value(s); the run it saved had already failed")
        try:
            return wp.array(data, dtype=like.dtype, device=device)
        except (ValueError, TypeError, RuntimeError) as exc:
            detail = " ".join(str(exc).split())
            raise CheckpointError(
                f"{path}: {key}: {data.dtype} {data.shape} is not a {like.dtype.__name__} array ({detail})"
            ) from None

    model = dataclasses.replace(
        model,
        **{name: type(value)(attrs[name]) for name, value in scalars.items()},
        **{name: attrs[name] for name in MODEL_TEXTS if isinstance(attrs.get(name), str)},
        **{name: load(f"model/{name}", getattr(model, name)) for name in model_checkpoint_arrays(model)},
    )
    state = State(**{name: load(f"state/{name}", a) for name, a in template.arrays().items()})
    return _restore_loads(model, arrays), state, attrs
