"""The house in layers (STYLE.md, "The house"): imports run downwards only, and no host modules import each other
round a circle.

Oracle: the import graph read from the source with ``ast`` — every ``import`` and ``from … import`` anywhere in a
module, inside functions and ``if TYPE_CHECKING:`` blocks too, since a circle there is a circle in the design even
where Python happens to resolve it.  Each module has a layer (below); an import must point to a lower layer, or stay
inside its own folder (a stage may use another stage), and the graph must have no cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "warpdem"

# Lower number = lower layer. Keys are module names or folder prefixes (longest prefix wins); the chain is
# cli → api → runner → io / bench → build / simulation → stages → model → leaves → kernels.
LAYERS: dict[str, int] = {
    "warpdem.kernels": 0,
    "warpdem._version": 1,
    "warpdem.limits": 1,
    "warpdem.budget": 1,
    "warpdem.fused": 1,
    "warpdem.recorded": 1,
    "warpdem.tables": 1,
    "warpdem.host_data": 1,
    "warpdem.materials": 1,
    "warpdem.scene": 2,
    "warpdem.load_data": 2,
    "warpdem.model": 3,
    "warpdem.stages": 4,
    "warpdem.build": 5,
    "warpdem.simulation": 5,
    "warpdem.io": 6,
    "warpdem.bench": 6,
    "warpdem.parallel": 5.5,
    "warpdem.runner": 7,
    "warpdem.api": 8,
    "warpdem.cli": 9,
    "warpdem.__main__": 10,
    "warpdem": 10,
}


def _module_name(path: Path) -> str:
    parts = ["warpdem", *path.relative_to(PACKAGE).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _group(module: str) -> str:
    """The layer key a module falls under (the longest matching prefix)."""
    best = ""
    for key in LAYERS:
        if (module == key or module.startswith(key + ".")) and len(key) > len(best):
            best = key
    assert best, f"{module} has no layer: add it to LAYERS in {Path(__file__).name}"
    return best


def _imports(module: str, path: Path, known: set[str]) -> set[str]:
    """The warpdem modules ``module`` imports (kernels collapsed to ``warpdem.kernels``)."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            candidates = [target] + [f"{target}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            candidates = [a.name for a in node.names]
        else:
            continue
        for name in candidates:
            if name.startswith("warpdem.kernels"):
                found.add("warpdem.kernels")
            elif name in known:
                found.add(name)
    found.discard(module)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {m: _imports(m, p, known) for m, p in modules.items()}


def test_every_import_points_to_a_lower_layer_or_stays_in_its_folder():
    bad = []
    for module, targets in _graph().items():
        group = _group(module)
        for target in sorted(targets):
            tgroup = _group(target)
            if tgroup == group and group not in ("warpdem",):
                continue  # inside one folder (stages using stages); circles are the next test's business
            if LAYERS[tgroup] >= LAYERS[group]:
                bad.append(f"{module} (layer {LAYERS[group]}) imports {target} (layer {LAYERS[tgroup]})")
    assert not bad, "imports that run upwards or sideways:\n  " + "\n  ".join(bad)


def test_no_two_host_modules_import_each_other_round_a_circle():
    graph = _graph()
    # Tarjan-free: depth-first search with colours, reporting the first cycle found from each start.
    colour: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(node: str) -> None:
        colour[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if colour.get(nxt, 0) == 0:
                visit(nxt)
            elif colour[nxt] == 1:
                cycles.append([*stack[stack.index(nxt) :], nxt])
        stack.pop()
        colour[node] = 2

    for node in sorted(graph):
        if colour.get(node, 0) == 0:
            visit(node)
    assert not cycles, "import circles:\n  " + "\n  ".join(" -> ".join(c) for c in cycles)


def test_the_kernels_import_no_host_module():
    """kernels/ is Warp code only: it never imports the host package above it (STYLE.md, "Kernels")."""
    bad = []
    for path in sorted((ROOT / "kernels").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("warpdem"):
                if not node.module.startswith("warpdem.kernels"):
                    bad.append(f"{path.name}: from {node.module}")
            elif isinstance(node, ast.ImportFrom) and node.level > 1:
                bad.append(f"{path.name}: relative import above the kernels ({'.' * node.level}{node.module})")
    assert not bad, "\n".join(bad)


FOLDERS = sorted(p.parent.relative_to(PACKAGE).as_posix() for p in PACKAGE.glob("*/__init__.py"))


def test_the_house_has_its_folders():
    assert {"scene", "build", "stages", "io", "runner", "bench"} <= set(FOLDERS), FOLDERS


@pytest.mark.parametrize("folder", FOLDERS)
def test_each_folder_is_a_package_that_installs(folder):
    """Every package folder of warpdem/ is listed in pyproject.toml's packages, or a wheel (pip install .) would
    leave it out and the installed package would fail to import it."""
    import tomllib

    packages = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    assert f"warpdem.{folder}" in packages, f"warpdem/{folder}/ is not in pyproject.toml [tool.setuptools] packages"
