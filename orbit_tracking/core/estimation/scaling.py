"""Jacobi scaling of symmetric normal matrices, shared by every solve of the estimator.

The unknowns' scales span many decades (a telemetry level with a prior of tens of metres
beside stiff B-spline coefficients, a station bias in microradians), so a normal matrix is
solved as ``D^-1/2 (D^-1/2 A D^-1/2 + ridge I)^-1 D^-1/2`` with ``D`` its diagonal: the scaled
matrix has a unit diagonal, and the cut-offs of a least-squares or pseudo-inverse solve act
on directions of comparable size instead of dropping those of the small unknowns.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = ['jacobi_scaled', 'scaled_solve']


def jacobi_scaled(a: FloatArray, ridge: float = 0.0) -> tuple[FloatArray, FloatArray]:
    """``(D^-1/2 A D^-1/2 + ridge I, sqrt(diag A))``; a zero diagonal element counts as
    1e-300 (its row and column are then huge, not NaN)."""
    d = np.sqrt(np.maximum(np.diag(a), 1e-300))
    scaled = a / d[:, None] / d[None, :]
    if ridge:
        scaled[np.diag_indices_from(scaled)] += ridge
    return scaled, d


def scaled_solve(
    a: FloatArray, b: FloatArray, ridge: float = 0.0, cholesky: bool = True
) -> tuple[FloatArray, bool]:
    """``x`` with ``(A + ridge D) x = b`` solved on the Jacobi-scaled matrix (``b`` a vector
    or a matrix of columns), and whether Cholesky was used: it is tried first when
    ``cholesky``; otherwise, or when it fails, least squares with ``rcond = 1e-12`` (the
    minimum-norm solution in the scaled unknowns)."""
    scaled, d = jacobi_scaled(a, ridge)
    dd = d.reshape((-1,) + (1,) * (np.ndim(b) - 1))  # rows of b, whatever its columns
    rhs = b / dd
    if cholesky:
        try:
            cf = sla.cho_factor(scaled, check_finite=False)
            return sla.cho_solve(cf, rhs, check_finite=False) / dd, True
        except np.linalg.LinAlgError:
            pass
    return np.linalg.lstsq(scaled, rhs, rcond=1e-12)[0] / dd, False
