"""Events at doubtful changes of acceleration that the measurements ask for (beyond the
paper).

A change of acceleration the rough trajectory's detector saw below its threshold is
*doubtful*: no knot, only a consider term in the covariance. Without telemetry the rough
trajectory is the triangulated fixes and the changes come from the first solution, whose
detector, fitting over a second or more each side, blurs two jumps a second apart into
doubtful changes about a second from either. On robustness draw ascent 98 (seven
stations, no telemetry, a cut-off and an ignition 1.14 s apart) the spline then rounded
the corners of the velocity, 1-2 m/s off at sigmas of 0.3-0.4 m/s, and too few values
were rejected for the gate's clusters (:mod:`.gate_events`) to find the jumps.

So :func:`doubtful_events` asks the measurements, at each doubtful change, whether an
event near it lowers their cost by more than the parameters it adds explain (a
likelihood-ratio test), on the local trials of :mod:`.gate_events`. The white-jerk
density away from events holds near the trial event too, so that the event frees its
jump and not the jerk around it (with the window's looser density near events the test
took events where there were none).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2 as chi2_dist

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.config import EstimatorConfig, Segment
from orbit_tracking.core.estimation.gate_events import (
    SPAN,
    LocalTrials,
    event_allowed,
    search_time,
    with_events,
)
from orbit_tracking.core.estimation.problem import Problem

__all__ = ['DOUBT_ALPHA', 'DOUBT_REACH', 'DOUBT_STEP', 'ECHO', 'doubtful_events']

FloatArray = NDArray[np.float64]

ECHO = 0.5
"""A doubtful change this close [s] to an event already knotted is taken for its echo."""

DOUBT_REACH = 1.2
"""How far [s] from a doubtful change an event may be taken: the first solution's change
detector, over a second or more each side, blurs two jumps a second apart into changes
about a second from either."""

DOUBT_ALPHA = 0.01
"""False-alarm probability of the test that takes an event at a doubtful change."""

DOUBT_STEP = 0.2
"""Step [s] of the grid screened around a doubtful change."""


class _Doubtful:
    """The search for events at one target's doubtful changes (:func:`doubtful_events`)."""

    def __init__(
        self,
        prob: Problem,
        beta: FloatArray,
        tid: int,
        cands: Sequence[float],
        segments: Sequence[Segment],
        obs: Observations,
        cfg: EstimatorConfig,
        t0: float,
        t1: float,
        scale: float,
    ) -> None:
        self.knotted = prob.trajs[tid].repeated_knots()
        self.scale = max(scale, 1.0)
        self.spans = segments
        self.axes = list(prob.trajs[tid].axes)
        self.taken: list[float] = []
        self.min_spacing = cfg.knots.min_spacing
        self.t0, self.t1 = t0, t1
        self.trials = {
            d: LocalTrials(prob, beta, tid, d, obs, cfg, t0, t1, DOUBT_REACH, stiff=True)
            for d in sorted(set(cands))
            if t0 < d < t1 and not any(abs(d - k) < ECHO for k in self.knotted)
        }

    def ok(self, tau: float, d: float, beyond: float = 0.0) -> bool:
        """Whether an event may stand at ``tau`` for the doubtful change ``d``."""
        return abs(tau - d) <= DOUBT_REACH + beyond + 1e-9 and event_allowed(
            tau, self.taken, self.knotted, self.spans, self.t0, self.t1
        )

    def best_of(self, d: float) -> tuple[float, float]:
        """The best time near ``d`` and its gain (``-inf``: none). A grid of
        :data:`DOUBT_STEP` screened by one predicted step each; where the best of it gains
        half the chi-square or more, the search from there by full trials."""
        trials, axes = self.trials[d], self.axes
        base = trials.cost(axes)
        if not math.isfinite(base):
            return d, -math.inf
        n = int(DOUBT_REACH / DOUBT_STEP + 1e-9)
        grid = [d + k * DOUBT_STEP for k in range(-n, n + 1)]
        screened = {
            t: trials.cost(with_events(axes, [t], self.min_spacing), screen=True)
            for t in grid
            if self.ok(t, d)
        }
        if not screened:
            return d, -math.inf
        first = min(screened, key=lambda t: screened[t])
        new = with_events(axes, [first], self.min_spacing)
        added = sum(b.interior.size - a.interior.size for a, b in zip(axes, new, strict=True))
        limit = self.scale * float(chi2_dist.ppf(1.0 - DOUBT_ALPHA, max(added, 0) + 1))
        if base - screened[first] < 0.5 * limit:
            return d, -math.inf
        costs: dict[float, float] = {}

        def cost(tau: float) -> float:
            costs[tau] = trials.cost(with_events(axes, [tau], self.min_spacing))
            return costs[tau]

        search_time(cost, lambda tau: self.ok(tau, d, 0.5 * SPAN), first)
        best = min(costs, key=lambda t: costs[t])
        return best, base - costs[best] - limit

    def run(self) -> tuple[list[float], int]:
        """The events taken, and the Gauss-Newton iterations spent."""
        found = {d: self.best_of(d) for d in self.trials}
        while found:
            d = max(found, key=lambda e: found[e][1])
            tau, gain = found.pop(d)
            if gain <= 0.0:
                break
            if not self.ok(tau, d, 0.5 * SPAN):  # searched before an event near it was taken
                found[d] = self.best_of(d)
                continue
            self.taken.append(tau)
            self.axes = with_events(self.axes, [tau], self.min_spacing)
            for e in found:
                if abs(e - tau) < DOUBT_REACH:
                    found[e] = self.best_of(e)
        return sorted(self.taken), sum(t.spent for t in self.trials.values())


def doubtful_events(
    prob: Problem,
    beta: FloatArray,
    doubtful: Mapping[int, Sequence[float]],
    segments: Mapping[int, Sequence[Segment]],
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
    scale: float = 1.0,
) -> tuple[dict[int, list[float]], int]:
    """Events at the ``doubtful`` changes (per target) that the measurements ask for.
    Around each (not within :data:`ECHO` of an event knotted), an event's time is
    searched on the local trials of :func:`refine_event_times` within
    :data:`DOUBT_REACH`, with the white-jerk density away from events near it too (an
    event frees its jump, not the jerk around it) and the simple knots kept: a grid
    screened by one predicted Gauss-Newton step each, then the search from its best. Its
    gain is how far its least cost lies below the cost without it, beyond the chi-square
    of the parameters it adds and its time at ``1 -`` :data:`DOUBT_ALPHA` (times ``scale``,
    the window's chi-square per degree of freedom, when above one). The event of
    largest positive gain is taken, the searches within ``DOUBT_REACH`` of it made again
    with it, and so on: a jump's misfit spreads, and an event a second beside it gains
    too. Returns the targets with events taken and their times, and the Gauss-Newton
    iterations spent."""
    out: dict[int, list[float]] = {}
    spent = 0
    for tid, cands in doubtful.items():
        taken, it = _Doubtful(
            prob, beta, tid, cands, segments.get(tid, ()), obs, cfg, t0, t1, scale
        ).run()
        spent += it
        if taken:
            out[tid] = taken
    return out, spent
