"""The telemetry's noise levels re-estimated from its residuals between the gate rounds of
:func:`.gauss_newton.solve`.

The declared telemetry sigmas are a starting point: real telemetry (a Kalman-filtered
GNSS/INS, a velocity from another source) has errors correlated in time that the error
model of :mod:`.telemetry_block` follows only in part. What it leaves in the residuals is
weighed as what it is, the mean of many samples being worth fewer independent ones.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.estimation.problem import Problem

__all__ = ['TELEMETRY_MAX_LAG1', 'lag1', 'long_run_ratio', 'reestimate_telemetry_noise']

FloatArray = NDArray[np.float64]

TELEMETRY_MAX_LAG1 = 0.99
"""Largest lag-1 autocorrelation taken from telemetry residuals (inflation at most 14x)."""


def _autocorrelations(e: FloatArray, lags: int) -> FloatArray:
    """Autocorrelations at lags ``1 .. lags`` of the time-ordered rows of ``e`` (m, 3),
    pooled over the columns (all zero for constant rows)."""
    c = e - e.mean(axis=0)
    den = float(np.sum(c * c))
    if den <= 0.0:
        return np.zeros(lags)
    return np.array([float(np.sum(c[k:] * c[:-k])) / den for k in range(1, lags + 1)])


def lag1(e: FloatArray) -> float:
    """Lag-1 autocorrelation of the rows of ``e`` (m, 3), time-ordered, pooled over the
    columns, clipped to [0, :data:`TELEMETRY_MAX_LAG1`]."""
    if e.shape[0] < 3:
        return 0.0
    return min(max(float(_autocorrelations(e, 1)[0]), 0.0), TELEMETRY_MAX_LAG1)


def long_run_ratio(e: FloatArray, lags: int) -> float:
    """Long-run variance of the time-ordered rows of ``e`` (m, 3), pooled over the columns,
    over their variance: ``1 + 2 sum_k (1 - k / (L + 1)) rho_k`` over the lags ``k = 1 ..
    L`` (Bartlett's weights, which keep the estimate non-negative), ``L`` = ``lags`` but at
    most a quarter of the rows; at least 1."""
    lags = min(lags, e.shape[0] // 4)
    if lags < 1:
        return 1.0
    k = np.arange(1, lags + 1)
    weights = 1.0 - k / (lags + 1.0)
    return max(1.0 + 2.0 * float(np.sum(weights * _autocorrelations(e, lags))), 1.0)


def reestimate_telemetry_noise(prob: Problem, beta: FloatArray, span: float) -> bool:
    """The telemetry's position and velocity noise levels from its residuals: their RMS,
    inflated by the square root of a variance ratio (the variance of a mean over many
    samples, against that of white residuals of the same RMS):

    - ``(1 + rho) / (1 - rho)`` with ``rho`` their lag-1 autocorrelation (the effective
      sample size of a first-order autoregressive error). Residuals that run in one
      direction for many samples (a random walk, jumps, a time-tag skew: errors the error
      spline does not follow) are that many fewer independent samples, and are weighed so.
    - for the velocity rows of a telemetry whose velocity has an error of its own (``w``,
      :mod:`.telemetry_velocity`), the larger of that and :func:`long_run_ratio` over the
      lags within ``span`` seconds (the base knot spacing: the trajectory's velocity over a
      knot interval is a mean of the samples in it). ``w`` has knots seconds apart; white
      noise on top of the part of its error that varies faster has a small lag-1
      autocorrelation, and the first-order formula took its mean over a second as ~20
      independent samples (robustness ascent draw 5: the velocity 0.2 m/s off at sigmas
      of 0.04 m/s). Position rows, and velocity rows without ``w``, keep the first-order
      formula: there the long-run ratio made a drifting telemetry's velocity over-confident
      in Monte Carlo (``test_monte_carlo_nees_of_position_and_velocity...``).

    White residuals keep their RMS. Returns whether a level moved by more than 5 %."""
    changed = False
    for tb in prob.telemetry:
        dp, dv = prob.telemetry_residuals(tb, beta)
        use_p, use_v = prob.telemetry_use(tb)
        order = np.argsort(tb.time, kind='stable')
        t_sorted = tb.time[order]
        new = list(tb.noise)
        for k, (d, use, floor) in enumerate(((dp, use_p, 1e-3), (dv, use_v, 1e-5))):
            e = d[order][use[order]]
            if not e.size:
                continue
            rho = lag1(e)
            ratio = (1.0 + rho) / (1.0 - rho)
            ts = t_sorted[use[order]]
            if k == 1 and tb.w_axis is not None and ts.size > 1:
                dt = float(np.median(np.diff(ts)))
                if dt > 0.0:
                    ratio = max(ratio, long_run_ratio(e, int(round(span / dt))))
            rms = float(np.sqrt(np.mean(e**2)))
            new[k] = max(rms * math.sqrt(ratio), floor)
        if any(abs(a - b) > 0.05 * b for a, b in zip(new, tb.noise, strict=True)):
            changed = True
        tb.noise = new
    return changed
