"""Telemetry error models and gross station errors of the simulator (issue 14).

Each model's simulated errors, whitened with the covariance the Cramér-Rao bound uses
(:func:`orbit_tracking.core.sim.telemetry.error_covariance`), must be white with unit
variance over many seeds: a sign, a factor or a missing term shows as a variance far from
1 or a lag correlation far from 0. The default ``drift`` model must be the formula it
always was, and a station without gross errors must be simulated exactly as before.
"""

from __future__ import annotations

import copy
import dataclasses
import zlib
from functools import cache
from typing import Any

import numpy as np
import pytest
import scipy.linalg as sla

from orbit_tracking.core.errors import ConfigError
from orbit_tracking.core.sim.scenario import Scenario, load_scenario, scenario_from_dict
from orbit_tracking.core.sim.simulator import World, simulate, simulate_telemetry
from orbit_tracking.core.sim.telemetry import ERROR_MODELS, MODEL_PARAMETERS, error_covariance

RUNS = 240


def _data(error_model: str = 'white', **params: float) -> dict[str, Any]:
    tel: dict[str, Any] = {
        'kind': 'gps',
        'rate_hz': 1.0,
        'position_sigma_m': 0.5,
        'velocity_sigma_m_s': 0.02,
        'error_model': error_model,
        **params,
    }
    return {
        'name': 'tel_test',
        'world_frame': 'earth',
        'span': [0.0, 80.0],
        'targets': [
            {
                'id': 0,
                'model': 'aircraft',
                'start': {'latitude_deg': 10.0, 'longitude_deg': 20.0, 'height_m': 3000.0},
                'speed_m_s': 200.0,
                'heading_deg': 30.0,
                'legs': [
                    {'duration_s': 30.0},
                    {'duration_s': 30.0, 'load_factor': 2.5, 'turn': 'left'},
                    {'duration_s': 30.0},
                ],
            }
        ],
        'stations': [
            {
                'id': 'opt',
                'kind': 'optical',
                'platform': {
                    'type': 'fixed',
                    'latitude_deg': 10.1,
                    'longitude_deg': 20.1,
                    'height_m': 0.0,
                },
                'rate_hz': 1.0,
                'sigma': {'azimuth': 1e-4, 'elevation': 1e-4},
            }
        ],
        'telemetry': tel,
    }


def _scenario(error_model: str = 'white', **params: float) -> Scenario:
    return scenario_from_dict(_data(error_model, **params), 'test')


@cache
def _world() -> World:
    return World(_scenario())


def _errors(sc: Scenario, runs: int = RUNS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position and velocity errors (runs, n, 3) of the telemetry over seeds, and epochs."""
    world = copy.copy(_world())
    eps, evs = [], []
    assert sc.telemetry is not None
    for seed in range(runs):
        world.scenario = dataclasses.replace(sc, random_seed=seed)
        tel = simulate_telemetry(world, sc.telemetry)[0]
        x = world.target_state(0, tel.time)
        eps.append(tel.position - x[:, :3])
        evs.append(tel.velocity - x[:, 3:])
    return np.array(eps), np.array(evs), tel.time


MODELS: dict[str, dict[str, float]] = {
    'white': {},
    # within the families' range velocity_drift_m_s <= 0.6 position_drift_m / span, where
    # drift's published sigma (which leaves out the slope terms) stays within 10 %
    'drift': {'position_drift_m': 8.0, 'velocity_drift_m_s': 0.05},
    'random_walk': {'position_walk_m_sqrt_s': 0.7},
    'gauss_markov': {
        'position_markov_m': 4.0,
        'position_markov_tau_s': 20.0,
        'velocity_markov_m_s': 0.1,
        'velocity_markov_tau_s': 8.0,
    },
    'bias_drift': {
        'position_bias_m': 6.0,
        'position_drift_rate_m_s': 0.2,
        'velocity_bias_m_s': 0.05,
    },
    'separate_velocity': {
        'position_drift_m': 8.0,
        'velocity_drift_m_s': 0.15,
        'velocity_markov_m_s': 0.1,
        'velocity_markov_tau_s': 15.0,
    },
    'jumps': {'jump_rate_hz': 0.05, 'jump_sigma_m': 5.0},
    # q^2/12 white is exact when the noise dithers the rounding (sigma >= q/2); on a steady
    # signal with less noise the rounding error is a slowly varying bias instead
    'quantised': {'position_quantum_m': 1.0, 'velocity_quantum_m_s': 0.04},
}


def _whiten(cov: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Whitened errors (runs, n', 3) of errors (runs, n', 3) with covariance (n', n')."""
    chol = sla.cholesky(0.5 * (cov + cov.T), lower=True)
    flat = np.moveaxis(e, 1, 0).reshape(e.shape[1], -1)
    w = sla.solve_triangular(chol, flat, lower=True)
    return np.moveaxis(w.reshape(e.shape[1], e.shape[0], 3), 0, 1)


def test_every_model_but_drift_has_its_parameters_listed():
    assert set(MODEL_PARAMETERS) == set(ERROR_MODELS)


@pytest.mark.parametrize('model', list(MODELS))
def test_model_errors_whitened_by_their_covariance_are_unit_white_noise(model: str):
    sc = _scenario(model, **MODELS[model])
    assert sc.telemetry is not None
    ep, ev, t = _errors(sc)
    cov = error_covariance(sc.telemetry, t, sc.t_start, sc.t_end)
    if cov.cross is None:
        w = np.concatenate(
            [_whiten(cov.position, ep), _whiten(cov.velocity, ev)], axis=1
        )  # position and velocity each whitened alone
    else:
        joint = np.block([[cov.position, cov.cross], [cov.cross.T, cov.velocity]])
        w = _whiten(joint, np.concatenate([ep, ev], axis=1))
    n = w.size
    # mean 0 and variance 1 within 5 standard errors (kurtosis of jumps/quantised allowed)
    assert abs(w.mean()) < 5.0 / np.sqrt(n)
    assert abs(w.var() - 1.0) < 5.0 * np.sqrt(3.0 / n), w.var()
    # no correlation left between neighbours: a wrong time constant leaves one
    lag = np.mean(w[:, 1:, :] * w[:, :-1, :])
    assert abs(lag) < 5.0 / np.sqrt(n), lag
    # a position error half its true size (or twice) would show in the variance
    half = _whiten(cov.position, 0.5 * ep)
    assert half.var() < 0.6


@pytest.mark.parametrize('model', list(MODELS))
def test_published_sigma_is_the_rms_of_the_simulated_error(model: str):
    sc = _scenario(model, **MODELS[model])
    ep, ev, _ = _errors(sc, runs=120)
    world = copy.copy(_world())
    world.scenario = sc
    assert sc.telemetry is not None
    tel = simulate_telemetry(world, sc.telemetry)[0]
    assert tel.position_sigma[0, 0] == pytest.approx(np.sqrt(np.mean(ep**2)), rel=0.12)
    if model == 'drift':
        # drift keeps the velocity sigma it always published, hypot(white,
        # velocity_drift_m_s): it leaves out the slope and the sinusoid, so it is low
        assert tel.velocity_sigma[0, 0] < np.sqrt(np.mean(ev**2))
    else:
        assert tel.velocity_sigma[0, 0] == pytest.approx(np.sqrt(np.mean(ev**2)), rel=0.12)


def test_separate_velocity_error_is_not_the_derivative_of_the_position_error():
    """E[e_p(t) e_v(t)] over seeds: ``drift``'s velocity error is the slope of its position
    error (``vd^2 tau + 2 (vd / T)^2 tau^3 > 0`` late in the span), separate_velocity's is
    independent of it."""

    def cross(model: str) -> float:
        ep, ev, t = _errors(_scenario(model, **MODELS[model]), runs=200)
        late = t >= 40.0
        return float(np.mean(ep[:, late] * ev[:, late]))

    assert cross('drift') > 0.2
    assert abs(cross('separate_velocity')) < 0.1


def test_time_skew_values_are_the_truth_at_the_delayed_epochs():
    sc = _scenario('time_skew', position_delay_s=0.08, velocity_delay_s=-0.03)
    ep, ev, t = _errors(sc, runs=60)
    world = _world()
    x = world.target_state(0, t)
    want_p = world.target_state(0, np.clip(t - 0.08, sc.t_start, sc.t_end))[:, :3] - x[:, :3]
    want_v = world.target_state(0, np.clip(t + 0.03, sc.t_start, sc.t_end))[:, 3:] - x[:, 3:]
    # the white noise averages out over the runs: 0.5 m / sqrt(60)
    np.testing.assert_allclose(ep.mean(axis=0), want_p, atol=5 * 0.5 / np.sqrt(60))
    np.testing.assert_allclose(ev.mean(axis=0), want_v, atol=5 * 0.02 / np.sqrt(60))
    assert np.max(np.abs(want_p)) > 10.0  # 200 m/s x 80 ms: the skew is not lost in noise


def test_none_model_is_exact_and_publishes_the_sigma_floor():
    ep, ev, _ = _errors(_scenario('none'), runs=2)
    assert np.max(np.abs(ep)) < 1e-6 and np.max(np.abs(ev)) < 1e-9
    with pytest.raises(ValueError, match='exact'):
        sc = _scenario('none')
        assert sc.telemetry is not None
        error_covariance(sc.telemetry, np.arange(3.0), 0.0, 80.0)


def test_default_drift_is_the_reference_formula_bit_for_bit():
    """The drift model as it was before the other models existed (the formula is copied
    here on purpose: it pins the reference scenarios' telemetry)."""
    sc = load_scenario('seed000_s1')
    assert sc.telemetry is not None and sc.telemetry.error_model == 'drift'
    world = World(sc)
    tel = simulate_telemetry(world, sc.telemetry)[0]
    cfg = sc.telemetry
    rng = np.random.default_rng([sc.random_seed, zlib.crc32(b'telemetry_0')])
    grid = tel.time
    x = world.target_state(0, grid)
    tau = grid - sc.t_start
    span = max(sc.t_end - sc.t_start, 1.0)
    a = rng.standard_normal(3) * cfg.position_drift_m
    b = rng.standard_normal(3) * cfg.velocity_drift_m_s
    c = rng.standard_normal(3) * cfg.velocity_drift_m_s / span
    amp = rng.standard_normal(3) * 0.2 * cfg.position_drift_m
    period = span * (1.0 + rng.random(3))
    ph = 2.0 * np.pi * rng.random(3)
    arg = 2.0 * np.pi * tau[:, None] / period + ph
    e_pos = a + b * tau[:, None] + c * tau[:, None] ** 2 + amp * np.sin(arg)
    e_vel = b + 2.0 * c * tau[:, None] + amp * 2.0 * np.pi / period * np.cos(arg)
    pos = x[:, :3] + e_pos + rng.standard_normal((grid.size, 3)) * cfg.position_sigma_m
    vel = x[:, 3:] + e_vel + rng.standard_normal((grid.size, 3)) * cfg.velocity_sigma_m_s
    np.testing.assert_array_equal(tel.position, pos)
    np.testing.assert_array_equal(tel.velocity, vel)
    np.testing.assert_array_equal(
        tel.position_sigma, np.hypot(cfg.position_sigma_m, cfg.position_drift_m)
    )


def test_gross_errors_touch_only_the_values_they_mark():
    base = _scenario()
    plain = simulate(base)
    st = dataclasses.replace(
        base.stations[0], gross_errors={'count': 4, 'min_sigma': 20.0, 'max_sigma': 1000.0}
    )
    dirty = simulate(dataclasses.replace(base, stations=(st,)))
    mask = dirty.gross_errors['opt']
    assert int(mask.sum()) == 4
    clean, bad = plain.measurements['opt'], dirty.measurements['opt']
    np.testing.assert_array_equal(clean.time, bad.time)
    np.testing.assert_array_equal(clean.values[~mask], bad.values[~mask])
    off = np.abs(bad.values[mask] - clean.values[mask])
    off = np.minimum(off, 2.0 * np.pi - off) / bad.sigmas[mask]  # azimuth wraps
    assert np.all((off > 20.0 - 1e-6) & (off < 1000.0 + 1e-6)), off
    assert not plain.gross_errors['opt'].any()


def test_scenario_refuses_a_parameter_of_another_error_model():
    with pytest.raises(ConfigError, match='position_walk_m_sqrt_s.*gauss_markov'):
        _scenario('gauss_markov', position_walk_m_sqrt_s=1.0)
    with pytest.raises(ConfigError, match='error_model'):
        _scenario('sinusoid')
    with pytest.raises(ConfigError, match='position_delay_s'):
        _scenario('time_skew', position_delay_s=2.0)


def test_scenario_refuses_gross_error_bounds_in_the_wrong_order():
    data = _data()
    data['stations'][0]['gross_errors'] = {'count': 2, 'min_sigma': 50.0, 'max_sigma': 20.0}
    with pytest.raises(ConfigError, match='min_sigma <= max_sigma'):
        scenario_from_dict(data, 'test')
