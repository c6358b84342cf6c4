"""The MPI world of a run, when there is one (mpi4py is an optional extra: ``pip install "warpdem[mpi]"``).

Without mpi4py, or under one rank, :func:`world` is None and warpdem runs in one process exactly as it always did.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

# Launchers set one of these in every rank's environment; without one, mpi4py is not even imported (importing it starts
# MPI, which a plain run should not pay for, nor its messages).
_LAUNCHER_VARIABLES = ("PMI_RANK", "PMIX_RANK", "OMPI_COMM_WORLD_RANK", "MPI_LOCALRANKID", "SLURM_PROCID")


def world() -> Any | None:
    """MPI's COMM_WORLD when this process is one of several ranks started by ``mpiexec``/``mpirun``, else None."""
    if not any(name in os.environ for name in _LAUNCHER_VARIABLES):
        return None
    try:
        from mpi4py import MPI
    except ImportError:
        return None
    comm = MPI.COMM_WORLD
    return comm if comm.Get_size() > 1 else None


def rank_device(name: str) -> str:
    """The Warp device this process runs on when asked for ``name``: ``name`` itself, except ``"cuda"`` (no index)
    on several ranks, which gives the ranks of one node that node's GPUs in turn (:func:`local_gpu`), one rank per
    GPU where there are as many. Every rank calls it (it splits the world by node)."""
    comm = world()
    if comm is None or name != "cuda":
        return name
    import warp as wp
    from mpi4py import MPI

    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    try:
        return local_gpu(node.Get_rank(), wp.get_cuda_device_count())
    finally:
        node.Free()


def local_gpu(local_rank: int, gpus: int) -> str:
    """The GPU of the ``local_rank``-th rank on a node of ``gpus`` GPUs: ``cuda:<local_rank mod gpus>`` (``"cuda"``
    where there is none, which then fails as one process would, saying the device is not available)."""
    return f"cuda:{local_rank % gpus}" if gpus > 0 else "cuda"


def launcher() -> str | None:
    """The MPI launcher: the ``mpiexec`` beside this Python (``pip install "warpdem[mpi]"`` puts MPICH's there), else
    the one on PATH, else None."""
    beside = Path(sys.executable).parent / "mpiexec"
    return str(beside) if beside.exists() else shutil.which("mpiexec")


def run_on_ranks(ranks: int, args: list[str]) -> int:
    """``python -m warpdem ARGS`` again on ``ranks`` ranks under the MPI launcher (what ``--ranks N`` asks for);
    its exit status, or 2 with a message when no launcher is found or this process is already one of several."""
    if world() is not None:
        print("error: --ranks: this process already runs under mpiexec; leave --ranks out there", file=sys.stderr)
        return 2
    found = launcher()
    if found is None:
        print(
            f'error: --ranks {ranks}: no mpiexec beside {sys.executable} or on PATH; pip install "warpdem[mpi]" brings '
            "mpi4py and MPICH",
            file=sys.stderr,
        )
        return 2
    return subprocess.run([found, "-n", str(ranks), sys.executable, "-m", "warpdem", *args]).returncode
