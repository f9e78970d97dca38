"""Plausibility limits of measured values, their sigmas and message-level quantities.

A value outside these limits cannot come from a working tracking sensor in this package's
domain (ground radars, theodolites, ships, observing satellites looking at a vehicle
between the ground and a few Earth radii), so it is a fault of the source: the row is
dropped at the boundary and counted by reason, before it can reach a fit. The limits are
wide on purpose: they catch corrupt and hostile data (a range of 1e300 m, an elevation of
4 rad, a sigma of 1e-300 whose weight would overflow), not merely poor measurements, which
are the estimator's residual gate's job.

===============  ====================  ========================
field            value                 sigma
===============  ====================  ========================
``range``        [0, 1e9] m            [1e-6, 1e7] m
``range_rate``   [-1e5, 1e5] m/s       [1e-6, 1e5] m/s
``azimuth``      [-4 pi, 4 pi] rad     [1e-12, pi] rad
``elevation``    [-pi/2, pi/2] rad     [1e-12, pi] rad
``los_alpha``    [-1e6, 1e6]           [1e-12, 1e6]
``los_beta``     [-1e6, 1e6]           [1e-12, 1e6]
===============  ====================  ========================

(1e9 m is about 2.6 times the Moon's distance; 1e5 m/s is over ten times orbital speed;
azimuth may come in either [0, 2 pi) or (-pi, pi] or unwrapped by one turn.)
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = [
    'MAX_POINTS',
    'MAX_POSITION_M',
    'MAX_SPEED_MPS',
    'MAX_TARGET_ID',
    'MAX_TIME_OFFSET_S',
    'SIGMA_LIMITS',
    'TargetLimit',
    'VALUE_LIMITS',
    'implausible_rows',
    'state_problem',
]

FloatArray = NDArray[np.float64]

VALUE_LIMITS: dict[str, tuple[float, float]] = {
    'range': (0.0, 1e9),
    'range_rate': (-1e5, 1e5),
    'azimuth': (-4.0 * math.pi, 4.0 * math.pi),
    'elevation': (-0.5 * math.pi - 1e-9, 0.5 * math.pi + 1e-9),
    'los_alpha': (-1e6, 1e6),
    'los_beta': (-1e6, 1e6),
}
"""Closed interval of plausible values per measurement field (units of the field)."""

SIGMA_LIMITS: dict[str, tuple[float, float]] = {
    'range': (1e-6, 1e7),
    'range_rate': (1e-6, 1e5),
    'azimuth': (1e-12, math.pi),
    'elevation': (1e-12, math.pi),
    'los_alpha': (1e-12, 1e6),
    'los_beta': (1e-12, 1e6),
}
"""Closed interval of plausible standard deviations per field. The lower limit keeps the
weight ``1 / sigma^2`` far from overflow; the upper one rejects sigmas that say "no
information" (send no value instead)."""

MAX_TIME_OFFSET_S = 3600.0
"""Largest ``|time_offset|`` [s] of a point in a measurement message: a station may batch
an hour of epochs in one message (store and forward after a link outage), not more."""

MAX_POINTS = 100_000
"""Largest number of points in one measurement message."""

MAX_TARGET_ID = 2**31 - 1
"""Largest target id. The wire field is UINT32, but the ids past the signed 32-bit range
are what -1 and other negative sentinels become when written as UINT32 ("no id", "not
set"), and the ids a node prints, publishes in topic names and hands to other tools
(``int32`` marker ids, integer columns) must fit a signed 32-bit integer."""

MAX_POSITION_M = 1e9
"""Largest distance [m] of a state (station, telemetry, fix) from the world frame's
origin, whichever world frame (ECEF, ECI, a local one) is used."""

MAX_SPEED_MPS = 1e5
"""Largest speed [m/s] of a state."""

_STATE_SIGMA = {'position': (1e-6, 1e7), 'velocity': (1e-6, 1e5)}


def implausible_rows(
    fields: Sequence[str], values: FloatArray, sigmas: FloatArray
) -> tuple[NDArray[np.bool_], Counter[str]]:
    """The rows of a batch that hold an implausible measured value or sigma.

    Parameters
    ----------
    fields : sequence of str
        Field of each column (keys of :data:`VALUE_LIMITS`).
    values, sigmas : ndarray, shape (n, k)
        Measured values and their sigmas; NaN values are "not measured" and ignored.

    Returns
    -------
    bad : ndarray of bool, shape (n,)
        Rows to drop.
    reasons : Counter
        Those rows per reason: ``<field>_out_of_range`` (a value outside
        :data:`VALUE_LIMITS`, infinities included) or ``sigma_<field>_out_of_range``
        (outside :data:`SIGMA_LIMITS`, non-finite included). A row counts once, under the
        first reason found in field order.
    """
    n = values.shape[0]
    bad = np.zeros(n, dtype=bool)
    reasons: Counter[str] = Counter()
    for j, f in enumerate(fields):
        measured = ~np.isnan(values[:, j])
        lo, hi = VALUE_LIMITS[f]
        v_bad = measured & ~((values[:, j] >= lo) & (values[:, j] <= hi))
        slo, shi = SIGMA_LIMITS[f]
        s = sigmas[:, j]
        s_bad = measured & ~v_bad & ~(np.isfinite(s) & (s >= slo) & (s <= shi))
        for key, mask in ((f'{f}_out_of_range', v_bad), (f'sigma_{f}_out_of_range', s_bad)):
            new = mask & ~bad
            if np.any(new):
                reasons[key] += int(new.sum())
                bad |= new
    return bad, reasons


class TargetLimit:
    """At most ``max_targets`` distinct target ids, first come.

    A node keeps state (buffers, publishers) per target id, so ids from the wire are
    admitted only while there is room; a flood of ids cannot grow it without bound.
    """

    def __init__(self, max_targets: int) -> None:
        if max_targets < 1:
            raise ValueError(f'max_targets must be >= 1; got {max_targets}')
        self.max_targets = max_targets
        self.known: set[int] = set()

    def admit(self, ids: NDArray[np.integer] | Sequence[int]) -> NDArray[np.bool_]:
        """Which of ``ids`` are admitted (new ones taken in increasing order while there
        is room)."""
        arr = np.asarray(ids, dtype=np.int64).ravel()
        new = sorted(set(np.unique(arr).tolist()) - self.known)
        room = max(self.max_targets - len(self.known), 0)
        self.known.update(new[:room])
        return np.isin(arr, list(self.known))


def state_problem(
    position: FloatArray,
    velocity: FloatArray | None = None,
    position_var: FloatArray | None = None,
    velocity_var: FloatArray | None = None,
) -> str | None:
    """What is implausible about a state (position [m], velocity [m/s], the variances of
    their components [m^2], [m^2/s^2]), or None.

    Limits: :data:`MAX_POSITION_M`, :data:`MAX_SPEED_MPS`, and standard deviations within
    [1e-6, 1e7] m and [1e-6, 1e5] m/s (a variance that was not filled in, 0 or -1, fails).
    """
    checks: list[tuple[str, FloatArray | None, float]] = [
        ('position', position, MAX_POSITION_M),
        ('velocity', velocity, MAX_SPEED_MPS),
    ]
    for name, vec, limit in checks:
        if vec is None:
            continue
        a = np.abs(np.asarray(vec, dtype=np.float64))
        size = float(np.linalg.norm(a)) if np.all(a <= limit) else math.inf  # no overflow
        if not size <= limit:
            return f'{name} of magnitude {size:g} beyond {limit:g}'
    for name, var in (('position', position_var), ('velocity', velocity_var)):
        if var is None:
            continue
        lo, hi = _STATE_SIGMA[name]
        v = np.asarray(var, dtype=np.float64)
        if not np.all((v >= lo * lo) & (v <= hi * hi)):
            return f'{name} variances {v.tolist()} outside [{lo * lo:g}, {hi * hi:g}]'
    return None
