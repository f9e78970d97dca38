"""Knots of a window beyond the first selection: the safe initial choice (fallbacks when
the l1 selection fails), and the measurement-driven refinement (a score test per knot
interval on the solved problem, new knots where the residuals say the spline is too stiff,
the problem rebuilt on the new knots)."""

from __future__ import annotations

import time as _time
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

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

__all__ = ['choose_knots_safely', 'polynomial_selection', 'prune_knots', 'rebuild', 'refine_knots']

FloatArray = NDArray[np.float64]


def _knot_scores(
    ax: SplineAxis,
    ts: FloatArray,
    up: FloatArray,
    uv: FloatArray,
    ridx: NDArray[np.intp],
    r: FloatArray,
    jac: sp.csr_matrix,
    cov: FloatArray,
    min_len: float,
) -> list[tuple[float, float]]:
    """Score statistic of a knot at the midpoint of every interval of ``ax``.

    ``ts`` are the (sorted) times of the residual rows ``ridx`` the axis acts on, and
    ``up``/``uv`` the whitened derivatives of those rows by the axis' value and rate.
    """
    from scipy.interpolate import BSpline

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


def _with_knots(ax: SplineAxis, new: Sequence[float]) -> SplineAxis:
    return SplineAxis.from_interior(
        np.sort(np.concatenate([ax.interior, np.asarray(new, dtype=float)])),
        ax.t0,
        ax.t1,
        ax.degree,
    )


def refine_knots(
    prob: Problem,
    r: FloatArray,
    jac: sp.csr_matrix,
    cov: FloatArray,
    cfg: EstimatorConfig,
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

    Returns the refined trajectory axes and telemetry error axes, per target (only those
    that changed).
    """
    from scipy.stats import chi2

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
            for tau, sc in _knot_scores(ax, ts, up, uv, order, r, jac, cov, min_len):
                traj_c.append((tid, a, tau, sc))
        tb = next((t for t in prob.telemetry if t.target == tid), None)
        if tb is None:
            continue
        tsel = order[is_tel[order]]
        for c in range(3):
            scores = _knot_scores(
                tb.axis, tim[tsel], hp[tsel, c], hv[tsel, c], tsel, r, jac, cov, min_len
            )
            tel_c.extend((tid, c, tau, sc) for tau, sc in scores)
    n_cand = len(traj_c) + len(tel_c)
    if n_cand == 0:
        return {}, {}
    limit = float(chi2.isf(cfg.refine_alpha / n_cand, 1))
    out: dict[int, list[SplineAxis]] = {}
    for tid, traj in prob.trajs.items():
        axes = list(traj.axes)
        changed = False
        for a in range(3):
            new = [tau for k, ax_, tau, sc in traj_c if k == tid and ax_ == a and sc > limit]
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
        if tb_new.w_axis is not None and tb_old.w_axis is not None:  # same window, same w
            n_w = 3 * tb_old.w_axis.n_coef
            o_old = tb_old.offset + 3 * tb_old.axis.n_coef
            o_new = tb_new.offset + 3 * tb_new.axis.n_coef
            beta_new[o_new : o_new + n_w] = beta[o_old : o_old + n_w]
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
) -> KnotSelection:
    """:func:`choose_knots`, but a failed l1 problem never loses the window: the other
    installed interior-point solver is tried, then the densified knots are kept (the
    reason is recorded in the selection's ``info``)."""
    try:
        return choose_knots(
            rough, t0, t1, segments, cfg.knots, method, frame, baseline_spacing, events, context
        )
    except KnotSelectionError as first:
        reason = str(first)
    if cfg.knots.solver.upper() != 'CLARABEL':
        try:
            alt = replace(cfg.knots, solver='CLARABEL')
            sel = choose_knots(
                rough, t0, t1, segments, alt, method, frame, baseline_spacing, events, context
            )
            return replace(sel, info={**sel.info, 'fallback': f'CLARABEL after: {reason}'})
        except KnotSelectionError as second:
            reason += f'; CLARABEL: {second}'
    sel = choose_knots(
        rough, t0, t1, segments, cfg.knots, 'dense', frame, events=events, context=context
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
