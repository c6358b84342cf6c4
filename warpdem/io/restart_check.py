"""What a restart file must hold before any kernel touches it (warpdem.io.restart.restore_checkpoint).

The kernels launch over capacities and trust the counts and indices they are given: an index past the end of the
array it points into reads or writes outside it (a segmentation fault, or silent corruption on a GPU), a count past
its capacity launches threads past every array. A checkpoint is therefore checked, on the host with numpy, once per
restart, against tables derived from the Model and State (warpdem.model):

- :data:`SIZES`: every array's length, as a product of the checkpoint's capacity attributes (``node_capacity``,
  ``particle_capacity × max_neighbors``, ...), and its item shape, that of the fresh model's or state's array;
- :data:`COUNTS`: every live count (a counter of shape (1,) in the state) against the capacity it fills;
- :data:`INDEXES`, :data:`SLOT_LISTS`, :data:`RANGES`: every index array, over its live items, against the count of
  what it indexes (a node index below ``node_count``, a bond index below ``bond_count``), with -1 allowed where the
  field says "-1 for none".

The run's attributes (:data:`RUN_ATTRS`: the frame grid, the frame period, the step still to take, the colour scales)
are checked to be of their type and in range, and the grid to hold the checkpoint's own step: a grid anchored far from
it would run that many steps past the ``--max-steps`` check, which counts frames. Anything else is one line naming the
file, the field and what was found (:class:`warpdem.io.checkpoint.CheckpointError`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..model import (
    BOND_FIELDS,
    COHESIVE_FIELDS,
    COUPLING_FIELDS,
    NEIGHBOR_FIELDS,
    RIGID_BODY_FIELDS,
    RIGID_NODE_FIELDS,
    Model,
    State,
)
from ..stages.energy import EnergyBalance
from ..stages.rigid import RigidReport
from .checkpoint import CheckpointError

# ----------------------------------------------------------------------------------------------------------------
# Sizes


@dataclass(frozen=True)
class Size:
    """The length of an array: ``scale`` × the product of the checkpoint attributes ``factors``.

    Attributes:
        factors: capacity attributes (``node_capacity``, ``max_neighbors``, ...).
        scale: a constant factor (4 tet-face slots per tet).
        floor: the least length (a placeholder slot where the product is 0).
        or_empty: the array may also be empty (sphere–face rows without boundary faces, rigid node fields before the
            switch).
    """

    factors: tuple[str, ...]
    scale: int = 1
    floor: int = 0
    or_empty: bool = False

    def length(self, attrs: dict) -> int:
        """The length the checkpoint's attributes give."""
        return max(self.scale * math.prod(int(attrs[name]) for name in self.factors), self.floor)

    def says(self, attrs: dict) -> str:
        """The expression and its value, in words (``particle_capacity × max_neighbors = 1024 × 8``)."""
        scale = [str(self.scale)] if self.scale != 1 else []
        names = " × ".join(scale + list(self.factors)) or "1"
        values = " × ".join(scale + [str(attrs[n]) for n in self.factors]) or "1"
        return (
            f"{names} = {values}"
            + (f", at least {self.floor}" if self.floor else "")
            + (", or 0" if self.or_empty else "")
        )


def _each(names: str, size: Size) -> dict[str, Size]:
    """``size`` for each of the space-separated field names."""
    return dict.fromkeys(names.split(), size)


_P, _N, _T = Size(("particle_capacity",)), Size(("node_capacity",)), Size(("tet_capacity",))
_ONE = Size((), floor=1)

_MODEL_SIZES: dict[str, Size] = {
    **_each("particle_radius particle_mass particle_inv_mass particle_inv_inertia particle_material", _P),
    **_each("particle_motion particle_part particle_id", _P),
    **_each("wall_normal wall_velocity wall_material", Size(("num_walls",))),
    **_each("node_ref_q node_mass node_inv_mass node_motion node_damping node_may_split", _N),
    **_each("node_contact_stiffness node_contact_material", _N),
    # The star CSR heads and the face adjacencies (warpdem.stages.topology.NodeStars) keep one placeholder slot in a
    # model without nodes or tets.
    **_each("star_offset star_count", Size(("node_capacity",), floor=1)),
    **_each("star_tets tet_face_nbr", Size(("tet_capacity",), scale=4, floor=1)),
    **_each("ref_tet_face_nbr", Size(("tet_capacity",), scale=4, floor=1)),
    **_each("tet_face_joint", Size(("tet_capacity",), scale=4)),
    **_each("tet_nodes tet_inv_ref tet_volume tet_length tet_material", _T),
    **_each("tet_may_convert tet_edge_degree tet_may_rigid tet_band_volume", _T),
    **_each("face_nodes face_tet face_joint face_depth", Size(("face_capacity",))),
    **_each("joint_a joint_b joint_area joint_kn joint_tet_face joint_set", Size(("joint_capacity",))),
}

_COUNTERS = (
    "particle_count rebuild_flag rebuild_total nbr_needed bond_count bonds_broken_total node_count tet_count time "
    "face_count fem_rebuild_flag fem_rebuild_total fem_sphere_builds_seen sphere_face_needed node_face_needed "
    "joint_count joints_broken_total cohesive_count cohesive_broken_total cohesive_area_broken cohesive_work_broken "
    "node_splits_total crack_area_total energy_contact_topology tets_converted_total spheres_spawned_total "
    "energy_released_conversion coupling_count rigid_switched energy_released_rigid energy_step_change"
)
_STATE_SIZES: dict[str, Size] = {
    **_each("particle_q particle_qd particle_qd_carry particle_omega particle_f particle_t particle_q_at_build", _P),
    **_each("nbr_count particle_bonds_broken contact_sums", _P),
    **_each("energy_damping energy_friction energy_boundary_work energy_bond_broken energy_stiffness_change", _P),
    **_each("contact_energy_prev energy_bond_trapezoid", _P),
    **_each(" ".join(NEIGHBOR_FIELDS), Size(("particle_capacity", "max_neighbors"))),
    **_each("wall_point", Size(("num_walls",))),
    **_each("wall_shear", Size(("particle_capacity", "num_walls"))),
    **_each(" ".join(BOND_FIELDS), Size(("bond_capacity",))),
    **_each("node_u node_q node_qd node_qd_carry node_f node_f_viscous node_f_absorbed node_f_load", _N),
    **_each("node_energy_damping node_energy_absorbed node_energy_boundary_work node_energy_contact", _N),
    **_each("node_q_at_fem_build node_face_count node_contact_hold node_f_contact node_contact_energy_prev", _N),
    **_each(
        "node_damage node_energy_cohesive node_energy_cohesive_trapezoid node_f_sphere_face node_energy_sphere_face", _N
    ),
    **_each("node_f_fast node_substepped node_energy_substep", _N),
    **_each("tet_active tet_stress tet_sphere", _T),
    # Sphere–face rows: empty in a model without boundary faces (warpdem.stages.fem_contact.sphere_face_rows).
    **_each(
        "sphere_face_count sphere_face_energy_prev sphere_face_f sphere_face_t sphere_face_dissipated",
        Size(("particle_capacity",), or_empty=True),
    ),
    **_each("sphere_face_index sphere_face_shear", Size(("particle_capacity", "max_sphere_faces"), or_empty=True)),
    **_each("node_face_index", Size(("node_capacity", "max_node_faces"))),
    **_each("node_face_spring node_face_offset node_face_shear", Size(("node_capacity", "node_springs"))),
    **_each("node_wall_shear", Size(("node_capacity", "num_walls"))),
    **_each("joint_broken", Size(("joint_capacity",))),
    **_each(" ".join(COHESIVE_FIELDS), Size(("cohesive_capacity",))),
    **_each(" ".join(COUPLING_FIELDS), Size(("coupling_capacity",))),
    # Rigid node fields: per node once the blocks turned rigid, empty before.
    **_each(" ".join(RIGID_NODE_FIELDS), Size(("node_capacity",), or_empty=True)),
    **_each(_COUNTERS, _ONE),
}

SIZES: dict[str, Size] = {
    **{f"model/{name}": size for name, size in _MODEL_SIZES.items()},
    **{f"state/{name}": size for name, size in _STATE_SIZES.items()},
    "loads/node_driver": _N,
}
"""The length of every checkpoint array that a capacity sizes, by key. The rigid bodies' fields (one item per body,
``body_mass`` the first) and ``rigid_nodes`` are sized by the switch instead (:func:`check_sizes`); the load face sets
by the scene's faces."""

SIZED_BY_BODIES = tuple(f"state/{name}" for name in RIGID_BODY_FIELDS)
"""State fields of one item per rigid body (as many as ``state/body_mass``)."""

LOADED_FACES = ("state/load_face_force", "state/load_face_work", "state/load_face_impulse")
"""State fields of one item per loaded face of the scene's pressure loads (:func:`check_sizes`)."""

UNSIZED = ("state/rigid_nodes", *LOADED_FACES)
"""Arrays no capacity sizes (the nodes of the bodies, the items per loaded face; the load face sets ``loads/*_nodes``
too)."""


# ----------------------------------------------------------------------------------------------------------------
# Counts and indices


COUNTS: dict[str, str] = {
    "particle_count": "particle_capacity",
    "node_count": "node_capacity",
    "tet_count": "tet_capacity",
    "face_count": "face_capacity",
    "bond_count": "bond_capacity",
    "joint_count": "joint_capacity",
    "cohesive_count": "cohesive_capacity",
    "coupling_count": "coupling_capacity",
}
"""Each live count of the state (``state/<name>``, shape (1,)) and the capacity attribute it may not exceed."""


@dataclass(frozen=True)
class Index:
    """An index array: its live items (the first ``live`` × ``per_item`` entries, all where ``live`` is None) each
    point below ``bound``, or are -1 where ``none`` (no partner).

    Attributes:
        key: the checkpoint array.
        live: the count (a name of :data:`COUNTS`) whose items are live.
        bound: what it indexes: a name of :func:`_limits`.
        none: -1 is allowed (no item).
        per_item: entries per live item of a flattened array (4 tet-face slots per tet, node_springs per node).
    """

    key: str
    live: str | None
    bound: str
    none: bool = False
    per_item: str | int = 1


INDEXES: tuple[Index, ...] = (
    # Model: materials, parts, mesh and surface topology, joint elements.
    Index("model/particle_material", "particle_count", "num_materials"),
    Index("model/particle_part", "particle_count", "parts"),
    Index("model/wall_material", None, "num_materials"),
    Index("model/tet_nodes", "tet_count", "node_count"),
    Index("model/tet_material", "tet_count", "num_materials"),
    Index("model/tet_face_joint", "tet_count", "joint sets", none=True, per_item=4),
    Index("model/tet_face_nbr", "tet_count", "tet_count", none=True, per_item=4),
    Index("model/ref_tet_face_nbr", "tet_count", "tet_count", none=True, per_item=4),
    Index("model/face_nodes", "face_count", "node_count"),
    Index("model/face_tet", "face_count", "tet_count"),
    Index("model/face_joint", "face_count", "joint sets", none=True),
    Index("model/node_contact_material", "node_count", "num_materials"),
    Index("model/joint_a", "joint_count", "node_count"),
    Index("model/joint_b", "joint_count", "node_count"),
    Index("model/joint_tet_face", "joint_count", "tet-face slots"),
    Index("model/joint_set", "joint_count", "joint sets"),
    # State: bonds, FEM contact springs, cohesive elements, couplings, converted tets, rigid bodies.
    Index("state/bond_i", "bond_count", "particle_count"),
    Index("state/bond_j", "bond_count", "particle_count"),
    Index("state/node_face_spring", "node_count", "face_count", none=True, per_item="node_springs"),
    Index("state/cohesive_a", "cohesive_count", "node_count"),
    Index("state/cohesive_b", "cohesive_count", "node_count"),
    Index("state/cohesive_tet_face", "cohesive_count", "tet-face slots", none=True),
    Index("state/coupling_particle", "coupling_count", "particle_count"),
    Index("state/coupling_tet", "coupling_count", "tet_count"),
    Index("state/tet_sphere", "tet_count", "particle_count", none=True),
    Index("state/node_body", "node_count", "bodies", none=True),
    Index("state/rigid_nodes", None, "node_count"),
    # Loads: the node drivers and (pattern, every face) the loaded and dashpot faces' nodes.
    Index("loads/node_driver", "node_count", "drivers", none=True),
)
"""Every index array of the Model, State and loads with what it indexes (warpdem.model's field docs). The load face
sets (``loads/pressure_<kind>_nodes``, ``loads/dashpots_nodes``) are checked as ``Index(key, None, "node_count")``."""


@dataclass(frozen=True)
class SlotList:
    """Rows of ``per_row`` slots per live item, the first ``count[i]`` (at most ``per_row``) in use; each used slot
    points below ``bound`` (or is -1 where ``none``)."""

    key: str
    count: str
    per_row: str
    live: str
    bound: str
    none: bool = False


SLOT_LISTS: tuple[SlotList, ...] = (
    SlotList("state/nbr_index", "state/nbr_count", "max_neighbors", "particle_count", "particle_count"),
    SlotList("state/nbr_bond", "state/nbr_count", "max_neighbors", "particle_count", "bond_count", none=True),
    SlotList("state/sphere_face_index", "state/sphere_face_count", "max_sphere_faces", "particle_count", "face_count"),
    SlotList("state/node_face_index", "state/node_face_count", "max_node_faces", "node_count", "listed faces"),
)
"""Candidate lists (kernels read ``min(count, per_row)`` slots of a row)."""


@dataclass(frozen=True)
class Ranges:
    """Ranges ``items[start[i] .. start[i] + count[i])`` of ``items``, one per live head; every item in a range points
    below ``bound``."""

    start: str
    count: str
    items: str
    live: str | None
    bound: str


RANGES: tuple[Ranges, ...] = (
    Ranges("model/star_offset", "model/star_count", "model/star_tets", "node_count", "tet_count"),
    Ranges("state/body_node_start", "state/body_node_count", "state/rigid_nodes", None, "node_count"),
)
"""Compressed adjacency lists: the node → tet star and the nodes of each rigid body."""


# ----------------------------------------------------------------------------------------------------------------
# Run attributes


@dataclass(frozen=True)
class RunAttr:
    """A run attribute's type and range (checked where the file holds it: older files and API checkpoints lack them).

    Attributes:
        kind: int, float (an int is a float too) or bool.
        low: the smallest value allowed (None: any), ``strict``: it must exceed it.
        optional: None is allowed.
    """

    kind: type
    low: float | None = 0.0
    strict: bool = False
    optional: bool = False


RUN_ATTRS: dict[str, RunAttr] = {
    "substeps": RunAttr(int, 1),
    "grid_step": RunAttr(int),
    "grid_frame": RunAttr(int),
    "grid_time": RunAttr(float),
    "frame_period": RunAttr(float, strict=True),
    "frame_step": RunAttr(int),
    "frame_time": RunAttr(float),
    "pending_dt": RunAttr(float, strict=True, optional=True),
    "rigid_step_taken": RunAttr(bool, None),
    "seed": RunAttr(int, None),
    "speed_scale": RunAttr(float),
    "rock_color_scale": RunAttr(float),
    "energy_in_play": RunAttr(float),
    "frame_points_crc32": RunAttr(int, optional=True),
}
"""Attributes the runner writes (warpdem.runner.run.Run.checkpoint) and reads back at a restart: the frame grid
(warpdem.runner.timing.FrameGrid: ``substeps`` steps per frame, frame ``grid_frame`` ends at step ``grid_step``), the
frame period [s], the step still to take at the next frame boundary, the colour scales. Numbers are finite."""

RUN_RECORDS: dict[str, type] = {"energy_start": EnergyBalance, "rigid_report": RigidReport}
"""Attributes holding a record (a dict of its fields) that a restart rebuilds."""

SCENE_SETTINGS = ("node_springs", "spheres_per_tet", "conversion_part", "band_width")
"""Model scalars a run never changes and the kernels or passes rely on (node_springs: the kernels are compiled for it;
the spheres and part of a converted tet; the overlap band's layers, whose α the tets' volumes hold): the scene's."""

# ----------------------------------------------------------------------------------------------------------------
# The checks


def check_restart(path: Path, arrays: dict[str, np.ndarray], attrs: dict, model: Model, template: State) -> None:
    """Refuses a restart file that a kernel could not safely read: arrays whose lengths the capacity attributes do not
    give (:data:`SIZES`), counts past their capacities (:data:`COUNTS`), indices out of range of what they index
    (:data:`INDEXES`, :data:`SLOT_LISTS`, :data:`RANGES`), model scalars out of range, run attributes of the wrong type
    or out of range, a frame grid that does not hold the checkpoint's step (:data:`RUN_ATTRS`). ``arrays`` and
    ``attrs`` are the file's, migrated (every key the restart reads is there and ``attrs`` passed its basic check);
    ``model`` and ``template`` are the fresh model and state of the scene.

    Raises:
        CheckpointError: one line: the file, the field, what was found.
    """
    check_scalars(path, attrs, model)
    check_sizes(path, arrays, attrs, model, template)
    counts = check_counts(path, arrays, attrs)
    limits = _limits(arrays, attrs, model, counts)
    for rule in (*INDEXES, *_load_faces(arrays)):
        _check_index(path, arrays, attrs, rule, counts, limits)
    for rule in SLOT_LISTS:
        _check_slots(path, arrays, attrs, rule, counts, limits)
    for rule in RANGES:
        _check_ranges(path, arrays, rule, counts, limits)
    check_run_attrs(path, attrs)


def check_scalars(path: Path, attrs: dict, model: Model) -> None:
    """The model's float scalars are numbers >= 0 (inf allowed: no bound) and its scene settings the scene's."""
    for f in dataclasses.fields(model):
        fresh = getattr(model, f.name)
        if type(fresh) is not float or f.name not in attrs:
            continue
        value = attrs[f.name]
        if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value) or value < 0:
            raise CheckpointError(f"{path}: attribute {f.name!r} is {value!r}; expected a number >= 0")
    for name in SCENE_SETTINGS:
        if name in attrs and attrs[name] != getattr(model, name):
            raise CheckpointError(
                f"{path}: attribute {name!r} is {attrs[name]!r}, but the scene builds {getattr(model, name)!r} (no run "
                "changes it)"
            )


def check_sizes(path: Path, arrays: dict[str, np.ndarray], attrs: dict, model: Model, template: State) -> None:
    """Every array is as long as its capacity attributes say (:data:`SIZES`), every body field as long as
    ``body_mass``, and its items are shaped as the fresh model's or state's (a vec3 of three numbers)."""
    fresh = {
        **{f"model/{name}": a for name, a in model.arrays().items()},
        **{f"state/{name}": a for name, a in template.arrays().items()},
    }
    for key, data in arrays.items():
        size = SIZES.get(key)
        if size is None or not (key in fresh or key.startswith("loads/")):
            continue  # an array this scene's model does not hold: the restart does not read it
        expected = size.length(attrs)
        n = len(data) if data.ndim else None
        if n != expected and not (size.or_empty and n == 0):
            raise CheckpointError(
                f"{path}: {key} has shape {data.shape}, not {expected} items as its attributes say ({size.says(attrs)})"
            )
    bodies = arrays.get("state/body_mass")
    for key in SIZED_BY_BODIES:
        data = arrays.get(key)
        if bodies is not None and data is not None and (data.ndim == 0 or len(data) != len(bodies)):
            raise CheckpointError(
                f"{path}: {key} has shape {data.shape}, not one item per rigid body ({len(bodies)}, as state/body_mass)"
            )
    for key, like in fresh.items():
        data = arrays.get(key)
        item = tuple(like.shape[1:]) + tuple(getattr(like.dtype, "_shape_", ()))
        if data is not None and data.ndim and data.shape[1:] != item:
            raise CheckpointError(f"{path}: {key} has shape {data.shape}; its items have shape {item}")
    faces = sum(f.count for f in model.loads.pressure.values()) if model.loads is not None else 0
    for key in LOADED_FACES:
        data = arrays.get(key)
        if data is not None and (data.ndim == 0 or len(data) != faces):
            raise CheckpointError(
                f"{path}: {key} has shape {data.shape}, not one item per loaded face of the scene's pressure loads "
                f"({faces})"
            )
    node_driver = arrays.get("loads/node_driver")
    if node_driver is not None and node_driver.ndim != 1:
        raise CheckpointError(f"{path}: loads/node_driver has shape {node_driver.shape}; its items have shape ()")


def check_counts(path: Path, arrays: dict[str, np.ndarray], attrs: dict) -> dict[str, int]:
    """The live counts (:data:`COUNTS`), each an integer within 0 .. its capacity.

    Returns:
        Count name -> value.
    """
    counts = {}
    for name, capacity in COUNTS.items():
        key = f"state/{name}"
        data = arrays.get(key)
        if data is None:
            continue
        if data.dtype.kind not in "iu":
            raise CheckpointError(f"{path}: {key} holds {data.dtype} values; expected an integer count")
        value = int(data.reshape(-1)[0])
        if not 0 <= value <= int(attrs[capacity]):
            raise CheckpointError(
                f"{path}: {key} is {value}, outside 0 .. {capacity} = {attrs[capacity]} (the slots it counts)"
            )
        counts[name] = value
    return counts


def _limits(arrays: dict[str, np.ndarray], attrs: dict, model: Model, counts: dict[str, int]) -> dict[str, int | None]:
    """What an index may point into, by name: the live counts, and the tables the scene gives (None: not known)."""
    rebuild = arrays.get("state/fem_rebuild_flag")
    joint_sets = model.joint_material_table.shape[0] if model.joint_material_table is not None else 0
    return {
        **counts,
        "num_materials": int(attrs["num_materials"]),
        "parts": len(model.part_names) or None,  # a model built in Python may name no parts
        "joint sets": joint_sets,
        "drivers": model.loads.num_drivers if model.loads is not None else 0,
        "bodies": len(arrays.get("state/body_mass", ())),
        "tet-face slots": 4 * counts.get("tet_count", 0),
        # Candidate lists of nodes awaiting a rebuild may name faces of the surface before the last topology pass.
        "listed faces": counts.get("face_count", 0)
        if rebuild is None or not np.any(rebuild)
        else int(attrs["face_capacity"]),
    }


_LIMIT_WORDS = {
    "parts": "the scene's parts",
    "joint sets": "the joint sets",
    "drivers": "the node drivers",
    "bodies": "the rigid bodies (state/body_mass)",
    "tet-face slots": "the tet-face slots, 4 tet_count",
    "listed faces": "the faces (face_capacity while the lists await a rebuild)",
}


def _out_of_range(
    path: Path,
    key: str,
    values: np.ndarray,
    positions: np.ndarray | None,
    bound: str,
    limit: int,
    none: bool,
    what: str,
) -> None:
    """Raises naming the first value of ``values`` (flat) outside 0 .. limit - 1 (or -1 where ``none``), at its
    ``what`` (item, slot) ``positions[i]`` (i where None); a limit of None bounds nothing."""
    if values.dtype.kind not in "iu":
        raise CheckpointError(f"{path}: {key} holds {values.dtype} values; expected integer indices")
    if limit is None:
        return
    bad = (values >= limit) | (values < (-1 if none else 0))
    if not np.any(bad):
        return
    first = int(np.argmax(bad))
    where = int(positions[first]) if positions is not None else first
    allowed = (["-1"] if none else []) + ([f"0 .. {limit - 1}"] if limit > 0 else [])
    raise CheckpointError(
        f"{path}: {key} holds {int(values[first])} at {what} {where}, out of range: it indexes "
        f"{_LIMIT_WORDS.get(bound, bound)} ({bound} = {limit}; allowed {' or '.join(allowed) or 'nothing'})"
    )


def _check_index(
    path: Path, arrays: dict[str, np.ndarray], attrs: dict, rule: Index, counts: dict[str, int], limits: dict[str, int]
) -> None:
    data = arrays.get(rule.key)
    if data is None or data.size == 0 or data.ndim == 0:
        return
    per = int(attrs[rule.per_item]) if isinstance(rule.per_item, str) else rule.per_item
    rows = len(data) if rule.live is None else min(len(data), counts.get(rule.live, 0) * per)
    live = data[:rows].reshape(-1)
    # Position in items of the array (a tet's row of four node indices is one item).
    width = int(np.prod(data.shape[1:], dtype=np.int64)) if data.ndim > 1 else 1
    positions = np.arange(live.size) // width if width > 1 else None
    _out_of_range(path, rule.key, live, positions, rule.bound, limits[rule.bound], rule.none, "item")


def _load_faces(arrays: dict[str, np.ndarray]) -> list[Index]:
    """The index rules of the load face sets the checkpoint holds."""
    return [
        Index(key, None, "node_count")
        for key in arrays
        if key.startswith("loads/") and key.endswith("_nodes") and key not in {r.key for r in INDEXES}
    ]


def _check_slots(
    path: Path, arrays: dict[str, np.ndarray], attrs: dict, rule: SlotList, counts: dict[str, int], limits: dict
) -> None:
    data, count = arrays.get(rule.key), arrays.get(rule.count)
    if data is None or count is None or data.size == 0 or count.size == 0:
        return
    per_row = int(attrs[rule.per_row])
    rows = min(counts.get(rule.live, 0), len(count), len(data) // max(per_row, 1))
    if count.dtype.kind not in "iu":
        raise CheckpointError(f"{path}: {rule.count} holds {count.dtype} values; expected integer counts")
    used = np.clip(count[:rows].astype(np.int64), 0, per_row)
    mask = np.arange(per_row)[None, :] < used[:, None]
    slots = np.flatnonzero(mask.reshape(-1))
    _out_of_range(path, rule.key, data[slots], slots, rule.bound, limits[rule.bound], rule.none, "slot")


def _check_ranges(
    path: Path, arrays: dict[str, np.ndarray], rule: Ranges, counts: dict[str, int], limits: dict
) -> None:
    start, count, items = arrays.get(rule.start), arrays.get(rule.count), arrays.get(rule.items)
    if start is None or count is None or items is None:
        return
    heads = min(len(start), len(count)) if rule.live is None else min(counts.get(rule.live, 0), len(start), len(count))
    for key, data in ((rule.start, start), (rule.count, count)):
        if data.dtype.kind not in "iu":
            raise CheckpointError(f"{path}: {key} holds {data.dtype} values; expected integers")
    first = start[:heads].astype(np.int64)
    n = count[:heads].astype(np.int64)
    bad = (first < 0) | (n < 0) | (first + n > len(items))
    if np.any(bad):
        i = int(np.argmax(bad))
        raise CheckpointError(
            f"{path}: {rule.start} / {rule.count} give item {i} the range {int(first[i])} .. {int(first[i] + n[i])}, "
            f"outside {rule.items} (0 .. {len(items)})"
        )
    total = int(n.sum())
    if total == 0:
        return
    # Positions of every item of every range: the range's start plus the offset within it.
    within = np.arange(total) - np.repeat(np.cumsum(n) - n, n)
    positions = np.repeat(first, n) + within
    _out_of_range(path, rule.items, items[positions], positions, rule.bound, limits[rule.bound], False, "item")


def check_run_attrs(path: Path, attrs: dict) -> None:
    """The run's attributes (:data:`RUN_ATTRS`, :data:`RUN_RECORDS`) where the file holds them, and the frame grid:
    the checkpoint's step lies within a frame of where the grid ends its frame (frame ``frame`` ends at step
    ``grid_step + (frame − grid_frame) × substeps``; a checkpoint taken at a frame is at that step, one taken between
    two frames, in a short last frame or inside the bridge to a new grid's first boundary within one frame of it)."""
    for name, spec in RUN_ATTRS.items():
        if name not in attrs:
            continue
        value = attrs[name]
        if value is None and spec.optional:
            continue
        if spec.kind is bool:
            ok = isinstance(value, bool)
        elif spec.kind is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = isinstance(value, int | float) and not isinstance(value, bool)
        if not ok:
            raise CheckpointError(f"{path}: attribute {name!r} is {value!r}; expected {_kind_words(spec.kind)}")
        if spec.kind is bool:
            continue
        low = -math.inf if spec.low is None else spec.low
        if not (math.isfinite(value) and (value > low if spec.strict else value >= low)):
            raise CheckpointError(
                f"{path}: attribute {name!r} is {value!r}; expected a finite number {'>' if spec.strict else '>='} "
                f"{low:g}"
            )
    for name, record in RUN_RECORDS.items():
        if name in attrs:
            _check_record(path, name, attrs[name], record)
    scales = attrs.get("load_scales")
    if scales is not None and not (
        isinstance(scales, dict)
        and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in scales.values())
    ):
        raise CheckpointError(f"{path}: attribute 'load_scales' is {scales!r}; expected finite numbers by load name")
    if "grid_step" not in attrs or "substeps" not in attrs:
        return  # a file written before grids were kept: frame 0 at step 0 (warpdem.runner.timing.FrameGrid)
    substeps, step, frame = int(attrs["substeps"]), int(attrs["step"]), int(attrs["frame"])
    grid_step, grid_frame = int(attrs["grid_step"]), int(attrs.get("grid_frame", 0))
    end = grid_step + (frame - grid_frame) * substeps
    if abs(end - step) > substeps + 1:
        raise CheckpointError(
            f"{path}: attribute 'grid_step' is {grid_step} (grid_frame {grid_frame}, substeps {substeps}): the grid "
            f"ends frame {frame} at step {end}, but the checkpoint is at step {step}, more than a frame away"
        )
    dt = attrs.get("pending_dt") or attrs["dt"]
    period = attrs.get("frame_period")
    if period is not None and not math.isclose(substeps * dt, period, rel_tol=1e-6):
        raise CheckpointError(
            f"{path}: attribute 'frame_period' is {period!r}, but the grid's {substeps} steps of {dt:.9g} s make "
            f"{substeps * dt:.9g} s"
        )


def _kind_words(kind: type) -> str:
    return {bool: "true or false", int: "an integer", float: "a number"}[kind]


def _check_record(path: Path, name: str, value: object, record: type) -> None:
    """A record attribute is a dict of the record's fields (those without a default all there), numbers."""
    fields = {f.name: f for f in dataclasses.fields(record)}
    required = {n for n, f in fields.items() if f.default is dataclasses.MISSING}
    if not isinstance(value, dict) or not required <= value.keys() <= fields.keys():
        raise CheckpointError(f"{path}: attribute {name!r} is not a record of the fields {sorted(fields)}")
    for key, v in value.items():
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise CheckpointError(f"{path}: attribute {name!r}: {key} is {v!r}; expected a number")
