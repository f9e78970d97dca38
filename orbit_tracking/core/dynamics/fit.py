"""A trajectory model with dynamics fitted to the raw measurements of every station,
jointly with the stations' systematic errors (seed 003, issue 15).

The unknowns are each target's model parameters (:class:`~.rocket.RocketModel`: state at
the epoch, exhaust speed, mass time) and the declared biases. The cost is the whitened
misfit of every measured value (``(measured - h(x(t; theta)) - bias terms) / sigma``, the
models of :mod:`~orbit_tracking.core.models.measurements` and
:mod:`~orbit_tracking.core.models.systematic`) plus each estimated bias's prior row.

It is minimised by Levenberg-Marquardt (Marquardt's damping on the Jacobi-scaled normal
matrix, the cost of a trial step from a propagation without sensitivities). The solve
**converged** when the full Gauss-Newton step would lower the cost by at most
``convergence_decrement`` (the same test as the spline estimator's, which a stalled step
cannot pass). Values beyond ``gate_sigma`` are then rejected and the fit repeated, a few
passes, unless a pass would reject more than ``max_gate_share`` of one station's field for
one target: then they are not outliers, the model does not fit the data, and the gate
refuses (the fit is not a success). Success is the one verdict of
:func:`~orbit_tracking.core.estimation.verdict.judge` (converged, chi-square per degree
of freedom consistent, not singular, the gate not refusing); the covariance is the
inverse normal matrix, scaled as the verdict says.
"""

from __future__ import annotations

import math
import time as _time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.dynamics.rocket import Flight, FlightError
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.verdict import Verdict, judge
from orbit_tracking.core.models.measurements import StationPose, predict, residual
from orbit_tracking.core.models.systematic import CLOCK, BiasModel, BiasParameter

__all__ = [
    'DynamicsFit',
    'FitConfig',
    'TargetFlight',
    'bound_at',
    'covariance_verdict',
    'fit_dynamics',
    'fit_tables',
    'gate_pass',
    'information_at',
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class FitConfig:
    """Settings of :func:`fit_dynamics` (the thresholds mean what the spline estimator's
    of the same name mean: :class:`~orbit_tracking.core.estimation.config.EstimatorConfig`).
    """

    max_iterations: int = 100
    convergence_decrement: float = 1e-4
    max_unconverged_decrement: float = 4.0
    gate_sigma: float = 5.0
    gate_passes: int = 4
    max_gate_share: float = 0.05
    max_chi2_dof: float = 1.5

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.gate_passes < 1:
            raise ValueError('max_iterations and gate_passes must be >= 1')
        if not self.convergence_decrement > 0.0:
            raise ValueError(
                f'convergence_decrement must be > 0; got {self.convergence_decrement}'
            )
        if not self.gate_sigma > 0.0:
            raise ValueError(f'gate_sigma must be > 0; got {self.gate_sigma}')


class FlightModel(Protocol):
    """What a fitted flight needs of its model (the rocket model, the adjoint's thrust
    spline model)."""

    @property
    def epoch(self) -> float: ...

    @property
    def names(self) -> tuple[str, ...]: ...

    @property
    def n_parameters(self) -> int: ...

    def propagate(self, theta: ArrayLike, t: ArrayLike, jacobian: bool = True) -> Flight: ...

    def thrust(self, theta: ArrayLike, t: ArrayLike) -> FloatArray: ...


@dataclass(frozen=True)
class TargetFlight:
    """The fitted flight of one target: parameters, their covariance (marginal, every
    other unknown estimated too) and states with covariance anywhere in ``[t0, t1]``
    (the rocket model's flight; the adjoint's is a subclass)."""

    target_id: int
    model: FlightModel
    theta: FloatArray
    covariance: FloatArray
    t0: float
    t1: float

    def states(self, t: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray]:
        """World-frame (position, velocity) (m, 6) and their covariance (m, 6, 6)."""
        f = self.model.propagate(self.theta, np.asarray(t, dtype=np.float64))
        assert f.sensitivity is not None
        g = f.sensitivity
        cov = np.einsum('mik,kl,mjl->mij', g, self.covariance, g)
        return f.state, 0.5 * (cov + np.transpose(cov, (0, 2, 1)))

    def thrust(self, t: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray]:
        """Thrust acceleration magnitude [m/s^2] and its sigma at ``t``, shape (m,) each
        (the model's closed-form thrust; its gradient by central differences)."""
        tt = np.asarray(t, dtype=np.float64)
        a = self.model.thrust(self.theta, tt)
        g = np.empty((tt.size, self.theta.size))
        for k in range(self.theta.size):
            h = 1e-6 * max(abs(float(self.theta[k])), 1.0)
            e = np.zeros(self.theta.size)
            e[k] = h
            g[:, k] = self.model.thrust(self.theta + e, tt) - self.model.thrust(self.theta - e, tt)
            g[:, k] /= 2.0 * h
        var = np.einsum('mi,ij,mj->m', g, self.covariance, g)
        return a, np.sqrt(np.maximum(var, 0.0))


@dataclass(frozen=True)
class DynamicsFit:
    """Outcome of :func:`fit_dynamics`, the way ``scipy.optimize`` reports.

    ``names`` label the rows and columns of ``covariance`` (``<target>/<parameter>`` and
    ``<station>/<bias>``); ``information`` is the normal matrix of the measurements alone
    (without the bias priors), for the observability analysis. ``residuals`` maps each
    station to (time (n,), fields, whitened residual (n, k), target id (n,)); NaN where a
    value was not measured or was rejected.
    """

    success: bool
    message: str
    targets: Mapping[int, TargetFlight]
    biases: tuple[BiasParameter, ...]
    bias_values: FloatArray
    iterations: int
    cost: float
    chi2_dof: float
    dof: int
    decrement: float
    covariance: FloatArray
    covariance_scale: float
    information: FloatArray
    names: tuple[str, ...]
    used: Counter[str]
    rejected: Counter[tuple[str, str]]
    residuals: Mapping[str, tuple[FloatArray, tuple[str, ...], FloatArray, FloatArray]]
    solve_time: float
    prior_sigma: FloatArray = field(default_factory=lambda: np.zeros(0))


@dataclass
class _Group:
    """The rows of one station about one target."""

    station: str
    target: int
    fields: tuple[str, ...]
    time: FloatArray
    values: FloatArray
    sigmas: FloatArray
    pose: StationPose
    keep: NDArray[np.bool_]  # (n, k): measured and not rejected


class _Problem:
    """Parameter vector ``[theta of each target..., estimated biases...]``."""

    def __init__(
        self,
        obs: Observations,
        models: Mapping[int, FlightModel],
        biases: Sequence[BiasParameter],
    ) -> None:
        self.models = dict(models)
        self.tids = sorted(models)
        clocks = [b for b in biases if b.name == CLOCK]
        if clocks:
            raise OrbitTrackingError(
                'the dynamics models do not estimate clock offsets; declare them known or '
                f'leave them out ({", ".join(b.station for b in clocks)})'
            )
        self.biases = tuple(biases)
        self.free = [i for i, b in enumerate(self.biases) if b.estimate]
        sizes = [self.models[t].n_parameters for t in self.tids]
        starts = np.cumsum([0, *sizes]).tolist()
        self.slices = {
            t: slice(a, b) for t, a, b in zip(self.tids, starts[:-1], starts[1:], strict=True)
        }
        self.n_traj = int(starts[-1])
        self.n = self.n_traj + len(self.free)
        self.groups: list[_Group] = []
        for st in obs.stations:
            tab = st.table
            for tid in self.tids:
                sel = tab.target_id == tid
                if not np.any(sel):
                    continue
                vals = tab.values[sel]
                sig = tab.sigmas[sel]
                keep = np.isfinite(vals) & np.isfinite(sig) & (sig > 0)
                self.groups.append(
                    _Group(
                        tab.station_id,
                        tid,
                        tuple(tab.fields),
                        tab.time[sel],
                        vals,
                        sig,
                        st.pose.take(np.flatnonzero(sel)),
                        keep,
                    )
                )
        self.times = {
            tid: np.unique(np.concatenate([g.time for g in self.groups if g.target == tid]))
            for tid in self.tids
            if any(g.target == tid for g in self.groups)
        }
        if set(self.times) != set(self.tids):
            missing = sorted(set(self.tids) - set(self.times))
            raise OrbitTrackingError(f'no measurement of target(s) {missing}')

    def bias_models(self, beta: FloatArray) -> dict[str, BiasModel]:
        vals: dict[str, dict[str, float]] = {}
        free = dict(zip(self.free, beta[self.n_traj :], strict=True))
        for i, b in enumerate(self.biases):
            vals.setdefault(b.station, {})[b.name] = float(free.get(i, b.prior))
        return {s: BiasModel(v) for s, v in vals.items()}

    def bias_values(self, beta: FloatArray) -> FloatArray:
        free = dict(zip(self.free, beta[self.n_traj :], strict=True))
        return np.array([free.get(i, b.prior) for i, b in enumerate(self.biases)])

    def flights(self, beta: FloatArray, jacobian: bool) -> dict[int, Flight]:
        return {
            tid: self.models[tid].propagate(beta[self.slices[tid]], self.times[tid], jacobian)
            for tid in self.tids
        }

    def evaluate(
        self, beta: FloatArray, jacobian: bool
    ) -> tuple[list[FloatArray], FloatArray | None]:
        """Whitened residual (n, k) per group (NaN where not kept), and the Jacobian of the
        residual vector (kept values, then the bias prior rows: :meth:`vector`)."""
        fl = self.flights(beta, jacobian)
        bm = self.bias_models(beta)
        res: list[FloatArray] = []
        blocks: list[FloatArray] = []
        for g in self.groups:
            f = fl[g.target]
            idx = np.searchsorted(self.times[g.target], g.time)
            x = f.state[idx]
            h, dh = predict(g.fields, x, g.pose, jacobian=jacobian)
            model = bm.get(g.station, BiasModel())
            pred = model.apply(g.fields, h)
            r = residual(g.fields, g.values, pred) / g.sigmas
            r[~g.keep] = np.nan
            res.append(r)
            if not jacobian:
                continue
            assert dh is not None and f.sensitivity is not None
            names = [self.biases[i].name for i in self.free if self.biases[i].station == g.station]
            cols = [
                self.n_traj + j
                for j, i in enumerate(self.free)
                if self.biases[i].station == g.station
            ]
            d_true, d_param = model.jacobian(g.fields, h, names)
            jx = np.einsum('mab,mbc,mcp->map', d_true, dh, f.sensitivity[idx])  # (m, k, n_p)
            blk = np.zeros((g.time.size, len(g.fields), self.n))
            blk[:, :, self.slices[g.target]] = jx
            if cols:
                blk[:, :, cols] = d_param
            blk /= -g.sigmas[:, :, None]  # the derivative of the residual, not of h
            blocks.append(blk[g.keep])
        if not jacobian:
            return res, None
        prior = np.zeros((len(self.free), self.n))
        for j, i in enumerate(self.free):
            prior[j, self.n_traj + j] = 1.0 / self.biases[i].sigma
        return res, np.vstack([*blocks, prior])

    def vector(self, res: Sequence[FloatArray], beta: FloatArray) -> FloatArray:
        data = [r[g.keep] for r, g in zip(res, self.groups, strict=True)]
        pri = [
            (beta[self.n_traj + j] - self.biases[i].prior) / self.biases[i].sigma
            for j, i in enumerate(self.free)
        ]
        return np.concatenate([*data, np.asarray(pri, dtype=np.float64)])

    def cost(self, beta: FloatArray) -> float:
        try:
            res, _ = self.evaluate(beta, False)
        except FlightError:
            return math.inf
        v = self.vector(res, beta)
        return float(v @ v) if np.all(np.isfinite(v)) else math.inf

    @property
    def n_rows(self) -> int:
        return int(sum(int(g.keep.sum()) for g in self.groups))


_LAMBDAS = (1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 1e2, 1e3, 1e4, 1e5, 1e6)


def _solve(
    prob: _Problem, beta: FloatArray, cfg: FitConfig
) -> tuple[FloatArray, int, bool, float, FloatArray, FloatArray, list[FloatArray]]:
    """Levenberg-Marquardt from ``beta``: (beta, iterations, converged, decrement, normal
    matrix, gradient, residuals)."""
    lam = 0.0
    it = 0
    while True:
        res, jac = prob.evaluate(beta, True)
        assert jac is not None
        r = prob.vector(res, beta)
        cost = float(r @ r)
        n = jac.T @ jac
        g = jac.T @ r
        d = np.sqrt(np.maximum(np.diag(n), 1e-300))
        ns = n / np.outer(d, d)
        gs = g / d
        try:
            step_s = -np.linalg.solve(ns, gs)
        except np.linalg.LinAlgError:
            step_s = -np.linalg.lstsq(ns, gs, rcond=None)[0]
        decrement = float(-gs @ step_s)
        if decrement <= cfg.convergence_decrement or it >= cfg.max_iterations:
            return beta, it, decrement <= cfg.convergence_decrement, decrement, n, g, res
        it += 1
        start = 0 if lam == 0.0 else _LAMBDAS.index(lam) + 1
        accepted = False
        for lam_try in (0.0, *_LAMBDAS)[start:]:
            if lam_try == 0.0:
                s = step_s
            else:
                s = -np.linalg.solve(ns + lam_try * np.eye(prob.n), gs)
            trial = beta + s / d
            c_new = prob.cost(trial)
            if c_new < cost:
                beta = trial
                lam = 0.0 if lam_try <= _LAMBDAS[0] else _LAMBDAS[_LAMBDAS.index(lam_try) - 1]
                accepted = True
                break
        if not accepted:  # no step lowers the cost: judged by its decrement
            return beta, it, False, decrement, n, g, res


Residuals = dict[str, tuple[FloatArray, tuple[str, ...], FloatArray, FloatArray]]


def gate_pass(
    res: Sequence[FloatArray], groups: Sequence[_Group], gate_sigma: float, max_share: float
) -> tuple[float, bool]:
    """One pass of the residual gate over the kept values of ``groups`` (whitened
    residuals ``res``, one (n, k) array a group): ``(refused, rejected)``. It refuses
    (``refused`` = the share, nothing rejected) when it would take more than ``max_share``
    of one group's field: those are not outliers, the model does not fit the data; else
    it rejects every value beyond ``gate_sigma`` (``rejected``: any was)."""
    bad = [
        g.keep & (np.abs(np.nan_to_num(r, nan=0.0)) > gate_sigma)
        for r, g in zip(res, groups, strict=True)
    ]
    share = max(
        float(np.max(b.sum(axis=0) / np.maximum(np.isfinite(g.values).sum(axis=0), 1)))
        for b, g in zip(bad, groups, strict=True)
    )
    if share > max_share:
        return share, False
    for b, g in zip(bad, groups, strict=True):
        g.keep &= ~b
    return 0.0, any(bool(np.any(b)) for b in bad)


def fit_tables(
    res: Sequence[FloatArray], groups: Sequence[_Group]
) -> tuple[Counter[str], Counter[tuple[str, str]], Residuals]:
    """Values used per station, values rejected per (station, ``residual_gate``), and the
    residuals per station (:attr:`DynamicsFit.residuals`)."""
    used: Counter[str] = Counter()
    rejected: Counter[tuple[str, str]] = Counter()
    resid: Residuals = {}
    for rr, g in zip(res, groups, strict=True):
        used[g.station] += int(g.keep.sum())
        out = int(np.sum(np.isfinite(g.values) & ~g.keep))
        if out:
            rejected[(g.station, 'residual_gate')] += out
        ids = np.full(g.time.size, float(g.target))
        prev = resid.get(g.station)
        if prev is None:
            resid[g.station] = (g.time, g.fields, rr, ids)
        else:
            resid[g.station] = (
                np.concatenate([prev[0], g.time]),
                g.fields,
                np.vstack([prev[2], rr]),
                np.concatenate([prev[3], ids]),
            )
    return used, rejected, resid


def covariance_verdict(
    n: FloatArray,
    cost: float,
    dof: int,
    converged: bool,
    decrement: float,
    refused: float,
    finite: bool,
    max_chi2_dof: float,
    max_unconverged_decrement: float,
) -> tuple[FloatArray, Verdict]:
    """The inverse of the normal matrix ``n`` (Jacobi-scaled: the units of the parameters
    differ by many decades) and the verdict of
    :func:`~orbit_tracking.core.estimation.verdict.judge`, the covariance scaled as it
    says."""
    d = np.sqrt(np.maximum(np.diag(n), 1e-300))
    try:
        cov = np.linalg.inv(n / np.outer(d, d)) / np.outer(d, d)
        singular = not np.all(np.isfinite(cov)) or np.linalg.cond(n / np.outer(d, d)) > 1e13
    except np.linalg.LinAlgError:
        cov, singular = np.full_like(n, np.nan), True
    verdict = judge(
        converged,
        cost / max(dof, 1),
        dof,
        max_chi2_dof,
        singular=singular,
        gate_refused=refused,
        finite=finite,
        decrement=decrement,
        max_decrement=max_unconverged_decrement,
    )
    return cov * verdict.covariance_scale, verdict


def fit_dynamics(
    obs: Observations,
    initial: Mapping[int, tuple[FlightModel, FloatArray]],
    biases: Sequence[BiasParameter] = (),
    config: FitConfig | None = None,
) -> DynamicsFit:
    """Fit each target's flight model, and the biases, to the raw measurements.

    Parameters
    ----------
    obs : Observations
        Station rows (their target ids pick the target); telemetry and fixes are not used.
    initial : mapping of target id to (model, theta (model.n_parameters,))
        The model of each target and its starting parameters.
    biases : sequence of BiasParameter
        Declared systematic errors (``estimate=False`` holds one at its prior).
    config : FitConfig, optional

    Returns
    -------
    DynamicsFit
    """
    cfg = config or FitConfig()
    t_start = _time.perf_counter()
    prob = _Problem(obs, {k: m for k, (m, _) in initial.items()}, biases)
    beta = np.concatenate(
        [np.asarray(initial[t][1], dtype=np.float64) for t in prob.tids]
        + [np.array([prob.biases[i].prior for i in prob.free])]
    )
    iterations = 0
    if prob.free:  # the flights first, the biases held: they can trade against a poor start
        held = _Problem(obs, prob.models, [replace(b, estimate=False) for b in prob.biases])
        first = _solve(held, beta[: prob.n_traj], cfg)
        iterations += first[1]
        beta[: prob.n_traj] = first[0]
    refused = 0.0
    for _ in range(cfg.gate_passes):
        beta, its, converged, decrement, n, _g, res = _solve(prob, beta, cfg)
        iterations += its
        if decrement > cfg.max_unconverged_decrement:
            break  # far from any optimum: its residuals say nothing about outliers
        refused, rejected_any = gate_pass(res, prob.groups, cfg.gate_sigma, cfg.max_gate_share)
        if refused or not rejected_any:
            break
    r = prob.vector(res, beta)
    cost = float(r @ r)
    dof = prob.n_rows - prob.n_traj  # the bias prior rows and columns cancel
    chi2_dof = cost / max(dof, 1)
    prior_info = np.zeros(prob.n)
    prior_info[prob.n_traj :] = [1.0 / prob.biases[i].sigma ** 2 for i in prob.free]
    cov, verdict = covariance_verdict(
        n,
        cost,
        dof,
        converged,
        decrement,
        refused,
        bool(np.all(np.isfinite(beta))),
        cfg.max_chi2_dof,
        cfg.max_unconverged_decrement,
    )
    names = tuple(f'{t}/{p}' for t in prob.tids for p in prob.models[t].names) + tuple(
        f'{prob.biases[i].station}/{prob.biases[i].name}' for i in prob.free
    )
    targets = {}
    for tid in prob.tids:
        sl = prob.slices[tid]
        tt = prob.times[tid]
        targets[tid] = TargetFlight(
            tid, prob.models[tid], beta[sl].copy(), cov[sl, sl].copy(), float(tt[0]), float(tt[-1])
        )
    used, rejected, resid = fit_tables(res, prob.groups)
    message = 'converged' if verdict.success else '; '.join(verdict.reasons)
    return DynamicsFit(
        success=verdict.success,
        message=message,
        targets=targets,
        biases=prob.biases,
        bias_values=prob.bias_values(beta),
        iterations=iterations,
        cost=cost,
        chi2_dof=chi2_dof,
        dof=dof,
        decrement=decrement,
        covariance=cov,
        covariance_scale=verdict.covariance_scale,
        information=n - np.diag(prior_info),
        names=names,
        used=used,
        rejected=rejected,
        residuals=resid,
        solve_time=_time.perf_counter() - t_start,
        prior_sigma=np.array([prob.biases[i].sigma for i in prob.free]),
    )


def bound_at(
    obs: Observations,
    truth: Mapping[int, tuple[FlightModel, FloatArray]],
    biases: Sequence[BiasParameter] = (),
) -> dict[int, TargetFlight]:
    """The Cramer-Rao bound of the model at the true parameters (``truth``; the biases at
    their ``prior``): each target's flight at the truth with the inverse information
    (measurements and bias priors, every row kept) as its covariance, so that
    :meth:`TargetFlight.states` gives the bound of the states."""
    prob = _Problem(obs, {k: m for k, (m, _) in truth.items()}, biases)
    beta = np.concatenate(
        [np.asarray(truth[t][1], dtype=np.float64) for t in prob.tids]
        + [np.array([prob.biases[i].prior for i in prob.free])]
    )
    _, jac = prob.evaluate(beta, True)
    assert jac is not None
    n = jac.T @ jac
    d = np.sqrt(np.maximum(np.diag(n), 1e-300))
    cov = np.linalg.pinv(n / np.outer(d, d), rcond=1e-14, hermitian=True) / np.outer(d, d)
    out = {}
    for tid in prob.tids:
        sl = prob.slices[tid]
        tt = prob.times[tid]
        out[tid] = TargetFlight(
            tid, prob.models[tid], beta[sl], cov[sl, sl], float(tt[0]), float(tt[-1])
        )
    return out


def information_at(
    obs: Observations,
    initial: Mapping[int, tuple[FlightModel, FloatArray]],
    biases: Sequence[BiasParameter] = (),
) -> tuple[FloatArray, tuple[str, ...], FloatArray, FloatArray]:
    """The normal matrix of the measurements alone (every measured value, without the bias
    priors) at the parameters ``initial`` (the biases at their priors): ``(information,
    names, prior sigmas of the estimated biases, parameter values)``."""
    prob = _Problem(obs, {k: m for k, (m, _) in initial.items()}, biases)
    beta = np.concatenate(
        [np.asarray(initial[t][1], dtype=np.float64) for t in prob.tids]
        + [np.array([prob.biases[i].prior for i in prob.free])]
    )
    _, jac = prob.evaluate(beta, True)
    assert jac is not None
    data = jac[: jac.shape[0] - len(prob.free)]
    names = tuple(f'{t}/{p}' for t in prob.tids for p in prob.models[t].names) + tuple(
        f'{prob.biases[i].station}/{prob.biases[i].name}' for i in prob.free
    )
    prior = np.array([prob.biases[i].sigma for i in prob.free])
    return data.T @ data, names, prior, beta
