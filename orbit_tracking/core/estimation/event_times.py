"""The uncertainty of the events' times in the states' covariance (beyond the paper).

An event (a knot of multiplicity ``degree - 1``: the acceleration may jump there) stands
at a time the data gave: the telemetry's detector, the gate's rejections, a doubtful
change, each then placed by the measurements (:mod:`.gate_events`,
:mod:`.doubtful_events`). The window's covariance is conditional on that time. A jump of
``da`` m/s^2 put ``dt`` s off leaves the velocity beside it ``da dt`` off, while the
covariance, which takes the time as known, may claim centimetres per second: on the
robustness families the over-confident states left after the events were placed lay
within a tenth of a second of jumps whose times were off by 10-60 ms (three stations and
5 Hz telemetry on ascent draw 67, its second event's cost nearly flat over 0.3 s).

So for each event :func:`event_time_terms` measures how well the measurements place it
and what that moves. On the local trials of :mod:`.gate_events` (the measurements
within two seconds, the window's biases and white-jerk density held, only gross errors
gated): the costs with the event at ``tau`` and ``tau +- STEP`` give a sigma of its time
on each side (the cost rises by one there, on a parabola through ``tau`` and
``tau +- STEP``: a V-shaped profile makes it larger than the rise of one itself, never
smaller), capped at :data:`MAX_SIGMA`; the states solved with the event a sigma either
side, minus those at ``tau``, are two sigma points ``d+`` and ``d-``, and the term
``(d+ d+^T + d- d-^T) / 2`` is added to the covariance of the states around the event
(:meth:`EventTimeTerms.state_covariance`). A consider term: the estimate does not move.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.bspline import SplineAxis
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.gate_events import (
    EDGE_MARGIN,
    LocalTrials,
    event_knots,
    with_events,
)
from orbit_tracking.core.estimation.knots import KnotSelection
from orbit_tracking.core.estimation.problem import Problem

__all__ = ['MAX_SIGMA', 'STEP', 'EventTimeTerms', 'event_time_terms', 'window_event_terms']

FloatArray = NDArray[np.float64]

STEP = 0.005
"""Step [s] of the event's time over which the rise of the cost is measured."""

MAX_SIGMA = 0.25
"""Largest sigma [s] of an event's time (the reach of the search that placed it)."""


@dataclass(frozen=True)
class EventTimeTerms:
    """Sigma points of the states for the events' times: per event, the times ``ts``
    (s,) and the state differences ``plus`` and ``minus`` (s, 6) [m, m/s], world frame;
    ``sigmas`` the events' times and their two one-sided sigmas [s]."""

    ts: tuple[FloatArray, ...]
    plus: tuple[FloatArray, ...]
    minus: tuple[FloatArray, ...]
    sigmas: tuple[tuple[float, float, float], ...]

    def state_covariance(self, t: FloatArray) -> FloatArray:
        """The term (m, 6, 6) at the times ``t`` (zero away from the events)."""
        out = np.zeros((t.shape[0], 6, 6))
        for ts, dp, dm in zip(self.ts, self.plus, self.minus, strict=True):
            inside = (t >= ts[0]) & (t <= ts[-1])
            if not inside.any():
                continue
            ti = t[inside]
            p = np.stack([np.interp(ti, ts, dp[:, k]) for k in range(6)], axis=1)
            m = np.stack([np.interp(ti, ts, dm[:, k]) for k in range(6)], axis=1)
            out[inside] += 0.5 * (p[:, :, None] * p[:, None, :] + m[:, :, None] * m[:, None, :])
        return out

    def note(self) -> str:
        """The events' times and sigmas, for the window's message."""
        return ', '.join(
            f'{tau:.3f} s (-{1e3 * lo:.0f}/+{1e3 * hi:.0f} ms)' for tau, lo, hi in self.sigmas
        )


def _sigma(c0: float, c_minus: float, c_plus: float) -> float:
    """The sigma [s] of an event's time from the costs at it and :data:`STEP` either side
    (NaN: not tried): on the parabola through them, the square root of its variance
    (``2 / curvature``) plus the square of the distance to its vertex (the event's
    estimate need not stand at the least cost of the local trials); one side only, or
    not bending upward: from the rise alone, or :data:`MAX_SIGMA`."""
    if math.isfinite(c_minus) and math.isfinite(c_plus):
        k = (c_plus + c_minus - 2.0 * c0) / STEP**2
        if k > 0.0:
            g = (c_plus - c_minus) / (2.0 * STEP)
            return min(math.sqrt(2.0 / k + (g / k) ** 2), MAX_SIGMA)
        return MAX_SIGMA
    rises = [c - c0 for c in (c_minus, c_plus) if math.isfinite(c)]
    if not rises or rises[0] <= 0.0:
        return MAX_SIGMA
    return min(STEP * math.sqrt(2.0 / rises[0]), MAX_SIGMA)


def event_time_terms(
    prob: Problem,
    beta: FloatArray,
    tid: int,
    events: Sequence[float],
    kinks: Sequence[float],
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> EventTimeTerms | None:
    """The sigma points of target ``tid``'s events (the ``events`` that stand on its
    spline as events, not ``kinks``) in ``prob`` solved at ``beta`` (None without any)."""
    traj = prob.trajs[tid]
    taus = event_knots(traj, events, kinks)
    if not taus:
        return None
    ts_all, plus, minus, sigmas = [], [], [], []
    gap = cfg.knots.min_spacing
    for tau in taus:
        others = [e for e in taus if e != tau]
        # the event's own knots out, and the simple knots within reach (the same freedom
        # at every trial time); the other events stay
        axes = []
        for ax in traj.axes:
            inner = ax.interior
            own = np.abs(inner - tau) < 1e-9
            values, counts = np.unique(inner, return_counts=True)
            repeated = np.isin(inner, values[counts > 1])
            near = np.abs(inner - tau) <= MAX_SIGMA + gap
            axes.append(
                SplineAxis.from_interior(
                    inner[~own & ~(near & ~repeated)], ax.t0, ax.t1, ax.degree
                )
            )
        lo_lim = max([t0 + 0.5 * EDGE_MARGIN, *(e + 0.5 * EDGE_MARGIN for e in others if e < tau)])
        hi_lim = min([t1 - 0.5 * EDGE_MARGIN, *(e - 0.5 * EDGE_MARGIN for e in others if e > tau)])
        trials = LocalTrials(prob, beta, tid, tau, obs, cfg, t0, t1, MAX_SIGMA)

        def at(
            t: float, axes: list[SplineAxis] = axes, trials: LocalTrials = trials
        ) -> tuple[float, FloatArray | None]:
            return trials.solve(with_events(axes, [t], gap))

        c0, x0 = at(tau)
        if x0 is None:
            continue
        costs = {
            sign: at(tau + sign * STEP)[0] if sign * (lim - tau) >= STEP else math.nan
            for sign, lim in ((1.0, hi_lim), (-1.0, lo_lim))
        }
        sigma = _sigma(c0, costs[-1.0], costs[1.0])
        side: list[tuple[float, FloatArray | None]] = []
        for sign, lim in ((1.0, hi_lim), (-1.0, lo_lim)):
            s = min(sigma, abs(lim - tau))
            if s <= 0.0:
                side.append((0.0, None))
                continue
            _, x_s = at(tau + sign * s)
            side.append((s, None if x_s is None else x_s - x0))
        (sp_, dp), (sm_, dm) = side
        if dp is None and dm is None:
            continue
        zero = np.zeros_like(x0)
        ts_all.append(trials.ts)
        plus.append(dp if dp is not None else zero)
        minus.append(dm if dm is not None else zero)
        sigmas.append((tau, sm_, sp_))
    if not ts_all:
        return None
    return EventTimeTerms(tuple(ts_all), tuple(plus), tuple(minus), tuple(sigmas))


def window_event_terms(
    prob: Problem,
    beta: FloatArray,
    selections: Mapping[int, KnotSelection],
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> tuple[dict[int, EventTimeTerms], str]:
    """:func:`event_time_terms` of every target with events (none when
    ``cfg.event_time_uncertainty`` is off), and the note for the window's message."""
    out: dict[int, EventTimeTerms] = {}
    if not cfg.event_time_uncertainty:
        return out, ''
    for tid, s in selections.items():
        term = event_time_terms(prob, beta, tid, s.events, s.kinks, obs, cfg, t0, t1)
        if term is not None:
            out[tid] = term
    note = ''.join(
        f'; target {tid} event times (sigmas in the covariance): {term.note()}'
        for tid, term in out.items()
    )
    return out, note
