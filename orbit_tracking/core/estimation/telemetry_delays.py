"""Whether a window estimates its telemetry's time-tag delays (issue 14).

A telemetry chain that tags its positions ``d_p`` seconds late (and its velocities ``d_v``)
gives position errors ``-d_p v(t)`` and velocity errors ``-d_v a(t)``: metres along track
for tens of milliseconds, and an error that turns with the vehicle. The slow error spline
``e`` of :mod:`~orbit_tracking.core.estimation.telemetry_block` can follow it only by giving
up most of the telemetry's position information, and its derivative then contradicts the
velocity rows wherever the vehicle accelerates. Two delay parameters describe it exactly.

:func:`delay_test` is the score test of
:mod:`~orbit_tracking.core.estimation.telemetry_velocity` for adding ``(d_p, d_v)`` to a
solved window (2 degrees of freedom at most, at ``telemetry_velocity_alpha``).

The events of a window's knots were found in the telemetry's velocity
(:func:`~orbit_tracking.core.estimation.knots.detect_events`), so they sit at the
telemetry's time tags, ``d_v`` after the true instants. Left there, the trajectory's
acceleration jump is misplaced by the very delay the window estimates, and the velocity
rows around the jump pull the delay towards zero with a confident sigma (robustness draw
ascent 34: 3.9 ms estimated against the true 26.4, states 9 sigma off inside an incomplete
segment). :func:`solve_with_aligned_events` estimates the delays without the telemetry
around the events, then moves them there (:func:`align_events`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.chi2 import chi2_isf
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.telemetry_velocity import (
    MIN_EPOCHS,
    ScoreTest,
    score_statistic,
)
from orbit_tracking.core.models.measurements import residual

if TYPE_CHECKING:
    from orbit_tracking.core.estimation.gauss_newton import GnOutcome
    from orbit_tracking.core.estimation.problem import Problem

__all__ = [
    'EVENT_MASK_S',
    'EVENT_SHIFT_CHI2',
    'EVENT_SHIFT_SIGMA',
    'DelayTest',
    'align_events',
    'delay_test',
    'solve_with_aligned_events',
    'station_chi2_near',
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DelayTest(ScoreTest):
    """The delay test on one target's telemetry residuals."""

    @property
    def delays(self) -> bool:
        """True when the window should estimate the delays."""
        return self.significant


def delay_test(
    prob: Problem, beta: FloatArray, obs: Observations, cfg: EstimatorConfig, t0: float, t1: float
) -> list[DelayTest]:
    """The score test for every telemetry block of ``prob`` without delays, at the
    solution ``beta``."""
    from orbit_tracking.core.estimation.knot_refinement import rebuild

    out = []
    for tb in prob.telemetry:
        use_p, use_v = prob.telemetry_use(tb)
        if tb.delays or min(int(use_p.sum()), int(use_v.sum())) < MIN_EPOCHS:
            continue
        aug, beta_a = rebuild(prob, beta, {}, {}, obs, cfg, t0, t1, tel_delays={tb.target: True})
        ta = next(b for b in aug.telemetry if b.target == tb.target)
        score = score_statistic(aug, beta_a, np.arange(ta.delay_offset, ta.delay_offset + 2))
        if score is None:
            continue
        stat, dof = score
        out.append(
            DelayTest(tb.target, stat, float(chi2_isf(cfg.telemetry_velocity_alpha, dof)), dof)
        )
    return out


def align_events(
    traj: SplineTrajectory,
    events: Sequence[float],
    old_shift: float,
    new_shift: float,
    min_spacing: float,
) -> list[SplineAxis] | None:
    """The axes of ``traj`` with its knots at the telemetry ``events`` (detected at the
    telemetry's time tags, now at ``event - old_shift``) moved to ``event - new_shift``;
    single knots closer than ``min_spacing`` to a moved event are dropped. None when no
    event knot lies inside the spline (nothing to move)."""
    axes: list[SplineAxis] = []
    moved = False
    at = [e - old_shift for e in events]
    to = [e - new_shift for e in events]
    for ax in traj.axes:
        knots = ax.interior.copy()
        keep = np.ones(knots.size, dtype=bool)
        new: list[float] = []
        for a, b in zip(at, to, strict=True):
            hit = np.abs(knots - a) < 1e-9
            if not hit.any() or not (ax.t0 + min_spacing < b < ax.t1 - min_spacing):
                continue
            keep &= ~hit
            lo, hi = min(a, b) - min_spacing, max(a, b) + min_spacing
            keep &= ~((knots > lo) & (knots < hi))  # the knots it would cross or crowd
            new.extend([b] * int(hit.sum()))
            moved = True
        axes.append(
            SplineAxis.from_interior(
                np.sort(np.concatenate([knots[keep], new])), ax.t0, ax.t1, ax.degree
            )
        )
    return axes if moved else None


EVENT_MASK_S = 2.0
"""Seconds of telemetry on each side of an event left out while the delays are estimated
for :func:`solve_with_aligned_events` (the white-jerk prior's margin around an event)."""


EVENT_SHIFT_SIGMA = 3.0
"""The events are moved only by a velocity delay this many of its sigmas from zero."""

EVENT_SHIFT_CHI2 = 3.84
"""... and only when the station values within :data:`EVENT_MASK_S` of the events fit
better by this much (chi-square of one degree of freedom at 5 %: the events' time, the one
thing moved) on the moved knots than on the telemetry's own time tags."""


def station_chi2_near(prob: Problem, beta: FloatArray, times: FloatArray, width: float) -> float:
    """Sum of the squared station residuals used (in their declared sigmas) within
    ``width`` [s] of any of ``times``: the evidence of data whose errors the telemetry's do
    not share."""
    total = 0.0
    for bi, b in enumerate(prob.stations):
        near = np.min(np.abs(b.time[:, None] - times[None, :]), axis=1) <= width
        if not near.any():
            continue
        pred, _, _ = prob.predict_block(bi, beta)
        with np.errstate(over='ignore', invalid='ignore'):
            r = residual(b.fields, np.nan_to_num(b.values), pred) / b.declared
        use = b.valid & ~prob.gated.get(bi, np.zeros_like(b.valid)) & near[:, None]
        total += float(np.sum(r[use] ** 2))
    return total


def solve_with_aligned_events(
    prob: Problem,
    out: GnOutcome,
    events: Mapping[int, Sequence[float]],
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> tuple[Problem, GnOutcome, int, int, str]:
    """The window solved again with the knots at its telemetry ``events`` (per target,
    the times detected in the telemetry) moved to the estimated velocity delay, for
    every target whose telemetry delays are estimated: first the delays are estimated
    without the telemetry within :data:`EVENT_MASK_S` of an event (where the misplaced
    jump pulls them), then the events are moved by that velocity delay
    (:func:`align_events`) when it is :data:`EVENT_SHIFT_SIGMA` of its sigmas from zero,
    and the window is solved with every row. Returns the
    problem, its solution, the iterations and halvings spent and a note for the window
    message ('' when nothing moved)."""
    from orbit_tracking.core.estimation.gauss_newton import covariance, solve
    from orbit_tracking.core.estimation.knot_refinement import rebuild

    todo = {
        tb.target: np.asarray([e for e in events.get(tb.target, ()) if t0 < e < t1])
        for tb in prob.telemetry
        if tb.delays
    }
    todo = {tid: ev for tid, ev in todo.items() if ev.size}
    if not todo:
        return prob, out, 0, 0, ''
    gated = {k: v.copy() for k, v in prob.gated.items()}  # (shared by the rebuilt problems)
    masked, beta = rebuild(prob, out.beta, {}, {}, obs, cfg, t0, t1)
    for tb in masked.telemetry:
        if tb.target in todo:
            near = np.min(np.abs(tb.time[:, None] - todo[tb.target][None, :]), axis=1)
            keep = near > EVENT_MASK_S
            tb.valid_p = tb.valid_p & keep
            tb.valid_v = tb.valid_v & keep
    first, iterations, halvings = solve(masked, beta, cfg, warm_up=False)
    cov = covariance(masked, first.beta)[2]
    shifts: dict[int, float] = {}
    axes = {}
    for tb in masked.telemetry:
        if tb.target not in todo:
            continue
        o = tb.delay_offset + 1
        d_v = float(first.beta[o])
        if not abs(d_v) > EVENT_SHIFT_SIGMA * math.sqrt(max(float(cov[o, o]), 0.0)):
            continue  # no velocity delay to speak of (a delay test that fired on another error)
        moved = align_events(
            prob.trajs[tb.target], list(todo[tb.target]), 0.0, d_v, cfg.knots.min_spacing
        )
        if moved is not None:
            axes[tb.target] = moved
            shifts[tb.target] = d_v
    if not axes:
        return prob, out, iterations, halvings, ''
    # the problem on the moved knots, every telemetry row back (rebuild starts afresh)
    new, beta = rebuild(masked, first.beta, axes, {}, obs, cfg, t0, t1)
    final, it2, h2 = solve(new, beta, cfg, warm_up=False)
    # the stations referee: telemetry errors that are not white (a random walk, a velocity
    # of its own) fire the delay test and give a delay of tens of milliseconds, and the
    # moved acceleration jump left the velocity ringing 0.25 m/s around it at 0.03 m/s
    # sigmas (robustness ascent draw 1010 of the scratch seeds: 38 ms, none true)
    near = np.concatenate([todo[tid] for tid in axes])
    chi2_kept = station_chi2_near(prob, out.beta, near, EVENT_MASK_S)
    chi2_moved = station_chi2_near(new, final.beta, near, EVENT_MASK_S)
    verb = 'moved' if chi2_moved < chi2_kept - EVENT_SHIFT_CHI2 else 'not moved'
    note = (
        ''.join(
            f'; telemetry {tid} events {verb} {1e3 * abs(d):.1f} ms '
            f'{"earlier" if d > 0.0 else "later"} to its velocity delay'
            for tid, d in sorted(shifts.items())
        )
        + f' (station chi2 near them {chi2_moved:.1f} moved, {chi2_kept:.1f} not)'
    )
    if verb == 'not moved':
        prob.gated.clear()
        prob.gated.update(gated)
        return prob, out, iterations + it2, halvings + h2, note
    return new, final, iterations + it2, halvings + h2, note
