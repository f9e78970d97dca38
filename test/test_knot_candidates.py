"""The measurement-driven knot test looks inside long knot intervals, not only at their
midpoints (issue 14: an axis the rough trajectory gave no knot kept a 7-sigma misfit
where an aircraft's manoeuvre ramp lay 13 s off the interval's midpoint)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.stats import chi2

from orbit_tracking.core.estimation import knot_refinement
from orbit_tracking.core.estimation.bspline import SplineAxis
from orbit_tracking.core.estimation.knot_refinement import CANDIDATE_SPACING, _knot_scores


def _scores(bump_at: float, amplitude: float) -> list[tuple[float, float, int]]:
    rng = np.random.default_rng(7)
    sigma = 0.1
    ts = np.arange(0.0, 60.0, 0.05)
    truth = 3.0 + 0.2 * ts - 0.01 * ts**2 + amplitude * np.exp(-(((ts - bump_at) / 1.5) ** 2))
    y = truth + sigma * rng.standard_normal(ts.size)
    ax = SplineAxis.from_interior(np.zeros(0), 0.0, 60.0, 4)  # one polynomial piece
    jac = sp.csr_matrix(ax.design(ts, 0)) / sigma
    beta = np.linalg.lstsq(jac.toarray(), y / sigma, rcond=None)[0]
    r = y / sigma - jac @ beta
    cov = np.linalg.inv((jac.T @ jac).toarray())
    up = np.full(ts.size, 1.0 / sigma)
    return _knot_scores(ax, ts, up, np.zeros(ts.size), np.arange(ts.size), r, jac, cov, 0.05)


def test_a_local_misfit_far_from_the_midpoint_gets_a_knot_there(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ((tau, score, tried),) = _scores(47.0, 0.5)
    assert tried == int(60.0 / CANDIDATE_SPACING) + 1
    assert abs(tau - 47.0) <= 3.0 * CANDIDATE_SPACING
    assert score > chi2.isf(0.01 / tried, 1)
    # the midpoint alone (the test before) does not see it
    monkeypatch.setattr(knot_refinement, 'CANDIDATE_SPACING', 1e9)
    ((tau, score, tried),) = _scores(47.0, 0.5)
    assert (tau, tried) == (30.0, 1)
    assert score < chi2.isf(0.01, 1)


def test_a_polynomial_asks_for_no_knot() -> None:
    ((_, score, tried),) = _scores(47.0, 0.0)
    assert score < chi2.isf(0.01 / tried, 1)
