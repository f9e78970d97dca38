"""One draw of the robustness benchmark (issue 14): simulate a randomised scenario, bound it,
run every method on it and score each against the truth and the bound.

:func:`run_draw` never raises: a draw that cannot be simulated or bounded is recorded with
its message (:attr:`DrawResult.error`), and an exception in a method (or a method running
past its time limit) is recorded as that method failing on that draw
(:attr:`MethodResult.error`).

Methods, all on the same simulated measurements:

* ``ours``: the offline pipeline exactly as ``orbit-tracking estimate`` runs it
  (:func:`~orbit_tracking.core.estimation.windows.solve_windows` and
  :func:`~orbit_tracking.core.estimation.windows.stitch` with the estimator node's default
  settings, :func:`~orbit_tracking.tools.estimator_parameters.estimator_configs`),
  telemetry fused; the rough trajectory is the telemetry, or, without telemetry, fixes
  triangulated from the draw's lines of sight, as ``estimate`` does on a bag without either;
* ``ours, stations only``: the same with ``use_telemetry=False`` (telemetry only places the
  knots);
* ``KF+RTS``: :func:`~orbit_tracking.core.baselines.kalman.smooth` on the station
  measurements (started from the triangulated fixes, else the telemetry), its jerk density
  tuned on the truth (:func:`tune_kalman`) and its innovation gate on
  (:data:`KALMAN_GATE`), since the draws hold gross errors.

Scores (:class:`MethodResult`), at the truth sampling times (20 Hz) each method covers
within the draw's data span (first to last station value; outside it every method, the
oracle too, would only extrapolate):
position and velocity RMS error inside the draw's gaps and outside them, and their ratio
to the bound of the same samples (``ours``: stations and telemetry; the other two:
stations only; :mod:`orbit_tracking.core.crb`); the mean position NEES of one sample
every :data:`NEES_STEP_S` seconds, counted as independent, with the two-sided 95 %
chi-square band for that count, and beside it the band for samples whose errors are
correlated as the bound's at the same times and the chance that an honest estimator as
good as the bound falls inside the independent band
(:func:`~orbit_tracking.core.metrics.correlated_nees_band`); the same samples' mean
velocity NEES with its independent band (the position alone did not show a covariance
term that widened every velocity sigma fourfold); windows not successful or
raising; *silent failures*: output states (the multiples of the output step) whose
position or whose velocity is more than :data:`SILENT_SIGMA` of its own published
covariance off the truth (Mahalanobis distance, so in any direction; counted together and
each alone) while every window whose span covers the state claims success; failed windows
are withheld, so that is every output state (the KF claims success everywhere it
outputs); wall time.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.baselines.kalman import KalmanConfig, smooth, tune_on_truth
from orbit_tracking.core.crb import Bound, bound, oracle_spline, station_information
from orbit_tracking.core.crb import telemetry_information as _telemetry_information
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.config import EstimationError
from orbit_tracking.core.estimation.results import Estimate
from orbit_tracking.core.estimation.windows import solve_windows, stitch
from orbit_tracking.core.metrics import (
    correlated_nees_band,
    nees,
    nees_summary,
    whitened_correlation,
)
from orbit_tracking.core.sim.families import Draw, draw
from orbit_tracking.core.sim.simulator import SimulationResult, World, simulate
from orbit_tracking.core.sim.stream import feed_simulation
from orbit_tracking.core.sim.telemetry import error_covariance
from orbit_tracking.core.triangulation.pipeline import TriangulationPipeline, fix_series
from orbit_tracking.tools.bench.time_limit import time_limit_of
from orbit_tracking.tools.estimator_parameters import estimator_configs

__all__ = [
    'BOUND_OF',
    'KALMAN_GATE',
    'KALMAN_TUNING_SEEDS',
    'METHODS',
    'NEES_STEP_S',
    'SILENT_SIGMA',
    'DrawResult',
    'MethodResult',
    'run_draw',
    'tune_kalman',
    'worst_sigma',
]

FloatArray = NDArray[np.float64]

OURS, OURS_STATIONS, KALMAN = 'ours', 'ours, stations only', 'KF+RTS'
METHODS: tuple[str, ...] = (OURS, OURS_STATIONS, KALMAN)
BOUND_OF = {OURS: 'stations+telemetry', OURS_STATIONS: 'stations', KALMAN: 'stations'}
"""Which bound each method is held against."""
NEES_STEP_S = 5.0
"""NEES samples are taken this far apart and counted as independent for the target's band.
The estimators' errors are correlated over their knot spacing (a few seconds; windows of
60 s), and a telemetry error the stations cannot separate over the whole span, so the
correlated band is given beside it."""
SILENT_SIGMA = 5.0
KALMAN_GATE = 1e-6
"""Chi-square tail probability of the KF's innovation gate (the draws hold gross errors)."""
KALMAN_TUNING_SEEDS = (0, 1, 2)
"""The jerk density is tuned on the truth of these draws of each kind, then fixed for every
draw of the kind (so one draw run alone, ``--seed S --draws 1``, gets the same ``q``)."""
TARGET = 0
ORACLE_STEP_S = 0.05


@dataclass(frozen=True)
class MethodResult:
    """Scores of one method on one draw (nan where not defined, e.g. no gap)."""

    method: str
    error: str = ''
    pos_rms_gap: float = math.nan
    pos_rms_out: float = math.nan
    vel_rms_gap: float = math.nan
    vel_rms_out: float = math.nan
    pos_ratio_gap: float = math.nan
    pos_ratio_out: float = math.nan
    vel_ratio_gap: float = math.nan
    vel_ratio_out: float = math.nan
    nees_mean: float = math.nan
    nees_n: int = 0
    nees_lo: float = math.nan
    nees_hi: float = math.nan
    nees_lo_correlated: float = math.nan  # the band allowing for the bound's correlation
    nees_hi_correlated: float = math.nan
    nees_ideal_in_band: float = math.nan  # chance an estimator as good as the bound is inside
    vel_nees_mean: float = math.nan  # the same samples' velocity NEES, and its band
    vel_nees_lo: float = math.nan
    vel_nees_hi: float = math.nan
    coverage: float = 0.0
    windows: int = 0
    windows_failed: int = 0
    windows_raised: int = 0
    window_messages: tuple[str, ...] = ()
    silent: int = 0  # states whose position is more than SILENT_SIGMA off
    silent_velocity: int = 0  # ... whose velocity is
    silent_states: int = 0  # ... whose position or velocity is (the silent failures)
    states: int = 0
    wall_s: float = math.nan
    max_window_s: float = math.nan

    @property
    def ran(self) -> bool:
        return not self.error

    @property
    def nees_in_band(self) -> bool:
        return self.nees_lo <= self.nees_mean <= self.nees_hi

    @property
    def vel_nees_in_band(self) -> bool:
        return self.vel_nees_lo <= self.vel_nees_mean <= self.vel_nees_hi

    @property
    def nees_in_correlated_band(self) -> bool:
        return self.nees_lo_correlated <= self.nees_mean <= self.nees_hi_correlated


@dataclass(frozen=True)
class DrawResult:
    """One draw: what was drawn, its bounds and every method's scores."""

    kind: str
    seed: int
    summary: str = ''
    telemetry_model: str | None = None
    gaps: tuple[tuple[float, float], ...] = ()
    stations: int = 0
    values: int = 0
    gross_errors: int = 0
    bounds: Mapping[str, tuple[float, float, float, float]] = field(default_factory=dict)
    """Per bound: position gap, position outside [m], velocity gap, outside [m/s]."""
    oracle: tuple[float, float, float, float] = (math.nan,) * 4
    """Representation error of the oracle spline: max and RMS position [m], velocity [m/s]."""
    oracle_knots: tuple[int, int, int] = (0, 0, 0)
    methods: tuple[MethodResult, ...] = ()
    error: str = ''
    wall_s: float = math.nan
    bound_s: float = math.nan

    def method(self, name: str) -> MethodResult | None:
        return next((m for m in self.methods if m.method == name), None)


def _fixes(result: SimulationResult) -> Observations:
    """Observations with fixes triangulated from the draw's lines of sight."""
    pipe = TriangulationPipeline()
    feed_simulation(pipe, result)
    return Observations.from_simulation(result, fix_series(pipe.flush()))


@dataclass
class _Case:
    """A simulated draw with what every method and score needs."""

    draw: Draw
    world: World
    result: SimulationResult
    truth_t: FloatArray
    truth_x: FloatArray
    obs_est: Observations
    obs_kf: Observations
    in_gap: NDArray[np.bool_]


def _case(
    kind: str, seed: int, span_s: float | None = None, telemetry_model: str | None = None
) -> _Case:
    d = draw(kind, seed, span_s, telemetry_model)
    world = World(d.scenario)
    result = simulate(d.scenario, world)
    tr = result.truth[TARGET]
    with_fixes = _fixes(result)
    # as `orbit-tracking estimate`: telemetry is the rough trajectory; without it, fixes
    obs_est = Observations.from_simulation(result) if result.telemetry else with_fixes
    # scored where there are station data: before the first value and after the last,
    # every method (and the oracle) would only extrapolate
    t_data = np.concatenate(
        [t.time[t.target_id == TARGET] for t in result.measurements.values()] or [np.zeros(0)]
    )
    if t_data.size == 0:
        raise EstimationError(f'{kind} seed {seed}: no station sees the target')
    keep = (tr.time >= t_data.min() - 1e-9) & (tr.time <= t_data.max() + 1e-9)
    t_eval = tr.time[keep]
    in_gap = np.zeros(t_eval.size, dtype=bool)
    for a, b in d.scenario.gaps:
        in_gap |= (t_eval >= a) & (t_eval <= b)
    return _Case(
        d,
        world,
        result,
        t_eval,
        np.hstack([tr.position, tr.velocity])[keep],
        obs_est,
        with_fixes,
        in_gap,
    )


def _bounds(case: _Case) -> tuple[dict[str, Bound], tuple[float, ...], tuple[int, int, int]]:
    """Stations-only and stations+telemetry bounds at the truth times, and the oracle's
    representation error and knots."""
    sc, world = case.draw.scenario, case.world
    t_or = np.append(np.arange(sc.t_start, sc.t_end, ORACLE_STEP_S), sc.t_end)
    oracle = oracle_spline(
        t_or,
        world.target_state(TARGET, t_or),
        sc.t_start,
        sc.t_end,
        case.draw.events,
        case.draw.kinks,
    )
    traj = oracle.trajectory
    rows = []
    for s in Observations.from_simulation(case.result).stations:
        tab = s.table
        mine = tab.target_id == TARGET
        gross = case.result.gross_errors.get(tab.station_id)
        valid = np.isfinite(tab.values) & mine[:, None]
        if gross is not None:
            valid &= ~gross
        clock = sc.station(tab.station_id).clock_bias_s
        t_true = np.clip(tab.time + clock, sc.t_start, sc.t_end)
        states = world.target_state(TARGET, t_true)
        rows.append((tab.fields, t_true, s.pose, states, tab.sigmas, valid))
    f_st = station_information(traj, rows)
    out = {'stations': bound(traj, f_st, case.truth_t)}
    tel = case.result.telemetry.get(TARGET)
    if sc.telemetry is not None and tel is not None and sc.telemetry.error_model != 'none':
        cov = error_covariance(sc.telemetry, tel.time, sc.t_start, sc.t_end)
        f = _telemetry_information(
            traj,
            cov,
            lambda t: world.target_state(TARGET, t)[:, 3:],
            lambda t: world.targets[TARGET].acceleration(t),
        )
        f[: traj.n_coef, : traj.n_coef] += f_st
        out['stations+telemetry'] = bound(traj, f, case.truth_t)
    else:
        out['stations+telemetry'] = out['stations']
    rep = (
        oracle.max_position_error_m,
        oracle.rms_position_error_m,
        oracle.max_velocity_error_m_s,
        oracle.rms_velocity_error_m_s,
    )
    return out, rep, oracle.knots


def _rms(e: FloatArray, sel: NDArray[np.bool_]) -> float:
    return float(np.sqrt(np.mean(np.sum(e[sel] ** 2, axis=1)))) if np.any(sel) else math.nan


def _ratio(rms: float, crb: float) -> float:
    return rms / crb if math.isfinite(crb) and crb > 0.0 and math.isfinite(rms) else math.nan


def _d2(e: FloatArray, cov: FloatArray) -> FloatArray:
    """Squared Mahalanobis distances of the rows of ``e`` (inf for all when a covariance
    is singular)."""
    try:
        return nees(e, cov)
    except np.linalg.LinAlgError:
        return np.full(e.shape[0], np.inf)


def worst_sigma(est: Estimate, case: _Case, a: float, b: float, rows: slice) -> float:
    """The largest error, in sigmas of its covariance, of target 0's states ``rows`` (the
    position ``slice(0, 3)`` or the velocity ``slice(3, 6)``) in window ``est`` at
    ``case``'s truth times from ``a`` to ``b``."""
    sel = (case.truth_t >= a) & (case.truth_t <= b)
    x, cov = est.targets[0].states(case.truth_t[sel])
    err = (x - case.truth_x[sel])[:, rows]
    return float(np.sqrt(_d2(err, cov[:, rows, rows]).max()))


def _score(
    case: _Case,
    name: str,
    tt: FloatArray,
    x: FloatArray,
    cov: FloatArray,
    bounds: Mapping[str, Bound],
    claims: Callable[[FloatArray], NDArray[np.bool_]],
    output_step: float,
    **extra: object,
) -> MethodResult:
    """Scores of states ``x`` (k, 6), covariances ``cov`` at covered truth times ``tt``;
    ``claims(t)`` says where the output claims success (failed windows are withheld, so
    every output state is a claim)."""
    if tt.size == 0:
        raise EstimationError('no output state')
    idx = np.clip(np.searchsorted(case.truth_t, tt), 0, case.truth_t.size - 1)
    if not np.allclose(case.truth_t[idx], tt, atol=1e-6):
        raise ValueError('method states must be at the truth sampling times')
    e = x - case.truth_x[idx]
    gap = case.in_gap[idx]
    b = bounds[BOUND_OF[name]]
    gap_full = np.zeros(case.truth_t.size, dtype=bool)
    out_full = np.zeros(case.truth_t.size, dtype=bool)
    gap_full[idx[gap]] = True
    out_full[idx[~gap]] = True
    pos_gap, pos_out = _rms(e[:, :3], gap), _rms(e[:, :3], ~gap)
    vel_gap, vel_out = _rms(e[:, 3:], gap), _rms(e[:, 3:], ~gap)
    # NEES: one sample every NEES_STEP_S seconds
    k = np.round(tt / NEES_STEP_S)
    pick = np.flatnonzero(np.abs(tt - k * NEES_STEP_S) < 1e-6)
    parts = (slice(0, 3), slice(3, 6))  # position, velocity
    nees_mean, lo, hi = vel_nees = (math.nan,) * 3
    band_c: tuple[float, float, float] = (math.nan,) * 3
    if pick.size:
        ps, vs = (nees_summary(_d2(e[pick, p], cov[pick, p, p]), 3, 0.95) for p in parts)
        (nees_mean, lo, hi), vel_nees = (ps.mean, ps.lo, ps.hi), (vs.mean, vs.lo, vs.hi)
        # the samples are not independent: how the bound's errors at them are correlated
        sigma, finite = b.joint_position_covariance(tt[pick])
        band_c = correlated_nees_band(whitened_correlation(sigma, 3, finite), 3, 0.95)
    # silent failures on the output grid
    on_grid = np.abs(tt / output_step - np.round(tt / output_step)) < 1e-6
    # off by more than SILENT_SIGMA of its own covariance in any direction (Mahalanobis:
    # an error along a thin direction of an elongated covariance counts, which the
    # per-axis sigmas would not see)
    off = {
        p.start: ~(_d2(e[:, p], cov[:, p, p]) <= SILENT_SIGMA**2) & on_grid & claims(tt)
        for p in parts
    }
    silent = int(np.sum(off[0]))
    return MethodResult(
        name,
        pos_rms_gap=pos_gap,
        pos_rms_out=pos_out,
        vel_rms_gap=vel_gap,
        vel_rms_out=vel_out,
        pos_ratio_gap=_ratio(pos_gap, b.position(gap_full)),
        pos_ratio_out=_ratio(pos_out, b.position(out_full)),
        vel_ratio_gap=_ratio(vel_gap, b.velocity(gap_full)),
        vel_ratio_out=_ratio(vel_out, b.velocity(out_full)),
        nees_mean=nees_mean,
        nees_n=int(pick.size),
        nees_lo=lo,
        nees_hi=hi,
        nees_lo_correlated=band_c[0],
        nees_hi_correlated=band_c[1],
        nees_ideal_in_band=band_c[2],
        vel_nees_mean=vel_nees[0],
        vel_nees_lo=vel_nees[1],
        vel_nees_hi=vel_nees[2],
        coverage=float(tt.size / case.truth_t.size),
        silent=silent,
        silent_velocity=int(np.sum(off[3])),
        silent_states=int(np.sum(off[0] | off[3])),
        states=int(np.sum(on_grid)),
        **extra,  # type: ignore[arg-type]
    )


def _run_ours(
    case: _Case, name: str, bounds: Mapping[str, Bound], time_limit: float | None
) -> MethodResult:
    est_cfg, win_cfg, _ = estimator_configs({})
    if name == OURS_STATIONS:
        est_cfg = dataclasses.replace(est_cfg, use_telemetry=False)
    spans: list[tuple[float, float, str, str]] = []  # (t0, t1, ok|unsuccessful|raised, why)
    walls: list[float] = []
    last = [time.perf_counter()]

    def progress(_i: int, _n: int, span: tuple[float, float], res: object) -> None:
        now = time.perf_counter()
        walls.append(now - last[0])
        last[0] = now
        if isinstance(res, Estimate):
            status, why = ('ok', '') if res.success else ('unsuccessful', res.message)
        else:
            status, why = 'raised', f'{type(res).__name__}: {res}'
        spans.append((span[0], span[1], status, why))

    start = time.perf_counter()
    with time_limit_of(time_limit):
        estimates = solve_windows(case.obs_est, est_cfg, win_cfg, progress)
        wall = time.perf_counter() - start
        if not estimates:
            why = '; '.join(w for *_, w in spans if w) or 'no data'
            raise EstimationError(f'no window could be solved ({why})')
        tt, x, cov = stitch(estimates, case.truth_t, TARGET)
        if tt.size == 0:  # every window failed: the trajectory leaves them out
            why = '; '.join(w for *_, w in spans if w)[:300]
            raise EstimationError(f'no output state: no window succeeded ({why})')

    def claims(t: FloatArray) -> NDArray[np.bool_]:
        # failed windows are withheld (stitch leaves them out): every output state comes
        # from windows that claim success, also where a failed window overlapped them
        return np.ones(t.size, dtype=bool)

    messages = tuple(f'[{a:.1f}, {b:.1f}] s: {w}'[:200] for a, b, st, w in spans if st != 'ok')
    return _score(
        case,
        name,
        tt,
        x,
        cov,
        bounds,
        claims,
        win_cfg.output_step,
        windows=len(spans),
        windows_failed=sum(1 for s in spans if s[2] == 'unsuccessful'),
        windows_raised=sum(1 for s in spans if s[2] == 'raised'),
        window_messages=messages,
        wall_s=wall,
        max_window_s=max(walls, default=math.nan),
    )


def _run_kalman(
    case: _Case, bounds: Mapping[str, Bound], q: float, time_limit: float | None
) -> MethodResult:
    start = time.perf_counter()
    with time_limit_of(time_limit):
        track = smooth(
            case.obs_kf,
            TARGET,
            case.truth_t,
            KalmanConfig(jerk_psd=q, gate_probability=KALMAN_GATE),
        )
    wall = time.perf_counter() - start
    x, cov = track.states(case.truth_t)
    _, win, _ = estimator_configs({})
    return _score(
        case,
        KALMAN,
        case.truth_t,
        x,
        cov,
        bounds,
        lambda t: np.ones(t.size, dtype=bool),
        win.output_step,
        windows=1,
        wall_s=wall,
        max_window_s=wall,
    )


def run_draw(
    kind: str,
    seed: int,
    kalman_q: float,
    methods: Sequence[str] = METHODS,
    time_limit: float | None = 600.0,
    fail: Mapping[str, str] | None = None,
    span_s: float | None = None,
    telemetry_model: str | None = None,
) -> DrawResult:
    """Simulate, bound and score draw ``(kind, seed)``; never raises.

    Parameters
    ----------
    kalman_q : float
        Jerk density of the KF [m^2/s^5] (:func:`tune_kalman`).
    methods : sequence of str
        Which of :data:`METHODS` to run.
    time_limit : float, optional
        Seconds a method may run before it is recorded as failed.
    fail : mapping, optional
        Methods made to raise with the given message (tests of the recording).
    span_s : float, optional
        Span of the draw instead of the family's (short draws for tests).
    telemetry_model : str, optional
        Telemetry with this error model (:func:`~orbit_tracking.core.sim.families.draw`).
    """
    start = time.perf_counter()
    base = DrawResult(kind, seed)
    try:
        case = _case(kind, seed, span_s, telemetry_model)
        d = case.draw
        values = sum(int(np.isfinite(t.values).sum()) for t in case.result.measurements.values())
        base = dataclasses.replace(
            base,
            summary=d.summary,
            telemetry_model=d.telemetry_model,
            gaps=d.segments,
            stations=len(d.scenario.stations),
            values=values,
            gross_errors=int(sum(int(g.sum()) for g in case.result.gross_errors.values())),
        )
        t_b = time.perf_counter()
        bounds, rep, knots = _bounds(case)
        base = dataclasses.replace(
            base,
            bounds={
                k: (
                    b.position(case.in_gap),
                    b.position(~case.in_gap),
                    b.velocity(case.in_gap),
                    b.velocity(~case.in_gap),
                )
                for k, b in bounds.items()
            },
            oracle=(rep[0], rep[1], rep[2], rep[3]),
            oracle_knots=knots,
            bound_s=time.perf_counter() - t_b,
        )
    except Exception as exc:  # noqa: BLE001 - a draw must never stop the suite
        return dataclasses.replace(
            base, error=f'{type(exc).__name__}: {exc}', wall_s=time.perf_counter() - start
        )
    results = []
    for name in methods:
        t_m = time.perf_counter()
        try:
            if fail and name in fail:
                raise RuntimeError(fail[name])
            if name == KALMAN:
                results.append(_run_kalman(case, bounds, kalman_q, time_limit))
            else:
                results.append(_run_ours(case, name, bounds, time_limit))
        except Exception as exc:  # noqa: BLE001 - a method failing is a result
            results.append(
                MethodResult(
                    name,
                    error=f'{type(exc).__name__}: {exc}'[:300],
                    wall_s=time.perf_counter() - t_m,
                )
            )
    return dataclasses.replace(base, methods=tuple(results), wall_s=time.perf_counter() - start)


def tune_kalman(kind: str, seeds: Sequence[int] = KALMAN_TUNING_SEEDS) -> float:
    """The KF's jerk density [m^2/s^5] with the smallest position RMS error against the
    truth over draws ``seeds`` of ``kind`` (:func:`~orbit_tracking.core.baselines.kalman.
    tune_on_truth`; a draw the KF cannot start on is left out)."""
    cases = [_case(kind, s) for s in seeds]

    def run(q: float) -> float:
        mse = []
        for c in cases:
            try:
                track = smooth(
                    c.obs_kf,
                    TARGET,
                    c.truth_t,
                    KalmanConfig(jerk_psd=q, gate_probability=KALMAN_GATE),
                )
            except (EstimationError, np.linalg.LinAlgError):
                continue
            x, _ = track.states(c.truth_t)
            mse.append(float(np.mean(np.sum((x[:, :3] - c.truth_x[:, :3]) ** 2, axis=1))))
        if not mse:
            raise EstimationError('the KF ran on none of the tuning draws')
        return float(np.sqrt(np.mean(mse)))

    q, _ = tune_on_truth(run)
    return q
