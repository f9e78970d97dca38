"""Sizes of a window's zero-mean priors estimated from its data (issue 14).

Two priors of :class:`~orbit_tracking.core.estimation.problem.Problem` have a size no one
declares well: the telemetry error spline ``e`` (declared: the telemetry's position
sigma, which for white telemetry is no slow error at all) and the white-jerk prior of every
trajectory (a density nobody declares). Both are variance components of a Gaussian model,
and :func:`reestimate_priors` sets them by their evidence (type-II maximum likelihood)
between the solve rounds of :func:`~orbit_tracking.core.estimation.gauss_newton.solve`:
the error spline's two sizes by a search on a grid
(:mod:`~orbit_tracking.core.estimation.telemetry_evidence`), the densities by MacKay's
update.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.problem import Problem
from orbit_tracking.core.estimation.scaling import jacobi_scaled, normal_matrix
from orbit_tracking.core.estimation.telemetry_block import TelemetryBlock
from orbit_tracking.core.estimation.telemetry_evidence import (
    ERROR_SIGMA_RANGE,
    choose_sizes,
    evidence_grid,
    reduced_information,
)

__all__ = ['ERROR_SIGMA_RANGE', 'JERK_Q_FLOOR', 'reestimate_priors']

FloatArray = NDArray[np.float64]


def reestimate_priors(prob: Problem, beta: FloatArray, cfg: EstimatorConfig) -> bool:
    """The sizes of the window's zero-mean priors from the data.

    - The telemetry error spline ``e`` (``estimate_telemetry_error``): its level and step
      sigmas of largest evidence, searched on a grid within :data:`ERROR_SIGMA_RANGE` of
      the declared sigma (:mod:`~orbit_tracking.core.estimation.telemetry_evidence`).
      White telemetry takes them to the floor (its positions then count in full, instead
      of being half absorbed by an error allowance they do not have); a drift as large as
      the declared sigma or larger keeps or raises them.
    - The white-jerk density ``q`` of every trajectory (``jerk_prior``), by MacKay's
      evidence update of a variance component iterated to its fixed point on the
      linearised problem (:func:`_jerk_densities`).

    True when a size moved by more than 5 %."""
    tels = prob.telemetry if cfg.estimate_telemetry_error else []
    if not tels and not prob.jerk:
        return False
    r, jac, _ = prob.evaluate(beta, True)
    if jac is None:
        return False
    normal = normal_matrix(jac)
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
        unit = np.zeros((prob.n, sl.stop - sl.start + 1))
        unit[sl, :-1] = np.eye(sl.stop - sl.start)
        unit[:, -1] = np.asarray(jac.T @ r)  # the whole problem's gradient
        sol = sla.cho_solve(fac, unit / d[:, None]) / d[:, None]
        changed |= _error_sizes(tb, beta[sl], sol[sl, :-1], sol[sl, -1])
    changed |= _jerk_densities(prob, beta, normal, np.asarray(jac.T @ r))
    return changed


def _error_sizes(tb: TelemetryBlock, e: FloatArray, c_ee: FloatArray, step: FloatArray) -> bool:
    """New level and step sigmas of ``tb``'s error spline, those of largest evidence, from
    its coefficients ``e``, their posterior covariance ``c_ee`` and ``N^-1 J^T r`` there
    (``step``); True when one moved by more than 5 %."""
    try:
        h, g = reduced_information(tb, e, c_ee, step)
    except np.linalg.LinAlgError:
        return False
    new = choose_sizes(*evidence_grid(tb, h, g, e), refine=(tb, h, g, e))
    if new is None:
        return False
    changed = any(abs(a - b) > 0.05 * b for a, b in zip(new, tb.prior_sigma, strict=True))
    tb.prior_sigma = new
    return changed


def _jerk_densities(prob: Problem, beta: FloatArray, normal: FloatArray, grad: FloatArray) -> bool:
    """The white-jerk densities of every trajectory, iterated to their fixed point on the
    problem linearised at ``beta`` (one evidence update per solve would leave them far
    off): the data's normal matrix ``N_d`` and gradient ``g_d`` without the jerk rows, and
    for each block in turn (a target's prior away from its events, and near them) the
    pencil ``(P, N_d + P / q0)`` diagonalised once (``P`` its penalty, ``q0`` its density
    so far, the other blocks held), in which the solution, ``tr(P C)`` and the penalty
    are sums over its eigenvalues for any ``q``. A density not set yet starts from the
    mean squared jerk of ``beta``. The density near events is never below the one away
    from them: it is there to let a staging's or a turn's jerk through, not to stiffen."""
    blocks = []
    for key, mj in prob.jerk.items():
        if mj.shape[0]:
            o = prob.offsets[key[0]]
            sl = slice(o, o + prob.trajs[key[0]].n_coef)
            blocks.append((key, sl, mj.shape[0], mj.T @ mj))
    if not blocks:
        return False
    n_d, g_d = normal.copy(), grad.copy()
    q: dict[tuple[int, bool], float] = {}
    for key, sl, rank, pen in blocks:
        old = prob.jerk_q[key]
        if old is not None:  # take the prior's rows out again
            n_d[sl, sl] -= pen / old
            g_d[sl] += pen @ beta[sl] / old
        q[key] = (
            old if old is not None else max(float(beta[sl] @ pen @ beta[sl]) / rank, JERK_Q_FLOOR)
        )
    for _ in range(2 if len(blocks) > 1 else 1):
        for key, sl, rank, pen in blocks:
            q0 = q[key]
            a = n_d.copy()
            for other, sl2, _, pen2 in blocks:
                a[sl2, sl2] += pen2 / q[other]
            p_full = np.zeros_like(a)
            p_full[sl, sl] = pen / q0
            g_t = g_d.copy()  # the gradient of the data and the other blocks' priors
            for other, sl2, _, pen2 in blocks:
                if other != key:
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
            if key[1]:  # near events: never held tighter than the rest of the trajectory
                value = max(value, q.get((key[0], False), value))
            q[key] = value
    changed = False
    for key, value in q.items():
        old = prob.jerk_q[key]
        changed |= old is None or abs(value - old) > JERK_Q_TOLERANCE * old
        prob.jerk_q[key] = value
    return changed


JERK_Q_TOLERANCE = 0.25
"""A jerk density that moved by less than this fraction asks for no further solve round
(the fit hardly depends on it at that level)."""

JERK_ITERATIONS = 200
"""Most evidence updates of a jerk density per call (each a sum over eigenvalues)."""

JERK_Q_FLOOR = 1e-3
"""Smallest white-jerk density [m^2/s^5]. A trajectory without any jerk would pin the
evidence to 0, and a window of straight flight after a telemetry outage did come out at
1e-8 to 1e-5 (as a pass's last window, and solved alone): its spline nearly jerk-free, its
velocity a quarter metre per second off at sigmas of two centimetres per second
(robustness aircraft draw 49, 120-151.7 s). 1e-3 is a jerk of
0.03 m/s^3 RMS over a second, far below any vehicle's (a turn's entry ramp has 20-30
m/s^3), and leaves the estimate of a window that needs more untouched."""
