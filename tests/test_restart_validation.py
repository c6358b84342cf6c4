"""A damaged restart file is refused before any kernel touches it (issue 29; warpdem.io.restart_check).

Real checkpoints of short runs of seven scenes, each field damaged one way with h5py, one field per file:

- pmma_plate mid-crack (nodes split, cohesive elements alive, pressure loads), rigid_slope (rigid bodies from the
  start), masonry_wall_blast (tets converted: spheres, bonds, neighbour lists), jointed_slope with bonded joints
  (joint interface elements) and its top held by a velocity load (node drivers), boulder_impact (a wall),
  dam_crest_blast (bonded spheres penalty-coupled to the tets, spheres listing boundary faces), masonry_tunnel_blast
  (non-reflecting dashpot faces).

Oracles:

- the issue's damages, restarted through the CLI in a subprocess (a segmentation fault shows as a negative status):
  exit 2, never a signal, and one line on stderr naming the file and the damaged field;
- every rule of the validator's tables, each damaged on the first live item of a scene that has one (an index set to
  2^31 - 1, past every count; a count past its capacity; a capacity one off the arrays it sizes): restore_checkpoint
  raises CheckpointError naming the file and the field, before any array reaches the device;
- the invariant each damage breaks is named with its case (an index below the count of what it indexes, a count within
  its capacity, a capacity equal to the length of the arrays it sizes, run attributes positive and finite, the frame
  grid holding the checkpoint's own step);
- the undamaged checkpoints pass the validator and restart (exit 0), and the tables know every array field of the
  Model and State (a field added later must say what sizes it and what it indexes).
"""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
import warp as wp

from warpdem.build.scene_build import finalize_scene, scene_builder
from warpdem.cli import main
from warpdem.io.checkpoint import CheckpointError, read_checkpoint
from warpdem.io.restart import restore_checkpoint
from warpdem.io.restart_check import COUNTS, INDEXES, RANGES, SIZED_BY_BODIES, SIZES, SLOT_LISTS, UNSIZED
from warpdem.model import Model, State
from warpdem.scene import load_scene

REPO = Path(__file__).resolve().parents[1]

BIG = 2**31 - 1
"""An int32 index past every count a run can reach (MAX_ELEMENTS)."""

RUNS: dict[str, tuple[str, list[str]]] = {
    # Mid-crack: the seed tips have split by 25 µs (8 cohesive elements alive; at 20 µs, with the scene's sub-stepped
    # elements, none was).
    "pmma_plate": ("scenes/pmma_plate.toml", ["--end-time", "2.5e-5"]),
    "rigid_slope": ("scenes/rigid_slope.toml", ["--frames", "1"]),
    "masonry_wall_blast": ("scenes/masonry_wall_blast.toml", ["--frames", "1"]),
    # jointed_slope with cohesive joints (elements exist) and its top held by a velocity load (written by the fixture)
    "bonded_joints": ("", ["--frames", "1"]),
    "boulder_impact": ("scenes/boulder_impact.toml", ["--frames", "1"]),
    "dam_crest_blast": ("scenes/dam_crest_blast.toml", ["--frames", "1"]),
    "masonry_tunnel_blast": ("scenes/masonry_tunnel_blast.toml", ["--frames", "1"]),
}


@dataclasses.dataclass
class Checkpoint:
    """A run's scene file, output folder and final checkpoint."""

    scene: Path
    out: Path
    path: Path


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Checkpoint]:
    """Each scene of :data:`RUNS` run once on the CPU, its final checkpoint."""
    folder = tmp_path_factory.mktemp("restart_validation")
    made = {}
    for name, (source, options) in RUNS.items():
        if name == "bonded_joints":
            text = (REPO / "scenes/jointed_slope.toml").read_text()
            text = text.replace('name = "jointed_slope"', 'name = "bonded_joints"', 1)
            text = text.replace("\ncohesion = 0.0", "\ncohesion = 1.0e5", 1)  # [joints]: bonded, so elements exist
            # The top held by a velocity load, so that loads/node_driver has live entries.
            text += '\n[[loads]]\nkind = "velocity"\nfaces = "z+"\nvelocity = [0.0, 0.0, 0.0]\n'
            scene = folder / "bonded_joints.toml"
            scene.write_text(text)
        else:
            scene = REPO / source
        out = folder / name
        assert main([str(scene), "--device", "cpu", "--quiet", "--out", str(out), *options]) == 0
        (path,) = (out / "checkpoints").glob("*.h5")
        made[name] = Checkpoint(scene, out, path)
    return made


@pytest.fixture(scope="module")
def fresh(runs: dict[str, Checkpoint]) -> Callable[[str], tuple[Model, State, str]]:
    """The fresh model, state and scene name a restart of a run starts from (built once per scene, as the runner
    builds them)."""
    cache: dict[str, tuple[Model, State, str]] = {}

    def get(name: str) -> tuple[Model, State, str]:
        if name not in cache:
            scene = load_scene(runs[name].scene)
            model, state = finalize_scene(scene, scene_builder(scene), wp.get_device("cpu"))
            cache[name] = (model, state, scene.name)
        return cache[name]

    return get


def damaged(source: Path, target: Path, edit: Callable[[h5py.File], None]) -> Path:
    """A copy of a checkpoint with one edit."""
    shutil.copyfile(source, target)
    with h5py.File(target, "r+") as f:
        edit(f)
    return target


def set_entry(key: str, flat: int | Callable[[h5py.File], int], value: int) -> Callable[[h5py.File], None]:
    """Set the entry of flat index ``flat`` (or the one ``flat(f)`` finds) of a dataset."""

    def edit(f: h5py.File) -> None:
        data = f[key][()]
        data.reshape(-1)[flat(f) if callable(flat) else flat] = value
        f[key][...] = data

    return edit


def set_attr(name: str, value: object | Callable[[h5py.File], object]) -> Callable[[h5py.File], None]:
    """Set a root attribute (to ``value(f)`` where callable)."""

    def edit(f: h5py.File) -> None:
        f.attrs[name] = value(f) if callable(value) else value

    return edit


def counter(name: str) -> Callable[[h5py.File], int]:
    """The value of a state counter (shape (1,))."""
    return lambda f: int(f[f"state/{name}"][0])


# ----------------------------------------------------------------------------------------------------------------
# The issue's damages, through the CLI


ISSUE_CASES = [
    # (run, field named in the one line, edit): the invariant each breaks.
    # A tet's node index below node_count (the boundary value node_count itself is out).
    ("pmma_plate", "model/tet_nodes", set_entry("model/tet_nodes", 0, BIG)),
    ("pmma_plate", "model/tet_nodes", lambda f: set_entry("model/tet_nodes", 1, counter("node_count")(f))(f)),
    # A boundary face's node index below node_count.
    ("pmma_plate", "model/face_nodes", set_entry("model/face_nodes", 1, BIG)),
    # A live cohesive element's daughter node below node_count.
    ("pmma_plate", "state/cohesive_a", set_entry("state/cohesive_a", 0, BIG)),
    # A live bond's sphere below particle_count (its boundary value too).
    ("masonry_wall_blast", "state/bond_i", set_entry("state/bond_i", 0, BIG)),
    (
        "masonry_wall_blast",
        "state/bond_j",
        lambda f: set_entry("state/bond_j", 0, counter("particle_count")(f))(f),
    ),
    # A body's node range within rigid_nodes.
    ("rigid_slope", "state/body_node_start", set_entry("state/body_node_start", 1, BIG)),
    # The node capacity equal to the length of the node arrays (here smaller: the live count).
    ("pmma_plate", "node_capacity", set_attr("node_capacity", counter("node_count"))),
    # Live counts within their capacities.
    ("masonry_wall_blast", "state/bond_count", set_entry("state/bond_count", 0, BIG)),
    ("pmma_plate", "state/node_count", set_entry("state/node_count", 0, BIG)),
    ("masonry_wall_blast", "state/particle_count", set_entry("state/particle_count", 0, BIG)),
    # Run attributes positive and finite.
    ("pmma_plate", "substeps", set_attr("substeps", 0)),
    ("rigid_slope", "frame_period", set_attr("frame_period", 0.0)),
    # The grid holds the checkpoint's own step (an anchor 1e15 steps away would run them past --max-steps).
    ("pmma_plate", "grid_step", set_attr("grid_step", 10**15)),
    ("rigid_slope", "grid_frame", set_attr("grid_frame", 10**12)),
]


@pytest.mark.parametrize(("run", "field", "edit"), ISSUE_CASES, ids=[f"{r}-{f}" for r, f, _ in ISSUE_CASES])
def test_the_issues_damaged_checkpoints_exit_2_with_one_line(runs, tmp_path, run, field, edit):
    ckpt = runs[run]
    bad = damaged(ckpt.path, tmp_path / "bad.h5", edit)
    argv = [str(ckpt.scene), "--device", "cpu", "--quiet", "--out", str(tmp_path / "out"), "--restart", str(bad)]
    result = subprocess.run(
        [sys.executable, "-m", "warpdem", *argv],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith(f"error: {bad}: ") and field in lines[0], result.stderr
    assert not (tmp_path / "out").exists()  # refused before any output was opened


# ----------------------------------------------------------------------------------------------------------------
# Every rule of the tables, in process (restore_checkpoint copies arrays; no kernel runs)


def refused(fresh, runs, name: str, tmp_path: Path, edit: Callable[[h5py.File], None]) -> str:
    """The one-line CheckpointError a restart of ``name``'s checkpoint with ``edit`` raises."""
    model, template, scene = fresh(name)
    bad = damaged(runs[name].path, tmp_path / f"{name}.h5", edit)
    with pytest.raises(CheckpointError) as info:
        restore_checkpoint(bad, model, template, scene)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{bad}: "), message
    return message


def first_live(arrays: dict[str, np.ndarray], attrs: dict, key: str) -> int | None:
    """The flat index of the first live entry of an index array (rules of INDEXES, SLOT_LISTS, RANGES), or None."""
    for rule in INDEXES:
        if rule.key == key:
            data = arrays.get(key)
            per = attrs[rule.per_item] if isinstance(rule.per_item, str) else rule.per_item
            live = len(data) if rule.live is None else int(arrays[f"state/{rule.live}"][0]) * per
            return 0 if data is not None and data.size and live > 0 else None
    for rule in SLOT_LISTS:
        if rule.key == key:
            count, per = arrays[rule.count], attrs[rule.per_row]
            rows = np.flatnonzero(count[: int(arrays[f"state/{rule.live}"][0])] > 0)
            return int(rows[0]) * per if len(rows) and arrays[key].size else None
    for rule in RANGES:
        if key in (rule.items, rule.start):
            heads = len(arrays[rule.start])
            if rule.live is not None:
                heads = min(heads, int(arrays[f"state/{rule.live}"][0]))
            counts = arrays[rule.count][:heads]
            used = np.flatnonzero(counts > 0)
            if not len(used):
                return None
            return int(used[0]) if key == rule.start else int(arrays[rule.start][used[0]])
    if key.startswith("loads/") and key in arrays:
        return 0 if arrays[key].size else None
    raise KeyError(key)


INDEX_KEYS = sorted(
    {r.key for r in INDEXES}
    | {r.key for r in SLOT_LISTS}
    | {r.items for r in RANGES}
    | {r.start for r in RANGES}
    | {"loads/pressure_blast_nodes", "loads/pressure_table_nodes", "loads/dashpots_nodes"}
)


@pytest.mark.parametrize("key", INDEX_KEYS)
def test_every_index_array_out_of_range_is_refused(runs, fresh, tmp_path, key):
    """Oracle: each live entry of an index array points below the count of what it indexes (warpdem.model's field
    docs), so 2^31 - 1 in the first live entry is refused, naming the array."""
    found = None
    for run, ckpt in runs.items():
        arrays, attrs = read_checkpoint(ckpt.path)
        flat = first_live(arrays, attrs, key) if key in arrays else None
        if found is None and flat is not None:
            found = run, flat
    if found is None:
        pytest.skip(f"no test scene has a live entry of {key}")
    name, flat = found
    message = refused(fresh, runs, name, tmp_path, set_entry(key, flat, BIG))
    assert key in message and str(BIG) in message, message


RUN_OF = {
    # The run whose arrays of each capacity are the largest of the seven (every run holds every capacity).
    "particle_capacity": "masonry_wall_blast",
    "max_neighbors": "masonry_wall_blast",
    "max_sphere_faces": "masonry_wall_blast",
    "bond_capacity": "masonry_wall_blast",
    "coupling_capacity": "dam_crest_blast",
    "node_capacity": "pmma_plate",
    "tet_capacity": "pmma_plate",
    "face_capacity": "pmma_plate",
    "cohesive_capacity": "pmma_plate",
    "max_node_faces": "pmma_plate",
    "node_springs": "rigid_slope",
    "joint_capacity": "bonded_joints",
    "num_walls": "boulder_impact",
}


@pytest.mark.parametrize("name", sorted(COUNTS))
def test_every_count_past_its_capacity_is_refused(runs, fresh, tmp_path, name):
    """Oracle: a live count lies within 0 .. its capacity (the slots every kernel launches over)."""
    capacity = COUNTS[name]
    run = RUN_OF[capacity]
    attrs = read_checkpoint(runs[run].path)[1]
    message = refused(fresh, runs, run, tmp_path, set_entry(f"state/{name}", 0, attrs[capacity] + 1))
    assert f"state/{name} is {attrs[capacity] + 1}" in message and capacity in message, message
    message = refused(fresh, runs, run, tmp_path, set_entry(f"state/{name}", 0, -1))
    assert f"state/{name} is -1" in message, message


CAPACITIES = sorted({factor for size in SIZES.values() for factor in size.factors})


@pytest.mark.parametrize("attr", CAPACITIES)
def test_every_capacity_that_does_not_match_its_arrays_is_refused(runs, fresh, tmp_path, attr):
    """Oracle: a capacity attribute equals the length its arrays have: one less (one more where it is 0) is refused,
    naming the attribute."""
    run = RUN_OF[attr]
    value = read_checkpoint(runs[run].path)[1][attr]
    message = refused(fresh, runs, run, tmp_path, set_attr(attr, value - 1 if value > 0 else value + 1))
    assert attr in message, message


RUN_ATTR_CASES = [
    # (attribute, damaged value): positive, finite, of its type; the grid holding the checkpoint's step.
    ("substeps", 0),
    ("substeps", 2.5),
    ("frame_period", 0.0),
    ("frame_period", float("inf")),
    ("frame_period", 1.0),  # not the grid's substeps × dt
    ("grid_step", 10**15),
    ("grid_step", -1),
    ("grid_frame", 10**12),
    ("grid_time", float("nan")),
    ("frame_step", -5),
    ("pending_dt", 0.0),
    ("speed_scale", float("inf")),
    ("rigid_step_taken", 3),
    ("energy_start", '{"kinetic": 1.0}'),
    ("dt", 1.0),  # the frame period is then not substeps × dt either
    ("skin", -1.0),
    ("node_springs", 2),
    ("spheres_per_tet", 7),
]


@pytest.mark.parametrize(("attr", "value"), RUN_ATTR_CASES, ids=[f"{a}={v}" for a, v in RUN_ATTR_CASES])
def test_run_attributes_out_of_range_are_refused(runs, fresh, tmp_path, attr, value):
    """Oracle: the run attributes a restart reads are of their type, positive where a period or a count of steps, and
    finite; the frame grid ends the checkpoint's frame within a frame of its step (a grid anchored 1e15 steps away
    would run them)."""

    def edit(f: h5py.File) -> None:
        if attr == "energy_start":
            f.attrs["__json__:energy_start"] = value
        else:
            f.attrs[attr] = value

    message = refused(fresh, runs, "pmma_plate", tmp_path, edit)
    assert attr in message or (attr == "dt" and "frame_period" in message), message


def test_body_fields_of_another_length_than_the_bodies_are_refused(runs, fresh, tmp_path):
    """Oracle: every rigid body field has one item per body (as many as state/body_mass)."""

    def edit(f: h5py.File) -> None:
        data = f["state/body_l"][()]
        del f["state/body_l"]
        f["state/body_l"] = data[:-1]

    assert "state/body_l" in refused(fresh, runs, "rigid_slope", tmp_path, edit)


# ----------------------------------------------------------------------------------------------------------------
# Good files


def test_undamaged_checkpoints_pass_and_restart(runs, fresh, tmp_path):
    """Oracle: the validator refuses no checkpoint a run wrote: each restores, and restarts through the CLI for one
    more frame (exit 0) from a copy of its run's folder."""
    for name, ckpt in runs.items():
        model, template, scene = fresh(name)
        restore_checkpoint(ckpt.path, model, template, scene)
        copy = tmp_path / name
        shutil.copytree(ckpt.out, copy)
        frames = read_checkpoint(ckpt.path)[1]["frame"] + 1
        restart = copy / "checkpoints" / ckpt.path.name
        argv = [str(ckpt.scene), "--device", "cpu", "--quiet", "--out", str(copy), "--frames", str(frames)]
        assert main([*argv, "--restart", str(restart)]) == 0, name


def _array_fields(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls) if "wp.array" in str(f.type)}


def test_the_tables_know_every_array_field(runs):
    """Oracle: every array field of the Model a checkpoint holds and every State field has a size rule (or is sized by
    the bodies), and every integer array of a real checkpoint is either an index the tables check or a flag, count or
    id that indexes nothing (listed here, so a new index array cannot slip past unchecked)."""
    known = {key.split("/", 1)[1] for key in (*SIZES, *SIZED_BY_BODIES, *UNSIZED)}
    structs = {"pair_table", "tet_material_table", "fem_pair_table", "joint_material_table"}
    structs |= {"fracture_material_table", "conversion_material_table"}
    assert _array_fields(Model) - structs <= known, sorted(_array_fields(Model) - structs - known)
    assert _array_fields(State) <= known, sorted(_array_fields(State) - known)
    indexes = set(INDEX_KEYS) | {r.count for r in SLOT_LISTS} | {r.count for r in RANGES}
    not_indexes = {
        # Flags, enumerations, counts per item and stable ids: not positions in another array.
        "model/particle_motion",
        "model/particle_id",
        "model/node_motion",
        "model/node_may_split",
        "model/tet_may_convert",
        "model/tet_may_rigid",
        "model/tet_edge_degree",
        "state/bond_broken",
        "state/particle_bonds_broken",
        "state/tet_active",
        "state/joint_broken",
        "state/cohesive_broken",
        "state/node_substepped",
        "state/body_fixed",
        "state/body_constraint",
    }
    for ckpt in runs.values():
        arrays = read_checkpoint(ckpt.path)[0]
        ints = {k for k, a in arrays.items() if a.dtype.kind in "iu" and a.ndim and a.shape != (1,)}
        assert ints - indexes - not_indexes - {"state/bond_key"} == set(), sorted(ints - indexes - not_indexes)
