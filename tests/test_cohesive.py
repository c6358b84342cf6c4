"""Cohesive elements between split daughters (kernels/cohesive.py, warpdem/stages/cohesive.py): LDEC eqs. 5–10.

Set-up: a model from the builder whose first nodes are taken as daughter pairs (2k, 2k + 1) sharing one reference
position X, as a split leaves them; its tets are never evaluated, so the nodes feel only the cohesive forces. The
cohesive slots are allocated with warpdem.model.fracture_state and filled here: f_c, δ_c from eq. 10 for a chosen
Γ and A_f, α, and the direction p1.

Oracles:
- (a) fracture energy: a pair opened quasi-statically until its element breaks has dissipated Γ A_f (eq. 9) within
  the break step's error, by the work of its force (trapezoid of the forces over the displacement increments,
  float64), and the books (Σ node_energy_cohesive, kept as velocity Verlet does the work) equal that work, for
  α = 1, 0.5 and 0 (the force jump); while intact, dissipated = ½ f_c δ_max, stored + dissipated = the work done so
  far, and the force is on the envelope; below 1e-4 δ_c the force keeps p1; a node split twice books half of each
  of its elements;
- (b) unloading and reloading follow the line to the origin: force/opening = k(δ_max) = f_c (1 − α δ_max/δ_c)/δ_max
  while d < d_max, the force meets the envelope exactly at d = d_max and follows it beyond; d_max does not move while
  d < d_max, nor do the books but for float32 rounding (the trapezoid of a linear spring is exact);
- (c) equal and opposite central forces: on one element node_f[A] = −node_f[B] bit for bit, and over elements sharing
  nodes the total force and the total moment Σ x × f vanish (to float32 rounding of the sums);
- (d) dynamics with the project's integrator (velocity Verlet, warpdem.stages.integrate): two free nodes flying apart
  conserve kinetic − shadow + stored + dissipated (EnergyBalance's books) to rounding, and kinetic + stored +
  dissipated to the shadow term, an O(dt²) bound; a pair with more energy than Γ A_f breaks, its books close to
  rounding through the break, and it keeps the kinetic energy minus Γ A_f within the break step's error (also with
  one node held by the integrator, which takes the force and stays);
- (e) compaction keeps the intact elements in their order, counters and books unchanged; regrowth copies them and
  gives the same forces;
- (f) dt = 0 changes no array but node_f, and gives the forces a step would; without energy tracking the history
  and counters advance and nothing is booked; an element that never opens keeps f_c along p1 and books nothing.

Tolerances (named below): float32 holds f_c, δ_c and the openings to a relative 2⁻²⁴, the books are float64 sums
(BOOK_RTOL); the trapezoid of the quasi-static drive is exact on the linear pieces of eqs. 6–7, and only the step
that breaks the element differs from the envelope, by at most ½ (1 − α) f_c Δd (the force drops to zero inside the
step) plus ½ f_c Δd²/δ_c (for α = 1 the force nears zero there): work_rtol below follows from Δd = δ_c/STEPS. The
dynamics' rounding bound (verlet_rounding) follows from the float32 drift and kicks.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import warp as wp

from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import box_mesh
from warpdem.model import COHESIVE_FIELDS, Model, State, fracture_state
from warpdem.stages.cohesive import cohesive_energy, compact_cohesive, eval_cohesive, regrow_cohesive
from warpdem.stages.compaction import Compactor
from warpdem.stages.integrate import integrate_first_half, integrate_second_half

F32_EPS = float(np.finfo(np.float32).eps)
FC = 1.0e3  # [N] f_c
GAMMA = 250.0  # [J/m²] Γ
AREA = 4.0e-6  # [m²] A_f, both faces: Γ A_f = 1e-3 J
STEPS = 2000  # quasi-static opening increments per δ_c
# Books: float64 sums of terms made from float32 f_c, δ_c and α (each rounded by 2⁻²⁴ relative).
BOOK_RTOL = 8 * F32_EPS
# Forces and ratios computed in float32 from float32 openings: a few roundings each.
FORCE_RTOL = 16 * F32_EPS
CHECK_EVERY = 25  # steps of the quasi-static drive between two checks of the books along the way
ISSUE_RTOL = 1.0e-3  # issue 9 §6: each fully broken element has dissipated Γ A_f within 0.1 %


def work_rtol(alpha: float) -> float:
    """Bound on |W − Γ A_f| / Γ A_f of the trapezoid work of a quasi-static drive with Δd = δ_c/STEPS.

    The trapezoid is exact on the linear pieces of eqs. 6–7; the step in which d passes δ_c adds ½ (1 − α) f_c Δd
    (the element lets go inside it) and ½ f_c Δd²/δ_c (the envelope's last piece); Γ A_f = (1 − α/2) f_c δ_c. The
    float32 forces add FORCE_RTOL.
    """
    step = 1.0 / STEPS
    return (0.5 * (1.0 - alpha) * step + 0.5 * step * step) / (1.0 - 0.5 * alpha) + FORCE_RTOL


def critical_opening(alpha: float, gamma: float = GAMMA, area: float = AREA, fc: float = FC) -> float:
    """δ_c = 2 Γ A_f / ((2 − α) f_c) [m] (LDEC eq. 10)."""
    return 2.0 * gamma * area / ((2.0 - alpha) * fc)


# ----------------------------------------------------------------------------------------------------------------
# Helpers


def daughter_model(
    device: str, sites: int, per_site: int = 2, capacity: int = 8, masses=(2.0, 3.0, 5.0), dt: float = 1.0e-7
) -> tuple[Model, State]:
    """A model whose nodes s·per_site .. s·per_site + per_site − 1 are the daughters of one split node at
    X = (s, 0, 0) (the same reference position, as a split leaves them), node k of a site with mass ``masses[k]``
    [kg], and ``capacity`` empty cohesive slots. Only these sites·per_site nodes are live; no gravity, no damping."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (1, 1, 1))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", 2000.0, 1.0e8, 0.25)
    b.add_tet_mesh(points, tets, "rock")
    n = sites * per_site
    model, state = b.finalize(device, dt=dt, node_capacity=max(n, len(points)), allow_unstable_dt=True)
    ncap = model.node_capacity
    x = np.zeros((ncap, 3), dtype=np.float32)
    x[:n, 0] = np.repeat(np.arange(sites), per_site)
    mass = np.zeros(ncap, dtype=np.float32)
    mass[:n] = np.tile(np.asarray(masses[:per_site]), sites)
    inv_mass = np.where(mass > 0.0, 1.0 / np.where(mass > 0.0, mass, 1.0), 0.0).astype(np.float32)
    model = dataclasses.replace(
        model,
        node_ref_q=wp.array(x, dtype=wp.vec3, device=device),
        node_mass=wp.array(mass, dtype=float, device=device),
        node_inv_mass=wp.array(inv_mass, dtype=float, device=device),
        node_motion=wp.zeros(ncap, dtype=int, device=device),
        node_damping=wp.zeros(ncap, dtype=float, device=device),
        cohesive_capacity=capacity,
    )
    state = dataclasses.replace(state, **fracture_state(model))
    state.node_count.fill_(n)
    state.node_q.assign(x)
    for name in ("node_u", "node_qd", "node_f", "fem_rebuild_flag"):
        getattr(state, name).zero_()
    return model, state


def set_elements(state: State, a, b, alpha, direction, fc=FC, gamma=GAMMA, area=AREA) -> None:
    """Fill the first len(a) cohesive slots (f_c, Γ and A_f scalars or per element; δ_c from eq. 10)."""
    n = len(a)
    alpha = np.broadcast_to(np.asarray(alpha, dtype=np.float64), (n,))
    fc, gamma, area = (np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)) for v in (fc, gamma, area))
    direction = np.broadcast_to(np.asarray(direction, dtype=np.float64), (n, 3))
    values = {
        "cohesive_a": np.asarray(a),
        "cohesive_b": np.asarray(b),
        "cohesive_fc": fc,
        "cohesive_delta_c": critical_opening(alpha, gamma, area, fc),
        "cohesive_alpha": alpha,
        "cohesive_area": area,
        "cohesive_dir": direction,
        # As a split leaves it: the books' trapezoid starts from the birth force f_c along the direction.
        "cohesive_f_prev": fc[:, None] * direction,
    }
    for name, v in values.items():
        host = getattr(state, name).numpy()
        host[:n] = v
        getattr(state, name).assign(host)
    state.cohesive_count.fill_(n)


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return (v / np.linalg.norm(v)).astype(np.float32)


def spent_books(state: State) -> np.ndarray:
    """Per node: what its cohesive elements spent, -W - ΔU, on the law's line and the trapezoid line together [J]."""
    return state.node_energy_cohesive.numpy() + state.node_energy_cohesive_trapezoid.numpy()


def forces_at(model: Model, state: State, u: np.ndarray, dt: float | None = None) -> np.ndarray:
    """Set the displacements, evaluate the cohesive forces alone, return node_f (float64, live nodes).

    The nodes move to ``u`` as a step of velocity Verlet would move them: node_qd = (u − u_before)/dt is their
    velocity over the step, which the books' trapezoid dots with the forces (kernels/cohesive.py)."""
    n = int(state.node_count.numpy()[0])
    host = np.zeros((model.node_capacity, 3), dtype=np.float32)
    host[:n] = u
    step = model.dt if dt is None else dt
    if step > 0.0:
        velocity = np.zeros_like(host)
        velocity[:n] = (host[:n].astype(np.float64) - state.node_u.numpy()[:n]) / step
        state.node_qd.assign(velocity.astype(np.float32))
    state.node_u.assign(host)
    state.node_f.zero_()
    eval_cohesive(model, state, dt)
    return state.node_f.numpy()[:n].astype(np.float64)


def envelope(d: float, fc: float, delta_c: float, alpha: float) -> float:
    """f_c (1 − α d/δ_c) [N] (eq. 6 at d = δ_max)."""
    return fc * (1.0 - alpha * d / delta_c)


def stored_f32(state: State) -> tuple[float, float, float]:
    """f_c, δ_c and α of element 0 as stored (float32), in float64."""
    return tuple(float(getattr(state, n).numpy()[0]) for n in ("cohesive_fc", "cohesive_delta_c", "cohesive_alpha"))


# ----------------------------------------------------------------------------------------------------------------
# (a) Each fully broken element has dissipated Γ A_f (eq. 9).


def test_broken_elements_dissipate_fracture_energy(device):
    """Three pairs with α = 1, 0.5, 0 opened quasi-statically along p1 (A and B in unequal shares), each by
    δ_c/STEPS per step, past δ_c (inside a step: offset 0.37 of a step)."""
    alphas = np.array([1.0, 0.5, 0.0])
    model, state = daughter_model(device, 3, capacity=4)
    p1 = unit([1.0, 2.0, 2.0])
    set_elements(state, [0, 2, 4], [1, 3, 5], alphas, p1)
    fc = state.cohesive_fc.numpy()[:3].astype(np.float64)
    delta_c = state.cohesive_delta_c.numpy()[:3].astype(np.float64)
    gamma_af = GAMMA * AREA
    share = np.tile([-0.3, 0.7], 3)  # node 2k moves back by 0.3 of the opening, node 2k + 1 forward by 0.7

    def u_of(n: float) -> np.ndarray:
        opening = np.repeat(max(n - 0.63, 0.0) * delta_c / STEPS, 2)
        return (share[:, None] * opening[:, None] * p1[None, :]).astype(np.float32).astype(np.float64)

    def per_element(x: np.ndarray) -> np.ndarray:
        return x.reshape(3, 2, *x.shape[1:]).sum(axis=1)

    work = np.zeros(3)  # work of the nodes on each element [J]
    u_prev = u_of(0)
    f_prev = forces_at(model, state, u_prev)
    np.testing.assert_allclose(f_prev[::2], fc[:, None] * p1, rtol=FORCE_RTOL)  # before any opening: f_c along p1
    for n in range(1, STEPS + 3):
        u = u_of(n)
        f = forces_at(model, state, u)
        # node_f of A is the element's force on it; the nodes do −f·Δu on the element (trapezoid, exact on a linear
        # piece of eqs. 6–7).
        work -= per_element(np.sum(0.5 * (f_prev + f) * (u - u_prev), axis=1))
        u_prev, f_prev = u, f
        if state.cohesive_broken.numpy()[:3].all():
            break
        if n % CHECK_EVERY:
            continue
        assert not state.cohesive_broken.numpy()[:3].any()
        assert int(state.fem_rebuild_flag.numpy()[0]) == 0
        d_max = state.cohesive_d_max.numpy()[:3].astype(np.float64)
        books = per_element(state.node_energy_cohesive.numpy()[:6])
        stored, spent = cohesive_energy(model, state)
        # ½ f_c δ_max dissipated while intact (independent of α); stored + spent (the law's line and the trapezoid
        # line) = the work so far.
        np.testing.assert_allclose(books, 0.5 * fc * d_max, rtol=BOOK_RTOL)
        np.testing.assert_allclose(stored + spent, work.sum(), rtol=FORCE_RTOL)
        np.testing.assert_allclose(state.node_damage.numpy()[:6], np.repeat(d_max / delta_c, 2), rtol=FORCE_RTOL)
        # Loading: the force is on the envelope (eq. 6 at d = δ_max), along the opening; for α = 0 it stays f_c up to
        # the break, then drops to zero (the jump of a law discontinuous in time). Absolute tolerance: float32
        # rounds 1 − α δ_max/δ_c to ε32 absolute, i.e. f_c ε32 of force where the envelope nears zero.
        f_env = np.array([envelope(*args) for args in zip(d_max, fc, delta_c, alphas, strict=True)])
        np.testing.assert_allclose(f[::2], f_env[:, None] * p1, rtol=FORCE_RTOL, atol=8 * F32_EPS * FC)
    # Each broke in the step that took its opening past δ_c, and applies no force since.
    assert n - 0.63 >= STEPS and n - 1 - 0.63 < STEPS
    np.testing.assert_array_equal(f_prev, 0.0)
    books = spent_books(state)[:6]
    np.testing.assert_array_equal(books[::2], books[1::2])  # half on A, half on B
    books = per_element(books)
    # The law's line holds its life total Γ A_f (eq. 9) exactly, however the step ends the opening; the trapezoid
    # line the rest of the work (a float32 rounding of Γ A_f in each fc δ_c product).
    law = per_element(state.node_energy_cohesive.numpy()[:6])
    np.testing.assert_allclose(law, gamma_af, rtol=BOOK_RTOL)
    for k, alpha in enumerate(alphas):
        print(
            f"alpha={alpha}: books/ΓA_f - 1 = {books[k] / gamma_af - 1:.2e}, "
            f"work/ΓA_f - 1 = {work[k] / gamma_af - 1:.2e} (bound {work_rtol(alpha):.1e})"
        )
        assert work_rtol(alpha) < ISSUE_RTOL
        np.testing.assert_allclose(work[k], gamma_af, rtol=work_rtol(alpha))
    # The books are the work the forces did (the same trapezoid, in float32 increments summed in float64).
    np.testing.assert_allclose(books, work, rtol=FORCE_RTOL)
    assert cohesive_energy(model, state) == (0.0, pytest.approx(books.sum(), rel=BOOK_RTOL))
    # Counters of the breaks (eq. 9). No FEM list rebuild is flagged: the node–face candidate test does not read the
    # elements, so a break changes no list (tests/test_fem_contact.py holds the lists after a pass to a full build).
    assert int(state.cohesive_broken_total.numpy()[0]) == 3
    np.testing.assert_allclose(state.cohesive_area_broken.numpy()[0], 3 * AREA, rtol=F32_EPS)
    np.testing.assert_allclose(state.cohesive_work_broken.numpy()[0], 3 * gamma_af, rtol=BOOK_RTOL)
    assert int(state.fem_rebuild_flag.numpy()[0]) == 0
    np.testing.assert_array_equal(state.node_damage.numpy()[:6], 1.0)


# ----------------------------------------------------------------------------------------------------------------
# (b) Unloading and reloading along the line to the origin (eqs. 6–8).


@pytest.mark.parametrize("alpha", [1.0, 0.5, 0.0])
def test_unloading_and_reloading_follow_the_line_to_the_origin(device, alpha):
    model, state = daughter_model(device, 1, capacity=2)
    p1 = unit([0.0, 0.0, 1.0])
    q = unit([1.0, -1.0, 0.5])  # the pair opens along q, not p1: after opening the force follows e = r/d
    set_elements(state, [0], [1], alpha, p1)
    fc, delta_c, _ = stored_f32(state)

    def u_of(opening: float) -> np.ndarray:
        """Displacements of A and B, rounded to float32 as the state holds them."""
        u = np.outer([-0.5, 0.5], float(opening) * q.astype(np.float64))
        return u.astype(np.float32).astype(np.float64)

    peak = 0.4 * delta_c
    for opening in np.linspace(0.0, peak, 41)[1:]:  # loading on the envelope
        f = forces_at(model, state, u_of(opening))
    f_peak = f.copy()
    r_peak = u_of(peak)[1] - u_of(peak)[0]
    d_peak = float(np.linalg.norm(r_peak.astype(np.float32)))
    np.testing.assert_allclose(np.linalg.norm(f_peak[0]), envelope(d_peak, fc, delta_c, alpha), rtol=FORCE_RTOL)
    d_max = float(state.cohesive_d_max.numpy()[0])
    books = state.node_energy_cohesive.numpy().copy()
    k = envelope(d_max, fc, delta_c, alpha) / d_max  # the line to the origin through (δ_max, f(δ_max))
    # Unload to closure and reload to the peak: f = k r on A (towards B), history and books frozen.
    path = np.concatenate([np.linspace(peak, 0.0, 21)[1:], np.linspace(0.0, peak, 21)[1:-1]])
    for opening in path:
        u = u_of(opening)
        f = forces_at(model, state, u)
        r = (u[1] - u[0]).astype(np.float32).astype(np.float64)
        np.testing.assert_allclose(f[0], k * r, rtol=FORCE_RTOL, atol=FORCE_RTOL * fc * opening / delta_c)
        np.testing.assert_array_equal(f[1], -f[0])
        assert float(state.cohesive_d_max.numpy()[0]) == d_max
        # On the line the trapezoid is exact, ½ (k r_n + k r_{n+1})·(r_{n+1} − r_n) = ΔU: the books move only by the
        # float32 rounding of each step's work and energy, FORCE_RTOL of the spring energy per step at most.
        np.testing.assert_allclose(
            state.node_energy_cohesive.numpy(),
            books,
            rtol=0,
            atol=len(path) * FORCE_RTOL * 0.5 * envelope(d_max, fc, delta_c, alpha) * d_max,
        )
        stored, _ = cohesive_energy(model, state)
        np.testing.assert_allclose(stored, 0.5 * k * float(r @ r), rtol=FORCE_RTOL, atol=1e-30)
    # Closed (d = 0 exactly, after an opening): no force.
    np.testing.assert_array_equal(forces_at(model, state, u_of(0.0)), 0.0)
    # Reloading meets the envelope exactly where it left it, and follows it beyond.
    np.testing.assert_array_equal(forces_at(model, state, u_of(peak)), f_peak)
    for opening in np.linspace(peak, 0.6 * delta_c, 11)[1:]:
        f = forces_at(model, state, u_of(opening))
        d = float(state.cohesive_d_max.numpy()[0])
        np.testing.assert_allclose(np.linalg.norm(f[0]), envelope(d, fc, delta_c, alpha), rtol=FORCE_RTOL)
        np.testing.assert_allclose(f[0] / np.linalg.norm(f[0]), q, rtol=0, atol=FORCE_RTOL)
    # Dissipated: ½ f_c δ_max (module docstring of kernels/cohesive.py), less what the first step's trapezoid missed
    # because the element, born along p1, opened along q: ½ (f_c p1 + f_1 q)·d_1 q instead of ½ (f_c + f_1) d_1.
    _, dissipated = cohesive_energy(model, state)
    d_1 = float(np.linalg.norm((u_of(peak / 40)[1] - u_of(peak / 40)[0]).astype(np.float32)))
    first_step = 0.5 * fc * d_1 * (1.0 - float(p1.astype(np.float64) @ q.astype(np.float64)))
    expected = 0.5 * fc * float(state.cohesive_d_max.numpy()[0]) - first_step
    np.testing.assert_allclose(dissipated, expected, rtol=len(path) * FORCE_RTOL)


def test_element_that_never_opens(device):
    """Daughters held together (d = 0) for many steps: the force stays f_c along p1, nothing is booked."""
    model, state = daughter_model(device, 1, capacity=2)
    p1 = unit([0.3, -0.4, 1.2])
    set_elements(state, [0], [1], 0.5, p1)
    u = np.full((2, 3), 0.25, dtype=np.float32)  # the same displacement on both: x_A = x_B
    for _ in range(10):
        f = forces_at(model, state, u)
        np.testing.assert_allclose(f[0], FC * p1, rtol=FORCE_RTOL)
        np.testing.assert_array_equal(f[1], -f[0])
    assert float(state.cohesive_d_max.numpy()[0]) == 0.0
    np.testing.assert_array_equal(state.node_damage.numpy(), 0.0)
    assert cohesive_energy(model, state) == (0.0, 0.0)
    assert int(state.cohesive_broken.numpy()[0]) == 0


# ----------------------------------------------------------------------------------------------------------------
# (c) Equal and opposite central forces, also where a node holds several elements.


def test_forces_are_equal_opposite_and_central(device):
    rng = np.random.default_rng(7)
    # Site 0: daughters 0, 1, 2 (a node split twice), elements 0–1, 0–2, 1–2; site 1: 3, 4, 5, elements 3–4, 3–5
    # (3–5 not yet open: the same displacement); site 2: one element 6–7.
    model, state = daughter_model(device, 3, per_site=3, capacity=8)
    a, b = [0, 0, 1, 3, 3, 6], [1, 2, 2, 4, 5, 7]
    set_elements(state, a, b, rng.uniform(0.0, 1.0, 6), unit([0.0, 1.0, 0.0]), fc=FC * rng.uniform(0.5, 2.0, 6))
    delta_c = state.cohesive_delta_c.numpy()[:6]
    # Some elements unloading (d_max above the present opening), the others loading.
    d_max = (np.array([0.5, 0.0, 0.5, 0.0, 0.0, 0.5]) * delta_c).astype(np.float32)
    state.cohesive_d_max.assign(np.concatenate([d_max, np.zeros(2, np.float32)]))
    u = rng.normal(0.0, 0.1 * delta_c.min(), (9, 3))
    u[5] = u[3]
    u[8] = 0.0  # node 8 holds no element
    f = forces_at(model, state, u)
    # One element on a node pair: bit-for-bit opposite.
    np.testing.assert_array_equal(f[7], -f[6])
    assert np.all(np.linalg.norm(f[:8], axis=1) > 0.0)
    np.testing.assert_array_equal(f[8], 0.0)
    # Σ f = 0 and Σ (x − X_site) × f = Σ u × f = 0 per site (central forces; the element not yet open pulls along
    # p1 with r = 0); tolerances: float32 rounding of the per-node sums.
    scale = np.abs(f).sum()
    u32 = u.astype(np.float32).astype(np.float64)
    for site in range(3):
        nodes = slice(3 * site, 3 * site + 3)
        np.testing.assert_allclose(f[nodes].sum(axis=0), 0.0, atol=FORCE_RTOL * scale)
        moment = np.cross(u32[nodes], f[nodes]).sum(axis=0)
        np.testing.assert_allclose(moment, 0.0, atol=FORCE_RTOL * scale * np.abs(u32).max())
    # The element not yet open (3–5) adds exactly f_c p1 to node 3 and −f_c p1 to node 5; element 3–4 the rest.
    fc = state.cohesive_fc.numpy()[4]
    np.testing.assert_allclose(f[5], -fc * unit([0.0, 1.0, 0.0]), rtol=FORCE_RTOL)
    np.testing.assert_allclose(f[3] + f[4] + f[5], 0.0, atol=FORCE_RTOL * scale)


# ----------------------------------------------------------------------------------------------------------------
# (d) Dynamics: two free daughters under velocity Verlet (warpdem.stages.integrate) with the cohesive force alone.


def energies(model: Model, state: State) -> tuple[float, float, float, float]:
    """(kinetic, shadow, stored, dissipated) [J] of the live nodes: the EnergyBalance lines of this system
    (warpdem.simulation: shadow = dt²/8 Σ |f|²/m over the moving nodes, at the forces held now)."""
    n = int(state.node_count.numpy()[0])
    m = model.node_mass.numpy()[:n].astype(np.float64)
    moving = model.node_inv_mass.numpy()[:n] > 0.0
    v = state.node_qd.numpy()[:n].astype(np.float64)
    f = state.node_f.numpy()[:n].astype(np.float64)
    kinetic = 0.5 * float(np.sum(m * np.sum(v * v, axis=1)))
    shadow = model.dt**2 / 8.0 * float(np.sum((np.sum(f * f, axis=1) / m)[moving]))
    return (kinetic, shadow, *cohesive_energy(model, state))


def verlet_rounding(steps: int, f_max: float, u_max: float, v_max: float, mass: float) -> float:
    """Bound [J] on the float32 rounding of the energy books of two nodes over ``steps`` velocity Verlet steps.

    Per step and node the drift u ← u + dt v rounds u by half a spacing of |u|, work f·δu the books do not see, and
    the two half kicks round v by half a spacing of |v| each, kinetic energy m v δv; the roundings are independent
    from step to step, a random walk: 4 standard deviations of it over the steps.
    """
    per_step = f_max * 0.5 * float(np.spacing(np.float32(u_max))) + mass * v_max * float(np.spacing(np.float32(v_max)))
    return 4.0 * math.sqrt(steps) * 2.0 * per_step


def fly_apart(
    device: str,
    alpha: float,
    energy_ratio: float,
    dt: float,
    steps: int,
    held_a: bool = False,
    drift=(0, 0, 0),
    lateral: float = 0.0,
) -> tuple[State, np.ndarray, dict]:
    """Daughters A (2 kg) and B (3 kg) leave each other along p1 with a relative kinetic energy ``energy_ratio`` ×
    Γ A_f, on top of a common ``drift`` [m/s] (``held_a``: A is a fixed node, which the integrator holds, and B alone
    moves); velocity Verlet as the Simulation runs it (first half, forces, second half). Returns the state, the
    energies of every step (steps + 1, 4), and the run's figures: total momentum at start and end [kg m/s], largest
    displacement and speed of a node, and the rounding bound of the books (:func:`verlet_rounding`). ``lateral``:
    the relative velocity turns by atan(lateral) away from p1 (same relative kinetic energy)."""
    model, state = daughter_model(device, 1, capacity=2, dt=dt)
    if held_a:
        model.node_motion.assign(np.array([1] + [0] * (model.node_capacity - 1), dtype=np.int32))
        inv_mass = model.node_inv_mass.numpy()
        inv_mass[0] = 0.0
        model.node_inv_mass.assign(inv_mass)
    p1 = unit([2.0, -1.0, 2.0])
    set_elements(state, [0], [1], alpha, p1)
    m_a, m_b = (math.inf if held_a else 2.0), 3.0
    mu = m_b if held_a else m_a * m_b / (m_a + m_b)
    v0 = math.sqrt(2.0 * energy_ratio * GAMMA * AREA / mu)
    v = np.zeros((model.node_capacity, 3), dtype=np.float32)
    across = unit([1.0, 2.0, 0.0])  # ⟂ p1
    rel = (p1 + lateral * across) / math.hypot(1.0, lateral)
    v[0] = np.asarray(drift) - v0 * (mu / m_a) * rel
    v[1] = np.asarray(drift) + v0 * (mu / m_b) * rel
    state.node_qd.assign(v)
    eval_cohesive(model, state, dt=0.0)  # the set-up evaluation: forces at t = 0
    mass = model.node_mass.numpy()[:2, None].astype(np.float64)
    p_start = (mass * state.node_qd.numpy()[:2]).sum(axis=0)
    books = [energies(model, state)]
    u_max = v_max = 0.0
    for _ in range(steps):
        integrate_first_half(model, state)
        eval_cohesive(model, state)
        integrate_second_half(model, state)
        books.append(energies(model, state))
        u_max = max(u_max, float(np.abs(state.node_u.numpy()[:2]).max()))
        v_max = max(v_max, float(np.abs(state.node_qd.numpy()[:2]).max()))
    if held_a:
        np.testing.assert_array_equal(state.node_u.numpy()[0], 0.0)  # the held node took the force, and stayed
        assert np.all(state.node_f.numpy()[0] == -state.node_f.numpy()[1])
    run = {
        "p_start": p_start,
        "p_end": (mass * state.node_qd.numpy()[:2]).sum(axis=0),
        "u_max": u_max,
        "v_max": v_max,
        "rounding": verlet_rounding(steps, FC, u_max, v_max, 3.0),
    }
    return state, np.array(books), run


def test_dynamics_conserve_energy_while_intact(device):
    """α = 1, relative kinetic energy ½ Γ A_f: the pair opens to δ* with W(δ*) = f_c δ* − ½ f_c δ*²/δ_c = ½ Γ A_f,
    i.e. δ* = (1 − 1/√2) δ_c, turns and then oscillates on the line to the origin without breaking.

    Velocity Verlet changes the kinetic energy by the trapezoid of the force's work plus the change of the shadow
    term S = dt²/8 Σ |f|²/m; the trapezoid is the exact work on the linear pieces of eqs. 6–7, and the turn happens
    at a step (the force before it is on the envelope, after it on the line through the same point). So
    kinetic − S + stored + dissipated is constant to rounding (round_rtol below), and kinetic + stored + dissipated to
    within 2 max S ≤ dt² f_c²/4 (1/m_A + 1/m_B): O(dt²).
    """
    dt = 4.0e-7  # ω dt ≈ 0.01 on the line
    # Line stiffness at δ*: k = f_c (1 − δ*/δ_c)/δ*, with the reduced mass 1.2 kg.
    omega = math.sqrt(FC / math.sqrt(2.0) / ((1.0 - 1.0 / math.sqrt(2.0)) * critical_opening(1.0)) / 1.2)
    steps = int(2.5 * 2.0 * math.pi / omega / dt)  # the opening and two periods on the line
    state, books, run = fly_apart(device, 1.0, 0.5, dt, steps)
    kinetic, shadow, stored, dissipated = books.T
    total0 = kinetic[0] - shadow[0] + stored[0] + dissipated[0]
    drift = np.abs(kinetic - shadow + stored + dissipated - total0).max()
    print(f"intact: shadowed total drift / E = {drift / total0:.2e} (rounding bound {run['rounding'] / total0:.1e})")
    assert drift <= run["rounding"]
    bound = dt**2 * FC**2 / 4.0 * (1.0 / 2.0 + 1.0 / 3.0)
    raw = np.abs(kinetic + stored + dissipated - (kinetic[0] + stored[0] + dissipated[0])).max()
    print(f"intact: unshadowed total drift / E = {raw / total0:.2e} (O(dt²) bound {bound / total0:.1e})")
    assert raw <= bound + run["rounding"]
    # The opening reached δ* (the turn is sampled within a step's motion near zero relative speed) and held.
    delta_c = float(state.cohesive_delta_c.numpy()[0])
    d_max = float(state.cohesive_d_max.numpy()[0])
    np.testing.assert_allclose(d_max, (1.0 - 1.0 / math.sqrt(2.0)) * delta_c, rtol=1e-3)
    assert int(state.cohesive_broken.numpy()[0]) == 0
    # The trapezoid is exact on the linear pieces (the turn included: both forces lie on lines through the turning
    # point), so the books still give the law's ½ f_c δ_max, to the float32 rounding of the steps' work.
    np.testing.assert_allclose(dissipated[-1], 0.5 * FC * d_max, atol=run["rounding"])


@pytest.mark.parametrize(("alpha", "held_a"), [(1.0, False), (0.5, False), (1.0, True)])
def test_dynamics_break_leaves_kinetic_energy_minus_fracture_energy(device, alpha, held_a):
    """Relative kinetic energy 2 Γ A_f: the element breaks, and the pair keeps K_0 − S_0 − Γ A_f (S_0 the shadow
    term at the start, when the force is f_c; it is 0 after the break).

    The only step not exact on the linear pieces is the break: the element lets go inside it, and velocity Verlet
    applies the force of the step before over the step's opening Δd ≤ v_0 dt instead of the envelope's: for α = 1
    that force is below f_c Δd/δ_c, an error ≤ ½ f_c Δd²/δ_c; for α < 1 the force drops from (1 − α) f_c to zero
    within the step, an error ≤ ½ (1 − α) f_c Δd (first order in dt: the price of a force law discontinuous in
    time, eq. 6 with α < 1). With A held (a fixed node) the same holds for B alone: the held node takes the force
    and does no work.
    """
    dt = 2.5e-7
    mu = 3.0 if held_a else 1.2  # reduced mass of the pair [kg]
    v0 = math.sqrt(2.0 * 2.0 * GAMMA * AREA / mu)
    delta_c = critical_opening(alpha)
    steps = int(3.0 * delta_c / (0.5 * v0) / dt)  # the relative speed stays above v0/√2
    drift = (0.0, 0.0, 0.0) if held_a else (0.01, 0.02, -0.01)
    state, books, run = fly_apart(device, alpha, 2.0, dt, steps, held_a, drift)
    kinetic, shadow, stored, dissipated = books.T
    assert int(state.cohesive_broken.numpy()[0]) == 1
    gamma_af = GAMMA * AREA
    assert stored[-1] == 0.0 and shadow[-1] == 0.0
    # The books are the work Verlet's forces did: kinetic − shadow + stored + dissipated is constant to rounding,
    # through the birth, the opening and the break.
    total = kinetic - shadow + stored + dissipated
    np.testing.assert_allclose(total, total[0], rtol=0, atol=run["rounding"])
    step = v0 * dt
    bound = 0.5 * FC * step * step / delta_c if alpha == 1.0 else 0.5 * (1.0 - alpha) * FC * step
    # ... and that work is the law's Γ A_f (eq. 9) but for the break step (above).
    np.testing.assert_allclose(dissipated[-1], gamma_af, atol=bound + run["rounding"])
    expected = kinetic[0] - shadow[0] - gamma_af
    print(
        f"alpha={alpha} held_a={held_a}: (K_end - K_0 + S_0 + ΓA_f)/ΓA_f = {(kinetic[-1] - expected) / gamma_af:.2e}, "
        f"bound {bound / gamma_af:.1e}"
    )
    np.testing.assert_allclose(kinetic[-1], expected, atol=bound + run["rounding"])
    if not held_a:
        # Momentum: the forces are equal and opposite; each half kick rounds a velocity by half a spacing.
        v_round = 0.5 * float(np.spacing(np.float32(run["v_max"])))
        atol = 4.0 * math.sqrt(2 * steps) * 5.0 * v_round
        np.testing.assert_allclose(run["p_end"], run["p_start"], atol=atol)


def test_coarse_step_books_close_and_dissipate_fracture_energy(device):
    """A step that barely resolves the opening: f_c dt²/m* = 0.1 δ_c (α = 1), the pair leaving at atan(0.3) to p1 with
    relative kinetic energy 1.5 Γ A_f, so that it crosses δ_c in a few steps.

    The books close to rounding (they are the trapezoid Verlet does, kernels/cohesive.py), through the birth along
    p1, the turn of the force onto r and the break; the element dissipates Γ A_f but for (i) the break step,
    ½ f_c Δd²/δ_c (Δd = v_0 dt), and (ii) the first step, where the birth force f_c along p1 works on the opening's
    projection onto p1 instead of its length: at most ½ f_c Δd (1 − cos θ), θ = atan(0.3).
    """
    dt_s = math.sqrt(0.1 * critical_opening(1.0) / (FC * (1.0 / 2.0 + 1.0 / 3.0)))
    mu = 1.2
    v0 = math.sqrt(2.0 * 1.5 * GAMMA * AREA / mu)
    steps = int(3.0 * critical_opening(1.0) / (0.5 * v0) / dt_s)
    state, books, run = fly_apart(device, 1.0, 1.5, dt_s, steps, lateral=0.3)
    kinetic, shadow, stored, dissipated = books.T
    assert int(state.cohesive_broken.numpy()[0]) == 1
    total = kinetic - shadow + stored + dissipated
    np.testing.assert_allclose(total, total[0], rtol=0, atol=run["rounding"])
    delta_c = critical_opening(1.0)
    step = v0 * dt_s
    bound = 0.5 * FC * step * step / delta_c + 0.5 * FC * step * (1.0 - 1.0 / math.hypot(1.0, 0.3))
    gamma_af = GAMMA * AREA
    print(f"coarse step: dissipated/ΓA_f - 1 = {dissipated[-1] / gamma_af - 1:.2e} (bound {bound / gamma_af:.1e})")
    np.testing.assert_allclose(dissipated[-1], gamma_af, atol=bound + run["rounding"])


# ----------------------------------------------------------------------------------------------------------------
# (e) Compaction of broken elements and growth of the slots.


def opened_sites(device: str, capacity: int = 8):
    """Six daughter pairs with one element each (α, f_c, A_f differing), opened by one step to 0.3 δ_c, except
    elements 1 and 4, opened past δ_c (they break). Returns the model, state and the displacements."""
    model, state = daughter_model(device, 6, capacity=capacity)
    k = np.arange(6)
    set_elements(
        state, 2 * k, 2 * k + 1, 0.2 * k, unit([1.0, 0.0, 1.0]), fc=FC * (1.0 + k), area=AREA * (1.0 + 0.1 * k)
    )
    delta_c = state.cohesive_delta_c.numpy()[:6].astype(np.float64)
    opening = np.where(np.isin(k, [1, 4]), 1.5, 0.3) * delta_c
    u = np.zeros((12, 3))
    u[1::2, 2] = opening
    forces_at(model, state, u)
    return model, state, u


def test_compaction_keeps_intact_elements_in_order(device):
    model, state, u = opened_sites(device)
    assert int(state.cohesive_broken_total.numpy()[0]) == 2
    before = {name: getattr(state, name).numpy().copy() for name in COHESIVE_FIELDS}
    counters = [getattr(state, n).numpy().copy() for n in ("cohesive_broken_total", "cohesive_area_broken")]
    books = state.node_energy_cohesive.numpy().copy()
    energy = cohesive_energy(model, state)
    f_before = forces_at(model, state, u, dt=0.0)
    with pytest.raises(ValueError, match="compactor has 4 slots"):
        compact_cohesive(model, state, Compactor(4, model.device))
    assert compact_cohesive(model, state, Compactor(model.cohesive_capacity, model.device)) == 4
    survivors = [0, 2, 3, 5]
    for name in COHESIVE_FIELDS:
        after = getattr(state, name).numpy()
        np.testing.assert_array_equal(after[:4], before[name][survivors], err_msg=name)
        np.testing.assert_array_equal(after[4:], 0, err_msg=name)
    assert int(state.cohesive_count.numpy()[0]) == 4
    for name, value in zip(("cohesive_broken_total", "cohesive_area_broken"), counters, strict=True):
        np.testing.assert_array_equal(getattr(state, name).numpy(), value)
    np.testing.assert_array_equal(state.node_energy_cohesive.numpy(), books)
    assert cohesive_energy(model, state) == energy
    np.testing.assert_array_equal(forces_at(model, state, u, dt=0.0), f_before)
    # A second pass finds nothing to remove and changes nothing.
    kept = {name: getattr(state, name).numpy().copy() for name in COHESIVE_FIELDS}
    assert compact_cohesive(model, state, Compactor(model.cohesive_capacity, model.device)) == 4
    for name in COHESIVE_FIELDS:
        np.testing.assert_array_equal(getattr(state, name).numpy(), kept[name], err_msg=name)


def test_regrow_copies_live_elements(device):
    model, state, u = opened_sites(device)
    compact_cohesive(model, state, Compactor(model.cohesive_capacity, model.device))
    f_before = forces_at(model, state, u, dt=0.0)
    kept = {name: getattr(state, name).numpy().copy() for name in COHESIVE_FIELDS}
    big_model, big = regrow_cohesive(model, state, 16)
    assert big_model.cohesive_capacity == 16
    for name in COHESIVE_FIELDS:
        grown = getattr(big, name).numpy()
        assert grown.shape[0] == 16
        np.testing.assert_array_equal(grown[:4], kept[name][:4], err_msg=name)
        np.testing.assert_array_equal(grown[4:], 0, err_msg=name)
    np.testing.assert_array_equal(forces_at(big_model, big, u, dt=0.0), f_before)
    # Back down to the live count: the original arrays again.
    small_model, small = regrow_cohesive(big_model, big, 4)
    assert small_model.cohesive_capacity == 4
    for name in COHESIVE_FIELDS:
        np.testing.assert_array_equal(getattr(small, name).numpy(), kept[name][:4], err_msg=name)
    with pytest.raises(ValueError, match="below the 4 live"):
        regrow_cohesive(model, state, 3)
    # Growth between steps and a step afterwards: the same as the run that had the room all along.
    u_next = u.copy()
    u_next[1::2, 2] *= 1.2
    f_small = forces_at(model, state, u_next)
    f_big = forces_at(big_model, big, u_next)
    np.testing.assert_array_equal(f_big, f_small)
    np.testing.assert_array_equal(big.cohesive_d_max.numpy()[:4], state.cohesive_d_max.numpy()[:4])


# ----------------------------------------------------------------------------------------------------------------
# (f) dt = 0 evaluates forces only; track_energy = False keeps the history but books nothing.


def test_zero_dt_changes_nothing_but_forces(device):
    model, state = daughter_model(device, 4, capacity=8)
    k = np.arange(4)
    set_elements(state, 2 * k, 2 * k + 1, 0.5, unit([0.0, 1.0, 0.0]))
    delta_c = float(state.cohesive_delta_c.numpy()[0])
    # Element 0 not yet open, 1 loading past its d_max, 2 unloading below it, 3 past δ_c (a step would break it).
    state.cohesive_d_max.assign(np.array([0.0, 0.1, 0.5, 0.9, 0, 0, 0, 0], dtype=np.float32) * delta_c)
    u = np.zeros((8, 3))
    u[1::2, 1] = np.array([0.0, 0.3, 0.2, 1.1]) * delta_c
    state.node_damage.fill_(0.25)
    state.node_energy_cohesive.fill_(1.0)
    snapshot = state.clone()
    f_zero = forces_at(model, state, u, dt=0.0)
    snapshot.node_u.assign(state.node_u)
    for name, a in state.arrays().items():
        if name != "node_f":
            np.testing.assert_array_equal(a.numpy(), getattr(snapshot, name).numpy(), err_msg=name)
    # A step's evaluation gives the same forces where it breaks nothing, and none from the element it breaks.
    f_step = forces_at(model, state, u)
    np.testing.assert_array_equal(f_step[:6], f_zero[:6])
    np.testing.assert_array_equal(f_step[6:], 0.0)
    assert np.all(np.linalg.norm(f_zero, axis=1) > 0.0)
    # The history moved where the opening grew (1: to 0.3 δ_c; 3: broken), and stayed elsewhere.
    d_max = state.cohesive_d_max.numpy()[:4]
    np.testing.assert_array_equal(d_max[[0, 2]], snapshot.cohesive_d_max.numpy()[[0, 2]])
    np.testing.assert_allclose(d_max[[1, 3]], np.array([0.3, 1.1]) * delta_c, rtol=FORCE_RTOL)
    np.testing.assert_array_equal(state.cohesive_broken.numpy()[:4], [0, 0, 0, 1])


def test_without_energy_tracking_history_advances_and_books_stay(device):
    model, state = daughter_model(device, 1, capacity=2)
    set_elements(state, [0], [1], 1.0, unit([1.0, 0.0, 0.0]))
    delta_c = float(state.cohesive_delta_c.numpy()[0])
    for opening in (0.3, 1.2):
        host = np.zeros((model.node_capacity, 3), dtype=np.float32)
        host[1, 0] = opening * delta_c
        state.node_u.assign(host)
        eval_cohesive(model, state, track_energy=False)
    assert int(state.cohesive_broken.numpy()[0]) == 1
    np.testing.assert_allclose(state.cohesive_work_broken.numpy()[0], GAMMA * AREA, rtol=BOOK_RTOL)
    np.testing.assert_array_equal(state.node_damage.numpy()[:2], 1.0)
    np.testing.assert_array_equal(state.node_energy_cohesive.numpy(), 0.0)


@pytest.mark.parametrize("s_over_dc", [None, 0.05])
def test_below_the_opening_threshold_the_force_keeps_p1(device, s_over_dc):
    """Below the threshold s = max(1e-4 δ_c, min(δ_c, f_c dt²/m*)) (kernels/cohesive.py ``open_length``) the force is
    f_env(δ_max) along p1 while loading and f_env(δ_max)(1 − (δ_max − d)/s) while unloading; past it, eq. 6 with
    e = r/d, continuous in magnitude, and no stiffness of the element exceeds f_c/s. ``s_over_dc`` None: the floor
    1e-4 δ_c (a small step: the opening there is float32 round-off of the displacements in a real run); 0.05: a step
    with f_c dt²/m* = 0.05 δ_c."""
    m_star = 1.0 / (1.0 / 2.0 + 1.0 / 3.0)  # the daughters' reduced mass [kg]
    delta_c = critical_opening(1.0)
    dt = 1.0e-7 if s_over_dc is None else math.sqrt(s_over_dc * delta_c * m_star / FC)
    model, state = daughter_model(device, 1, capacity=2, dt=dt)
    p1 = unit([0.0, 0.0, 1.0])
    q = unit([1.0, 1.0, 0.0])
    set_elements(state, [0], [1], 1.0, p1)
    fc, delta_c, _ = stored_f32(state)
    s_open = max(1.0e-4 * delta_c, min(delta_c, fc * dt * dt / m_star))
    for ratio in (0.25, 0.5, 0.3):  # 0.3: below the largest opening so far: the short unloading line
        u = np.zeros((2, 3))
        u[1] = ratio * s_open * q
        f = forces_at(model, state, u)
        d_max = float(state.cohesive_d_max.numpy()[0])
        d = float(np.linalg.norm(u[1].astype(np.float32)))
        expected = envelope(d_max, fc, delta_c, 1.0) * (1.0 - (d_max - d) / s_open)
        np.testing.assert_allclose(f[0], expected * p1, rtol=4 * FORCE_RTOL, atol=FORCE_RTOL * fc)
    u[1] = 2.0 * s_open * q
    f = forces_at(model, state, u)
    d_max = float(state.cohesive_d_max.numpy()[0])
    np.testing.assert_allclose(f[0], envelope(d_max, fc, delta_c, 1.0) * q, rtol=FORCE_RTOL, atol=FORCE_RTOL * fc)
    # Unloading from there: the line to the origin, of slope f_env(δ_max)/δ_max ≤ f_c/s.
    u[1] = 1.5 * s_open * q
    f = forces_at(model, state, u)
    k = float(np.linalg.norm(f[0])) / (1.5 * s_open)
    np.testing.assert_allclose(k, envelope(d_max, fc, delta_c, 1.0) / d_max, rtol=4 * FORCE_RTOL)
    assert k <= fc / s_open


def test_node_with_several_elements_books_each_half(device):
    """Node 0 split twice: elements 0–1 and 0–2 (different Γ A_f) both broken: node 0 holds half of each element's
    Γ A_f, nodes 1 and 2 the other halves; the damage of all three is 1, and the counters add up."""
    model, state = daughter_model(device, 1, per_site=3, capacity=4)
    direction = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=np.float32)
    set_elements(state, [0, 0], [1, 2], [1.0, 0.5], direction, area=[AREA, 3.0 * AREA])
    delta_c = state.cohesive_delta_c.numpy()[:2].astype(np.float64)
    u = np.zeros((3, 3))
    u_prev, f_prev = u.copy(), forces_at(model, state, u)
    work = np.zeros(2)  # trapezoid work of the nodes on each element (float64 reference)
    for opening in np.linspace(0.0, 1.05, 22)[1:]:  # both open gradually past δ_c, in opposite directions
        u[1, 1] = opening * delta_c[0]
        u[2, 1] = -opening * delta_c[1]
        u = u.astype(np.float32).astype(np.float64)
        f = forces_at(model, state, u)
        # Node 1 feels only element 0 and node 2 only element 1: −f_B·Δu_B is each element's work (A = 0 stays).
        work -= np.sum(0.5 * (f_prev + f)[1:] * (u - u_prev)[1:], axis=1)
        u_prev, f_prev = u.copy(), f
    np.testing.assert_array_equal(state.cohesive_broken.numpy()[:2], 1)
    gamma_af = GAMMA * AREA * np.array([1.0, 3.0])
    # The work is Γ A_f but for the break step: ½ f_c Δd²/δ_c (α = 1) and ½ (1 − α) f_c Δd (α = 0.5), Δd = 0.05 δ_c.
    bound = np.array([0.5 * FC * 0.05**2 * delta_c[0], 0.25 * FC * 0.05 * delta_c[1]])
    assert np.all(np.abs(work - gamma_af) <= bound + FORCE_RTOL * gamma_af)  # plus the float32 rounding
    books = spent_books(state)[:3]
    np.testing.assert_allclose(books, 0.5 * np.array([work.sum(), work[0], work[1]]), rtol=FORCE_RTOL)
    np.testing.assert_array_equal(state.node_damage.numpy()[:3], 1.0)
    assert int(state.cohesive_broken_total.numpy()[0]) == 2
    np.testing.assert_allclose(state.cohesive_work_broken.numpy()[0], gamma_af.sum(), rtol=BOOK_RTOL)
    np.testing.assert_allclose(state.cohesive_area_broken.numpy()[0], 4.0 * AREA, rtol=F32_EPS)


def test_daughters_that_cross_in_a_step_leave_the_law_line_at_fracture_energy(device):
    """A blast's first step after a split: B goes 50 δ_c through A, against the birth force f_c along p1 (limestone
    tunnel's elements cross by 40–100 δ_c; issue 28). The element breaks in that step. Oracles: the nodes did the
    trapezoid -½ (f_c p1 + 0)·Δr on it (negative: the force pulled B through), all of which the two lines hold together
    (stored 0 after the break); the law's line holds exactly Γ A_f (eq. 9: what it spends for good is a function of
    δ_max alone, topped up at the break) and the trapezoid line the rest, negative."""
    model, state = daughter_model(device, 1, capacity=2)
    p1 = unit([0.0, 0.6, 0.8])
    set_elements(state, [0], [1], 1.0, p1)
    _, delta_c, _ = stored_f32(state)
    u_prev = np.zeros((2, 3))
    f_prev = forces_at(model, state, u_prev)
    u = np.zeros((2, 3))
    u[1] = (-50.0 * delta_c * p1.astype(np.float64)).astype(np.float32)
    f = forces_at(model, state, u)
    assert int(state.cohesive_broken.numpy()[0]) == 1
    np.testing.assert_array_equal(f, 0.0)
    work = -float(np.sum(0.5 * (f_prev + f) * (u - u_prev)))  # the nodes' work on the element (A does not move)
    assert work < 0.0
    law = float(state.node_energy_cohesive.numpy()[:2].sum())
    spent = float(spent_books(state)[:2].sum())
    np.testing.assert_allclose(law, GAMMA * AREA, rtol=BOOK_RTOL)
    np.testing.assert_allclose(spent, work, rtol=FORCE_RTOL)
    assert cohesive_energy(model, state) == (0.0, pytest.approx(spent, rel=BOOK_RTOL))
