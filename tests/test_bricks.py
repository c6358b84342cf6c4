"""Brick meshes (warpdem/build/bricks.py) and the rigid blocks' stable step on the limestone tunnel's bricks
(scenes/limestone_tunnel.toml, LDEC §4).

Oracles:
- the mesh of a 4 × 4 running-bond wall against counting by hand: 4 full blocks in the even courses, 3 full and 2 half
  ones in the odd; 2 × 24 triangles on each of the 3 bedding planes and 2 per head joint; the volume of the box
  less a room of whole cells; the room's face set covers its walls (area of the cut-out's surface); every tet's
  block is one brick (its cells' extent is one block length or the half ones at the ends);
- the rigid step on the scene's joints: each free block is a box of mass M = ρ L W H and principal moments
  M (b² + c²)/12, on node springs k_n/2 × the nodes' area shares of its surface (k_n the scene's normal stiffness,
  the same on every face, × SPRING_BOUND = 2 for a node's springs on up to three planes); ω² = 2 λ_max(M⁻¹K) with
  K = Σ k_i J_iᵀ J_i computed here in float64 from the box's surface triangles, dt = 2/ω (sqrt(1 + ζ²) − ζ).
  warpdem.stages.rigid_step.rigid_critical_step must give it to STEP_RTOL (the device's float32 node springs and
  positions), and at LDEC's own tet size (10 cm: [run] resolution 3) it must be
  at least 10× the deformable step the builder takes (issue 11: "the rigid step is at least 10× the deformable step
  on the tunnel scene"). The rigid step hardly depends on the mesh (mass and springs both scale with the block, not
  the tets), the deformable one is ∝ h: at the scene's own CPU resolution 1 (30 cm cells) the gain is a third of it;
  the scene itself at resolution 3, whose smallest pieces set its step, must gain at least 10× too;
- an opening's min_piece against a brute-force walk over the tets' shared faces: it takes exactly the pieces under
  that fraction of a block that border it;
- the scene's deformable phase: the wave's speed across the bedding (courses and joints in series), the charge's peak
  particle speed at the tunnel against the confined-charge scaled-distance law it is calibrated on (within the law's
  scatter), and the books across the node splitting and the switch.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from test_lattice import walk_components
from warpdem.kernels.node_face_target import SPRING_BOUND

from warpdem.build.bricks import brick_cells, mesh_bricks
from warpdem.build.geology import Room, Tunnel
from warpdem.build.scene_build import finalize_scene, scene_builder
from warpdem.scene import load_scene
from warpdem.simulation import Simulation
from warpdem.stages.rigid import box_inertia
from warpdem.stages.rigid_step import contact_damping_ratio
from warpdem.tables import TET_FACES

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "limestone_tunnel.toml"
# The tunnel's section, the PPV bands and the charge's PPV law as the scene's report measures them
# (benchmarks/limestone_tunnel.py, not an installed module).
_spec = importlib.util.spec_from_file_location(
    "limestone_tunnel", Path(__file__).resolve().parent.parent / "benchmarks" / "limestone_tunnel.py"
)
tunnel = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = tunnel
_spec.loader.exec_module(tunnel)
F32_EPS = float(np.finfo(np.float32).eps)
STEP_RTOL = 64.0 * F32_EPS  # float32 node springs (sums of a few area shares) and positions, in an eigenvalue
GAIN = 10.0
LDEC_RESOLUTION = 3.0
"""[run] resolution of LDEC's 10 cm tets (the scene's h = 0.31 m / 3: cells of 0.102 × 0.1 × 0.1 m)."""


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


def tet_pieces(tets: np.ndarray, block: np.ndarray) -> np.ndarray:
    """Brute-force reference: the face-connected components of the tets within each block, by a breadth-first walk
    over the tets that share a face (labels (T,))."""
    faces = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    by_face: dict[tuple[int, ...], list[int]] = {}
    for slot, face in enumerate(map(tuple, faces)):
        by_face.setdefault(face, []).append(slot // 4)
    neighbours: list[list[int]] = [[] for _ in range(len(tets))]
    for pair in by_face.values():
        if len(pair) == 2 and block[pair[0]] == block[pair[1]]:
            neighbours[pair[0]].append(pair[1])
            neighbours[pair[1]].append(pair[0])
    return walk_components(neighbours)


def test_opening_takes_the_small_pieces_it_cuts():
    """A circular opening through a wall with min_piece = 0.3: the mesh equals the one without it less exactly the
    pieces (face-connected tets of one block, brute force) that border the opening and hold under 0.3 of a whole
    block's volume (none lies within rounding of it: a piece is a whole number of 1/36 blocks), and every piece it
    leaves bordering the opening holds at least that."""
    brick, h, limit = (1.83, 0.3, 0.3), 0.155, 0.3
    hole = Tunnel("y", (3.1, 1.25), "circular", radius=0.83)
    args = ((0.0, 0.0, 0.0), (7.32, 0.3, 2.4), brick, h, "rock")
    full = mesh_bricks(*args, openings=[hole])
    taken = mesh_bricks(*args, openings=[hole], min_pieces=[limit])
    label = tet_pieces(full.tets, full.tet_block)
    volume = full.tet_volumes()
    on_hole = np.zeros(len(full.points), dtype=bool)
    on_hole[full.boundary_faces["opening"].ravel()] = True
    bordering = np.unique(label[np.any(on_hole[full.tets], axis=1)])
    piece_volume = np.bincount(label, weights=volume)
    small = bordering[piece_volume[bordering] < limit * np.prod(brick)]
    assert len(small) >= 2 and np.any(piece_volume[np.setdiff1d(bordering, small)] > 0)  # the case has both kinds
    left = ~np.isin(label, small)
    np.testing.assert_allclose(taken.tet_volumes().sum(), volume[left].sum(), rtol=1e-12)
    centres = np.sort(full.points[full.tets[left]].mean(axis=1).round(9), axis=0)
    np.testing.assert_array_equal(np.sort(taken.points[taken.tets].mean(axis=1).round(9), axis=0), centres)
    after = tet_pieces(taken.tets, taken.tet_block)
    on_hole = np.zeros(len(taken.points), dtype=bool)
    on_hole[taken.boundary_faces["opening"].ravel()] = True
    kept = np.unique(after[np.any(on_hole[taken.tets], axis=1)])
    assert np.all(np.bincount(after, weights=taken.tet_volumes())[kept] >= limit * np.prod(brick) * (1 - 1e-12))
    with pytest.raises(ValueError, match="min_piece"):
        mesh_bricks(*args, openings=[hole], min_pieces=[1.0])


def analytic_block_step(
    points: np.ndarray, tets: np.ndarray, k_n: float, density: float, zeta: float, dofs: list[int] | None = None
) -> float:
    """dt = 2/ω (sqrt(1 + ζ²) − ζ), ω² = 2 λ_max(M⁻¹K) of one box block (module docstring), each node's spring
    SPRING_BOUND × its k_n/2 share (a node holds a spring per face plane it lies behind, no stiffer than that along
    any direction: kernels/node_face_target.py), in float64; ``dofs``:
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
        k_matrix += SPRING_BOUND * 0.5 * k_n * share[i] * jac.T @ jac
    inv_sqrt = 1.0 / np.sqrt(np.concatenate([np.full(3, mass), box_inertia(mass, size)]))
    keep = np.arange(6) if dofs is None else np.asarray(dofs)
    scaled = (inv_sqrt[:, None] * k_matrix * inv_sqrt[None, :])[np.ix_(keep, keep)]
    lam = np.linalg.eigvalsh(scaled)[-1]
    return 2.0 / math.sqrt(2.0 * lam) * (math.sqrt(1.0 + zeta**2) - zeta)


def test_limestone_tunnel_rigid_step_is_ten_times_the_deformable(device):
    """A small wall of the scene's bricks, joints, rock and boundaries (4 blocks × 4 courses, no tunnel, charge or
    fracture) at LDEC's 10 cm tets: every block lies between the slab's roller faces y± (2-D: vx, vz, ωy left); the
    end blocks of each course above the base (full ones in the even courses, half ones in the odd) also touch a side
    roller (x-normal: on two planes that meet, only vz is left); the rigid step is the smallest of those boxes'; the
    gain over the builder's deformable step is ≥ 10."""
    scene = load_scene(SCENE)
    mesh = scene.mesh.model_copy(
        update={"lo": (0.0, 0.0, 0.0), "hi": (7.32, 0.3, 1.2), "openings": [], "h": scene.mesh.h}
    )
    fracture = scene.fracture.model_copy(update={"enabled": False})
    run = scene.run.model_copy(update={"resolution": LDEC_RESOLUTION})
    small = scene.model_copy(update={"mesh": mesh, "loads": [], "fracture": fracture, "run": run})
    h = scene.mesh.h / LDEC_RESOLUTION
    model, state = finalize_scene(small, scene_builder(small), device)
    deformable = model.critical_dt
    sim = Simulation(model, state)
    report = sim.switch_to_rigid()
    assert report.bodies == 18 and report.fixed == 4  # the bottom course; the end blocks above it roll
    k_n = scene.joints.normal_stiffness
    assert scene.contact.surface_normal_stiffness == k_n  # every face of a block is the same spring per area
    density, zeta = scene.materials["limestone"].density, contact_damping_ratio(sim.model)
    steps = []
    for length, dofs in ((1.83, [0, 2, 4]), (1.83, [2]), (0.915, [2])):
        # stagger 0: the cells along the block as in the wall (a half block's 9, where a stagger of 0.5 would ask 10)
        one = mesh_bricks((0.0, 0.0, 0.0), (length, 0.3, 0.3), (length, 0.3, 0.3), h, "limestone", stagger=0.0)
        steps.append(analytic_block_step(one.points, one.tets, k_n, density, zeta, dofs))
    expected = min(steps)
    np.testing.assert_allclose(report.critical_dt, expected, rtol=STEP_RTOL)
    np.testing.assert_allclose(report.deformable_dt, deformable)
    assert report.critical_dt >= GAIN * deformable, report.format()


def test_limestone_tunnel_scene_rigid_step_gain_at_ldec_resolution(device):
    """The scene as shipped (tunnel, charge cavity, boundaries), built at LDEC's 10 cm tets and switched to rigid
    blocks at once: the rigid step is at least 10× the deformable step (issue 11, "on the tunnel scene"). The wall
    test above pins the value for whole blocks; here the scene's smallest pieces set it: the tunnel's walls lie on
    head joints (its cut leaves half blocks), and the cavity takes the pieces under min_piece of a block it cuts
    (without both, one-cell pieces on the cavity's wall gave 5.2×)."""
    scene = load_scene(SCENE)
    run = scene.run.model_copy(update={"resolution": LDEC_RESOLUTION})
    fine = scene.model_copy(update={"run": run})
    model, state = finalize_scene(fine, scene_builder(fine), device)
    deformable = model.critical_dt
    report = Simulation(model, state).switch_to_rigid()
    np.testing.assert_allclose(report.deformable_dt, deformable)
    assert report.critical_dt >= GAIN * deformable, report.format()


PROBE_DEPTHS = (1.3, 4.9)
"""Depths below the charge's cavity [m] of the two bedding planes the wave's arrival is timed at."""
ARRIVAL_WINDOW = 4.5e-3
"""End [s] of the probes' record: past the front's arrival at the deeper probe, before reflections from the tunnel and
the surface come back to the column (a later, larger peak would move the half level)."""
PPV_SCATTER = 2.0
"""Measured PPV scatters about a site's scaled-distance fit by up to a factor of about 2 (Dowding 1985): the median
PPV/law at the tunnel must lie within [1/2, 2]."""


def test_limestone_tunnel_wave_speed_ppv_and_books(device):
    """The scene as shipped to its switch at 10 ms, then rigid blocks for 1 ms.
    Wave speed: the charge's wave runs down the column of courses under the cavity at the speed of the courses in
    series with their bedding joints,
        1/M_eff = 1/M + 1/(k_eff s),  c = sqrt(M_eff/ρ),  M = E (1 − ν) / ((1 + ν)(1 − 2ν))
    (M: the P-wave modulus, a front wide in x between the slab's roller faces y±; s = 0.3 m per course; k_eff [Pa/m]
    the bedding's springs per unit area in the model: Σ node_contact_stiffness of the nodes on a bedding plane, both
    sides, over its area: a node's spring sums all its boundary faces, so the slab's y faces and the head joints add
    to k_n there). The front is timed where the vertical velocity first reaches half its own peak (within
    ARRIVAL_WINDOW) at two bedding planes 3.6 m apart (about 2.7 ms of travel): the pulse changes shape on the way
    (a discrete chain of one-cell courses disperses it; the cylindrical front spreads), which moves its half level by
    up to one course transit (0.22 ms) at each probe, ±16 % of the travel time, so the measured speed lies within
    [0.8, 1.2] × c. Intact limestone (sqrt(M/ρ) = 4.3 km/s, 3.2 c) and joints of the nominal k_n alone (0.7 c) lie
    outside it.
    PPV: the charge is calibrated on the peak particle speed at the tunnel (the scene's header): the median over the
    rock 0.5-1 m from the tunnel's left wall and roof of each node's PPV / the confined-charge law K (R/sqrt(W))^-β at
    its distance R from the charge (benchmarks/limestone_tunnel.py's bands and law) lies within the law's scatter,
    PPV_SCATTER (the 0.4 m borehole at the same 300 MPa gave 0.45).
    Books: they close to 1e-3 of the energy in play across the node splitting and the switch (the charge's pulse,
    0.7 % of its peak left at the switch, still acts on the rigid blocks)."""
    from warpdem.build.scene_build import build_scene
    from warpdem.stages.energy import balance_error
    from warpdem.stages.rigid_step import rigid_step_after_switch

    scene = load_scene(SCENE)
    charge = scene.loads[0]
    model, state = build_scene(scene, device)
    sim = Simulation(model, state)
    hole = charge.region.cylinder
    cx, bottom = hole.center[0], hole.center[2] - scene.mesh.openings[1].radius
    ref = model.node_ref_q.numpy()
    column = ref[np.argmin(np.abs(ref[:, 0] - cx)), 0]  # the grid line nearest the charge's centre
    course = scene.mesh.brick[2]
    planes = [course * round((bottom - d) / course) for d in PROBE_DEPTHS]
    probes = [np.flatnonzero((np.abs(ref[:, 0] - column) < 1e-4) & (np.abs(ref[:, 2] - z) < 1e-4)) for z in planes]
    assert all(len(p) for p in probes)
    peak = np.zeros(len(ref))  # each node's largest speed while deformable [m/s]
    e0 = sim.energy()
    in_play = e0.in_play
    times, vz = [], []
    steps = 0
    while not sim.rigid:
        sim.advance(1)
        steps += 1
        v = sim.state.node_qd.numpy()
        if not sim.rigid:  # the switch step's speeds are the blocks' (benchmarks/limestone_tunnel.py)
            np.maximum(peak, np.linalg.norm(v[: len(ref)], axis=1), out=peak)
        if sim.time <= ARRIVAL_WINDOW:
            times.append(sim.time)
            vz.append([float(v[p, 2].mean()) for p in probes])
        in_play = max(in_play, sim.energy().in_play) if steps % 50 == 0 else in_play
    assert int(sim.state.node_splits_total.numpy()[0]) > 0  # the tunnel's rock cracked before the switch
    critical = rigid_step_after_switch(sim.model, sim.state)
    sim.set_time_step(scene.run.safety_factor * critical.value, critical)
    sim.advance(round(1e-3 / sim.model.dt))
    in_play = max(in_play, sim.energy().in_play)
    error = balance_error(e0, sim.energy(), in_play)
    assert abs(error) < 1e-3, error

    speed = np.abs(np.asarray(vz))
    arrival = [times[int(np.argmax(speed[:, j] >= 0.5 * speed[:, j].max()))] for j in range(2)]
    measured = (planes[0] - planes[1]) / (arrival[1] - arrival[0])
    rock = scene.materials["limestone"]
    nu = rock.poisson_ratio
    m_intact = rock.youngs_modulus * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))
    k = model.node_contact_stiffness.numpy().astype(np.float64)
    on = np.abs(ref[:, 2] - planes[0]) < 1e-4  # the upper plane: whole (the tunnel cuts the lower one)
    area = float(np.prod(ref[:, [0, 1]].max(axis=0) - ref[:, [0, 1]].min(axis=0)))
    k_eff = k[on].sum() / area
    c = math.sqrt(1.0 / (1.0 / m_intact + 1.0 / (k_eff * course)) / rock.density)
    assert 0.8 * c <= measured <= 1.2 * c, (measured, c, k_eff)
    assert measured < 0.5 * math.sqrt(m_intact / rock.density)

    lo, hi = tunnel.tunnel_section(scene)
    bands = tunnel.ppv_bands(ref.astype(np.float64), lo, hi)
    rock_near = np.logical_or(*bands.values())
    distance = np.hypot(ref[rock_near, 0] - cx, ref[rock_near, 2] - hole.center[2])
    ratio = float(np.median(peak[rock_near] / tunnel.ppv_law(distance)))
    assert 1.0 / PPV_SCATTER <= ratio <= PPV_SCATTER, ratio
