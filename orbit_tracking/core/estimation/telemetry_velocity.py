"""Which telemetry velocity error a window needs (issue 14): the derivative of the position
error, or an error of its own.

Fused telemetry is modelled as ``p(t) + e(t)`` and ``v(t) + e'(t)`` (one error source:
the velocity integrated into the position, or the position differentiated). Real
telemetry often has a velocity from another source than its position (GNSS Doppler, an
INS), or the two time-tagged differently, and then its velocity error is not ``e'``. The
velocity rows, ~100 times more precise than the position rows, then pull ``e'`` (and with
it the trajectory inside an incomplete segment) to an error that is not the position's.

:func:`velocity_error_test` is a score (Lagrange-multiplier) test at the solved window for
adding ``w``, a piecewise-linear velocity error of its own (knots every
``telemetry_velocity_error_spacing`` s): ``g^T S^-1 g`` with ``g = J_w^T r`` the gradient
of the whitened residuals along ``w`` and ``S = J_w^T J_w - C^T (J^T J)^-1 C``, ``C =
J^T J_w``, what of ``w`` the other parameters cannot take. Under the one-source model it is
chi-square with as many degrees of freedom as ``S`` has rank; above its
``1 - telemetry_velocity_alpha`` quantile the window is solved again with ``e' + w``.

A velocity error of its own is often correlated over seconds (an INS or a Doppler loop,
a Gauss-Markov error of a few seconds' time constant), which a ``w`` with knots 20 s apart
cannot follow: the rest stays in the velocity rows as white noise by the noise
re-estimation, and the ~100-times-more-precise velocity then makes the trajectory
over-confident by its integral. :func:`refine_velocity_error` asks the same question of
``w`` at half the spacing (the same score test, for the finer ``w`` with the solved one
mapped onto it), and halves while the residuals ask for it, down to
``telemetry_velocity_error_min_spacing``.

A test that does not reject ``e'`` alone does not prove it: in a short window, or one
whose telemetry an outage cut, a velocity error of a few centimetres per second of its own
hides in ``e'`` (a position drift of the same size moves the positions by less than their
noise), and the trajectory's velocity takes it while its covariance, conditional on
``e'`` alone, claims a tenth of it (robustness aircraft draw 97, a bias-and-drift
telemetry after an outage: 0.14 m/s off at 0.022 m/s). :func:`velocity_error_consider`
publishes what the data cannot rule out: the evidence (Laplace) of ``w`` with prior sigmas
over :data:`VELOCITY_ERROR_SIZES` times the telemetry velocity's white sigma (as the window
weighs its rows) against none, from the
same projected information ``S`` and gradient ``g`` as the test, and the second moment of
the mixture of their posteriors about the published solution (half the prior on ``e'``
alone), carried to every unknown by its regression on ``w`` (``-(J^T J)^-1 J^T J_w``). A
``w`` the data would show makes the mixture wide; one they exclude leaves it as it was.
The estimate is not changed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.chi2 import chi2_isf
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.scaling import scaled_solve
from orbit_tracking.core.estimation.telemetry_block import VELOCITY_ERROR_PRIOR

if TYPE_CHECKING:
    from orbit_tracking.core.estimation.problem import Problem
    from orbit_tracking.core.estimation.telemetry_block import TelemetryBlock

__all__ = [
    'VELOCITY_ERROR_SIZES',
    'ScoreTest',
    'refine_velocity_error',
    'VelocityErrorTest',
    'quadratic_score',
    'score_statistic',
    'velocity_error_consider',
    'velocity_error_test',
    'value_quantum',
    'w_mixture_moment',
]

FloatArray = NDArray[np.float64]

MIN_EPOCHS = 20
"""Telemetry velocity epochs a window needs before the test is made."""


@dataclass(frozen=True)
class ScoreTest:
    """A score test on one target's telemetry residuals: its statistic, the chi-square
    quantile it is held against and its degrees of freedom."""

    target: int
    statistic: float
    threshold: float
    dof: int

    @property
    def significant(self) -> bool:
        """True when the residuals ask for the parameters tested."""
        return self.statistic > self.threshold


@dataclass(frozen=True)
class VelocityErrorTest(ScoreTest):
    """The test on one target's telemetry velocity residuals for ``w``."""

    @property
    def separate(self) -> bool:
        """True when the velocity has an error of its own."""
        return self.significant


def _w_columns(tb: TelemetryBlock) -> NDArray[np.int_]:
    """The unknowns of block ``tb``'s separate velocity error ``w``."""
    assert tb.w_axis is not None
    o = tb.offset + 3 * tb.axis.n_coef
    return np.arange(o, o + 3 * tb.w_axis.n_coef)


def _w_score(aug: Problem, beta: FloatArray, tb: TelemetryBlock) -> tuple[float, int] | None:
    """:func:`score_statistic` for the separate velocity error ``w`` of block ``tb``."""
    return score_statistic(aug, beta, _w_columns(tb))


def _with_w(
    prob: Problem,
    beta: FloatArray,
    tb: TelemetryBlock,
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> tuple[Problem, FloatArray, TelemetryBlock] | None:
    """``prob`` with a separate velocity error ``w`` (at zero) added to block ``tb``, its
    start and its new block; None where ``tb`` has one already or too few velocity epochs
    (:data:`MIN_EPOCHS`) for the question."""
    from orbit_tracking.core.estimation.knot_refinement import rebuild

    if tb.w_axis is not None or int(prob.telemetry_use(tb)[1].sum()) < MIN_EPOCHS:
        return None
    aug, beta_a = rebuild(prob, beta, {}, {}, obs, cfg, t0, t1, {tb.target: True})
    return aug, beta_a, next(b for b in aug.telemetry if b.target == tb.target)


def velocity_error_test(
    prob: Problem,
    beta: FloatArray,
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> list[VelocityErrorTest]:
    """The score test of the module docstring for every telemetry block of ``prob`` modelled
    with ``e'`` only (no separate velocity error yet), at the solution ``beta``."""
    out = []
    for tb in prob.telemetry:
        augmented = _with_w(prob, beta, tb, obs, cfg, t0, t1)
        if augmented is None:
            continue
        aug, beta_a, ta = augmented
        score = _w_score(aug, beta_a, ta)
        if score is None:
            continue
        stat, dof = score
        out.append(
            VelocityErrorTest(
                tb.target, stat, float(chi2_isf(cfg.telemetry_velocity_alpha, dof)), dof
            )
        )
    return out


def refine_velocity_error(
    prob: Problem,
    beta: FloatArray,
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> tuple[list[ScoreTest], tuple[EstimatorConfig, Problem, FloatArray] | None]:
    """The score tests, for every separate velocity error ``w`` of ``prob`` (solved at
    ``beta``), of a ``w`` at half the spacing with the solved one mapped onto it; and, if
    one is significant (at ``telemetry_velocity_alpha``), ``cfg`` with the halved
    ``telemetry_velocity_error_spacing`` and the problem on it with its start (else None).
    The caller solves that problem and asks again."""
    from orbit_tracking.core.estimation.knot_refinement import rebuild

    spacing = cfg.telemetry_velocity_error_spacing / 2.0
    coarse = {tb.target: tb.w_axis.n_coef for tb in prob.telemetry if tb.w_axis is not None}
    if not coarse or spacing < cfg.telemetry_velocity_error_min_spacing * (1.0 - 1e-9):
        return [], None
    finer = replace(cfg, telemetry_velocity_error_spacing=spacing)
    aug, beta_a = rebuild(prob, beta, {}, {}, obs, finer, t0, t1)
    out: list[ScoreTest] = []
    for tb in aug.telemetry:
        if tb.w_axis is None or tb.target not in coarse:
            continue
        score = _w_score(aug, beta_a, tb)
        if score is None:
            continue
        # the finer w contains the solved one, along which the gradient is zero (it is
        # solved): the statistic is the test of the added directions alone, with their
        # degrees of freedom (the score test is invariant to how the block is spanned)
        stat, dof = score[0], score[1] - 3 * coarse[tb.target]
        if dof < 1:
            continue
        out.append(
            ScoreTest(tb.target, stat, float(chi2_isf(cfg.telemetry_velocity_alpha, dof)), dof)
        )
    return out, ((finer, aug, beta_a) if any(t.significant for t in out) else None)


def score_statistic(
    aug: Problem, beta: FloatArray, cols: NDArray[np.int_]
) -> tuple[float, int] | None:
    """The score statistic ``g^T S^+ g`` of the module docstring for the unknowns ``cols``
    of ``aug`` at ``beta`` (where they are zero), and its degrees of freedom (the rank of
    ``S``); None when the data do not determine them at all."""
    r, jac, _ = aug.evaluate(beta, True)
    assert jac is not None
    mask = np.zeros(aug.n, dtype=bool)
    mask[cols] = True
    jw = jac[:, np.flatnonzero(mask)].toarray()
    jo = jac[:, np.flatnonzero(~mask)]
    a = (jo.T @ jo).toarray()
    # Jacobi-scaled: the unknowns' scales span many decades (a telemetry level with a
    # prior of tens of metres beside stiff trajectory coefficients), and unscaled the
    # cut-off of the least-squares solve dropped directions at random (a frozen station
    # bias, which changes nothing, moved a statistic from 29 to 1.7)
    c = np.asarray(jo.T @ jw)
    s = jw.T @ jw - c.T @ scaled_solve(a, c, 1e-10, cholesky=False)[0]
    return quadratic_score(jw.T @ r, s)


def quadratic_score(
    g: FloatArray, s: FloatArray, rank: int | None = None
) -> tuple[float, int] | None:
    """``g^T S^+ g`` and the rank of ``S`` (the projected Gram matrix of the new unknowns'
    columns, ``g`` their products with the residuals): the pseudo-inverse on the
    eigen-directions above ``1e-9`` of the largest, at most the ``rank`` largest of them;
    None when there is none."""
    w, v = np.linalg.eigh(0.5 * (s + s.T))
    keep = w > 1e-9 * max(float(w.max()), 1e-300)
    if rank is not None and int(keep.sum()) > rank:
        keep &= np.arange(w.size) >= w.size - rank  # eigh sorts ascending
    if not keep.any():
        return None
    proj = v[:, keep].T @ g
    return float(np.sum(proj**2 / w[keep])), int(keep.sum())


VELOCITY_ERROR_SIZES = np.geomspace(0.1, 10.0, 9)
"""Prior sigmas of ``w`` whose evidence :func:`velocity_error_consider` weighs, in multiples
of the telemetry velocity's white sigma as the window weighs its rows (``TelemetryBlock.
noise``; the other half of the prior is on none)."""


def velocity_error_consider(
    prob: Problem,
    beta: FloatArray,
    cov: FloatArray,
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> tuple[FloatArray, dict[int, tuple[float, float, float]]]:
    """What to add to ``cov`` (the window's ``(J^T J)^-1`` at its solution ``beta``) for a
    separate velocity error of every telemetry block modelled with ``e'`` alone, as in the
    module docstring; and per target the posterior weight of "a ``w``", the largest
    ratio of a trajectory variance with the addition to without, and the step the
    telemetry velocity is rounded to (0 if none: :func:`value_quantum`, or if no value
    repeats; a rounded velocity gets, besides, a ``w`` of the slow part of that error for
    certain)."""
    extra = np.zeros_like(cov)
    notes: dict[int, tuple[float, float, float]] = {}
    for tb in prob.telemetry:
        augmented = _with_w(prob, beta, tb, obs, cfg, t0, t1)
        if augmented is None:
            continue
        aug, beta_a, ta = augmented
        cols = _w_columns(ta)
        if aug.n - cols.size != prob.n:
            continue
        r, jac, _ = aug.evaluate(beta_a, True)
        assert jac is not None
        mask = np.zeros(aug.n, dtype=bool)
        mask[cols] = True
        jw = jac[:, cols].toarray()
        c = np.asarray(jac.T @ jw)[~mask]  # (n, k): J^T J_w, without slicing J's columns
        gain = cov @ c  # the unknowns' regression on w, up to sign
        s0 = jw.T @ jw - c.T @ gain - np.eye(cols.size) / VELOCITY_ERROR_PRIOR**2
        lam, vec = np.linalg.eigh(0.5 * (s0 + s0.T))
        sizes = VELOCITY_ERROR_SIZES * float(tb.noise[1])
        g_w = vec.T @ (jw.T @ r)
        moment, p_w = w_mixture_moment(np.maximum(lam, 0.0), g_w, sizes)
        v_tel = tb.velocity[tb.valid_v][np.argsort(tb.time[tb.valid_v], kind='stable')]
        q = value_quantum(v_tel)
        slow = float(np.mean(np.diff(v_tel, axis=0) == 0.0)) if q > 0.0 else 0.0
        if slow > 0.0:
            # rounded values: an error of variance q^2 / 12, constant while the velocity
            # stays within one step (its slow part: the share of values that repeat), on
            # top of any error of the telemetry's own; certain, not weighed by the
            # residuals that hide it. The piecewise-linear w has half its coefficients'
            # variance midway between knots, so they get twice that (docs/ESTIMATOR.md)
            size = np.array([q * math.sqrt(slow / 6.0)])
            moment = moment + w_mixture_moment(np.maximum(lam, 0.0), g_w, size, 0.0)[0]
        root = gain @ vec
        add = root @ moment @ root.T
        add = 0.5 * (add + add.T)
        extra += add
        sl = slice(prob.offsets[tb.target], prob.offsets[tb.target] + prob.trajs[tb.target].n_coef)
        d0 = np.diag(cov)[sl]
        seen = d0 > 1e-12 * max(float(d0.max(initial=0.0)), 1e-300)  # not a pinned coefficient
        ratio = 1.0 + np.diag(add)[sl][seen] / d0[seen]
        notes[tb.target] = (p_w, float(np.max(ratio, initial=1.0)), q if slow > 0.0 else 0.0)
    return extra, notes


def w_mixture_moment(
    lam: FloatArray, g: FloatArray, sizes: FloatArray, p_none: float = 0.5
) -> tuple[FloatArray, float]:
    """Second moment about zero of ``w`` (in the eigenbasis of its projected information,
    eigenvalues ``lam`` >= 0, ``g`` the gradient there) under the mixture of "no ``w``"
    (prior ``p_none``) and a zero-mean ``w`` of each prior sigma of ``sizes`` (the rest of
    the prior, evenly), weighted by their evidence; and the posterior of "a ``w``".

    Against no ``w``, the log evidence of a prior sigma ``s`` is, for a model linear in
    ``w`` with the other unknowns' prior flat, ``g^T (S + I/s^2)^-1 g / 2 - log det(I +
    s^2 S) / 2`` (test_velocity_error_consider checks it against the Gaussian densities);
    each size's posterior is ``N((S + I/s^2)^-1 g, (S + I/s^2)^-1)``."""
    log_ev = np.array(
        [
            0.5 * float(np.sum(g**2 / (lam + 1.0 / sz**2)))
            - 0.5 * float(np.sum(np.log1p(sz**2 * lam)))
            for sz in sizes
        ]
    )
    none = math.log(p_none) if p_none > 0.0 else -math.inf
    logs = np.concatenate([[none], log_ev + math.log((1.0 - p_none) / sizes.size)])
    post = np.exp(logs - logs.max())
    post /= post.sum()
    moment = np.zeros((lam.size, lam.size))
    for p_k, sz in zip(post[1:], sizes, strict=True):
        inv = 1.0 / (lam + 1.0 / sz**2)
        w_hat = inv * g
        moment += p_k * (np.diag(inv) + np.outer(w_hat, w_hat))
    return moment, float(1.0 - post[0])


QUANTUM_MIN_VALUES = 20
"""Fewest values :func:`value_quantum` judges: rounding shows only over many of them."""


def value_quantum(values: FloatArray) -> float:
    """The step ``q`` the finite ``values`` were rounded to (every one an integer multiple
    of it, to 1e-6 of a step), the smallest gap between distinct values; 0 when they are
    not (or fewer than :data:`QUANTUM_MIN_VALUES`, or fewer than three distinct ones).

    Telemetry rounded to a step comparable to its noise (a velocity sent in 0.1 m/s) has an
    error that stays constant while the value stays within one step: on straight flight a
    bias of up to half a step for tens of seconds, which the residuals cannot show (the
    trajectory follows it) and which the white weighting of the rows would average away
    (robustness aircraft draw 1010: velocity 0.07 m/s off at 0.017 m/s sigmas for 20 s)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size < QUANTUM_MIN_VALUES:
        return 0.0
    u = np.unique(v)
    if u.size < 3:
        return 0.0
    gaps = np.diff(u)
    q = float(gaps.min())
    if not q > 1e-12 * max(float(np.max(np.abs(u))), 1.0):
        return 0.0
    k = v / q
    return q if float(np.max(np.abs(k - np.round(k)))) <= 1e-6 else 0.0
