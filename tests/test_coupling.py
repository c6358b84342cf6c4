"""Penalty coupling of spheres to material points in tets (kernels/coupling.py, warpdem/stages/coupling.py; CIMNE eqs.
8–9).

Oracles:
- forces against a float64 host evaluation of f = k g, g = Σ N_a x_a - x_p, and -N_a f on the nodes; Σ forces = 0
  and Σ (x - c) × F = 0 (the sphere's k g and the nodes' shares -N_a k g are a collinear pair along g);
- a rigid rotation and translation of the tet, the sphere carried to where its material point goes: no force
  (barycentric interpolation is affine);
- energy: a sphere coupled to a tet block, oscillating, run by the real integrator: kinetic − shadow + strain +
  ½ k|g|² + the bulk viscosity's take is constant (Verlet conserves it exactly for a quadratic potential, and the
  viscous work is booked as Verlet does it), held block or free, at dt and dt/2;
- compaction: the survivors are exactly the couplings whose tet is active, in their order; regrow copies the live
  slots; an evaluation at dt = 0 books nothing and applies the same forces as at dt > 0;
- the stiffness rule: k ≤ k_n and the coupling's two-body mode no faster than a bond's, ω_c² ≤ 2 k_n / m_s.

Tolerances. Forces: each node's share is a float32 product and the sums are float32 atomics, FORCE_ROUNDOFF ε₃₂ of
Σ |f|; the gap is formed from float32 displacements, so a rigid motion of size |u| leaves a gap of a few ε₃₂ |u|
(RIGID_ROUNDOFF). Energy: the coupled sphere's books close to rounding of the gap (float32 X_a - x_p at the tet's
size L: 8 ε₃₂ L / |g|), against a held block and a free one alike.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from warpdem.bench.overlap_band import launch_pulse  # the bar wave of the band benchmark: same bar, same launch
from warpdem.build.builder import InteractionProps, ModelBuilder
from warpdem.build.geology import Geology, RockMass, mesh_geology
from warpdem.build.mesh import box_mesh
from warpdem.model import COUPLING_FIELDS
from warpdem.simulation import Simulation
from warpdem.stages.compaction import Compactor
from warpdem.stages.conversion import ConversionProps, attach_conversion
from warpdem.stages.coupling import (
    compact_coupling,
    coupling_energy,
    coupling_stiffness,
    eval_coupling,
    material_point,
    regrow_coupling,
    set_couplings,
)
from warpdem.stages.tets import TetProps, tet_energies
from warpdem.tables import TET_FACES

YOUNG = 1.0e8  # [Pa]
POISSON = 0.25
DENSITY = 2000.0  # [kg/m³]
F32_EPS = float(np.finfo(np.float32).eps)
FORCE_ROUNDOFF = 16.0
RIGID_ROUNDOFF = 16.0
FLOOR_REFLECTED = 0.02  # measured 0.006 left behind, 0.99 through, in a bar without a band
# Energy fractions (wave_fractions), measured on the CPU; the bounds leave ~1.5× on what is reflected for the order
# of float32 atomics on a GPU and small changes of the network. A spring interface alone would reflect
# (ω Z / 2 κ)² ≈ 1 % here (warpdem/stages/coupling.py); the rest is the network's own impedance and dispersion.
FIRST_REFLECTED = 0.08  # measured 0.0545
BAND_REFLECTED = 0.11  # measured 0.077
BAND_TRANSMITTED = 0.88  # measured 0.914
CALIBRATION_RTOL = {"kuhn": 0.10, "gmsh": 0.10}
"""Tolerance on the fully converted bar's wave speed and strength against the continuum's [-]: the issue's 10 % on
either mesh. attach_conversion calibrates κ and S on the bar's own network (warpdem.stages.lattice, "Calibration on the
mesh"); measured, Kuhn cells 0.992 sqrt(E/ρ) and 0.987 T_f (four spheres per tet 0.978 and 1.010), Gmsh at h = 0.8 CELL
1.001 and 0.997 (before the calibration, with the Kuhn constants: 1.116 and 0.905)."""
WAVE_BOOKS_RTOL = 5.0e-3  # measured ≤ 2.6e-3 while the pulse is in the far dashpots, ~1e-4 otherwise


def block_with_spheres(
    device, n_spheres: int, divisions=(2, 2, 1), capacity: int = 8, offset=(0.0, 0.0, 0.0), held: bool = False
):
    """A box of tets [0, 1]² × [0, 0.5] (shifted by ``offset``; free, or every node ``held``) and ``n_spheres``
    small spheres well above it (no sphere–face contact), no gravity, ``capacity`` coupling slots."""
    o = np.asarray(offset, dtype=np.float64)
    points, tets = box_mesh(o, o + np.array([1.0, 1.0, 0.5]), divisions)
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.set_interaction("rock", "rock", InteractionProps(friction=0.0, restitution=1.0))
    b.add_tet_mesh(points, tets, "rock", fixed_nodes=np.arange(len(points)) if held else None)
    for s in range(n_spheres):
        b.add_sphere(o + np.array([0.2 + 0.6 * s / max(n_spheres - 1, 1), 0.5, 0.8]), 0.05, "rock")
    model, state = b.finalize(device, sort=False)
    return regrow_coupling(model, state, capacity)


def host_gap(model, state, particle, tet, bary) -> np.ndarray:
    """g = Σ N_a (X_a + u_a) - x_p in float64 [m], shape (K, 3)."""
    nodes = model.tet_nodes.numpy()[tet]
    x = model.node_ref_q.numpy().astype(np.float64) + state.node_u.numpy().astype(np.float64)
    xp = state.particle_q.numpy()[particle]
    return np.einsum("ka,kad->kd", bary.astype(np.float64), x[nodes]) - xp


def clear_forces(state) -> None:
    state.particle_f.zero_()
    state.node_f.zero_()


# ----------------------------------------------------------------------------------------------------------------
# Forces


def test_forces_match_host_and_balance(device):
    rng = np.random.default_rng(3)
    model, state = block_with_spheres(device, 3)
    nn = int(state.node_count.numpy()[0])
    state.node_u.assign(rng.normal(0.0, 0.01, (model.node_capacity, 3)).astype(np.float32))
    particle = np.array([0, 1, 2, 0])
    tet = np.array([0, 3, 7, 5])
    # N_a summing to 1, one coupling with a material point outside its tet (a negative weight).
    bary = rng.uniform(0.0, 1.0, (4, 4))
    bary[3] = (1.2, 0.4, -0.3, 0.1)
    bary /= bary.sum(axis=1, keepdims=True)
    k = np.array([1.0e6, 3.0e6, 2.0e6, 5.0e5])
    set_couplings(model, state, particle, tet, bary, k)
    clear_forces(state)
    eval_coupling(model, state)
    g = host_gap(model, state, particle, tet, bary.astype(np.float32))
    f = k[:, None] * g
    # Sphere forces: f = k g, summed per sphere (sphere 0 has two couplings).
    expect_p = np.zeros((3, 3))
    np.add.at(expect_p, particle, f)
    fp = state.particle_f.numpy()[:3].astype(np.float64)
    fn = state.node_f.numpy()[:nn].astype(np.float64)
    scale = float(np.abs(f).sum())
    np.testing.assert_allclose(fp, expect_p, rtol=0, atol=FORCE_ROUNDOFF * F32_EPS * scale)
    # Node forces: -N_a f on node a.
    expect_n = np.zeros((nn, 3))
    nodes = model.tet_nodes.numpy()[tet]
    np.add.at(expect_n, nodes.ravel(), (-bary.astype(np.float32)[:, :, None] * f[:, None, :]).reshape(-1, 3))
    np.testing.assert_allclose(fn, expect_n, rtol=0, atol=FORCE_ROUNDOFF * F32_EPS * scale)
    # Σ F = 0 and Σ (x - c) × F = 0 about the block's centre: each coupling's forces are collinear along g.
    xn = model.node_ref_q.numpy()[:nn].astype(np.float64) + state.node_u.numpy()[:nn].astype(np.float64)
    xp = state.particle_q.numpy()[:3]
    c = xn.mean(axis=0)
    net = fp.sum(axis=0) + fn.sum(axis=0)
    moment = np.cross(xp - c, fp).sum(axis=0) + np.cross(xn - c, fn).sum(axis=0)
    arm = float(np.abs(np.concatenate([xp, xn]) - c).max())
    np.testing.assert_allclose(net, 0.0, atol=FORCE_ROUNDOFF * F32_EPS * scale)
    np.testing.assert_allclose(moment, 0.0, atol=FORCE_ROUNDOFF * F32_EPS * scale * arm)
    assert scale > 1.0e3  # the springs are stretched: the balance is not 0 = 0
    # The recorded spring energies are ½ k |g|², and coupling_energy sums them.
    u = 0.5 * k * np.sum(g * g, axis=1)
    np.testing.assert_allclose(state.coupling_energy_prev.numpy()[:4], u, rtol=1.0e-5)
    np.testing.assert_allclose(coupling_energy(model, state), u.sum(), rtol=1.0e-5)


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (2000.0, -1500.0, 300.0)], ids=["origin", "far"])
def test_rigid_motion_gives_no_force(device, offset):
    model, state = block_with_spheres(device, 2, offset=offset)
    nn = int(state.node_count.numpy()[0])
    x_ref = model.node_ref_q.numpy()[:nn].astype(np.float64)
    tet = np.array([2, 9])
    # Material points in the reference configuration: one inside its tet, one 0.3 m beyond it.
    centre = x_ref[model.tet_nodes.numpy()[tet]].mean(axis=1)
    points = centre + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3]])
    bary = material_point(model, tet, points)
    np.testing.assert_allclose(bary.sum(axis=1), 1.0, atol=4 * F32_EPS)
    assert bary[1].min() < 0.0  # the second lies outside: extrapolation is part of the test
    # Rotate by 40° about a tilted axis through the block's centre and translate; carry the spheres along.
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    a = np.radians(40.0)
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx
    c = x_ref.mean(axis=0)
    shift = np.array([0.7, -0.4, 0.25])
    moved = (x_ref - c) @ rot.T + c + shift
    u = np.zeros((model.node_capacity, 3), dtype=np.float32)
    u[:nn] = moved - x_ref
    state.node_u.assign(u)
    q = state.particle_q.numpy()
    q[:2] = (points - c) @ rot.T + c + shift
    state.particle_q.assign(q)
    k = 1.0e6
    set_couplings(model, state, [0, 1], tet, bary, [k, k])
    clear_forces(state)
    eval_coupling(model, state)
    # |g| ≤ a few ε₃₂ of |u| (the float32 displacements) and of |X - x_p| (rounded once), plus the float32 N_a.
    size = float(np.abs(u).max()) + 1.0
    np.testing.assert_allclose(state.particle_f.numpy()[:2], 0.0, atol=RIGID_ROUNDOFF * F32_EPS * k * size)
    np.testing.assert_allclose(state.node_f.numpy()[:nn], 0.0, atol=RIGID_ROUNDOFF * F32_EPS * k * size)


def test_material_point_of_current_position_has_no_gap(device):
    rng = np.random.default_rng(5)
    model, state = block_with_spheres(device, 1)
    state.node_u.assign(rng.normal(0.0, 0.02, (model.node_capacity, 3)).astype(np.float32))
    tets = np.array([0, 4, 6])
    nn = int(state.node_count.numpy()[0])
    xn = model.node_ref_q.numpy()[:nn].astype(np.float64) + state.node_u.numpy()[:nn].astype(np.float64)
    pts = xn[model.tet_nodes.numpy()[tets]].mean(axis=1) + rng.normal(0.0, 0.1, (3, 3))
    bary = material_point(model, tets, pts, state)
    back = np.einsum("ka,kad->kd", bary.astype(np.float64), xn[model.tet_nodes.numpy()[tets]])
    np.testing.assert_allclose(back, pts, atol=8 * F32_EPS)  # rounded once at the scale of the tet (1 m)


# ----------------------------------------------------------------------------------------------------------------
# Energy


def oscillator_drift(device, dt_factor: float, held: bool = False, gap: float = 0.004) -> tuple[float, float]:
    """A sphere coupled to a material point 0.3 m above a tet block (free or ``held``), released with a gap and a
    velocity, run for a fixed time; ``gap`` scales the release gap [m]. Returns (largest |Δ total| / in play, periods
    of the coupling run)."""
    model, state = block_with_spheres(device, 1, divisions=(1, 1, 1), held=held)
    model = dataclasses.replace(model, dt=model.dt * dt_factor)
    tet = 0
    nn = int(state.node_count.numpy()[0])
    x_ref = model.node_ref_q.numpy()[:nn].astype(np.float64)
    point = x_ref[model.tet_nodes.numpy()[tet]].mean(axis=0) + np.array([0.1, 0.0, 0.3])
    bary = material_point(model, tet, point)
    m_s = float(model.particle_mass.numpy()[0])
    node_mass = model.node_mass.numpy()[model.tet_nodes.numpy()[tet]]
    k = coupling_stiffness(m_s, 5.0e6, node_mass, bary)
    q = state.particle_q.numpy()
    q[0] = point + gap * np.array([0.5, -0.25, 0.75])  # released with a gap
    state.particle_q.assign(q)
    state.particle_qd.assign(np.array([[0.05, 0.1, -0.02]], dtype=np.float32))
    set_couplings(model, state, [0], [tet], bary[None], [k])
    sim = Simulation(model, state, use_graph=False)  # the step evaluates the couplings

    def total() -> tuple[float, float]:
        e = sim.energy()  # coupling_elastic is a line of the books (in total and in_play)
        return e.total, e.in_play

    t0, in_play = total()
    worst = 0.0
    period = 2 * np.pi / np.sqrt(k / m_s)
    n_steps = round(3.0 * period / model.dt)
    chunk = -(-n_steps // 30)
    for _ in range(30):
        sim.advance(chunk)
        t, p = total()
        in_play = max(in_play, p)
        worst = max(worst, abs(t - t0))
    return worst / in_play, chunk * 30 * model.dt / period


def test_books_close_for_coupled_oscillator(device):
    # Verlet + shadow term conserve Σ ½ m v_{n-1/2}·v_{n+1/2} + U exactly for a quadratic U
    # (warpdem/stages/coupling.py): against a held block the coupled sphere is a linear oscillator and the books close
    # to rounding. Rounding: the gap is formed from X_a - x_p rounded to float32 at the tet's size L (~1 m), an error of
    # a few ε₃₂ L in g, so ½ k|g|² is resolved to ~2 · 4 ε₃₂ L / |g| of itself.
    gap = 0.04
    exact, periods = oscillator_drift(device, 1.0, held=True, gap=gap)
    assert periods >= 2.9
    assert exact < 8.0 * F32_EPS * 1.0 / gap
    # A free block (the default bulk viscosity in its tet): the same rounding bound at its own gap, at dt and dt/2.
    # The viscous work is booked as Verlet's trapezoid does it; booked for a whole step at v_{n+1/2} it left an
    # error shrinking with dt, 4.9e-4 at dt and 1.2e-4 at dt/2 (measured), over this bound.
    free_gap = 0.004
    coarse, _ = oscillator_drift(device, 1.0, gap=free_gap)
    fine, _ = oscillator_drift(device, 0.5, gap=free_gap)
    print(f"books: held {exact:.2e}, free {coarse:.2e} at dt, {fine:.2e} at dt/2")
    assert max(coarse, fine) < 8.0 * F32_EPS * 1.0 / free_gap


def test_dt_zero_books_nothing(device):
    model, state = block_with_spheres(device, 2)
    rng = np.random.default_rng(11)
    state.node_u.assign(rng.normal(0.0, 0.01, (model.node_capacity, 3)).astype(np.float32))
    set_couplings(model, state, [0, 1], [1, 4], np.full((2, 4), 0.25), [1.0e6, 2.0e6])
    lines = ("energy_damping", "energy_friction", "energy_boundary_work", "node_energy_damping")
    before = {name: getattr(state, name).numpy().copy() for name in lines}
    forces = []
    for dt in (0.0, model.dt):
        clear_forces(state)
        eval_coupling(model, state, dt=dt)
        forces.append((state.particle_f.numpy().copy(), state.node_f.numpy().copy()))
        for name in lines:
            np.testing.assert_array_equal(getattr(state, name).numpy(), before[name])
    np.testing.assert_array_equal(forces[0][0], forces[1][0])
    np.testing.assert_array_equal(forces[0][1], forces[1][1])
    assert np.abs(forces[0][0]).max() > 0.0


# ----------------------------------------------------------------------------------------------------------------
# Compaction and capacity


def test_compaction_keeps_couplings_of_active_tets(device):
    rng = np.random.default_rng(7)
    model, state = block_with_spheres(device, 3, capacity=16)
    n_tets = int(state.tet_count.numpy()[0])
    count = 13
    particle = rng.integers(0, 3, count)
    tet = rng.integers(0, 6, count)  # several couplings per tet, so a conversion releases some of them
    bary = rng.dirichlet(np.ones(4), count)
    k = rng.uniform(1.0e5, 1.0e6, count)
    set_couplings(model, state, particle, tet, bary, k)
    active = state.tet_active.numpy()
    converted = [1, 4, n_tets - 1]
    active[converted] = 0
    state.tet_active.assign(active)
    # A coupling whose tet converted applies no force and holds no energy before it is removed.
    keep = active[tet] != 0
    clear_forces(state)
    eval_coupling(model, state)
    f_before = state.particle_f.numpy().copy()
    e_before = coupling_energy(model, state)
    live = compact_coupling(model, state, Compactor(model.coupling_capacity, model.device))
    assert live == int(keep.sum()) and 0 < live < count
    np.testing.assert_array_equal(state.coupling_particle.numpy()[:live], particle[keep])
    np.testing.assert_array_equal(state.coupling_tet.numpy()[:live], tet[keep])
    np.testing.assert_array_equal(state.coupling_bary.numpy()[:live], bary[keep].astype(np.float32))
    np.testing.assert_array_equal(state.coupling_k.numpy()[:live], k[keep].astype(np.float32))
    clear_forces(state)
    eval_coupling(model, state)
    np.testing.assert_array_equal(state.particle_f.numpy(), f_before)
    assert coupling_energy(model, state) == e_before
    # Slots past the count are zero (a bitwise restart sees no leftovers).
    for name in COUPLING_FIELDS:
        assert not np.any(getattr(state, name).numpy()[live:])


def test_regrow_copies_live_couplings(device):
    model, state = block_with_spheres(device, 2, capacity=2)
    set_couplings(model, state, [0, 1], [3, 5], np.full((2, 4), 0.25), [1.0e6, 2.0e6])
    grown_model, grown = regrow_coupling(model, state, 8)
    assert grown_model.coupling_capacity == 8 and model.coupling_capacity == 2
    for name in COUPLING_FIELDS:
        old, new = getattr(state, name).numpy(), getattr(grown, name).numpy()
        assert new.shape[0] == 8
        np.testing.assert_array_equal(new[:2], old[:2])
        assert not np.any(new[2:])
    clear_forces(state)
    eval_coupling(model, state)
    f = state.particle_f.numpy().copy()
    clear_forces(grown)
    eval_coupling(grown_model, grown)
    np.testing.assert_array_equal(grown.particle_f.numpy(), f)
    with pytest.raises(ValueError, match="below the 2 live"):
        regrow_coupling(model, state, 1)
    with pytest.raises(ValueError, match="couplings for 2 slots"):
        set_couplings(model, state, [0, 1, 1], [0, 1, 2], np.full((3, 4), 0.25), [1.0, 1.0, 1.0])


# ----------------------------------------------------------------------------------------------------------------
# Stiffness rule


def test_stiffness_rule_bounds():
    rng = np.random.default_rng(13)
    m_s = rng.uniform(0.1, 10.0, 200)
    kn = rng.uniform(1.0e5, 1.0e8, 200)
    node_mass = rng.uniform(0.01, 20.0, (200, 4))
    bary = rng.dirichlet(np.ones(4), 200) * 1.4 - 0.1  # some outside the tet (Σ = 1.0)
    k = coupling_stiffness(m_s, kn, node_mass, bary)
    omega_c2 = k * (1.0 / m_s + np.sum(bary**2 / node_mass, axis=1))
    assert np.all(k <= kn * (1 + 1e-12))
    assert np.all(omega_c2 <= 2.0 * kn / m_s * (1 + 1e-12))
    # Heavy nodes (intact continuum around): the cap is the bond stiffness itself.
    assert coupling_stiffness(1.0, 1.0e6, np.full(4, 10.0), np.full(4, 0.25)) == 1.0e6
    with pytest.raises(ValueError, match="positive"):
        coupling_stiffness(0.0, 1.0e6, np.full(4, 1.0), np.full(4, 0.25))


# ----------------------------------------------------------------------------------------------------------------
# Waves through a converted band (ISSUE §3) and the fully converted bar (§2)

BAR_E = 1.0e9  # [Pa]
BAR_NU = 0.25
BAR_TF = 1.0e6  # [Pa]
CELL = 0.05  # [m], cubic cells, 2 × 2 across
BAR_WAVE = float(np.sqrt(BAR_E / DENSITY))  # sqrt(E/ρ) [m/s]


GMSH_H = 0.8 * CELL
"""Target edge of the unstructured (Gmsh) bar [m]: 2.5 tets across, as the Kuhn bar's 2 cells (at h = CELL Gmsh
meshes the box with the nodes of its edge subdivision alone, a near-structured mesh)."""


def bar(
    device,
    cells: int,
    band: tuple[int, int] | None,
    far_dashpots: bool = False,
    spheres_per_tet: int = 1,
    mesh: str = "kuhn",
):
    """A bar ``cells`` × CELL long and 2 CELL × 2 CELL across, no bulk viscosity: Kuhn tets of cubic cells, or with
    ``mesh`` "gmsh" an unstructured Delaunay mesh of edge GMSH_H (warpdem.build.geology.mesh_geology); the tets whose
    centroid lies in band[0] < x / CELL < band[1] converted (Simulation.convert_tets) into ``spheres_per_tet`` spheres
    each; non-reflecting dashpots on the far end if asked. Returns (sim, points, tets)."""
    size = (cells * CELL, 2 * CELL, 2 * CELL)
    if mesh == "gmsh":
        unstructured = mesh_geology(Geology(RockMass((0.0, 0.0, 0.0), size), h=GMSH_H))
        points, tets = unstructured.points, unstructured.tets
    else:
        points, tets = box_mesh((0.0, 0.0, 0.0), size, (cells, 2, 2))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, BAR_E, BAR_NU)
    b.set_tet_properties("rock", TetProps(bulk_viscosity_linear=0.0, bulk_viscosity_quadratic=0.0))
    b.set_interaction("rock", "rock", InteractionProps(friction=0.0, restitution=1.0))
    b.add_tet_mesh(points, tets, "rock")
    if far_dashpots:
        faces = tets[:, TET_FACES].reshape(-1, 3)
        far = np.all(np.isclose(points[faces][:, :, 0], cells * CELL), axis=1)
        b.add_boundary(np.unique(np.sort(faces[far], axis=1), axis=0), "non_reflecting")
    model, state = b.finalize(device, sort=False)
    props = ConversionProps(criterion="rankine", tensile_strength=BAR_TF, fraction=1.0)
    model, state = attach_conversion(  # no stress-driven pass
        model, state, [props], check_interval=10**9, spheres_per_tet=spheres_per_tet
    )
    sim = Simulation(model, state, use_graph=False)
    if band is not None:
        x = points[tets].mean(axis=1)[:, 0] / CELL
        mask = (x > band[0]) & (x < band[1])
        sim.convert_tets(mask)  # spheres, the edge-bond network (warpdem.stages.lattice) and the couplings
    return sim, points, tets

    sim.evaluate_forces()


def region_energies(sim: Simulation, points: np.ndarray, tets: np.ndarray, x1: float, x2: float) -> tuple:
    """Energy [J] of the tets (and their nodes) left of x1, and right of x2 plus what the far dashpots absorbed."""
    m, s = sim.model, sim.state
    nn = int(s.node_count.numpy()[0])
    x = m.node_ref_q.numpy()[:nn, 0]
    v = s.node_qd.numpy()[:nn].astype(np.float64)
    kinetic = 0.5 * m.node_mass.numpy()[:nn] * np.sum(v * v, axis=1)
    strain = tet_energies(m, s).numpy()[: len(tets)]
    centre = points[tets].mean(axis=1)[:, 0]
    tol = 1e-6 * x2
    left = kinetic[x <= x1 + tol].sum() + strain[centre < x1].sum()
    right = kinetic[x >= x2 - tol].sum() + strain[centre > x2].sum()
    return float(left), float(right + s.node_energy_absorbed.numpy()[:nn].sum())


def wave_fractions(device, band: tuple[int, int] | None) -> tuple[float, float, float, float]:
    """A bar pulse 12 cells wide launched in the first 20 cells of a 40-cell bar (front at x = 0.7 m, tail at
    0.1 m) towards a band of converted cells 20..28 (x1 = 1 m, x2 = 1.4 m) or none, non-reflecting far end.
    Timeline at c = 707 m/s: the front meets x1 at 0.42 ms and x2 at 0.99 ms, the tail passes x1 at 1.27 ms, what
    x2 reflects is back at x1 from 1.56 ms, what x1 reflects returns from the free near end to x1 at 3.7 ms.
    Returns, as fractions of the launched energy: what is left of the band at 1.45 ms (the first interface's
    reflection), at 3.0 ms (the band's whole reflection), right of it + absorbed at 3.0 ms (transmitted), and
    the largest |Δ books| / in play at the two times."""
    sim, points, tets = bar(device, 40, band, far_dashpots=True)
    x1, x2 = 20 * CELL, 28 * CELL
    launch_pulse(sim, centre=8 * CELL, width=12 * CELL, amplitude=1.0e-5)
    e0 = sim.energy()
    incident, _ = region_energies(sim, points, tets, x1, x2)
    sim.advance(round(1.45e-3 / sim.model.dt))
    first, _ = region_energies(sim, points, tets, x1, x2)
    books = abs(sim.energy().total - e0.total) / e0.in_play
    sim.advance(round(1.55e-3 / sim.model.dt))
    left, right = region_energies(sim, points, tets, x1, x2)
    books = max(books, abs(sim.energy().total - e0.total) / e0.in_play)
    return first / incident, left / incident, right / incident, books


def test_plane_wave_crosses_converted_band(device):
    # Oracle 1: the same bar without a band: the launch (a right-going bar wave with its Poisson contraction) leaves
    # only what the tets' dispersion and the far dashpots' mismatch (c_p vs the bar speed) send back: the floor.
    _, floor_left, floor_right, _ = wave_fractions(device, None)
    assert floor_left < FLOOR_REFLECTED and floor_right > 1.0 - FLOOR_REFLECTED
    # The band: tets → bonded spheres (the edge network) → tets, each sphere tied to every active tet sharing an edge
    # with its tet, by the stiffness rule (what Simulation.convert_tets makes).
    first, reflected, transmitted, books = wave_fractions(device, (20, 28))
    print(
        f"wave: floor {floor_left:.4f} / {floor_right:.4f}; first interface {first:.4f}, band reflected "
        f"{reflected:.4f}, transmitted {transmitted:.4f}, books {books:.1e}"
    )
    assert first < FIRST_REFLECTED
    assert reflected < BAND_REFLECTED
    assert transmitted > BAND_TRANSMITTED
    # Oracle 2: the books close (no damping anywhere; the far dashpots' take is a line of them).
    assert books < WAVE_BOOKS_RTOL


@pytest.mark.parametrize(("spheres_per_tet", "mesh"), [(1, "kuhn"), (4, "kuhn"), (1, "gmsh")])
def test_converted_bar_wave_speed(device, spheres_per_tet, mesh):
    # A fully converted bar (one sphere per tet, or four: warpdem.stages.multisphere), 12 cells long, free at both ends,
    # set moving in its lowest longitudinal mode
    # v = v0 cos(π x / L): the left half's momentum swings as cos(ω t), ω = π c / L, c = sqrt(E/ρ) for a bar whose
    # wavelength (2 L = 24 cells) is long against its width. Zero crossings of that momentum give the half period.
    sim, _, _ = bar(device, 12, (0, 12), spheres_per_tet=spheres_per_tet, mesh=mesh)
    m, s = sim.model, sim.state
    n = sim.particle_count
    length = 12 * CELL
    x = s.particle_q.numpy()[:n, 0].copy()
    v = np.zeros((m.particle_capacity, 3), dtype=np.float32)
    v[:n, 0] = 0.01 * np.cos(np.pi * x / length)
    s.particle_qd.assign(v)
    sim.evaluate_forces()
    mass = m.particle_mass.numpy()[:n].astype(np.float64)
    left = x < 0.5 * length
    times, momenta = [], []
    chunk = 4
    for _ in range(round(2.2 * 2.0 * length / BAR_WAVE / (chunk * m.dt))):
        sim.advance(chunk)
        times.append(sim.time)
        momenta.append(float(np.sum(mass[left] * sim.state.particle_qd.numpy()[:n, 0][left])))
    t, p = np.array(times), np.array(momenta)
    k = np.nonzero(p[:-1] * p[1:] < 0.0)[0]
    crossings = t[k] - p[k] * (t[k + 1] - t[k]) / (p[k + 1] - p[k])
    assert len(crossings) >= 3
    speed = 2.0 * length / (2.0 * np.mean(np.diff(crossings)))
    print(
        f"converted {mesh} bar ({spheres_per_tet} per tet): c = {speed:.1f} m/s, sqrt(E/rho) = {BAR_WAVE:.1f} m/s, "
        f"ratio {speed / BAR_WAVE:.4f}"
    )
    # The zero crossings are interpolated within a chunk of 4 steps (< 1 % of the half period).
    np.testing.assert_allclose(speed, BAR_WAVE, rtol=CALIBRATION_RTOL[mesh])


@pytest.mark.parametrize(("spheres_per_tet", "mesh"), [(1, "kuhn"), (4, "kuhn"), (1, "gmsh")])
def test_converted_bar_tensile_strength(device, spheres_per_tet, mesh):
    # The same bar pulled apart: the first cell's spheres held, the last cell's driven along +x at a speed ramped up
    # over 3 transits L / c (so the stress wave of the start, ρ c v, stays a few % of T_f) to ε_f L / (10 L / c),
    # failure in ~10 transits: close to quasi-static. Nominal stress = the pull on the driven spheres / the
    # cross-section; the strength, against T_f, is the largest before the first bond breaks (sampled every 20 steps,
    # ~1 % of the load's growth). After it the bar is failing: with one sphere per tet the load drops at once; the
    # four-sphere network still carries load through its other bonds while the energy each break releases rings
    # through the undamped bar, so later samples swing dynamically (measured up to 1.25 T_f within 0.15 transits,
    # far faster than the load grows) before the bar parts. The run goes on until it has parted (< 0.2 of the peak).
    sim, _, _ = bar(device, 12, (0, 12), spheres_per_tet=spheres_per_tet, mesh=mesh)
    m, s = sim.model, sim.state
    n = sim.particle_count
    length = 12 * CELL
    x = s.particle_q.numpy()[:n, 0].copy()
    held, pulled = x < CELL, x > length - CELL
    motion = m.particle_motion.numpy()
    motion[:n][held] = 1
    motion[:n][pulled] = 2
    m.particle_motion.assign(motion)
    transit = length / BAR_WAVE
    speed = BAR_TF / BAR_E * length / (10.0 * transit)
    area = (2 * CELL) ** 2
    peak, strength, chunk = 0.0, 0.0, 20
    while True:
        ramp = min(sim.time / (3.0 * transit), 1.0)
        v = sim.state.particle_qd.numpy()
        v[:n][pulled] = (speed * ramp, 0.0, 0.0)
        sim.state.particle_qd.assign(v)
        sim.advance(chunk)
        stress = -float(sim.state.particle_f.numpy()[:n][pulled, 0].sum()) / area
        peak = max(peak, stress)
        broken = int(sim.state.bonds_broken_total.numpy()[0])
        if not broken:
            strength = stress
        if (broken and stress < 0.2 * peak) or sim.time > 30.0 * transit:
            break
    print(
        f"converted {mesh} bar ({spheres_per_tet} per tet): strength {strength:.4e} Pa = {strength / BAR_TF:.4f} T_f "
        f"(peak {peak / BAR_TF:.4f} T_f), {broken} bonds broken"
    )
    assert broken > 0 and stress < 0.2 * peak  # it parted
    np.testing.assert_allclose(strength, BAR_TF, rtol=CALIBRATION_RTOL[mesh])
