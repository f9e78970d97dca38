"""Accuracy figures: errors against truth, normalised estimation error squared (NEES)
and its chi-square consistency band, for independent samples or correlated ones."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.chi2 import chi2_ppf

__all__ = [
    'NEES_BAND_DRAWS',
    'NeesSummary',
    'correlated_nees_band',
    'hermite_states',
    'nees',
    'nees_summary',
    'whitened_correlation',
]

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


def whitened_correlation(
    covariance: ArrayLike, dof: int = 3, finite: ArrayLike | None = None
) -> FloatArray:
    """The joint covariance ``(n dof, n dof)`` of ``n`` samples' errors, each sample's
    block whitened by its own (``W Σ W^T`` with ``W`` block diagonal, ``W_k Σ_kk W_k^T =
    I``): the correlation of the errors an honest estimator's NEES normalises. Samples
    not ``finite`` (an infinite bound) are counted as independent of the rest."""
    c = np.asarray(covariance, dtype=np.float64)
    n = c.shape[0] // dof
    ok = np.ones(n, dtype=bool) if finite is None else np.asarray(finite, dtype=bool)
    w = np.zeros_like(c)
    for k in np.flatnonzero(ok):
        sl = slice(dof * k, dof * k + dof)
        val, vec = np.linalg.eigh(0.5 * (c[sl, sl] + c[sl, sl].T))
        val = np.maximum(val, 1e-300 * max(float(val.max()), 1e-300))
        w[sl, sl] = (vec / np.sqrt(val)) @ vec.T
    r = w @ c @ w.T
    for k in np.flatnonzero(~ok):
        sl = slice(dof * k, dof * k + dof)
        r[sl, :] = 0.0
        r[:, sl] = 0.0
        r[sl, sl] = np.eye(dof)
    return 0.5 * (r + r.T)


NEES_BAND_DRAWS = 40_000
"""Monte Carlo draws of :func:`correlated_nees_band` (fixed seed: the same band every call;
quantile errors about 1 % of the band)."""


def correlated_nees_band(
    correlation: ArrayLike, dof: int = 3, probability: float = 0.95
) -> tuple[float, float, float]:
    """The two-sided ``probability`` band of the mean NEES of ``n`` samples whose
    whitened errors are correlated as ``correlation`` (:func:`whitened_correlation`),
    and the probability that it lies inside the band of independent samples
    (:func:`nees_summary`).

    ``n`` times the mean NEES is then ``sum_i l_i z_i^2`` with ``l_i`` the eigenvalues of
    the correlation and ``z_i`` independent standard normal: mean ``n dof`` as for
    independent samples, variance ``2 sum l_i^2`` instead of ``2 n dof``. Its quantiles
    are those of :data:`NEES_BAND_DRAWS` draws of that sum (a scaled chi-square with the
    same two moments put the lower end a third too low where the errors are correlated
    over the whole span). Errors correlated over the whole span (a telemetry bias the
    stations cannot separate) leave few independent samples: the mean NEES of an honest
    estimator then falls outside the independent band far more often than ``1 -
    probability``."""
    r = np.asarray(correlation, dtype=np.float64)
    n = r.shape[0] // dof
    lam = np.clip(np.linalg.eigvalsh(0.5 * (r + r.T)), 0.0, None) / n
    big = lam > 1e-6 * max(float(lam.max()), 1e-300)
    rng = np.random.default_rng(20261206)
    chunks = []
    for _ in range(NEES_BAND_DRAWS // 10_000):
        z = rng.standard_normal((10_000, int(big.sum())))
        chunks.append((z**2) @ lam[big] + float(lam[~big].sum()))
    q = np.concatenate(chunks)
    a = (1.0 - probability) / 2.0
    lo, hi = np.quantile(q, [a, 1.0 - a])
    ind = nees_summary(np.full(n, float(dof)), dof, probability)
    return float(lo), float(hi), float(np.mean((q >= ind.lo) & (q <= ind.hi)))


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
