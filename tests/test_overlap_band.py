"""The blended DEM/FEM overlap band (warpdem/stages/overlap_band.py; CIMNE eqs. 8–9) against the tie.

Oracles:
- mass: every converted tet's ρ V₀ is split α to its FEM element's nodes, 1 − α to its sphere, so Σ node masses +
  Σ sphere masses is the built mass, and each sphere holds (1 − α) ρ V₀ with α = 1 − d / (w + 1) by layer;
- patch test: a rigid translation of the bar with its band gives no force (the tets see no gradient, the bonds no
  stretch, the couplings no gap); under a uniform strain the band's penalty springs carry nothing (eq. 9's
  constraint is exact for an affine field: barycentric interpolation reproduces it) and the forces sum to zero;
- linear momentum: conserved through a band pass (mass moves with its velocity) and a free run;
- energy: the books close across the band's passes (start_as_spheres, then an adaptive pass that moves the band) and
  over a run of a pulse through it;
- the default: the scene's [conversion] coupling is 'band', and the band reflects less than the tie on the bar of
  warpdem.bench.overlap_band (the comparison that chose it, benchmarks/results/overlap_band.json).

Tolerances. Masses are float32: sums of N of them agree to N ε₃₂ of the total. Forces under a translation d: the
coupling gap is formed from float32 displacements (|d| ε₃₂ each, kernels/coupling.py) and sphere centres are
float64, so |f| ≤ ε₃₂ k |d| per spring, 4 ε₃₂ k |d| for the few springs of an item. Momentum: each step's kick
rounds each float32 velocity to ε₃₂, so |ΔP| ≤ steps ε₃₂ Σ m |v|. Books across a pass: float64 sums of float32
stores (masses and velocities rounded to ε₃₂ once), 16 ε₃₂ of the energy in play; over a run, Verlet's error of the
non-quadratic tets plus the float32 rounding of the band's springs, measured ≤ 1.5e-5 of in play on the benchmark
bar (BOOKS_RUN).
"""

from __future__ import annotations

import numpy as np
import pydantic
import pytest

from warpdem.bench import overlap_band as bench
from warpdem.scene.failure import Conversion
from warpdem.stages.coupling import eval_coupling
from warpdem.stages.overlap_band import tet_alpha

F32_EPS = float(np.finfo(np.float32).eps)
WIDTH = 2
CELLS = 24
BOOKS_PASS = 16.0 * F32_EPS
BOOKS_RUN = 1.0e-4  # measured 1.5e-5 on the 60-cell benchmark bar (490 steps)


def band_bar(device, cells: int = CELLS, spheres_from: float = 12.0, width: int = WIDTH):
    return bench.build_bar(device, cells, spheres_from, band_width=width)


def total_mass(sim) -> float:
    m = sim.model
    return float(
        m.node_mass.numpy()[: sim.node_count].astype(np.float64).sum()
        + m.particle_mass.numpy()[: sim.particle_count].astype(np.float64).sum()
    )


def momentum(sim) -> tuple[np.ndarray, float]:
    """Linear momentum [kg m/s] and Σ m |v| [kg m/s] of nodes and spheres."""
    m, s = sim.model, sim.state
    nn, n = sim.node_count, sim.particle_count
    mv = np.concatenate(
        [
            m.node_mass.numpy()[:nn, None].astype(np.float64) * s.node_qd.numpy()[:nn],
            m.particle_mass.numpy()[:n, None].astype(np.float64) * s.particle_qd.numpy()[:n],
        ]
    )
    return mv.sum(axis=0), float(np.linalg.norm(mv, axis=1).sum())


def test_mass_is_split_by_alpha(device):
    # Σ α m_F + (1 − α) m_D = ρ V₀ per tet, so the total is the built bar's.
    built = bench.build_bar(device, CELLS, None)[0]
    sim, _, tets = band_bar(device)
    np.testing.assert_allclose(total_mass(sim), total_mass(built), rtol=4 * len(tets) * F32_EPS)
    m, s = sim.model, sim.state
    alpha = tet_alpha(m, s)
    sphere = s.tet_sphere.numpy()[: len(tets)]
    converted = sphere >= 0
    full = bench.DENSITY * m.tet_volume.numpy()[: len(tets)].astype(np.float64)
    np.testing.assert_allclose(
        m.particle_mass.numpy()[sphere[converted]], (1.0 - alpha[converted]) * full[converted], rtol=4 * F32_EPS
    )
    # α takes the band's w + 1 steps: 1 on the continuum, (w + 1 − d)/(w + 1) on layer d, 0 beyond.
    levels = np.unique(np.round(alpha[converted] * (WIDTH + 1), 4))
    np.testing.assert_array_equal(levels, np.arange(WIDTH + 1))
    assert np.all(alpha[~converted] == 1.0)
    # Every band sphere is tied to its own tet, and only those.
    n = int(s.coupling_count.numpy()[0])
    band = np.flatnonzero(converted & (alpha > 0.0))
    assert n == len(band)
    np.testing.assert_array_equal(np.sort(s.coupling_tet.numpy()[:n]), band)
    np.testing.assert_array_equal(s.coupling_particle.numpy()[:n], sphere[s.coupling_tet.numpy()[:n]])


def _forces(sim) -> tuple[np.ndarray, np.ndarray]:
    sim.evaluate_forces()
    return sim.state.node_f.numpy()[: sim.node_count], sim.state.particle_f.numpy()[: sim.particle_count]


def test_translation_gives_no_force(device):
    sim, _, _ = band_bar(device)
    s = sim.state
    shift = np.array([0.3, -0.2, 0.1])
    s.node_u.assign(s.node_u.numpy() + shift.astype(np.float32))
    s.node_q.assign(s.node_q.numpy() + shift.astype(np.float32))
    n = sim.particle_count
    q = s.particle_q.numpy()
    q[:n] += shift
    s.particle_q.assign(q)
    node_f, particle_f = _forces(sim)
    k = max(float(s.coupling_k.numpy().max()), float(s.bond_kn.numpy().max()))
    # u is float32: |d| ε₃₂ / 2 per component, k times that per spring, a few springs per item (measured 0.87 N, where
    # a force that did not follow the translation would be k |d| = 8e7 N).
    tol = 4.0 * F32_EPS * k * np.linalg.norm(shift)
    assert np.abs(node_f).max() <= tol
    assert np.abs(particle_f).max() <= tol


def test_uniform_strain_leaves_the_penalty_idle(device):
    # u = ε x e_x on nodes and sphere centres: the material point Σ N_a x_a of each sphere is where the affine map
    # takes it, so every coupling's gap is zero (eq. 9 holds exactly) and the penalty springs apply nothing.
    sim, _, _ = band_bar(device)
    m, s = sim.model, sim.state
    eps = 1.0e-4
    nn, n = sim.node_count, sim.particle_count
    x = m.node_ref_q.numpy()[:nn].astype(np.float64)
    u = np.zeros((m.node_capacity, 3), dtype=np.float32)
    u[:nn, 0] = eps * x[:, 0]
    s.node_u.assign(u)
    s.node_q.assign(m.node_ref_q.numpy() + u)
    q = s.particle_q.numpy()
    q[:n, 0] *= 1.0 + eps
    s.particle_q.assign(q)
    s.particle_f.zero_()
    s.node_f.zero_()
    eval_coupling(m, s)
    # The gap is Σ N_a (X_a - x_p + u_a) with X_a - x_p rounded to float32 (kernels/coupling.py): a few ε₃₂ of the
    # tet's size h = sqrt(3) CELL per term, against the ε h = 9e-6 m a constraint that missed the affine field would
    # leave.
    k = float(s.coupling_k.numpy().max())
    tol = 4.0 * F32_EPS * np.sqrt(3.0) * bench.CELL * k
    assert np.abs(s.particle_f.numpy()[:n]).max() <= tol
    assert np.abs(s.node_f.numpy()[:nn]).max() <= tol
    # All the forces (tets weighted by α, bonds by 1 − ᾱ, couplings) are pairs or element-internal: they sum to zero.
    node_f, particle_f = _forces(sim)
    scale = np.abs(node_f).sum() + np.abs(particle_f).sum()
    np.testing.assert_allclose(node_f.sum(axis=0) + particle_f.sum(axis=0), 0.0, atol=8 * F32_EPS * scale)


def test_adaptive_pass_moves_the_band_and_conserves(device):
    # A pulse in flight, then a pass converts more tets (as an adaptive pass would): the old band deepens, its α falls,
    # its deepest tets drop; mass, momentum and the books hold across it.
    sim, points, tets = band_bar(device)
    bench.launch_pulse(sim, 4 * bench.CELL, 6 * bench.CELL, bench.AMPLITUDE)
    sim.advance(40)
    mass0 = total_mass(sim)
    p0, scale = momentum(sim)
    e0 = sim.energy()
    alpha0 = tet_alpha(sim.model, sim.state)
    x = points[tets].mean(axis=1)[:, 0] / bench.CELL
    report = sim.convert_tets((x > 9.0) & (x <= 12.0))
    assert report.converted > 0
    alpha1 = tet_alpha(sim.model, sim.state)
    assert np.all(alpha1 <= alpha0 + 1e-6)  # α only falls
    assert np.any((alpha0 > 0.0) & (alpha0 < 1.0) & (alpha1 == 0.0))  # the old band's deep layer dropped
    np.testing.assert_allclose(total_mass(sim), mass0, rtol=4 * len(tets) * F32_EPS)
    p1, _ = momentum(sim)
    np.testing.assert_allclose(p1, p0, atol=4 * F32_EPS * scale)
    e1 = sim.energy()
    assert abs(e1.total - e0.total) <= BOOKS_PASS * e0.in_play


def test_free_run_conserves_momentum_and_closes_books(device):
    sim, _, _ = band_bar(device)
    bench.launch_pulse(sim, 5 * bench.CELL, 8 * bench.CELL, bench.AMPLITUDE)
    p0, scale = momentum(sim)
    e0 = sim.energy()
    steps = 200
    sim.advance(steps)
    p1, _ = momentum(sim)
    np.testing.assert_allclose(p1, p0, atol=steps * F32_EPS * scale)
    e1 = sim.energy()
    assert abs(e1.total - e0.total) <= BOOKS_RUN * max(e0.in_play, e1.in_play)


def test_schema_band_options():
    assert Conversion().coupling == "band" and Conversion().band_width == 3
    assert Conversion(spheres_per_tet=4).coupling == "tie"  # the default falls back where the band cannot go
    with pytest.raises(pydantic.ValidationError, match="spheres_per_tet = 1"):
        Conversion(spheres_per_tet=4, coupling="band")
    with pytest.raises(pydantic.ValidationError, match="band_width"):
        Conversion(band_width=0)
    with pytest.raises(pydantic.ValidationError, match="band_penalty"):
        Conversion(band_penalty=0.0)
    with pytest.raises(pydantic.ValidationError, match="coupling"):
        Conversion(coupling="glue")


def test_default_reflects_less(device):
    # The comparison that made the band the default (benchmarks/overlap_band.py, all widths and penalties there):
    # on its bar, the band of the default width reflects a smaller amplitude than the tie, by either measure.
    reference = bench.run_case(device, "none")
    tie = bench.reflection(reference, bench.run_case(device, "tie"), "tie", 0, 1.0)
    default = Conversion()
    band = bench.reflection(
        reference,
        bench.run_case(device, "band", default.band_width, default.band_penalty),
        "band",
        default.band_width,
        default.band_penalty,
    )
    print(f"R tie {tie.r_energy:.3f} / {tie.r_gauge:.3f}, band {band.r_energy:.3f} / {band.r_gauge:.3f}")
    assert default.coupling == "band"
    assert band.r_energy < tie.r_energy
    assert abs(band.r_gauge) < abs(tie.r_gauge)
