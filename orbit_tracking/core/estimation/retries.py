"""What a window that is not a success is solved again with (issue 14).

**An incomplete segment at a window edge.** A window whose end (or start) lies inside an
incomplete segment has nothing beyond that edge to anchor the segment's part of the
trajectory: two CW radars place it on a circle, one theodolite on a line, and the solve
crawls along that valley without settling (robustness ascent draw 1022 of the scratch
seeds: 23 s of iterations, then a failed window and its 40 s of good data lost). A segment
shorter than the windows' overlap is covered by the window next to it with data on both
sides, so this window is cut at the segment's boundary (:func:`cut_span`; not later: where
the unsettled solution's covariance still looked linear was no guide, draw 1011's window
cut 5 s into its segment crawled as the whole one had). A longer segment reaching past the
edges of both windows is held by neither with data on both sides, and is left out. The
cut is made in two ways:

* when the segment holds no telemetry (telemetry anchors it) and another window covers
  it (at the start: the previous window reaches past the segment's end; at the end: a
  window follows), the first attempt gives up as soon as its first solve has not settled
  (:class:`EdgeNotSettled`) and the cut span becomes the window, for the solve and every
  retry below;
* a window that failed otherwise is solved cut (:func:`edge_cut`): a cut window publishes
  what its data hold, a failed one nothing. It is the first retry when the failed fit was
  consistent (chi2/dof within ``max_chi2_dof``: it did not settle, as at an edge segment);
  after the safer settings when it did not fit the data, their own remedy (robustness
  ascent draw 88, time-skewed telemetry: cut first, the window's position error was
  0.64 m RMS; with fewer knots first, 0.06 m).

A cut window's estimate spans the cut span; a sliver between it and the next window's start
is left out of the trajectory rather than published from a solve that did not settle.

**Safer settings** (:func:`safer_settings`) follow: fewer knots, then without telemetry
fused. When none is a success, the attempt with the smallest chi-square per degree of
freedom is returned as failed, its message naming every attempt.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import replace

import numpy as np

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.config import EstimationError, EstimatorConfig, Segment
from orbit_tracking.core.estimation.gauss_newton import GnOutcome
from orbit_tracking.core.estimation.results import Estimate, TargetSolution

__all__ = [
    'COVERED_S',
    'EDGE_TOLERANCE_S',
    'MIN_CUT_S',
    'Attempt',
    'EdgeNotSettled',
    'cut_span',
    'edge_cut',
    'give_up_early',
    'previous_end',
    'safer_settings',
    'solve_with_retries',
]

MIN_CUT_S = 5.0
"""A window cut short of an incomplete segment keeps at least this span [s]; a shorter
one is not tried (too little data for a spline solve with its own knots)."""

EDGE_TOLERANCE_S = 1e-6
"""A segment within this of a window edge touches it."""

Attempt = Callable[
    [float, float, EstimatorConfig, Mapping[int, TargetSolution] | None, bool], Estimate
]
"""One solve of the window ``[t0, t1]`` with ``cfg`` from ``previous``; with ``quick`` it
may raise :class:`EdgeNotSettled` instead of solving a window it cannot settle to the end."""


def safer_settings(
    cfg: EstimatorConfig,
    previous: Mapping[int, TargetSolution] | None,
    telemetry: bool = True,
) -> list[tuple[str, EstimatorConfig, Mapping[int, TargetSolution] | None]]:
    """The retries of a window that was not a success, safest last: a start from the rough
    trajectory alone with fewer knots (events and a knot every ``baseline_spacing`` s; the
    measurement-driven knot test then adds those the residuals ask for, a manoeuvre that 3 s
    knots cannot follow), then the same without telemetry fused (telemetry whose errors its model
    does not describe pulls the fit away from the stations); that one only when the window
    has ``telemetry``: without, it is the same solve again (a failed window without
    telemetry, robustness ascent draw 1022 of the scratch seeds, spent a third of its 29 s
    on it)."""
    del previous  # the retries start from the rough trajectory, not the previous window
    fewer = replace(cfg, knot_method='dynamics')
    out: list[tuple[str, EstimatorConfig, Mapping[int, TargetSolution] | None]] = [
        (
            f'fewer knots (every {cfg.baseline_spacing:g} s and events, then the knot test)',
            fewer,
            None,
        )
    ]
    if cfg.use_telemetry and telemetry:
        out.append(('fewer knots, telemetry not fused', replace(fewer, use_telemetry=False), None))
    return out


def cut_span(
    t0: float,
    t1: float,
    segments: Iterable[Segment],
    start: bool = True,
    end: bool = True,
    min_span: float = MIN_CUT_S,
    after: float = -math.inf,
) -> tuple[float, float] | None:
    """``[t0, t1]`` cut at the boundaries of the incomplete ``segments`` (of every target)
    that touch its edges (only at the start with ``start``, at the end with ``end``), or
    None when none does, less than ``min_span`` seconds would remain, or the cut window
    would not end after ``after`` (the previous window's end: a window that ends earlier
    adds nothing to it, and the results node takes a window ending before the last one
    for time going back)."""
    lo, hi = t0, t1
    for a, b in segments:
        if end and b >= t1 - EDGE_TOLERANCE_S and a > t0:
            hi = min(hi, a)
        if start and a <= t0 + EDGE_TOLERANCE_S and b < t1:
            lo = max(lo, b)
    if (lo, hi) == (t0, t1) or hi - lo < min_span or not hi > after:
        return None
    return lo, hi


def previous_end(previous: Mapping[int, TargetSolution] | None) -> float:
    """The end of the previous window's solution (-inf without one)."""
    return max((p.t1 for p in previous.values()), default=-math.inf) if previous else -math.inf


def edge_cut(
    failed: Estimate, min_span: float = MIN_CUT_S, after: float = -math.inf
) -> tuple[float, float] | None:
    """The span of ``failed`` (a window that was not a success) cut at the incomplete
    segments at both its edges (:func:`cut_span`)."""
    segs = [seg for sol in failed.targets.values() for seg in sol.segments]
    return cut_span(failed.t0, failed.t1, segs, min_span=min_span, after=after)


class EdgeNotSettled(EstimationError):
    """A first solve that did not settle, with an incomplete segment at a window edge
    that another window covers: raised by the estimator when asked to give up early
    (``quick`` of :data:`Attempt`), with the span to solve instead."""

    def __init__(self, span: tuple[float, float], decrement: float) -> None:
        self.span = span
        self.decrement = decrement
        super().__init__(
            f'the first solve did not settle (its Gauss-Newton step would still lower the '
            f'cost by {decrement:.3g}) with an incomplete segment at the window edge'
        )


COVERED_S = 1.0
"""Data more than this [s] after a window's end mean another window follows it
(``more_after`` of :func:`~orbit_tracking.core.estimation.estimator.estimate`)."""


def give_up_early(
    out: GnOutcome,
    obs: Observations,
    segments: Mapping[int, tuple[Segment, ...]],
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
    previous: Mapping[int, TargetSolution] | None,
    more_after: bool,
) -> None:
    """Raise :class:`EdgeNotSettled` when the first
    solve did not settle (not converged, and beyond ``max_unconverged_decrement``) and an
    incomplete segment without telemetry lies at a window edge where another window covers
    it: at the start, a ``previous`` window reaching past the segment's end; at the end,
    one that follows (``more_after``). The solve would crawl along the segment's
    unanchored valley for many rounds (robustness ascent draw 1022 of the scratch seeds:
    23 s, then failed). A segment with telemetry in it is anchored by it (draw 1028: such a
    window, cut, lost the leverage of its last 18 s on the telemetry's error and its error
    outside the segment grew from 0.79 to 1.22 times the bound). The span to solve instead
    is :func:`cut_span`'s."""
    if out.converged or not out.decrement > cfg.max_unconverged_decrement:
        return
    segs = []
    for tid, spans in segments.items():
        tel = obs.telemetry.get(tid) if cfg.use_telemetry else None
        prev = previous.get(tid) if previous else None
        for x, y in spans:
            if tel is not None and np.any((tel.time >= x) & (tel.time <= y)):
                continue
            if x <= t0 + EDGE_TOLERANCE_S and (prev is None or prev.t1 < y):
                continue  # no window before this one holds the segment
            segs.append((x, y))
    span = cut_span(t0, t1, segs, end=more_after, after=previous_end(previous))
    if span is not None:
        raise EdgeNotSettled(span, out.decrement)


def _cut_label(span: tuple[float, float]) -> str:
    return (
        f'the window cut to [{span[0]:.2f}, {span[1]:.2f}] s, short of the incomplete segment '
        'at its edge'
    )


def solve_with_retries(
    attempt: Attempt,
    t0: float,
    t1: float,
    cfg: EstimatorConfig,
    previous: Mapping[int, TargetSolution] | None,
    telemetry: bool,
) -> Estimate:
    """The first attempt, then the retries of the module docstring until one is a success
    (``telemetry``: whether the window holds telemetry, for :func:`safer_settings`). With
    ``cfg.retry`` the first attempt may give up early (:class:`EdgeNotSettled`): the span
    it names is then the window."""
    early = ''
    try:
        first = attempt(t0, t1, cfg, previous, cfg.retry)
    except EdgeNotSettled as exc:
        early = f'; {_cut_label(exc.span)}: {exc}'
        t0, t1 = exc.span
        first = attempt(t0, t1, cfg, previous, False)
    if first.success or not cfg.retry:
        return replace(first, message=first.message + early) if early else first
    tried = [('the settings', first)]
    plan: list[tuple[str, EstimatorConfig, Mapping[int, TargetSolution] | None, float, float]]
    plan = [(*s, t0, t1) for s in safer_settings(cfg, previous, telemetry)]
    cut = edge_cut(first, after=previous_end(previous))
    if cut is not None:
        # first when the fit was consistent but did not settle (what an edge segment
        # does); after the safer settings when it did not fit (their own remedy)
        at = 0 if first.chi2_dof <= cfg.max_chi2_dof else len(plan)
        plan.insert(at, (_cut_label(cut), cfg, previous, *cut))
    for label, cfg2, prev2, a, b in plan:
        try:
            e = attempt(a, b, cfg2, prev2, False)
        except OrbitTrackingError as exc:
            tried.append((label, replace(first, message=f'{label}: {exc}', chi2_dof=math.inf)))
            continue
        tried.append((label, e))
        if e.success:
            return replace(
                e,
                message=f'{e.message}; solved with {label} after: {first.message}{early}',
                iterations=sum(t.iterations for _, t in tried),
                attempts=len(tried),
            )
    best = min(tried, key=lambda t: t[1].chi2_dof if math.isfinite(t[1].chi2_dof) else math.inf)
    text = ' | '.join(f'{label}: {e.message}' for label, e in tried)
    return replace(
        best[1],
        success=False,
        message=f'FAILED with every setting tried ({text}){early}',
        iterations=sum(t.iterations for _, t in tried),
        attempts=len(tried),
    )
