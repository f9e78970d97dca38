"""Systematic-error (bias) models of a station.

Two kinds of parameters are supported, named as the contract's
``trajectory/biases`` keys without the ``_bias`` suffix:

* an **offset** per value field (``range``, ``range_rate``, ``azimuth``, ``elevation``,
  ``los_alpha``, ``los_beta``): ``measured = true + offset``;
* seed 003's **rotation** ``los_theta`` (dθ) of the line-of-sight pair. The seed writes
  the true values from the measured ones (its eq. 5-39)::

      alpha0 = alpha1 cos dθ - beta1 sin dθ - dα
      beta0  = alpha1 sin dθ + beta1 cos dθ - dβ

  so the forward model used here (measured from true) is its exact inverse::

      [alpha1, beta1] = Rot(-dθ) [alpha0 + dα, beta0 + dβ].

  With ``dθ = 0`` it reduces to the two offsets.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.models.measurements import FIELDS

__all__ = ['BIAS_PARAMETERS', 'CLOCK', 'ESTIMABLE_BIASES', 'BiasModel', 'BiasParameter']

FloatArray = NDArray[np.float64]

BIAS_PARAMETERS: tuple[str, ...] = (*FIELDS, 'los_theta')
"""Every systematic-error parameter of the measured values."""

CLOCK = 'clock'
"""The station's time-tag offset [s]: its clock reads ``t`` when the true time is
``t + clock``, so a row tagged ``t`` measured the target at ``t + clock`` (the station's
own pose is taken at the tag: its navigation data runs on the reference clock)."""

ESTIMABLE_BIASES: tuple[str, ...] = (*BIAS_PARAMETERS, CLOCK)
"""Every systematic error the estimator can declare (``trajectory/biases`` key without
the ``_bias`` suffix)."""


@dataclass(frozen=True)
class BiasModel:
    """Systematic errors of one station.

    Attributes
    ----------
    values : mapping of str to float
        Parameter name (one of :data:`BIAS_PARAMETERS`) to value (field units; rad for
        ``los_theta``). Missing parameters are zero.
    """

    values: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        bad = [k for k in self.values if k not in BIAS_PARAMETERS]
        if bad:
            raise MeasurementError(f'unknown bias parameter(s) {bad}; known: {BIAS_PARAMETERS}')

    def get(self, name: str) -> float:
        return float(self.values.get(name, 0.0))

    def apply(self, fields: Sequence[str], true_values: ArrayLike) -> FloatArray:
        """Measured values from true ones, shape (m, k) with columns ``fields``."""
        y = np.array(true_values, dtype=np.float64, copy=True)
        for j, f in enumerate(fields):
            y[:, j] += self.get(f)
        theta = self.get('los_theta')
        if theta != 0.0:
            ia, ib = _los_columns(fields)
            c, s = np.cos(theta), np.sin(theta)
            a, b = y[:, ia].copy(), y[:, ib].copy()
            y[:, ia] = c * a + s * b
            y[:, ib] = -s * a + c * b
        return y

    def remove(self, fields: Sequence[str], measured: ArrayLike) -> FloatArray:
        """True values from measured ones (the inverse of :meth:`apply`; seed eq. 5-39)."""
        y = np.array(measured, dtype=np.float64, copy=True)
        theta = self.get('los_theta')
        if theta != 0.0:
            ia, ib = _los_columns(fields)
            c, s = np.cos(theta), np.sin(theta)
            a, b = y[:, ia].copy(), y[:, ib].copy()
            y[:, ia] = c * a - s * b
            y[:, ib] = s * a + c * b
        for j, f in enumerate(fields):
            y[:, j] -= self.get(f)
        return y

    def jacobian(
        self, fields: Sequence[str], true_values: ArrayLike, parameters: Sequence[str]
    ) -> tuple[FloatArray, FloatArray]:
        """Derivatives of the measured values.

        Parameters
        ----------
        fields : sequence of str
            Columns of ``true_values``.
        true_values : array_like, shape (m, k)
        parameters : sequence of str
            Bias parameters to differentiate by.

        Returns
        -------
        d_true : ndarray, shape (m, k, k)
            ``d measured / d true``.
        d_param : ndarray, shape (m, k, p)
            ``d measured / d parameters``.
        """
        y0 = np.asarray(true_values, dtype=np.float64)
        m, k = y0.shape
        d_true = np.tile(np.eye(k), (m, 1, 1))
        d_param = np.zeros((m, k, len(parameters)))
        col = {f: j for j, f in enumerate(fields)}
        for q, name in enumerate(parameters):
            if name in col:
                d_param[:, col[name], q] = 1.0
        theta = self.get('los_theta')
        if 'los_alpha' in col and 'los_beta' in col:
            ia, ib = col['los_alpha'], col['los_beta']
            c, s = np.cos(theta), np.sin(theta)
            rot = np.array([[c, s], [-s, c]])
            d_true[:, [ia, ib][0], [ia, ib]] = rot[0]
            d_true[:, [ia, ib][1], [ia, ib]] = rot[1]
            for q, name in enumerate(parameters):
                if name == 'los_alpha':
                    d_param[:, [ia, ib], q] = rot[:, 0]
                elif name == 'los_beta':
                    d_param[:, [ia, ib], q] = rot[:, 1]
            if 'los_theta' in parameters:
                q = list(parameters).index('los_theta')
                a = y0[:, ia] + self.get('los_alpha')
                b = y0[:, ib] + self.get('los_beta')
                d_param[:, ia, q] = -s * a + c * b
                d_param[:, ib, q] = -c * a - s * b
        elif 'los_theta' in parameters:
            raise MeasurementError('los_theta needs both los_alpha and los_beta fields')
        return d_true, d_param


def _los_columns(fields: Sequence[str]) -> tuple[int, int]:
    try:
        return list(fields).index('los_alpha'), list(fields).index('los_beta')
    except ValueError:
        raise MeasurementError(
            f'the los_theta rotation needs los_alpha and los_beta fields; got {list(fields)}'
        ) from None


@dataclass(frozen=True)
class BiasParameter:
    """A systematic error to estimate (or to hold at a known value), like a parameter
    driver: declared per station and parameter name.

    Attributes
    ----------
    station : str
        Station id.
    name : str
        One of :data:`ESTIMABLE_BIASES` (field units; rad for ``los_theta``, s for
        ``clock``).
    prior : float
        Prior (initial) value.
    sigma : float
        Prior standard deviation: a weak prior keeps the estimate bounded when the data
        barely constrain it.
    estimate : bool
        False holds the bias at ``prior`` (a known calibration).
    bounds : (float, float)
        Lower and upper bound; the estimate is projected into them at every step and
        flagged when it ends on one. Default unbounded.
    """

    station: str
    name: str
    prior: float = 0.0
    sigma: float = 1.0
    estimate: bool = True
    bounds: tuple[float, float] = (-math.inf, math.inf)

    def __post_init__(self) -> None:
        if self.name not in ESTIMABLE_BIASES:
            raise MeasurementError(
                f'station {self.station}: unknown bias parameter {self.name!r}; '
                f'known: {ESTIMABLE_BIASES}'
            )
        if not (self.sigma > 0.0 and np.isfinite(self.sigma)):
            raise ValueError(
                f'bias {self.station}/{self.name}: sigma must be > 0; got {self.sigma}'
            )
        if not np.isfinite(self.prior):
            raise ValueError(f'bias {self.station}/{self.name}: prior must be finite')
        lo, hi = self.bounds
        if not lo < hi:
            raise ValueError(
                f'bias {self.station}/{self.name}: bounds must have lower < upper; '
                f'got {self.bounds}'
            )
        if not lo <= self.prior <= hi:
            raise ValueError(
                f'bias {self.station}/{self.name}: prior {self.prior} outside the bounds '
                f'{self.bounds}'
            )
