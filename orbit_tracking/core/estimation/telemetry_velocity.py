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
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.chi2 import chi2_isf
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.scaling import scaled_solve

if TYPE_CHECKING:
    from orbit_tracking.core.estimation.problem import Problem
    from orbit_tracking.core.estimation.telemetry_block import TelemetryBlock

__all__ = [
    'ScoreTest',
    'refine_velocity_error',
    'VelocityErrorTest',
    'quadratic_score',
    'score_statistic',
    'velocity_error_test',
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


def _w_score(aug: Problem, beta: FloatArray, tb: TelemetryBlock) -> tuple[float, int] | None:
    """:func:`score_statistic` for the separate velocity error ``w`` of block ``tb``."""
    assert tb.w_axis is not None
    o = tb.offset + 3 * tb.axis.n_coef
    return score_statistic(aug, beta, np.arange(o, o + 3 * tb.w_axis.n_coef))


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
    from orbit_tracking.core.estimation.knot_refinement import rebuild

    out = []
    for tb in prob.telemetry:
        if tb.w_axis is not None or int(prob.telemetry_use(tb)[1].sum()) < MIN_EPOCHS:
            continue
        aug, beta_a = rebuild(prob, beta, {}, {}, obs, cfg, t0, t1, {tb.target: True})
        ta = next(b for b in aug.telemetry if b.target == tb.target)
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
