"""Trajectory estimation on a window of raw measurements (seed 000).

(About 900 lines, over the ~600-line guide: the steps of one window solve, from the
knots to the verdict, read best in one place; its parts live in the modules it imports,
the retries of a failed window in :mod:`~orbit_tracking.core.estimation.retries`.)

The unknowns are the spline coefficients of every target's trajectory
(:mod:`~orbit_tracking.core.estimation.bspline`, knots from
:mod:`~orbit_tracking.core.estimation.knots`) and,
when on-board telemetry is fused, the coefficients of its slowly varying error. Every
measurement is whitened by its sigma, ``Y = F(beta) + E, E ~ N(0, I)``, and

    beta <- beta + omega (J^T J)^-1 J^T (Y - F(beta))            (seed 000, eq. 7)

with ``omega = 1`` halved while the cost rises (Gauss-Newton with step halving). The
Jacobian is sparse (a row touches ``degree + 1`` coefficients per axis); the normal
matrix is small and solved by Cholesky. The coefficient covariance ``(J^T J)^-1`` is
propagated to position and velocity at any time.

Measurement rows:

* stations: every field of the contract (range, range_rate, azimuth with wrap-around,
  elevation, los_alpha, los_beta) through :func:`~orbit_tracking.core.models.measurements.predict`;
* telemetry (beyond the paper): ``tel_p = p(t) + e(t) + w``, ``tel_v = v(t) + e'(t) + w'``
  with ``e`` a cubic spline per axis with knots every ``telemetry_error_spacing`` s (an
  offset and a drift that may bend slowly), a weak prior on ``e`` (the telemetry's
  reported sigma) and white-noise levels re-estimated from the residuals;
* fixes, optionally, as weak position measurements (their covariance divided by
  ``fix_weight``); they come from the same measurements, so they are off by default.

Outliers (:func:`~orbit_tracking.core.estimation.gauss_newton.solve`): values with an
absurd whitened residual are set aside first; a robust warm-up solve (``robust_loss``,
Huber by default) fits the window without letting a gross error drag it, and what lies
beyond 20 sigma of it is rejected as a gross error. The plain solve then runs on the
rest and its own residual gate rejects station values and fixes beyond ``gate_sigma``
(telemetry epochs beyond 20 sigma), re-solving until the gate settles. Rejections are
counted per station (or ``telemetry_<id>``, ``fixes_<id>``) and reason. On a window
without gross errors the warm-up takes the plain solve's own steps.
"""

from __future__ import annotations

import math
import time as _time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.bspline import SplineAxis
from orbit_tracking.core.estimation.config import EstimationError, EstimatorConfig, Segment
from orbit_tracking.core.estimation.coverage import (
    find_incomplete_segments,
    merge_segments,
)
from orbit_tracking.core.estimation.doubtful_events import doubtful_events
from orbit_tracking.core.estimation.event_times import window_event_terms
from orbit_tracking.core.estimation.gap_manoeuvres import unseen_spans, window_manoeuvres
from orbit_tracking.core.estimation.gate_events import (
    event_knots,
    gate_cluster_events,
    place_rough_events,
    refine_event_times,
    with_events,
    without_events,
)
from orbit_tracking.core.estimation.gauss_newton import GnOutcome, covariance, solve
from orbit_tracking.core.estimation.knot_refinement import (
    choose_knots_safely,
    polynomial_selection,
    prune_knots,
    rebuild,
    refine_knots,
)
from orbit_tracking.core.estimation.knots import (
    KnotSelection,
    RoughTrajectory,
    detect_changes,
    rough_trajectory,
    selection_span,
)
from orbit_tracking.core.estimation.observability import (
    bias_estimates,
    freeze_unobservable,
    isotropic_note,
    isotropic_spans,
)
from orbit_tracking.core.estimation.problem import Problem
from orbit_tracking.core.estimation.results import Estimate, TargetSolution, state_covariance
from orbit_tracking.core.estimation.retries import (
    COVERED_S,
    give_up_early,
    solve_with_retries,
)
from orbit_tracking.core.estimation.telemetry_block import TelemetryBlock
from orbit_tracking.core.estimation.telemetry_delays import delay_test, solve_with_aligned_events
from orbit_tracking.core.estimation.telemetry_evidence import (
    carried_evidence,
    evidence_covariances,
)
from orbit_tracking.core.estimation.telemetry_velocity import (
    refine_velocity_error,
    velocity_error_consider,
    velocity_error_test,
)
from orbit_tracking.core.estimation.verdict import judge
from orbit_tracking.core.models.measurements import residual

__all__ = ['REFINE_MAX_CHI2', 'estimate']

FloatArray = NDArray[np.float64]


REFINE_MAX_CHI2 = 3.0
"""The measurement-driven knot test runs only while chi2/dof of the fit is below this."""


# ---------------------------------------------------------------------------------------
# the window


def _rough_from_previous(prev: TargetSolution, t0: float, t1: float) -> RoughTrajectory | None:
    a, b = max(t0, prev.t0), min(t1, prev.t1)
    if b - a < 1.0:
        return None
    t = np.linspace(a, b, max(10, int((b - a) * 10) + 1))
    x = prev.trajectory.states(prev.coef, t)
    return RoughTrajectory('previous window', t, x[:, :3], x[:, 3:], 0.1, 0.01)


def _estimate_once(
    obs: Observations,
    t0: float,
    t1: float,
    cfg: EstimatorConfig | None = None,
    target_ids: Sequence[int] | None = None,
    previous: Mapping[int, TargetSolution] | None = None,
    frame: tuple[FloatArray, FloatArray] | None = None,
    quick: bool = False,
    more_after: bool = False,
) -> Estimate:
    """Estimate the trajectories of ``target_ids`` over [t0, t1] from ``obs``.

    With ``quick`` a first solve that does not settle, with an incomplete segment at a
    window edge that another window covers (``previous`` at the start, ``more_after``: a
    window follows this one), raises
    :class:`~orbit_tracking.core.estimation.retries.EdgeNotSettled` naming the span to
    solve instead (:func:`~orbit_tracking.core.estimation.retries.give_up_early`).

    Parameters
    ----------
    obs : Observations
        Measurements (rows outside [t0, t1] are ignored).
    t0, t1 : float
        Window span [s].
    cfg : EstimatorConfig
    target_ids : sequence of int, optional
        Default: every target with measurements.
    previous : mapping of target id to TargetSolution, optional
        The previous window's solution: the initial guess where it overlaps, and the
        rough trajectory when no telemetry or fixes exist.
    frame : (origin, rotation), optional
        Spline frame (e.g. the launch frame); default a launch-like frame at the first
        rough point.

    Raises
    ------
    EstimationError
        No measurements, or no rough trajectory to start from: for a target asked for in
        ``target_ids``, or for every target when they are not given (then a target without
        one is left out and named in the message, so that stray data of an unknown target
        cannot fail the others' window).
    """
    cfg = cfg or EstimatorConfig()
    if not t1 > t0:
        raise EstimationError(f'window must have t1 > t0; got [{t0}, {t1}]')
    everything, obs = obs, obs.window(t0, t1)
    wide = selection_span(t0, t1, cfg.knots)
    ids = list(target_ids) if target_ids is not None else obs.target_ids
    if not ids:
        raise EstimationError(f'no measurements in window [{t0:.3f}, {t1:.3f}]')
    k_start = _time.perf_counter()
    left_out: list[int] = []
    selections: dict[int, KnotSelection] = {}
    segments: dict[int, tuple[Segment, ...]] = {}
    for tid in ids:
        rough = rough_trajectory(obs, tid, t0, t1)
        if rough is None and previous and tid in previous:
            rough = _rough_from_previous(previous[tid], t0, t1)
        if rough is None:
            if target_ids is None:  # every target: one without a start is left out
                left_out.append(tid)
                continue
            raise EstimationError(
                f'target {tid}: no telemetry, fixes or previous solution in '
                f'[{t0:.3f}, {t1:.3f}] to start from'
            )
        segs = list(cfg.segments)
        if cfg.detect_segments:
            segs += find_incomplete_segments(obs, tid, rough.state, t0, t1, cfg.coverage)
        segs = merge_segments([(max(a, t0), min(b, t1)) for a, b in segs])
        segments[tid] = tuple(segs)
        if cfg.knot_method == 'polynomial':
            sel = polynomial_selection(rough, t0, t1, cfg.polynomial_degree)
        else:
            # knots chosen on the rough trajectory around the window: the same whether an
            # edge moves by a microsecond or not (knots.selection_span)
            around = rough_trajectory(everything, tid, *wide)
            context = (around, *wide) if around and around.source == rough.source else None
            sel = choose_knots_safely(
                rough,
                t0,
                t1,
                segs,
                cfg,
                cfg.knot_method,
                frame,
                cfg.baseline_spacing,
                context=context,
            )
        if previous and tid in previous:
            sel = _seed_from_previous(sel, previous[tid], rough)
        sel = replace(sel, rough_source=rough.source)
        selections[tid] = sel
    if not selections:
        raise EstimationError(
            f'no target in [{t0:.3f}, {t1:.3f}] has telemetry, fixes or a previous solution '
            f'to start from (targets {left_out})'
        )
    knot_time = _time.perf_counter() - k_start
    s_start = _time.perf_counter()
    events = {t: s.events for t, s in selections.items()}

    def problem_on_selections() -> Problem:
        assert cfg is not None  # (mypy: cfg is rebound below, to a finer velocity error)
        sols = {t: (s.trajectory, s.coef) for t, s in selections.items()}
        built = Problem(obs, sols, cfg, t0, t1, tel_events=events)
        if not (cfg.estimate_telemetry_error and previous):
            return built
        for tb in built.telemetry:
            prev = previous.get(tb.target)
            if prev is None:
                continue
            tb.size_prior = carried_evidence(prev.telemetry_size_evidence, tb.declared_sigma)
            if tb.size_prior is not None and prev.telemetry_error_sigma:
                tb.prior_sigma = prev.telemetry_error_sigma  # start where it ended
        return built

    prob = problem_on_selections()
    beta = np.zeros(prob.n)
    for tid, s in selections.items():
        o = prob.offsets[tid]
        beta[o : o + s.trajectory.n_coef] = s.coef
    beta[prob.bias_offset : prob.bias_offset + len(prob.biases)] = prob.bias_prior
    if 'estimated' in prob.bias_status:
        # observability before solving: the augmented normal matrix at the initial guess
        _, _, cov0, _, _ = covariance(prob, beta)
        freeze_unobservable(prob, beta, cov0, cfg, 'before the solve')
    start = beta.copy()
    iterations = halvings = 0

    def solve_on(
        p: Problem, b: FloatArray, warm_up: bool = True, early: bool = False
    ) -> tuple[GnOutcome, FloatArray, sp.csr_matrix, FloatArray, float, bool]:
        """Solve ``p`` from ``b`` (counting the iterations), with the covariance; with
        ``early`` (and ``quick``) give up as soon as the first plain solve has not settled
        at an unanchored edge segment, before the gate rounds."""
        nonlocal iterations, halvings
        assert cfg is not None  # (mypy: cfg is rebound below, to a finer velocity error)

        def check(o: GnOutcome) -> None:
            assert cfg is not None
            give_up_early(o, obs, segments, cfg, t0, t1, previous, more_after)

        o, i2, h2 = solve(p, b, cfg, warm_up=warm_up, check=check if early and quick else None)
        iterations += i2
        halvings += h2
        return (o, *covariance(p, o.beta))

    out, r, jac, cov, cond, singular = solve_on(prob, beta, early=True)
    if freeze_unobservable(prob, out.beta, cov, cfg, 'at the solution'):
        # solve again from the start: the frozen biases must not leave their pull in the
        # trajectory through a flat valley of the cost
        prob.gated.clear()
        out, r, jac, cov, cond, singular = solve_on(prob, start)
    if quick:
        give_up_early(out, obs, segments, cfg, t0, t1, previous, more_after)
    noisy = [t for t, s in selections.items() if s.rough_source == 'fixes']
    if noisy and cfg.knot_method == 'sparse':
        # fixes are a poor rough trajectory (no velocity, metres of noise): select the
        # knots again on the first solution, which the raw measurements made precise
        for tid in noisy:
            sol = prob.trajs[tid]
            coef = prob._coef(out.beta, tid)
            o = prob.offsets[tid]
            tt = np.linspace(t0, t1, max(50, int((t1 - t0) * 10) + 1))
            x = sol.states(coef, tt)
            pc = state_covariance(sol, cov[o : o + sol.n_coef, o : o + sol.n_coef], tt)
            sp_ = float(np.sqrt(np.median(np.trace(pc[:, :3, :3], axis1=1, axis2=2)) / 3))
            sv_ = float(np.sqrt(np.median(np.trace(pc[:, 3:, 3:], axis1=1, axis2=2)) / 3))
            if not (np.isfinite(sp_) and np.isfinite(sv_) and sp_ > 0.0 and sv_ > 0.0):
                continue  # a degenerate first solution: keep the knots from the fixes
            rough2 = RoughTrajectory(
                'first solution', tt, x[:, :3], x[:, 3:], sp_, sv_, covariance=pc
            )
            sel2 = choose_knots_safely(
                rough2,
                t0,
                t1,
                segments[tid],
                cfg,
                'sparse',
                (sol.origin, sol.rotation),
                events=selections[tid].events,
                kinks=selections[tid].kinks,
            )
            # the first solution's changes of acceleration make no knots (a smooth spline's
            # velocity is no white noise: the detector's statistics do not hold for it),
            # but where it sees one the knots may miss it: doubtful, for the consider term
            seen = detect_changes(rough2, cfg.knots) if cfg.knots.events else None
            from_first = () if seen is None else (*seen.times, *seen.doubtful)
            selections[tid] = replace(
                sel2,
                rough_source='fixes, then first solution',
                weak=selections[tid].weak,
                doubtful=tuple(
                    sorted({*selections[tid].doubtful, *(e for e in from_first if t0 < e < t1)})
                ),
            )
        first, first_beta = prob, out.beta
        prob = problem_on_selections()
        beta = np.zeros(prob.n)
        for tid, s in selections.items():
            o = prob.offsets[tid]
            beta[o : o + s.trajectory.n_coef] = s.coef
        nb = len(prob.biases)
        beta[prob.bias_offset : prob.bias_offset + nb] = first_beta[
            first.bias_offset : first.bias_offset + nb
        ]
        prob.bias_sigma, prob.bias_status = first.bias_sigma, first.bias_status
        out, r, jac, cov, cond, singular = solve_on(prob, beta)
    tel_note = ''
    if cfg.telemetry_delays == 'auto' and prob.telemetry:
        d_tests = delay_test(prob, out.beta, obs, cfg, t0, t1)
        add = {t.target: True for t in d_tests if t.delays}
        if add:
            prob, beta = rebuild(prob, out.beta, {}, {}, obs, cfg, t0, t1, tel_delays=add)
            out, r, jac, cov, cond, singular = solve_on(prob, beta, warm_up=False)
        tel_note = ''.join(
            f'; telemetry {t.target} time-tag delays '
            + ('estimated' if t.delays else 'not estimated')
            + f' (test {t.statistic:.3g} vs {t.threshold:.3g}, {t.dof} dof)'
            for t in d_tests
        )
    # (a no-op unless delays are estimated and the telemetry showed events)
    prob, out, it2, h2, shift_note = solve_with_aligned_events(prob, out, events, obs, cfg, t0, t1)
    iterations += it2
    halvings += h2
    if shift_note:
        r, jac, cov, cond, singular = covariance(prob, out.beta)
        tel_note += shift_note
        for tid in selections:  # the knots the solution is on
            selections[tid] = replace(selections[tid], trajectory=prob.trajs[tid])
    if cfg.telemetry_velocity_error == 'auto' and prob.telemetry:
        tests = velocity_error_test(prob, out.beta, obs, cfg, t0, t1)
        switch = {t.target: True for t in tests if t.separate}
        if switch:
            prob, beta = rebuild(prob, out.beta, {}, {}, obs, cfg, t0, t1, switch)
            out, r, jac, cov, cond, singular = solve_on(prob, beta, warm_up=False)
        tel_note += ''.join(
            f'; telemetry {t.target} velocity error '
            + ('of its own' if t.separate else '= d/dt position error')
            + f' (test {t.statistic:.3g} vs {t.threshold:.3g}, {t.dof} dof)'
            for t in tests
        )
    elif cfg.telemetry_velocity_error == 'separate' and prob.telemetry:
        tel_note += '; telemetry velocity error of its own (configured)'
    while True:  # a faster separate velocity error while the residuals ask for it
        v_tests, finer = refine_velocity_error(prob, out.beta, obs, cfg, t0, t1)
        tel_note += ''.join(
            f'; telemetry {t.target} velocity error knots every '
            f'{cfg.telemetry_velocity_error_spacing / 2:g} s '
            + ('asked for' if t.significant else 'not asked for')
            + f' (test {t.statistic:.3g} vs {t.threshold:.3g}, {t.dof} dof)'
            for t in v_tests
        )
        if finer is None:
            break
        cfg, prob, beta = finer  # the problem the test was made on
        out, r, jac, cov, cond, singular = solve_on(prob, beta, warm_up=False)

    def on_new_knots(
        axes: Mapping[int, list[SplineAxis]], tel: Mapping[int, SplineAxis] | None = None
    ) -> tuple[Problem, FloatArray, dict[int, int]]:
        """The problem rebuilt on new knots from the current solution (the selections
        follow it), its start, and the change of each target's interior knot count."""
        assert cfg is not None
        p, b = rebuild(prob, out.beta, axes, tel or {}, obs, cfg, t0, t1)
        change = {}
        for tid in axes:
            change[tid] = p.trajs[tid].n_interior - selections[tid].trajectory.n_interior
            selections[tid] = replace(selections[tid], trajectory=p.trajs[tid])
        return p, b, change

    def on_events(
        before: Mapping[int, Sequence[SplineAxis]], taus: Mapping[int, list[float]]
    ) -> None:
        """The problem rebuilt on the axes ``before`` with the events ``taus`` and solved,
        the gate decided afresh (the values a missed event spoiled)."""
        nonlocal prob, out, r, jac, cov, cond, singular
        assert cfg is not None
        prob, b, _ = on_new_knots(
            {tid: with_events(before[tid], t, cfg.knots.min_spacing) for tid, t in taus.items()}
        )
        prob.gated.clear()
        out, r, jac, cov, cond, singular = solve_on(prob, b)

    def placed(
        before: Mapping[int, Sequence[SplineAxis]], found: Mapping[int, list[float]]
    ) -> dict[int, list[float]]:
        """:func:`on_events` with the events ``found``, then with each moved to where the
        measurements fit it best (:func:`refine_event_times`); their times."""
        nonlocal iterations
        assert cfg is not None
        on_events(before, found)
        moved, it = refine_event_times(prob, out.beta, before, found, segments, obs, cfg, t0, t1)
        iterations += it
        if moved:
            on_events(before, moved)
        return {**found, **moved}

    if cfg.move_events:
        # the rough trajectory's events are timed by its own samples: the measurements
        # place them (as the gate's events below)
        tel_ev = {
            tid: taus
            for tid, s in selections.items()
            if (taus := event_knots(prob.trajs[tid], s.events, s.kinks))
        }
        bare = {tid: without_events(prob.trajs[tid].axes, taus) for tid, taus in tel_ev.items()}
        moved, it_moved = place_rough_events(
            prob, out.beta, bare, tel_ev, segments, obs, cfg, t0, t1
        )
        iterations += it_moved
        if moved:
            on_events(bare, moved)
            pairs = [p for tid in moved for p in zip(tel_ev[tid], moved[tid], strict=True)]
            shifts = [b - a for a, b in pairs if b != a]
            for tid, taus in moved.items():
                kept = [e for e in selections[tid].events if e not in tel_ev[tid]]
                selections[tid] = replace(selections[tid], events=tuple(sorted([*kept, *taus])))
            tel_note += (
                f'; {len(shifts)} events of the rough trajectory moved to where the '
                f'measurements fit them best, by up to {1e3 * max(map(abs, shifts)):.0f} ms'
            )

    pruned = {tid: 0 for tid in selections}
    if cfg.prune_z > 0.0 and cfg.knot_method == 'sparse':
        # knots the measurements do not support go before the knot test adds any
        reduced = prune_knots(prob, out.beta, cov, cfg.prune_z)
        if reduced:
            prob, beta, change = on_new_knots(reduced)
            for tid, n in change.items():
                pruned[tid] = -n
            out, r, jac, cov, cond, singular = solve_on(prob, beta, warm_up=False)
    added = {tid: 0 for tid in selections}
    refine_note = ''
    for _ in range(cfg.refine_rounds):
        fit = float(r @ r) / max(r.size - prob.n, 1)
        if fit > REFINE_MAX_CHI2:
            # the score test assumes the model fits up to its knots; data this far off
            # (unmodelled systematic errors) would ask for knots everywhere
            refine_note = (
                f'; knot test skipped: chi2/dof {fit:.1f} > {REFINE_MAX_CHI2:g}, the model '
                'does not fit the data'
            )
            break
        new_axes, new_tel = refine_knots(prob, r, jac, cov, cfg, segments)
        if not new_axes and not new_tel:
            break
        prob, beta, change = on_new_knots(new_axes, new_tel)
        for tid, n in change.items():
            added[tid] += n
        # the refined problem carries the gates over (rebuild): no warm-up to decide them
        out, r, jac, cov, cond, singular = solve_on(prob, beta, warm_up=False)
    gate_events: dict[int, list[float]] = {}
    shifts = []  # of the gate events the measurements moved [s]
    for _ in range(cfg.gate_event_rounds):
        found = gate_cluster_events(prob, segments, t0, t1)
        if not found:
            break
        # the rejections' median is where the misfit showed: the data place the jump
        final = placed({tid: prob.trajs[tid].axes for tid in found}, found)
        for tid, taus in final.items():
            shifts.extend(b - a for a, b in zip(found[tid], taus, strict=True) if b != a)
            gate_events.setdefault(tid, []).extend(taus)
            knotted = tuple(sorted(selections[tid].events + tuple(taus)))
            selections[tid] = replace(selections[tid], events=knotted)
    if cfg.doubtful_events:
        # the first solution's changes (no telemetry): its detector blurs close jumps
        doubts = {
            tid: s.doubtful
            for tid, s in selections.items()
            if s.rough_source == 'fixes, then first solution'
        }
        fit = float(r @ r) / max(r.size - prob.n, 1)  # as the knot test: the gains assume
        doubts = doubts if fit <= REFINE_MAX_CHI2 else {}  # that the model fits
        asked, it_asked = doubtful_events(prob, out.beta, doubts, segments, obs, cfg, t0, t1, fit)
        iterations += it_asked
        if asked:
            asked = placed({tid: prob.trajs[tid].axes for tid in asked}, asked)
        for tid, taus in asked.items():
            knotted = tuple(sorted(selections[tid].events + tuple(taus)))
            selections[tid] = replace(selections[tid], events=knotted)
            refine_note += (
                f'; target {tid} events the measurements asked for at doubtful changes: '
                + ', '.join(f'{t:.3f} s' for t in taus)
            )
    for tid, taus in gate_events.items():
        refine_note += (
            f'; target {tid} events where the gate rejections clustered: '
            + ', '.join(f'{t:.3f} s' for t in taus)
        )
    if shifts:
        refine_note += (
            f' ({len(shifts)} moved to where the measurements fit them best, by up to '
            f'{1e3 * max(abs(d) for d in shifts):.0f} ms)'
        )
    for tid, n_added in added.items():
        selections[tid] = replace(selections[tid], refined=n_added, pruned=pruned[tid])
    solve_time = _time.perf_counter() - s_start
    used: Counter[str] = Counter()
    rejected: Counter[tuple[str, str]] = Counter()
    residuals: dict[str, tuple[FloatArray, tuple[str, ...], FloatArray]] = {}
    for bi, b in enumerate(prob.stations):
        g = prob.gated.get(bi, np.zeros_like(b.valid))
        used[b.station] += int((b.valid & ~g).sum())
        if g.any():
            rejected[(b.station, 'residual_gate')] += int(g.sum())
        nan = int((~b.valid).sum())
        if nan:
            rejected[(b.station, 'not_measured')] += nan
        pred, _, _ = prob.predict_block(bi, out.beta)
        with np.errstate(over='ignore', invalid='ignore'):  # a gated absurd value
            rr = residual(b.fields, b.values, pred) / b.declared
        rr[g] = np.nan
        residuals[b.station if b.target == ids[0] else f'{b.station}/{b.target}'] = (
            b.time,
            b.fields,
            rr,
        )
    for tb in prob.telemetry:
        use_p, use_v = prob.telemetry_use(tb)
        used[f'telemetry_{tb.target}'] += int(use_p.sum() + use_v.sum())
        n_gated = int((tb.valid_p & ~use_p).sum() + (tb.valid_v & ~use_v).sum())
        if n_gated:
            rejected[(f'telemetry_{tb.target}', 'residual_gate')] += n_gated
    for fb in prob.fixes:
        g = prob.gated.get(('fix', fb.target), np.zeros_like(fb.valid))
        if g.any():
            rejected[(f'fixes_{fb.target}', 'residual_gate')] += int((fb.valid & g).sum())
    dof = max(r.size - prob.n, 1)
    chi2_dof = out.cost / dof
    finite = bool(np.all(np.isfinite(out.beta)) and np.all(np.isfinite(cov)))
    verdict = judge(
        out.converged,
        chi2_dof,
        dof,
        cfg.max_chi2_dof,
        singular,
        prob.gate_refused,
        finite,
        out.decrement,
        cfg.max_unconverged_decrement,
    )
    event_terms, event_note = window_event_terms(prob, out.beta, selections, obs, cfg, t0, t1)
    tel_note += event_note
    manoeuvres = {
        tid: window_manoeuvres(
            prob,
            jac,
            cov,
            tid,
            segments[tid],
            selections[tid].events + selections[tid].doubtful,
            cfg,
            verdict.covariance_scale,
            unseen_spans(obs, tid, t0, t1, cfg),
            selections[tid].weak,
        )
        for tid in selections
    }
    # after the consider term, which needs the data's own (J^T J)^-1
    size_evidence: dict[int, tuple[float, FloatArray]] = {}
    raw = cov  # the data's own (J^T J)^-1, for the velocity error's term below
    if cfg.estimate_telemetry_error:
        cov, ratios, tables = evidence_covariances(prob.telemetry, out.beta, cov)
        for tb, ratio, table in zip(prob.telemetry, ratios, tables, strict=True):
            if table is not None:
                size_evidence[tb.target] = (tb.declared_sigma, table)
            if ratio > 1.01:
                tel_note += (
                    f'; telemetry {tb.target} error sizes uncertain: their evidence-weighted '
                    f'spread widens variances by up to x{ratio:.3g}'
                )
    if cfg.telemetry_velocity_error == 'auto' and prob.telemetry:
        extra, v_notes = velocity_error_consider(prob, out.beta, raw, obs, cfg, t0, t1)
        cov = cov + extra  # beside the evidence's term
        for tid, (p_w, ratio, q) in v_notes.items():
            if q > 0.0:
                tel_note += (
                    f'; telemetry {tid} velocity rounded to steps of {q:.3g} m/s: the '
                    f'covariance carries the rounding as a slow velocity error: variances up '
                    f'to x{ratio:.3g}'
                )
            elif ratio > 1.01:
                tel_note += (
                    f'; telemetry {tid} covariance carries a separate velocity error the '
                    f'test could not exclude (posterior {p_w:.2g}): variances up to '
                    f'x{ratio:.3g}'
                )
    cov = cov * verdict.covariance_scale
    targets = {}
    for tid, s in selections.items():
        o = prob.offsets[tid]
        nt = s.trajectory.n_coef
        tel = next((tb for tb in prob.telemetry if tb.target == tid), None)
        targets[tid] = TargetSolution(
            tid,
            s.trajectory,
            out.beta[o : o + nt].copy(),
            cov[o : o + nt, o : o + nt].copy(),
            s,
            segments[tid],
            None
            if tel is None
            else (tel.axis, out.beta[tel.offset : tel.offset + 3 * tel.axis.n_coef].copy()),
            None if tel is None else (tel.noise[0], tel.noise[1]),
            isotropic_spans(
                prob, tid, s.trajectory, out.beta[o : o + nt], cov[o : o + nt, o : o + nt], cfg
            ),
            '' if tel is None else ('separate' if tel.w_axis is not None else 'derivative'),
            None if tel is None else tel.prior_sigma,
            prob.jerk_q.get((tid, False)),
            _delays(tel, out.beta, cov),
            manoeuvres[tid],
            size_evidence.get(tid),
            prob.jerk_q.get((tid, True)),
            event_terms.get(tid),
        )
    factors = {
        (b.station, f): float(b.factor[j])
        for b in prob.stations
        for j, f in enumerate(b.fields)
        if b.factor[j] != 1.0
    }
    msg = (
        out.message
        + tel_note
        + refine_note
        + (
            f'; target(s) {left_out} left out: no telemetry, fixes or previous solution'
            if left_out
            else ''
        )
        + ('; normal matrix singular (pseudo-inverse covariance)' if singular else '')
    )
    if prob.gate_refused:
        msg += (
            f'; the residual gate would reject {prob.gate_refused:.0%} of the rows, so the '
            'model does not fit the data (unmodelled systematic errors?): nothing gated'
        )
    near = 1.0
    if not out.converged and verdict.success:
        near = 1.0 + out.decrement
        msg += (
            f'; taken within {math.sqrt(out.decrement):.2g} sigma of its optimum, its '
            f'covariance scaled by {near:.3g}'
        )
    if verdict.covariance_scale != near:
        msg += f'; covariance scaled by the misfit ({verdict.covariance_scale / near:.3g})'
    msg += isotropic_note(targets, t0, t1, cfg.nonlinear_sigma)
    msg += ''.join(
        f'; target {tid} covariance carries the manoeuvres {g.note}'
        for tid, g in sorted(manoeuvres.items())
        if g is not None
    )
    msg += ''.join(
        f'; target {tid} events: {len(k.events) - len(k.kinks)} acceleration jumps, '
        f'{len(k.kinks)} ramp ends or bends'
        + (f', {len(k.doubtful)} doubtful (no knots)' if k.doubtful else '')
        + (f', {len(k.weak)} weak (no knots)' if k.weak else '')
        for tid, k in sorted((tid, ts.knots) for tid, ts in targets.items())
        if k.events or k.doubtful or k.weak
    )
    msg += ''.join(
        f'; target {tid} white-jerk prior {q:.3g} m^2/s^5' + (' near events' if near else '')
        for (tid, near), q in sorted(prob.jerk_q.items())
        if q is not None
    )
    if cfg.estimate_telemetry_error:
        msg += ''.join(
            f'; telemetry {tb.target} error spline sigma {tb.prior_sigma[0]:.3g} m, '
            f'steps {tb.prior_sigma[1]:.3g} m (declared {tb.declared_sigma:.3g} m)'
            for tb in prob.telemetry
        )
    if factors:
        msg += '; sigmas used larger than declared: ' + ', '.join(
            f'{st} {f} x{k:.2f}' for (st, f), k in sorted(factors.items())
        )
    if not verdict.success:
        msg = 'FAILED (' + '; '.join(verdict.reasons) + '): ' + msg
    return Estimate(
        success=verdict.success,
        message=msg,
        t0=t0,
        t1=t1,
        targets=targets,
        iterations=iterations,
        halvings=halvings,
        cost=out.cost,
        chi2_dof=chi2_dof,
        condition=cond,
        n_parameters=prob.n,
        used=used,
        rejected=rejected,
        residuals=residuals,
        knot_time=knot_time,
        solve_time=solve_time,
        covariance=cov,
        biases=bias_estimates(prob, out.beta, cov),
        covariance_scale=verdict.covariance_scale,
        noise_factors=factors,
    )


def estimate(
    obs: Observations,
    t0: float,
    t1: float,
    cfg: EstimatorConfig | None = None,
    target_ids: Sequence[int] | None = None,
    previous: Mapping[int, TargetSolution] | None = None,
    frame: tuple[FloatArray, FloatArray] | None = None,
    more_after: bool | None = None,
) -> Estimate:
    """Estimate the trajectories of ``target_ids`` over [t0, t1] from ``obs``.

    A window that is not a success (:mod:`~orbit_tracking.core.estimation.verdict`) is
    solved again (:mod:`~orbit_tracking.core.estimation.retries`: cut short of an
    incomplete segment at its edge, then with safer settings), in turn, until one is a
    success; when none is, the attempt with the smallest chi-square per degree of freedom
    is returned as failed, its message naming every attempt. A cut window's estimate spans
    the cut span (its ``t0``, ``t1``).

    Parameters
    ----------
    obs : Observations
        Measurements (rows outside [t0, t1] are ignored).
    t0, t1 : float
        Window span [s].
    cfg : EstimatorConfig
    target_ids : sequence of int, optional
        Default: every target with measurements.
    previous : mapping of target id to TargetSolution, optional
        The previous window's solution: the initial guess where it overlaps, and the
        rough trajectory when no telemetry or fixes exist.
    frame : (origin, rotation), optional
        Spline frame (e.g. the launch frame); default a launch-like frame at the first
        rough point.
    more_after : bool, optional
        Whether another window follows this one (it covers an incomplete segment at this
        window's end: :mod:`~orbit_tracking.core.estimation.retries`). Default: whether
        ``obs`` holds data more than
        :data:`~orbit_tracking.core.estimation.retries.COVERED_S` after ``t1``.

    Raises
    ------
    EstimationError
        No measurements, or no rough trajectory to start from: for a target asked for in
        ``target_ids``, or for every target when they are not given (then a target without
        one is left out and named in the message, so that stray data of an unknown target
        cannot fail the others' window).
    """
    cfg = cfg or EstimatorConfig()
    if more_after is None:
        more_after = bool(obs.measured_span()[1] > t1 + COVERED_S)
    fitted = obs if cfg.use_telemetry else obs.without_telemetry()
    t0, t1, edge_note = _measured_edges(fitted, t0, t1, cfg.edge_gap)
    telemetry = any(np.any((v.time >= t0) & (v.time <= t1)) for v in obs.telemetry.values())

    def attempt(
        a: float,
        b: float,
        c: EstimatorConfig,
        prev: Mapping[int, TargetSolution] | None,
        quick: bool,
    ) -> Estimate:
        return _attempt(obs, a, b, c, target_ids, prev, frame, quick, more_after)

    first = solve_with_retries(attempt, t0, t1, cfg, previous, telemetry)
    if edge_note:
        first = replace(first, message=f'{first.message}; {edge_note}')
    return first


def _measured_edges(
    obs: Observations, t0: float, t1: float, edge_gap: float
) -> tuple[float, float, str]:
    """[t0, t1] narrowed to the station rows and telemetry in it where they stop more than
    ``edge_gap`` s short of an edge (``EstimatorConfig.edge_gap``), and a note saying so."""
    a, b = obs.measured_span(t0, t1)
    if not (math.isfinite(a) and math.isfinite(b)):
        return t0, t1, ''  # no data: the attempt says so
    lo = a if a - t0 > edge_gap else t0
    hi = b if t1 - b > edge_gap else t1
    if (lo, hi) == (t0, t1):
        return t0, t1, ''
    if not hi > lo:
        raise EstimationError(
            f'window [{t0:.3f}, {t1:.3f}]: its station rows and telemetry span only '
            f'{a:.3f}-{b:.3f} s'
        )
    empty = [f'{x:.2f}-{y:.2f} s' for x, y in ((t0, lo), (hi, t1)) if y > x]
    note = (
        f'no station rows or telemetry in {" and ".join(empty)} of the window: solved over '
        f'[{lo:.2f}, {hi:.2f}] s'
    )
    return lo, hi, note


def _attempt(
    obs: Observations,
    t0: float,
    t1: float,
    cfg: EstimatorConfig,
    target_ids: Sequence[int] | None,
    previous: Mapping[int, TargetSolution] | None,
    frame: tuple[FloatArray, FloatArray] | None,
    quick: bool = False,
    more_after: bool = False,
) -> Estimate:
    """One solve; a numerical breakdown (LAPACK not converging on a matrix that overflowed)
    is an :class:`EstimationError` of that window, never an exception that stops a pass."""
    try:
        return _estimate_once(obs, t0, t1, cfg, target_ids, previous, frame, quick, more_after)
    except (np.linalg.LinAlgError, FloatingPointError) as exc:
        raise EstimationError(f'numerical failure: {type(exc).__name__}: {exc}') from exc


def _seed_from_previous(
    sel: KnotSelection, prev: TargetSolution, rough: RoughTrajectory
) -> KnotSelection:
    """Initial coefficients: the previous window's trajectory where it overlaps, the rough
    trajectory's fit on the new knots beyond.

    Both are sampled eight times per knot interval of the new spline (whatever its knot
    density), so that every coefficient is fitted to samples: a coarse sampling of a
    spline with dense knots leaves coefficients without data, which a least-squares fit
    sets to the frame origin (an initial guess 1e5 m off)."""
    del rough  # its fit on the new knots is ``sel.coef``
    traj = sel.trajectory
    a, b = max(traj.t0, prev.t0), min(traj.t1, prev.t1)
    if b - a < 1.0:
        return sel
    brk = np.unique(np.concatenate([ax.knots for ax in traj.axes]))
    brk = brk[(brk >= traj.t0) & (brk <= traj.t1)]
    t = np.unique(
        np.concatenate([np.linspace(lo, hi, 8) for lo, hi in zip(brk[:-1], brk[1:], strict=True)])
    )
    inside = (t >= a) & (t <= b)
    x = traj.states(sel.coef, t)
    x[inside] = prev.trajectory.states(prev.coef, t[inside])
    try:
        coef = traj.fit_states(t, x[:, :3], x[:, 3:], 1.0, 100.0)
    except np.linalg.LinAlgError:
        return sel
    if not np.all(np.isfinite(coef)):
        return sel
    return replace(sel, coef=coef)


def _delays(
    tel: TelemetryBlock | None, beta: FloatArray, cov: FloatArray
) -> tuple[float, float, float, float] | None:
    """The telemetry's estimated time-tag delays and their sigmas (None without)."""
    if tel is None or not tel.delays:
        return None
    o = tel.delay_offset
    sig = np.sqrt(np.maximum(np.diag(cov)[o : o + 2], 0.0))
    return float(beta[o]), float(sig[0]), float(beta[o + 1]), float(sig[1])
