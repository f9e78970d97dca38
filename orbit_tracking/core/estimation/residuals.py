"""Whitened-residual statistics per station: of one window (what the estimator node reports
on ``estimator/window_residuals``) and summed over a pass (what the results node reports).

The residual of a measured value is ``(measured - predicted) / sigma`` after the window's
solve (:attr:`~orbit_tracking.core.estimation.estimator.Estimate.residuals`): with a model that
fits and honest sigmas, about zero mean and unit RMS.

Consecutive windows overlap, so the same measurement is fitted by two windows. To let the
statistics of successive windows be summed without counting a measurement twice, a
window's statistics can be restricted to the rows after a time (the end of the previous
window): every measurement then counts in the first window that fitted it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # the estimator is heavy to import; the messages only need ResidualStats
    from orbit_tracking.core.data.observations import Observations
    from orbit_tracking.core.estimation.results import Estimate

__all__ = ['ResidualStats', 'window_residual_stats']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class ResidualStats:
    """Whitened-residual statistics of one station's measurement rows.

    Attributes
    ----------
    station : str
    fields : tuple of str
        Measured fields, in the order of the arrays below.
    rows : int
        Measurement rows (one epoch of one target).
    count : ndarray of int, shape (k,)
        Values with a residual (measured and not rejected), per field.
    total, total_sq : ndarray, shape (k,)
        Sum and sum of squares of those residuals [1].
    rejected : ndarray of int, shape (k,)
        Measured values rejected by the estimator's residual gate, per field.
    not_measured : int
        Values the rows do not carry (NaN).
    """

    station: str
    fields: tuple[str, ...]
    rows: int
    count: IntArray
    total: FloatArray
    total_sq: FloatArray
    rejected: IntArray
    not_measured: int

    def __post_init__(self) -> None:
        k = len(self.fields)
        for name in ('count', 'total', 'total_sq', 'rejected'):
            if np.shape(getattr(self, name)) != (k,):
                raise ValueError(
                    f'station {self.station}: {name} must have shape ({k},) for fields '
                    f'{self.fields}; got {np.shape(getattr(self, name))}'
                )

    @classmethod
    def from_moments(
        cls,
        station: str,
        fields: tuple[str, ...],
        rows: int,
        count: Mapping[str, int],
        mean: Mapping[str, float],
        rms: Mapping[str, float],
        rejected: Mapping[str, int],
        not_measured: int,
    ) -> ResidualStats:
        """Statistics given as count, mean and RMS per field (as in the messages)."""
        n = np.array([int(count[f]) for f in fields], dtype=np.int64)
        mu = np.array([float(mean[f]) if count[f] else 0.0 for f in fields])
        r = np.array([float(rms[f]) if count[f] else 0.0 for f in fields])
        return cls(
            station,
            tuple(fields),
            int(rows),
            n,
            n * mu,
            n * r**2,
            np.array([int(rejected.get(f, 0)) for f in fields], dtype=np.int64),
            int(not_measured),
        )

    @property
    def mean(self) -> FloatArray:
        """Mean residual per field (NaN without values)."""
        with np.errstate(invalid='ignore', divide='ignore'):
            return np.where(self.count > 0, self.total / np.maximum(self.count, 1), math.nan)

    @property
    def rms(self) -> FloatArray:
        """Root mean square residual per field (NaN without values)."""
        with np.errstate(invalid='ignore', divide='ignore'):
            return np.where(
                self.count > 0, np.sqrt(self.total_sq / np.maximum(self.count, 1)), math.nan
            )

    def merged(self, other: ResidualStats) -> ResidualStats:
        """Statistics of both sets of rows (fields in first-seen order)."""
        if other.station != self.station:
            raise ValueError(
                f'cannot merge statistics of stations {self.station!r} and {other.station!r}'
            )
        fields = self.fields + tuple(f for f in other.fields if f not in self.fields)

        def pad(s: ResidualStats, a: NDArray[Any]) -> NDArray[Any]:
            out = np.zeros(len(fields), dtype=a.dtype)
            for j, f in enumerate(s.fields):
                out[fields.index(f)] = a[j]
            return out

        return ResidualStats(
            self.station,
            fields,
            self.rows + other.rows,
            pad(self, self.count) + pad(other, other.count),
            pad(self, self.total) + pad(other, other.total),
            pad(self, self.total_sq) + pad(other, other.total_sq),
            pad(self, self.rejected) + pad(other, other.rejected),
            self.not_measured + other.not_measured,
        )


def window_residual_stats(
    est: Estimate, obs: Observations, after: float | None = None
) -> dict[str, ResidualStats]:
    """Per-station statistics of a window's whitened residuals.

    Parameters
    ----------
    est : Estimate
        The solved window.
    obs : Observations
        What it was solved from (to tell values the gate rejected from values the rows do
        not carry: both have no residual).
    after : float, optional
        Count only rows with time > ``after`` [s] (the previous window's end); default:
        every row of the window.

    Returns
    -------
    dict of station id to ResidualStats
        Stations with at least one row counted, sorted by id.
    """
    lo = -math.inf if after is None else after
    blocks: dict[str, list[tuple[tuple[str, ...], FloatArray]]] = {}
    for key, (t, fields, r) in est.residuals.items():
        station = key.split('/', 1)[0]  # 'station/target' for the other targets
        keep = np.asarray(t) > lo
        if np.any(keep):
            blocks.setdefault(station, []).append((tuple(fields), np.asarray(r)[keep]))
    # values the rows do not carry, per station and field, from the same rows
    missing: dict[str, dict[str, int]] = {}
    targets = np.array(sorted(est.targets), dtype=np.int64)
    for s in obs.stations:
        tab = s.table
        keep = (
            (tab.time >= est.t0)
            & (tab.time <= est.t1)
            & (tab.time > lo)
            & np.isin(np.asarray(tab.target_id, dtype=np.int64), targets)
        )
        if not np.any(keep):
            continue
        unmeasured = ~(np.isfinite(tab.values[keep]) & (tab.sigmas[keep] > 0.0))
        per = missing.setdefault(tab.station_id, {})
        for j, f in enumerate(tab.fields):
            per[f] = per.get(f, 0) + int(np.count_nonzero(unmeasured[:, j]))
    out: dict[str, ResidualStats] = {}
    for station in sorted(blocks):
        parts = [_block_stats(station, fields, r) for fields, r in blocks[station]]
        total = parts[0]
        for part in parts[1:]:
            total = total.merged(part)
        nm = missing.get(station, {})
        not_measured = np.array([nm.get(f, 0) for f in total.fields], dtype=np.int64)
        out[station] = ResidualStats(
            station,
            total.fields,
            total.rows,
            total.count,
            total.total,
            total.total_sq,
            np.maximum(total.rejected - not_measured, 0),
            int(not_measured.sum()),
        )
    return out


def _block_stats(station: str, fields: tuple[str, ...], r: FloatArray) -> ResidualStats:
    """Statistics of one residual block; ``rejected`` counts every value without a
    residual (gated or not measured) until the caller takes the unmeasured ones out."""
    finite = np.isfinite(r)
    rz = np.where(finite, r, 0.0)
    return ResidualStats(
        station,
        fields,
        int(r.shape[0]),
        finite.sum(axis=0).astype(np.int64),
        rz.sum(axis=0),
        (rz**2).sum(axis=0),
        (~finite).sum(axis=0).astype(np.int64),
        0,
    )
