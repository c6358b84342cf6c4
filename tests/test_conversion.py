"""FEM→DEM conversion (kernels/conversion.py, warpdem/stages/conversion.py, Simulation.conversion_pass): the pass on the
device.

Oracles: conservation of mass and linear momentum by a conversion (the spheres carry ρV and the tet's momentum);
angular momentum against its derived change ΔH = Σ (J_t − (2/5) m r² 1) ω for a rigidly spinning body (J_t the tet's
lumped inertia about its centroid: warpdem.stages.conversion's bound); the criterion against numpy principal stresses of
the same tet stresses (no conversion below f, every tet above f converted in the check that first sees it); brute-force
overlap checks of the new spheres against each other and the remaining boundary faces; topology invariants (indices
in range, bond keys sorted, node masses = Σ ρV/4 of the active tets); determinism (two runs); capacity growth against
a large-capacity run; a restart from a checkpoint against the uninterrupted run; the energy books closing across
conversions.

Tolerances: float32 round-off ε₃₂ = 1.19e-7. Masses are float32 sums of a handful of ρV/4 terms: relative
MASS_RTOL = 16 ε₃₂ of the total. Momenta are float64 sums of float32 m v: relative MOMENTUM_RTOL = 16 ε₃₂ of Σ m |v|.
Criterion: wp.eig3 of a float32 stress against numpy's float64 eigenvalues: relative CRITERION_RTOL = 1e-5.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import box_mesh
from warpdem.model import NEIGHBOR_FIELDS
from warpdem.simulation import Simulation
from warpdem.stages.conversion import (
    ConversionProps,
    attach_conversion,
    conversion_material_table,
    regrow_bonds,
    regrow_particles,
)
from warpdem.stages.energy import balance_error
from warpdem.stages.fem_contact import contact_stiffness_in_use
from warpdem.stages.fracture import FractureProps, attach_fracture
from warpdem.stages.lattice import edge_pairs
from warpdem.stages.multisphere import mesh_lattice_factors
from warpdem.stages.tets import TetProps, eval_tet_stresses, set_node_displacements
from warpdem.tables import TET_FACES

YOUNG = 1.0e9  # [Pa]
DENSITY = 2000.0  # [kg/m³]
POISSON = 0.25
TRESCA = 1.0e6  # τ_f [Pa]
LENGTH = 4.0  # bar length along x [m]
F32_EPS = float(np.finfo(np.float32).eps)
MASS_RTOL = 16 * F32_EPS
MOMENTUM_RTOL = 16 * F32_EPS
CRITERION_RTOL = 1.0e-5


# ----------------------------------------------------------------------------------------------------------------
# Helpers


def bar(
    device,
    *,
    may_convert="mid",
    driver_speed: float = 0.0,
    particle_capacity: int | None = None,
    check_interval: int = 1,
    jitter: float = 0.0,
    criterion: str = "tresca",
    divisions=(8, 2, 2),
    origin=(0.0, 0.0, 0.0),
    spheres_per_tet: int = 1,
    max_sphere_faces: int = 8,
    tet_props: TetProps | None = None,
):
    """A bar [0, 4] × [0, 1] × [0, 1] m of tets with conversion attached; ``may_convert`` "mid" (tets with centroids in
    1.5 < x < 2.5), "all" or a mask; optional velocity drivers ±driver_speed along x on the ends (negative: pushed
    in); ``spheres_per_tet`` spheres per converted tet (4: at 0.2 of the tets' critical step; the sub-lattice's bonds
    need about 1/4); ``tet_props`` the bulk viscosity and damping (default TetProps: the default bulk viscosity, no
    damping)."""
    pts, tets = box_mesh((0.0, 0.0, 0.0), (LENGTH, 1.0, 1.0), divisions)
    if jitter:
        rng = np.random.default_rng(7)
        inner = np.all((pts > 1e-9) & (pts < np.array([LENGTH, 1.0, 1.0]) - 1e-9), axis=1)
        pts = pts + inner[:, None] * rng.uniform(-jitter, jitter, pts.shape)
    pts = pts + np.asarray(origin)
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    if tet_props is not None:
        b.set_tet_properties("rock", tet_props)
    b.add_tet_mesh(pts, tets, "rock")
    if driver_speed:
        b.add_node_velocity(np.isclose(pts[:, 0], 0.0), (-driver_speed, 0.0, 0.0))
        b.add_node_velocity(np.isclose(pts[:, 0], LENGTH), (driver_speed, 0.0, 0.0))
    safety = 0.5 if spheres_per_tet == 1 else 0.2
    model, state = b.finalize(
        device, safety_factor=safety, particle_capacity=particle_capacity, max_sphere_faces=max_sphere_faces
    )
    centroid = pts[tets].mean(axis=1) - np.asarray(origin)
    if isinstance(may_convert, str):
        mask = (np.abs(centroid[:, 0] - LENGTH / 2) < 0.5) if may_convert == "mid" else None
    else:
        mask = may_convert
    props = ConversionProps(criterion=criterion, tresca_strength=TRESCA, tensile_strength=2 * TRESCA)
    model, state = attach_conversion(
        model, state, [props], check_interval=check_interval, may_convert=mask, spheres_per_tet=spheres_per_tet
    )
    return model, state, pts, tets


def stretch(sim: Simulation, eps: float) -> None:
    """Uniaxial stress along x: u = (ε x, -ν ε y, -ν ε z) on the live nodes (by their reference positions)."""
    x = sim.model.node_ref_q.numpy()[: sim.node_count].astype(np.float64)
    set_node_displacements(
        sim.model, sim.state, np.stack([eps * x[:, 0], -POISSON * eps * x[:, 1], -POISSON * eps * x[:, 2]], 1)
    )
    sim.evaluate_forces()


def tresca_measure(sim: Simulation) -> np.ndarray:
    """(σ1 − σ3)/(2 τ_f) of every live tet at the current displacements, active or not (numpy eigenvalues of the
    device's float32 stresses, computed on a copy with every tet active), float64."""
    nt = int(sim.state.tet_count.numpy()[0])
    probe = sim.state.clone()
    probe.tet_active.fill_(1)
    eval_tet_stresses(sim.model, probe)
    sig = np.linalg.eigvalsh(probe.tet_stress.numpy()[:nt].astype(np.float64))
    return (sig[:, -1] - sig[:, 0]) / (2.0 * TRESCA)


def totals(sim: Simulation) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Total mass [kg], linear momentum [kg m/s], angular momentum about the origin [kg m²/s] (node points, sphere
    orbits and spins) and Σ m |v| [kg m/s], in float64."""
    m, s = sim.model, sim.state
    n, nn = sim.particle_count, sim.node_count
    mp = m.particle_mass.numpy()[:n].astype(np.float64)
    xp = s.particle_q.numpy()[:n]
    vp = s.particle_qd.numpy()[:n].astype(np.float64)
    wp_ = s.particle_omega.numpy()[:n].astype(np.float64)
    r = m.particle_radius.numpy()[:n].astype(np.float64)
    mn = m.node_mass.numpy()[:nn].astype(np.float64)
    xn = m.node_ref_q.numpy()[:nn].astype(np.float64) + s.node_u.numpy()[:nn].astype(np.float64)
    vn = s.node_qd.numpy()[:nn].astype(np.float64)
    mass = mp.sum() + mn.sum()
    p = (mp[:, None] * vp).sum(0) + (mn[:, None] * vn).sum(0)
    h = np.cross(xp, mp[:, None] * vp).sum(0) + (0.4 * mp * r**2)[:, None].__mul__(wp_).sum(0)
    h += np.cross(xn, mn[:, None] * vn).sum(0)
    scale = float(np.sum(mp * np.linalg.norm(vp, axis=1)) + np.sum(mn * np.linalg.norm(vn, axis=1)))
    return float(mass), p, h, scale


def live(sim: Simulation) -> dict[str, np.ndarray]:
    """Every live slot of the particle, bond, coupling, node and tet arrays (capacity-independent)."""
    m, s = sim.model, sim.state
    n, nb, nn = sim.particle_count, sim.bond_count, sim.node_count
    nc, nt = int(s.coupling_count.numpy()[0]), int(s.tet_count.numpy()[0])
    out = {}
    for obj in (m, s):
        for f in dataclasses.fields(obj):
            a = getattr(obj, f.name)
            if not hasattr(a, "numpy") or f.name in NEIGHBOR_FIELDS or f.name == "bond_key":
                continue
            for prefix, k in (("particle_", n), ("bond_", nb), ("coupling_", nc), ("node_", nn), ("tet_", nt)):
                if f.name.startswith(prefix) and a.ndim == 1 and a.shape[0] >= k:
                    out[f.name] = a.numpy()[:k]
    for name in ("energy_released_conversion", "tets_converted_total", "spheres_spawned_total", "time"):
        out[name] = getattr(s, name).numpy()
    return out


def check_invariants(sim: Simulation) -> None:
    """Indices in range, bonds sorted by key, masses re-lumped from the active tets, deactivated nodes held."""
    m, s = sim.model, sim.state
    n, nb, nn = sim.particle_count, sim.bond_count, sim.node_count
    nt = int(s.tet_count.numpy()[0])
    active = s.tet_active.numpy()[:nt] == 1
    sphere = s.tet_sphere.numpy()[:nt]
    assert np.all((sphere >= 0) == ~active)
    assert sorted(sphere[~active].tolist()) == list(range(n))  # one sphere per converted tet, ids 0..n-1
    np.testing.assert_array_equal(m.particle_id.numpy()[:n], np.arange(n))
    bi, bj, key = s.bond_i.numpy()[:nb], s.bond_j.numpy()[:nb], s.bond_key.numpy()[:nb]
    assert np.all((bi >= 0) & (bi < bj) & (bj < n))
    np.testing.assert_array_equal(key, bi.astype(np.int64) * m.particle_capacity + bj)
    assert np.all(np.diff(key) > 0)
    nc = int(s.coupling_count.numpy()[0])
    cp, ct = s.coupling_particle.numpy()[:nc], s.coupling_tet.numpy()[:nc]
    assert np.all((cp >= 0) & (cp < n) & (ct >= 0) & (ct < nt))
    assert np.all(active[ct])  # couplings of converted tets were released
    tets = m.tet_nodes.numpy()[:nt]
    quarter = 0.25 * DENSITY * m.tet_volume.numpy()[:nt].astype(np.float64)
    lumped = np.bincount(tets[active].ravel(), weights=np.repeat(quarter[active], 4), minlength=nn)
    np.testing.assert_allclose(m.node_mass.numpy()[:nn], lumped, rtol=MASS_RTOL, atol=MASS_RTOL * quarter.max())
    orphan = lumped == 0.0
    assert np.all(m.node_inv_mass.numpy()[:nn][orphan] == 0.0)
    assert np.all(s.node_qd.numpy()[:nn][orphan] == 0.0)


# ----------------------------------------------------------------------------------------------------------------
# Tests


def test_conversion_conserves_mass_momentum_and_the_derived_angular_momentum(device):
    # A rigid spin ω0 and drift v0 plus a stretch: converting the middle tets hands each one's ρV and momentum to its
    # sphere. Mass and linear momentum are conserved to round-off (Σ m_a v_a = m v̄ per tet); the angular momentum
    # changes by exactly Σ_t (J_t − (2/5) m_t r_t² 1) ω0 (warpdem.stages.conversion: a rigidly spinning tet's internal
    # part J ω is replaced by the sphere's spin), which is the stated bound |ΔH| ≤ Σ (‖J‖ + I_s) |ω|.
    model, state, pts, tets = bar(device, jitter=0.05)
    sim = Simulation(model, state)
    stretch(sim, 2.5e-3)
    omega0, v0 = np.array([0.3, -0.2, 0.5]), np.array([1.0, 2.0, -0.5])
    x = sim.model.node_ref_q.numpy()[: sim.node_count].astype(np.float64) + sim.state.node_u.numpy()[
        : sim.node_count
    ].astype(np.float64)
    sim.state.node_qd.assign((v0 + np.cross(omega0, x)).astype(np.float32))
    mass0, p0, h0, scale = totals(sim)
    measure = tresca_measure(sim)
    report = sim.conversion_pass()
    expected = np.nonzero((measure >= 0.9) & (np.abs(pts[tets].mean(1)[:, 0] - 2.0) < 0.5))[0]
    assert report.converted == len(expected) > 0
    mass1, p1, h1, _ = totals(sim)
    np.testing.assert_allclose(mass1, mass0, rtol=MASS_RTOL)
    np.testing.assert_allclose(p1, p0, atol=MOMENTUM_RTOL * scale)
    # Spheres: mass exactly ρV, at the centroid, with the centroid's velocity and the spin ω0 (L = [ω0]×).
    n = sim.particle_count
    sphere = sim.state.tet_sphere.numpy()[expected]
    vol = sim.model.tet_volume.numpy()[expected].astype(np.float64)
    np.testing.assert_allclose(sim.model.particle_mass.numpy()[sphere], DENSITY * vol, rtol=F32_EPS)
    c = x[tets[expected]].mean(axis=1)
    np.testing.assert_allclose(sim.state.particle_q.numpy()[sphere], c, rtol=0, atol=1e-6)
    np.testing.assert_allclose(sim.state.particle_qd.numpy()[sphere], v0 + np.cross(omega0, c), atol=1e-5)
    np.testing.assert_allclose(sim.state.particle_omega.numpy()[:n], np.tile(omega0, (n, 1)), atol=1e-4)
    # ΔH = Σ (J_t − I_s) ω0, J_t = Σ_a (m/4)(|r_a|² 1 − r_a r_aᵀ) about the centroid.
    r = x[tets[expected]] - c[:, None, :]
    quarter = DENSITY * vol / 4.0
    j = quarter[:, None, None] * (
        np.einsum("tai,tai->t", r, r)[:, None, None] * np.eye(3) - np.einsum("tai,taj->tij", r, r)
    )
    radius = sim.model.particle_radius.numpy()[sphere].astype(np.float64)
    i_s = 0.4 * DENSITY * vol * radius**2
    loss = np.einsum("tij,j->ti", j, omega0).sum(0) - i_s.sum() * omega0
    # Float32 velocities and positions: ΔH to ~ε₃₂ Σ m |x| |v| (the sums' scale).
    node_mass = np.bincount(tets.ravel(), weights=np.repeat(DENSITY * sim.model.tet_volume.numpy()[: len(tets)] / 4, 4))
    h_scale = float(np.sum(node_mass * np.linalg.norm(x, axis=1) * np.linalg.norm(v0 + np.cross(omega0, x), axis=1)))
    atol = 64 * F32_EPS * h_scale
    np.testing.assert_allclose(h0 - h1, loss, atol=atol)
    assert np.linalg.norm(loss) > 100 * atol  # the change is the derived one, well above round-off
    check_invariants(sim)


def test_no_conversion_below_the_threshold_and_in_the_first_check_above(device):
    # Driven bar: the stress grows step by step. After every check (interval 1), every tet that converted had
    # (σ1 − σ3)/2 ≥ f τ_f at that check and every tet still active is below it: no conversion below the threshold,
    # and each conversion in the first check that sees the threshold crossed.
    model, state, _, tets = bar(device, driver_speed=2.0)
    sim = Simulation(model, state)
    may = sim.model.tet_may_convert.numpy()[: len(tets)] == 1
    converted_at = []
    for step in range(60):
        before = sim.state.tet_active.numpy()[: len(tets)] == 1
        sim.advance(1)
        after = sim.state.tet_active.numpy()[: len(tets)] == 1
        measure = tresca_measure(sim)
        new = before & ~after
        assert np.all(measure[new] >= 0.9 * (1 - CRITERION_RTOL)), step
        assert np.all(measure[after & may] < 0.9 * (1 + CRITERION_RTOL)), step
        assert not np.any(new & ~may)
        if new.any():
            converted_at.append(step)
    assert converted_at and converted_at[0] > 0  # it crossed during the run, not at the start
    check_invariants(sim)


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distance from points p (K, 3) to triangles (a, b, c) (K, 3) each: the closest of the plane projection (when it
    falls inside) and the three edges."""

    def segment(p, u, v):
        d = v - u
        t = np.clip(np.einsum("ki,ki->k", p - u, d) / np.einsum("ki,ki->k", d, d), 0.0, 1.0)
        return np.linalg.norm(p - (u + t[:, None] * d), axis=1)

    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    h = np.einsum("ki,ki->k", p - a, n)
    q = p - h[:, None] * n
    inside = np.ones(len(p), dtype=bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ki,ki->k", np.cross(v - u, q - u), n) >= 0.0
    edges = np.minimum(np.minimum(segment(p, a, b), segment(p, b, c)), segment(p, c, a))
    return np.where(inside, np.abs(h), edges)


@pytest.mark.parametrize("origin", [(0.0, 0.0, 0.0), (2.0e3, -1.0e3, 5.0e2)])
def test_spheres_touch_but_overlap_neither_each_other_nor_the_remaining_faces(device, origin):
    # A random third of a jittered, stretched bar converts, at the origin and 2 km from it (float32 node positions
    # resolve 1.2e-4 m there): brute force over all pairs, every two spheres are apart by at least r_i + r_j and every
    # sphere is at least r from every remaining boundary face; each sphere touches its own tet's nearest face (gap
    # below the float32 margin of the radius rule).
    rng = np.random.default_rng(3)
    model, state, _, tets = bar(device, jitter=0.08, may_convert="all", origin=origin)
    sim = Simulation(model, state)
    stretch(sim, 1e-4)
    mask = rng.random(len(tets)) < 0.35
    report = sim.convert_tets(mask)
    assert report.converted == mask.sum()
    n = sim.particle_count
    q = sim.state.particle_q.numpy()[:n]
    r = sim.model.particle_radius.numpy()[:n].astype(np.float64)
    d = np.linalg.norm(q[:, None] - q[None], axis=2) + np.eye(n) * 1e9
    assert np.all(d >= r[:, None] + r[None])
    nf = int(sim.state.face_count.numpy()[0])
    faces = sim.model.face_nodes.numpy()[:nf]
    x = sim.model.node_ref_q.numpy().astype(np.float64) + sim.state.node_u.numpy().astype(np.float64)
    for k in range(n):
        dist = point_triangle_distance(np.repeat(q[k : k + 1], nf, 0), x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]])
        assert dist.min() >= r[k]
    own = x[tets[np.nonzero(mask)[0]]]  # the converted tets, in sphere order (scan order = tet order)
    c = own.mean(axis=1)
    gaps = []
    for f in TET_FACES:
        tri = own[:, f]
        gaps.append(point_triangle_distance(c, tri[:, 0], tri[:, 1], tri[:, 2]))
    nearest = np.min(gaps, axis=0)
    # The radius rule keeps 8 ulps of max(|c|∞, |x_0 − c|) clear of the nearest face; float32 geometry adds a few ε.
    margin = 8 * F32_EPS * np.maximum(np.abs(c).max(axis=1), np.linalg.norm(own[:, 0] - c, axis=1))
    assert np.all(nearest - r >= 0.0)
    assert np.all(nearest - r <= margin + 8 * F32_EPS * nearest)
    assert sim.energy().elastic == 0.0  # no contact or bond holds energy at birth
    check_invariants(sim)


def test_two_runs_are_identical_and_growth_equals_a_large_capacity_run(device):
    # A model without spheres (particle capacity 1, no bonds, 1 coupling slot) converts as it is pulled: particles,
    # bonds and couplings grow ×2 as needed. The same run with everything allocated large at the start gives the
    # same live slots bit for bit (CPU), and a second small run repeats the first.
    def run(large: bool) -> Simulation:
        model, state, _, _ = bar(device, driver_speed=2.0, particle_capacity=256 if large else None)
        if large:
            model, state = regrow_bonds(model, state, 1024)
        else:
            from warpdem.stages.coupling import regrow_coupling

            model, state = regrow_coupling(dataclasses.replace(model, coupling_capacity=0), state, 1)
        sim = Simulation(model, state)
        sim.advance(50)
        return sim

    small, again, large = run(False), run(False), run(True)
    assert small.growths > 0 and small.particle_count > 0 and small.bond_count > 0
    assert int(small.state.coupling_count.numpy()[0]) > 0
    check_invariants(small)
    if device != "cpu":
        return  # float atomics make GPU runs differ in the last bits
    a, b, c = live(small), live(again), live(large)
    assert a.keys() == c.keys()
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
        np.testing.assert_array_equal(a[name], c[name], err_msg=name)


def test_a_pass_whose_sphere_face_lists_overflow_builds_the_contact_lists_once(device):
    # With one sphere–face slot per sphere, the new spheres (each next to the faces its tet's neighbours now expose)
    # overflow it. The pass sizes those lists first, so the force evaluation after it builds the FEM contact lists
    # once (fem_rebuild_total + 1, not + 2), and the lists and forces equal a run with 16 slots from the start.
    def converted(slots: int) -> Simulation:
        model, state, _, _ = bar(device, max_sphere_faces=slots)
        sim = Simulation(model, state)
        stretch(sim, 3e-3)
        builds = int(sim.state.fem_rebuild_total.numpy()[0])
        assert sim.conversion_pass().converted > 0
        assert int(sim.state.fem_rebuild_total.numpy()[0]) == builds + 1
        return sim

    small, large = converted(1), converted(16)
    # The particle slots grow in both runs, the sphere–face slots in the small one alone.
    assert small.model.max_sphere_faces > 1 and small.growths == large.growths + 1
    if device != "cpu":
        return  # float atomics make GPU runs differ in the last bits
    n = small.particle_count
    counts = small.state.sphere_face_count.numpy()[:n]
    np.testing.assert_array_equal(counts, large.state.sphere_face_count.numpy()[:n])
    assert counts.max() > 1
    for name in ("sphere_face_index", "sphere_face_shear"):
        a, b = (getattr(sim.state, name).numpy() for sim in (small, large))
        a = a.reshape(-1, small.model.max_sphere_faces, *a.shape[1:])
        b = b.reshape(-1, large.model.max_sphere_faces, *b.shape[1:])
        for i, c in enumerate(counts):
            np.testing.assert_array_equal(a[i, :c], b[i, :c], err_msg=name)
    np.testing.assert_array_equal(small.state.particle_f.numpy()[:n], large.state.particle_f.numpy()[:n])
    np.testing.assert_array_equal(small.state.node_f.numpy(), large.state.node_f.numpy())


def test_regrow_particles_grows_every_per_particle_array(device):
    # Invariant: every array sized by the particle capacity (or rows of it) grows by the same factor, live slots
    # copied, and bond keys stay i · capacity + j.
    model, state, _, _ = bar(device)
    sim = Simulation(model, state)
    stretch(sim, 3e-3)
    assert sim.conversion_pass().bonds > 0
    m, s = sim.model, sim.state
    old = m.particle_capacity
    m2, s2 = regrow_particles(m, s, 4 * old)
    rows = {"nbr_": m.max_neighbors, "sphere_face_index": m.max_sphere_faces, "sphere_face_shear": m.max_sphere_faces}
    for before, after in ((m, m2), (s, s2)):
        for f in dataclasses.fields(before):
            a, a2 = getattr(before, f.name), getattr(after, f.name)
            if not hasattr(a, "numpy") or f.name.startswith(("node_", "tet_", "face_", "bond_", "coupling_", "star_")):
                continue
            k = next((v for p, v in rows.items() if f.name.startswith(p)), 1)
            if f.name == "wall_shear":
                k = m.num_walls
            if a.shape[0] == old * k and a.shape[0] > 1:
                assert a2.shape[0] == 4 * old * k, f.name
                np.testing.assert_array_equal(a2.numpy()[: old * k], a.numpy(), err_msg=f.name)
    nb = sim.bond_count
    np.testing.assert_array_equal(
        s2.bond_key.numpy()[:nb], s.bond_i.numpy()[:nb].astype(np.int64) * 4 * old + s.bond_j.numpy()[:nb]
    )


def test_restart_continues_bit_for_bit_across_a_conversion(device, tmp_path):
    from warpdem.io.restart import restore_checkpoint, save_checkpoint

    # Checkpoint after conversions (spheres, bonds, couplings alive, capacities grown from a model without spheres),
    # restart, continue: the restarted run equals the uninterrupted one bit for bit on the CPU, through further
    # conversions.
    model, state, _, _ = bar(device, driver_speed=2.0)
    ref = Simulation(model, state)
    ref.advance(18)  # the middle starts converting at step 17 and is done by step 19
    assert ref.particle_count > 0
    path = save_checkpoint(tmp_path / "c.h5", ref, 1, {})
    fresh_model, fresh_state, _, _ = bar(device, driver_speed=2.0)
    model, state, attrs = restore_checkpoint(path, fresh_model, fresh_state)
    restarted = Simulation(model, state, primed=True, step=int(attrs["step"]), time=float(attrs["time"]))
    count = ref.particle_count
    ref.advance(10)
    restarted.advance(10)
    assert ref.particle_count > count  # further conversions after the restart
    if device != "cpu":
        return  # float atomics make GPU runs differ in the last bits
    a, b = live(ref), live(restarted)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def worst_balance_error(sim: Simulation, chunks: int, steps: int) -> float:
    """The largest |balance error| (warpdem.stages.energy.balance_error) over ``chunks`` advances of ``steps`` [-]."""
    start = sim.energy()
    in_play = start.in_play
    worst = 0.0
    for _ in range(chunks):
        sim.advance(steps)
        now = sim.energy()
        in_play = max(in_play, now.in_play)
        worst = max(worst, abs(balance_error(start, now, in_play)))
    return worst


ENERGY_BOUND = 5.0e-5
"""Bound on the energy balance error of a pulled bar converting its middle [-] (relative to the largest energy in
play). A pass closes the books exactly (released = strain + kinetic energy about the centroid beyond the spin + the
change of the shadow term and of the coupling springs; test_a_pass_closes_the_books_exactly), and the bulk viscosity's
work is booked as Verlet does it (test_viscous_books_close_across_conversions); what remains is the elastic forces'
trapezoid error, O((ω dt)²), of the release each conversion causes in the tets and of the new bonds and couplings:
measured 6.2e-6 over 60 steps (48 tets converted; 8.0e-4 while the viscous power was booked half a step ahead), bound
with a margin of 8 for the order of float32 atomics on a GPU."""


def test_energy_balance_closes_across_conversions(device):
    model, state, _, _ = bar(device, driver_speed=2.0)
    sim = Simulation(model, state)
    worst = worst_balance_error(sim, 12, 5)
    assert int(sim.state.tets_converted_total.numpy()[0]) > 0
    assert sim.energy().released_conversion > 0.0
    assert worst < ENERGY_BOUND


VISCOUS_BOOKS_FACTOR = 2.0
"""Bound on the balance error of the viscous run over the conservative one's [-] (test below)."""
ROUNDING_FLOOR = 64 * F32_EPS
"""The books' float32 rounding (kinetic and strain energies summed from float32 velocities and displacements) [-]."""


def test_viscous_books_close_across_conversions(device):
    # A bar pushed in at 2 m/s from both ends: the compression waves meet in the middle, which converts (Tresca), with
    # the default bulk viscosity working in every compressed tet and mass-proportional damping α = 200/s on the nodes.
    # Oracle: Verlet does a dissipative force's work as the trapezoid ½ dt f_n·(v_{n-1/2} + v_{n+1/2}) and the books
    # take exactly that (half at the evaluation, half at the next kick from node_f_viscous; a pass's re-evaluation
    # starts the sums again), so they close as well as the same bar's without any dissipation: to the elastic forces'
    # own trapezoid error, O((ω dt)²) at the conservative run's step (the viscous run's stable step is smaller). Booking
    # the power at v_{n+1/2} for the whole step instead left ½ dt f·v of every converted tet and every re-evaluated
    # node in the books: 4.6e-3 of the energy in play with the viscosity, 1.9e-2 with the damping too (measured).
    errors = {}
    for name, props in (("conservative", TetProps(0.0, 0.0, 0.0)), ("viscous", TetProps(0.06, 1.2, 200.0))):
        model, state, _, _ = bar(device, driver_speed=-2.0, tet_props=props)
        sim = Simulation(model, state)
        errors[name] = worst_balance_error(sim, 12, 5)
        assert int(sim.state.tets_converted_total.numpy()[0]) > 0
        e = sim.energy()
        if name == "viscous":
            # The dissipation is no small part of the energy in play: a lead of half a step of it would show.
            assert e.dissipated_viscous > 0.1 * e.in_play
    print(f"viscous books: {errors}")
    assert errors["viscous"] <= VISCOUS_BOOKS_FACTOR * errors["conservative"] + ROUNDING_FLOOR


def test_a_pass_closes_the_books_exactly(device):
    # Across one pass (between steps) nothing moves: total before = total after, to float64 round-off of the sums.
    model, state, _, _ = bar(device)
    sim = Simulation(model, state)
    stretch(sim, 3e-3)
    e0 = sim.energy()
    report = sim.conversion_pass()
    e1 = sim.energy()
    assert report.converted > 0 and report.couplings > 0
    np.testing.assert_allclose(e1.total, e0.total, rtol=1e-9)
    np.testing.assert_allclose(e0.strain - e1.strain, e1.released_conversion - (e1.shadow - e0.shadow), rtol=1e-6)


def test_conversion_runs_before_splitting_on_a_tet_that_qualifies_for_both(device):
    # Every tet of a stretched bar is above both its Tresca conversion threshold and its nodes' tensile strength. At
    # the shared boundary the conversion pass runs first: every tet converts, so the split pass finds no tet left and
    # splits nothing (the other order would split nodes and then empty their stars).
    model, state, _, tets = bar(device, may_convert="all")
    model, state = attach_fracture(model, state, [FractureProps(1.0e5, 10.0)], check_interval=1)
    sim = Simulation(model, state)
    stretch(sim, 3e-3)
    assert np.all(tresca_measure(sim) >= 0.9)
    sim.advance(1)
    assert int(sim.state.tets_converted_total.numpy()[0]) == len(tets)
    assert int(sim.state.node_splits_total.numpy()[0]) == 0
    assert sim.particle_count == len(tets)


@pytest.mark.parametrize("split_first", [False, True])
def test_bond_and_coupling_stiffness_use_the_edge_degrees_of_the_current_mesh(device, split_first):
    # k_b = κ E V_b / L_b² with V_b = V_t / Z_t + V_n / Z_n (warpdem.stages.lattice), Z the live tets sharing an edge
    # with a tet in the mesh as it is at the pass: against a brute-force numpy count (warpdem.stages.lattice.edge_pairs)
    # over the current tet nodes. Without fracture the pass reads the Z found at attach; after a split pass (split nodes
    # cut edges) it finds Z again around the converting tets. A coupling's k is k_b min(1, 2/(1 + m_s Σ N²/m_a)) ≤ k_b
    # and equals k_b where the ratio allows (checked on the bonds' V_b / L_b² through the neighbour's centroid).
    # Tolerance: a handful of float32 products and quotients, 16 ε₃₂.
    model, state, pts, tets = bar(device, may_convert="all")
    # κ as attach calibrated it on this mesh's own network (warpdem.stages.multisphere.mesh_lattice_factors; its own
    # tests).
    kappa = mesh_lattice_factors(tets, model.node_ref_q.numpy(), np.ones(len(tets), dtype=bool), 1)[0]
    if split_first:  # nodes left of the middle may split: Z changes there, the right side stays joined (couplings)
        model, state = attach_fracture(
            model, state, [FractureProps(1.0e5, 10.0)], check_interval=1, may_split=pts[:, 0] < LENGTH / 2
        )
    sim = Simulation(model, state)
    stretch(sim, 3e-3)
    if split_first:
        assert sim.fracture_pass().splits > 0
    nt = len(tets)
    current = sim.model.tet_nodes.numpy()[:nt]
    degree = np.bincount(edge_pairs(current, np.ones(nt, dtype=bool)).ravel(), minlength=nt).astype(np.float64)
    attach_degree = sim.model.tet_edge_degree.numpy()[:nt]
    # The splits changed Z (so a pass that read the attach-time Z would fail below); without them it is the same.
    assert np.any(degree != attach_degree) == split_first
    centroid = pts[tets].mean(axis=1)
    sim.convert_tets(np.abs(centroid[:, 0] - LENGTH / 2) < 0.5)
    m, s = sim.model, sim.state
    nb, n = sim.bond_count, sim.particle_count
    assert nb > 0
    sphere_tet = np.empty(n, dtype=np.int64)
    tet_sphere = s.tet_sphere.numpy()[:nt]
    sphere_tet[tet_sphere[tet_sphere >= 0]] = np.nonzero(tet_sphere >= 0)[0]
    ti, tj = sphere_tet[s.bond_i.numpy()[:nb]], sphere_tet[s.bond_j.numpy()[:nb]]
    q = s.particle_q.numpy()[:n]
    length = np.linalg.norm(q[s.bond_i.numpy()[:nb]] - q[s.bond_j.numpy()[:nb]], axis=1)
    volume = m.tet_volume.numpy()[:nt].astype(np.float64)
    vb = volume[ti] / degree[ti] + volume[tj] / degree[tj]
    np.testing.assert_allclose(s.bond_kn.numpy()[:nb], kappa * YOUNG * vb / length**2, rtol=16 * F32_EPS)
    nc = int(s.coupling_count.numpy()[0])
    assert nc > 0
    tp, tn = sphere_tet[s.coupling_particle.numpy()[:nc]], s.coupling_tet.numpy()[:nc]
    x = m.node_ref_q.numpy().astype(np.float64) + s.node_u.numpy().astype(np.float64)
    gap = np.linalg.norm(x[m.tet_nodes.numpy()[tn]].mean(axis=1) - q[s.coupling_particle.numpy()[:nc]], axis=1)
    kb = kappa * YOUNG * (volume[tp] / degree[tp] + volume[tn] / degree[tn]) / gap**2
    k = s.coupling_k.numpy()[:nc]
    assert np.all(k <= kb * (1 + 16 * F32_EPS))
    full = k >= kb * (1 - 16 * F32_EPS)
    assert np.any(full)  # couplings at the full bond stiffness pin Z of both ends


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"check_interval": 0}, "check_interval"),
        ({"spheres_per_tet": 2}, "spheres_per_tet"),
        ({"may_convert": np.ones(3, bool)}, "may_convert"),
        ({"coupling_capacity": 0}, "coupling_capacity"),
        ({"materials": [ConversionProps(criterion="von_mises", tresca_strength=1.0)]}, "criterion"),
        ({"materials": [ConversionProps(criterion="rankine")]}, "tensile_strength"),
        ({"materials": [ConversionProps(fraction=1.5, tresca_strength=1.0)]}, "fraction"),
        ({"materials": [None, None]}, "one ConversionProps"),
    ],
)
def test_attach_conversion_rejects_bad_input(kwargs, message):
    pts, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (1, 1, 1))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(pts, tets, "rock")
    model, state = b.finalize("cpu")
    materials = kwargs.pop("materials", [ConversionProps(tresca_strength=TRESCA)])
    with pytest.raises(ValueError, match=message):
        attach_conversion(model, state, materials, **kwargs)


def test_material_that_never_converts_stays_a_continuum(device):
    pts, tets = box_mesh((0.0, 0.0, 0.0), (LENGTH, 1.0, 1.0), (4, 1, 1))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(pts, tets, "rock")
    model, state = b.finalize(device, safety_factor=0.5)
    model, state = attach_conversion(model, state, [None])
    sim = Simulation(model, state)
    stretch(sim, 1e-2)
    assert sim.conversion_pass().converted == 0
    assert sim.particle_count == 0


def test_pressure_on_faces_of_converted_tets_is_dropped(device):
    # Pressure on both ends of a bar; the tets of the x = 0 end convert. Their loaded faces are dropped (collapsed,
    # zero area): from then on the load does no work on those nodes (the work of the x = 0 faces' nodes stays constant;
    # the push goes on on the spheres: tests/test_loads_handover.py), while
    # the x = 4 end, still a continuum, keeps being pushed (its work grows).
    from warpdem.stages.loads import PressureHistory

    pts, tets = box_mesh((0.0, 0.0, 0.0), (LENGTH, 1.0, 1.0), (8, 2, 2))
    faces = tets[:, TET_FACES].reshape(-1, 3)
    on = {end: faces[np.all(np.isclose(pts[faces][:, :, 0], end), axis=1)] for end in (0.0, LENGTH)}
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(pts, tets, "rock")
    b.add_face_pressure(np.concatenate([on[0.0], on[LENGTH]]), PressureHistory.blast(1.0e5, 0.0, 1.0))
    model, state = b.finalize(device, safety_factor=0.5)
    model, state = attach_conversion(model, state, [ConversionProps(tresca_strength=1e12)])
    sim = Simulation(model, state)
    # Only the tets that own the loaded faces (three nodes on x = 0): most end nodes keep other tets, mass and motion,
    # so only the dropping keeps the load off them.
    end_tets = np.sum(np.isclose(pts[tets][:, :, 0], 0.0), axis=1) == 3
    sim.convert_tets(end_tets)
    left = np.unique(on[0.0])
    assert np.count_nonzero(sim.model.node_inv_mass.numpy()[left] > 0.0) >= len(left) - 1
    right = np.unique(on[LENGTH])
    work = sim.state.node_energy_boundary_work
    w0 = work.numpy().copy()
    sim.advance(10)
    w1 = work.numpy()
    np.testing.assert_array_equal(w1[left], w0[left])
    assert np.all(w1[right] > w0[right])
    nodes = next(iter(sim.model.loads.pressure.values())).nodes.numpy()
    collapsed = (nodes[:, 0] == nodes[:, 1]) & (nodes[:, 1] == nodes[:, 2])
    assert collapsed.sum() == len(on[0.0])


def criterion_measure(stress: np.ndarray, criterion: str, props: ConversionProps) -> np.ndarray:
    """The criterion's stress over strength from numpy principal stresses (tension positive), float64."""
    sig = np.linalg.eigvalsh(stress.astype(np.float64))
    s1, s3 = sig[:, -1], sig[:, 0]
    if criterion == "tresca":
        return (s1 - s3) / (2.0 * props.tresca_strength)
    if criterion == "rankine":
        return s1 / props.tensile_strength
    phi = np.radians(props.friction_angle)
    return (s1 * (1 + np.sin(phi)) - s3 * (1 - np.sin(phi))) / (2.0 * props.cohesion * np.cos(phi))


@pytest.mark.parametrize("criterion", ["tresca", "rankine", "mohr_coulomb"])
def test_each_criterion_converts_exactly_the_tets_at_or_above_its_fraction(device, criterion):
    # A random smooth displacement field gives every tet another stress state (tension, compression, shear). With the
    # strength set at the median of the criterion's measure, the pass converts exactly the tets whose numpy measure
    # reaches f (tets within CRITERION_RTOL of f excluded: float32 eig3 against float64).
    rng = np.random.default_rng(11)
    model, state, _, tets = bar(device, may_convert="all", divisions=(6, 3, 3), jitter=0.05)
    sim = Simulation(model, state)
    x = sim.model.node_ref_q.numpy()[: sim.node_count].astype(np.float64)
    coeff = rng.normal(0.0, 1e-3, (3, 3, 2))
    u = np.stack([np.sin(x @ coeff[i, :, 0]) + x @ coeff[i, :, 1] for i in range(3)], 1)
    set_node_displacements(sim.model, sim.state, u)
    eval_tet_stresses(sim.model, sim.state)
    stress = sim.state.tet_stress.numpy()[: len(tets)]
    unit = ConversionProps(criterion, 0.9, 1.0, 1.0, 1.0, 25.0)
    measure = criterion_measure(stress, criterion, unit)
    strength = float(np.median(measure) / 0.9)
    assert strength > 0.0
    props = ConversionProps(criterion, 0.9, strength, strength, strength, 25.0)
    sim.model = dataclasses.replace(
        sim.model,
        conversion_material_table=conversion_material_table(sim.model, [props], sim.model.device),
    )
    measure = criterion_measure(stress, criterion, props)
    sim.conversion_pass()
    converted = sim.state.tet_active.numpy()[: len(tets)] == 0
    clear = np.abs(measure / 0.9 - 1.0) > CRITERION_RTOL
    np.testing.assert_array_equal(converted[clear], measure[clear] >= 0.9)
    assert 0 < converted.sum() < len(tets)


def test_attach_conversion_refuses_a_step_the_bonded_spheres_cannot_take():
    # dt at 0.9 of the tets' critical step is stable for the continuum but above the bonded spheres' (about 0.6 of
    # it here: k_n = α E A / L on a sphere of ρ V): refused with the stable step named; 0.5 of it is accepted and
    # recorded as the model's critical step.
    pts, tets = box_mesh((0.0, 0.0, 0.0), (LENGTH, 1.0, 1.0), (8, 2, 2))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(pts, tets, "rock")
    model, state = b.finalize("cpu", safety_factor=0.9)
    with pytest.raises(ValueError, match="exceeds the stable step"):
        attach_conversion(model, state, [ConversionProps(tresca_strength=TRESCA)])
    model, state = b.finalize("cpu", safety_factor=0.5)
    model, _ = attach_conversion(model, state, [ConversionProps(tresca_strength=TRESCA)])
    assert model.dt < model.critical_dt and "bonded spheres" in model.critical_dt_source
    # dt = "auto" (the fraction it was built at given): the spheres' step joins the critical step and dt becomes that
    # fraction of the smaller, at 0.9 as at 0.5 (dt = s × min(tets' step, spheres' step), in float64 exactly).
    for safety in (0.9, 0.5):
        model, state = b.finalize("cpu", safety_factor=safety)
        tets_step = model.critical_dt
        model, _ = attach_conversion(model, state, [ConversionProps(tresca_strength=TRESCA)], safety_factor=safety)
        assert model.critical_dt < tets_step and "bonded spheres" in model.critical_dt_source
        assert model.dt == safety * model.critical_dt
    with pytest.raises(ValueError, match="safety_factor must be a number in"):
        attach_conversion(model, state, [ConversionProps(tresca_strength=TRESCA)], safety_factor=1.5)


CONTACT_RTOL = 16 * F32_EPS
"""Bound on the change of a node's contact force across a conversion pass beyond its mass share, relative to the
largest contact force [-]: k = ω² m is one float32 rounding from k₀ m/m₀ (the held ω² = k₀/m₀ is float64), and the
re-lumped masses are float32 sums of a handful of ρV/4 (MASS_RTOL)."""


def test_a_conversion_lowers_the_contact_springs_by_the_mass_that_left(device):
    # A block pressed δ into the ground; a pass converts two of its bottom tets. Every node keeps the stiffness per
    # unit mass it held, ω² = k₀/m₀ (kernels/fem_contact.py, "Held stiffness"), so its wall force becomes
    # F₀ m₁/m₀ (its contact acceleration unchanged, and k/m never above the stable step's) and the springs' energy
    # falls by exactly Σ ½ k₀ (1 − m₁/m₀) δ², which the pass books as contact gain: never a gain of ½ Δk δ² from the
    # faces the converted tets leave to their neighbours.
    depth = 1.0e-4
    pts, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 0.5), (2, 2, 1))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.add_tet_mesh(pts, tets, "rock")
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "rock")
    model, state = b.finalize(device, safety_factor=0.5)
    model, state = attach_conversion(model, state, [ConversionProps(criterion="tresca", tresca_strength=TRESCA)])
    set_node_displacements(model, state, np.tile([0.0, 0.0, -depth], (len(pts), 1)))
    sim = Simulation(model, state)
    n = sim.node_count
    k0 = sim.model.node_contact_stiffness.numpy()[:n].astype(np.float64)
    m0 = sim.model.node_mass.numpy()[:n].astype(np.float64)
    f0 = sim.state.node_f.numpy()[:n].astype(np.float64)
    gain0 = sim.energy().contact_topology
    centroid = pts[tets].mean(axis=1)
    mask = np.zeros(len(tets), dtype=bool)
    mask[np.argsort(centroid[:, 2] + 1e-3 * centroid[:, 0], kind="stable")[:2]] = True  # two of the lowest tets
    report = sim.convert_tets(mask)
    assert report.converted == 2
    m1 = sim.model.node_mass.numpy()[:n].astype(np.float64)
    k1 = sim.model.node_contact_stiffness.numpy()[:n].astype(np.float64)
    f1 = sim.state.node_f.numpy()[:n].astype(np.float64)
    pressed = pts[:, 2] == 0.0
    changed = m1 != m0
    assert np.any(pressed & changed & (m1 > 0.0)), "the pass must lighten nodes that press the ground"
    assert np.any(pressed & changed & (np.abs(k1 - k0) > 1e-3 * k0)), "and change their faces"
    # Wall forces (no strain, no velocity: node_f is the wall springs alone) scale with the mass share.
    share = np.divide(m1, m0, out=np.zeros(n), where=m0 > 0.0)
    scale = np.abs(f0).max()
    np.testing.assert_allclose(f1, f0 * share[:, None], rtol=0.0, atol=CONTACT_RTOL * scale)
    # The stiffness in use, as the host reads it, is the held k₀ m₁/m₀ (the lumped one of nodes that press nothing).
    in_use = contact_stiffness_in_use(sim.model, sim.state)
    np.testing.assert_allclose(in_use[pressed], (k0 * share)[pressed], rtol=CONTACT_RTOL)
    np.testing.assert_array_equal(in_use[~pressed], k1[~pressed])
    # ½ k δ² per pressed node (δ the float32 depth of its position, as the kernels take it).
    delta = -sim.state.node_q.numpy()[:n, 2].astype(np.float64)
    lost = np.sum(np.where(pressed, 0.5 * k0 * (1.0 - share) * delta**2, 0.0))
    stored = np.sum(np.where(pressed, 0.5 * k0 * delta**2, 0.0))
    gain = sim.energy().contact_topology - gain0
    np.testing.assert_allclose(gain, -lost, rtol=0.0, atol=CONTACT_RTOL * stored)
