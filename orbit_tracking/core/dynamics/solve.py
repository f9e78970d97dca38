"""One call from observations to a fitted rocket flight (what the offline tool, the
benchmark and the estimator node call): starting points for every target, the fit from
each, the best kept (seed 003, issue 15)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core import frames
from orbit_tracking.core.chi2 import chi2_ppf
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.dynamics.adjoint import (
    AdjointConfig,
    AdjointFit,
    fit_adjoint,
    initial_from_rocket,
)
from orbit_tracking.core.dynamics.fit import DynamicsFit, FitConfig, FlightModel, fit_dynamics
from orbit_tracking.core.dynamics.observability import bias_estimates, classify
from orbit_tracking.core.dynamics.range_search import start_candidates
from orbit_tracking.core.dynamics.rocket import FlightError, RocketModel
from orbit_tracking.core.dynamics.staging import STAGED_PARAMETERS, StagedRocketModel, staged_start
from orbit_tracking.core.dynamics.start import rough_fixes, start_from_fixes
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.results import Estimate, TargetSolution
from orbit_tracking.core.models.systematic import BiasParameter

__all__ = [
    'DYNAMICS_MODELS',
    'RocketConfig',
    'dynamics_window',
    'fit_model',
    'fit_rocket',
    'start_points',
]

FloatArray = NDArray[np.float64]

DYNAMICS_MODELS: tuple[str, ...] = ('rocket', 'adjoint')
"""The models with dynamics: the rocket-equation flight, and the seed's adjoint
assimilation of a free thrust profile (started from the rocket fit)."""

STAGING_GRID_S = 10.0
"""Spacing [s] of the staging times tried for a two-stage start."""

STAGING_SCOUT_ITERATIONS = 6
"""Levenberg-Marquardt steps each staging time of the grid gets."""

SCOUT_ITERATIONS = 12
"""Levenberg-Marquardt steps each start of a search gets before the best goes on."""

STAGING_EVIDENCE = float(chi2_ppf(0.999, 3))
"""Cost decrease (chi-square, three more parameters, 0.1 % false alarm) that makes the
automatic choice prefer two stages to one consistent burn."""

FULL_STARTS = 3
"""Scouted starts fitted to the end (:func:`_fit_best`)."""

EARTH_RATE = 7.2921150e-5
"""The Earth's rotation rate [rad/s] (for the rotating ``earth`` world frame)."""


@dataclass(frozen=True)
class RocketConfig:
    """Settings of :func:`fit_rocket`.

    Attributes
    ----------
    gm, j2 : float
        Gravity model (point mass; J2 0 to leave it out).
    rotating : bool
        The world frame turns with the Earth (``earth``): Coriolis and centrifugal terms.
    min_altitude, max_altitude : float
        The altitude band [m] the range hypotheses of a single station's start search.
    stages : int
        1: one burn; 2: a staging at an unknown time and a second stage
        (:mod:`~.staging`); 0 (auto): one, and two as well unless one burn's
        chi-square is as white noise gives it; two are kept when one burn is not a
        success or when they lower the cost by more than :data:`STAGING_EVIDENCE` (a
        staging that leaves one burn consistent can still bias it by several sigma).
    fit : FitConfig
    """

    gm: float = frames.WGS84_GM
    j2: float = 0.0
    rotating: bool = False
    min_altitude: float = 0.0
    max_altitude: float = 1.5e6
    stages: int = 1
    fit: FitConfig = FitConfig()

    def __post_init__(self) -> None:
        if self.stages not in (0, 1, 2):
            raise ValueError(f'stages must be 1, 2 or 0 (auto); got {self.stages}')

    @classmethod
    def for_frame(cls, frame: str, **settings: Any) -> RocketConfig:
        """The config for a world frame: ``eci`` inertial, ``earth`` rotating.

        Raises
        ------
        OrbitTrackingError
            Any other frame: the models need an Earth-centred one.
        """
        if frame not in ('eci', 'earth'):
            raise OrbitTrackingError(
                "the dynamics models need an Earth-centred world frame ('eci' or 'earth'); "
                f'the data are in {frame or "no stated frame"!r}'
            )
        return cls(rotating=frame == 'earth', **settings)

    def model(self, epoch: float) -> RocketModel:
        return RocketModel(
            epoch, self.gm, self.j2, frames.WGS84_A, EARTH_RATE if self.rotating else 0.0
        )

    def staged_model(self, epoch: float) -> StagedRocketModel:
        return StagedRocketModel(
            epoch, self.gm, self.j2, frames.WGS84_A, EARTH_RATE if self.rotating else 0.0
        )


def _starts(
    obs: Observations, tid: int, cfg: RocketConfig
) -> list[tuple[RocketModel, FloatArray]]:
    times = [s.table.time[s.table.target_id == tid] for s in obs.stations]
    times = [t for t in times if t.size]
    if not times:
        raise OrbitTrackingError(f'target {tid}: no station measures it')
    model = cfg.model(float(min(t.min() for t in times)))
    fixes = obs.fixes.get(tid)
    if fixes is None or len(fixes) < 6:
        fixes = rough_fixes(obs.stations, tid)
    if fixes is not None and len(fixes) >= 6:
        return [(model, start_from_fixes(fixes, model))]
    # no fixes: the station with the most rows about this target, angles only
    st = max(obs.stations, key=lambda s: int(np.sum(s.table.target_id == tid)))
    return [
        (model, th) for th in start_candidates(st, tid, model, cfg.min_altitude, cfg.max_altitude)
    ]


Starts = dict[int, list[tuple[RocketModel, FloatArray]]]
"""Every target's starting points, best first (:func:`start_points`)."""


def start_points(
    obs: Observations, target_ids: Sequence[int] | None = None, config: RocketConfig | None = None
) -> Starts:
    """The starting points of every measured target that :func:`fit_rocket` tries (the
    first of each also serves the observability before the solve)."""
    cfg = config or RocketConfig()
    ids = sorted(target_ids) if target_ids is not None else obs.target_ids
    ids = [t for t in ids if any(np.any(s.table.target_id == t) for s in obs.stations)]
    return {tid: _starts(obs, tid, cfg) for tid in ids}


def fit_rocket(
    obs: Observations,
    target_ids: Sequence[int] | None = None,
    biases: Sequence[BiasParameter] = (),
    config: RocketConfig | None = None,
    starts: Starts | None = None,
) -> DynamicsFit:
    """Fit the rocket model of every target (jointly, sharing the biases).

    Each target starts from its fixes (``obs.fixes``) when it has some, else from rough
    fixes made from the rows (:func:`~.start.rough_fixes`: radar points, two stations'
    crossing lines), else from the range-hypothesis search on the angles of the station
    that sees it most (:func:`~.range_search.start_candidates`); ``starts`` (from
    :func:`start_points`) skips that search when it was made already. With several starts
    each is
    fitted a few steps (:data:`SCOUT_ITERATIONS`, biases held) and the fit goes on from the
    one of lowest cost.

    Raises
    ------
    OrbitTrackingError
        No target, no usable start, or no start could be flown.
    """
    cfg = config or RocketConfig()
    if starts is None:
        starts = start_points(obs, target_ids, cfg)
    if not starts:
        raise OrbitTrackingError('no station measurement of any target to fit')
    n_alt = max(len(v) for v in starts.values())
    errors = []
    ranked: list[tuple[float, dict[int, tuple[FlightModel, FloatArray]]]] = []  # by cost
    if n_alt > 1:  # scout every start a few steps, biases held; go on from the best
        scout = replace(cfg.fit, max_iterations=SCOUT_ITERATIONS, gate_passes=1)
        held = [replace(b, estimate=False) for b in biases]
        for k in range(n_alt):
            initial = {tid: s[min(k, len(s) - 1)] for tid, s in starts.items()}
            try:
                trial = fit_dynamics(obs, initial, held, scout)
            except FlightError as exc:
                errors.append(str(exc))
                continue
            scouted: dict[int, tuple[FlightModel, FloatArray]] = {
                t: (m, trial.targets[t].theta) for t, (m, _) in initial.items()
            }
            ranked.append((trial.cost, scouted))
        if not ranked:
            raise OrbitTrackingError('no start could be flown: ' + '; '.join(errors))
        ranked.sort(key=lambda c: c[0])
    else:
        ranked = [(0.0, {tid: s[0] for tid, s in starts.items()})]
    by_target = {tid: [d[tid] for _, d in ranked] for tid in ranked[0][1]}
    single = _fit_best(obs, by_target, biases, cfg, 'the rocket fit failed')
    if cfg.stages == 1 or (cfg.stages == 0 and single.success and _white(single)):
        return single
    sources = {
        tid: [(tf.model, tf.theta), ranked[0][1][tid]] for tid, tf in single.targets.items()
    }
    try:
        staged = _fit_best(
            obs, _staged_starts(obs, sources, biases, cfg), biases, cfg, 'no staging flew'
        )
    except OrbitTrackingError as exc:
        if cfg.stages == 2:
            raise OrbitTrackingError(f'the two-stage fit failed: {exc}') from exc
        return single
    if cfg.stages == 2:
        return staged
    if single.success:  # a staging must earn its three parameters (likelihood ratio)
        gain = single.cost - staged.cost
        return staged if staged.success and gain > STAGING_EVIDENCE else single
    return staged if staged.success or staged.chi2_dof < single.chi2_dof else single


def _white(fit: DynamicsFit) -> bool:
    """Whether a fit's chi-square is within three of its standard deviations of its
    degrees of freedom: nothing left for a staging to explain (the automatic choice
    then skips the two-stage search, which costs a hundred one-stage fits)."""
    return fit.chi2_dof <= 1.0 + 3.0 * math.sqrt(2.0 / max(fit.dof, 1))


def _staged_starts(
    obs: Observations,
    sources: Mapping[int, Sequence[tuple[FlightModel, FloatArray]]],
    biases: Sequence[BiasParameter],
    cfg: RocketConfig,
) -> dict[int, list[tuple[FlightModel, FloatArray]]]:
    """Each target's two-stage starts, best first: each one-stage source (the one-stage
    fit, and the start it came from, which a diverged fit cannot spoil) continued by a
    second stage from a staging on a :data:`STAGING_GRID_S` grid over the target's
    span; each is scouted a few steps (that target alone, biases held), and the best
    source of each staging time is kept, ranked by its cost."""
    scout = replace(cfg.fit, max_iterations=STAGING_SCOUT_ITERATIONS, gate_passes=1)
    held = [replace(b, estimate=False) for b in biases]
    out: dict[int, list[tuple[FlightModel, FloatArray]]] = {}
    for tid, flights in sources.items():
        epoch = flights[0][0].epoch
        model = cfg.staged_model(epoch)
        times = [s.table.time[s.table.target_id == tid] for s in obs.stations]
        t0 = min(float(t.min()) for t in times if t.size)
        t1 = max(float(t.max()) for t in times if t.size)
        best: dict[float, tuple[float, FloatArray]] = {}
        for t_s in np.arange(t0 + STAGING_GRID_S, t1 - 0.5 * STAGING_GRID_S, STAGING_GRID_S):
            for _, theta in flights:
                start = staged_start(theta, float(t_s), epoch)
                try:
                    trial = fit_dynamics(obs, {tid: (model, start)}, held, scout)
                except FlightError:
                    continue
                if trial.cost < best.get(float(t_s), (math.inf, None))[0]:
                    best[float(t_s)] = (trial.cost, trial.targets[tid].theta)
        if not best:
            raise OrbitTrackingError(f'target {tid}: no staging time gave a flight')
        out[tid] = [(model, th) for _, th in sorted(best.values(), key=lambda c: c[0])]
    return out


def _fit_best(
    obs: Observations,
    ranked: Mapping[int, Sequence[tuple[FlightModel, FloatArray]]],
    biases: Sequence[BiasParameter],
    cfg: RocketConfig,
    failure: str,
) -> DynamicsFit:
    """The full fit from each of the :data:`FULL_STARTS` best starts (the k-th of every
    target together; one satellite's angles and the staging time have several valleys,
    and the best after scouting is not always the deepest); the success of lowest cost,
    else the lowest cost."""
    best: DynamicsFit | None = None
    errors = []
    for k in range(min(FULL_STARTS, max(len(v) for v in ranked.values()))):
        initial = {tid: v[min(k, len(v) - 1)] for tid, v in ranked.items()}
        try:
            trial = fit_dynamics(obs, initial, biases, cfg.fit)
        except FlightError as exc:
            errors.append(str(exc))
            continue
        if best is None or (trial.success, -trial.cost) > (best.success, -best.cost):
            best = trial
    if best is None:
        raise OrbitTrackingError(f'{failure}: ' + '; '.join(errors))
    return best


def fit_model(
    obs: Observations,
    model: str = 'rocket',
    target_ids: Sequence[int] | None = None,
    biases: Sequence[BiasParameter] = (),
    config: RocketConfig | None = None,
    adjoint: AdjointConfig | None = None,
    starts: Starts | None = None,
    cover: tuple[float, float] | None = None,
) -> DynamicsFit | AdjointFit:
    """:func:`fit_rocket`, or for ``model='adjoint'`` the adjoint assimilation started
    from it (its gravity settings are the rocket config's; the rocket fit need not be a
    success to start from). ``cover`` (first, last) [s] are times the adjoint's flights
    must reach (report times), up to :data:`~.adjoint.COVER_LIMIT_S` beyond the data;
    the rocket's flights reach any time.

    Raises
    ------
    ValueError
        An unknown model.
    OrbitTrackingError
        No fit could start.
    """
    if model not in DYNAMICS_MODELS:
        raise ValueError(f'model must be one of {", ".join(DYNAMICS_MODELS)}; got {model!r}')
    cfg = config or RocketConfig()
    rocket = fit_rocket(obs, target_ids, biases, cfg, starts)
    if model == 'rocket':
        return rocket
    acfg = replace(adjoint or AdjointConfig(), gm=cfg.gm, j2=cfg.j2, rotating=cfg.rotating)
    try:
        first, last = cover if cover is not None else (None, None)
        jumps = {  # where the rocket fit found a staging, the thrust spline may jump
            tid: (float(tf.theta[STAGED_PARAMETERS.index('staging_time')]),)
            for tid, tf in rocket.targets.items()
            if isinstance(tf.model, StagedRocketModel)
        }
        return fit_adjoint(
            obs, initial_from_rocket(rocket.targets, first), biases, acfg, last, jumps
        )
    except FlightError as exc:
        raise OrbitTrackingError(f'the adjoint assimilation failed: {exc}') from exc


def dynamics_window(
    obs: Observations,
    t0: float,
    t1: float,
    model: str = 'rocket',
    target_ids: Sequence[int] | None = None,
    biases: Sequence[BiasParameter] = (),
    config: RocketConfig | None = None,
) -> Estimate:
    """:func:`fit_model` on the rows in ``[t0, t1]``, reported as a window
    :class:`~orbit_tracking.core.estimation.results.Estimate` (what the estimator node
    publishes with ``model: rocket`` or ``adjoint``). Its targets are the fitted flights:
    they offer what the node and the stitcher use of a solution (``t0``, ``t1``,
    ``states``), not the spline's coefficients, so they cannot seed a spline window.
    A bias's status is its observability class."""
    fit = fit_model(obs.window(t0, t1), model, target_ids, biases, config)
    rows = bias_estimates(fit, classify(fit))
    d = np.sqrt(np.maximum(np.diag(fit.information), 1e-300))
    with np.errstate(all='ignore'):
        cond = float(np.linalg.cond(fit.information / np.outer(d, d)))
    return Estimate(
        success=fit.success,
        message=fit.message,
        t0=t0,
        t1=t1,
        targets=cast('dict[int, TargetSolution]', dict(fit.targets)),
        iterations=fit.iterations,
        halvings=0,
        cost=fit.cost,
        chi2_dof=fit.chi2_dof,
        condition=cond,
        n_parameters=len(fit.names),
        used=fit.used,
        rejected=fit.rejected,
        residuals={s: (t, f, r) for s, (t, f, r, _) in fit.residuals.items()},
        knot_time=0.0,
        solve_time=fit.solve_time,
        covariance=fit.covariance,
        biases=tuple(rows),
        covariance_scale=fit.covariance_scale,
    )
