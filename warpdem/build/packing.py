"""Initial sphere arrangements, built once on the host: regular lattices and random sequential addition.

Regions are small frozen dataclasses (:class:`Box`, :class:`Cylinder`). Every placed sphere lies fully inside its
region: its centre is at least its radius from the boundary. Spheres of a packing never overlap.

Lattices (:func:`lattice_packing`) put equal spheres in contact with their neighbours: simple cubic (6 contacts,
solid fraction π/6 ≈ 0.524) or hexagonal close packing (12 contacts, π/(3√2) ≈ 0.7405) with close-packed
layers stacked ABAB along z. Random packings (:func:`random_packing`) place spheres one at a time at uniformly
random positions, rejecting overlaps (random sequential addition, RSA); RSA of equal spheres jams near a solid
fraction of 0.38 (Widom 1966; φ_∞ = 0.3841 by Zhang & Torquato 2013), lower still in small regions
because walls exclude a layer of thickness r. Denser random packings need dynamic compaction (gravity
deposition, isotropic compression) in the simulator itself.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = ["Box", "Cylinder", "lattice_packing", "random_packing"]

_REL_TOL = 1e-12
"""Containment tolerance relative to the region size: lattice points that land on the boundary of the allowed
region up to round-off (a box exactly n diameters wide) are kept."""


def _check_positive(value: float, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def _vec3(value: np.ndarray | tuple[float, float, float] | list[float], name: str) -> np.ndarray:
    array = np.array(value, dtype=np.float64).reshape(-1)
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    array.flags.writeable = False  # the dataclasses are frozen; so are their arrays
    return array


@dataclass(frozen=True, eq=False)
class Box:
    """Axis-aligned box.

    Attributes:
        lo: lower corner [m], shape (3,).
        hi: upper corner [m], shape (3,), hi > lo componentwise.
    """

    lo: np.ndarray
    hi: np.ndarray

    def __post_init__(self) -> None:
        lo, hi = _vec3(self.lo, "Box.lo"), _vec3(self.hi, "Box.hi")
        if not np.all(hi > lo):
            raise ValueError(f"Box needs hi > lo in every component, got lo={lo.tolist()}, hi={hi.tolist()}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    def contains(self, points: np.ndarray, margin: float | np.ndarray = 0.0) -> np.ndarray:
        """Which points lie inside the box, at least margin from its faces.

        Args:
            points: positions [m], shape (N, 3).
            margin: distance to keep from the boundary [m], scalar or shape (N,).

        Returns:
            Mask, shape (N,), bool.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        margin = np.asarray(margin, dtype=np.float64).reshape(-1, 1)
        return np.all((points >= self.lo + margin) & (points <= self.hi - margin), axis=1)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo, hi) [m], each shape (3,)."""
        return self.lo.copy(), self.hi.copy()

    def volume(self) -> float:
        """Volume [m³]."""
        return float(np.prod(self.hi - self.lo))


@dataclass(frozen=True, eq=False)
class Cylinder:
    """Solid circular cylinder aligned with a coordinate axis.

    Attributes:
        center: centre of the base disc [m], shape (3,); the cylinder extends from it by height along +axis.
        radius: radius [m], > 0.
        height: height [m], > 0.
        axis: coordinate axis of the cylinder: 0 (x), 1 (y) or 2 (z).
    """

    center: np.ndarray
    radius: float
    height: float
    axis: int = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "Cylinder.center"))
        for name in ("radius", "height"):
            object.__setattr__(self, name, _check_positive(getattr(self, name), f"Cylinder.{name}"))
        if isinstance(self.axis, bool) or not isinstance(self.axis, numbers.Integral) or self.axis not in (0, 1, 2):
            raise ValueError(f"Cylinder.axis must be 0, 1 or 2, got {self.axis!r}")
        object.__setattr__(self, "axis", int(self.axis))

    def _radial_axes(self) -> tuple[int, int]:
        return (self.axis + 1) % 3, (self.axis + 2) % 3

    def contains(self, points: np.ndarray, margin: float | np.ndarray = 0.0) -> np.ndarray:
        """Which points lie inside the cylinder, at least margin from its mantle and end discs.

        Args:
            points: positions [m], shape (N, 3).
            margin: distance to keep from the boundary [m], scalar or shape (N,).

        Returns:
            Mask, shape (N,), bool.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        margin = np.broadcast_to(np.asarray(margin, dtype=np.float64), points.shape[:1])
        rel = points - self.center
        u, w = self._radial_axes()
        rho = np.hypot(rel[:, u], rel[:, w])
        along = rel[:, self.axis]
        return (rho <= self.radius - margin) & (along >= margin) & (along <= self.height - margin)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo, hi) [m], each shape (3,)."""
        lo = self.center - self.radius
        hi = self.center + self.radius
        lo[self.axis] = self.center[self.axis]
        hi[self.axis] = self.center[self.axis] + self.height
        return lo, hi

    def volume(self) -> float:
        """Volume π r² h [m³]."""
        return math.pi * self.radius**2 * self.height


Region = Box | Cylinder


def _tolerance(region: Region) -> float:
    lo, hi = region.bounds()
    return _REL_TOL * float(max(np.max(np.abs(lo)), np.max(np.abs(hi)), np.max(hi - lo)))


def _check_max_count(max_count: int | None) -> int | None:
    if max_count is not None and (isinstance(max_count, bool) or not isinstance(max_count, int) or max_count < 0):
        raise ValueError(f"max_count must be None or an integer >= 0, got {max_count!r}")
    return max_count


def lattice_packing(
    region: Region,
    radius: float,
    arrangement: Literal["hcp", "cubic"],
    max_count: int | None = None,
) -> np.ndarray:
    """Equal spheres on a lattice, each touching its lattice neighbours, all fully inside a region.

    The lattice is anchored at the lower corner of the region's bounding box, offset by the radius, so a box
    exactly n diameters wide holds n spheres per row.

    - "cubic": centres at lo + r + 2r (i, j, k); 6 contacts per sphere, solid fraction π/6.
    - "hcp": close-packed (triangular) layers of spacing 2r normal to z; within a layer, rows are √3 r apart in y
      and every other row is shifted by r in x; layers are 2r sqrt(2/3) apart in z, and every other layer (B) is
      shifted by (r, r/√3), the centroid of a triangle of layer A, giving ABAB stacking: 12 contacts per sphere
      (6 in-plane, 3 above, 3 below), solid fraction π/(3√2).

    Args:
        region: region to fill.
        radius: sphere radius r [m], > 0.
        arrangement: "hcp" or "cubic".
        max_count: keep at most this many spheres; the order is z-major, then y, then x, so the lowest layers
            are kept. None keeps all.

    Returns:
        Centres [m], shape (N, 3), ordered by layer (z), then row (y), then x.

    Raises:
        ValueError: unknown arrangement, radius not > 0, or max_count negative.
    """
    r = _check_positive(radius, "radius")
    max_count = _check_max_count(max_count)
    lo, hi = region.bounds()
    extent = hi - lo
    if arrangement == "cubic":
        spacing = np.array([2.0 * r, 2.0 * r, 2.0 * r])
    elif arrangement == "hcp":
        spacing = np.array([2.0 * r, math.sqrt(3.0) * r, 2.0 * r * math.sqrt(2.0 / 3.0)])
    else:
        raise ValueError(f"arrangement must be 'hcp' or 'cubic', got {arrangement!r}")
    # Index ranges cover the bounding box; offset rows/layers shift by at most r, so one extra index at each end
    # suffices and the containment test trims the rest.
    counts = np.floor(np.maximum(extent - 2.0 * r, 0.0) / spacing + 1e-9).astype(np.int64) + 1
    k, j, i = np.meshgrid(
        np.arange(counts[2]), np.arange(counts[1]), np.arange(-1, counts[0] + 1), indexing="ij"
    )  # z-major then y then x, the documented order
    k, j, i = k.ravel(), j.ravel(), i.ravel()
    x = i * spacing[0]
    y = j * spacing[1]
    z = k * spacing[2]
    if arrangement == "hcp":
        layer_b = (k % 2).astype(np.float64)
        x = x + r * (j % 2) + r * layer_b
        y = y + r / math.sqrt(3.0) * layer_b
    points = np.stack([x, y, z], axis=1) + (lo + r)
    keep = region.contains(points, margin=r - _tolerance(region))
    points = points[keep]
    if max_count is not None:
        points = points[:max_count]
    return np.ascontiguousarray(points)


class _CellGrid:
    """Placed spheres binned on a uniform grid of cubic cells of side >= 2 r_max, for overlap queries.

    Two spheres can overlap only if their centres are less than r_i + r_j <= 2 r_max apart, i.e. in the same or
    adjacent cells, so a query reads the 27 cells around a point. The grid has one empty cell of padding on every
    side, so the 27 neighbours of any cell inside the region exist. Coordinates and radii are kept as separate
    arrays with one trailing NaN sentinel that empty slots (-1) point to: comparisons with NaN are false, so the
    query needs no validity mask, and the gathers stay contiguous.
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray, cell: float, capacity: int) -> None:
        self.lo = lo
        self.cell = cell
        self.dims = np.ceil((hi - lo) / cell).astype(np.int64) + 2
        n_cells = int(np.prod(self.dims))
        self.depth = 1  # slots per cell, grown on demand: mostly 0-3 spheres per cell of side 2 r_max
        self.slots = np.full((n_cells, self.depth), -1, dtype=np.int64)
        self.fill = np.zeros(n_cells, dtype=np.int64)
        offsets = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), axis=-1).reshape(-1, 3)
        self.strides = np.array([self.dims[1] * self.dims[2], self.dims[2], 1], dtype=np.int64)
        self.neighbour_offsets = offsets @ self.strides
        self.count = 0
        self.xyzr = np.full((4, capacity + 1), np.nan)  # rows x, y, z, r [m]; column -1 is the sentinel

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """Flat cell index of each point (shape (N, 3)), shape (N,)."""
        ijk = np.floor((points - self.lo) / self.cell).astype(np.int64) + 1
        ijk = np.clip(ijk, 1, self.dims - 2)  # round-off at the far faces stays inside the unpadded range
        return ijk @ self.strides

    def overlaps(self, points: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """Whether spheres (centres (N, 3), radii (N,)) overlap a placed sphere, shape (N,)."""
        cells = self.cell_of(points)[:, None] + self.neighbour_offsets[None, :]
        near = np.take(self.slots, cells, axis=0).reshape(len(points), -1)  # np.take: ~5x faster than [] here
        x, y, z, r = self.xyzr
        # |p - c_j|² < (ρ + r_j)², accumulated in place: this is the innermost loop of the packing.
        gap2 = np.take(x, near)
        gap2 -= points[:, 0:1]
        gap2 *= gap2
        for axis, coord in ((1, y), (2, z)):
            d = np.take(coord, near)
            d -= points[:, axis : axis + 1]
            d *= d
            gap2 += d
        reach = np.take(r, near)
        reach += radii[:, None]
        reach *= reach
        return np.any(gap2 < reach, axis=1)

    def insert(self, points: np.ndarray, radii: np.ndarray) -> None:
        """Add spheres (centres (M, 3), radii (M,)); they get the next indices in order."""
        indices = np.arange(self.count, self.count + len(points))
        if self.count + len(points) >= self.xyzr.shape[1]:
            grown = np.full((4, max(2 * self.xyzr.shape[1], self.count + len(points) + 1)), np.nan)
            grown[:, : self.count] = self.xyzr[:, : self.count]
            self.xyzr = grown
        self.xyzr[:3, indices] = points.T
        self.xyzr[3, indices] = radii
        self.count += len(points)
        cells = self.cell_of(points)
        order = np.argsort(cells, kind="stable")
        cells, indices = cells[order], indices[order]
        # Position of each new sphere among the new ones in the same cell, then its slot after those already there.
        first = np.searchsorted(cells, cells, side="left")
        slot = self.fill[cells] + np.arange(len(cells)) - first
        needed = int(slot.max(initial=-1)) + 1
        if needed > self.depth:
            # Grow to exactly what is needed: every query reads 27 * depth slots, so spare slots cost time.
            slots = np.full((self.slots.shape[0], needed), -1, dtype=np.int64)
            slots[:, : self.depth] = self.slots
            self.slots, self.depth = slots, needed
        self.slots[cells, slot] = indices
        np.add.at(self.fill, cells, 1)

    def spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the placed centres [m], shape (N, 3), and radii [m], shape (N,)."""
        return self.xyzr[:3, : self.count].T.copy(), self.xyzr[3, : self.count].copy()


class _ExclusionVoxels:
    """Fine voxels that record which candidate radii certainly overlap a placed sphere, to reject cheaply.

    A candidate of radius ρ overlaps sphere j iff its centre is closer than ρ + r_j to c_j. If f_j(v) is the
    distance from c_j to the farthest point of voxel v, every candidate centred in v with ρ > f_j(v) - r_j overlaps
    j. Each voxel keeps min_j (f_j(v) - r_j), rounded up onto 256 levels over [r_min, r_max] (uint8) so that the
    test "ρ > level" never rejects a free position. With voxels of side r_max/2.5 this rejects ~88 % of all
    candidates of an RSA run of equal spheres up to a solid fraction of 0.3 (where only 0.1 % of the space is
    still free) by one table lookup instead of a search of 27 cells. Finer voxels reject more but cost more to
    mark (∝ h⁻³ per sphere); r_max/2.5 was the fastest in total for 10⁵ spheres.
    """

    _CHUNK = 256
    """Spheres marked per vectorised batch, bounding the temporaries to _CHUNK × stencil size floats."""

    _LEVELS = 254
    """Codes 1.._LEVELS are thresholds r_min + code/_LEVELS (r_max - r_min); 0 rejects all radii, 255 none."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, r_min: float, r_max: float, max_voxels: int) -> None:
        self.lo = lo
        # Coarser only where the voxel count would exceed max_voxels (then fewer candidates are rejected early,
        # which costs speed, never correctness).
        self.h = max(r_max / 2.5, float(np.prod(hi - lo) / max_voxels) ** (1.0 / 3.0))
        self.r_min, self.span = r_min, r_max - r_min
        self.reach = math.ceil(2.0 * r_max / self.h)  # f_j - r_j < r_max needs f_j < r_j + r_max <= 2 r_max
        self.top = np.floor((hi - lo) / self.h).astype(np.int64)  # largest unpadded voxel index per axis
        self.dims = self.top + 1 + 2 * self.reach
        self.strides = np.array([self.dims[1] * self.dims[2], self.dims[2], 1], dtype=np.int64)
        o = np.arange(-self.reach, self.reach + 1)
        self.offsets = o
        grid = np.stack(np.meshgrid(o, o, o, indexing="ij"), axis=-1).reshape(-1, 3)
        # The farthest point of the voxel at offset o is at least h sqrt(Σ max(|o_i|, 1/2)²) from any centre in
        # the own voxel; beyond 2 r_max no radius is ever rejected, so the stencil is a ball, not a cube.
        near = self.h * np.sqrt(np.sum(np.maximum(np.abs(grid), 0.5) ** 2, axis=1)) < 2.0 * r_max
        self.stencil_axes = (grid[near] + self.reach).T  # per-axis indices into the offsets, shape (3, S)
        self.stencil = grid[near] @ self.strides
        self.code = np.full(int(np.prod(self.dims)), 255, dtype=np.uint8)
        self.threshold = np.concatenate(
            [[-np.inf], r_min + np.arange(1, self._LEVELS + 1) / self._LEVELS * self.span, [np.inf]]
        )

    def _voxel(self, points: np.ndarray) -> np.ndarray:
        """Unpadded integer voxel coordinates, shape (N, 3)."""
        return np.clip(np.floor((points - self.lo) / self.h).astype(np.int64), 0, self.top)

    def is_dead(self, points: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """Whether candidates (centres (N, 3), radii (N,)) certainly overlap a placed sphere, shape (N,)."""
        return radii > self.threshold[self.code[(self._voxel(points) + self.reach) @ self.strides]]

    def insert(self, points: np.ndarray, radii: np.ndarray) -> None:
        """Record the exclusion zones of new spheres (centres (M, 3), radii (M,))."""
        for start in range(0, len(points), self._CHUNK):
            centre, radius = points[start : start + self._CHUNK], radii[start : start + self._CHUNK]
            voxel = self._voxel(centre)
            # Per axis, the squared distance from the centre to the farther face of each voxel in the stencil.
            faces = self.lo + (voxel[:, None, :] + self.offsets[None, :, None]) * self.h  # (M, 2 reach + 1, 3)
            rel = centre[:, None, :] - faces
            far2 = np.maximum(rel * rel, (rel - self.h) ** 2)
            ox, oy, oz = self.stencil_axes
            d2 = far2[:, ox, 0] + far2[:, oy, 1] + far2[:, oz, 2]  # (M, S)
            block = np.sqrt(d2) - radius[:, None]  # reject ρ > block
            if self.span > 0.0:
                level = np.ceil((block - self.r_min) / self.span * self._LEVELS)  # rounded up: never too strict
                code = np.where(block < self.r_min, 0, np.where(level > self._LEVELS, 255, np.maximum(level, 1)))
            else:
                code = np.where(block < self.r_min, 0, 255)
            which, cell = np.nonzero(code < 255)
            flat = ((voxel + self.reach) @ self.strides)[which] + self.stencil[cell]
            np.minimum.at(self.code, flat, code[which, cell].astype(np.uint8))


def _first_come(points: np.ndarray, radii: np.ndarray, grid: _CellGrid) -> np.ndarray:
    """Greedy selection in order: sphere i is kept unless it overlaps a kept sphere j < i.

    Candidate pairs come from the cell grid (same or adjacent cells), found by sorting the cell ids.

    Args:
        points: centres [m], shape (M, 3).
        radii: radii [m], shape (M,).
        grid: the cell grid, for its cell ids only (nothing is inserted).

    Returns:
        Mask of kept spheres, shape (M,), bool.
    """
    keep = np.ones(len(points), dtype=bool)
    if len(points) < 2:
        return keep
    cells = grid.cell_of(points)
    order = np.argsort(cells, kind="stable")
    sorted_cells = cells[order]
    targets = cells[:, None] + grid.neighbour_offsets[None, :]  # (M, 27)
    first = np.searchsorted(sorted_cells, targets, side="left").ravel()
    count = np.searchsorted(sorted_cells, targets, side="right").ravel() - first
    i = np.repeat(np.repeat(np.arange(len(points)), targets.shape[1]), count)
    run_start = np.cumsum(count) - count
    j = order[np.repeat(first, count) + np.arange(int(count.sum())) - np.repeat(run_start, count)]
    lower = j < i
    i, j = i[lower], j[lower]
    close = np.sum((points[i] - points[j]) ** 2, axis=1) < (radii[i] + radii[j]) ** 2
    i, j = i[close], j[close]
    if len(i) == 0:
        return keep
    pair_order = np.argsort(i, kind="stable")
    i, j = i[pair_order], j[pair_order]  # overlapping pairs i > j, by i
    rows, starts = np.unique(i, return_index=True)
    for row, earlier in zip(rows, np.split(j, starts[1:]), strict=True):
        keep[row] = not keep[earlier].any()
    return keep


def _sample_inside(region: Region, margin: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Uniform random points in the region shrunk by margin (one margin per point, shape (N,)); shape (N, 3)."""
    n = len(margin)
    if isinstance(region, Box):
        span = (region.hi - region.lo)[None, :] - 2.0 * margin[:, None]
        return region.lo + margin[:, None] + rng.random((n, 3)) * span
    u, w = region._radial_axes()
    # Uniform in the disc: radius ∝ sqrt(uniform), since the area within radius ρ grows as ρ².
    rho = (region.radius - margin) * np.sqrt(rng.random(n))
    phi = 2.0 * math.pi * rng.random(n)
    points = np.empty((n, 3))
    points[:, u] = region.center[u] + rho * np.cos(phi)
    points[:, w] = region.center[w] + rho * np.sin(phi)
    points[:, region.axis] = region.center[region.axis] + margin + (region.height - 2.0 * margin) * rng.random(n)
    return points


def _fits(region: Region, radius: np.ndarray) -> np.ndarray:
    """Whether a sphere of each radius fits into the region at all, shape (N,)."""
    if isinstance(region, Box):
        return np.all(2.0 * radius[:, None] <= (region.hi - region.lo)[None, :], axis=1)
    return (radius <= region.radius) & (2.0 * radius <= region.height)


def random_packing(
    region: Region,
    radius_min: float,
    radius_max: float,
    rng: np.random.Generator,
    volume_fraction: float = 0.5,
    max_count: int | None = None,
    max_attempts: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Random non-overlapping spheres fully inside a region, by random sequential addition (RSA).

    Radii are drawn one after another from U(radius_min, radius_max) (a radius too large to fit into the region
    at all is redrawn) until their total volume reaches volume_fraction × the region volume or max_count radii
    are drawn; the radius that crosses the target is kept. Each drawn sphere is then tried at uniformly random
    positions inside the region (shrunk by its radius) until one overlaps no placed sphere. Because every drawn
    radius is placed unless the attempts run out, the placed radii are the draws themselves: the size
    distribution is not skewed towards small spheres, which fit more easily.

    For speed, up to 1024 drawn spheres are handled per round: each draws a few candidate positions (about
    2 / the current acceptance rate); candidates are rejected through a voxel table of known exclusion zones,
    then tested exactly against the placed spheres on a cell grid (cell side >= 2 radius_max, so 27 cells are
    read); each sphere takes its first free candidate, and the spheres are accepted in draw order unless they
    overlap one accepted earlier in the round. The rest retry in the next round.

    The run ends when all drawn spheres are placed, or earlier when max_attempts candidate positions have been
    tried; the spheres placed so far are returned either way. RSA of equal spheres jams near a solid fraction of
    0.38 (0.3841, Zhang & Torquato 2013), lower in small regions, whose walls exclude a layer of thickness r, and
    lower for the largest radii of a wide distribution: near that limit almost every candidate is rejected, so
    a target above it is not an error, the run just uses up max_attempts. 10⁵ equal spheres at a solid fraction
    of 0.3 take about 4 s.

    The result is a deterministic function of the arguments and the state of rng.

    Args:
        region: region to fill.
        radius_min: smallest radius [m], > 0.
        radius_max: largest radius [m], >= radius_min.
        rng: random generator; advanced by the call.
        volume_fraction: target solid fraction, in (0, 1) [-].
        max_count: at most this many spheres; None for no limit.
        max_attempts: at most this many candidate positions tried in total (a sphere's candidates count up to
            its first free one). None: 100 000 + 200 per sphere the target needs.

    Returns:
        (centres [m], shape (N, 3); radii [m], shape (N,)), in placement order.

    Raises:
        ValueError: invalid radii, volume fraction, max_count or max_attempts.
    """
    r_min = _check_positive(radius_min, "radius_min")
    r_max = _check_positive(radius_max, "radius_max")
    if r_max < r_min:
        raise ValueError(f"radius_max must be >= radius_min, got {radius_max!r} < {radius_min!r}")
    if isinstance(volume_fraction, bool) or not (isinstance(volume_fraction, numbers.Real) and 0 < volume_fraction < 1):
        raise ValueError(f"volume_fraction must be in (0, 1), got {volume_fraction!r}")
    max_count = _check_max_count(max_count)

    target_volume = volume_fraction * region.volume()
    mean_volume = math.pi / 3.0 * (r_min + r_max) * (r_min**2 + r_max**2)  # (4π/3) E[r³] for r ~ U(a, b)
    count_limit = max_count if max_count is not None else np.iinfo(np.int64).max
    expected = min(target_volume / mean_volume, count_limit)
    if max_attempts is None:
        max_attempts = 100_000 + int(200 * expected)
    if isinstance(max_attempts, bool) or not isinstance(max_attempts, numbers.Integral) or max_attempts < 0:
        raise ValueError(f"max_attempts must be None or an integer >= 0, got {max_attempts!r}")

    lo, hi = region.bounds()
    # Cells of side 2 r_max, coarsened when that would make far more cells than spheres (tiny spheres, small
    # max_count in a large region); larger cells are still correct, the grid grows its per-cell depth.
    cell = max(2.0 * r_max, float(np.prod(hi - lo) / max(4.0 * expected, 4096.0)) ** (1.0 / 3.0))
    grid = _CellGrid(lo, hi, cell, capacity=max(int(expected * 1.1) + 16, 64))

    voxels = _ExclusionVoxels(lo, hi, r_min, r_max, max_voxels=1 << 26)

    if not _fits(region, np.array([r_min]))[0]:
        return np.zeros((0, 3)), np.zeros(0)  # not even the smallest sphere fits

    # Radii are committed when drawn: drawing stops after the radius whose volume reaches the target (or at
    # max_count), exactly as in one-at-a-time addition, and every drawn sphere is then placed unless the attempts
    # run out. So the placed radii are the first draws of U(radius_min, radius_max), unbiased by their size.
    drawn_count = 0
    drawn_volume = 0.0
    attempts = 0
    pool = np.empty(0)  # drawn radii not yet placed, in draw order
    pool_size = 1024
    candidates_per_round = 16384
    acceptance = 1.0  # fraction of free candidates in the last round

    while attempts < max_attempts:
        if len(pool) < pool_size and drawn_count < count_limit and drawn_volume < target_volume:
            fresh = r_min + (r_max - r_min) * rng.random(pool_size - len(pool))
            fresh = fresh[_fits(region, fresh)]  # radii too large for a thin region are redrawn
            volume = drawn_volume + np.cumsum(4.0 / 3.0 * math.pi * fresh**3)
            reached = (volume >= target_volume) | (drawn_count + np.arange(1, len(fresh) + 1) >= count_limit)
            if reached.any():
                fresh = fresh[: int(np.argmax(reached)) + 1]
            drawn_count += len(fresh)
            drawn_volume = float(volume[len(fresh) - 1]) if len(fresh) else drawn_volume
            pool = np.concatenate([pool, fresh])
        if len(pool) == 0:
            if drawn_count >= count_limit or drawn_volume >= target_volume:
                break
            continue
        # Enough candidates per sphere that most find a free one, within the round's budget and max_attempts.
        n_active = int(min(len(pool), max_attempts - attempts))
        tries = int(np.clip(math.ceil(2.0 / max(acceptance, 1e-6)), 1, max(1, candidates_per_round // n_active)))
        radius = np.repeat(pool[:n_active], tries)
        trial = _sample_inside(region, radius, rng)

        # Overlap with placed spheres: |p - c_j| < r + r_j for any j in the 27 surrounding cells; candidates in
        # voxels already covered by an exclusion zone are rejected without the search.
        free = ~voxels.is_dead(trial, radius)
        test = np.flatnonzero(free)
        free[test] = ~grid.overlaps(trial[test], radius[test])
        free = free.reshape(n_active, tries)
        acceptance = float(free.mean())

        # Each pooled sphere takes its first free candidate (the later ones were never tried), then clashes
        # within the round are resolved in pool order, as sequential addition would.
        has_free = free.any(axis=1)
        first = np.argmax(free, axis=1)
        attempts += int(np.where(has_free, first + 1, tries).sum())
        who = np.flatnonzero(has_free)
        pos = trial.reshape(n_active, tries, 3)[who, first[who]]
        rad = pool[who]
        accept = _first_come(pos, rad, grid)
        who, pos, rad = who[accept], pos[accept], rad[accept]

        grid.insert(pos, rad)
        voxels.insert(pos, rad)
        pool = np.delete(pool, who)

    return grid.spheres()
