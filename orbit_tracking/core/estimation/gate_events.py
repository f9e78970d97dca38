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

The median of the rejected epochs is only where the misfit showed, not where the
acceleration jumped: on robustness draw ascent 39 it put a staging 33 ms early, and the
velocity beside it was 0.2 m/s off at 0.04 m/s sigmas. So once the window is solved with
the new events, :func:`refine_event_times` moves each of them to where the measurements
fit it best (the profile of the cost over the event's time, from the measurements around
it with only the gross errors gated, searched downhill from the median and closed by
parabolas), when that lowers the cost by more than :data:`MOVE_CHI2`.

The rough trajectory's own events are timed by its samples alone, and two jumps half a
second apart can confuse its detector (one of them put half a second late on robustness
draw ascent 35), so :func:`place_rough_events` moves them the same way after the window's
first solve: first on a grid within :data:`ROUGH_REACH`, then once more nearby when all
have moved.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimatorConfig, Segment
from orbit_tracking.core.estimation.gauss_newton import (
    GROSS_FACTOR,
    decrement,
    gate_residuals,
    gauss_newton,
)
from orbit_tracking.core.estimation.problem import ROBUST_KINDS, GateKey, Problem
from orbit_tracking.core.estimation.scaling import normal_matrix

__all__ = [
    'EDGE_MARGIN',
    'FIRST_STEP',
    'GRID_STEP',
    'LOCAL_S',
    'MAX_TRIALS',
    'MIN_VALUES',
    'MOVE_CHI2',
    'ROUGH_REACH',
    'SEGMENT_MARGIN',
    'SPAN',
    'TOLERANCE',
    'TRIAL_ITERATIONS',
    'LocalTrials',
    'event_allowed',
    'event_knots',
    'gate_cluster_events',
    'place_rough_events',
    'refine_event_times',
    'search_time',
    'with_events',
    'without_events',
]

FloatArray = NDArray[np.float64]

SPAN = 0.5
"""Width [s] of the span in which rejected station epochs count as one cluster."""

MIN_VALUES = 3
"""Rejected station epochs (any field, any station) a cluster needs."""

EDGE_MARGIN = 0.5
"""No event closer than this [s] to a window edge, or (half of it) to an event already
knotted."""


SEGMENT_MARGIN = 1.0
"""No event closer than this [s] to an incomplete segment: the one or two stations there
cannot pin the acceleration on that side of a jump. At a quarter of a second (half of
:data:`EDGE_MARGIN`), robustness draw ascent 62 got events at 27.07 s and 27.72 s, before
a segment from 27.83 s that two CW radars alone see, and the positions in the segment
came out 1-6 m off at sigmas of a metre or less (120 states beyond 5 sigma); at one
second it has none."""

FIRST_STEP = 0.01
"""First step [s] of the search for an event's time; each further step downhill doubles."""

MAX_TRIALS = 8
"""Solves the search for one event's time may spend (beyond its grid)."""

ROUGH_REACH = 0.6
"""How far [s] the search may move an event of the rough trajectory: its detector, fitting
quadratics over a second or two of telemetry, can misplace one of two jumps half a second
apart (a cut-off and the next ignition) by that much."""


GRID_STEP = 0.1
"""Step [s] of the grid a search with a reach tries first."""

TOLERANCE = 0.001
"""The search for an event's time stops when its next trial is this close [s] to one made."""

LOCAL_S = 2.0
"""Seconds of measurements on each side of the search's reach that its trials fit."""

TRIAL_ITERATIONS = 3
"""Gauss-Newton iterations a trial time may spend (one or two settle it as a rule)."""

MOVE_CHI2 = 3.84
"""An event moves only when the cost falls by more than this (chi-square of one degree of
freedom at 5 %: the event's time, the one thing moved)."""


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
            if event_allowed(tau, (), knotted, segments.get(tid, ()), t0, t1)
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


def event_knots(
    traj: SplineTrajectory, events: Sequence[float], kinks: Sequence[float]
) -> list[float]:
    """The ``events`` (not ``kinks``) that stand on ``traj`` as repeated knots of every
    axis: acceleration jumps the spline may take."""
    kink = {round(float(k), 12) for k in kinks}
    out = []
    for e in events:
        if round(float(e), 12) in kink:
            continue
        if all(int(np.sum(np.abs(ax.interior - e) < 1e-9)) > 1 for ax in traj.axes):
            out.append(float(e))
    return out


def without_events(axes: Sequence[SplineAxis], taus: Sequence[float]) -> list[SplineAxis]:
    """``axes`` without their knots at the events ``taus``."""
    t = np.asarray(taus, dtype=float)
    return [
        SplineAxis.from_interior(
            ax.interior[np.min(np.abs(ax.interior[:, None] - t[None, :]), axis=1) > 1e-9]
            if ax.interior.size and t.size
            else ax.interior,
            ax.t0,
            ax.t1,
            ax.degree,
        )
        for ax in axes
    ]


def event_allowed(
    tau: float,
    others: Sequence[float],
    knotted: FloatArray,
    segments: Sequence[Segment],
    t0: float,
    t1: float,
) -> bool:
    """Whether an event may stand at ``tau``: :data:`EDGE_MARGIN` inside the window, half
    of it from ``others`` and the ``knotted`` events, :data:`SEGMENT_MARGIN` from the
    ``segments``."""
    near = [*others, *knotted]
    return (
        t0 + EDGE_MARGIN < tau < t1 - EDGE_MARGIN
        and not any(abs(k - tau) < 0.5 * EDGE_MARGIN for k in near)
        and not any(a - SEGMENT_MARGIN <= tau <= b + SEGMENT_MARGIN for a, b in segments)
    )


def _cleared(axes: Sequence[SplineAxis], tau: float, reach: float) -> list[SplineAxis]:
    """``axes`` without their knots within ``reach`` of ``tau``."""
    return [
        SplineAxis.from_interior(
            ax.interior[np.abs(ax.interior - tau) > reach], ax.t0, ax.t1, ax.degree
        )
        for ax in axes
    ]


def search_time(
    cost: Callable[[float], float], ok: Callable[[float], bool], tau0: float, reach: float = 0.0
) -> float:
    """The time of least ``cost`` found from ``tau0`` among the times ``ok`` allows, or
    ``tau0`` unless that lowers the cost by :data:`MOVE_CHI2`. With a ``reach``, first the
    costs on a grid of :data:`GRID_STEP` within it (the profile of a jump's time may have
    several valleys when another jump is near), and the search goes on from the least.
    After the costs at ``+- FIRST_STEP`` of the best time: while the least cost is at the
    end of the times tried, a step beyond it twice as long as the last; once a time is
    bracketed by higher costs, the vertex of the parabola through it and its neighbours
    (until it lands within :data:`TOLERANCE` of a time tried); at most :data:`MAX_TRIALS`
    costs beyond the grid."""
    tried: dict[float, float] = {tau0: cost(tau0)}
    n = int(reach / GRID_STEP + 1e-9)
    for k in range(1, n + 1):
        for t in (tau0 - k * GRID_STEP, tau0 + k * GRID_STEP):
            if ok(t):
                tried[t] = cost(t)
    budget = len(tried) - 1 + MAX_TRIALS
    start = min(tried, key=lambda t: tried[t])
    for t in (start - FIRST_STEP, start + FIRST_STEP):
        if ok(t) and t not in tried:
            tried[t] = cost(t)
    while len(tried) < budget:
        times = sorted(tried)
        k = min(range(len(times)), key=lambda j: tried[times[j]])
        if 0 < k < len(times) - 1:
            v = _vertex([(t, tried[t]) for t in times[k - 1 : k + 2]])
            if v is None or min(abs(v - t) for t in times) < TOLERANCE or not ok(v):
                break
            nxt = v
        elif len(times) > 1:
            nxt = times[k] + 2.0 * (times[k] - times[1 if k == 0 else k - 1])
            if not ok(nxt):
                break
        else:
            break
        tried[nxt] = cost(nxt)
    best = min(tried, key=lambda t: tried[t])
    return best if tried[best] < tried[tau0] - MOVE_CHI2 else tau0


def _vertex(pts: Sequence[tuple[float, float]]) -> float | None:
    """Abscissa of the minimum of the parabola through three (tau, cost) points, or None
    when they do not bend upward."""
    (x0, y0), (x1, y1), (x2, y2) = pts
    d = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / d
    b = (x2**2 * (y0 - y1) + x1**2 * (y2 - y0) + x0**2 * (y1 - y2)) / d
    return -b / (2.0 * a) if a > 0.0 else None


class LocalTrials:
    """The window's measurements within :data:`LOCAL_S` of the reach of one event's search
    around ``tau0`` (clipped to the window), fitted by the target's spline cut to that
    span: each trial time's cost is the least-squares cost of that span solved from the
    window's solution with the event there (the window's biases and white-jerk density
    held; the gross errors of the first trial gated in all). A B-spline is local, and so
    is what a jump's time changes: a trial costs a small part of a window's solve."""

    def __init__(
        self,
        prob: Problem,
        beta: FloatArray,
        tid: int,
        tau0: float,
        obs: Observations,
        cfg: EstimatorConfig,
        t0: float,
        t1: float,
        limit: float = 0.5 * SPAN,
        stiff: bool = False,
    ) -> None:
        reach = limit + LOCAL_S
        self.a, self.b = max(t0, tau0 - reach), min(t1, tau0 + reach)
        self.tid = tid
        self.traj = prob.trajs[tid]
        self.obs = obs.window(self.a, self.b)
        self.ts = np.linspace(self.a, self.b, int(200 * (self.b - self.a)) + 2)
        self.x = self.traj.states(prob._coef(beta, tid), self.ts)
        held = tuple(
            replace(
                bp, prior=float(np.clip(beta[prob.bias_offset + q], *bp.bounds)), estimate=False
            )
            for q, bp in enumerate(prob.biases)
        )
        self.cfg = replace(
            cfg, biases=held, max_iterations=min(cfg.max_iterations, TRIAL_ITERATIONS)
        )
        self.gates: dict[GateKey, NDArray[np.bool_]] | None = None
        self.jerk_q = dict(prob.jerk_q)
        self.stiff = stiff
        self.spent = 0

    def cost(self, axes: Sequence[SplineAxis], screen: bool = False) -> float:
        """Least-squares cost of the span on ``axes`` (window axes; cut to the span); with
        ``screen``, the cost one Gauss-Newton step would reach, predicted from the start
        (one Jacobian, no step taken)."""
        return self.solve(axes, screen)[0]

    def solve(
        self, axes: Sequence[SplineAxis], screen: bool = False
    ) -> tuple[float, FloatArray | None]:
        """:meth:`cost`, and the states (world position and velocity) on :attr:`ts` it
        was solved to (None with ``screen`` or when the solve failed)."""
        gap = self.cfg.knots.min_spacing
        cut = []
        for ax in axes:
            inner = ax.interior[(ax.interior > self.a + gap) & (ax.interior < self.b - gap)]
            cut.append(SplineAxis.from_interior(inner, self.a, self.b, ax.degree))
        local = self.traj.with_axes(cut)
        try:
            coef = local.fit_states(self.ts, self.x[:, :3], self.x[:, 3:])
            p = Problem(self.obs, {self.tid: (local, coef)}, self.cfg, self.a, self.b)
            # the window's white-jerk density: the same stiffness as the window's solve
            p.jerk_q.update({k: q for k, q in self.jerk_q.items() if k in p.jerk_q})
            if self.stiff:  # the density away from events near them too: an event frees
                # its jump, not the jerk around it
                p.jerk_q.update({k: self.jerk_q.get((k[0], False)) for k in p.jerk_q})
            start = np.zeros(p.n)
            start[p.offsets[self.tid] : p.offsets[self.tid] + coef.size] = coef
            start[p.bias_offset : p.bias_offset + len(p.biases)] = p.bias_prior
            if self.gates is None:
                gate_residuals(
                    p, start, dict.fromkeys(ROBUST_KINDS, GROSS_FACTOR * self.cfg.gate_sigma)
                )
                self.gates = {k: v.copy() for k, v in p.gated.items()}
            else:
                p.gated = {k: v.copy() for k, v in self.gates.items()}
            if screen:
                r, jac, _ = p.evaluate(start, True)
                assert jac is not None
                c = float(r @ r) - decrement(p, start, normal_matrix(jac), jac.T @ r)
                return (c if math.isfinite(c) else math.inf), None
            o = gauss_newton(p, start, self.cfg)
        except (ValueError, np.linalg.LinAlgError):
            return math.inf, None
        self.spent += o.iterations
        if not np.isfinite(o.cost):
            return math.inf, None
        o_t = p.offsets[self.tid]
        return o.cost, local.states(o.beta[o_t : o_t + coef.size], self.ts)


def refine_event_times(
    prob: Problem,
    beta: FloatArray,
    before: Mapping[int, Sequence[SplineAxis]],
    found: Mapping[int, Sequence[float]],
    segments: Mapping[int, Sequence[Segment]],
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
    reach: float = 0.0,
) -> tuple[dict[int, list[float]], int]:
    """The events ``found`` (per target), which ``prob`` holds on the axes ``before``
    (:func:`with_events`) and is solved for at ``beta``, each moved to the time of least
    cost that :func:`search_time` finds within ``SPAN / 2`` of it, the others held. Every trial
    solves the measurements around the event afresh (:class:`LocalTrials`) with only the
    gross errors gated (the values a misplaced jump spoils are the evidence of where it
    is) and no simple knot within reach of the search (the same freedom at every trial
    time). Returns the targets with a moved event and their event times, and the
    Gauss-Newton iterations spent."""
    moved: dict[int, list[float]] = {}
    spent = 0
    limit = max(reach, 0.5 * SPAN)
    for tid, first in found.items():
        taus = list(first)
        knotted = np.concatenate(  # the events ``before`` has
            [v[c > 1] for v, c in (np.unique(a.interior, return_counts=True) for a in before[tid])]
        )
        for i, tau0 in enumerate(first):
            clear = _cleared(before[tid], tau0, limit + cfg.knots.min_spacing)
            others = taus[:i] + taus[i + 1 :]
            trials = LocalTrials(prob, beta, tid, tau0, obs, cfg, t0, t1, limit)

            def cost(
                tau: float,
                clear: list[SplineAxis] = clear,
                others: list[float] = others,
                trials: LocalTrials = trials,
            ) -> float:
                return trials.cost(with_events(clear, [*others, tau], cfg.knots.min_spacing))

            def ok(
                tau: float,
                tau0: float = tau0,
                others: list[float] = others,
                knotted: FloatArray = knotted,
                spans: Sequence[Segment] = segments.get(tid, ()),
            ) -> bool:
                return abs(tau - tau0) <= limit + 1e-9 and event_allowed(
                    tau, others, knotted, spans, t0, t1
                )

            taus[i] = search_time(cost, ok, tau0, reach)
            spent += trials.spent
        if taus != list(first):
            moved[tid] = taus
    return moved, spent


def place_rough_events(
    prob: Problem,
    beta: FloatArray,
    bare: Mapping[int, Sequence[SplineAxis]],
    events: Mapping[int, Sequence[float]],
    segments: Mapping[int, Sequence[Segment]],
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> tuple[dict[int, list[float]], int]:
    """The rough trajectory's ``events`` (per target), which ``prob`` holds and is solved
    for at ``beta``, placed by the measurements: :func:`refine_event_times` within
    :data:`ROUGH_REACH` (on its grid), then once more within ``SPAN / 2`` of where that
    put them (each event's first search held the others where the rough trajectory had
    them). Returns the targets with a moved event and their event times, and the
    Gauss-Newton iterations spent."""
    now = {tid: list(taus) for tid, taus in events.items()}
    spent = 0
    for reach in (ROUGH_REACH, 0.0):
        moved, it = refine_event_times(prob, beta, bare, now, segments, obs, cfg, t0, t1, reach)
        spent += it
        if not moved:
            break
        now.update(moved)
    return {tid: taus for tid, taus in now.items() if taus != list(events[tid])}, spent
