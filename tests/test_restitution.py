"""Restitution ↔ damping maps of the clamped normal contact laws (warpdem.stages.restitution).

Oracles:
- an independent small-step integration of the dimensional equation of motion, m* δ'' = -max(0, F(δ, δ')), run
  until the spheres separate (δ < 0), for two masses/stiffnesses/impact speeds per model;
- the closed form of the clamped linear model (Schwager & Pöschel 2007): contact ends at the first zero of
  k δ + γ δ', giving e = exp(-ζ t*) (underdamped) or e = λ₁² exp(λ₁ t*) (overdamped), derived below;
- the textbook unclamped linear result e = exp(-π ζ / sqrt(1 - ζ²)), reproduced by the same RK4 integrator with
  the contact ending at δ = 0 instead of at the force zero.

Tolerances:
- DIMENSIONAL_TOL: the reference integrator is second order with dt = t_contact / 20000, so its error is
  O(dt²) ~ 1e-8 away from the clamp, and O(dt · |F'|) ~ 5e-5 from the kink where the force is clamped; 1e-3
  (the brief's requirement) leaves ample margin.
- CLOSED_FORM_TOL: RK4 with 200 steps per unit time has local error ~ (1/200)⁵; 1e-8 relative covers it.
- ROUND_TRIP_TOL: the inverse maps stop at |e(p) - e| <= 1e-11 and |de/dp| is O(0.1..1) for the values used.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from warpdem.stages import restitution
from warpdem.stages.restitution import (
    hertz_damping_coefficient,
    linear_damping_ratio,
    restitution_hertz,
    restitution_linear,
)

DIMENSIONAL_TOL = 1e-3
CLOSED_FORM_TOL = 1e-8
CLASSIC_TOL = 1e-5
ROUND_TRIP_TOL = 1e-7
REFERENCE_STEPS = 20_000

RESTITUTIONS = (0.1, 0.5, 0.9)

# (effective mass m* [kg], linear stiffness k [N/m], impact speed v0 [m/s])
LINEAR_CASES = ((2.0e-3, 1.0e5, 0.5), (3.0, 2.0e8, 20.0))
# (effective mass m* [kg], effective modulus E* [Pa], effective radius R* [m], impact speed v0 [m/s])
HERTZ_CASES = ((1.0e-3, 3.0e10, 5.0e-3, 0.01), (40.0, 1.0e9, 0.2, 50.0))


def _impact(force: Callable[[float, float], float], mass: float, v0: float, dt: float) -> tuple[float, float]:
    """Rebound speed and contact duration of m δ'' = -max(0, force(δ, δ')), δ(0) = 0, δ'(0) = v0.

    Velocity Verlet with a predicted velocity in the force (second order for velocity-dependent forces), run until
    δ < 0: after the clamp the force stays 0, so the velocity at separation is the rebound velocity.
    """
    delta, vel, t = 0.0, v0, 0.0
    acc = -max(0.0, force(delta, vel)) / mass
    for _ in range(10 * REFERENCE_STEPS):
        delta_new = delta + vel * dt + 0.5 * acc * dt * dt
        acc_new = -max(0.0, force(max(delta_new, 0.0), vel + acc * dt)) / mass
        vel = vel + 0.5 * (acc + acc_new) * dt
        delta, acc, t = delta_new, acc_new, t + dt
        if delta < 0.0:
            return -vel, t
    raise AssertionError("the spheres did not separate")


def _restitution_reference(force: Callable[[float, float], float], mass: float, v0: float, t_scale: float) -> float:
    """Independent restitution: a pilot run finds the contact time, the final run uses dt = t_contact / 20000."""
    _, t_contact = _impact(force, mass, v0, t_scale / 200.0)
    rebound, _ = _impact(force, mass, v0, t_contact / REFERENCE_STEPS)
    return rebound / v0


@pytest.mark.parametrize("e", RESTITUTIONS)
def test_linear_matches_dimensional_integration(e: float) -> None:
    zeta = linear_damping_ratio(e)
    for mass, k, v0 in LINEAR_CASES:
        gamma = 2.0 * zeta * math.sqrt(mass * k)
        e_ref = _restitution_reference(lambda d, v, k=k, g=gamma: k * d + g * v, mass, v0, math.sqrt(mass / k))
        np.testing.assert_allclose(e_ref, e, rtol=DIMENSIONAL_TOL)
        np.testing.assert_allclose(restitution_linear(zeta), e, rtol=ROUND_TRIP_TOL)


@pytest.mark.parametrize("e", RESTITUTIONS)
def test_hertz_matches_dimensional_integration_for_any_impact_speed(e: float) -> None:
    c = hertz_damping_coefficient(e)
    results = []
    for mass, estar, rstar, v0 in HERTZ_CASES:
        k = 4.0 / 3.0 * estar * math.sqrt(rstar)
        eta = c * math.sqrt(mass * k)
        t_scale = (mass * v0**2 / k) ** 0.4 / v0  # T = L / v0 with L = (m* v0² / k)^{2/5}

        def force(d: float, v: float, k: float = k, eta: float = eta) -> float:
            return k * d**1.5 + eta * d**0.25 * v

        results.append(_restitution_reference(force, mass, v0, t_scale))
    # Impact speeds 0.01 and 50 m/s (and different m*, E*, R*) give the same restitution: it depends on c only.
    np.testing.assert_allclose(results, e, rtol=DIMENSIONAL_TOL)
    np.testing.assert_allclose(results[0], results[1], rtol=DIMENSIONAL_TOL)


def _clamped_linear_closed_form(zeta: float) -> float:
    """Schwager & Pöschel (2007): e of x'' = -max(0, x + 2ζx'), x(0) = 0, x'(0) = 1.

    Underdamped (ω = sqrt(1 - ζ²)): x = e^{-ζt} sin(ωt)/ω and the force e^{-ζt}[(1 - 2ζ²) sin(ωt)/ω + 2ζ cos(ωt)]
    vanishes at tan(ωt*) = -2ζω / (1 - 2ζ²); there x' = -e^{-ζt*}, so e = exp(-ζ t*).
    Overdamped (λ₁,₂ = -ζ ± sqrt(ζ² - 1), λ₁λ₂ = 1, 1 + 2ζλᵢ = -λᵢ²): the force ∝ -λ₁² e^{λ₁t} + λ₂² e^{λ₂t}
    vanishes at t* = 2 ln(λ₂/λ₁) / (λ₁ - λ₂), where x' = -λ₁² e^{λ₁t*}.
    """
    if zeta < 1.0:
        omega = math.sqrt(1.0 - zeta * zeta)
        # atan2 picks the branch ωt* in (π/2, π) for ζ < 1/√2 and in (0, π/2) above.
        phase = math.atan2(2.0 * zeta * omega, -(1.0 - 2.0 * zeta * zeta))
        return math.exp(-zeta * phase / omega)
    root = math.sqrt(zeta * zeta - 1.0)
    lam1, lam2 = -zeta + root, -zeta - root
    t_end = 2.0 * math.log(lam2 / lam1) / (lam1 - lam2)
    return lam1 * lam1 * math.exp(lam1 * t_end)


@pytest.mark.parametrize("zeta", [1e-4, 0.05, 0.3, 0.6, 0.8, 0.95, 1.5, 5.0, 40.0])
def test_linear_forward_matches_closed_form(zeta: float) -> None:
    np.testing.assert_allclose(restitution_linear(zeta), _clamped_linear_closed_form(zeta), rtol=CLOSED_FORM_TOL)


def _classic_zeta(e: float) -> float:
    """Textbook damping ratio of the unclamped linear spring–dashpot: e = exp(-π ζ / sqrt(1 - ζ²)) inverted."""
    log_e = math.log(e)
    return -log_e / math.sqrt(math.pi**2 + log_e**2)


@pytest.mark.parametrize("e", RESTITUTIONS)
def test_clamp_changes_linear_damping_ratio(e: float) -> None:
    # Without attraction near the end of the contact less energy is lost, so more damping is needed.
    zeta, zeta_classic = linear_damping_ratio(e), _classic_zeta(e)
    assert zeta > zeta_classic * 1.01
    assert restitution_linear(zeta_classic) > e + 1e-3


@pytest.mark.parametrize("zeta", [0.01, 0.1, 0.3, 0.6, 0.9])
def test_unclamped_integrator_reproduces_classic_formula(zeta: float) -> None:
    # Same RK4 integrator, but the unclamped law keeps the spheres in contact until x returns to 0.
    h = 1.0 / restitution._STEPS_PER_UNIT_TIME
    e = restitution._rebound_speed(lambda x, v: -(x + 2.0 * zeta * v), lambda x, v: x, h, 1.0)
    np.testing.assert_allclose(e, math.exp(-math.pi * zeta / math.sqrt(1.0 - zeta**2)), rtol=CLASSIC_TOL)


@pytest.mark.parametrize("e", [1e-3, 0.1, 0.5, 0.9, 0.999])
def test_inverse_round_trip(e: float) -> None:
    zeta, c = linear_damping_ratio(e), hertz_damping_coefficient(e)
    np.testing.assert_allclose(restitution_linear(zeta), e, rtol=ROUND_TRIP_TOL)
    np.testing.assert_allclose(restitution_hertz(c), e, rtol=ROUND_TRIP_TOL)


@pytest.mark.parametrize("p", [0.01, 0.3, 1.0, 4.0])
def test_forward_round_trip(p: float) -> None:
    np.testing.assert_allclose(linear_damping_ratio(restitution_linear(p)), p, rtol=ROUND_TRIP_TOL)
    np.testing.assert_allclose(hertz_damping_coefficient(restitution_hertz(p)), p, rtol=ROUND_TRIP_TOL)


def test_forward_maps_decrease() -> None:
    params = np.geomspace(1e-3, 1e2, 40)
    for forward in (restitution_linear, restitution_hertz):
        values = np.array([forward(float(p)) for p in params])
        assert np.all(np.diff(values) < 0.0)
        assert np.all((values > 0.0) & (values < 1.0))


def test_elastic_limit_is_exact() -> None:
    assert linear_damping_ratio(1.0) == 0.0
    assert hertz_damping_coefficient(1.0) == 0.0
    assert restitution_linear(0.0) == 1.0
    assert restitution_hertz(0.0) == 1.0


@pytest.mark.parametrize("bad", [0.0, -0.2, 1.0 + 1e-12, 2.0, math.nan, math.inf, "0.5", None, True])
def test_invalid_restitution_raises(bad: object) -> None:
    for inverse in (linear_damping_ratio, hertz_damping_coefficient):
        with pytest.raises(ValueError, match="0 < e <= 1"):
            inverse(bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [-1e-9, math.nan, math.inf, "1"])
def test_invalid_damping_raises(bad: object) -> None:
    for forward in (restitution_linear, restitution_hertz):
        with pytest.raises(ValueError, match=">= 0"):
            forward(bad)  # type: ignore[arg-type]
