"""What a window solve returns: per-target spline solutions with their coefficient
covariance (:class:`TargetSolution`, states and covariance at any time), the estimated
biases (:class:`BiasEstimate`) and the whole window (:class:`Estimate`)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimationError, Segment
from orbit_tracking.core.estimation.event_times import EventTimeTerms
from orbit_tracking.core.estimation.gap_manoeuvres import GapManoeuvres
from orbit_tracking.core.estimation.knots import KnotSelection
from orbit_tracking.core.estimation.linearity import isotropic

__all__ = ['BiasEstimate', 'Estimate', 'TargetSolution', 'state_covariance']

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TargetSolution:
    """The fitted trajectory of one target.

    ``covariance`` is the marginal covariance of ``coef`` (all other parameters
    estimated too); use :meth:`states` for position/velocity and their covariance.

    ``telemetry_velocity`` is the telemetry velocity error model the window used
    (``derivative`` or ``separate``; empty without telemetry fused). ``isotropic_spans``
    are where that covariance is no statement about the error (the
    measurements are not linear over one sigma there:
    :func:`~orbit_tracking.core.estimation.linearity.nonlinear_spans`); :meth:`states`
    gives the largest sigma in every direction there. ``telemetry_error_sigma`` is the
    pair of prior sigmas [m] the telemetry error spline ended with, its level and its steps
    from one coefficient to the next (the declared position sigma, or estimated from the
    data; None without telemetry fused).
    ``jerk_density`` is the white-jerk prior's density [m^2/s^5] estimated for this
    trajectory away from its events, ``jerk_density_near_events`` the one within
    :data:`~orbit_tracking.core.estimation.motion_rows.JERK_EVENT_MARGIN` of them (None
    without the prior, or without events). ``telemetry_delays`` are the telemetry's
    estimated time-tag delays of position and velocity and their sigmas, ``(d_p, sigma,
    d_v, sigma)`` [s] (None when the window did not estimate them). ``manoeuvres`` is the
    consider term of the manoeuvres its incomplete segments may hide, which :meth:`states`
    adds to the covariance (None when off or without segments).
    ``telemetry_size_evidence`` is the telemetry's declared position sigma and the log
    evidence of the error sizes on the grid of
    :func:`~orbit_tracking.core.estimation.telemetry_evidence.evidence_grid`, this
    window's and its predecessors' (what the next window starts from; None without
    telemetry fused or without the sizes estimated). ``event_times`` is the consider term
    of the uncertainty of its events' times, which :meth:`states` adds too
    (:mod:`~orbit_tracking.core.estimation.event_times`; None when off or without events).
    """

    target_id: int
    trajectory: SplineTrajectory
    coef: FloatArray
    covariance: FloatArray
    knots: KnotSelection
    segments: tuple[Segment, ...]
    telemetry_error: tuple[SplineAxis, FloatArray] | None = None
    telemetry_noise: tuple[float, float] | None = None
    isotropic_spans: tuple[Segment, ...] = ()
    telemetry_velocity: str = ''
    telemetry_error_sigma: tuple[float, float] | None = None
    jerk_density: float | None = None
    telemetry_delays: tuple[float, float, float, float] | None = None
    manoeuvres: GapManoeuvres | None = None
    telemetry_size_evidence: tuple[float, FloatArray] | None = None
    jerk_density_near_events: float | None = None
    event_times: EventTimeTerms | None = None

    @property
    def t0(self) -> float:
        return self.trajectory.t0

    @property
    def t1(self) -> float:
        return self.trajectory.t1

    def states(self, t: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray]:
        """World-frame (position, velocity) (m, 6) and their covariance (m, 6, 6)."""
        tt = np.asarray(t, dtype=np.float64)
        x = self.trajectory.states(self.coef, tt)
        design = world_designs(self.trajectory, tt)
        cov = state_covariance(self.trajectory, self.covariance, tt, design)
        if self.manoeuvres is not None:
            cov = cov + self.manoeuvres.state_covariance(self.trajectory, tt, design)
        if self.event_times is not None:
            cov = cov + self.event_times.state_covariance(tt)
        if not self.isotropic_spans:
            return x, cov
        inside = np.zeros(tt.shape[0], dtype=bool)
        for a, b in self.isotropic_spans:
            inside |= (tt >= a) & (tt <= b)
        return x, isotropic(cov, inside)

    def parameters_in(self, a: float, b: float) -> int:
        """Coefficients whose support overlaps (a, b) (the seed's 'parameters in the gap')."""
        n = 0
        for ax in self.trajectory.axes:
            k, p = ax.knots, ax.degree
            lo, hi = k[: ax.n_coef], k[p + 1 : p + 1 + ax.n_coef]
            n += int(np.sum((hi > a) & (lo < b)))
        return n


Designs = tuple[sp.csr_matrix, sp.csr_matrix]
"""World-frame design matrices of position and velocity at some times (3m, n_coef) each."""


def world_designs(traj: SplineTrajectory, t: FloatArray) -> Designs:
    """The position and velocity design matrices of ``traj`` at ``t`` (built once for the
    formal covariance and the manoeuvre term)."""
    return traj.world_design(t, 0), traj.world_design(t, 1)


def state_covariance(
    traj: SplineTrajectory, cov: FloatArray, t: FloatArray, design: Designs | None = None
) -> FloatArray:
    """Covariance (m, 6, 6) of world position and velocity from the coefficient
    covariance ``cov`` (n_coef, n_coef); ``design``: :func:`world_designs` at ``t``, if
    already built."""
    m = t.shape[0]
    g = sp.vstack(design if design is not None else world_designs(traj, t)).tocsr()
    gp = np.asarray(g @ cov)  # (6m, n)
    gd = g.toarray() if g.shape[0] * g.shape[1] < 5e7 else None
    if gd is None:
        raise EstimationError('too many output times for one covariance evaluation')
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
    covariance : ndarray
        Covariance of every parameter (scaled by ``covariance_scale``).
    biases : tuple of BiasEstimate
    covariance_scale : float
        Factor the formal covariance was scaled by (the chi-square per degree of freedom
        when it exceeds 1 significantly; :mod:`~orbit_tracking.core.estimation.verdict`).
    noise_factors : mapping of (station id, field) to float
        Fields used with sigmas larger than declared, and the factor (white residuals
        larger than declared).
    attempts : int
        Solves the window took (more than 1 when the first was not a success and safer
        settings were tried).
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
    covariance_scale: float = 1.0
    noise_factors: Mapping[tuple[str, str], float] = field(default_factory=dict)
    attempts: int = 1
