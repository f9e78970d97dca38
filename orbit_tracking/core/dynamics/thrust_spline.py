"""Seed 003's flight with an unknown thrust acceleration ``F(t)`` as a control: the model
the adjoint assimilation (:mod:`.adjoint`) fits.

The vehicle obeys (world frame Earth-centred; inertial unless ``earth_rate`` is set)::

    r' = v,   v' = g(r) + F(t, v)  [- 2 w x v - w x (w x r)]

with ``F`` a cubic B-spline in time on a clamped knot vector over ``[t0, t1]`` (interior
knots evenly spaced, at most ``knot_spacing`` apart): either a magnitude along the
velocity, ``F = a(t) v / |v|, a(t) = sum_j c_j B_j(t)`` (``direction='velocity'``), or
three free components ``F = sum_j C_j B_j(t)``, ``C_j`` in R^3 (``direction='free'``).
The parameters ``theta`` are the state ``(r0, v0)`` at ``t0`` and the coefficients (the
free ones ordered ``C_0x, C_0y, C_0z, C_1x, ...``).

With ``y = (r, v)``, ``A = df/dy = [[0, I], [dg/dr, dF/dv]]`` and ``G = dF/dc`` (3 x n_c),
the forward sensitivities ``Phi = dy(t)/dtheta`` obey ``Phi' = A Phi + [0; [0 | G]]``,
``Phi(t0) = [I_6 | 0]`` (:meth:`ThrustSplineModel.propagate`), and the costate of
:meth:`ThrustSplineModel.costate` obeys ``lambda' = -A^T lambda`` backward (the
equations are in :mod:`.adjoint`). The integration restarts at every knot (the control's
third derivative jumps there, which would otherwise stall DOP853's error control).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import OdeSolution, solve_ivp
from scipy.interpolate import BSpline

from orbit_tracking.core import frames
from orbit_tracking.core.dynamics.rocket import Flight, FlightError
from orbit_tracking.core.estimation.bspline import clamped_knots
from orbit_tracking.core.models.dynamics import gravity

__all__ = ['DIRECTIONS', 'ThrustControl', 'ThrustSplineModel']

FloatArray = NDArray[np.float64]

Rhs = Callable[[float, FloatArray], FloatArray]

DIRECTIONS: tuple[str, ...] = ('velocity', 'free')
"""Thrust parametrisations: a magnitude along the velocity, or three free components."""

_RTOL = 1e-11
_ATOL_STATE = np.concatenate([np.full(3, 1e-6), np.full(3, 1e-9)])
_ATOL_SENS = 1e-10
_MAX_EVALUATIONS = 20000
"""Right-hand side evaluations per knot interval beyond which a flight is refused (a few
hundred suffice for any plausible one; a line search's wild trial would take minutes)."""
_MAX_COSTATE_STEP_S = 0.5
"""Longest step of the costate integration between two measurement epochs [s]."""


@dataclass(frozen=True)
class ThrustControl:
    """Cubic B-spline basis of the thrust over ``[t0, t1]`` [s].

    Attributes
    ----------
    t0, t1 : float
        Span of the control [s] (``t0`` is the epoch of the state parameters).
    knot_spacing : float
        Largest distance between knots [s]; the interior knots are evenly spaced.
    direction : {'velocity', 'free'}
    jumps : tuple of float
        Times [s] where the thrust may jump (a staging): a knot of full multiplicity
        there, the even spacing restarting from it; those within a second of the span's
        ends are ignored.
    """

    t0: float
    t1: float
    knot_spacing: float = 10.0
    direction: str = 'velocity'
    jumps: tuple[float, ...] = ()
    knots: FloatArray = field(init=False, repr=False, compare=False)
    breaks: FloatArray = field(init=False, repr=False, compare=False)
    pieces: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.t0) and math.isfinite(self.t1) and self.t1 > self.t0):
            raise ValueError(f'the control span must have t1 > t0; got [{self.t0}, {self.t1}]')
        if not self.knot_spacing > 0.0:
            raise ValueError(f'knot_spacing must be > 0 s; got {self.knot_spacing}')
        if self.direction not in DIRECTIONS:
            raise ValueError(f'direction must be one of {DIRECTIONS}; got {self.direction!r}')
        cuts = sorted(j for j in self.jumps if self.t0 + 1.0 < j < self.t1 - 1.0)
        ends = [self.t0, *cuts, self.t1]
        # one clamped cubic spline per stretch between jumps (together: the spline with a
        # knot of multiplicity four at each jump); per knot interval, the Taylor
        # coefficients of every basis function about its middle (cubic, so exact): the
        # right-hand sides evaluate them by Horner's rule
        seg_breaks, seg_pieces = [], []
        for a, b in zip(ends[:-1], ends[1:], strict=True):
            br = np.linspace(a, b, max(math.ceil((b - a) / self.knot_spacing - 1e-9), 1) + 1)
            kn = clamped_knots(br[1:-1], a, b, 3)
            basis = BSpline(kn, np.eye(kn.size - 4), 3)
            mid = 0.5 * (br[:-1] + br[1:])
            seg_breaks.append(br)
            seg_pieces.append(
                np.stack(
                    [
                        basis.derivative(k)(mid) / math.factorial(k) if k else basis(mid)
                        for k in range(4)
                    ],
                    axis=1,
                )  # (n_pieces, 4, n_coef of the stretch)
            )
        n_coef = sum(p.shape[2] for p in seg_pieces)
        pieces = np.zeros((sum(p.shape[0] for p in seg_pieces), 4, n_coef))
        row = col = 0
        for p in seg_pieces:
            pieces[row : row + p.shape[0], :, col : col + p.shape[2]] = p
            row, col = row + p.shape[0], col + p.shape[2]
        breaks = np.unique(np.concatenate(seg_breaks))
        inner = np.sort(np.concatenate([breaks[1:-1], np.repeat(cuts, 3)]))
        knots = np.concatenate([np.full(4, self.t0), inner, np.full(4, self.t1)])
        object.__setattr__(self, 'knots', knots)
        object.__setattr__(self, 'breaks', breaks)
        object.__setattr__(self, 'pieces', pieces)

    @property
    def n_coef(self) -> int:
        """Number of basis functions."""
        return int(self.knots.size - 4)

    @property
    def components(self) -> int:
        """1 along the velocity, 3 free."""
        return 1 if self.direction == 'velocity' else 3

    @property
    def n_parameters(self) -> int:
        return self.n_coef * self.components

    def basis(self, t: ArrayLike) -> FloatArray:
        """``B_j(t)``, shape (m, n_coef) (times clipped into the span)."""
        tt = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), self.t0, self.t1)
        return np.asarray(BSpline.design_matrix(tt, self.knots, 3).toarray())

    def coefficients(self, coef: ArrayLike) -> FloatArray:
        """Coefficients as (n_coef,) along the velocity or (n_coef, 3) free."""
        c = np.asarray(coef, dtype=np.float64)
        shape = (self.n_coef,) if self.components == 1 else (self.n_coef, 3)
        if c.size != self.n_parameters:
            raise ValueError(
                f'{self.direction} thrust needs {self.n_parameters} coefficients '
                f'(shape {shape}); got shape {c.shape}'
            )
        return c.reshape(shape)

    def values(self, coef: ArrayLike, t: ArrayLike) -> FloatArray:
        """Spline values at ``t``: magnitude (m,) or components (m, 3) [m/s^2]."""
        return self.basis(t) @ self.coefficients(coef)

    def fit(self, t: ArrayLike, values: ArrayLike) -> FloatArray:
        """Least-squares coefficients (flat) of samples (m,) or (m, 3) at times ``t``."""
        b = self.basis(t)
        v = np.asarray(values, dtype=np.float64)
        if v.shape[0] != b.shape[0]:
            raise ValueError(f'{b.shape[0]} times but values of shape {v.shape}')
        return np.asarray(np.linalg.lstsq(b, v, rcond=None)[0]).ravel()


def _gravity_gradient(r: FloatArray, gm: float, j2: float, radius: float) -> FloatArray:
    """``dg/dr`` at positions (m, 3), shape (m, 3, 3)."""
    rn = np.linalg.norm(r, axis=1)
    u = r / rn[:, None]
    grad = (gm / rn**3)[:, None, None] * (3.0 * u[:, :, None] * u[:, None, :] - np.eye(3))
    if j2 != 0.0:  # the J2 part by central differences (it is 1e-3 of the whole)
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1.0
            dj = (gravity(r + e, gm, j2, radius) - gravity(r + e, gm, 0.0)) - (
                gravity(r - e, gm, j2, radius) - gravity(r - e, gm, 0.0)
            )
            grad[:, :, k] += 0.5 * dj
    return grad


@dataclass
class DenseFlight:
    """The forward solution: one DOP853 dense output per knot interval."""

    breaks: FloatArray
    pieces: list[OdeSolution]

    def __call__(self, t: ArrayLike) -> FloatArray:
        """States (and sensitivities, flattened) at ``t``, shape (m, n)."""
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        idx = np.clip(np.searchsorted(self.breaks, tt, side='right') - 1, 0, len(self.pieces) - 1)
        out: FloatArray | None = None
        for i in np.unique(idx):
            sel = idx == i
            y = self.pieces[i](tt[sel]).T
            if out is None:
                out = np.empty((tt.size, y.shape[1]))
            out[sel] = y
        assert out is not None
        return out


@dataclass(frozen=True)
class ThrustSplineModel:
    """Gravity plus a spline thrust control (see the module docstring).

    Attributes
    ----------
    control : ThrustControl
    gm, j2, radius, earth_rate : float
        Gravity and world-frame rotation, as :class:`~.rocket.RocketModel`'s.
    """

    control: ThrustControl
    gm: float = frames.WGS84_GM
    j2: float = 0.0
    radius: float = frames.WGS84_A
    earth_rate: float = 0.0

    @property
    def epoch(self) -> float:
        return float(self.control.t0)

    @property
    def n_parameters(self) -> int:
        return 6 + self.control.n_parameters

    @property
    def names(self) -> tuple[str, ...]:
        n = self.control.n_coef
        if self.control.components == 1:
            thrust = [f'thrust_{j:02d}' for j in range(n)]
        else:
            thrust = [f'thrust_{j:02d}_{a}' for j in range(n) for a in 'xyz']
        return ('x', 'y', 'z', 'vx', 'vy', 'vz', *thrust)

    def _check(self, theta: ArrayLike) -> tuple[FloatArray, FloatArray]:
        th = np.asarray(theta, dtype=np.float64).reshape(-1)
        if th.shape != (self.n_parameters,) or not np.all(np.isfinite(th)):
            raise FlightError(f'the model needs {self.n_parameters} finite parameters; got {th}')
        if self.control.components == 1 and np.linalg.norm(th[3:6]) <= 0.0:
            raise FlightError('the thrust direction needs a nonzero velocity')
        return th, self.control.coefficients(th[6:])

    def _rhs(self, coef: FloatArray, piece: int, sens: bool) -> Rhs:
        poly = self.control.pieces[piece]
        mid = 0.5 * (self.control.breaks[piece] + self.control.breaks[piece + 1])
        along = self.control.components == 1
        w = self.earth_rate
        wx = np.array([[0.0, -w, 0.0], [w, 0.0, 0.0], [0.0, 0.0, 0.0]])
        n_p = self.n_parameters

        def rhs(t: float, y: FloatArray) -> FloatArray:
            s = t - mid
            b = poly[0] + s * (poly[1] + s * (poly[2] + s * poly[3]))
            r, v = y[:3], y[3:6]
            if along:
                a = float(b @ coef)
                speed = float(np.linalg.norm(v))
                vh = v / speed
                thrust = a * vh
            else:
                thrust = b @ coef
            acc = gravity(r, self.gm, self.j2, self.radius) + thrust
            if w:
                acc = acc - 2.0 * (wx @ v) - wx @ (wx @ r)
            if not sens:
                return np.concatenate([v, acc])
            phi = y[6:].reshape(6, n_p)
            da_dr = _gravity_gradient(r[None], self.gm, self.j2, self.radius)[0]
            dphi = np.empty((6, n_p))
            dphi[:3] = phi[3:]
            if w:
                da_dr = da_dr - wx @ wx
            dphi[3:] = da_dr @ phi[:3]
            if along:
                da_dv = (a / speed) * (np.eye(3) - np.outer(vh, vh))
                dphi[3:] += (da_dv - 2.0 * wx) @ phi[3:] if w else da_dv @ phi[3:]
                dphi[3:, 6:] += np.outer(vh, b)
            else:
                if w:
                    dphi[3:] -= 2.0 * wx @ phi[3:]
                for k in range(3):
                    dphi[3 + k, 6 + k :: 3] += b
            return np.concatenate([v, acc, dphi.ravel()])

        return rhs

    def forward(self, theta: ArrayLike, sensitivities: bool = False) -> DenseFlight:
        """Integrate from ``t0`` to ``t1`` (DOP853, dense output, one run per knot interval).

        Raises
        ------
        FlightError
            Bad parameters, zero speed along the velocity, or a failed integration.
        """
        th, coef = self._check(theta)
        n_p = self.n_parameters
        y = th[:6].copy()
        atol = _ATOL_STATE
        if sensitivities:
            y = np.concatenate([y, np.hstack([np.eye(6), np.zeros((6, n_p - 6))]).ravel()])
            atol = np.concatenate([atol, np.full(6 * n_p, _ATOL_SENS)])
        br = self.control.breaks
        sols = []
        for i in range(br.size - 1):
            rhs = self._rhs(coef, i, sensitivities)
            span = (float(br[i]), float(br[i + 1]))
            calls = [0]

            def counted(
                t: float,
                y: FloatArray,
                rhs: Rhs = rhs,
                calls: list[int] = calls,
                span: tuple[float, float] = span,
            ) -> FloatArray:
                calls[0] += 1
                if calls[0] > _MAX_EVALUATIONS:
                    raise FlightError(
                        f'the flight needs more than {_MAX_EVALUATIONS} evaluations between '
                        f'{span[0]:.3f} and {span[1]:.3f} s: parameters far from any flight'
                    )
                return rhs(t, y)

            sol = solve_ivp(
                counted,
                span,
                y,
                method='DOP853',
                dense_output=True,
                rtol=_RTOL,
                atol=atol,
            )
            if not sol.success or not np.all(np.isfinite(sol.y[:, -1])):
                raise FlightError(f'integration failed: {sol.message}')
            sols.append(sol.sol)
            y = sol.y[:, -1]
        return DenseFlight(br, sols)

    def _times(self, t: ArrayLike) -> FloatArray:
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        c = self.control
        if tt.size and (tt.min() < c.t0 - 1e-9 or tt.max() > c.t1 + 1e-9):
            raise FlightError(
                f'times [{tt.min():.3f}, {tt.max():.3f}] s outside the control span '
                f'[{c.t0:.3f}, {c.t1:.3f}] s'
            )
        return tt

    def thrust(self, theta: ArrayLike, t: ArrayLike) -> FloatArray:
        """Thrust acceleration magnitude [m/s^2] at ``t``, shape (m,) (along the velocity:
        the signed spline value)."""
        th = np.asarray(theta, dtype=np.float64).reshape(-1)
        f = self.control.values(th[6:], self._times(t))
        return f if f.ndim == 1 else np.linalg.norm(f, axis=1)

    def propagate(self, theta: ArrayLike, t: ArrayLike, jacobian: bool = True) -> Flight:
        """States (and sensitivities (m, 6, n_parameters)) at times ``t`` in the span."""
        tt = self._times(t)
        y = self.forward(theta, jacobian)(tt)
        sens = y[:, 6:].reshape(-1, 6, self.n_parameters) if jacobian else None
        return Flight(tt, y[:, :6].copy(), sens, self.thrust(theta, tt))

    def system(self, theta: ArrayLike, t: FloatArray, y: FloatArray) -> tuple[FloatArray, ...]:
        """``A = df/dy`` (m, 6, 6), the basis (m, n_coef) and the thrust direction (m, 3)
        (zeros when free) at states ``y`` (m, 6) at ``t``."""
        _, coef = self._check(theta)
        m = t.size
        r, v = y[:, :3], y[:, 3:6]
        b = self.control.basis(t)
        a_mat = np.zeros((m, 6, 6))
        a_mat[:, :3, 3:] = np.eye(3)
        a_mat[:, 3:, :3] = _gravity_gradient(r, self.gm, self.j2, self.radius)
        vh = np.zeros((m, 3))
        if self.control.components == 1:
            speed = np.linalg.norm(v, axis=1)
            vh = v / speed[:, None]
            a = b @ coef
            a_mat[:, 3:, 3:] = (a / speed)[:, None, None] * (
                np.eye(3) - vh[:, :, None] * vh[:, None, :]
            )
        if self.earth_rate:
            w = self.earth_rate
            wx = np.array([[0.0, -w, 0.0], [w, 0.0, 0.0], [0.0, 0.0, 0.0]])
            a_mat[:, 3:, :3] -= wx @ wx
            a_mat[:, 3:, 3:] -= 2.0 * wx
        return a_mat, b, vh

    def costate(
        self, theta: ArrayLike, flight: DenseFlight, times: FloatArray, jumps: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Integrate ``lambda' = -A^T lambda`` backward from the last of ``times`` to ``t0``,
        adding ``jumps`` (n, 6) at ``times`` (n,) (ascending, in the span), and the
        gradient ``int G^T lambda_v dt``.

        The costate is linear, so each step of the classical Runge-Kutta scheme (on a
        grid of the epochs, the knots and at most :data:`_MAX_COSTATE_STEP_S` apart, ``A``
        from the dense forward solution) is a 6 x 6 matrix, built for every step at once;
        the quadrature of the gradient uses the same stages (Simpson's rule on each step).

        Returns
        -------
        lambda0 : ndarray, shape (6,)
            ``lambda(t0)``, the gradient with respect to the state at ``t0``.
        grad : ndarray, shape (n_coef * components,)
            Gradient with respect to the thrust coefficients.
        """
        c = self.control
        inner = c.breaks[(c.breaks > c.t0) & (c.breaks < times[-1])]
        grid = np.unique(np.concatenate([[c.t0], times, inner]))
        n_sub = np.ceil(np.diff(grid) / _MAX_COSTATE_STEP_S).astype(int)
        if np.any(n_sub > 1):
            grid = np.unique(
                np.concatenate(
                    [
                        np.linspace(a, b, k + 1)
                        for a, b, k in zip(grid[:-1], grid[1:], n_sub, strict=True)
                    ]
                )
            )
        kick = np.zeros((grid.size, 6))
        np.add.at(kick, np.searchsorted(grid, times), jumps)
        mid = 0.5 * (grid[:-1] + grid[1:])
        pts = np.concatenate([grid, mid])
        a_mat, b, vh = self.system(theta, pts, flight(pts)[:, :6])
        cm = -np.transpose(a_mat, (0, 2, 1))
        n = grid.size
        c_l, c_r, c_m = cm[: n - 1], cm[1:n], cm[n:]
        h = np.diff(grid)[:, None, None]
        eye = np.eye(6)
        m2 = eye - 0.5 * h * c_r
        m3 = eye - 0.5 * h * (c_m @ m2)
        m4 = eye - h * (c_m @ m3)
        step = eye - h / 6.0 * (c_r + 2.0 * c_m @ m2 + 2.0 * c_m @ m3 + c_l @ m4)
        lam = np.zeros(6)
        right = np.empty((n - 1, 6))
        for k in range(n - 2, -1, -1):
            lam = lam + kick[k + 1]
            right[k] = lam
            lam = step[k] @ lam
        lam0 = lam + kick[0]
        hv = h[:, :, 0]
        w_r = hv / 6.0 * right[:, 3:]
        w_m = hv / 3.0 * (np.einsum('kij,kj->ki', m2, right) + np.einsum('kij,kj->ki', m3, right))
        w_l = hv / 6.0 * np.einsum('kij,kj->ki', m4, right)[:, 3:]
        w = np.zeros((pts.size, 3))
        w[: n - 1] += w_l
        w[1:n] += w_r
        w[n:] += w_m[:, 3:]
        if c.components == 1:
            grad = b.T @ np.einsum('pi,pi->p', vh, w)
        else:
            grad = (b.T @ w).ravel()
        return lam0, grad
