"""warpdem: rock and structures breaking under blast and impact, on NVIDIA Warp.

The package is split into host code (this package: scene loading, model building, the step pipeline,
output) and Warp kernels (:mod:`warpdem.kernels`). Imports run one way: host → kernels.

The Python API (:mod:`warpdem.api`) is reachable from here, loaded on first use so that ``import warpdem`` stays
light (no Warp, no USD) until a name of it is asked for::

    import warpdem as wd

    sim = wd.build(wd.load_scene("scenes/boulder_impact.toml"), device="cpu")
    for frame in sim.frames():
        print(frame.time, frame.energy.error, frame.splits)
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path
from typing import Any

from . import build
from ._version import __version__

_API_NAMES = {
    "Scene": "scene",
    "SceneError": "scene",
    "load_scene": "scene",
    "parse_scene": "scene",
    "CheckpointError": "api",
    "Frame": "api",
    "FrameEnergy": "api",
    "NothingToDo": "api",
    "Run": "api",
    "RunInterrupted": "api",
    "RunSummary": "api",
    "restart": "api",
    "validate": "api",
}
"""The names of the Python API this package gives on first use (PEP 562 ``__getattr__``), by the module they come
from: the scene's from :mod:`warpdem.scene` (no Warp: loading and checking a scene stays fast), the rest from
:mod:`warpdem.api`."""

__all__ = ["__version__", "build", *_API_NAMES]


class _CallableBuildPackage(types.ModuleType):
    """The class of the :mod:`warpdem.build` package: a module, as the import system knows it, that can also be
    called as :func:`warpdem.api.build` (``wd.build(scene, device="cpu")``).

    The API's ``build`` and the package that builds models share the name ``warpdem.build``; the package must stay
    the attribute (``import warpdem.build.geology as g`` looks it up there), so the package answers the call.
    """

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        """:func:`warpdem.api.build`: validate a scene, build its model, open its outputs, write frame 0."""
        from .api import build as build_run

        return build_run(*args, **kwargs)


build.__class__ = _CallableBuildPackage  # its __init__ imports nothing: this import stays light


def __getattr__(name: str) -> Any:
    """A name of the Python API (:data:`_API_NAMES`), importing its module the first time one is asked for.

    Raises:
        AttributeError: no such name (a submodule not imported yet is then imported by ``from warpdem import x``).
    """
    home = _API_NAMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module = importlib.import_module(f"{__name__}.{home}")
    value = getattr(module, name)
    globals()[name] = value  # later lookups find it without coming here
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_API_NAMES})


def _import_source_kernels() -> None:
    """Make the source tree's top-level ``kernels/`` importable as :mod:`warpdem.kernels`.

    An installed warpdem holds ``warpdem/kernels/`` (pyproject.toml maps the top-level folder there). Python run from
    the root of a checkout imports this package from ``./warpdem/`` instead (the working directory comes first on
    sys.path), where ``kernels/`` is a sibling, not a subfolder; the same happens to an editable install, whose
    finder is consulted only after the working directory. So when this package has no ``kernels/`` of its own, its
    sibling is registered under the installed name, before any module asks for it. Nothing else is added to the
    package's search path.
    """
    here = Path(__file__).resolve().parent
    source = here.parent / "kernels" / "__init__.py"
    if (here / "kernels").is_dir() or not source.is_file() or f"{__name__}.kernels" in sys.modules:
        return
    spec = importlib.util.spec_from_file_location(
        f"{__name__}.kernels", source, submodule_search_locations=[str(source.parent)]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    globals()["kernels"] = module  # what `import warpdem.kernels` binds on the parent package


_import_source_kernels()
