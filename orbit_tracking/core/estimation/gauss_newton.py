"""Gauss-Newton (seed 000, eq. 7) on a window's :class:`.problem.Problem`, the robust
warm-up and residual gate against gross errors and outliers, the re-estimated noise levels
(the priors' sizes: :mod:`.priors`) and the covariance (frozen biases as consider ones).

Bad rows are decided in three steps (:func:`solve`):

1. units whose whitened residual at the start is absurd (beyond :data:`ABSURD_SIGMA`, or
   not finite) are gated: no sum of squares can hold them;
2. a robust warm-up (:func:`robust_warm_up`, iteratively reweighted Gauss-Newton on a
   Huber or Cauchy loss) fits the rest without letting a wild row pull harder than one
   at the gross-error limit, and the units beyond that limit (:data:`GROSS_FACTOR` x
   ``gate_sigma`` of the robust scale) are gated. A plain first fit instead follows a
   wild row until most rows look wrong, and the gate refuses;
3. plain weighted least squares on the rows kept, gated on its own residuals at
   ``gate_sigma`` and solved again until the gate stops changing. The solution and the
   covariance come from this step only: no robust weight reaches them.

On a window without gross errors step 2 takes exactly the steps of the plain solve.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.estimation.config import EstimationError, EstimatorConfig
from orbit_tracking.core.estimation.priors import reestimate_priors
from orbit_tracking.core.estimation.problem import ROBUST_KINDS, GateKey, Problem
from orbit_tracking.core.estimation.scaling import jacobi_scaled, normal_matrix, scaled_solve
from orbit_tracking.core.estimation.telemetry_noise import reestimate_telemetry_noise
from orbit_tracking.core.models.measurements import residual

__all__ = [
    'ABSURD_SIGMA',
    'DAMPING',
    'LM_LAMBDAS',
    'NOISE_MIN_VALUES',
    'NOISE_WHITE_LAG1',
    'decrement',
    'reestimate_station_noise',
    'GATE_MAX_FRACTION',
    'GROSS_FACTOR',
    'GnOutcome',
    'covariance',
    'gate_limits',
    'gate_residuals',
    'gauss_newton',
    'robust_warm_up',
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
    decrement: float = 0.0
    """What the Gauss-Newton step from ``beta`` would still lower the cost by."""


DAMPING = 1e-10
"""Relative (Jacobi-scaled) damping of the normal matrix: directions the data do not
determine to better than 1e-10 of the best-determined one stay where they are instead of
running away (Levenberg-Marquardt with a fixed, tiny lambda)."""


def _normal_solve(n: FloatArray, g: FloatArray, lam: float = 0.0) -> tuple[FloatArray, bool]:
    """Step ``(N + lam D) step = g`` on the Jacobi-scaled normal matrix (``D`` its
    diagonal; ``lam = 0`` is the Gauss-Newton step with :data:`DAMPING`), and whether
    Cholesky succeeded."""
    return scaled_solve(n, g, DAMPING + lam)


LM_LAMBDAS = tuple(10.0**k for k in range(-6, 9))
"""Levenberg-Marquardt damping tried, in turn, when the Gauss-Newton step raises the cost
(relative to the Jacobi-scaled normal matrix, whose diagonal is 1): from a nudge to a
short steepest-descent step."""


def _free(prob: Problem, beta: FloatArray, step: FloatArray) -> NDArray[np.bool_]:
    """Parameters free to move: all but the biases held at a bound by this step."""
    free = np.ones(beta.size, dtype=bool)
    if prob.biases:
        sl = slice(prob.bias_offset, prob.bias_offset + len(prob.biases))
        b, s = beta[sl], step[sl]
        free[sl] = ~(((b <= prob.bias_lower) & (s < 0)) | ((b >= prob.bias_upper) & (s > 0)))
    return free


def _gn_step(
    prob: Problem, beta: FloatArray, n: FloatArray, g: FloatArray
) -> tuple[FloatArray, float]:
    """The Gauss-Newton step at ``beta`` and its :func:`decrement`."""
    step, _ = _normal_solve(n, g)
    free = _free(prob, beta, step)
    if free.all():
        return step, max(float(g @ step), 0.0)
    inner = np.zeros_like(step)
    inner[free], _ = _normal_solve(n[np.ix_(free, free)], g[free])
    return step, max(float(g @ inner), 0.0)


def decrement(prob: Problem, beta: FloatArray, n: FloatArray, g: FloatArray) -> float:
    """Predicted decrease of the cost by the full Gauss-Newton step at ``beta``:
    ``g^T N^-1 g`` over the parameters free to move (a bias held at its bound by the step
    is left out). The step moves the solution by about ``sqrt`` of it in units of its own
    standard deviation, so it tells a solution that cannot improve from one that merely
    found no step that lowers the cost."""
    return _gn_step(prob, beta, n, g)[1]


def _damped_step(
    prob: Problem,
    beta: FloatArray,
    n: FloatArray,
    g: FloatArray,
    gn_step: FloatArray,
    lam: float,
    cost: float,
    cost_of: Callable[[FloatArray], float],
) -> tuple[FloatArray | None, float, float, int]:
    """One Levenberg-Marquardt step (Marquardt's schedule): from damping ``lam`` (0 = the
    Gauss-Newton step ``gn_step``), damping ten times more while the cost rises, up to the
    last of :data:`LM_LAMBDAS`. Returns the accepted point (None if no step lowers the
    cost), its cost, the damping to start the next iteration with (a tenth of the one that
    worked; 0 below the first of :data:`LM_LAMBDAS`) and the damped steps tried."""
    tried = 0
    while True:
        step = gn_step if lam == 0.0 else _normal_solve(n, g, lam)[0]
        trial = prob.project(beta + step)
        c_new = cost_of(trial)
        if c_new <= cost:
            nxt = lam / 10.0 if lam / 10.0 >= LM_LAMBDAS[0] else 0.0
            return trial, c_new, nxt, tried
        lam = LM_LAMBDAS[0] if lam == 0.0 else lam * 10.0
        if lam > LM_LAMBDAS[-1]:
            return None, cost, 0.0, tried
        tried += 1


def gauss_newton(prob: Problem, beta: FloatArray, cfg: EstimatorConfig) -> GnOutcome:
    """Gauss-Newton (seed 000, eq. 7) with Levenberg-Marquardt steps when a plain step
    raises the cost.

    Each iteration takes the Gauss-Newton step at the current point; if the cost rises it
    damps the step ten times more until the cost falls (:func:`_damped_step`: a trust
    region that shrinks toward a short gradient step, better than halving a step that
    points the wrong way in an ill-conditioned valley), and starts the next iteration
    from a tenth of that damping. It has *converged* when the Gauss-Newton step from the
    current point would lower the cost by at most ``cfg.convergence_decrement``
    (:func:`decrement`: the solution would move by less than its square root of a
    standard deviation), checked at every point, never inferred from a small step. When
    no damped step lowers the cost either it has converged only if that test holds;
    otherwise the outcome says it stalled.
    """
    r, jac, _ = prob.evaluate(beta, True)
    cost = float(r @ r)
    tried = 0
    lam = 0.0
    for it in range(1, cfg.max_iterations + 1):
        assert jac is not None
        n = normal_matrix(jac)
        g = jac.T @ r
        step, dec = _gn_step(prob, beta, n, g)
        if dec <= cfg.convergence_decrement:
            return GnOutcome(beta, cost, it - 1, tried, True, 'converged', dec)
        trial, _, lam, k = _damped_step(prob, beta, n, g, step, lam, cost, prob.cost)
        tried += k
        if trial is None:
            return GnOutcome(
                beta,
                cost,
                it,
                tried,
                False,
                f'stalled: no step lowers the cost, the Gauss-Newton step would lower it by '
                f'{dec:.3g}',
                dec,
            )
        beta = trial
        r, jac, _ = prob.evaluate(beta, True)
        cost = float(r @ r)
    assert jac is not None
    n = normal_matrix(jac)
    dec = decrement(prob, beta, n, jac.T @ r)
    if dec <= cfg.convergence_decrement:
        return GnOutcome(beta, cost, cfg.max_iterations, tried, True, 'converged', dec)
    return GnOutcome(
        beta,
        cost,
        cfg.max_iterations,
        tried,
        False,
        f'iteration limit: the Gauss-Newton step would still lower the cost by {dec:.3g}',
        dec,
    )


GATE_MAX_FRACTION = 0.05
"""The residual gate rejects outliers, not the data: if it would reject more than this
fraction of the station values, or of the telemetry or fix epochs, the model itself does
not fit (e.g. unmodelled systematic errors), nothing is gated and the estimate says so."""

GROSS_FACTOR = 4.0
"""A whitened residual beyond ``GROSS_FACTOR * gate_sigma`` (20 by default) is a gross
error. The robust warm-up gates only those and leaves the ordinary outliers to the plain
fit's gate, as without the warm-up: its fit runs on the rough knots, before the knot
test, and on 46 clean 20 s windows its residuals reached 7.7 robust sigmas on station
values and 9.4 on telemetry velocity, model error that the knot test removes later.
Telemetry epochs are gated only beyond this limit at all: their noise level is itself an
estimate, their error spline coarse until the knot test refines it, and clean telemetry
velocity residuals reached 5.8 sigma of the re-estimated noise in the plain solves."""

ABSURD_SIGMA = 1e10
"""A whitened residual beyond this (or not finite) is no measurement error any model
explains: the row is always gated, whatever the gate's setting, even when the gate
refuses (it still counts toward :data:`GATE_MAX_FRACTION`, so a window made of such rows
fails). Far below the square root of the largest double, so the squares of the rows kept
add up without overflow."""


def gate_limits(gate: float) -> dict[str, float]:
    """Whitened-residual limit of the plain gate for every kind of row: ``gate`` for
    station values and fixes, ``GROSS_FACTOR * gate`` for telemetry epochs."""
    return {
        kind: gate * (GROSS_FACTOR if kind.startswith('telemetry') else 1.0)
        for kind in ROBUST_KINDS
    }


def gate_residuals(prob: Problem, beta: FloatArray, limits: Mapping[str, float]) -> bool:
    """Mark the units (station values; telemetry and fix epochs) whose whitened residual
    exceeds the limit of their kind (``limits``, e.g. :func:`gate_limits`), and every
    unit beyond :data:`ABSURD_SIGMA`; True if any mark changed. Decided afresh on every
    call; if more than :data:`GATE_MAX_FRACTION` of a family would go, only the absurd
    units are marked and ``prob.gate_refused`` holds that fraction."""
    marks: dict[GateKey, tuple[NDArray[np.bool_], NDArray[np.bool_]]] = {}
    n_rows: Counter[str] = Counter()
    n_bad: Counter[str] = Counter()
    with np.errstate(invalid='ignore'):
        for key, kind, r, valid in prob.gate_units(beta):
            a = np.abs(r)
            absurd = valid & ~(a <= ABSURD_SIGMA)
            bad = valid & ~absurd & (a > limits[kind])
            family = 'telemetry' if kind.startswith('telemetry') else kind
            n_rows[family] += int(np.count_nonzero(valid))
            n_bad[family] += int(np.count_nonzero(bad | absurd))
            marks[key] = (bad, absurd)
    worst = max((n_bad[f] / n for f, n in n_rows.items() if n), default=0.0)
    refused = worst > GATE_MAX_FRACTION
    prob.gate_refused = worst if refused else 0.0
    changed = False
    for key, (bad, absurd) in marks.items():
        new = absurd if refused else bad | absurd
        old = prob.gated.get(key)
        if (old is None and new.any()) or (old is not None and not np.array_equal(old, new)):
            changed = True
        prob.gated[key] = new
    return changed


NOISE_MIN_VALUES = 30
"""A station field's noise level is re-estimated from at least this many residuals."""

NOISE_WHITE_LAG1 = 0.5
"""... and only when their lag-1 autocorrelation is below this: noise larger than declared
is white, a model that does not follow the trajectory leaves residuals that run in the same
direction for many epochs (those must show as a misfit, not be absorbed into a sigma)."""


def reestimate_station_noise(prob: Problem, beta: FloatArray) -> bool:
    """Per station and field, the factor its declared sigmas are used with: the robust
    scale of its whitened residuals (rows kept; 1.4826 x their median absolute value, which
    a few gross errors do not move: a wild value must be gated, never absorbed into a
    sigma) when that is significantly above 1 (its square beyond ``1 + 7 / sqrt(n)``, three
    standard deviations of that estimate for normal residuals) and the residuals are white
    (lag-1 autocorrelation of the residuals clipped at 3 robust scales below
    :data:`NOISE_WHITE_LAG1`); else 1. Never below the declared sigma. True if a factor
    changed by more than 5 %."""
    changed = False
    for bi, b in enumerate(prob.stations):
        pred, _, _ = prob.predict_block(bi, beta)
        with np.errstate(over='ignore', invalid='ignore'):
            r = residual(b.fields, np.nan_to_num(b.values), pred) / b.declared
        use = b.valid & ~prob.gated.get(bi, np.zeros_like(b.valid))
        order = np.argsort(b.time, kind='stable')
        for j in range(len(b.fields)):
            rj = r[order, j][use[order, j]]
            n = rj.size
            new = 1.0
            if n >= NOISE_MIN_VALUES:
                scale = 1.4826 * float(np.median(np.abs(rj)))
                if scale * scale > 1.0 + 7.0 / math.sqrt(n):
                    c = np.clip(rj, -3.0 * scale, 3.0 * scale)
                    lag1 = float(c[1:] @ c[:-1]) / float(c @ c)
                    if lag1 < NOISE_WHITE_LAG1:
                        new = scale
            if abs(new - b.factor[j]) > 0.05 * b.factor[j]:
                changed = True
                b.factor[j] = new
        b.sigmas = b.declared * b.factor[None, :]
    return changed


# ---------------------------------------------------------------------------------------
# the robust warm-up


def _kind_scales(r: FloatArray, kinds: NDArray[np.int_]) -> FloatArray:
    """Robust scale of the whitened residuals of each kind of measurement row: 1.4826 x
    the median absolute residual (the sigma of a normal sample, unmoved by a few gross
    errors), never below 1 (the stated sigmas). A rough start, far from every row, gets a
    scale that large, so the loss does not single out rows before the fit is good."""
    out = np.ones(len(ROBUST_KINDS))
    for k in range(len(ROBUST_KINDS)):
        a = np.abs(r[kinds == k])
        if a.size:
            out[k] = max(1.0, 1.4826 * float(np.median(a)))
    return out


def _robust_terms(
    r: FloatArray, kinds: NDArray[np.int_], scales: FloatArray, loss: str, c: float
) -> tuple[FloatArray, float, float]:
    """IRLS weights of the rows, the robust cost ``sum rho(r)`` and the part of it from
    rows at full weight.

    With ``b = c s`` (``s`` the robust scale of the row's kind): Huber
    ``rho = r^2`` for ``|r| <= b`` and ``2 b |r| - b^2`` beyond (weight ``b / |r|``);
    Cauchy ``rho = b^2 log(1 + (r/b)^2)`` (weight ``1 / (1 + (r/b)^2)``). Rows that are not
    measurements (priors, constraints) keep ``r^2`` and weight 1. Everything stays finite
    for any finite residual (no ``r^2`` of a gross error is formed)."""
    meas = kinds >= 0
    bound = c * scales[np.where(meas, kinds, 0)]
    a = np.abs(r)
    inside = ~meas | (a <= bound)
    if loss == 'huber' and inside.all():  # least squares, summed as Gauss-Newton does
        cost = float(r @ r)
        return np.ones_like(r), cost, cost
    sq = np.where(inside, r, 0.0) ** 2
    if loss == 'huber':
        w = np.where(inside, 1.0, bound / np.where(inside, 1.0, a))
        rho = np.where(inside, sq, 2.0 * bound * a - bound * bound)
    else:  # cauchy: log1p(u^2) = 2 log(u) + log1p(u^-2), without squaring a large u
        u = a / bound
        big = u > 1e8
        ub = np.where(big, 1.0, u)
        w = np.where(meas, np.where(big, 0.0, 1.0 / (1.0 + ub * ub)), 1.0)
        logt = np.where(big, 2.0 * np.log(np.where(big, u, 1.0)), np.log1p(ub * ub))
        rho = np.where(meas, bound * bound * logt, r * r)
        inside = ~meas
    return w, float(np.sum(rho)), float(np.sum(np.where(inside, sq, 0.0)))


def robust_warm_up(
    prob: Problem, beta: FloatArray, cfg: EstimatorConfig
) -> tuple[GnOutcome, dict[str, float], int]:
    """Gauss-Newton on the robust loss ``cfg.robust_loss`` (iteratively reweighted).

    Units whose whitened residual at ``beta`` is absurd (:data:`ABSURD_SIGMA`) are gated
    first. Each iteration then takes the robust scale of every kind of measurement row
    (:func:`_kind_scales`), weighs the rows by the loss, solves the weighted normal
    equations ``J^T W J step = J^T W r`` (a descent direction of the robust cost) and
    takes the plain solve's steps on that cost (Gauss-Newton, then Levenberg-Marquardt
    damping while the cost rises). While a row is below full weight it stops when an
    accepted step lowers the cost by less than ``tolerance`` times the part of it from rows
    at full weight, so that the large, nearly constant cost of a gross error does not end it
    early; with every row at full weight it is the plain solve, and stops by its test
    (:func:`decrement`).

    A gross error pulls no harder than a residual of ``c`` robust sigmas (Huber; ``c`` is
    ``robust_scale``, default ``GROSS_FACTOR * gate_sigma``) or hardly at all (Cauchy).
    With the default Huber loss every row within ``c`` is plain least squares: on a
    window whose rows all stay within it this *is* the plain Gauss-Newton solve, step for
    step.

    Returns the outcome (its ``cost`` is the plain sum of squares), the robust scale of
    each kind of row at its solution and the number of rows below full weight there.
    """
    loss = cfg.robust_loss
    c = cfg.robust_scale if cfg.robust_scale is not None else GROSS_FACTOR * cfg.gate_sigma
    r, jac, tags = prob.evaluate(beta, True)
    with np.errstate(invalid='ignore'):
        absurd = not np.all(np.abs(r) <= ABSURD_SIGMA)
    if absurd:
        gate_residuals(prob, beta, dict.fromkeys(ROBUST_KINDS, math.inf))
        r, jac, tags = prob.evaluate(beta, True)
    kinds = prob.row_kinds(tags)
    scales = _kind_scales(r, kinds)
    w, cost, full = _robust_terms(r, kinds, scales, loss, c)
    halvings = iterations = 0
    lam = 0.0
    message, converged = 'iteration limit', False

    def robust_cost(b: FloatArray) -> float:
        return _robust_terms(prob.evaluate(b, False)[0], kinds, scales, loss, c)[1]

    while iterations < cfg.max_iterations:
        assert jac is not None
        plain = bool(np.all(w == 1.0))
        if plain:
            n, g = normal_matrix(jac), jac.T @ r
            step, dec = _gn_step(prob, beta, n, g)
            if dec <= cfg.convergence_decrement:
                message, converged = 'converged', True  # the plain solve's own test
                break
        else:
            jw = sp.diags(np.sqrt(w)) @ jac
            n, g = normal_matrix(jw), jac.T @ (w * r)
            step = _normal_solve(n, g)[0]
        iterations += 1
        # the plain solve's steps (gauss_newton), on the robust cost
        trial, c_new, lam, k = _damped_step(prob, beta, n, g, step, lam, cost, robust_cost)
        halvings += k
        if trial is None:
            message = 'stalled: no step lowers the robust cost'
            converged = not plain  # a plain stall is judged by gauss_newton's test
            break
        change = cost - c_new
        beta = trial
        r, jac, _ = prob.evaluate(beta, True)
        scales = _kind_scales(r, kinds)
        w, cost, full = _robust_terms(r, kinds, scales, loss, c)
        if not plain and change <= cfg.tolerance * max(full, 1.0):
            message, converged = 'converged', True
            break
    dec = math.nan
    if np.all(w == 1.0):
        assert jac is not None
        dec = decrement(prob, beta, normal_matrix(jac), jac.T @ r)
        if not converged and message == 'iteration limit':
            converged = dec <= cfg.convergence_decrement
    out = GnOutcome(beta, float(r @ r), iterations, halvings, converged, message, dec)
    return out, dict(zip(ROBUST_KINDS, scales.tolist(), strict=True)), int(np.sum(w < 1.0))


def solve(
    prob: Problem,
    beta: FloatArray,
    cfg: EstimatorConfig,
    warm_up: bool = True,
    check: Callable[[GnOutcome], None] | None = None,
) -> tuple[GnOutcome, int, int]:
    """Gauss-Newton, then telemetry noise re-estimation and residual gating, repeated
    until neither changes (at most ``gate_rounds`` times).

    ``warm_up`` (a problem whose gates are not decided yet): absurd rows are gated first
    and, unless ``robust_loss`` is ``none`` or the gate is off, the robust warm-up
    (:func:`robust_warm_up`) fits the window and the units beyond ``GROSS_FACTOR *
    gate_sigma`` of its robust scale are gated as gross errors; the plain solve then
    starts from the same ``beta`` as the warm-up did, so that it takes exactly the steps
    it would have taken had those rows never arrived (from the warm-up's solution it would
    end within the Gauss-Newton tolerance of that, ~1 mm, instead). When the warm-up left
    every row at full weight it was the plain solve already and is taken as such. Without
    ``warm_up`` (a problem that carries the gates of an earlier solve, e.g. on refined
    knots) the plain solve starts at once.

    ``check`` is called with the first plain outcome, before the noise and gate rounds; it
    may raise to end the solve there (the estimator's early give-up at an unanchored edge
    segment: the rounds would crawl on for as long again).
    """
    iterations = halvings = 0
    out: GnOutcome | None = None
    if warm_up and cfg.robust_loss != 'none' and cfg.gate_sigma > 0.0:
        first, scales, downweighted = robust_warm_up(prob, beta, cfg)
        iterations, halvings = first.iterations, first.halvings
        gross = GROSS_FACTOR * cfg.gate_sigma
        c = cfg.robust_scale if cfg.robust_scale is not None else gross
        gated = False
        if downweighted or c > gross:  # else no row lies beyond the gross limit either
            gated = gate_residuals(prob, first.beta, {k: gross * v for k, v in scales.items()})
        if not downweighted:
            out = first
        elif not gated:
            beta = first.beta
    elif warm_up:
        gate_residuals(prob, beta, dict.fromkeys(ROBUST_KINDS, math.inf))
    if out is None:
        out = gauss_newton(prob, beta, cfg)
        iterations += out.iterations
        halvings += out.halvings
    if check is not None:
        check(out)
    for _ in range(max(cfg.gate_rounds, 1)):
        changed = False
        if cfg.estimate_telemetry_noise and prob.telemetry:
            changed |= reestimate_telemetry_noise(prob, out.beta, cfg.knots.base_spacing)
        changed |= reestimate_priors(prob, out.beta, cfg)
        if cfg.estimate_station_noise:
            changed |= reestimate_station_noise(prob, out.beta)
        if cfg.gate_sigma > 0.0:
            changed |= gate_residuals(prob, out.beta, gate_limits(cfg.gate_sigma))
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
    n = normal_matrix(jac)
    ns, d = jacobi_scaled(n)
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
