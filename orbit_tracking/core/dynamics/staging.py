"""The rocket model with a second stage (seed 003, issue 15): a staging at an unknown time
``t_s`` after which a new stage burns with its own exhaust speed and mass time.

Parameters (:data:`STAGED_PARAMETERS`, 11): the state at the epoch, the first stage's
``(c1, tau1)``, the staging time ``t_s`` [s] and the second stage's ``(c2, tau2)`` with
``tau2`` counted from ``t_s``::

    a(t) = c1 / (tau1 - (t - t0))   for t < t_s,      c2 / (tau2 - (t - t_s))   after.

Each stage is a :class:`~.rocket.RocketModel` flight; the second starts at ``t_s`` from
the state the first reaches there. The sensitivities chain through the switch: for
``t > t_s``, with ``Phi2`` the second flight's sensitivity to its starting state,
``d y / d theta_1 = Phi2 d y(t_s) / d theta_1`` and ``d y / d t_s = Phi2 f1(t_s) -
f2(y(t), t)``: a later staging starts the second stage from a later state of the first
(``f1`` its rate at ``t_s``) and shifts the second stage's own clock (``f2``, its rate at
``t``). Checked against finite differences in the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core import frames
from orbit_tracking.core.dynamics.rocket import PARAMETERS, Flight, FlightError, RocketModel

__all__ = ['STAGED_PARAMETERS', 'StagedRocketModel', 'staged_start']

FloatArray = NDArray[np.float64]

STAGED_PARAMETERS: tuple[str, ...] = (
    *PARAMETERS,
    'staging_time',
    'exhaust_speed_2',
    'mass_time_2',
)
"""The staged model's parameters: the rocket model's eight, the staging time [s], and the
second stage's exhaust speed [m/s] and mass time at the staging [s]."""

_MARGIN_S = 0.5
"""The staging must fall at least this far inside the span it is asked about."""


@dataclass(frozen=True)
class StagedRocketModel:
    """Two rocket-equation stages (module docstring); the attributes are
    :class:`~.rocket.RocketModel`'s."""

    epoch: float
    gm: float = frames.WGS84_GM
    j2: float = 0.0
    radius: float = frames.WGS84_A
    earth_rate: float = 0.0

    names: tuple[str, ...] = STAGED_PARAMETERS

    @property
    def n_parameters(self) -> int:
        return len(STAGED_PARAMETERS)

    def _stage(self, epoch: float) -> RocketModel:
        return RocketModel(epoch, self.gm, self.j2, self.radius, self.earth_rate)

    def thrust(self, theta: ArrayLike, t: ArrayLike) -> FloatArray:
        """Thrust acceleration magnitude [m/s^2], shape (m,)."""
        th = np.asarray(theta, dtype=np.float64)
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        ts = float(th[8])
        first = th[6] / (th[7] - (tt - self.epoch))
        second = th[9] / (th[10] - (tt - ts))
        return np.where(tt < ts, first, second)

    def propagate(self, theta: ArrayLike, t: ArrayLike, jacobian: bool = True) -> Flight:
        """States (and sensitivities, (m, 6, 11)) at times ``t`` from ``theta``.

        Raises
        ------
        FlightError
            The staging is not inside ``(epoch, last time)``, or a stage cannot fly.
        """
        th = np.asarray(theta, dtype=np.float64).reshape(-1)
        if th.shape != (11,) or not np.all(np.isfinite(th)):
            raise FlightError(f'staged rocket parameters must be 11 finite numbers; got {th}')
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        ts = float(th[8])
        if tt.size and not (self.epoch + _MARGIN_S < ts < float(tt.max()) - _MARGIN_S):
            raise FlightError(
                f'the staging at {ts:.3f} s is not inside the flight '
                f'({self.epoch:.3f}-{float(tt.max()):.3f} s)'
            )
        before = tt < ts
        one = self._stage(self.epoch)
        head = one.propagate(th[:8], np.append(tt[before], ts), jacobian)
        y_s = head.state[-1]
        two = self._stage(ts)
        tail = two.propagate(np.concatenate([y_s, th[9:11]]), tt[~before], jacobian)
        state = np.empty((tt.size, 6))
        state[before] = head.state[:-1]
        state[~before] = tail.state
        sens = None
        if jacobian:
            assert head.sensitivity is not None and tail.sensitivity is not None
            sens = np.zeros((tt.size, 6, 11))
            sens[before, :, :8] = head.sensitivity[:-1]
            phi_s = head.sensitivity[-1]  # d y(t_s) / d theta_1 (6, 8)
            phi2 = tail.sensitivity  # (m2, 6, 8): by y(t_s), c2, tau2
            f1 = np.concatenate(
                [y_s[3:], one.acceleration(y_s, th[6] / (th[7] - (ts - self.epoch)))]
            )
            y2, t2 = tail.state, tt[~before]
            f2 = np.array(
                [
                    np.concatenate([y[3:], two.acceleration(y, th[9] / (th[10] - (ti - ts)))])
                    for y, ti in zip(y2, t2, strict=True)
                ]
            ).reshape(-1, 6)
            sens[~before, :, :8] = np.einsum('mij,jk->mik', phi2[:, :, :6], phi_s)
            sens[~before, :, 8] = np.einsum('mij,j->mi', phi2[:, :, :6], f1) - f2
            sens[~before, :, 9:11] = phi2[:, :, 6:8]
        return Flight(tt, state, sens, self.thrust(th, tt))


def staged_start(theta: FloatArray, t_s: float, epoch: float) -> FloatArray:
    """Staged parameters (11,) from single-stage ones (8,) and a staging time: the second
    stage continues the first's thrust at ``t_s`` with the same exhaust speed."""
    c, tau = float(theta[6]), float(theta[7])
    tau2 = max(tau - (t_s - epoch), 5.0)
    return np.concatenate([theta, [t_s, c, tau2]])
