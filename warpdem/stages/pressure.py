"""Pressure histories p(t, x) of the loads (host side, DESIGN.md stage 8): an explosive cavity or borehole (``blast``),
a table, or a surface airblast (``friedlander``); validated when built, evaluated in float64 on the host for plots and
checks, and handed to the device as a :class:`warpdem.kernels.loads.PressureLoad`. The face sets they act on are
:mod:`warpdem.stages.loads`'.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import loads as kl


@dataclass(frozen=True)
class PressureHistory:
    """A pressure history p(t, x) [Pa] (positive pushes into the solid). Build one with :meth:`blast`,
    :meth:`table` or :meth:`friedlander`; the constructor validates the parameters of its kind.

    Attributes:
        kind: "blast", "table" or "friedlander".
        peak: blast peak pressure, Friedlander peak overpressure P_s [Pa].
        start: blast start time, Friedlander source time t0 [s].
        rise_time: blast rise time t_rise [s] (0: instantaneous).
        decay_time: blast decay time t_decay [s].
        times: table times t_k [s] (strictly increasing).
        values: table pressures p_k [Pa].
        duration: Friedlander positive-phase duration t_d [s].
        decay_coefficient: Friedlander decay coefficient b [-].
        source: Friedlander source point [m].
        front_speed: speed of the Friedlander front [m/s] (inf: it arrives everywhere at t0).

    Raises:
        ValueError: an unknown kind, or a parameter outside its range (named in the message).
    """

    kind: str
    peak: float = 0.0
    start: float = 0.0
    rise_time: float = 0.0
    decay_time: float = 0.0
    times: tuple[float, ...] = ()
    values: tuple[float, ...] = ()
    duration: float = 0.0
    decay_coefficient: float = 0.0
    source: tuple[float, float, float] = (0.0, 0.0, 0.0)
    front_speed: float = math.inf

    def __post_init__(self) -> None:
        if self.kind not in kl.PRESSURE_KINDS:
            raise ValueError(f"pressure history kind {self.kind!r}; allowed: {', '.join(kl.PRESSURE_KINDS)}")

        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"{self.kind} pressure history: {what}")

        need(math.isfinite(self.start), f"start must be finite, got {self.start}")
        if self.kind == "blast":
            need(math.isfinite(self.peak) and self.peak > 0.0, f"peak must be > 0 [Pa], got {self.peak}")
            need(
                math.isfinite(self.rise_time) and self.rise_time >= 0.0, f"rise_time must be >= 0, got {self.rise_time}"
            )
            need(
                math.isfinite(self.decay_time) and self.decay_time > 0.0,
                f"decay_time must be > 0, got {self.decay_time}",
            )
        elif self.kind == "table":
            t, v = np.asarray(self.times, dtype=np.float64), np.asarray(self.values, dtype=np.float64)
            need(t.ndim == 1 and len(t) >= 2, f"needs at least 2 times, got {len(np.atleast_1d(t))}")
            need(v.shape == t.shape, f"{len(t)} times but {len(np.atleast_1d(v))} values")
            need(bool(np.all(np.isfinite(t)) and np.all(np.isfinite(v))), "times and values must be finite")
            need(bool(np.all(np.diff(t) > 0.0)), "times must be strictly increasing")
        else:
            need(math.isfinite(self.peak) and self.peak > 0.0, f"peak must be > 0 [Pa], got {self.peak}")
            need(math.isfinite(self.duration) and self.duration > 0.0, f"duration must be > 0, got {self.duration}")
            need(
                math.isfinite(self.decay_coefficient) and self.decay_coefficient > 0.0,
                f"decay_coefficient must be > 0, got {self.decay_coefficient}",
            )
            need(self.front_speed > 0.0, f"front_speed must be > 0 (inf allowed), got {self.front_speed}")
            src = np.asarray(self.source, dtype=np.float64)
            need(src.shape == (3,) and bool(np.all(np.isfinite(src))), f"source must be a finite point, got {src}")

    @staticmethod
    def blast(peak: float, rise_time: float, decay_time: float, start: float = 0.0) -> PressureHistory:
        """Explosive cavity or borehole: p = P τ/t_rise for 0 ≤ τ < t_rise, then P exp(-(τ - t_rise)/t_decay),
        τ = t - start; 0 before the start. Times [s], peak [Pa]."""
        return PressureHistory(
            "blast", peak=float(peak), start=float(start), rise_time=float(rise_time), decay_time=float(decay_time)
        )

    @staticmethod
    def table(times: Sequence[float], values: Sequence[float]) -> PressureHistory:
        """Piecewise linear through (times [s], values [Pa]), 0 before the first time and after the last."""
        return PressureHistory("table", times=tuple(float(t) for t in times), values=tuple(float(v) for v in values))

    @staticmethod
    def friedlander(
        peak: float,
        duration: float,
        decay_coefficient: float,
        source: Sequence[float],
        front_speed: float = math.inf,
        start: float = 0.0,
    ) -> PressureHistory:
        """Surface airblast: the front leaves ``source`` at ``start`` and reaches x at
        t_a = start + |x - source| / front_speed; then p = P_s (1 - τ/t_d) exp(-b τ/t_d), τ = t - t_a (with its
        negative phase); 0 before. peak = P_s [Pa], duration = t_d [s], decay_coefficient = b [-]."""
        return PressureHistory(
            "friedlander",
            peak=float(peak),
            start=float(start),
            duration=float(duration),
            decay_coefficient=float(decay_coefficient),
            source=tuple(float(s) for s in source),
            front_speed=float(front_speed),
        )

    def pressure(self, t: np.ndarray | float, x: np.ndarray | None = None) -> np.ndarray:
        """p(t, x) [Pa] on the host in float64 (plots, checks). t: times [s], any shape; x: points [m] (..., 3)
        broadcast against t, needed by a Friedlander history with a finite front speed."""
        t = np.asarray(t, dtype=np.float64)
        if self.kind == "blast":
            tau = t - self.start
            rising = self.peak * tau / self.rise_time if self.rise_time > 0.0 else np.full_like(tau, self.peak)
            decaying = self.peak * np.exp(-(tau - self.rise_time) / self.decay_time)
            return np.where(tau < 0.0, 0.0, np.where(tau < self.rise_time, rising, decaying))
        if self.kind == "table":
            times = np.asarray(self.times)
            inside = (t >= times[0]) & (t <= times[-1])
            return np.where(inside, np.interp(t, times, np.asarray(self.values)), 0.0)
        distance = 0.0 if x is None else np.linalg.norm(np.asarray(x, dtype=np.float64) - self.source, axis=-1)
        tau = t - (self.start + distance / self.front_speed)
        s = tau / self.duration
        return np.where(tau < 0.0, 0.0, self.peak * (1.0 - s) * np.exp(-self.decay_coefficient * s))

    def device_load(self, table_first: int) -> kl.PressureLoad:
        """The device-side parameters (``table_first``: where this load's table starts in the shared table)."""
        p = kl.PressureLoad()
        p.peak = self.peak
        p.start = self.start
        p.rise = self.rise_time
        p.decay = self.decay_time if self.kind == "blast" else self.duration
        p.shape = self.decay_coefficient
        p.source = wp.vec3(*self.source)
        p.slowness = 1.0 / self.front_speed
        p.table_first = table_first
        p.table_count = len(self.times)
        return p
