"""Node and sphere numberings for memory locality: the Z order of points, and nodes grouped block by block after
the joints' pre-split (:data:`NODE_ORDERS`, the choices of ModelBuilder.finalize)."""

from __future__ import annotations

import numpy as np

from ..model import Model, State
from .fragments import block_labels


def morton_order(q: np.ndarray, cell: float) -> np.ndarray:
    """Permutation that sorts points along a Z-order curve of cells of size ``cell`` (memory locality)."""
    if len(q) == 0:
        return np.zeros(0, dtype=np.int64)
    c = np.floor((q - q.min(axis=0)) / cell).astype(np.uint64)
    c = np.minimum(c, np.uint64(2**21 - 1))
    code = np.zeros(len(q), dtype=np.uint64)
    for bit in range(21):
        for axis in range(3):
            code |= ((c[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def block_node_order(model: Model, state: State) -> np.ndarray:
    """A node numbering for memory locality after the joints' pre-split, which numbers each split node's daughters
    past all the mesh's nodes, far from their block's other nodes: the blocks (warpdem.stages.fragments.block_labels:
    tets connected through shared nodes) in the Z order of their centroids on cells of the mean block size, each block's
    nodes together in their old order, nodes of no tet last. A body's nodes are then contiguous, and a node–face
    contact's face nodes (a neighbouring block's) near in memory: `bench blocks` gains with it at 103 823 blocks and
    breaks even at 4096, where the split's numbering suits the node–face stage better (benchmarks/README.md,
    "bench blocks").

    Returns:
        New node i = old node order[i], shape (node_count,), int64.
    """
    label, count = block_labels(model, state)
    if count == 0:
        return np.arange(len(label), dtype=np.int64)
    q = model.node_ref_q.numpy()[: len(label)].astype(np.float64)
    inside = label >= 0
    sums = np.zeros((count, 3))
    np.add.at(sums, label[inside], q[inside])
    centroid = sums / np.bincount(label[inside], minlength=count)[:, None]
    extent = np.ptp(q[inside], axis=0)
    cell = max(float(np.prod(np.maximum(extent, 1e-12)) / count) ** (1.0 / 3.0), 1e-12)
    rank = np.empty(count, dtype=np.int64)
    rank[morton_order(centroid, cell)] = np.arange(count)
    key = np.where(inside, rank[np.maximum(label, 0)], count)
    return np.argsort(key, kind="stable").astype(np.int64)


NODE_ORDERS = {"split": None, "blocks": block_node_order}
"""The node numberings of :meth:`ModelBuilder.finalize`: name → the order after the pre-split (None: keep it)."""
