"""The one compaction helper: flag → exclusive scan → scatter → remap, on the device.

Removing broken bonds uses it now; node splitting and tet conversion reuse it. A pass keeps the survivors in
their original order, so it is deterministic, and it produces an ``old_to_new`` map (-1 for removed slots) that
:meth:`Compactor.remap` applies to every index array pointing into the compacted set.

The same helper runs the mirror-image pass that *appends* slots (pre-split joints now, nodal fracture later):
count the copies each live slot needs → exclusive scan → each parent's first new slot (``count + offset``) →
:meth:`Compactor.replicate` copies the parent into its new slots. The new slots follow the live ones in the order
of their parents, so this pass is deterministic too; a total past the capacity writes nothing out of bounds and
leaves ``new_count`` at the size the host must grow to before redoing the pass.
"""

from __future__ import annotations

from collections.abc import Sequence

import warp as wp

from ..fused import WordTable, cached_table
from ..kernels import compaction as kc

MAX_TABLES = 16
"""Word tables a Compactor keeps (one per set of arrays it has seen since the last growth)."""


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
        self._tables: dict[tuple, WordTable] = {}

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
        """Move the survivors of each array to their new slots, in place: three launches for all the arrays together
        (zero a scratch buffer, gather the survivors' words into it, copy it back; slots past the survivors come back
        zero, so they do not keep a removed slot's leftovers and restarts stay bitwise)."""
        table = self._table(arrays)
        if table.rows == 0:
            return
        table.scratch.zero_()
        wp.launch(
            kc.gather_survivor_words_kernel,
            dim=(table.rows, self.capacity),
            inputs=[count, self.old_to_new, *table.args(), table.offset],
            outputs=[table.scratch],
            device=self.device,
        )
        wp.launch(
            kc.copy_back_words_kernel,
            dim=(table.rows, self.capacity),
            inputs=[*table.args(), table.offset, table.scratch],
            device=self.device,
        )

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

    def remove(
        self, count: wp.array, dead: wp.array, arrays: Sequence[wp.array], remap: Sequence[wp.array] = ()
    ) -> None:
        """A whole removal pass: :meth:`plan`, :meth:`scatter` ``arrays``, :meth:`remap` the index arrays ``remap``
        that point into the set, and :meth:`finish` (the live ``count`` becomes the survivors' count).

        Args:
            count: live slots, shape (1,), int32 (updated).
            dead: non-zero for slots to remove, shape (capacity,), int32.
            arrays: the parallel arrays of the set, each of shape (capacity,) (``dead`` may be one of them).
            remap: index arrays pointing into the set (negative entries stay as they are).
        """
        self.plan(count, dead)
        self.scatter(count, arrays)
        for indices in remap:
            self.remap(indices)
        self.finish(count)

    def plan_append(self, count: wp.array, copies: wp.array) -> wp.array:
        """Plan an append pass: live slot k (k < count) gets ``copies[k]`` new slots after the live ones.

        Args:
            count: live slots, shape (1,), int32.
            copies: new slots wanted per slot (negative and past-count entries count as 0), shape (capacity,).

        Returns:
            ``first_new``: first appended slot of each live slot (-1 past the count), shape (capacity,), int32; its
            copies take ``first_new[k] .. first_new[k] + copies[k] - 1``. ``self.new_count`` holds count + Σ copies,
            which may exceed the capacity (then grow and redo; :meth:`replicate` writes nothing out of bounds).
        """
        if self.capacity == 0:
            wp.copy(self.new_count, count)
            return self.old_to_new
        wp.launch(
            kc.mask_copies_kernel, dim=self.capacity, inputs=[count, copies], outputs=[self.keep], device=self.device
        )
        wp.utils.array_scan(self.keep, self.offset, inclusive=False)
        wp.launch(
            kc.first_new_slot_kernel,
            dim=self.capacity,
            inputs=[count, self.keep, self.offset],
            outputs=[self.old_to_new, self.new_count],
            device=self.device,
        )
        return self.old_to_new

    @property
    def first_new(self) -> wp.array:
        """First appended slot of each live slot after :meth:`plan_append` (the buffer ``old_to_new`` uses for a
        removal pass: one Compactor runs one pass at a time)."""
        return self.old_to_new

    @property
    def copies(self) -> wp.array:
        """Appended slots of each slot after :meth:`plan_append` (0 past the count), shape (capacity,), int32."""
        return self.keep

    def replicate(self, count: wp.array, arrays: Sequence[wp.array], per_row: int = 1) -> None:
        """Copy every live slot of each array into its appended slots (after :meth:`plan_append`), in place; with
        ``per_row`` > 1 each slot is a row of that many entries (e.g. a node's wall springs, one per wall)."""
        self.replicate_rows(count, [(a, per_row) for a in arrays])

    def replicate_rows(self, count: wp.array, rows: Sequence[tuple[wp.array, int]]) -> None:
        """:meth:`replicate` for many arrays at once, each with its own row length: (array, entries per slot). One
        launch, whatever the number of arrays."""
        if self.capacity == 0:
            return
        table = self.rows_table(rows)
        if table.rows:
            wp.launch(
                kc.replicate_words_kernel,
                dim=self.capacity,
                inputs=[count, self.keep, self.old_to_new, *table.args()],
                device=self.device,
            )

    def rows_table(self, rows: Sequence[tuple[wp.array, int]]) -> WordTable:
        """The word table :meth:`replicate_rows` launches over for ``rows``, built now if not kept (so that a recording
        of the replicate allocates nothing, warpdem.recorded)."""
        return self._table([a for a, _ in rows], [per_row for _, per_row in rows])

    def _table(self, arrays: Sequence[wp.array], per_row: Sequence[int] | None = None) -> WordTable:
        """The word table of a set of arrays (kept while the same arrays come again: no allocation per pass)."""
        per_row = [1] * len(arrays) if per_row is None else list(per_row)
        # Empty arrays (a set of no slots) have no address and nothing to move.
        kept = [(a, n) for a, n in zip(arrays, per_row, strict=True) if a.size]
        arrays, per_row = [a for a, _ in kept], [n for _, n in kept]
        return cached_table(self._tables, arrays, per_row, self.capacity, self.device, MAX_TABLES)

    def finish(self, count: wp.array) -> None:
        """Set the live count to the pass's new count (the survivors of a removal, count + copies of an append)."""
        wp.copy(count, self.new_count)


def grow_live_slots(state: object, fields: Sequence[str], live: int, capacity: int) -> dict[str, wp.array]:
    """New arrays of ``capacity`` slots for the named fields of ``state`` (a set compacted together: cohesive
    elements, couplings), the first ``live`` slots copied, the others zero; the caller swaps them in between steps."""
    out = {}
    for name in fields:
        old = getattr(state, name)
        new = wp.zeros(capacity, dtype=old.dtype, device=old.device)
        if live:
            wp.copy(new, old, count=live)
        out[name] = new
    return out
