"""Settings of the seed-000 window estimator (:class:`EstimatorConfig`) and its error type."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.coverage import CoverageConfig
from orbit_tracking.core.estimation.knots import KnotConfig
from orbit_tracking.core.models.systematic import BiasParameter

__all__ = [
    'KNOT_METHODS',
    'ROBUST_LOSSES',
    'TELEMETRY_DELAYS',
    'TELEMETRY_VELOCITY_ERRORS',
    'EstimationError',
    'EstimatorConfig',
    'Segment',
]


FloatArray = NDArray[np.float64]


Segment = tuple[float, float]


KNOT_METHODS: tuple[str, ...] = ('sparse', 'dense', 'uniform', 'dynamics', 'polynomial')

ROBUST_LOSSES: tuple[str, ...] = ('huber', 'cauchy', 'none')
"""Losses of the robust warm-up solve that decides which rows are gross errors."""

TELEMETRY_VELOCITY_ERRORS: tuple[str, ...] = ('auto', 'derivative', 'separate')
"""How the telemetry velocity error is modelled: the derivative of the position error
only, with a separate error of its own, or chosen per window by a test on the residuals."""

TELEMETRY_DELAYS: tuple[str, ...] = ('auto', 'off', 'on')
"""Whether the telemetry's time-tag delays (position and velocity) are estimated: chosen
per window by a test on the residuals, never, or always."""


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
    max_iterations : int
        Gauss-Newton (Levenberg-Marquardt) iterations at most.
    convergence_decrement : float
        A solve has converged when the Gauss-Newton step from its solution would lower the
        cost (chi-square) by at most this: the step would move it by less than the square
        root of this in units of its own standard deviations (0.01 by default).
    max_unconverged_decrement : float
        A solve that ended without converging, its Gauss-Newton step still promising at
        most this much lower chi2, is taken with its covariance scaled by ``1 +`` that
        (within about its square root of standard deviations of the optimum); 0 = never
        (:mod:`~orbit_tracking.core.estimation.verdict`).
    tolerance, max_halvings :
        The robust warm-up stops when its relative cost change falls below ``tolerance``;
        its step is halved at most ``max_halvings`` times.
    gate_sigma : float
        Whitened-residual gate (0 disables it); ``gate_rounds`` re-solves at most.
        Station values and fixes beyond it are rejected; telemetry epochs only beyond
        ``GROSS_FACTOR`` (4) times it (see :mod:`~orbit_tracking.core.estimation.gauss_newton`).
    robust_loss : str
        Loss of the warm-up solve that decides the gross errors (residuals beyond
        ``GROSS_FACTOR * gate_sigma``, 20 sigma) before the plain solve: ``huber``
        (default), ``cauchy``, or ``none`` (no warm-up, the behaviour before: one gross
        error drags the first fit until the gate sees most rows off and refuses; only
        absurd values, beyond 1e10 sigma, are still set aside). The robust fit only
        chooses rows to gate: the solution and its covariance are plain weighted least
        squares on the rows kept.
    robust_scale : float, optional
        Tuning constant ``c`` of that loss in units of the rows' robust scale (1.4826 x
        the median absolute whitened residual of each kind of row, never below 1): with
        Huber a row beyond ``c`` pulls no harder than one at ``c``. Default (None):
        ``GROSS_FACTOR * gate_sigma``, so every row within the gross-error limit is
        plain least squares and a window without gross errors takes exactly the plain
        solve's steps (no extra cost). Smaller values (Huber's classical 1.345,
        Cauchy's 2.385) downweight clean rows too and cost a separate warm-up solve.
    use_telemetry : bool
        Fuse telemetry as weighted measurements with its own error model (whose knots
        the measurement-driven test refines like the trajectory's).
    telemetry_error_spacing : float
        Knot spacing [s] of the telemetry error spline (cubic).
    telemetry_velocity_error : str
        ``derivative``: the telemetry velocity error is ``e'`` (velocity integrated into
        the position, one error source); ``separate``: ``e' + w`` with ``w`` an error of
        its own (velocity from GNSS Doppler or an INS, a time-tag skew between the two);
        ``auto`` (default): ``derivative`` unless the velocity residuals of the solved
        window show an error of their own (a test at ``telemetry_velocity_alpha``).
    telemetry_velocity_error_spacing : float
        Knot spacing [s] of ``w`` (piecewise linear) when it is added.
    telemetry_velocity_error_min_spacing : float
        The spacing of ``w`` is halved, down to this [s], while a score test on the
        telemetry velocity residuals (at ``telemetry_velocity_alpha``) asks for a faster
        ``w`` (a velocity error correlated over seconds, not tens of seconds).
    telemetry_velocity_alpha : float
        Significance of the test that switches ``auto`` to ``separate``, and of the test
        that adds time-tag delays.
    telemetry_delays : str
        ``auto``: a window estimates a time-tag delay of the telemetry position and one of
        its velocity (``p(t - d_p)``, ``v(t - d_v)``) when a score test on its residuals
        asks for them (:mod:`~orbit_tracking.core.estimation.telemetry_delays`; the
        default); ``off``: never; ``on``: always. See docs/ESTIMATOR.md.
    nonlinear_sigma : float
        Where three sigma of a state along its longest axis change a nearby station value
        to second order by more than this many of its sigmas (the row's, or the fitted
        value's from the state covariance if smaller), the linearised covariance
        is published as its largest sigma in every direction
        (:mod:`~orbit_tracking.core.estimation.linearity`); 0 = never.
    edge_gap : float
        A window whose station rows and telemetry start more than this many seconds after
        its start (or end as long before its end) is solved over the span they cover: the
        trajectory beyond the last datum is not determined by it (a restart, a loss of
        all data at the end of a pass), and the next or previous window covers it.
    estimate_telemetry_noise : bool
        Re-estimate the telemetry white-noise levels from the residuals.
    estimate_telemetry_error : bool
        Re-estimate the two prior sigmas of the telemetry error spline (its level and its
        steps between consecutive coefficients) from the data (the pair of largest evidence
        per solve round, the uncertainty of the pair added to the published covariance;
        :mod:`~orbit_tracking.core.estimation.telemetry_evidence`) instead of holding them
        at the declared position sigma.
    max_chi2_dof : float
        Largest chi-square per degree of freedom of a window that is a success (with few
        degrees of freedom ``1 + 5 sqrt(2 / dof)`` if larger; see
        :mod:`~orbit_tracking.core.estimation.verdict`).
    retry : bool
        Solve a window that is not a success again: cut short of an incomplete segment at
        its edge, then with safer settings (:mod:`~orbit_tracking.core.estimation.retries`).
    estimate_station_noise : bool
        Use a station field's sigmas scaled up to the RMS of its residuals when these show
        white noise significantly larger than declared (never below the declared sigma;
        see :func:`~orbit_tracking.core.estimation.gauss_newton.reestimate_station_noise`).
    fix_weight : float
        Fixes as measurements with covariance / ``fix_weight``; 0 = not used.
    refine_rounds : int
        Rounds of measurement-driven knot insertion after the solve (0 = off).
    refine_alpha : float
        Family-wise false-alarm probability of that knot test.
    gate_event_rounds : int
        Rounds of events put where the residual gate's rejected station values cluster in
        time (a staging no knot follows: :mod:`~orbit_tracking.core.estimation.
        gate_events`), each event then moved to where the measurements fit it best, and
        followed by a new solve; 0 = off.
    move_events : bool
        Move each event of the rough trajectory (timed by its own samples) to where the
        station measurements fit it best, as the gate's events, and solve again.
    doubtful_events : bool
        Without telemetry, test an event near each change of acceleration the first
        solution's detector saw (a doubtful change: no knots); taken where the measurements
        ask for it (:mod:`~orbit_tracking.core.estimation.doubtful_events`).
    event_time_uncertainty : bool
        Add the uncertainty of the events' times to the states' covariance, from how well
        the measurements place each event (:mod:`~orbit_tracking.core.estimation.
        event_times`).
    refine_events : bool
        Let that test also insert events (a knot of multiplicity ``degree - 1`` on every
        axis: the acceleration may jump there) where the measurements ask for one, outside
        the incomplete segments (:func:`~orbit_tracking.core.estimation.knot_refinement.
        refine_knots`). Off by default: on the benchmarks it removed over-confident states
        but cost time and accuracy on seed003_q2 (docs/ESTIMATOR.md).
    prune_z : float
        After the first solve, a single interior knot whose derivative jump is below this
        many of its standard deviations is dropped (the measurements do not support it);
        0 (default) = keep every selected knot (:func:`~orbit_tracking.core.estimation.
        knot_refinement.prune_knots`). Off by default: in an incomplete segment the
        measurements seldom make a knot the telemetry chose significant, and dropping it
        removed real curvature (seed000_s2_range8m: gap error 0.077 m without, 0.126 m
        with 2).
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
    jerk_prior : bool
        A white-jerk prior on every trajectory, ``|p'''|^2 / q`` integrated over the
        window, with its density ``q`` [m^2/s^5] estimated from the data (an evidence
        update per solve round): what bridges a span the measurements hardly determine (a
        telemetry outage with a turn in it) the way a Kalman smoother's motion model does.
    jerk_grid : float
        Quadrature step [s] of that integral.
    gap_manoeuvre_density : float
        Density q [m^2/s^5] of the manoeuvres an incomplete segment may hide (staging, a
        turn's onset): steps of the acceleration inside every incomplete segment, a white
        jerk of this density, carried as consider parameters in the published state
        covariance (:mod:`~orbit_tracking.core.estimation.gap_manoeuvres`); the estimate
        itself does not change. 0 = off.
    gap_manoeuvre_step : float
        Spacing [s] of those steps' instants.
    event_manoeuvre_density : float
        Density q [m^2/s^5] of the same consider term across ``event +-
        event_manoeuvre_half_width`` around every detected event (acceleration jump, ramp
        end or bend): the detail of a manoeuvre the event's knots follow only
        approximately (a ramp end placed a few tenths of a second off). 0 = off.
    event_manoeuvre_half_width : float
        Half width [s] of those spans.
    unseen_manoeuvre_density : float
        Density q [m^2/s^5] of the same consider term across the spans where the
        telemetry (the rough trajectory whose events make knots) has no samples, widened
        by ``knots.event_window``: a turn or a staging inside a telemetry outage has no
        event found, no knots at its instants and none of the term above. 0 = off.
    weak_manoeuvre_gain : float
        Gain [s] of the same consider term across ``weak +- event_manoeuvre_half_width``
        around every weak change (a jerk jump ``j`` too small for an event,
        :attr:`~orbit_tracking.core.estimation.events.Changes.weak`): density
        ``gain * j^2`` [m^2/s^5]. 0 = off.
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
    convergence_decrement: float = 1e-4
    max_unconverged_decrement: float = 4.0
    tolerance: float = 1e-9
    max_halvings: int = 12
    gate_sigma: float = 5.0
    gate_rounds: int = 3
    robust_loss: str = 'huber'
    robust_scale: float | None = None
    use_telemetry: bool = True
    telemetry_error_spacing: float = 15.0
    telemetry_velocity_error: str = 'auto'
    telemetry_velocity_error_spacing: float = 20.0
    telemetry_velocity_error_min_spacing: float = 5.0
    telemetry_velocity_alpha: float = 1e-3
    telemetry_delays: str = 'auto'
    nonlinear_sigma: float = 1.0
    edge_gap: float = 0.5
    estimate_telemetry_noise: bool = True
    estimate_telemetry_error: bool = True
    estimate_station_noise: bool = True
    max_chi2_dof: float = 1.5
    retry: bool = True
    fix_weight: float = 0.0
    refine_rounds: int = 4
    prune_z: float = 0.0
    refine_alpha: float = 0.01
    refine_events: bool = False
    gate_event_rounds: int = 2
    move_events: bool = True
    doubtful_events: bool = True
    event_time_uncertainty: bool = True
    biases: tuple[BiasParameter, ...] = ()
    bias_observability: float = 0.9
    thrust_along_velocity: float = 0.0
    thrust_grid: float = 0.5
    jerk_prior: bool = True
    jerk_grid: float = 0.25
    gap_manoeuvre_density: float = 300.0
    gap_manoeuvre_step: float = 0.5
    event_manoeuvre_density: float = 30.0
    event_manoeuvre_half_width: float = 3.0
    unseen_manoeuvre_density: float = 10.0
    weak_manoeuvre_gain: float = 1.0
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
        if not self.prune_z >= 0.0:
            raise ValueError(f'prune_z must be >= 0; got {self.prune_z}')
        if not self.max_chi2_dof >= 1.0:
            raise ValueError(f'max_chi2_dof must be >= 1; got {self.max_chi2_dof}')
        if not self.max_unconverged_decrement >= 0.0:
            raise ValueError(
                f'max_unconverged_decrement must be >= 0; got {self.max_unconverged_decrement}'
            )
        if not self.convergence_decrement > 0.0:
            raise ValueError(
                f'convergence_decrement must be > 0; got {self.convergence_decrement}'
            )
        if self.gate_sigma < 0.0 or self.fix_weight < 0.0:
            raise ValueError('gate_sigma and fix_weight must be >= 0')
        if self.gate_event_rounds < 0:
            raise ValueError(f'gate_event_rounds must be >= 0; got {self.gate_event_rounds}')
        if self.robust_loss not in ROBUST_LOSSES:
            raise ValueError(
                f'robust_loss must be one of {ROBUST_LOSSES}; got {self.robust_loss!r}'
            )
        if self.robust_scale is not None and not (
            np.isfinite(self.robust_scale) and self.robust_scale > 0.0
        ):
            raise ValueError(f'robust_scale must be finite and > 0; got {self.robust_scale}')
        if self.telemetry_error_spacing <= 0.0:
            raise ValueError('telemetry_error_spacing must be > 0')
        if not 0.0 < self.jerk_grid <= 10.0:
            raise ValueError(f'jerk_grid must lie in (0, 10] s; got {self.jerk_grid}')
        if not 0.0 <= self.gap_manoeuvre_density <= 1e6:
            raise ValueError(
                f'gap_manoeuvre_density must lie in [0, 1e6] m^2/s^5; got '
                f'{self.gap_manoeuvre_density}'
            )
        if not 0.0 <= self.event_manoeuvre_density <= 1e6:
            raise ValueError(
                f'event_manoeuvre_density must lie in [0, 1e6] m^2/s^5; got '
                f'{self.event_manoeuvre_density}'
            )
        if not 0.0 <= self.unseen_manoeuvre_density <= 1e6:
            raise ValueError(
                f'unseen_manoeuvre_density must lie in [0, 1e6] m^2/s^5; got '
                f'{self.unseen_manoeuvre_density}'
            )
        if not 0.0 <= self.weak_manoeuvre_gain <= 1e3:
            raise ValueError(
                f'weak_manoeuvre_gain must lie in [0, 1e3] s; got {self.weak_manoeuvre_gain}'
            )
        if not 0.05 <= self.event_manoeuvre_half_width <= 30.0:
            raise ValueError(
                'event_manoeuvre_half_width must lie in [0.05, 30] s; got '
                f'{self.event_manoeuvre_half_width}'
            )
        if not 0.01 <= self.gap_manoeuvre_step <= 10.0:
            raise ValueError(
                f'gap_manoeuvre_step must lie in [0.01, 10] s; got {self.gap_manoeuvre_step}'
            )
        if self.telemetry_velocity_error not in TELEMETRY_VELOCITY_ERRORS:
            raise ValueError(
                f'telemetry_velocity_error must be one of {TELEMETRY_VELOCITY_ERRORS}; '
                f'got {self.telemetry_velocity_error!r}'
            )
        if not self.telemetry_velocity_error_spacing > 0.0:
            raise ValueError('telemetry_velocity_error_spacing must be > 0')
        min_spacing = self.telemetry_velocity_error_min_spacing
        if not 0.0 < min_spacing <= self.telemetry_velocity_error_spacing:
            raise ValueError(
                'telemetry_velocity_error_min_spacing must lie in (0, '
                'telemetry_velocity_error_spacing]'
            )
        if self.telemetry_delays not in TELEMETRY_DELAYS:
            raise ValueError(
                f'telemetry_delays must be one of {TELEMETRY_DELAYS}; '
                f'got {self.telemetry_delays!r}'
            )
        if not 0.0 < self.telemetry_velocity_alpha < 1.0:
            raise ValueError('telemetry_velocity_alpha must lie in (0, 1)')
        if not self.edge_gap > 0.0:
            raise ValueError(f'edge_gap must be > 0; got {self.edge_gap}')
        if not self.nonlinear_sigma >= 0.0:
            raise ValueError(f'nonlinear_sigma must be >= 0; got {self.nonlinear_sigma}')
        if self.thrust_along_velocity < 0.0 or self.thrust_grid <= 0.0 or self.gm <= 0.0:
            raise ValueError('thrust_along_velocity must be >= 0, thrust_grid and gm > 0')
        for a, b in self.segments:
            if not b > a:
                raise ValueError(f'segment ({a}, {b}) must have end > start')
