"""Events where the residual gate's rejections cluster (beyond the paper).

An acceleration jump (a staging, an engine cut-off) that no knot follows leaves the spline
rounding the corner of the velocity: a tenth of a second either side of the instant, its
velocity is off by tenths of a metre per second, or metres, while its covariance, which
assumes the spline can take the true shape, claims centimetres per second. The
measurements there do not fit, and the residual gate (:func:`.gauss_newton.gate_residuals`)
rejects them as outliers, which hides the misfit from the chi-square and from the knot
test. Gross errors and outliers are scattered in time and over the stations; the values a
missed event spoils are not: they gather within a fraction of a second around it.

The rough trajectory finds events only where it has velocity samples: a draw without
telemetry, or a staging inside a telemetry outage, gave the robustness families most of
their over-confident states, and given the true event times (an oracle) the knot
selection removed them. So after the solve, :func:`gate_cluster_events` looks for
:data:`MIN_VALUES` or more rejected station epochs within :data:`SPAN` seconds, and an
event (a knot of multiplicity ``degree - 1`` on every axis, as for the rough trajectory's
events) goes at the median of their times; the estimator rebuilds the problem on the new
knots, decides the gate afresh and solves again (``EstimatorConfig.gate_event_rounds``).
Not inside an incomplete segment (one or two stations cannot pin an acceleration jump
there), nor beside an event already knotted or a window edge.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.estimation.bspline import SplineAxis
from orbit_tracking.core.estimation.config import Segment
from orbit_tracking.core.estimation.problem import Problem

__all__ = ['EDGE_MARGIN', 'MIN_VALUES', 'SPAN', 'gate_cluster_events', 'with_events']

FloatArray = NDArray[np.float64]

SPAN = 0.5
"""Width [s] of the span in which rejected station epochs count as one cluster."""

MIN_VALUES = 3
"""Rejected station epochs (any field, any station) a cluster needs."""

EDGE_MARGIN = 0.5
"""No event closer than this [s] to a window edge, or (half of it) to an event already
knotted or an incomplete segment."""


def _clusters(times: FloatArray) -> list[float]:
    """Median times of the runs of at least :data:`MIN_VALUES` sorted ``times`` within
    :data:`SPAN`, scanned from the earliest."""
    out = []
    i = 0
    while i < times.size:
        j = int(np.searchsorted(times, times[i] + SPAN, side='right'))
        if j - i >= MIN_VALUES:
            out.append(float(np.median(times[i:j])))
            i = j
        else:
            i += 1
    return out


def gate_cluster_events(
    prob: Problem, segments: Mapping[int, Sequence[Segment]], t0: float, t1: float
) -> dict[int, list[float]]:
    """Per target, the instants where the gate's rejected station epochs cluster, away
    from window edges, knotted events and incomplete segments."""
    by_target: dict[int, list[FloatArray]] = {}
    for bi, b in enumerate(prob.stations):
        g = prob.gated.get(bi)
        if g is None or not g.any():
            continue
        rejected = g.any(axis=1) if g.ndim == 2 else g
        by_target.setdefault(b.target, []).append(b.time[rejected])
    out: dict[int, list[float]] = {}
    for tid, parts in by_target.items():
        traj = prob.trajs.get(tid)
        if traj is None:
            continue
        knotted = traj.repeated_knots()
        found = [
            tau
            for tau in _clusters(np.sort(np.concatenate(parts)))
            if t0 + EDGE_MARGIN < tau < t1 - EDGE_MARGIN
            and not np.any(np.abs(knotted - tau) < 0.5 * EDGE_MARGIN)
            and not any(
                a - 0.5 * EDGE_MARGIN <= tau <= b + 0.5 * EDGE_MARGIN
                for a, b in segments.get(tid, ())
            )
        ]
        if found:
            out[tid] = found
    return out


def with_events(
    axes: Sequence[SplineAxis], taus: Sequence[float], min_spacing: float
) -> list[SplineAxis]:
    """``axes`` with an event at each of ``taus``: the simple knots within
    ``min_spacing`` of it dropped, a knot of multiplicity ``degree - 1`` put there."""
    t = np.asarray(taus, dtype=float)
    out = []
    for ax in axes:
        inner = ax.interior
        if inner.size:
            inner = inner[np.min(np.abs(inner[:, None] - t[None, :]), axis=1) > min_spacing]
        knots = np.sort(np.concatenate([inner, np.repeat(t, ax.degree - 1)]))
        out.append(SplineAxis.from_interior(knots, ax.t0, ax.t1, ax.degree))
    return out
