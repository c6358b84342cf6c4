"""Space cut into slabs, one per rank (recursive coordinate bisection of 2–4 ranks along one axis is a row of
slabs): who owns a sphere, and which ranks hold it as a ghost.

A sphere belongs to the slab its centre lies in. Rank ``d`` holds as ghosts the spheres of other slabs within the
halo width of its own: a pair that can enter a list (centres closer than r_i + r_j + skin ≤ 2 r_max + skin) has its
other sphere within that width of the slab, so every pair of an owned sphere is seen whole.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Slabs:
    """Slabs along one axis.

    Attributes:
        axis: 0, 1 or 2 (x, y, z).
        cuts: the n_ranks - 1 interior boundaries [m], ascending; slab r is [cuts[r - 1], cuts[r]) with the outer two
            open to infinity.
        halo: ghost width [m] beyond a slab's faces.
    """

    axis: int
    cuts: tuple[float, ...]
    halo: float

    @property
    def ranks(self) -> int:
        return len(self.cuts) + 1

    @staticmethod
    def balanced(q: np.ndarray, weight: np.ndarray, ranks: int, halo: float, axis: int | None = None) -> Slabs:
        """Slabs across the longest extent of the centres ``q`` (shape (n, 3); or along ``axis``) holding equal shares
        of ``weight`` (the spheres' measured or estimated cost, shape (n,))."""
        if axis is None:
            extent = q.max(axis=0) - q.min(axis=0) if len(q) else np.zeros(3)
            axis = int(np.argmax(extent))
        x = q[:, axis]
        order = np.argsort(x, kind="stable")
        share = np.cumsum(weight[order]) / max(float(weight.sum()), 1e-300)
        cuts = []
        for r in range(1, ranks):
            k = int(np.searchsorted(share, r / ranks))
            k = min(max(k, 0), len(x) - 1)
            # Halfway between two neighbouring centres, so no centre sits on a cut.
            cuts.append(0.5 * (x[order[k]] + x[order[min(k + 1, len(x) - 1)]]) if len(x) else 0.0)
        return Slabs(axis, tuple(float(c) for c in np.maximum.accumulate(cuts)), float(halo))

    def owner(self, q: np.ndarray) -> np.ndarray:
        """The rank that owns each centre (shape (n, 3) → (n,), int)."""
        return np.searchsorted(np.asarray(self.cuts), q[:, self.axis], side="right").astype(np.int64)

    def holds(self, q: np.ndarray, rank: int) -> np.ndarray:
        """Whether rank ``rank`` holds each centre, owned or as a ghost (shape (n,), bool)."""
        x = q[:, self.axis]
        lo = self.cuts[rank - 1] - self.halo if rank > 0 else -np.inf
        hi = self.cuts[rank] + self.halo if rank < len(self.cuts) else np.inf
        return (x >= lo) & (x < hi)
