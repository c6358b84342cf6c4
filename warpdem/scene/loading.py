"""Loading a scene file or mapping into a :class:`Scene`, and turning pydantic's errors into one readable line each."""

from __future__ import annotations

import math
import os
import re
import sys
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ValidationError,
)

from .document import Scene
from .fields import (
    _BARE_KEY,
    _MAX_GOT_CHARS,
    _PLAIN_MESSAGES,
    INT64_MAX,
    INT64_MIN,
    MAX_NESTING,
    RESERVED_SECTIONS,
    SCHEMA_VERSION,
    SceneError,
    _format_key,
)
from .particles import FileSource

# ----------------------------------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------------------------------


def default_scene_path() -> Path:
    """Path of the scene shipped with the package (``warpdem/data/default.toml``)."""
    return Path(__file__).parent.parent / "data" / "default.toml"


def load_scene(path: str | os.PathLike[str]) -> Scene:
    """Reads and validates a TOML scene file.

    Relative particle file paths are resolved against the scene file's directory.

    Args:
        path: Scene file.

    Returns:
        The validated scene; ``FileSource.path`` values are absolute.

    Raises:
        SceneError: The file is missing, unreadable, not TOML, or not a valid scene; lists every problem.
    """
    path = Path(path)
    source = str(path)
    if not path.exists():
        raise SceneError(f"{source}: file not found")
    if path.is_dir():
        raise SceneError(f"{source}: is a directory, expected a TOML scene file")
    try:
        with path.open("rb") as f:
            text = f.read().decode("utf-8")
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SceneError(f"{source}: invalid TOML: {err}") from None
    except UnicodeDecodeError as err:
        raise SceneError(f"{source}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    except OSError as err:
        raise SceneError(f"{source}: cannot read: {err.strerror or err}") from None
    except RecursionError:
        # tomllib recurses once per level of nested arrays and inline tables and gives up at about 490.
        line, key = _deepest_value(text)
        raise SceneError(
            f"{source}: line {line}: {key}: arrays and inline tables nested too deeply to read; allowed: at most "
            f"{MAX_NESTING} levels"
        ) from None
    except ValueError as err:
        # Python refuses to read an integer of more than sys.get_int_max_str_digits() digits (4300).
        line, key, digits = _longest_integer(text)
        if not digits:
            raise SceneError(f"{source}: invalid TOML: {' '.join(str(err).split())}") from None
        raise SceneError(
            f"{source}: line {line}: {key}: an integer of {digits} digits; allowed: integers from {INT64_MIN} to "
            f"{INT64_MAX} (64 bits)"
        ) from None
    return _parse(data, source, path.resolve().parent, default_name=path.stem or "scene")


def _key_on(line: str, table: str) -> str:
    """The key a TOML line assigns (its text before ``=``), under the table header in force; ``?`` for none."""
    key = line.split("=", 1)[0].strip() if "=" in line else ""
    return ".".join(part for part in (table, key) if part) or "?"


_LONG_INTEGER = re.compile(r"[+-]?[0-9][0-9_]*")
_TABLE_HEADER = re.compile(r"\s*\[\[?\s*([^\]]*?)\s*\]\]?\s*(#.*)?$")


def _longest_integer(text: str) -> tuple[int, str, int]:
    """(line number, key, digits) of the integer with the most digits in a TOML text, for the message about an
    integer too long to read; digits 0 when none is longer than Python reads."""
    limit = sys.get_int_max_str_digits()
    table, best = "", (0, "?", 0)
    for number, line in enumerate(text.splitlines(), start=1):
        header = _TABLE_HEADER.match(line)
        if header:
            table = header.group(1)
            continue
        for match in _LONG_INTEGER.finditer(line):
            digits = sum(c.isdigit() for c in match.group())
            if limit and digits > limit and digits > best[2]:
                best = (number, _key_on(line, table), digits)
    return best


def _line_end(text: str, i: int) -> int:
    """Index of the newline that ends the line holding ``text[i]`` (the text's length on the last line)."""
    end = text.find("\n", i)
    return len(text) if end < 0 else end


def _deepest_value(text: str) -> tuple[int, str]:
    """(line number, key) where the nesting of arrays and inline tables of a TOML text first exceeds MAX_NESTING,
    counting brackets outside strings and comments; table headers set the table of the keys after them."""
    table, key, depth, number, line_start, i = "", "?", 0, 1, 0, 0
    while i < len(text):
        c = text[i]
        if c == "\n":
            number, line_start = number + 1, i + 1
        elif c == "#":
            i = _line_end(text, i)
            continue
        elif c in "\"'":
            quote = text[i : i + 3] if text[i : i + 3] in ('"""', "'''") else c
            j = i + len(quote)
            while j < len(text) and not text.startswith(quote, j):
                j += 2 if c == '"' and text[j] == "\\" else 1
            number += text.count("\n", i, j)
            i = j + len(quote)
            continue
        elif c == "[" and depth == 0 and not text[line_start:i].strip():
            end = _line_end(text, i)
            header = _TABLE_HEADER.match(text[line_start:end])
            table = header.group(1) if header else table
            i = end
            continue
        elif c in "[{":
            if depth == 0:
                key = _key_on(text[line_start:i], table)
            depth += 1
            if depth > MAX_NESTING:
                return number, key
        elif c in "]}":
            depth = max(depth - 1, 0)
        i += 1
    return number, key


def parse_scene(data: Mapping[str, Any], source: str = "<scene>", base_dir: Path | None = None) -> Scene:
    """Validates a scene given as a dict (the structure of the TOML file).

    Args:
        data: Scene tables and values, SI units.
        source: Name used at the start of every problem line.
        base_dir: Directory that relative particle file paths are resolved against; the current working
            directory when None.

    Returns:
        The validated scene.

    Raises:
        SceneError: Lists every problem, one line each.
    """
    default_name = "scene" if source.startswith("<") else (Path(source).stem or "scene")
    return _parse(data, source, base_dir, default_name=default_name)


def _parse(data: Any, source: str, base_dir: Path | None, default_name: str) -> Scene:
    if not isinstance(data, Mapping):
        raise SceneError(f"{source}: a scene must be a table (dict), got {type(data).__name__}")
    deep = _too_deep(data)
    if deep is not None:
        # Before pydantic, whose validation and messages recurse once per level too.
        raise SceneError(
            f"{source}: {_format_path(deep)}...: tables and arrays nested more than {MAX_NESTING} levels deep; "
            f"allowed: at most {MAX_NESTING}"
        )
    try:
        scene = Scene.model_validate(data, context={"default_name": default_name})
    except ValidationError as err:
        raise SceneError(_format_validation_error(err, source)) from None
    if not source.startswith("<"):
        scene._source = source
    problems = [f"{source}: {path}: {message}" for path, message in scene.reference_problems()]
    if not problems:
        # Sizes only of a scene whose references hold: the estimate reads the sources' parts and materials.
        problems = [f"{source}: {path}: {message}" for path, message in scene.size_problems()]
    problems += _resolve_files(scene, source, base_dir if base_dir is not None else Path.cwd())
    if problems:
        raise SceneError(problems)
    return scene


def _too_deep(data: Mapping[str, Any]) -> list[str | int] | None:
    """Key path of the first value nested more than MAX_NESTING tables and arrays deep (cut after the first few
    keys), or None. Walks without recursion, so any depth is measured."""
    stack: list[tuple[Any, list[str | int]]] = [(data, [])]
    while stack:
        value, path = stack.pop()
        if len(path) > MAX_NESTING:
            return path[:4]
        if isinstance(value, Mapping):
            stack += [(v, [*path, str(k)]) for k, v in value.items()]
        elif isinstance(value, list | tuple):
            stack += [(v, [*path, i]) for i, v in enumerate(value)]
    return None


def _resolve_files(scene: Scene, source: str, base_dir: Path) -> list[str]:
    problems = []
    if scene.mesh is not None and scene.mesh.kind == "file":
        resolved = scene.mesh.path.expanduser()
        if not resolved.is_absolute():
            resolved = base_dir / resolved
        if not resolved.exists():
            problems.append(f"{source}: mesh.path: file not found: {resolved}")
        elif not resolved.is_file():
            problems.append(f"{source}: mesh.path: not a regular file: {resolved}")
        scene.mesh.path = resolved
    for i, particle_source in enumerate(scene.particles):
        if not isinstance(particle_source, FileSource):
            continue
        resolved = particle_source.path.expanduser()
        if not resolved.is_absolute():
            resolved = base_dir / resolved
        if not resolved.exists():
            problems.append(f"{source}: particles[{i}].path: file not found: {resolved}")
        elif not resolved.is_file():
            problems.append(f"{source}: particles[{i}].path: not a regular file: {resolved}")
        particle_source.path = resolved
    return problems


# ----------------------------------------------------------------------------------------------------------------------
# Validation error formatting
# ----------------------------------------------------------------------------------------------------------------------


def _format_path(path: list[str | int]) -> str:
    text = ""
    for part in path:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += ("." if text else "") + _format_key(part)
    return text


def _unwrap(tp: Any) -> Any:
    """Strips Annotated and Optional wrappers from a type annotation."""
    while True:
        origin = typing.get_origin(tp)
        if origin is Annotated:
            tp = typing.get_args(tp)[0]
        elif origin in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) != 1:
                return tp
            tp = args[0]
        else:
            return tp


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _union_members(tp: Any) -> list[type[BaseModel]]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return [a for a in typing.get_args(tp) if _is_model(a)]
    return []


def _tags(members: list[type[BaseModel]], discriminator: str = "kind") -> list[str]:
    tags = []
    for member in members:
        field = member.model_fields.get(discriminator)
        if field is not None:
            tags += [str(v) for v in typing.get_args(_unwrap(field.annotation))]
    return tags


def _walk(loc: tuple[str | int, ...]) -> tuple[list[str | int], Any, Any]:
    """Follows a pydantic error location through the Scene type tree.

    Returns:
        The user-facing key path (union tags and validator labels removed), the annotation at the end of the
        path and the annotation of its parent (None where unknown).
    """
    path: list[str | int] = []
    tp: Any = Scene
    parent: Any = None
    for part in loc:
        tp = _unwrap(tp)
        members = _union_members(tp)
        if members:
            # pydantic inserts the tag of a discriminated union member into the location; the user never wrote it.
            chosen = [m for m in members if str(part) in _tags([m])]
            tp = chosen[0] if chosen else None
            continue
        if part == "[key]":  # dict key validation label: the key is already in the path
            continue
        parent = tp
        if isinstance(part, int):
            path.append(part)
            origin = typing.get_origin(tp)
            args = typing.get_args(tp)
            if origin is list and args:
                tp = args[0]
            elif origin is tuple and args:
                tp = args[0] if args[-1] is Ellipsis else (args[part] if part < len(args) else None)
            else:
                tp = None
        elif _is_model(tp):
            path.append(part)
            field = tp.model_fields.get(part)
            tp = field.annotation if field is not None else None
        elif typing.get_origin(tp) is dict:
            path.append(part)
            tp = typing.get_args(tp)[1]
        elif tp is None and _BARE_KEY.fullmatch(part):
            path.append(part)
        # Otherwise a validator label such as "function-after[...]": not part of the user's key path.
    return path, _unwrap(tp) if tp is not None else None, parent


def _got(value: Any) -> str:
    if isinstance(value, int) and value.bit_length() > 200:
        # repr of an integer past sys.get_int_max_str_digits() raises; its size is what the user needs to see.
        return f" (got an integer of {math.floor(value.bit_length() * math.log10(2)) + 1} digits)"
    text = repr(value)
    if len(text) > _MAX_GOT_CHARS:
        text = text[: _MAX_GOT_CHARS - 3] + "..."
    return f" (got {text})"


def _format_error(error: Mapping[str, Any]) -> tuple[str, str]:
    """One pydantic error as ``(key path, message)``."""
    kind = error["type"]
    loc = tuple(error["loc"])
    ctx = error.get("ctx") or {}
    value = error.get("input")
    path, tp, parent = _walk(loc)

    if kind == "extra_forbidden":
        if len(path) == 1 and path[0] in RESERVED_SECTIONS:
            return _format_path(path), (
                f"section not supported by this version of warpdem (schema_version {SCHEMA_VERSION}) yet"
            )
        allowed = ", ".join(parent.model_fields) if _is_model(parent) else "see the documentation"
        return _format_path(path), f"unknown key; allowed keys: {allowed}"
    if kind == "missing":
        if path and isinstance(path[-1], int):
            expected = len(typing.get_args(parent)) if typing.get_origin(parent) is tuple else "more"
            return _format_path(path[:-1]), f"too few values; expected {expected}{_got(value)}"
        return _format_path(path), "required key is missing"
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        discriminator = str(ctx.get("discriminator", "kind")).strip("'")
        allowed = ", ".join(repr(t) for t in _tags(_union_members(tp), discriminator))
        path = [*path, discriminator]
        if kind == "union_tag_not_found":
            return _format_path(path), f"required key is missing; allowed: {allowed}"
        return _format_path(path), f"unknown value {ctx.get('tag')!r}; allowed: {allowed}"
    if kind == "literal_error":
        values = typing.get_args(tp) if typing.get_origin(tp) is Literal else ()
        allowed = ", ".join(repr(v) for v in values) if values else str(ctx.get("expected", ""))
        return _format_path(path), f"unknown value {value!r}; allowed: {allowed}"

    message = _PLAIN_MESSAGES.get(kind) or str(error["msg"])
    for prefix in ("Value error, ", "Assertion failed, "):
        message = message.removeprefix(prefix)
    # A whole table as 'got' is noise; the message of a table-level check already says what is wrong.
    if not isinstance(value, Mapping):
        message += _got(value)
    return _format_path(path), message


def _format_validation_error(err: ValidationError, source: str) -> list[str]:
    errors = err.errors(include_url=False)
    # A file written for another schema version produces errors everywhere; only the version matters then.
    version_errors = [e for e in errors if tuple(e["loc"]) == ("schema_version",)]
    if version_errors:
        errors = version_errors
    lines: list[str] = []
    for error in errors:
        path, message = _format_error(error)
        line = f"{source}: {path}: {message}" if path else f"{source}: {message}"
        if line not in lines:
            lines.append(line)
    return lines
