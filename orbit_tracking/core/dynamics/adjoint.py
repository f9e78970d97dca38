"""Seed 003's adjoint (4D-Var) assimilation: the state at an epoch and an unknown thrust
acceleration ``F(t)`` fitted to the raw station measurements, by a quasi-Newton descent
on the gradient that the adjoint (costate) equations give.

The seed (eqs. 5-26 to 5-35) writes the vehicle as ``r'' = -GM r / |r|^3 + F(t)`` with
``F`` a free function of time, the cost as ``J = kappa/2 int |r - r_obs|^2 dt`` against
triangulated positions, and adjoins the dynamics with Lagrange multipliers: setting the
variation of the Lagrangian to zero with respect to the state gives the adjoint
equations, second order in the multipliers and driven by the misfit ``kappa (r -
r_obs)``, integrated backward in time; the variation with respect to ``F`` says the
gradient of ``J`` with respect to ``F(t)`` is the multiplier itself, and ``F`` is
corrected along it (eq. 5-33) until the cost stops decreasing. Here, in first-order form
with ``y = (r, v)`` and ``y' = f(y, t)`` (:mod:`.thrust_spline`):

* the control is a cubic B-spline ``F(t; c)``, a magnitude along the velocity or three
  free components; the unknowns ``p`` are each target's ``(r0, v0)`` at its epoch ``t0``,
  its coefficients ``c`` and the declared biases ``b``;
* the cost is that of the raw measurements, as :mod:`.fit` has it::

      J(p) = 1/2 sum_i |e_i|^2 + 1/2 sum_b ((b - b_prior) / sigma_b)^2
             [+ 1/2 sum_j |c_(j+1) - 2 c_j + c_(j-1)|^2 / sigma_s^2]

  with ``e_i = (z_i - B(h(y(t_i)); b)) / sigma_i`` the whitened residual of every value
  measured at ``t_i`` (``h`` the measurement model, ``B`` the bias model) and the last
  sum an optional weak smoothness prior on the second differences of the coefficients
  (``smoothness_sigma`` [m/s^2]; off by default);
* the costate ``lambda = (lambda_r, lambda_v)`` obeys, backward from the last epoch
  (``lambda = 0`` after it) to ``t0``::

      lambda' = -A(t)^T lambda,     A = df/dy = [[0, I], [dg/dr, dF/dv]],
      lambda(t_i-) = lambda(t_i+) + (de_i/dy)^T e_i     at every measurement epoch,

  the misfit entering as jumps at the epochs where the seed's integral cost has a
  continuous forcing;
* the gradient is ``dJ/d(r0, v0) = lambda(t0)`` and ``dJ/dc = int_t0^t1 G^T lambda_v dt``
  with ``G = dF/dc`` (the seed's ``dJ/dF(t) = lambda_v(t)`` projected on the basis); the
  bias and prior terms are differentiated directly.

The descent is L-BFGS-B on that gradient, in variables whitened by the Gauss-Newton
Hessian at the start (``p = p_s + D^-1 L^-T z`` with ``D^-1 N D^-1 = L L^T``, the
control-variable transform of operational 4D-Var): without it the parameters' scales
differ by ten decades and the descent crawls. Each run is short (``run_iterations``) and
kept in a box a few Gauss-Newton steps wide (``trust_factor``); at its end the
Gauss-Newton decrement ``g^T N^-1 g`` is taken at the new point, and above
``convergence_decrement`` the descent restarts from there with a new transform. The
solve **converged** when that decrement passes (the test of :mod:`.fit`). The Hessian
``N = J^T J`` comes from the forward sensitivities (variational equations,
:meth:`.ThrustSplineModel.propagate`); its inverse is the covariance. Residual gate,
chi-square and verdict are those of :func:`~.fit.fit_dynamics`, and the result has the
same fields as its :class:`~.fit.DynamicsFit`, so that callers treat both fits alike.
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import solve_triangular
from scipy.optimize import minimize

from orbit_tracking.core import frames
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.dynamics.adjoint_problem import AdjointProblem
from orbit_tracking.core.dynamics.fit import (
    DynamicsFit,
    TargetFlight,
    covariance_verdict,
    fit_tables,
    gate_pass,
)
from orbit_tracking.core.dynamics.rocket import FlightError
from orbit_tracking.core.dynamics.thrust_spline import ThrustControl, ThrustSplineModel
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.models.systematic import BiasParameter

__all__ = [
    'AdjointConfig',
    'adjoint_bound',
    'AdjointFit',
    'AdjointFlight',
    'AdjointProblem',
    'COVER_LIMIT_S',
    'ThrustStart',
    'fit_adjoint',
    'initial_from_rocket',
]

FloatArray = NDArray[np.float64]

COVER_LIMIT_S = 10.0
"""Longest extension of a fitted flight beyond its first or last measurement [s] for
reported states (both models): farther out is prediction, not estimation."""

ThrustStart = float | Callable[[FloatArray], ArrayLike] | ArrayLike
"""A starting thrust: a constant magnitude along the velocity [m/s^2], a function of time
(m,) -> magnitudes (m,) or vectors (m, 3), or the coefficients themselves."""


@dataclass(frozen=True)
class AdjointConfig:
    """Settings of :func:`fit_adjoint`.

    Attributes
    ----------
    knot_spacing : float
        Largest spacing of the thrust spline's knots [s].
    direction : {'velocity', 'free'}
        Thrust along the velocity (a magnitude) or three free components.
    smoothness_sigma : float or None
        Sigma [m/s^2] of the weak prior on the coefficients' second differences.
    gm, j2 : float
        Gravity model; ``rotating`` adds the Earth's rotation (``earth`` world frame).
    max_iterations : int
        L-BFGS-B iterations in all (per descent: the biases-held one, each gate pass).
    run_iterations, max_restarts : int
        Iterations of one L-BFGS-B run, and runs after the first at most: each new run
        starts from the Gauss-Newton transform at its start (far from the optimum the
        problem is not quadratic, and a fresh transform gains more than a long run).
    gtol : float
        L-BFGS-B's gradient tolerance in the whitened variables.
    precondition : bool
        Whiten by the Gauss-Newton Hessian (False: by its diagonal only, for comparison).
    trust_factor : float
        Each run stays in a box of ``max(trust_factor max|g_z|, 1)`` about its start in the
        whitened variables ``z`` (``g_z`` the gradient there, ``-g_z`` the Gauss-Newton
        step): the line search cannot try parameters far beyond the quadratic model's reach,
        which the integrator would crawl through.
    convergence_decrement, max_unconverged_decrement, gate_sigma, gate_passes,
    max_gate_share, max_chi2_dof
        As :class:`~.fit.FitConfig`'s.
    """

    knot_spacing: float = 10.0
    direction: str = 'velocity'
    smoothness_sigma: float | None = None
    gm: float = frames.WGS84_GM
    j2: float = 0.0
    rotating: bool = False
    max_iterations: int = 300
    run_iterations: int = 10
    max_restarts: int = 30
    gtol: float = 1e-3
    precondition: bool = True
    trust_factor: float = 4.0
    convergence_decrement: float = 1e-4
    max_unconverged_decrement: float = 4.0
    gate_sigma: float = 5.0
    gate_passes: int = 4
    max_gate_share: float = 0.05
    max_chi2_dof: float = 1.5

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.gate_passes < 1 or self.max_restarts < 0:
            raise ValueError('max_iterations and gate_passes must be >= 1, max_restarts >= 0')
        if not self.trust_factor > 0.0:
            raise ValueError(f'trust_factor must be > 0; got {self.trust_factor}')
        if self.smoothness_sigma is not None and not self.smoothness_sigma > 0.0:
            raise ValueError(f'smoothness_sigma must be > 0; got {self.smoothness_sigma}')
        ThrustControl(0.0, 1.0, self.knot_spacing, self.direction)  # checks both

    def model(self, t0: float, t1: float, jumps: Sequence[float] = ()) -> ThrustSplineModel:
        control = ThrustControl(t0, t1, self.knot_spacing, self.direction, tuple(jumps))
        rate = 7.2921150e-5 if self.rotating else 0.0
        return ThrustSplineModel(control, self.gm, self.j2, frames.WGS84_A, rate)


@dataclass(frozen=True)
class AdjointFlight(TargetFlight):
    """The fitted flight of one target, a :class:`~.fit.TargetFlight` whose parameters
    are the state at ``model.epoch`` and the thrust coefficients (states with covariance
    anywhere in ``[t0, t1]``, first and last measurement)."""

    model: ThrustSplineModel

    def thrust(self, t: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray]:
        """Thrust acceleration magnitude [m/s^2] and its sigma at ``t``, shape (m,) each."""
        ctl = self.model.control
        b = ctl.basis(np.asarray(t, dtype=np.float64))
        cov = self.covariance[6:, 6:]
        if ctl.components == 1:
            mag = b @ self.theta[6:]
            var = np.einsum('mi,ij,mj->m', b, cov, b)
        else:
            vec = b @ self.theta[6:].reshape(-1, 3)
            mag = np.linalg.norm(vec, axis=1)
            u = vec / np.maximum(mag, 1e-300)[:, None]
            g = (b[:, :, None] * u[:, None, :]).reshape(b.shape[0], -1)  # d|F| / dC
            var = np.einsum('mi,ij,mj->m', g, cov, g)
        return mag, np.sqrt(np.maximum(var, 0.0))


@dataclass(frozen=True)
class AdjointFit(DynamicsFit):
    """Outcome of :func:`fit_adjoint`: a :class:`~.fit.DynamicsFit` (same meanings;
    ``cost`` is the sum of squares of the measurement and bias prior rows, without the
    smoothness prior), plus the cost-and-gradient ``evaluations`` and the optimizer's
    last ``optimizer_message``."""

    targets: Mapping[int, AdjointFlight]
    evaluations: int = 0
    optimizer_message: str = ''


def _descend(
    prob: AdjointProblem, p: FloatArray, cfg: AdjointConfig
) -> tuple[FloatArray, int, int, bool, float, FloatArray, FloatArray, str]:
    """Preconditioned L-BFGS-B runs from ``p`` until the Gauss-Newton decrement passes:
    (p, iterations, evaluations, converged, decrement, normal matrix, measurement-only
    normal matrix, optimizer message)."""
    its = evals = 0
    message = 'the start is the optimum'
    for restart in range(cfg.max_restarts + 1):
        vec, jac, n_data = prob.jacobian(p)
        n = jac.T @ jac
        g = jac.T @ vec
        d = np.sqrt(np.maximum(np.diag(n), 1e-300))
        ns = n / np.outer(d, d)
        try:
            chol = np.linalg.cholesky(ns)
        except np.linalg.LinAlgError:  # singular: a ridge keeps the transform defined
            chol = np.linalg.cholesky(ns + 1e-10 * np.eye(prob.n))
        gs = solve_triangular(chol, g / d, lower=True)
        decrement = float(gs @ gs)
        done = decrement <= cfg.convergence_decrement
        if done or restart == cfg.max_restarts or its >= cfg.max_iterations:
            info = jac[:n_data].T @ jac[:n_data]
            return p, its, evals, done, decrement, n, info, message
        if cfg.precondition:
            t_mat = solve_triangular(chol, np.eye(prob.n), lower=True).T / d[:, None]
        else:
            t_mat = np.diag(1.0 / d)
        base = p

        def fun(
            z: FloatArray, base: FloatArray = base, t_mat: FloatArray = t_mat
        ) -> tuple[float, FloatArray]:
            try:
                cost, grad = prob.gradient(base + t_mat @ z)
            except FlightError:
                return math.inf, np.zeros_like(z)
            return cost, t_mat.T @ grad

        # a trust region holding the Gauss-Newton step -g_z: no wild line-search trials
        radius = max(cfg.trust_factor * float(np.max(np.abs(t_mat.T @ g))), 1.0)
        res = minimize(
            fun,
            np.zeros(prob.n),
            jac=True,
            method='L-BFGS-B',
            bounds=[(-radius, radius)] * prob.n,
            options={
                'maxiter': min(cfg.run_iterations, cfg.max_iterations - its),
                'gtol': cfg.gtol,
                'ftol': 1e-15,
            },
        )
        its += int(res.nit)
        evals += int(res.nfev)
        message = str(res.message)
        p = base + t_mat @ res.x
    raise AssertionError('unreachable')  # pragma: no cover


def _start_coefficients(
    model: ThrustSplineModel, state: FloatArray, thrust: ThrustStart
) -> FloatArray:
    """Flat thrust coefficients of a :data:`ThrustStart` (least squares on 20 samples a
    knot interval). Vectors given to the velocity mode count by their magnitude; magnitudes
    given to the free mode point along the velocity of the flight they give in the
    velocity mode."""
    ctl = model.control
    if not callable(thrust) and np.ndim(thrust) > 0:
        return ctl.coefficients(thrust).ravel()
    grid = np.linspace(ctl.t0, ctl.t1, 20 * (ctl.breaks.size - 1) + 1)
    if callable(thrust):
        vals = np.asarray(thrust(grid), dtype=np.float64)
    else:
        vals = np.full(grid.size, float(thrust))  # type: ignore[arg-type]
    if vals.shape not in ((grid.size,), (grid.size, 3)):
        raise ValueError(f'a thrust function must give (m,) or (m, 3) values; got {vals.shape}')
    if ctl.components == 1:
        return ctl.fit(grid, vals if vals.ndim == 1 else np.linalg.norm(vals, axis=1))
    if vals.ndim == 1:
        along = replace(
            model, control=ThrustControl(ctl.t0, ctl.t1, ctl.knot_spacing, jumps=ctl.jumps)
        )
        theta = np.concatenate([state, along.control.fit(grid, vals)])
        v = along.forward(theta)(grid)[:, 3:6]
        vals = vals[:, None] * v / np.linalg.norm(v, axis=1)[:, None]
    return ctl.fit(grid, vals)


def initial_from_rocket(
    targets: Mapping[int, TargetFlight], start: float | None = None
) -> dict[int, tuple[float, FloatArray, ThrustStart]]:
    """Starts for :func:`fit_adjoint` from a rocket fit's flights: each target's state at
    the rocket epoch and the rocket-equation thrust ``c / (tau - (t - t0))``.

    ``start`` [s] moves the epoch earlier, to cover a report time before the first
    measurement (at most :data:`COVER_LIMIT_S` before it; the state there is the rocket
    flight's)."""
    out: dict[int, tuple[float, FloatArray, ThrustStart]] = {}
    for tid, tf in targets.items():

        def thrust(t: FloatArray, tf: TargetFlight = tf) -> FloatArray:
            return tf.model.thrust(tf.theta, t)

        epoch = float(tf.model.epoch)
        state = np.asarray(tf.theta[:6], dtype=np.float64)
        if start is not None and math.isfinite(start) and start < epoch:
            epoch = max(float(start), tf.t0 - COVER_LIMIT_S, epoch - COVER_LIMIT_S)
            state = tf.states([epoch])[0][0]
        out[tid] = (epoch, state, thrust)
    return out


def fit_adjoint(
    obs: Observations,
    initial: Mapping[int, tuple[float, ArrayLike, ThrustStart]],
    biases: Sequence[BiasParameter] = (),
    config: AdjointConfig | None = None,
    until: float | None = None,
    jumps: Mapping[int, Sequence[float]] | None = None,
) -> AdjointFit:
    """Fit each target's state and thrust control, and the biases, to the raw
    measurements by adjoint assimilation (seed 003; see the module docstring).

    Parameters
    ----------
    obs : Observations
        Station rows (their target ids pick the target); telemetry and fixes are not used.
    initial : mapping of target id to (epoch, state (6,), thrust)
        The epoch ``t0`` [s] of each target's state parameters (at or before its first
        measurement; the control spans ``t0`` to its last measurement), the starting
        position [m] and velocity [m/s] there, and the starting thrust
        (:data:`ThrustStart`). :func:`initial_from_rocket` gives them from a rocket fit.
    biases : sequence of BiasParameter
        Declared systematic errors (``estimate=False`` holds one at its prior).
    config : AdjointConfig, optional
    until : float, optional
        Extend each control to this time [s] when it is after the last measurement (at
        most :data:`COVER_LIMIT_S` after it), so that states and thrust can be reported
        there; the spline's last piece carries the thrust past the data, and the
        covariance says how little the data tell of it.
    jumps : mapping of target id to times, optional
        Where each target's thrust may jump (a staging the rocket fit found): the spline
        gets a discontinuity there (:class:`~.thrust_spline.ThrustControl`).

    Returns
    -------
    AdjointFit
    """
    cfg = config or AdjointConfig()
    t_start = _time.perf_counter()
    models, starts = {}, {}
    for tid, (epoch, state, thrust) in initial.items():
        x0 = np.asarray(state, dtype=np.float64).reshape(-1)
        if x0.shape != (6,) or not np.all(np.isfinite(x0)) or not math.isfinite(epoch):
            raise ValueError(f'target {tid}: the start needs a finite epoch and state (6,)')
        last = [s.table.time[s.table.target_id == tid] for s in obs.stations]
        last = [t for t in last if t.size]
        if not last:
            raise OrbitTrackingError(f'no measurement of target(s) [{tid}]')
        end = max(float(t.max()) for t in last)
        if until is not None and math.isfinite(until):
            end = max(end, min(float(until), end + COVER_LIMIT_S))
        models[tid] = cfg.model(float(epoch), end, (jumps or {}).get(tid, ()))
        starts[tid] = np.concatenate([x0, _start_coefficients(models[tid], x0, thrust)])
    prob = AdjointProblem(obs, models, biases, cfg.smoothness_sigma)
    p = np.concatenate(
        [starts[t] for t in prob.tids] + [np.array([prob.biases[i].prior for i in prob.free])]
    )
    iterations = evaluations = 0
    if prob.free:  # the flights first, the biases held: they can trade against a poor start
        held = [replace(b, estimate=False) for b in prob.biases]
        hp = AdjointProblem(obs, models, held, cfg.smoothness_sigma)
        first = _descend(hp, p[: prob.n_traj], cfg)
        p[: prob.n_traj] = first[0]
        iterations, evaluations = first[1], first[2]
    refused = 0.0
    for _ in range(cfg.gate_passes):
        p, its, ev, converged, decrement, n, info, opt_message = _descend(prob, p, cfg)
        iterations += its
        evaluations += ev
        if decrement > cfg.max_unconverged_decrement:
            break  # far from any optimum: its residuals say nothing about outliers
        refused, rejected_any = gate_pass(
            prob.residuals(p), prob.groups, cfg.gate_sigma, cfg.max_gate_share
        )
        if refused or not rejected_any:
            break
    res = prob.residuals(p)
    prior = prob._prior(p)
    cost = sum(float(np.nansum(r**2)) for r in res) + float(prior @ prior)
    rows = int(sum(int(g.keep.sum()) for g in prob.groups))
    dof = rows - prob.n_traj  # the bias prior rows and columns cancel
    chi2_dof = cost / max(dof, 1)
    cov, verdict = covariance_verdict(
        n,
        cost,
        dof,
        converged,
        decrement,
        refused,
        bool(np.all(np.isfinite(p))),
        cfg.max_chi2_dof,
        cfg.max_unconverged_decrement,
    )
    targets = {}
    for tid in prob.tids:
        k, n_p = prob.offsets[tid], models[tid].n_parameters
        sl = slice(k, k + n_p)
        tt = prob.times[tid]
        targets[tid] = AdjointFlight(
            tid, models[tid], p[sl].copy(), cov[sl, sl].copy(), float(tt[0]), float(tt[-1])
        )
    used, rejected, resid = fit_tables(res, prob.groups)
    names = tuple(f'{t}/{n}' for t in prob.tids for n in models[t].names) + tuple(
        f'{prob.biases[i].station}/{prob.biases[i].name}' for i in prob.free
    )
    return AdjointFit(
        success=verdict.success,
        message='converged' if verdict.success else '; '.join(verdict.reasons),
        targets=targets,
        biases=prob.biases,
        bias_values=prob.bias_values(p),
        iterations=iterations,
        cost=cost,
        chi2_dof=chi2_dof,
        dof=dof,
        decrement=decrement,
        covariance=cov,
        covariance_scale=verdict.covariance_scale,
        information=info,
        names=names,
        used=used,
        rejected=rejected,
        residuals=resid,
        solve_time=_time.perf_counter() - t_start,
        prior_sigma=np.array([prob.biases[i].sigma for i in prob.free]),
        evaluations=evaluations,
        optimizer_message=opt_message,
    )


def adjoint_bound(
    obs: Observations,
    truth: Mapping[int, tuple[float, ArrayLike, ThrustStart]],
    biases: Sequence[BiasParameter] = (),
    config: AdjointConfig | None = None,
    jumps: Mapping[int, Sequence[float]] | None = None,
) -> dict[int, AdjointFlight]:
    """The Cramér–Rao bound of the adjoint model: its information (every measured value,
    the bias priors at their ``prior``) at the true state and the thrust spline closest to
    the true thrust (``truth`` as :func:`fit_adjoint`'s ``initial``), inverted; each
    target's flight there with that covariance, so that :meth:`AdjointFlight.states`
    gives the bound of the states."""
    cfg = config or AdjointConfig()
    models, starts = {}, {}
    for tid, (epoch, state, thrust) in truth.items():
        x0 = np.asarray(state, dtype=np.float64).reshape(6)
        last = max(
            float(s.table.time[s.table.target_id == tid].max())
            for s in obs.stations
            if np.any(s.table.target_id == tid)
        )
        models[tid] = cfg.model(float(epoch), last, (jumps or {}).get(tid, ()))
        starts[tid] = np.concatenate([x0, _start_coefficients(models[tid], x0, thrust)])
    prob = AdjointProblem(obs, models, biases, cfg.smoothness_sigma)
    p = np.concatenate(
        [starts[t] for t in prob.tids] + [np.array([prob.biases[i].prior for i in prob.free])]
    )
    _, jac, _ = prob.jacobian(p)
    n = jac.T @ jac
    d = np.sqrt(np.maximum(np.diag(n), 1e-300))
    cov = np.linalg.pinv(n / np.outer(d, d), rcond=1e-14, hermitian=True) / np.outer(d, d)
    out = {}
    for tid in prob.tids:
        k, n_p = prob.offsets[tid], models[tid].n_parameters
        tt = prob.times[tid]
        out[tid] = AdjointFlight(
            tid,
            models[tid],
            p[k : k + n_p],
            cov[k : k + n_p, k : k + n_p],
            float(tt[0]),
            float(tt[-1]),
        )
    return out
