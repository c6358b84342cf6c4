"""Initial sphere arrangements (warpdem.build.packing).

Oracles:
- brute-force O(N²) pair distances (N <= 2000): no two spheres overlap, and every sphere lies inside its region;
- lattice geometry: contact numbers (hcp 12, cubic 6) and the ABAB signature of hcp (2 neighbours at
  2r sqrt(8/3), straight above and below; fcc has none at that distance);
- solid fraction of a lattice in a box, bracketed by the Voronoi-cell argument below;
- brute-force checks of the two acceleration structures (exclusion voxels, in-round conflict resolution).

Solid-fraction bracket. Every lattice site owns its Voronoi cell, of volume V_s / φ_∞ (V_s = 4/3 π r³, φ_∞ the
infinite-lattice fraction), and every point of the cell is within the cell's circumradius R_v of the site. Its
vertices are the centres of the holes: for close packing the octahedral holes at a/√2 = √2 r (a = 2r; the
tetrahedral ones are nearer, at a sqrt(3/8)), for the cubic lattice the cube centres at √3 r. Kept sites are at
least r inside the box, so their cells lie in the box grown by R_v - r: N V_s / φ_∞ <= Π (L_i + 2 (R_v - r)).
Conversely any point p of the box shrunk by r + R_v has a site within R_v, which is then at least r inside and
kept, so the kept cells cover that shrunk box: N V_s / φ_∞ >= Π (L_i - 2 (r + R_v)). Dividing by Π L_i:

    φ_∞ Π (1 - 2 (r + R_v) / L_i) <= φ <= φ_∞ Π (1 + 2 (R_v - r) / L_i),

a boundary layer of relative size O(r / L) that vanishes for large boxes.

Tolerances:
- OVERLAP_TOL = 1e-12 × the region size: the only round-off is in differences of coordinates of that size.
- LATTICE_REL_TOL = 1e-9: lattice distances are sums of a few products of r with √2, √3, exact to ~1e-15.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from warpdem.build.packing import Box, Cylinder, lattice_packing, random_packing

OVERLAP_TOL = 1e-12
LATTICE_REL_TOL = 1e-9
PHI_HCP = math.pi / (3.0 * math.sqrt(2.0))
PHI_CUBIC = math.pi / 6.0


def _scale(region: Box | Cylinder) -> float:
    lo, hi = region.bounds()
    return float(max(np.abs(lo).max(), np.abs(hi).max(), (hi - lo).max()))


def _assert_valid_packing(region: Box | Cylinder, centres: np.ndarray, radii: np.ndarray) -> None:
    """Brute force: all pairs at least r_i + r_j apart, every sphere inside the region (N <= 2000)."""
    assert centres.shape == (len(radii), 3)
    assert 0 < len(centres) <= 2000
    tol = OVERLAP_TOL * _scale(region)
    diff = centres[:, None, :] - centres[None, :, :]
    dist = np.sqrt(np.sum(diff * diff, axis=2))
    gap = dist - (radii[:, None] + radii[None, :])
    np.fill_diagonal(gap, np.inf)
    assert gap.min() >= -tol
    assert np.all(region.contains(centres, margin=radii - tol))


def _regions(size: float) -> list[Box | Cylinder]:
    """A box off the origin and a cylinder along each axis, all about size across."""
    regions: list[Box | Cylinder] = [Box(np.array([-1.3, 0.7, 2.0]), np.array([-1.3, 0.7, 2.0]) + size)]
    for axis in range(3):
        regions.append(Cylinder(center=np.array([0.5, -2.0, 1.0]), radius=0.5 * size, height=size, axis=axis))
    return regions


def _neighbour_counts(points: np.ndarray, distance: float) -> np.ndarray:
    dist = np.sqrt(np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=2))
    return np.sum(np.abs(dist - distance) <= LATTICE_REL_TOL * distance, axis=1)


# ------------------------------------------------------------------------------------------------------------
# Regions


def test_box_contains_and_bounds() -> None:
    box = Box(np.zeros(3), np.array([1.0, 2.0, 3.0]))
    points = np.array([[0.5, 1.0, 1.5], [0.05, 1.0, 1.5], [1.01, 1.0, 1.5], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(box.contains(points), [True, True, False, True])
    np.testing.assert_array_equal(box.contains(points, margin=0.1), [True, False, False, False])
    lo, hi = box.bounds()
    np.testing.assert_array_equal(lo, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(hi, [1.0, 2.0, 3.0])
    assert box.volume() == pytest.approx(6.0)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_cylinder_contains_and_bounds(axis: int) -> None:
    cylinder = Cylinder(center=np.array([1.0, 2.0, 3.0]), radius=2.0, height=5.0, axis=axis)
    radial = [a for a in range(3) if a != axis]
    inside = np.array([1.0, 2.0, 3.0])
    inside[axis] += 2.5
    outside_radially = inside.copy()
    outside_radially[radial[0]] += 1.5
    outside_radially[radial[1]] += 1.5  # 1.5√2 ≈ 2.12 > 2 from the axis
    below = inside.copy()
    below[axis] = cylinder.center[axis] - 0.01
    points = np.stack([inside, outside_radially, below])
    np.testing.assert_array_equal(cylinder.contains(points), [True, False, False])
    np.testing.assert_array_equal(cylinder.contains(points[:1], margin=2.0), [True])
    np.testing.assert_array_equal(cylinder.contains(points[:1], margin=2.01), [False])
    lo, hi = cylinder.bounds()
    expected_lo = np.array([1.0, 2.0, 3.0]) - 2.0
    expected_hi = np.array([1.0, 2.0, 3.0]) + 2.0
    expected_lo[axis] = (1.0, 2.0, 3.0)[axis]
    expected_hi[axis] = (1.0, 2.0, 3.0)[axis] + 5.0
    np.testing.assert_allclose(lo, expected_lo)
    np.testing.assert_allclose(hi, expected_hi)
    assert cylinder.volume() == pytest.approx(math.pi * 4.0 * 5.0)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Box(np.zeros(3), np.array([1.0, 0.0, 1.0])),
        lambda: Box(np.zeros(2), np.ones(2)),
        lambda: Cylinder(np.zeros(3), radius=0.0, height=1.0),
        lambda: Cylinder(np.zeros(3), radius=1.0, height=-1.0),
        lambda: Cylinder(np.zeros(3), radius=1.0, height=1.0, axis=3),
    ],
)
def test_invalid_regions_raise(make: Callable[[], object]) -> None:
    with pytest.raises(ValueError):
        make()


# ------------------------------------------------------------------------------------------------------------
# Lattices


@pytest.mark.parametrize("arrangement", ["hcp", "cubic"])
def test_lattice_spheres_inside_and_disjoint(arrangement: str) -> None:
    r = 0.5
    for region in _regions(7.3):
        centres = lattice_packing(region, r, arrangement)  # type: ignore[arg-type]
        _assert_valid_packing(region, centres, np.full(len(centres), r))


def test_lattice_fills_exact_fit() -> None:
    # A box exactly 4 x 3 x 2 diameters holds 24 cubic-lattice spheres, touching the walls, despite round-off.
    r = 0.1
    box = Box(np.array([0.3, 0.3, 0.3]), np.array([0.3 + 8 * r, 0.3 + 6 * r, 0.3 + 4 * r]))
    assert len(lattice_packing(box, r, "cubic")) == 24


def test_hcp_contacts_and_stacking() -> None:
    r = 0.5
    box = Box(np.zeros(3), np.full(3, 8.0))
    centres = lattice_packing(box, r, "hcp")
    assert len(centres) <= 2000
    dist = np.sqrt(np.sum((centres[:, None, :] - centres[None, :, :]) ** 2, axis=2))
    np.fill_diagonal(dist, np.inf)
    # Nothing closer than contact anywhere.
    assert dist.min() >= 2.0 * r * (1.0 - LATTICE_REL_TOL)
    # Interior spheres (whose neighbour shells up to 2r sqrt(8/3) ≈ 3.27 r lie inside the box) have 12 contacts
    # and exactly 2 neighbours straight above/below two layers away (ABAB); fcc (ABC) would have 0 there.
    interior = box.contains(centres, margin=4.0 * r)
    assert interior.sum() >= 20
    np.testing.assert_array_equal(_neighbour_counts(centres, 2.0 * r)[interior], 12)
    np.testing.assert_array_equal(_neighbour_counts(centres, 2.0 * r * math.sqrt(8.0 / 3.0))[interior], 2)


def test_cubic_contacts() -> None:
    r = 0.5
    box = Box(np.zeros(3), np.full(3, 8.0))
    centres = lattice_packing(box, r, "cubic")
    interior = box.contains(centres, margin=3.0 * r)
    assert interior.sum() >= 8
    np.testing.assert_array_equal(_neighbour_counts(centres, 2.0 * r)[interior], 6)
    np.testing.assert_array_equal(_neighbour_counts(centres, 2.0 * r * math.sqrt(2.0))[interior], 12)


@pytest.mark.parametrize(
    ("arrangement", "phi_inf", "circumradius"),
    [("hcp", PHI_HCP, math.sqrt(2.0)), ("cubic", PHI_CUBIC, math.sqrt(3.0))],
)
def test_lattice_solid_fraction_approaches_ideal(arrangement: str, phi_inf: float, circumradius: float) -> None:
    r = 1.0
    rv = circumradius * r
    widths = []
    for size in (np.array([12.0, 17.3, 9.1]), np.array([30.7, 41.3, 25.9]), np.array([150.3, 141.7, 160.1])):
        box = Box(np.array([-5.0, 2.0, 11.0]), np.array([-5.0, 2.0, 11.0]) + size)
        n = len(lattice_packing(box, r, arrangement))  # type: ignore[arg-type]
        phi = n * 4.0 / 3.0 * math.pi * r**3 / box.volume()
        lower = phi_inf * np.prod(1.0 - 2.0 * (r + rv) / size)
        upper = phi_inf * np.prod(1.0 + 2.0 * (rv - r) / size)
        assert lower <= phi <= upper
        widths.append((upper - lower) / phi_inf)
    # The bracket shrinks like 1/L around π/(3√2) (or π/6): to 11 % (13.5 %) of it for a box ~150 r wide.
    assert widths[0] > widths[1] > widths[2]
    assert widths[2] < 0.14


def test_lattice_max_count_keeps_lowest_layers_in_order() -> None:
    box = Box(np.zeros(3), np.full(3, 6.0))
    for arrangement in ("hcp", "cubic"):
        full = lattice_packing(box, 0.5, arrangement)  # type: ignore[arg-type]
        # z-major, then y, then x: lexicographic order of (z, y, x).
        order = np.lexsort((full[:, 0], full[:, 1], full[:, 2]))
        np.testing.assert_array_equal(order, np.arange(len(full)))
        part = lattice_packing(box, 0.5, arrangement, max_count=17)  # type: ignore[arg-type]
        np.testing.assert_array_equal(part, full[:17])
        assert part[:, 2].max() <= full[17:, 2].min()


def test_lattice_invalid_arguments_raise() -> None:
    box = Box(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="arrangement"):
        lattice_packing(box, 0.1, "fcc")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="radius"):
        lattice_packing(box, -0.1, "hcp")
    with pytest.raises(ValueError, match="max_count"):
        lattice_packing(box, 0.1, "hcp", max_count=-1)


# ------------------------------------------------------------------------------------------------------------
# Random sequential addition


@pytest.mark.parametrize(("r_min", "r_max"), [(0.5, 0.5), (0.3, 0.7)])
def test_random_spheres_inside_and_disjoint(r_min: float, r_max: float) -> None:
    rng = np.random.default_rng(11)
    for region in _regions(9.0):
        centres, radii = random_packing(region, r_min, r_max, rng, volume_fraction=0.25)
        _assert_valid_packing(region, centres, radii)
        assert np.all((radii >= r_min) & (radii <= r_max))


def test_random_packing_reaches_target_fraction() -> None:
    box = Box(np.zeros(3), np.full(3, 12.0))
    centres, radii = random_packing(box, 0.5, 0.5, np.random.default_rng(3), volume_fraction=0.3)
    _assert_valid_packing(box, centres, radii)
    phi = np.sum(4.0 / 3.0 * math.pi * radii**3) / box.volume()
    # Stops right after the sphere that reaches the target: within one sphere volume above it.
    assert 0.3 <= phi < 0.3 + 4.0 / 3.0 * math.pi * 0.5**3 / box.volume()


def test_random_packing_is_deterministic() -> None:
    cylinder = Cylinder(center=np.zeros(3), radius=4.0, height=8.0, axis=1)
    a = random_packing(cylinder, 0.3, 0.6, np.random.default_rng(42), volume_fraction=0.3)
    b = random_packing(cylinder, 0.3, 0.6, np.random.default_rng(42), volume_fraction=0.3)
    c = random_packing(cylinder, 0.3, 0.6, np.random.default_rng(43), volume_fraction=0.3)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert len(a[0]) != len(c[0]) or not np.array_equal(a[0], c[0])


def test_random_packing_max_count() -> None:
    box = Box(np.zeros(3), np.full(3, 10.0))
    centres, radii = random_packing(box, 0.2, 0.4, np.random.default_rng(0), volume_fraction=0.4, max_count=123)
    assert centres.shape == (123, 3) and radii.shape == (123,)
    _assert_valid_packing(box, centres, radii)
    empty = random_packing(box, 0.2, 0.4, np.random.default_rng(0), max_count=0)
    assert empty[0].shape == (0, 3) and empty[1].shape == (0,)


def test_random_radii_and_positions_are_uniform() -> None:
    # Far from jamming, the placed radii are the drawn U(a, b) radii and the centres uniform in the box shrunk by
    # the radius: their means lie within 5 standard errors of (a + b)/2 and of the box centre.
    a, b = 0.2, 0.6
    box = Box(np.zeros(3), np.array([20.0, 14.0, 10.0]))
    centres, radii = random_packing(box, a, b, np.random.default_rng(5), volume_fraction=0.15)
    n = len(radii)
    assert n > 1000
    np.testing.assert_allclose(radii.mean(), 0.5 * (a + b), atol=5.0 * (b - a) / math.sqrt(12.0 * n))
    half = 0.5 * (box.hi - box.lo)
    for axis in range(3):
        # A uniform coordinate over a span of ~2 half has standard deviation half/√3.
        np.testing.assert_allclose(centres[:, axis].mean(), half[axis], atol=5.0 * half[axis] / math.sqrt(3.0 * n))


def test_random_packing_jams_gracefully() -> None:
    # Equal spheres cannot pass ~0.38 by RSA (less in a small box): the run stops when attempts run out.
    box = Box(np.zeros(3), np.full(3, 8.0))
    centres, radii = random_packing(box, 0.5, 0.5, np.random.default_rng(9), volume_fraction=0.6, max_attempts=200_000)
    _assert_valid_packing(box, centres, radii)
    phi = np.sum(4.0 / 3.0 * math.pi * radii**3) / box.volume()
    assert 0.2 < phi < 0.38


def test_random_packing_nothing_fits() -> None:
    box = Box(np.zeros(3), np.array([1.0, 1.0, 0.5]))
    centres, radii = random_packing(box, 0.3, 0.4, np.random.default_rng(0))
    assert centres.shape == (0, 3) and radii.shape == (0,)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"radius_min": 0.0},
        {"radius_min": 0.5, "radius_max": 0.4},
        {"volume_fraction": 0.0},
        {"volume_fraction": 1.0},
        {"max_count": -1},
        {"max_attempts": -5},
    ],
)
def test_random_packing_invalid_arguments_raise(kwargs: dict) -> None:
    args = {"radius_min": 0.1, "radius_max": 0.2, "volume_fraction": 0.3} | kwargs
    with pytest.raises(ValueError):
        random_packing(Box(np.zeros(3), np.ones(3)), rng=np.random.default_rng(0), **args)


# ------------------------------------------------------------------------------------------------------------
# Acceleration structures against brute force


def test_exclusion_voxels_never_reject_free_positions() -> None:
    from warpdem.build.packing import _ExclusionVoxels

    rng = np.random.default_rng(1)
    lo, hi = np.zeros(3), np.full(3, 6.0)
    r_min, r_max = 0.2, 0.5
    centres = rng.random((300, 3)) * 6.0
    radii = r_min + (r_max - r_min) * rng.random(300)
    voxels = _ExclusionVoxels(lo, hi, r_min, r_max, max_voxels=1 << 22)
    voxels.insert(centres, radii)
    points = rng.random((20000, 3)) * 6.0
    rho = r_min + (r_max - r_min) * rng.random(20000)
    dead = voxels.is_dead(points, rho)
    dist = np.sqrt(np.sum((points[:, None, :] - centres[None, :, :]) ** 2, axis=2))
    overlapping = np.any(dist < rho[:, None] + radii[None, :], axis=1)
    assert not np.any(dead & ~overlapping)  # a rejection is always a true overlap
    assert dead.sum() > 0.5 * overlapping.sum()  # and it catches most of them


def test_first_come_matches_sequential_greedy() -> None:
    from warpdem.build.packing import _CellGrid, _first_come

    rng = np.random.default_rng(2)
    points = rng.random((400, 3)) * 5.0
    radii = 0.2 + 0.3 * rng.random(400)
    grid = _CellGrid(np.zeros(3), np.full(3, 5.0), cell=1.0, capacity=8)
    keep = _first_come(points, radii, grid)
    expected = np.zeros(400, dtype=bool)
    for i in range(400):
        gaps = np.sqrt(np.sum((points[:i][expected[:i]] - points[i]) ** 2, axis=1)) - radii[:i][expected[:i]]
        expected[i] = not np.any(gaps < radii[i])
    np.testing.assert_array_equal(keep, expected)
    assert 0 < keep.sum() < 400
