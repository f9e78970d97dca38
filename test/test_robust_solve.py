"""The robust first solve of a window (issue 13, gross errors): one wild value, however
large, must move the trajectory no more than the same value removed would.

Before it, one CW range of 500 km (true range ~100 km in the issue) dragged the window's
first least-squares fit so far that the residual gate saw most rows off, refused to gate,
and the window came out up to 149 m off; a range of 1e300 overflowed the sums of squares.
Now absurd residuals are set aside first, a Huber warm-up fit (rows inside 20 sigma are
plain least squares) decides the gross errors, and the plain solve runs on the rest.

The windows are the 20 s cut of seed000_s1 of ``test_estimator_core`` (random seed 4);
the reference for a wild value is the same window with that value not measured (NaN),
which the estimator treats exactly like an absent row.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from functools import cache

import numpy as np
import pytest
from test_estimator_core import (
    _problem_on,
    _replace_station,
    _short_observations,
    _station,
    _with_values,
)

from orbit_tracking.core.data.observations import FixSeries, Observations
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.core.estimation.gauss_newton import GnOutcome, solve
from orbit_tracking.core.estimation.problem import Problem
from orbit_tracking.core.estimation.results import Estimate

T = np.linspace(0.5, 19.5, 39)
"""Output times [s] at which trajectories are compared."""

WINDOW = (0.0, 20.0)


@cache
def _observations() -> Observations:
    return _short_observations(4)[0]


def _with_station_value(sid: str, j: int, value: Callable[[float], float]) -> Observations:
    """The window with field ``j`` of the middle row of ``sid`` replaced by ``value(old)``."""
    obs = _observations()
    st = _station(obs, sid)
    values = st.table.values.copy()
    k = len(st.table) // 2
    values[k, j] = value(float(values[k, j]))
    return _replace_station(obs, sid, _with_values(st, values))


@cache
def _estimate(case: tuple[str, int, str] | None, cfg: EstimatorConfig) -> Estimate:
    """Estimates by case (cached: several tests share a reference)."""
    if case is None:
        return estimate(_observations(), *WINDOW, cfg)
    sid, j, what = case
    return estimate(_with_station_value(sid, j, WILD[what]), *WINDOW, cfg)


def _not_measured(_: float) -> float:
    return float('nan')


WILD: dict[str, Callable[[float], float]] = {
    'range +400 km': lambda x: x + 4e5,  # true range ~48 km here; 480 000 sigma
    'range 1e9 m': lambda x: 1e9,  # 1.2e9 sigma: still a finite robust weight
    'range 1e30': lambda x: 1e30,
    'range 1e300': lambda x: 1e300,
    'range -1e300': lambda x: -1e300,
    'azimuth +1 rad': lambda x: x + 1.0,  # 41 000 sigma on a theodolite
    'not measured': _not_measured,
}

STATION_CASES = [
    ('cw03', 0, 'range +400 km'),
    ('cw03', 0, 'range 1e9 m'),
    ('cw03', 0, 'range 1e30'),
    ('cw03', 0, 'range 1e300'),
    ('cw03', 0, 'range -1e300'),
    ('opt01', 0, 'azimuth +1 rad'),
]


def _max_difference(a: Estimate, b: Estimate) -> tuple[float, float]:
    """Largest position difference [m] at :data:`T`, and largest difference of any state
    component in units of ``b``'s posterior sigma."""
    xa, _ = a.targets[0].states(T)
    xb, cov = b.targets[0].states(T)
    sd = np.sqrt(np.einsum('mii->mi', cov))
    dpos = float(np.max(np.linalg.norm(xa[:, :3] - xb[:, :3], axis=1)))
    return dpos, float(np.max(np.abs(xa - xb) / sd))


@pytest.mark.parametrize('use_telemetry', [True, False], ids=['telemetry', 'stations_only'])
@pytest.mark.parametrize('case', STATION_CASES, ids=[c[2] for c in STATION_CASES])
def test_one_wild_station_value_is_gated_and_moves_nothing(case, use_telemetry):
    """Measured: the trajectory with the wild value equals the one with it removed to the
    bit (the plain solve restarts from where the warm-up started, so it takes the same
    steps); before that restart it was within the Gauss-Newton tolerance only (1e-9 m,
    5e-8 m for the azimuth without telemetry, 0.7 mm in a DDS replay). On the code
    before the robust solve, with telemetry: +400 km 661 m off (the gate refused: 99 % of
    the rows 'bad'), 1e30 1.6e27 m off, 1e300 64 m off, the azimuth 105 m off."""
    cfg = EstimatorConfig(use_telemetry=use_telemetry)
    sid, j, _ = case
    with warnings.catch_warnings():
        warnings.simplefilter('error', RuntimeWarning)  # no overflow anywhere in the core
        bad = _estimate(case, cfg)
    ref = _estimate((sid, j, 'not measured'), cfg)
    assert ref.success, ref.message
    assert bad.success, bad.message
    assert 'would reject' not in bad.message
    assert np.isfinite(bad.cost) and np.isfinite(bad.chi2_dof)
    gated = bad.rejected[(sid, 'residual_gate')]
    assert gated == ref.rejected[(sid, 'residual_gate')] + 1
    assert bad.used[sid] == ref.used[sid]
    assert bad.rejected[(sid, 'not_measured')] + 1 == ref.rejected[(sid, 'not_measured')]
    k = len(_station(_observations(), sid).table) // 2
    _, fields, res = bad.residuals[sid]
    assert np.isnan(res[k, j])  # the gated value carries no residual
    assert np.all(np.isfinite(res[k, np.arange(len(fields)) != j]))  # its row's others do
    dpos, dsig = _max_difference(bad, ref)
    assert dpos < 1e-9, dpos
    assert dsig < 1e-9, dsig
    # the covariance is that of the plain fit on the rows kept (no robust weights left)
    np.testing.assert_allclose(
        bad.targets[0].covariance, ref.targets[0].covariance, rtol=1e-9, atol=0.0
    )


def test_the_cauchy_loss_gates_the_same_value_and_none_restores_the_old_failure():
    case = ('cw03', 0, 'range +400 km')
    ref = _estimate(('cw03', 0, 'not measured'), EstimatorConfig())
    cauchy = _estimate(case, EstimatorConfig(robust_loss='cauchy'))
    assert cauchy.success, cauchy.message
    assert cauchy.rejected[('cw03', 'residual_gate')] == 1
    assert _max_difference(cauchy, ref)[0] < 1e-6
    # without the warm-up the first fit follows the outlier and the gate refuses
    plain = _estimate(case, EstimatorConfig(robust_loss='none'))
    assert not plain.success
    assert 'the residual gate would reject' in plain.message
    assert _max_difference(plain, ref)[0] > 100.0
    # absurd values are set aside even then: no least-squares sum can hold them
    absurd = _estimate(('cw03', 0, 'range 1e300'), EstimatorConfig(robust_loss='none'))
    assert absurd.success, absurd.message
    assert _max_difference(absurd, ref)[0] < 1e-6


def test_clean_windows_take_the_same_path_as_the_plain_solve():
    """Without gross errors the Huber warm-up (inside 20 sigma) is the plain Gauss-Newton
    solve step for step: same iterations, same gates, same trajectory (measured: 0 m)."""
    for use_telemetry in (False, True):
        robust = _estimate(None, EstimatorConfig(use_telemetry=use_telemetry))
        plain = _estimate(None, EstimatorConfig(use_telemetry=use_telemetry, robust_loss='none'))
        assert robust.success and plain.success
        assert robust.iterations == plain.iterations
        assert robust.rejected == plain.rejected
        assert _max_difference(robust, plain)[0] < 1e-9


@pytest.mark.parametrize('bias', [10.0, 50.0, 5e5], ids=['12_sigma', '60_sigma', '500_km'])
def test_the_gate_still_refuses_when_many_rows_do_not_fit(bias):
    """An unmodelled range bias on two CW radars (7.7 % of the station values) is a model
    that does not fit, not outliers: the gate refuses, nothing is gated and the estimate
    says so, whether the bias is below the gross-error limit (12 sigma, the plain gate
    refuses) or far above it (the warm-up's gate refuses)."""
    obs = _observations()
    n_values = sum(int(np.isfinite(s.table.values).sum()) for s in obs.stations)
    biased = 0
    for sid in ('cw03', 'cw07'):
        st = _station(obs, sid)
        values = st.table.values.copy()
        values[:, 0] += bias
        biased += int(np.isfinite(values[:, 0]).sum())
        obs = _replace_station(obs, sid, _with_values(st, values))
    assert biased / n_values > 0.05
    est = estimate(obs, *WINDOW, EstimatorConfig(use_telemetry=False))
    assert not est.success
    assert 'the residual gate would reject' in est.message
    assert not any(why == 'residual_gate' for _, why in est.rejected)


# ---------------------------------------------------------------------------------------
# telemetry


def _telemetry_glitch(what: str, offset: float) -> tuple[Observations, int]:
    """The window with the x ``what`` (position or velocity) of its middle telemetry
    epoch off by ``offset``."""
    obs = _observations()
    tel = obs.telemetry[0]
    k = tel.time.size // 2
    values = getattr(tel, what).copy()
    values[k, 0] += offset
    glitch = dataclasses.replace(tel, **{what: values})
    return Observations(obs.stations, {0: glitch}, obs.fixes), k


def _solve_on(
    obs: Observations,
    axes: tuple[SplineAxis, ...],
    cfg: EstimatorConfig,
    drop: tuple[str, int] | None = None,
) -> tuple[Problem, SplineTrajectory, GnOutcome]:
    """:func:`solve` on given knots from the rough-trajectory fit, telemetry fused (its
    error coefficients start at zero); ``drop`` = (position | velocity, epoch) marks that
    telemetry value as not measured."""
    prob, traj, coef0 = _problem_on(obs.window(*WINDOW), axes, cfg)
    if drop is not None:
        getattr(prob.telemetry[0], f'valid_{drop[0][0]}')[drop[1]] = False
    beta0 = np.zeros(prob.n)
    beta0[: coef0.size] = coef0
    out, _, _ = solve(prob, beta0, cfg)
    return prob, traj, out


GLITCHES = [('position', 1e3), ('velocity', 1e3)]
"""1 km and 1 km/s: 1000 and 50 000 times the telemetry's white noise."""


@pytest.mark.parametrize(('what', 'offset'), GLITCHES, ids=['position_1km', 'velocity_1km_s'])
def test_a_wild_telemetry_epoch_is_gated_and_the_noise_level_kept(what, offset):
    """Before: telemetry was never gated; the glitch raised the re-estimated telemetry
    noise from 1.0 m to 28.8 m (position), or from 0.02 to 28.8 m/s (velocity): the
    telemetry all but dropped out of the fit. The knots may differ from the clean
    window's: they are chosen on the raw telemetry (a velocity glitch even looks like a
    staging event there), so the noise levels are compared to 5 %."""
    obs, _ = _telemetry_glitch(what, offset)
    clean = _estimate(None, EstimatorConfig())
    with warnings.catch_warnings():
        warnings.simplefilter('error', RuntimeWarning)
        est = estimate(obs, *WINDOW, EstimatorConfig())
    assert est.success, est.message
    assert est.rejected[('telemetry_0', 'residual_gate')] == 1
    assert est.used['telemetry_0'] == clean.used['telemetry_0'] - 1
    noise, clean_noise = est.targets[0].telemetry_noise, clean.targets[0].telemetry_noise
    assert noise is not None and clean_noise is not None
    np.testing.assert_allclose(noise, clean_noise, rtol=0.05)


@pytest.mark.parametrize(('what', 'offset'), GLITCHES, ids=['position_1km', 'velocity_1km_s'])
def test_a_gated_telemetry_epoch_leaves_the_solution_of_it_removed(what, offset):
    """On the knots of the clean estimate, the solve with the glitch equals the solve with
    that epoch's position (velocity) not measured: the same rows, the same re-estimated
    noise levels, the same trajectory (measured: within 1e-9 m)."""
    cfg = EstimatorConfig()
    axes = _estimate(None, cfg).targets[0].trajectory.axes
    obs, k = _telemetry_glitch(what, offset)
    prob, traj, out = _solve_on(obs, axes, cfg)
    ref_prob, ref_traj, ref = _solve_on(_observations(), axes, cfg, drop=(what, k))
    gated = prob.gated[(f'telemetry_{what}', 0)]
    assert gated.sum() == 1 and gated[k]
    assert prob.telemetry[0].noise == pytest.approx(ref_prob.telemetry[0].noise, rel=1e-6)
    x = traj.states(out.beta, T)
    x_ref = ref_traj.states(ref.beta, T)
    assert np.max(np.linalg.norm(x[:, :3] - x_ref[:, :3], axis=1)) < 1e-6


def test_a_wild_fix_is_gated_when_fixes_are_fused():
    """Fixes fused as measurements (``fix_weight`` > 0): one 1 km off leaves the solution
    of it removed (measured: 5e-10 m; 0.1 m before, when fixes were never gated)."""
    obs, world = _short_observations(4)
    t = np.arange(0.0, 20.0, 0.5)
    position = world.target_state(0, t)[:, :3] + np.random.default_rng(0).normal(
        0, 5.0, (t.size, 3)
    )
    cov = np.tile(np.eye(3) * 25.0, (t.size, 1, 1))
    k = t.size // 2
    wild, removed = position.copy(), position.copy()
    wild[k, 2] += 1e3
    removed[k] = np.nan
    cfg = EstimatorConfig(fix_weight=1.0)
    bad, ref = (
        estimate(
            Observations(obs.stations, obs.telemetry, {0: FixSeries(0, t, p, cov)}), *WINDOW, cfg
        )
        for p in (wild, removed)
    )
    assert bad.success, bad.message
    assert bad.rejected[('fixes_0', 'residual_gate')] == 1
    assert ('fixes_0', 'residual_gate') not in ref.rejected
    assert _max_difference(bad, ref)[0] < 1e-6


def test_robust_settings_are_validated():
    with pytest.raises(ValueError, match='robust_loss must be one of'):
        EstimatorConfig(robust_loss='tukey')
    for bad in (0.0, -1.0, float('inf'), float('nan')):
        with pytest.raises(ValueError, match='robust_scale must be finite and > 0'):
            EstimatorConfig(robust_scale=bad)


def test_the_check_sees_the_first_plain_outcome_and_can_end_the_solve_before_its_rounds():
    """``solve``'s ``check`` (the estimator's early give-up at an unanchored edge segment)
    is called once, with the first plain outcome, and changes nothing when it returns;
    raising in it ends the solve before the noise re-estimation and gate rounds."""
    cfg = EstimatorConfig()
    axes = _estimate(None, cfg).targets[0].trajectory.axes

    def fresh() -> tuple[Problem, np.ndarray]:
        prob, _, coef0 = _problem_on(_observations().window(*WINDOW), axes, cfg)
        beta0 = np.zeros(prob.n)
        beta0[: coef0.size] = coef0
        return prob, beta0

    prob, beta0 = fresh()
    plain, _, _ = solve(prob, beta0, cfg)
    seen: list[GnOutcome] = []
    prob, beta0 = fresh()
    checked, _, _ = solve(prob, beta0, cfg, check=seen.append)
    assert len(seen) == 1
    np.testing.assert_array_equal(checked.beta, plain.beta)

    class Stop(Exception):
        pass

    def stop(o: GnOutcome) -> None:
        raise Stop

    prob, beta0 = fresh()
    noise = prob.telemetry[0].noise
    with pytest.raises(Stop):
        solve(prob, beta0, cfg, check=stop)
    assert prob.telemetry[0].noise == noise  # not re-estimated: the rounds did not run
    prob, beta0 = fresh()
    solve(prob, beta0, cfg)
    assert prob.telemetry[0].noise != noise
