"""A Kalman filter and Rauch–Tung–Striebel smoother on the raw station measurements.

This is the textbook recursive alternative to the spline estimator, kept as a baseline
for the benchmark (and as the starting point of the tracking filter): an extended Kalman
filter with a nearly-constant-acceleration motion model runs forward over every epoch
that has station measurements of the target, and an RTS pass runs backward over the same
epochs, so every output state uses all the data, as the spline fit does.

Motion model (per world axis, state ``(p, v, a)``): the acceleration is a Wiener process,
white jerk of spectral density ``q`` [m^2/s^5]. Over a step ``dt``::

    F = [[1, dt, dt^2/2], [0, 1, dt], [0, 0, 1]]
    Q = q [[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]]

(Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, 6.2.3). Measurements use the same models and Jacobians as the estimator
(:func:`orbit_tracking.core.models.measurements.predict`); all stations' rows at one epoch form
one update (iterated, so the strongly non-linear angle-only rows of a far satellite
linearise about the updated state). No systematic errors are modelled.

``q`` decides everything here; :func:`tune_on_truth` picks it the way a user of such a
framework tunes it on simulated truth, which favours the baseline.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.chi2 import chi2_isf_each
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.config import EstimationError
from orbit_tracking.core.models.measurements import StationPose, predict, residual

__all__ = ['KalmanConfig', 'SmoothedTrack', 'smooth', 'tune_on_truth']

FloatArray = NDArray[np.float64]

_EPOCH_TOL_S = 1e-9


@dataclass(frozen=True)
class KalmanConfig:
    """Settings of the filter/smoother.

    Attributes
    ----------
    jerk_psd : float
        Spectral density ``q`` of the white jerk [m^2/s^5].
    init_sigma : (float, float, float)
        Initial standard deviation of position [m], velocity [m/s] and acceleration
        [m/s^2] about the starting state (taken from the first fixes or telemetry).
    passes : int
        Forward/backward passes: 1 is the EKF with an RTS smoother; each further pass
        re-linearises about the previous smoothed trajectory.
    tolerance : float
        Passes stop when no position moved more than this [m].
    gate_probability : float
        A station row whose innovation has a chi-square tail probability below this is
        not used (counted in :attr:`SmoothedTrack.rejected`); 0 (default) turns the gate
        off.
    """

    jerk_psd: float = 10.0
    init_sigma: tuple[float, float, float] = (100.0, 50.0, 50.0)
    passes: int = 5
    tolerance: float = 1e-3
    gate_probability: float = 0.0

    def __post_init__(self) -> None:
        if not self.jerk_psd > 0:
            raise ValueError(f'jerk_psd must be > 0 m^2/s^5; got {self.jerk_psd}')
        if len(self.init_sigma) != 3 or not all(s > 0 for s in self.init_sigma):
            raise ValueError(f'init_sigma must be three values > 0; got {self.init_sigma}')
        if self.passes < 1:
            raise ValueError(f'passes must be >= 1; got {self.passes}')
        if not self.tolerance > 0:
            raise ValueError(f'tolerance must be > 0 m; got {self.tolerance}')
        if not 0.0 <= self.gate_probability < 1.0:
            raise ValueError(f'gate_probability must be in [0, 1); got {self.gate_probability}')


@dataclass(frozen=True)
class SmoothedTrack:
    """Smoothed states of one target at the requested output times.

    Attributes
    ----------
    target_id : int
    time : ndarray, shape (n,)
    state : ndarray, shape (n, 9)
        Position [m], velocity [m/s], acceleration [m/s^2] in the world frame.
    covariance : ndarray, shape (n, 9, 9)
    rows : int
        Station rows (epochs of one station) processed.
    rejected : int
        Rows the innovation gate left out in the last pass.
    passes : int
        Forward/backward passes run.
    """

    target_id: int
    time: FloatArray
    state: FloatArray
    covariance: FloatArray
    rows: int
    rejected: int
    passes: int

    @property
    def t0(self) -> float:
        return float(self.time[0])

    @property
    def t1(self) -> float:
        return float(self.time[-1])

    def states(self, t: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Position/velocity (m, 6) and covariance (m, 6, 6) at output times ``t`` (each
        must be one of :attr:`time`)."""
        tq = np.asarray(t, dtype=np.float64)
        i = np.searchsorted(self.time, tq)
        i = np.clip(i, 0, self.time.size - 1)
        if not np.allclose(self.time[i], tq, rtol=0.0, atol=1e-6):
            raise ValueError('smoothed states exist only at the output times they were run for')
        return self.state[i, :6], self.covariance[i][:, :6, :6]


@dataclass(frozen=True)
class _Station:
    """One station's rows of the target, with the timeline node of each row."""

    fields: tuple[str, ...]
    node: NDArray[np.intp]  # (n,)
    values: FloatArray  # (n, k), NaN where not measured
    variances: FloatArray  # (n, k)
    pose: StationPose  # n epochs


def _transitions(dt: FloatArray, q: float) -> tuple[FloatArray, FloatArray]:
    """F and Q (each (n, 9, 9), state order p, v, a) of the steps ``dt`` (n,)."""
    one, zero = np.ones_like(dt), np.zeros_like(dt)
    f1 = np.stack(
        [
            np.stack([one, dt, 0.5 * dt * dt], -1),
            np.stack([zero, one, dt], -1),
            np.stack([zero, zero, one], -1),
        ],
        -2,
    )
    q1 = q * np.stack(
        [
            np.stack([dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0], -1),
            np.stack([dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0], -1),
            np.stack([dt**3 / 6.0, dt**2 / 2.0, dt], -1),
        ],
        -2,
    )
    eye = np.eye(3)
    n = dt.size
    f = np.einsum('nij,kl->nikjl', f1, eye).reshape(n, 9, 9)
    qq = np.einsum('nij,kl->nikjl', q1, eye).reshape(n, 9, 9)
    return f, qq


def _timeline(
    obs: Observations, target_id: int, t_out: FloatArray
) -> tuple[FloatArray, list[_Station]]:
    """Nodes (every measurement epoch of the target and every output time, merged to
    ``_EPOCH_TOL_S``) and the stations' rows placed on them."""
    rows = []
    for s in obs.stations:
        tab = s.table
        sel = np.flatnonzero(tab.target_id == target_id)
        ok = np.isfinite(tab.values[sel]) & np.isfinite(tab.sigmas[sel])
        sel = sel[np.any(ok, axis=1)]
        if sel.size:
            rows.append((s, sel))
    if not rows:
        raise EstimationError(f'target {target_id}: no station measurements for the filter')
    times = np.unique(np.concatenate([s.table.time[i] for s, i in rows] + [t_out]))
    times = times[np.concatenate([[True], np.diff(times) > _EPOCH_TOL_S])]
    stations = []
    for s, i in rows:
        tab = s.table
        node = np.clip(np.searchsorted(times, tab.time[i] - _EPOCH_TOL_S), 0, times.size - 1)
        vals = np.where(np.isfinite(tab.sigmas[i]), tab.values[i], np.nan)
        stations.append(_Station(tab.fields, node, vals, np.square(tab.sigmas[i]), s.pose.take(i)))
    return times, stations


Linearised = tuple[FloatArray, FloatArray, FloatArray]
"""A station row about a linearisation point: residual (k,), Jacobian (k, 6), variances."""


def _linearise(
    stations: Sequence[_Station], nominal: FloatArray, n: int
) -> list[list[Linearised]]:
    """Per node, each row about the nominal trajectory, measured fields only."""
    per_node: list[list[Linearised]] = [[] for _ in range(n)]
    for st in stations:
        pred, jac = predict(st.fields, nominal[st.node, :6], st.pose, jacobian=True)
        if jac is None:  # pragma: no cover - predict returns it when asked
            raise EstimationError('measurement model returned no Jacobian')
        res = residual(st.fields, st.values, pred)
        for j in range(st.node.size):
            m = np.isfinite(res[j])
            per_node[st.node[j]].append((res[j][m], jac[j][m], st.variances[j][m]))
    return per_node


def _row_now(st: _Station, j: int, x: FloatArray) -> Linearised:
    """Row ``j`` about the current estimate (the first pass)."""
    m = np.isfinite(st.values[j])
    fields = [f for f, keep in zip(st.fields, m, strict=True) if keep]
    pred, jac = predict(fields, x[None, :6], st.pose.take([j]), jacobian=True)
    if jac is None:  # pragma: no cover - predict returns it when asked
        raise EstimationError('measurement model returned no Jacobian')
    return residual(fields, st.values[j][m][None, :], pred)[0], jac[0], st.variances[j][m]


def _start(obs: Observations, target_id: int, t_first: float) -> FloatArray:
    """Position, velocity and acceleration at ``t_first`` from a quadratic fit to the
    first few seconds of fixes (else telemetry)."""
    if target_id in obs.fixes and len(obs.fixes[target_id]) >= 3:
        f = obs.fixes[target_id]
        t, p = f.time, f.position
    elif target_id in obs.telemetry and len(obs.telemetry[target_id]) >= 3:
        tm = obs.telemetry[target_id]
        t, p = tm.time, tm.position
    else:
        raise EstimationError(
            f'target {target_id}: the Kalman filter needs at least 3 fixes or telemetry '
            'points to start from'
        )
    use = np.argsort(np.abs(t - t_first))[: max(3, min(40, t.size))]
    dt = t[use] - t_first
    a = np.stack([np.ones_like(dt), dt, 0.5 * dt * dt], axis=1)
    coef, *_ = np.linalg.lstsq(a, p[use], rcond=None)
    return np.concatenate([coef[0], coef[1], coef[2]])


def smooth(
    obs: Observations,
    target_id: int,
    t_out: ArrayLike,
    cfg: KalmanConfig | None = None,
) -> SmoothedTrack:
    """Filter forward and smooth backward over the target's measurement epochs.

    The first pass is an extended Kalman filter (each row linearised about the state just
    before it) and an RTS smoother; each further pass linearises every row about the
    previous pass's smoothed trajectory (the iterated extended Kalman smoother, a
    Gauss–Newton step on the whole track), until the positions move less than
    ``cfg.tolerance``.

    Parameters
    ----------
    obs : Observations
        Station rows of the target drive the filter; its fixes (else telemetry) only give
        the starting state.
    target_id : int
    t_out : array_like, shape (n,)
        Output times [s], non-decreasing.
    cfg : KalmanConfig

    Raises
    ------
    EstimationError
        No station rows of the target, or nothing to start from.
    """
    cfg = cfg or KalmanConfig()
    tq = np.asarray(t_out, dtype=np.float64).reshape(-1)
    if tq.size == 0 or np.any(np.diff(tq) < 0):
        raise ValueError('t_out must be a non-empty, non-decreasing array of times')
    times, stations = _timeline(obs, target_id, tq)
    n = times.size
    fs, qs = _transitions(np.diff(times, prepend=times[0]), cfg.jerk_psd)
    first: list[list[tuple[_Station, int]]] = [[] for _ in range(n)]
    for st in stations:
        for j, k in enumerate(st.node):
            first[k].append((st, j))
    gate = (
        chi2_isf_each(cfg.gate_probability, np.arange(1, 64)) if cfg.gate_probability > 0 else None
    )
    x0 = _start(obs, target_id, float(times[0]))
    p0 = np.diag(np.repeat(np.square(cfg.init_sigma), 3))
    nominal: FloatArray | None = None
    passes = rejected = 0
    xs, ps = np.empty((n, 9)), np.empty((n, 9, 9))
    for _ in range(cfg.passes):
        lin = None if nominal is None else _linearise(stations, nominal, n)
        x, p = x0, p0
        xs_f, ps_f = np.empty((n, 9)), np.empty((n, 9, 9))
        xs_p, ps_p = np.empty((n, 9)), np.empty((n, 9, 9))
        rejected = 0
        for k in range(n):
            f = fs[k]
            x = f @ x
            p = f @ p @ f.T + qs[k]
            xs_p[k], ps_p[k] = x, p
            if lin is None or nominal is None:
                for st, j in first[k]:  # each row about the state after the one before
                    x, p, ok = _update(x, p, *_row_now(st, j, x), gate)
                    rejected += not ok
            else:
                for res, h, r in lin[k]:
                    # z - h(x) ~ res - H (x - nominal)
                    innov = res - h @ (x[:6] - nominal[k, :6])
                    x, p, ok = _update(x, p, innov, h, r, gate)
                    rejected += not ok
            xs_f[k], ps_f[k] = x, p
        xs, ps = _rts(xs_f, ps_f, xs_p, ps_p, fs)
        passes += 1
        moved = np.inf if nominal is None else float(np.max(np.abs(xs[:, :3] - nominal[:, :3])))
        nominal = xs
        if moved < cfg.tolerance:
            break
    idx = np.clip(np.searchsorted(times, tq - _EPOCH_TOL_S), 0, n - 1)
    n_rows = sum(st.node.size for st in stations)
    return SmoothedTrack(target_id, tq, xs[idx], ps[idx], n_rows, rejected, passes)


def _update(
    x: FloatArray,
    p: FloatArray,
    innov: FloatArray,
    h6: FloatArray,
    r_diag: FloatArray,
    gate: FloatArray | None,
) -> tuple[FloatArray, FloatArray, bool]:
    """Kalman update with one station row: innovation (k,), Jacobian w.r.t. position and
    velocity (k, 6), variances (k,). Returns (x, P, used).

    The noise is uncorrelated between fields, so the fields are taken one at a time
    (scalar updates, no matrix inverse); the gate, when on, tests the row as a whole.
    """
    if gate is not None:
        s = h6 @ p[:6, :6] @ h6.T + np.diag(r_diag)
        d2 = float(innov @ np.linalg.solve(s, innov))
        if d2 > gate[min(innov.size, gate.size) - 1]:
            return x, p, False
    x0 = x
    for i in range(innov.size):
        h = h6[i]
        ph = p[:, :6] @ h  # P H^T, (9,)
        s_i = float(h @ ph[:6]) + float(r_diag[i])
        k_gain = ph / s_i
        # the innovation was formed about the state before this row
        x = x + k_gain * (innov[i] - h @ (x[:6] - x0[:6]))
        p = p - np.outer(k_gain, ph)
    return x, 0.5 * (p + p.T), True


def _rts(
    xs_f: FloatArray,
    ps_f: FloatArray,
    xs_p: FloatArray,
    ps_p: FloatArray,
    fs: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Rauch–Tung–Striebel backward pass; ``fs[k]`` takes node k-1 to node k.

    The gains ``G_k = P_k|k F_k+1^T P_k+1|k^-1`` do not depend on the backward pass, so
    they are solved for all nodes at once.
    """
    n = xs_f.shape[0]
    xs = xs_f.copy()
    ps = ps_f.copy()
    if n < 2:
        return xs, ps
    cross = fs[1:] @ ps_f[:-1]  # F_k+1 P_k|k, (n-1, 9, 9)
    gains = np.swapaxes(np.linalg.solve(ps_p[1:], cross), 1, 2)
    for k in range(n - 2, -1, -1):
        g = gains[k]
        xs[k] = xs_f[k] + g @ (xs[k + 1] - xs_p[k + 1])
        pk = ps_f[k] + g @ (ps[k + 1] - ps_p[k + 1]) @ g.T
        ps[k] = 0.5 * (pk + pk.T)
    return xs, ps


def tune_on_truth(
    run: Callable[[float], float],
    grid: Sequence[float] = tuple(10.0 ** np.arange(-3.0, 3.5, 1.0)),
    refine: int = 2,
) -> tuple[float, float]:
    """The jerk density minimising ``run(q)`` (an error against truth): a coarse
    log-spaced grid, then ``refine`` rounds of halving the log step about the best.

    Returns ``(q, error)``. Runs that raise :class:`EstimationError` count as infinite.
    """

    def score(q: float) -> float:
        try:
            e = run(q)
        except (EstimationError, np.linalg.LinAlgError):
            return float('inf')
        return e if np.isfinite(e) else float('inf')

    tried = {float(q): score(float(q)) for q in grid}
    step = float(np.log10(grid[1] / grid[0])) if len(grid) > 1 else 1.0
    for _ in range(refine):
        step /= 2.0
        best = min(tried, key=tried.__getitem__)
        for q in (best * 10.0**-step, best * 10.0**step):
            if q not in tried:
                tried[q] = score(q)
    best = min(tried, key=tried.__getitem__)
    return best, tried[best]
