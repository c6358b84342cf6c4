"""The user reference in docs/ keeps up with the code it describes.

Oracles, read from the code rather than from a list kept by hand:
- docs/scene-files.md names every key of the scene schema: every field of every pydantic model reachable from
  :class:`warpdem.scene.Scene` appears as a word inside a code span of the page (`` `key` ``, `` `box.lo` ``,
  `` `lo`, `hi` ``) or, for a section, as the TOML table of a heading (``## [run]``), so a key added to
  warpdem/scene/ without its line in the reference fails here;
- docs/cli.md names every option of every ``python -m warpdem`` parser (the run, the five benchmarks, plot and
  preview), read from the argparse parsers of warpdem/cli.py.

The site's links, anchors and docstrings are checked by ``mkdocs build --strict`` in .ci/run, not here.
"""

from __future__ import annotations

import re
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from warpdem import cli
from warpdem.scene import Scene

DOCS = Path(__file__).resolve().parent.parent / "docs"


def _code_words(page: Path) -> set[str]:
    """The words (``[A-Za-z_][A-Za-z0-9_-]*``, with ``-`` for options) inside the page's inline code spans, and the
    TOML table names of its headings (``## [run]``, ``### [[loads]]``, ``## [materials.NAME]``)."""
    text = page.read_text(encoding="utf-8")
    spans = re.findall(r"`([^`\n]+)`", text)
    spans += re.findall(r"^#+ .*?\[\[?([A-Za-z_]+)", text, flags=re.MULTILINE)
    return {w for span in spans for w in re.findall(r"-{0,2}[A-Za-z_][A-Za-z0-9_-]*", span)}


def _models(annotation: object) -> list[type[BaseModel]]:
    """The pydantic models an annotation refers to (through unions, lists, dicts, tuples and Annotated)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models(arg)]


def _schema_keys() -> dict[str, set[str]]:
    """Every model reachable from Scene, by name, with its field names."""
    keys: dict[str, set[str]] = {}
    todo = [Scene]
    while todo:
        model = todo.pop()
        if model.__name__ in keys:
            continue
        keys[model.__name__] = set(model.model_fields)
        for info in model.model_fields.values():
            todo += _models(info.annotation)
    return keys


def test_scene_reference_names_every_schema_key():
    words = _code_words(DOCS / "scene-files.md")
    missing = sorted(f"{model}.{key}" for model, fields in _schema_keys().items() for key in fields if key not in words)
    assert not missing, f"docs/scene-files.md does not name these scene keys: {', '.join(missing)}"


def test_schema_walk_reaches_the_sections():
    # The walk above must see the nested models, or the test would pass on an empty set.
    keys = _schema_keys()
    for model in ("Run", "Material", "PackingSource", "GeologyMeshSpec", "JointSetSpec", "BlastHistory", "Rigid"):
        assert model in keys


PARSERS = {
    "run": cli.run_parser,
    "bench": cli.bench_parser,
    "bench tets": cli.tet_bench_parser,
    "bench blocks": cli.block_bench_parser,
    "bench fracture": lambda: cli.pass_bench_parser("fracture"),
    "bench conversion": lambda: cli.pass_bench_parser("conversion"),
    "plot": cli.plot_parser,
    "preview": cli.preview_parser,
}


@pytest.mark.parametrize("command", list(PARSERS))
def test_cli_reference_names_every_option(command):
    words = _code_words(DOCS / "cli.md")
    options = {
        opt
        for action in PARSERS[command]()._actions
        for opt in action.option_strings
        if opt.startswith("--") and opt != "--help"
    }
    missing = sorted(options - words)
    assert not missing, f"docs/cli.md does not name these options of 'python -m warpdem {command}': {missing}"
