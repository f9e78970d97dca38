"""Seed 003's powered-flight model: gravity plus a thrust along the velocity whose
magnitude follows the rocket equation, with its sensitivities by the variational
equations.

The vehicle obeys (world frame Earth-centred; inertial unless ``earth_rate`` is set)::

    r'' = g(r) + a(t) v / |v|  [- 2 w x v - w x (w x r)],     a(t) = c / (tau - (t - t0))

with ``c`` the effective exhaust speed and ``tau = m0 / mdot`` the time the mass would
take to run out, counted from the parameter epoch ``t0`` (``c mdot / m`` is the rocket
equation's thrust acceleration). The eight parameters are the state at ``t0`` and
``(c, tau)``: :data:`PARAMETERS`. ``g`` is point-mass gravity with an optional J2 term.

The sensitivities ``Phi = d(r, v)(t) / d theta`` (6 x 8) obey the variational equations::

    Phi' = A(t) Phi + [0 | B(t)],   Phi(t0) = [I_6 | 0],
    A = [[0, I], [dg/dr, da_T/dv]],  B = [[0, 0], [v_hat / s, -c v_hat / s^2]],

with ``s = tau - (t - t0)`` and ``da_T/dv = (c / s) (I - v_hat v_hat^T) / |v|``; they are
integrated with the state (one ODE of dimension 54) and checked against finite
differences in the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import solve_ivp

from orbit_tracking.core import frames
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.models.dynamics import gravity

__all__ = ['PARAMETERS', 'Flight', 'RocketModel']

FloatArray = NDArray[np.float64]

PARAMETERS: tuple[str, ...] = (
    'x',
    'y',
    'z',
    'vx',
    'vy',
    'vz',
    'exhaust_speed',
    'mass_time',
)
"""The rocket model's parameters: position [m] and velocity [m/s] at the epoch, effective
exhaust speed ``c`` [m/s] and ``tau = m0 / mdot`` at the epoch [s]."""

_RTOL = 1e-11
_ATOL = np.concatenate([np.full(3, 1e-6), np.full(3, 1e-9), np.full(48, 1e-10)])
_MAX_THRUST = 2000.0
"""Largest thrust acceleration [m/s^2] (about 200 g) a flight may reach in its span:
beyond it the parameters are no vehicle (and the integration would crawl)."""
_MAX_RHS_CALLS = 100_000
"""Right-hand-side evaluations after which an integration is abandoned."""
_MIN_RADIUS = 1.0e6
"""Distance from the Earth's centre [m] below which a flight is abandoned."""
_MIN_MASS_TIME_S = 1.0
"""The mass may not run out within a second of any requested time (the thrust
acceleration diverges there)."""


class FlightError(OrbitTrackingError, ValueError):
    """Parameters the model cannot fly (the mass runs out, the speed is zero, the
    integration fails)."""


@dataclass(frozen=True)
class Flight:
    """States of one parameter vector at the requested times.

    Attributes
    ----------
    time : ndarray, shape (m,)
    state : ndarray, shape (m, 6)
        Position [m] and velocity [m/s] in the world frame.
    sensitivity : ndarray, shape (m, 6, 8) or None
        ``d state / d theta`` in the order of :data:`PARAMETERS`.
    thrust : ndarray, shape (m,)
        Magnitude of the thrust acceleration [m/s^2].
    """

    time: FloatArray
    state: FloatArray
    sensitivity: FloatArray | None
    thrust: FloatArray


@dataclass(frozen=True)
class RocketModel:
    """The rocket-equation flight of one vehicle.

    Attributes
    ----------
    epoch : float
        Time of the parameters' state [s].
    gm : float
        Gravitational parameter [m^3/s^2].
    j2 : float
        Second zonal harmonic of the gravity (0: point mass).
    radius : float
        Reference radius of ``j2`` [m].
    earth_rate : float
        Rotation rate of the world frame about its z axis [rad/s] (0 for an inertial
        frame such as ``eci``; the Earth's rate for ``earth``), adding the Coriolis and
        centrifugal accelerations; the thrust then points along the velocity relative to
        the rotating frame.
    """

    epoch: float
    gm: float = frames.WGS84_GM
    j2: float = 0.0
    radius: float = frames.WGS84_A
    earth_rate: float = 0.0

    names: tuple[str, ...] = PARAMETERS

    @property
    def n_parameters(self) -> int:
        return len(PARAMETERS)

    def thrust(self, theta: ArrayLike, t: ArrayLike) -> FloatArray:
        """Thrust acceleration magnitude ``c / (tau - (t - t0))`` [m/s^2], shape (m,)."""
        th = np.asarray(theta, dtype=np.float64)
        return th[6] / (th[7] - (np.atleast_1d(np.asarray(t, float)) - self.epoch))

    def acceleration(self, y: FloatArray, thrust: float) -> FloatArray:
        """Acceleration [m/s^2] at state ``y`` (6,) with a thrust of magnitude ``thrust``
        along the velocity (gravity, and the rotating frame's terms)."""
        r, v = y[:3], y[3:6]
        acc = gravity(r, self.gm, self.j2, self.radius) + thrust * v / np.linalg.norm(v)
        if self.earth_rate:
            w = np.array([0.0, 0.0, self.earth_rate])
            acc = acc - 2.0 * np.cross(w, v) - np.cross(w, np.cross(w, r))
        return np.asarray(acc, dtype=np.float64)

    def _gravity_gradient(self, r: FloatArray) -> FloatArray:
        rn = float(np.linalg.norm(r))
        u = r / rn
        grad = self.gm / rn**3 * (3.0 * np.outer(u, u) - np.eye(3))
        if self.j2 != 0.0:  # the J2 part by central differences (it is 1e-3 of the whole)
            h = 1.0
            for k in range(3):
                e = np.zeros(3)
                e[k] = h
                gp = gravity(r + e, self.gm, self.j2, self.radius)
                gm_ = gravity(r - e, self.gm, self.j2, self.radius)
                gp0 = gravity(r + e, self.gm, 0.0)
                gm0 = gravity(r - e, self.gm, 0.0)
                grad[:, k] += ((gp - gp0) - (gm_ - gm0)) / (2 * h)
        return grad

    def _rhs(self, theta: FloatArray, with_sens: bool):  # type: ignore[no-untyped-def]
        c, tau = float(theta[6]), float(theta[7])
        w = np.array([0.0, 0.0, self.earth_rate])
        wx = np.array([[0.0, -w[2], 0.0], [w[2], 0.0, 0.0], [0.0, 0.0, 0.0]])
        t0 = self.epoch

        calls = [0]

        def rhs(t: float, y: FloatArray) -> FloatArray:
            calls[0] += 1
            if calls[0] > _MAX_RHS_CALLS:
                raise FlightError(f'integration abandoned after {_MAX_RHS_CALLS} evaluations')
            r, v = y[:3], y[3:6]
            if not np.linalg.norm(r) > _MIN_RADIUS:
                raise FlightError("the flight passes through the Earth's centre")
            s = tau - (t - t0)
            speed = float(np.linalg.norm(v))
            vh = v / speed
            acc = self.acceleration(y, c / s)
            if not with_sens:
                return np.concatenate([v, acc])
            phi = y[6:].reshape(6, 8)
            da_dr = self._gravity_gradient(r)
            da_dv = (c / s) * (np.eye(3) - np.outer(vh, vh)) / speed
            if self.earth_rate:
                da_dr = da_dr - wx @ wx
                da_dv = da_dv - 2.0 * wx
            dphi = np.empty((6, 8))
            dphi[:3] = phi[3:]
            dphi[3:] = da_dr @ phi[:3] + da_dv @ phi[3:]
            dphi[3:, 6] += vh / s
            dphi[3:, 7] -= (c / s**2) * vh
            return np.concatenate([v, acc, dphi.ravel()])

        return rhs

    def propagate(self, theta: ArrayLike, t: ArrayLike, jacobian: bool = True) -> Flight:
        """States (and sensitivities) at times ``t`` (any order) from ``theta``.

        Raises
        ------
        FlightError
            ``tau`` ends within :data:`_MIN_MASS_TIME_S` of a requested time, the speed is
            zero, or the integration fails.
        """
        th = np.asarray(theta, dtype=np.float64).reshape(-1)
        if th.shape != (8,) or not np.all(np.isfinite(th)):
            raise FlightError(f'rocket parameters must be 8 finite numbers; got {th}')
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        if tt.size == 0:
            return Flight(tt, np.zeros((0, 6)), np.zeros((0, 6, 8)), np.zeros(0))
        if th[7] - (tt.max() - self.epoch) < _MIN_MASS_TIME_S:
            raise FlightError(
                f'the mass runs out at {self.epoch + th[7]:.3f} s, before the last time '
                f'{tt.max():.3f} s'
            )
        late = th[7] - (tt.max() - self.epoch)
        if th[6] <= 0.0 or th[6] / late > _MAX_THRUST:
            raise FlightError(
                f'the thrust acceleration reaches {th[6] / late:.3g} m/s^2 within the span '
                f'(exhaust speed {th[6]:.4g} m/s, mass time {th[7]:.4g} s): no vehicle'
            )
        if np.linalg.norm(th[3:6]) <= 0.0:
            raise FlightError('the thrust direction needs a nonzero velocity')
        n = 54 if jacobian else 6
        y0 = np.zeros(n)
        y0[:6] = th[:6]
        if jacobian:
            y0[6:] = np.hstack([np.eye(6), np.zeros((6, 2))]).ravel()
        rhs = self._rhs(th, jacobian)
        tu, back = np.unique(tt, return_inverse=True)  # many rows share an epoch
        out = np.empty((tu.size, n))
        at = tu == self.epoch
        out[at] = y0
        for sel, end in ((tu > self.epoch, tu[-1]), (tu < self.epoch, tu[0])):
            if not np.any(sel):
                continue
            ts = tu[sel] if end > self.epoch else tu[sel][::-1]
            sol = solve_ivp(
                rhs,
                (self.epoch, float(end)),
                y0,
                method='DOP853',
                t_eval=ts,
                rtol=_RTOL,
                atol=_ATOL[:n],
            )
            if not sol.success or sol.y.shape[1] != ts.size or not np.all(np.isfinite(sol.y)):
                raise FlightError(f'integration failed: {sol.message}')
            out[sel] = sol.y.T if end > self.epoch else sol.y.T[::-1]
        out = out[back]
        sens = out[:, 6:].reshape(-1, 6, 8) if jacobian else None
        return Flight(tt, out[:, :6].copy(), sens, self.thrust(th, tt))
