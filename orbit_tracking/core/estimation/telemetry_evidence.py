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
point of the grid, then of a finer grid around it), or with the smallest ones whose
evidence is nearly as large (:data:`PARSIMONY_NATS`). Where the
evidence is flat (the stations too weak to tell a slow telemetry error from none, e.g. a
random walk seen only by far radars), the best sizes are one guess among many equally
likely: the published covariance then carries all of them, :func:`evidence_covariance`
adds the spread of the evidence-weighted mixture over the grid (each size's posterior
covariance and its solution's offset from the chosen one), never less than the chosen
sizes' own covariance (Bayesian averaging over the sizes, as a second moment about the
published solution).

A window's own data may be too few to tell the sizes at all and still look decisive: the
estimator restarted mid-pass (``test_restart``) solved a window holding 2.4 s of data
inside an incomplete segment, two CW radars and the telemetry. On that alone the evidence
preferred a constant telemetry error by 13 nats (steps of 0.17 m where the drift needs
metres), the telemetry velocity then counted in full, and the radars' range rates placed
the target 103 m off at 7.6 of its sigma. The telemetry's error is the same from one
window to the next, so each window adds the log evidence of its predecessors
(:func:`carried_evidence`, at :data:`CARRY_WEIGHT`) to its own before choosing, and
starts from the sizes the previous window ended with; it passes the sum on. A window
with data of its own is hardly moved by it; one without keeps what the pass has shown.
The predecessors can be the ones that could not see the error (a random walk far radars
watched over the first windows, seen only later): so the published covariance averages
half over the window's own evidence and half over the sum (:func:`evidence_covariance`),
as if either could be the right one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from orbit_tracking.core.estimation.telemetry_block import TelemetryBlock, error_step_matrix

__all__ = [
    'ERROR_SIGMA_RANGE',
    'CARRY_FLOOR',
    'CARRY_WEIGHT',
    'EVIDENCE_GRID',
    'PARSIMONY_NATS',
    'carried_evidence',
    'choose_sizes',
    'error_evidence',
    'error_precision',
    'evidence_covariance',
    'evidence_covariances',
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
    sizes = _grid(tb)
    ev = evidence_table(h, g, e, tb.axis.n_coef, sizes, sizes)
    if tb.size_prior is not None:
        ev = ev + tb.size_prior
    return sizes, ev


def _grid(tb: TelemetryBlock) -> FloatArray:
    """The sizes of the grid [m] (for level and step alike): :data:`EVIDENCE_GRID` points
    spaced evenly in their logarithm over :data:`ERROR_SIGMA_RANGE` of the declared sigma."""
    lo, hi = (k * tb.declared_sigma for k in ERROR_SIGMA_RANGE)
    return np.geomspace(lo, hi, EVIDENCE_GRID)


def carried_evidence(
    previous: tuple[float, FloatArray] | None, declared: float
) -> FloatArray | None:
    """The log evidence of the sizes a window inherits from its predecessors
    (``previous``: their declared sigma and table, ``TargetSolution.
    telemetry_size_evidence``), counted at :data:`CARRY_WEIGHT`; None when there is none
    or the telemetry's declared sigma changed by more than 1 % (another grid)."""
    if previous is None:
        return None
    d0, table = previous
    if not (abs(d0 - declared) <= 0.01 * declared and table.shape == (EVIDENCE_GRID,) * 2):
        return None
    finite = np.isfinite(table)
    if not finite.any():
        return None
    return CARRY_WEIGHT * np.maximum(table - np.max(table[finite]), CARRY_FLOOR)


CARRY_WEIGHT = 0.5
"""Weight of the predecessors' log evidence in a window's: consecutive windows share their
overlap's data (counted twice otherwise), and a telemetry error may change its character
during a pass (an INS coasting through a GNSS outage), which a weight below 1 forgets
within a few windows."""

CARRY_FLOOR = -1e4
"""Lowest carried log evidence (relative to its best): an impossible pair of the last
window stays possible here, only very unlikely."""


def _prior_at(tb: TelemetryBlock, levels: FloatArray, steps: FloatArray) -> FloatArray:
    """``tb.size_prior`` at the sizes ``levels`` x ``steps`` (bilinear in their
    logarithms; zero without one)."""
    if tb.size_prior is None:
        return np.zeros((levels.size, steps.size))
    grid = np.log(_grid(tb))  # np.interp holds the end values beyond it
    a, b = np.log(levels), np.log(steps)
    by_level = np.array([np.interp(b, grid, row) for row in tb.size_prior])  # (grid, steps)
    return np.array([np.interp(a, grid, col) for col in by_level.T]).T


def evidence_table(
    h: FloatArray, g: FloatArray, e: FloatArray, n_coef: int, levels: FloatArray, steps: FloatArray
) -> FloatArray:
    """:func:`error_evidence` of every pair of ``levels`` and ``steps``, ``(len(levels),
    len(steps))``, with one factorisation per step: the level enters the prior precision
    only through the first coefficient of each axis, a rank-3 term, so that for a step's
    ``K = h + D^T D / step^2`` the solution and the determinant of every level follow from
    ``K^-1`` by Woodbury's identity and the determinant lemma; and ``log det Q`` of a
    random walk is ``-6 log(level) - 6 (n_coef - 1) log(step)``."""
    d = error_step_matrix(n_coef).toarray()
    dtd = d.T @ d
    v = h @ e - g
    out = np.full((levels.size, steps.size), -math.inf)
    for j, b in enumerate(steps):
        k = h + dtd / b**2
        try:
            ck = sla.cho_factor(k)
        except np.linalg.LinAlgError:  # only the level term makes it definite: one by one
            for i, a in enumerate(levels):
                out[i, j] = error_evidence(h, g, e, error_precision(n_coef, a, b))
            continue
        z = sla.cho_solve(ck, v)
        p = sla.cho_solve(ck, np.eye(k.shape[0])[:, :3])  # K^-1 U, U the level's columns
        logdet_k = 2.0 * float(np.sum(np.log(np.diag(ck[0]))))
        m = levels[:, None, None] ** 2 * np.eye(3) + p[:3]  # (k, 3, 3)
        try:
            lm = np.linalg.cholesky(m)
        except np.linalg.LinAlgError:
            continue
        y = np.linalg.solve(m, np.broadcast_to(z[:3, None], (levels.size, 3, 1)))[..., 0]
        x = z[None, :] - y @ p.T  # (k, n): the solutions of every level
        dx = x - e
        dxx = x @ d.T
        cost = (
            dx @ g
            + 0.5 * np.einsum('ki,ij,kj->k', dx, h, dx)
            + 0.5 * (np.sum(x[:, :3] ** 2, axis=1) / levels**2 + np.sum(dxx**2, axis=1) / b**2)
        )
        # log det(K + U U^T / a^2) = log det K + log det(M) - 6 log a
        log_a = np.log(levels)
        logdet_m = 2.0 * np.sum(np.log(np.diagonal(lm, axis1=1, axis2=2)), axis=1)
        logdet_post = logdet_k + logdet_m - 6.0 * log_a
        logdet_q = -6.0 * log_a - 6.0 * (n_coef - 1) * math.log(b)
        out[:, j] = -cost - 0.5 * (logdet_post - logdet_q)
    return out


def choose_sizes(
    sizes: FloatArray,
    ev: FloatArray,
    refine: tuple[TelemetryBlock, FloatArray, FloatArray, FloatArray] | None = None,
) -> tuple[float, float] | None:
    """The ``(level, step)`` the window is solved with; None when no pair of the grid has
    a finite log evidence ``ev``. The pair of largest evidence, unless smaller sizes come
    within :data:`PARSIMONY_NATS` of it: then the grid pair of smallest ``level * step``
    among those (:func:`_simplest`). Where the evidence is that flat the data cannot tell
    the sizes apart, and its maximum is set by noise: white GPS watched by one ship's radar
    (robustness aircraft draw 1020, outside the benchmark's seeds) took a level of 0.67 of
    the declared sigma from it, the stations alone then had to place the trajectory, and
    its position outside the outages came out at 2.9 times the bound (0.94 with the
    floor). The covariance still carries every size the evidence allows
    (:func:`evidence_covariance`). With ``refine`` (the block and its ``h, g, e``) a best
    point of largest evidence is then searched again on a grid :data:`REFINE_POINTS` times
    finer around it (within one step of the coarse grid and :data:`ERROR_SIGMA_RANGE`)."""
    if not np.isfinite(ev).any():
        return None
    flat = int(np.argmax(np.where(np.isfinite(ev), ev, -np.inf)))
    i, j = (int(x) for x in np.unravel_index(flat, ev.shape))
    small = _simplest(sizes, ev, float(ev[i, j]))
    if small != (i, j):  # the data do not ask for the sizes of largest evidence
        return float(sizes[small[0]]), float(sizes[small[1]])
    best = (float(sizes[i]), float(sizes[j]))
    if refine is None:
        return best
    tb, h, g, e = refine
    ratio = float(sizes[1] / sizes[0])
    fine = np.geomspace(1.0 / ratio, ratio, 2 * REFINE_POINTS + 1)
    levels = np.clip(best[0] * fine, sizes[0], sizes[-1])
    steps = np.clip(best[1] * fine, sizes[0], sizes[-1])
    table = evidence_table(h, g, e, tb.axis.n_coef, levels, steps)
    table = table + _prior_at(tb, levels, steps)
    if np.max(table) > ev[i, j]:
        k, m = np.unravel_index(int(np.argmax(table)), table.shape)
        best = (float(levels[k]), float(steps[m]))
    return best


REFINE_POINTS = 4
"""Points per coarse grid step of the refined search around the best pair."""

PARSIMONY_NATS = 1.0
"""How much less log evidence than the grid's best the smallest sizes may have and still
be chosen (:func:`choose_sizes`). Where the telemetry has no slow error, a level's log
evidence at its maximum exceeds that at zero by ``1.5 (z - 1 - log z)`` (for z > 1,
else 0), ``z`` a chi-square of three degrees of freedom over three (one offset per
axis): below one nat in 95 % of windows. A slow error the data see clearly is many nats
ahead. (Two nats, also tried on the scratch families, chose the floor more often on
correlated telemetry too: more states beyond five sigma on the aircraft draws.)"""


def _simplest(sizes: FloatArray, ev: FloatArray, best: float) -> tuple[int, int]:
    """The grid pair of smallest ``level * step`` among those whose log evidence is within
    :data:`PARSIMONY_NATS` of ``best`` (of those, the one of largest evidence)."""
    ok = np.isfinite(ev) & (ev >= best - PARSIMONY_NATS)
    log_size = np.log(sizes)
    volume = np.where(ok, log_size[:, None] + log_size[None, :], np.inf)
    least = volume <= volume.min() + 1e-9  # inf (never least) where not ok
    k, m = np.unravel_index(int(np.argmax(np.where(least, ev, -np.inf))), ev.shape)
    return int(k), int(m)


def evidence_covariance(
    tb: TelemetryBlock, beta: FloatArray, cov: FloatArray
) -> tuple[FloatArray, float, FloatArray | None]:
    """``cov`` (the window's posterior covariance with ``tb``'s current sizes, at the
    converged solution ``beta``) with the uncertainty of those sizes added, as in the
    module docstring: the error block's second moment about the solution under the
    evidence-weighted mixture over the grid, where it exceeds the current sizes'
    covariance, carried to every unknown by its regression on the error coefficients.
    Also the largest ratio of a variance of the result to that of ``cov`` among the
    other unknowns (the trajectory's, the biases'), and the grid's log evidence (None
    when it was not computed)."""
    sl = slice(tb.offset, tb.offset + 3 * tb.axis.n_coef)
    e = beta[sl]
    c_ee = cov[sl, sl]
    try:
        h, g = reduced_information(tb, e, c_ee)
    except np.linalg.LinAlgError:
        return cov, 1.0, None
    sizes, ev = evidence_grid(tb, h, g, e)
    if not np.isfinite(ev).any():
        return cov, 1.0, None
    w = _weights(ev)
    if tb.size_prior is not None:  # half on the window's own evidence alone
        own = ev - tb.size_prior
        if np.isfinite(own).any():
            w = 0.5 * w + 0.5 * _weights(own)
    moment = _mixture_moment(h, g, e, tb.axis.n_coef, sizes, w)
    extra = moment - c_ee
    val, vec = np.linalg.eigh(0.5 * (extra + extra.T))
    keep = val > 0.0
    if not keep.any():
        return cov, 1.0, ev
    gain = cov[:, sl] @ np.linalg.inv(c_ee)  # regression of every unknown on e
    root = gain @ (vec[:, keep] * np.sqrt(val[keep]))
    out = cov + root @ root.T
    d0 = np.diag(cov)
    rest = d0 > 0
    rest[sl] = False
    ratio = float(np.max(np.diag(out)[rest] / d0[rest], initial=1.0))
    return out, ratio, ev


def _weights(ev: FloatArray) -> FloatArray:
    """Normalised ``exp(ev)`` (zero where ``ev`` is not finite)."""
    w = np.exp(np.where(np.isfinite(ev), ev - np.max(ev[np.isfinite(ev)]), -np.inf))
    return w / w.sum()


def evidence_covariances(
    blocks: Sequence[TelemetryBlock], beta: FloatArray, cov: FloatArray
) -> tuple[FloatArray, list[float], list[FloatArray | None]]:
    """:func:`evidence_covariance` of every block (one per target), each from ``cov``
    itself, their widenings summed: a block's error information is read off the window's
    covariance, not off one already widened for another block, and the order of the
    blocks does not matter. Also each block's ratio and table."""
    out = cov
    ratios: list[float] = []
    tables: list[FloatArray | None] = []
    for tb in blocks:
        wider, ratio, table = evidence_covariance(tb, beta, cov)
        out = out + (wider - cov)
        ratios.append(ratio)
        tables.append(table)
    return out, ratios, tables


def _mixture_moment(
    h: FloatArray, g: FloatArray, e: FloatArray, n_coef: int, sizes: FloatArray, w: FloatArray
) -> FloatArray:
    """Second moment about ``e`` of the error coefficients under the mixture of the grid's
    posteriors with weights ``w`` (``[level, step]``): ``sum w (C + dx dx^T)``, with the
    factorisation per step of :func:`evidence_table`."""
    d = error_step_matrix(n_coef).toarray()
    dtd = d.T @ d
    v = h @ e - g
    n = e.size
    moment = np.zeros((n, n))
    for j, b in enumerate(sizes):
        wj = w[:, j]
        live = wj >= 1e-9
        if not live.any():
            continue
        levels, wl = sizes[live], wj[live]
        try:
            ki = sla.cho_solve(sla.cho_factor(h + dtd / b**2), np.eye(n))
        except np.linalg.LinAlgError:
            for a, wa in zip(levels, wl, strict=True):
                ca = sla.cho_factor(h + error_precision(n_coef, float(a), float(b)))
                dx = sla.cho_solve(ca, v) - e
                moment += wa * (sla.cho_solve(ca, np.eye(n)) + np.outer(dx, dx))
            continue
        z = ki @ v
        p = ki[:, :3]
        m_inv = np.linalg.inv(levels[:, None, None] ** 2 * np.eye(3) + p[:3])  # (k, 3, 3)
        x = z[None, :] - np.einsum('kab,b->ka', m_inv, z[:3]) @ p.T
        dx = x - e
        moment += wl.sum() * ki - p @ np.einsum('k,kab->ab', wl, m_inv) @ p.T
        moment += (dx * wl[:, None]).T @ dx
    return 0.5 * (moment + moment.T)
