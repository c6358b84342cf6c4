"""Runs decomposed in space over MPI ranks (issue 25): ``mpiexec -n N python -m warpdem SCENE.toml``.

:mod:`.comm` finds the MPI world (none without mpi4py or under one rank), :mod:`.domain` cuts space into slabs,
:mod:`.rows` moves spheres and bonds between ranks as rows keyed by global id, :mod:`.subdomain` steps one rank's
part with its halo, :mod:`.run` is what the runner holds on rank 0 and what the other ranks run.
"""
