"""Knots of a window beyond the first selection: the safe initial choice (fallbacks when
the l1 selection fails), and the measurement-driven refinement (a score test per knot
interval on the solved problem, new knots where the residuals say the spline is too stiff,
the problem rebuilt on the new knots)."""

from __future__ import annotations

import time as _time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.chi2 import chi2_isf
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimatorConfig, Segment
from orbit_tracking.core.estimation.knots import (
    KnotSelection,
    KnotSelectionError,
    RoughTrajectory,
    choose_knots,
)
from orbit_tracking.core.estimation.problem import Problem
from orbit_tracking.core.estimation.telemetry_velocity import quadratic_score

__all__ = [
    'ScoreRows',
    'choose_knots_safely',
    'event_scores',
    'insertion_score',
    'significance',
    'polynomial_selection',
    'prune_knots',
    'rebuild',
    'refine_knots',
]

FloatArray = NDArray[np.float64]


class ScoreRows(NamedTuple):
    """What a score test of new knots reads of a solved window: ``ts`` the sorted times of
    the rows ``ridx`` (into ``r`` and ``jac``) a spline acts on, ``up``/``uv`` the whitened
    derivatives of those rows by its value and rate (one column per axis, or a vector for
    one axis), ``r`` the whitened residuals, ``jac`` the whitened Jacobian and ``cov`` the
    parameters' covariance at the solution."""

    ts: FloatArray
    up: FloatArray
    uv: FloatArray
    ridx: NDArray[np.intp]
    r: FloatArray
    jac: sp.csr_matrix
    cov: FloatArray


def _knot_scores(ax: SplineAxis, rows_: ScoreRows, min_len: float) -> list[tuple[float, float]]:
    """Score statistic of a knot at the midpoint of every interval of ``ax`` (``rows_``
    with ``up``/``uv`` of this axis)."""
    from scipy.interpolate import BSpline

    ts, up, uv, ridx, r, jac, cov = rows_
    out = []
    brk = np.unique(ax.knots)
    p = ax.degree
    for lo, hi in zip(brk[:-1], brk[1:], strict=True):
        if hi - lo < min_len:
            continue
        # the midpoint on the time axis's grid of min_len / 2: an interval that ends at a
        # window edge gets the same candidate whether the edge moved by 1e-6 s or not
        q = 0.5 * min_len
        tau = round(0.5 * (lo + hi) / q) * q
        if not lo + 0.5 * q <= tau <= hi - 0.5 * q:
            continue
        idx = int(np.searchsorted(ax.knots, tau))
        refined = np.insert(ax.knots, idx, tau)
        s0 = min(max(idx - 2, 0), refined.size - p - 2)
        local = refined[s0 : s0 + p + 2]
        i0, i1 = np.searchsorted(ts, [local[0], local[-1]])
        if i1 - i0 < 2:
            continue
        b = BSpline.basis_element(local, extrapolate=False)
        tt = ts[i0:i1]
        col = np.nan_to_num(b(tt)) * up[i0:i1] + np.nan_to_num(b.derivative()(tt)) * uv[i0:i1]
        rows = ridx[i0:i1]
        g = float(col @ r[rows])
        c = jac[rows].T @ col
        den = float(col @ col - c @ (cov @ c))
        if den <= 1e-12 * float(col @ col):
            continue
        out.append((tau, g * g / den))
    return out


def insertion_score(
    axes: Sequence[SplineAxis], inserts: Sequence[FloatArray], rows_: ScoreRows
) -> tuple[float, int] | None:
    """Score statistic ``(s, dof)`` of inserting the knots ``inserts[a]`` into ``axes[a]``
    (all at once), or None with too few rows; ``rows_.up``/``uv`` (n, 3) by each axis (in
    the spline frame).

    The columns are the refined splines' basis functions around the new knots;
    projected on what the current spline already represents (``J (J^T J)^-1 J^T``), they
    leave ``dof`` new directions (one per inserted knot), and ``s = g^T G^+ g`` (``g`` their
    products with the residuals, ``G`` their projected Gram matrix on those directions) is
    chi-square(``dof``) when the current knots represent the trajectory.
    """
    ts, up, uv, ridx, r, jac, cov = rows_
    parts: list[tuple[int, FloatArray, int, int, int, int]] = []
    lo_t, hi_t = np.inf, -np.inf
    for ax, new in zip(axes, inserts, strict=True):
        if len(new) == 0:
            continue
        p = ax.degree
        refined = np.sort(np.concatenate([ax.knots, np.asarray(new, dtype=float)]))
        first = int(np.searchsorted(refined, float(np.min(new))))
        last = int(np.searchsorted(refined, float(np.max(new)), side='right'))
        j0, j1 = max(first - p - 1, 0), min(last + 1, refined.size - p - 1)
        parts.append((len(parts), refined, j0, j1, p, len(new)))
        lo_t = min(lo_t, float(refined[j0]))
        hi_t = max(hi_t, float(refined[min(j1 + p, refined.size - 1)]))
    dof = sum(part[5] for part in parts)
    i0, i1 = np.searchsorted(ts, [lo_t, hi_t])
    if dof == 0 or i1 - i0 < 2 * dof:
        return None
    tt = ts[i0:i1]
    cols = []
    axis_of = [a for a, new in enumerate(inserts) if len(new)]
    for k, refined, j0, j1, p, _ in parts:
        a = axis_of[k]
        sa = SplineAxis(refined, p)
        val = sa.design(tt)[:, j0:j1].toarray()
        rate = sa.design(tt, 1)[:, j0:j1].toarray()
        cols.append(val * up[i0:i1, a, None] + rate * uv[i0:i1, a, None])
    c_mat = np.hstack(cols)
    rows = ridx[i0:i1]
    g = c_mat.T @ r[rows]
    jc = np.asarray(jac[rows].T @ c_mat)
    gram = c_mat.T @ c_mat - jc.T @ (cov @ jc)
    return quadratic_score(g, gram, dof)


def event_scores(
    axes: Sequence[SplineAxis], rows_: ScoreRows, taus: FloatArray
) -> list[tuple[float, float, int]]:
    """:func:`insertion_score` of an *event* at each of ``taus``: a knot of multiplicity
    ``degree - 1`` at ``tau`` on all three axes at once (the acceleration may jump there:
    an engine cut-off or ignition, the start or end of a turn); ``dof = 3 (degree - 1)``.
    Returns ``(tau, s, dof)`` for each tau with enough rows."""
    out = []
    for tau in taus:
        inserts = [np.full(ax.degree - 1, float(tau)) for ax in axes]
        sc = insertion_score(axes, inserts, rows_)
        if sc is not None:
            out.append((float(tau), sc[0], sc[1]))
    return out


def significance(s: float, dof: int) -> float:
    """How far a chi-square(``dof``) statistic ``s`` is in its upper tail, as a normal
    deviate (Wilson-Hilferty): increasing with ``s``, comparable across ``dof``, and finite
    where the tail probability itself underflows (misfits of thousands of sigma)."""
    c = 2.0 / (9.0 * dof)
    return float(((max(s, 0.0) / dof) ** (1.0 / 3.0) - (1.0 - c)) / np.sqrt(c))


def _with_knots(ax: SplineAxis, new: Sequence[float]) -> SplineAxis:
    return SplineAxis.from_interior(
        np.sort(np.concatenate([ax.interior, np.asarray(new, dtype=float)])),
        ax.t0,
        ax.t1,
        ax.degree,
    )


def _interval(ax: SplineAxis, tau: float) -> tuple[float, float]:
    brk = np.unique(ax.knots)
    i = int(np.clip(np.searchsorted(brk, tau) - 1, 0, brk.size - 2))
    return float(brk[i]), float(brk[i + 1])


def _events(
    prob: Problem,
    traj_c: Sequence[tuple[int, int, float, float]],
    limit: float,
    rows: tuple[FloatArray, FloatArray, FloatArray, FloatArray],
    r: FloatArray,
    jac: sp.csr_matrix,
    cov: FloatArray,
    cfg: EstimatorConfig,
    avoid: Mapping[int, Sequence[tuple[float, float]]],
) -> dict[int, list[tuple[float, float, float]]]:
    """Events the failing knot intervals ask for: per target, ``(tau, lo, hi)`` with
    [lo, hi] the run of failing intervals it replaces (see :func:`refine_knots`)."""
    tgt, tim, hp, hv = rows
    q = cfg.knots.min_spacing  # the instants tried lie on this grid (edge-stable)
    tests: list[
        tuple[int, float, float, list[tuple[float, float, int]], tuple[float, int] | None]
    ] = []
    n_tried = 0
    for tid, traj in prob.trajs.items():
        flagged = sorted(
            {_interval(traj.axes[a], tau) for k, a, tau, sc in traj_c if k == tid and sc > limit}
        )
        if not flagged:
            continue
        regions: list[list[float]] = []  # [lo, hi, intervals]
        for lo, hi in flagged:
            if regions and lo <= regions[-1][1] + 1e-9:
                regions[-1][1] = max(regions[-1][1], hi)
                regions[-1][2] += 1
            else:
                regions.append([lo, hi, 1])
        # An event misfits the few intervals its jump reaches; a longer run of failing
        # intervals is a spline too stiff all along (or a first fit far off), not an event.
        # A run at an event already there (a repeated knot, from the rough trajectory or an
        # earlier round) is left to the midpoint knots: a second event next to it would
        # only be a worse-conditioned stand-in for moving it (seen: the search put one
        # between two detected staging events 1 s apart, and the fit got worse).
        p = traj.axes[0].degree
        multiple = traj.repeated_knots()
        regions = [
            reg
            for reg in regions
            if reg[2] <= p + 1
            and not np.any((multiple >= reg[0] - 1e-9) & (multiple <= reg[1] + 1e-9))
        ]
        sel = np.flatnonzero(tgt == tid)
        order = sel[np.argsort(tim[sel], kind='stable')]
        ts = tim[order]
        up, uv = hp[order] @ traj.rotation, hv[order] @ traj.rotation
        data = ScoreRows(ts, up, uv, order, r, jac, cov)
        knots = np.unique(np.concatenate([ax.knots for ax in traj.axes]))
        segs = list(avoid.get(tid, ()))

        def allowed(g: FloatArray, knots: FloatArray = knots, segs: list = segs) -> FloatArray:
            near = np.min(np.abs(g[:, None] - knots[None, :]), axis=1)
            # inside the spline (the fine grid can reach past a window edge), off its knots
            ok = (near >= q) & (g > knots[0]) & (g < knots[-1])
            for a0, a1 in segs:
                ok &= (g < a0) | (g > a1)
            return g[ok]

        for lo, hi, _ in regions:
            step = max(q, q * np.ceil((hi - lo) / 16.0 / q))
            coarse = allowed(step * np.arange(np.ceil(lo / step), np.floor(hi / step) + 1))
            sc = event_scores(traj.axes, data, coarse)
            if not sc:
                continue
            best = max(sc, key=lambda x: significance(x[1], x[2]))[0]
            k0, k1 = np.ceil((best - step) / q), np.floor((best + step) / q)
            fine = allowed(q * np.arange(k0, k1 + 1))
            sc += event_scores(traj.axes, data, fine)
            n_tried += len(sc)
            # the alternative: the midpoint knots this run would get, tested together
            mine = [(a, t) for k, a, t, v in traj_c if k == tid and v > limit and lo <= t <= hi]
            mids = [np.array([t for a_, t in mine if a_ == a]) for a in range(3)]
            alt = insertion_score(traj.axes, mids, data)
            tests.append((tid, lo, hi, sc, alt))
    found: dict[int, list[tuple[float, float, float]]] = {}
    for tid, lo, hi, sc, alt in tests:
        tau, s, dof = max(sc, key=lambda x: significance(x[1], x[2]))
        # significant, and a better explanation than the midpoint knots (a smaller p-value:
        # more misfit explained per degree of freedom)
        better = alt is None or significance(s, dof) > significance(*alt)
        if s > chi2_isf(cfg.refine_alpha / n_tried, dof) and better:
            found.setdefault(tid, []).append((tau, lo, hi))
    return found


def refine_knots(
    prob: Problem,
    r: FloatArray,
    jac: sp.csr_matrix,
    cov: FloatArray,
    cfg: EstimatorConfig,
    avoid: Mapping[int, Sequence[tuple[float, float]]] | None = None,
) -> tuple[dict[int, list[SplineAxis]], dict[int, SplineAxis]]:
    """Knots the measurements ask for (beyond the paper).

    For every knot interval of every axis, a score (Lagrange-multiplier) test of adding
    a knot at its midpoint: with ``j`` the Jacobian column of the new basis function,
    ``s = (j^T r)^2 / (j^T j - (J^T j)^T (J^T J)^-1 (J^T j))`` is chi-square(1) when the
    spline already represents the trajectory. Midpoints with ``s`` above the Bonferroni
    quantile at ``refine_alpha`` are inserted. This catches what the rough trajectory
    could not show (its noise hides model errors the measurements resolve). The same
    test runs on the telemetry error spline (each component), so a drift that bends
    faster than its initial knots gets knots too instead of an optimistic covariance.

    Where intervals fail that test, an *event* (the acceleration jumping: an engine
    cut-off or ignition the rough trajectory did not show, a turn starting) may explain
    them better than midpoint knots: with ``cfg.refine_events``, each short run of
    failing intervals (at most ``degree + 1``, with no repeated knot in it) is searched for
    the instant whose event test (:func:`event_scores`) is most significant. It replaces
    the run's midpoint knots when it is beyond its Bonferroni quantile at ``refine_alpha``
    (over every instant tried) and more significant than those midpoint knots tested
    together (:func:`insertion_score`). Not inside ``avoid`` (per target: its incomplete
    segments, where the few measurements cannot pin an event and its freedom only lets
    the fit wander).

    Returns the refined trajectory axes and telemetry error axes, per target (only those
    that changed).
    """
    tgt = np.concatenate([np.full(row[1].size, row[0]) for row in prob.rows])
    tim = np.concatenate([row[1] for row in prob.rows])
    hp = np.concatenate([row[2] for row in prob.rows])
    hv = np.concatenate([row[3] for row in prob.rows])
    is_tel = np.concatenate([np.full(row[1].size, row[4]) for row in prob.rows])
    min_len = 2.0 * cfg.knots.min_spacing
    traj_c: list[tuple[int, int, float, float]] = []  # (target, axis, tau, score)
    tel_c: list[tuple[int, int, float, float]] = []  # (target, component, tau, score)
    for tid, traj in prob.trajs.items():
        sel = np.flatnonzero(tgt == tid)
        order = sel[np.argsort(tim[sel], kind='stable')]
        ts = tim[order]
        for a, ax in enumerate(traj.axes):
            up = hp[order] @ traj.rotation[:, a]
            uv = hv[order] @ traj.rotation[:, a]
            data = ScoreRows(ts, up, uv, order, r, jac, cov)
            for tau, sc in _knot_scores(ax, data, min_len):
                traj_c.append((tid, a, tau, sc))
        tb = next((t for t in prob.telemetry if t.target == tid), None)
        if tb is None:
            continue
        tsel = order[is_tel[order]]
        for c in range(3):
            data = ScoreRows(tim[tsel], hp[tsel, c], hv[tsel, c], tsel, r, jac, cov)
            scores = _knot_scores(tb.axis, data, min_len)
            tel_c.extend((tid, c, tau, sc) for tau, sc in scores)
    n_cand = len(traj_c) + len(tel_c)
    if n_cand == 0:
        return {}, {}
    limit = float(chi2_isf(cfg.refine_alpha / n_cand, 1))
    events: dict[int, list[tuple[float, float, float]]] = {}
    if cfg.refine_events:
        events = _events(prob, traj_c, limit, (tgt, tim, hp, hv), r, jac, cov, cfg, avoid or {})
    out: dict[int, list[SplineAxis]] = {}
    for tid, traj in prob.trajs.items():
        axes = list(traj.axes)
        changed = False
        found = events.get(tid, [])
        for a in range(3):
            new = [
                tau
                for k, ax_, tau, sc in traj_c
                if k == tid
                and ax_ == a
                and sc > limit
                and not any(lo <= tau <= hi for _, lo, hi in found)
            ]
            new += [tau for tau, _, _ in found for _ in range(axes[a].degree - 1)]
            if new:
                axes[a] = _with_knots(axes[a], new)
                changed = True
        if changed:
            out[tid] = axes
    tel_out: dict[int, SplineAxis] = {}
    for tb in prob.telemetry:
        new = sorted({tau for k, _c, tau, sc in tel_c if k == tb.target and sc > limit})
        if new:
            tel_out[tb.target] = _with_knots(tb.axis, new)
    return out, tel_out


def prune_knots(
    prob: Problem, beta: FloatArray, cov: FloatArray, z_min: float
) -> dict[int, list[SplineAxis]]:
    """Knots the measurements do not support (beyond the paper; the counterpart of
    :func:`refine_knots`).

    At every single interior knot of every axis, the Wald statistic of the jump of the
    ``degree``-th derivative there (seed 000's eqs. 10-13): ``|d| / sd(d)`` with ``d = C c``
    and ``sd`` from the solution's covariance. A knot whose jump the data cannot tell from
    zero (below ``z_min``) only lets the spline bend where nothing says it does: it is
    dropped. Repeated knots (events) are kept. The rough trajectory chose the knots; this
    test keeps only those the measurements (and fused telemetry) determine, so the window's
    model, and its covariance, no longer depend on which of several near-equal knot sets
    the l1 problem returned.

    Returns the reduced axes per target (only those that changed).
    """
    out: dict[int, list[SplineAxis]] = {}
    for tid, traj in prob.trajs.items():
        o = prob.offsets[tid]
        axes = list(traj.axes)
        changed = False
        for a, ax in enumerate(traj.axes):
            n = ax.n_coef
            c_mat, tau = ax.jump_matrix()
            if not tau.size:
                o += n
                continue
            c = beta[o : o + n]
            p = cov[o : o + n, o : o + n]
            o += n
            jump = c_mat @ c
            var = np.einsum('ij,ij->i', (c_mat @ p), c_mat.toarray())
            with np.errstate(divide='ignore', invalid='ignore'):
                z = np.abs(jump) / np.sqrt(np.maximum(var, 0.0))
            mult = np.array([np.count_nonzero(np.abs(ax.interior - t) < 1e-9) for t in tau])
            drop = tau[(mult == 1) & ~(z >= z_min)]
            if drop.size:
                keep = [k for k in ax.interior if np.min(np.abs(drop - k)) > 1e-9]
                axes[a] = SplineAxis.from_interior(np.asarray(keep), ax.t0, ax.t1, ax.degree)
                changed = True
        if changed:
            out[tid] = axes
    return out


def rebuild(
    prob: Problem,
    beta: FloatArray,
    new_axes: Mapping[int, list[SplineAxis]],
    new_tel: Mapping[int, SplineAxis],
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
    tel_separate: Mapping[int, bool] | None = None,
    tel_delays: Mapping[int, bool] | None = None,
) -> tuple[Problem, FloatArray]:
    """The problem on new knots, started from the current solution (refined knots contain
    the old ones, so the current spline is represented exactly; pruned ones get its
    least-squares fit). ``tel_separate`` switches targets' telemetry to a velocity error
    of its own, ``tel_delays`` to estimated time-tag delays (both started at zero); the
    others keep their model."""
    sols: dict[int, tuple[SplineTrajectory, FloatArray]] = {}
    for tid, traj in prob.trajs.items():
        coef = prob._coef(beta, tid)
        if tid in new_axes:
            nt = traj.with_axes(new_axes[tid])
            brk = np.unique(np.concatenate([a.knots for a in nt.axes]))
            ts = np.unique(
                np.concatenate(
                    [np.linspace(x0, x1, 8) for x0, x1 in zip(brk[:-1], brk[1:], strict=True)]
                )
            )
            x = traj.states(coef, ts)
            coef = nt.fit_states(ts, x[:, :3], x[:, 3:], 1.0, 1.0)
            traj = nt
        sols[tid] = (traj, coef)
    tel_axes = {tb.target: new_tel.get(tb.target, tb.axis) for tb in prob.telemetry}
    separate = {tb.target: tb.w_axis is not None for tb in prob.telemetry}
    separate.update(tel_separate or {})
    delays = {tb.target: tb.delays for tb in prob.telemetry}
    delays.update(tel_delays or {})
    new = Problem(obs, sols, cfg, t0, t1, tel_axes, separate, prob.tel_events, delays)
    new.gated = prob.gated
    new.jerk_q.update({tid: q for tid, q in prob.jerk_q.items() if tid in new.jerk_q})
    new.gate_refused = prob.gate_refused
    beta_new = np.zeros(new.n)
    for tid, (traj, coef) in sols.items():
        o = new.offsets[tid]
        beta_new[o : o + traj.n_coef] = coef
    nb = len(prob.biases)
    beta_new[new.bias_offset : new.bias_offset + nb] = beta[
        prob.bias_offset : prob.bias_offset + nb
    ]
    new.bias_sigma, new.bias_status = prob.bias_sigma, prob.bias_status
    for tb_new, tb_old in zip(new.telemetry, prob.telemetry, strict=True):
        tb_new.noise = list(tb_old.noise)
        tb_new.prior_sigma = tb_old.prior_sigma
        tb_new.size_prior = tb_old.size_prior
        old_e = beta[tb_old.offset : tb_old.offset + 3 * tb_old.axis.n_coef].reshape(-1, 3)
        if tb_new.axis is tb_old.axis:
            new_e = old_e
        else:  # refined knots contain the old ones: refit the same error curves
            brk = np.unique(tb_new.axis.knots)
            ts = np.unique(
                np.concatenate(
                    [np.linspace(a, b, 6) for a, b in zip(brk[:-1], brk[1:], strict=True)]
                )
            )
            vals = tb_old.axis.evaluate(old_e, ts)
            new_e = np.stack(
                [tb_new.axis.fit(ts, vals[:, c], ridge=0.0) for c in range(3)], axis=1
            )
        beta_new[tb_new.offset : tb_new.offset + new_e.size] = new_e.ravel()
        if tb_new.w_axis is not None and tb_old.w_axis is not None:
            n_w = 3 * tb_old.w_axis.n_coef
            o_old = tb_old.offset + 3 * tb_old.axis.n_coef
            o_new = tb_new.offset + 3 * tb_new.axis.n_coef
            old_w = beta[o_old : o_old + n_w]
            if tb_new.w_axis.n_coef != tb_old.w_axis.n_coef:
                # a finer w (its knots contain the old ones): piecewise linear, so its
                # coefficients are the old error's values at its knots
                sites = tb_new.w_axis.knots[1:-1]
                old_w = tb_old.w_axis.evaluate(old_w.reshape(-1, 3), sites).ravel()
            beta_new[o_new : o_new + old_w.size] = old_w
        if tb_new.delays and tb_old.delays:
            beta_new[tb_new.delay_offset : tb_new.delay_offset + 2] = beta[
                tb_old.delay_offset : tb_old.delay_offset + 2
            ]
    return new, beta_new


def choose_knots_safely(
    rough: RoughTrajectory,
    t0: float,
    t1: float,
    segments: Sequence[Segment],
    cfg: EstimatorConfig,
    method: str,
    frame: tuple[FloatArray, FloatArray] | None,
    baseline_spacing: float = 3.0,
    events: Sequence[float] | None = None,
    context: tuple[RoughTrajectory, float, float] | None = None,
    kinks: Sequence[float] = (),
) -> KnotSelection:
    """:func:`choose_knots`, but a failed l1 problem never loses the window: the other
    installed interior-point solver is tried, then the densified knots are kept (the
    reason is recorded in the selection's ``info``).

    ``max_spacing`` applies only where fused telemetry places the knots. From fixes the
    knots are chosen again on the first solution, which the measurements determine, and
    the added knots made seed003_q2 (satellite fixes) worse (3.6 -> 4.6 m, 0.7 -> 1.7
    m/s). Without ``use_telemetry`` the stations alone would have to determine the added
    coefficients, and where none sees the target (aircraft draw 14 of the robustness
    suite) the window's states went to 1e13 times the bound."""
    fused = cfg.use_telemetry and rough.source == 'telemetry'
    knots = cfg.knots if fused else replace(cfg.knots, max_spacing=0.0)
    try:
        return choose_knots(
            rough, t0, t1, segments, knots, method, frame, baseline_spacing, events, context, kinks
        )
    except KnotSelectionError as first:
        reason = str(first)
    if knots.solver.upper() != 'CLARABEL':
        try:
            alt = replace(knots, solver='CLARABEL')
            sel = choose_knots(
                rough,
                t0,
                t1,
                segments,
                alt,
                method,
                frame,
                baseline_spacing,
                events,
                context,
                kinks,
            )
            return replace(sel, info={**sel.info, 'fallback': f'CLARABEL after: {reason}'})
        except KnotSelectionError as second:
            reason += f'; CLARABEL: {second}'
    sel = choose_knots(
        rough, t0, t1, segments, knots, 'dense', frame, events=events, context=context, kinks=kinks
    )
    return replace(sel, info={'fallback': f'densified knots kept: {reason}'})


def polynomial_selection(
    rough: RoughTrajectory, t0: float, t1: float, degree: int
) -> KnotSelection:
    from orbit_tracking.core.estimation.knots import _fit_rough, spline_frame

    start = _time.perf_counter()
    frame = spline_frame(rough)
    ax = SplineAxis.from_interior([], t0, t1, degree)
    traj = SplineTrajectory((ax, ax, ax), frame[0], frame[1])
    coef = _fit_rough(traj, rough, 0.5)
    return KnotSelection(
        traj, coef, (), (0, 0, 0), (0, 0, 0), 0, 0.0, _time.perf_counter() - start, 'polynomial'
    )
