"""A structured mesh of rock laid in courses of equal blocks (bricks): bedding joints between the courses, head joints
between the blocks of a course, every other course shifted by a fraction of a block (running bond), openings cut
out cell by cell. The LDEC §4 limestone (1.83 m × 0.30 m blocks around a tunnel) is its scene
(scenes/limestone_tunnel.toml).

Why structured: the blocks are boxes, and a Gmsh mesh of thin boxes that conforms to every joint has slivers (the
T-junctions where a head joint ends on a bedding plane give tets 1/20 of the target size, and the stable step
with them); a grid of cells of the target size, each split into 6 Kuhn tets (:func:`warpdem.build.mesh.box_mesh`), has
none. The grid: each block is ``nx × ny × nz`` cells with ``nx`` = the block length / h rounded up to a multiple
of what the stagger needs (so the shifted courses' head joints fall on grid lines), ``ny``, ``nz`` the depth and
height / h rounded up. The box is a whole number of cells from ``lo`` (its ``hi`` rounded to the nearest cell);
course k starts with a block at ``lo`` shifted by ``k × stagger`` block lengths (modulo one block). An opening
removes every cell whose centre lies inside it, so its walls follow the grid (a size that is no whole number of
cells rounds to the nearest one). An opening may also take the pieces of the blocks it cuts that are left smaller
than a fraction of a whole block (``min_piece``): a charge's equivalent cavity stands for its crushed zone, and the
staircase its cells cut from the bricks around it leaves pieces of a cell or two, rubble of that zone, whose
springs would otherwise set the rigid blocks' stable step (∝ sqrt(mass / stiffness), smallest for the smallest
piece).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..limits import MAX_ELEMENTS
from ..scene.continuum import block_cells, brick_cells
from ..tables import BOX_FACE_NAMES, OPENING_FACE_NAME, TET_FACES
from .geology import GeologyMesh, Room, Shaft, Tunnel
from .mesh import box_mesh

__all__ = ["BRICK_JOINT_SETS", "brick_cells", "mesh_bricks"]

BRICK_JOINT_SETS = ("bedding", "head")
"""Joint sets of a brick mesh: 0 between courses (normal z), 1 between the blocks of a course (normal x or y)."""


def _inside(opening: Tunnel | Shaft | Room, x: np.ndarray) -> np.ndarray:
    """Which points (M, 3) [m] lie inside an opening (boundary included)."""
    if isinstance(opening, Room):
        return np.all((x >= np.asarray(opening.lo)) & (x <= np.asarray(opening.hi)), axis=1)
    if isinstance(opening, Shaft):
        r2 = np.sum((x[:, :2] - np.asarray(opening.centre)) ** 2, axis=1)
        inside = r2 <= opening.radius**2
        if opening.bottom is not None:
            inside &= x[:, 2] >= opening.bottom
        if opening.top is not None:
            inside &= x[:, 2] <= opening.top
        return inside
    along = "xy".index(opening.axis)
    across = x[:, 1 - along] - opening.centre[0]
    up = x[:, 2] - opening.centre[1]
    if opening.shape == "circular":
        inside = across**2 + up**2 <= opening.radius**2
    else:
        half_w, half_h = 0.5 * opening.width, 0.5 * opening.height
        inside = (np.abs(across) <= half_w) & (np.abs(up) <= half_h)
        if opening.shape == "horseshoe":  # a semicircular crown of radius width/2 on straight walls
            spring = half_h - half_w
            inside &= (up <= spring) | (across**2 + (up - spring) ** 2 <= half_w**2)
    if opening.span is not None:
        inside &= (x[:, along] >= opening.span[0]) & (x[:, along] <= opening.span[1])
    return inside


def _small_pieces(
    keep: np.ndarray,
    removed: np.ndarray,
    block_key: np.ndarray,
    cell: np.ndarray,
    n: np.ndarray,
    whole: int,
    limit: float,
) -> np.ndarray:
    """Which tets (T,) lie in a piece smaller than ``limit`` × ``whole`` cells of a block an opening cut.

    Args:
        keep: (T,) tets still in the rock. removed: (T,) tets this opening removed. block_key: (T,) each tet's brick.
        cell: (T,) each tet's cell, numbered x fastest on the grid of n (3,) cells. whole: cells of a whole block.
        limit: fraction of a whole block below which a piece goes [-].
    """
    # A piece is a face-connected set of kept cells of one brick (a cut can leave two): its cells' labels settle on
    # the smallest cell number of the piece by passes of the minimum over the grid neighbours of the same brick, at
    # most a brick's length of passes.
    grid_keep = np.zeros(n[::-1], dtype=bool)
    grid_block = np.full(n[::-1], -1, dtype=np.int64)
    grid_keep.ravel()[cell[keep]] = True
    grid_block.ravel()[cell] = block_key
    none = np.iinfo(np.int64).max
    label = np.where(grid_keep, np.arange(grid_keep.size).reshape(grid_keep.shape), none)
    while True:
        before = label.copy()
        for axis in range(3):
            for step in (1, -1):
                lo = [slice(None)] * 3
                hi = [slice(None)] * 3
                lo[axis], hi[axis] = (slice(0, -1), slice(1, None)) if step == 1 else (slice(1, None), slice(0, -1))
                a, b = tuple(lo), tuple(hi)
                joined = grid_keep[a] & grid_keep[b] & (grid_block[a] == grid_block[b])
                label[a] = np.where(joined, np.minimum(label[a], label[b]), label[a])
        if np.array_equal(label, before):
            break
    cut_blocks = np.unique(block_key[removed])
    flat_label = label.ravel()
    in_cut = grid_keep.ravel() & np.isin(grid_block.ravel(), cut_blocks)
    pieces, size = np.unique(flat_label[in_cut], return_counts=True)
    small = pieces[size < limit * whole]
    return keep & np.isin(flat_label[cell], small)


def mesh_bricks(
    lo: Sequence[float],
    hi: Sequence[float],
    brick: Sequence[float],
    h: float,
    material: str,
    stagger: float = 0.5,
    openings: Sequence[Tunnel | Shaft | Room] = (),
    min_pieces: Sequence[float] | None = None,
) -> GeologyMesh:
    """The brick mesh of the box [lo, hi] (module docstring).

    Args:
        lo: lower corner of the box [m].
        hi: upper corner of the box [m]; rounded to whole cells.
        brick: block length along x, depth along y and height along z [m].
        h: largest cell edge [m].
        material: the rock's material name.
        stagger: shift of each course against the one below, in block lengths, [0, 1).
        openings: cut out cell by cell.
        min_pieces: per opening, the fraction of a whole block's volume [0, 1) below which a connected piece of a
            block it cuts is removed with it; ``None``: 0 for each (every piece stays).

    Returns:
        The mesh: joint sets :data:`BRICK_JOINT_SETS`, one block (``tet_block``) per brick piece left after the
        openings, the box faces and ``"opening"`` as face sets.

    Raises:
        ValueError: a size that is not positive, a stagger outside [0, 1), a min_pieces entry outside [0, 1) or
            of another length than openings, or openings that remove every cell.
    """
    lo_a, hi_a, size = (np.asarray(v, dtype=np.float64) for v in (lo, hi, brick))
    if not (h > 0 and np.all(size > 0) and np.all(hi_a > lo_a)):
        raise ValueError(f"bricks: need h > 0, brick sizes > 0 and hi > lo, got h {h}, brick {size.tolist()}")
    if not 0.0 <= stagger < 1.0:
        raise ValueError(f"bricks: stagger must lie in [0, 1) block lengths, got {stagger}")
    limits = [0.0] * len(openings) if min_pieces is None else [float(v) for v in min_pieces]
    if len(limits) != len(openings) or not all(0.0 <= v < 1.0 for v in limits):
        raise ValueError(f"bricks: need one min_piece in [0, 1) per opening, got {limits} for {len(openings)}")
    grid = block_cells(tuple(size.tolist()), stagger, h)
    if max(grid) > MAX_ELEMENTS:
        # Scene validation refuses this first (Scene.size_problems); here for Python callers, before numpy would hold
        # the count as an object array.
        raise ValueError(
            f"bricks: a block of {size.tolist()} m is {list(grid)} cells of h = {h} m; allowed: at most "
            f"{MAX_ELEMENTS} along each edge"
        )
    per = np.array(grid, dtype=np.int64)
    cell = size / per
    n = np.maximum(np.rint((hi_a - lo_a) / cell).astype(np.int64), 1)
    top = lo_a + n * cell
    points, tets = box_mesh(lo_a, top, n)
    tets = tets.astype(np.int64)
    # Cell (i, j, k) of each tet (box_mesh numbers the tets cell-major, 6 per cell, cells x fastest).
    c = np.arange(len(tets)) // 6
    i, j, k = c % n[0], (c // n[0]) % n[1], c // (n[0] * n[1])
    course = k // per[2]
    shift = np.rint(course * stagger * per[0]).astype(np.int64) % per[0]
    column = (i + per[0] - shift) // per[0]  # the block along x within the course (0: the partial one at lo)
    block_key = column + (n[0] // per[0] + 2) * ((j // per[1]) + (n[1] // per[1] + 1) * course)
    centre = points[tets].mean(axis=1)
    cell_centre = lo_a + (np.stack([i, j, k], axis=1) + 0.5) * cell
    cut = [_inside(opening, cell_centre) for opening in openings]
    keep = ~np.any(cut, axis=0) if cut else np.ones(len(tets), dtype=bool)
    for removed, limit in zip(cut, limits, strict=True):
        if limit > 0.0:
            keep &= ~_small_pieces(keep, removed, block_key, c, n, int(np.prod(per)), limit)
    if not np.any(keep):
        raise ValueError("bricks: the openings remove every cell")
    tets, block_key, centre = tets[keep], block_key[keep], centre[keep]
    used = np.unique(tets)
    renumber = np.full(len(points), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    points, tets = points[used], renumber[tets]
    _, block = np.unique(block_key, return_inverse=True)

    faces = tets[:, TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    owner = np.repeat(np.arange(len(tets)), 4)
    # Interior faces: the two slots of each shared face; a joint where their tets lie in different blocks.
    shared = np.flatnonzero(counts[inverse] == 2)
    order = shared[np.argsort(inverse[shared], kind="stable")]
    a, b = order[0::2], order[1::2]
    joint = block[owner[a]] != block[owner[b]]
    joint_faces = faces[a[joint]]
    d = centre[owner[b[joint]]] - centre[owner[a[joint]]]
    joint_face_set = np.where(np.abs(d[:, 2]) > np.maximum(np.abs(d[:, 0]), np.abs(d[:, 1])), 0, 1).astype(np.int64)

    # Boundary faces (TET_FACES of a positive tet point out of it, so out of the rock) on the box planes or openings.
    outer = faces[counts[inverse] == 1]
    x = points[outer]
    boundary: dict[str, np.ndarray] = {}
    on_box = np.zeros(len(outer), dtype=bool)
    tol = 1e-6 * float(np.max(top - lo_a))
    for name in BOX_FACE_NAMES:
        axis = "xyz".index(name[0])
        plane = lo_a[axis] if name[1] == "-" else top[axis]
        on = np.all(np.abs(x[:, :, axis] - plane) < tol, axis=1)
        boundary[name] = outer[on]
        on_box |= on
    if openings:
        boundary[OPENING_FACE_NAME] = outer[~on_box]
    return GeologyMesh(
        points=points,
        tets=tets,
        tet_block=block.astype(np.int64),
        tet_material=np.zeros(len(tets), dtype=np.int64),
        material_names=[material],
        joint_faces=joint_faces,
        joint_face_set=joint_face_set,
        joint_set_names=list(BRICK_JOINT_SETS),
        boundary_faces=boundary,
        num_blocks=int(block.max()) + 1,
    )
