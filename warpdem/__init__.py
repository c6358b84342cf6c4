"""warpdem: rock and structures breaking under blast and impact, on NVIDIA Warp.

The package is split into host code (this package: scene loading, model building, the step pipeline,
output) and Warp kernels (:mod:`warpdem.kernels`). Imports run one way: host → kernels.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from ._version import __version__

__all__ = ["__version__"]


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
