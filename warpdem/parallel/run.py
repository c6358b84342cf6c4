"""A run on several ranks as the runner sees it: rank 0 drives, the other ranks follow its commands.

Rank 0 holds a :class:`Decomposed` in place of the :class:`~warpdem.simulation.Simulation`: each ``advance`` is sent
to every rank, each steps its subdomain, and the owned spheres are gathered into the whole run's state on rank 0,
which writes frames, books and checkpoints from it as one process would (the whole state is the one-process state bit
for bit on the CPU). The other ranks run :func:`serve` until rank 0 says stop. A checkpoint is therefore one file
of the whole run, and a restart on any number of ranks cuts it again.

What is decomposed so far (issue 25): spheres with their contact laws and history, rolling, bonds and their
breakage (warpdem.parallel.subdomain); or Cosserat tets with joint elements, FEM contact, pressure loads,
non-reflecting dashpots and drivers (warpdem.parallel.continuum); walls and gravity. A scene with anything else
(both together, fracture, conversion, the rigid switch) is refused on more than one rank with a message that says
what.
"""

from __future__ import annotations

import atexit
import signal
import sys
from typing import Any

from ..model import Model, State
from ..simulation import Simulation
from ..stages.guard import CriticalStep, UnstableRunError
from .comm import world
from .continuum import ContinuumSubdomain
from .ranked import Ranked
from .subdomain import Subdomain

CROWDED = 0.9
"""The share of the whole run's nodes a rank may hold before rank 0 warns that the ranks gain little."""


class NotDecomposable(ValueError):
    """The scene has what a decomposed run cannot run yet; the message says what."""


class WorkerDone(SystemExit):
    """A follower rank's run is over (rank 0 said stop): the process exits with status 0, nothing printed."""

    def __init__(self) -> None:
        super().__init__(0)


def unsupported(model: Model, state: State) -> list[str]:
    """What ``model`` has that a decomposed run cannot run yet (empty: it can)."""
    found = []
    spheres = int(state.particle_count.numpy()[0]) > 0
    nodes = model.node_capacity > 0 and int(state.node_count.numpy()[0]) > 0
    if spheres and nodes:
        found.append("spheres and tets together")
    if not spheres and not nodes:
        found.append("neither spheres nor tets")
    if model.has_fracture or model.fracture_interval:
        found.append("nodal fracture")
    if model.conversion_interval or model.coupling_capacity:
        found.append("FEM→DEM conversion")
    if model.rigid_switch or model.rigid_energy_fraction > 0.0:
        found.append("the rigid-block switch")
    return found


def subdomain_of(comm: Any, model: Model, state: State, **kwargs: Any) -> Ranked:
    """This rank's part of the whole run ``model``/``state``: its spheres (:class:`~warpdem.parallel.subdomain
    .Subdomain`), or its tets (:class:`~warpdem.parallel.continuum.ContinuumSubdomain`)."""
    if model.node_capacity and int(state.node_count.numpy()[0]):
        return ContinuumSubdomain(comm, model, state, **kwargs)
    return Subdomain(comm, model, state, **kwargs)


def make_simulation(model: Model, state: State, **kwargs: Any) -> Simulation | Decomposed:
    """The stepper of a run: a :class:`~warpdem.simulation.Simulation` in one process; under ``mpiexec`` with more
    than one rank, a :class:`Decomposed` on rank 0, while every other rank follows it in :func:`serve` and leaves
    with :class:`WorkerDone`.

    Raises:
        NotDecomposable: the scene has what a decomposed run cannot run yet (every rank raises it alike).
    """
    comm = world()
    if comm is None:
        return Simulation(model, state, **kwargs)
    missing = unsupported(model, state)
    if missing:
        raise NotDecomposable(
            f"this scene cannot run on {comm.Get_size()} ranks yet; decomposed so far: spheres with their contacts "
            "and bonds, or tets with their joints, contacts, loads and boundaries, walls and gravity; this scene has "
            f"{', '.join(missing)} (run it in one process)"
        )
    if comm.Get_rank() == 0:
        sim = Decomposed(comm, model, state, **kwargs)
        # Whatever way rank 0 leaves (an error in the runner included), the followers are released.
        atexit.register(sim.close)
        return sim
    serve(comm, model, state, **kwargs)
    raise WorkerDone()


def _gather(comm: Any, local: Ranked) -> list[tuple[Any, int, dict[str, float]]] | None:
    """Every rank's owned part, its halo's bytes a step and where its step time went (:attr:`Ranked.times`), at rank
    0 (None elsewhere)."""
    return comm.gather((local.owned_part(), local.halo_bytes(), dict(local.times)), root=0)


def serve(comm: Any, model: Model, state: State, **kwargs: Any) -> None:
    """A follower rank: step its subdomain as rank 0 commands, until it says stop. An unstable run stops every rank
    together (rank 0 reports it); any other error here aborts the whole job, since rank 0 would wait for this rank."""
    # mpiexec passes Ctrl-C (and a TERM) to every rank: rank 0 stops the run at the next frame and writes its
    # checkpoint (warpdem.runner), which needs every rank to keep stepping and gathering until it says stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        local = subdomain_of(comm, model, state, **kwargs)
        while True:
            command, args = comm.bcast(None, root=0)
            if command == "stop":
                return
            if command == "gather":
                _gather(comm, local)
            elif command == "advance":
                try:
                    local.advance(*args)
                except UnstableRunError:
                    continue  # rank 0 raised it too and ends the run; wait for its stop
            elif command == "set_time_step":
                local.set_time_step(*args)
    except Exception as exc:
        _abort(comm, exc)


def _abort(comm: Any, exc: BaseException) -> None:
    """End every rank after an error on this one, with its traceback and one line on the process's own stderr (the
    command line sends a follower's output to nowhere)."""
    import traceback

    traceback.print_exception(exc, file=sys.__stderr__)
    print(f"rank {comm.Get_rank()}: {type(exc).__name__}: {exc}; aborting every rank", file=sys.__stderr__, flush=True)
    comm.Abort(1)


class Decomposed:
    """Rank 0's stepper of a run decomposed over ``comm``: the :class:`~warpdem.simulation.Simulation` interface
    the runner uses, over the whole run's state, gathered from the ranks when it is read after an ``advance`` (the
    runner advances in pieces between frames; the state is read at the frames).

    Args:
        comm: the MPI communicator (mpi4py).
        model: the whole run's model (every rank built it alike).
        state: the whole run's state.
        **kwargs: as :class:`~warpdem.simulation.Simulation`'s.
    """

    def __init__(self, comm: Any, model: Model, state: State, **kwargs: Any) -> None:
        self.comm = comm
        self.ranks = comm.Get_size()
        self.local = subdomain_of(comm, model, state, **kwargs)
        share = getattr(self.local, "held_share", 0.0)
        if share > CROWDED:
            print(
                f"warning: one rank holds {100 * share:.0f} % of the nodes (its slab and the ghosts within "
                f"{self.local.slabs.halo:.3g} m of it, two FEM contact reaches and a tet edge): the model is too "
                f"short along its longest side for {self.ranks} ranks to gain time",
                file=sys.stderr,
            )
        # The whole run, never stepped: what frames, books and checkpoints read.
        self.whole = Simulation(model, state, primed=True, step=kwargs.get("step", 0), time=kwargs.get("time"))
        self._closed = False
        self.halo_bytes = 0  # bytes of a step's halo messages, all ranks (at the last gather)
        self.rank_times: list[dict[str, float]] = []  # each rank's Ranked.times at the last gather [s]
        self._stale = True  # the whole state lags the ranks'

    # The runner's view of the whole run.
    @property
    def model(self) -> Model:
        return self._gathered().model

    @property
    def state(self) -> State:
        return self._gathered().state

    @property
    def step_count(self) -> int:
        return self.local.step_count

    @property
    def time(self) -> float:
        return self.local.time

    rigid = False
    rigid_report = None

    @property
    def has_spheres(self) -> bool:
        return self.local.has_spheres

    @property
    def migrations(self) -> int:
        """Times the items moved between ranks so far (every rank counts alike)."""
        return self.local.migrations

    @property
    def particle_count(self) -> int:
        return self._gathered().particle_count

    @property
    def bond_count(self) -> int:
        return self._gathered().bond_count

    @property
    def node_count(self) -> int:
        return self._gathered().node_count

    def energy(self) -> Any:
        return self._gathered().energy()

    def step_times(self) -> list[dict[str, float]]:
        """Where each rank's step time went since the start, cumulative seconds by :data:`~warpdem.parallel.ranked
        .STEP_TIMES` (gathered now where the ranks have stepped since)."""
        self._gathered()
        return [dict(t) for t in self.rank_times]

    def shadow(self) -> float:
        return self._gathered().shadow()

    def contact_count(self) -> int:
        return self._gathered().contact_count()

    def advance(self, n_steps: int, stop_at_switch: bool = False) -> int:
        """``n_steps`` on every rank (the whole state is gathered when next read).

        Raises:
            UnstableRunError: as :meth:`~warpdem.simulation.Simulation.advance`, on every rank together. Any other
                error here aborts every rank with its message: the others would wait for this one in the next
                exchange.
        """
        self.comm.bcast(("advance", (n_steps, stop_at_switch)), root=0)
        self._stale = True
        try:
            self.local.advance(n_steps, stop_at_switch)
        except UnstableRunError:
            raise
        except BaseException as exc:
            _abort(self.comm, exc)
        return n_steps

    def set_time_step(self, dt: float, critical: CriticalStep | None = None) -> float:
        self.comm.bcast(("set_time_step", (dt, critical)), root=0)
        self._gathered().set_time_step(dt, critical)
        return self.local.set_time_step(dt, critical)

    def close(self) -> None:
        """Release the follower ranks (they leave :func:`serve`); idempotent."""
        if not self._closed:
            self._closed = True
            self.comm.bcast(("stop", ()), root=0)

    def _gathered(self) -> Simulation:
        """The whole run, its state gathered from the ranks first where it lags theirs."""
        if self._stale and not self._closed:
            self.comm.bcast(("gather", ()), root=0)
            self._collect()
            self._stale = False
        return self.whole

    def _collect(self) -> None:
        """The owned parts of every rank into the whole state (the shared arrays from rank 0's)."""
        parts = _gather(self.comm, self.local)
        self.halo_bytes = sum(p[1] for p in parts)  # what the ranks send each other a step now
        self.rank_times = [p[2] for p in parts]
        w = self.whole
        model, state = self.local.write_whole(w.model, w.state, [p[0] for p in parts])
        if model is not w.model or state is not w.state:
            w.model, w.state = model, state
            w._setup()
        w.step_count, w.time = self.local.step_count, self.local.time
        w.state.rebuild_flag.zero_()


def rank_is_follower() -> bool:
    """Whether this process is a rank other than 0 of a decomposed run (it prints nothing of the run)."""
    comm = world()
    return comm is not None and comm.Get_rank() > 0


def release_ranks(sim: object) -> None:
    """Release the followers of a decomposed run (a no-op for any other stepper)."""
    if isinstance(sim, Decomposed):
        sim.close()


__all__ = [
    "Decomposed",
    "NotDecomposable",
    "WorkerDone",
    "make_simulation",
    "rank_is_follower",
    "release_ranks",
    "serve",
    "unsupported",
]
