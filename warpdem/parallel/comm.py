"""The MPI world of a run, when there is one (mpi4py is an optional extra: ``pip install "warpdem[mpi]"``).

Without mpi4py, or under one rank, :func:`world` is None and warpdem runs in one process exactly as it always did.
"""

from __future__ import annotations

import os
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
