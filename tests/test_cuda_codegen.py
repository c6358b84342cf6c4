"""CUDA code generation of the kernels the shipped scenes run, checked on machines without a GPU (CI).

Oracle (the invariant behind "CPU and CUDA from the same code"): after every shipped scene has run one frame on the
CPU, every Warp module of warpdem that this instantiated (the module-level kernels and the law- and
history-specialised kernels of the factories) generates CUDA source and compiles with Warp's NVRTC for sm_90 (the
H100) and sm_80 (A100). A kernel that uses something CUDA lacks, or that only type-checks on the CPU path of a
``wp.static`` branch, fails here. What it cannot show is run-time behaviour on a GPU: where one is present the
``device`` fixture runs the whole suite there as well.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
import warp as wp
from warp._src import context

from warpdem.runner import RunOptions, run_scene
from warpdem.scene import default_scene_path, load_scene

SCENES = [*sorted((Path(__file__).resolve().parent.parent / "scenes").glob("*.toml")), default_scene_path()]
CUDA_ARCHS = (90, 80)
# Kernel files that no shipped scene may reach yet (nodal fracture and conversion run only where a scene enables
# them): imported here, so that their kernels are compiled whatever the scenes do.
IMPORTED_STAGES = ("cohesive", "conversion", "fracture", "multisphere", "topology")


def warpdem_modules() -> list:
    """The loaded Warp modules holding a kernel defined in warpdem (module-level or made by a factory)."""
    modules = []
    for module in context.user_modules.values():
        keys = [k.func.__module__ for k in module.kernels.values()]
        if any(name.startswith("warpdem") for name in keys):
            modules.append(module)
    return modules


@pytest.mark.skipif(
    not context.runtime.is_cuda_enabled, reason="this Warp build has no CUDA compiler (CPU-only platform build)"
)
def test_every_scene_kernel_compiles_for_cuda(tmp_path):
    for path in SCENES:
        run_scene(load_scene(path), RunOptions(device="cpu", frames=1, out_dir=tmp_path / path.stem, quiet=True))
    for stage in IMPORTED_STAGES:
        importlib.import_module(f"warpdem.kernels.{stage}")
    modules = warpdem_modules()
    defined_in = {k.func.__module__ for m in modules for k in m.kernels.values()}
    # Every kernel file of the step is reached by some scene family.
    stages = (
        "integrate",
        "contact",
        "neighbors",
        "bonds",
        "tets",
        "joints",
        "fem_contact",
        "fem_surface",
        "sphere_face",  # the scenes with spheres and tets
        "loads",
        "compaction",
        "guard",
        "fragments",  # labelled at every output frame of the scenes with bonds or joints
        "rigid",  # rigid_slope
        *IMPORTED_STAGES,
    )
    assert {f"warpdem.kernels.{stage}" for stage in stages} <= defined_in
    failures, compiled = [], 0
    for module in modules:
        if not any(not k.is_generic or k.overloads for k in module.kernels.values()):
            continue  # generic kernels never launched here (no overload to compile)
        try:
            files = wp.compile_aot_module(module, arch=CUDA_ARCHS, use_ptx=True, module_dir=tmp_path / "cuda")
        except Exception as exc:  # any compile error, with the module named
            failures.append(f"{module.name}: {exc}")
            continue
        # One PTX file per architecture: the compiler ran (an empty result would pass silently otherwise).
        assert sorted(p.suffixes[-2] for p in map(Path, files) if p.suffix == ".ptx") == [f".sm{a}" for a in (80, 90)]
        compiled += 1
    assert not failures, "\n".join(failures)
    assert compiled >= 20  # the module-level kernel files plus the specialised factory kernels of the scenes
