"""Compaction passes: flag → exclusive scan → scatter → remap (deterministic by construction).

Used wherever topology changes: removing broken bonds; appending new node slots when joints are pre-split (and when
nodes split at run time); converting tets later. The scan itself is ``wp.utils.array_scan``; these kernels are the
steps around it.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def flag_survivors_kernel(
    # In:
    count: wp.array(dtype=int),
    dead: wp.array(dtype=int),
    # Out:
    keep: wp.array(dtype=int),
):
    k = wp.tid()  # one thread per slot of the compacted set (over its capacity)
    if k < count[0] and dead[k] == 0:
        keep[k] = 1
    else:
        keep[k] = 0


@wp.kernel
def old_to_new_kernel(
    # In:
    count: wp.array(dtype=int),
    keep: wp.array(dtype=int),
    offset: wp.array(dtype=int),
    # Out:
    old_to_new: wp.array(dtype=int),
    new_count: wp.array(dtype=int),
):
    k = wp.tid()  # one thread per slot (over capacity)
    if keep[k] != 0:
        old_to_new[k] = offset[k]
    else:
        old_to_new[k] = -1
    last = keep.shape[0] - 1
    if k == last:
        new_count[0] = offset[last] + keep[last]


@wp.kernel
def remap_indices_kernel(
    # In:
    old_to_new: wp.array(dtype=int),
    # State out:
    indices: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per stored index
    idx = indices[t]
    if idx >= 0:
        indices[t] = old_to_new[idx]


@wp.kernel
def first_new_slot_kernel(
    # In:
    count: wp.array(dtype=int),
    copies: wp.array(dtype=int),
    offset: wp.array(dtype=int),
    # Out:
    first_new: wp.array(dtype=int),
    new_count: wp.array(dtype=int),
):
    k = wp.tid()  # one thread per slot (over capacity)
    n = count[0]
    # The appended slots follow the live ones, in the order of their parents.
    if k < n:
        first_new[k] = n + offset[k]
    else:
        first_new[k] = -1
    last = copies.shape[0] - 1
    if k == last:
        # copies is zero past the live count (mask_copies_kernel), so the scan's last entry holds the total. The
        # count may exceed the capacity: the host learns the size it needs.
        new_count[0] = n + offset[last] + copies[last]


@wp.kernel
def mask_copies_kernel(
    # In:
    count: wp.array(dtype=int),
    copies_in: wp.array(dtype=int),
    # Out:
    copies: wp.array(dtype=int),
):
    k = wp.tid()  # one thread per slot (over capacity)
    if k < count[0]:
        copies[k] = wp.max(copies_in[k], 0)
    else:
        copies[k] = 0


# ----------------------------------------------------------------------------------------------------------------
# Fused passes over many arrays (issue 24): one launch carries a pass over every array of a set, whatever their
# number and types. Each array is seen as 32-bit words (every field type here is a multiple of 4 bytes: int32,
# float32, vectors, matrices, float64), through a table of (pointer, words per slot, words in all) built on the host
# once per set of arrays (warpdem.fused.WordTable). Copying words copies values bit for bit.


@wp.kernel
def replicate_words_kernel(
    # In:
    count: wp.array(dtype=int),
    copies: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    pointers: wp.array(dtype=wp.uint64),
    slot_words: wp.array(dtype=int),
    total_words: wp.array(dtype=int),
):
    k = wp.tid()  # one thread per parent slot; it writes its appended slots in every array of the table
    if k >= count[0] or copies[k] == 0:  # most parents have no copies: one test each, not one per array
        return
    first = first_new[k]
    for i in range(pointers.shape[0]):
        w = slot_words[i]
        n = total_words[i]
        words = wp.array(ptr=pointers[i], shape=(n,), dtype=wp.int32)
        for c in range(copies[k]):
            dst = first + c
            # Past capacity: the host grows and redoes the pass, nothing is written out of bounds.
            if (dst + 1) * w <= n:
                for r in range(w):
                    words[dst * w + r] = words[k * w + r]


@wp.kernel
def gather_survivor_words_kernel(
    # In:
    count: wp.array(dtype=int),
    old_to_new: wp.array(dtype=int),
    pointers: wp.array(dtype=wp.uint64),
    slot_words: wp.array(dtype=int),
    total_words: wp.array(dtype=int),
    scratch_offset: wp.array(dtype=int),
    # Out:
    scratch: wp.array(dtype=wp.int32),
):
    i, k = wp.tid()  # one thread per (array, old slot): its survivor's words go to the new slot in the scratch
    if k >= count[0]:
        return
    new = old_to_new[k]
    if new < 0:
        return
    w = slot_words[i]
    words = wp.array(ptr=pointers[i], shape=(total_words[i],), dtype=wp.int32)
    base = scratch_offset[i]
    for r in range(w):
        scratch[base + new * w + r] = words[k * w + r]


@wp.kernel
def copy_back_words_kernel(
    # In:
    pointers: wp.array(dtype=wp.uint64),
    slot_words: wp.array(dtype=int),
    total_words: wp.array(dtype=int),
    scratch_offset: wp.array(dtype=int),
    scratch: wp.array(dtype=wp.int32),
):
    i, k = wp.tid()  # one thread per (array, slot over the capacity): the compacted slot, zero past the survivors
    w = slot_words[i]
    n = total_words[i]
    if (k + 1) * w > n:
        return
    words = wp.array(ptr=pointers[i], shape=(n,), dtype=wp.int32)
    base = scratch_offset[i]
    for r in range(w):
        words[k * w + r] = scratch[base + k * w + r]
