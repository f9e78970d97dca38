"""Accuracy figures: errors against truth, normalised estimation error squared (NEES)
and its chi-square consistency band."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.chi2 import chi2_ppf

__all__ = ['NeesSummary', 'hermite_states', 'nees', 'nees_summary']

FloatArray = NDArray[np.float64]


def nees(errors: ArrayLike, covariances: ArrayLike) -> FloatArray:
    """``e_kᵀ P_k⁻¹ e_k`` for errors (n, d) and covariances (n, d, d)."""
    e = np.asarray(errors, dtype=np.float64)
    p = np.asarray(covariances, dtype=np.float64)
    return np.einsum('ni,ni->n', e, np.linalg.solve(p, e[..., None])[..., 0])


@dataclass(frozen=True)
class NeesSummary:
    """Mean NEES of n independent samples and its two-sided chi-square band.

    If the covariances are right, ``n * mean`` follows χ²(n·dof), so the mean lies in
    ``[lo, hi]`` with probability ``probability``.
    """

    mean: float
    n: int
    dof: int
    lo: float
    hi: float
    probability: float

    @property
    def consistent(self) -> bool:
        return self.lo <= self.mean <= self.hi

    def __str__(self) -> str:
        verdict = 'inside' if self.consistent else 'OUTSIDE'
        return (
            f'mean NEES {self.mean:.3f} over {self.n} fixes (dof {self.dof}); '
            f'{100 * self.probability:.0f}% band [{self.lo:.3f}, {self.hi:.3f}]: {verdict}'
        )


def nees_summary(values: ArrayLike, dof: int = 3, probability: float = 0.95) -> NeesSummary:
    """Mean of NEES values and the chi-square band for their number."""
    v = np.asarray(values, dtype=np.float64)
    n = int(v.size)
    if n == 0:
        raise ValueError('no NEES values')
    a = (1.0 - probability) / 2.0
    return NeesSummary(
        float(v.mean()),
        n,
        dof,
        float(chi2_ppf(a, n * dof)) / n,
        float(chi2_ppf(1.0 - a, n * dof)) / n,
        probability,
    )


def hermite_states(
    t_samples: ArrayLike, positions: ArrayLike, velocities: ArrayLike, t: ArrayLike
) -> FloatArray:
    """Position (m, 3) at times ``t`` by cubic Hermite interpolation of state samples
    (truth at a few hertz is then exact to well below a millimetre for our vehicles).

    Times outside the samples give NaN rows.
    """
    ts = np.asarray(t_samples, dtype=np.float64)
    p = np.asarray(positions, dtype=np.float64)
    v = np.asarray(velocities, dtype=np.float64)
    tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
    i = np.clip(np.searchsorted(ts, tt) - 1, 0, ts.size - 2)
    h = ts[i + 1] - ts[i]
    s = ((tt - ts[i]) / h)[:, None]
    hh = h[:, None]
    out = (
        (2 * s**3 - 3 * s**2 + 1) * p[i]
        + (s**3 - 2 * s**2 + s) * hh * v[i]
        + (-2 * s**3 + 3 * s**2) * p[i + 1]
        + (s**3 - s**2) * hh * v[i + 1]
    )
    out[(tt < ts[0] - 1e-9) | (tt > ts[-1] + 1e-9)] = np.nan
    return out
