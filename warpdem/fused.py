"""Fused passes over many arrays (issue 24): one launch for a pass over every array of a set, whatever their number
and types, where one launch (or one copy) per array would pay a driver call each on a GPU and ~30 µs of Python each
on the CPU.

Each array is seen as 32-bit words (every field type warpdem stores is a multiple of 4 bytes: int32, float32,
vectors, matrices, quaternions, float64) through a :class:`WordTable`: the arrays' addresses, words per slot and
words in all, on the device. Kernels index a table row by row (kernels/compaction.py for the replicate and removal
passes, kernels/fused.py for copies); copying words copies values bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import warp as wp

from .kernels import fused as kf


class WordTable:
    """A set of arrays seen as 32-bit words, for the fused passes of kernels/compaction.py: each array's pointer,
    words per slot and words in all, on the device, and (for a removal) a scratch buffer holding them all.

    Args:
        arrays: contiguous arrays of ``capacity`` slots (of ``per_row`` entries each), of types whose size is a
            multiple of 4 bytes.
        per_row: entries per slot of each array.
        capacity: slots of the set.
        device: Warp device.

    Raises:
        ValueError: an array is not contiguous, its type's size is not a multiple of 4 bytes, or its length is not
            ``capacity`` × its row.
    """

    def __init__(
        self, arrays: Sequence[wp.array], per_row: Sequence[int], capacity: int, device: wp.context.Device
    ) -> None:
        pointers, slot_words, total_words = [], [], []
        for a, n in zip(arrays, per_row, strict=True):
            size = wp.types.type_size_in_bytes(a.dtype)
            if not a.is_contiguous or size % 4 or a.size != capacity * n:
                raise ValueError(
                    f"WordTable: an array of {a.size} entries of {a.dtype.__name__} ({size} bytes, contiguous "
                    f"{a.is_contiguous}) is not a contiguous set of {capacity} slots of {n} entries in 4-byte words"
                )
            pointers.append(a.ptr)
            slot_words.append(n * size // 4)
            total_words.append(a.size * size // 4)
        self.rows = len(pointers)
        self.pointers = wp.array(pointers, dtype=wp.uint64, device=device)
        self.slot_words = wp.array(slot_words, dtype=int, device=device)
        self.total_words = wp.array(total_words, dtype=int, device=device)
        self.offset = wp.array(np.concatenate([[0], np.cumsum(total_words)[:-1]]).astype(np.int32), device=device)
        self._scratch_words = int(sum(total_words))
        self._scratch: wp.array | None = None

    def args(self) -> list[wp.array]:
        """The table as kernel arguments: pointers, words per slot, words in all."""
        return [self.pointers, self.slot_words, self.total_words]

    @property
    def scratch(self) -> wp.array:
        """A buffer of every array's words (allocated on first use)."""
        if self._scratch is None:
            self._scratch = wp.zeros(max(self._scratch_words, 1), dtype=wp.int32, device=self.pointers.device)
        return self._scratch


def table_key(arrays: Sequence[wp.array], per_row: Sequence[int]) -> tuple:
    """What a word table depends on: each array's address, length, type size and row."""
    return tuple((a.ptr, a.size, wp.types.type_size_in_bytes(a.dtype), n) for a, n in zip(arrays, per_row, strict=True))


def cached_table(
    cache: dict[tuple, WordTable],
    arrays: Sequence[wp.array],
    per_row: Sequence[int],
    capacity: int,
    device: wp.context.Device,
    limit: int,
) -> WordTable:
    """The word table of ``arrays`` from ``cache``, built and kept on a miss (no allocation when the same arrays come
    again, as they do pass after pass). Keyed by address, length, type size and row: a table describes the arrays'
    layout, so arrays allocated anew at the same address and of the same layout use it as well as the ones it was built
    for. A full cache (``limit`` tables: arrays reallocated by growths leave dead ones) is emptied first."""
    key = table_key(arrays, per_row)
    table = cache.get(key)
    if table is None:
        if len(cache) >= limit:
            cache.clear()
        table = cache[key] = WordTable(arrays, per_row, capacity, device)
    return table


COPY_THREADS_CUDA = 1 << 15
"""Threads per array of a fused copy on a GPU (each strides over its array, so neighbouring threads touch
neighbouring words); on the CPU one thread copies an array front to back."""

_COPY_TABLES: dict[tuple, WordTable] = {}
MAX_COPY_TABLES = 16
"""Tables :func:`copy_arrays` keeps (a state and its snapshot are two; a growth makes new ones)."""


def copy_arrays(dst: Sequence[wp.array], src: Sequence[wp.array]) -> None:
    """``wp.copy(d, s)`` for every pair, as one launch: arrays of the same lengths and types, contiguous, on one
    device (a State into another of the same capacities: ``warpdem.model.State.assign``). Each array is one slot of
    all its words in the tables.

    Raises:
        ValueError: two arrays of a pair differ in type or length, or an array is not contiguous 4-byte words.
    """
    pairs = [(d, s) for d, s in zip(dst, src, strict=True) if d.size or s.size]
    if not pairs:
        return
    for d, s in pairs:
        if d.dtype != s.dtype or d.shape != s.shape:
            raise ValueError(f"copy_arrays: {d.dtype.__name__}{d.shape} <- {s.dtype.__name__}{s.shape}")
    device = pairs[0][0].device
    whole = [d.size for d, _ in pairs]
    # Room for both tables of the pair, so that building one never evicts the other; a pair already kept is kept.
    missing = sum(table_key(side, whole) not in _COPY_TABLES for side in ([d for d, _ in pairs], [s for _, s in pairs]))
    if missing and len(_COPY_TABLES) + missing > MAX_COPY_TABLES:
        _COPY_TABLES.clear()
    to = cached_table(_COPY_TABLES, [d for d, _ in pairs], whole, 1, device, MAX_COPY_TABLES)
    of = cached_table(_COPY_TABLES, [s for _, s in pairs], whole, 1, device, MAX_COPY_TABLES)
    threads = COPY_THREADS_CUDA if device.is_cuda else 1
    wp.launch(
        kf.copy_words_kernel,
        dim=(to.rows, threads),
        inputs=[of.pointers, to.total_words, threads],
        outputs=[to.pointers],
        device=device,
    )
