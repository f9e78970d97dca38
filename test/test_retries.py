"""The retries of a window that is not a success (issue 14): the window cut short of an
incomplete segment at its edge (:func:`~orbit_tracking.core.estimation.retries.edge_cut`),
then the safer settings, in that order, with the attempt that succeeds returned."""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.results import Estimate
from orbit_tracking.core.estimation.retries import (
    MIN_CUT_S,
    EdgeNotSettled,
    cut_span,
    edge_cut,
    give_up_early,
    solve_with_retries,
)


def _estimate(t0: float, t1: float, success: bool, chi2: float = 1.0, **targets: Any) -> Estimate:
    """An estimate whose targets (keyword ``target<id>=(segments, isotropic spans)``)
    carry only what :func:`edge_cut` reads."""
    sols = {
        int(k.removeprefix('target')): SimpleNamespace(segments=seg, isotropic_spans=iso)
        for k, (seg, iso) in targets.items()
    }
    return Estimate(
        success=success,
        message='ok' if success else 'FAILED (not converged)',
        t0=t0,
        t1=t1,
        targets=sols,  # type: ignore[arg-type]  # edge_cut reads these two fields only
        iterations=3,
        halvings=0,
        cost=1.0,
        chi2_dof=chi2,
        condition=1.0,
        n_parameters=10,
        used=Counter(),
        rejected=Counter(),
        residuals={},
        knot_time=0.0,
        solve_time=0.0,
    )


def test_the_edges_are_cut_at_the_segments_boundaries_and_the_narrowest_target_decides():
    e = _estimate(0.0, 60.0, False, target0=(((40.0, 60.0),), ()))
    assert edge_cut(e) == (0.0, 40.0)
    e = _estimate(
        40.0,
        100.0,
        False,
        target0=(((40.0, 50.0), (60.0, 70.0)), ()),
        target1=(((40.0, 45.0), (90.0, 100.0)), ()),
    )
    assert edge_cut(e) == (50.0, 90.0)


@pytest.mark.parametrize(
    'segments',
    [
        ((20.0, 30.0),),  # inside: no edge to cut
        ((0.0, 60.0),),  # the whole window: nothing would remain
        ((0.0, 25.0), (24.0 + MIN_CUT_S, 60.0)),  # less than MIN_CUT_S would remain
        (),
    ],
)
def test_no_cut_without_a_segment_at_an_edge_or_with_too_little_left(segments):
    assert edge_cut(_estimate(0.0, 60.0, False, target0=(segments, ()))) is None


def test_the_cut_window_is_tried_first_and_its_success_is_returned():
    calls: list[tuple[float, float, str]] = []

    def attempt(a, b, cfg, prev, quick):
        calls.append((a, b, cfg.knot_method))
        if (a, b) == (0.0, 60.0):
            return _estimate(a, b, False, chi2=1.0, target0=(((40.0, 60.0),), ()))
        return _estimate(a, b, True)

    out = solve_with_retries(attempt, 0.0, 60.0, EstimatorConfig(), None, telemetry=True)
    assert calls == [(0.0, 60.0, 'sparse'), (0.0, 40.0, 'sparse')]
    assert out.success and (out.t0, out.t1) == (0.0, 40.0) and out.attempts == 2
    assert 'cut to [0.00, 40.00] s' in out.message and 'FAILED' in out.message


def test_a_window_whose_fit_was_inconsistent_tries_the_safer_settings_before_the_cut():
    """A failed fit that does not fit the data (chi2/dof far above its limit) is not what
    an edge segment does: the safer settings, its own remedy, come first (robustness ascent
    draw 88, time-skewed telemetry: cut first, the window's position error was 0.64 m RMS
    and the draw's 4.3 times its bound; with fewer knots first, 0.06 m)."""
    calls: list[tuple[float, float, str]] = []

    def attempt(a, b, cfg, prev, quick):
        calls.append((a, b, cfg.knot_method))
        return _estimate(a, b, False, chi2=5522.0, target0=(((0.0, 6.0),), ()))

    solve_with_retries(attempt, 0.0, 60.0, EstimatorConfig(), None, telemetry=False)
    assert calls == [(0.0, 60.0, 'sparse'), (0.0, 60.0, 'dynamics'), (6.0, 60.0, 'sparse')]


def test_without_a_segment_at_an_edge_the_safer_settings_follow_and_all_failing_fails():
    calls: list[tuple[float, float, str, bool]] = []

    def attempt(a, b, cfg, prev, quick):
        calls.append((a, b, cfg.knot_method, cfg.use_telemetry))
        return _estimate(a, b, False, chi2=5.0 - len(calls), target0=(((20.0, 30.0),), ()))

    out = solve_with_retries(attempt, 0.0, 60.0, EstimatorConfig(), None, telemetry=True)
    assert calls == [
        (0.0, 60.0, 'sparse', True),
        (0.0, 60.0, 'dynamics', True),
        (0.0, 60.0, 'dynamics', False),
    ]
    assert not out.success and out.attempts == 3 and out.chi2_dof == 2.0
    assert out.message.startswith('FAILED with every setting tried')
    # no retry at all when asked for none
    calls.clear()
    out = solve_with_retries(
        attempt, 0.0, 60.0, EstimatorConfig(retry=False), None, telemetry=True
    )
    assert len(calls) == 1 and not out.success


def test_cut_span_cuts_only_the_edges_asked_for():
    """The estimator gives up early only at an edge beyond which other data (another
    window) cover the segment."""
    segs = ((0.0, 12.0), (45.0, 60.0))
    assert cut_span(0.0, 60.0, segs) == (12.0, 45.0)
    assert cut_span(0.0, 60.0, segs, start=False) == (0.0, 45.0)
    assert cut_span(0.0, 60.0, segs, end=False) == (12.0, 60.0)
    assert cut_span(0.0, 60.0, segs, start=False, end=False) is None


def test_no_cut_that_would_end_before_the_previous_window():
    """A window cut to end before the previous window's end adds nothing to it, and the
    results node would take it for time going back: not tried, neither as a retry nor
    when giving up early."""
    segs = ((55.0, 100.0),)
    assert cut_span(40.0, 100.0, segs) == (40.0, 55.0)
    assert cut_span(40.0, 100.0, segs, after=60.0) is None
    assert cut_span(40.0, 100.0, segs, after=50.0) == (40.0, 55.0)
    calls: list[tuple[float, float, str]] = []

    def attempt(a, b, cfg, prev, quick):
        calls.append((a, b, cfg.knot_method))
        return _estimate(a, b, False, target0=(segs, ()))

    previous = {0: SimpleNamespace(t1=60.0)}
    solve_with_retries(attempt, 40.0, 100.0, EstimatorConfig(), previous, telemetry=False)
    assert calls == [(40.0, 100.0, 'sparse'), (40.0, 100.0, 'dynamics')]


def test_a_first_attempt_that_gives_up_early_is_solved_cut_at_once():
    """The first attempt (asked to be quick) raises EdgeNotSettled: the span it names is
    solved next, not quick; its success is returned, naming why."""
    calls: list[tuple[float, float, bool]] = []

    def attempt(a, b, cfg, prev, quick):
        calls.append((a, b, quick))
        if quick:
            raise EdgeNotSettled((0.0, 41.0), 637.0)
        return _estimate(a, b, True)

    out = solve_with_retries(attempt, 0.0, 60.0, EstimatorConfig(), None, telemetry=False)
    assert calls == [(0.0, 60.0, True), (0.0, 41.0, False)]
    assert out.success and (out.t0, out.t1) == (0.0, 41.0)
    assert 'cut to [0.00, 41.00] s' in out.message and 'did not settle' in out.message


def test_after_giving_up_early_the_cut_span_is_the_window_for_every_retry():
    """The whole window, which did not settle, is not solved again: the retries are on
    the cut span, and when they all fail the window fails saying why it was cut."""
    calls: list[tuple[float, float, bool, str]] = []

    def attempt(a, b, cfg, prev, quick):
        calls.append((a, b, quick, cfg.knot_method))
        if quick:
            raise EdgeNotSettled((0.0, 41.0), 637.0)
        return _estimate(a, b, False, chi2=3.0, target0=(((20.0, 30.0),), ()))

    out = solve_with_retries(attempt, 0.0, 60.0, EstimatorConfig(), None, telemetry=False)
    assert calls == [
        (0.0, 60.0, True, 'sparse'),
        (0.0, 41.0, False, 'sparse'),
        (0.0, 41.0, False, 'dynamics'),
    ]
    assert not out.success and out.attempts == 2 and (out.t0, out.t1) == (0.0, 41.0)
    assert out.message.startswith('FAILED with every setting tried')
    assert 'did not settle' in out.message
    # without retries the first attempt is never asked to be quick
    calls.clear()
    solve_with_retries(attempt, 0.0, 60.0, EstimatorConfig(retry=False), None, telemetry=False)
    assert calls == [(0.0, 60.0, False, 'sparse')]


def test_a_window_ending_inside_an_unanchored_segment_is_solved_cut_short_of_it():
    """Robustness ascent draw 1022 (scratch seeds, no telemetry): its first window ends
    inside an incomplete segment (39.7-65.2 s) that two CW radars alone see. Solved to
    its end the Gauss-Newton crawled for 23 s without settling and the window failed,
    taking its 40 s of good data with it. Now the first solve gives up and the window is
    solved up to the segment, a success whose states are within a metre and honest."""
    from orbit_tracking.core.estimation.estimator import estimate
    from orbit_tracking.core.metrics import nees
    from orbit_tracking.tools.bench.robustness_draw import _case
    from orbit_tracking.tools.estimator_parameters import estimator_configs

    case = _case('ascent', 1022)
    cfg = estimator_configs({})[0]
    est = estimate(case.obs_est, 0.0121, 60.0121, cfg)
    assert est.success, est.message
    assert 'did not settle' in est.message and 'cut to' in est.message
    assert est.t0 == 0.0121 and abs(est.t1 - 39.73) < 0.5, (est.t0, est.t1)
    sel = (case.truth_t >= est.t0) & (case.truth_t <= est.t1)
    x, cov = est.targets[0].states(case.truth_t[sel])
    err = x[:, :3] - case.truth_x[sel, :3]
    assert np.max(np.linalg.norm(err, axis=1)) < 1.0
    assert np.max(nees(err, cov[:, :3, :3])) < 25.0


def test_the_first_solve_gives_up_only_on_an_unanchored_segment_another_window_covers():
    """Given up early: not settled, a segment at the edge without telemetry in it, and
    another window holding it (a window that follows; at the start, a previous window that
    reaches past the segment). Telemetry in the segment anchors it; a settled solve (or one
    within ``max_unconverged_decrement``) is kept."""
    from orbit_tracking.core.data.observations import Observations
    from orbit_tracking.core.data.tables import TargetStates
    from orbit_tracking.core.estimation.gauss_newton import GnOutcome

    def tel(*spans):  # telemetry at 10 Hz over the spans (only its times matter here)
        t = np.concatenate([np.arange(a, b, 0.1) for a, b in spans])
        z = np.zeros((t.size, 3))
        return Observations((), {0: TargetStates(0, t, z, z, z + 1.0, z + 0.1)})

    cfg = EstimatorConfig()
    crawl = GnOutcome(np.zeros(3), 1.0, 20, 20, False, 'iteration limit', 637.0)
    end = {0: ((40.0, 60.0),)}
    outage = tel((0.0, 39.0)).window(0.0, 60.0)
    with pytest.raises(EdgeNotSettled) as info:
        give_up_early(crawl, outage, end, cfg, 0.0, 60.0, None, True)
    assert info.value.span == (0.0, 40.0) and info.value.decrement == 637.0
    give_up_early(crawl, outage, end, cfg, 0.0, 60.0, None, False)  # the last window
    anchored = tel((0.0, 60.0))
    give_up_early(crawl, anchored, end, cfg, 0.0, 60.0, None, True)
    settled = GnOutcome(np.zeros(3), 1.0, 5, 0, True, 'converged', 1e-6)
    give_up_early(settled, outage, end, cfg, 0.0, 60.0, None, True)
    near = GnOutcome(np.zeros(3), 1.0, 20, 20, False, 'iteration limit', 3.0)
    give_up_early(near, outage, end, cfg, 0.0, 60.0, None, True)
    # at the start: only when the previous window reaches past the segment's end
    start = {0: ((40.0, 55.0),)}
    late = tel((56.0, 100.0)).window(40.0, 100.0)
    reach = {0: SimpleNamespace(t1=60.0)}
    with pytest.raises(EdgeNotSettled) as info:
        give_up_early(crawl, late, start, cfg, 40.0, 100.0, reach, True)  # type: ignore[arg-type]
    assert info.value.span == (55.0, 100.0)
    short = {0: SimpleNamespace(t1=50.0)}  # cut short of the same segment itself
    give_up_early(crawl, late, start, cfg, 40.0, 100.0, short, True)  # type: ignore[arg-type]
    give_up_early(crawl, late, start, cfg, 40.0, 100.0, None, True)

