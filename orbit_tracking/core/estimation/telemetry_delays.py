"""Whether a window estimates its telemetry's time-tag delays (issue 14).

A telemetry chain that tags its positions ``d_p`` seconds late (and its velocities ``d_v``)
gives position errors ``-d_p v(t)`` and velocity errors ``-d_v a(t)``: metres along track
for tens of milliseconds, and an error that turns with the vehicle. The slow error spline
``e`` of :mod:`~orbit_tracking.core.estimation.telemetry_block` can follow it only by giving
up most of the telemetry's position information, and its derivative then contradicts the
velocity rows wherever the vehicle accelerates. Two delay parameters describe it exactly.

:func:`delay_test` is the score test of
:mod:`~orbit_tracking.core.estimation.telemetry_velocity` for adding ``(d_p, d_v)`` to a
solved window (2 degrees of freedom at most, at ``telemetry_velocity_alpha``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.chi2 import chi2_isf
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.telemetry_velocity import (
    MIN_EPOCHS,
    ScoreTest,
    score_statistic,
)

if TYPE_CHECKING:
    from orbit_tracking.core.estimation.problem import Problem

__all__ = ['DelayTest', 'delay_test']

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DelayTest(ScoreTest):
    """The delay test on one target's telemetry residuals."""

    @property
    def delays(self) -> bool:
        """True when the window should estimate the delays."""
        return self.significant


def delay_test(
    prob: Problem, beta: FloatArray, obs: Observations, cfg: EstimatorConfig, t0: float, t1: float
) -> list[DelayTest]:
    """The score test for every telemetry block of ``prob`` without delays, at the
    solution ``beta``."""
    from orbit_tracking.core.estimation.knot_refinement import rebuild

    out = []
    for tb in prob.telemetry:
        use_p, use_v = prob.telemetry_use(tb)
        if tb.delays or min(int(use_p.sum()), int(use_v.sum())) < MIN_EPOCHS:
            continue
        aug, beta_a = rebuild(prob, beta, {}, {}, obs, cfg, t0, t1, tel_delays={tb.target: True})
        ta = next(b for b in aug.telemetry if b.target == tb.target)
        score = score_statistic(aug, beta_a, np.arange(ta.delay_offset, ta.delay_offset + 2))
        if score is None:
            continue
        stat, dof = score
        out.append(
            DelayTest(tb.target, stat, float(chi2_isf(cfg.telemetry_velocity_alpha, dof)), dof)
        )
    return out
