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
import scipy.sparse as sp
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = ['jacobi_scaled', 'normal_matrix', 'scaled_solve']

DENSE_ROW_FRACTION = 0.2
"""A Jacobian row with nonzeros in more than this share of the columns (and more than
:data:`DENSE_ROW_MIN`) goes through the dense product in :func:`normal_matrix`."""

DENSE_ROW_MIN = 64


def normal_matrix(jac: sp.spmatrix | sp.sparray) -> FloatArray:
    """``J^T J`` as a dense array, the same numbers as ``(jac.T @ jac).toarray()`` up to
    rounding. The estimator's Jacobians are mostly rows of a few spline coefficients, with
    a few hundred rows over every coefficient (the jerk prior's square root, the telemetry
    error prior); a sparse product spends most of its time on those, so they go through
    one dense (BLAS) product and the rest through the sparse one (six to eight times
    faster on a 13 000 x 360 window Jacobian with 300 full rows)."""
    j = sp.csr_matrix(jac)
    counts = np.diff(j.indptr)
    dense = counts > max(DENSE_ROW_MIN, DENSE_ROW_FRACTION * j.shape[1])
    if not dense.any():
        return np.asarray((j.T @ j).toarray())
    thin = j[np.flatnonzero(~dense)]
    full = j[np.flatnonzero(dense)].toarray()
    out = np.asarray((thin.T @ thin).toarray())
    out += full.T @ full
    return out


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
