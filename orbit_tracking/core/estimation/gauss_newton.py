"""Gauss-Newton with step halving on a window's
:class:`~orbit_tracking.core.estimation.problem.Problem` (seed 000, eq. 7), the residual
gate that rejects gross errors, the re-estimated telemetry noise, and the covariance of the
solution (with consider parameters for frozen biases)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.estimation.config import EstimationError, EstimatorConfig
from orbit_tracking.core.estimation.problem import Problem
from orbit_tracking.core.models.measurements import residual

__all__ = [
    'DAMPING',
    'GATE_MAX_FRACTION',
    'GnOutcome',
    'covariance',
    'gate_residuals',
    'gauss_newton',
    'solve',
]

FloatArray = NDArray[np.float64]


@dataclass
class GnOutcome:
    beta: FloatArray
    cost: float
    iterations: int
    halvings: int
    converged: bool
    message: str


DAMPING = 1e-10
"""Relative (Jacobi-scaled) damping of the normal matrix: directions the data do not
determine to better than 1e-10 of the best-determined one stay where they are instead of
running away (Levenberg-Marquardt with a fixed, tiny lambda)."""


def _normal_solve(n: FloatArray, g: FloatArray) -> tuple[FloatArray, float, bool]:
    d = np.sqrt(np.maximum(np.diag(n), 1e-300))
    ns = n / d[:, None] / d[None, :]
    ns[np.diag_indices_from(ns)] += DAMPING
    try:
        cf = sla.cho_factor(ns, check_finite=False)
        step = sla.cho_solve(cf, g / d, check_finite=False) / d
        ok = True
    except np.linalg.LinAlgError:
        step = np.linalg.lstsq(ns, g / d, rcond=1e-12)[0] / d
        ok = False
    ev = np.linalg.eigvalsh(ns)
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
    return step, cond, ok


def gauss_newton(prob: Problem, beta: FloatArray, cfg: EstimatorConfig) -> GnOutcome:
    r, jac, _ = prob.evaluate(beta, True)
    cost = float(r @ r)
    halvings = 0
    for it in range(1, cfg.max_iterations + 1):
        assert jac is not None
        n = (jac.T @ jac).toarray()
        g = jac.T @ r
        step, _, _ = _normal_solve(n, g)
        omega = 1.0
        for _ in range(cfg.max_halvings + 1):
            trial = prob.project(beta + omega * step)
            c_new = prob.cost(trial)
            if c_new <= cost:
                break
            omega *= 0.5
            halvings += 1
        else:
            return GnOutcome(beta, cost, it, halvings, True, 'no step reduces the cost')
        change = cost - c_new
        beta = trial
        r, jac, _ = prob.evaluate(beta, True)
        cost = float(r @ r)
        if change <= cfg.tolerance * max(cost, 1.0):
            return GnOutcome(beta, cost, it, halvings, True, 'converged')
    return GnOutcome(beta, cost, cfg.max_iterations, halvings, False, 'iteration limit')


GATE_MAX_FRACTION = 0.05
"""The residual gate rejects outliers, not the data: if it would reject more than this
fraction of the rows, the model itself does not fit (e.g. unmodelled systematic errors),
nothing is gated and the estimate says so."""


def gate_residuals(prob: Problem, beta: FloatArray, gate: float) -> bool:
    """Mark station rows whose whitened residual exceeds ``gate``; True if it changed."""
    new_masks = {}
    n_rows = n_bad = 0
    for bi, b in enumerate(prob.stations):
        pred, _, _ = prob.predict_block(bi, beta)
        r = residual(b.fields, np.nan_to_num(b.values), pred) / b.sigmas
        new_masks[bi] = b.valid & (np.abs(r) > gate)
        n_rows += int(b.valid.sum())
        n_bad += int(new_masks[bi].sum())
    if n_rows and n_bad > GATE_MAX_FRACTION * n_rows:
        prob.gate_refused = n_bad / n_rows
        new_masks = {bi: np.zeros_like(b.valid) for bi, b in enumerate(prob.stations)}
    else:
        prob.gate_refused = 0.0
    changed = False
    for bi, new in new_masks.items():
        old = prob.gated.get(bi)
        if (old is None and new.any()) or (old is not None and not np.array_equal(old, new)):
            changed = True
        prob.gated[bi] = new
    return changed


def _reestimate_telemetry_noise(prob: Problem, beta: FloatArray) -> bool:
    changed = False
    for tb in prob.telemetry:
        coef = prob._coef(beta, tb.target)
        ecoef = beta[tb.offset : tb.offset + 3 * tb.axis.n_coef]
        m = tb.time.size
        ep = tb.position - (tb.pw @ coef + tb.ew @ ecoef).reshape(m, 3) - prob.origin[tb.target]
        ep = ep[tb.valid_p]
        ev = (tb.velocity - (tb.vw @ coef + tb.edw @ ecoef).reshape(m, 3))[tb.valid_v]
        new = [
            max(float(np.sqrt(np.mean(ep**2))), 1e-3) if ep.size else tb.noise[0],
            max(float(np.sqrt(np.mean(ev**2))), 1e-5) if ev.size else tb.noise[1],
        ]
        if any(abs(a - b) > 0.05 * b for a, b in zip(new, tb.noise, strict=True)):
            changed = True
        tb.noise = new
    return changed


def solve(prob: Problem, beta: FloatArray, cfg: EstimatorConfig) -> tuple[GnOutcome, int, int]:
    """Gauss-Newton, then telemetry noise re-estimation and residual gating, repeated
    until neither changes (at most ``gate_rounds`` times)."""
    out = gauss_newton(prob, beta, cfg)
    iterations, halvings = out.iterations, out.halvings
    for _ in range(max(cfg.gate_rounds, 1)):
        changed = False
        if cfg.estimate_telemetry_noise and prob.telemetry:
            changed |= _reestimate_telemetry_noise(prob, out.beta)
        if cfg.gate_sigma > 0.0:
            changed |= gate_residuals(prob, out.beta, cfg.gate_sigma)
        if not changed:
            break
        out = gauss_newton(prob, out.beta, cfg)
        iterations += out.iterations
        halvings += out.halvings
    return out, iterations, halvings


def covariance(
    prob: Problem, beta: FloatArray
) -> tuple[FloatArray, sp.csr_matrix, FloatArray, float, bool]:
    """Residuals, Jacobian, ``(J^T J)^-1``, condition number of the scaled normal matrix,
    and whether it was singular."""
    r, jac, _ = prob.evaluate(beta, True)
    if jac is None:
        raise EstimationError('no measurement rows to estimate from')
    n = (jac.T @ jac).toarray()
    d = np.sqrt(np.maximum(np.diag(n), 1e-300))
    ns = n / d[:, None] / d[None, :]
    ev = np.linalg.eigvalsh(ns)
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
    try:
        cov = sla.cho_solve(sla.cho_factor(ns), np.eye(prob.n)) / d[:, None] / d[None, :]
        singular = False
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(ns) / d[:, None] / d[None, :]
        singular = True
    frozen = [
        (prob.bias_offset + q, bp.sigma)
        for q, bp in enumerate(prob.biases)
        if prob.bias_status[q].startswith('unobservable')
    ]
    if frozen:
        cov = _consider(cov, n, frozen)
    return r, jac, cov, cond, singular


def _consider(
    cov: FloatArray, normal: FloatArray, frozen: Sequence[tuple[int, float]]
) -> FloatArray:
    """Covariance with the frozen biases as *consider* parameters.

    A frozen bias is held at its prior, but its prior uncertainty still moves everything
    fitted with it: with ``S = -N_xx^-1 N_xc`` the sensitivity of the estimated
    parameters to the frozen ones, ``P_x += S P_c S^T`` (and ``P_xc = S P_c``). Without
    this the other estimates would claim an accuracy the frozen errors deny them.
    ``cov`` (from the normal matrix with the frozen biases pinned) is ``N_xx^-1`` on the
    estimated block.
    """
    c = np.array([k for k, _ in frozen])
    pc = np.array([sig for _, sig in frozen]) ** 2
    x = np.setdiff1d(np.arange(cov.shape[0]), c)
    sens = -cov[np.ix_(x, x)] @ normal[np.ix_(x, c)]  # (n_x, n_c)
    out = cov.copy()
    out[np.ix_(x, x)] += (sens * pc) @ sens.T
    out[np.ix_(x, c)] = sens * pc
    out[np.ix_(c, x)] = (sens * pc).T
    out[np.ix_(c, c)] = np.diag(pc)
    return out
