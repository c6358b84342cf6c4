"""Property-based scene fuzzer: mutate the shipped scenes, run each through the command line, judge the outcome.

Used by ``tests/test_fuzz.py`` (a short, derandomised run in the test suite) and ``benchmarks/fuzz_scenes.py``
(a long run that counts outcomes). The property, for any input the fuzzer can write:

- exit 0: the summary's energy lines are finite and the USD stage exists; or
- exit 2 or 3: stderr holds the message, every line ``error: ...`` (one line per problem), never a traceback;
- within :data:`TIME_BOUND` seconds (no input may hang the program).

A scene is one of the shipped scenes (``scenes/*.toml``, the embedded default scene) or a small synthetic one that
reads a tet mesh file and a sphere file, made to run in a few steps per frame (the output rate raised) and then
mutated 1–3 times: keys dropped, values replaced by extreme numbers (0, -1, 1e-300, 1e39, 1e300, inf, nan, 2^31,
2^63), wrong types, bad names (empty, NUL, too long, a path), table entries duplicated (coincident spheres), an
explicit time step, mild rescaling, mesh files with NaN points, out-of-range indices or degenerate tets, and sphere
files with coincident or NaN centres. Each run happens in a worker process (Warp imported once) so that a hang
can be detected and the worker replaced; the worker calls ``warpdem.cli.main`` in-process, as ``python -m warpdem``
does.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import multiprocessing
import tempfile
import tomllib
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
from hypothesis import strategies as st

REPO = Path(__file__).resolve().parents[1]
SCENE_FILES = [*sorted((REPO / "scenes").glob("*.toml")), REPO / "warpdem" / "data" / "default.toml"]

TIME_BOUND = 300.0
"""Seconds one example may take (set-up, meshing, one frame) before it counts as a hang. Far above the few seconds a
shrunk scene needs on two CPU cores, so that a loaded machine never fails it; what it catches is a run that does
not end."""

MAX_STEPS = 20_000
"""``--max-steps`` of every fuzz run: a scene whose valid but extreme numbers ask for more steps than this is refused
(exit 2) rather than run for hours."""

FRAME_PERIOD = 2e-5
"""Frame period [s] the base scenes are shrunk to (their output rate raised), so one frame is a few steps."""

EXTREME_NUMBERS = (0, -1, 1e-300, 1e-40, 1e39, 1e300, math.inf, -math.inf, math.nan, 2**31, 2**63 - 1, -(2**63))
WRONG_TYPES = ("x", "", True, [], {}, [1.0, 2.0], {"a": 1})
BAD_NAMES = ("", "\x00", "a\x00b", "x" * 300, "../escape", "sub/dir", ".", " ")
BAD_USD_NAMES = ("\x00.usdc", "x" * 300 + ".usdc", ".usdc", "sub/dir/x.usda", "a\nb.usd")
EXPLICIT_DT = (0, -1e-6, 1e-300, 1e-12, 1e-7, 1e-3, 1e300, math.nan)
SCALES = (0.5, 2.0, -1.0)
RUNTIME_SCALES = (0.5, 0.9, 1.1, 2.0, -1.0)  # within a factor 2: sizes grow at most 8-fold


# ----------------------------------------------------------------------------------------------------------------
# Synthetic base: a small tet mesh read from a file plus spheres read from a file, both mutable.


def _unit_cube_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The 6 Kuhn tets of a unit cube (positive volume), points (8, 3) [m], tets (6, 4)."""
    from warpdem.build.mesh import box_mesh

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (1, 1, 1))
    return np.asarray(points, dtype=np.float64), np.asarray(tets, dtype=np.int64)


FILE_SCENE: dict[str, Any] = {
    "schema_version": 1,
    "name": "file_inputs",
    "run": {"end_time": 0.01, "output_rate": 1.0 / FRAME_PERIOD},
    "gravity": {"vector": [0.0, 0.0, -9.81]},
    "materials": {"rock": {"density": 2600.0, "youngs_modulus": 1.0e8, "poisson_ratio": 0.25}},
    "parts": {"grains": {"material": "rock"}},
    "particles": [{"kind": "file", "part": "grains", "path": "spheres.txt", "radius": 0.05}],
    "mesh": {"kind": "file", "path": "rock.vtu", "material": "rock"},
    "walls": [{"kind": "plane", "point": [0.0, 0.0, -1.0], "normal": [0.0, 0.0, 1.0], "material": "rock"}],
}
SPHERES = np.array([[0.3, 0.3, 1.2], [0.6, 0.5, 1.2], [0.45, 0.7, 1.35]])


def _base_scenes() -> dict[str, dict[str, Any]]:
    bases = {}
    for path in SCENE_FILES:
        with path.open("rb") as f:
            data = tomllib.load(f)
        data["run"]["output_rate"] = 1.0 / FRAME_PERIOD
        bases[path.name] = data
    bases["file_inputs"] = FILE_SCENE
    return bases


BASES = _base_scenes()


# ----------------------------------------------------------------------------------------------------------------
# Mutations


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path into a TOML tree (tables and arrays, their members, recursively), root excluded."""
    out = []
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        path = (*prefix, key)
        out.append(path)
        out += _paths(value, path)
    return out


def _get(tree: Any, path: tuple) -> Any:
    for key in path:
        tree = tree[key]
    return tree


def _set(tree: Any, path: tuple, value: Any) -> None:
    _get(tree, path[:-1])[path[-1]] = value


def _delete(tree: Any, path: tuple) -> None:
    del _get(tree, path[:-1])[path[-1]]


@dataclass
class Case:
    """One fuzz example: the scene tree, the files next to it, and what was done to it (for the report)."""

    base: str
    scene: dict[str, Any]
    mesh_points: np.ndarray | None = None
    mesh_tets: np.ndarray | None = None
    spheres: np.ndarray | None = None
    mutations: list[str] = field(default_factory=list)

    def write(self, folder: Path) -> Path:
        """Writes the scene (and its mesh and sphere files) into ``folder``; returns the scene path."""
        import meshio

        if self.mesh_points is not None:
            mesh = meshio.Mesh(self.mesh_points, [("tetra", self.mesh_tets)])
            mesh.write(folder / "rock.vtu")
        if self.spheres is not None:
            np.savetxt(folder / "spheres.txt", self.spheres)
        path = folder / "scene.toml"
        path.write_text(tomli_w.dumps(self.scene))
        return path


def _leaf_value(draw: Any, path: tuple, old: Any) -> tuple[Any, str]:
    last = path[-1]
    if isinstance(old, str):
        # A string leaf (a name, a path, a law): a bad name, or a value of the wrong type.
        choice = draw(st.sampled_from(("name", "name", "wrong_type", "extreme")))
    else:
        choice = draw(st.sampled_from(("extreme", "extreme", "extreme", "scale", "scale", "wrong_type")))
    if choice == "name":
        value = draw(st.sampled_from(BAD_USD_NAMES if last == "usd" else BAD_NAMES))
    elif choice == "extreme":
        value = draw(st.sampled_from(EXTREME_NUMBERS))
    elif choice == "wrong_type":
        value = draw(st.sampled_from(WRONG_TYPES))
    elif isinstance(old, int | float) and not isinstance(old, bool):
        value = old * draw(st.sampled_from(SCALES))
    else:
        value = draw(st.sampled_from(EXTREME_NUMBERS))
    return value, f"{_key(path)} = {value!r}"


def _key(path: tuple) -> str:
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path).lstrip(".")


@st.composite
def cases(draw: Any, profile: str = "all") -> Case:
    """A mutated scene (Hypothesis strategy).

    Args:
        profile: ``"all"``: every kind of mutation (most scenes are then refused at validation); ``"runtime"``:
            only numbers rescaled within a factor 2 (or negated) and entries duplicated, so that most scenes validate
            and run, which is where NaN and hangs live.
    """
    base = draw(st.sampled_from(sorted(BASES)))
    case = Case(base, copy.deepcopy(BASES[base]))
    if base == "file_inputs":
        case.mesh_points, case.mesh_tets = _unit_cube_mesh()
        case.spheres = SPHERES.copy()
    kinds = ("replace",) * 5 + ("drop", "duplicate", "duplicate", "dt", "usd", "files")
    if profile == "runtime":
        kinds = ("rescale",) * 4 + ("duplicate", "duplicate")
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(kinds))
        paths = _paths(case.scene)
        if kind == "rescale":
            numbers = [p for p in paths if type(_get(case.scene, p)) in (int, float) and p[-1] != "schema_version"]
            path = draw(st.sampled_from(numbers))
            factor = draw(st.sampled_from(RUNTIME_SCALES))
            old = _get(case.scene, path)
            _set(case.scene, path, type(old)(old * factor) if isinstance(old, float) else max(1, round(old * factor)))
            case.mutations.append(f"{_key(path)} = {_get(case.scene, path)!r}")
        elif kind == "replace":
            path = draw(st.sampled_from(paths))
            value, text = _leaf_value(draw, path, _get(case.scene, path))
            _set(case.scene, path, value)
            case.mutations.append(text)
        elif kind == "drop":
            path = draw(st.sampled_from(paths))
            _delete(case.scene, path)
            case.mutations.append(f"drop {_key(path)}")
        elif kind == "duplicate":
            # A repeated array entry: a second copy of a sphere, packing, bond region, wall or load.
            arrays = [p for p in paths if isinstance(_get(case.scene, p), list) and _get(case.scene, p)]
            arrays = [p for p in arrays if isinstance(_get(case.scene, p)[0], dict)]
            if not arrays:
                continue
            path = draw(st.sampled_from(arrays))
            entries = _get(case.scene, path)
            k = draw(st.integers(0, len(entries) - 1))
            entries.append(copy.deepcopy(entries[k]))
            case.mutations.append(f"duplicate {_key((*path, k))}")
        elif kind == "dt":
            dt = draw(st.sampled_from(EXPLICIT_DT))
            case.scene.setdefault("run", {})["dt"] = dt
            case.mutations.append(f"run.dt = {dt!r}")
        elif kind == "usd":
            name = draw(st.sampled_from(BAD_USD_NAMES + BAD_NAMES))
            key = draw(st.sampled_from(("usd", "name")))
            if key == "usd":
                case.scene.setdefault("output", {})["usd"] = name
            else:
                case.scene["name"] = name
            case.mutations.append(f"{'output.usd' if key == 'usd' else 'name'} = {name!r}")
        elif case.mesh_points is not None:
            _mutate_files(draw, case)
    return case


def _mutate_files(draw: Any, case: Case) -> None:
    what = draw(
        st.sampled_from(
            (
                "nan_point",
                "index_out_of_range",
                "negative_index",
                "degenerate",
                "flat",
                "coincident_spheres",
                "nan_sphere",
                "far_point",
            )
        )
    )
    if what == "nan_point":
        case.mesh_points[draw(st.integers(0, len(case.mesh_points) - 1)), 0] = math.nan
    elif what == "index_out_of_range":
        case.mesh_tets[0, 3] = len(case.mesh_points) + 5
    elif what == "negative_index":
        case.mesh_tets[0, 1] = -3
    elif what == "degenerate":
        case.mesh_tets[0, 1] = case.mesh_tets[0, 0]  # a node twice: zero volume
    elif what == "flat":
        case.mesh_points[:, 2] = 0.0  # every tet flat
    elif what == "coincident_spheres":
        case.spheres = np.concatenate([case.spheres, case.spheres[:1]])
    elif what == "nan_sphere":
        case.spheres[0, 1] = math.nan
    else:
        case.mesh_points[0] = (1e35, 0.0, 0.0)
    case.mutations.append(f"files: {what}")


# ----------------------------------------------------------------------------------------------------------------
# Running and judging


@dataclass
class Outcome:
    """What a run did: exit status, stderr, the summary (exit 0), whether the USD stage exists, or a hang."""

    status: int | None
    stderr: str
    summary: dict | None = None
    usd_exists: bool = False
    hang: bool = False

    def problem(self) -> str | None:
        """Why the outcome breaks the property, or None when it holds."""
        if self.hang:
            return f"no result within {TIME_BOUND:.0f} s (a hang)"
        if "Traceback" in self.stderr:
            return "a traceback on stderr"
        if self.status == 0:
            if self.summary is None:
                return "exit 0 without a summary"
            numbers = [v for e in ("energy_start", "energy_end") for v in self.summary[e].values()]
            if not all(math.isfinite(v) for v in numbers):
                return "exit 0 with a non-finite energy line"
            if not self.usd_exists:
                return "exit 0 without a USD stage"
            return None
        if self.status in (2, 3):
            lines = [line for line in self.stderr.splitlines() if line.strip()]
            messages = [line for line in lines if line.startswith("error: ")]
            if not messages:
                return f"exit {self.status} without an 'error: ...' line"
            return None
        return f"exit status {self.status}"


def run_case_in_process(scene_text: str, files: dict[str, bytes]) -> tuple[int | None, str, dict | None, bool]:
    """Runs one scene through ``warpdem.cli.main`` in this process (the worker's side)."""
    from warpdem.cli import main

    with tempfile.TemporaryDirectory(prefix="warpdem-fuzz-") as tmp:
        folder = Path(tmp)
        for name, data in files.items():
            (folder / name).write_bytes(data)
        (folder / "scene.toml").write_text(scene_text)
        out = folder / "out"
        summary_path = folder / "summary.json"
        err = io.StringIO()
        argv = [str(folder / "scene.toml"), "--frames", "1", "--quiet", "--out", str(out)]
        argv += ["--summary-json", str(summary_path), "--max-steps", str(MAX_STEPS)]
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                status = main(argv)
            except SystemExit as exc:
                status = exc.code if isinstance(exc.code, int) else 1
            except BaseException:
                # Anything escaping main would reach the user as a traceback: report it as one.
                err.write(traceback.format_exc())
                status = None
        summary = json.loads(summary_path.read_text()) if status == 0 and summary_path.is_file() else None
        usd = summary is not None and summary.get("usd_path") and Path(summary["usd_path"]).is_file()
        return status, err.getvalue(), summary, bool(usd)


def case_payload(case: Case) -> tuple[str, dict[str, bytes]]:
    """The scene text and the bytes of its files (what a worker needs)."""
    with tempfile.TemporaryDirectory(prefix="warpdem-fuzz-") as tmp:
        folder = Path(tmp)
        case.write(folder)
        files = {p.name: p.read_bytes() for p in folder.iterdir() if p.name != "scene.toml"}
        return (folder / "scene.toml").read_text(), files


def _worker_init() -> None:
    import logging

    import warp as wp

    wp.config.log_level = logging.WARNING
    wp.config.quiet = True
    with contextlib.redirect_stdout(io.StringIO()):
        wp.init()


class Runner:
    """Runs cases in a worker process, replacing it when a case does not finish within the time bound."""

    def __init__(self, time_bound: float = TIME_BOUND) -> None:
        self.time_bound = time_bound
        self._pool: Any = None

    def _start(self) -> Any:
        if self._pool is None:
            ctx = multiprocessing.get_context("spawn")
            self._pool = ctx.Pool(1, initializer=_worker_init, maxtasksperchild=200)
        return self._pool

    def run(self, case: Case) -> Outcome:
        scene_text, files = case_payload(case)
        result = self._start().apply_async(run_case_in_process, (scene_text, files))
        try:
            status, stderr, summary, usd = result.get(self.time_bound)
        except multiprocessing.TimeoutError:
            self.close()
            return Outcome(None, "", hang=True)
        return Outcome(status, stderr, summary, usd)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None
