"""Sizes of a window's zero-mean priors estimated from its data (issue 14).

Two priors of :class:`~orbit_tracking.core.estimation.problem.Problem` have a size no one
declares well: the telemetry error spline ``e`` (declared: the telemetry's position
sigma, which for white telemetry is no slow error at all) and the white-jerk prior of every
trajectory (a density nobody declares). Both are variance components of a Gaussian model,
and :func:`reestimate_priors` sets them by MacKay's evidence update (type-II maximum
likelihood) between the solve rounds of
:func:`~orbit_tracking.core.estimation.gauss_newton.solve`.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.optimize import minimize_scalar
from scipy.stats import chi2

from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.motion_rows import JerkRows
from orbit_tracking.core.estimation.problem import Problem
from orbit_tracking.core.estimation.scaling import jacobi_scaled
from orbit_tracking.core.estimation.telemetry_block import TelemetryBlock, error_step_matrix

__all__ = ['ERROR_SIGMA_RANGE', 'JERK_Q_FLOOR', 'block_factors', 'reestimate_priors']

FloatArray = NDArray[np.float64]


ERROR_SIGMA_RANGE = (1e-3, 10.0)
"""The telemetry error spline's prior sigma stays within these multiples of the declared
position sigma."""


def reestimate_priors(prob: Problem, beta: FloatArray, cfg: EstimatorConfig) -> bool:
    """The sizes of the window's zero-mean priors from the data, by MacKay's evidence
    update of a variance component: for a prior ``|M x|^2 / s^2`` of rank ``r`` on some
    unknowns ``x``, ``s^2 = |M x|^2 / gamma`` with ``gamma = r - tr(M C M^T) / s^2`` the
    number of its directions the data determine (``C`` the posterior covariance of
    ``x``); at most a factor of 10 per round once set.

    - The telemetry error spline ``e`` (``estimate_telemetry_error``): white telemetry
      drives its sigma down (its positions then count in full, instead of being half
      absorbed by an error allowance they do not have); a drift as large as the declared
      sigma or larger keeps or raises it (within :data:`ERROR_SIGMA_RANGE`).
    - The white-jerk density ``q`` of every trajectory (``jerk_prior``), iterated to its
      fixed point on the linearised problem (:func:`_jerk_densities`).

    True when a size moved by more than 5 %."""
    tels = prob.telemetry if cfg.estimate_telemetry_error else []
    if not tels and not prob.jerk:
        return False
    r, jac, _ = prob.evaluate(beta, True)
    if jac is None:
        return False
    normal = (jac.T @ jac).toarray()
    changed = False
    if tels:
        d = np.sqrt(np.maximum(np.diag(normal), 1e-300))
        ns = normal / d[:, None] / d[None, :]
        ns[np.diag_indices_from(ns)] += 1e-10
        try:
            fac = sla.cho_factor(ns)
        except np.linalg.LinAlgError:
            tels = []
    for tb in tels:
        sl = slice(tb.offset, tb.offset + 3 * tb.axis.n_coef)
        unit = np.zeros((prob.n, sl.stop - sl.start))
        unit[sl] = np.eye(sl.stop - sl.start)
        c_ee = (sla.cho_solve(fac, unit) / d[:, None])[sl] / d[None, sl]
        changed |= _error_sizes(tb, beta[sl], c_ee)
    grad = np.asarray(jac.T @ r)
    before = {tid: prob.jerk_penalty(tid) for tid in prob.jerk}
    changed |= _jerk_densities(prob, beta, normal, grad)
    changed |= _jerk_blocks(prob, beta, normal, grad, before, cfg.jerk_block_alpha)
    return changed


def _error_sizes(tb: TelemetryBlock, e: FloatArray, c_ee: FloatArray) -> bool:
    """New level and step sigmas of ``tb``'s error spline from its coefficients ``e`` and
    their posterior covariance ``c_ee``; True when one moved by more than 5 %."""
    bounds = tuple(k * tb.declared_sigma for k in ERROR_SIGMA_RANGE)
    new = (
        _component(tb.prior_sigma[0], np.eye(3, e.size), e, c_ee, bounds),
        _component(
            tb.prior_sigma[1], error_step_matrix(tb.axis.n_coef).toarray(), e, c_ee, bounds
        ),
    )
    changed = any(abs(a - b) > 0.05 * b for a, b in zip(new, tb.prior_sigma, strict=True))
    tb.prior_sigma = new
    return changed


def _component(
    old: float, m: FloatArray, x: FloatArray, cov: FloatArray, bounds: tuple[float, ...]
) -> float:
    """The new sigma of the prior ``|m x|^2 / sigma^2`` (``cov``: the posterior covariance
    of ``x``), moved by at most a factor of 10 and kept within ``bounds``."""
    y = m @ x
    new = _variance_update(old, float(y @ y), y.size, float(np.sum((m @ cov) * m)))
    return min(max(new, old / 10.0, bounds[0]), 10.0 * old, bounds[1])


def _variance_update(old: float, square: float, rank: int, trace: float) -> float:
    """The evidence update of one variance component's sigma: MacKay's
    ``|M x|^2 / gamma`` where the data determine enough of it (``gamma > 0.5``), else the
    EM update ``(|M x|^2 + tr(M C M^T)) / rank``, which keeps a size the data cannot tell
    (MacKay's would take it to zero there)."""
    gamma = rank - trace / old**2
    if gamma > 0.5:
        return math.sqrt(square / gamma)
    return math.sqrt((square + trace) / rank)


def _jerk_densities(prob: Problem, beta: FloatArray, normal: FloatArray, grad: FloatArray) -> bool:
    """The white-jerk densities of every trajectory, iterated to their fixed point on the
    problem linearised at ``beta`` (one evidence update per solve would leave them far
    off): the data's normal matrix ``N_d`` and gradient ``g_d`` without the jerk rows, and
    for each target in turn the pencil ``(P, N_d + P / q0)`` diagonalised once (``P`` its
    penalty, ``q0`` its density so far, the other targets' priors held), in which the
    solution, ``tr(P C)`` and the penalty are sums over its eigenvalues for any ``q``. A
    density not set yet starts from the mean squared jerk of ``beta``."""
    blocks = []
    for tid, jr in prob.jerk.items():
        if jr.rows.shape[0]:
            o = prob.offsets[tid]
            sl = slice(o, o + prob.trajs[tid].n_coef)
            w = jr.rows / np.sqrt(prob.jerk_scale[tid][jr.block])[:, None]
            blocks.append((tid, sl, jr.rank, w.T @ w))
    if not blocks:
        return False
    n_d, g_d = normal.copy(), grad.copy()
    q: dict[int, float] = {}
    for tid, sl, rank, pen in blocks:
        old = prob.jerk_q[tid]
        if old is not None:  # take the prior's rows out again
            n_d[sl, sl] -= pen / old
            g_d[sl] += pen @ beta[sl] / old
        q[tid] = (
            old if old is not None else max(float(beta[sl] @ pen @ beta[sl]) / rank, JERK_Q_FLOOR)
        )
    for _ in range(2 if len(blocks) > 1 else 1):
        for tid, sl, rank, pen in blocks:
            q0 = q[tid]
            a = n_d.copy()
            for other, sl2, _, pen2 in blocks:
                a[sl2, sl2] += pen2 / q[other]
            p_full = np.zeros_like(a)
            p_full[sl, sl] = pen / q0
            g_t = g_d.copy()  # the gradient of the data and the other targets' priors
            for other, sl2, _, pen2 in blocks:
                if other != tid:
                    g_t[sl2] -= pen2 @ beta[sl2] / q[other]
            a_s, d = jacobi_scaled(a, 1e-10)
            try:
                mu, v = sla.eigh(p_full / d[:, None] / d[None, :], a_s)
            except (np.linalg.LinAlgError, ValueError):
                return False
            mu = np.clip(mu, 0.0, 1.0)
            u = v.T @ (a_s @ (d * beta))  # beta in the pencil's coordinates
            w = v.T @ (g_t / d)  # ... and that gradient
            value = q0
            for _it in range(JERK_ITERATIONS):
                ratio = q0 / value  # the prior is P / value = ratio * P / q0
                den = 1.0 - mu + ratio * mu
                y = u + (w - ratio * mu * u) / den
                gamma = rank - ratio * float(np.sum(mu / den))
                new = q0 * float(np.sum(mu * y**2)) / gamma if gamma > 0.5 else value / 10.0
                new = min(max(new, value / 10.0, JERK_Q_FLOOR), 10.0 * value)
                done = abs(math.log(new / value)) < 1e-3
                value = new
                if done:
                    break
            q[tid] = value
    changed = False
    for tid, value in q.items():
        old = prob.jerk_q[tid]
        changed |= old is None or abs(value - old) > JERK_Q_TOLERANCE * old
        prob.jerk_q[tid] = value
    return changed


JERK_Q_TOLERANCE = 0.25
"""A jerk density that moved by less than this fraction asks for no further solve round
(the fit hardly depends on it at that level)."""

JERK_ITERATIONS = 200
"""Most evidence updates of a jerk density per call (each a sum over eigenvalues)."""

JERK_Q_FLOOR = 1e-8
"""Smallest white-jerk density [m^2/s^5] (a trajectory without any jerk would pin it to 0)."""


def _jerk_blocks(
    prob: Problem,
    beta: FloatArray,
    normal: FloatArray,
    grad: FloatArray,
    before: dict[int, FloatArray | None],
    alpha: float,
) -> bool:
    """Raise the white-jerk density of the blocks whose jerk the data show to be larger
    than the prior allows (a staging or a turn's onset that no knot marks), so that the
    prior neither flattens that jerk nor claims a sigma that ignores it.

    Each block is tested together with :data:`JERK_BLOCK_REACH` blocks on each side (the
    jerk of the spline is continuous, so its neighbours' priors alone would pin a lone
    block's jerk): with ``W`` the square-root rows of their prior as it stands (``u = W c``
    is ``N(0, I)`` under it), the alternative is that prior divided by ``f >= 1``. From
    the current solution ``c`` and posterior covariance ``C``, with ``S = W C W^T``
    diagonalised (eigenvalues ``s_i < 1``), the data-only estimate of ``u`` has variances
    ``k_i = s_i / (1 - s_i)`` and values ``zeta_i = (U^T W c)_i / (1 - s_i)``, and the
    evidence is ``-1/2 sum log(f + k_i) + zeta_i^2 / (f + k_i)`` (directions with ``s_i``
    at 1, which the data do not inform, left out). Where its maximum beats ``f = 1`` by a
    likelihood ratio beyond the chi-square quantile of ``alpha`` (one parameter on its
    boundary), those blocks' factors are multiplied by ``f`` (never lowered within a
    window). ``normal`` and ``grad`` are those of ``beta`` under the priors ``before`` (the
    densities since re-estimated). True when a factor moved by more than
    :data:`JERK_Q_TOLERANCE`."""
    targets = [
        tid
        for tid, jr in prob.jerk.items()
        if jr.n_blocks > 1 and jr.rows.shape[0] and prob.jerk_q[tid] is not None
    ]
    if not targets:
        return False
    a, g = normal.copy(), grad.copy()
    for tid in prob.jerk:
        o = prob.offsets[tid]
        sl = slice(o, o + prob.trajs[tid].n_coef)
        old, new = before.get(tid), prob.jerk_penalty(tid)
        diff = (0.0 if new is None else new) - (0.0 if old is None else old)
        if isinstance(diff, np.ndarray):
            a[sl, sl] += diff
            g[sl] -= diff @ beta[sl]
    threshold = float(chi2.isf(2.0 * alpha, 1))
    start = {tid: prob.jerk_scale[tid].copy() for tid in targets}
    for _ in range(JERK_BLOCK_ROUNDS):  # to the fixed point on the linearised problem
        a_s, d = jacobi_scaled(a, 1e-10)
        try:
            fac = sla.cho_factor(a_s)
        except np.linalg.LinAlgError:
            break
        x = beta + sla.cho_solve(fac, g / d) / d
        raised = False
        for tid in targets:
            jr = prob.jerk[tid]
            o = prob.offsets[tid]
            n = prob.trajs[tid].n_coef
            unit = np.zeros((prob.n, n))
            unit[o : o + n] = np.eye(n)
            c_ss = (sla.cho_solve(fac, unit / d[:, None]) / d[:, None])[o : o + n]
            x_s = x[o : o + n]
            scale = prob.jerk_scale[tid]
            new_scale = block_factors(jr, prob.jerk_weights(tid), scale, c_ss, x_s, threshold)
            if np.array_equal(new_scale, scale):
                continue
            raised = True
            sl = slice(o, o + n)
            old_pen = prob.jerk_penalty(tid)
            prob.jerk_scale[tid] = new_scale
            new_pen = prob.jerk_penalty(tid)
            assert old_pen is not None and new_pen is not None  # the density is set
            diff = new_pen - old_pen
            a[sl, sl] += diff
            g[sl] -= diff @ beta[sl]
        if not raised:
            break
    changed = False
    for tid in targets:
        moved = np.abs(np.log(prob.jerk_scale[tid] / start[tid])) > math.log1p(JERK_Q_TOLERANCE)
        changed |= bool(moved.any())
    return changed


def block_factors(
    jr: JerkRows,
    weights: FloatArray,
    scale: FloatArray,
    c: FloatArray,
    x: FloatArray,
    threshold: float,
) -> FloatArray:
    """The blocks' factors after one round of the test of :func:`_jerk_blocks`: ``jr``
    the prior's rows, ``weights`` their weights as they stand (``1 / sqrt(q s)``),
    ``scale`` the blocks' factors so far, ``c`` and ``x`` the posterior covariance and
    solution of the trajectory's coefficients, ``threshold`` the likelihood ratio a
    group of blocks must pass."""
    weighted = weights[:, None] * jr.rows
    new = scale.copy()
    for b in np.unique(jr.block):
        w = weighted[np.abs(jr.block - b) <= JERK_BLOCK_REACH]
        cols = np.flatnonzero(np.any(w != 0.0, axis=0))
        f = _block_factor(w[:, cols], c[np.ix_(cols, cols)], x[cols], threshold)
        if f > 1.0:
            lo, hi = max(b - JERK_BLOCK_REACH, 0), b + JERK_BLOCK_REACH + 1
            new[lo:hi] = np.maximum(new[lo:hi], scale[lo:hi] * f)
    return np.minimum(new, JERK_BLOCK_MAX)


def _block_factor(w: FloatArray, c: FloatArray, x: FloatArray, threshold: float) -> float:
    """The factor ``f`` of one group of blocks (:func:`_jerk_blocks`): ``w`` the rows of
    their prior as it stands, ``c`` and ``x`` the posterior covariance and solution of the
    coefficients under them; 1 unless the likelihood ratio passes ``threshold``."""
    lam, vec = np.linalg.eigh(w.T @ w)
    top = float(lam.max()) if lam.size else 0.0
    keep = lam > 1e-10 * max(top, 1e-300)
    if not keep.any():
        return 1.0
    root = np.sqrt(lam[keep])[:, None] * vec[:, keep].T  # orthogonal square-root rows
    sm = root @ c @ root.T
    sig, u = np.linalg.eigh(0.5 * (sm + sm.T))
    sig = np.clip(sig, 0.0, None)
    informed = sig < 1.0 - 1e-9
    if not informed.any():
        return 1.0
    sig, u = sig[informed], u[:, informed]
    k = sig / (1.0 - sig)
    zeta2 = ((u.T @ (root @ x)) / (1.0 - sig)) ** 2

    def minus_log_evidence(log_f: float) -> float:
        v = math.exp(log_f) + k
        return 0.5 * float(np.sum(np.log(v) + zeta2 / v))

    best = minimize_scalar(
        minus_log_evidence, bounds=(0.0, math.log(JERK_BLOCK_MAX)), method='bounded'
    )
    ratio = 2.0 * (minus_log_evidence(0.0) - float(best.fun))
    return math.exp(float(best.x)) if ratio > threshold else 1.0


JERK_BLOCK_MAX = 1e6
"""Largest factor on a block's white-jerk density."""

JERK_BLOCK_REACH = 1
"""Blocks on each side tested together with a block (:func:`_jerk_blocks`)."""

JERK_BLOCK_ROUNDS = 6
"""Most rounds of the block test per call (each one factorisation)."""
