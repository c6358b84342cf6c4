"""Node–face contact at the rim of a joint (kernels/node_face_target.py ``new_plane_face``, kernels/fem_surface.py
RIM_EPS): two faces that overlap by nearly all of a face, every node of each lying just past an edge of the other.

The limestone tunnel's defect (docs/limitations.md): its bricks are one 30 cm cell tall and the slab one cell
deep, so a head joint's face is one cell, and its four nodes are the corners of the face opposite. The bedding's
compression shifts the two blocks along the joint, which moves two corners of each face past the far edge of the
other along z; the other two sit on the edges along y (the rollers align the faces in y exactly), outside or inside
by float32 rounding. Measured at the head joint behind the charge cavity's brick remnant (x = 0.915 m, z 9.3-9.6 m):
its springs held at 0.3 ms (3 mm deep); by 0.6 ms the shift was 0.9 mm, 3e-3 of the face, past the KEEP_EPS (then
1e-3) a kept spring allowed and the BARY_EPS (1e-5) a new one did, and no node held the joint: the remnant was 10 cm
into the half brick by 2.4 ms and through it by 5 ms.

Here: block A pushed into block B (held by a wall behind it) across a one-cell joint, A's face taller than B's by
2 OFFSET of the face along one in-plane direction (its corners past B's edges by OFFSET) and narrower by 2 ROUNDING
along the other (B's corners past A's edges by ROUNDING, the scale rounding puts the aligned edges at in the tunnel):
every node of either face lies outside the face opposite. Both in-plane directions (z, and y, the slab's depth),
rigid mode and deformable.

Oracles: (1) the joint holds: A's face penetrates B's by at most DYNAMIC × the static δ = P A / Σ k over A's face
nodes (B's nodes on the joint only stiffen it: the two sets of springs act in parallel; DYNAMIC bounds the overshoot
of a suddenly applied load, a ramp over several periods overshoots less), and it does penetrate (the push is carried
by the joint's springs); (2) the energy books close (warpdem.stages.energy balance error) to BOOKS_ROUNDOFF ε₃₂ sqrt(N)
of the energy in play over the N steps, as the contact books of tests/test_fem_contact.py: the wider rim creates no
energy (a new spring starts at the depth gained in the step). On the code before the rim tolerance A ran 0.22 m into
B (rigid; 21 mm deformable) against a static δ of 1.0 mm.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp
from test_fem_contact import BOOKS_ROUNDOFF, DYNAMIC, F32_EPS, block_parts, hold, part_nodes, plane_faces
from warpdem.kernels.fem_surface import RimFaces, rim_margins

from warpdem.build.mesh import box_mesh
from warpdem.simulation import Simulation
from warpdem.stages.loads import PressureHistory

OFFSET = 3.0e-3
"""How far A's corners lie past B's edges along the offset direction, as a fraction of the 1 m face [-]: the
limestone head joint's 3e-3."""

ROUNDING = 1.0e-4
"""How far B's corners lie past A's edges along the other in-plane direction, as a fraction of the face [-]: ten
times BARY_EPS, the float32 rounding of the tunnel's aligned edges at z ≈ 10 m over a 0.3 m face (~1e-5) and more."""

RIM_PRESSURE = 3.0e5
"""Push on A's outer face [Pa], ramped over 10 ms and then held."""


def rim_blocks(device, along: int, rigid: bool) -> tuple:
    """Block A (x in [0, 1]) pushed into block B (x in [1, 2]) held by a wall (x in [2, 3]), no gravity, no friction;
    A's face taller than B's by 2 OFFSET along axis ``along`` (1: y, 2: z) and narrower by 2 ROUNDING along the
    other. Returns (simulation, A's joint nodes, B's joint nodes, the static δ [m])."""
    from warpdem.stages.fem_contact import contact_stiffness_in_use
    from warpdem.stages.rigid_step import rigid_time_step

    other = 3 - along
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0])
    lo[along], hi[along] = -OFFSET, 1.0 + OFFSET
    lo[other], hi[other] = ROUNDING, 1.0 - ROUNDING
    parts = {
        "a": (tuple(lo), tuple(hi), (1, 1, 1)),
        "b": ((1.0, 0.0, 0.0), (2.0, 1.0, 1.0), (1, 1, 1)),
        "wall": ((2.0, -1.0, -1.0), (3.0, 2.0, 2.0), (1, 1, 1)),
    }
    b, ranges = block_parts(device, parts, (0.0, 0.0, 0.0))
    points, tets = box_mesh(*parts["a"][:2], (1, 1, 1))
    ramp = PressureHistory.table([0.0, 0.01, 10.0], [0.0, RIM_PRESSURE, RIM_PRESSURE])
    b.add_face_pressure(plane_faces(points, tets, 0, 0.0), ramp)
    model, state = b.finalize(device, safety_factor=0.5)
    nodes = part_nodes(model, ranges)
    hold(model, nodes["wall"])
    if rigid:
        model = rigid_time_step(model, state, 0.5)
    sim = Simulation(model, state, track_energy=True)
    if rigid:
        report = sim.switch_to_rigid()
        assert (report.bodies, report.fixed) == (3, 1)
    x0 = sim.model.node_ref_q.numpy().astype(np.float64)
    a_face = nodes["a"][x0[nodes["a"], 0] == 1.0]
    b_face = nodes["b"][x0[nodes["b"], 0] == 1.0]
    area = (1.0 + 2.0 * OFFSET) * (1.0 - 2.0 * ROUNDING)
    static = RIM_PRESSURE * area / contact_stiffness_in_use(sim.model, sim.state)[a_face].sum()
    return sim, a_face, b_face, static


@pytest.mark.parametrize("rigid", [True, False], ids=["rigid", "deformable"])
@pytest.mark.parametrize("along", [2, 1], ids=["z", "y"])
def test_joint_holds_where_every_node_is_past_the_rim_of_the_face_opposite(device, along, rigid):
    """See the module docstring: the joint holds within DYNAMIC × its static δ and the books close."""
    from warpdem.stages.energy import balance_error

    sim, a_face, b_face, static = rim_blocks(device, along, rigid)
    start = sim.energy()
    in_play, worst, deepest, steps = start.in_play, 0.0, 0.0, 0
    chunk = max(int(0.005 / sim.model.dt), 1)
    for _ in range(12):  # to 60 ms: the ramp and 50 ms of the full push
        sim.advance(chunk)
        steps += chunk
        x = sim.state.node_q.numpy().astype(np.float64)
        deepest = max(deepest, float(x[a_face, 0].mean() - x[b_face, 0].mean()))
        now = sim.energy()
        in_play = max(in_play, now.in_play)
        worst = max(worst, abs(balance_error(start, now, in_play)))
    x = sim.state.node_q.numpy().astype(np.float64)
    assert (x[a_face, 0].mean() - x[b_face, 0].mean()) > 0.1 * static  # pressed, and carried by the joint
    assert deepest < DYNAMIC * static, (deepest, static)
    assert worst < BOOKS_ROUNDOFF * F32_EPS * math.sqrt(steps), worst


@wp.kernel
def _margins_kernel(rims: RimFaces, out: wp.array(dtype=wp.vec2)):
    f = wp.tid()
    out[f] = rim_margins(f, rims)


def _face_margins(sim) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """rim_margins of every live face, the faces' reference positions (F, 3, 3) and their joint sets."""
    from warpdem.stages.fem_contact import rim_faces

    m, s = sim.model, sim.state
    nf = int(s.face_count.numpy()[0])
    out = wp.zeros(max(nf, 1), dtype=wp.vec2, device=m.device)
    wp.launch(_margins_kernel, dim=nf, inputs=[rim_faces(m)], outputs=[out], device=m.device)
    faces = m.face_nodes.numpy()[:nf]
    return out.numpy()[:nf], m.node_ref_q.numpy()[faces].astype(np.float64), m.face_joint.numpy()[:nf]


def _inside_the_built_mesh(positions: np.ndarray, sim) -> np.ndarray:
    """Brute force: a face lay inside the built mesh when a face of another live tet has the same three reference
    positions (daughters share their parent's bit for bit), i.e. the unsplit mesh had a tet across it."""
    from warpdem.tables import TET_FACES

    m, s = sim.model, sim.state
    nt = int(s.tet_count.numpy()[0])
    tets = m.tet_nodes.numpy()[:nt][s.tet_active.numpy()[:nt] != 0]
    x = m.node_ref_q.numpy().astype(np.float64)
    all_faces = {}
    for tet in tets:
        for face in tet[TET_FACES]:
            key = tuple(sorted(map(tuple, x[face])))
            all_faces[key] = all_faces.get(key, 0) + 1
    return np.array([all_faces[tuple(sorted(map(tuple, p)))] == 2 for p in positions])


def test_a_cracks_faces_take_the_narrow_margins_and_the_others_the_rim_ones(device):
    """kernels/fem_surface.py ``rim_margins``: (BARY_EPS, FACE_KEEP_EPS) on the faces of a crack, (RIM_EPS, KEEP_EPS)
    on every other face: the outer surface and joint faces (a joint's two sides also lie inside the built mesh).
    A ledge of RIM_EPS on every kink of a crack held the Brazilian disc's crack shut (fem_surface.py RIM_EPS).
    Oracles: a bar pulled apart along z with nodal fracture on (tests/test_timeseries.py's) until nodes split, and a
    jointed cube (two cells across a joint plane, no crack); each face's class by brute force over the live tets'
    faces (:func:`_inside_the_built_mesh`) and the joint sets."""
    from test_timeseries import BAR_FRACTURE, BAR_SCENE
    from warpdem.kernels.fem_surface import BARY_EPS, FACE_KEEP_EPS, KEEP_EPS, RIM_EPS

    from warpdem.build.builder import ModelBuilder
    from warpdem.build.scene_build import build_scene
    from warpdem.scene import parse_scene
    from warpdem.stages.fracture import FractureProps, attach_fracture
    from warpdem.stages.joints import JointProps
    from warpdem.tables import TET_FACES

    narrow, wide = (float(BARY_EPS), float(FACE_KEEP_EPS)), (float(RIM_EPS), float(KEEP_EPS))
    model, state = build_scene(parse_scene(BAR_SCENE), device)
    model, state = attach_fracture(model, state, [FractureProps(**BAR_FRACTURE)], check_interval=1)
    sim = Simulation(model, state)
    n0 = sim.node_count
    sim.advance(int(1.0e-4 / sim.model.dt))
    assert sim.node_count > n0, "the bar should have cracked"
    margins, positions, joint = _face_margins(sim)
    crack = _inside_the_built_mesh(positions, sim) & (joint < 0)
    assert crack.any() and (~crack).any()
    np.testing.assert_allclose(margins[crack], np.tile(narrow, (crack.sum(), 1)), rtol=1e-6)
    np.testing.assert_allclose(margins[~crack], np.tile(wide, ((~crack).sum(), 1)), rtol=1e-6)

    points, tets = box_mesh((0.0, 0.0, 0.0), (2.0, 1.0, 1.0), (2, 1, 1))
    faces = tets[:, TET_FACES].reshape(-1, 3)
    on_joint = np.all(points[faces][:, :, 0] == 1.0, axis=1)
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", 2600.0, 5.0e9, 0.25)
    js = b.add_joint_set(JointProps(friction=0.5))
    b.add_tet_mesh(points, tets, "rock", joint_faces=np.unique(np.sort(faces[on_joint], axis=1), axis=0), joint_set=js)
    model, state = b.finalize(device)
    model, state = attach_fracture(model, state, [FractureProps(None, None)])
    jointed = Simulation(model, state)
    margins, positions, joint = _face_margins(jointed)
    assert _inside_the_built_mesh(positions, jointed)[joint >= 0].all() and (joint >= 0).sum() == 4
    np.testing.assert_allclose(margins, np.tile(wide, (len(margins), 1)), rtol=1e-6)
