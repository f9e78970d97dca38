"""Telemetry error models of the simulator and their exact second-order statistics.

Each model makes the error of on-board telemetry (or airborne GPS) as a random process of
scenario time ``tau = t - t_start`` over the span ``T = max(t_end - t_start, 1 s)``, per
world axis, independent and identically distributed over the three axes. Every model but
``none`` adds white noise of ``position_sigma_m`` / ``velocity_sigma_m_s`` on top.

==================  ==========================================================================
model               position error e_p, velocity error e_v (besides the white noise)
==================  ==========================================================================
``drift``           ``a + b tau + c tau^2 + A sin(2 pi tau / P + phi)``, ``e_v = d e_p/dt``
                    (the reference scenarios' model, in :mod:`.simulator`)
``none``            no error at all (not even white noise)
``white``           nothing
``random_walk``     ``e_p`` a Wiener process from 0 at ``t_start``, ``q^2`` per second
``gauss_markov``    stationary first-order Gauss-Markov processes, ``s^2 exp(-|dt| / tc)``,
                    independent for position and velocity (a Kalman-filtered GNSS/INS)
``bias_drift``      ``e_p = b + d tau``, ``e_v = c`` (three independent constants)
``separate_veloc``  ``e_p`` as in ``drift``; ``e_v`` an independent Gauss-Markov process
``ity``             (GNSS Doppler, INS velocity: not the derivative of ``e_p``)
``time_skew``       position stamped ``position_delay_s`` late, velocity ``velocity_delay_s``
                    late: the values are the truth at ``t - delay``
``jumps``           ``e_p`` a compound Poisson process: steps at rate ``jump_rate_hz``, each
                    ``N(0, jump_sigma_m^2)`` per axis (re-acquisition)
``quantised``       values rounded to ``position_quantum_m`` / ``velocity_quantum_m_s``
==================  ==========================================================================

The published sigma of every model is honest: the root mean over the span of the marginal
variance of the total error (for ``none``, whose error is zero, the floors
:data:`SIGMA_FLOOR`, since a zero sigma is refused at the boundary). ``drift`` keeps the
sigma it always published, ``hypot(white, position_drift_m)``, so the reference scenarios
do not change; it leaves out the slope terms and is slightly optimistic.

:func:`error_covariance` gives the exact covariance of the errors at given epochs (the
per-axis ``(2n x 2n)`` matrix, or its position and velocity blocks when they are
independent), which is what the Cramér-Rao bound of a draw (:mod:`orbit_tracking.core.crb`)
whitens telemetry with. For the models that are not Gaussian (``drift``'s random-period
sinusoid, ``jumps``, ``quantised``) it is the exact covariance, so the bound is that of
the Gaussian errors with the same second-order statistics.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.crb import TelemetryErrorCovariance

if TYPE_CHECKING:
    from orbit_tracking.core.sim.scenario import TelemetryConfig

__all__ = [
    'ERROR_MODELS',
    'MODEL_PARAMETERS',
    'SIGMA_FLOOR',
    'TelemetrySample',
    'error_covariance',
    'parameters_of',
    'simulate_model',
]

FloatArray = NDArray[np.float64]
StateFn = Callable[[FloatArray], FloatArray]

ERROR_MODELS: tuple[str, ...] = (
    'drift',
    'none',
    'white',
    'random_walk',
    'gauss_markov',
    'bias_drift',
    'separate_velocity',
    'time_skew',
    'jumps',
    'quantised',
)
"""Telemetry error models (``telemetry.error_model``); ``drift`` is the default."""

MODEL_PARAMETERS: dict[str, tuple[str, ...]] = {
    'drift': ('position_drift_m', 'velocity_drift_m_s'),
    'none': (),
    'white': (),
    'random_walk': ('position_walk_m_sqrt_s',),
    'gauss_markov': (
        'position_markov_m',
        'position_markov_tau_s',
        'velocity_markov_m_s',
        'velocity_markov_tau_s',
    ),
    'bias_drift': ('position_bias_m', 'position_drift_rate_m_s', 'velocity_bias_m_s'),
    'separate_velocity': (
        'position_drift_m',
        'velocity_drift_m_s',
        'velocity_markov_m_s',
        'velocity_markov_tau_s',
    ),
    'time_skew': ('position_delay_s', 'velocity_delay_s'),
    'jumps': ('jump_rate_hz', 'jump_sigma_m'),
    'quantised': ('position_quantum_m', 'velocity_quantum_m_s'),
}
"""The keys of each model besides the white-noise sigmas (which every model but ``none``
uses)."""

SIGMA_FLOOR = (1e-3, 1e-4)
"""Published position [m] and velocity [m/s] sigma of the ``none`` model."""

_DELAY_PRIOR_FLOOR_S = 1e-3
_QUADRATURE = np.polynomial.legendre.leggauss(16)


@dataclass(frozen=True)
class TelemetrySample:
    """Telemetry of one target: values (n, 3) and the published sigmas (one each)."""

    position: FloatArray
    velocity: FloatArray
    position_sigma: float
    velocity_sigma: float


def _param(tel: TelemetryConfig, name: str) -> float:
    return float(tel.error_parameters.get(name, 0.0))


def _gauss_markov(
    rng: np.random.Generator, tau: FloatArray, sigma: float, tc: float
) -> FloatArray:
    """Stationary first-order Gauss-Markov process (n, 3), exact on any grid."""
    z = rng.standard_normal((tau.size, 3))
    out = np.empty((tau.size, 3))
    if tau.size == 0:
        return out
    out[0] = sigma * z[0]
    phi = np.exp(-np.diff(tau) / tc)
    for k in range(1, tau.size):
        out[k] = phi[k - 1] * out[k - 1] + sigma * np.sqrt(1.0 - phi[k - 1] ** 2) * z[k]
    return out


def _smooth_drift(
    rng: np.random.Generator, tau: FloatArray, span: float, pd: float, vd: float
) -> FloatArray:
    """Position part of the ``drift`` model, drawn in the same order as :mod:`.simulator`."""
    a = rng.standard_normal(3) * pd
    b = rng.standard_normal(3) * vd
    c = rng.standard_normal(3) * vd / span
    amp = rng.standard_normal(3) * 0.2 * pd
    period = span * (1.0 + rng.random(3))
    ph = 2.0 * np.pi * rng.random(3)
    arg = 2.0 * np.pi * tau[:, None] / period + ph
    return np.asarray(a + b * tau[:, None] + c * tau[:, None] ** 2 + amp * np.sin(arg))


def _drift_variance(tau: FloatArray, span: float, pd: float, vd: float) -> float:
    """Mean over the epochs of the marginal variance of the smooth drift."""
    if tau.size == 0:
        return 0.0
    return float(
        pd**2
        + vd**2 * np.mean(tau**2)
        + (vd / span) ** 2 * np.mean(tau**4)
        + 0.5 * (0.2 * pd) ** 2
    )


def simulate_model(
    tel: TelemetryConfig,
    grid: FloatArray,
    t_start: float,
    t_end: float,
    state_at: StateFn,
    rng: np.random.Generator,
) -> TelemetrySample:
    """Telemetry values of one target under ``tel.error_model`` (any model but ``drift``,
    which :func:`~orbit_tracking.core.sim.simulator.simulate_telemetry` makes itself).

    Parameters
    ----------
    tel : TelemetryConfig
    grid : ndarray, shape (n,)
        Epochs [s] (outages already removed).
    t_start, t_end : float
        Scenario span [s].
    state_at : callable
        Truth ``(m,) -> (m, 6)`` position [m] and velocity [m/s].
    rng : numpy.random.Generator
    """
    model = tel.error_model
    if model == 'drift' or model not in ERROR_MODELS:
        raise ValueError(f'simulate_model makes the models {ERROR_MODELS[1:]}; got {model!r}')
    n = grid.size
    tau = grid - t_start
    span = max(t_end - t_start, 1.0)
    x = state_at(grid)
    sp_, sv_ = tel.position_sigma_m, tel.velocity_sigma_m_s
    ep = np.zeros((n, 3))
    ev = np.zeros((n, 3))
    var_p = var_v = 0.0
    mean_tau = float(np.mean(tau)) if n else 0.0
    mean_tau2 = float(np.mean(tau**2)) if n else 0.0
    if model == 'random_walk':
        q = _param(tel, 'position_walk_m_sqrt_s')
        steps = np.diff(np.concatenate([[0.0], tau]))
        ep = np.cumsum(rng.standard_normal((n, 3)) * q * np.sqrt(steps)[:, None], axis=0)
        var_p = q**2 * mean_tau
    elif model == 'gauss_markov':
        s_p, s_v = _param(tel, 'position_markov_m'), _param(tel, 'velocity_markov_m_s')
        ep = _gauss_markov(rng, tau, s_p, _param(tel, 'position_markov_tau_s'))
        ev = _gauss_markov(rng, tau, s_v, _param(tel, 'velocity_markov_tau_s'))
        var_p, var_v = s_p**2, s_v**2
    elif model == 'bias_drift':
        s_b, s_d = _param(tel, 'position_bias_m'), _param(tel, 'position_drift_rate_m_s')
        s_c = _param(tel, 'velocity_bias_m_s')
        b = rng.standard_normal(3) * s_b
        d = rng.standard_normal(3) * s_d
        c = rng.standard_normal(3) * s_c
        ep = b + d * tau[:, None]
        ev = np.tile(c, (n, 1))
        var_p, var_v = s_b**2 + s_d**2 * mean_tau2, s_c**2
    elif model == 'separate_velocity':
        pd, vd = _param(tel, 'position_drift_m'), _param(tel, 'velocity_drift_m_s')
        s_v = _param(tel, 'velocity_markov_m_s')
        ep = _smooth_drift(rng, tau, span, pd, vd)
        ev = _gauss_markov(rng, tau, s_v, _param(tel, 'velocity_markov_tau_s'))
        var_p, var_v = _drift_variance(tau, span, pd, vd), s_v**2
    elif model == 'time_skew':
        dp, dv = _param(tel, 'position_delay_s'), _param(tel, 'velocity_delay_s')
        ep = state_at(np.clip(grid - dp, t_start, t_end))[:, :3] - x[:, :3]
        ev = state_at(np.clip(grid - dv, t_start, t_end))[:, 3:] - x[:, 3:]
        var_p = float(np.mean(ep**2)) if n else 0.0
        var_v = float(np.mean(ev**2)) if n else 0.0
    elif model == 'jumps':
        rate, s_j = _param(tel, 'jump_rate_hz'), _param(tel, 'jump_sigma_m')
        k = int(rng.poisson(rate * span))
        when = t_start + rng.random(k) * span
        size = rng.standard_normal((k, 3)) * s_j
        ep = (grid[:, None] >= when[None, :]).astype(float) @ size
        var_p = rate * s_j**2 * mean_tau
    if model == 'none':
        pos, vel = x[:, :3].copy(), x[:, 3:].copy()
        return TelemetrySample(pos, vel, SIGMA_FLOOR[0], SIGMA_FLOOR[1])
    pos = x[:, :3] + ep + rng.standard_normal((n, 3)) * sp_
    vel = x[:, 3:] + ev + rng.standard_normal((n, 3)) * sv_
    if model == 'quantised':
        qp, qv = _param(tel, 'position_quantum_m'), _param(tel, 'velocity_quantum_m_s')
        if qp > 0.0:
            pos = np.round(pos / qp) * qp
        if qv > 0.0:
            vel = np.round(vel / qv) * qv
        var_p, var_v = qp**2 / 12.0, qv**2 / 12.0
    return TelemetrySample(
        pos, vel, float(np.sqrt(sp_**2 + var_p)), float(np.sqrt(sv_**2 + var_v))
    )


def _markov(tau: FloatArray, sigma: float, tc: float) -> FloatArray:
    return np.asarray(sigma**2 * np.exp(-np.abs(tau[:, None] - tau[None, :]) / tc))


def _drift_blocks(
    tau: FloatArray, span: float, pd: float, vd: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Covariance blocks (pp, pv, vv) of the smooth drift: the random quadratic (a, b, c)
    plus the sinusoid of random amplitude, phase and period ``P = T (1 + U)``; the
    expectation over ``U ~ U(0, 1)`` by 16-point Gauss-Legendre quadrature."""
    one = np.ones_like(tau)
    bp = np.stack([one, tau, tau**2], axis=1)
    bv = np.stack([0.0 * one, one, 2.0 * tau], axis=1)
    prior = np.array([pd**2, vd**2, (vd / span) ** 2])
    pp = (bp * prior) @ bp.T
    pv = (bp * prior) @ bv.T
    vv = (bv * prior) @ bv.T
    half_s2 = 0.5 * (0.2 * pd) ** 2
    if half_s2 > 0.0:
        lag = tau[:, None] - tau[None, :]
        nodes, weights = _QUADRATURE
        for u, w in zip(0.5 * (nodes + 1.0), 0.5 * weights, strict=True):
            om = 2.0 * np.pi / (span * (1.0 + u))
            arg = om * lag
            c, s = np.cos(arg), np.sin(arg)
            pp += w * half_s2 * c
            pv += w * half_s2 * om * s  # Cov(e_p(i), e_v(j)) with lag = tau_i - tau_j
            vv += w * half_s2 * om**2 * c
    return pp, pv, vv


def error_covariance(
    tel: TelemetryConfig,
    times: FloatArray,
    t_start: float,
    t_end: float,
) -> TelemetryErrorCovariance:
    """Exact covariance of the telemetry errors of one world axis at ``times``.

    Parameters
    ----------
    tel : TelemetryConfig
    times : ndarray, shape (n,)
        Telemetry epochs [s].
    t_start, t_end : float
        Scenario span [s] (the models' time origin and span).

    Returns
    -------
    TelemetryErrorCovariance
        Position and velocity blocks (n, n) [m^2, m^2/s^2], their cross block when they
        are correlated (``drift``), and for ``time_skew`` the delays and their prior
        sigma (the size of the delay itself, at least 1 ms): the skew is a random constant
        the bound estimates along with the trajectory.

    Raises
    ------
    ValueError
        For ``none``: exact telemetry has no covariance (its information is unbounded).
    """
    model = tel.error_model
    if model not in ERROR_MODELS:
        raise ValueError(f'unknown telemetry error model {model!r}; known: {ERROR_MODELS}')
    if model == 'none':
        raise ValueError('telemetry error model none is exact: it has no error covariance')
    t = np.asarray(times, dtype=np.float64)
    tau = t - t_start
    span = max(t_end - t_start, 1.0)
    eye = np.eye(t.size)
    pp = tel.position_sigma_m**2 * eye
    vv = tel.velocity_sigma_m_s**2 * eye
    cross: FloatArray | None = None
    delays = (0.0, 0.0)
    delay_sigma = (0.0, 0.0)
    if model == 'drift' or model == 'separate_velocity':
        d_pp, d_pv, d_vv = _drift_blocks(
            tau, span, _param(tel, 'position_drift_m'), _param(tel, 'velocity_drift_m_s')
        )
        pp = pp + d_pp
        if model == 'drift':
            vv, cross = vv + d_vv, d_pv
        else:
            vv = vv + _markov(
                tau, _param(tel, 'velocity_markov_m_s'), _param(tel, 'velocity_markov_tau_s')
            )
    elif model == 'random_walk':
        pp = pp + _param(tel, 'position_walk_m_sqrt_s') ** 2 * np.minimum.outer(tau, tau)
    elif model == 'gauss_markov':
        pp = pp + _markov(
            tau, _param(tel, 'position_markov_m'), _param(tel, 'position_markov_tau_s')
        )
        vv = vv + _markov(
            tau, _param(tel, 'velocity_markov_m_s'), _param(tel, 'velocity_markov_tau_s')
        )
    elif model == 'bias_drift':
        pp = (
            pp
            + _param(tel, 'position_bias_m') ** 2
            + _param(tel, 'position_drift_rate_m_s') ** 2 * np.outer(tau, tau)
        )
        vv = vv + _param(tel, 'velocity_bias_m_s') ** 2
    elif model == 'jumps':
        rate, s_j = _param(tel, 'jump_rate_hz'), _param(tel, 'jump_sigma_m')
        pp = pp + rate * s_j**2 * np.minimum.outer(tau, tau)
    elif model == 'quantised':
        pp = pp + _param(tel, 'position_quantum_m') ** 2 / 12.0 * eye
        vv = vv + _param(tel, 'velocity_quantum_m_s') ** 2 / 12.0 * eye
    elif model == 'time_skew':
        delays = (_param(tel, 'position_delay_s'), _param(tel, 'velocity_delay_s'))
        delay_sigma = (
            max(abs(delays[0]), _DELAY_PRIOR_FLOOR_S),
            max(abs(delays[1]), _DELAY_PRIOR_FLOOR_S),
        )
    return TelemetryErrorCovariance(t, pp, vv, cross, delays, delay_sigma)


def parameters_of(tel_mapping: Mapping[str, Any]) -> dict[str, float]:
    """The error-model parameters of a validated telemetry mapping (every key of
    :data:`MODEL_PARAMETERS`)."""
    keys = sorted({k for ks in MODEL_PARAMETERS.values() for k in ks})
    return {k: float(tel_mapping[k]) for k in keys if k in tel_mapping}
