"""Mesh topology and node duplication (kernels/topology.py, warpdem/stages/topology.py), shared by joints and fracture.

Oracles: numpy rebuilds of the star CSR and of the unsplit face adjacency (faces matched by sorted node triples of
the original mesh, an independent method from the device's star search through reference positions); the hand-over
invariant (each element's representative tets hold its nodes) after repeated splits of one node and of joint nodes;
loaded faces still faces of the tets that hold them after a split; growth that keeps every live slot bit for bit.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import box_mesh
from warpdem.simulation import Simulation
from warpdem.stages.fracture import FractureProps, attach_fracture
from warpdem.stages.joints import JointProps
from warpdem.stages.loads import PressureHistory
from warpdem.stages.tets import set_node_displacements
from warpdem.stages.topology import NodeStars, reference_face_neighbors, regrow_nodes
from warpdem.tables import TET_FACES

YOUNG = 1.0e9  # [Pa]
DENSITY = 2000.0  # [kg/m³]
STRENGTH = 1.0e6  # [Pa]


def numpy_face_neighbors(tets: np.ndarray) -> np.ndarray:
    """The tet across each tet-face slot 4t + k (-1 on the surface), by sorted node triples."""
    key = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    same = np.nonzero(inverse[order][1:] == inverse[order][:-1])[0]  # the two slots of an interior face, adjacent
    a, b = order[same], order[same + 1]
    out = np.full(len(key), -1)
    out[a], out[b] = b // 4, a // 4
    return out


def test_star_csr_matches_numpy(device):
    pts, tets = box_mesh((0, 0, 0), (2, 1, 1), (4, 2, 3))
    nn, nt = len(pts), len(tets)
    active = np.ones(nt, dtype=np.int32)
    active[::5] = 0  # inactive tets are in no star
    stars = NodeStars(nn, nt, device)
    tet_nodes = wp.array(tets.astype(np.int32), dtype=wp.vec4i, device=device)
    stars.build(
        tet_nodes,
        wp.array([nt], dtype=int, device=device),
        wp.array(active, dtype=int, device=device),
        wp.array([nn], dtype=int, device=device),
    )
    off, cnt, star = stars.offset.numpy(), stars.count.numpy(), stars.tets.numpy()
    for v in range(nn):
        expected = np.nonzero(np.any(tets == v, axis=1) & (active == 1))[0]
        np.testing.assert_array_equal(star[off[v] : off[v] + cnt[v]], expected)
    # Face neighbours of the active tets: those of the active sub-mesh.
    nbr = stars.tet_face_nbr.numpy()[: 4 * nt].reshape(nt, 4)
    live = np.nonzero(active)[0]
    expected = numpy_face_neighbors(tets[live]).reshape(-1, 4)
    got = nbr[live]
    np.testing.assert_array_equal(np.where(got >= 0, np.searchsorted(live, np.maximum(got, 0)), -1), expected)


def split_model(device, *, joint: bool, pressure: bool = False):
    """A 2 × 1 × 1 m block (4 × 2 × 2 cells) with fracture attached; optionally a bonded joint on x = 1 (pre-split at
    build) and a pressure load on its top face."""
    pts, tets = box_mesh((0, 0, 0), (2, 1, 1), (4, 2, 2))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, 0.25)
    kw = {}
    if joint:
        faces = tets[:, TET_FACES].reshape(-1, 3)
        on = np.all(np.isclose(pts[faces][:, :, 0], 1.0), axis=1)
        kw = {"joint_faces": np.unique(np.sort(faces[on], axis=1), axis=0)}
        kw["joint_set"] = b.add_joint_set(JointProps(friction=0.5, cohesion=1e9, tensile_strength=1e9))
    b.add_tet_mesh(pts, tets, "rock", **kw)
    if pressure:
        faces = tets[:, TET_FACES].reshape(-1, 3)
        top = np.all(np.isclose(pts[faces][:, :, 2], 1.0), axis=1)
        b.add_face_pressure(np.unique(np.sort(faces[top], axis=1), axis=0), PressureHistory.table([0, 1], [1e3, 1e3]))
    model, state = b.finalize(device, safety_factor=0.5)
    model, state = attach_fracture(model, state, [FractureProps(STRENGTH, 100.0)])
    return model, state, pts, tets


def test_reference_adjacency_is_the_unsplit_meshs(device):
    # A joint pre-split at build separates the two halves; the reference adjacency still joins them, as numpy's
    # adjacency of the original mesh does (model tets mapped back to original nodes by reference position).
    model, state, pts, tets = split_model(device, joint=True)
    nt = len(tets)
    lookup = {tuple(np.round(p, 9)): i for i, p in enumerate(pts)}
    ref = model.node_ref_q.numpy().astype(np.float64)
    original = np.array([[lookup[tuple(np.round(ref[v], 9))] for v in t] for t in model.tet_nodes.numpy()[:nt]])
    expected = numpy_face_neighbors(original)
    np.testing.assert_array_equal(model.ref_tet_face_nbr.numpy()[: 4 * nt], expected)
    np.testing.assert_array_equal(reference_face_neighbors(model, state).numpy()[: 4 * nt], expected)
    assert model.joint_capacity > 0 and np.any(model.tet_face_nbr.numpy()[: 4 * nt] != expected)  # the joint is open


def representative_invariant(model, state) -> None:
    """Each cohesive and joint element's representative tets hold its nodes (the hand-over rule); joint elements stay
    sorted by node pair."""
    nt = int(state.tet_count.numpy()[0])
    tets = model.tet_nodes.numpy()[:nt]
    ref_nbr = model.ref_tet_face_nbr.numpy()
    n = int(state.cohesive_count.numpy()[0])
    groups = [(state.cohesive_a.numpy()[:n], state.cohesive_b.numpy()[:n], state.cohesive_tet_face.numpy()[:n])]
    if model.joint_capacity:
        ja, jb = model.joint_a.numpy(), model.joint_b.numpy()
        groups.append((ja, jb, model.joint_tet_face.numpy()))
        # Sorted by pair (min, max), strictly: the contact stage finds an element by binary search.
        key = np.minimum(ja, jb).astype(np.int64) * model.node_capacity + np.maximum(ja, jb)
        assert np.all(np.diff(key) > 0)
    for a, b, slot in groups:
        assert np.all(np.any(tets[slot // 4] == a[:, None], axis=1))
        assert np.all(np.any(tets[ref_nbr[slot]] == b[:, None], axis=1))
        ref = model.node_ref_q.numpy()
        np.testing.assert_array_equal(ref[a], ref[b])


def test_elements_follow_their_representative_tets(device):
    # Stretch along x, then along y, then along z: nodes split again and again, across joints and earlier cracks;
    # every cohesive and joint element keeps nodes its representative tets hold, and the pressure faces stay faces
    # of the tets behind them.
    model, state, _pts, tets = split_model(device, joint=True, pressure=True)
    sim = Simulation(model, state)
    total = 0
    for axis in (0, 1, 2):
        n = sim.node_count
        x = sim.model.node_ref_q.numpy()[:n].astype(np.float64)
        u = np.zeros_like(x)
        u[:, axis] = 2.0 * STRENGTH / YOUNG * x[:, axis]
        set_node_displacements(sim.model, sim.state, u)
        total += sim.fracture_pass().splits
        representative_invariant(sim.model, sim.state)
    assert total > 10 and int(sim.state.cohesive_count.numpy()[0]) == total
    nt = len(tets)
    cur = sim.model.tet_nodes.numpy()[:nt]
    faces = np.sort(cur[:, TET_FACES].reshape(-1, 3), axis=1)
    known = {tuple(f) for f in faces.tolist()}
    for fs in sim.model.loads.pressure.values():
        for f in fs.nodes.numpy().tolist():
            assert tuple(sorted(f)) in known


def test_regrow_nodes_keeps_live_slots(device):
    model, state, _pts, _tets = split_model(device, joint=False)
    cap = model.node_capacity
    grown_model, grown_state = regrow_nodes(model, state, 2 * cap)
    assert grown_model.node_capacity == 2 * cap
    for obj, grown in ((model, grown_model), (state, grown_state)):
        for name, a in obj.arrays().items():
            g = getattr(grown, name)
            if name.startswith("node_") and a.shape[0] == cap:
                assert g.shape[0] == 2 * cap, name
                np.testing.assert_array_equal(g.numpy()[:cap], a.numpy(), err_msg=name)
    spring = grown_state.node_face_spring.numpy()  # node_springs slots per node
    assert spring.shape[0] == 2 * cap * model.node_springs
    np.testing.assert_array_equal(spring[: cap * model.node_springs], state.node_face_spring.numpy())
    assert np.all(spring[cap * model.node_springs :] == -1)
    k = model.max_node_faces
    np.testing.assert_array_equal(grown_state.node_face_index.numpy()[: cap * k], state.node_face_index.numpy())
    assert grown_state.node_face_index.shape[0] == 2 * cap * k


# Renumbering the nodes (finalize(node_order="blocks")) changes only the order in which float32 sums of a node's
# forces are added (contacts scatter onto a face's nodes; a body's force sums its nodes in node order): each such sum
# of K terms may round differently by up to ~K ε₃₂ of its size, which feeds the next step. Over STEPS steps the two
# runs stay within STEPS · K ε₃₂ of each quantity's scale (K = 32: the most terms a node's force gathers here, its
# tets and node–face candidates); a node or id mapped wrongly moves a node by its whole displacement, far above.
RENUMBER_TERMS = 32


def same_node(a_model, b_model, nt: int) -> np.ndarray:
    """The node of ``b_model`` that is each node of ``a_model``: tets keep their slots, so corner k of tet t is the
    same node in both; shape (live nodes of a,)."""
    ta = a_model.tet_nodes.numpy()[:nt].ravel()
    tb = b_model.tet_nodes.numpy()[:nt].ravel()
    m = np.full(ta.max() + 1, -1)
    m[ta] = tb
    return m


def test_block_node_order_gives_the_same_deformable_motion(device):
    """A loaded 2 × 1 × 1 m block cut by a bonded joint on x = 1, numbered as the split leaves it and block by block:
    the same motion, node for node (positions within STEPS · K ε₃₂ of the displacement scale), the same joint
    elements and the same loaded faces (mapped through the node map), under a pressure on its top, a driven end and
    non-reflecting dashpots on the other."""
    steps = 200
    runs = []
    for order in ("split", "blocks"):
        pts, tets = box_mesh((0, 0, 0), (2, 1, 1), (4, 2, 2))
        b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
        b.add_material("rock", DENSITY, YOUNG, 0.25)
        faces = tets[:, TET_FACES].reshape(-1, 3)
        on = np.all(np.isclose(pts[faces][:, :, 0], 1.0), axis=1)
        js = b.add_joint_set(JointProps(friction=0.5, cohesion=1e5, tensile_strength=1e5))
        b.add_tet_mesh(pts, tets, "rock", joint_faces=np.unique(np.sort(faces[on], axis=1), axis=0), joint_set=js)
        top = np.all(np.isclose(pts[faces][:, :, 2], 1.0), axis=1)
        b.add_face_pressure(np.unique(np.sort(faces[top], axis=1), axis=0), PressureHistory.table([0, 1], [1e6, 1e6]))
        b.add_node_velocity(np.flatnonzero(np.isclose(pts[:, 0], 0.0)), (-0.1, 0.0, 0.0))
        end = np.all(np.isclose(pts[faces][:, :, 0], 2.0), axis=1)
        b.add_boundary(np.unique(np.sort(faces[end], axis=1), axis=0), "non_reflecting")
        model, state = b.finalize(device, safety_factor=0.5, node_order=order)
        sim = Simulation(model, state)
        sim.advance(steps)
        runs.append((sim, len(tets)))
    (a, nt), (b_, _) = runs
    nn = a.node_count
    m = same_node(a.model, b_.model, nt)
    assert not np.array_equal(m[:nn], np.arange(nn))  # the numbering did change (the daughters move up)
    ua, ub = a.state.node_u.numpy()[:nn], b_.state.node_u.numpy()[m[:nn]]
    scale = np.abs(ua).max()
    assert scale > 1e-3  # it moved: driven at 0.1 m/s and pushed
    print("renumbered deformable run: max |Δu| / max |u| =", np.abs(ua - ub).max() / scale)
    assert np.abs(ua - ub).max() <= steps * RENUMBER_TERMS * np.finfo(np.float32).eps * scale
    ja = np.sort(np.stack([m[a.model.joint_a.numpy()], m[a.model.joint_b.numpy()]], axis=1), axis=1)
    jb = np.sort(np.stack([b_.model.joint_a.numpy(), b_.model.joint_b.numpy()], axis=1), axis=1)
    assert len(ja) > 0
    np.testing.assert_array_equal(np.unique(ja, axis=0), jb)  # jb sorted by pair: find_joint's bisection holds
    la, lb = a.model.loads, b_.model.loads
    for fa, fb in zip([*la.pressure.values(), la.dashpots], [*lb.pressure.values(), lb.dashpots], strict=True):
        np.testing.assert_array_equal(m[fa.nodes.numpy()], fb.nodes.numpy())
    np.testing.assert_array_equal(a.model.loads.node_driver.numpy()[:nn], b_.model.loads.node_driver.numpy()[m[:nn]])


def test_block_node_order_gives_the_same_rigid_blocks(device):
    """The rattling jointed cube of 27 rigid blocks (warpdem.bench.jointed_cube, 100 steps, its inner joints in
    contact), numbered as the split leaves it and block by block (the bench's order): every body's displacement,
    velocity, rotation and angular momentum within STEPS · K ε₃₂ of its scale, and the same node–face springs (the
    target face of each node as its node triple, mapped through the node map)."""
    from warpdem.bench import jointed_cube

    steps = 100
    a, b_ = jointed_cube(3, device, node_order="split"), jointed_cube(3, device, node_order="blocks")
    for sim in (a, b_):
        sim.advance(steps)
    nn, nt = a.node_count, int(a.state.tet_count.numpy()[0])
    m = same_node(a.model, b_.model, nt)
    assert not np.array_equal(m[:nn], np.arange(nn))
    body = np.full(a.state.body_mass.shape[0], -1)
    body[a.state.node_body.numpy()[:nn]] = b_.state.node_body.numpy()[m[:nn]]
    assert np.array_equal(np.sort(body), np.arange(len(body)))  # a bijection of the bodies
    worst = 0.0
    for name in ("body_dc", "body_v", "body_q", "body_l"):
        x, y = getattr(a.state, name).numpy(), getattr(b_.state, name).numpy()[body]
        scale = np.abs(x).max()
        assert scale > 0.0, name
        worst = max(worst, np.abs(x - y).max() / scale)
        assert np.abs(x - y).max() <= steps * RENUMBER_TERMS * np.finfo(np.float32).eps * scale, name
    print("renumbered rigid cube: worst max |Δ| / scale =", worst)
    k = a.model.node_springs  # spring slots per node: compare the rows of the same node
    sa = a.state.node_face_spring.numpy().reshape(-1, k)[:nn]
    sb = b_.state.node_face_spring.numpy().reshape(-1, k)[m[:nn]]
    assert np.count_nonzero((sa >= 0).any(axis=1)) > nn // 3
    np.testing.assert_array_equal(sa >= 0, sb >= 0)
    fa, fb = a.model.face_nodes.numpy(), b_.model.face_nodes.numpy()
    np.testing.assert_array_equal(np.sort(m[fa[sa[sa >= 0]]], axis=1), np.sort(fb[sb[sb >= 0]], axis=1))
