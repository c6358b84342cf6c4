"""Jointed-rock geology: a rock mass with openings and joint sets, meshed with tetrahedra that conform to the joints.

The model follows the jointed geologies of LDEC (Morris et al., §3 and Fig. 6): regular persistent joint sets
that cut the whole model into polyhedral blocks, and non-persistent sets (finite discs, or planes that persist
only through a few layers between the planes of a persistent set). :func:`mesh_geology` builds the geometry
with the Gmsh OpenCASCADE kernel: the box minus the openings (boolean cut) is fragmented by the material layer
planes and by every joint surface, so each rock block is one Gmsh volume and the tetrahedral mesh conforms to
the joints: the two tetrahedra on either side of a joint share the face's three nodes. Splitting those nodes
into cohesive or contact interfaces is left to the FEM/DEM builder.

Coordinates: x east, y north, z up, all lengths in metres. Joint orientation uses the geological convention:
dip δ ∈ [0°, 90°] is the angle of the plane below the horizontal, dip direction α is the azimuth of the
steepest descent measured clockwise from north (+y). The upward unit normal of the plane is (see
:func:`joint_normal`)::

    n = (sin δ sin α, sin δ cos α, cos δ)

A joint set's planes are ``n · x = offset + k · spacing`` for every integer k whose plane cuts the box.

:func:`read_mesh` and :func:`write_mesh` move a :class:`GeologyMesh` through meshio (Gmsh ``.msh`` and VTU):
tetrahedra carry a physical group (the material) and a geometrical entity (the block), triangles a physical
group whose name makes it a joint set (``joint*``) or a named boundary/load set.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import pathlib
import re
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal
from xml.sax.saxutils import quoteattr

import numpy as np

from .limits import F32_MAX
from .mesh import TET_FACES
from .mesh import boundary_faces as outer_faces

__all__ = [
    "BOX_FACE_NAMES",
    "Geology",
    "GeologyMesh",
    "JointSet",
    "MeshImportError",
    "RockMass",
    "Room",
    "Shaft",
    "Tunnel",
    "component_labels",
    "interior_faces",
    "joint_normal",
    "mesh_cylinder",
    "mesh_ellipsoid",
    "mesh_geology",
    "mesh_geology_cached",
    "read_mesh",
    "write_mesh",
]

BOX_FACE_NAMES = ("x-", "x+", "y-", "y+", "z-", "z+")
"""Names of the outer box faces in :attr:`GeologyMesh.boundary_faces`, in (axis, low/high) order."""

OPENING_FACE_NAME = "opening"
"""Name of the tunnel, shaft and room walls in :attr:`GeologyMesh.boundary_faces`."""

SURFACE_FACE_NAME = "surface"
"""Name of the whole outer surface of a solid meshed by :func:`mesh_cylinder` or :func:`mesh_ellipsoid`."""

# Openings spanning the model and joint polygons are built this fraction of the box diagonal past the box, so
# every boolean intersection with the box faces is transversal rather than coincident.
_MARGIN = 0.05

OPTIMIZE_THRESHOLD = 0.5
"""Gmsh optimises the tets whose quality gamma (inradius over longest edge, 1 for a regular tet) is below this.
Gmsh's default is 0.3; 0.5 raises the tets' stable time step of the non-persistent tunnel scene by 21 % and the
smallest dihedral angle of the slope scene from 13° to 18°."""

# Points closer than this fraction of the box diagonal count as coincident (plane on a box face, polygon
# vertices merged after clipping, mesh nodes on a box face).
_REL_TOL = 1e-9

_GMSH_TET = 4  # Gmsh element type: 4-node tetrahedron
_GMSH_TRIANGLE = 2  # Gmsh element type: 3-node triangle

# Outward faces of a positively oriented tetrahedron (0, 1, 2, 3): face i is opposite vertex i.

_READ_SUFFIXES = {".msh": "gmsh", ".vtu": "vtu", ".vtk": "vtk"}
_LINEAR_VOLUME_CELLS = {"tetra"}
_SURFACE_CELLS = {"triangle"}


class MeshImportError(ValueError):
    """A mesh file cannot be used as a geology mesh; the message is one line naming the file and the problem.

    Attributes:
        argument: The :func:`read_mesh` argument the problem is about (``"material_map"``, ``"joint_groups"``), or
            None for a problem of the file itself.
    """

    def __init__(self, message: str, argument: str | None = None) -> None:
        super().__init__(message)
        self.argument = argument


# ---------------------------------------------------------------------------------------------------------------
# Scene description
# ---------------------------------------------------------------------------------------------------------------


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
        jitter_position: Each plane (each disc, each plane piece of a ``"layers"`` group) is shifted along its
            normal by a uniform draw from [-jitter_position, jitter_position] [m]; disc centres are also
            shifted by such draws along strike and dip.
        jitter_angle: Each plane's (disc's, piece's) normal is tilted by a uniform draw from [0, jitter_angle]
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
    """

    rock: RockMass
    openings: list[Opening] = field(default_factory=list)
    joint_sets: list[JointSet] = field(default_factory=list)
    h: float = 1.0
    h_opening: float | None = None
    refine_distance: float | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.h > 0:
            raise ValueError(f"Geology.h must be > 0, got {self.h!r}")
        if self.h_opening is not None and not self.h_opening > 0:
            raise ValueError(f"Geology.h_opening must be > 0, got {self.h_opening!r}")
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


@dataclass
class GeologyMesh:
    """A tetrahedral rock mesh with its blocks, materials, joint faces and boundary sets.

    Attributes:
        points: Node positions [m], shape (N, 3), float64. Nodes are numbered 0..N-1 and all belong to tets.
        tets: Node indices of the tetrahedra, shape (M, 4), int64, positively oriented
            (``det[p1 - p0, p2 - p0, p3 - p0] > 0``).
        tet_block: Rock block (Gmsh volume) of each tet, shape (M,), int64, values 0..num_blocks-1.
        tet_material: Index into ``material_names`` of each tet, shape (M,), int64.
        material_names: Material names.
        joint_faces: Node triples of the mesh faces on joint surfaces, shape (J, 3), int64. Each face appears
            once and is shared by the two tets on either side. :func:`mesh_geology` orients each face so its
            right-hand normal points along the set's nominal normal (:func:`joint_normal`).
        joint_face_set: Joint set of each joint face, shape (J,), int64, index into ``joint_set_names``.
        joint_set_names: Joint set names.
        boundary_faces: Named face sets, name → node triples shape (F, 3), int64. :func:`mesh_geology` gives the
            outer box faces (:data:`BOX_FACE_NAMES`) and ``"opening"`` (tunnel, shaft and room walls), each face
            oriented with its normal pointing out of the rock.
        num_blocks: Number of rock blocks.
    """

    points: np.ndarray
    tets: np.ndarray
    tet_block: np.ndarray
    tet_material: np.ndarray
    material_names: list[str]
    joint_faces: np.ndarray
    joint_face_set: np.ndarray
    joint_set_names: list[str]
    boundary_faces: dict[str, np.ndarray]
    num_blocks: int

    def tet_volumes(self) -> np.ndarray:
        """Volume of each tet [m³], shape (M,)."""
        p = self.points[self.tets]
        return np.linalg.det(p[:, 1:] - p[:, :1]) / 6.0


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
            groups = sorted({math.floor(k / js.layers) for k in ref_ks[:-1]})
            ks = _plane_index_range(nominal[i], js.offset, js.spacing, lo, hi, pad=1)
            for g in groups:
                k0, k1 = g * js.layers, (g + 1) * js.layers
                if g % 2 != js.phase or k0 not in ref or k1 not in ref:
                    continue
                bottom, top = ref[k0], ref[k1]
                for k in ks:  # each group's pieces jitter independently: the joints do not line up across groups
                    plane = _jittered_plane(js, nominal[i], k, _rng(seed, i, k, g))
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


# ---------------------------------------------------------------------------------------------------------------
# Gmsh model
# ---------------------------------------------------------------------------------------------------------------


def _add_opening(occ: Any, opening: Opening, lo: np.ndarray, hi: np.ndarray, margin: float) -> int:
    """Adds the opening as an OCC volume; openings that span the model overshoot the box by the margin."""
    if isinstance(opening, Room):
        rlo, rhi = np.asarray(opening.lo, float), np.asarray(opening.hi, float)
        return occ.addBox(*rlo, *(rhi - rlo))
    if isinstance(opening, Shaft):
        z0 = lo[2] - margin if opening.bottom is None else opening.bottom
        z1 = hi[2] + margin if opening.top is None else opening.top
        return occ.addCylinder(opening.centre[0], opening.centre[1], z0, 0.0, 0.0, z1 - z0, opening.radius)
    along = 0 if opening.axis == "x" else 1
    across = 1 - along
    s0, s1 = opening.span if opening.span is not None else (lo[along] - margin, hi[along] + margin)
    length = s1 - s0
    c, zc = opening.centre

    def point(a: float, t: float, z: float) -> np.ndarray:
        p = np.zeros(3)
        p[along], p[across], p[2] = a, t, z
        return p

    axis_vec = point(length, 0.0, 0.0)
    if opening.shape == "circular":
        return occ.addCylinder(*point(s0, c, zc), *axis_vec, opening.radius)
    w, ht = opening.width, opening.height
    if opening.shape == "rectangular":
        corner = point(s0, c - 0.5 * w, zc - 0.5 * ht)
        return occ.addBox(*corner, *point(length, w, ht))
    # Horseshoe: extrude the profile (floor, walls, two quarter arcs of the crown) along the axis.
    z_floor, z_spring, r = zc - 0.5 * ht, zc + 0.5 * ht - 0.5 * w, 0.5 * w
    profile = [(c - r, z_floor), (c + r, z_floor), (c + r, z_spring), (c, z_spring + r), (c - r, z_spring)]
    p = [occ.addPoint(*point(s0, t, z)) for t, z in profile]
    o = occ.addPoint(*point(s0, c, z_spring))
    curves = [
        occ.addLine(p[0], p[1]),
        occ.addLine(p[1], p[2]),
        occ.addCircleArc(p[2], o, p[3]),
        occ.addCircleArc(p[3], o, p[4]),
        occ.addLine(p[4], p[0]),
    ]
    face = occ.addPlaneSurface([occ.addCurveLoop(curves)])
    out = occ.extrude([(2, face)], *axis_vec)
    occ.remove([(0, o)])
    return next(tag for dim, tag in out if dim == 3)


def _add_polygon(occ: Any, vertices: list[np.ndarray]) -> int:
    pts = [occ.addPoint(*v) for v in vertices]
    lines = [occ.addLine(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
    return occ.addPlaneSurface([occ.addCurveLoop(lines)])


def _on_box_face(bbox: Sequence[float], lo: np.ndarray, hi: np.ndarray, tol: float) -> bool:
    """Whether a Gmsh bounding box (xmin, ymin, zmin, xmax, ymax, zmax) lies flat on one of the box faces."""
    for axis in range(3):
        for value in (lo[axis], hi[axis]):
            if abs(bbox[axis] - value) <= tol and abs(bbox[axis + 3] - value) <= tol:
                return True
    return False


def _gmsh_options(h: float, refine: bool) -> dict[str, float]:
    """Every Gmsh option a mesh depends on, so that a caller's own Gmsh settings do not leak in.

    Args:
        h: target tet edge length [m]. refine: a background size field (opening refinement) sets the sizes.
    """
    return {
        "General.Terminal": 0,
        "General.NumThreads": 1,  # single-threaded Delaunay: equal inputs, identical meshes
        "Mesh.Algorithm3D": 1,
        "Mesh.MeshSizeMin": 0.0,
        "Mesh.MeshSizeMax": h,
        "Mesh.MeshSizeFromCurvature": 0,
        "Mesh.MeshSizeExtendFromBoundary": 0 if refine else 1,
        "Mesh.MeshSizeFromPoints": 0 if refine else 1,
        "Mesh.Algorithm": 6,  # Frontal-Delaunay surfaces
        "Mesh.Smoothing": 1,
        "Mesh.QualityType": 2,  # gamma (inradius / longest edge): the quality the optimiser works on
        "Mesh.Optimize": 1,
        "Mesh.OptimizeThreshold": OPTIMIZE_THRESHOLD,
        "Mesh.OptimizeNetgen": 0,  # adds ~70 % tets and lowers the stable step on jointed models
    }


@contextlib.contextmanager
def _gmsh_model(options: Mapping[str, float], model_name: str, what: str) -> Iterator[Any]:
    """A fresh Gmsh model with ``options`` set, yielding the ``gmsh`` module; afterwards Gmsh is finalized if this
    started it, else the caller's model and option values are restored. A Gmsh failure (a plain ``Exception`` with
    Gmsh's last error) becomes ``RuntimeError("<what>: Gmsh failed: ...")``."""
    import gmsh

    started = not gmsh.isInitialized()
    if started:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    saved = {} if started else {name: gmsh.option.getNumber(name) for name in options}
    current_model = None if started else gmsh.model.getCurrent()
    try:
        for name, value in options.items():
            gmsh.option.setNumber(name, value)
        gmsh.model.add(model_name)
        yield gmsh
    except Exception as exc:
        if type(exc) is Exception:  # the Gmsh API raises plain Exception with its last error message
            raise RuntimeError(f"{what}: Gmsh failed: {exc}") from exc
        raise
    finally:
        if started:
            gmsh.finalize()
        else:
            if model_name in gmsh.model.list():
                gmsh.model.setCurrent(model_name)
                gmsh.model.remove()
            if current_model in gmsh.model.list():
                gmsh.model.setCurrent(current_model)
            for name, value in saved.items():
                gmsh.option.setNumber(name, value)


def _gmsh_volume_tets(
    gmsh: Any, volume_tags: Sequence[int], what: str
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """The meshed nodes and the tets of each volume of the current Gmsh model.

    Returns:
        Node coordinates [m] (K, 3); Gmsh node tag → row of the coordinates (-1: none); the tets of each volume
        as rows into the coordinates (T_v, 4); the block index of each of those tets (its volume's position).
    """
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
    index[node_tags.astype(np.int64)] = np.arange(len(node_tags))
    tet_parts, block_parts = [], []
    for b, v in enumerate(volume_tags):
        for etype, _, enodes in zip(*gmsh.model.mesh.getElements(3, v), strict=True):
            if etype != _GMSH_TET:
                raise RuntimeError(f"{what}: Gmsh produced element type {etype} in volume {v}")
            tet_parts.append(index[enodes.astype(np.int64)].reshape(-1, 4))
            block_parts.append(np.full(len(tet_parts[-1]), b, dtype=np.int64))
    return coords.reshape(-1, 3), index, tet_parts, block_parts


def _used_nodes(coords: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contiguous numbering over the nodes the tets use: points (N, 3) float64, the positively oriented tets (M, 4)
    and the map old row → new node (-1 where unused), shape (K,)."""
    used = np.unique(tets)
    renumber = np.full(len(coords), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    points = np.ascontiguousarray(coords[used], dtype=np.float64)
    return points, _orient_tets(points, renumber[tets]), renumber


MESH_CACHE_SIZE = 16
"""Geology meshes :func:`mesh_geology_cached` keeps (the most recently used)."""

_mesh_cache: dict[str, GeologyMesh] = {}


def mesh_geology_cached(geology: Geology) -> GeologyMesh:
    """:func:`mesh_geology`, remembered for the process: a geology equal to one of the last MESH_CACHE_SIZE meshed
    (equal ``repr``: every field, floats exactly) gets a copy of that mesh without Gmsh. Equal inputs give identical
    meshes (single-threaded Delaunay, every Gmsh option pinned), so the copy is the mesh Gmsh would make. A shipped
    scene of a few thousand blocks takes Gmsh half a minute to a minute; its run, restart and half-step tests, and a
    report that builds it again, mesh it once.

    Returns:
        A fresh copy (its arrays and face-set dict are the caller's to change).
    """
    key = repr(geology)
    mesh = _mesh_cache.pop(key, None)
    if mesh is None:
        mesh = mesh_geology(geology)
    _mesh_cache[key] = mesh  # (re)inserted last: the dict's order is the order of use
    while len(_mesh_cache) > MESH_CACHE_SIZE:
        del _mesh_cache[next(iter(_mesh_cache))]
    return _copy_mesh(mesh)


def _copy_mesh(mesh: GeologyMesh) -> GeologyMesh:
    """A deep copy of a mesh: its arrays, names and face-set dict."""
    return GeologyMesh(
        points=mesh.points.copy(),
        tets=mesh.tets.copy(),
        tet_block=mesh.tet_block.copy(),
        tet_material=mesh.tet_material.copy(),
        material_names=list(mesh.material_names),
        joint_faces=mesh.joint_faces.copy(),
        joint_face_set=mesh.joint_face_set.copy(),
        joint_set_names=list(mesh.joint_set_names),
        boundary_faces={name: faces.copy() for name, faces in mesh.boundary_faces.items()},
        num_blocks=mesh.num_blocks,
    )


def mesh_geology(geology: Geology) -> GeologyMesh:
    """Meshes a jointed rock mass with first-order tetrahedra conforming to its joints, layers and openings.

    The Gmsh OCC model is the box minus the openings, fragmented by the layer tops and by every joint surface;
    joint pieces outside the box or inside an opening are removed. Each resulting volume is one rock block.
    Meshing is single-threaded Delaunay, so equal inputs give identical meshes. Gmsh's tetrahedral optimiser then
    improves every tet whose quality is below :data:`OPTIMIZE_THRESHOLD` by edge and face swaps and node
    relocation; nodes on joints, layers and walls stay on their surfaces, so the mesh still conforms. Without it,
    Delaunay leaves slivers (radius ratio down to 3e-4) that cut the tets' stable time step 20 to 240 times on the
    repository's jointed scenes. The worst tets that remain sit in geometric features smaller than ``h`` (joints
    crossing each other or a box face within a fraction of ``h`` of an edge), which no optimiser can remove: there
    the step is set by the feature's size.

    Args:
        geology: The rock mass, openings, joint sets, mesh size and seed.

    Returns:
        The mesh; ``boundary_faces`` holds the six box faces and ``"opening"``.

    Raises:
        ValueError: If the openings remove the whole box.
        RuntimeError: If Gmsh fails to build or mesh the model (its message included).
    """
    rock = geology.rock
    lo, hi = np.asarray(rock.lo, float), np.asarray(rock.hi, float)
    diag = float(np.linalg.norm(hi - lo))
    margin = _MARGIN * diag
    tol = _REL_TOL * diag
    joint_surfaces = _joint_geometry(geology)
    refine = geology.h_opening is not None and bool(geology.openings)
    with _gmsh_model(_gmsh_options(geology.h, refine), f"warpdem_geology_{id(geology)}", "mesh_geology") as gmsh:
        occ = gmsh.model.occ

        box = occ.addBox(*lo, *(hi - lo))
        volumes = [(3, box)]
        if geology.openings:
            tools = [(3, _add_opening(occ, o, lo, hi, margin)) for o in geology.openings]
            volumes, _ = occ.cut(volumes, tools)
            if not volumes:
                raise ValueError("mesh_geology: the openings remove the whole rock box")

        # Cutting surfaces in input order; kinds[i] is the joint set of surface i, or -1 for a layer top.
        cutters: list[tuple[int, int]] = []
        kinds: list[int] = []
        for z_top, _ in rock.layers:
            if lo[2] + tol < z_top < hi[2] - tol:
                size = hi - lo + 2.0 * margin
                cutters.append((2, occ.addRectangle(lo[0] - margin, lo[1] - margin, z_top, size[0], size[1])))
                kinds.append(-1)
        for s in joint_surfaces:
            if isinstance(s, _JointPolygon):
                cutters.append((2, _add_polygon(occ, s.vertices)))
            else:
                e1, _ = _in_plane_axes(s.normal)
                tag = occ.addDisk(*s.centre, s.radius, s.radius, zAxis=list(s.normal), xAxis=list(e1))
                cutters.append((2, tag))
            kinds.append(s.set_index)

        surface_set: dict[int, int] = {}
        if cutters:
            _, pieces = occ.fragment(volumes, cutters)
            # A piece that lies on several cutters (coplanar joints) belongs to the lowest joint set.
            for kind, out in zip(kinds, pieces[len(volumes) :], strict=True):
                for dim, tag in out:
                    if dim == 2 and kind >= 0:
                        surface_set[tag] = min(kind, surface_set.get(tag, kind))
        occ.synchronize()

        # Drop joint pieces that bound no block and are embedded in none: outside the box or inside openings.
        # Removing them from the Gmsh model only (the OCC shapes stay) is several times faster than
        # occ.remove + synchronize on models with hundreds of blocks.
        volume_tags = sorted(tag for _, tag in gmsh.model.getEntities(3))
        embedded = {tag for v in volume_tags for dim, tag in gmsh.model.mesh.getEmbedded(3, v) if dim == 2}
        free = [
            (2, s)
            for _, s in gmsh.model.getEntities(2)
            if len(gmsh.model.getAdjacencies(2, s)[0]) == 0 and s not in embedded
        ]
        if free:
            gmsh.model.removeEntities(free, recursive=True)
        surfaces = {tag for _, tag in gmsh.model.getEntities(2)}
        surface_set = {s: k for s, k in surface_set.items() if s in surfaces}

        if refine:
            walls = [
                s
                for s in sorted(surfaces)
                if len(gmsh.model.getAdjacencies(2, s)[0]) == 1
                and not _on_box_face(gmsh.model.getBoundingBox(2, s), lo, hi, 1e3 * tol)
            ]
            field_mesh = gmsh.model.mesh.field
            distance = field_mesh.add("Distance")
            field_mesh.setNumbers(distance, "SurfacesList", walls)
            field_mesh.setNumber(distance, "Sampling", 30)
            threshold = field_mesh.add("Threshold")
            field_mesh.setNumber(threshold, "InField", distance)
            field_mesh.setNumber(threshold, "SizeMin", geology.h_opening)
            field_mesh.setNumber(threshold, "SizeMax", geology.h)
            field_mesh.setNumber(threshold, "DistMin", 0.0)
            field_mesh.setNumber(threshold, "DistMax", geology.refine_distance or 4.0 * geology.h)
            field_mesh.setAsBackgroundMesh(threshold)
        gmsh.model.mesh.generate(3)

        coords, index, tet_parts, block_parts = _gmsh_volume_tets(gmsh, volume_tags, "mesh_geology")
        face_parts, face_set_parts = [], []
        for s, k in sorted(surface_set.items(), key=lambda item: (item[1], item[0])):  # grouped by set
            for etype, _, enodes in zip(*gmsh.model.mesh.getElements(2, s), strict=True):
                if etype == _GMSH_TRIANGLE:
                    face_parts.append(index[enodes.astype(np.int64)].reshape(-1, 3))
                    face_set_parts.append(np.full(len(face_parts[-1]), k, dtype=np.int64))

    tets = np.concatenate(tet_parts) if tet_parts else np.zeros((0, 4), np.int64)
    if len(tets) == 0:
        raise RuntimeError("mesh_geology: Gmsh produced no tetrahedra")
    joint_faces = np.concatenate(face_parts) if face_parts else np.zeros((0, 3), np.int64)
    joint_face_set = np.concatenate(face_set_parts) if face_set_parts else np.zeros(0, np.int64)

    points, tets, renumber = _used_nodes(coords, tets)
    joint_faces = renumber[joint_faces]

    # Joint faces: normal along the set's nominal normal.
    nominal = np.array([joint_normal(js.dip, js.dip_direction) for js in geology.joint_sets]).reshape(-1, 3)
    if len(joint_faces):
        flip = np.einsum("ij,ij->i", _face_normals(points, joint_faces), nominal[joint_face_set]) < 0.0
        joint_faces[flip] = joint_faces[flip][:, [0, 2, 1]]

    centroid_z = points[tets][:, :, 2].mean(axis=1)
    return GeologyMesh(
        points=points,
        tets=tets,
        tet_block=np.concatenate(block_parts),
        tet_material=rock.material_of_z(centroid_z),
        material_names=rock.material_names(),
        joint_faces=joint_faces,
        joint_face_set=joint_face_set,
        joint_set_names=geology.joint_set_names(),
        boundary_faces=_classify_boundary(points, tets, lo, hi, 1e3 * tol),
        num_blocks=len(volume_tags),
    )


def _mesh_solid(add: Callable[[Any], int], h: float, material: str, what: str) -> GeologyMesh:
    """One OCC solid (``add(occ)`` returns its volume tag) meshed with tets of edge about ``h`` [m], as one block
    of one material; ``boundary_faces`` holds its outer surface as :data:`SURFACE_FACE_NAME`."""
    with _gmsh_model(_gmsh_options(h, refine=False), f"warpdem_{what}_{id(add)}", what) as gmsh:
        volume = add(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        gmsh.model.mesh.generate(3)
        coords, _, tet_parts, _ = _gmsh_volume_tets(gmsh, [volume], what)
    if not tet_parts or not sum(len(t) for t in tet_parts):
        raise RuntimeError(f"{what}: Gmsh produced no tetrahedra")
    points, tets, _ = _used_nodes(coords, np.concatenate(tet_parts))
    return GeologyMesh(
        points=points,
        tets=tets,
        tet_block=np.zeros(len(tets), np.int64),
        tet_material=np.zeros(len(tets), np.int64),
        material_names=[material],
        joint_faces=np.zeros((0, 3), np.int64),
        joint_face_set=np.zeros(0, np.int64),
        joint_set_names=[],
        boundary_faces={SURFACE_FACE_NAME: outer_faces(tets).astype(np.int64)},
        num_blocks=1,
    )


def mesh_cylinder(
    center: Sequence[float], axis: Sequence[float], radius: float, height: float, h: float, material: str
) -> GeologyMesh:
    """A solid circular cylinder (a disc when ``height`` is small) meshed with Gmsh (the options of
    :func:`mesh_geology`, so equal inputs give identical meshes).

    Args:
        center: centre of the base disc [m], shape (3,). axis: direction of the axis (any length), shape (3,).
        radius: radius [m]. height: length along ``axis`` from the base disc [m]. h: target tet edge [m].
        material: the material name of every tet.

    Raises:
        RuntimeError: Gmsh fails.
    """
    direction = np.asarray(axis, dtype=np.float64)
    direction = height * direction / np.linalg.norm(direction)
    return _mesh_solid(lambda occ: occ.addCylinder(*center, *direction, radius), h, material, "mesh_cylinder")


def mesh_ellipsoid(center: Sequence[float], radii: Sequence[float], h: float, material: str) -> GeologyMesh:
    """A solid ellipsoid with semi-axes ``radii`` along x, y and z [m] (a unit OCC sphere scaled by them), meshed
    with Gmsh; see :func:`mesh_cylinder`."""

    def add(occ: Any) -> int:
        tag = occ.addSphere(*center, 1.0)
        occ.dilate([(3, tag)], *center, *radii)
        return tag

    return _mesh_solid(add, h, material, "mesh_ellipsoid")


# ---------------------------------------------------------------------------------------------------------------
# Mesh topology helpers
# ---------------------------------------------------------------------------------------------------------------


def _orient_tets(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swaps two nodes of every negatively oriented tet."""
    p = points[tets]
    negative = np.linalg.det(p[:, 1:] - p[:, :1]) < 0.0
    tets = tets.astype(np.int64, copy=True)
    tets[negative] = tets[negative][:, [0, 2, 1, 3]]
    return tets


def _face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = points[faces]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def _tet_face_table(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All tet faces, outward oriented, shape (4M, 3) (row 4t + i is face i of tet t), with the unique sorted
    node triples, the index of each face's triple among them and how many tets share each triple."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    keys, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    return faces, keys, inverse.reshape(-1), counts


def interior_faces(tets: np.ndarray) -> np.ndarray:
    """Faces shared by two tets, as sorted node triples, shape (F, 3), int64, in lexicographic order."""
    _, keys, _, counts = _tet_face_table(np.asarray(tets, dtype=np.int64))
    return keys[counts == 2]


def _classify_boundary(
    points: np.ndarray, tets: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float
) -> dict[str, np.ndarray]:
    """Faces of exactly one tet, outward oriented, sorted onto the six box faces and the opening walls."""
    outer = outer_faces(tets).astype(np.int64)
    p = points[outer]
    remaining = np.ones(len(outer), dtype=bool)
    result: dict[str, np.ndarray] = {}
    for name in BOX_FACE_NAMES:
        axis = "xyz".index(name[0])
        value = lo[axis] if name[1] == "-" else hi[axis]
        on = remaining & np.all(np.abs(p[:, :, axis] - value) <= tol, axis=1)
        result[name] = outer[on]
        remaining &= ~on
    result[OPENING_FACE_NAME] = outer[remaining]
    return result


def _blocks_from_components(tets: np.ndarray, joint_faces: np.ndarray) -> np.ndarray:
    """Connected components of tets across shared faces that are not joint faces, numbered in tet order."""
    _, keys, inverse, counts = _tet_face_table(tets)
    is_joint = np.zeros(len(keys), dtype=bool)
    if len(joint_faces):
        pos = _row_lookup(keys, np.sort(joint_faces, axis=1))
        is_joint[pos[pos >= 0]] = True
    order = np.argsort(inverse, kind="stable")  # the two rows of a shared face become neighbours
    shared = (counts[inverse[order]] == 2) & ~is_joint[inverse[order]]
    pairs = order[shared].reshape(-1, 2) // 4
    return component_labels(len(tets), pairs[:, 0], pairs[:, 1])


def component_labels(count: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected components of the graph on ``count`` vertices with edges ``a[i]``–``b[i]``.

    Returns:
        The component of each vertex, shape (count,), int64, numbered 0, 1, ... in order of each component's lowest
        vertex.
    """
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    labels = np.arange(count)
    while True:  # min-label propagation with pointer jumping
        new = labels.copy()
        m = np.minimum(labels[a], labels[b])
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]
        if np.array_equal(new, labels):
            break
        labels = new
    _, block = np.unique(labels, return_inverse=True)
    return block.reshape(-1).astype(np.int64)


def _row_lookup(table: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Index of each row of ``rows`` in the lexicographically sorted unique ``table``, -1 where absent."""
    if len(table) == 0:
        return np.full(len(rows), -1, dtype=np.int64)
    dtype = np.dtype((np.void, table.dtype.itemsize * table.shape[1]))
    t = np.ascontiguousarray(table).view(dtype).reshape(-1)
    r = np.ascontiguousarray(rows.astype(table.dtype)).view(dtype).reshape(-1)
    order = np.argsort(t)
    pos = np.searchsorted(t[order], r)
    pos = np.clip(pos, 0, len(t) - 1)
    found = t[order][pos] == r
    return np.where(found, order[pos], -1)


# ---------------------------------------------------------------------------------------------------------------
# Import and export
# ---------------------------------------------------------------------------------------------------------------


def _import_error(path: pathlib.Path, problem: str, argument: str | None = None) -> MeshImportError:
    return MeshImportError(f"{path}: {' '.join(problem.split())}", argument)


def _check_cells(path: pathlib.Path, cells: np.ndarray, num_points: int, what: str) -> None:
    """Raises MeshImportError naming the first cell with a node index outside 0 .. num_points - 1 (numpy would wrap a
    negative one silently, and fail on a large one without naming the file)."""
    bad = np.nonzero(np.any((cells < 0) | (cells >= num_points), axis=1))[0]
    if len(bad):
        k = int(bad[0])
        raise _import_error(
            path, f"{what} {k} has node indices {cells[k].tolist()} outside 0..{num_points - 1} (the file's nodes)"
        )


def read_mesh(
    path: str | os.PathLike,
    *,
    material_map: Mapping[int | str, str] | None = None,
    material_array: str | None = None,
    joint_groups: Sequence[str] | None = None,
) -> GeologyMesh:
    """Reads a ready tetrahedral mesh (Gmsh ``.msh`` v2/v4, VTU, legacy VTK) through meshio.

    Tetrahedra: the material comes from the cell-data array ``material_array`` if given, else
    ``"gmsh:physical"``, ``"material"``, ``"MaterialIds"`` or ``"gmsh:geometrical"``, the first present; each
    distinct value is a group, named through ``field_data`` (Gmsh physical names) where possible. Without any
    such array every tet is ``"rock"``. The block is the ``"gmsh:geometrical"`` entity (or a ``"block"``
    array); failing both, blocks are the connected sets of tets across non-joint faces.

    Triangles: grouped by ``"gmsh:physical"`` and named through ``field_data`` (unnamed groups are named by
    their number). Groups in ``joint_groups`` (default: names starting with ``"joint"``) are joint sets, the
    rest go to ``boundary_faces`` under their names. Lines and points are ignored.

    Args:
        path: Mesh file.
        material_map: Group tag or group name → material name. When given, every tet group must appear in it.
        material_array: Name of the tet cell-data array holding the material groups.
        joint_groups: Names of the triangle groups that are joints; each must be a triangle group of the file.

    Returns:
        The mesh, with unused nodes dropped and tets positively oriented.

    Raises:
        MeshImportError: If the file is missing, of unknown format or unreadable, has no tetrahedra, has other
            volume cells (hexahedra, wedges, pyramids, quadratic tets), has triangles that are not tet faces,
            has a tet group missing from ``material_map``, or lacks a group named in ``joint_groups``.
    """
    import meshio

    path = pathlib.Path(path)
    if not path.is_file():
        raise _import_error(path, "no such file")
    file_format = _READ_SUFFIXES.get(path.suffix.lower())
    if file_format is None:
        raise _import_error(path, f"unknown mesh format {path.suffix!r}, expected one of {', '.join(_READ_SUFFIXES)}")
    # The format readers directly: meshio.read reports a failed read by printing and calling sys.exit.
    reader = {"gmsh": meshio.gmsh.read, "vtu": meshio.vtu.read, "vtk": meshio.vtk.read}[file_format]
    try:
        raw = reader(str(path))
    except Exception as exc:
        detail = str(exc) or type(exc).__name__
        raise _import_error(path, f"cannot read as {file_format}: {detail}") from exc

    volume_types = {c.type for c in raw.cells if c.dim == 3}
    unsupported = sorted(volume_types - _LINEAR_VOLUME_CELLS)
    if unsupported:
        counts = ", ".join(f"{sum(len(c.data) for c in raw.cells if c.type == t)} {t}" for t in unsupported)
        raise _import_error(path, f"has {counts} cells; only linear tetrahedra (tetra) are supported")
    tet_blocks = [i for i, c in enumerate(raw.cells) if c.type == "tetra"]
    tri_blocks = [i for i, c in enumerate(raw.cells) if c.type in _SURFACE_CELLS]
    if not tet_blocks or sum(len(raw.cells[i].data) for i in tet_blocks) == 0:
        found = ", ".join(sorted({c.type for c in raw.cells})) or "no cells"
        raise _import_error(path, f"has no tetrahedra (found {found})")

    def cell_array(name: str, blocks: list[int]) -> np.ndarray | None:
        data = raw.cell_data.get(name)
        if data is None:
            return None
        return np.concatenate([np.asarray(data[i]).reshape(len(raw.cells[i].data), -1)[:, 0] for i in blocks])

    names_by_dim: dict[int, dict[int, str]] = {2: {}, 3: {}}
    for name, value in raw.field_data.items():
        value = np.asarray(value).reshape(-1)
        if len(value) >= 2 and int(value[1]) in names_by_dim:
            names_by_dim[int(value[1])][int(value[0])] = str(name)

    tets = np.concatenate([np.asarray(raw.cells[i].data, dtype=np.int64) for i in tet_blocks])
    _check_cells(path, tets, len(raw.points), "tet")
    candidates = (
        [material_array] if material_array else ["gmsh:physical", "material", "MaterialIds", "gmsh:geometrical"]
    )
    groups = next((g for g in (cell_array(n, tet_blocks) for n in candidates) if g is not None), None)
    if material_array and groups is None:
        raise _import_error(path, f"has no tet cell-data array {material_array!r} (has {sorted(raw.cell_data)})")

    if groups is None:
        tet_material = np.zeros(len(tets), dtype=np.int64)
        material_names = ["rock"]
    else:
        groups = groups.astype(np.int64)
        tags, group_index = np.unique(groups, return_inverse=True)
        group_names = [names_by_dim[3].get(int(t)) for t in tags]
        if material_map is None:
            resolved = [name or f"material{t}" for t, name in zip(tags, group_names, strict=True)]
        else:
            resolved = []
            for t, name in zip(tags, group_names, strict=True):
                key: int | str | None = name if name in material_map else int(t) if int(t) in material_map else None
                if key is None:
                    label = f"{int(t)} ({name!r})" if name else f"{int(t)}"
                    raise _import_error(
                        path,
                        f"tet physical group {label} is not in material_map (keys: {sorted(map(str, material_map))})",
                        "material_map",
                    )
                resolved.append(material_map[key])
        material_names = list(dict.fromkeys(resolved))
        lookup = np.array([material_names.index(n) for n in resolved], dtype=np.int64)
        tet_material = lookup[group_index.reshape(-1)]

    joint_parts, joint_set_parts, boundary_parts = [], [], {}
    joint_set_names: list[str] = []
    tris = np.zeros((0, 3), np.int64)
    tri_groups = np.zeros(0, np.int64)
    if tri_blocks:
        tris = np.concatenate([np.asarray(raw.cells[i].data, dtype=np.int64) for i in tri_blocks])
        _check_cells(path, tris, len(raw.points), "triangle")
        tri_groups = cell_array("gmsh:physical", tri_blocks)
        tri_groups = np.zeros(len(tris), np.int64) if tri_groups is None else tri_groups.astype(np.int64)
    tri_names = [names_by_dim[2].get(int(t), str(int(t))) for t in np.unique(tri_groups)]
    missing = [name for name in joint_groups or [] if name not in tri_names]
    if missing:
        raise _import_error(
            path,
            f"has no triangle group {', '.join(repr(n) for n in missing)} named in joint_groups "
            f"(its triangle groups: {', '.join(repr(n) for n in tri_names) or 'none'})",
            "joint_groups",
        )
    for t, name in zip(np.unique(tri_groups), tri_names, strict=True):
        faces = tris[tri_groups == t]
        is_joint = name in joint_groups if joint_groups is not None else name.lower().startswith("joint")
        if is_joint:
            joint_parts.append(faces)
            joint_set_parts.append(np.full(len(faces), len(joint_set_names), dtype=np.int64))
            joint_set_names.append(name)
        else:
            boundary_parts[name] = faces

    used = np.unique(tets)
    renumber = np.full(len(raw.points), -1, dtype=np.int64)
    renumber[used] = np.arange(len(used))
    points = np.ascontiguousarray(np.asarray(raw.points, dtype=np.float64)[used])
    if points.shape[1] != 3:
        raise _import_error(path, f"has {points.shape[1]}-dimensional points; a tet mesh needs 3")
    # The device holds positions in float32: a coordinate it cannot represent is refused with the node that has it.
    bad = np.nonzero(~np.all(np.isfinite(points) & (np.abs(points) <= F32_MAX), axis=1))[0]
    if len(bad):
        node = int(used[bad[0]])
        raise _import_error(
            path, f"node {node} has coordinates {raw.points[node].tolist()}; allowed: finite, at most {F32_MAX:g} m"
        )
    tets = _orient_tets(points, renumber[tets])

    face_keys = np.unique(np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1), axis=0)
    for name, faces in [*zip(joint_set_names, joint_parts, strict=True), *boundary_parts.items()]:
        mapped = renumber[faces]
        if np.any(mapped < 0) or np.any(_row_lookup(face_keys, np.sort(mapped, axis=1)) < 0):
            raise _import_error(path, f"triangle group {name!r} has triangles that are not faces of the tets")
    joint_faces = renumber[np.concatenate(joint_parts)] if joint_parts else np.zeros((0, 3), np.int64)
    joint_face_set = np.concatenate(joint_set_parts) if joint_set_parts else np.zeros(0, np.int64)
    boundary_faces = {name: renumber[faces] for name, faces in boundary_parts.items()}

    block_ids = cell_array("gmsh:geometrical", tet_blocks)
    if block_ids is None:
        block_ids = cell_array("block", tet_blocks)
    if block_ids is None:
        tet_block = _blocks_from_components(tets, joint_faces)
    else:
        _, tet_block = np.unique(block_ids.astype(np.int64), return_inverse=True)
        tet_block = tet_block.reshape(-1).astype(np.int64)

    return GeologyMesh(
        points=points,
        tets=tets,
        tet_block=tet_block,
        tet_material=tet_material,
        material_names=material_names,
        joint_faces=joint_faces,
        joint_face_set=joint_face_set,
        joint_set_names=joint_set_names,
        boundary_faces=boundary_faces,
        num_blocks=int(tet_block.max()) + 1,
    )


def write_mesh(path: str | os.PathLike, mesh: GeologyMesh) -> None:
    """Writes a mesh that :func:`read_mesh` reads back unchanged (Gmsh MSH 2.2 ASCII or VTU), through meshio.

    Tets carry ``"gmsh:physical"`` = material index + 1 and ``"gmsh:geometrical"`` = block + 1; joint and
    boundary faces are triangles whose ``"gmsh:physical"`` tag follows the materials (joint sets first). Group
    names go to the Gmsh physical names (name → [tag, dim]); for VTU, whose meshio writer drops field data, they
    are added as a ``FieldData`` element of the same layout, which meshio and ParaView read. Empty face sets are
    not written. MSH 4.1 is not offered: meshio's 4.1 writer needs a node entity for every element entity.

    Args:
        path: Output file; the suffix picks the format: ``.msh`` or ``.vtu``. Parent directories are created.
        mesh: The mesh to write.

    Raises:
        ValueError: If the suffix is neither ``.msh`` nor ``.vtu``, or a group name is used twice.
    """
    import meshio

    path = pathlib.Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".msh", ".vtu"):
        raise ValueError(f"write_mesh {str(path)!r}: unsupported suffix {path.suffix!r}, expected .msh or .vtu")

    field_data: dict[str, np.ndarray] = {}
    for i, name in enumerate(mesh.material_names):
        field_data[name] = np.array([i + 1, 3])
    cells = [("tetra", mesh.tets)]
    physical = [mesh.tet_material + 1]
    geometrical = [mesh.tet_block + 1]
    face_sets = [
        (name, mesh.joint_faces[mesh.joint_face_set == k]) for k, name in enumerate(mesh.joint_set_names)
    ] + list(mesh.boundary_faces.items())
    tag = len(mesh.material_names)
    for name, faces in face_sets:
        if len(faces) == 0:
            continue
        if name in field_data:
            raise ValueError(f"write_mesh {str(path)!r}: group name {name!r} is used twice")
        tag += 1
        field_data[name] = np.array([tag, 2])
        cells.append(("triangle", np.asarray(faces, dtype=np.int64)))
        physical.append(np.full(len(faces), tag, dtype=np.int64))
        geometrical.append(np.full(len(faces), tag, dtype=np.int64))

    out = meshio.Mesh(
        mesh.points,
        cells,
        cell_data={"gmsh:physical": physical, "gmsh:geometrical": geometrical},
        field_data=field_data,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".msh":
        meshio.write(path, out, file_format="gmsh22", binary=False)
        return
    meshio.write(path, out, file_format="vtu")
    arrays = "".join(
        f'<DataArray type="Int64" Name={quoteattr(name)} NumberOfTuples="2" format="ascii">'
        f"{int(v[0])} {int(v[1])}</DataArray>\n"
        for name, v in field_data.items()
    )
    text = path.read_text()
    text = re.sub(
        r"(<UnstructuredGrid[^>]*>\s*)", lambda m: m.group(1) + f"<FieldData>\n{arrays}</FieldData>\n", text, count=1
    )
    path.write_text(text)
