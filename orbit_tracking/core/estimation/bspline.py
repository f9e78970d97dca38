"""B-spline trajectory model (seed 000): one spline per axis, sparse design matrices.

A coordinate ``s(t) = sum_i c_i B_i(t)`` is a spline of degree ``p`` (order ``p + 1``;
the seed uses order 5) on a clamped knot vector. Its ``p``-th derivative is piecewise
constant and jumps only at interior knots; those jumps are linear in the coefficients,
``d = C c`` (:meth:`SplineAxis.jump_matrix`), which is what the sparse knot selection
minimises. A knot of multiplicity ``m`` leaves the spline ``C^(p - m)`` there, so a
knot repeated ``p - 1`` times lets the acceleration jump (staging, engine cut-off).

:class:`SplineTrajectory` holds three axes expressed in a Cartesian *spline frame*
(``world = origin + R s``), so that each axis can carry its own knots (e.g. downrange,
up and crossrange of seed 000's launch frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import BSpline

__all__ = ['SplineAxis', 'SplineTrajectory', 'clamped_knots']

FloatArray = NDArray[np.float64]


def clamped_knots(interior: ArrayLike, t0: float, t1: float, degree: int) -> FloatArray:
    """Full knot vector: ``t0`` and ``t1`` repeated ``degree + 1`` times around the
    interior knots (which may repeat, at most ``degree`` times each)."""
    inner = np.sort(np.asarray(interior, dtype=np.float64).ravel())
    if inner.size and (inner[0] <= t0 or inner[-1] >= t1):
        raise ValueError(
            f'interior knots must lie strictly inside ({t0}, {t1}); got [{inner[0]}, {inner[-1]}]'
        )
    if not t1 > t0:
        raise ValueError(f'spline span must have t1 > t0; got [{t0}, {t1}]')
    return np.concatenate([np.full(degree + 1, t0), inner, np.full(degree + 1, t1)])


def _derivative_matrix(knots: FloatArray, degree: int) -> sp.csr_matrix:
    """Coefficients of the derivative spline (degree - 1, knots[1:-1]) from those of the
    spline: ``c'_i = p (c_{i+1} - c_i) / (t_{i+p+1} - t_{i+1})``."""
    n = knots.size - degree - 1
    span = knots[degree + 1 : degree + n] - knots[1:n]
    with np.errstate(divide='ignore'):
        w = np.where(span > 0.0, degree / np.where(span > 0.0, span, 1.0), 0.0)
    rows = np.repeat(np.arange(n - 1), 2)
    cols = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).ravel()
    vals = np.stack([-w, w], axis=1).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(n - 1, n))


@dataclass(frozen=True, eq=False)
class SplineAxis:
    """Basis of one coordinate: a clamped knot vector and a degree.

    Attributes
    ----------
    knots : ndarray, shape (n + degree + 1,)
        Full, non-decreasing knot vector [s], end knots repeated ``degree + 1`` times.
    degree : int
        Polynomial degree ``p`` (order ``p + 1``).
    """

    knots: FloatArray
    degree: int

    def __post_init__(self) -> None:
        t = np.asarray(self.knots, dtype=np.float64)
        p = int(self.degree)
        if p < 1:
            raise ValueError(f'spline degree must be >= 1; got {p}')
        if t.ndim != 1 or t.size < 2 * (p + 1):
            raise ValueError(f'knot vector needs at least {2 * (p + 1)} knots; got {t.shape}')
        if np.any(np.diff(t) < 0.0):
            raise ValueError(f'knot vector must be non-decreasing; got {t[:6]}...')
        if (
            np.any(t[: p + 1] != t[0])
            or np.any(t[-p - 1 :] != t[-1])
            or t[p + 1] == t[0]
            or t[-p - 2] == t[-1]
        ):
            raise ValueError(f'knot vector must be clamped (exactly {p + 1} equal end knots)')
        _, counts = np.unique(t[p + 1 : -p - 1], return_counts=True)
        if counts.size and counts.max() > p:
            raise ValueError(f'an interior knot repeats more than degree = {p} times')
        object.__setattr__(self, 'knots', t)
        object.__setattr__(self, 'degree', p)

    @classmethod
    def from_interior(
        cls, interior: ArrayLike, t0: float, t1: float, degree: int = 4
    ) -> SplineAxis:
        return cls(clamped_knots(interior, t0, t1, degree), degree)

    @property
    def n_coef(self) -> int:
        return int(self.knots.size - self.degree - 1)

    @property
    def t0(self) -> float:
        return float(self.knots[0])

    @property
    def t1(self) -> float:
        return float(self.knots[-1])

    @property
    def interior(self) -> FloatArray:
        """Interior knots, repeated ones repeated."""
        return self.knots[self.degree + 1 : -self.degree - 1]

    def _check_times(self, t: FloatArray) -> None:
        if t.size and (t.min() < self.t0 - 1e-9 or t.max() > self.t1 + 1e-9):
            raise ValueError(
                f'times [{t.min()}, {t.max()}] fall outside the spline span [{self.t0}, {self.t1}]'
            )

    def design(self, t: ArrayLike, nu: int = 0) -> sp.csr_matrix:
        """Sparse design matrix ``D[j, i] = B_i^(nu)(t_j)``, shape (m, n_coef)."""
        x = np.clip(np.asarray(t, dtype=np.float64).ravel(), self.t0, self.t1)
        self._check_times(np.asarray(t, dtype=np.float64).ravel())
        knots, deg = self.knots, self.degree
        chain: sp.csr_matrix | None = None
        for _ in range(nu):
            d = _derivative_matrix(knots, deg)
            chain = d if chain is None else d @ chain
            knots, deg = knots[1:-1], deg - 1
            if deg < 0:
                return sp.csr_matrix((x.size, self.n_coef))
        base = BSpline.design_matrix(x, knots, deg).tocsr()
        return base if chain is None else (base @ chain).tocsr()

    def evaluate(self, coef: ArrayLike, t: ArrayLike, nu: int = 0) -> FloatArray:
        """``s^(nu)(t)`` for coefficients ``coef`` (n_coef,) or (n_coef, q)."""
        return np.asarray(self.design(t, nu) @ np.asarray(coef, dtype=np.float64))

    def jump_matrix(self) -> tuple[sp.csr_matrix, FloatArray]:
        """Jumps of the ``degree``-th derivative at the distinct interior knots.

        Returns
        -------
        C : sparse matrix, shape (q, n_coef)
            ``(C c)_j = s^(p)(tau_j+) - s^(p)(tau_j-)`` (seed 000 eqs. 10-13, built here
            from the piecewise-constant ``p``-th derivative of each basis function).
        tau : ndarray, shape (q,)
            The distinct interior knots.
        """
        brk = np.unique(self.knots)
        tau = brk[1:-1]
        if tau.size == 0:
            return sp.csr_matrix((0, self.n_coef)), tau
        mid = 0.5 * (brk[:-1] + brk[1:])  # one point per non-empty interval
        d = self.design(mid, self.degree).toarray()
        return sp.csr_matrix(d[1:] - d[:-1]), tau

    def fit(
        self,
        t: ArrayLike,
        values: ArrayLike,
        weights: ArrayLike | None = None,
        derivative_t: ArrayLike | None = None,
        derivative_values: ArrayLike | None = None,
        derivative_weights: ArrayLike | None = None,
        ridge: float = 1e-9,
    ) -> FloatArray:
        """Weighted least-squares coefficients from values (and first derivatives).

        Minimises ``sum w (s(t) - y)^2 + sum w' (s'(t') - y')^2`` (seed 000's rough-
        trajectory fit with ``w = rho``, ``w' = 1 - rho``). A tiny ridge keeps basis
        functions without data defined.
        """
        a = self.design(t)
        y = np.asarray(values, dtype=np.float64)
        w = np.ones(a.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
        blocks, rhs = [sp.diags(np.sqrt(w)) @ a], [np.sqrt(w) * y]
        if derivative_t is not None:
            ad = self.design(derivative_t, 1)
            yd = np.asarray(derivative_values, dtype=np.float64)
            wd = (
                np.ones(ad.shape[0])
                if derivative_weights is None
                else np.asarray(derivative_weights, dtype=np.float64)
            )
            blocks.append(sp.diags(np.sqrt(wd)) @ ad)
            rhs.append(np.sqrt(wd) * yd)
        m = sp.vstack(blocks).tocsr()
        b = np.concatenate(rhs)
        n = (m.T @ m).toarray()
        scale = max(float(np.max(np.diag(n))), 1e-300)
        # the ridge only defines coefficients that no datum touches; it does not pull
        # the others toward zero
        empty = np.diag(n) <= 1e-12 * scale
        n[empty, empty] += ridge * scale + 1e-300
        return np.asarray(np.linalg.solve(n, m.T @ b))


@dataclass(frozen=True, eq=False)
class SplineTrajectory:
    """Three spline axes in a Cartesian frame: ``world(t) = origin + R s(t)``.

    Attributes
    ----------
    axes : tuple of three SplineAxis
        Bases of the spline-frame coordinates; they must share the span.
    origin : ndarray, shape (3,)
        Spline-frame origin in the world frame [m].
    rotation : ndarray, shape (3, 3)
        Columns are the spline-frame axes in the world frame.
    """

    axes: tuple[SplineAxis, SplineAxis, SplineAxis]
    origin: FloatArray
    rotation: FloatArray

    def __post_init__(self) -> None:
        if len(self.axes) != 3:
            raise ValueError(f'a trajectory needs three axes; got {len(self.axes)}')
        spans = {(a.t0, a.t1) for a in self.axes}
        if len(spans) != 1:
            raise ValueError(f'spline axes must share their span; got {sorted(spans)}')
        r = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-9):
            raise ValueError('spline-frame rotation must be orthonormal')
        object.__setattr__(self, 'origin', np.asarray(self.origin, dtype=np.float64).reshape(3))
        object.__setattr__(self, 'rotation', r)

    @property
    def t0(self) -> float:
        return self.axes[0].t0

    @property
    def t1(self) -> float:
        return self.axes[0].t1

    @cached_property
    def offsets(self) -> tuple[int, int, int, int]:
        """Start of each axis' coefficients in the parameter vector, and the total."""
        n = [a.n_coef for a in self.axes]
        return (0, n[0], n[0] + n[1], n[0] + n[1] + n[2])

    @property
    def n_coef(self) -> int:
        return self.offsets[3]

    @property
    def n_interior(self) -> int:
        """Interior knots over the three axes."""
        return sum(a.interior.size for a in self.axes)

    def repeated_knots(self) -> FloatArray:
        """Interior knots repeated on an axis (events: a jump the spline may take there),
        one entry per axis that repeats them."""
        return np.concatenate(
            [v[c > 1] for v, c in (np.unique(a.interior, return_counts=True) for a in self.axes)]
        )

    def with_axes(self, axes: Sequence[SplineAxis]) -> SplineTrajectory:
        return SplineTrajectory((axes[0], axes[1], axes[2]), self.origin, self.rotation)

    def designs(self, t: ArrayLike, nu: int = 0) -> tuple[sp.csr_matrix, ...]:
        """Design matrices of the three axes at times ``t``."""
        return tuple(a.design(t, nu) for a in self.axes)

    def world_design(self, t: ArrayLike, nu: int = 0) -> sp.csr_matrix:
        """Sparse ``d world^(nu)(t) / d coef``, shape (3 m, n_coef), rows (x, y, z) per
        time interleaved: row ``3 j + c`` is world component ``c`` at ``t_j``."""
        ds = self.designs(t, nu)
        m = ds[0].shape[0]
        blocks = []
        for c in range(3):
            blocks.append(sp.hstack([self.rotation[c, a] * ds[a] for a in range(3)]))
        stacked = sp.vstack(blocks).tocsr()  # rows: component-major
        order = (np.arange(3)[None, :] * m + np.arange(m)[:, None]).ravel()
        return stacked[order]

    def local(self, coef: ArrayLike, t: ArrayLike, nu: int = 0) -> FloatArray:
        """Spline-frame coordinates (or derivatives), shape (m, 3)."""
        c = np.asarray(coef, dtype=np.float64)
        o = self.offsets
        return np.stack(
            [self.axes[a].evaluate(c[o[a] : o[a + 1]], t, nu) for a in range(3)], axis=1
        )

    def states(self, coef: ArrayLike, t: ArrayLike) -> FloatArray:
        """World-frame position and velocity, shape (m, 6)."""
        p = self.local(coef, t, 0) @ self.rotation.T + self.origin
        v = self.local(coef, t, 1) @ self.rotation.T
        return np.hstack([p, v])

    def acceleration(self, coef: ArrayLike, t: ArrayLike) -> FloatArray:
        return self.local(coef, t, 2) @ self.rotation.T

    def fit_states(
        self,
        t: ArrayLike,
        position: ArrayLike,
        velocity: ArrayLike | None = None,
        position_weight: float = 1.0,
        velocity_weight: float = 1.0,
    ) -> FloatArray:
        """Least-squares coefficients from world-frame positions (and velocities)."""
        p = (np.asarray(position, dtype=np.float64) - self.origin) @ self.rotation
        v = None if velocity is None else np.asarray(velocity, dtype=np.float64) @ self.rotation
        tt = np.asarray(t, dtype=np.float64)
        out = []
        for a, ax in enumerate(self.axes):
            out.append(
                ax.fit(
                    tt,
                    p[:, a],
                    np.full(tt.size, position_weight),
                    None if v is None else tt,
                    None if v is None else v[:, a],
                    None if v is None else np.full(tt.size, velocity_weight),
                )
            )
        return np.concatenate(out)
