"""The description of a jointed rock mass and the geometry of its joints (pure numpy).

A :class:`Geology` is a rock mass (a box of layered materials) with openings (:class:`Tunnel`, :class:`Shaft`,
:class:`Room`), solids put back inside the openings (:class:`Solid`) and joint sets (:class:`JointSet`); the joint
surfaces it implies (planes clipped to the box, discs, planes that persist through a few layers) are polygons computed
here, ready for the Gmsh model of :mod:`warpdem.build.geology`. Conventions (coordinates, dip and dip direction) are
:mod:`warpdem.build.geology`'s.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ..scene.continuum import cavity_flush, cavity_problem

# Openings spanning the model and joint polygons are built this fraction of the box diagonal past the box, so
# every boolean intersection with the box faces is transversal rather than coincident.
_MARGIN = 0.05

# Points closer than this fraction of the box diagonal count as coincident (plane on a box face, polygon
# vertices merged after clipping, mesh nodes on a box face).
_REL_TOL = 1e-9


@dataclass
class RockMass:
    """The model box and its horizontal material layers.

    Attributes:
        lo: Lower corner (x, y, z) of the box [m].
        hi: Upper corner (x, y, z) of the box [m].
        layers: Horizontal layers from the bottom up as ``(z_top, material_name)``: each layer fills from the
            previous ``z_top`` (or the box bottom) up to its own ``z_top`` [m]. Layer tops inside the box become
            conforming internal surfaces of the mesh (material interfaces, not joints).
        material: Material above the highest layer top (the whole box when ``layers`` is empty).
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    layers: list[tuple[float, str]] = field(default_factory=list)
    material: str = "rock"

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)):
            raise ValueError(f"RockMass: lo and hi must be three finite numbers, got {self.lo!r}, {self.hi!r}")
        if np.any(hi <= lo):
            raise ValueError(f"RockMass: hi {self.hi!r} must exceed lo {self.lo!r} on every axis")
        tops = [float(z) for z, _ in self.layers]
        if any(b <= a for a, b in itertools.pairwise(tops)):
            raise ValueError(f"RockMass.layers: z_top must increase from the bottom up, got {tops}")
        if tops and (tops[0] <= lo[2] or tops[-1] > hi[2]):
            raise ValueError(f"RockMass.layers: every z_top must lie in ({lo[2]}, {hi[2]}], got {tops}")

    def material_names(self) -> list[str]:
        """Distinct material names present in the box, bottom to top."""
        names = [name for _, name in self.layers]
        if not self.layers or self.layers[-1][0] < self.hi[2]:
            names.append(self.material)
        return list(dict.fromkeys(names))

    def material_of_z(self, z: np.ndarray) -> np.ndarray:
        """Index into :meth:`material_names` of the layer holding each height ``z`` [m], shape like ``z``."""
        names = self.material_names()
        layer_names = [name for _, name in self.layers] + [self.material]
        layer_index = np.searchsorted(np.array([t for t, _ in self.layers], float), z, side="left")
        lookup = np.array([names.index(n) if n in names else 0 for n in layer_names], dtype=np.int64)
        return lookup[layer_index]


@dataclass
class Tunnel:
    """A horizontal tunnel along x or y.

    The cross-section is centred on ``centre``, the centre of its bounding rectangle: for ``axis="y"`` it is
    (x, z) of the tunnel axis, for ``axis="x"`` it is (y, z).

    Attributes:
        axis: Direction of the tunnel axis, ``"x"`` or ``"y"``.
        centre: Cross-section centre [m], (x, z) or (y, z) as above.
        shape: ``"circular"`` (radius ``radius``), ``"rectangular"`` (``width`` × ``height``) or ``"horseshoe"``
            (flat floor, vertical walls, semicircular crown of radius ``width / 2``; total height ``height``,
            which must exceed ``width / 2``).
        radius: Radius of a circular tunnel [m].
        width: Span of a rectangular or horseshoe tunnel [m].
        height: Floor-to-crown height of a rectangular or horseshoe tunnel [m].
        span: (start, end) of the tunnel along its axis [m]; ``None`` runs it through the whole model.
    """

    axis: Literal["x", "y"]
    centre: tuple[float, float]
    shape: Literal["circular", "horseshoe", "rectangular"] = "circular"
    radius: float | None = None
    width: float | None = None
    height: float | None = None
    span: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.axis not in ("x", "y"):
            raise ValueError(f"Tunnel.axis: expected 'x' or 'y', got {self.axis!r}")
        if self.shape == "circular":
            if self.radius is None or not self.radius > 0:
                raise ValueError(f"Tunnel: a circular tunnel needs radius > 0, got {self.radius!r}")
        elif self.shape in ("rectangular", "horseshoe"):
            if self.width is None or self.height is None or not (self.width > 0 and self.height > 0):
                raise ValueError(f"Tunnel: a {self.shape} tunnel needs width > 0 and height > 0")
            if self.shape == "horseshoe" and not self.height > 0.5 * self.width:
                raise ValueError(f"Tunnel: a horseshoe needs height > width / 2, got {self.height} ≤ {self.width}/2")
        else:
            raise ValueError(f"Tunnel.shape: expected 'circular', 'horseshoe' or 'rectangular', got {self.shape!r}")
        if self.span is not None and not self.span[1] > self.span[0]:
            raise ValueError(f"Tunnel.span: end must exceed start, got {self.span!r}")


@dataclass
class Shaft:
    """A vertical cylindrical shaft.

    Attributes:
        centre: (x, y) of the shaft axis [m].
        radius: Shaft radius [m].
        bottom: Height of the shaft floor [m]; ``None`` runs it through the box bottom.
        top: Height of the shaft top [m]; ``None`` runs it through the box top (open to the surface).
    """

    centre: tuple[float, float]
    radius: float
    bottom: float | None = None
    top: float | None = None

    def __post_init__(self) -> None:
        if not self.radius > 0:
            raise ValueError(f"Shaft.radius must be > 0, got {self.radius!r}")
        if self.bottom is not None and self.top is not None and not self.top > self.bottom:
            raise ValueError(f"Shaft: top {self.top} must exceed bottom {self.bottom}")


@dataclass
class Room:
    """An axis-aligned box-shaped excavation.

    Attributes:
        lo: Lower corner (x, y, z) [m].
        hi: Upper corner (x, y, z) [m].
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self) -> None:
        if np.any(np.asarray(self.hi, float) <= np.asarray(self.lo, float)):
            raise ValueError(f"Room: hi {self.hi!r} must exceed lo {self.lo!r} on every axis")


Opening = Tunnel | Shaft | Room


@dataclass
class Refinement:
    """A box meshed finer than the rest of a geology model (a wall that needs more elements through its thickness
    than the rock around it): Gmsh's tets have edge ``h`` inside it and the model's ``h`` outside; the size steps at
    its faces, and Gmsh grades the tets across them.

    Attributes:
        lo: Lower corner (x, y, z) [m].
        hi: Upper corner (x, y, z) [m].
        h: Target tet edge length inside [m]; below the model's ``h``.
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    h: float

    def __post_init__(self) -> None:
        if np.any(np.asarray(self.hi, float) <= np.asarray(self.lo, float)):
            raise ValueError(f"Refinement: hi {self.hi!r} must exceed lo {self.lo!r} on every axis")
        if not self.h > 0:
            raise ValueError(f"Refinement.h must be > 0, got {self.h!r}")


@dataclass
class Solid:
    """An axis-aligned box put back inside the openings (a concrete box in a tunnel, a charge's casing): a body of its
    own, meshed with the rock but sharing no node with it, with an optional box-shaped cavity (a charge chamber).

    Attributes:
        name: Name of the solid; its walls are the face set ``name`` and its cavity's walls ``name + "_cavity"``.
        lo: Lower corner (x, y, z) [m].
        hi: Upper corner (x, y, z) [m].
        cavity_lo: Lower corner of the cavity [m], or ``None`` for a full box.
        cavity_hi: Upper corner of the cavity [m], or ``None``.

    The cavity lies strictly inside the box, except that it may pass right through along one axis (the thickness of
    a 2-D slice): a cavity flush with a face along another axis would leave a notch, or cut the box in two.
    """

    name: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    cavity_lo: tuple[float, float, float] | None = None
    cavity_hi: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if np.any(hi <= lo):
            raise ValueError(f"Solid {self.name!r}: hi {self.hi!r} must exceed lo {self.lo!r} on every axis")
        if (self.cavity_lo is None) != (self.cavity_hi is None):
            raise ValueError(f"Solid {self.name!r}: a cavity needs both cavity_lo and cavity_hi")
        if self.cavity_lo is None:
            return
        problem = cavity_problem(self.lo, self.hi, self.cavity_lo, self.cavity_hi)
        if problem:
            raise ValueError(f"Solid {self.name!r}: {problem}")

    def through_axes(self) -> list[int]:
        """The axes along which the cavity passes right through the box (at most one)."""
        if self.cavity_lo is None or self.cavity_hi is None:
            return []
        return [
            a
            for a in range(3)
            if cavity_flush(self.cavity_lo[a], self.lo[a], self.hi[a] - self.lo[a])
            and cavity_flush(self.cavity_hi[a], self.hi[a], self.hi[a] - self.lo[a])
        ]


@dataclass
class JointSet:
    """A set of parallel joints.

    Attributes:
        dip: Dip δ [deg], 0 (horizontal) to 90 (vertical).
        dip_direction: Dip direction α [deg], azimuth clockwise from north (+y); the plane normal is
            ``(sin δ sin α, sin δ cos α, cos δ)``.
        spacing: Distance between neighbouring planes along the normal [m].
        offset: Signed distance of plane k = 0 from the origin along the normal [m].
        persistence: ``"persistent"``: planes through the whole model. ``"disc"``: circular joints of radius
            ``radius`` centred on the planes on a square grid of pitch ``disc_spacing`` along strike and dip.
            ``"layers"``: planes that persist through ``layers`` consecutive slabs between the planes of the
            persistent set ``reference``, then stop for the next ``layers`` slabs, alternately (LDEC Fig. 6).
        radius: Disc radius [m] (``"disc"``).
        disc_spacing: Centre-to-centre pitch of the discs within a plane [m] (``"disc"``); default
            ``2.5 * radius``.
        reference: Index in :attr:`Geology.joint_sets` of the persistent set whose planes bound the slabs
            (``"layers"``).
        layers: Number of consecutive slabs a plane persists through (``"layers"``). Slab k lies between
            reference planes k and k + 1; the set's planes fill the slabs with ``(k // layers) % 2 == phase``.
        phase: 0 or 1, which alternation of slab groups holds joints (``"layers"``).
        layers_max: Randomized persistence (``"layers"``; LDEC's "non-persistent (i.e., randomized)" geology, its
            Fig. 6): each plane of the set, on its own, alternates runs of slabs that hold a joint piece with runs
            that hold none, each run a uniform draw of ``layers`` to ``layers_max`` slabs, starting at a random point
            of a random run; a run's piece is one plane polygon through its slabs. ``phase`` is not used then.
        jitter_position: Each plane (each disc, each plane piece of a ``"layers"`` group) is shifted along its
            normal by a uniform draw from ``[-jitter_position, jitter_position]`` [m]; disc centres are also
            shifted by such draws along strike and dip.
        jitter_angle: Each plane's (disc's, piece's) normal is tilted by a uniform draw from ``[0, jitter_angle]``
            [deg] about a uniformly random axis in the plane.
        name: Name of the set (physical group name on export); default ``joint<i>``.
    """

    dip: float
    dip_direction: float
    spacing: float
    offset: float = 0.0
    persistence: Literal["persistent", "disc", "layers"] = "persistent"
    radius: float | None = None
    disc_spacing: float | None = None
    reference: int | None = None
    layers: int = 1
    phase: int = 0
    layers_max: int | None = None
    jitter_position: float = 0.0
    jitter_angle: float = 0.0
    name: str | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.dip <= 90.0:
            raise ValueError(f"JointSet.dip must lie in [0, 90] degrees, got {self.dip!r}")
        if not self.spacing > 0:
            raise ValueError(f"JointSet.spacing must be > 0, got {self.spacing!r}")
        if self.jitter_position < 0 or self.jitter_angle < 0:
            raise ValueError("JointSet: jitter_position and jitter_angle must be ≥ 0")
        if self.persistence == "disc":
            if self.radius is None or not self.radius > 0:
                raise ValueError(f"JointSet: persistence 'disc' needs radius > 0, got {self.radius!r}")
            if self.disc_spacing is not None and not self.disc_spacing > 0:
                raise ValueError(f"JointSet.disc_spacing must be > 0, got {self.disc_spacing!r}")
        elif self.persistence == "layers":
            if self.reference is None:
                raise ValueError("JointSet: persistence 'layers' needs reference (index of a persistent set)")
            if self.layers < 1 or self.phase not in (0, 1):
                raise ValueError(f"JointSet: layers must be ≥ 1 and phase 0 or 1, got {self.layers}, {self.phase}")
            if self.layers_max is not None and self.layers_max < self.layers:
                raise ValueError(f"JointSet: layers_max must be ≥ layers ({self.layers}), got {self.layers_max}")
        elif self.layers_max is not None:
            raise ValueError(f"JointSet: layers_max is for persistence 'layers', not {self.persistence!r}")
        elif self.persistence != "persistent":
            raise ValueError(
                f"JointSet.persistence: expected 'persistent', 'disc' or 'layers', got {self.persistence!r}"
            )


@dataclass
class Geology:
    """A jointed rock mass with openings, ready for :func:`mesh_geology`.

    Attributes:
        rock: The model box and its material layers.
        openings: Tunnels, shafts and rooms cut out of the box.
        joint_sets: Joint sets; set i is named ``joint<i>`` unless it has a name.
        h: Target tetrahedron edge length [m].
        h_opening: Edge length on the opening walls [m]; ``None`` meshes them at ``h``.
        refine_distance: Distance from the opening walls over which the size grows from ``h_opening`` to ``h``
            [m]; default ``4 * h``.
        seed: Seed of the jitter draws. Every joint surface draws from its own generator keyed by (seed, set
            index, plane index k, and the slab group or in-plane disc position), so a surface's jitter does not
            change when sets are added or the box is resized.
        solids: Boxes put back inside the openings (:class:`Solid`), each a separate body of the mesh; joints do not
            cut them.
        refinements: Boxes meshed at an edge below ``h`` (:class:`Refinement`).
    """

    rock: RockMass
    openings: list[Opening] = field(default_factory=list)
    joint_sets: list[JointSet] = field(default_factory=list)
    h: float = 1.0
    h_opening: float | None = None
    refine_distance: float | None = None
    seed: int = 0
    solids: list[Solid] = field(default_factory=list)
    refinements: list[Refinement] = field(default_factory=list)

    def __post_init__(self) -> None:
        names = [s.name for s in self.solids]
        for name in names:
            if names.count(name) > 1:
                raise ValueError(f"Geology.solids: the name {name!r} is used twice")
        for (i, a), (j, b) in itertools.combinations(enumerate(self.solids), 2):
            if all(a.lo[k] < b.hi[k] and b.lo[k] < a.hi[k] for k in range(3)):
                raise ValueError(f"Geology.solids: solids {i} ({a.name!r}) and {j} ({b.name!r}) overlap")
        if not self.h > 0:
            raise ValueError(f"Geology.h must be > 0, got {self.h!r}")
        if self.h_opening is not None and not self.h_opening > 0:
            raise ValueError(f"Geology.h_opening must be > 0, got {self.h_opening!r}")
        for i, r in enumerate(self.refinements):
            if not r.h < self.h:
                raise ValueError(f"Geology.refinements[{i}].h = {r.h!r} must be below h = {self.h!r}")
        for i, js in enumerate(self.joint_sets):
            if js.persistence != "layers":
                continue
            ref = js.reference
            if ref is None or not 0 <= ref < len(self.joint_sets) or ref == i:
                raise ValueError(f"Geology.joint_sets[{i}].reference: {ref!r} is not another joint set's index")
            if self.joint_sets[ref].persistence != "persistent":
                raise ValueError(f"Geology.joint_sets[{i}].reference: joint set {ref} is not persistent")

    def joint_set_names(self) -> list[str]:
        """Names of the joint sets, ``joint<i>`` where a set has none."""
        return [js.name or f"joint{i}" for i, js in enumerate(self.joint_sets)]


def joint_normal(dip: float, dip_direction: float) -> np.ndarray:
    """Upward unit normal of a plane with the given dip and dip direction.

    Args:
        dip: Dip δ [deg] below the horizontal.
        dip_direction: Dip direction α [deg], azimuth clockwise from north (+y), x east, z up.

    Returns:
        ``(sin δ sin α, sin δ cos α, cos δ)``, shape (3,).
    """
    d, a = math.radians(dip), math.radians(dip_direction)
    return np.array([math.sin(d) * math.sin(a), math.sin(d) * math.cos(a), math.cos(d)])


# ---------------------------------------------------------------------------------------------------------------
# Joint geometry (pure numpy)
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class _Plane:
    """A plane ``normal · x = distance`` (unit normal)."""

    normal: np.ndarray
    distance: float


def _in_plane_axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane with normal n: strike (horizontal) and the up-dip direction."""
    strike = np.cross(np.array([0.0, 0.0, 1.0]), n)
    if np.linalg.norm(strike) < 1e-12:  # horizontal plane: any horizontal pair
        strike = np.array([1.0, 0.0, 0.0])
    strike /= np.linalg.norm(strike)
    return strike, np.cross(n, strike)


def _tilt(n: np.ndarray, max_angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Rotates unit vector n by a uniform angle in [0, max] about a uniformly random axis perpendicular to n."""
    angle = math.radians(max_angle_deg) * rng.random()
    phi = 2.0 * math.pi * rng.random()
    e1, e2 = _in_plane_axes(n)
    axis = math.cos(phi) * e1 + math.sin(phi) * e2
    return n * math.cos(angle) + np.cross(axis, n) * math.sin(angle)  # Rodrigues with axis ⟂ n


def _rng(seed: int, *keys: int) -> np.random.Generator:
    """Generator for one joint surface, keyed by (seed, set, plane, ...); integers map zigzag onto the
    non-negative entropy words numpy accepts, so every surface's draws depend only on its own keys."""
    return np.random.default_rng([2 * k if k >= 0 else -2 * k - 1 for k in (seed, *keys)])


def _plane_index_range(n: np.ndarray, offset: float, spacing: float, lo: np.ndarray, hi: np.ndarray, pad: int) -> range:
    """Integer range of the plane indices k whose nominal plane can meet the box, widened by pad on both sides."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    d = corners @ n
    return range(math.floor((d.min() - offset) / spacing) - pad, math.ceil((d.max() - offset) / spacing) + pad + 1)


def _jittered_plane(js: JointSet, n0: np.ndarray, k: int, rng: np.random.Generator) -> _Plane:
    """Plane k of set js with its position and angle jitter drawn from rng (two draws for the tilt, one shift)."""
    n = _tilt(n0, js.jitter_angle, rng) if js.jitter_angle > 0 else n0
    shift = js.jitter_position * (2.0 * rng.random() - 1.0) if js.jitter_position > 0 else 0.0
    return _Plane(n, js.offset + k * js.spacing + shift)


def _cuts_box(plane: _Plane, lo: np.ndarray, hi: np.ndarray, tol: float) -> bool:
    """Whether the plane passes through the box interior (not just touching a face, edge or corner)."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    d = corners @ plane.normal - plane.distance
    return bool(d.max() > tol and d.min() < -tol)


def _clip_polygon(poly: list[np.ndarray], a: np.ndarray, b: float) -> list[np.ndarray]:
    """Sutherland–Hodgman: the part of the planar polygon with ``a · x ≤ b``."""
    out: list[np.ndarray] = []
    for i, p in enumerate(poly):
        q = poly[(i + 1) % len(poly)]
        fp, fq = float(a @ p - b), float(a @ q - b)
        if fp <= 0.0:
            out.append(p)
        if fp * fq < 0.0:
            out.append(p + (fp / (fp - fq)) * (q - p))
    return out


def _clip_to_box(poly: list[np.ndarray], lo: np.ndarray, hi: np.ndarray) -> list[np.ndarray]:
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = 1.0
        poly = _clip_polygon(poly, e, float(hi[axis]))
        poly = _clip_polygon(poly, -e, -float(lo[axis])) if poly else poly
        if not poly:
            break
    return poly


def _dedupe(poly: list[np.ndarray], tol: float) -> list[np.ndarray]:
    """Drops consecutive (cyclically) vertices closer than tol."""
    out: list[np.ndarray] = []
    for p in poly:
        if not out or np.linalg.norm(p - out[-1]) > tol:
            out.append(p)
    while len(out) > 1 and np.linalg.norm(out[0] - out[-1]) <= tol:
        out.pop()
    return out


def _polygon_area(poly: list[np.ndarray]) -> float:
    p = np.asarray(poly)
    return 0.5 * float(np.linalg.norm(np.cross(p - p[0], np.roll(p, -1, axis=0) - p[0]).sum(axis=0)))


def _plane_square(plane: _Plane, centre: np.ndarray, half: float) -> list[np.ndarray]:
    """A square of half-size ``half`` on the plane, centred on the projection of ``centre``."""
    c = centre - (plane.normal @ centre - plane.distance) * plane.normal
    e1, e2 = _in_plane_axes(plane.normal)
    return [c + half * (s1 * e1 + s2 * e2) for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1))]


@dataclass
class _JointPolygon:
    set_index: int
    vertices: list[np.ndarray]


@dataclass
class _JointDisc:
    set_index: int
    centre: np.ndarray
    normal: np.ndarray
    radius: float


def _layer_pieces(js: JointSet, ref_ks: list[int], ks: range, seed: int, i: int) -> list[tuple[int, int, int, int]]:
    """The pieces of a ``"layers"`` set ``i``: (plane index k, first reference plane k0, last k1, jitter key), a
    piece lying in the slabs between reference planes k0 and k1 (``ref_ks``: the reference set's plane indices, in
    order). Regular: every plane fills the slab groups g (``layers`` slabs each) with g % 2 == phase, keyed by g.
    Randomized (``layers_max``): each plane alternates runs of ``layers`` to ``layers_max`` slabs with and without a
    piece (:func:`_random_runs`), its draws its own (keyed by (seed, set, plane) alone), a piece keyed by its k0."""
    pieces = []
    if js.layers_max is None:
        for g in sorted({math.floor(k / js.layers) for k in ref_ks[:-1]}):
            if g % 2 == js.phase:
                pieces += [(k, g * js.layers, (g + 1) * js.layers, g) for k in ks]
        return pieces
    for k in ks:
        rng = _rng(seed, i, k, 0, 0, 0)  # six keys: no other surface's generator has as many
        pieces += [(k, k0, k1, k0) for k0, k1 in _random_runs(rng, ref_ks[0], ref_ks[-1], js.layers, js.layers_max)]
    return pieces


def _random_runs(rng: np.random.Generator, first: int, last: int, shortest: int, longest: int) -> list[tuple[int, int]]:
    """Runs [k0, k1) of the slabs first..last - 1 that hold a joint piece: runs with and without alternate, each
    ``shortest`` to ``longest`` slabs long (uniform), the first with or without (even odds) and begun a uniform
    0..longest - 1 slabs before ``first``, so that the pattern has no edge at the box's."""
    runs = []
    has_piece = bool(rng.integers(2))
    k = first - int(rng.integers(longest))
    while k < last:
        n = int(rng.integers(shortest, longest + 1))
        if has_piece and min(k + n, last) > max(k, first):
            runs.append((max(k, first), min(k + n, last)))
        k += n
        has_piece = not has_piece
    return runs


def _joint_geometry(geology: Geology) -> list[_JointPolygon | _JointDisc]:
    """Joint surfaces of every set: polygons clipped to the box grown by the margin (and to the slabs of a
    ``"layers"`` set), and discs. Pieces outside the box or inside openings are removed after the fragment."""
    lo, hi = np.asarray(geology.rock.lo, float), np.asarray(geology.rock.hi, float)
    diag = float(np.linalg.norm(hi - lo))
    tol = _REL_TOL * diag
    margin = _MARGIN * diag
    glo, ghi = lo - margin, hi + margin
    centre = 0.5 * (lo + hi)
    sets = geology.joint_sets
    seed = geology.seed
    nominal = [joint_normal(js.dip, js.dip_direction) for js in sets]

    # Every persistent set's planes, padded past the box: a reference set reaches one slab group past the box
    # on each side, so the groups cut by the box faces have both bounding planes.
    pads = [
        1 + max((js.layers for js in sets if js.persistence == "layers" and js.reference == i), default=0)
        for i in range(len(sets))
    ]
    planes: dict[int, dict[int, _Plane]] = {}
    for i, js in enumerate(sets):
        if js.persistence == "persistent":
            ks = _plane_index_range(nominal[i], js.offset, js.spacing, lo, hi, pad=pads[i])
            planes[i] = {k: _jittered_plane(js, nominal[i], k, _rng(seed, i, k)) for k in ks}

    surfaces: list[_JointPolygon | _JointDisc] = []
    for i, js in enumerate(sets):
        if js.persistence == "persistent":
            for plane in planes[i].values():
                if _cuts_box(plane, lo, hi, tol):
                    poly = _dedupe(_clip_to_box(_plane_square(plane, centre, diag), glo, ghi), tol)
                    if len(poly) >= 3:
                        surfaces.append(_JointPolygon(i, poly))
        elif js.persistence == "layers":
            ref = planes[js.reference]
            ref_ks = sorted(ref)
            ks = _plane_index_range(nominal[i], js.offset, js.spacing, lo, hi, pad=1)
            for k, k0, k1, key in _layer_pieces(js, ref_ks, ks, seed, i):
                if k0 not in ref or k1 not in ref:
                    continue
                bottom, top = ref[k0], ref[k1]
                # Each piece jitters on its own: the joints do not line up across groups.
                plane = _jittered_plane(js, nominal[i], k, _rng(seed, i, k, key))
                if not _cuts_box(plane, lo, hi, tol):
                    continue
                poly = _clip_to_box(_plane_square(plane, centre, diag), glo, ghi)
                poly = _clip_polygon(poly, -bottom.normal, -bottom.distance) if poly else poly
                poly = _clip_polygon(poly, top.normal, top.distance) if poly else poly
                poly = _dedupe(poly, tol) if poly else poly
                if len(poly) >= 3 and _polygon_area(poly) > tol * diag:
                    surfaces.append(_JointPolygon(i, poly))
        else:  # disc
            pitch = js.disc_spacing or 2.5 * js.radius
            e1, e2 = _in_plane_axes(nominal[i])
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            reach = js.radius + 2.0 * js.jitter_position
            u_range = range(
                math.floor(((corners @ e1).min() - reach) / pitch),
                math.ceil(((corners @ e1).max() + reach) / pitch) + 1,
            )
            v_range = range(
                math.floor(((corners @ e2).min() - reach) / pitch),
                math.ceil(((corners @ e2).max() + reach) / pitch) + 1,
            )
            for k in _plane_index_range(nominal[i], js.offset, js.spacing, lo, hi, pad=0):
                for u in u_range:
                    for v in v_range:
                        rng = _rng(seed, i, k, u, v)
                        c = (js.offset + k * js.spacing) * nominal[i] + u * pitch * e1 + v * pitch * e2
                        n = _tilt(nominal[i], js.jitter_angle, rng) if js.jitter_angle > 0 else nominal[i]
                        if js.jitter_position > 0:
                            shift = js.jitter_position * (2.0 * rng.random(3) - 1.0)
                            c = c + shift @ np.array([nominal[i], e1, e2])
                        # Keep discs that reach the box; a disc only touching it would add a stray curve.
                        if np.linalg.norm(c - np.clip(c, lo, hi)) < js.radius - tol:
                            surfaces.append(_JointDisc(i, c, n, js.radius))
    return surfaces
