"""Fragments (kernels/fragments.py, warpdem/stages/fragments.py): device labelling, masses and speeds, the HDF5 record.

Oracles:
- partitions: a breadth-first search on the host over the same graph (items: nodes with mass, free spheres; edges:
  active tets, intact cohesive and joint elements, intact bonds, couplings into active tets), numbering components
  by their smallest item — exact equality of every label, on random break patterns;
- determinism: two labellings of one state are identical (the union–find roots are component minima whatever the
  thread order);
- conservation: the fragment masses sum to the mass of all items, Σ_f M_f = Σ_i m_i, and each fragment's momentum
  M_f v_f = Σ_{i ∈ f} m_i v_i. Both sides are float64 sums of the same float32 data in different orders: relative
  error ≤ n ε₆₄ ≈ 1e-13 for the few hundred items here, so rtol = 1e-12;
- output: the HDF5 file reads back what was recorded, a restart from frame M keeps frames < M, the USD stage holds
  the ``fragment`` primvar with the labels given.
"""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
import pytest
import warp as wp

from warpdem.build import packing
from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import box_mesh
from warpdem.model import Model, State, conversion_state, fracture_state
from warpdem.stages.fragments import FragmentFile, fragment_colors, label_fragments, read_fragments

RTOL_SUM = 1e-12  # float64 sums of a few hundred float32 values in two orders (module docstring)
SEEDS = (0, 1, 2, 3)


def exploded_model(device: str, *, tets: bool = True, spheres: bool = True) -> tuple[Model, State]:
    """A 2×2×2 box of tets whose every tet has its own four nodes (a fully split mesh: the daughters of one mesh
    node sit at its position), with two spare node slots, and an hcp block of bonded spheres beside it (three of
    them fixed), with three spare sphere slots."""
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", 2600.0, 5.0e7, 0.25)
    nn = nt = 0
    if tets:
        points, cells = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
        nt = len(cells)
        nn = 4 * nt
        b.add_tet_mesh(points[cells].reshape(-1, 3), np.arange(nn).reshape(nt, 4), "rock")
    n = 0
    if spheres:
        radius = 0.1
        q = packing.lattice_packing(packing.Box(np.array([2.0, 0.0, 0.0]), np.array([2.6, 0.6, 0.4])), radius, "hcp")
        free = b.add_spheres(q[3:], radius, "rock")
        held = b.add_spheres(q[:3], radius, "rock", motion="fixed")
        b.add_bonded_group(np.concatenate([held, free]), youngs_modulus=5.0e7, tensile_strength=1e5, shear_strength=1e5)
        n = len(q)
    model, state = b.finalize(
        device,
        dt=1e-6,
        allow_unstable_dt=True,
        particle_capacity=n + 3 if spheres else None,
        node_capacity=nn + 2 if tets else None,
    )
    return model, state


def coincident_pairs(model: Model, nn: int, rng: np.random.Generator) -> np.ndarray:
    """Random pairs (a < b) of live nodes at the same reference position (daughters of one mesh node), shape (K, 2)."""
    x = model.node_ref_q.numpy()[:nn]
    _, root = np.unique(x, axis=0, return_inverse=True)
    root = root.reshape(-1)
    pairs = []
    for r in np.unique(root):
        members = np.flatnonzero(root == r)
        for _ in range(len(members) // 2):
            a, c = rng.choice(members, 2, replace=len(members) < 2)
            if a != c:
                pairs.append((min(a, c), max(a, c)))
    return np.array(pairs, dtype=np.int32).reshape(-1, 2)


def break_randomly(model: Model, state: State, seed: int) -> tuple[Model, State]:
    """A random break pattern: tets deactivated (their nodes' masses re-lumped from the active ones, so a node of
    inactive tets only has none), cohesive and joint elements between daughters of one node, bonds and couplings,
    each broken at random; random velocities."""
    rng = np.random.default_rng(seed)
    d = model.device
    nn = int(state.node_count.numpy()[0])
    nt = int(state.tet_count.numpy()[0])
    n = int(state.particle_count.numpy()[0])
    fields: dict[str, wp.array] = {}
    if nt:
        active = (rng.random(model.tet_capacity) < rng.uniform(0.5, 0.95)).astype(np.int32)
        state.tet_active.assign(active)
        tet_nodes = model.tet_nodes.numpy()[:nt]
        mass = np.zeros(model.node_capacity, dtype=np.float32)
        np.add.at(
            mass, tet_nodes[active[:nt] == 1].reshape(-1), rng.uniform(0.5, 2.0, (nt, 4))[active[:nt] == 1].ravel()
        )
        model = dataclasses.replace(model, node_mass=wp.array(mass, dtype=float, device=d))
        state.node_qd.assign(rng.normal(size=(model.node_capacity, 3)).astype(np.float32))
        cohesive = coincident_pairs(model, nn, rng)
        joints = coincident_pairs(model, nn, rng)
        model = dataclasses.replace(
            model,
            cohesive_capacity=len(cohesive) + 3,
            joint_capacity=len(joints) + 2,
            joint_a=wp.array(np.append(joints[:, 0], [0, 0]), dtype=int, device=d),
            joint_b=wp.array(np.append(joints[:, 1], [1, 1]), dtype=int, device=d),
        )
        fields |= fracture_state(model)
        fields["cohesive_count"] = wp.array([len(cohesive)], dtype=int, device=d)
        fields["cohesive_a"] = wp.array(np.append(cohesive[:, 0], [0, 0, 0]), dtype=int, device=d)
        fields["cohesive_b"] = wp.array(np.append(cohesive[:, 1], [1, 1, 1]), dtype=int, device=d)
        p = rng.uniform(0.4, 0.9)
        fields["cohesive_broken"] = wp.array((rng.random(len(cohesive) + 3) < p).astype(np.int32), device=d)
        fields["joint_count"] = wp.array([len(joints)], dtype=int, device=d)
        broken = (rng.random(len(joints) + 2) < 0.7) * rng.integers(1, 3, len(joints) + 2)
        fields["joint_broken"] = wp.array(broken.astype(np.int32), device=d)
    if n:
        nb = int(state.bond_count.numpy()[0])
        state.bond_broken.assign(
            (rng.random(model.bond_capacity) < rng.uniform(0.5, 0.9)).astype(np.int32)
            * (rng.integers(1, 3, model.bond_capacity))
        )
        state.particle_qd.assign(rng.normal(size=(model.particle_capacity, 3)).astype(np.float32))
        assert nb > 0
    if n and nt:
        k = int(rng.integers(1, 4))
        model = dataclasses.replace(model, coupling_capacity=k + 2)
        fields |= conversion_state(model)
        fields["coupling_count"] = wp.array([k], dtype=int, device=d)
        fields["coupling_particle"] = wp.array(rng.integers(0, n, k + 2).astype(np.int32), device=d)
        fields["coupling_tet"] = wp.array(rng.integers(0, nt, k + 2).astype(np.int32), device=d)
    return model, dataclasses.replace(state, **fields)


def brute_force_labels(model: Model, state: State) -> tuple[np.ndarray, np.ndarray]:
    """Fragment ids of the live nodes and spheres by breadth-first search (module docstring), -1 for non-items."""
    ncap = model.node_capacity
    nn = int(state.node_count.numpy()[0]) if ncap else 0
    n = int(state.particle_count.numpy()[0]) if model.particle_capacity else 0
    item = np.zeros(nn + n, dtype=bool)
    item[:nn] = model.node_mass.numpy()[:nn] > 0.0
    item[nn:] = model.particle_motion.numpy()[:n] == 0
    edges = []
    if model.tet_capacity:
        nt = int(state.tet_count.numpy()[0])
        active = state.tet_active.numpy()[:nt] == 1
        tets = model.tet_nodes.numpy()[:nt]
        edges += [(t[0], t[k]) for t in tets[active] for k in (1, 2, 3)]
    if model.cohesive_capacity:
        c = int(state.cohesive_count.numpy()[0])
        intact = state.cohesive_broken.numpy()[:c] == 0
        edges += list(zip(state.cohesive_a.numpy()[:c][intact], state.cohesive_b.numpy()[:c][intact], strict=True))
    if model.joint_capacity:
        c = int(state.joint_count.numpy()[0])
        intact = state.joint_broken.numpy()[:c] == 0
        edges += list(zip(model.joint_a.numpy()[:c][intact], model.joint_b.numpy()[:c][intact], strict=True))
    if model.bond_capacity:
        c = int(state.bond_count.numpy()[0])
        intact = state.bond_broken.numpy()[:c] == 0
        edges += [
            (nn + i, nn + j)
            for i, j in zip(state.bond_i.numpy()[:c][intact], state.bond_j.numpy()[:c][intact], strict=True)
        ]
    if model.coupling_capacity:
        c = int(state.coupling_count.numpy()[0])
        active = state.tet_active.numpy()
        tets = model.tet_nodes.numpy()
        for p, t in zip(state.coupling_particle.numpy()[:c], state.coupling_tet.numpy()[:c], strict=True):
            if active[t]:
                edges += [(nn + p, tets[t][k]) for k in range(4)]
    adjacency: list[list[int]] = [[] for _ in range(nn + n)]
    for a, b in edges:
        if item[a] and item[b]:
            adjacency[a].append(b)
            adjacency[b].append(a)
    label = np.full(nn + n, -1, dtype=np.int32)
    count = 0
    for start in range(nn + n):  # in item order: component ids follow their smallest items
        if not item[start] or label[start] >= 0:
            continue
        label[start] = count
        queue = deque([start])
        while queue:
            for other in adjacency[queue.popleft()]:
                if label[other] < 0:
                    label[other] = count
                    queue.append(other)
        count += 1
    return label[:nn], label[nn:]


@pytest.mark.parametrize("seed", SEEDS)
def test_labels_match_brute_force(device, seed):
    model, state = break_randomly(*exploded_model(device), seed)
    stats = label_fragments(model, state)
    node_label, particle_label = brute_force_labels(model, state)
    np.testing.assert_array_equal(stats.node_label, node_label)
    np.testing.assert_array_equal(stats.particle_label, particle_label)
    assert stats.count == max(node_label.max(initial=-1), particle_label.max(initial=-1)) + 1
    assert stats.count > 1  # the pattern did break something: the test is not one of a single piece
    again = label_fragments(model, state)
    np.testing.assert_array_equal(again.node_label, stats.node_label)
    np.testing.assert_array_equal(again.particle_label, stats.particle_label)
    np.testing.assert_array_equal(again.masses, stats.masses)


@pytest.mark.parametrize(("tets", "spheres"), [(True, False), (False, True)])
def test_one_kind_of_item(device, tets, spheres):
    """A mesh alone and spheres alone (the other capacity is zero) label as the brute force does."""
    model, state = break_randomly(*exploded_model(device, tets=tets, spheres=spheres), 7)
    stats = label_fragments(model, state)
    node_label, particle_label = brute_force_labels(model, state)
    np.testing.assert_array_equal(stats.node_label, node_label)
    np.testing.assert_array_equal(stats.particle_label, particle_label)


def test_intact_mesh_is_one_fragment(device):
    """Nothing broken: the tets through their cohesive elements and the bonded block are two fragments, the held
    spheres none; masses and momenta are the sums over their items."""
    model, state = exploded_model(device)
    model, state = break_randomly(model, state, 11)
    state.tet_active.fill_(1)
    state.cohesive_broken.zero_()
    state.joint_broken.zero_()
    state.bond_broken.zero_()
    state.coupling_count.zero_()
    nn = int(state.node_count.numpy()[0])
    tets = model.tet_nodes.numpy()[: int(state.tet_count.numpy()[0])]
    mass = np.zeros(model.node_capacity, np.float32)
    np.add.at(mass, tets.reshape(-1), 0.25)
    model = dataclasses.replace(model, node_mass=wp.array(mass, dtype=float, device=device))
    stats = label_fragments(model, state)
    # The daughters of the 27 mesh nodes are chained by the random cohesive pairs only where they were drawn, so
    # the oracle is again the search; the point here is the masses.
    node_label, particle_label = brute_force_labels(model, state)
    np.testing.assert_array_equal(stats.node_label, node_label)
    n = int(state.particle_count.numpy()[0])
    free = model.particle_motion.numpy()[:n] == 0
    m_nodes = mass[:nn].astype(np.float64)
    m_spheres = model.particle_mass.numpy()[:n].astype(np.float64)
    total = m_nodes.sum() + m_spheres[free].sum()
    np.testing.assert_allclose(stats.masses.sum(), total, rtol=RTOL_SUM)
    np.testing.assert_array_equal(particle_label[~free], -1)
    # Momentum of each fragment: M_f v_f = Σ m_i v_i over its items.
    v = np.concatenate([state.node_qd.numpy()[:nn], state.particle_qd.numpy()[:n]]).astype(np.float64)
    m = np.concatenate([m_nodes, m_spheres])
    labels = np.concatenate([node_label, particle_label])
    for f in range(stats.count):
        members = labels == f
        np.testing.assert_allclose(
            stats.fragment_mass[f] * stats.fragment_velocity[f],
            (m[members, None] * v[members]).sum(axis=0),
            rtol=RTOL_SUM,
            atol=RTOL_SUM * np.abs(m[members, None] * v[members]).sum(),
        )
    assert np.all(np.diff(stats.masses) <= 0.0)
    np.testing.assert_allclose(stats.largest, stats.masses[0])


@pytest.mark.parametrize("seed", SEEDS[:2])
def test_masses_sum_to_total(device, seed):
    """Σ_f M_f = Σ of the items' masses (nodes with mass, free spheres), and speeds are the norms of the
    centre-of-mass velocities, listed with their masses."""
    model, state = break_randomly(*exploded_model(device), seed)
    stats = label_fragments(model, state)
    nn = int(state.node_count.numpy()[0])
    n = int(state.particle_count.numpy()[0])
    free = model.particle_motion.numpy()[:n] == 0
    total = model.node_mass.numpy()[:nn].astype(np.float64).sum()
    total += model.particle_mass.numpy()[:n][free].astype(np.float64).sum()
    np.testing.assert_allclose(stats.total_mass, total, rtol=RTOL_SUM)
    order = np.argsort(-stats.fragment_mass, kind="stable")
    np.testing.assert_array_equal(stats.speeds, np.linalg.norm(stats.fragment_velocity[order], axis=1))


def test_fragment_colors():
    """One colour per label, grey for -1, and distinct ids look different."""
    colors = fragment_colors(np.array([-1, 0, 1, 2, 0]))
    assert colors.shape == (5, 3)
    np.testing.assert_array_equal(colors[0], [0.5, 0.5, 0.5])
    np.testing.assert_array_equal(colors[1], colors[4])
    assert np.abs(colors[1] - colors[2]).max() > 0.1 and np.abs(colors[2] - colors[3]).max() > 0.1
    # The vectorised HSV conversion against the standard library's, over many hues.
    import colorsys

    labels = np.arange(500)
    hues = np.mod(labels * 0.618033988749895, 1.0)
    expected = np.array([colorsys.hsv_to_rgb(h, 0.65, 0.9) for h in hues])
    np.testing.assert_allclose(fragment_colors(labels), expected, rtol=0, atol=1e-12)


def test_hdf5_round_trip_and_restart(tmp_path, device):
    """Frames 0–3 recorded, then a restart from frame 2 records new frames 2–3: frames 0–1 are the first run's,
    2–3 the restart's, and nothing but the published file is left."""
    model, state = break_randomly(*exploded_model(device), 5)
    stats = label_fragments(model, state)
    first = FragmentFile(tmp_path, "run")
    for frame in range(4):
        first.record(frame, 0.5 * frame, stats)
    series = read_fragments(first.path)
    np.testing.assert_array_equal(series.frame, [0, 1, 2, 3])
    np.testing.assert_array_equal(series.time, [0.0, 0.5, 1.0, 1.5])
    np.testing.assert_array_equal(series.count, stats.count)
    np.testing.assert_array_equal(series.masses[3], stats.masses)
    np.testing.assert_array_equal(series.speeds[3], stats.speeds)
    np.testing.assert_array_equal(series.largest, stats.largest)
    # The restart's frames carry other numbers (one fragment less: its masses dropped), so they can be told apart.
    other = dataclasses.replace(stats, count=stats.count - 1, masses=stats.masses[1:], speeds=stats.speeds[1:])
    restart = FragmentFile(tmp_path, "run", first_frame=2)
    for frame in (2, 3):
        restart.record(frame, 0.5 * frame, other)
    series = read_fragments(restart.path)
    np.testing.assert_array_equal(series.frame, [0, 1, 2, 3])
    np.testing.assert_array_equal(series.count, [stats.count] * 2 + [stats.count - 1] * 2)
    np.testing.assert_array_equal(series.masses[1], stats.masses)
    np.testing.assert_array_equal(series.masses[2], stats.masses[1:])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run_fragments.h5"]
    # A new run (frame 0) replaces the file.
    fresh = FragmentFile(tmp_path, "run")
    fresh.record(0, 0.0, other)
    np.testing.assert_array_equal(read_fragments(fresh.path).frame, [0])


FRAMES = 4


@pytest.fixture(scope="module")
def struck_bar_run(tmp_path_factory):
    """The struck bonded bar of the time-series tests (bonds break within the first frames), coloured by fragment,
    checkpointed every frame."""
    from test_timeseries import SPHERE_SCENE

    from warpdem.runner import RunOptions, run_scene
    from warpdem.scene import parse_scene

    out = tmp_path_factory.mktemp("fragments")
    scene = parse_scene({**SPHERE_SCENE, "output": {"color_by": "fragment"}})
    options = RunOptions(device="cpu", frames=FRAMES, out_dir=out, quiet=True, checkpoint_every=1.0 / 200.0)
    return scene, out, run_scene(scene, options)


def test_run_writes_fragments(struck_bar_run):
    """Every frame has its group; the last one and the summary agree; the stage's ``fragment`` primvar holds a label
    per sphere whose distinct values are the fragment count (the ball and the bar's pieces; no held spheres here)."""
    from pxr import Usd

    from warpdem.io.plot import plot_run

    _, out, summary = struck_bar_run
    series = read_fragments(summary.fragments_path)
    np.testing.assert_array_equal(series.frame, np.arange(FRAMES + 1))
    assert series.time[-1] == summary.simulated_time
    assert series.count[-1] == summary.fragment_count and series.count[0] >= 2  # bar and ball at least
    assert series.largest[-1] == summary.fragment_largest
    np.testing.assert_allclose(series.total_mass, series.total_mass[0], rtol=RTOL_SUM)  # no sphere appears or leaves
    assert "fragments" in summary.format() and "ejecta speed" in summary.format()
    stage = Usd.Stage.Open(str(summary.usd_path))
    primvar = stage.GetPrimAtPath("/World/Particles").GetAttribute("primvars:fragment")
    label = np.asarray(primvar.Get(float(FRAMES)))
    assert len(label) == summary.particles
    np.testing.assert_array_equal(np.unique(label), np.arange(summary.fragment_count))
    written = plot_run(out)
    assert out / "struck_bar_fragments.png" in written


def test_restart_continues_the_fragment_file(struck_bar_run, tmp_path):
    """A restart from the frame-2 checkpoint, in a folder whose fragment file an interrupted run left with frame 3
    spoiled and without frame 4, leaves the uninterrupted run's file (CPU restarts are bit-identical): every frame's
    masses and speeds equal."""
    import shutil

    import h5py

    from warpdem.runner import RunOptions, run_scene

    scene, out, summary = struck_bar_run
    before = read_fragments(summary.fragments_path)
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    with h5py.File(copy / summary.fragments_path.name, "a") as f:
        f["frame_000003"].attrs["count"] = -1
        del f["frame_000004"]
    checkpoint = copy / summary.checkpoints[1].relative_to(out)
    options = RunOptions(device="cpu", frames=FRAMES, out_dir=copy, quiet=True, restart=checkpoint)
    again = run_scene(scene, options)
    after = read_fragments(again.fragments_path)
    np.testing.assert_array_equal(after.frame, before.frame)
    np.testing.assert_array_equal(after.count, before.count)
    for k in range(FRAMES + 1):
        np.testing.assert_array_equal(after.masses[k], before.masses[k])
        np.testing.assert_array_equal(after.speeds[k], before.speeds[k])


def test_usd_fragment_primvars(tmp_path):
    """The writer stores the labels it is given as int vertex primvars on the spheres and the rock, per frame."""
    from pxr import Usd

    from warpdem.io.usd import SurfaceFrame, UsdWriter

    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [5.0, 5.0, 5.0]])
    surface = SurfaceFrame(
        points=points,
        faces=np.array([[0, 1, 2]]),
        velocities=np.zeros((4, 3)),
        von_mises=np.zeros(1),
        max_principal=np.zeros(1),
        colors=fragment_colors(np.array([0, 0, 0, -1])),
        vertex_colors=True,
        fragment=np.array([0, 0, 0, -1]),
    )
    path = tmp_path / "f.usda"
    with UsdWriter(path, 10.0) as usd:
        for frame in range(2):
            usd.write_frame(
                time=0.1 * frame,
                positions=np.zeros((3, 3)) + np.arange(3)[:, None],
                radii=np.full(3, 0.1),
                velocities=np.zeros((3, 3)),
                ids=np.arange(3),
                colors=np.zeros((3, 3)),
                surface=surface,
                fragments=np.array([1, 2, frame + 1]),
            )
    stage = Usd.Stage.Open(str(path))
    spheres = stage.GetPrimAtPath("/World/Particles").GetAttribute("primvars:fragment")
    np.testing.assert_array_equal(spheres.Get(0.0), [1, 2, 1])
    np.testing.assert_array_equal(spheres.Get(1.0), [1, 2, 2])
    rock = stage.GetPrimAtPath("/World/Rock").GetAttribute("primvars:fragment")
    np.testing.assert_array_equal(rock.Get(1.0), [0, 0, 0, -1])
    assert str(rock.GetTypeName()) == "int[]"


def test_rock_surface_by_fragment(device):
    """The rock surface coloured by fragment carries the node labels and one colour per fragment; tets per fragment
    count each active tet once, in the fragment of its nodes."""
    from warpdem.io.output import RockFrames
    from warpdem.stages.fragments import tets_per_fragment

    model, state = break_randomly(*exploded_model(device, spheres=False), 3)
    stats = label_fragments(model, state)
    surface = RockFrames("fragment").surface(model, state, stats.node_label)
    np.testing.assert_array_equal(surface.fragment, stats.node_label)
    assert surface.vertex_colors
    np.testing.assert_array_equal(surface.colors, fragment_colors(stats.node_label))
    nt = int(state.tet_count.numpy()[0])
    active = state.tet_active.numpy()[:nt] == 1
    tets = model.tet_nodes.numpy()[:nt][active]
    per_tet = stats.node_label[tets]
    assert np.all(per_tet == per_tet[:, :1])  # a tet's four nodes are in one fragment
    # Every node with mass lies in an active tet, so every fragment (nodes only here) holds one; each tet counts once.
    counts = tets_per_fragment(model, state, stats)
    assert counts.sum() == len(tets) and np.all(counts > 0)


@pytest.mark.parametrize("seed", SEEDS[:2])
def test_converted_spheres_end_to_end(device, seed):
    """A bar of tets whose middle band and a random fifth elsewhere convert into bonded spheres coupled to the
    remaining tets (warpdem.stages.conversion), then a random half of the bonds broken: the labels equal the search's
    (nodes left without mass are in no fragment, couplings join spheres to the continuum), and the fragments hold the
    bar's mass
    ρ L W H: Σ of float32 node and sphere masses, rtol = 16 ε₃₂ as the conversion tests' mass bound."""
    from test_conversion import DENSITY, LENGTH, bar

    from warpdem.simulation import Simulation

    rng = np.random.default_rng(seed)
    model, state, points, tets = bar(device, may_convert="all")
    sim = Simulation(model, state)
    # The band 1.5 < x < 2.5 converts whole (its inner nodes lose all their mass), elsewhere a random fifth.
    band = np.abs(points[tets].mean(axis=1)[:, 0] - LENGTH / 2) < 0.5
    mask = band | (rng.random(len(tets)) < 0.2)
    assert sim.convert_tets(mask).converted == mask.sum()
    m, s = sim.model, sim.state
    nb = sim.bond_count
    broken = s.bond_broken.numpy()
    broken[:nb] = rng.random(nb) < 0.5
    s.bond_broken.assign(broken)
    stats = label_fragments(m, s)
    node_label, particle_label = brute_force_labels(m, s)
    np.testing.assert_array_equal(stats.node_label, node_label)
    np.testing.assert_array_equal(stats.particle_label, particle_label)
    assert np.any(node_label < 0) and int(s.coupling_count.numpy()[0]) > 0  # both rules were exercised
    np.testing.assert_allclose(stats.total_mass, DENSITY * LENGTH, rtol=16 * np.finfo(np.float32).eps)


def test_rock_coloured_by_fragment_in_a_run(tmp_path):
    """A block that cannot break (no fracture, joints, bonds or conversion) writes no fragment record, but with
    mesh_color_by = "fragment" its stage carries the rock's labels: one fragment, every vertex 0."""
    from pxr import Usd
    from test_timeseries import MESH_SCENE

    from warpdem.runner import RunOptions, run_scene
    from warpdem.scene import parse_scene

    scene = parse_scene({**MESH_SCENE, "output": {"mesh_color_by": "fragment"}})
    summary = run_scene(scene, RunOptions(device="cpu", frames=1, out_dir=tmp_path, quiet=True))
    assert summary.fragments_path is None and not list(tmp_path.glob("*_fragments.h5"))
    stage = Usd.Stage.Open(str(summary.usd_path))
    rock = stage.GetPrimAtPath("/World/Rock")
    label = np.asarray(rock.GetAttribute("primvars:fragment").Get(1.0))
    np.testing.assert_array_equal(label, np.zeros(summary.nodes, dtype=np.int32))
