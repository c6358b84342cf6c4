"""Joints (kernels/joints.py, warpdem/stages/joints.py): the device pass that pre-splits joint faces, the append pass of
warpdem.stages.compaction it runs on, and the cohesive joint interface elements.

Oracles:
- the append pass against numpy (the parents' copies land after the live slots, in the parents' order; a total past
  the capacity writes nothing out of bounds and reports the size needed);
- the split against a brute-force union-find of every node's star over the faces that hold the node and are no
  joint faces (a plain Python loop over the mesh): the node count, and the exact partition of each star onto the
  new nodes; topology invariants (indices in range, no tet holding nodes of both sides, the blocks of a geology mesh
  are exactly the connected components); mass, volume and reference positions preserved; identical arrays on two
  runs; the pass run again over its own result splits nothing (idempotent);
- a hanging block on a horizontal bonded joint: the static tension is the block's weight over the joint area,
  σ = ρ g H. A joint of strength well above it holds (no element fails; the block hangs within the elastic
  stretch); one below it lets go (every element fails in tension and the block falls at g).

Tolerances. Masses are float32 sums of ρV/4 shares: MASS_RTOL. A suddenly applied load on an undamped spring
overshoots to twice its static value, and the lumped interface puts up to LUMPING× the mean traction on a corner
or edge pair: a joint holds when its strength exceeds DYNAMIC × LUMPING × σ (HOLD_RATIO is above that), and fails
at once below σ (LET_GO_RATIO). The hanging block's displacement stays below DYNAMIC × the static stretch
(joint: σ / k with k = 2 E / h the two-sided penalty per area; block: σ H / (2 E)) with STRETCH_MARGIN; a released
block falls at g within FALL_RTOL (float32 velocities, a few steps to break).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp
from warpdem.kernels.node_face_target import SPRING_BOUND

from warpdem.build.builder import ModelBuilder
from warpdem.build.geology import Geology, JointSet, RockMass, mesh_geology
from warpdem.build.mesh import box_mesh, tet_signed_volumes
from warpdem.simulation import Simulation
from warpdem.stages.compaction import Compactor
from warpdem.stages.joints import JointFaceError, JointProps, NodeSplitter
from warpdem.tables import TET_FACES

YOUNG = 1.0e8  # [Pa] a soft rock, so that the physics tests take few steps
POISSON = 0.25
DENSITY = 2000.0  # [kg/m³]
GRAVITY = 9.81  # [m/s²]
F32_EPS = float(np.finfo(np.float32).eps)
MASS_RTOL = 16 * F32_EPS
DYNAMIC = 2.0
LUMPING = 1.5
HOLD_RATIO = 4.0  # > DYNAMIC × LUMPING
LET_GO_RATIO = 0.5
STRETCH_MARGIN = 1.5
FALL_RTOL = 0.01


# ----------------------------------------------------------------------------------------------------------------
# Helpers


def plane_faces(points: np.ndarray, tets: np.ndarray, axis: int, value: float, keep=None) -> np.ndarray:
    """The distinct tet faces lying in the plane x_axis = value (optionally only those whose centroid passes
    ``keep``), sorted node triples."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    on = np.all(np.isclose(points[faces][:, :, axis], value), axis=1)
    if keep is not None:
        on &= keep(points[faces].mean(axis=1))
    return np.unique(np.sort(faces[on], axis=1), axis=0)


def build(device, points, tets, joint_faces, props: JointProps | None = None, *, gravity=(0.0, 0.0, 0.0), **kw):
    b = ModelBuilder(gravity=gravity)
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    js = b.add_joint_set(props or JointProps(friction=0.5))
    b.add_tet_mesh(points, tets, "rock", joint_faces=joint_faces, joint_set=js, **kw)
    return b.finalize(device, safety_factor=0.5)


def star_components(tets: np.ndarray, joint_faces: np.ndarray, num_nodes: int) -> list[list[set[int]]]:
    """Brute force: for every node, its tets grouped into components joined across faces that hold the node and
    are no joint faces."""
    joint = {tuple(sorted(f)) for f in joint_faces.tolist()}
    face_tets: dict[tuple, list[int]] = {}
    for t, tet in enumerate(tets.tolist()):
        for k in range(4):
            key = tuple(sorted(tet[:k] + tet[k + 1 :]))
            face_tets.setdefault(key, []).append(t)
    star: list[list[int]] = [[] for _ in range(num_nodes)]
    for t, tet in enumerate(tets.tolist()):
        for v in tet:
            star[v].append(t)

    def find(parent: dict[int, int], t: int) -> int:
        while parent[t] != t:
            parent[t] = parent[parent[t]]
            t = parent[t]
        return t

    out = []
    for v in range(num_nodes):
        parent = {t: t for t in star[v]}
        for key, ts in face_tets.items():
            if v in key and key not in joint and len(ts) == 2:
                a, b = find(parent, ts[0]), find(parent, ts[1])
                parent[max(a, b)] = min(a, b)
        groups: dict[int, set[int]] = {}
        for t in star[v]:
            groups.setdefault(find(parent, t), set()).add(t)
        out.append(sorted(groups.values(), key=min))
    return out


def tet_components(tets: np.ndarray) -> np.ndarray:
    """Connected components of tets joined through shared nodes (numpy union-find), label per tet."""
    parent = np.arange(len(tets))

    def find(t: int) -> int:
        while parent[t] != t:
            parent[t] = parent[parent[t]]
            t = parent[t]
        return t

    first_tet: dict[int, int] = {}
    for t, tet in enumerate(tets.tolist()):
        for v in tet:
            if v in first_tet:
                a, b = find(t), find(first_tet[v])
                parent[max(a, b)] = min(a, b)
            else:
                first_tet[v] = t
    return np.array([find(t) for t in range(len(tets))])


def check_split(model, state, points, tets, joint_faces) -> np.ndarray:
    """Every invariant of a split against the brute-force components; returns the split tets."""
    n0, nt = len(points), len(tets)
    n = int(state.node_count.numpy()[0])
    new_tets = model.tet_nodes.numpy()[:nt].astype(np.int64)
    comps = star_components(tets, joint_faces, n0)
    # Node count: one new node per extra component.
    assert n == n0 + sum(len(c) - 1 for c in comps)
    assert np.all((new_tets >= 0) & (new_tets < n))
    # Each component of each star maps onto one node, different components onto different nodes; the component with
    # the lowest tet keeps the original index, the others get new slots in their parents' order.
    last_new = n0 - 1
    for v, groups in enumerate(comps):
        ids = []
        for g in groups:
            got = {int(new_tets[t][list(tets[t]).index(v)]) for t in g}
            assert len(got) == 1, f"node {v}: a component maps onto {got}"
            ids.append(got.pop())
        assert ids[0] == v and len(set(ids)) == len(ids)
        for new in ids[1:]:
            assert new == last_new + 1
            last_new = new
    # Geometry: every tet keeps its reference shape; copies sit where their parent is.
    ref = model.node_ref_q.numpy()[:n].astype(np.float64)
    np.testing.assert_array_equal(
        tet_signed_volumes(ref, new_tets), tet_signed_volumes(ref, tets)
    )  # the same float32 points, in the same order
    np.testing.assert_array_equal(ref[new_tets], ref[tets])
    # Mass re-lumped per component: the total is unchanged, every node carries its own tets' shares.
    volume = tet_signed_volumes(points, tets)
    mass = model.node_mass.numpy()[:n].astype(np.float64)
    np.testing.assert_allclose(mass.sum(), DENSITY * volume.sum(), rtol=MASS_RTOL)
    expected = np.bincount(new_tets.ravel(), weights=np.repeat(0.25 * DENSITY * volume, 4), minlength=n)
    np.testing.assert_allclose(mass, expected, rtol=MASS_RTOL)
    return new_tets


# ----------------------------------------------------------------------------------------------------------------
# The append pass


@pytest.mark.parametrize(("capacity", "count", "seed"), [(0, 0, 0), (5, 0, 1), (16, 7, 2), (64, 64, 3), (300, 111, 4)])
def test_append_pass_matches_numpy(device, capacity, count, seed):
    rng = np.random.default_rng(seed)
    copies = rng.integers(-1, 4, size=capacity).astype(np.int32)  # negative counts as 0
    want = np.where(np.arange(capacity) < count, np.maximum(copies, 0), 0)
    total = count + int(want.sum())
    values = rng.normal(size=(capacity, 3)).astype(np.float32)
    ints = rng.integers(0, 1000, size=capacity).astype(np.int32)

    compactor = Compactor(capacity, device)
    w_count = wp.array([count], dtype=int, device=device)
    first_new = compactor.plan_append(w_count, wp.array(copies, dtype=int, device=device)).numpy()
    assert int(compactor.new_count.numpy()[0]) == total
    expected_first = count + np.concatenate([[0], np.cumsum(want)[:-1]]) if capacity else np.zeros(0)
    np.testing.assert_array_equal(first_new[:count], expected_first[:count])
    assert np.all(first_new[count:] == -1)

    w_values = wp.array(values, dtype=wp.vec3, device=device)
    w_ints = wp.array(ints, dtype=int, device=device)
    compactor.replicate(w_count, [w_values, w_ints])
    got_v, got_i = w_values.numpy(), w_ints.numpy()
    parents = np.repeat(np.arange(capacity), want)
    fit = min(total, capacity) - count  # appended slots that fit the capacity
    np.testing.assert_array_equal(got_v[:count], values[:count])
    np.testing.assert_array_equal(got_v[count : count + fit], values[parents[:fit]])
    np.testing.assert_array_equal(got_i[count : count + fit], ints[parents[:fit]])
    compactor.finish(w_count)
    assert int(w_count.numpy()[0]) == total


# ----------------------------------------------------------------------------------------------------------------
# Pre-splitting


def test_split_box_through_joint(device):
    """A box cut through by a plane joint: every node on the plane splits (those on the outer boundary too: the
    joint separates their stars as well), into two blocks that share no node."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.2, 1.0, 1.0), (3, 2, 4))
    joint = plane_faces(points, tets, 2, 0.5)
    velocity = np.column_stack([points[:, 0], -points[:, 2], np.ones(len(points))])  # distinct per node
    model, state = build(device, points, tets, joint, velocity=velocity)
    on_plane = np.isclose(points[:, 2], 0.5)
    assert int(state.node_count.numpy()[0]) == len(points) + int(on_plane.sum())
    new_tets = check_split(model, state, points, tets, joint)

    below = points[tets].mean(axis=1)[:, 2] < 0.5
    assert not set(new_tets[below].ravel()) & set(new_tets[~below].ravel())
    labels = tet_components(new_tets)
    assert len(np.unique(labels)) == 2
    assert len(np.unique(labels[below])) == 1 and len(np.unique(labels[~below])) == 1
    # Velocities (and every other per-node array) are copied: a tet's nodes keep their parents' values.
    qd = state.node_qd.numpy()
    np.testing.assert_array_equal(qd[new_tets], velocity.astype(np.float32)[tets])
    # Idempotent: the same pass over the split mesh, with the same faces tagged, finds nothing left to split.
    before = model.tet_nodes.numpy().copy()
    splitter = NodeSplitter(model.node_capacity, model.tet_capacity, model.device)
    splitter.plan(model.tet_nodes, state.tet_count, state.tet_active, state.node_count, model.tet_face_joint)
    assert splitter.new_node_count() == int(state.node_count.numpy()[0])
    splitter.apply(model, state)
    np.testing.assert_array_equal(model.tet_nodes.numpy(), before)
    assert int(state.node_count.numpy()[0]) == len(points) + int(on_plane.sum())
    # The joint's faces are boundary faces on both sides now: 2 per joint face more than the box's own surface.
    box_faces = 2 * 2 * (3 * 2 + 3 * 4 + 2 * 4)
    assert int(state.face_count.numpy()[0]) == box_faces + 2 * len(joint)
    assert np.count_nonzero(model.face_joint.numpy()[: int(state.face_count.numpy()[0])] == 0) == 2 * len(joint)


def test_split_partial_joint_spares_its_rim(device):
    """A joint covering part of a plane: the nodes inside it and where it meets the outer boundary split, the nodes
    on its rim inside the rock do not (the rock around the rim still joins the two sides)."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (4, 4, 2))
    joint = plane_faces(points, tets, 2, 0.5, keep=lambda c: c[:, 0] < 0.5)  # x < 0.5 half of the plane
    model, state = build(device, points, tets, joint)
    check_split(model, state, points, tets, joint)
    on_joint = np.isclose(points[:, 2], 0.5) & (points[:, 0] < 0.5 - 1e-9)
    # Rim at x = 0.5 inside the rock: not split; every other joint node (x < 0.5, boundary or not) is.
    assert int(state.node_count.numpy()[0]) == len(points) + int(on_joint.sum())
    # One block: the two sides still meet beyond the rim.
    assert len(np.unique(tet_components(model.tet_nodes.numpy()[: len(tets)]))) == 1
    assert model.joint_capacity == 0  # a frictional joint has no interface elements


def test_split_geology_blocks_and_determinism(device):
    """A jointed rock mass meshed by Gmsh with two crossing persistent sets: after the split the connected
    components of the tets are exactly the mesher's blocks, and a node splits into as many nodes as blocks meet at
    it. Two builds give identical arrays."""
    geology = Geology(
        RockMass((0.0, 0.0, 0.0), (2.0, 1.0, 1.0)),
        joint_sets=[JointSet(90.0, 90.0, 1.0, 0.95), JointSet(35.0, 0.0, 0.8, 0.45)],
        h=0.35,
    )
    mesh = mesh_geology(geology)
    assert mesh.num_blocks >= 4
    runs = []
    for _ in range(2):
        model, state = build(device, mesh.points, mesh.tets, mesh.joint_faces)
        runs.append((model, state))
    model, state = runs[0]
    new_tets = check_split(model, state, mesh.points, mesh.tets.astype(np.int64), mesh.joint_faces)
    labels = tet_components(new_tets)
    # Same partition as the blocks: each component is one block and each block one component.
    pairs = np.unique(np.column_stack([labels, mesh.tet_block]), axis=0)
    assert len(pairs) == len(np.unique(labels)) == mesh.num_blocks
    blocks_at = [set() for _ in range(len(mesh.points))]
    for t, tet in enumerate(mesh.tets.tolist()):
        for v in tet:
            blocks_at[v].add(int(mesh.tet_block[t]))
    assert int(state.node_count.numpy()[0]) == sum(len(b) for b in blocks_at)
    # Determinism: every array of the model and state is identical on a second build.
    other_model, other_state = runs[1]
    for name, a in model.arrays().items():
        np.testing.assert_array_equal(a.numpy(), getattr(other_model, name).numpy(), err_msg=name)
    for name, a in state.arrays().items():
        np.testing.assert_array_equal(a.numpy(), getattr(other_state, name).numpy(), err_msg=name)


def test_joint_face_must_be_interior(device):
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    outer = plane_faces(points, tets, 2, 0.0)[:1]  # a face of the box's bottom: one tet only
    with pytest.raises(JointFaceError):
        build(device, points, tets, outer)


# ----------------------------------------------------------------------------------------------------------------
# Cohesive joints


def hanging_block(device, strength_ratio: float, steps: int):
    """A 1 × 1 × 0.5 m block hanging below a fixed one from a horizontal joint of tensile strength and cohesion
    ``strength_ratio`` × ρ g H. Returns (model, sim, hanging nodes, their masses, static joint stress)."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    sigma = DENSITY * GRAVITY * 0.5
    props = JointProps(friction=0.5, tensile_strength=strength_ratio * sigma, cohesion=strength_ratio * sigma)
    model, state = build(device, points, tets, plane_faces(points, tets, 2, 0.5), props, gravity=(0, 0, -GRAVITY))
    # The upper block is held: its nodes after the split (both sides' copies exist only now) are fixed.
    new_tets = model.tet_nodes.numpy()[: len(tets)]
    above = points[tets].mean(axis=1)[:, 2] > 0.5
    held = np.unique(new_tets[above])
    hanging = np.unique(new_tets[~above])
    inv_mass = model.node_inv_mass.numpy()
    inv_mass[held] = 0.0
    model.node_inv_mass.assign(inv_mass)
    motion = model.node_motion.numpy()
    motion[held] = 1
    model.node_motion.assign(motion)
    sim = Simulation(model, state)
    sim.advance(steps)
    return model, sim, hanging, model.node_mass.numpy()[hanging].astype(np.float64), sigma


def test_bonded_joint_holds_below_its_strength(device):
    model, sim, hanging, _mass, sigma = hanging_block(device, HOLD_RATIO, 300)
    assert model.joint_capacity == 9  # one element per node pair of the 3 × 3 joint nodes
    np.testing.assert_allclose(model.joint_area.numpy().sum(), 1.0, rtol=MASS_RTOL)
    assert not np.any(sim.state.joint_broken.numpy())
    # The hanging block stays within the dynamic elastic stretch of the joint and of itself.
    h = 0.5  # tet height over the joint faces of this mesh
    stretch = sigma / (2.0 * YOUNG / h) + sigma * 0.5 / (2.0 * YOUNG)
    u = sim.state.node_u.numpy()[hanging].astype(np.float64)
    assert np.abs(u).max() < STRETCH_MARGIN * DYNAMIC * stretch


def test_bonded_joint_lets_go_above_its_strength(device):
    # 3 ms, ten steps of the step before it took a node's springs on several planes (1/√SPRING_BOUND of it since):
    # the suddenly hung block stretches the joint past half its static stress within them.
    model, sim, hanging, mass, _ = hanging_block(device, LET_GO_RATIO, math.ceil(10 * math.sqrt(SPRING_BOUND)))
    assert np.all(sim.state.joint_broken.numpy() == 1)  # every element failed in tension
    assert int(sim.state.joints_broken_total.numpy()[0]) == model.joint_capacity
    # From then on the block falls freely: its mean velocity gains g per unit time.
    v0 = (mass[:, None] * sim.state.node_qd.numpy()[hanging]).sum(axis=0) / mass.sum()
    t0 = sim.time
    sim.advance(200)
    v1 = (mass[:, None] * sim.state.node_qd.numpy()[hanging]).sum(axis=0) / mass.sum()
    np.testing.assert_allclose((v1[2] - v0[2]) / (sim.time - t0), -GRAVITY, rtol=FALL_RTOL)
    assert math.isclose(v1[0], 0.0, abs_tol=1e-3) and math.isclose(v1[1], 0.0, abs_tol=1e-3)


def test_bonded_joint_dashpots_book_what_verlet_works(device):
    """Two blocks joined by a strong bonded joint of soft springs (k_n = K_N per unit area) and dashpots of
    restitution 0.2 bounce apart and back from a relative velocity, no gravity, no bulk viscosity: the joint does all
    the dissipating. The dashpots book Verlet's trapezoid ½ dt F·(v_{n-1/2} + v_{n+1/2}) (half at the evaluation,
    half at the next from node_f_contact), the springs are linear in the gap (their trapezoid is -ΔU), so the total
    is Verlet's conserved energy: it swings about zero within the largest shadow term dt²/8 Σ |f|²/m the motion has
    had (VERLET_MARGIN: the shadow is read at whole frames only). Booked at the half-step velocity alone, the
    dashpots' line leads by about ½ dt c v², first order in dt where the shadow is second: at a fifth of the stable
    step that lead is 9× the bound (measured), and the test fails on it."""
    from test_loads import VERLET_MARGIN, shadow_energy

    from warpdem.stages.tets import TetProps

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    strong = 1.0e3 * YOUNG  # never reached: the joint stays intact
    props = JointProps(friction=0.5, tensile_strength=strong, cohesion=strong, restitution=0.2, normal_stiffness=K_N)
    upper = points[:, 2] > 0.75  # the joint's nodes split later; the upper block's own nodes move
    velocity = np.where(upper[:, None], [0.01, -0.02, 0.05], 0.0)
    b = ModelBuilder()
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.set_tet_properties("rock", TetProps(bulk_viscosity_linear=0.0, bulk_viscosity_quadratic=0.0))  # joint only
    js = b.add_joint_set(props)
    b.add_tet_mesh(points, tets, "rock", joint_faces=plane_faces(points, tets, 2, 0.5), joint_set=js, velocity=velocity)
    # A fifth of the builder's stable step: the shadow term shrinks as dt², the old booking's lead only as dt. What
    # is left below the shadow is float32: the tets' stress formed at the order of the strain (kernels/tets.py
    # director_forces) leaves ~3e-6 of the energy here at any step; formed as μ F + g cof F, whose O(μ) terms cancel,
    # it left ~2e-4, which exceeded the bound below about an eighth of the step (this test failed on it at 0.1).
    model, state = b.finalize(device, safety_factor=0.1)
    sim = Simulation(model, state)
    e0 = sim.energy()
    errors, shadow = [], []
    for _ in range(30):
        sim.advance(20)
        errors.append(sim.energy().total - e0.total)
        shadow.append(shadow_energy(model, sim.state))
    e = sim.energy()
    assert not np.any(sim.state.joint_broken.numpy())
    assert e.dissipated_fem_contact > 0.1 * e0.kinetic  # the dashpots took a good part of the motion
    np.testing.assert_array_less(np.abs(errors), VERLET_MARGIN * np.maximum.accumulate(shadow))


# ----------------------------------------------------------------------------------------------------------------
# Joint normal stiffness per unit area (JointProps.normal_stiffness)

K_N = 1.0e7  # [Pa/m] joint normal stiffness: a 1 m block of 2000 kg/m³ presses it closed by about 1 mm
TINY_FACTOR = 1.0e-7  # penalty factor of the faces that are no joint faces. Their springs (f E / h per unit area
# over the joint nodes' share of the half-block's outer faces: under 5 m², tet heights ≥ 0.25 m) add at most
# 20 f E [N/m] to a side's Σ k = k_n A / 2: RIM_RTOL of it, and of the closure and the contact step.
RIM_RTOL = 20.0 * TINY_FACTOR * YOUNG / (0.5 * K_N)
CLOSURE_SETTLE = 1.0e-3  # the dashpot (restitution 0.2, ζ ≈ 0.46) leaves e^(-ζ ω t) ≈ 1e-9 of the first swing after
# 0.5 s (ω = sqrt(K_N A / M) = 100 rad/s); the tets' own modes, damped by damping_alpha, leave less than this


def stacked_blocks(device, props: JointProps, mode: str):
    """The 1 × 1 × 1 m box cut by a horizontal joint at z = 0.5 into two blocks, the lower one held, under gravity,
    run 0.5 s until it rests. Returns (model, sim, upper-side joint nodes, lower-side joint nodes)."""
    from test_fem_contact import hold

    from warpdem.stages.tets import TetProps

    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    b = ModelBuilder(gravity=(0.0, 0.0, -GRAVITY), contact_stiffness_factor=TINY_FACTOR)
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.set_tet_properties("rock", TetProps(damping_alpha=50.0))
    js = b.add_joint_set(props)
    b.add_tet_mesh(points, tets, "rock", joint_faces=plane_faces(points, tets, 2, 0.5), joint_set=js)
    model, state = b.finalize(device, safety_factor=0.5)
    new_tets = model.tet_nodes.numpy()[: len(tets)]
    above = points[tets].mean(axis=1)[:, 2] > 0.5
    upper, lower = np.unique(new_tets[above]), np.unique(new_tets[~above])
    hold(model, lower)
    sim = Simulation(model, state)
    if mode == "rigid":
        report = sim.switch_to_rigid()
        assert (report.bodies, report.fixed) == (2, 1)
    sim.advance(int(0.5 / model.dt))
    on_joint = np.isclose(model.node_ref_q.numpy()[: int(sim.state.node_count.numpy()[0]), 2], 0.5)
    return model, sim, upper[on_joint[upper]], lower[on_joint[lower]]


@pytest.mark.parametrize("mode", ["deformable", "rigid"])
def test_normal_stiffness_closes_by_stress_over_k_n(device, mode):
    """A joint of normal stiffness k_n under the upper block's weight: σ = ρ g H closes it by σ / k_n, the same in
    both modes. The node springs are k_n/2 × each face's area share on either side (Σ = k_n A/2 per side, to float32
    rounding of the face areas); at rest the upper block's nodes sit σ / k_n below the lower block's (within
    CLOSURE_SETTLE of what is left of the drop's swing and RIM_RTOL of the rim's other faces)."""
    model, sim, upper, lower = stacked_blocks(
        device, JointProps(friction=0.5, restitution=0.2, normal_stiffness=K_N), mode
    )
    k = model.node_contact_stiffness.numpy().astype(np.float64)
    for nodes in (upper, lower):  # k_n / 2 × the joint's area (1 m²) on each side
        np.testing.assert_allclose(k[nodes].sum(), K_N / 2.0, rtol=RIM_RTOL + 16.0 * F32_EPS)
    sigma = DENSITY * GRAVITY * 0.5
    u = sim.state.node_u.numpy().astype(np.float64)
    ref = model.node_ref_q.numpy()
    upper, lower = (n[np.lexsort(ref[n][:, :2].T)] for n in (upper, lower))  # pairs that started at the same point
    np.testing.assert_allclose(ref[upper], ref[lower])
    closure = u[lower, 2] - u[upper, 2]
    # The upper node i presses into the lower faces at lower node i (they coincide) by closure_i, and so does lower
    # node i into the upper faces: at rest Σ (k_i^U + k_i^L) closure_i = ρ g H A, the stiffness-weighted mean is σ/k_n.
    weight = k[upper] + k[lower]
    np.testing.assert_allclose((weight * closure).sum() / weight.sum(), sigma / K_N, rtol=CLOSURE_SETTLE + RIM_RTOL)
    # Rigid blocks close evenly; deformable ones unevenly by at most the rock's own compression σ H / E.
    spread = CLOSURE_SETTLE * sigma / K_N + (sigma * 0.5 / YOUNG if mode == "deformable" else 0.0)
    np.testing.assert_allclose(closure, sigma / K_N, atol=spread)


def test_normal_stiffness_sets_bonded_elements_and_the_contact_step(device):
    """The bonded joint's interface elements carry k_n × their area share (Σ = k_n A exactly as float32 sums); the
    builder's contact step follows the joint's springs: ω² ∝ k_n, so 4 k_n halves it (to the rim's TINY_FACTOR
    faces), and it names the joint set."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    props = JointProps(friction=0.5, tensile_strength=1e6, normal_stiffness=K_N)
    model, _ = build(device, points, tets, plane_faces(points, tets, 2, 0.5), props)
    np.testing.assert_allclose(model.joint_kn.numpy().astype(np.float64).sum(), K_N * 1.0, rtol=16.0 * F32_EPS)

    def contact_step(k_n: float) -> tuple[float, str]:
        b = ModelBuilder(gravity=(0.0, 0.0, 0.0), contact_stiffness_factor=TINY_FACTOR)
        b.add_material("rock", DENSITY, YOUNG, POISSON)
        js = b.add_joint_set(JointProps(friction=0.5, restitution=1.0, normal_stiffness=k_n), name="bed")
        b.add_tet_mesh(points, tets, "rock", joint_faces=plane_faces(points, tets, 2, 0.5), joint_set=js)
        step = b.contact_critical_step(b.tet_mesh_data())
        return step.value, step.source

    (one, source), (four, _) = contact_step(1e3 * K_N), contact_step(4e3 * K_N)
    assert "joint set bed" in source
    np.testing.assert_allclose(four / one, 0.5, rtol=RIM_RTOL)


def test_surface_normal_stiffness_sums_to_half_k_n_per_area(device):
    """ModelBuilder.contact_normal_stiffness k_s: every face that is no joint face is a spring of k_s / 2 per unit area
    whatever the tets behind it, a joint face k_n / 2; so the nodes' springs sum to k_s/2 × the box's 6 m² plus
    k_n/2 × both sides of the 1 m² joint (float32 sums of the area shares)."""
    k_s = 3.0 * K_N
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 3, 2))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0), contact_normal_stiffness=k_s)
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    js = b.add_joint_set(JointProps(friction=0.5, normal_stiffness=K_N))
    b.add_tet_mesh(points, tets, "rock", joint_faces=plane_faces(points, tets, 2, 0.5), joint_set=js)
    model, state = b.finalize(device, safety_factor=0.5)
    k = model.node_contact_stiffness.numpy()[: int(state.node_count.numpy()[0])].astype(np.float64)
    np.testing.assert_allclose(k.sum(), k_s / 2.0 * 6.0 + K_N / 2.0 * 2.0, rtol=16.0 * F32_EPS)
    with pytest.raises(ValueError, match="contact_normal_stiffness must be > 0"):
        ModelBuilder(contact_normal_stiffness=-1.0)._surface_spring()


def test_normal_stiffness_bad_input():
    with pytest.raises(ValueError, match="not both"):
        JointProps(friction=0.5, stiffness_factor=2.0, normal_stiffness=K_N)
    with pytest.raises(ValueError, match="normal_stiffness > 0"):
        JointProps(friction=0.5, normal_stiffness=-K_N)
    assert JointProps(friction=0.5).stiffness_factor == 1.0  # neither given: the rock-relative default
