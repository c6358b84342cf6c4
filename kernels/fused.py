"""Fused copies over many arrays (warpdem.fused): each array seen as 32-bit words through a table of addresses."""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def copy_words_kernel(
    # In:
    source: wp.array(dtype=wp.uint64),
    total_words: wp.array(dtype=int),
    threads: int,
    # Out (the arrays the addresses point at):
    target: wp.array(dtype=wp.uint64),
):
    i, c = wp.tid()  # one of ``threads`` threads of array i; it copies words c, c + threads, c + 2 threads, ...
    n = total_words[i]
    src = wp.array(ptr=source[i], shape=(n,), dtype=wp.int32)
    dst = wp.array(ptr=target[i], shape=(n,), dtype=wp.int32)
    j = c
    while j < n:
        dst[j] = src[j]
        j += threads
