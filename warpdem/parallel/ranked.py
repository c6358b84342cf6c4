"""What every rank's part of a decomposed run shares (issue 25), whatever it holds: a
:class:`~warpdem.simulation.Simulation` of its own items and their ghosts, stepped with one forward halo message per
neighbour between the drift and the forces.

Per step (DESIGN.md, "Scale"): after the drift each rank sends the positions and velocities of its owned items that
others hold as ghosts (:class:`Channel`: spheres, FEM nodes); forces on ghosts are computed again where they are held
("newton off"), nothing is sent back; the same wait completes one reduction of the owned items' skin tests, so the
ranks meet once a step and decide together what the one-process run decides from all items (a list rebuild, a
migration). The subclasses say what is held and what the tests are: warpdem.parallel.subdomain (spheres and bonds),
warpdem.parallel.continuum (tets, joints, loads).
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any

import numpy as np
import warp as wp

from ..kernels import halo as kh
from ..model import Model, State
from ..simulation import Simulation
from ..stages.guard import UnstableRunError
from ..stages.integrate import integrate_first_half, kick_drift
from ..stages.tets import eval_tet_stresses

IMBALANCE = 1.10
"""Largest rank's measured step work over the mean before the slabs are cut again (at a list rebuild)."""

MEASURED = 0.25
"""Seconds of step work each rank must have measured before the ranks' work is compared: less is noise."""

STEP_TIMES = ("kernels", "pack", "post", "wait", "unpack", "exchange")
"""What a rank's step time is cut into, cumulative seconds since the start (:attr:`Ranked.times`): its own kernels
(the two halves), the halo's packing (with a GPU's copies and wait), posting the messages, waiting for them (the other
ranks' imbalance and the transfer), unpacking, and the whole exchange (the halo and, every few steps, a list rebuild
or a migration)."""

SHARED_FIELDS = ("time", "wall_point", "rebuild_total", "fem_rebuild_total", "fem_sphere_builds_seen")
"""State arrays every rank holds alike (the clock, the walls, the list builds all ranks decide together)."""


STAGING_VARIABLE = "WARPDEM_HALO_STAGING"
"""An environment variable: set to 1, the CPU ranks stage their halo messages through host copies as GPU ranks do."""


def staged_on(device: Any) -> bool:
    """Whether halo messages on ``device`` go through host copies: on a GPU (MPI reads host memory), and on the CPU
    where :data:`STAGING_VARIABLE` asks for it (which tests the path GPU ranks take)."""
    return not wp.get_device(device).is_cpu or os.environ.get(STAGING_VARIABLE, "") == "1"


def host_mirror(array: wp.array) -> wp.array:
    """A host array shaped and typed like ``array``, page-locked where CUDA is present (copies to and from a GPU
    then run asynchronously, at full speed)."""
    return wp.empty(array.shape, dtype=array.dtype, device="cpu", pinned=wp.is_cuda_available())


@dataclasses.dataclass
class Channel:
    """One kind of item the halo refreshes: the three State fields it carries (vec3 each, a row of 9 values per item
    in one message per neighbour and kind), the local indices each rank is sent and each rank's ghosts received, in
    global-id order on both sides. The rows are packed and unpacked by one kernel each (kernels/halo.py) in buffers
    made once per set of lists, each neighbour's message a slice of one buffer. On the CPU the numpy views MPI reads
    and writes are those buffers themselves; on a GPU the messages are staged through page-locked host copies of them
    (:attr:`staged`; one copy each way a step, the caller synchronising the device once before the sends), which
    works with any MPI, CUDA-aware or not.

    Attributes:
        fields: State field names, each (capacity,) vec3 (or vec3d).
        dtype: the message's numpy dtype (float64 carries float32 values exactly).
        send: local indices of owned items by destination rank.
        recv: local indices of ghosts by source rank.
        tag: the MPI tag of its messages.
        device: the Warp device of the fields.
        staged: whether the messages go through host copies of the device buffers (None: :func:`staged_on`).
    """

    fields: tuple[str, ...]
    dtype: type
    send: dict[int, np.ndarray]
    recv: dict[int, np.ndarray]
    tag: int
    device: Any = "cpu"
    staged: bool | None = None

    def __post_init__(self) -> None:
        if len(self.fields) != 3:
            raise ValueError(f"a halo channel carries three vec3 fields, not {self.fields}")
        if self.staged is None:
            self.staged = staged_on(self.device)
        elif not (self.staged or wp.get_device(self.device).is_cpu):
            raise ValueError(f"a halo channel on {self.device} must be staged: MPI reads host memory")
        self._send_index, self._send_rows, self._send_host, self.outbox = self._buffer(self.send)
        self._recv_index, self._recv_rows, self._recv_host, self.inbox = self._buffer(self.recv)
        self._recorded: dict[str, tuple[tuple[wp.array, ...], Any]] = {}  # pack/unpack: the arrays, their launch

    def _buffer(self, by_rank: dict[int, np.ndarray]) -> tuple[wp.array, wp.array, wp.array, dict[int, np.ndarray]]:
        """The local indices of ``by_rank``'s items one rank after the other (int32), a buffer of their rows (3 vec3
        of the message's precision per item), the host array MPI reads or writes (the buffer itself unless staged)
        and each rank's rows in that as a (count, 9) numpy view."""
        index = np.concatenate([by_rank[r] for r in by_rank]) if by_rank else np.zeros(0, dtype=np.int32)
        vec = wp.vec3d if np.dtype(self.dtype) == np.float64 else wp.vec3f
        rows = wp.empty(3 * len(index), dtype=vec, device=self.device)
        host = host_mirror(rows) if self.staged else rows
        view = host.numpy().reshape(len(index), 9)
        blocks, start = {}, 0
        for r, idx in by_rank.items():
            blocks[r] = view[start : start + len(idx)]
            start += len(idx)
        return wp.array(index.astype(np.int32), dtype=int, device=self.device), rows, host, blocks

    def pack(self, state: State) -> None:
        """Every destination's rows from the owned items' fields in ``state`` (one launch; staged: then copied to the
        host, asynchronously on a GPU: the caller synchronises before the sends)."""
        if self._send_index.shape[0]:
            fields = [getattr(state, name) for name in self.fields]
            self._launch("pack", kh.pack_rows_kernel, [*fields, self._send_index], [self._send_rows], self._send_index)
            if self.staged:
                wp.copy(self._send_host, self._send_rows)

    def unpack(self, state: State) -> None:
        """The ghosts' fields in ``state`` from the rows received (staged: copied to the device first; one launch)."""
        if self._recv_index.shape[0]:
            if self.staged:
                wp.copy(self._recv_rows, self._recv_host)
            fields = [getattr(state, name) for name in self.fields]
            self._launch("unpack", kh.unpack_rows_kernel, [self._recv_rows, self._recv_index], fields, self._recv_index)

    def _launch(
        self, what: str, kernel: wp.Kernel, inputs: list[wp.array], outputs: list[wp.array], index: wp.array
    ) -> None:
        """Launch ``kernel`` over the items of ``index``, from a launch recorded for these very arrays (a step launches
        it again and again: a recorded launch skips the checks and packing of its arguments, most of a small
        launch's cost on the CPU); recorded again when the state's arrays were replaced (a regrowth). The record
        keeps the arrays, so no other array can take their identity."""
        arrays = (*inputs, *outputs)
        kept = self._recorded.get(what)
        if kept is None or any(a is not b for a, b in zip(kept[0], arrays, strict=True)):
            dim = index.shape[0]
            command = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device, record_cmd=True)
            kept = self._recorded[what] = (arrays, command)
        kept[1].launch()

    @staticmethod
    def between(
        fields: tuple[str, ...],
        dtype: type,
        tag: int,
        rank: int,
        owner: np.ndarray,
        held_by: list[np.ndarray],
        device: Any = "cpu",
    ) -> Channel:
        """The channel of local items whose ranks are ``owner`` (shape (n,)), where ``held_by[d]`` says which of them
        rank d holds (shape (n,), bool; every rank decides from the same data, so sends and receives match), of
        fields on ``device``."""
        recv = {src: np.flatnonzero(owner == src) for src in range(len(held_by)) if src != rank}
        mine = owner == rank
        send = {d: np.flatnonzero(mine & held) for d, held in enumerate(held_by) if d != rank}
        return Channel(
            fields,
            dtype,
            {d: idx for d, idx in send.items() if len(idx)},
            {s: idx for s, idx in recv.items() if len(idx)},
            tag,
            device,
        )

    @property
    def bytes_sent(self) -> int:
        """Bytes this rank sends of it a step."""
        return sum(block.nbytes for block in self.outbox.values())


class Ranked(Simulation):
    """A rank's part of a decomposed run, stepped (subclasses: what it holds, :meth:`_flag_moved`, :meth:`_exchange`).

    Args:
        comm: the MPI communicator (mpi4py).
        model: the rank's own model (its items and ghosts).
        state: its state.
        flags: the skin tests reduced over the ranks each step (``self._moved``'s length).
        **kwargs: as :class:`~warpdem.simulation.Simulation`'s. A step is not one recorded graph here: the halo runs
            on the host between its two halves, each recorded after its first eager run (:meth:`_body`).
    """

    channels: list[Channel]

    def __init__(self, comm: Any, model: Model, state: State, flags: int, **kwargs: Any) -> None:
        self.comm = comm
        self._moved = wp.zeros(flags, dtype=int, device=model.device)
        # What the reduction sends: on the CPU the array itself (through its numpy view); on a GPU a page-locked
        # copy, made each step in the halo's one synchronisation (:meth:`_halo`).
        self._staged = staged_on(model.device)
        self._moved_host = host_mirror(self._moved) if self._staged else self._moved
        self._flags = self._moved_host.numpy()
        self._moved_all = np.zeros_like(self._flags)  # the reduction's result, every rank's flags (reused each step)
        self._busy = 0.0  # seconds of this rank's own step work since the ranks' work was last compared
        self.times = dict.fromkeys(STEP_TIMES, 0.0)  # where this rank's step time went [s], since the start
        self._slowest = -1  # the rank found slowest at that comparison (-1: none)
        self.migrations = 0  # times the items moved between ranks since the start (every rank counts alike)
        super().__init__(model, state, use_graph=False, **kwargs)

    def _setup(self) -> None:
        super()._setup()
        self._halves: tuple | None = None  # new arrays: the recorded halves are recorded again

    # ------------------------------------------------------------------------------------------------------------
    # The step
    def _flag_moved(self) -> None:
        """The owned items' skin tests into ``self._moved``, and the drift's own flags lowered (a ghost's drift on a
        partial force may have raised them; what is rebuilt is decided together, :meth:`_exchange`). Launches only."""
        raise NotImplementedError

    def _exchange(self) -> None:
        """Between the drift and the forces: the halo (:meth:`_halo`) and what every rank decides with it."""
        raise NotImplementedError

    def _drift_half(self) -> None:
        """A step's launches before the halo: kick, drift, the skin tests."""
        kick_drift(self.model, self.state, self.track_energy, self.drift_nodes)
        self._flag_moved()

    def _head(self) -> None:
        integrate_first_half(self.model, self.state, self.track_energy, self.drift_nodes)
        self._flag_moved()
        self._exchange()
        self._forces()

    def _body(self) -> None:
        start = time.perf_counter()
        if self._halves is None:
            self._drift_half()
        else:
            wp.capture_launch(self._halves[0])
        first = self._finished() - start
        start = time.perf_counter()
        self._exchange()
        self.times["exchange"] += time.perf_counter() - start
        start = time.perf_counter()
        if self._halves is None:  # none yet, or new arrays dropped them
            self._forces()
            self._record_halves()
        else:
            wp.capture_launch(self._halves[1])
        # The rank's own work (its kernels run on this thread on the CPU), not its waits: the measured cost the slabs
        # are balanced by.
        work = first + self._finished() - start
        self._busy += work
        self.times["kernels"] += work

    def _finished(self) -> float:
        """The clock [s] once the work launched so far has run: on a GPU after waiting for it (the halo waits for the
        first half anyway; the second's wait is what measuring a GPU rank's work costs)."""
        if not self.model.device.is_cpu:
            wp.synchronize_device(self.model.device)
        return time.perf_counter()

    def _record_halves(self) -> None:
        """Record the two halves of a step (after an eager run of each, so every kernel is compiled)."""
        graphs = []
        for part in (self._drift_half, self._forces):
            with wp.ScopedCapture(device=self.model.device) as capture:
                part()
            graphs.append(capture.graph)
        self._halves = tuple(graphs)

    def _halo(self) -> np.ndarray:
        """One message to each rank per channel that holds owned items as ghosts (rows of each item's vec3 fields);
        with them, one reduction of the owned items' skin tests, whose result it returns (``self._moved``'s shape).
        One wait for all, so the ranks meet once a step."""
        from mpi4py import MPI

        clock = [time.perf_counter()]
        requests = [
            self.comm.Irecv(block, source=src, tag=channel.tag)
            for channel in self.channels
            for src, block in channel.inbox.items()
        ]
        for channel in self.channels:
            channel.pack(self.state)
        if self._staged:
            # The skin tests and the packed rows to the host, and one wait for the device before MPI reads them.
            wp.copy(self._moved_host, self._moved)
            wp.synchronize_device(self.model.device)
        clock.append(time.perf_counter())
        moved = self._moved_all
        requests.append(self.comm.Iallreduce(self._flags, moved, op=MPI.MAX))
        for channel in self.channels:
            for dest, block in channel.outbox.items():
                requests.append(self.comm.Isend(block, dest=dest, tag=channel.tag))
        clock.append(time.perf_counter())
        MPI.Request.Waitall(requests)
        clock.append(time.perf_counter())
        for channel in self.channels:
            channel.unpack(self.state)
        if self._staged:
            wp.synchronize_device(self.model.device)  # the unpacking's time, not the next half's
        clock.append(time.perf_counter())
        for name, spent in zip(("pack", "post", "wait", "unpack"), np.diff(clock), strict=True):
            self.times[name] += spent
        return moved

    # ------------------------------------------------------------------------------------------------------------
    # Between steps
    def _measured_work(self) -> np.ndarray | None:
        """At a list rebuild: every rank's measured step work since the last decision [s] (the same figures on every
        rank) when the same rank's exceeded the mean by more than :data:`IMBALANCE` twice running, so that the slabs
        are cut again; None when they are even, when too little was measured to tell (under :data:`MEASURED` on some
        rank), or on the first uneven window (a 2-core machine's timings wander by ±20 % between windows of one cut:
        one window alone would cut the slabs back and forth)."""
        busy = np.array(self.comm.allgather(self._busy))
        if busy.min() < MEASURED:
            return None
        self._busy = 0.0
        slowest = int(np.argmax(busy)) if busy.max() > IMBALANCE * busy.mean() else -1
        confirmed = slowest >= 0 and slowest == self._slowest
        self._slowest = -1 if confirmed else slowest
        return busy if confirmed else None

    def _advance_chunk(self, n_steps: int) -> int:
        """n steps, then the status read: the guard's verdict is every rank's (one rank's bad item stops all)."""
        self._run(n_steps)
        self._epilogue()
        status = self.status.read()
        self.step_count += n_steps
        self.time = status.time
        report = self.guard.interpret(status.guard)
        from mpi4py import MPI

        if self.comm.allreduce(report is not None, op=MPI.LOR):
            if report is not None:
                raise self.guard.error(self.model, self.state, report, self.step_count, self.time)
            raise UnstableRunError(
                self.time, self.step_count, "another rank's items", "see the first rank's message", ""
            )
        # Broken bonds compacted away at the chunk's end, as in one process (every rank sees the same bonds break).
        self.remove_broken_bonds(status.bonds_broken)
        if self.model.node_capacity:
            # As one process: the tet stresses brought up to date for whoever reads the state now.
            eval_tet_stresses(self.model, self.state)
        return 0

    def halo_bytes(self) -> int:
        """Bytes this rank sends in a step's halo messages."""
        return sum(channel.bytes_sent for channel in self.channels)

    def owned_part(self) -> Any:
        """What this rank owns, as rows keyed by global id, with the largest count its lists needed (picklable): what
        is written into the whole run's state (:meth:`write_whole`)."""
        raise NotImplementedError

    def write_whole(self, model: Model, state: State, parts: list[Any]) -> tuple[Model, State]:
        """Write every rank's :meth:`owned_part` into the whole run's ``model``/``state``, the arrays every rank holds
        alike from this rank's (:meth:`_share_into`), the lists' largest count over the parts; returns them, grown
        where a part has more list slots."""
        raise NotImplementedError

    def _share_into(self, state: State) -> None:
        """The arrays every rank holds alike (:data:`SHARED_FIELDS`), from this rank's state into ``state``."""
        for name in SHARED_FIELDS:
            getattr(state, name).assign(getattr(self.state, name))
