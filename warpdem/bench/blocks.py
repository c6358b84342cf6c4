"""Rigid blocks (issue 11 §5): block-steps/s of a jointed cube of 1 m granite blocks, one Kuhn cell (6 tets) each, on a
ground wall under gravity, rattling from seeded random velocities, in rigid mode at half the blocks' stable step
(:func:`jointed_cube`); the engaged node–face contacts, and the device memory of every array per block.
"""

from __future__ import annotations

import resource
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .common import GRANITE, write_json

if TYPE_CHECKING:
    from ..simulation import Simulation


@dataclass
class BlockBenchResult:
    """One rigid-block benchmark row: blocks, steps, throughput [block-steps/s] per second of wall time and per second
    of the process's CPU time (on the CPU device the steps run on one core, so the CPU time is what the steps cost
    whatever else shares the machine; a CUDA device's steps do not show in it), engaged contacts, the FEM contact-list
    builds during the timed steps (the hash-grid rebuild a node's half-skin move flags), device memory per block [B]
    (every Model and State array), the stable steps [s] and whether the energy stayed finite."""

    device: str
    blocks: int
    held: int
    nodes: int
    tets: int
    steps: int
    dt: float
    deformable_dt: float
    build_time: float
    wall_time: float
    block_steps_per_second: float
    cpu_time: float
    block_steps_per_cpu_second: float
    contacts: int
    list_builds: int
    bytes_per_block: float
    peak_rss_mb: float
    finite: bool


def jointed_cube(cells: int, device: str, node_order: str = "blocks") -> Simulation:
    """A cube of ``cells``³ granite blocks of 1 m, one Kuhn cell (6 tets) each: every cell face inside the cube is a
    frictional joint (μ = 0.5), so the blocks are the cells. It rests on a ground wall under gravity, each block with
    a seeded small random velocity (the blocks rattle, so the contacts work), in rigid mode from the start at half
    the blocks' stable step (warpdem.stages.rigid_step.rigid_time_step), as a Simulation. ``node_order``:
    ModelBuilder.finalize's (the bench's, "blocks", numbers the nodes block by block; benchmarks/README.md,
    "bench blocks", compares it with "split")."""
    from ..build.builder import ModelBuilder
    from ..build.mesh import box_mesh
    from ..simulation import Simulation
    from ..stages.joints import JointProps
    from ..stages.rigid_step import rigid_time_step
    from ..tables import TET_FACES

    points, tets = box_mesh((0.0, 0.0, 0.0), (float(cells),) * 3, (cells,) * 3)
    faces = tets[:, TET_FACES].reshape(-1, 3)
    xf = points[faces]  # (F, 3, 3)
    on_grid = np.zeros(len(faces), dtype=bool)
    for axis in range(3):
        c = xf[:, :, axis]
        flat = np.all(c == c[:, :1], axis=1)
        on_grid |= flat & (c[:, 0] > 0.0) & (c[:, 0] < cells) & (np.round(c[:, 0]) == c[:, 0])
    joint_faces = np.unique(np.sort(faces[on_grid], axis=1), axis=0)
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("granite", **GRANITE)
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "granite")
    js = b.add_joint_set(JointProps(friction=0.5, restitution=0.5))
    rng = np.random.default_rng(0)
    cell = np.floor(points[tets].mean(axis=1)).astype(np.int64)
    kick = rng.normal(scale=0.01, size=(cells**3, 3))[(cell[:, 0] * cells + cell[:, 1]) * cells + cell[:, 2]]
    velocity = np.zeros((len(points), 3))
    velocity[tets.ravel()] = np.repeat(kick, 4, axis=0)
    b.add_tet_mesh(points, tets, "granite", joint_faces=joint_faces, joint_set=js, velocity=velocity)
    # A block corner inside the cube is a corner of eight blocks: some thirty faces of the seven others touch it, all
    # node–face candidates. Slots for them from the start spare the set-up a list build that overflows and is redone.
    model, state = b.finalize(device, safety_factor=0.5, max_node_faces=32, node_order=node_order)
    sim = Simulation(rigid_time_step(model, state, 0.5), state, track_energy=False)
    sim.switch_to_rigid()
    return sim


def bench_blocks(blocks_wanted: int, steps: int = 50, device: str = "cpu", repeat: int = 3) -> BlockBenchResult:
    """Build the jointed cube of at least ``blocks_wanted`` blocks once, then time ``repeat`` runs of ``steps`` steps;
    the fastest counts."""
    import math

    import warp as wp

    cells = max(1, math.ceil(blocks_wanted ** (1.0 / 3.0) - 1e-9))
    t0 = time.perf_counter()
    sim = jointed_cube(cells, device)
    build = time.perf_counter() - t0
    sim.advance(2)  # compile and capture outside the clock
    builds = int(sim.state.fem_rebuild_total.numpy()[0])
    wall = cpu = float("inf")
    for _ in range(repeat):
        wp.synchronize_device(sim.model.device)
        t0, c0 = time.perf_counter(), time.process_time()
        sim.advance(steps)
        wp.synchronize_device(sim.model.device)
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    s = sim.state
    blocks = s.body_mass.shape[0]
    nn = sim.node_count
    total_bytes = sum(a.capacity for a in {**sim.model.arrays(), **s.arrays()}.values())
    return BlockBenchResult(
        device=str(device),
        blocks=blocks,
        held=int(s.body_fixed.numpy().sum()),
        nodes=nn,
        tets=int(s.tet_count.numpy()[0]),
        steps=steps,
        dt=sim.model.dt,
        deformable_dt=0.5 * sim.model.deformable_critical_dt,
        build_time=build,
        wall_time=wall,
        block_steps_per_second=blocks * steps / wall,
        cpu_time=cpu,
        block_steps_per_cpu_second=blocks * steps / cpu if cpu > 0.0 else math.inf,
        contacts=int(np.count_nonzero(s.node_face_spring.numpy()[: nn * sim.model.node_springs] >= 0)),  # every slot
        list_builds=int(s.fem_rebuild_total.numpy()[0]) - builds,
        bytes_per_block=total_bytes / blocks,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        finite=bool(np.all(np.isfinite(s.body_v.numpy())) and np.all(np.isfinite(s.node_u.numpy()[:nn]))),
    )


def format_block_row(r: BlockBenchResult, header: bool) -> str:
    line = (
        f"{r.device:<8}{r.blocks:>9}{r.held:>7}{r.tets:>9}{r.steps:>7}{r.dt:>11.3g}{r.deformable_dt:>11.3g}"
        f"{r.build_time:>9.1f}{r.wall_time:>9.3f}{r.block_steps_per_second / 1e6:>17.3f}"
        f"{r.block_steps_per_cpu_second / 1e6:>13.3f}{r.contacts:>10}{r.list_builds:>8}"
        f"{r.bytes_per_block:>9.0f}{r.peak_rss_mb:>9.0f}" + ("" if r.finite else "   NON-FINITE")
    )
    if not header:
        return line
    head = (
        f"{'device':<8}{'blocks':>9}{'held':>7}{'tets':>9}{'steps':>7}{'dt s':>11}{'deform. dt':>11}{'build s':>9}"
        f"{'wall s':>9}{'M block-steps/s':>17}{'M per cpu-s':>13}{'contacts':>10}{'builds':>8}{'B/block':>9}"
        f"{'RSS MB':>9}"
    )
    return "\n".join([head, "-" * len(head), line])


def run_block_bench(sizes: list[int], steps: int, device: str, json_path: Path | None = None, repeat: int = 3) -> int:
    """``python -m warpdem bench blocks``: print the table; returns the exit status (1 on a non-finite state)."""
    rows = []
    for n in sizes:
        rows.append(bench_blocks(n, steps, device, repeat))
        print(format_block_row(rows[-1], header=len(rows) == 1), flush=True)
    write_json(json_path, {"blocks": [asdict(r) for r in rows]})
    return 0 if all(r.finite for r in rows) else 1
