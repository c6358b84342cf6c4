"""A whole double-curvature arch dam (:class:`warpdem.scene.ArchDamMesh`) built and meshed with Gmsh.

The solid: the horizontal arch sections of the layout (:class:`~warpdem.scene.ArchDamMesh`: concentric arcs of radii
R_u, R_d about the arch's centre, ±ARCH_DAM_SECTOR either side of the crown) at LOFT_SECTIONS elevations from a little
below the floor to the crest, lofted by OpenCASCADE into one B-spline solid, intersected with the valley (a
trapezoidal prism along y: the floor and two plane walls through L2 at 0.15 H and L1 at H). The charge disc is
fragmented into the crest, so the crest's triangles conform to its circle. Sizes: a background field of the distance
to the disc (Gmsh Distance + Threshold), h_charge within fine_distance, growing linearly to h over grading_distance.
Every Gmsh option is pinned and the mesher runs on one thread (:func:`warpdem.build.geology._gmsh_options`), so equal
inputs give identical meshes.

Face sets (:data:`warpdem.scene.ARCH_DAM_FACE_NAMES`) are sorted from the outer triangles by geometry, which OCC
keeps exact: ``charge`` on the crest plane inside the disc (the disc's triangles' centroids lie inside its circle,
every other crest triangle's outside it, the mesh conforming to it), ``crest`` the rest of the crest plane,
``foundation`` on the floor plane or a wall plane, and of the curved faces ``upstream`` where the outward normal
points away from the arch's centre (the convex face) and ``downstream`` where it points towards it.

Host code, run once before the model is built.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..scene import ArchDamMesh
from ..scene.continuum import ARCH_DAM_SECTOR
from .geology import GeologyMesh, _gmsh_model, _gmsh_options, _gmsh_volume_tets, _used_nodes
from .mesh import boundary_faces as outer_faces

__all__ = ["LOFT_SECTIONS", "mesh_arch_dam"]

LOFT_SECTIONS = 25
"""Arch sections the loft passes through, evenly spaced in ζ from -LOFT_BELOW to 1. The layout's functions are
parabolas and lines in ζ; the loft's cubic B-splines through 25 sections follow them to well under a millimetre on a
60 m dam (the volume test measures it)."""

LOFT_BELOW = 0.05
"""The loft starts this fraction of the height below the floor, which the valley cuts (an OCC boolean of two
coincident planes is fragile)."""

PLANE_TOLERANCE = 1e-7
"""A node lies on the crest, floor or a wall plane when within this fraction of the dam's height of it [-]: far above
OCC's and Gmsh's rounding (1e-12 relative), far below any tet."""

SIZE_SAMPLING = 40
"""Points per direction Gmsh samples the charge disc with for the Distance field."""


def _section(occ: Any, spec: ArchDamMesh, zeta: float) -> int:
    """The closed wire of the arch section at ζ (may be below the floor): upstream arc, end, downstream arc, end."""
    x0, z0 = spec.origin[0], spec.origin[2] + zeta * spec.height
    yc = float(spec.arch_center_y(zeta))
    outer, inner = (float(r) for r in spec.radii(zeta))
    phi = np.radians(ARCH_DAM_SECTOR)
    centre = occ.addPoint(x0, yc, z0)

    def at(r: float, sign: float) -> int:
        return occ.addPoint(x0 + sign * r * np.sin(phi), yc + r * np.cos(phi), z0)

    ol, orr, il, ir = at(outer, -1.0), at(outer, 1.0), at(inner, -1.0), at(inner, 1.0)
    curves = [
        occ.addCircleArc(ol, centre, orr),
        occ.addLine(orr, ir),
        occ.addCircleArc(ir, centre, il),
        occ.addLine(il, ol),
    ]
    wire = occ.addWire(curves)
    occ.remove([(0, centre)])
    return wire


def _valley(occ: Any, spec: ArchDamMesh) -> int:
    """The valley as a solid: the trapezoid of its cross-section (floor to above the crest) extruded along y over
    more than the dam's extent."""
    x0, y0, z0 = spec.origin
    top = 1.5  # ζ of the trapezoid's top, above the crest (the loft's top face makes the crest)
    reach = 4.0 * float(spec.radii(1.0)[0]) + spec.height
    corners = [(-0.5, 0.0), (0.5, 0.0), (0.5, top), (-0.5, top)]
    points = [
        occ.addPoint(x0 + side * float(spec.valley_width(zeta)), y0 - reach, z0 + zeta * spec.height)
        for side, zeta in corners
    ]
    lines = [occ.addLine(points[i], points[(i + 1) % 4]) for i in range(4)]
    face = occ.addPlaneSurface([occ.addCurveLoop(lines)])
    out = occ.extrude([(2, face)], 0.0, 2.0 * reach, 0.0)
    return next(tag for dim, tag in out if dim == 3)


def _size_field(gmsh: Any, spec: ArchDamMesh, disc: int) -> None:
    """Background size: h_charge within fine_distance of the disc, linear to h at fine_distance + grading_distance."""
    field = gmsh.model.mesh.field
    distance = field.add("Distance")
    field.setNumbers(distance, "SurfacesList", [disc])
    field.setNumber(distance, "Sampling", SIZE_SAMPLING)
    threshold = field.add("Threshold")
    field.setNumber(threshold, "InField", distance)
    field.setNumber(threshold, "SizeMin", spec.h_charge)
    field.setNumber(threshold, "SizeMax", spec.h)
    field.setNumber(threshold, "DistMin", spec.fine_distance)
    field.setNumber(threshold, "DistMax", spec.fine_distance + spec.grading_distance)
    field.setAsBackgroundMesh(threshold)


def mesh_arch_dam(spec: ArchDamMesh) -> GeologyMesh:
    """The tet mesh of a whole arch dam (see the module docstring), one block of ``spec.material``.

    Args:
        spec: the ``[mesh]`` of kind ``"arch_dam"`` (at the scene's resolution).

    Returns:
        The mesh, positively oriented tets, face sets :data:`warpdem.scene.ARCH_DAM_FACE_NAMES` (outward triangles).

    Raises:
        RuntimeError: Gmsh fails, or the solid is not one volume with the disc in its crest.
    """
    what = "mesh_arch_dam"
    with _gmsh_model(_gmsh_options(spec.h, refine=True), f"warpdem_{what}", what) as gmsh:
        occ = gmsh.model.occ
        zetas = np.linspace(-LOFT_BELOW, 1.0, LOFT_SECTIONS)
        wires = [_section(occ, spec, float(z)) for z in zetas]
        loft = occ.addThruSections(wires, makeSolid=True, makeRuled=False)
        solid = next(tag for dim, tag in loft if dim == 3)
        dam, _ = occ.intersect([(3, solid)], [(3, _valley(occ, spec))])
        cx, cy, cz = spec.charge_center()
        disc = occ.addDisk(cx, cy, cz, spec.charge_radius, spec.charge_radius)
        pieces, parts = occ.fragment(dam, [(2, disc)])
        occ.synchronize()
        volumes = [tag for dim, tag in pieces if dim == 3]
        discs = [tag for dim, tag in parts[-1] if dim == 2]  # what became of the disc
        if len(volumes) != 1 or len(discs) != 1:
            raise RuntimeError(f"{what}: expected one dam volume with the charge disc in its crest, got {pieces}")
        _size_field(gmsh, spec, discs[0])
        gmsh.model.mesh.generate(3)
        coords, _, tet_parts, _ = _gmsh_volume_tets(gmsh, volumes, what)
    if not tet_parts or not sum(len(t) for t in tet_parts):
        raise RuntimeError(f"{what}: Gmsh produced no tetrahedra")
    points, tets, _ = _used_nodes(coords, np.concatenate(tet_parts))
    return GeologyMesh.single(points, tets, spec.material, arch_dam_face_sets(spec, points, tets))


def arch_dam_face_sets(spec: ArchDamMesh, points: np.ndarray, tets: np.ndarray) -> dict[str, np.ndarray]:
    """The outer faces of an arch dam mesh sorted onto :data:`warpdem.scene.ARCH_DAM_FACE_NAMES` (module docstring).

    Args:
        spec: the dam. points: node positions [m], shape (N, 3). tets: positively oriented tets, shape (M, 4).

    Returns:
        Name → outward triangles, shape (F, 3), int64; every outer face in exactly one set.
    """
    faces = outer_faces(tets).astype(np.int64)
    tri = points[faces]
    rel = tri - np.asarray(spec.origin, dtype=np.float64)
    tol = PLANE_TOLERANCE * spec.height
    zeta = rel[..., 2] / spec.height
    crest = np.all(np.abs(rel[..., 2] - spec.height) <= tol, axis=1)
    floor = np.all(np.abs(rel[..., 2]) <= tol, axis=1)
    # Each wall: the plane through (±L(ζ)/2, ζ H) for all ζ; distance along the wall's unit normal in the xz plane.
    slope = 0.5 * (spec.crest_length - spec.lower_length) / 0.85 / spec.height  # dx/dz of the right wall
    cos = 1.0 / np.hypot(1.0, slope)
    wall = np.zeros(len(faces), dtype=bool)
    for side in (-1.0, 1.0):
        off = (side * rel[..., 0] - 0.5 * spec.valley_width(zeta)) * cos
        wall |= np.all(np.abs(off) <= tol, axis=1)
    centroid = tri.mean(axis=1)
    charge = crest & (np.hypot(*(centroid[:, :2] - np.asarray(spec.charge_center()[:2])).T) < spec.charge_radius)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    zc = (centroid[:, 2] - spec.origin[2]) / spec.height
    radial = centroid[:, :2] - np.stack([np.full(len(faces), spec.origin[0]), spec.arch_center_y(zc)], axis=1)
    outward = np.einsum("ij,ij->i", normal[:, :2], radial) > 0.0
    curved = ~(crest | floor | wall)
    return {
        "upstream": faces[curved & outward],
        "downstream": faces[curved & ~outward],
        "crest": faces[crest & ~charge],
        "charge": faces[charge],
        "foundation": faces[(floor | wall) & ~crest],
    }
