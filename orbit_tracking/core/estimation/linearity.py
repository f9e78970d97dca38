"""Where a window's covariance still describes its error (issue 14).

The covariance of a window is that of the problem linearised at the solution. Where the
data leave a state uncertain (an incomplete segment seen by two CW radars, a window edge
inside it), the measurements are no longer linear over one sigma: a range changes by
``sigma_perp^2 / (2 R)`` across the ellipsoid's long axis, which at 170 m and 30 km is
already a CW radar's sigma. There the estimate can sit hundreds of metres off along a
direction the linearisation calls thin (robustness draws had states 20-160 sigma off by
their own ellipsoid, with nothing in the residuals to say so).

:func:`nonlinear_spans` measures that directly: at every sample time it moves the state
:data:`EXCURSION` (3) sigma either way along its covariance's longest position axis and
takes the second difference of every nearby station value, in sigmas of that value as the
fit knows it (the smaller of the row's sigma and ``sqrt(J P J^T)``: a bend smaller than one
row's sigma still misleads a fit that knows the value to a centimetre). Above
``nonlinear_sigma`` the linear covariance is no statement about the error, and
:meth:`~orbit_tracking.core.estimation.results.TargetSolution.states` publishes the largest
sigma in every direction there (:func:`isotropic`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.models.measurements import StationPose, predict, residual

__all__ = ['EXCURSION', 'SAMPLE_S', 'StationRows', 'isotropic', 'nonlinear_spans']

FloatArray = NDArray[np.float64]

Segment = tuple[float, float]

SAMPLE_S = 0.5
"""Spacing [s] of the sample times the test is made at."""

EXCURSION = 3.0
"""How far [sigmas] along the longest axis the test moves the state: the linear
covariance has to hold over the region the estimate is likely in, not only at one sigma."""

NEAR_S = 1.0
"""A station value within this many seconds of a sample time is used at that time."""

StationRows = tuple[tuple[str, ...], FloatArray, FloatArray, StationPose]
"""One station's rows: field names, times (m,), sigmas (m, k), poses."""


def isotropic(cov: FloatArray, where: NDArray[np.bool_]) -> FloatArray:
    """``cov`` (m, 6, 6) with its position and velocity blocks replaced by their largest
    variance times the identity at the rows ``where`` (cross terms kept, so the result
    exceeds ``cov`` by a positive semidefinite matrix: never smaller in any direction).
    Rows that are not finite are left as they are."""
    sel = where & np.isfinite(cov).all(axis=(1, 2))
    if not sel.any():
        return cov
    out = cov.copy()
    eye = np.eye(3)
    for blk in (slice(0, 3), slice(3, 6)):
        lam = np.linalg.eigvalsh(cov[sel][:, blk, blk])[:, -1]
        sub = out[sel]
        sub[:, blk, blk] = lam[:, None, None] * eye
        out[sel] = sub
    return out


def nonlinear_spans(
    times: FloatArray,
    states: FloatArray,
    cov: FloatArray,
    stations: Sequence[StationRows],
    limit: float,
) -> tuple[Segment, ...]:
    """Spans around the sample ``times`` (m,) where a station value within :data:`NEAR_S`
    changes to second order by more than ``limit`` of its sigma (the row's, or the value's
    own ``sqrt(J P J^T)`` if smaller) across :data:`EXCURSION`
    sigma of the state (``states`` (m, 6), ``cov`` (m, 6, 6)) along its longest position axis."""
    m = times.size
    if m == 0 or limit <= 0.0:
        return ()
    ok = np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(states).all(axis=1)
    worst = np.zeros(m)
    if ok.any():
        lam, vec = np.linalg.eigh(cov[ok][:, :3, :3])
        step = np.zeros((m, 3))
        step[ok] = EXCURSION * vec[:, :, -1] * np.sqrt(np.maximum(lam[:, -1], 0.0))[:, None]
        for fields, t, sig, pose in stations:
            if t.size == 0:
                continue
            j = np.clip(np.searchsorted(t, times), 1, t.size - 1) if t.size > 1 else None
            near = (
                np.zeros(m, dtype=np.intp)
                if j is None
                else np.where(np.abs(t[j - 1] - times) <= np.abs(t[j] - times), j - 1, j)
            )
            use = ok & (np.abs(t[near] - times) <= NEAR_S)
            if not use.any():
                continue
            idx = near[use]
            x0 = states[use]
            xp, xm = x0.copy(), x0.copy()
            xp[:, :3] += step[use]
            xm[:, :3] -= step[use]
            with np.errstate(all='ignore'):
                f0, jac = predict(fields, x0, pose.take(idx), jacobian=True)
                assert jac is not None
                f, _ = predict(fields, np.vstack([xp, xm]), pose.take(np.concatenate([idx, idx])))
                k = idx.size
                second = residual(fields, f[:k], f0) + residual(fields, f[k:], f0)
                # the value's own precision from the state (J P J^T): a fit of many
                # rows knows a value far better than one row's sigma, and a bend of the
                # long axis by more than that is what the linear covariance misses
                fitted = np.sqrt(np.maximum(np.einsum('mki,mij,mkj->mk', jac, cov[use], jac), 0.0))
                scale = np.minimum(sig[idx], np.maximum(fitted, 1e-3 * sig[idx]))
                c = np.abs(second) / (2.0 * scale)
            c = np.where(np.isfinite(c), c, np.inf).max(axis=1)
            worst[use] = np.maximum(worst[use], c)
    bad = worst > limit
    if not bad.any():
        return ()
    spans: list[Segment] = []
    half = 0.5 * SAMPLE_S
    for i in np.flatnonzero(bad):
        a, b = float(times[i] - half), float(times[i] + half)
        if spans and a <= spans[-1][1] + 1e-9:
            spans[-1] = (spans[-1][0], b)
        else:
            spans.append((a, b))
    return tuple(spans)
