"""Issue 14: the prior of the telemetry error spline is a random walk of its
coefficients with two sizes, one for its level at the window's start and one for its
steps from one coefficient to the next, so that a large but slow error (a bias, a drift)
does not also allow a fast one."""

from __future__ import annotations

import numpy as np
import pytest

from orbit_tracking.core.data.tables import TargetStates
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.priors import _component
from orbit_tracking.core.estimation.telemetry_block import (
    DELAY_PRIOR_S,
    VELOCITY_ERROR_PRIOR,
    error_prior_matrix,
    error_step_matrix,
    telemetry_block,
)


def _block(separate: bool, delays: bool):
    t = np.linspace(0.0, 60.0, 121)
    tel = TargetStates(
        0,
        t,
        np.zeros((t.size, 3)),
        np.zeros((t.size, 3)),
        np.full(t.size, 2.0),
        np.full(t.size, 0.1),
    )
    axis = SplineAxis.from_interior(np.arange(10.0, 60.0, 10.0), 0.0, 60.0, 4)
    traj = SplineTrajectory((axis, axis, axis), np.zeros(3), np.eye(3))
    e_axis = SplineAxis.from_interior([15.0, 30.0, 45.0], 0.0, 60.0, 3)
    w_axis = SplineAxis.from_interior([20.0, 40.0], 0.0, 60.0, 1) if separate else None
    tb = telemetry_block(0, tel, traj, e_axis, 0, w_axis, delays)
    tb.prior_sigma = (3.0, 0.5)
    return tb


@pytest.mark.parametrize(('separate', 'delays'), [(False, False), (True, True)])
def test_the_prior_is_a_random_walk_of_the_coefficients(separate, delays):
    tb = _block(separate, delays)
    m = error_prior_matrix(tb).toarray()
    n_e = 3 * tb.axis.n_coef
    assert m.shape == (tb.n_error, tb.n_error)
    d = error_step_matrix(tb.axis.n_coef).toarray()
    assert d.shape == (n_e - 3, n_e)
    # a step is one coefficient minus its predecessor on the same axis
    x = np.arange(n_e, dtype=float) ** 2
    assert np.allclose((d @ x).reshape(-1, 3), np.diff(x.reshape(-1, 3), axis=0))
    want = np.vstack([np.eye(3, n_e) / 3.0, d / 0.5])
    assert np.allclose(m[:n_e, :n_e], want)
    assert np.allclose(m[:n_e, n_e:], 0.0) and np.allclose(m[n_e:, :n_e], 0.0)
    rest = np.diag(m)[n_e:]
    if separate:
        n_w = 3 * tb.w_axis.n_coef
        assert np.allclose(rest[:n_w], 1.0 / VELOCITY_ERROR_PRIOR)
    if delays:
        assert np.allclose(rest[-2:], 1.0 / DELAY_PRIOR_S)


def test_the_evidence_update_of_a_component():
    """MacKay's update where the data determine the component, the EM update (which keeps
    the size) where they do not, within a factor of ten and the bounds."""
    rng = np.random.default_rng(1)
    x = rng.standard_normal(30) * 2.0
    well = np.eye(30) * 1e-4  # the data determine every coefficient: sigma = rms of x
    got = _component(1.0, np.eye(30), x, well, (1e-3, 100.0))
    assert got == pytest.approx(np.sqrt(x @ x / (30 - 30 * 1e-4)), rel=1e-9)
    # nothing determined: the posterior is the prior, and the size stays where it was
    assert _component(5.0, np.eye(30), np.zeros(30), np.eye(30) * 25.0, (1e-3, 100.0)) == (
        pytest.approx(5.0)
    )
    # at most a factor of ten per update, and within the bounds
    assert _component(1.0, np.eye(30), x * 1e3, well, (1e-3, 1e6)) == pytest.approx(10.0)
    assert _component(1.0, np.eye(30), x * 1e-6, well, (1e-3, 1e6)) == pytest.approx(0.1)
    assert _component(1.0, np.eye(30), x, well, (1e-3, 1.5)) == pytest.approx(1.5)
