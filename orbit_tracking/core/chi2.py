"""Chi-square quantiles for the core's tests and gates, without ``scipy.stats``.

``scipy.stats`` takes most of a second to import (it builds every distribution and parses
their docstrings), and the triangulation, the estimator and the simulator each need two
functions of one distribution from it; every node and command process paid for it at start.
These are the special functions ``scipy.stats.chi2`` itself evaluates (``gammaincinv`` for
the quantile, ``chdtri`` for the upper one), with its answers at the ends of [0, 1], so the
numbers are the same to the last bit (test_chi2.py compares them).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

__all__ = ['chi2_isf', 'chi2_isf_each', 'chi2_ppf', 'chi2_ppf_each']


def chi2_ppf(p: float, dof: float) -> float:
    """The value a chi-square variable with ``dof`` degrees of freedom stays below with
    probability ``p`` (``scipy.stats.chi2.ppf``): 0 at p = 0, inf at p = 1, NaN outside
    [0, 1] or for ``dof`` <= 0."""
    if not dof > 0 or not 0 <= p <= 1:
        return math.nan
    if p == 0:
        return 0.0
    if p == 1:
        return math.inf
    return float(2 * special.gammaincinv(dof / 2, p))


def chi2_isf(p: float, dof: float) -> float:
    """The value a chi-square variable with ``dof`` degrees of freedom exceeds with
    probability ``p`` (``scipy.stats.chi2.isf``): inf at p = 0, 0 at p = 1, NaN outside
    [0, 1] or for ``dof`` <= 0."""
    if not dof > 0 or not 0 <= p <= 1:
        return math.nan
    if p == 0:
        return math.inf
    if p == 1:
        return 0.0
    return float(special.chdtri(dof, p))


def chi2_ppf_each(p: float, dof: ArrayLike) -> NDArray[np.float64]:
    """:func:`chi2_ppf` of one probability for each of an array of degrees of freedom."""
    k = np.asarray(dof, dtype=np.float64)
    out = np.full(k.shape, math.nan)
    ok = k > 0
    if 0 < p < 1:
        out[ok] = 2 * special.gammaincinv(k[ok] / 2, p)
    elif p in (0, 1):
        out[ok] = 0.0 if p == 0 else math.inf
    return out


def chi2_isf_each(p: float, dof: ArrayLike) -> NDArray[np.float64]:
    """:func:`chi2_isf` of one probability for each of an array of degrees of freedom."""
    k = np.asarray(dof, dtype=np.float64)
    out = np.full(k.shape, math.nan)
    ok = k > 0
    if 0 < p < 1:
        out[ok] = special.chdtri(k[ok], p)
    elif p in (0, 1):
        out[ok] = math.inf if p == 0 else 0.0
    return out
