"""Seed 003's adjoint assimilation and its quadratic baseline: the adjoint gradient against
finite differences of the cost, the flight given back from exact lines of sight, the fit
on q2's noisy ones against its sigma and the baseline, and a misfit that is not a success."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_dynamics_fit import _noise_free, _run

from orbit_tracking.core.data.observations import FixSeries, Observations, StationObservations
from orbit_tracking.core.dynamics.adjoint import (
    AdjointConfig,
    AdjointProblem,
    fit_adjoint,
    initial_from_rocket,
)
from orbit_tracking.core.dynamics.quadratic import QuadraticTrack
from orbit_tracking.core.dynamics.rocket import RocketModel
from orbit_tracking.core.dynamics.solve import RocketConfig, fit_rocket
from orbit_tracking.core.dynamics.start import start_from_fixes
from orbit_tracking.core.dynamics.thrust_spline import ThrustControl, ThrustSplineModel
from orbit_tracking.core.models.systematic import BiasParameter
from orbit_tracking.core.sim.scenario import build_targets, load_scenario
from orbit_tracking.core.sim.simulator import SimulationResult

GM = 3.986005e14
BIASES = (
    BiasParameter('sat06', 'los_alpha', 0.0, 1e-4),
    BiasParameter('sat06', 'los_theta', 0.0, 1e-4),
    BiasParameter('sat09', 'los_beta', 2e-5, 1e-4),
    BiasParameter('sat09', 'los_alpha', 1e-5, 1e-4, estimate=False),
)


def _errors(result: SimulationResult, tf) -> tuple[float, float, float, float]:  # type: ignore[no-untyped-def]
    """RMS position and velocity errors against the truth, and the RMS formal sigmas."""
    tr = result.truth[tf.target_id]
    m = (tr.time >= tf.t0) & (tr.time <= tf.t1)
    x, cov = tf.states(tr.time[m])
    e = x - np.hstack([tr.position[m], tr.velocity[m]])
    return (
        float(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, axis=1)))),
        float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, axis=1)))),
        float(np.sqrt(np.mean(np.trace(cov[:, :3, :3], axis1=1, axis2=2)))),
        float(np.sqrt(np.mean(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2)))),
    )


def _fixes_start(obs: Observations) -> tuple[float, np.ndarray, np.ndarray]:
    epoch = min(float(s.table.time.min()) for s in obs.stations)
    theta = start_from_fixes(obs.fixes[0], RocketModel(epoch, GM))
    return epoch, theta[:6], theta


def _check_sensitivities(model: ThrustSplineModel, theta: np.ndarray, t: np.ndarray) -> None:
    """The variational sensitivities at ``t`` against central differences of the flight."""
    sens = model.propagate(theta, t).sensitivity
    assert sens is not None
    for k in range(theta.size):
        h = 1.0 if k < 3 else 1e-3
        e = np.zeros(theta.size)
        e[k] = h
        fd = (
            model.propagate(theta + e, t, False).state - model.propagate(theta - e, t, False).state
        ) / (2 * h)
        assert np.abs(fd - sens[:, :, k]).max() <= 1e-6 * np.abs(sens[:, :, k]).max()


@pytest.mark.parametrize('rotating', [False, True])
@pytest.mark.parametrize('direction', ['velocity', 'free'])
def test_the_sensitivities_are_the_finite_differences_of_the_flight(
    direction: str, rotating: bool
) -> None:
    """Inertial, and rotating with J2 (the Coriolis and centrifugal terms)."""
    control = ThrustControl(50.0, 90.0, 10.0, direction)
    model = ThrustSplineModel(
        control, GM, j2=1.0826e-3 if rotating else 0.0, earth_rate=7.29e-5 if rotating else 0.0
    )
    x0 = build_targets(load_scenario('seed003_q2'))[0].state([50.0])[0]
    t = np.linspace(50.0, 90.0, 41)
    coef = control.fit(t, 3700.0 / (200.0 - t))
    if direction == 'free':
        coef = np.outer(coef, x0[3:] / np.linalg.norm(x0[3:])).ravel()
    theta = np.concatenate([x0, coef])
    t = np.linspace(50.0, 90.0, 17)
    _check_sensitivities(model, theta, t)


def test_a_jump_in_the_control_is_a_full_knot_and_its_pieces_are_the_spline() -> None:
    """A staging at 73.7 s: one clamped spline on each side (the spacing restarting at the
    jump), right-continuous there, and the per-interval Taylor pieces the right-hand sides
    use equal to the spline itself on both sides."""
    ctl = ThrustControl(50.0, 120.0, 10.0, 'velocity', (73.7,))
    plain = ThrustControl(50.0, 120.0, 10.0)
    assert 73.7 in ctl.breaks and ctl.n_coef == (3 + 3) + (5 + 3)  # intervals + degree
    assert np.count_nonzero(ctl.knots == 73.7) == 4 and plain.n_coef == 10
    coef = np.cos(np.arange(ctl.n_coef))
    t = np.array([50.0, 60.3, 73.7 - 1e-9, 73.7, 73.7 + 1e-9, 99.0, 120.0])
    v = ctl.values(coef, t)
    assert abs(v[2] - v[3]) > 1e-3 and abs(v[3] - v[4]) < 1e-6  # a jump, right-continuous
    k = np.clip(np.searchsorted(ctl.breaks, t, side='right') - 1, 0, ctl.breaks.size - 2)
    s = (t - 0.5 * (ctl.breaks[k] + ctl.breaks[k + 1]))[:, None]
    p = ctl.pieces[k]
    np.testing.assert_allclose((p[:, 0] + s * (p[:, 1] + s * (p[:, 2] + s * p[:, 3]))) @ coef, v)
    assert ThrustControl(50.0, 120.0, 10.0, jumps=(50.5, 130.0)).n_coef == plain.n_coef


def test_the_sensitivities_cross_a_jump() -> None:
    model = ThrustSplineModel(ThrustControl(50.0, 90.0, 10.0, 'velocity', (71.3,)), GM)
    x0 = build_targets(load_scenario('seed003_q2'))[0].state([50.0])[0]
    t = np.linspace(50.0, 90.0, 41)
    thrust = np.where(t < 71.3, 3700.0 / (200.0 - t), 2500.0 / (150.0 - (t - 71.3)))
    theta = np.concatenate([x0, model.control.fit(t, thrust)])
    t = np.linspace(60.0, 90.0, 7)
    _check_sensitivities(model, theta, t)


@pytest.mark.parametrize('direction', ['velocity', 'free'])
@pytest.mark.parametrize('biases', [False, True])
def test_the_adjoint_gradient_is_the_finite_differences_of_the_cost(
    direction: str, biases: bool
) -> None:
    """At a point ten formal sigmas off in every parameter, each component of the adjoint
    gradient equals the central difference of the cost (steps of a hundredth of a sigma).
    The bias case also carries a held bias, the smoothness prior, J2 and the rotating
    frame's terms."""
    _, obs = _run('seed003_q2')
    obs = obs.window(50.0, 80.0)
    t_last = max(float(s.table.time.max()) for s in obs.stations)
    x0 = build_targets(load_scenario('seed003_q2'))[0].state([50.0])[0]
    cfg = AdjointConfig(
        gm=GM, direction=direction, j2=1.0826e-3 if biases else 0.0, rotating=biases
    )
    model = cfg.model(50.0, t_last)
    prob = AdjointProblem(obs, {0: model}, BIASES if biases else (), 0.5 if biases else None)
    t = np.linspace(50.0, t_last, 61)
    coef = model.control.fit(t, 3700.0 / (200.0 - t))
    if direction == 'free':
        coef = np.outer(coef, x0[3:] / np.linalg.norm(x0[3:])).ravel()
    p = np.concatenate([x0, coef, np.full(len(prob.free), 1e-5)])
    vec, jac, _ = prob.jacobian(p)
    sigma = 1.0 / np.sqrt(np.diag(jac.T @ jac))
    p = p + 10.0 * sigma * np.random.default_rng(1).standard_normal(p.size)
    cost, grad = prob.gradient(p)
    assert cost == pytest.approx(prob.cost(p), rel=1e-12)
    fd = np.empty(p.size)
    for k in range(p.size):
        e = np.zeros(p.size)
        e[k] = 1e-2 * sigma[k]
        fd[k] = (prob.cost(p + e) - prob.cost(p - e)) / (2 * e[k])
    assert np.all(np.abs(grad - fd) <= 1e-5 * np.abs(fd))


def test_noise_free_lines_of_sight_give_back_the_flight() -> None:
    """From the fixes' state with a constant thrust along the velocity (velocity mode) and
    from the rocket-equation thrust of the fixes (free mode)."""
    obs = _noise_free('seed003_q2')
    result, _ = _run('seed003_q2')
    epoch, x0, theta = _fixes_start(obs)
    for direction, thrust in (
        ('velocity', 40.0),
        ('free', lambda t: RocketModel(epoch, GM).thrust(theta, t)),
    ):
        fit = fit_adjoint(
            obs, {0: (epoch, x0, thrust)}, config=AdjointConfig(gm=GM, direction=direction)
        )
        assert fit.success, fit.message
        assert fit.chi2_dof < 1e-6
        tr = result.truth[0]
        m = (tr.time >= fit.targets[0].t0) & (tr.time <= fit.targets[0].t1)
        x, _ = fit.targets[0].states(tr.time[m])
        assert np.abs(x[:, :3] - tr.position[m]).max() < 1.0
        assert np.abs(x[:, 3:] - tr.velocity[m]).max() < 0.1
        a, _ = fit.targets[0].thrust(tr.time[m])
        assert np.abs(a - 3700.0 / (200.0 - tr.time[m])).max() < 0.5


def test_q2_adjoint_is_within_its_sigma_and_beats_the_quadratic() -> None:
    result, obs = _run('seed003_q2')
    rocket = fit_rocket(obs, config=RocketConfig(gm=GM))
    quad = QuadraticTrack(obs.fixes[0], 20.0)
    _, quad_vel, _, _ = _errors(result, quad)
    for direction in ('velocity', 'free'):
        cfg = AdjointConfig(gm=GM, direction=direction)
        fit = fit_adjoint(obs, initial_from_rocket(rocket.targets), config=cfg)
        assert fit.success, fit.message
        pos, vel, pos_sigma, vel_sigma = _errors(result, fit.targets[0])
        assert pos < 1.5 * pos_sigma
        assert vel < 1.5 * vel_sigma
        assert vel < quad_vel
        _, sigma = fit.targets[0].thrust([100.0])
        assert 0.0 < sigma[0] < 5.0


def test_a_step_in_one_satellites_angles_is_not_a_success() -> None:
    """Both angles of sat09 jump by 50 sigma after 110 s: no thrust explains both
    satellites."""
    result, obs = _run('seed003_q2')
    stations = []
    for st in obs.stations:
        tab = st.table
        if tab.station_id == 'sat09':
            vals = tab.values + np.where(tab.time[:, None] > 110.0, 50.0 * tab.sigmas, 0.0)
            tab = dataclasses.replace(tab, values=vals)
        stations.append(StationObservations(tab, st.pose))
    bad = Observations(tuple(stations), {}, obs.fixes)
    epoch, x0, theta = _fixes_start(bad)
    thrust = lambda t: RocketModel(epoch, GM).thrust(theta, t)  # noqa: E731
    fit = fit_adjoint(bad, {0: (epoch, x0, thrust)}, config=AdjointConfig(gm=GM, direction='free'))
    assert not fit.success
    assert 'inconsistent' in fit.message or 'gate' in fit.message


def test_the_start_must_fit_the_span() -> None:
    _, obs = _run('seed003_q2')
    epoch, x0, _ = _fixes_start(obs)
    with pytest.raises(ValueError, match='outside its model span'):
        fit_adjoint(obs, {0: (epoch + 5.0, x0, 30.0)}, config=AdjointConfig(gm=GM))
    with pytest.raises(ValueError, match='coefficients'):
        fit_adjoint(obs, {0: (epoch, x0, np.zeros(4))}, config=AdjointConfig(gm=GM))


def test_the_quadratic_gives_back_a_quadratic_flight() -> None:
    """Exact fixes of a quadratic with correlated covariances: every window gives it back;
    with diagonal covariances the sigma is numpy's per-axis weighted polyfit's."""
    t = np.linspace(50.0, 110.0, 301)
    a, b, c = (
        np.array([-1.1e6, 6.2e6, 1.1e6]),
        np.array([-700.0, 820.0, 940.0]),
        np.array([3.0, -4.0, 12.0]),
    )
    pos = a + np.outer(t - 60.0, b) + np.outer((t - 60.0) ** 2, c)
    vel = b + 2.0 * np.outer(t - 60.0, c)
    rng = np.random.default_rng(3)
    m = rng.standard_normal((t.size, 3, 3))
    cov = 100.0 * (m @ np.transpose(m, (0, 2, 1)) + np.eye(3))
    for window in (None, 20.0):
        x, _ = QuadraticTrack(FixSeries(0, t, pos, cov), window).states(t[::7])
        assert np.abs(x[:, :3] - pos[::7]).max() < 1e-6
        assert np.abs(x[:, 3:] - vel[::7]).max() < 1e-8
    sig = np.linspace(10.0, 30.0, t.size)
    diag = np.zeros((t.size, 3, 3))
    diag[:, [0, 1, 2], [0, 1, 2]] = (sig**2)[:, None]
    _, cov_q = QuadraticTrack(FixSeries(0, t, pos, diag)).states([80.0])
    _, cov_np = np.polyfit(t - 80.0, pos[:, 0], 2, w=1.0 / sig, cov='unscaled')
    assert np.sqrt(cov_q[0, 0, 0]) == pytest.approx(np.sqrt(cov_np[2, 2]), rel=1e-9)
    assert np.sqrt(cov_q[0, 3, 3]) == pytest.approx(np.sqrt(cov_np[1, 1]), rel=1e-9)
