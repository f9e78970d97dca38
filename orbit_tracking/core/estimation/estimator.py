"""Trajectory estimation on a window of raw measurements (seed 000).

The unknowns are the spline coefficients of every target's trajectory
(:mod:`~orbit_tracking.core.estimation.bspline`, knots from
:mod:`~orbit_tracking.core.estimation.knots`) and,
when on-board telemetry is fused, the coefficients of its slowly varying error. Every
measurement is whitened by its sigma, ``Y = F(beta) + E, E ~ N(0, I)``, and

    beta <- beta + omega (J^T J)^-1 J^T (Y - F(beta))            (seed 000, eq. 7)

with ``omega = 1`` halved while the cost rises (Gauss-Newton with step halving). The
Jacobian is sparse (a row touches ``degree + 1`` coefficients per axis); the normal
matrix is small and solved by Cholesky. The coefficient covariance ``(J^T J)^-1`` is
propagated to position and velocity at any time.

Measurement rows:

* stations: every field of the contract (range, range_rate, azimuth with wrap-around,
  elevation, los_alpha, los_beta) through :func:`~orbit_tracking.core.models.measurements.predict`;
* telemetry (beyond the paper): ``tel_p = p(t) + e(t) + w``, ``tel_v = v(t) + e'(t) + w'``
  with ``e`` a cubic spline per axis with knots every ``telemetry_error_spacing`` s (an
  offset and a drift that may bend slowly), a weak prior on ``e`` (the telemetry's
  reported sigma) and white-noise levels re-estimated from the residuals;
* fixes, optionally, as weak position measurements (their covariance divided by
  ``fix_weight``); they come from the same measurements, so they are off by default.

Outliers: after the warm-up solve, rows whose whitened residual exceeds ``gate_sigma``
are rejected (counted per station and reason) and the solve repeated.
"""

from __future__ import annotations

import math
import time as _time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.coverage import (
    CoverageConfig,
    find_incomplete_segments,
    merge_segments,
)
from orbit_tracking.core.estimation.knots import (
    KnotConfig,
    KnotSelection,
    KnotSelectionError,
    RoughTrajectory,
    choose_knots,
    rough_trajectory,
    uniform_knots,
)
from orbit_tracking.core.models.measurements import predict, residual
from orbit_tracking.core.models.systematic import CLOCK, BiasModel, BiasParameter

__all__ = [
    'KNOT_METHODS',
    'BiasEstimate',
    'EstimationError',
    'Estimate',
    'EstimatorConfig',
    'TargetSolution',
    'estimate',
    'state_covariance',
]

FloatArray = NDArray[np.float64]
Segment = tuple[float, float]

KNOT_METHODS: tuple[str, ...] = ('sparse', 'dense', 'uniform', 'dynamics', 'polynomial')


class EstimationError(OrbitTrackingError, RuntimeError):
    """A window cannot be estimated (no data, no rough trajectory, singular problem)."""


@dataclass(frozen=True)
class EstimatorConfig:
    """Settings of one window's estimation.

    Attributes
    ----------
    knots : KnotConfig
    knot_method : str
        ``sparse`` (the seed's method), or the baselines ``dynamics`` (b), ``uniform``
        (c, dense uniform knots), ``dense`` (densified, no selection), ``polynomial``
        (a, one polynomial of ``polynomial_degree`` per axis over the window).
    baseline_spacing : float
        Knot spacing [s] of the ``dynamics`` baseline.
    polynomial_degree : int
    max_iterations, tolerance, max_halvings :
        Gauss-Newton stops when the relative cost change falls below ``tolerance`` or
        after ``max_iterations``; a step is halved at most ``max_halvings`` times.
    gate_sigma : float
        Whitened-residual gate (0 disables it); ``gate_rounds`` re-solves at most.
    use_telemetry : bool
        Fuse telemetry as weighted measurements with its own error model (whose knots
        the measurement-driven test refines like the trajectory's).
    telemetry_error_spacing : float
        Knot spacing [s] of the telemetry error spline (cubic).
    estimate_telemetry_noise : bool
        Re-estimate the telemetry white-noise levels from the residuals.
    fix_weight : float
        Fixes as measurements with covariance / ``fix_weight``; 0 = not used.
    refine_rounds : int
        Rounds of measurement-driven knot insertion after the solve (0 = off).
    refine_alpha : float
        Family-wise false-alarm probability of that knot test.
    biases : tuple of BiasParameter
        Systematic errors estimated jointly with the trajectories (shared by every
        target a station sees), or held at known values.
    bias_observability : float
        A bias whose posterior sigma exceeds this fraction of its prior sigma is not
        separable from the trajectory with this geometry: it is frozen at its prior and
        reported as unobservable.
    thrust_along_velocity : float
        Sigma [m/s^2] of an optional dynamics constraint for a vehicle boosting with its
        thrust along the velocity (zero angle of attack, seed 003): at every
        ``thrust_grid`` seconds the component of ``a - g(p)`` normal to ``v`` is a
        pseudo-measurement of zero. Needs an inertial, Earth-centred world frame (point-mass
        gravity ``gm``; J2 is left in the sigma). 0 (default) = off. It is what lets one
        target separate the satellites' biases from its trajectory.
    thrust_grid : float
        Spacing [s] of those pseudo-measurements.
    gm : float
        Gravitational parameter [m^3/s^2] of that constraint.
    segments : tuple of (start, end)
        Declared incomplete segments [s] (added to the detected ones).
    detect_segments : bool
    coverage : CoverageConfig
    """

    knots: KnotConfig = field(default_factory=KnotConfig)
    knot_method: str = 'sparse'
    baseline_spacing: float = 3.0
    polynomial_degree: int = 6
    max_iterations: int = 20
    tolerance: float = 1e-9
    max_halvings: int = 12
    gate_sigma: float = 5.0
    gate_rounds: int = 3
    use_telemetry: bool = True
    telemetry_error_spacing: float = 15.0
    estimate_telemetry_noise: bool = True
    fix_weight: float = 0.0
    refine_rounds: int = 4
    refine_alpha: float = 0.01
    biases: tuple[BiasParameter, ...] = ()
    bias_observability: float = 0.9
    thrust_along_velocity: float = 0.0
    thrust_grid: float = 0.5
    gm: float = 3.986005e14
    segments: tuple[Segment, ...] = ()
    detect_segments: bool = True
    coverage: CoverageConfig = field(default_factory=CoverageConfig)

    def __post_init__(self) -> None:
        if self.knot_method not in KNOT_METHODS:
            raise ValueError(
                f'knot_method must be one of {KNOT_METHODS}; got {self.knot_method!r}'
            )
        if self.max_iterations < 1 or self.max_halvings < 0:
            raise ValueError('max_iterations must be >= 1 and max_halvings >= 0')
        if self.gate_sigma < 0.0 or self.fix_weight < 0.0:
            raise ValueError('gate_sigma and fix_weight must be >= 0')
        if self.telemetry_error_spacing <= 0.0:
            raise ValueError('telemetry_error_spacing must be > 0')
        if self.thrust_along_velocity < 0.0 or self.thrust_grid <= 0.0 or self.gm <= 0.0:
            raise ValueError('thrust_along_velocity must be >= 0, thrust_grid and gm > 0')
        for a, b in self.segments:
            if not b > a:
                raise ValueError(f'segment ({a}, {b}) must have end > start')


@dataclass(frozen=True)
class TargetSolution:
    """The fitted trajectory of one target.

    ``covariance`` is the marginal covariance of ``coef`` (all other parameters
    estimated too); use :meth:`states` for position/velocity and their covariance.
    """

    target_id: int
    trajectory: SplineTrajectory
    coef: FloatArray
    covariance: FloatArray
    knots: KnotSelection
    segments: tuple[Segment, ...]
    telemetry_error: tuple[SplineAxis, FloatArray] | None = None
    telemetry_noise: tuple[float, float] | None = None

    @property
    def t0(self) -> float:
        return self.trajectory.t0

    @property
    def t1(self) -> float:
        return self.trajectory.t1

    def states(self, t: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray]:
        """World-frame (position, velocity) (m, 6) and their covariance (m, 6, 6)."""
        tt = np.asarray(t, dtype=np.float64)
        return self.trajectory.states(self.coef, tt), state_covariance(
            self.trajectory, self.covariance, tt
        )

    def parameters_in(self, a: float, b: float) -> int:
        """Coefficients whose support overlaps (a, b) (the seed's 'parameters in the gap')."""
        n = 0
        for ax in self.trajectory.axes:
            k, p = ax.knots, ax.degree
            lo, hi = k[: ax.n_coef], k[p + 1 : p + 1 + ax.n_coef]
            n += int(np.sum((hi > a) & (lo < b)))
        return n


def state_covariance(traj: SplineTrajectory, cov: FloatArray, t: FloatArray) -> FloatArray:
    """Covariance (m, 6, 6) of world position and velocity from the coefficient
    covariance ``cov`` (n_coef, n_coef)."""
    m = t.shape[0]
    g = sp.vstack([traj.world_design(t, 0), traj.world_design(t, 1)]).tocsr()
    gp = np.asarray(g @ cov)  # (6m, n)
    gd = g.toarray() if g.shape[0] * g.shape[1] < 5e7 else None
    if gd is None:
        raise EstimationError('too many output times for one covariance evaluation')
    rows = np.concatenate([np.arange(m) * 3 + c for c in range(3)] + [])
    del rows
    # index of (time j, component c) in g: position rows 3j + c, velocity rows 3m + 3j + c
    idx = np.empty((m, 6), dtype=int)
    for c in range(3):
        idx[:, c] = 3 * np.arange(m) + c
        idx[:, 3 + c] = 3 * m + 3 * np.arange(m) + c
    a = gp[idx]  # (m, 6, n)
    b = gd[idx]  # (m, 6, n)
    out = np.einsum('min,mjn->mij', a, b)
    return 0.5 * (out + np.transpose(out, (0, 2, 1)))


@dataclass(frozen=True)
class BiasEstimate:
    """One systematic error after the solve. ``status`` is ``estimated``, ``known``
    (held at its declared value) or ``unobservable: <reason>`` (frozen at its prior)."""

    station: str
    name: str
    value: float
    sigma: float
    prior: float
    prior_sigma: float
    status: str


@dataclass(frozen=True)
class Estimate:
    """Outcome of one window, the way ``scipy.optimize`` reports.

    Attributes
    ----------
    success : bool
    message : str
    t0, t1 : float
        Window span [s].
    targets : mapping of target id to TargetSolution
    iterations, halvings : int
    cost : float
        Final ``|r|^2`` (whitened).
    chi2_dof : float
        ``cost / (rows - parameters)``.
    condition : float
        Condition number of the Jacobi-scaled normal matrix.
    n_parameters : int
    used, rejected : Counter
        Rows used per station id; rejected rows per ``(station id, reason)``.
    residuals : mapping of station id to (time (n,), field names, whitened residual (n, k))
    knot_time, solve_time : float
        Wall time [s] of knot selection and of the Gauss-Newton solve.
    """

    success: bool
    message: str
    t0: float
    t1: float
    targets: Mapping[int, TargetSolution]
    iterations: int
    halvings: int
    cost: float
    chi2_dof: float
    condition: float
    n_parameters: int
    used: Counter[str]
    rejected: Counter[tuple[str, str]]
    residuals: Mapping[str, tuple[FloatArray, tuple[str, ...], FloatArray]]
    knot_time: float
    solve_time: float
    covariance: FloatArray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))
    biases: tuple[BiasEstimate, ...] = ()


# ---------------------------------------------------------------------------------------
# problem assembly


@dataclass
class _StationBlock:
    station: str
    target: int
    fields: tuple[str, ...]
    time: FloatArray
    values: FloatArray
    sigmas: FloatArray
    pose: object
    pw: sp.csr_matrix  # (3m, n_t) world position design
    vw: sp.csr_matrix
    valid: NDArray[np.bool_]  # (m, k)
    bias_index: list[int] = field(default_factory=list)  # into _Problem.biases
    clock: int | None = None  # position of the clock bias in bias_index
    tau: float = 0.0  # clock offset the designs pw, vw (and aw) are evaluated at
    aw: sp.csr_matrix | None = None  # acceleration design (clock Jacobian)


@dataclass
class _TelemetryBlock:
    target: int
    time: FloatArray
    position: FloatArray
    velocity: FloatArray
    pw: sp.csr_matrix
    vw: sp.csr_matrix
    ew: sp.csr_matrix  # (3m, 3 n_e) error design (position)
    edw: sp.csr_matrix
    axis: SplineAxis
    offset: int  # first error coefficient
    prior_sigma: tuple[float, float]
    noise: list[float]  # [position, velocity] white sigma
    valid_p: NDArray[np.bool_]
    valid_v: NDArray[np.bool_]


@dataclass
class _FixBlock:
    target: int
    time: FloatArray
    position: FloatArray
    whiten: FloatArray  # (m, 3, 3), W^T W = weight * inv(cov)
    pw: sp.csr_matrix
    valid: NDArray[np.bool_]


def _row_contract(h: FloatArray, design: sp.csr_matrix) -> sp.csr_matrix:
    """Rows ``sum_c h[i, j, c] design[3 i + c]`` for every (i, j): (m k, n)."""
    m, k, _ = h.shape
    indptr = np.arange(m * k + 1) * 3
    indices = (3 * np.arange(m)[:, None, None] + np.arange(3)[None, None, :]).repeat(k, axis=1)
    s = sp.csr_matrix((h.ravel(), indices.ravel(), indptr), shape=(m * k, 3 * m))
    return (s @ design).tocsr()


def _thrust_normal(
    p: FloatArray, v: FloatArray, a: FloatArray, gm: float, jacobian: bool
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``c = (I - u u^T)(a - g(p))`` with ``u = v/|v|`` and ``g = -gm p/|p|^3``: the
    non-gravitational acceleration normal to the velocity, (m, 3); and its derivatives
    by p, v and a, (m, 3, 3) each (zeros when ``jacobian`` is False)."""
    rn = np.linalg.norm(p, axis=1)
    g = -gm * p / rn[:, None] ** 3
    f = a - g
    vn = np.linalg.norm(v, axis=1)
    u = v / vn[:, None]
    eye = np.eye(3)
    proj = eye - np.einsum('mi,mj->mij', u, u)
    c = np.einsum('mij,mj->mi', proj, f)
    m = p.shape[0]
    if not jacobian:
        z = np.zeros((m, 3, 3))
        return c, z, z, z
    dg = -gm * (
        eye / rn[:, None, None] ** 3 - 3.0 * np.einsum('mi,mj->mij', p, p) / rn[:, None, None] ** 5
    )
    jp = -np.einsum('mij,mjk->mik', proj, dg)
    fm = np.einsum('mj,mjk->mk', f, proj)  # f^T (I - u u^T)
    fu = np.einsum('mi,mi->m', f, u)
    jv = -(np.einsum('mi,mk->mik', u, fm) + fu[:, None, None] * proj) / vn[:, None, None]
    return c, jp, jv, proj


def _shift(mat: sp.spmatrix, offset: int, n: int) -> sp.csr_matrix:
    coo = mat.tocoo()
    return sp.csr_matrix((coo.data, (coo.row, coo.col + offset)), shape=(coo.shape[0], n))


class _Problem:
    def __init__(
        self,
        obs: Observations,
        solutions: dict[int, tuple[SplineTrajectory, FloatArray]],
        cfg: EstimatorConfig,
        t0: float,
        t1: float,
        tel_axes: Mapping[int, SplineAxis] | None = None,
    ) -> None:
        self.cfg = cfg
        self.offsets: dict[int, int] = {}
        n = 0
        for tid, (traj, _) in solutions.items():
            self.offsets[tid] = n
            n += traj.n_coef
        self.trajs = {tid: s[0] for tid, s in solutions.items()}
        self.origin = {tid: tr.origin for tid, tr in self.trajs.items()}
        self.stations: list[_StationBlock] = []
        for s in obs.stations:
            tab = s.table
            for tid in self.trajs:
                sel = tab.target_id == tid
                if not np.any(sel):
                    continue
                idx = np.flatnonzero(sel)
                t = tab.time[idx]
                traj = self.trajs[tid]
                valid = np.isfinite(tab.values[idx]) & (tab.sigmas[idx] > 0)
                self.stations.append(
                    _StationBlock(
                        tab.station_id,
                        tid,
                        tab.fields,
                        t,
                        tab.values[idx],
                        tab.sigmas[idx],
                        s.pose.take(idx),
                        traj.world_design(t, 0),
                        traj.world_design(t, 1),
                        valid,
                    )
                )
        self.telemetry: list[_TelemetryBlock] = []
        if cfg.use_telemetry:
            for tid, tel in obs.telemetry.items():
                if tid not in self.trajs or len(tel) < 4:
                    continue
                traj = self.trajs[tid]
                if tel_axes and tid in tel_axes:
                    axis = tel_axes[tid]
                else:
                    knots = uniform_knots(t0, t1, cfg.telemetry_error_spacing, degree=3)
                    axis = SplineAxis.from_interior(knots, t0, t1, 3)
                e0, e1 = axis.design(tel.time, 0), axis.design(tel.time, 1)
                i3 = sp.identity(3, format='csr')
                self.telemetry.append(
                    _TelemetryBlock(
                        tid,
                        tel.time,
                        tel.position,
                        tel.velocity,
                        traj.world_design(tel.time, 0),
                        traj.world_design(tel.time, 1),
                        sp.kron(e0, i3, format='csr'),
                        sp.kron(e1, i3, format='csr'),
                        axis,
                        n,
                        (
                            float(np.median(tel.position_sigma)),
                            float(np.median(tel.velocity_sigma)),
                        ),
                        [
                            float(np.median(tel.position_sigma)),
                            float(np.median(tel.velocity_sigma)),
                        ],
                        np.asarray(np.isfinite(tel.position).all(axis=1)),
                        np.asarray(np.isfinite(tel.velocity).all(axis=1)),
                    )
                )
                n += 3 * axis.n_coef
        self.fixes: list[_FixBlock] = []
        if cfg.fix_weight > 0.0:
            for tid, fx in obs.fixes.items():
                if tid not in self.trajs or not len(fx):
                    continue
                inv = np.linalg.inv(fx.covariance) * cfg.fix_weight
                w = np.transpose(np.linalg.cholesky(inv), (0, 2, 1))
                self.fixes.append(
                    _FixBlock(
                        tid,
                        fx.time,
                        fx.position,
                        w,
                        self.trajs[tid].world_design(fx.time, 0),
                        np.asarray(np.isfinite(fx.position).all(axis=1)),
                    )
                )
        # the thrust-along-velocity constraint: designs on a grid per target
        self.dynamics: list[tuple[int, sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]] = []
        if cfg.thrust_along_velocity > 0.0:
            for tid, traj in self.trajs.items():
                tg = np.arange(t0 + 0.5 * cfg.thrust_grid, t1, cfg.thrust_grid)
                self.dynamics.append((tid, *(traj.world_design(tg, nu) for nu in (0, 1, 2))))
        present = {b.station for b in self.stations}
        self.biases = [bp for bp in cfg.biases if bp.station in present]
        for b in self.stations:
            b.bias_index = [q for q, bp in enumerate(self.biases) if bp.station == b.station]
            names = [self.biases[q].name for q in b.bias_index]
            b.clock = names.index(CLOCK) if CLOCK in names else None
        self.bias_offset = n
        n += len(self.biases)
        # prior sigma of each bias; a frozen or known bias gets a vanishing one
        self.bias_sigma = np.array(
            [bp.sigma if bp.estimate else bp.sigma * 1e-9 for bp in self.biases], dtype=float
        )
        self.bias_prior = np.array([bp.prior for bp in self.biases], dtype=float)
        self.bias_status = ['estimated' if bp.estimate else 'known' for bp in self.biases]
        self.bias_lower = np.array([bp.bounds[0] for bp in self.biases], dtype=float)
        self.bias_upper = np.array([bp.bounds[1] for bp in self.biases], dtype=float)
        self.n = n
        self.gated: dict[int, NDArray[np.bool_]] = {}
        self.gate_refused = 0.0
        self.rows: list[tuple[int, FloatArray, FloatArray, FloatArray, bool]] = []

    # -- evaluation ------------------------------------------------------------------

    def predict_block(
        self, bi: int, beta: FloatArray, jacobian: bool = False
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
        """Measured values predicted for station block ``bi`` (biases applied), with
        ``d/d state`` (m, k, 6) and ``d/d biases`` (m, k, p) of the block's biases."""
        b = self.stations[bi]
        coef = self._coef(beta, b.target)
        idx = self.bias_offset + np.asarray(b.bias_index, dtype=int)
        if b.clock is not None:
            self._clock_designs(b, float(beta[idx[b.clock]]))
        m = b.time.size
        p = (b.pw @ coef).reshape(m, 3) + self.origin[b.target]
        v = (b.vw @ coef).reshape(m, 3)
        true, h = predict(b.fields, np.hstack([p, v]), b.pose, jacobian=jacobian)  # type: ignore[arg-type]
        if not b.bias_index:
            return true, h, None
        names = [self.biases[q].name for q in b.bias_index]
        keep = [j for j, name in enumerate(names) if name != CLOCK]
        values = beta[idx]
        model = BiasModel({names[j]: float(values[j]) for j in keep})
        measured = model.apply(b.fields, true)
        if not jacobian or h is None:
            return measured, None, None
        d_true, d_value = model.jacobian(b.fields, true, [names[j] for j in keep])
        h_meas = np.einsum('mkj,mjs->mks', d_true, h)
        d_param = np.zeros((m, len(b.fields), len(names)))
        d_param[:, :, keep] = d_value
        if b.clock is not None:
            # the row tagged t measured the target at t + clock: d/d clock = H [v; a]
            assert b.aw is not None
            a = (b.aw @ coef).reshape(m, 3)
            d_param[:, :, b.clock] = np.einsum('mks,ms->mk', h_meas, np.hstack([v, a]))
        return measured, h_meas, d_param

    def _clock_designs(self, b: _StationBlock, tau: float) -> None:
        """Designs of a block at its rows' true epochs ``t + tau`` (rebuilt when the
        clock estimate moves)."""
        if b.aw is not None and tau == b.tau:
            return
        traj = self.trajs[b.target]
        t = np.clip(b.time + tau, traj.t0, traj.t1)  # a row at the edge stays on it
        b.pw, b.vw, b.aw = (traj.world_design(t, nu) for nu in (0, 1, 2))
        b.tau = tau

    def project(self, beta: FloatArray) -> FloatArray:
        """``beta`` with every bias clipped into its declared bounds."""
        if self.biases:
            sl = slice(self.bias_offset, self.bias_offset + len(self.biases))
            beta[sl] = np.clip(beta[sl], self.bias_lower, self.bias_upper)
        return beta

    def _coef(self, beta: FloatArray, tid: int) -> FloatArray:
        o = self.offsets[tid]
        return beta[o : o + self.trajs[tid].n_coef]

    def evaluate(
        self, beta: FloatArray, jacobian: bool
    ) -> tuple[FloatArray, sp.csr_matrix | None, list[tuple[str, int, NDArray[np.bool_]]]]:
        """Whitened residuals (and Jacobian of the model, ``d F / d beta``)."""
        res: list[FloatArray] = []
        jac: list[sp.csr_matrix] = []
        tags: list[tuple[str, int, NDArray[np.bool_]]] = []
        # per residual row: target, time, dF/dp and dF/dv (whitened), for the knot test
        rows: list[tuple[int, FloatArray, FloatArray, FloatArray, bool]] = []
        for bi, b in enumerate(self.stations):
            pred, h, dpar = self.predict_block(bi, beta, jacobian)
            r = residual(b.fields, np.nan_to_num(b.values), pred) / b.sigmas
            use = b.valid & ~self.gated.get(bi, np.zeros_like(b.valid))
            res.append(r[use])
            tags.append(('station', bi, use))
            if jacobian:
                assert h is not None
                hw = h / b.sigmas[:, :, None]
                jm = _row_contract(hw[:, :, :3], b.pw) + _row_contract(hw[:, :, 3:], b.vw)
                jm = jm[np.flatnonzero(use.ravel())]
                jm = _shift(jm, self.offsets[b.target], self.n)
                if dpar is not None:
                    dw = (dpar / b.sigmas[:, :, None])[use]  # (rows, p)
                    cols = self.bias_offset + np.asarray(b.bias_index)
                    rr, cc = np.nonzero(dw)
                    jm = jm + sp.csr_matrix(
                        (dw[rr, cc], (rr, cols[cc])), shape=(dw.shape[0], self.n)
                    )
                jac.append(jm)
                tt = np.broadcast_to(b.time[:, None], use.shape)[use]
                rows.append((b.target, tt, hw[:, :, :3][use], hw[:, :, 3:][use], False))
        for tb in self.telemetry:
            coef = self._coef(beta, tb.target)
            ecoef = beta[tb.offset : tb.offset + 3 * tb.axis.n_coef]
            m = tb.time.size
            pred_p = (tb.pw @ coef + tb.ew @ ecoef).reshape(m, 3) + self.origin[tb.target]
            pred_v = (tb.vw @ coef + tb.edw @ ecoef).reshape(m, 3)
            sp_, sv_ = tb.noise
            rp = ((np.nan_to_num(tb.position) - pred_p) / sp_)[tb.valid_p].ravel()
            rv = ((np.nan_to_num(tb.velocity) - pred_v) / sv_)[tb.valid_v].ravel()
            prior = ecoef / np.tile([tb.prior_sigma[0]], ecoef.size)
            res.extend([rp, rv, -prior])
            tags.append(('telemetry_position', tb.target, tb.valid_p))
            tags.append(('telemetry_velocity', tb.target, tb.valid_v))
            tags.append(('telemetry_prior', tb.target, np.ones(ecoef.size, dtype=bool)))
            if jacobian:
                rows_p = np.flatnonzero(np.repeat(tb.valid_p, 3))
                rows_v = np.flatnonzero(np.repeat(tb.valid_v, 3))
                o = self.offsets[tb.target]
                jp = _shift(tb.pw[rows_p], o, self.n) + _shift(tb.ew[rows_p], tb.offset, self.n)
                jv = _shift(tb.vw[rows_v], o, self.n) + _shift(tb.edw[rows_v], tb.offset, self.n)
                jac.extend([jp / sp_, jv / sv_])
                pj = sp.identity(ecoef.size, format='csr') / tb.prior_sigma[0]
                jac.append(-_shift(pj, tb.offset, self.n))
                eye = np.eye(3)
                for valid, sig, vel in ((tb.valid_p, sp_, False), (tb.valid_v, sv_, True)):
                    nv = int(valid.sum())
                    unit = np.tile(eye / sig, (nv, 1))
                    zero = np.zeros_like(unit)
                    tt = np.repeat(tb.time[valid], 3)
                    rows.append(
                        (tb.target, tt, zero if vel else unit, unit if vel else zero, True)
                    )
                z = np.zeros((ecoef.size, 3))
                rows.append((-1, np.zeros(ecoef.size), z, z, False))
        for fb in self.fixes:
            coef = self._coef(beta, fb.target)
            m = fb.time.size
            d = fb.position - (fb.pw @ coef).reshape(m, 3) - self.origin[fb.target]
            r = np.einsum('mij,mj->mi', fb.whiten, d)[fb.valid].ravel()
            res.append(r)
            tags.append(('fix', fb.target, fb.valid))
            if jacobian:
                wblk = sp.block_diag(list(fb.whiten), format='csr')
                jm = (wblk @ fb.pw)[np.flatnonzero(np.repeat(fb.valid, 3))]
                jac.append(_shift(jm, self.offsets[fb.target], self.n))
                wv = fb.whiten[fb.valid].reshape(-1, 3)
                tt = np.repeat(fb.time[fb.valid], 3)
                rows.append((fb.target, tt, wv, np.zeros_like(wv), False))
        for tid, dp, dv, da in self.dynamics:
            coef = self._coef(beta, tid)
            c, jp, jv, ja = _thrust_normal(
                (dp @ coef).reshape(-1, 3) + self.origin[tid],
                (dv @ coef).reshape(-1, 3),
                (da @ coef).reshape(-1, 3),
                self.cfg.gm,
                jacobian,
            )
            sig = self.cfg.thrust_along_velocity
            res.append(-c.ravel() / sig)
            tags.append(('thrust', tid, np.ones(c.shape[0], dtype=bool)))
            if jacobian:
                jm = (
                    _row_contract(jp / sig, dp)
                    + _row_contract(jv / sig, dv)
                    + _row_contract(ja / sig, da)
                )
                jac.append(_shift(jm, self.offsets[tid], self.n))
                z = np.zeros((c.size, 3))
                rows.append((-1, np.zeros(c.size), z, z, False))
        if self.biases:
            bvals = beta[self.bias_offset : self.bias_offset + len(self.biases)]
            res.append((self.bias_prior - bvals) / self.bias_sigma)
            tags.append(('bias_prior', -1, np.ones(len(self.biases), dtype=bool)))
            if jacobian:
                q = np.arange(len(self.biases))
                jac.append(
                    sp.csr_matrix(
                        (1.0 / self.bias_sigma, (q, self.bias_offset + q)),
                        shape=(q.size, self.n),
                    )
                )
                z = np.zeros((q.size, 3))
                rows.append((-1, np.zeros(q.size), z, z, False))
        r_all = np.concatenate(res) if res else np.zeros(0)
        j_all = sp.vstack(jac).tocsr() if jacobian and jac else None
        if jacobian:
            self.rows = rows
        return r_all, j_all, tags

    def cost(self, beta: FloatArray) -> float:
        r, _, _ = self.evaluate(beta, False)
        return float(r @ r)


# ---------------------------------------------------------------------------------------
# solver


@dataclass
class _GnOutcome:
    beta: FloatArray
    cost: float
    iterations: int
    halvings: int
    converged: bool
    message: str


DAMPING = 1e-10
"""Relative (Jacobi-scaled) damping of the normal matrix: directions the data do not
determine to better than 1e-10 of the best-determined one stay where they are instead of
running away (Levenberg-Marquardt with a fixed, tiny lambda)."""


def _normal_solve(n: FloatArray, g: FloatArray) -> tuple[FloatArray, float, bool]:
    d = np.sqrt(np.maximum(np.diag(n), 1e-300))
    ns = n / d[:, None] / d[None, :]
    ns[np.diag_indices_from(ns)] += DAMPING
    try:
        cf = sla.cho_factor(ns, check_finite=False)
        step = sla.cho_solve(cf, g / d, check_finite=False) / d
        ok = True
    except np.linalg.LinAlgError:
        step = np.linalg.lstsq(ns, g / d, rcond=1e-12)[0] / d
        ok = False
    ev = np.linalg.eigvalsh(ns)
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
    return step, cond, ok


def _gauss_newton(prob: _Problem, beta: FloatArray, cfg: EstimatorConfig) -> _GnOutcome:
    r, jac, _ = prob.evaluate(beta, True)
    cost = float(r @ r)
    halvings = 0
    for it in range(1, cfg.max_iterations + 1):
        assert jac is not None
        n = (jac.T @ jac).toarray()
        g = jac.T @ r
        step, _, _ = _normal_solve(n, g)
        omega = 1.0
        for _ in range(cfg.max_halvings + 1):
            trial = prob.project(beta + omega * step)
            c_new = prob.cost(trial)
            if c_new <= cost:
                break
            omega *= 0.5
            halvings += 1
        else:
            return _GnOutcome(beta, cost, it, halvings, True, 'no step reduces the cost')
        change = cost - c_new
        beta = trial
        r, jac, _ = prob.evaluate(beta, True)
        cost = float(r @ r)
        if change <= cfg.tolerance * max(cost, 1.0):
            return _GnOutcome(beta, cost, it, halvings, True, 'converged')
    return _GnOutcome(beta, cost, cfg.max_iterations, halvings, False, 'iteration limit')


REFINE_MAX_CHI2 = 3.0
"""The measurement-driven knot test runs only while chi2/dof of the fit is below this."""

GATE_MAX_FRACTION = 0.05
"""The residual gate rejects outliers, not the data: if it would reject more than this
fraction of the rows, the model itself does not fit (e.g. unmodelled systematic errors),
nothing is gated and the estimate says so."""


def _gate(prob: _Problem, beta: FloatArray, gate: float) -> bool:
    """Mark station rows whose whitened residual exceeds ``gate``; True if it changed."""
    new_masks = {}
    n_rows = n_bad = 0
    for bi, b in enumerate(prob.stations):
        pred, _, _ = prob.predict_block(bi, beta)
        r = residual(b.fields, np.nan_to_num(b.values), pred) / b.sigmas
        new_masks[bi] = b.valid & (np.abs(r) > gate)
        n_rows += int(b.valid.sum())
        n_bad += int(new_masks[bi].sum())
    if n_rows and n_bad > GATE_MAX_FRACTION * n_rows:
        prob.gate_refused = n_bad / n_rows
        new_masks = {bi: np.zeros_like(b.valid) for bi, b in enumerate(prob.stations)}
    else:
        prob.gate_refused = 0.0
    changed = False
    for bi, new in new_masks.items():
        old = prob.gated.get(bi)
        if (old is None and new.any()) or (old is not None and not np.array_equal(old, new)):
            changed = True
        prob.gated[bi] = new
    return changed


def _reestimate_telemetry_noise(prob: _Problem, beta: FloatArray) -> bool:
    changed = False
    for tb in prob.telemetry:
        coef = prob._coef(beta, tb.target)
        ecoef = beta[tb.offset : tb.offset + 3 * tb.axis.n_coef]
        m = tb.time.size
        ep = tb.position - (tb.pw @ coef + tb.ew @ ecoef).reshape(m, 3) - prob.origin[tb.target]
        ep = ep[tb.valid_p]
        ev = (tb.velocity - (tb.vw @ coef + tb.edw @ ecoef).reshape(m, 3))[tb.valid_v]
        new = [
            max(float(np.sqrt(np.mean(ep**2))), 1e-3) if ep.size else tb.noise[0],
            max(float(np.sqrt(np.mean(ev**2))), 1e-5) if ev.size else tb.noise[1],
        ]
        if any(abs(a - b) > 0.05 * b for a, b in zip(new, tb.noise, strict=True)):
            changed = True
        tb.noise = new
    return changed


def _solve(prob: _Problem, beta: FloatArray, cfg: EstimatorConfig) -> tuple[_GnOutcome, int, int]:
    """Gauss-Newton, then telemetry noise re-estimation and residual gating, repeated
    until neither changes (at most ``gate_rounds`` times)."""
    out = _gauss_newton(prob, beta, cfg)
    iterations, halvings = out.iterations, out.halvings
    for _ in range(max(cfg.gate_rounds, 1)):
        changed = False
        if cfg.estimate_telemetry_noise and prob.telemetry:
            changed |= _reestimate_telemetry_noise(prob, out.beta)
        if cfg.gate_sigma > 0.0:
            changed |= _gate(prob, out.beta, cfg.gate_sigma)
        if not changed:
            break
        out = _gauss_newton(prob, out.beta, cfg)
        iterations += out.iterations
        halvings += out.halvings
    return out, iterations, halvings


def _covariance(
    prob: _Problem, beta: FloatArray
) -> tuple[FloatArray, sp.csr_matrix, FloatArray, float, bool]:
    """Residuals, Jacobian, ``(J^T J)^-1``, condition number of the scaled normal matrix,
    and whether it was singular."""
    r, jac, _ = prob.evaluate(beta, True)
    if jac is None:
        raise EstimationError('no measurement rows to estimate from')
    n = (jac.T @ jac).toarray()
    d = np.sqrt(np.maximum(np.diag(n), 1e-300))
    ns = n / d[:, None] / d[None, :]
    ev = np.linalg.eigvalsh(ns)
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else math.inf
    try:
        cov = sla.cho_solve(sla.cho_factor(ns), np.eye(prob.n)) / d[:, None] / d[None, :]
        singular = False
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(ns) / d[:, None] / d[None, :]
        singular = True
    frozen = [
        (prob.bias_offset + q, bp.sigma)
        for q, bp in enumerate(prob.biases)
        if prob.bias_status[q].startswith('unobservable')
    ]
    if frozen:
        cov = _consider(cov, n, frozen)
    return r, jac, cov, cond, singular


def _consider(
    cov: FloatArray, normal: FloatArray, frozen: Sequence[tuple[int, float]]
) -> FloatArray:
    """Covariance with the frozen biases as *consider* parameters.

    A frozen bias is held at its prior, but its prior uncertainty still moves everything
    fitted with it: with ``S = -N_xx^-1 N_xc`` the sensitivity of the estimated
    parameters to the frozen ones, ``P_x += S P_c S^T`` (and ``P_xc = S P_c``). Without
    this the other estimates would claim an accuracy the frozen errors deny them.
    ``cov`` (from the normal matrix with the frozen biases pinned) is ``N_xx^-1`` on the
    estimated block.
    """
    c = np.array([k for k, _ in frozen])
    pc = np.array([sig for _, sig in frozen]) ** 2
    x = np.setdiff1d(np.arange(cov.shape[0]), c)
    sens = -cov[np.ix_(x, x)] @ normal[np.ix_(x, c)]  # (n_x, n_c)
    out = cov.copy()
    out[np.ix_(x, x)] += (sens * pc) @ sens.T
    out[np.ix_(x, c)] = sens * pc
    out[np.ix_(c, x)] = (sens * pc).T
    out[np.ix_(c, c)] = np.diag(pc)
    return out


def _knot_scores(
    ax: SplineAxis,
    ts: FloatArray,
    up: FloatArray,
    uv: FloatArray,
    ridx: NDArray[np.intp],
    r: FloatArray,
    jac: sp.csr_matrix,
    cov: FloatArray,
    min_len: float,
) -> list[tuple[float, float]]:
    """Score statistic of a knot at the midpoint of every interval of ``ax``.

    ``ts`` are the (sorted) times of the residual rows ``ridx`` the axis acts on, and
    ``up``/``uv`` the whitened derivatives of those rows by the axis' value and rate.
    """
    from scipy.interpolate import BSpline

    out = []
    brk = np.unique(ax.knots)
    p = ax.degree
    for lo, hi in zip(brk[:-1], brk[1:], strict=True):
        if hi - lo < min_len:
            continue
        tau = 0.5 * (lo + hi)
        idx = int(np.searchsorted(ax.knots, tau))
        refined = np.insert(ax.knots, idx, tau)
        s0 = min(max(idx - 2, 0), refined.size - p - 2)
        local = refined[s0 : s0 + p + 2]
        i0, i1 = np.searchsorted(ts, [local[0], local[-1]])
        if i1 - i0 < 2:
            continue
        b = BSpline.basis_element(local, extrapolate=False)
        tt = ts[i0:i1]
        col = np.nan_to_num(b(tt)) * up[i0:i1] + np.nan_to_num(b.derivative()(tt)) * uv[i0:i1]
        rows = ridx[i0:i1]
        g = float(col @ r[rows])
        c = jac[rows].T @ col
        den = float(col @ col - c @ (cov @ c))
        if den <= 1e-12 * float(col @ col):
            continue
        out.append((tau, g * g / den))
    return out


def _with_knots(ax: SplineAxis, new: Sequence[float]) -> SplineAxis:
    return SplineAxis.from_interior(
        np.sort(np.concatenate([ax.interior, np.asarray(new, dtype=float)])),
        ax.t0,
        ax.t1,
        ax.degree,
    )


def _refine_knots(
    prob: _Problem,
    r: FloatArray,
    jac: sp.csr_matrix,
    cov: FloatArray,
    cfg: EstimatorConfig,
) -> tuple[dict[int, list[SplineAxis]], dict[int, SplineAxis]]:
    """Knots the measurements ask for (beyond the paper).

    For every knot interval of every axis, a score (Lagrange-multiplier) test of adding
    a knot at its midpoint: with ``j`` the Jacobian column of the new basis function,
    ``s = (j^T r)^2 / (j^T j - (J^T j)^T (J^T J)^-1 (J^T j))`` is chi-square(1) when the
    spline already represents the trajectory. Midpoints with ``s`` above the Bonferroni
    quantile at ``refine_alpha`` are inserted. This catches what the rough trajectory
    could not show (its noise hides model errors the measurements resolve). The same
    test runs on the telemetry error spline (each component), so a drift that bends
    faster than its initial knots gets knots too instead of an optimistic covariance.

    Returns the refined trajectory axes and telemetry error axes, per target (only those
    that changed).
    """
    from scipy.stats import chi2

    tgt = np.concatenate([np.full(row[1].size, row[0]) for row in prob.rows])
    tim = np.concatenate([row[1] for row in prob.rows])
    hp = np.concatenate([row[2] for row in prob.rows])
    hv = np.concatenate([row[3] for row in prob.rows])
    is_tel = np.concatenate([np.full(row[1].size, row[4]) for row in prob.rows])
    min_len = 2.0 * cfg.knots.min_spacing
    traj_c: list[tuple[int, int, float, float]] = []  # (target, axis, tau, score)
    tel_c: list[tuple[int, int, float, float]] = []  # (target, component, tau, score)
    for tid, traj in prob.trajs.items():
        sel = np.flatnonzero(tgt == tid)
        order = sel[np.argsort(tim[sel], kind='stable')]
        ts = tim[order]
        for a, ax in enumerate(traj.axes):
            up = hp[order] @ traj.rotation[:, a]
            uv = hv[order] @ traj.rotation[:, a]
            for tau, sc in _knot_scores(ax, ts, up, uv, order, r, jac, cov, min_len):
                traj_c.append((tid, a, tau, sc))
        tb = next((t for t in prob.telemetry if t.target == tid), None)
        if tb is None:
            continue
        tsel = order[is_tel[order]]
        for c in range(3):
            scores = _knot_scores(
                tb.axis, tim[tsel], hp[tsel, c], hv[tsel, c], tsel, r, jac, cov, min_len
            )
            tel_c.extend((tid, c, tau, sc) for tau, sc in scores)
    n_cand = len(traj_c) + len(tel_c)
    if n_cand == 0:
        return {}, {}
    limit = float(chi2.isf(cfg.refine_alpha / n_cand, 1))
    out: dict[int, list[SplineAxis]] = {}
    for tid, traj in prob.trajs.items():
        axes = list(traj.axes)
        changed = False
        for a in range(3):
            new = [tau for k, ax_, tau, sc in traj_c if k == tid and ax_ == a and sc > limit]
            if new:
                axes[a] = _with_knots(axes[a], new)
                changed = True
        if changed:
            out[tid] = axes
    tel_out: dict[int, SplineAxis] = {}
    for tb in prob.telemetry:
        new = sorted({tau for k, _c, tau, sc in tel_c if k == tb.target and sc > limit})
        if new:
            tel_out[tb.target] = _with_knots(tb.axis, new)
    return out, tel_out


def _rebuild(
    prob: _Problem,
    beta: FloatArray,
    new_axes: Mapping[int, list[SplineAxis]],
    new_tel: Mapping[int, SplineAxis],
    obs: Observations,
    cfg: EstimatorConfig,
    t0: float,
    t1: float,
) -> tuple[_Problem, FloatArray]:
    """The problem on refined knots, started from the current solution (refined knots
    contain the old ones, so the current spline is represented exactly)."""
    sols: dict[int, tuple[SplineTrajectory, FloatArray]] = {}
    for tid, traj in prob.trajs.items():
        coef = prob._coef(beta, tid)
        if tid in new_axes:
            nt = traj.with_axes(new_axes[tid])
            brk = np.unique(np.concatenate([a.knots for a in nt.axes]))
            ts = np.unique(
                np.concatenate(
                    [np.linspace(x0, x1, 8) for x0, x1 in zip(brk[:-1], brk[1:], strict=True)]
                )
            )
            x = traj.states(coef, ts)
            coef = nt.fit_states(ts, x[:, :3], x[:, 3:], 1.0, 1.0)
            traj = nt
        sols[tid] = (traj, coef)
    tel_axes = {tb.target: new_tel.get(tb.target, tb.axis) for tb in prob.telemetry}
    new = _Problem(obs, sols, cfg, t0, t1, tel_axes)
    new.gated = prob.gated
    new.gate_refused = prob.gate_refused
    beta_new = np.zeros(new.n)
    for tid, (traj, coef) in sols.items():
        o = new.offsets[tid]
        beta_new[o : o + traj.n_coef] = coef
    nb = len(prob.biases)
    beta_new[new.bias_offset : new.bias_offset + nb] = beta[
        prob.bias_offset : prob.bias_offset + nb
    ]
    new.bias_sigma, new.bias_status = prob.bias_sigma, prob.bias_status
    for tb_new, tb_old in zip(new.telemetry, prob.telemetry, strict=True):
        tb_new.noise = list(tb_old.noise)
        old_e = beta[tb_old.offset : tb_old.offset + 3 * tb_old.axis.n_coef].reshape(-1, 3)
        if tb_new.axis is tb_old.axis:
            new_e = old_e
        else:  # refined knots contain the old ones: refit the same error curves
            brk = np.unique(tb_new.axis.knots)
            ts = np.unique(
                np.concatenate(
                    [np.linspace(a, b, 6) for a, b in zip(brk[:-1], brk[1:], strict=True)]
                )
            )
            vals = tb_old.axis.evaluate(old_e, ts)
            new_e = np.stack(
                [tb_new.axis.fit(ts, vals[:, c], ridge=0.0) for c in range(3)], axis=1
            )
        beta_new[tb_new.offset : tb_new.offset + new_e.size] = new_e.ravel()
    return new, beta_new


def _freeze_unobservable(
    prob: _Problem, beta: FloatArray, cov: FloatArray, cfg: EstimatorConfig, when: str
) -> bool:
    """Freeze at their priors the biases the data do not separate from the rest.

    A bias is observable when the measurements shrink its uncertainty well below its
    prior: posterior sigma at most ``bias_observability`` times the prior sigma. Those
    that fail are reset to the prior, get a vanishing prior sigma (so they no longer
    move) and are reported with the reason, including their strongest correlation.
    Returns True if any bias was frozen.
    """
    frozen = False
    o = prob.bias_offset
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    for q, bp in enumerate(prob.biases):
        if prob.bias_status[q] != 'estimated':
            continue
        ratio = sd[o + q] / bp.sigma
        if ratio <= cfg.bias_observability:
            continue
        corr = cov[o + q] / (sd[o + q] * sd)
        corr[o + q] = 0.0
        k = int(np.argmax(np.abs(corr)))
        what = _parameter_name(prob, k)
        prob.bias_status[q] = (
            f'unobservable ({when}): the data leave {ratio:.0%} of its prior sigma '
            f'(strongest correlation {corr[k]:+.3f} with {what}); held at its prior'
        )
        prob.bias_sigma[q] = bp.sigma * 1e-9
        beta[o + q] = bp.prior
        frozen = True
    return frozen


def _parameter_name(prob: _Problem, k: int) -> str:
    if k >= prob.bias_offset:
        bp = prob.biases[k - prob.bias_offset]
        return f'bias {bp.station}/{bp.name}'
    for tb in prob.telemetry:
        if tb.offset <= k < tb.offset + 3 * tb.axis.n_coef:
            return f'telemetry error of target {tb.target}'
    for tid, off in prob.offsets.items():
        if off <= k < off + prob.trajs[tid].n_coef:
            return f'trajectory of target {tid}'
    return f'parameter {k}'


def _bias_estimates(prob: _Problem, beta: FloatArray, cov: FloatArray) -> tuple[BiasEstimate, ...]:
    o = prob.bias_offset
    out = []
    for q, bp in enumerate(prob.biases):
        status = prob.bias_status[q]
        estimated = status == 'estimated'
        value = float(beta[o + q])
        for side, limit in (('lower', bp.bounds[0]), ('upper', bp.bounds[1])):
            if estimated and math.isfinite(limit) and abs(value - limit) <= 1e-9 * bp.sigma:
                status = (
                    f'estimated, at its {side} bound {limit:g}: the data push beyond it, '
                    'so the sigma is conditional on the bound'
                )
        out.append(
            BiasEstimate(
                bp.station,
                bp.name,
                value,
                float(np.sqrt(max(cov[o + q, o + q], 0.0))) if estimated else float(bp.sigma),
                bp.prior,
                bp.sigma,
                status,
            )
        )
    return tuple(out)


def _choose_knots_safely(
    rough: RoughTrajectory,
    t0: float,
    t1: float,
    segments: Sequence[Segment],
    cfg: EstimatorConfig,
    method: str,
    frame: tuple[FloatArray, FloatArray] | None,
    baseline_spacing: float = 3.0,
    events: Sequence[float] | None = None,
) -> KnotSelection:
    """:func:`choose_knots`, but a failed l1 problem never loses the window: the other
    installed interior-point solver is tried, then the densified knots are kept (the
    reason is recorded in the selection's ``info``)."""
    try:
        return choose_knots(
            rough, t0, t1, segments, cfg.knots, method, frame, baseline_spacing, events
        )
    except KnotSelectionError as first:
        reason = str(first)
    if cfg.knots.solver.upper() != 'CLARABEL':
        try:
            alt = replace(cfg.knots, solver='CLARABEL')
            sel = choose_knots(
                rough, t0, t1, segments, alt, method, frame, baseline_spacing, events
            )
            return replace(sel, info={**sel.info, 'fallback': f'CLARABEL after: {reason}'})
        except KnotSelectionError as second:
            reason += f'; CLARABEL: {second}'
    sel = choose_knots(rough, t0, t1, segments, cfg.knots, 'dense', frame, events=events)
    return replace(sel, info={'fallback': f'densified knots kept: {reason}'})


# ---------------------------------------------------------------------------------------
# the window


def _polynomial_selection(
    rough: RoughTrajectory, t0: float, t1: float, degree: int
) -> KnotSelection:
    from orbit_tracking.core.estimation.knots import _fit_rough, spline_frame

    start = _time.perf_counter()
    frame = spline_frame(rough)
    ax = SplineAxis.from_interior([], t0, t1, degree)
    traj = SplineTrajectory((ax, ax, ax), frame[0], frame[1])
    coef = _fit_rough(traj, rough, 0.5)
    return KnotSelection(
        traj, coef, (), (0, 0, 0), (0, 0, 0), 0, 0.0, _time.perf_counter() - start, 'polynomial'
    )


def _rough_from_previous(prev: TargetSolution, t0: float, t1: float) -> RoughTrajectory | None:
    a, b = max(t0, prev.t0), min(t1, prev.t1)
    if b - a < 1.0:
        return None
    t = np.linspace(a, b, max(10, int((b - a) * 10) + 1))
    x = prev.trajectory.states(prev.coef, t)
    return RoughTrajectory('previous window', t, x[:, :3], x[:, 3:], 0.1, 0.01)


def estimate(
    obs: Observations,
    t0: float,
    t1: float,
    cfg: EstimatorConfig | None = None,
    target_ids: Sequence[int] | None = None,
    previous: Mapping[int, TargetSolution] | None = None,
    frame: tuple[FloatArray, FloatArray] | None = None,
) -> Estimate:
    """Estimate the trajectories of ``target_ids`` over [t0, t1] from ``obs``.

    Parameters
    ----------
    obs : Observations
        Measurements (rows outside [t0, t1] are ignored).
    t0, t1 : float
        Window span [s].
    cfg : EstimatorConfig
    target_ids : sequence of int, optional
        Default: every target with measurements.
    previous : mapping of target id to TargetSolution, optional
        The previous window's solution: the initial guess where it overlaps, and the
        rough trajectory when no telemetry or fixes exist.
    frame : (origin, rotation), optional
        Spline frame (e.g. the launch frame); default a launch-like frame at the first
        rough point.

    Raises
    ------
    EstimationError
        No measurements, or no rough trajectory to start from.
    """
    cfg = cfg or EstimatorConfig()
    if not t1 > t0:
        raise EstimationError(f'window must have t1 > t0; got [{t0}, {t1}]')
    obs = obs.window(t0, t1)
    ids = list(target_ids) if target_ids is not None else obs.target_ids
    if not ids:
        raise EstimationError(f'no measurements in window [{t0:.3f}, {t1:.3f}]')
    k_start = _time.perf_counter()
    selections: dict[int, KnotSelection] = {}
    segments: dict[int, tuple[Segment, ...]] = {}
    for tid in ids:
        rough = rough_trajectory(obs, tid, t0, t1)
        if rough is None and previous and tid in previous:
            rough = _rough_from_previous(previous[tid], t0, t1)
        if rough is None:
            raise EstimationError(
                f'target {tid}: no telemetry, fixes or previous solution in '
                f'[{t0:.3f}, {t1:.3f}] to start from'
            )
        segs = list(cfg.segments)
        if cfg.detect_segments:
            segs += find_incomplete_segments(obs, tid, rough.state, t0, t1, cfg.coverage)
        segs = merge_segments([(max(a, t0), min(b, t1)) for a, b in segs])
        segments[tid] = tuple(segs)
        if cfg.knot_method == 'polynomial':
            sel = _polynomial_selection(rough, t0, t1, cfg.polynomial_degree)
        else:
            sel = _choose_knots_safely(
                rough, t0, t1, segs, cfg, cfg.knot_method, frame, cfg.baseline_spacing
            )
        if previous and tid in previous:
            sel = _seed_from_previous(sel, previous[tid], rough)
        sel = replace(sel, rough_source=rough.source)
        selections[tid] = sel
    knot_time = _time.perf_counter() - k_start
    s_start = _time.perf_counter()
    prob = _Problem(obs, {t: (s.trajectory, s.coef) for t, s in selections.items()}, cfg, t0, t1)
    beta = np.zeros(prob.n)
    for tid, s in selections.items():
        o = prob.offsets[tid]
        beta[o : o + s.trajectory.n_coef] = s.coef
    beta[prob.bias_offset : prob.bias_offset + len(prob.biases)] = prob.bias_prior
    if 'estimated' in prob.bias_status:
        # observability before solving: the augmented normal matrix at the initial guess
        _, _, cov0, _, _ = _covariance(prob, beta)
        _freeze_unobservable(prob, beta, cov0, cfg, 'before the solve')
    start = beta.copy()
    out, iterations, halvings = _solve(prob, beta, cfg)
    r, jac, cov, cond, singular = _covariance(prob, out.beta)
    if _freeze_unobservable(prob, out.beta, cov, cfg, 'at the solution'):
        # solve again from the start: the frozen biases must not leave their pull in the
        # trajectory through a flat valley of the cost
        prob.gated.clear()
        out, it2, h2 = _solve(prob, start, cfg)
        iterations += it2
        halvings += h2
        r, jac, cov, cond, singular = _covariance(prob, out.beta)
    noisy = [t for t, s in selections.items() if s.rough_source == 'fixes']
    if noisy and cfg.knot_method == 'sparse':
        # fixes are a poor rough trajectory (no velocity, metres of noise): select the
        # knots again on the first solution, which the raw measurements made precise
        for tid in noisy:
            sol = prob.trajs[tid]
            coef = prob._coef(out.beta, tid)
            o = prob.offsets[tid]
            tt = np.linspace(t0, t1, max(50, int((t1 - t0) * 10) + 1))
            x = sol.states(coef, tt)
            pc = state_covariance(sol, cov[o : o + sol.n_coef, o : o + sol.n_coef], tt)
            sp_ = float(np.sqrt(np.median(np.trace(pc[:, :3, :3], axis1=1, axis2=2)) / 3))
            sv_ = float(np.sqrt(np.median(np.trace(pc[:, 3:, 3:], axis1=1, axis2=2)) / 3))
            if not (np.isfinite(sp_) and np.isfinite(sv_) and sp_ > 0.0 and sv_ > 0.0):
                continue  # a degenerate first solution: keep the knots from the fixes
            rough2 = RoughTrajectory(
                'first solution', tt, x[:, :3], x[:, 3:], sp_, sv_, covariance=pc
            )
            sel2 = _choose_knots_safely(
                rough2,
                t0,
                t1,
                segments[tid],
                cfg,
                'sparse',
                (sol.origin, sol.rotation),
                events=selections[tid].events,
            )
            selections[tid] = replace(sel2, rough_source='fixes, then first solution')
        first, first_beta = prob, out.beta
        prob = _Problem(
            obs, {t: (s.trajectory, s.coef) for t, s in selections.items()}, cfg, t0, t1
        )
        beta = np.zeros(prob.n)
        for tid, s in selections.items():
            o = prob.offsets[tid]
            beta[o : o + s.trajectory.n_coef] = s.coef
        nb = len(prob.biases)
        beta[prob.bias_offset : prob.bias_offset + nb] = first_beta[
            first.bias_offset : first.bias_offset + nb
        ]
        prob.bias_sigma, prob.bias_status = first.bias_sigma, first.bias_status
        out, it2, h2 = _solve(prob, beta, cfg)
        iterations += it2
        halvings += h2
        r, jac, cov, cond, singular = _covariance(prob, out.beta)
    added = {tid: 0 for tid in selections}
    refine_note = ''
    for _ in range(cfg.refine_rounds):
        fit = float(r @ r) / max(r.size - prob.n, 1)
        if fit > REFINE_MAX_CHI2:
            # the score test assumes the model fits up to its knots; data this far off
            # (unmodelled systematic errors) would ask for knots everywhere
            refine_note = (
                f'; knot test skipped: chi2/dof {fit:.1f} > {REFINE_MAX_CHI2:g}, the model '
                'does not fit the data'
            )
            break
        new_axes, new_tel = _refine_knots(prob, r, jac, cov, cfg)
        if not new_axes and not new_tel:
            break
        prob, beta = _rebuild(prob, out.beta, new_axes, new_tel, obs, cfg, t0, t1)
        for tid, axes in new_axes.items():
            added[tid] += sum(a.interior.size for a in axes) - sum(
                a.interior.size for a in selections[tid].trajectory.axes
            )
            selections[tid] = replace(selections[tid], trajectory=prob.trajs[tid])
        out, it2, h2 = _solve(prob, beta, cfg)
        iterations += it2
        halvings += h2
        r, jac, cov, cond, singular = _covariance(prob, out.beta)
    for tid, n_added in added.items():
        selections[tid] = replace(selections[tid], refined=n_added)
    solve_time = _time.perf_counter() - s_start
    used: Counter[str] = Counter()
    rejected: Counter[tuple[str, str]] = Counter()
    residuals: dict[str, tuple[FloatArray, tuple[str, ...], FloatArray]] = {}
    for bi, b in enumerate(prob.stations):
        g = prob.gated.get(bi, np.zeros_like(b.valid))
        used[b.station] += int((b.valid & ~g).sum())
        if g.any():
            rejected[(b.station, 'residual_gate')] += int(g.sum())
        nan = int((~b.valid).sum())
        if nan:
            rejected[(b.station, 'not_measured')] += nan
        pred, _, _ = prob.predict_block(bi, out.beta)
        rr = residual(b.fields, b.values, pred) / b.sigmas
        rr[g] = np.nan
        residuals[b.station if b.target == ids[0] else f'{b.station}/{b.target}'] = (
            b.time,
            b.fields,
            rr,
        )
    for tb in prob.telemetry:
        used[f'telemetry_{tb.target}'] += int(tb.valid_p.sum() + tb.valid_v.sum())
    dof = max(r.size - prob.n, 1)
    targets = {}
    for tid, s in selections.items():
        o = prob.offsets[tid]
        nt = s.trajectory.n_coef
        tel = next((tb for tb in prob.telemetry if tb.target == tid), None)
        targets[tid] = TargetSolution(
            tid,
            s.trajectory,
            out.beta[o : o + nt].copy(),
            cov[o : o + nt, o : o + nt].copy(),
            s,
            segments[tid],
            None
            if tel is None
            else (tel.axis, out.beta[tel.offset : tel.offset + 3 * tel.axis.n_coef].copy()),
            None if tel is None else (tel.noise[0], tel.noise[1]),
        )
    msg = (
        out.message
        + refine_note
        + ('; normal matrix singular (pseudo-inverse covariance)' if singular else '')
    )
    if prob.gate_refused:
        msg += (
            f'; the residual gate would reject {prob.gate_refused:.0%} of the rows, so the '
            'model does not fit the data (unmodelled systematic errors?): nothing gated'
        )
    return Estimate(
        success=out.converged and not singular and not prob.gate_refused,
        message=msg,
        t0=t0,
        t1=t1,
        targets=targets,
        iterations=iterations,
        halvings=halvings,
        cost=out.cost,
        chi2_dof=out.cost / dof,
        condition=cond,
        n_parameters=prob.n,
        used=used,
        rejected=rejected,
        residuals=residuals,
        knot_time=knot_time,
        solve_time=solve_time,
        covariance=cov,
        biases=_bias_estimates(prob, out.beta, cov),
    )


def _seed_from_previous(
    sel: KnotSelection, prev: TargetSolution, rough: RoughTrajectory
) -> KnotSelection:
    """Initial coefficients: the previous window's trajectory where it overlaps, the
    rough trajectory beyond."""

    traj = sel.trajectory
    a, b = max(traj.t0, prev.t0), min(traj.t1, prev.t1)
    if b - a < 1.0:
        return sel
    t_prev = np.linspace(a, b, max(10, int((b - a) * 10) + 1))
    xp = prev.trajectory.states(prev.coef, t_prev)
    keep = rough.time > b
    t = np.concatenate([t_prev, rough.time[keep]])
    state = rough.state(rough.time[keep])
    pos = np.vstack([xp[:, :3], state[:, :3]])
    vel = np.vstack([xp[:, 3:], state[:, 3:]])
    try:
        coef = traj.fit_states(t, pos, vel, 1.0, 100.0)
    except np.linalg.LinAlgError:
        return sel
    return replace(sel, coef=coef)
