"""Contact stage: skinned neighbour list and sphere contact laws (warpdem.stages.contact, warpdem.kernels.contact).

Oracles:
- neighbour list: the O(N²) brute-force pair set, exact equality at the positions of the last build, and every
  touching pair listed at the current positions;
- normal impact: Hertz theory (peak overlap, peak force, contact duration) and the undamped linear oscillator,
  for sphere–sphere and sphere–wall; restitution: the rebound speed e v;
- oblique sliding impact: the rigid-body Coulomb impulse (tangential speed and spin after impact), and the
  Coulomb inequality |F_t| <= μ F_n at every step;
- a closed cloud: conservation of linear and angular momentum (to float32 round-off) and, with damping and
  friction off, of energy;
- rolling resistance: the deceleration (5/7) μ_r g of a solid sphere rolling on a plane.

Time steps are fractions of the analytic contact time, so every tolerance below follows from the number of steps
per contact, float32 precision and the geometry; each is derived where it is defined.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from warpdem.build.builder import InteractionProps, ModelBuilder
from warpdem.simulation import Simulation
from warpdem.stages.contact import critical_time_step_hertz, neighbor_pairs

EPS32 = float(np.finfo(np.float32).eps)
"""float32 machine epsilon, 2⁻²³: ulp(x) <= EPS32 |x|, and rounding to nearest errs by at most ulp/2."""

# Material of the impact tests (glass-like density, soft enough for overlaps of a few % of the radius, so that the
# float32 differences of the centres resolve them finely).
RADIUS = 0.01  # [m]
DENSITY = 2500.0  # [kg/m³]
YOUNG = 1.0e7  # [Pa]
POISSON = 0.3  # [-]
IMPACT_SPEED = 1.0  # relative approach speed [m/s]

HERTZ_DURATION_FACTOR = 2.0 * 0.4 * math.sqrt(math.pi) * math.gamma(0.4) / math.gamma(0.9)
"""t_c = HERTZ_DURATION_FACTOR δ_max / v = 2.9432 δ_max / v. Energy conservation m* δ'²/2 + (8/15) E* √R* δ^{5/2}
= m* v²/2 gives δ' = v sqrt(1 - (δ/δ_max)^{5/2}), so t_c = 2 (δ_max/v) ∫₀¹ (1 - x^{5/2})^{-1/2} dx
= 2 (δ_max/v) (2/5) B(2/5, 1/2) = (4/5) √π Γ(2/5)/Γ(9/10) δ_max/v."""

STEPS_PER_CONTACT = 2000
"""dt = t_c / STEPS_PER_CONTACT in the impact tests."""

PEAK_RTOL = 1.0e-3
"""Peak overlap and force. Velocity Verlet's error over one contact is O((ω dt)²) = (π/2000)² ≈ 2.5e-6. The
centres are float64 (their drift rounds by 2⁻⁵³ |x|, negligible); the force law sees their difference rounded to
float32 (|x_i - x_j| ≈ 2r: by at most ulp(2r)/2 = 9.3e-10 m per evaluation), and these roundings vary from step to
step during the contact, so over 2000 steps they move the peak by about 4σ = 4 √(2000/12) ulp(2r) ≈ 1e-7 m, i.e.
4e-4 of the smallest peak overlap here (linear model, δ_max = 2.3e-4 m). 1e-3 covers the sum with a factor 2.5 to
spare."""

DURATION_RTOL = 2.0 / STEPS_PER_CONTACT
"""Contact duration counted in whole steps: it can be off by at most one step at each end."""

RESTITUTION_RTOL = 2.0 / STEPS_PER_CONTACT
"""Rebound speed. The dashpot sees the half-step velocity v_{n+1/2}, half a step old, which shifts e by O(dt/t_c)
(measured ≈ 0.3/STEPS_PER_CONTACT); float32 velocities add ~1e-5. Two steps' worth covers both."""

# Oblique impact: stiff spheres (δ_max/r = 0.50 %) sliding on a wall.
OBLIQUE_YOUNG = 1.0e10  # [Pa]
OBLIQUE_NORMAL_SPEED = 1.0  # [m/s]
OBLIQUE_TANGENTIAL_SPEED = 3.0  # [m/s], > (7/2) μ (1 + e) v_n = 1.575 m/s: slides throughout
OBLIQUE_FRICTION = 0.3
OBLIQUE_STEPS = 1000
OBLIQUE_RESTITUTION_RTOL = 2.0 / OBLIQUE_STEPS
"""Normal rebound of the oblique impact: as RESTITUTION_RTOL, at OBLIQUE_STEPS steps per contact."""
OBLIQUE_RTOL = 1.0e-2
"""Rigid-body impulse result. The friction torque acts at the lever r − δ instead of r, so ω′ is low by
∫δ F_n dt / (r ∫F_n dt) < δ_max/r = 0.50 % (asserted below); the normal impulse (1 + e) m v_n carries the
restitution error, <= OBLIQUE_RESTITUTION_RTOL = 2e-3. 1 % covers the sum."""

COULOMB_RTOL = 4.0 * EPS32
"""|F_t| <= μ F_n holds exactly in real arithmetic; F_t is rescaled to μ F_n in float32 (a few roundings)."""

# Closed cloud of spheres.
CLOUD_COUNT = 150
CLOUD_YOUNG = 1.0e8  # [Pa]
CLOUD_STEPS = 4000
CLOUD_FRAMES = 400  # frames of CLOUD_STEPS / CLOUD_FRAMES = 10 steps: shorter than any contact (~50 steps)
CLOUD_STEPS_PER_CONTACT = 50  # dt = (shortest Hertz contact time of the cloud) / 50
MIN_COLLISIONS = 100
MOMENTUM_SIGMAS = 4.0
"""Forces are pairwise opposite and the torques balance, (x_i − x_j) × F_t = (c_i + c_j) n × F_t, so velocity
Verlet conserves P and L exactly in real arithmetic; what is left is float32 rounding of the state. Bounds used,
as MOMENTUM_SIGMAS standard deviations of rounding errors uniform in ±ulp/2 (σ = ulp/√12), independent between
spheres:
- P: each of the <= 2n kicks of a sphere rounds v by ulp(v)/2 <= EPS32 |v|/2, in varying amounts (the
  accelerations change every step), so σ_P = EPS32 √(2n/12) sqrt(Σ (m |v|)²);
- L: a drift x ← x + dt v repeats almost the same increment between collisions, so its rounding is systematic:
  after n steps a sphere is off by up to n ulp(x)/2 (the centres are float64 and round far less; the float32 bound
  is kept), σ = n ulp(x)/√12 <= n EPS32 |x|/√12 per sphere, giving
  σ_L = n EPS32 / √12 sqrt(Σ (m |x| |v|)²), plus kick terms like σ_P's for |x| m v and I ω.
Measured: |ΔP| and |ΔL| reach 5 % and 2 % of these tolerances."""

ENERGY_RTOL = (math.pi / CLOUD_STEPS_PER_CONTACT) ** 2
"""Velocity Verlet conserves a shadow energy; the true energy differs from it by O((ω dt)²) of the energy held in
contacts, with ω dt <= π / CLOUD_STEPS_PER_CONTACT ≈ 0.063: at most 3.9e-3 of the total."""

# Rolling resistance (a stiffer material: static overlap δ₀/r = 5.8e-4).
ROLLING_YOUNG = 1.0e8  # [Pa]
ROLLING_FRICTION = 0.1  # μ_r [-]
ROLLING_SPEED = 0.1  # initial rolling speed [m/s]
GRAVITY = 9.81  # [m/s²]
ROLLING_RTOL = 5.0e-3
"""Spin-down time. Bounds: the tangential force acts at the lever c = r − δ₀ (δ₀/r = 5.8e-4 here), which makes the
deceleration μ_r g r c / ((2/5) r² + c²) = (5/7) μ_r g (1 + (3/7) δ₀/r + ...), 2.5e-4 faster; float32 velocity
kicks of a nearly constant increment round systematically, by at most n ulp(v₀) / v₀ ≈ 6400 × 7.5e-8 = 5e-4 over
the n ≈ 6400 steps (dt = ROLLING_DT_FACTOR × the Rayleigh step); and the Mindlin spring slips while it builds up
the rolling friction force (measured slip < 0.4 % of v₀ for well under 1 % of the run). 5e-3 covers their sum
(~1e-3) with a factor 5 to spare."""
ROLLING_DT_FACTOR = 0.2

# Neighbour list.
NEIGHBOR_COUNT = 400
NEIGHBOR_BOX = 0.16  # [m]
NEIGHBOR_FRAMES = 40
NEIGHBOR_STEPS_PER_FRAME = 25
MIN_REBUILD_FRAMES = 5


# ----------------------------------------------------------------------------------------------------------------
# Helpers


def sphere_mass(radius: float, density: float = DENSITY) -> float:
    return density * 4.0 / 3.0 * math.pi * radius**3


def effective_modulus(young: float) -> float:
    """E* of two bodies of one material: 1 / (2 (1 − ν²) / E) [Pa]."""
    return young / (2.0 * (1.0 - POISSON**2))


@dataclass
class ImpactReference:
    """Analytic head-on impact: effective mass [kg], peak overlap [m], peak force [N], contact time [s]."""

    mstar: float
    delta_max: float
    force_max: float
    t_contact: float


def impact_reference(normal: str, target: str, speed: float = IMPACT_SPEED, young: float = YOUNG) -> ImpactReference:
    """Elastic head-on impact of two equal spheres (target "sphere") or of a sphere on a wall ("wall").

    Sphere–sphere: m* = m/2, R* = r/2. Sphere–wall (infinite mass and radius): m* = m, R* = r.
    Hertz: δ_max = (15 m* v² / (16 E* √R*))^{2/5}, F_max = (4/3) E* √R* δ_max^{3/2}, t_c = 2.9432 δ_max / v.
    Linear (k_n = 2 E_a r_a E_b r_b / (E_a r_a + E_b r_b) = E r for equal materials and radii, the wall taking
    r_b = r_a): a half period of the undamped oscillator, δ_max = v √(m*/k_n), F_max = k_n δ_max,
    t_c = π √(m*/k_n).
    """
    m = sphere_mass(RADIUS)
    mstar, rstar = (0.5 * m, 0.5 * RADIUS) if target == "sphere" else (m, RADIUS)
    if normal == "hertz":
        k = 4.0 / 3.0 * effective_modulus(young) * math.sqrt(rstar)
        delta_max = (15.0 * mstar * speed**2 / (16.0 * effective_modulus(young) * math.sqrt(rstar))) ** 0.4
        return ImpactReference(mstar, delta_max, k * delta_max**1.5, HERTZ_DURATION_FACTOR * delta_max / speed)
    kn = young * RADIUS
    delta_max = speed * math.sqrt(mstar / kn)
    return ImpactReference(mstar, delta_max, kn * delta_max, math.pi * math.sqrt(mstar / kn))


def impact_simulation(
    device: str, normal: str, target: str, restitution: float, dt: float, speed: float = IMPACT_SPEED
) -> Simulation:
    """Head-on impact along x, no gravity, no friction; the bodies touch 3.5 steps after the start."""
    b = ModelBuilder(normal=normal, gravity=(0.0, 0.0, 0.0))
    b.add_material("grain", DENSITY, YOUNG, POISSON)
    b.default_interaction = InteractionProps(friction=0.0, restitution=restitution)
    gap = 3.5 * speed * dt
    if target == "sphere":
        b.add_sphere((-RADIUS - 0.5 * gap, 0.0, 0.0), RADIUS, "grain", velocity=(0.5 * speed, 0.0, 0.0))
        b.add_sphere((RADIUS + 0.5 * gap, 0.0, 0.0), RADIUS, "grain", velocity=(-0.5 * speed, 0.0, 0.0))
    else:
        b.add_plane_wall((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), "grain")
        b.add_sphere((RADIUS + gap, 0.0, 0.0), RADIUS, "grain", velocity=(-speed, 0.0, 0.0))
    model, state = b.finalize(device, dt=dt, sort=False)
    return Simulation(model, state)


def impact_overlap(sim: Simulation, target: str) -> float:
    """Overlap now [m], from the float64 centres."""
    x = sim.state.particle_q.numpy()[:, 0].astype(np.float64)
    return 2.0 * RADIUS - (x[1] - x[0]) if target == "sphere" else RADIUS - x[0]


def separation_speed(sim: Simulation, target: str) -> float:
    """Normal speed at which the bodies move apart [m/s]."""
    v = sim.state.particle_qd.numpy()[:, 0].astype(np.float64)
    return v[1] - v[0] if target == "sphere" else v[0]


def random_spheres(
    rng: np.random.Generator, count: int, r_min: float, r_max: float, lo: float, hi: float
) -> tuple[np.ndarray, np.ndarray]:
    """Non-overlapping spheres with radii uniform in [r_min, r_max] and centres inside the cube [lo, hi]³
    (random sequential addition)."""
    radii = rng.uniform(r_min, r_max, count)
    centers = np.zeros((count, 3))
    k = 0
    while k < count:
        p = rng.uniform(lo + radii[k], hi - radii[k], 3)
        if np.all(np.linalg.norm(centers[:k] - p, axis=1) > radii[:k] + radii[k]):
            centers[k] = p
            k += 1
    return centers, radii


def pairs_within(q: np.ndarray, radius: np.ndarray, skin: float) -> set[tuple[int, int]]:
    """Brute-force O(N²) set of pairs i < j with |x_i − x_j| < r_i + r_j + skin, in the arithmetic of
    is_neighbor_candidate: d = x_i − x_j formed in float64 and rounded to float32, then d·d < (r_i + r_j + skin)² in
    float32."""
    q = q.astype(np.float64)
    r = radius.astype(np.float32)
    d = (q[:, None, :] - q[None, :, :]).astype(np.float32)
    d2 = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
    cutoff = r[:, None] + r[None, :] + np.float32(skin)
    i, j = np.nonzero(np.triu(d2 < cutoff * cutoff, 1))
    return set(zip(i.tolist(), j.tolist(), strict=True))


def touching_pairs(q: np.ndarray, radius: np.ndarray) -> set[tuple[int, int]]:
    """Pairs i < j that overlap, |x_i − x_j| < r_i + r_j (float64)."""
    q = q.astype(np.float64)
    r = radius.astype(np.float64)
    dist = np.linalg.norm(q[:, None, :] - q[None, :, :], axis=2)
    i, j = np.nonzero(np.triu(dist < r[:, None] + r[None, :], 1))
    return set(zip(i.tolist(), j.tolist(), strict=True))


# ----------------------------------------------------------------------------------------------------------------
# Neighbour list


def neighbor_simulation(device: str, max_neighbors: int) -> Simulation:
    """NEIGHBOR_COUNT polydisperse spheres (r = 5..10 mm, solid fraction 0.19) with random velocities (σ = 1 m/s)
    in a closed box, gravity on, friction and damping on."""
    rng = np.random.default_rng(1)
    centers, radii = random_spheres(rng, NEIGHBOR_COUNT, 0.005, 0.01, 0.0, NEIGHBOR_BOX)
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("grain", DENSITY, 1.0e8, POISSON)
    b.default_interaction = InteractionProps(friction=0.5, restitution=0.8)
    b.add_spheres(centers, radii, "grain", velocity=rng.normal(0.0, 1.0, (NEIGHBOR_COUNT, 3)))
    b.add_box_walls((0.0, 0.0, 0.0), (NEIGHBOR_BOX,) * 3, "grain")
    model, state = b.finalize(device, max_neighbors=max_neighbors)
    return Simulation(model, state)


def check_neighbor_frames(sim: Simulation, frames: int) -> int:
    """Advance frame by frame; after each, the list must equal the brute-force set at the positions of the last
    build and contain every pair touching now. Returns the number of frames in which the list was rebuilt."""
    previous_build = sim.state.particle_q_at_build.numpy().copy()
    rebuild_frames = 0
    for frame in range(frames):
        sim.advance(NEIGHBOR_STEPS_PER_FRAME)
        model, state = sim.model, sim.state  # a regrowth replaces them
        radius = model.particle_radius.numpy()
        at_build = state.particle_q_at_build.numpy()
        if not np.array_equal(at_build, previous_build):
            rebuild_frames += 1
        previous_build = at_build.copy()
        listed = set(map(tuple, neighbor_pairs(model, state).tolist()))
        expected = pairs_within(at_build, radius, model.skin)
        assert listed == expected, (
            f"frame {frame}: {len(listed - expected)} listed pairs not within r_i + r_j + skin "
            f"(e.g. {sorted(listed - expected)[:3]}), {len(expected - listed)} pairs within it missing "
            f"(e.g. {sorted(expected - listed)[:3]})"
        )
        missing = touching_pairs(state.particle_q.numpy(), radius) - listed
        assert not missing, f"frame {frame}: touching pairs not in the neighbour list: {sorted(missing)[:5]}"
    return rebuild_frames


def test_neighbor_list_matches_brute_force(device: str) -> None:
    sim = neighbor_simulation(device, max_neighbors=16)
    rebuild_frames = check_neighbor_frames(sim, NEIGHBOR_FRAMES)
    assert sim.growths == 0
    assert rebuild_frames >= MIN_REBUILD_FRAMES, f"only {rebuild_frames} frames rebuilt the list"


def test_neighbor_list_regrown_after_overflow_matches_brute_force(device: str) -> None:
    # Two slots per sphere: the very first build (in Simulation.__init__) overflows; the grown list must hold
    # exactly the same pairs as a list that was large enough from the start.
    sim = neighbor_simulation(device, max_neighbors=2)
    check_neighbor_frames(sim, 4)
    assert sim.growths >= 1, "the list never overflowed: the regrowth path was not exercised"


# ----------------------------------------------------------------------------------------------------------------
# Normal impact


@pytest.mark.parametrize("target", ["sphere", "wall"])
@pytest.mark.parametrize("normal", ["hertz", "linear"])
def test_elastic_normal_impact_matches_theory(device: str, normal: str, target: str) -> None:
    ref = impact_reference(normal, target)
    dt = ref.t_contact / STEPS_PER_CONTACT
    sim = impact_simulation(device, normal, target, restitution=1.0, dt=dt)
    overlap, force = [], []
    for _ in range(2 * STEPS_PER_CONTACT):
        sim.advance(1)
        overlap.append(impact_overlap(sim, target))
        force.append(abs(float(sim.state.particle_f.numpy()[0, 0])))  # contact force at the new positions
        if overlap[-1] <= 0.0 < max(overlap):
            break
    overlap, force = np.array(overlap), np.array(force)
    assert overlap[-1] <= 0.0, "the contact did not end within twice the theoretical duration"
    np.testing.assert_allclose(overlap.max(), ref.delta_max, rtol=PEAK_RTOL)
    np.testing.assert_allclose(force.max(), ref.force_max, rtol=PEAK_RTOL)
    np.testing.assert_allclose(np.count_nonzero(overlap > 0.0) * dt, ref.t_contact, rtol=DURATION_RTOL)
    np.testing.assert_allclose(separation_speed(sim, target), IMPACT_SPEED, rtol=RESTITUTION_RTOL)


@pytest.mark.parametrize("restitution", [0.5, 0.9])
@pytest.mark.parametrize("target", ["sphere", "wall"])
@pytest.mark.parametrize("normal", ["hertz", "linear"])
def test_rebound_speed_is_restitution_times_impact_speed(
    device: str, normal: str, target: str, restitution: float
) -> None:
    # v_out = e v_in: the damping of both clamped laws is set from e (warpdem.stages.restitution), for any m*, k, v.
    ref = impact_reference(normal, target)
    dt = ref.t_contact / STEPS_PER_CONTACT
    sim = impact_simulation(device, normal, target, restitution=restitution, dt=dt)
    # A damped contact is shorter than the elastic one; after 1.5 elastic contact times the bodies are apart.
    sim.advance(int(1.5 * STEPS_PER_CONTACT))
    assert impact_overlap(sim, target) < 0.0
    np.testing.assert_allclose(separation_speed(sim, target), restitution * IMPACT_SPEED, rtol=RESTITUTION_RTOL)


# ----------------------------------------------------------------------------------------------------------------
# Oblique impact


def oblique_simulation(device: str, restitution: float) -> tuple[Simulation, float]:
    """A sphere hits the wall z = 0 with normal speed v_n and tangential speed v_t along +x, no spin.

    Returns the simulation and δ_max/r of the impact."""
    vn = OBLIQUE_NORMAL_SPEED
    ref = impact_reference("hertz", "wall", speed=vn, young=OBLIQUE_YOUNG)
    dt = ref.t_contact / OBLIQUE_STEPS
    b = ModelBuilder(normal="hertz", tangential="mindlin", gravity=(0.0, 0.0, 0.0))
    b.add_material("grain", DENSITY, OBLIQUE_YOUNG, POISSON)
    b.default_interaction = InteractionProps(friction=OBLIQUE_FRICTION, restitution=restitution)
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "grain")
    b.add_sphere((0.0, 0.0, RADIUS + 3.5 * vn * dt), RADIUS, "grain", velocity=(OBLIQUE_TANGENTIAL_SPEED, 0.0, -vn))
    model, state = b.finalize(device, dt=dt, sort=False)
    return Simulation(model, state), ref.delta_max / RADIUS


@pytest.mark.parametrize("restitution", [0.5, 1.0])
def test_oblique_sliding_impact_matches_coulomb_impulse(device: str, restitution: float) -> None:
    # Sliding throughout (v_t > (7/2) μ (1 + e) v_n), the friction impulse is μ times the normal impulse
    # (1 + e) m v_n and acts at the contact point (-r e_z):
    #   v_t' = v_t − μ (1 + e) v_n,   ω_y' = (5/2) μ (1 + e) v_n / r,
    # from m Δv_t = −J_t, I Δω = (−r e_z) × (−J_t e_x) = r J_t e_y, I = (2/5) m r², J_t = μ (1 + e) m v_n.
    vn, vt, mu, e = OBLIQUE_NORMAL_SPEED, OBLIQUE_TANGENTIAL_SPEED, OBLIQUE_FRICTION, restitution
    assert vt > 3.5 * mu * (1.0 + e) * vn
    sim, overlap_ratio = oblique_simulation(device, restitution)
    assert overlap_ratio < 0.0051  # the lever-arm bound behind OBLIQUE_RTOL
    sim.advance(2 * OBLIQUE_STEPS)
    v = sim.state.particle_qd.numpy()[0].astype(np.float64)
    omega = sim.state.particle_omega.numpy()[0].astype(np.float64)
    impulse = mu * (1.0 + e) * vn  # friction impulse per unit mass [m/s]
    np.testing.assert_allclose(v[2], e * vn, rtol=OBLIQUE_RESTITUTION_RTOL)
    np.testing.assert_allclose(v[0], vt - impulse, rtol=OBLIQUE_RTOL)
    np.testing.assert_allclose(omega[1], 2.5 * impulse / RADIUS, rtol=OBLIQUE_RTOL)
    np.testing.assert_allclose([v[1], omega[0], omega[2]], 0.0, atol=EPS32 * vt)


def test_tangential_force_never_exceeds_coulomb_limit(device: str) -> None:
    # Coulomb: |F_t| <= μ F_n at every step, whatever the spring and dashpot say (damped, sliding contact).
    sim, _ = oblique_simulation(device, restitution=0.5)
    ratios = []
    for _ in range(int(1.2 * OBLIQUE_STEPS)):
        sim.advance(1)
        f = sim.state.particle_f.numpy()[0].astype(np.float64)
        if f[2] > 0.0:
            ratios.append(math.hypot(f[0], f[1]) / (OBLIQUE_FRICTION * f[2]))
    ratios = np.array(ratios)
    assert len(ratios) > OBLIQUE_STEPS // 2
    worst = int(np.argmax(ratios))
    assert ratios.max() <= 1.0 + COULOMB_RTOL, (
        f"|F_t| / (μ F_n) reaches {ratios.max():.3f} at contact step {worst} of {len(ratios)}; "
        f"{np.count_nonzero(ratios > 1.0 + COULOMB_RTOL)} steps exceed the Coulomb limit"
    )


def test_a_reevaluation_between_steps_keeps_a_sliding_spring_and_the_books(device: str) -> None:
    # Invariant: an evaluation at dt = 0 (the set-up, or the re-evaluation after a topology pass) moves nothing, so it
    # changes no contact history and no energy line. The case that broke it: a sliding contact (spring at the Coulomb
    # limit μ F_n, F_n with its dashpot) re-evaluated between steps, where the dashpot sees the velocity v_{n+1} in
    # place of the step's v_{n+1/2}; the limit then differs and a spring cut back to it lost ½ k_t (|ξ|² − |ξ'|²) from
    # the books (−77 J over masonry_tunnel_blast's conversion passes). Tolerance: the spring bit for bit, the
    # elastic line exactly (the same float32 terms summed in the same order), the lines' sum to its float64 rounding.
    sim, _ = oblique_simulation(device, restitution=0.5)
    sim.advance(OBLIQUE_STEPS // 2)  # mid-impact: compressing or rebounding, and sliding
    shear = sim.state.wall_shear.numpy().copy()
    assert np.linalg.norm(shear[0]) > 0.0
    before = sim.energy()
    sim.evaluate_forces()
    after = sim.energy()
    np.testing.assert_array_equal(sim.state.wall_shear.numpy(), shear)
    assert after.elastic == before.elastic
    # Every line but the shadow term (the forces, and so it, may move): their sum to the float64 rounding of the sum.
    unshadowed = before.total + before.shadow
    np.testing.assert_allclose(after.total + after.shadow, unshadowed, rtol=8 * np.finfo(np.float64).eps)


# ----------------------------------------------------------------------------------------------------------------
# Closed cloud: conservation


def cloud_simulation(device: str, friction: float, restitution: float) -> Simulation:
    """CLOUD_COUNT spheres in a 0.2 m cube, no walls, no gravity, converging on the centre (v = −8 x + noise)
    with random spins, dt = (shortest Hertz contact time) / CLOUD_STEPS_PER_CONTACT."""
    rng = np.random.default_rng(3)
    centers, radii = random_spheres(rng, CLOUD_COUNT, 0.008, 0.012, -0.1, 0.1)
    velocity = -8.0 * centers + rng.normal(0.0, 0.3, (CLOUD_COUNT, 3))
    spin = rng.normal(0.0, 50.0, (CLOUD_COUNT, 3))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("grain", DENSITY, CLOUD_YOUNG, POISSON)
    b.default_interaction = InteractionProps(friction=friction, restitution=restitution)
    b.add_spheres(centers, radii, "grain", velocity=velocity, angular_velocity=spin)
    # The shortest contact: the two smallest spheres meeting at twice the largest speed (t_c ∝ m*^{2/5} v^{-1/5}).
    r_min = float(radii.min())
    mstar, rstar = 0.5 * sphere_mass(r_min), 0.5 * r_min
    speed = 2.0 * float(np.linalg.norm(velocity, axis=1).max())
    delta_max = (15.0 * mstar * speed**2 / (16.0 * effective_modulus(CLOUD_YOUNG) * math.sqrt(rstar))) ** 0.4
    t_contact = HERTZ_DURATION_FACTOR * delta_max / speed
    model, state = b.finalize(device, dt=t_contact / CLOUD_STEPS_PER_CONTACT)
    return Simulation(model, state)


def cloud_run(sim: Simulation) -> int:
    """Run CLOUD_STEPS steps in CLOUD_FRAMES frames; returns the number of collisions (pairs that start to touch
    between two frames; frames are shorter than any contact, so none is missed)."""
    radius = sim.model.particle_radius.numpy()
    touching = touching_pairs(sim.state.particle_q.numpy(), radius)
    collisions = 0
    for _ in range(CLOUD_FRAMES):
        sim.advance(CLOUD_STEPS // CLOUD_FRAMES)
        now = touching_pairs(sim.state.particle_q.numpy(), radius)
        collisions += len(now - touching)
        touching = now
    return collisions


def momenta(sim: Simulation) -> tuple[np.ndarray, np.ndarray]:
    """Total linear momentum P = Σ m v [kg m/s] and angular momentum about the origin L = Σ (x × m v + I ω)
    [kg m²/s], in float64 from the float32 state."""
    m = sim.model.particle_mass.numpy().astype(np.float64)
    inertia = 0.4 * m * sim.model.particle_radius.numpy().astype(np.float64) ** 2
    x = sim.state.particle_q.numpy().astype(np.float64)
    p = m[:, None] * sim.state.particle_qd.numpy().astype(np.float64)
    spin = inertia[:, None] * sim.state.particle_omega.numpy().astype(np.float64)
    return p.sum(axis=0), np.cross(x, p).sum(axis=0) + spin.sum(axis=0)


def momentum_roundoff(sim: Simulation, n: int) -> tuple[float, float]:
    """Tolerances on P and L after n steps from float32 round-off (MOMENTUM_SIGMAS standard deviations; the
    derivation is under MOMENTUM_SIGMAS)."""
    m = sim.model.particle_mass.numpy().astype(np.float64)
    inertia = 0.4 * m * sim.model.particle_radius.numpy().astype(np.float64) ** 2
    mv = m * np.linalg.norm(sim.state.particle_qd.numpy().astype(np.float64), axis=1)
    xmv = np.linalg.norm(sim.state.particle_q.numpy().astype(np.float64), axis=1) * mv
    iw = inertia * np.linalg.norm(sim.state.particle_omega.numpy().astype(np.float64), axis=1)
    kicks = EPS32 * math.sqrt(2.0 * n / 12.0)  # 2n kicks of varying size: random walk
    drifts = EPS32 * n / math.sqrt(12.0)  # n drifts of a nearly constant increment: systematic per sphere
    sigma_p = kicks * math.sqrt(np.sum(mv**2))
    sigma_l = drifts * math.sqrt(np.sum(xmv**2)) + kicks * math.sqrt(np.sum(xmv**2 + iw**2))
    return MOMENTUM_SIGMAS * sigma_p, MOMENTUM_SIGMAS * sigma_l


def test_closed_cloud_conserves_momentum(device: str) -> None:
    sim = cloud_simulation(device, friction=0.5, restitution=0.5)
    p0, l0 = momenta(sim)
    atol_p, atol_l = momentum_roundoff(sim, CLOUD_STEPS)
    collisions = cloud_run(sim)
    p, angular = momenta(sim)
    assert collisions >= MIN_COLLISIONS
    np.testing.assert_allclose(p, p0, rtol=0.0, atol=atol_p)
    np.testing.assert_allclose(angular, l0, rtol=0.0, atol=atol_l)
    # The collisions were not trivial: friction and damping took a good part of the kinetic energy.
    balance = sim.energy()
    assert balance.dissipated_friction > 0.01 * balance.kinetic
    assert balance.dissipated_damping > 0.01 * balance.kinetic


def test_elastic_frictionless_cloud_conserves_energy(device: str) -> None:
    # Restitution 1 and friction 0: no dashpot, no tangential force; kinetic + Hertz elastic energy is conserved.
    sim = cloud_simulation(device, friction=0.0, restitution=1.0)
    e0 = sim.energy()
    collisions = cloud_run(sim)
    e1 = sim.energy()
    assert collisions >= MIN_COLLISIONS
    # No tangential force but the float32 rounding of f - (f·n) n, which the books follow as the spheres do.
    assert abs(e1.dissipated_friction) <= EPS32 * (e0.kinetic + e0.elastic) and e1.stiffness_change == 0.0
    np.testing.assert_allclose(e1.kinetic + e1.elastic, e0.kinetic + e0.elastic, rtol=ENERGY_RTOL)
    # The normal line books -W - ΔU with W Verlet's trapezoid of the Hertz force: what the scheme's work misses of
    # the Hertz potential, O((ω dt)²) per collision, of either sign; no dashpot works.
    assert abs(e1.dissipated_damping) <= ENERGY_RTOL * (e0.kinetic + e0.elastic)


# ----------------------------------------------------------------------------------------------------------------
# Rolling resistance


def test_constant_torque_rolling_resistance_stops_sphere(device: str) -> None:
    # Sphere rolling without slip on a plane (v = r ω) under gravity, resisting torque M = μ_r R* F_n = μ_r r m g.
    # Rolling friction force F on the sphere at the contact point: m a = F, I α = −r F − M, a = r α
    # ⇒ a = −M r / (I + m r²) = −(5/7) μ_r g, so it stops at t_stop = v₀ / ((5/7) μ_r g).
    m = sphere_mass(RADIUS)
    estar = effective_modulus(ROLLING_YOUNG)
    overlap0 = (m * GRAVITY / (4.0 / 3.0 * estar * math.sqrt(RADIUS))) ** (2.0 / 3.0)  # static Hertz overlap
    b = ModelBuilder(normal="hertz", tangential="mindlin", rolling="constant_torque", gravity=(0.0, 0.0, -GRAVITY))
    b.add_material("grain", DENSITY, ROLLING_YOUNG, POISSON)
    b.default_interaction = InteractionProps(friction=0.5, restitution=0.5, rolling_friction=ROLLING_FRICTION)
    b.add_plane_wall((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "grain")
    b.add_sphere(
        (0.0, 0.0, RADIUS - overlap0),
        RADIUS,
        "grain",
        velocity=(ROLLING_SPEED, 0.0, 0.0),
        angular_velocity=(0.0, ROLLING_SPEED / RADIUS, 0.0),
    )
    dt = ROLLING_DT_FACTOR * critical_time_step_hertz(RADIUS, DENSITY, ROLLING_YOUNG, POISSON)
    model, state = b.finalize(device, dt=dt, sort=False)
    sim = Simulation(model, state)
    decel = 5.0 / 7.0 * ROLLING_FRICTION * GRAVITY
    t_stop = ROLLING_SPEED / decel
    chunk = max(1, round(t_stop / model.dt / 200))
    times, speeds = [0.0], [ROLLING_SPEED]
    while speeds[-1] > 0.0 and times[-1] < 1.5 * t_stop:
        sim.advance(chunk)
        times.append(sim.time)
        speeds.append(float(sim.state.particle_qd.numpy()[0, 0]))
    assert speeds[-1] <= 0.0, "the sphere did not stop within 1.5 t_stop"
    # v(t) is linear until it stops: interpolate the zero crossing between the last two frames.
    t0, t1, v0, v1 = times[-2], times[-1], speeds[-2], speeds[-1]
    t_cross = t0 + v0 * (t1 - t0) / (v0 - v1)
    np.testing.assert_allclose(t_cross, t_stop, rtol=ROLLING_RTOL)
