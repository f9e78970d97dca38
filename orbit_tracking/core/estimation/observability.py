"""What the window's data determine. Which station biases: unobservable ones are frozen
(kept as consider parameters) before and after the solve, and the estimates of the others
are reported with their covariance. And where the trajectory's linearised covariance
still describes its error (:func:`isotropic_spans`, by
:mod:`~orbit_tracking.core.estimation.linearity`)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.estimation.bspline import SplineTrajectory
from orbit_tracking.core.estimation.config import EstimatorConfig, Segment
from orbit_tracking.core.estimation.linearity import SAMPLE_S, nonlinear_spans
from orbit_tracking.core.estimation.problem import Problem
from orbit_tracking.core.estimation.results import (
    BiasEstimate,
    TargetSolution,
    state_covariance,
)

__all__ = ['bias_estimates', 'freeze_unobservable', 'isotropic_note', 'isotropic_spans']

FloatArray = NDArray[np.float64]


def freeze_unobservable(
    prob: Problem, beta: FloatArray, cov: FloatArray, cfg: EstimatorConfig, when: str
) -> bool:
    """Freeze at their priors the biases the data do not separate from the rest.

    A bias is observable when the measurements shrink its uncertainty well below its
    prior: posterior sigma at most ``bias_observability`` times the prior sigma. Those
    that fail are reset to the prior, get a vanishing prior sigma (so they no longer
    move) and are reported with the reason, including their strongest correlation.
    Returns True if any bias was frozen.
    """
    frozen = False
    o = prob.bias_offset
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    for q, bp in enumerate(prob.biases):
        if prob.bias_status[q] != 'estimated':
            continue
        ratio = sd[o + q] / bp.sigma
        if ratio <= cfg.bias_observability:
            continue
        corr = cov[o + q] / (sd[o + q] * sd)
        corr[o + q] = 0.0
        k = int(np.argmax(np.abs(corr)))
        what = _parameter_name(prob, k)
        prob.bias_status[q] = (
            f'unobservable ({when}): the data leave {ratio:.0%} of its prior sigma '
            f'(strongest correlation {corr[k]:+.3f} with {what}); held at its prior'
        )
        prob.bias_sigma[q] = bp.sigma * 1e-9
        beta[o + q] = bp.prior
        frozen = True
    return frozen


def _parameter_name(prob: Problem, k: int) -> str:
    if k >= prob.bias_offset:
        bp = prob.biases[k - prob.bias_offset]
        return f'bias {bp.station}/{bp.name}'
    for tb in prob.telemetry:
        if tb.offset <= k < tb.offset + tb.n_error:
            return f'telemetry error of target {tb.target}'
    for tid, off in prob.offsets.items():
        if off <= k < off + prob.trajs[tid].n_coef:
            return f'trajectory of target {tid}'
    return f'parameter {k}'


def bias_estimates(prob: Problem, beta: FloatArray, cov: FloatArray) -> tuple[BiasEstimate, ...]:
    o = prob.bias_offset
    out = []
    for q, bp in enumerate(prob.biases):
        status = prob.bias_status[q]
        estimated = status == 'estimated'
        value = float(beta[o + q])
        for side, limit in (('lower', bp.bounds[0]), ('upper', bp.bounds[1])):
            if estimated and math.isfinite(limit) and abs(value - limit) <= 1e-9 * bp.sigma:
                status = (
                    f'estimated, at its {side} bound {limit:g}: the data push beyond it, '
                    'so the sigma is conditional on the bound'
                )
        out.append(
            BiasEstimate(
                bp.station,
                bp.name,
                value,
                float(np.sqrt(max(cov[o + q, o + q], 0.0))) if estimated else float(bp.sigma),
                bp.prior,
                bp.sigma,
                status,
            )
        )
    return tuple(out)


def isotropic_spans(
    prob: Problem,
    tid: int,
    traj: SplineTrajectory,
    coef: FloatArray,
    cov: FloatArray,
    cfg: EstimatorConfig,
) -> tuple[Segment, ...]:
    """Where target ``tid``'s linearised covariance is no statement about its error
    (:func:`~orbit_tracking.core.estimation.linearity.nonlinear_spans`)."""
    if cfg.nonlinear_sigma <= 0.0 or not np.all(np.isfinite(cov)):
        return ()
    # the grid and the window's two ends: a state before the first grid time is tested
    # too (robustness draws had the first 0.2 s of a window off by 350 of its sigmas)
    grid = np.arange(math.ceil(traj.t0 / SAMPLE_S) * SAMPLE_S, traj.t1, SAMPLE_S)
    tt = np.unique(np.concatenate([[traj.t0], grid, [traj.t1]]))
    rows = []
    for b in prob.stations:
        if b.target != tid or b.time.size == 0:
            continue
        order = np.argsort(b.time, kind='stable')
        sig = np.where(b.valid, b.sigmas, np.inf)[order]
        rows.append((b.fields, b.time[order], sig, b.pose.take(order)))
    x = traj.states(coef, tt)
    return nonlinear_spans(tt, x, state_covariance(traj, cov, tt), rows, cfg.nonlinear_sigma)


def isotropic_note(
    targets: Mapping[int, TargetSolution], t0: float, t1: float, limit: float
) -> str:
    """The window message's note on the spans :func:`isotropic_spans` found."""
    msg = ''
    for tid, ts_ in targets.items():
        if ts_.isotropic_spans:
            lo, hi = ts_.isotropic_spans[0][0], ts_.isotropic_spans[-1][1]
            length = sum(b - a for a, b in ts_.isotropic_spans)
            msg += (
                f'; target {tid}: {length:.1f} s within {max(lo, t0):.1f}-{min(hi, t1):.1f} s '
                f'beyond the linear range (three sigma move a station value by more than '
                f'{limit:g} of its sigma to second order): covariance isotropic there'
            )
    return msg
