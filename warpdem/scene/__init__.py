"""Scene files: the validated TOML schema (SI units) that describes one simulation.

A scene file maps onto the pydantic models below (all ``extra="forbid"``). Every problem found while
loading is reported as one line ``<file>: <key.path>: <what is allowed> (got <value>)``, and all
problems of a file are reported together in one :class:`SceneError`, so a user fixes a file in one
pass instead of one error per run.

Loading happens in four passes:

1. TOML parsing (``tomllib``): syntax errors carry line and column.
2. Field validation (pydantic): types, ranges, unknown keys, unknown ``kind`` values.
3. Cross references and files: material / part names used before they are defined, duplicate
   interaction pairs, particle files that do not exist. These run only on a structurally valid scene,
   because they need the validated objects.
4. Sizes (:meth:`Scene.size_problems`): spheres, neighbour slots, nodes, tets and joint surfaces estimated from the
   scene and held against :mod:`warpdem.limits` before anything is packed, meshed or allocated. Every float is also
   held to the range the device's float32 represents (``Float``), so no scene number becomes inf or 0 on the device.

Python users build scenes without files through :func:`parse_scene`, which reports the same errors.
This module is pure host code: it must not import warp, so ``warpdem --help`` and scene checks stay fast.
"""

from __future__ import annotations

from .continuum import (
    ARCH_DAM_FACE_NAMES,
    ARCH_FACE_NAMES,
    ArchDamMesh,
    ArchMesh,
    BoxMesh,
    BrickMeshSpec,
    CylinderMesh,
    EllipsoidMesh,
    FileMesh,
    GeologyMeshSpec,
    JointDefaults,
    JointProperties,
    JointSetSpec,
    Layer,
    Mesh,
    Opening,
    PositiveInt,
    RoomOpening,
    ShaftOpening,
    TunnelOpening,
    Vec2,
)
from .document import Scene
from .failure import CONVERSION_STRENGTH, Conversion, Fracture, MaterialRegion, Rigid, SeedCrack
from .fields import (
    MAX_FILE_NAME_BYTES,
    MAX_GRAVITY,
    MAX_JOINT_SURFACES,
    MAX_NESTING,
    RESERVED_SECTIONS,
    SCHEMA_VERSION,
    AutoOrNonNegative,
    AutoOrPositive,
    Bool,
    FilePath,
    Float,
    Int,
    Name,
    PathText,
    SceneError,
    Str,
    Vec3,
)
from .loading import default_scene_path, load_scene, parse_scene
from .loads import (
    AirblastLoad,
    BlastHistory,
    Boundary,
    FriedlanderHistory,
    Load,
    PressureHistorySpec,
    PressureLoad,
    TableHistory,
    VelocityLoad,
)
from .particles import BondRegion, BoxWall, FileSource, PackingSource, ParticleSource, PlaneWall, SphereSource, Wall
from .regions import Box, Cylinder, Region
from .run import (
    Capacity,
    ContactSettings,
    Gravity,
    InteractionPair,
    InteractionProps,
    Interactions,
    Material,
    Output,
    Part,
    Run,
)

__all__ = [
    "ARCH_DAM_FACE_NAMES",
    "ARCH_FACE_NAMES",
    "CONVERSION_STRENGTH",
    "MAX_FILE_NAME_BYTES",
    "MAX_GRAVITY",
    "MAX_JOINT_SURFACES",
    "MAX_NESTING",
    "RESERVED_SECTIONS",
    "SCHEMA_VERSION",
    "AirblastLoad",
    "ArchDamMesh",
    "ArchMesh",
    "AutoOrNonNegative",
    "AutoOrPositive",
    "BlastHistory",
    "BondRegion",
    "Bool",
    "Boundary",
    "Box",
    "BoxMesh",
    "BoxWall",
    "BrickMeshSpec",
    "Capacity",
    "ContactSettings",
    "Conversion",
    "Cylinder",
    "CylinderMesh",
    "EllipsoidMesh",
    "FileMesh",
    "FilePath",
    "FileSource",
    "Float",
    "Fracture",
    "FriedlanderHistory",
    "GeologyMeshSpec",
    "Gravity",
    "Int",
    "InteractionPair",
    "InteractionProps",
    "Interactions",
    "JointDefaults",
    "JointProperties",
    "JointSetSpec",
    "Layer",
    "Load",
    "Material",
    "MaterialRegion",
    "Mesh",
    "Name",
    "Opening",
    "Output",
    "PackingSource",
    "Part",
    "ParticleSource",
    "PathText",
    "PlaneWall",
    "PositiveInt",
    "PressureHistorySpec",
    "PressureLoad",
    "Region",
    "Rigid",
    "RoomOpening",
    "Run",
    "Scene",
    "SceneError",
    "SeedCrack",
    "ShaftOpening",
    "SphereSource",
    "Str",
    "TableHistory",
    "TunnelOpening",
    "Vec2",
    "Vec3",
    "VelocityLoad",
    "Wall",
    "default_scene_path",
    "load_scene",
    "parse_scene",
]
