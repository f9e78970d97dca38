"""Seed 003's baseline for the adjoint assimilation: a quadratic polynomial in time per
axis, fitted by weighted least squares to a target's position fixes, over the whole span
or a sliding window; position and velocity with covariance anywhere in the span.

In a window centred on ``t_c`` (``tau = t - t_c``) the position is ``p(t) = a + b tau +
c tau^2`` with ``a, b, c`` in R^3. Each fix ``p_i`` with covariance ``C_i`` weighs in by
``C_i^-1`` (generalised least squares; with diagonal covariances it is one fit per axis,
the seed's)::

    N = sum_i H_i^T C_i^-1 H_i,   H_i = [I, tau_i I, tau_i^2 I]  (3 x 9)
    x = N^-1 sum_i H_i^T C_i^-1 p_i,   cov(x) = N^-1

and the state at ``t`` is ``[p; v] = [[I, tau I, tau^2 I], [0, I, 2 tau I]] x``. The
covariance is formal: a quadratic cannot follow a growing thrust, and the misfit it leaves
(``chi2_dof`` of :meth:`QuadraticTrack.window_fit`) is not folded into it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.data.observations import FixSeries

__all__ = ['QuadraticTrack', 'WindowFit']

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class WindowFit:
    """The quadratic of one window.

    Attributes
    ----------
    t0, t1 : float
        The window [s]; ``center`` is the origin of ``tau``.
    coef : ndarray, shape (9,)
        ``(a, b, c)``: position [m], velocity [m/s] and half the acceleration [m/s^2] at
        the centre.
    covariance : ndarray, shape (9, 9)
    chi2_dof : float
        Whitened misfit of the window's fixes per degree of freedom.
    n_fixes : int
    """

    t0: float
    t1: float
    center: float
    coef: FloatArray
    covariance: FloatArray
    chi2_dof: float
    n_fixes: int


@dataclass(frozen=True)
class QuadraticTrack:
    """Quadratic fits to the fixes of one target.

    Attributes
    ----------
    fixes : FixSeries
    window_s : float or None
        Length of the sliding window [s], centred on each requested time and shifted to
        stay inside the fixes' span; ``None`` fits one quadratic to the whole span.
    """

    fixes: FixSeries
    window_s: float | None = None

    def __post_init__(self) -> None:
        if np.unique(self.fixes.time).size < 3:
            raise ValueError(
                f'target {self.fixes.target_id}: a quadratic needs fixes at 3 epochs or more; '
                f'got {np.unique(self.fixes.time).size}'
            )
        if self.window_s is not None and not self.window_s > 0.0:
            raise ValueError(f'window_s must be > 0 s or None; got {self.window_s}')

    @property
    def target_id(self) -> int:
        return self.fixes.target_id

    @property
    def t0(self) -> float:
        return float(np.min(self.fixes.time))

    @property
    def t1(self) -> float:
        return float(np.max(self.fixes.time))

    def window(self, t: float) -> tuple[float, float]:
        """The window [s] the state at ``t`` comes from."""
        if self.window_s is None or self.window_s >= self.t1 - self.t0:
            return self.t0, self.t1
        lo = min(max(t - 0.5 * self.window_s, self.t0), self.t1 - self.window_s)
        return lo, lo + self.window_s

    def window_fit(self, t0: float, t1: float) -> WindowFit:
        """Weighted least-squares quadratic through the fixes in ``[t0, t1]`` (NaN when
        they lie at fewer than 3 epochs)."""
        fx = self.fixes
        sel = (fx.time >= t0) & (fx.time <= t1)
        sel &= np.all(np.isfinite(fx.position), axis=1)
        sel &= np.all(np.isfinite(fx.covariance), axis=(1, 2))
        center = 0.5 * (t0 + t1)
        if np.unique(fx.time[sel]).size < 3:
            nan = np.full(9, np.nan)
            return WindowFit(t0, t1, center, nan, np.full((9, 9), np.nan), np.nan, 0)
        tau = fx.time[sel] - center
        w = np.linalg.inv(fx.covariance[sel])  # (n, 3, 3)
        h = np.concatenate(
            [
                np.broadcast_to(np.eye(3), (tau.size, 3, 3)),
                tau[:, None, None] * np.eye(3),
                (tau**2)[:, None, None] * np.eye(3),
            ],
            axis=2,
        )  # (n, 3, 9)
        n = np.einsum('nai,nab,nbj->ij', h, w, h)
        rhs = np.einsum('nai,nab,nb->i', h, w, fx.position[sel])
        cov = np.linalg.inv(n)
        coef = cov @ rhs
        r = fx.position[sel] - np.einsum('nai,i->na', h, coef)
        chi2 = float(np.einsum('na,nab,nb->', r, w, r))
        dof = max(3 * tau.size - 9, 1)
        return WindowFit(t0, t1, center, coef, 0.5 * (cov + cov.T), chi2 / dof, int(tau.size))

    def states(self, t: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Position and velocity (m, 6) [m, m/s] and their covariance (m, 6, 6) at ``t``
        (extrapolated beyond the fixes' span by the end windows' quadratics)."""
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        x = np.empty((tt.size, 6))
        cov = np.empty((tt.size, 6, 6))
        fits: dict[tuple[float, float], WindowFit] = {}
        for k, tk in enumerate(tt):
            key = self.window(float(tk))
            if key not in fits:
                fits[key] = self.window_fit(*key)
            f = fits[key]
            tau = tk - f.center
            e = np.eye(3)
            g = np.block([[e, tau * e, tau**2 * e], [np.zeros((3, 3)), e, 2.0 * tau * e]])
            x[k] = g @ f.coef
            cov[k] = g @ f.covariance @ g.T
        return x, cov
