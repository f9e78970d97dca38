"""The size of the telemetry error spline from the evidence, and what not knowing it costs
(issue 14, item 3).

The telemetry error spline ``e`` (:mod:`~orbit_tracking.core.estimation.telemetry_block`)
has two prior sigmas nobody declares: its level and its steps between consecutive
coefficients. White telemetry has no slow error at all (both sizes ~0: its positions count
in full); a drift, a random walk or a bias needs them as large as the error. Which one a
window has is a question for its data, answered by the evidence (the marginal likelihood,
type-II maximum likelihood) of the window linearised at its solution:

* the data's information on ``e`` with every other unknown marginalised, ``h`` (the Schur
  complement of the normal matrix without ``e``'s prior), and its gradient ``g``, give the
  data's half chi-square in ``e`` as ``g^T (x - e) + (x - e)^T h (x - e) / 2``;
* for a prior precision ``Q(level, step)`` the log evidence is, up to a constant,
  ``-min_x [that + x^T Q x / 2] - log det(h + Q) / 2 + log det(Q) / 2``
  (:func:`error_evidence`), evaluated on a grid of both sizes over
  :data:`ERROR_SIGMA_RANGE` of the declared sigma (:func:`evidence_grid`). An iterated
  evidence update (EM) crept along the flat evidence of white telemetry and stopped at a
  tenth of the declared sigma, which took half the telemetry's information away.

The window is solved with the sizes of largest evidence (:func:`choose_sizes`: the best
point of the grid, then of a finer grid around it). Where the
evidence is flat (the stations too weak to tell a slow telemetry error from none, e.g. a
random walk seen only by far radars), the best sizes are one guess among many equally
likely: the published covariance then carries all of them, :func:`evidence_covariance`
adds the spread of the evidence-weighted mixture over the grid (each size's posterior
covariance and its solution's offset from the chosen one), never less than the chosen
sizes' own covariance (Bayesian averaging over the sizes, as a second moment about the
published solution).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from orbit_tracking.core.estimation.telemetry_block import TelemetryBlock, error_step_matrix

__all__ = [
    'ERROR_SIGMA_RANGE',
    'EVIDENCE_GRID',
    'choose_sizes',
    'error_evidence',
    'error_precision',
    'evidence_covariance',
    'evidence_grid',
]

FloatArray = NDArray[np.float64]

ERROR_SIGMA_RANGE = (1e-3, 10.0)
"""The telemetry error spline's prior sigmas stay within these multiples of the declared
position sigma."""

EVIDENCE_GRID = 17
"""Points per size on the grid of the evidence (a quarter decade apart over the four
decades of :data:`ERROR_SIGMA_RANGE`)."""


def error_precision(n_coef: int, level: float, step: float) -> FloatArray:
    """The prior precision of ``e``'s ``3 n_coef`` coefficients: its first coefficient per
    axis over ``level``, each later one minus its predecessor over ``step``
    (:func:`~orbit_tracking.core.estimation.telemetry_block.error_prior_matrix`)."""
    m = error_step_matrix(n_coef).toarray()
    q = m.T @ m / step**2
    q[:3, :3] += np.eye(3) / level**2
    return q


def error_evidence(h: FloatArray, g: FloatArray, e: FloatArray, q: FloatArray) -> float:
    """Log evidence, up to a constant, of the prior precision ``q`` of the error
    coefficients: the data's half chi-square in them ``g^T (x - e) + (x - e)^T h (x - e)
    / 2`` (everything else marginalised), the prior ``x^T q x / 2``; ``-inf`` where
    ``h + q`` is not positive definite."""
    try:
        ca = sla.cho_factor(h + q)
        cq = sla.cho_factor(q)
    except np.linalg.LinAlgError:
        return -math.inf
    x = sla.cho_solve(ca, h @ e - g)
    dx = x - e
    cost = float(g @ dx + 0.5 * dx @ h @ dx + 0.5 * x @ q @ x)
    return -cost - float(np.sum(np.log(np.diag(ca[0]))) - np.sum(np.log(np.diag(cq[0]))))


def reduced_information(
    tb: TelemetryBlock, e: FloatArray, c_ee: FloatArray, step: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """``(h, g)`` of the module docstring for ``tb``'s error coefficients ``e`` from their
    posterior covariance ``c_ee`` under the current sizes and the ``e`` part of the whole
    problem's Gauss-Newton step there, ``N^-1 J^T r`` (None at a converged solution,
    where it is zero): the reduced gradient of the half chi-square is ``-C_ee^-1`` times
    that step, the data's part of it that less the prior's ``Q e``."""
    q0 = error_precision(tb.axis.n_coef, *tb.prior_sigma)
    s = np.linalg.inv(0.5 * (c_ee + c_ee.T))
    h = s - q0
    g = -q0 @ e if step is None else -s @ step - q0 @ e
    return 0.5 * (h + h.T), g


def evidence_grid(
    tb: TelemetryBlock, h: FloatArray, g: FloatArray, e: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The sizes tried (``(k,)`` [m], for level and step alike) and the log evidence of
    each pair, ``(k, k)`` indexed ``[level, step]``."""
    lo, hi = (k * tb.declared_sigma for k in ERROR_SIGMA_RANGE)
    sizes = np.geomspace(lo, hi, EVIDENCE_GRID)
    n = tb.axis.n_coef
    ev = np.array(
        [[error_evidence(h, g, e, error_precision(n, a, b)) for b in sizes] for a in sizes]
    )
    return sizes, ev


def choose_sizes(
    sizes: FloatArray,
    ev: FloatArray,
    refine: tuple[TelemetryBlock, FloatArray, FloatArray, FloatArray] | None = None,
) -> tuple[float, float] | None:
    """The ``(level, step)`` of largest evidence on the grid; None when no pair has a
    finite one. With ``refine`` (the block and its ``h, g, e``) the best point is then
    searched again on a grid :data:`REFINE_POINTS` times finer around it (within one step
    of the coarse grid and :data:`ERROR_SIGMA_RANGE`)."""
    if not np.isfinite(ev).any():
        return None
    i, j = np.unravel_index(int(np.argmax(np.where(np.isfinite(ev), ev, -np.inf))), ev.shape)
    best = (float(sizes[i]), float(sizes[j]))
    if refine is None:
        return best
    tb, h, g, e = refine
    ratio = float(sizes[1] / sizes[0])
    fine = np.geomspace(1.0 / ratio, ratio, 2 * REFINE_POINTS + 1)
    lo, hi = sizes[0], sizes[-1]
    levels = np.clip(best[0] * fine, lo, hi)
    steps = np.clip(best[1] * fine, lo, hi)
    top = float(ev[i, j])
    for a in levels:
        for b in steps:
            v = error_evidence(h, g, e, error_precision(tb.axis.n_coef, a, b))
            if v > top:
                top, best = v, (float(a), float(b))
    return best


REFINE_POINTS = 4
"""Points per coarse grid step of the refined search around the best pair."""


def evidence_covariance(
    tb: TelemetryBlock, beta: FloatArray, cov: FloatArray
) -> tuple[FloatArray, float]:
    """``cov`` (the window's posterior covariance with ``tb``'s current sizes, at the
    converged solution ``beta``) with the uncertainty of those sizes added, as in the
    module docstring: the error block's second moment about the solution under the
    evidence-weighted mixture over the grid, where it exceeds the current sizes'
    covariance, carried to every unknown by its regression on the error coefficients.
    Also the largest ratio of a variance of the result to that of ``cov``."""
    sl = slice(tb.offset, tb.offset + 3 * tb.axis.n_coef)
    e = beta[sl]
    c_ee = cov[sl, sl]
    try:
        h, g = reduced_information(tb, e, c_ee)
    except np.linalg.LinAlgError:
        return cov, 1.0
    sizes, ev = evidence_grid(tb, h, g, e)
    if not np.isfinite(ev).any():
        return cov, 1.0
    w = np.exp(np.where(np.isfinite(ev), ev - np.max(ev[np.isfinite(ev)]), -np.inf))
    w /= w.sum()
    moment = np.zeros_like(c_ee)
    n = tb.axis.n_coef
    for (i, j), wij in np.ndenumerate(w):
        if wij < 1e-6:
            continue
        ca = sla.cho_factor(h + error_precision(n, float(sizes[i]), float(sizes[j])))
        dx = sla.cho_solve(ca, h @ e - g) - e
        moment += wij * (sla.cho_solve(ca, np.eye(e.size)) + np.outer(dx, dx))
    extra = moment - c_ee
    val, vec = np.linalg.eigh(0.5 * (extra + extra.T))
    keep = val > 0.0
    if not keep.any():
        return cov, 1.0
    gain = cov[:, sl] @ np.linalg.inv(c_ee)  # regression of every unknown on e
    root = gain @ (vec[:, keep] * np.sqrt(val[keep]))
    out = cov + root @ root.T
    d0 = np.diag(cov)
    ratio = float(np.max(np.diag(out)[d0 > 0] / d0[d0 > 0]))
    return out, ratio
