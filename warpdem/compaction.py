"""The one compaction helper: flag → exclusive scan → scatter → remap, on the device.

Removing broken bonds uses it now; node splitting and tet conversion reuse it. A pass keeps the survivors in
their original order, so it is deterministic, and it produces an ``old_to_new`` map (-1 for removed slots) that
:meth:`Compactor.remap` applies to every index array pointing into the compacted set.
"""

from __future__ import annotations

from collections.abc import Sequence

import warp as wp

from .kernels import compaction as kc


class Compactor:
    """Compacts a set of parallel arrays of one capacity.

    Args:
        capacity: slots of the compacted set.
        device: Warp device.
    """

    def __init__(self, capacity: int, device: wp.context.Device) -> None:
        self.capacity = capacity
        self.device = device
        self.keep = wp.zeros(capacity, dtype=int, device=device)
        self.offset = wp.zeros(capacity, dtype=int, device=device)
        self.old_to_new = wp.zeros(capacity, dtype=int, device=device)
        self.new_count = wp.zeros(1, dtype=int, device=device)
        self._scratch: dict[tuple, wp.array] = {}

    def plan(self, count: wp.array, dead: wp.array) -> wp.array:
        """Flag the survivors (slot < count and dead == 0), scan, and build ``old_to_new``.

        Args:
            count: live slots, shape (1,), int32.
            dead: non-zero for slots to remove, shape (capacity,), int32.

        Returns:
            ``old_to_new``, shape (capacity,), int32; ``self.new_count`` holds the survivors' count.
        """
        if self.capacity == 0:
            self.new_count.zero_()
            return self.old_to_new
        wp.launch(
            kc.flag_survivors_kernel, dim=self.capacity, inputs=[count, dead], outputs=[self.keep], device=self.device
        )
        wp.utils.array_scan(self.keep, self.offset, inclusive=False)
        wp.launch(
            kc.old_to_new_kernel,
            dim=self.capacity,
            inputs=[count, self.keep, self.offset],
            outputs=[self.old_to_new, self.new_count],
            device=self.device,
        )
        return self.old_to_new

    def scatter(self, count: wp.array, arrays: Sequence[wp.array]) -> None:
        """Move the survivors of each array to their new slots, in place (through a scratch buffer)."""
        for a in arrays:
            key = (a.dtype, a.shape)
            tmp = self._scratch.get(key)
            if tmp is None:
                tmp = self._scratch[key] = wp.zeros_like(a)
            else:
                tmp.zero_()  # slots past the survivors must not keep another array's leftovers (bitwise restarts)
            wp.launch(
                kc.scatter_kernel,
                dim=self.capacity,
                inputs=[count, self.old_to_new, a],
                outputs=[tmp],
                device=self.device,
            )
            wp.copy(a, tmp)

    def remap(self, indices: wp.array) -> None:
        """Rewrite an index array that points into the compacted set (negative entries stay as they are)."""
        if indices.shape[0]:
            wp.launch(
                kc.remap_indices_kernel,
                dim=indices.shape[0],
                inputs=[self.old_to_new],
                outputs=[indices],
                device=self.device,
            )

    def finish(self, count: wp.array) -> None:
        """Set the compacted set's live count to the survivors' count."""
        wp.copy(count, self.new_count)
