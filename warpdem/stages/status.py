"""The chunk status (issue 24): after a run of steps, everything the host must know gathered on the device into one
small vector and read back once (kernels/status.py): the lists' largest counts (a growth and redo is due when they
pass their slots), the device clock, the stability guard's report, how many bonds and cohesive elements broke (a
compaction is due) and the live cohesive count. Before it, each of these was its own read-back, and the broken flags
were read back whole (every bond, every element, every chunk).
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from ..kernels import status as ks
from ..model import Model, State


@dataclass(frozen=True)
class ChunkStatus:
    """The status after a run of steps (counts, the clock [s], the guard's four values)."""

    nbr_needed: int
    sphere_face_needed: int
    node_face_needed: int
    time: float
    guard: tuple[float, float, float, float]
    bonds_broken: int
    cohesive_broken: int
    cohesive_count: int


class StatusReader:
    """Gathers and reads the chunk status: one launch (:meth:`launch`, which a recording may replay), one read-back
    (:meth:`read`).

    Args:
        device: Warp device of the model.
    """

    def __init__(self, device: wp.context.Device) -> None:
        self.values = wp.zeros(ks.SLOTS, dtype=wp.float64, device=device)
        self.needs = wp.zeros(3, dtype=int, device=device)

    def read_needs(self, state: State) -> tuple[int, int, int]:
        """The lists' largest counts since their last build (neighbours, sphere–face, node–face), in one read-back
        (between steps: after a set-up or a pass's force evaluation)."""
        wp.launch(
            ks.list_needs_kernel,
            dim=1,
            inputs=[state.nbr_needed, state.sphere_face_needed, state.node_face_needed],
            outputs=[self.needs],
            device=self.needs.device,
        )
        nbr, sphere_face, node_face = (int(x) for x in self.needs.numpy())
        return nbr, sphere_face, node_face

    def launch(self, model: Model, state: State, report: wp.array, clean: wp.array) -> None:
        """Gather the status of ``state`` (launches only). ``report`` (the stability guard's, its launches done) is
        copied in and reset to ``clean`` for the next check."""
        m, s = model, state
        self.values.zero_()
        wp.launch(
            ks.chunk_status_kernel,
            dim=max(m.bond_capacity, m.cohesive_capacity, 1),
            inputs=[
                s.nbr_needed,
                s.sphere_face_needed,
                s.node_face_needed,
                s.time,
                s.bond_count,
                s.bond_broken,
                s.cohesive_count,
                s.cohesive_broken,
                clean,
            ],
            outputs=[report, self.values],
            device=m.device,
        )

    def read(self) -> ChunkStatus:
        """Read back the status :meth:`launch` gathered."""
        v = self.values.numpy()
        return ChunkStatus(
            nbr_needed=int(v[ks.NBR_NEEDED]),
            sphere_face_needed=int(v[ks.SPHERE_FACE_NEEDED]),
            node_face_needed=int(v[ks.NODE_FACE_NEEDED]),
            time=float(v[ks.TIME]),
            guard=tuple(float(x) for x in v[ks.GUARD : ks.GUARD + 4]),
            bonds_broken=int(v[ks.BONDS_BROKEN]),
            cohesive_broken=int(v[ks.COHESIVE_BROKEN]),
            cohesive_count=int(v[ks.COHESIVE_COUNT]),
        )
