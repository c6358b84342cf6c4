"""Damping parameters that give an exact coefficient of restitution for the clamped normal contact laws.

Both normal laws in :mod:`warpdem.kernels.contact` clamp the total normal force to be non-negative (no
attraction). A collision therefore ends as soon as the total force would turn tensile, which happens while the
spheres still overlap; from then on they coast apart at constant relative velocity, so

    e = (normal rebound speed at the first zero of the total force) / (normal impact speed).

With this clamp the textbook closed form e = exp(-π ζ / sqrt(1 - ζ²)) of the linear spring–dashpot is wrong (it
assumes the contact lasts until δ = 0, with attraction near the end), and the Hertz law with Tsuji damping has no
closed form at all. Both are therefore solved here numerically, once per value on the host: the forward maps
integrate the dimensionless equation of motion with RK4, the inverse maps find its root by regula falsi, and the
results are cached.

Dimensionless equations (impact at t = 0 with δ(0) = 0, δ'(0) = v0 > 0, m* the effective mass):

- Linear: m* δ'' = -max(0, k δ + γ δ') with γ = 2 ζ sqrt(m* k). With time scale T = sqrt(m*/k) and length scale
  L = v0 T, x = δ/L and τ = t/T give x'' = -max(0, x + 2 ζ x'), x(0) = 0, x'(0) = 1.
- Hertz: m* δ'' = -max(0, k δ^{3/2} + η δ^{1/4} δ') with k = (4/3) E* sqrt(R*) and η = c sqrt(m* k)
  (Tsuji et al. 1992). See :func:`hertz_damping_coefficient` for the scaling, which removes v0.

References:
    Tsuji, Tanaka, Ishida (1992), Powder Technol. 71, 239-250.
    Schwager, Pöschel (2007), "Coefficient of restitution and linear-dashpot model revisited", Granular Matter 9,
    465-469 (closed form of the clamped linear case, used as an oracle in the tests).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from functools import lru_cache

__all__ = [
    "hertz_damping_coefficient",
    "linear_damping_ratio",
    "restitution_hertz",
    "restitution_linear",
]

# Acceleration of the scaled equation as a function of (x, x'), and a contact-end indicator that is positive
# during the contact and crosses zero where it ends.
_Accel = Callable[[float, float], float]
_Event = Callable[[float, float], float]

_STEPS_PER_UNIT_TIME = 200
"""Main RK4 steps per unit of the fastest scaled time scale. Halving the step changes e by < 2e-9 relative for
c >= 1e-6 (4th-order convergence; the end of a nearly elastic Hertz contact, at tiny x, is the worst case), far
below the 1e-6 required, at about 1 ms per evaluation."""

_MAX_STEPS = 2_000_000
"""Safety stop: no contact in the admissible parameter range lasts this many steps."""

_E_TOL = 1e-11
"""Absolute tolerance on e of the inverse maps (1e-8 required); the discrete forward maps are continuous and
monotone far below this (the end of the contact is located by root finding, not snapped to the step grid)."""


def _rk4_step(accel: _Accel, x: float, v: float, h: float) -> tuple[float, float]:
    """One classical RK4 step of x' = v, v' = accel(x, v) over time h."""
    a1 = accel(x, v)
    x2, v2 = x + 0.5 * h * v, v + 0.5 * h * a1
    a2 = accel(x2, v2)
    x3, v3 = x + 0.5 * h * v2, v + 0.5 * h * a2
    a3 = accel(x3, v3)
    x4, v4 = x + h * v3, v + h * a3
    a4 = accel(x4, v4)
    return (
        x + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4),
        v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
    )


def _rk4_step_quartic(accel: _Accel, s: float, x: float, v: float, h: float) -> tuple[float, float]:
    """One RK4 step over h in s of the equation rewritten for t = s⁴: dx/ds = 4 s³ v, dv/ds = 4 s³ accel(x, v)."""
    w1 = 4.0 * s**3
    w2 = 4.0 * (s + 0.5 * h) ** 3
    w4 = 4.0 * (s + h) ** 3
    a1 = accel(x, v)
    kx1, kv1 = w1 * v, w1 * a1
    x2, v2 = x + 0.5 * h * kx1, v + 0.5 * h * kv1
    kx2, kv2 = w2 * v2, w2 * accel(x2, v2)
    x3, v3 = x + 0.5 * h * kx2, v + 0.5 * h * kv2
    kx3, kv3 = w2 * v3, w2 * accel(x3, v3)
    x4, v4 = x + h * kx3, v + h * kv3
    kx4, kv4 = w4 * v4, w4 * accel(x4, v4)
    return (
        x + h / 6.0 * (kx1 + 2.0 * kx2 + 2.0 * kx3 + kx4),
        v + h / 6.0 * (kv1 + 2.0 * kv2 + 2.0 * kv3 + kv4),
    )


def _locate_event(step: Callable[[float], tuple[float, float]], event: _Event, g0: float, h: float) -> float:
    """Velocity where the event function crosses zero inside one step.

    The crossing is found by Illinois regula falsi on the length of a partial RK4 step from the start of the step,
    so the returned velocity has the accuracy of RK4 on the smooth part of the trajectory, not that of an
    interpolant across the kink of the clamp.

    Args:
        step: partial step, length in (0, h] → state (x, v) at its end.
        event: contact-end indicator (x, v) → positive inside the contact.
        g0: event value at the start of the step, > 0.
        h: full step length (the event value at its end is <= 0).

    Returns:
        x' at the crossing.
    """
    a, ga = 0.0, g0
    b = h
    x, v = step(b)
    gb = event(x, v)
    side = 0
    for _ in range(200):
        m = (a * gb - b * ga) / (gb - ga)
        x, v = step(m)
        gm = event(x, v)
        if gm > 0.0:
            a, ga = m, gm
            if side == 1:
                gb *= 0.5  # Illinois: halve the stale end so the secant does not stall on one side.
            side = 1
        else:
            b, gb = m, gm
            if side == -1:
                ga *= 0.5
            side = -1
        if gm == 0.0 or b - a <= 1e-14 * h:
            break
    return v


def _rebound_speed(accel: _Accel, event: _Event, h: float, t_start: float) -> float:
    """Rebound speed of the scaled impact x'' = accel(x, x'), x(0) = 0, x'(0) = 1, ending where event drops to 0.

    The Hertz force x^{3/2} + c x^{1/4} x' is not smooth at x = 0: with x ≈ t at the start, x^{1/4} ≈ t^{1/4} and
    RK4 would lose its order there (its local error h⁵ d⁵x/dt⁵ ~ h⁵ t^{-19/4} sums to O(h^{1/4}) if uniform steps
    start at t = 0). The first t_start of time is therefore integrated in s = t^{1/4}, in which
    x(s) = s⁴ - (16 c/45) s⁹ + … is a smooth function; the remainder, where t >= t_start bounds the derivatives,
    uses uniform steps h and converges at 4th order. The end of the contact lies at x > 0 where the force is
    smooth, and is located inside its step by :func:`_locate_event`.

    Args:
        accel: scaled acceleration (x, v) → x'' of the unclamped law, valid while the contact lasts.
        event: contact-end indicator (x, v), positive during the contact after t = 0.
        h: main time step (scaled).
        t_start: length of the start phase (scaled), about one unit of the fastest time scale.

    Returns:
        -x' at the end of the contact, i.e. the coefficient of restitution.
    """
    x, v = 0.0, 1.0
    # With n steps of ds = t_start^{1/4}/n, the last one spans dt = 4 s³ ds = 4 t_start/n: n = 4 t_start/h makes it
    # h, so the start phase is resolved as finely as the rest.
    n_start = max(1, math.ceil(4.0 * t_start / h))
    ds = t_start**0.25 / n_start
    g = math.inf  # The contact has just begun; the event function may be exactly 0 at t = 0 (Hertz).
    for i in range(n_start):
        s = i * ds
        xn, vn = _rk4_step_quartic(accel, s, x, v, ds)
        gn = event(xn, vn)
        if gn <= 0.0:
            if i == 0:
                raise RuntimeError("contact ended within the first step; the time step is too coarse")
            return -_locate_event(lambda dh, s=s, x=x, v=v: _rk4_step_quartic(accel, s, x, v, dh), event, g, ds)
        x, v, g = xn, vn, gn
    for _ in range(_MAX_STEPS):
        xn, vn = _rk4_step(accel, x, v, h)
        gn = event(xn, vn)
        if gn <= 0.0:
            return -_locate_event(lambda dh, x=x, v=v: _rk4_step(accel, x, v, dh), event, g, h)
        x, v, g = xn, vn, gn
    raise RuntimeError("contact did not end within the step limit")


def _as_float(value: float) -> float:
    """value as a Python float, or NaN if it is not a real number (so that the range checks reject it)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return math.nan
    return float(value)


def _check_restitution(e: float) -> float:
    value = _as_float(e)
    if not 0.0 < value <= 1.0:
        raise ValueError(f"coefficient of restitution must be a number with 0 < e <= 1, got {e!r}")
    return value


def _check_damping(value: float, name: str) -> float:
    number = _as_float(value)
    if not (math.isfinite(number) and number >= 0.0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return number


def _invert(forward: Callable[[float], float], e: float) -> float:
    """Damping parameter p >= 0 with forward(p) = e, by Illinois regula falsi on a bracket [0, hi].

    forward is decreasing from forward(0) = 1 towards 0; the bracket is grown by doubling until it straddles e.
    """
    lo, f_lo = 0.0, 1.0 - e
    hi = 1.0
    f_hi = forward(hi) - e
    while f_hi > 0.0:
        lo, f_lo = hi, f_hi
        hi *= 2.0
        f_hi = forward(hi) - e
        if hi > 1e12:
            raise ValueError(f"coefficient of restitution {e!r} is too small to be reached")
    side = 0
    p = hi
    for _ in range(200):
        p = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        f_p = forward(p) - e
        if abs(f_p) <= _E_TOL:
            break
        if f_p > 0.0:
            lo, f_lo = p, f_p
            if side == 1:
                f_hi *= 0.5
            side = 1
        else:
            hi, f_hi = p, f_p
            if side == -1:
                f_lo *= 0.5
            side = -1
        if hi - lo <= 1e-15 * hi:
            break
    return p


@lru_cache(maxsize=256, typed=True)  # typed: True must not hit the entry of 1.0
def restitution_linear(zeta: float) -> float:
    """Coefficient of restitution of the clamped linear spring–dashpot for a damping ratio.

    Integrates x'' = -max(0, x + 2 ζ x'), x(0) = 0, x'(0) = 1 (time in units of sqrt(m*/k), length in units of
    v0 sqrt(m*/k); see the module docstring) until the force x + 2 ζ x' first reaches zero, and returns -x' there.
    The result does not depend on the impact speed, mass or stiffness.

    Args:
        zeta: damping ratio ζ >= 0 of γ = 2 ζ sqrt(m* k) [-].

    Returns:
        e in (0, 1]; exactly 1 for ζ = 0 [-].

    Raises:
        ValueError: ζ negative or not finite.
    """
    zeta = _check_damping(zeta, "damping ratio zeta")
    if zeta == 0.0:
        return 1.0
    two_zeta = 2.0 * zeta

    def force(x: float, v: float) -> float:
        return x + two_zeta * v

    # The fastest rates are the undamped frequency 1 and the dashpot rate 2 ζ (overdamped fast mode).
    t_unit = 1.0 / max(1.0, two_zeta)
    return _rebound_speed(lambda x, v: -force(x, v), force, t_unit / _STEPS_PER_UNIT_TIME, t_unit)


@lru_cache(maxsize=256, typed=True)  # typed: True must not hit the entry of 1.0
def restitution_hertz(c: float) -> float:
    """Coefficient of restitution of the clamped Hertz law with Tsuji damping for a damping coefficient.

    Integrates x'' = -max(0, x^{3/2} + c x^{1/4} x'), x(0) = 0, x'(0) = 1 (scaling in
    :func:`hertz_damping_coefficient`) until the force first reaches zero, and returns -x' there. The result does
    not depend on the impact speed, mass, modulus or radius.

    Args:
        c: damping coefficient c >= 0 of η = c sqrt(m* k) [-].

    Returns:
        e in (0, 1]; exactly 1 for c = 0 [-].

    Raises:
        ValueError: c negative or not finite.
    """
    c = _check_damping(c, "damping coefficient c")
    if c == 0.0:
        return 1.0

    def accel(x: float, v: float) -> float:
        # The contact ends at x > 0; stage values of x can only touch 0 at t = 0, where the force is 0.
        q = math.sqrt(math.sqrt(max(x, 0.0)))  # x^{1/4}
        return -(q**6 + c * q * v)

    def event(x: float, v: float) -> float:
        # Sign of the force x^{1/4} (x^{5/4} + c x'), without the x^{1/4} factor that vanishes at t = 0.
        return max(x, 0.0) ** 1.25 + c * v

    # Rates: the Hertz frequency sqrt(1.5 x^{1/2}) <= ~1.3 for x <= x_max ≈ 1.09, and the dashpot rate c x^{1/4}.
    t_unit = 1.0 / max(1.0, c)
    return _rebound_speed(accel, event, t_unit / _STEPS_PER_UNIT_TIME, t_unit)


@lru_cache(maxsize=256, typed=True)  # typed: True must not hit the entry of 1.0
def linear_damping_ratio(e: float) -> float:
    """Damping ratio of the clamped linear spring–dashpot that gives a coefficient of restitution.

    Inverse of :func:`restitution_linear`, to 1e-11 in e. Because the force is clamped (no attraction), the
    contact ends before δ returns to 0 without the attractive pull of the unclamped law near its end; more damping
    is needed than the textbook ζ = -ln e / sqrt(π² + ln² e) says, e.g. ζ ≈ 0.2553 instead of 0.2155 for e = 0.5.

    Args:
        e: coefficient of restitution, 0 < e <= 1 [-].

    Returns:
        ζ >= 0 for γ = 2 ζ sqrt(m* k) [-]; exactly 0 for e = 1.

    Raises:
        ValueError: e outside (0, 1].
    """
    e = _check_restitution(e)
    if e == 1.0:
        return 0.0
    return _invert(restitution_linear, e)


@lru_cache(maxsize=256, typed=True)  # typed: True must not hit the entry of 1.0
def hertz_damping_coefficient(e: float) -> float:
    """Damping coefficient c of the clamped Hertz law with Tsuji damping that gives a coefficient of restitution.

    The law m* δ'' = -max(0, k δ^{3/2} + η δ^{1/4} δ'), k = (4/3) E* sqrt(R*), η = c sqrt(m* k), with impact
    speed v0 = δ'(0), is made dimensionless by δ = L x, t = T τ with

        L = (m* v0² / k)^{2/5},  T = L / v0,

    so that x'(0) = 1. Dividing by m* L / T² leaves x'' = -max(0, a x^{3/2} + b x^{1/4} x') with
    a = k L^{1/2} T² / m* = k L^{5/2} / (m* v0²) = 1 and b = c sqrt(k/m*) L^{1/4} T = c sqrt(k L^{5/2} / (m* v0²))
    = c. Hence x'' = -max(0, x^{3/2} + c x^{1/4} x'): the restitution depends on c only, not on v0, m*, E* or R*.
    This function inverts :func:`restitution_hertz` to 1e-11 in e.

    Args:
        e: coefficient of restitution, 0 < e <= 1 [-].

    Returns:
        c >= 0 [-]; exactly 0 for e = 1.

    Raises:
        ValueError: e outside (0, 1].
    """
    e = _check_restitution(e)
    if e == 1.0:
        return 0.0
    return _invert(restitution_hertz, e)
