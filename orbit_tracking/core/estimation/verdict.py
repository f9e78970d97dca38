"""When a window's solution is a success: the one definition the node's diagnostics, the
offline summary and the main job's summary all report.

A window is a **success** when

* its solve **converged**: the Gauss-Newton step from the solution would lower the cost by
  at most ``convergence_decrement`` (:func:`~orbit_tracking.core.estimation.gauss_newton.
  decrement`), a test a stalled step cannot pass. A solve that ended (iteration limit, or
  no step lowering the cost) with that step still promising ``d`` up to
  ``max_unconverged_decrement`` lies within about ``sqrt(d)`` standard deviations of the
  optimum along the worst direction (typically one the data hardly determine, at a window
  end inside an incomplete segment, where the quadratic model overshoots and the solve
  crawls): it counts, with its covariance scaled by ``1 + d`` so that the published sigma
  covers that distance;
* its fit is **consistent** with the measurement model: the chi-square per degree of
  freedom of the rows kept is at most :func:`chi2_limit` (``max_chi2_dof``, or the
  ``1 + 5 sqrt(2 / dof)`` a consistent fit stays under when it has few degrees of freedom);
* its normal matrix is **not singular**, its states and covariance are **finite**, and the
  residual gate did **not refuse** (it would have rejected more than 5 % of a family of rows:
  the model does not fit the data).

Between ``1 + 3 sqrt(2 / dof)`` (a significant excess) and the limit the covariance is
scaled by the chi-square per degree of freedom (the misfit), as a fit with an unknown
common variance factor reports it. A window that fails is not published as final: the node
withholds it and counts it, the offline trajectory leaves it out (docs/ESTIMATOR.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ['Verdict', 'chi2_limit', 'judge']


def chi2_limit(dof: int, max_chi2_dof: float) -> float:
    """Largest chi-square per degree of freedom of a consistent fit: ``max_chi2_dof``, or
    ``1 + 5 sqrt(2 / dof)`` when that is larger (a fit with few degrees of freedom)."""
    return max(max_chi2_dof, 1.0 + 5.0 * math.sqrt(2.0 / max(dof, 1)))


@dataclass(frozen=True)
class Verdict:
    """Outcome of :func:`judge`.

    Attributes
    ----------
    success : bool
    reasons : tuple of str
        Why not, one sentence each (empty on success).
    covariance_scale : float
        Factor the covariance is published with (1, or the chi-square per degree of freedom
        when it exceeds 1 significantly).
    """

    success: bool
    reasons: tuple[str, ...]
    covariance_scale: float


def judge(
    converged: bool,
    chi2_dof: float,
    dof: int,
    max_chi2_dof: float,
    singular: bool = False,
    gate_refused: float = 0.0,
    finite: bool = True,
    decrement: float = math.inf,
    max_decrement: float = 0.0,
) -> Verdict:
    """The verdict on one window (see the module docstring)."""
    reasons = []
    near = 1.0  # a solve that ended near its optimum: its covariance covers the distance
    if not converged:
        if math.isfinite(decrement) and decrement <= max_decrement:
            near = 1.0 + decrement
        else:
            reasons.append('not converged')
    limit = chi2_limit(dof, max_chi2_dof)
    if not chi2_dof <= limit:
        reasons.append(f'chi2/dof {chi2_dof:.3g} above {limit:.3g}: the fit is inconsistent')
    if singular:
        reasons.append('normal matrix singular')
    if gate_refused:
        reasons.append(f'the residual gate would reject {gate_refused:.0%} of a family of rows')
    if not finite:
        reasons.append('states or covariance not finite')
    significant = 1.0 + 3.0 * math.sqrt(2.0 / max(dof, 1))
    scale = chi2_dof if math.isfinite(chi2_dof) and chi2_dof > significant else 1.0
    return Verdict(not reasons, tuple(reasons), scale * near)
