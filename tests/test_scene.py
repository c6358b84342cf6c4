"""Scene file schema: defaults, one readable error line per problem, region geometry.

Pure host tests (no warp). Error oracles are the exact key path and a phrase saying what is allowed;
region oracles are hand-computed point classifications.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pydantic import BaseModel

from warpdem import scene as scene_module
from warpdem.scene import (
    Region,
    Scene,
    SceneError,
    default_scene_path,
    load_scene,
    parse_scene,
)

MINIMAL = """\
[run]
end_time = 0.1

[materials.rock]
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.3

[parts.grains]
material = "rock"

[[particles]]
kind = "sphere"
part = "grains"
center = [0.0, 0.0, 0.0]
radius = 0.01
"""

PACKING = MINIMAL.replace(
    'kind = "sphere"\npart = "grains"\ncenter = [0.0, 0.0, 0.0]',
    'kind = "packing"\npart = "grains"\nregion = { box = { lo = [0.0, 0.0, 0.0], hi = [1.0, 1.0, 1.0] } }',
)


def edit(old: str, new: str, base: str = MINIMAL) -> str:
    """The base scene with one exact substring replaced (asserting it is there, so a case cannot go stale)."""
    assert old in base, old
    return base.replace(old, new)


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def problems_of(path: Path) -> list[str]:
    with pytest.raises(SceneError) as info:
        load_scene(path)
    err = info.value
    assert str(err) == "\n".join(err.problems)
    return err.problems


def test_minimal_scene_defaults(tmp_path: Path) -> None:
    scene = load_scene(write(tmp_path, MINIMAL, "granular_pour.toml"))
    assert scene.schema_version == 1
    assert scene.name == "granular_pour"
    assert scene.run.end_time == 0.1
    assert scene.run.dt == "auto"
    assert scene.run.safety_factor == 0.2
    assert scene.run.output_rate == 50.0
    assert scene.run.seed == 0
    assert scene.run.device == "cpu"
    assert scene.gravity.vector == (0.0, 0.0, -9.81)
    assert scene.interactions.default.friction == 0.5
    assert scene.interactions.default.restitution == 0.5
    assert scene.interactions.default.rolling_friction == 0.0
    assert scene.interactions.pairs == []
    assert (scene.contact.normal, scene.contact.tangential, scene.contact.rolling) == ("hertz", "mindlin", "none")
    assert scene.contact.skin == "auto"
    assert scene.output.directory == "out"
    assert scene.output.usd == "granular_pour.usdc"
    assert scene.output.color_by == "speed"
    assert scene.output.checkpoint_every == 0.0
    assert scene.output.checkpoint_dir == "checkpoints"
    assert scene.capacity.particles is None
    assert scene.capacity.neighbors_per_particle == 8
    assert scene.material_names() == ["rock"]
    assert scene.part_names() == ["grains"]
    assert scene.part_material("grains").density == 2500.0
    sphere = scene.particles[0]
    assert sphere.kind == "sphere"
    assert sphere.velocity == (0.0, 0.0, 0.0)
    assert sphere.motion == "free"
    assert scene.bonds == [] and scene.walls == []


def test_explicit_values_survive(tmp_path: Path) -> None:
    text = edit("end_time = 0.1", 'end_time = 0.1\ndt = 1e-5\ndevice = "cuda:1"\nseed = 7')
    text = 'schema_version = 1\nname = "custom"\n' + text
    text += '\n[output]\nusd = "result.usda"\n\n[contact]\nnormal = "linear"\nskin = 0.001\n'
    scene = load_scene(write(tmp_path, text))
    assert scene.name == "custom"
    assert scene.run.dt == 1e-5
    assert scene.run.device == "cuda:1"
    assert scene.run.seed == 7
    assert scene.output.usd == "result.usda"
    assert scene.contact.normal == "linear"
    assert scene.contact.skin == 0.001


# (case id, TOML text, key path expected in the line or None, phrase expected in the line)
BAD_SCENES = [
    (
        "unknown_key",
        edit("end_time = 0.1", "end_time = 0.1\nfoo = 1"),
        "run.foo",
        "unknown key; allowed keys: end_time",
    ),
    (
        "unknown_key_in_list_entry",
        edit("radius = 0.01", 'radius = 0.01\ncolour = "red"'),
        "particles[0].colour",
        "unknown key; allowed keys: kind, part, center, radius",
    ),
    (
        "negative_density",
        edit("density = 2500.0", "density = -2500.0"),
        "materials.rock.density",
        "greater than 0 (got -2500.0)",
    ),
    (
        "poisson_too_large",
        edit("poisson_ratio = 0.3", "poisson_ratio = 0.6"),
        "materials.rock.poisson_ratio",
        "must be > -1 and < 0.5 (got 0.6)",
    ),
    (
        "poisson_exactly_half",
        edit("poisson_ratio = 0.3", "poisson_ratio = 0.5"),
        "materials.rock.poisson_ratio",
        "must be > -1 and < 0.5 (got 0.5)",
    ),
    (
        "unknown_material_in_parts",
        edit('material = "rock"', 'material = "granite"'),
        "parts.grains.material",
        "unknown material 'granite'; defined materials: 'rock'",
    ),
    (
        "unknown_part_in_particles",
        edit('part = "grains"', 'part = "pebbles"'),
        "particles[0].part",
        "unknown part 'pebbles'; defined parts: 'grains'",
    ),
    ("malformed_toml", edit("end_time = 0.1", "end_time = "), None, "invalid TOML: Invalid value (at line 2, column"),
    (
        "string_for_float",
        edit("end_time = 0.1", 'end_time = "0.1"'),
        "run.end_time",
        "valid number (got '0.1')",
    ),
    (
        "missing_required_key",
        edit("end_time = 0.1", "seed = 1"),
        "run.end_time",
        "required key is missing",
    ),
    (
        "box_hi_below_lo",
        edit("hi = [1.0, 1.0, 1.0]", "hi = [1.0, -1.0, 1.0]", base=PACKING),
        "particles[0].region.box.hi",
        "must be > lo = [0.0, 0.0, 0.0] in every component (got [1.0, -1.0, 1.0])",
    ),
    (
        "region_without_shape",
        edit("region = { box = { lo = [0.0, 0.0, 0.0], hi = [1.0, 1.0, 1.0] } }", "region = {}", base=PACKING),
        "particles[0].region",
        "needs exactly one of 'box' or 'cylinder'",
    ),
    (
        "bad_device",
        edit("end_time = 0.1", 'end_time = 0.1\ndevice = "gpu"'),
        "run.device",
        "must be 'cpu', 'cuda' or 'cuda:<index>' (got 'gpu')",
    ),
    (
        "bad_dt_string",
        edit("end_time = 0.1", 'end_time = 0.1\ndt = "fast"'),
        "run.dt",
        "must be 'auto' or a number > 0 (got 'fast')",
    ),
    (
        "unsupported_schema_version",
        "schema_version = 2\n" + MINIMAL,
        "schema_version",
        "unsupported schema version; supported: 1 (got 2)",
    ),
    (
        "reserved_section_tets",
        MINIMAL + "\n[tets]\nmesh = 'block.msh'\n",
        "tets",
        "section not supported by this version of warpdem (schema_version 1) yet",
    ),
    (
        "unknown_wall_kind",
        MINIMAL + '\n[[walls]]\nkind = "cone"\nmaterial = "rock"\n',
        "walls[0].kind",
        "unknown value 'cone'; allowed: 'plane', 'box'",
    ),
    (
        "unknown_literal",
        edit('kind = "sphere"', 'kind = "sphere"\nmotion = "wobble"'),
        "particles[0].motion",
        "unknown value 'wobble'; allowed: 'free', 'fixed', 'prescribed'",
    ),
    (
        "non_finite_vector",
        MINIMAL + "\n[gravity]\nvector = [0.0, 0.0, nan]\n",
        "gravity.vector[2]",
        "finite number (got nan)",
    ),
    (
        "short_vector",
        edit("center = [0.0, 0.0, 0.0]", "center = [0.0, 0.0]"),
        "particles[0].center",
        "too few values; expected 3",
    ),
    (
        "zero_plane_normal",
        MINIMAL + '\n[[walls]]\nkind = "plane"\npoint = [0, 0, 0]\nnormal = [0, 0, 0]\nmaterial = "rock"\n',
        "walls[0].normal",
        "must be a nonzero vector",
    ),
    (
        "unknown_wall_material",
        MINIMAL + '\n[[walls]]\nkind = "box"\nlo = [0, 0, 0]\nhi = [1, 1, 1]\nmaterial = "steel"\n',
        "walls[0].material",
        "unknown material 'steel'; defined materials: 'rock'",
    ),
    (
        "duplicate_interaction_pair",
        MINIMAL
        + '\n[[interactions.pairs]]\nmaterials = ["rock", "rock"]\nfriction = 0.2\n'
        + '\n[[interactions.pairs]]\nmaterials = ["rock", "rock"]\nfriction = 0.3\n',
        "interactions.pairs[1].materials",
        "duplicate pair ['rock', 'rock']; already defined at interactions.pairs[0]",
    ),
    (
        "bond_without_stiffness",
        MINIMAL + "\n[[bonds]]\nregion = { box = { lo = [0, 0, 0], hi = [1, 1, 1] } }\n"
        "tensile_strength = 1e6\nshear_strength = 1e6\n",
        "bonds[0]",
        "needs 'material' or 'youngs_modulus'",
    ),
    (
        "missing_particle_file",
        edit(
            'kind = "sphere"\npart = "grains"\ncenter = [0.0, 0.0, 0.0]',
            'kind = "file"\npart = "grains"\npath = "missing_init.txt"',
        ),
        "particles[0].path",
        "file not found",
    ),
]


# A continuum scene: materials with fracture properties, a box mesh, a load and a boundary (no particles).
MESH_BASE = """\
[run]
end_time = 0.01

[materials.rock]
density = 2600.0
youngs_modulus = 5e10
poisson_ratio = 0.25

[mesh]
kind = "box"
lo = [0.0, 0.0, 0.0]
hi = [1.0, 1.0, 4.0]
divisions = [2, 2, 8]
material = "rock"

[[loads]]
kind = "pressure"
faces = "z+"
history = { kind = "blast", peak = 1e6, rise_time = 1e-5, decay_time = 1e-4 }

[[boundaries]]
faces = "z-"
kind = "non_reflecting"
"""

GEOLOGY_BASE = """\
[run]
end_time = 0.01

[materials.rock]
density = 2600.0
youngs_modulus = 5e10
poisson_ratio = 0.25

[mesh]
kind = "geology"
lo = [0.0, 0.0, 0.0]
hi = [10.0, 10.0, 10.0]
material = "rock"
h = 2.0

[[mesh.openings]]
kind = "tunnel"
axis = "y"
center = [5.0, 4.0]
radius = 1.5

[[mesh.joint_sets]]
dip = 60.0
dip_direction = 90.0
spacing = 3.0
"""

MESH_BAD_SCENES = [
    (
        "unknown_mesh_kind",
        edit('kind = "box"', 'kind = "sphere"', base=MESH_BASE),
        "mesh.kind",
        "unknown value 'sphere'; allowed: 'box', 'geology', 'file', 'cylinder', 'ellipsoid'",
    ),
    (
        "zero_division",
        edit("divisions = [2, 2, 8]", "divisions = [2, 0, 8]", base=MESH_BASE),
        "mesh.divisions[1]",
        "greater than 0 (got 0)",
    ),
    (
        "unknown_mesh_material",
        edit('divisions = [2, 2, 8]\nmaterial = "rock"', 'divisions = [2, 2, 8]\nmaterial = "basalt"', base=MESH_BASE),
        "mesh.material",
        "unknown material 'basalt'; defined materials: 'rock'",
    ),
    (
        "negative_fracture_energy",
        edit("poisson_ratio = 0.25", "poisson_ratio = 0.25\nfracture_energy = -5.0", base=MESH_BASE),
        "materials.rock.fracture_energy",
        "greater than 0 (got -5.0)",
    ),
    (
        "negative_mass_damping",
        edit("poisson_ratio = 0.25", "poisson_ratio = 0.25\nmass_damping = -1", base=MESH_BASE),
        "materials.rock.mass_damping",
        "greater than or equal to 0 (got -1)",
    ),
    (
        "unknown_face_set",
        edit('faces = "z+"', 'faces = "top"', base=MESH_BASE),
        "loads[0].faces",
        "unknown face set 'top'; the box mesh has: 'x-', 'x+', 'y-', 'y+', 'z-', 'z+'",
    ),
    (
        "opening_on_box_mesh",
        edit('faces = "z-"', 'faces = "opening"', base=MESH_BASE),
        "boundaries[0].faces",
        "unknown face set 'opening'",
    ),
    (
        "unknown_load_kind",
        edit('kind = "pressure"', 'kind = "impulse"', base=MESH_BASE),
        "loads[0].kind",
        "unknown value 'impulse'; allowed: 'pressure', 'airblast', 'velocity'",
    ),
    (
        "unknown_history_kind",
        edit('history = { kind = "blast"', 'history = { kind = "sine"', base=MESH_BASE),
        "loads[0].history.kind",
        "unknown value 'sine'; allowed: 'blast', 'table', 'friedlander'",
    ),
    (
        "blast_without_decay",
        edit(", decay_time = 1e-4", "", base=MESH_BASE),
        "loads[0].history.decay_time",
        "required key is missing",
    ),
    (
        "table_not_increasing",
        edit(
            'history = { kind = "blast", peak = 1e6, rise_time = 1e-5, decay_time = 1e-4 }',
            'history = { kind = "table", times = [0.0, 2e-4, 1e-4], values = [0.0, 1e6, 0.0] }',
            base=MESH_BASE,
        ),
        "loads[0].history.times",
        "must be strictly increasing",
    ),
    (
        "table_lengths_differ",
        edit(
            'history = { kind = "blast", peak = 1e6, rise_time = 1e-5, decay_time = 1e-4 }',
            'history = { kind = "table", times = [0.0, 1e-4], values = [0.0, 1e6, 0.0] }',
            base=MESH_BASE,
        ),
        "loads[0].history.values",
        "needs one value per time (2)",
    ),
    (
        "faces_and_region",
        edit('faces = "z+"', 'faces = "z+"\nregion = { box = { lo = [0, 0, 0], hi = [1, 1, 1] } }', base=MESH_BASE),
        "loads[0]",
        "needs exactly one of 'faces' or 'region' (got both)",
    ),
    (
        "velocity_end_before_start",
        MESH_BASE + '\n[[loads]]\nkind = "velocity"\nfaces = "x-"\nvelocity = [1, 0, 0]\nstart = 0.002\nend = 0.001\n',
        "loads[1].end",
        "must be > start = 0.002 (got 0.001)",
    ),
    (
        "unknown_boundary_kind",
        edit('kind = "non_reflecting"', 'kind = "absorbing"', base=MESH_BASE),
        "boundaries[0].kind",
        "unknown value 'absorbing'; allowed: 'fixed', 'roller', 'non_reflecting'",
    ),
    (
        "oblique_roller_normal",
        edit('kind = "non_reflecting"', 'kind = "roller"\nnormal = [1.0, 1.0, 0.0]', base=MESH_BASE),
        "boundaries[0].normal",
        "must be a nonzero vector along x, y or z",
    ),
    (
        "normal_on_fixed_boundary",
        edit('kind = "non_reflecting"', 'kind = "fixed"\nnormal = [0.0, 0.0, 1.0]', base=MESH_BASE),
        "boundaries[0]",
        "'normal' is only used by kind 'roller', not 'fixed'",
    ),
    (
        "loads_without_mesh",
        MINIMAL + '\n[[boundaries]]\nfaces = "z-"\nkind = "fixed"\n',
        "boundaries",
        "needs a [mesh] to act on",
    ),
    (
        "tunnel_without_radius",
        edit("radius = 1.5", "width = 3.0", base=GEOLOGY_BASE),
        "mesh.openings[0]",
        "a circular tunnel needs 'radius'",
    ),
    (
        "refinement_not_finer",
        edit("h = 2.0\n", "h = 2.0\nrefinements = [{ lo = [0, 0, 0], hi = [5, 5, 5], h = 2.5 }]\n", base=GEOLOGY_BASE),
        "mesh.refinements",
        "[0].h = 2.5 m must be below the mesh's h = 2 m (a finer edge)",
    ),
    (
        "refinement_outside_model",
        edit(
            "h = 2.0\n", "h = 2.0\nrefinements = [{ lo = [11, 0, 0], hi = [12, 5, 5], h = 1.0 }]\n", base=GEOLOGY_BASE
        ),
        "mesh.refinements",
        "[0]: the box [[11.0, 0.0, 0.0], [12.0, 5.0, 5.0]] does not overlap the model's box",
    ),
    (
        "tunnel_bad_axis",
        edit('axis = "y"', 'axis = "z"', base=GEOLOGY_BASE),
        "mesh.openings[0].axis",
        "unknown value 'z'; allowed: 'x', 'y'",
    ),
    (
        "unknown_opening_kind",
        edit('kind = "tunnel"', 'kind = "cave"', base=GEOLOGY_BASE),
        "mesh.openings[0].kind",
        "unknown value 'cave'; allowed: 'tunnel', 'shaft', 'room'",
    ),
    (
        "dip_too_steep",
        edit("dip = 60.0", "dip = 120.0", base=GEOLOGY_BASE),
        "mesh.joint_sets[0].dip",
        "less than or equal to 90 (got 120.0)",
    ),
    (
        "unknown_persistence",
        edit("spacing = 3.0", 'spacing = 3.0\npersistence = "partial"', base=GEOLOGY_BASE),
        "mesh.joint_sets[0].persistence",
        "unknown value 'partial'; allowed: 'persistent', 'disc', 'layers'",
    ),
    (
        "disc_without_radius",
        edit("spacing = 3.0", 'spacing = 3.0\npersistence = "disc"', base=GEOLOGY_BASE),
        "mesh.joint_sets[0]",
        "persistence 'disc' needs 'radius'",
    ),
    (
        "layers_reference_itself",
        edit("spacing = 3.0", 'spacing = 3.0\npersistence = "layers"\nreference = 0', base=GEOLOGY_BASE),
        "mesh.joint_sets[0].reference",
        "must be the index of another joint set, 0..0 except 0 (got 0)",
    ),
    (
        "layers_reference_not_persistent",
        GEOLOGY_BASE + '\n[[mesh.joint_sets]]\ndip = 10.0\ndip_direction = 0.0\nspacing = 2.0\npersistence = "layers"\n'
        "reference = 2\n"
        + '\n[[mesh.joint_sets]]\ndip = 10.0\ndip_direction = 0.0\nspacing = 2.0\npersistence = "disc"\n'
        "radius = 1.0\n",
        "mesh.joint_sets[1].reference",
        "joint set 2 is not persistent",
    ),
    (
        "layers_max_below_layers",
        GEOLOGY_BASE + '\n[[mesh.joint_sets]]\ndip = 90.0\ndip_direction = 0.0\nspacing = 2.0\npersistence = "layers"\n'
        "reference = 0\nlayers = 2\nlayers_max = 1\n",
        "mesh.joint_sets[1]",
        "'layers_max' (1) must be at least 'layers' (2)",
    ),
    (
        "layers_max_without_layers",
        edit("spacing = 3.0", "spacing = 3.0\nlayers_max = 3", base=GEOLOGY_BASE),
        "mesh.joint_sets[0]",
        "'layers_max' not used with persistence 'persistent'",
    ),
    (
        "bad_phase",
        edit("spacing = 3.0", "spacing = 3.0\nphase = 2", base=GEOLOGY_BASE),
        "mesh.joint_sets[0].phase",
        "unknown value 2; allowed: 0, 1",
    ),
    (
        "negative_joint_friction",
        edit("spacing = 3.0", "spacing = 3.0\nfriction = -0.1", base=GEOLOGY_BASE),
        "mesh.joint_sets[0].friction",
        "greater than or equal to 0 (got -0.1)",
    ),
    (
        "joint_set_both_stiffness_keys",
        edit("spacing = 3.0", "spacing = 3.0\nstiffness_factor = 2.0\nnormal_stiffness = 1.0e10", base=GEOLOGY_BASE),
        "mesh.joint_sets[0]",
        "takes one of 'stiffness_factor' and 'normal_stiffness', not both",
    ),
    (
        "joint_defaults_both_stiffness_keys",
        GEOLOGY_BASE + "\n[joints]\nstiffness_factor = 2.0\nnormal_stiffness = 1.0e10\n",
        "joints",
        "takes one of 'stiffness_factor' and 'normal_stiffness', not both",
    ),
    (
        "negative_normal_stiffness",
        edit("spacing = 3.0", "spacing = 3.0\nnormal_stiffness = -1.0e10", base=GEOLOGY_BASE),
        "mesh.joint_sets[0].normal_stiffness",
        "greater than 0 (got -10000000000.0)",
    ),
    (
        "layers_out_of_order",
        GEOLOGY_BASE.replace(
            "h = 2.0\n",
            'h = 2.0\nlayers = [{ z_top = 6.0, material = "rock" }, { z_top = 3.0, material = "rock" }]\n',
        ),
        "mesh.layers[1].z_top",
        "must be > mesh.layers[0].z_top = 6.0 and <= the box top = 10.0 (got 3.0)",
    ),
    (
        "layer_unknown_material",
        GEOLOGY_BASE.replace("h = 2.0\n", 'h = 2.0\nlayers = [{ z_top = 6.0, material = "shale" }]\n'),
        "mesh.layers[0].material",
        "unknown material 'shale'",
    ),
    (
        "geology_face_set_opening_ok_but_typo",
        GEOLOGY_BASE + '\n[[boundaries]]\nfaces = "openings"\nkind = "fixed"\n',
        "boundaries[0].faces",
        "the geology mesh has: 'x-', 'x+', 'y-', 'y+', 'z-', 'z+', 'opening'",
    ),
    (
        "missing_mesh_file",
        MINIMAL + '\n[mesh]\nkind = "file"\npath = "rock.msh"\n',
        "mesh.path",
        "file not found",
    ),
    (
        "file_material_and_map",
        MINIMAL + '\n[mesh]\nkind = "file"\npath = "rock.msh"\nmaterial = "rock"\nmaterial_map = { 1 = "rock" }\n',
        "mesh",
        "give 'material' or 'material_map', not both",
    ),
    (
        "bricks_zero_height",
        MINIMAL + '\n[mesh]\nkind = "bricks"\nlo = [0, 0, 0]\nhi = [4, 1, 2]\nmaterial = "rock"\n'
        "brick = [1.0, 1.0, 0.0]\nh = 0.5\n",
        "mesh.brick",
        "every size must be > 0 (got [1.0, 1.0, 0.0])",
    ),
    (
        "bricks_stagger_one",
        MINIMAL + '\n[mesh]\nkind = "bricks"\nlo = [0, 0, 0]\nhi = [4, 1, 2]\nmaterial = "rock"\n'
        "brick = [1.0, 1.0, 0.5]\nh = 0.5\nstagger = 1.0\n",
        "mesh.stagger",
        "less than 1",
    ),
    (
        "file_joint_group_negative_friction",
        MINIMAL + '\n[mesh]\nkind = "file"\npath = "rock.msh"\n[mesh.joint_groups.bedding]\nfriction = -0.2\n',
        "mesh.joint_groups.bedding.friction",
        "greater than or equal to 0 (got -0.2)",
    ),
    (
        "file_joint_group_geology_key",
        MINIMAL + '\n[mesh]\nkind = "file"\npath = "rock.msh"\n[mesh.joint_groups.bedding]\ndip = 30.0\n',
        "mesh.joint_groups.bedding.dip",
        "unknown key; allowed keys: friction, cohesion, tensile_strength, stiffness_factor",
    ),
    (
        "file_joint_groups_not_array_or_table",
        MINIMAL + '\n[mesh]\nkind = "file"\npath = "rock.msh"\njoint_groups = "bedding"\n',
        "mesh.joint_groups",
        "must be an array of triangle group names or a table of group name -> joint properties",
    ),
    (
        "file_joint_groups_listed_twice",
        MINIMAL + '\n[mesh]\nkind = "file"\npath = "rock.msh"\njoint_groups = ["bedding", "bedding"]\n',
        "mesh.joint_groups",
        "group 'bedding' is listed twice",
    ),
    (
        "geology_opening_min_piece",
        edit("radius = 1.5", "radius = 1.5\nmin_piece = 0.25", base=GEOLOGY_BASE),
        "mesh.openings",
        "'min_piece' is for bricks meshes only",
    ),
    (
        "bricks_opening_min_piece_one",
        MINIMAL + '\n[mesh]\nkind = "bricks"\nlo = [0, 0, 0]\nhi = [4, 1, 2]\nmaterial = "rock"\n'
        'brick = [1.0, 1.0, 0.5]\nh = 0.5\n[[mesh.openings]]\nkind = "room"\nlo = [1, -1, 0.5]\nhi = [2, 2, 1]\n'
        "min_piece = 1.0\n",
        "mesh.openings[0].min_piece",
        "less than 1",
    ),
    (
        "geology_solid_overlaps_the_rock",
        GEOLOGY_BASE + '\n[[mesh.solids]]\nname = "box"\nlo = [3.0, 0.0, 3.5]\nhi = [5.5, 10.0, 4.5]\n',
        "mesh.solids",
        "solids[0] ('box'): not inside any opening with a gap all round",
    ),
    (
        "geology_solid_outside_the_box",
        GEOLOGY_BASE + '\n[[mesh.solids]]\nname = "box"\nlo = [4.5, -1.0, 3.5]\nhi = [5.5, 10.0, 4.5]\n',
        "mesh.solids",
        "is not inside the model's box",
    ),
    (
        "geology_solid_name_taken",
        GEOLOGY_BASE + '\n[[mesh.solids]]\nname = "opening"\nlo = [4.5, 0.0, 3.5]\nhi = [5.5, 10.0, 4.5]\n',
        "mesh.solids",
        "the face set name 'opening' is taken",
    ),
    (
        "geology_solid_cavity_notch",
        GEOLOGY_BASE + '\n[[mesh.solids]]\nname = "box"\nlo = [4.5, 0.0, 3.5]\nhi = [5.5, 10.0, 4.5]\n'
        "cavity = { lo = [4.8, 0.0, 3.8], hi = [5.5, 10.0, 4.2] }\n",
        "mesh.solids[0]",
        "cavity: the cavity [4.8, 5.5] along x is not inside the solid [4.5, 5.5]",
    ),
    (
        "geology_solid_unknown_face_set",
        GEOLOGY_BASE + '\n[[mesh.solids]]\nname = "box"\nlo = [4.5, 0.0, 3.5]\nhi = [5.5, 10.0, 4.5]\n'
        '\n[[boundaries]]\nfaces = "box_cavity"\nkind = "fixed"\n',
        "boundaries[0].faces",
        "the geology mesh has: 'x-', 'x+', 'y-', 'y+', 'z-', 'z+', 'opening', 'box'",
    ),
    (
        "geology_joint_set_restitution_zero",
        edit("spacing = 3.0", "spacing = 3.0\nrestitution = 0.0", base=GEOLOGY_BASE),
        "mesh.joint_sets[0].restitution",
        "greater than 0 (got 0.0)",
    ),
    (
        "negative_joint_default",
        MESH_BASE + "\n[joints]\ncohesion = -1.0\n",
        "joints.cohesion",
        "greater than or equal to 0 (got -1.0)",
    ),
    (
        "vtu_not_bool",
        MESH_BASE + '\n[output]\nvtu = "yes"\n',
        "output.vtu",
        "valid boolean (got 'yes')",
    ),
]
BAD_SCENES += MESH_BAD_SCENES

FRACTURING = edit(
    "poisson_ratio = 0.25",
    "poisson_ratio = 0.25\ntensile_strength = 1e7\nfracture_energy = 100.0",
    base=MESH_BASE,
)
FRACTURE_ON = FRACTURING + "\n[fracture]\nenabled = true\n"
SEED = (
    "[[fracture.seed_cracks]]\npoint = [0.5, 0.5, 2.0]\nnormal = [0.0, 0.0, 1.0]\n"
    "region = { box = { lo = [0.0, 0.0, 1.9], hi = [0.5, 1.0, 2.1] } }\n"
)

FRACTURE_BAD_SCENES = [
    (
        "fracture_check_interval_zero",
        FRACTURE_ON + "check_interval = 0\n",
        "fracture.check_interval",
        "greater than or equal to 1 (got 0)",
    ),
    (
        "fracture_cohesive_capacity_zero",
        FRACTURE_ON + "cohesive_capacity = 0\n",
        "fracture.cohesive_capacity",
        "greater than 0 (got 0)",
    ),
    ("fracture_unknown_key", FRACTURE_ON + "interval = 3\n", "fracture.interval", "unknown key"),
    (
        "fracture_region_two_shapes",
        FRACTURE_ON
        + "region = { box = { lo = [0, 0, 0], hi = [1, 1, 1] }, cylinder = { center = [0, 0, 0], radius = 1, "
        "height = 1 } }\n",
        "fracture.region",
        "needs exactly one of 'box' or 'cylinder'",
    ),
    (
        "cohesive_alpha_above_one",
        edit("fracture_energy = 100.0", "fracture_energy = 100.0\ncohesive_alpha = 1.5", base=FRACTURE_ON),
        "materials.rock.cohesive_alpha",
        "less than or equal to 1 (got 1.5)",
    ),
    (
        "cohesive_alpha_negative",
        edit("fracture_energy = 100.0", "fracture_energy = 100.0\ncohesive_alpha = -0.1", base=FRACTURE_ON),
        "materials.rock.cohesive_alpha",
        "greater than or equal to 0 (got -0.1)",
    ),
    (
        "fracture_without_mesh",
        MINIMAL + "\n[fracture]\nenabled = true\n",
        "fracture.enabled",
        "needs a [mesh]",
    ),
    (
        "seed_cracks_without_mesh",
        MINIMAL + "\n" + SEED,
        "fracture.seed_cracks",
        "needs a [mesh]",
    ),
    (
        "fracture_material_without_fracture_energy",
        edit("fracture_energy = 100.0\n", "", base=FRACTURE_ON),
        "materials.rock.fracture_energy",
        "required: [fracture] is enabled",
    ),
    (
        "fracture_material_without_tensile_strength",
        edit("tensile_strength = 1e7\n", "", base=FRACTURE_ON),
        "materials.rock.tensile_strength",
        "required: [fracture] is enabled",
    ),
    (
        "seed_crack_zero_normal",
        FRACTURING + "\n" + SEED.replace("normal = [0.0, 0.0, 1.0]", "normal = [0.0, 0.0, 0.0]"),
        "fracture.seed_cracks[0].normal",
        "must be a nonzero vector",
    ),
    (
        "seed_crack_negative_friction",
        FRACTURING + "\n" + SEED + "friction = -0.2\n",
        "fracture.seed_cracks[0].friction",
        "greater than or equal to 0 (got -0.2)",
    ),
    (
        "seed_crack_without_region",
        FRACTURING + "\n" + SEED.replace("region = { box = { lo = [0.0, 0.0, 1.9], hi = [0.5, 1.0, 2.1] } }\n", ""),
        "fracture.seed_cracks[0].region",
        "required",
    ),
    (
        "cohesive_as_curves_not_bool",
        MESH_BASE + '\n[output]\ncohesive_as_curves = "yes"\n',
        "output.cohesive_as_curves",
        "valid boolean (got 'yes')",
    ),
    (
        "cylinder_mesh_zero_radius",
        MINIMAL + '\n[mesh]\nkind = "cylinder"\ncenter = [0, 0, 0]\nradius = 0.0\nheight = 0.1\nh = 0.05\n'
        'material = "rock"\n',
        "mesh.radius",
        "greater than 0 (got 0.0)",
    ),
    (
        "cylinder_mesh_bad_axis",
        MINIMAL + '\n[mesh]\nkind = "cylinder"\ncenter = [0, 0, 0]\naxis = "w"\nradius = 1.0\nheight = 0.1\n'
        'h = 0.05\nmaterial = "rock"\n',
        "mesh.axis",
        "allowed: 'x', 'y', 'z'",
    ),
    (
        "ellipsoid_mesh_negative_radius",
        MINIMAL + '\n[mesh]\nkind = "ellipsoid"\ncenter = [0, 0, 0]\nradii = [1.0, -1.0, 1.0]\nh = 0.5\n'
        'material = "rock"\n',
        "mesh.radii",
        "every component must be > 0",
    ),
    (
        "ellipsoid_mesh_unknown_material",
        MINIMAL + '\n[mesh]\nkind = "ellipsoid"\ncenter = [0, 0, 0]\nradii = [1.0, 1.0, 1.0]\nh = 0.5\n'
        'material = "granite"\n',
        "mesh.material",
        "unknown material 'granite'",
    ),
]
BAD_SCENES += FRACTURE_BAD_SCENES


CONVERTING = edit("poisson_ratio = 0.25", "poisson_ratio = 0.25\ntresca_strength = 1e7", base=MESH_BASE)
CONVERSION_ON = CONVERTING + "\n[conversion]\nenabled = true\n"
ARCH = (
    MINIMAL + '\n[mesh]\nkind = "arch"\ncenter = [0, 0, 0]\nradius = 10.0\nthickness = 2.0\nheight = 4.0\n'
    'angle = 60.0\ndivisions = [6, 2, 4]\nmaterial = "rock"\n'
)

CONVERSION_BAD_SCENES = [
    (
        "conversion_without_mesh",
        MINIMAL + "\n[conversion]\nenabled = true\n",
        "conversion.enabled",
        "needs a [mesh] to convert",
    ),
    (
        "conversion_unknown_criterion",
        CONVERSION_ON + 'criterion = "von_mises"\n',
        "conversion.criterion",
        "unknown value 'von_mises'; allowed: 'tresca', 'rankine', 'mohr_coulomb'",
    ),
    ("conversion_fraction_zero", CONVERSION_ON + "fraction = 0.0\n", "conversion.fraction", "greater than 0"),
    ("conversion_fraction_above_one", CONVERSION_ON + "fraction = 1.5\n", "conversion.fraction", "less than or equal"),
    (
        "conversion_check_interval_zero",
        CONVERSION_ON + "check_interval = 0\n",
        "conversion.check_interval",
        "greater than or equal to 1",
    ),
    (
        "conversion_spheres_per_tet_two",
        CONVERSION_ON + "spheres_per_tet = 2\n",
        "conversion.spheres_per_tet",
        "must be 1 or 4",
    ),
    ("conversion_unknown_key", CONVERSION_ON + "interval = 3\n", "conversion.interval", "unknown key"),
    ("conversion_bad_part_name", CONVERSION_ON + 'part = "1st"\n', "conversion.part", "invalid name"),
    (
        "conversion_region_empty",
        CONVERSION_ON + "region = {}\n",
        "conversion.region",
        "needs exactly one of 'box' or 'cylinder'",
    ),
    (
        "start_as_spheres_without_conversion",
        CONVERTING + "\n[conversion]\nstart_as_spheres = { box = { lo = [0, 0, 0], hi = [1, 1, 1] } }\n",
        "conversion.start_as_spheres",
        "needs conversion.enabled = true",
    ),
    (
        "tresca_material_without_tresca_strength",
        MESH_BASE + "\n[conversion]\nenabled = true\n",
        "materials.rock.tresca_strength",
        "required: [conversion] is enabled with criterion 'tresca'",
    ),
    (
        "rankine_material_without_tensile_strength",
        CONVERSION_ON + 'criterion = "rankine"\n',
        "materials.rock.tensile_strength",
        "required: [conversion] is enabled with criterion 'rankine'",
    ),
    (
        "mohr_coulomb_material_without_cohesion",
        CONVERSION_ON + 'criterion = "mohr_coulomb"\n',
        "materials.rock.cohesion",
        "required: [conversion] is enabled with criterion 'mohr_coulomb'",
    ),
    (
        "negative_cohesion",
        edit("tresca_strength = 1e7", "tresca_strength = 1e7\ncohesion = -1.0", base=CONVERSION_ON),
        "materials.rock.cohesion",
        "greater than 0",
    ),
    (
        "friction_angle_90",
        edit("tresca_strength = 1e7", "tresca_strength = 1e7\nfriction_angle = 90.0", base=CONVERSION_ON),
        "materials.rock.friction_angle",
        "less than 90",
    ),
    ("resolution_zero", edit("end_time = 0.1", "end_time = 0.1\nresolution = 0.0"), "run.resolution", "greater than 0"),
    (
        "resolution_string",
        edit("end_time = 0.1", 'end_time = 0.1\nresolution = "high"'),
        "run.resolution",
        "valid number",
    ),
    (
        "material_region_unknown_material",
        CONVERTING + '\n[[material_regions]]\nregion = { box = { lo = [0, 0, 0], hi = [1, 1, 1] } }\nmaterial = "x"\n',
        "material_regions[0].material",
        "unknown material 'x'",
    ),
    (
        "material_regions_without_mesh",
        MINIMAL + '\n[[material_regions]]\nregion = { box = { lo = [0, 0, 0], hi = [1, 1, 1] } }\nmaterial = "rock"\n',
        "material_regions",
        "needs a [mesh]",
    ),
    (
        "material_region_without_strength",
        edit(
            "[[loads]]",
            "[materials.soil]\ndensity = 2000.0\nyoungs_modulus = 1e9\npoisson_ratio = 0.3\n\n[[loads]]",
            base=CONVERSION_ON,
        )
        + '\n[[material_regions]]\nregion = { box = { lo = [0, 0, 0], hi = [1, 1, 1] } }\nmaterial = "soil"\n',
        "materials.soil.tresca_strength",
        "required: [conversion] is enabled",
    ),
    ("arch_too_thick", ARCH.replace("thickness = 2.0", "thickness = 10.0"), "mesh", "radius must exceed the thickness"),
    ("arch_angle_above_180", ARCH.replace("angle = 60.0", "angle = 200.0"), "mesh.angle", "less than or equal to 180"),
    (
        "arch_unknown_face_set",
        ARCH + '\n[[boundaries]]\nfaces = "z-"\nkind = "fixed"\n',
        "boundaries[0].faces",
        "unknown face set 'z-'; the arch mesh has: 'left', 'right', 'downstream', 'upstream', 'base', 'crest'",
    ),
]
BAD_SCENES += CONVERSION_BAD_SCENES


@pytest.mark.parametrize(("text", "key_path", "phrase"), [c[1:] for c in BAD_SCENES], ids=[c[0] for c in BAD_SCENES])
def test_bad_scene_reports_one_line(tmp_path: Path, text: str, key_path: str | None, phrase: str) -> None:
    path = write(tmp_path, text, "bad_scene.toml")
    problems = problems_of(path)
    assert len(problems) == 1, problems
    line = problems[0]
    assert "\n" not in line
    assert line.startswith(f"{path}: ")
    if key_path is not None:
        assert line.startswith(f"{path}: {key_path}: "), line
    assert phrase in line, line


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.toml"
    assert problems_of(path) == [f"{path}: file not found"]


def test_directory(tmp_path: Path) -> None:
    (problem,) = problems_of(tmp_path)
    assert problem.startswith(f"{tmp_path}: ")
    assert "is a directory" in problem


def test_two_independent_errors_give_two_lines(tmp_path: Path) -> None:
    text = edit("density = 2500.0", "density = -1.0")
    text = edit("end_time = 0.1", 'end_time = 0.1\ndevice = "tpu"', base=text)
    path = write(tmp_path, text)
    problems = problems_of(path)
    assert len(problems) == 2, problems
    assert any(p.startswith(f"{path}: materials.rock.density: ") for p in problems)
    assert any(p.startswith(f"{path}: run.device: ") for p in problems)


def test_cross_reference_errors_are_all_reported(tmp_path: Path) -> None:
    text = edit('material = "rock"', 'material = "granite"')
    text = edit('part = "grains"', 'part = "pebbles"', base=text)
    problems = problems_of(write(tmp_path, text))
    assert len(problems) == 2, problems
    assert any("parts.grains.material: unknown material 'granite'" in p for p in problems)
    assert any("particles[0].part: unknown part 'pebbles'" in p for p in problems)


def test_file_source_resolved_against_scene_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    scene_dir = tmp_path / "scenes"
    scene_dir.mkdir()
    (scene_dir / "init.txt").write_text("# x y z\n0 0 0\n")
    text = edit(
        'kind = "sphere"\npart = "grains"\ncenter = [0.0, 0.0, 0.0]',
        'kind = "file"\npart = "grains"\npath = "init.txt"',
    )
    write(scene_dir, text)
    # Load through a relative path from elsewhere: resolution must not depend on the working directory.
    monkeypatch.chdir(tmp_path)
    scene = load_scene(Path("scenes") / "scene.toml")
    source = scene.particles[0]
    assert source.path.is_absolute()
    assert source.path == (scene_dir / "init.txt").resolve()
    assert source.radius == 0.01


def test_parse_scene_from_dict() -> None:
    data = {
        "run": {"end_time": 2.0, "dt": 1e-4},
        "materials": {
            "rock": {"density": 2600.0, "youngs_modulus": 5e9, "poisson_ratio": 0.25},
            "steel": {"density": 7800.0, "youngs_modulus": 2e11, "poisson_ratio": 0.3},
        },
        "interactions": {
            "default": {"friction": 0.6},
            "pairs": [{"materials": ["steel", "rock"], "restitution": 0.9}],
        },
        "parts": {"block": {"material": "rock"}},
        "particles": [
            {"kind": "sphere", "part": "block", "center": np.array([0.0, 0.0, 1.0]), "radius": 0.1},
        ],
        "bonds": [
            {
                "region": {"cylinder": {"center": [0, 0, 0], "radius": 1.0, "height": 2.0}},
                "material": "rock",
                "tensile_strength": 1e6,
                "shear_strength": 2e6,
            }
        ],
        "walls": [{"kind": "plane", "point": [0, 0, 0], "normal": [0, 0, 2.0], "material": "steel"}],
    }
    scene = parse_scene(data)
    assert isinstance(scene, Scene)
    assert scene.name == "scene"
    assert scene.output.usd == "scene.usdc"
    assert scene.particles[0].center == (0.0, 0.0, 1.0)
    assert scene.walls[0].normal == (0.0, 0.0, 1.0)
    assert scene.material_names() == ["rock", "steel"]
    assert scene.material_index("steel") == 1
    assert scene.bond_youngs_modulus(scene.bonds[0]) == 5e9
    # Pair values override the default; the rest come from the default; order of the pair is free.
    pair = scene.interaction_for("rock", "steel")
    assert (pair.friction, pair.restitution, pair.rolling_friction) == (0.6, 0.9, 0.0)
    same = scene.interaction_for("rock", "rock")
    assert (same.friction, same.restitution) == (0.6, 0.5)
    # The caller's data is not modified (the default name is injected into a copy).
    assert "name" not in data

    with pytest.raises(SceneError) as info:
        parse_scene({**data, "run": {"end_time": -1.0}}, source="inline")
    assert info.value.problems == ["inline: run.end_time: Input should be greater than 0 (got -1.0)"]


def test_parse_scene_rejects_non_table() -> None:
    with pytest.raises(SceneError, match="<scene>: a scene must be a table"):
        parse_scene([1, 2, 3])  # type: ignore[arg-type]


def test_box_region_contains_and_bounds() -> None:
    region = Region.model_validate({"box": {"lo": [0.0, 0.0, 0.0], "hi": [2.0, 1.0, 1.0]}})
    points = np.array(
        [
            [1.0, 0.5, 0.5],  # centre: inside
            [2.0, 1.0, 1.0],  # corner: boundary counts as inside
            [2.1, 0.5, 0.5],  # beyond +x
            [1.0, -0.1, 0.5],  # below -y
            [0.0, 0.0, 1.5],  # above +z
        ]
    )
    np.testing.assert_array_equal(region.contains(points), [True, True, False, False, False])
    # Any leading shape, including a single point.
    assert region.contains(points.reshape(5, 1, 3)).shape == (5, 1)
    assert bool(region.contains(np.array([0.5, 0.5, 0.5])))
    lo, hi = region.bounds()
    np.testing.assert_array_equal(lo, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(hi, [2.0, 1.0, 1.0])
    np.testing.assert_allclose(region.volume(), 2.0)


def test_cylinder_region_contains_and_bounds() -> None:
    # Axis x, base disc centred at (1, 0, 0), radius 0.5, height 2: x in [1, 3], y^2 + z^2 <= 0.25.
    region = Region.model_validate({"cylinder": {"center": [1.0, 0.0, 0.0], "radius": 0.5, "height": 2.0, "axis": "x"}})
    points = np.array(
        [
            [2.0, 0.0, 0.0],  # on the axis: inside
            [1.0, 0.3, 0.4],  # on the base disc rim (0.09 + 0.16 = 0.25): inside
            [3.0, 0.0, 0.0],  # top disc centre: inside
            [0.9, 0.0, 0.0],  # below the base
            [3.1, 0.0, 0.0],  # above the top
            [2.0, 0.4, 0.4],  # radial distance^2 = 0.32 > 0.25
            [2.0, 0.0, -0.49],  # just inside radially
        ]
    )
    np.testing.assert_array_equal(region.contains(points), [True, True, True, False, False, False, True])
    lo, hi = region.bounds()
    np.testing.assert_array_equal(lo, [1.0, -0.5, -0.5])
    np.testing.assert_array_equal(hi, [3.0, 0.5, 0.5])
    np.testing.assert_allclose(region.volume(), np.pi * 0.25 * 2.0)


def test_cylinder_default_axis_is_z() -> None:
    region = Region.model_validate({"cylinder": {"center": [0.0, 0.0, 1.0], "radius": 1.0, "height": 1.0}})
    np.testing.assert_array_equal(region.contains(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1.5]])), [False, True])
    lo, hi = region.bounds()
    np.testing.assert_array_equal(lo, [-1.0, -1.0, 1.0])
    np.testing.assert_array_equal(hi, [1.0, 1.0, 2.0])


def test_scene_error_text() -> None:
    err = SceneError(["a.toml: run.dt: bad", "a.toml: run.seed: bad"])
    assert err.problems == ["a.toml: run.dt: bad", "a.toml: run.seed: bad"]
    assert str(err) == "a.toml: run.dt: bad\na.toml: run.seed: bad"
    assert SceneError("x.toml: file not found").problems == ["x.toml: file not found"]


def test_every_field_is_documented() -> None:
    # The schema is the user's reference: every field must say what it is (and its unit).
    import importlib
    import pkgutil

    modules = [importlib.import_module(m.name) for m in pkgutil.iter_modules(scene_module.__path__, "warpdem.scene.")]
    models = {
        obj
        for module in modules
        for obj in vars(module).values()
        if isinstance(obj, type) and issubclass(obj, BaseModel) and obj.__module__.startswith("warpdem.scene")
    }
    assert Scene in models and len(modules) > 1
    undocumented = [
        f"{model.__name__}.{name}"
        for model in models
        for name, field in model.model_fields.items()
        if not field.description
    ]
    assert undocumented == []


def test_default_scene_path() -> None:
    # The scene shipped in the package's data folder (pyproject.toml's package-data), next to the bench's cases.
    import warpdem

    assert default_scene_path() == Path(warpdem.__file__).parent / "data" / "default.toml"
    assert default_scene_path().is_file()


def test_default_scene_loads() -> None:
    assert isinstance(load_scene(default_scene_path()), Scene)


def test_import_does_not_load_warp() -> None:
    # Scene checks and `--help` must stay fast: warp initialisation takes seconds.
    code = "import sys, warpdem.scene; print('warp' in sys.modules)"
    repo_root = Path(__file__).resolve().parents[1]
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=repo_root)
    assert result.stdout.strip() == "False"


def test_continuum_scene_defaults_and_values(tmp_path: Path) -> None:
    scene = load_scene(write(tmp_path, MESH_BASE, "column.toml"))
    rock = scene.materials["rock"]
    assert (rock.tensile_strength, rock.fracture_energy, rock.tresca_strength) == (None, None, None)
    assert (rock.bulk_viscosity_linear, rock.bulk_viscosity_quadratic, rock.mass_damping) == (0.06, 1.2, 0.0)
    mesh = scene.mesh
    assert mesh is not None and mesh.kind == "box"
    assert mesh.divisions == (2, 2, 8) and mesh.fixed is False and mesh.velocity == (0.0, 0.0, 0.0)
    (load,) = scene.loads
    assert load.kind == "pressure" and load.faces == "z+" and load.region is None
    assert (load.history.kind, load.history.peak, load.history.start) == ("blast", 1e6, 0.0)
    (boundary,) = scene.boundaries
    assert (boundary.faces, boundary.kind, boundary.normal) == ("z-", "non_reflecting", None)
    assert scene.face_set_names() == ["x-", "x+", "y-", "y+", "z-", "z+"]
    assert scene.joints.friction == 0.6 and scene.joints.cohesion == 0.0
    assert scene.output.vtu is False and scene.output.mesh_color_by == "stress"
    assert scene.capacity.nodes is None and scene.capacity.tets is None
    assert scene.particles == []


def test_geology_scene_values(tmp_path: Path) -> None:
    text = GEOLOGY_BASE.replace(
        "h = 2.0\n", 'h = 2.0\nh_opening = 0.8\nlayers = [{ z_top = 4.0, material = "rock" }]\n'
    )
    text += '\n[[mesh.joint_sets]]\nname = "bedding"\ndip = 0.0\ndip_direction = 0.0\nspacing = 2.0\n'
    text += 'persistence = "layers"\nreference = 0\nlayers = 2\nphase = 1\nfriction = 0.4\n'
    text += '\n[[loads]]\nkind = "airblast"\nfaces = "z+"\npeak = 2e5\npositive_duration = 5e-3\n'
    text += "source = [5.0, 5.0, 12.0]\nfront_speed = 500.0\n"
    text += '\n[[loads]]\nkind = "velocity"\nregion = { box = { lo = [0, 0, 0], hi = [10, 10, 0.1] } }\n'
    text += "velocity = [0.0, 0.0, 1.0]\nend = 0.001\n"
    text += '\n[[boundaries]]\nfaces = "opening"\nkind = "fixed"\n'
    text += '\n[[boundaries]]\nfaces = "x-"\nkind = "roller"\nnormal = [-1.0, 0.0, 0.0]\n'
    scene = load_scene(write(tmp_path, text))
    mesh = scene.mesh
    assert mesh is not None and mesh.kind == "geology"
    assert mesh.h_opening == 0.8 and mesh.layers[0].z_top == 4.0 and mesh.seed is None
    tunnel = mesh.openings[0]
    assert (tunnel.kind, tunnel.axis, tunnel.center, tunnel.shape, tunnel.radius) == (
        "tunnel",
        "y",
        (5.0, 4.0),
        "circular",
        1.5,
    )
    first, bedding = mesh.joint_sets
    assert first.name is None and first.persistence == "persistent" and first.friction is None
    assert (bedding.name, bedding.reference, bedding.layers, bedding.phase, bedding.friction) == (
        "bedding",
        0,
        2,
        1,
        0.4,
    )
    airblast, velocity = scene.loads
    assert (airblast.kind, airblast.decay_coefficient, airblast.t0) == ("airblast", 1.0, 0.0)
    assert velocity.kind == "velocity" and velocity.region is not None and velocity.end == 0.001
    assert [b.kind for b in scene.boundaries] == ["fixed", "roller"]
    assert scene.face_set_names() == ["x-", "x+", "y-", "y+", "z-", "z+", "opening"]


def test_file_mesh_path_resolved_against_scene_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    scene_dir = tmp_path / "scenes"
    scene_dir.mkdir()
    (scene_dir / "rock.msh").write_text("")
    write(scene_dir, MINIMAL + '\n[mesh]\nkind = "file"\npath = "rock.msh"\nmaterial_map = { 1 = "rock" }\n')
    monkeypatch.chdir(tmp_path)
    scene = load_scene(Path("scenes") / "scene.toml")
    assert scene.mesh is not None and scene.mesh.kind == "file"
    assert scene.mesh.path == (scene_dir / "rock.msh").resolve()
    assert scene.mesh.material_map == {"1": "rock"}
    assert scene.face_set_names() is None  # a file's face sets are known when it is read


def test_fracture_keys_default_off(tmp_path: Path) -> None:
    scene = load_scene(write(tmp_path, MESH_BASE, "column.toml"))
    assert scene.materials["rock"].cohesive_alpha == 1.0
    fracture = scene.fracture
    assert (fracture.enabled, fracture.check_interval, fracture.region, fracture.cohesive_capacity) == (
        False,
        1,
        None,
        None,
    )
    assert fracture.seed_cracks == []
    assert scene.output.cohesive_as_curves is False


def test_fracture_keys_values(tmp_path: Path) -> None:
    text = edit("fracture_energy = 100.0", "fracture_energy = 100.0\ncohesive_alpha = 0.5", base=FRACTURE_ON)
    text += "check_interval = 5\ncohesive_capacity = 128\nregion = { box = { lo = [0, 0, 1], hi = [1, 1, 3] } }\n"
    text += "\n" + SEED + "friction = 0.3\n\n[output]\ncohesive_as_curves = true\n"
    scene = load_scene(write(tmp_path, text))
    assert scene.materials["rock"].cohesive_alpha == 0.5
    fracture = scene.fracture
    assert (fracture.enabled, fracture.check_interval, fracture.cohesive_capacity) == (True, 5, 128)
    assert fracture.region is not None and fracture.region.box.hi == (1.0, 1.0, 3.0)
    (crack,) = fracture.seed_cracks
    assert crack.point == (0.5, 0.5, 2.0) and crack.normal == (0.0, 0.0, 1.0) and crack.friction == 0.3
    assert scene.output.cohesive_as_curves is True


def test_solid_mesh_kinds(tmp_path: Path) -> None:
    text = MINIMAL + (
        '\n[mesh]\nkind = "cylinder"\ncenter = [0, -0.01, 0]\naxis = "y"\nradius = 0.05\nheight = 0.02\n'
        'h = 0.01\nmaterial = "rock"\n'
    )
    scene = load_scene(write(tmp_path, text))
    mesh = scene.mesh
    assert mesh is not None and mesh.kind == "cylinder" and mesh.axis == "y" and mesh.fixed is False
    assert scene.face_set_names() == ["surface"]
    text = MINIMAL + '\n[mesh]\nkind = "ellipsoid"\ncenter = [0, 0, 1]\nradii = [1.0, 0.8, 0.6]\nh = 0.3\n'
    text += 'material = "rock"\n'
    mesh = load_scene(write(tmp_path, text)).mesh
    assert mesh is not None and mesh.kind == "ellipsoid" and mesh.radii == (1.0, 0.8, 0.6)


def test_seed_crack_faces_on_a_box_mesh(tmp_path: Path) -> None:
    """A Kuhn box mesh cuts every cell face of a grid plane into two triangles, so a seed crack on an interior grid
    plane whose region holds an a × b patch of cells cracks exactly 2 a b faces (exact: the grid nodes lie on the
    plane to round-off, SEED_PLANE_TOLERANCE is 1e-9 of the diagonal)."""
    from warpdem.build.mesh import box_mesh
    from warpdem.build.scene_mesh import seed_crack_faces

    # Cells of 0.5 x 0.5 x 0.5 m; the plane z = 2 is interior; the region holds x in [0, 0.5], y in [0, 1].
    scene = load_scene(write(tmp_path, FRACTURING + "\n" + SEED))
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 4.0), (2, 2, 8))
    (crack,) = scene.fracture.seed_cracks
    faces = seed_crack_faces(points, tets, crack, "scene: fracture.seed_cracks[0]")
    cells_x, cells_y = 1, 2
    assert faces.shape == (2 * cells_x * cells_y, 3)
    assert np.all(np.abs(points[faces][..., 2] - 2.0) <= 1e-12)
    assert np.all(points[faces][..., 0] <= 0.5)
    # Each face is shared by two tets (an interior face).
    all_faces = np.sort(tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    for face in faces:
        assert np.count_nonzero(np.all(all_faces == np.sort(face), axis=1)) == 2

    # A plane off the grid (z = 2.1) holds no mesh face: a SceneError naming the crack's region.
    off = crack.model_copy(update={"point": (0.5, 0.5, 2.1)})
    with pytest.raises(SceneError, match=r"fracture.seed_cracks\[0\].region: no interior face"):
        seed_crack_faces(points, tets, off, "scene: fracture.seed_cracks[0]")


def test_conversion_keys_default_off(tmp_path: Path) -> None:
    scene = load_scene(write(tmp_path, MESH_BASE, "column.toml"))
    rock = scene.materials["rock"]
    assert (rock.cohesion, rock.friction_angle) == (None, 30.0)
    c = scene.conversion
    assert (c.enabled, c.criterion, c.fraction, c.check_interval, c.spheres_per_tet, c.part) == (
        False,
        "tresca",
        0.9,
        1,
        1,
        "converted",
    )
    assert (c.region, c.start_as_spheres) == (None, None)
    assert scene.run.resolution == 1.0 and scene.material_regions == []
    assert scene.scaled_mesh() is scene.mesh  # resolution 1: the mesh as written


def test_conversion_keys_values(tmp_path: Path) -> None:
    text = edit("tresca_strength = 1e7", "tresca_strength = 1e7\ncohesion = 5e6\nfriction_angle = 35.0", CONVERSION_ON)
    text += (
        'criterion = "mohr_coulomb"\nfraction = 0.8\ncheck_interval = 10\nspheres_per_tet = 4\npart = "debris"\n'
        "region = { box = { lo = [0, 0, 1], hi = [1, 1, 3] } }\n"
        "start_as_spheres = { cylinder = { center = [0.5, 0.5, 3.0], radius = 0.3, height = 1.0 } }\n"
    )
    scene = load_scene(write(tmp_path, text))
    rock = scene.materials["rock"]
    assert (rock.tresca_strength, rock.cohesion, rock.friction_angle) == (1e7, 5e6, 35.0)
    c = scene.conversion
    assert (c.enabled, c.criterion, c.fraction, c.check_interval, c.part) == (True, "mohr_coulomb", 0.8, 10, "debris")
    assert c.spheres_per_tet == 4
    assert c.region is not None and c.region.box.hi == (1.0, 1.0, 3.0)
    assert c.start_as_spheres is not None and c.start_as_spheres.cylinder.radius == 0.3


def test_resolution_scales_the_mesh(tmp_path: Path) -> None:
    """run.resolution k: box and arch divisions × k (rounded, at least 1), Gmsh edge lengths h / k; the size estimate
    grows with it (6 tets per cell: k³ as many)."""
    scene = load_scene(write(tmp_path, edit("end_time = 0.01", "end_time = 0.01\nresolution = 2.5", MESH_BASE)))
    assert scene.scaled_mesh().divisions == (5, 5, 20)  # (2, 2, 8) × 2.5
    assert scene.mesh.divisions == (2, 2, 8)  # the scene itself is unchanged
    coarse = load_scene(write(tmp_path, edit("end_time = 0.01", "end_time = 0.01\nresolution = 0.1", MESH_BASE)))
    assert coarse.scaled_mesh().divisions == (1, 1, 1)
    text = MINIMAL.replace("end_time = 0.1", "end_time = 0.1\nresolution = 2.0") + (
        '\n[mesh]\nkind = "cylinder"\ncenter = [0, 0, 0]\nradius = 0.05\nheight = 0.02\nh = 0.01\nmaterial = "rock"\n'
    )
    assert load_scene(write(tmp_path, text)).scaled_mesh().h == 0.005
    arch = load_scene(write(tmp_path, ARCH.replace("end_time = 0.1", "end_time = 0.1\nresolution = 2.0")))
    assert arch.scaled_mesh().divisions == (12, 4, 8)
    assert arch.face_set_names() == ["left", "right", "downstream", "upstream", "base", "crest"]
    boxed = GEOLOGY_BASE.replace("end_time = 0.01", "end_time = 0.01\nresolution = 2.0").replace(
        "h = 2.0\n", "h = 2.0\nrefinements = [{ lo = [0, 0, 0], hi = [10, 10, 5], h = 1.0 }]\n"
    )
    geology = load_scene(write(tmp_path, boxed))
    assert geology.scaled_mesh().h == 1.0 and [r.h for r in geology.scaled_mesh().refinements] == [0.5]
    assert geology.mesh.refinements[0].h == 1.0
