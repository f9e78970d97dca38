"""Cramér–Rao bound of one simulated draw, for an oracle that knows the model structure.

Issue 14 states every accuracy claim against the bound of each draw. The bound must not
depend on the estimator's choices, so it is that of an *oracle*:

* **Model.** A degree-4 B-spline per axis of a local launch-like frame
  (:func:`local_frame`), whose knots come from the truth (:func:`oracle_spline`): the
  acceleration jumps of the truth each get a knot of multiplicity ``degree - 1`` (its
  jerk jumps, ``degree - 2``), and
  single knots are inserted by bisection where the least-squares fit of the noise-free
  truth misses it by more than 1 cm in position or 1 mm/s in velocity (vector norms, on a
  dense grid), then dropped again one by one while the fit stays within tolerance. The
  fit's remaining misfit (the representation error) is reported, so that anyone can see
  the bound is not biased by the model.
* **Data.** Every station value of the draw with its true sigma (gross errors left out),
  and, for the bound of a method that fuses telemetry, the telemetry with its *true*
  error covariance (:class:`TelemetryErrorCovariance`, made by
  :func:`orbit_tracking.core.sim.telemetry.error_covariance`).
* **Information.** ``F = J^T W J`` at the truth: station rows through
  :func:`~orbit_tracking.core.models.measurements.predict` and the chain rule to the
  spline coefficients (:func:`station_jacobian`); telemetry rows whitened per world axis
  by the Cholesky factor of their ``(2n x 2n)`` covariance (position and velocity blocks
  apart when independent) (:func:`telemetry_information`). A random constant shared by
  the axes (a time skew) is a nuisance parameter with its prior variance, eliminated by
  taking the coefficient block of ``F^-1``.
* **Bound.** The state covariance ``G(t) F^-1 G(t)^T`` at the truth sampling times;
  :class:`Bound` reports ``sqrt(mean trace)`` of its position and velocity blocks over any
  subset of them (inside and outside the incomplete segments), and the joint covariance
  of the positions at any set of times (:meth:`Bound.joint_position_covariance`): how
  the errors of an estimator as good as the oracle are correlated from one time to
  another, which sets the spread of a mean NEES over them
  (:func:`~orbit_tracking.core.metrics.correlated_nees_band`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.models.measurements import StationPose, predict

__all__ = [
    'Bound',
    'OracleSpline',
    'TelemetryErrorCovariance',
    'bound',
    'local_frame',
    'oracle_spline',
    'station_information',
    'station_jacobian',
    'telemetry_information',
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class TelemetryErrorCovariance:
    """True covariance of the telemetry errors of one world axis (the same for all three,
    independent between them).

    Attributes
    ----------
    time : ndarray, shape (n,)
        Telemetry epochs [s].
    position, velocity : ndarray, shape (n, n)
        Covariance of the position [m^2] and velocity [m^2/s^2] errors.
    cross : ndarray, shape (n, n) or None
        ``Cov(e_p(t_i), e_v(t_j))`` [m^2/s]; None when they are independent.
    delays_s : (float, float)
        True time skew of position and velocity [s]: the values are the truth at
        ``t - delay``.
    delay_sigma_s : (float, float)
        Prior sigma of those delays [s]; 0 means they are known (not estimated).
    """

    time: FloatArray
    position: FloatArray
    velocity: FloatArray
    cross: FloatArray | None = None
    delays_s: tuple[float, float] = (0.0, 0.0)
    delay_sigma_s: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        n = np.asarray(self.time).shape[0]
        for name in ('position', 'velocity', 'cross'):
            m = getattr(self, name)
            if m is not None and np.asarray(m).shape != (n, n):
                raise ValueError(
                    f'telemetry {name} covariance must be ({n}, {n}) for {n} epochs; '
                    f'got {np.asarray(m).shape}'
                )

    @property
    def nuisance(self) -> int:
        """Number of nuisance parameters (delays estimated with the trajectory)."""
        return int(sum(s > 0.0 for s in self.delay_sigma_s))


@dataclass(frozen=True)
class OracleSpline:
    """The oracle's trajectory model, fitted to the noise-free truth.

    Attributes
    ----------
    trajectory : SplineTrajectory
    coef : ndarray
        Least-squares coefficients of the truth.
    events : tuple of float
        Acceleration jumps [s] given a knot of multiplicity ``degree - 1``.
    rounds : int
        Bisection rounds run.
    max_position_error_m, max_velocity_error_m_s : float
        Largest norm of the fit's miss of the truth on the grid it was built on.
    rms_position_error_m, rms_velocity_error_m_s : float
        Their RMS.
    """

    trajectory: SplineTrajectory
    coef: FloatArray
    events: tuple[float, ...]
    rounds: int
    max_position_error_m: float
    max_velocity_error_m_s: float
    rms_position_error_m: float
    rms_velocity_error_m_s: float

    @property
    def knots(self) -> tuple[int, int, int]:
        """Interior knots per axis (repeated ones counted each time)."""
        a = self.trajectory.axes
        return (a[0].interior.size, a[1].interior.size, a[2].interior.size)

    def errors(self, times: ArrayLike, states: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Norm of the position [m] and velocity [m/s] misfit (m,) at other samples."""
        x = self.trajectory.states(self.coef, np.asarray(times, dtype=np.float64))
        d = x - np.asarray(states, dtype=np.float64)
        return np.linalg.norm(d[:, :3], axis=1), np.linalg.norm(d[:, 3:], axis=1)


def local_frame(position: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """A launch-like frame of a track: origin at its first point, ``y`` along the
    geocentric radial there, ``x`` along the horizontal part of the chord from the first
    to the last point, ``z = x × y``.

    Parameters
    ----------
    position : array_like, shape (n, 3)
        World positions [m].

    Returns
    -------
    origin : ndarray, shape (3,)
    rotation : ndarray, shape (3, 3)
        Columns are the frame's axes in the world frame.
    """
    p = np.asarray(position, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 1:
        raise ValueError(f'positions must have shape (n, 3) with n >= 1; got {p.shape}')
    origin = p[0]
    r = float(np.linalg.norm(origin))
    up = origin / r if r > 1.0 else np.array([0.0, 0.0, 1.0])
    chord = p[-1] - p[0]
    h = chord - up * float(chord @ up)
    if np.linalg.norm(h) < 1e-6 * max(float(np.linalg.norm(chord)), 1.0):
        h = np.cross(np.array([0.0, 0.0, 1.0]), up)
        if np.linalg.norm(h) < 1e-9:
            h = np.array([1.0, 0.0, 0.0])
    x = h / np.linalg.norm(h)
    return origin, np.column_stack([x, up, np.cross(x, up)])


def _fit_axis(
    axis: SplineAxis, t: FloatArray, y: FloatArray, dy: FloatArray, tol_p: float, tol_v: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Weighted least squares of values and derivatives (weights 1/tol); returns the
    coefficients and the misfits of value and derivative."""
    d0, d1 = axis.design(t, 0), axis.design(t, 1)
    a = sp.vstack([d0 / tol_p, d1 / tol_v]).tocsr()
    b = np.concatenate([y / tol_p, dy / tol_v])
    n = (a.T @ a).toarray()
    rhs = a.T @ b
    scale = np.sqrt(np.maximum(np.diag(n), 1e-300))
    ns = n / np.outer(scale, scale)
    ns[np.diag_indices_from(ns)] += 1e-12
    coef = np.linalg.solve(ns, rhs / scale) / scale
    return coef, d0 @ coef - y, d1 @ coef - dy


def oracle_spline(
    times: ArrayLike,
    states: ArrayLike,
    t0: float,
    t1: float,
    events: Sequence[float] = (),
    kinks: Sequence[float] = (),
    degree: int = 4,
    position_tol_m: float = 0.01,
    velocity_tol_m_s: float = 1e-3,
    min_spacing_s: float = 0.02,
    max_rounds: int = 40,
    prune: bool = True,
) -> OracleSpline:
    """The sparsest knots (greedy) that represent the noise-free truth within tolerance.

    Per axis of :func:`local_frame`: knots of multiplicity ``degree - 1`` at the
    ``events`` (acceleration jumps), then rounds of bisection (a knot at the middle of
    every knot interval where the weighted least-squares fit of position and velocity
    misses by more than ``tol / sqrt(3)``, so that the vector misses stay within
    ``tol``), then, with ``prune``, each inserted knot removed again if the fit stays
    within tolerance without it.

    Parameters
    ----------
    times : array_like, shape (n,)
        Dense truth epochs [s] covering [t0, t1] (the tolerance holds there).
    states : array_like, shape (n, 6)
        Truth position [m] and velocity [m/s] at ``times``, world frame.
    t0, t1 : float
        Spline span [s].
    events : sequence of float
        Times of acceleration jumps [s]; those within ``min_spacing_s`` of the span's
        ends are left to the bisection.
    kinks : sequence of float
        Times where the jerk jumps [s] (the acceleration has a kink: a control ramp
        ending, a pitch-program node): knots of multiplicity ``degree - 2``.
    """
    t = np.asarray(times, dtype=np.float64)
    x = np.asarray(states, dtype=np.float64)
    if t.ndim != 1 or x.shape != (t.size, 6):
        raise ValueError(f'truth needs times (n,) and states (n, 6); got {t.shape}, {x.shape}')
    if not t1 > t0 or t.size < 2 or t.min() < t0 - 1e-9 or t.max() > t1 + 1e-9:
        raise ValueError(f'truth epochs must lie in the span [{t0}, {t1}] with t1 > t0')
    if degree < 2:
        raise ValueError(f'oracle spline degree must be >= 2; got {degree}')
    origin, rot = local_frame(x[:, :3])
    lp = (x[:, :3] - origin) @ rot
    lv = x[:, 3:] @ rot
    tol_p = position_tol_m / np.sqrt(3.0)
    tol_v = velocity_tol_m_s / np.sqrt(3.0)
    ev = sorted({float(e) for e in events if t0 + min_spacing_s < e < t1 - min_spacing_s})
    kk = sorted({float(e) for e in kinks if t0 + min_spacing_s < e < t1 - min_spacing_s} - set(ev))
    fixed = [e for e in ev for _ in range(degree - 1)] + [e for e in kk for _ in range(degree - 2)]
    axes: list[SplineAxis] = []
    coefs: list[FloatArray] = []
    rounds_run = 0

    def build(free: Sequence[float]) -> SplineAxis:
        return SplineAxis.from_interior(sorted([*fixed, *free]), t0, t1, degree)

    def ok(ep: FloatArray, evv: FloatArray) -> bool:
        return bool(np.all(np.abs(ep) <= tol_p) and np.all(np.abs(evv) <= tol_v))

    for a in range(3):
        free: list[float] = []
        for r in range(max_rounds):
            rounds_run = max(rounds_run, r + 1)
            ax = build(free)
            _, ep, evv = _fit_axis(ax, t, lp[:, a], lv[:, a], tol_p, tol_v)
            bad = (np.abs(ep) > tol_p) | (np.abs(evv) > tol_v)
            if not np.any(bad):
                break
            brk = np.unique(ax.knots)
            j = np.unique(np.clip(np.searchsorted(brk, t[bad], side='right') - 1, 0, brk.size - 2))
            new = [
                0.5 * (brk[k] + brk[k + 1]) for k in j if brk[k + 1] - brk[k] >= 2 * min_spacing_s
            ]
            if not new:
                break
            free = sorted(free + new)
        if prune:
            for k in list(free):
                trial = [f for f in free if f != k]
                _, ep, evv = _fit_axis(build(trial), t, lp[:, a], lv[:, a], tol_p, tol_v)
                if ok(ep, evv):
                    free = trial
        ax = build(free)
        coef, _, _ = _fit_axis(ax, t, lp[:, a], lv[:, a], tol_p, tol_v)
        axes.append(ax)
        coefs.append(coef)
    traj = SplineTrajectory((axes[0], axes[1], axes[2]), origin, rot)
    coef_all = np.concatenate(coefs)
    d = traj.states(coef_all, t) - x
    ep_n, ev_n = np.linalg.norm(d[:, :3], axis=1), np.linalg.norm(d[:, 3:], axis=1)
    return OracleSpline(
        traj,
        coef_all,
        tuple(ev),
        rounds_run,
        float(ep_n.max()),
        float(ev_n.max()),
        float(np.sqrt(np.mean(ep_n**2))),
        float(np.sqrt(np.mean(ev_n**2))),
    )


def station_jacobian(
    traj: SplineTrajectory,
    fields: Sequence[str],
    time: ArrayLike,
    pose: StationPose,
    states: ArrayLike,
    sigmas: ArrayLike,
    valid: ArrayLike | None = None,
) -> sp.csr_matrix:
    """Whitened Jacobian of one station's values with respect to the spline coefficients.

    Row ``(j, f)`` is ``(dh_f/dp G_p(t_j) + dh_f/dv G_v(t_j)) / sigma_jf`` with ``h`` from
    :func:`~orbit_tracking.core.models.measurements.predict` evaluated at ``states`` and
    ``G_p``, ``G_v`` the spline's world position and velocity designs.

    Parameters
    ----------
    traj : SplineTrajectory
    fields : sequence of str
    time : array_like, shape (m,)
        True epochs of the values [s] (a station clock offset already added).
    pose : StationPose
        Station pose at the m epochs.
    states : array_like, shape (m, 6)
        Target state where the models are linearised (the truth).
    sigmas : array_like, shape (m, k)
        Standard deviations of the values.
    valid : array_like of bool, shape (m, k), optional
        Values to keep (default all).

    Returns
    -------
    scipy.sparse.csr_matrix, shape (number of valid values, traj.n_coef)
        Rows field-major: every valid value of the first field, then the second, ...
    """
    t = np.asarray(time, dtype=np.float64)
    m, k = t.size, len(fields)
    sig = np.asarray(sigmas, dtype=np.float64).reshape(m, k)
    keep = np.ones((m, k), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    _, h = predict(fields, np.asarray(states, dtype=np.float64), pose, jacobian=True)
    assert h is not None  # asked for
    gp = traj.world_design(t, 0)
    gv = traj.world_design(t, 1)
    comps_p = [gp[c::3] for c in range(3)]
    comps_v = [gv[c::3] for c in range(3)]
    blocks = []
    for f in range(k):
        hf = h[:, f, :] / sig[:, f, None]
        jf = sp.csr_matrix((m, traj.n_coef))
        for c in range(3):
            jf = jf + sp.diags(hf[:, c]) @ comps_p[c] + sp.diags(hf[:, 3 + c]) @ comps_v[c]
        blocks.append(jf.tocsr()[np.flatnonzero(keep[:, f])])
    if not blocks:
        return sp.csr_matrix((0, traj.n_coef))
    return sp.vstack(blocks).tocsr()


def station_information(
    traj: SplineTrajectory,
    rows: Sequence[
        tuple[Sequence[str], FloatArray, StationPose, FloatArray, FloatArray, BoolArray]
    ],
) -> FloatArray:
    """Fisher information (n_coef, n_coef) of station values: the sum of ``J^T J`` of
    :func:`station_jacobian` over ``rows`` = ``(fields, time, pose, states, sigmas,
    valid)`` per station."""
    info = np.zeros((traj.n_coef, traj.n_coef))
    for fields, time, pose, states, sigmas, valid in rows:
        j = station_jacobian(traj, fields, time, pose, states, sigmas, valid)
        if j.shape[0]:
            info += (j.T @ j).toarray()
    return info


def telemetry_information(
    traj: SplineTrajectory,
    cov: TelemetryErrorCovariance,
    velocity_at: Callable[[FloatArray], FloatArray] | None = None,
    acceleration_at: Callable[[FloatArray], FloatArray] | None = None,
) -> FloatArray:
    """Fisher information of the telemetry about the spline coefficients and the
    nuisance delays.

    Per world axis ``c`` the rows are ``p_c(t_i - d_p)`` and ``v_c(t_i - d_v)``, whitened by
    the Cholesky factor of the true covariance of their errors (one factor for the three
    axes, whose errors are independent and alike). A delay with a prior sigma adds a
    column (``-v_c(t - d_p)`` for the position rows, ``-a_c(t - d_v)`` for the velocity
    rows, from the truth) and its prior information ``1 / sigma^2``.

    Parameters
    ----------
    traj : SplineTrajectory
    cov : TelemetryErrorCovariance
    velocity_at, acceleration_at : callable, optional
        Truth velocity (m, 3) and acceleration (m, 3) at epochs (m,); needed when
        ``cov`` has nuisance delays.

    Returns
    -------
    ndarray, shape (n_coef + q, n_coef + q)
        ``q = cov.nuisance`` extra parameters last.
    """
    n_c = traj.n_coef
    q = cov.nuisance
    t = np.asarray(cov.time, dtype=np.float64)
    n = t.size
    info = np.zeros((n_c + q, n_c + q))
    if n == 0:
        return info
    dp, dv = cov.delays_s
    tp = np.clip(t - dp, traj.t0, traj.t1)
    tv = np.clip(t - dv, traj.t0, traj.t1)
    gp = traj.world_design(tp, 0).toarray()
    gv = traj.world_design(tv, 1).toarray()
    nuis: list[tuple[int, FloatArray]] = []  # (which rows: 0 position / 1 velocity, values)
    if cov.delay_sigma_s[0] > 0.0:
        if velocity_at is None:
            raise ValueError('a position delay needs the truth velocity (velocity_at)')
        nuis.append((0, -np.asarray(velocity_at(tp), dtype=np.float64)))
    if cov.delay_sigma_s[1] > 0.0:
        if acceleration_at is None:
            raise ValueError('a velocity delay needs the truth acceleration (acceleration_at)')
        nuis.append((1, -np.asarray(acceleration_at(tv), dtype=np.float64)))
    # design of the three axes side by side: columns (axis c: n_c + q) each
    width = n_c + q
    a_p = np.zeros((n, 3 * width))
    a_v = np.zeros((n, 3 * width))
    for c in range(3):
        a_p[:, c * width : c * width + n_c] = gp[c::3]
        a_v[:, c * width : c * width + n_c] = gv[c::3]
        for i, (which, vals) in enumerate(nuis):
            target = a_p if which == 0 else a_v
            target[:, c * width + n_c + i] = vals[:, c]
    if cov.cross is None:
        blocks = [(cov.position, a_p), (cov.velocity, a_v)]
    else:
        joint = np.block([[cov.position, cov.cross], [cov.cross.T, cov.velocity]])
        blocks = [(joint, np.vstack([a_p, a_v]))]
    for c_mat, a in blocks:
        chol = sla.cholesky(0.5 * (c_mat + c_mat.T), lower=True)
        w = sla.solve_triangular(chol, a, lower=True)
        for c in range(3):
            wc = w[:, c * width : (c + 1) * width]
            info += wc.T @ wc
    for i in range(q):
        sig = [s for s in cov.delay_sigma_s if s > 0.0][i]
        info[n_c + i, n_c + i] += 1.0 / sig**2
    return info


@dataclass(frozen=True)
class Bound:
    """The bound's state covariance at the truth sampling times.

    Attributes
    ----------
    time : ndarray, shape (m,)
    position_var : ndarray, shape (m,)
        Trace of the 3x3 position block [m^2] (inf where the information is singular).
    velocity_var : ndarray, shape (m,)
        Trace of the velocity block [m^2/s^2].
    singular : bool
        Some direction of the parameters is not observed (the states that depend on it
        have an infinite bound).
    parameters : int
        Spline coefficients (nuisance parameters not counted).
    trajectory, basis, eigenvalues :
        The oracle's spline and the eigen-decomposition of ``F`` (Jacobi-scaled) seen from
        the coefficients, ``F^+`` being ``basis diag(1 / eigenvalues) basis^T`` over the
        observed directions, for :meth:`joint_position_covariance` (None where not kept).
    """

    time: FloatArray
    position_var: FloatArray
    velocity_var: FloatArray
    singular: bool
    parameters: int
    trajectory: SplineTrajectory | None = field(default=None, repr=False, compare=False)
    basis: FloatArray | None = field(default=None, repr=False, compare=False)
    eigenvalues: FloatArray | None = field(default=None, repr=False, compare=False)
    null_tolerance: float = 1e-12

    def joint_position_covariance(self, times: ArrayLike) -> tuple[FloatArray, NDArray[np.bool_]]:
        """The bound's joint covariance of the positions at ``times`` (``(3m, 3m)``, the
        three world axes of each time together), and which times it holds finitely
        (False where a position depends on an unobserved direction, as in :func:`bound`;
        their rows and columns are then meaningless)."""
        if self.trajectory is None or self.basis is None or self.eigenvalues is None:
            raise ValueError('this bound kept no factor of its information')
        w = self.eigenvalues
        null = w <= self.null_tolerance * max(float(w.max()), 1e-300)
        g = self.trajectory.world_design(np.asarray(times, dtype=np.float64), 0)
        gv = np.asarray(g @ self.basis)
        leak = np.sum(gv[:, null] ** 2, axis=1)
        total = np.sum(gv**2, axis=1)
        finite = ~np.any((leak > 1e-8 * np.maximum(total, 1e-300)).reshape(-1, 3), axis=1)
        root = gv[:, ~null] / np.sqrt(w[~null])
        return root @ root.T, finite

    def position(self, mask: ArrayLike | None = None) -> float:
        """``sqrt(mean trace)`` of the position block [m] over ``mask`` (nan if empty)."""
        return self._root_mean(self.position_var, mask)

    def velocity(self, mask: ArrayLike | None = None) -> float:
        """``sqrt(mean trace)`` of the velocity block [m/s] over ``mask``."""
        return self._root_mean(self.velocity_var, mask)

    def _root_mean(self, v: FloatArray, mask: ArrayLike | None) -> float:
        sel = v if mask is None else v[np.asarray(mask, dtype=bool)]
        return float(np.sqrt(np.mean(sel))) if sel.size else float('nan')


def bound(
    traj: SplineTrajectory,
    information: ArrayLike,
    times: ArrayLike,
    null_tolerance: float = 1e-12,
) -> Bound:
    """Invert the information and map it to the states at ``times``.

    The Jacobi-scaled information is decomposed into eigenvectors; directions with an
    eigenvalue below ``null_tolerance`` times the largest are not observed. A state that
    depends on one of them has an infinite bound; every other state's covariance is
    ``G F^+ G^T`` over the observed directions (the coefficient block of ``F^-1`` where
    ``F`` is invertible, nuisance parameters included in ``F`` and eliminated).

    Parameters
    ----------
    traj : SplineTrajectory
    information : array_like, shape (n_coef + q, n_coef + q)
        Coefficients first, then any nuisance parameters.
    times : array_like, shape (m,)
        Truth sampling times [s] inside the spline span.
    """
    f = np.asarray(information, dtype=np.float64)
    n_c = traj.n_coef
    if f.ndim != 2 or f.shape[0] != f.shape[1] or f.shape[0] < n_c:
        raise ValueError(f'information must be square and at least ({n_c}, {n_c}); got {f.shape}')
    if not np.all(np.isfinite(f)):
        raise ValueError('information must be finite')
    t = np.asarray(times, dtype=np.float64)
    d = np.sqrt(np.maximum(np.diag(f), 0.0))
    d = np.where(d > 0.0, d, 1.0)
    w, v = np.linalg.eigh(0.5 * (f + f.T) / np.outer(d, d))
    null = w <= null_tolerance * max(float(w.max()), 1e-300)
    # G D^-1 V for the coefficient rows (nuisance parameters do not enter the states)
    vc = v[:n_c] / d[:n_c, None]
    out = []
    for nu in (0, 1):
        var = np.empty(t.size)
        for lo in range(0, t.size, 2000):  # bounded memory for long spans
            g = traj.world_design(t[lo : lo + 2000], nu)
            gv = np.asarray(g @ vc)
            seen = np.sum(gv[:, ~null] ** 2 / w[~null], axis=1)
            leak = np.sum(gv[:, null] ** 2, axis=1)
            total = np.sum(gv**2, axis=1)
            rows = np.where(leak > 1e-8 * np.maximum(total, 1e-300), np.inf, seen)
            var[lo : lo + 2000] = rows.reshape(-1, 3).sum(axis=1)
        out.append(var)
    return Bound(t, out[0], out[1], bool(np.any(null)), n_c, traj, vc, w, null_tolerance)
