"""Brick meshes (warpdem/bricks.py) and the rigid blocks' stable step on the limestone tunnel's bricks
(scenes/limestone_tunnel.toml, LDEC §4).

Oracles:
- the mesh of a 4 × 4 running-bond wall against counting by hand: 4 full blocks in the even courses, 3 full and 2 half
  ones in the odd; 2 × 24 triangles on each of the 3 bedding planes and 2 per head joint; the volume of the box
  less a room of whole cells; the room's face set covers its walls (area of the cut-out's surface); every tet's
  block is one brick (its cells' extent is one block length or the half ones at the ends);
- the rigid step on the scene's joints: each free block is a box of mass M = ρ L W H and principal moments
  M (b² + c²)/12, on node springs k_n/2 × the nodes' area shares of its surface (k_n the scene's normal stiffness,
  the same on every face); ω² = 2 λ_max(M⁻¹K) with K = Σ k_i J_iᵀ J_i computed here in float64 from the box's
  surface triangles, dt = 2/ω (sqrt(1 + ζ²) − ζ). warpdem.rigid.rigid_critical_step must give it to STEP_RTOL (the
  device's float32 node springs and positions), and it must be at least 10× the deformable step the builder takes
  (issue 11: "the rigid step is at least 10× the deformable step on the tunnel scene").
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from warpdem.bricks import brick_cells, mesh_bricks
from warpdem.geology import Room
from warpdem.mesh import TET_FACES
from warpdem.rigid import box_inertia, contact_damping_ratio
from warpdem.scene import load_scene
from warpdem.scene_build import finalize_scene, scene_builder
from warpdem.simulation import Simulation

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "limestone_tunnel.toml"
F32_EPS = float(np.finfo(np.float32).eps)
STEP_RTOL = 64.0 * F32_EPS  # float32 node springs (sums of a few area shares) and positions, in an eigenvalue
GAIN = 10.0


def triangle_areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    x = points[faces]
    return 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)


def test_running_bond_wall_counts():
    brick, h = (1.83, 0.3, 0.3), 0.31
    assert brick_cells(1.83, 0.5, h) == 6 and brick_cells(1.83, 0.0, h) == 6 and brick_cells(1.0, 0.25, 0.3) == 4
    mesh = mesh_bricks((0.0, 0.0, 0.0), (7.32, 0.3, 1.2), brick, h, "rock")
    assert mesh.num_blocks == 2 * 4 + 2 * 5
    bedding = np.count_nonzero(mesh.joint_face_set == 0)
    head = np.count_nonzero(mesh.joint_face_set == 1)
    assert (bedding, head) == (3 * 24 * 2, 2 * (3 * 2) + 2 * (4 * 2))
    np.testing.assert_allclose(mesh.tet_volumes().sum(), 7.32 * 0.3 * 1.2, rtol=1e-12)
    assert np.all(mesh.tet_volumes() > 0.0)
    # Each block spans one block length along x (or half of one at the ends of the odd courses) and one course.
    centre = mesh.points[mesh.tets].mean(axis=1)
    for b in range(mesh.num_blocks):
        x = mesh.points[mesh.tets[mesh.tet_block == b]].reshape(-1, 3)
        length = x[:, 0].max() - x[:, 0].min()
        assert math.isclose(length, 1.83, rel_tol=1e-9) or math.isclose(length, 0.915, rel_tol=1e-9)
        np.testing.assert_allclose(x[:, 2].max() - x[:, 2].min(), 0.3, rtol=1e-9)
        assert len(np.unique(np.floor(centre[mesh.tet_block == b, 2] / 0.3))) == 1
    # Joint faces are interior faces between two blocks: none on the box's outer faces.
    for name in ("x-", "x+", "y-", "y+", "z-", "z+"):
        assert len(mesh.boundary_faces[name])
    np.testing.assert_allclose(triangle_areas(mesh.points, mesh.boundary_faces["z+"]).sum(), 7.32 * 0.3, rtol=1e-12)


def test_opening_removes_whole_cells():
    cell = np.array([1.83 / 6, 0.3, 0.3])
    room = Room(
        (cell[0] * 5.2, -1.0, 0.3 * 1.2), (cell[0] * 8.8, 1.0, 0.3 * 2.8)
    )  # cell centres 5.5 .. 8.5, 1.5 .. 2.5
    mesh = mesh_bricks((0.0, 0.0, 0.0), (7.32, 0.3, 1.2), (1.83, 0.3, 0.3), 0.31, "rock", openings=[room])
    removed = 4 * 2  # cells: x 5..8, z 1..2
    np.testing.assert_allclose(mesh.tet_volumes().sum(), 7.32 * 0.3 * 1.2 - removed * np.prod(cell), rtol=1e-12)
    walls = triangle_areas(mesh.points, mesh.boundary_faces["opening"]).sum()
    # Its floor, roof and side walls (4 cells wide, 2 high, one deep), not its open front and back.
    np.testing.assert_allclose(walls, 2 * (4 * cell[0] + 2 * 0.3) * 0.3, rtol=1e-12)
    with pytest.raises(ValueError, match="stagger"):
        mesh_bricks((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (1.0, 1.0, 1.0), 0.5, "rock", stagger=1.0)


def analytic_block_step(
    points: np.ndarray, tets: np.ndarray, k_n: float, density: float, zeta: float, dofs: list[int] | None = None
) -> float:
    """dt = 2/ω (sqrt(1 + ζ²) − ζ), ω² = 2 λ_max(M⁻¹K) of one box block (module docstring), in float64; ``dofs``:
    the velocities (vx, vy, vz, ωx, ωy, ωz) a roller leaves the block, all by default (the box's principal axes are
    the coordinate axes, so the constrained problem is the submatrix of K and M on them)."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    surface = faces[counts[inverse.ravel()] == 1]
    share = np.zeros(len(points))
    np.add.at(share, surface.ravel(), np.repeat(triangle_areas(points, surface) / 3.0, 3))
    lo, hi = points.min(axis=0), points.max(axis=0)
    size = hi - lo
    mass = density * np.prod(size)
    r = points - 0.5 * (lo + hi)  # the box's principal axes are the coordinate axes
    k_matrix = np.zeros((6, 6))
    for i in np.flatnonzero(share):
        cross = np.array([[0.0, -r[i, 2], r[i, 1]], [r[i, 2], 0.0, -r[i, 0]], [-r[i, 1], r[i, 0], 0.0]])
        jac = np.hstack([np.eye(3), -cross])
        k_matrix += 0.5 * k_n * share[i] * jac.T @ jac
    inv_sqrt = 1.0 / np.sqrt(np.concatenate([np.full(3, mass), box_inertia(mass, size)]))
    keep = np.arange(6) if dofs is None else np.asarray(dofs)
    scaled = (inv_sqrt[:, None] * k_matrix * inv_sqrt[None, :])[np.ix_(keep, keep)]
    lam = np.linalg.eigvalsh(scaled)[-1]
    return 2.0 / math.sqrt(2.0 * lam) * (math.sqrt(1.0 + zeta**2) - zeta)


def test_limestone_tunnel_rigid_step_is_ten_times_the_deformable(device):
    """A small wall of the scene's bricks, joints, rock and boundaries (4 blocks × 4 courses, no tunnel, charge or
    fracture): the full bricks inside are free boxes; the end blocks of each course above the base (full ones in the
    even courses, half ones in the odd) move on the side rollers (x-normal: vy, vz, ωx left); the rigid step is the
    smallest of those boxes'; the gain over the builder's deformable step is ≥ 10."""
    scene = load_scene(SCENE)
    mesh = scene.mesh.model_copy(update={"hi": (7.32, 0.3, 1.2), "openings": [], "h": scene.mesh.h})
    fracture = scene.fracture.model_copy(update={"enabled": False})
    small = scene.model_copy(update={"mesh": mesh, "loads": [], "fracture": fracture})
    model, state = finalize_scene(small, scene_builder(small), device)
    deformable = model.critical_dt
    sim = Simulation(model, state)
    report = sim.switch_to_rigid()
    assert report.bodies == 18 and report.fixed == 4  # the bottom course; the end blocks above it roll
    k_n = scene.joints.normal_stiffness
    assert scene.contact.surface_normal_stiffness == k_n  # every face of a block is the same spring per area
    density, zeta = scene.materials["limestone"].density, contact_damping_ratio(sim.model)
    steps = []
    for length, dofs in ((1.83, None), (1.83, [1, 2, 3]), (0.915, [1, 2, 3])):
        one = mesh_bricks((0.0, 0.0, 0.0), (length, 0.3, 0.3), (length, 0.3, 0.3), scene.mesh.h, "limestone")
        steps.append(analytic_block_step(one.points, one.tets, k_n, density, zeta, dofs))
    expected = min(steps)
    np.testing.assert_allclose(report.critical_dt, expected, rtol=STEP_RTOL)
    np.testing.assert_allclose(report.deformable_dt, deformable)
    assert report.critical_dt >= GAIN * deformable, report.format()
