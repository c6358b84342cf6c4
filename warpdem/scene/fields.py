"""The scene schema's shared pieces: limits on names and sizes, the one error type, the strict scalar and vector
field types and the base model (unknown keys are errors)."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    AllowInfNan,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Strict,
)

from ..limits import (
    BYTES_PER_NEIGHBOR_SLOT,
    BYTES_PER_NODE,
    BYTES_PER_SPHERE,
    BYTES_PER_TET,
    F32_MAX,
    F32_MIN,
)

SCHEMA_VERSION = 1
"""The only scene schema version this release reads."""

RESERVED_SECTIONS = ("tets",)
"""Top-level sections planned for later schema versions; named explicitly so users are not told 'unknown key'."""

_NAME_PATTERN = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*")
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_DEVICE_PATTERN = re.compile(r"cpu|cuda(:\d+)?")
_USD_SUFFIXES = (".usd", ".usda", ".usdc")
_MAX_GOT_CHARS = 80
MAX_FILE_NAME_BYTES = 200
"""Longest file or folder name a scene may give (file systems allow 255 bytes; the writers add suffixes such as
``.partial.usdc``)."""
MAX_GRAVITY = 1e6
"""Largest gravity magnitude a scene may give [m/s²] (about 1e5 g)."""
MAX_JOINT_SURFACES = 5000
"""Most joint planes and discs a geology mesh may be fragmented by (Gmsh's boolean fragment grows faster than
linearly in their number)."""
MAX_NESTING = 32
"""Deepest nesting of tables and arrays a scene may have (the schema's deepest is a handful: a table of a list entry
of a table); far deeper input (thousands of levels) would exhaust Python's recursion limit in the parser."""
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1
"""The integers a scene may give: those of 64 bits, as numpy and the device hold them."""
_LATTICE_FRACTION = {"hcp": math.pi / (3.0 * math.sqrt(2.0)), "cubic": math.pi / 6.0}
_BYTES_EACH = {
    "spheres": BYTES_PER_SPHERE,
    "neighbor slots": BYTES_PER_NEIGHBOR_SLOT,
    "nodes": BYTES_PER_NODE,
    "tets": BYTES_PER_TET,
}


def _regular_tet_volume(edge: float) -> float:
    """Volume of a regular tetrahedron of edge ``edge`` [m³]: edge³ / (6√2)."""
    return edge**3 / (6.0 * math.sqrt(2.0))


# pydantic messages that speak Python where the user wrote TOML.
_PLAIN_MESSAGES = {
    "model_type": "must be a table",
    "model_attributes_type": "must be a table",
    "dict_type": "must be a table",
    "list_type": "must be an array",
    "tuple_type": "must be an array",
}


class SceneError(Exception):
    """A scene could not be loaded; carries one readable line per problem.

    Attributes:
        problems: One line per problem, ``<file>: <key.path>: <message>``.
    """

    def __init__(self, problems: list[str] | str) -> None:
        self.problems: list[str] = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(self.problems))

    def __str__(self) -> str:
        return "\n".join(self.problems)


# ----------------------------------------------------------------------------------------------------------------------
# Scalar and vector types
# ----------------------------------------------------------------------------------------------------------------------


def _check_float32(value: float) -> float:
    # The device computes in float32: a number it would turn into inf or 0 is refused here, naming the key, rather
    # than becoming NaN in the first frame (warpdem.limits).
    if value != 0.0 and not F32_MIN <= abs(value) <= F32_MAX:
        raise ValueError(
            f"must be 0 or between {F32_MIN:g} and {F32_MAX:g} in magnitude (the device computes in float32)"
        )
    return value


# Strict so that a quoted number ("1.0") or a boolean is reported instead of being silently converted;
# ints are still accepted for floats because TOML writers often drop the ".0". Every float of a scene lies in the
# range float32 represents (warpdem.limits.F32_MIN .. F32_MAX).
Float = Annotated[float, Strict(), AllowInfNan(False), AfterValidator(_check_float32)]


def _check_int64(value: int) -> int:
    # Every integer of a scene becomes a numpy or device integer (a count, an index, a seed): one beyond 64 bits would
    # fail there, after the set-up, rather than here naming the key.
    if not INT64_MIN <= value <= INT64_MAX:
        raise ValueError(f"must be an integer from {INT64_MIN} to {INT64_MAX} (64 bits)")
    return value


Int = Annotated[int, Strict(), AfterValidator(_check_int64)]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]


def _array_to_list(value: Any) -> Any:
    # Python users pass numpy vectors; TOML gives lists. Both must validate as the same tuple.
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


Vec3 = Annotated[tuple[Float, Float, Float], BeforeValidator(_array_to_list)]
"""Three finite floats; accepts a list, tuple or numpy array of length 3."""


def _check_name(value: str) -> str:
    if not _NAME_PATTERN.fullmatch(value):
        raise ValueError("invalid name; names start with a letter or '_' and contain only letters, digits, '_' and '-'")
    return value


def _check_path_text(value: Any) -> Any:
    # A file or folder name the operating system cannot take is refused here, naming the key, rather than failing
    # as an OSError when the first output file is opened after minutes of set-up.
    if isinstance(value, str | Path):
        text = str(value)
        if not text:
            raise ValueError("must not be empty")
        if any(ord(c) < 32 or ord(c) == 127 for c in text):
            raise ValueError("must not contain control characters (NUL, newline, ...)")
        longest = max((len(part.encode("utf-8", "surrogateescape")) for part in re.split(r"[/\\]", text)), default=0)
        if longest > MAX_FILE_NAME_BYTES:
            raise ValueError(f"a file or folder name is {longest} bytes long; allowed: at most {MAX_FILE_NAME_BYTES}")
    return value


PathText = Annotated[str, Strict(), AfterValidator(_check_path_text)]
"""A string that names a file or folder: no control characters, no name longer than MAX_FILE_NAME_BYTES."""

FilePath = Annotated[Path, BeforeValidator(_check_path_text)]
"""A path to an input file, checked like :data:`PathText`."""

Name = Annotated[str, Strict(), AfterValidator(_check_name)]
"""A material or part name: ``[A-Za-z_][A-Za-z0-9_-]*``."""


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _auto_or_positive(value: Any) -> Literal["auto"] | float:
    # Hand-written instead of a Literal | float union: a union reports one error per branch, and the
    # user should see a single line.
    if value == "auto":
        return "auto"
    if _is_number(value) and value > 0:
        return _check_float32(float(value))
    raise ValueError("must be 'auto' or a number > 0")


def _auto_or_non_negative(value: Any) -> Literal["auto"] | float:
    if value == "auto":
        return "auto"
    if _is_number(value) and value >= 0:
        return _check_float32(float(value))
    raise ValueError("must be 'auto' or a number >= 0")


AutoOrPositive = Annotated[Literal["auto"] | float, BeforeValidator(_auto_or_positive)]
AutoOrNonNegative = Annotated[Literal["auto"] | float, BeforeValidator(_auto_or_non_negative)]


class _Model(BaseModel):
    """Base of all scene models: unknown keys are errors, because a misspelt key silently ignored is a wrong run."""

    model_config = ConfigDict(extra="forbid")


def _format_key(key: str) -> str:
    # TOML quoting, so a path with odd characters can still be found in the file.
    return key if _BARE_KEY.fullmatch(key) else '"' + key.replace("\\", "\\\\").replace('"', '\\"') + '"'
