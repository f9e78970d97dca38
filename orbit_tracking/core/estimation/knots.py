"""Knot placement for the trajectory spline (seed 000, section 3).

1. **Rough trajectory** (:func:`rough_trajectory`): on-board telemetry when present,
   otherwise the triangulated fixes. It carries the true dynamic features.
2. **Events** (:func:`detect_changes`, :mod:`.events`): instants where the acceleration
   jumps (engine cut-off, ignition). A degree-``p`` spline with single knots is
   ``C^(p-1)`` and cannot follow them, so the knot there is repeated ``p - 1`` times
   (``C^1``: position and velocity continuous, acceleration free to jump). Where the
   acceleration ramps instead (a turn's control ramp) or only bends, the knot at each
   end of the ramp or at the bend is repeated ``p - 2`` times (the jerk may jump).
3. **Densification** (:func:`densify`): dense equally spaced knots (finer inside the
   incomplete segments), a weighted least-squares fit of the rough position and velocity
   ``min rho |r - K c|^2 + (1 - rho) |v - K' c|^2`` (each term whitened by the rough
   trajectory's noise), and midpoints inserted around intervals whose fit error exceeds
   ``sigma1`` / ``sigma2`` beyond the rough trajectory's own noise; repeated.
4. **Sparse selection** (:func:`select_knots`): the convex problem
   ``min |C c|_1  s.t.  |r - K c|_inf <= delta1, |v - K' c|_inf <= delta2`` (seed eq. 14)
   solved with cvxpy, and knots whose ``p``-th-derivative jump is below ``epsilon``
   dropped. ``r`` and ``v`` here are the densified fit, not the raw rough samples, so
   the noise of the rough trajectory is not what the knots follow; the tolerances are
   widened to ``3 sigma`` of that fit where it is less certain than ``delta``.

The module is longer than the project's ~600-line guide on purpose: it is seed 000's knot
method, and its four steps share the rough trajectory's frame, noise level and tolerances;
kept together they read top to bottom like the seed's section 3.
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.chi2 import chi2_ppf_each
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.events import Changes, find_changes

__all__ = [
    'KnotConfig',
    'KnotSelection',
    'KnotSelectionError',
    'RoughTrajectory',
    'choose_knots',
    'densify',
    'detect_changes',
    'detect_events',
    'dynamics_knots',
    'load_solver',
    'rough_trajectory',
    'select_knots',
    'selection_span',
    'spline_frame',
    'uniform_knots',
]

FloatArray = NDArray[np.float64]

SOLVERS = ('HIGHS', 'CLARABEL', 'ECOS', 'SCS')


class KnotSelectionError(OrbitTrackingError, RuntimeError):
    """The sparse knot-selection problem has no optimal solution."""


@dataclass(frozen=True)
class KnotConfig:
    """Knot placement settings (seed 000 defaults).

    Attributes
    ----------
    degree : int
        Spline degree (order - 1); the seed uses 4.
    base_spacing, gap_spacing : float
        Initial knot spacing [s] outside / inside incomplete segments.
    min_spacing : float
        Densification never goes below this spacing [s].
    rho : float
        Weight of the position term (velocity gets ``1 - rho``).
    sigma_position, sigma_velocity : float
        Densification thresholds sigma1 [m], sigma2 [m/s].
    max_rounds : int
        Densification rounds.
    delta_position, delta_velocity : float
        Sparse-selection tolerances delta1 [m], delta2 [m/s].
    jump_epsilon : float
        A knot whose ``p``-th-derivative jump is at most this [m/s^p] is dropped.
    solver : str
        cvxpy solver, one of ``HIGHS`` (default: simplex, exact zeros), ``CLARABEL``,
        ``ECOS``, ``SCS``.
    sparse : bool
        False keeps the densified knots (no selection).
    events : bool
        Detect acceleration jumps, ramps and bends and repeat the knots there
        (:mod:`.events`).
    event_min_jump : float
        Smallest acceleration jump treated as an event [m/s^2].
    event_sigma : float
        ... and its significance against the rough trajectory's noise.
    event_window : float
        Half-length of the local fits on each side of a candidate [s].
    max_spacing : float
        Longest span [s] the selection may leave without a knot on an axis: points of the
        grid ``k * max_spacing`` at least ``max_spacing / 2`` from every selected knot are
        added (0 = no limit). The rough trajectory's noise can hide a slow bend (an
        aircraft's height over a turn, metres over tens of seconds) that the stations
        see; without a knot the spline cannot take it, and its covariance, conditional on
        that shape, claims centimetres. The white-jerk prior keeps the added knots from
        fitting noise. Not inside incomplete segments: the one or two stations there
        cannot pin such a bend either, the added knots only loosened the fit (seed000_s1
        gap error 0.023 -> 0.059 m), and the covariance carries the manoeuvres a segment
        may hide (:mod:`~orbit_tracking.core.estimation.gap_manoeuvres`). The estimator
        applies it only where fused telemetry places the knots
        (:func:`~orbit_tracking.core.estimation.knot_refinement.choose_knots_safely`).
    """

    degree: int = 4
    base_spacing: float = 1.0
    gap_spacing: float = 0.2
    min_spacing: float = 0.025
    rho: float = 0.5
    sigma_position: float = 0.1
    sigma_velocity: float = 0.05
    max_rounds: int = 4
    delta_position: float = 0.1
    delta_velocity: float = 0.05
    jump_epsilon: float = 1e-5
    solver: str = 'HIGHS'
    sparse: bool = True
    events: bool = True
    event_min_jump: float = 2.0
    event_sigma: float = 10.0
    event_window: float = 1.0
    max_spacing: float = 5.0

    def __post_init__(self) -> None:
        if self.degree < 2:
            raise ValueError(f'spline degree must be >= 2; got {self.degree}')
        if not (0.0 <= self.rho <= 1.0):
            raise ValueError(f'rho must lie in [0, 1]; got {self.rho}')
        positive = (
            'base_spacing',
            'gap_spacing',
            'min_spacing',
            'event_window',
            'sigma_position',
            'sigma_velocity',
            'delta_position',
            'delta_velocity',
        )
        for name in positive:
            if not getattr(self, name) > 0.0:
                raise ValueError(f'{name} must be > 0; got {getattr(self, name)}')
        if not self.max_spacing >= 0.0:
            raise ValueError(f'max_spacing must be >= 0; got {self.max_spacing}')
        if self.jump_epsilon < 0.0 or self.max_rounds < 0:
            raise ValueError('jump_epsilon and max_rounds must be >= 0')
        if self.solver.upper() not in SOLVERS:
            raise ValueError(f'solver must be one of {SOLVERS}; got {self.solver!r}')


@dataclass(frozen=True)
class RoughTrajectory:
    """Samples of the rough trajectory of one target (world frame).

    ``velocity`` is None when the source gives positions only (fixes).
    ``position_noise`` / ``velocity_noise`` are the white-noise levels estimated from
    the samples themselves (the reported sigmas of telemetry include slow drifts).
    ``covariance`` (n, 6, 6), world frame, is given when the samples are themselves an
    estimate (a first solution): their errors are smooth and correlated in time, not
    white, and the knot selection then accepts any spline within 3 sigma of them.
    """

    source: str
    time: FloatArray
    position: FloatArray
    velocity: FloatArray | None
    position_noise: float
    velocity_noise: float
    covariance: FloatArray | None = None

    def axis_sigma(self, rotation: FloatArray) -> tuple[FloatArray, FloatArray] | None:
        """Standard deviations (n, 3) of position and velocity along the axes of a frame
        whose axes are the columns of ``rotation``, from :attr:`covariance`."""
        if self.covariance is None:
            return None
        c = self.covariance
        pp = np.einsum('ia,nij,jb->nab', rotation, c[:, :3, :3], rotation)
        vv = np.einsum('ia,nij,jb->nab', rotation, c[:, 3:, 3:], rotation)
        return _diag_sd(pp), _diag_sd(vv)

    def __len__(self) -> int:
        return int(self.time.shape[0])

    def state(self, t: FloatArray) -> FloatArray:
        """Linear interpolation of (position, velocity) at ``t``, shape (m, 6)."""
        p = np.stack([np.interp(t, self.time, self.position[:, c]) for c in range(3)], 1)
        if self.velocity is not None:
            v = np.stack([np.interp(t, self.time, self.velocity[:, c]) for c in range(3)], 1)
        else:
            g = np.gradient(self.position, self.time, axis=0) if len(self) > 1 else 0 * p
            v = np.stack([np.interp(t, self.time, g[:, c]) for c in range(3)], 1)
        return np.hstack([p, v])


def _diag_sd(m: FloatArray) -> FloatArray:
    """Square roots of the diagonals of a stack of covariances (n, k, k) -> (n, k)."""
    return np.sqrt(np.maximum(np.diagonal(m, axis1=1, axis2=2), 0.0))


def _noise_level(y: FloatArray) -> float:
    """White-noise sigma from the MAD of second differences (robust to smooth trends)."""
    if y.shape[0] < 5:
        return float('nan')
    d2 = np.diff(y, 2, axis=0)
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / 0.6745
    return float(np.median(mad) / np.sqrt(6.0))


def rough_trajectory(
    obs: Observations, target_id: int, t0: float, t1: float, min_samples: int = 10
) -> RoughTrajectory | None:
    """The rough trajectory of ``target_id`` over [t0, t1]: telemetry if it has enough
    samples there, else the fixes; None when neither exists."""
    tel = obs.telemetry.get(target_id)
    if tel is not None:
        m = (tel.time >= t0) & (tel.time <= t1)
        if int(m.sum()) >= min_samples:
            t, p, v = tel.time[m], tel.position[m], tel.velocity[m]
            return RoughTrajectory(
                'telemetry', t, p, v, max(_noise_level(p), 1e-6), max(_noise_level(v), 1e-9)
            )
    fx = obs.fixes.get(target_id)
    if fx is not None:
        m = (fx.time >= t0) & (fx.time <= t1)
        if int(m.sum()) >= min_samples:
            t, p = fx.time[m], fx.position[m]
            return RoughTrajectory('fixes', t, p, None, max(_noise_level(p), 1e-6), 0.0)
    return None


def spline_frame(rough: RoughTrajectory) -> tuple[FloatArray, FloatArray]:
    """A launch-like frame at the rough trajectory's first point: ``y`` up (geocentric
    radial), ``x`` along the horizontal part of the mean velocity, ``z = x × y``."""
    origin = rough.position[0]
    up = origin / max(np.linalg.norm(origin), 1.0)
    if np.linalg.norm(origin) < 1.0:
        up = np.array([0.0, 0.0, 1.0])
    v = rough.state(rough.time[[0, -1]])[:, 3:].mean(axis=0)
    if len(rough) > 1:
        v = rough.position[-1] - rough.position[0]
    h = v - up * float(v @ up)
    if np.linalg.norm(h) < 1e-6 * max(float(np.linalg.norm(v)), 1.0):
        h = np.cross(np.array([0.0, 0.0, 1.0]), up)
        if np.linalg.norm(h) < 1e-9:
            h = np.array([1.0, 0.0, 0.0])
    x = h / np.linalg.norm(h)
    z = np.cross(x, up)
    return origin, np.column_stack([x, up, z])


def detect_changes(rough: RoughTrajectory, cfg: KnotConfig) -> Changes:
    """Where the rough trajectory's acceleration jumps, and where it ramps (the ends of the
    ramp: the jerk jumps there), by :func:`~orbit_tracking.core.estimation.events.
    find_changes`. Needs velocity samples (telemetry); fixes give none."""
    if rough.velocity is None or len(rough) < 10:
        return Changes()
    return find_changes(
        rough.time,
        rough.velocity,
        rough.velocity_noise,
        cfg.event_min_jump,
        cfg.event_sigma,
        cfg.event_window,
    )


def detect_events(rough: RoughTrajectory, cfg: KnotConfig) -> list[float]:
    """Every event time of :func:`detect_changes` (acceleration jumps and ramp ends),
    sorted."""
    return detect_changes(rough, cfg).times


def _grid(t0: float, t1: float, spacing: float) -> FloatArray:
    """``t0``, the multiples of ``spacing`` strictly inside (``t0``, ``t1``) and ``t1``: a
    grid anchored to the time axis, not to the window, so that moving a window's edges moves
    none of its interior knots (a grid anchored at ``t0`` shifted by 1e-8 s met a segment's
    own grid 1e-8 s away and made the l1 problem degenerate)."""
    k0 = math.floor(t0 / spacing + 1e-9) + 1
    k1 = math.ceil(t1 / spacing - 1e-9) - 1
    inner = np.arange(k0, k1 + 1, dtype=np.float64) * spacing
    inner = inner[(inner > t0 + 1e-9 * spacing) & (inner < t1 - 1e-9 * spacing)]
    return np.concatenate([[t0], inner, [t1]])


def _merge_close(knots: FloatArray, gap: float) -> FloatArray:
    """Sorted knots with those closer than ``gap`` to the previous one kept dropped."""
    knots = np.sort(knots)
    keep = [0] if knots.size else []
    for i in range(1, knots.size):
        if knots[i] - knots[keep[-1]] >= gap:
            keep.append(i)
    return knots[keep]


def uniform_knots(
    t0: float,
    t1: float,
    spacing: float,
    segments: Sequence[tuple[float, float]] = (),
    segment_spacing: float | None = None,
    events: Sequence[float] = (),
    degree: int = 4,
    kinks: Sequence[float] = (),
) -> FloatArray:
    """Interior knots: the multiples of ``spacing`` s, the multiples of ``segment_spacing``
    s inside the segments (and their ends), and each event repeated ``degree - 1`` times,
    or ``degree - 2`` times (at least once) when it is among the ``kinks`` (the ends of an
    acceleration ramp: the jerk jumps there; :mod:`.events`); ordinary knots closer than a
    third of the local spacing to an event are dropped.
    Knots closer than a quarter of the finer spacing to each other, or to the window's ends,
    are dropped."""
    pts = [_grid(t0, t1, spacing)]
    for a, b in segments:
        a, b = max(a, t0), min(b, t1)
        if b > a and segment_spacing:
            pts[0] = pts[0][(pts[0] <= a) | (pts[0] >= b)]
            pts.append(_grid(a, b, segment_spacing))
    local = min(spacing, segment_spacing or spacing)
    knots = _merge_close(np.concatenate(pts), 0.25 * local)
    # nor closer than that to the window's ends: an edge moved by 1e-6 s changes no knot
    knots = knots[(knots > t0 + 0.25 * local) & (knots < t1 - 0.25 * local)]
    # each event time once, at its own value; the end of a ramp gets one knot fewer
    kink = {round(float(e), 12) for e in kinks}
    first: dict[float, float] = {}
    for e in events:
        if t0 < e < t1:
            first.setdefault(round(float(e), 12), float(e))
    keys = sorted(first)
    ev = np.asarray([first[key] for key in keys], dtype=float)
    mult = [max(degree - 2, 1) if key in kink else degree - 1 for key in keys]
    if ev.size:
        near = np.min(np.abs(knots[:, None] - ev[None, :]), axis=1) < local / 3.0
        knots = knots[~near]
        knots = np.sort(np.concatenate([knots, np.repeat(ev, mult)]))
    return knots


def dynamics_knots(
    rough: RoughTrajectory,
    t0: float,
    t1: float,
    spacing: float,
    events: Sequence[float],
    degree: int = 4,
    kinks: Sequence[float] = (),
) -> FloatArray:
    """Baseline (b), seed 000's method 1 in spirit: knots set from the dynamics of the
    rough trajectory, without sparse selection: a repeated knot at each detected event
    (staging) and otherwise uniform knots at ``spacing``."""
    del rough
    return uniform_knots(t0, t1, spacing, events=events, degree=degree, kinks=kinks)


def _whitened_fit(
    ax: SplineAxis,
    rough: RoughTrajectory,
    pos: FloatArray,
    vel: FloatArray | None,
    rho: float,
    noise: tuple[float, float] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Least-squares fit of one axis; returns (coef, covariance). ``noise`` (position,
    velocity) replaces the rough trajectory's own levels."""
    sp_, sv_ = noise if noise is not None else (rough.position_noise, rough.velocity_noise)
    wp = rho / sp_**2 if vel is not None else 1.0 / sp_**2
    a = ax.design(rough.time)
    blocks = [np.sqrt(wp) * a]
    rhs = [np.sqrt(wp) * pos]
    if vel is not None:
        wv = (1.0 - rho) / sv_**2
        blocks.append(np.sqrt(wv) * ax.design(rough.time, 1))
        rhs.append(np.sqrt(wv) * vel)
    m = sp.vstack(blocks).tocsr()
    b = np.concatenate(rhs)
    n = (m.T @ m).toarray()
    n += 1e-12 * np.max(np.diag(n)) * np.eye(ax.n_coef)
    cov = np.linalg.inv(n)
    return cov @ (m.T @ b), cov


def _robust_rms(e: FloatArray) -> float:
    return 1.4826 * float(np.median(np.abs(e))) if e.size else 0.0


def _axis_noise(
    ax: SplineAxis,
    rough: RoughTrajectory,
    pos: FloatArray,
    vel: FloatArray | None,
    rho: float,
) -> tuple[float, float]:
    """Noise levels of one axis of the rough trajectory at the time scales the knots can
    follow: the larger of its own white-noise level (second differences) and the robust RMS
    of the residuals of a fit on the base knots. Errors correlated in time (a random walk,
    a Gauss-Markov process), a velocity from another source than the position, a time-tag
    skew between the two: the second differences hardly see them, the fit's residuals do.
    Only what varies faster than the base knots, or what position and velocity disagree
    on, is left in those residuals, and no knot should follow it."""
    coef, _ = _whitened_fit(ax, rough, pos, vel, rho)
    sp_ = max(rough.position_noise, _robust_rms(pos - ax.evaluate(coef, rough.time)))
    sv_ = rough.velocity_noise
    if vel is not None:
        sv_ = max(sv_, _robust_rms(vel - ax.evaluate(coef, rough.time, 1)))
    return sp_, sv_


def densify(
    rough: RoughTrajectory,
    frame: tuple[FloatArray, FloatArray],
    t0: float,
    t1: float,
    segments: Sequence[tuple[float, float]],
    events: Sequence[float],
    cfg: KnotConfig,
    kinks: Sequence[float] = (),
) -> tuple[list[SplineAxis], list[FloatArray], list[FloatArray], int]:
    """Seed 000's densification, per spline-frame axis.

    The fit and its tests use each axis's noise levels at the scale of the base knots
    (:func:`_axis_noise`), knot intervals never get shorter than two rough-trajectory
    samples (nor ``min_spacing``), and an axis gains at most as many knots as its base
    grid holds, worst intervals first: the knots stay bounded whatever the rough
    trajectory's errors.

    Returns the axes, their fitted coefficients and coefficient covariances, and the
    number of rounds run.
    """
    origin, rot = frame
    local_p = (rough.position - origin) @ rot
    local_v = None if rough.velocity is None else rough.velocity @ rot
    base = uniform_knots(
        t0, t1, cfg.base_spacing, segments, cfg.gap_spacing, events, cfg.degree, kinks
    )
    dt = float(np.median(np.diff(rough.time))) if len(rough) > 1 else 0.0
    min_spacing = max(cfg.min_spacing, 2.0 * dt)
    event_set = set(np.round(np.asarray(events, dtype=float), 12))
    axes, coefs, covs = [], [], []
    rounds_used = 0
    for a in range(3):
        knots = base.copy()
        vel = None if local_v is None else local_v[:, a]
        ax = SplineAxis.from_interior(knots, t0, t1, cfg.degree)
        noise = _axis_noise(ax, rough, local_p[:, a], vel, cfg.rho)
        budget = base.size
        for rnd in range(cfg.max_rounds + 1):
            ax = SplineAxis.from_interior(knots, t0, t1, cfg.degree)
            coef, cov = _whitened_fit(ax, rough, local_p[:, a], vel, cfg.rho, noise)
            if rnd == cfg.max_rounds or budget <= 0:
                break
            bad = _bad_intervals(ax, coef, rough, local_p[:, a], vel, cfg, noise)
            new = _midpoints(ax, bad, min_spacing, event_set)[:budget]
            if new.size == 0:
                break
            budget -= new.size
            knots = np.sort(np.concatenate([knots, new]))
            rounds_used = max(rounds_used, rnd + 1)
        axes.append(ax)
        coefs.append(coef)
        covs.append(cov)
    return axes, coefs, covs, rounds_used


def _bad_intervals(
    ax: SplineAxis,
    coef: FloatArray,
    rough: RoughTrajectory,
    pos: FloatArray,
    vel: FloatArray | None,
    cfg: KnotConfig,
    noise: tuple[float, float] | None = None,
) -> FloatArray:
    """How far each knot interval's fit error exceeds the thresholds beyond the noise: the
    largest ratio, over position and velocity, of the mean squared error of the ``n``
    samples in the interval to ``sigma^2 + noise^2 q / n``, ``q`` the chi-square(n)
    quantile at ``1 - 0.01 / N`` (``N`` intervals tested), so noise alone rarely makes an
    interval bad (ratio above 1). ``noise`` (position, velocity) replaces the rough
    trajectory's own levels."""
    sp_, sv_ = noise if noise is not None else (rough.position_noise, rough.velocity_noise)
    brk = np.unique(ax.knots)
    idx = np.clip(np.searchsorted(brk, rough.time, side='right') - 1, 0, brk.size - 2)
    n_int = brk.size - 1
    cnt = np.bincount(idx, minlength=n_int).astype(float)
    ratio = np.zeros(n_int)
    checks = [(pos - ax.evaluate(coef, rough.time), sp_, cfg.sigma_position)]
    if vel is not None:
        checks.append((vel - ax.evaluate(coef, rough.time, 1), sv_, cfg.sigma_velocity))
    for e, noise_level, sigma in checks:
        mse = np.bincount(idx, weights=e**2, minlength=n_int) / np.maximum(cnt, 1.0)
        n = np.maximum(cnt, 1.0)
        limit = sigma**2 + noise_level**2 * chi2_ppf_each(1.0 - 0.01 / n_int, n) / n
        ratio = np.maximum(ratio, np.where(cnt > 0, mse / limit, 0.0))
    return ratio


def _midpoints(
    ax: SplineAxis, ratio: FloatArray, min_spacing: float, events: set[float]
) -> FloatArray:
    """Midpoints of each bad interval (``ratio`` above 1) and of its neighbours (clustered
    insertion), worst first; an interval shorter than ``2 min_spacing`` is not split."""
    brk = np.unique(ax.knots)
    bad = ratio > 1.0
    score = np.where(bad, ratio, 0.0)
    # a neighbour of a bad interval is split too, ranked just below the interval itself
    near = np.zeros_like(score)
    near[1:] = np.maximum(near[1:], score[:-1])
    near[:-1] = np.maximum(near[:-1], score[1:])
    score = np.maximum(score, 0.999 * near)
    pick = score > 0.0
    lo, hi, sc = brk[:-1][pick], brk[1:][pick], score[pick]
    ok = (hi - lo) >= 2.0 * min_spacing
    lo, hi, sc = lo[ok], hi[ok], sc[ok]
    del events
    return (0.5 * (lo + hi))[np.argsort(-sc, kind='stable')]


def load_solver(solver: str = 'HIGHS') -> None:
    """Import cvxpy and solve a two-variable LP of the knot selection's shape with
    ``solver``: what a process's first knot selection would otherwise pay (a second, more
    under load), paid ahead of it (the estimator node does it on its worker at start)."""
    import cvxpy as cp

    x = cp.Variable(2)
    prob = cp.Problem(cp.Minimize(cp.norm1(x - 1.0)), [cp.abs(x) <= 2.0])
    prob.solve(solver=solver.upper())  # type: ignore[no-untyped-call]


def select_knots(
    ax: SplineAxis,
    coef: FloatArray,
    cov: FloatArray,
    times: FloatArray,
    cfg: KnotConfig,
    fixed: Sequence[float] = (),
    floor: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[SplineAxis, FloatArray, dict[str, float | str]]:
    """Seed 000's sparse optimisation (eq. 14) on one axis.

    Parameters
    ----------
    ax, coef, cov : the densified axis, its fitted coefficients and their covariance.
    times : ndarray
        Where the fit tolerances are enforced (the rough trajectory's epochs).
    fixed : sequence of float
        Knots never dropped (events).
    floor : (ndarray, ndarray), optional
        Standard deviations of the rough trajectory's position and velocity on this axis
        at ``times`` (an estimate's own uncertainty); the tolerances are at least 3 times
        these.

    Returns
    -------
    axis : SplineAxis
        The reduced basis.
    jumps : ndarray
        ``p``-th-derivative jumps of the sparse solution at the candidate knots.
    info : dict
        ``solver``, ``status``, ``solve_time``.
    """
    import cvxpy as cp

    c_all, tau = ax.jump_matrix()
    fixed_arr = np.asarray(fixed, dtype=float)
    cand = np.ones(tau.size, dtype=bool)
    if fixed_arr.size:
        cand &= np.min(np.abs(tau[:, None] - fixed_arr[None, :]), axis=1) > 1e-9
    c = c_all[np.flatnonzero(cand)]
    all_times = np.asarray(times, dtype=np.float64)
    times = _constraint_times(ax, all_times)
    k0, k1 = ax.design(times), ax.design(times, 1)
    sd0 = np.sqrt(np.maximum(np.einsum('ij,ji->i', (k0 @ cov), k0.T.toarray()), 0.0))
    sd1 = np.sqrt(np.maximum(np.einsum('ij,ji->i', (k1 @ cov), k1.T.toarray()), 0.0))
    d0 = np.maximum(cfg.delta_position, 3.0 * sd0)
    d1 = np.maximum(cfg.delta_velocity, 3.0 * sd1)
    if floor is not None:
        d0 = np.maximum(d0, 3.0 * np.interp(times, all_times, floor[0]))
        d1 = np.maximum(d1, 3.0 * np.interp(times, all_times, floor[1]))
    x = cp.Variable(ax.n_coef)
    base = c @ coef
    if float(np.max(np.abs(base), initial=0.0)) <= cfg.jump_epsilon:
        # every candidate jump is already negligible (a rough trajectory that is one
        # polynomial): drop them all without an LP that would only be scaled noise
        interior = ax.interior
        drop = set(np.round(tau[cand], 12))
        kept = np.array([k for k in interior if round(float(k), 12) not in drop])
        reduced = SplineAxis.from_interior(kept, ax.t0, ax.t1, ax.degree)
        return (
            reduced,
            np.asarray(c_all @ coef),
            {'solver': 'none', 'status': 'negligible jumps', 'solve_time': 0.0},
        )
    scale = 1.0 / float(np.max(np.abs(base)))
    prob = cp.Problem(
        cp.Minimize(scale * cp.norm1(c @ x + base)),
        [cp.abs(k0 @ x) <= d0, cp.abs(k1 @ x) <= d1],
    )
    start = _time.perf_counter()
    solver = cfg.solver.upper()
    try:
        if solver == 'HIGHS':
            # interior point + crossover: a vertex (exact zeros) in half the simplex time;
            # on a badly scaled problem the interior point may stall, and the dual
            # simplex then usually still finds the vertex
            try:
                prob.solve(solver=solver, highs_options={'solver': 'ipm'})  # type: ignore[no-untyped-call]
            except (cp.error.SolverError, ValueError):
                prob.solve(solver=solver)  # type: ignore[no-untyped-call]
            if prob.status != cp.OPTIMAL:
                prob.solve(solver=solver)  # type: ignore[no-untyped-call]
        else:
            prob.solve(solver=solver)  # type: ignore[no-untyped-call]
    except (cp.error.SolverError, ValueError) as exc:
        # cvxpy raises ValueError when the solver ends with an unknown status
        installed = cp.installed_solvers()  # type: ignore[no-untyped-call]
        raise KnotSelectionError(
            f'knot selection: solver {solver} failed ({exc}); installed: {installed}'
        ) from exc
    elapsed = _time.perf_counter() - start
    if prob.status != cp.OPTIMAL or x.value is None:
        raise KnotSelectionError(
            f'knot selection: solver {solver} returned status {prob.status!r}, not optimal'
        )
    new = coef + np.asarray(x.value)
    jumps = np.asarray(c @ new)
    keep = np.abs(jumps) > max(cfg.jump_epsilon, 1e-7 * float(np.max(np.abs(jumps), initial=0)))
    interior = ax.interior
    drop = set(np.round(tau[cand][~keep], 12))
    kept = np.array([k for k in interior if round(float(k), 12) not in drop])
    reduced = SplineAxis.from_interior(kept, ax.t0, ax.t1, ax.degree)
    return reduced, jumps, {'solver': solver, 'status': prob.status, 'solve_time': elapsed}


def _unsampled_knots(ax: SplineAxis, times: FloatArray, gap: float, spacing: float) -> list[float]:
    """Interior knots of ``ax`` on the multiples of ``spacing`` (the base grid, not the finer
    grid of an incomplete segment, which the measurements there could not determine) inside
    stretches longer than ``gap`` without a sample."""
    t = np.sort(np.asarray(times, dtype=np.float64))
    if t.size == 0:
        return []
    lo = np.concatenate([[ax.t0], t])
    hi = np.concatenate([t, [ax.t1]])
    holes = [(a, b) for a, b in zip(lo, hi, strict=True) if b - a > gap]
    on_grid = np.abs(ax.interior / spacing - np.round(ax.interior / spacing)) < 1e-6
    return [
        float(k)
        for k, g in zip(ax.interior, on_grid, strict=True)
        if g and any(a < k < b for a, b in holes)
    ]


def _constraint_times(ax: SplineAxis, t: FloatArray, per_interval: int = 4) -> FloatArray:
    """Thin the epochs where the tolerances are enforced to about ``per_interval`` per
    knot interval (all of them in short intervals): the LP shrinks, the fit does not."""
    if t.size < 2:
        return t
    dt = float(np.median(np.diff(t)))
    brk = np.unique(ax.knots)
    j = np.clip(np.searchsorted(brk, t, side='right') - 1, 0, brk.size - 2)
    length = (brk[1:] - brk[:-1])[j]
    step = np.maximum(1, np.floor(length / (per_interval * dt))).astype(int)
    first = np.searchsorted(t, brk[j], side='left')
    keep = ((np.arange(t.size) - first) % step) == 0
    return t[keep]


@dataclass(frozen=True)
class KnotSelection:
    """Outcome of :func:`choose_knots`.

    ``dense`` and ``selected`` hold the interior-knot counts per axis before and after
    the sparse selection; ``coef`` is the rough trajectory fitted on the selected knots
    (the Gauss-Newton start).
    """

    trajectory: SplineTrajectory
    coef: FloatArray
    events: tuple[float, ...]
    dense: tuple[int, int, int]
    selected: tuple[int, int, int]
    rounds: int
    solve_time: float
    total_time: float
    method: str
    info: dict[str, str] = field(default_factory=dict)
    refined: int = 0
    """Knots added afterwards by the estimator's measurement-driven test."""
    rough_source: str = ''
    pruned: int = 0
    """Knots dropped afterwards: their jump is not significant in the first solution."""
    kinks: tuple[float, ...] = ()
    """The events that are ends of an acceleration ramp (knots of multiplicity
    ``degree - 2``; the others have ``degree - 1``)."""
    doubtful: tuple[float, ...] = ()
    """Where the rough trajectory may change its acceleration but no event was found
    (:attr:`~orbit_tracking.core.estimation.events.Changes.doubtful`): no knots, only the
    covariance's consider term."""
    weak: tuple[tuple[float, float], ...] = ()
    """``(time, jerk jump [m/s^3])`` of the rough trajectory's weak changes
    (:attr:`~orbit_tracking.core.estimation.events.Changes.weak`): no knots, a consider
    term sized by the jump."""


def choose_knots(
    rough: RoughTrajectory,
    t0: float,
    t1: float,
    segments: Sequence[tuple[float, float]],
    cfg: KnotConfig,
    method: str = 'sparse',
    frame: tuple[FloatArray, FloatArray] | None = None,
    baseline_spacing: float = 3.0,
    events: Sequence[float] | None = None,
    context: tuple[RoughTrajectory, float, float] | None = None,
    kinks: Sequence[float] = (),
) -> KnotSelection:
    """Knots of the trajectory spline over [t0, t1].

    ``events`` overrides the detection of acceleration jumps and ramps; ``kinks`` are then
    those of them that are ends of a ramp (:func:`detect_changes`).

    ``method``: ``sparse`` (densify + l1 selection, the seed's method), ``dense``
    (densified grid, no selection: baseline (c)), ``dynamics`` (baseline (b): events +
    uniform ``baseline_spacing``).

    ``context`` ``(rough, a0, a1)``: the rough trajectory over a span [a0, a1] around the
    window (:func:`selection_span`). The ``sparse`` and ``dense`` knots are chosen there and
    the window keeps those inside it (not closer than a quarter of the finer spacing to its
    ends): the selection then sees the same data whether a window edge moves by 1e-6 s or
    not, and neighbouring windows agree where they overlap.
    """
    start = _time.perf_counter()
    src, a0, a1 = context if context is not None else (rough, t0, t1)
    frame = frame or spline_frame(src)
    doubtful: tuple[float, ...] = ()
    weak: tuple[tuple[float, float], ...] = ()
    if events is None:
        found = detect_changes(src, cfg) if cfg.events else Changes()
        events, kinks = found.times, found.kinks
        doubtful = tuple(e for e in found.doubtful if t0 < e < t1)
        if src.source == 'telemetry':  # samples with their own noise, not a spline's
            weak = tuple(w for w in found.weak if t0 < w[0] < t1)
    wide_events = [e for e in events if a0 + cfg.base_spacing / 2 < e < a1 - cfg.base_spacing / 2]
    events = [e for e in events if t0 + cfg.base_spacing / 2 < e < t1 - cfg.base_spacing / 2]
    solve = 0.0
    info: dict[str, str] = {}
    if method == 'dynamics':
        knots = dynamics_knots(rough, t0, t1, baseline_spacing, events, cfg.degree, kinks)
        axes = [SplineAxis.from_interior(knots, t0, t1, cfg.degree) for _ in range(3)]
        dense = tuple(a.interior.size for a in axes)
        selected, rounds = dense, 0
    elif method == 'uniform':
        knots = uniform_knots(t0, t1, cfg.base_spacing, segments, cfg.gap_spacing, (), cfg.degree)
        axes = [SplineAxis.from_interior(knots, t0, t1, cfg.degree) for _ in range(3)]
        dense = tuple(a.interior.size for a in axes)
        selected, rounds = dense, 0
    elif method in ('sparse', 'dense'):
        axes, coefs, covs, rounds = densify(src, frame, a0, a1, segments, wide_events, cfg, kinks)
        dense = tuple(a.interior.size for a in axes)
        if method == 'sparse' and cfg.sparse:
            red = []
            floors = src.axis_sigma(frame[1])
            # where the rough trajectory has no samples (a telemetry outage) nothing says a
            # knot is not needed: those stay, and the measurements decide the shape there
            kept = [
                *wide_events,
                *_unsampled_knots(axes[0], src.time, 2.0 * cfg.base_spacing, cfg.base_spacing),
            ]
            for a in range(3):
                fl = None if floors is None else (floors[0][:, a], floors[1][:, a])
                ax, _, inf = select_knots(
                    axes[a], coefs[a], covs[a], src.time, cfg, kept, floor=fl
                )
                red.append(ax)
                solve += float(inf['solve_time'])
                info = {'solver': str(inf['solver']), 'status': str(inf['status'])}
            axes = red
        if context is not None:
            q = 0.25 * min(cfg.base_spacing, cfg.gap_spacing)
            axes = [
                SplineAxis.from_interior(
                    ax.interior[(ax.interior > t0 + q) & (ax.interior < t1 - q)],
                    t0,
                    t1,
                    cfg.degree,
                )
                for ax in axes
            ]
        if cfg.max_spacing > 0.0:
            axes = [_fill_long_spans(ax, cfg, segments) for ax in axes]
        selected = tuple(a.interior.size for a in axes)
    else:
        raise ValueError(
            f"method must be 'sparse', 'dense', 'uniform' or 'dynamics'; got {method!r}"
        )
    traj = SplineTrajectory((axes[0], axes[1], axes[2]), frame[0], frame[1])
    coef = _fit_rough(traj, rough, cfg.rho)
    return KnotSelection(
        traj,
        coef,
        tuple(events),
        (int(dense[0]), int(dense[1]), int(dense[2])),
        (int(selected[0]), int(selected[1]), int(selected[2])),
        rounds,
        solve,
        _time.perf_counter() - start,
        method,
        info,
        kinks=tuple(k for k in kinks if k in events),
        doubtful=doubtful,
        weak=weak,
    )


def _fill_long_spans(
    axis: SplineAxis, cfg: KnotConfig, segments: Sequence[tuple[float, float]] = ()
) -> SplineAxis:
    """``axis`` with the points of the grid ``k * max_spacing`` inside its span that lie at
    least ``max_spacing / 2`` from every interior knot and from the ends, and outside the
    incomplete ``segments`` (see :class:`KnotConfig`); the grid does not depend on the
    window's edges."""
    h = cfg.max_spacing
    t0, t1 = axis.t0, axis.t1
    grid = np.arange(np.ceil(t0 / h), np.floor(t1 / h) + 1) * h
    if grid.size == 0:
        return axis
    have = np.concatenate([[t0, t1], axis.interior])
    far = np.min(np.abs(grid[:, None] - have[None, :]), axis=1) >= 0.5 * h
    for a, b in segments:
        far &= ~((grid > a) & (grid < b))
    if not np.any(far):
        return axis
    interior = np.sort(np.concatenate([axis.interior, grid[far]]))  # repeats stay
    return SplineAxis.from_interior(interior, t0, t1, cfg.degree)


def selection_span(t0: float, t1: float, cfg: KnotConfig) -> tuple[float, float]:
    """The span around the window [t0, t1] whose rough trajectory the knots are chosen on
    (:func:`choose_knots`' ``context``): out to the multiples of ``base_spacing`` beyond the
    window and one more spacing, so that moving an edge by much less than a spacing changes
    nothing."""
    b = cfg.base_spacing
    # rounded from half a spacing away: windows start and end on round times, and a span
    # rounded at them would flip with the edge (ceil(80.000001) = 81)
    return (math.floor(t0 / b - 0.5) - 1) * b, (math.ceil(t1 / b + 0.5) + 1) * b


def _fit_rough(traj: SplineTrajectory, rough: RoughTrajectory, rho: float) -> FloatArray:
    origin, rot = traj.origin, traj.rotation
    lp = (rough.position - origin) @ rot
    lv = None if rough.velocity is None else rough.velocity @ rot
    out = []
    for a, ax in enumerate(traj.axes):
        coef, _ = _whitened_fit(ax, rough, lp[:, a], None if lv is None else lv[:, a], rho)
        out.append(coef)
    return np.concatenate(out)
