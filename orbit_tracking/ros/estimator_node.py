"""``estimator``: sliding-window trajectory estimation from the raw measurements.

Subscribes to ``stations/<id>/measurements`` and ``stations/<id>/state`` of the stations in
its ``stations`` parameter (or of every station that appears), to ``telemetry/state`` and to
``triangulation/fixes`` (the rough trajectory when there is no telemetry). It buffers them
by stamp and solves a window of ``window_length`` seconds once the newest stamp is
``latency`` seconds past the window's end, on the ``~/solve`` service (``std_srvs/Trigger``:
solve what is buffered now), and when no input message (measurements, states, telemetry,
fixes) has arrived for ``flush_after`` wall seconds (end of the stream; the fixes of the
stream's tail come last, after the triangulation node's own flush). Consecutive windows
overlap by ``window_overlap`` seconds and each starts from the previous solution.

Publishes each window's fitted states with covariance on ``estimator/window_states``
(``sensor_msgs/PointCloud2``, internal: see docs/CONTRACT.md) and ``/diagnostics``. With
station biases declared (``bias_file``: ``auto`` or a YAML file) they are estimated in every
window and published on ``trajectory/biases`` (``diagnostic_msgs/DiagnosticArray``,
transient local, one status per station). With ``journal_dir`` set, every input it accepts
is journaled, and a node killed at any moment resumes from the journal when started again
(:mod:`orbit_tracking.ros.journal`).

Example::

    ros2 run orbit_tracking estimator --ros-args -p window_length:=60.0 -p latency:=2.0

The module is over the project's ~600-line guide: about 230 lines of it are the node's
parameter declarations (each with its description and range). What the node publishes for a
solved or failed window is in :mod:`orbit_tracking.ros.estimator_outputs`; the estimation
itself is one call into :func:`orbit_tracking.core.estimation.estimator.estimate` (with
``model: rocket`` or ``adjoint``,
:func:`orbit_tracking.core.dynamics.solve.dynamics_window`).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections import Counter
from dataclasses import replace

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from orbit_tracking.core.data.buffer import ObservationBuffer
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.dynamics.solve import RocketConfig, dynamics_window
from orbit_tracking.core.estimation.bias_files import load_bias_declaration, station_fields
from orbit_tracking.core.estimation.config import KNOT_METHODS, EstimatorConfig
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.core.estimation.knots import KnotConfig, load_solver
from orbit_tracking.core.estimation.results import Estimate, TargetSolution
from orbit_tracking.core.estimation.retries import COVERED_S
from orbit_tracking.core.estimation.windows import (
    Span,
    WindowConfig,
    WindowScheduler,
)
from orbit_tracking.core.time import format_stamp
from orbit_tracking.ros import qos
from orbit_tracking.ros.conversions import (
    MeasurementBatch,
    StationStateSample,
    TargetStateSample,
    TimeBase,
    diagnostic_array,
    diagnostic_status,
    msg_to_fix,
    odometry_to_target_state,
)
from orbit_tracking.ros.estimator_outputs import WindowOutputs
from orbit_tracking.ros.journal import EstimatorJournal
from orbit_tracking.ros.parameters import declare, diagnostics_timer
from orbit_tracking.ros.runner import run_node
from orbit_tracking.ros.solve_worker import SolveWorker
from orbit_tracking.ros.station_inputs import StationInputs

MODELS = ('spline', 'rocket', 'adjoint')
"""The trajectory models of the ``model`` parameter."""

__all__ = ['EstimatorNode', 'main']


# every input stream is read keep-all and reliable, so nothing is overwritten unseen

_MAX_WINDOWS_PER_CALL = 20
"""Windows solved in one timer tick or service call at most, so that a flood of due
windows (a long backlog after a stall) cannot keep the executor from its other work."""


def _segments(flat: list[float]) -> tuple[tuple[float, float], ...]:
    """``[a0, b0, a1, b1, ...]`` as pairs; the core config checks ``b > a``."""
    if len(flat) % 2:
        raise ValueError(
            f'segments must be a flat list of start, end pairs; got {len(flat)} numbers'
        )
    return tuple((float(flat[i]), float(flat[i + 1])) for i in range(0, len(flat), 2))


class EstimatorNode(WindowOutputs, StationInputs):
    def __init__(self) -> None:
        super().__init__('estimator')
        station_filter = self._declare_station_filter()
        win = WindowConfig(
            length=declare(
                self,
                'window_length',
                60.0,
                'Length of one estimation window [s of stamps].',
                read_only=True,
                min_value=1.0,
                max_value=3600.0,
            ),
            overlap=declare(
                self,
                'window_overlap',
                20.0,
                'Seconds shared by consecutive windows (at most half the length); the output '
                'hands over from one window to the next across the middle half of it.',
                read_only=True,
                min_value=0.0,
                max_value=1800.0,
            ),
            latency=declare(
                self,
                'latency',
                2.0,
                'Data seconds to wait past a window end before solving it (late and '
                'out-of-order measurements).',
                read_only=True,
                min_value=0.0,
                max_value=600.0,
            ),
            output_step=declare(
                self,
                'output_step',
                0.1,
                'Spacing of the published states [s]; they fall on multiples of it.',
                read_only=True,
                min_value=0.001,
                max_value=60.0,
            ),
        )
        knots = KnotConfig(
            degree=declare(
                self,
                'degree',
                4,
                'Spline degree (seed 000: 4).',
                read_only=True,
                min_value=2,
                max_value=7,
            ),
            base_spacing=declare(
                self,
                'base_spacing',
                1.0,
                'Initial knot spacing outside incomplete segments [s].',
                read_only=True,
                min_value=0.01,
                max_value=60.0,
            ),
            gap_spacing=declare(
                self,
                'gap_spacing',
                0.2,
                'Initial knot spacing inside incomplete segments [s].',
                read_only=True,
                min_value=0.01,
                max_value=60.0,
            ),
            delta_position=declare(
                self,
                'delta_position',
                0.1,
                'Sparse knot selection: position tolerance delta1 [m].',
                read_only=True,
                min_value=1e-6,
                max_value=1e4,
            ),
            delta_velocity=declare(
                self,
                'delta_velocity',
                0.05,
                'Sparse knot selection: velocity tolerance delta2 [m/s].',
                read_only=True,
                min_value=1e-6,
                max_value=1e3,
            ),
            solver=declare(
                self,
                'solver',
                'HIGHS',
                'cvxpy solver of the knot selection: HIGHS, CLARABEL, ECOS or SCS.',
                read_only=True,
            ),
            sparse=declare(
                self,
                'sparse',
                True,
                'Run the sparse (l1) knot selection; false keeps the densified knots.',
                read_only=True,
            ),
            max_spacing=declare(
                self,
                'max_knot_spacing',
                5.0,
                'Longest span [s] the knot selection may leave without a knot on an axis '
                '(knots are added on a grid of this spacing); 0 = no limit.',
                read_only=True,
                min_value=0.0,
                max_value=600.0,
            ),
        )
        self.model = declare(
            self,
            'model',
            'spline',
            "Trajectory model: 'spline' (the seed's B-spline with sparse knots), 'rocket' "
            "(seed 003's rocket-equation flight, gravity + thrust along the velocity, fitted "
            "to each window's raw measurements; Earth-centred world frames 'eci' or 'earth'; "
            "telemetry unused) or 'adjoint' (seed 003's adjoint assimilation of a free thrust "
            'profile, started from the rocket fit).',
            read_only=True,
        )
        self.stages = declare(
            self,
            'stages',
            1,
            "Burns of the rocket model (model 'rocket' or 'adjoint'): 1, 2 (a staging at an "
            'unknown time) or 0 (auto: two when one does not fit, or when a staging explains what '
            'one leaves).',
            read_only=True,
            min_value=0,
            max_value=2,
        )
        if self.model not in MODELS:
            raise ValueError(f'model must be one of {", ".join(MODELS)}; got {self.model!r}')
        knot_method = declare(
            self,
            'knot_method',
            'sparse',
            f'Knot placement: one of {", ".join(KNOT_METHODS)}.',
            read_only=True,
        )
        self.time_reference = declare(
            self,
            'time_reference',
            0.0,
            'Stamp [s] of internal time 0; 0 = the whole second of the first stamp received.',
            read_only=True,
            min_value=0.0,
        )
        segments = _segments(
            declare(
                self,
                'segments',
                [],
                'Declared incomplete segments as a flat list start0, end0, start1, ... in '
                'seconds after time_reference (added to the detected ones).',
                read_only=True,
                param_type=Parameter.Type.DOUBLE_ARRAY,
            )
        )
        if segments and self.time_reference <= 0.0:
            raise ValueError('segments are given relative to time_reference; set it (> 0)')
        self.est_cfg = EstimatorConfig(
            knots=knots,
            knot_method=knot_method,
            use_telemetry=declare(
                self,
                'use_telemetry',
                True,
                'Fuse telemetry as measurements (with its own error model); it is the rough '
                'trajectory for the knots either way.',
                read_only=True,
            ),
            gate_sigma=declare(
                self,
                'gate_sigma',
                5.0,
                'Reject measurement rows whose whitened residual exceeds this; 0 = off.',
                read_only=True,
                min_value=0.0,
                max_value=1e6,
            ),
            telemetry_velocity_error=declare(
                self,
                'telemetry_velocity_error',
                'auto',
                'Telemetry velocity error model: derivative (of the position error), separate '
                '(an error of its own: GNSS Doppler, INS, a time-tag skew) or auto (chosen per '
                'window by a score test on the velocity residuals).',
                read_only=True,
            ),
            telemetry_delays=declare(
                self,
                'telemetry_delays',
                'auto',
                'Time-tag delays of the telemetry position and velocity: auto (default: '
                'estimated in a window whose residuals ask for them, by a score test), off '
                'or on; see docs/ESTIMATOR.md.',
                read_only=True,
            ),
            move_events=declare(
                self,
                'move_events',
                True,
                'Move each event of the rough trajectory (timed by its own samples) to where '
                'the station measurements fit it best, and solve the window again.',
                read_only=True,
            ),
            doubtful_events=declare(
                self,
                'doubtful_events',
                True,
                'Without telemetry, test an event near each change of acceleration the first '
                'solution saw but did not knot; taken where the measurements ask for it.',
                read_only=True,
            ),
            event_time_uncertainty=declare(
                self,
                'event_time_uncertainty',
                True,
                "Add the uncertainty of each event's time (how well the measurements place it) "
                'to the covariance of the states around it.',
                read_only=True,
            ),
            refine_events=declare(
                self,
                'refine_events',
                False,
                'Let the knot test also insert events (the acceleration may jump there: a '
                'staging the telemetry did not show, a turn starting) where the measurements '
                'ask for one; off by default: it costs time and one reference scenario '
                '(seed003_q2) loses accuracy, see docs/ESTIMATOR.md.',
                read_only=True,
            ),
            estimate_telemetry_error=declare(
                self,
                'estimate_telemetry_error',
                True,
                'Estimate the two prior sizes of the telemetry error spline (its level and '
                'its steps between coefficients) from the data, by their evidence, and add '
                'the uncertainty of that choice to the covariance (white telemetry then '
                'counts in full); false holds both at the declared position sigma.',
                read_only=True,
            ),
            jerk_prior=declare(
                self,
                'jerk_prior',
                True,
                'A white-jerk prior on the trajectory, its density estimated from the data in '
                'every window: it bridges spans the measurements hardly determine (a turn in a '
                'GPS outage) as a Kalman smoother motion model would.',
                read_only=True,
            ),
            nonlinear_sigma=declare(
                self,
                'nonlinear_sigma',
                1.0,
                'Where three sigma of a state along its longest axis change a nearby station '
                "value to second order by more than this many of its sigmas (the row's, or "
                "the fitted value's from the state covariance if smaller), the linearised "
                'covariance no longer describes the error: it is published as its largest '
                'sigma in every direction. 0 = never.',
                read_only=True,
                min_value=0.0,
                max_value=1e6,
            ),
            gap_manoeuvre_density=declare(
                self,
                'gap_manoeuvre_density',
                300.0,
                'Density [m^2/s^5] of the manoeuvres an incomplete segment may hide (a staging '
                'or a turn the few stations there cannot show): steps of the acceleration '
                'inside every incomplete segment, a white jerk of this density, carried as '
                'consider parameters in the published state covariance (the estimate does not '
                'change). 0 = off; see docs/ESTIMATOR.md.',
                read_only=True,
                min_value=0.0,
                max_value=1e6,
            ),
            gap_manoeuvre_step=declare(
                self,
                'gap_manoeuvre_step',
                0.5,
                'Spacing [s] of the instants of those acceleration steps.',
                read_only=True,
                min_value=0.01,
                max_value=10.0,
            ),
            event_manoeuvre_density=declare(
                self,
                'event_manoeuvre_density',
                30.0,
                'Density [m^2/s^5] of the same consider term across event_manoeuvre_half_width '
                "either side of every detected event (an acceleration jump, a turn ramp's "
                'end): the detail of a manoeuvre its knots follow only approximately (a ramp '
                'end placed tenths of a second off). The estimate does not change. 0 = off.',
                read_only=True,
                min_value=0.0,
                max_value=1e6,
            ),
            event_manoeuvre_half_width=declare(
                self,
                'event_manoeuvre_half_width',
                3.0,
                'Half width [s] of the spans around detected events that carry that term.',
                read_only=True,
                min_value=0.05,
                max_value=30.0,
            ),
            unseen_manoeuvre_density=declare(
                self,
                'unseen_manoeuvre_density',
                10.0,
                'Density [m^2/s^5] of the same consider term across the spans where the '
                'telemetry has no samples (an outage): a turn or a staging there has no event '
                'found and no knots at its instants. The estimate does not change. 0 = off.',
                read_only=True,
                min_value=0.0,
                max_value=1e6,
            ),
            weak_manoeuvre_gain=declare(
                self,
                'weak_manoeuvre_gain',
                1.0,
                'Gain [s] of the same consider term around weak changes (a jerk jump j in the '
                "telemetry too small for an event: a gentle turn ramp's end): density "
                'gain * j^2 [m^2/s^5] across event_manoeuvre_half_width either side. The '
                'estimate does not change. 0 = off.',
                read_only=True,
                min_value=0.0,
                max_value=1e3,
            ),
            refine_rounds=declare(
                self,
                'refine_rounds',
                4,
                'Rounds of knot insertion where the measurements misfit the spline (a score '
                'test on the residuals), each followed by a new solve; 0 = off.',
                read_only=True,
                min_value=0,
                max_value=20,
            ),
            gate_event_rounds=declare(
                self,
                'gate_event_rounds',
                2,
                'Rounds of events put where the residual gate rejected station values '
                'clustered in time (a staging no knot follows), each event then moved to where '
                'the measurements fit it best, and followed by a new solve; 0 = off.',
                read_only=True,
                min_value=0,
                max_value=10,
            ),
            edge_gap=declare(
                self,
                'edge_gap',
                0.5,
                'A window whose station rows and telemetry stop more than this many seconds '
                'short of its start or end (a restart, the end of the data) is solved over '
                'the span they cover [s].',
                read_only=True,
                min_value=1e-3,
                max_value=1e6,
            ),
            max_chi2_dof=declare(
                self,
                'max_chi2_dof',
                1.5,
                'A window is a success only if the chi2 per degree of freedom of its fit is at '
                'most this (or 1 + 5 sqrt(2/dof) for few degrees of freedom); otherwise it is '
                'retried with safer settings and, if still inconsistent, withheld.',
                read_only=True,
                min_value=1.0,
                max_value=1e6,
            ),
            max_unconverged_decrement=declare(
                self,
                'max_unconverged_decrement',
                4.0,
                'A solve that stopped before converging is still taken if its Gauss-Newton '
                'step promises at most this much lower chi2; its covariance is then scaled by '
                '1 + that. 0 = only converged solves.',
                read_only=True,
                min_value=0.0,
                max_value=100.0,
            ),
            segments=segments,
        )
        # resolved per window against the stations in it (what 'auto' needs)
        self.bias_declaration = load_bias_declaration(
            declare(
                self,
                'bias_file',
                '',
                'Station biases to estimate with the trajectory: "" = none, "auto" = every '
                'measured field of every station (weak priors), else a YAML declaration file '
                '(see config/biases_example.yaml).',
                read_only=True,
            )
        )
        self.bias_notes: set[str] = set()
        self.flush_after = declare(
            self,
            'flush_after',
            4.0,
            'Wall seconds without any input message (measurements, telemetry, fixes) after '
            'which what is buffered is solved (end of the stream). Keep it above the '
            "triangulation node's flush_after: the tail's fixes come after that.",
            read_only=True,
            min_value=0.1,
            max_value=3600.0,
        )
        self.background = declare(
            self,
            'solve_in_background',
            False,
            'Solve windows on a worker thread, so that messages, services and /diagnostics '
            'go on during a solve (the solve then shares the interpreter with the intake and '
            'takes longer under a heavy stream); false: the intake waits while a window is '
            'solved (messages queue in the middleware), for the lowest window latency.',
            read_only=True,
        )
        self.target_id = declare(
            self,
            'target_id',
            -1,
            'Target to estimate; -1 = every target. Fixes on triangulation/fixes are taken '
            'as this target (0 if -1).',
            read_only=True,
            min_value=-1,
            max_value=2**31 - 1,
        )
        self.win_cfg = win
        self.scheduler = WindowScheduler(win)
        self.buffer = ObservationBuffer()
        self.previous: dict[int, TargetSolution] = {}
        self.counts: Counter[str] = Counter()
        self.last: dict[str, object] = {}
        self.last_ok = True
        self.last_data = time.monotonic()
        self.flushed = True
        self._flush_windows = 0  # windows solved since the stream went silent
        history = qos.window_stream(
            declare(
                self,
                'window_history',
                16,
                'Windows (and their residual statistics) kept for a reader that (re)joins: a '
                'results node restarted while fewer windows than this went out gets every one '
                'it missed, those in flight when it died included.',
                read_only=True,
                min_value=1,
                max_value=1000,
            )
        )
        self.window_pub = self.create_publisher(PointCloud2, 'estimator/window_states', history)
        self.residual_pub = self.create_publisher(
            DiagnosticArray, 'estimator/window_residuals', history
        )
        self.residuals_after: float | None = None  # end of the last window reported
        self.bias_pub = self.create_publisher(DiagnosticArray, 'trajectory/biases', qos.LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', qos.DIAGNOSTICS)
        self.create_subscription(
            Odometry,
            'telemetry/state',
            lambda m: self._guarded('telemetry', self._on_telemetry, m),
            qos.MEASUREMENTS_SUB,
        )
        self.create_subscription(
            PoseWithCovarianceStamped,
            'triangulation/fixes',
            lambda m: self._guarded('fix', self._on_fix, m),
            qos.MEASUREMENTS_SUB,
        )
        self.create_service(Trigger, '~/solve', self._on_solve)
        self._start_station_inputs(station_filter, self.time_reference)
        self.worker = SolveWorker(
            self,
            lambda: self._guarded('tick', self._tick),
            # cvxpy and the LP solver loaded while the first window's data come in
            prepare=lambda: (
                load_solver(self.est_cfg.knots.solver)
                if self.model == 'spline' and self.est_cfg.knot_method == 'sparse'
                else None
            ),
        )
        self.create_timer(0.2, lambda: self._guarded('tick', self._tick))
        diagnostics_timer(self, self._publish_diagnostics)
        self.get_logger().info(
            f'estimating in {win.length:g} s windows overlapping {win.overlap:g} s '
            f'(latency {win.latency:g} s, knots {knot_method}) from {self._stations_text()}'
        )
        # journal_dir: replays what a killed run had accepted, then journals every input
        self.journal = EstimatorJournal(self)

    # -- callbacks -----------------------------------------------------------------
    def _add_pose(self, sid: str, st: StationStateSample) -> None:
        self.buffer.add_pose(sid, st.time, st.position, st.velocity, st.rotation, st.moving)

    def _add_measurements(self, sid: str, batch: MeasurementBatch) -> None:
        if self.target_id >= 0:
            keep = batch.target_id == self.target_id
            if not np.all(keep):
                self.counts['other_target'] += int((~keep).sum())
        else:
            keep = np.ones(batch.time.size, dtype=bool)
        self.buffer.add_measurements(
            sid,
            batch.fields,
            batch.time[keep],
            batch.target_id[keep],
            batch.values[keep],
            batch.sigmas[keep],
        )
        self.last_data = time.monotonic()
        self.flushed = False

    def _on_telemetry(self, msg: Odometry) -> None:
        self.counts['telemetry_messages'] += 1
        ns = self._stamp_of(msg, 'telemetry')
        if ns is None:
            return
        try:
            s = odometry_to_target_state(msg, self._timebase(ns), check=True)
        except ValueError as exc:
            self._reject('invalid_telemetry', f'telemetry rejected: {exc}')
            return
        if self.target_id >= 0 and s.target_id != self.target_id:
            return
        if self.world_frame and msg.header.frame_id != self.world_frame:
            self._reject(
                'frame_mismatch',
                f'telemetry in frame {msg.header.frame_id!r}, expected {self.world_frame!r}',
            )
            return
        if not self._admit({s.target_id}):
            self._reject('too_many_targets', f'telemetry of target {s.target_id} dropped')
            return
        if self._in_time('telemetry', ns, lambda: self._add_telemetry(s)):
            self._add_telemetry(s)

    def _add_telemetry(self, s: TargetStateSample) -> None:
        self.last_data = time.monotonic()
        try:
            self.buffer.add_telemetry(
                s.target_id,
                s.time,
                s.position,
                s.velocity,
                # an unfilled (0 or -1) variance gives sigma 0, which the buffer rejects
                np.sqrt(np.clip(np.diag(s.position_cov), 0.0, None)),
                np.sqrt(np.clip(np.diag(s.velocity_cov), 0.0, None)),
            )
        except ValueError as exc:
            self._reject('invalid_telemetry', f'telemetry rejected: {exc}')

    def _on_fix(self, msg: PoseWithCovarianceStamped) -> None:
        ns = self._stamp_of(msg, 'fix')
        if ns is None:
            return
        try:
            t, p, c = msg_to_fix(msg, self._timebase(ns))
        except ValueError as exc:
            self._reject('invalid_fix', f'fix rejected: {exc}')
            return
        if self.world_frame and msg.header.frame_id != self.world_frame:
            self._reject(
                'frame_mismatch',
                f'fix in frame {msg.header.frame_id!r}, expected {self.world_frame!r}',
            )
            return
        if self._in_time('fixes', ns, lambda: self._add_fix(t, p, c)):
            self._add_fix(t, p, c)

    def _add_fix(self, t: float, p: np.ndarray, c: np.ndarray) -> None:
        self.last_data = time.monotonic()  # the tail's fixes follow the measurements
        try:
            self.buffer.add_fix(max(self.target_id, 0), t, p, c)
        except ValueError as exc:
            self._reject('invalid_fix', f'fix rejected: {exc}')

    def _on_solve(self, _req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        spans = self._solve_due(final=True, block=True)
        solved = [s for s, ok in spans if ok]
        resp.success = bool(solved)
        if not spans:
            resp.message = 'nothing new to solve since the last window'
        else:
            resp.message = ', '.join(
                f'[{a:.3f}, {b:.3f}] {"solved" if ok else "failed"}' for (a, b), ok in spans
            )
        return resp

    # -- windows -------------------------------------------------------------------
    def _tick(self) -> None:
        """On the timer and whenever the worker finished a solve: publish it, start the
        next due window; at the end of the stream (silence) every window there is."""
        spans = self._solve_due(final=False)
        if spans and not self.background:
            # messages waited in the queues while we solved: that was not silence
            self.last_data = time.monotonic()
        if self.flushed or not self._silent():
            return
        last = self._solve_due(final=True)
        self._flush_windows += len(spans) + len(last)
        # done once nothing is in flight and nothing was left for the next tick
        self.flushed = not self.worker.busy and len(last) < _MAX_WINDOWS_PER_CALL
        if self.flushed and self._flush_windows:
            self.get_logger().info(
                f'no measurements for {self.flush_after:g} s: solved '
                f'{self._flush_windows} window(s) up to the newest stamp'
            )
            self._flush_windows = 0

    def _silent(self) -> bool:
        """No input for ``flush_after`` wall seconds: the end of the stream."""
        return time.monotonic() - self.last_data >= self.flush_after

    def _on_time_reset(self) -> str:
        """Time went back (see StationInputs): solve what is buffered as at the end of a
        stream, then start with an empty buffer and no previous window; counters carry on."""
        spans = self._solve_due(final=True, block=True)
        counts = self.buffer.counts
        self.buffer = self.journal.fresh_buffer()  # the journal starts afresh too
        self.buffer.counts.update(counts)
        self.scheduler = WindowScheduler(self.win_cfg)
        self.previous = {}
        self.residuals_after = None
        self.flushed = True
        return f'{len(spans)} window(s) solved up to the old newest stamp'

    def _solve_due(self, final: bool, block: bool = False) -> list[tuple[Span, bool]]:
        """Finish the window the worker solved (publish it) and hand it the next one that
        is due (every one there is with ``final``). Without ``block`` this returns while a
        solve runs (the worker wakes the executor when it is done: :meth:`_tick`);
        with it, it waits for each solve (the ~/solve service, a time reset)."""
        out: list[tuple[Span, bool]] = []
        if self.timebase is None:
            return out
        latest = self.buffer.latest_time() if final else self._horizon()
        block = block or not self.background
        while len(out) < _MAX_WINDOWS_PER_CALL:
            with self._working() if block else contextlib.nullcontext():
                job = self.worker.take(block)
            if job is not None:
                out.append((job.context[0], self._finish(job)))
                self.buffer.prune(self.scheduler.keep_from)
                continue
            if self.worker.busy:
                break
            start = -math.inf if self.scheduler.next_t0 is None else self.scheduler.next_t0
            first = self.buffer.first_time(after=start)
            span = self.scheduler.next_window(first, latest, final)
            if span is None:
                break
            self._begin(span, self.timebase)
        else:  # the rest waits for the next tick: timers, services and signals go on
            self.get_logger().warning(
                f'{len(out)} windows solved in one go; the rest follows on the next tick'
            )
        return out

    def _horizon(self) -> float:
        """Data time every delivering stream has reached (see StationInputs): a window is
        due once this passes its end by ``latency``, so a topic that fell behind while we
        were solving is waited for instead of being cut off."""
        if self._awaiting_first_fix():
            return -math.inf
        latest = self.buffer.latest_time()
        live = self._delivering()
        return min(latest, *live.values()) if live and math.isfinite(latest) else latest

    def _awaiting_first_fix(self) -> bool:
        """Without telemetry or a previous window, a window's rough trajectory is the
        triangulation node's fixes. While that node is up (a publisher on
        ``triangulation/fixes``) but has not sent one yet (it started late or is starved
        of CPU), windows wait for it rather than fail; the end of the stream solves them
        regardless."""
        if self.previous:
            return False
        for stream in ('telemetry', 'fixes'):
            gen = self._streams.get(stream)
            if gen is not None and gen[0] == self._generation:
                return False
        return self.count_publishers('triangulation/fixes') > 0

    def _begin(self, span: Span, tb: TimeBase) -> None:
        """Gather the window's inputs and hand its core call to the worker."""
        t0, t1 = span
        obs = self.buffer.observations(t0, t1)
        withheld = Counter(self.buffer.withheld)
        previous = self.previous or None
        more_after = bool(self.buffer.latest_time() > t1 + COVERED_S)  # a window follows
        self.worker.submit(
            (span, tb, obs, withheld),
            lambda: self._core(obs, t0, t1, previous, more_after),
            here=not self.background,
        )

    def _core(
        self,
        obs: Observations,
        t0: float,
        t1: float,
        previous: dict[int, TargetSolution] | None,
        more_after: bool = False,
    ) -> Estimate:
        """The window's one core call (on the worker thread)."""
        ids = None if self.target_id < 0 else [self.target_id]
        cfg = self._window_config(obs)
        if self.model != 'spline':
            return dynamics_window(
                obs,
                t0,
                t1,
                self.model,
                ids,
                cfg.biases,
                RocketConfig.for_frame(self.world_frame, stages=self.stages),
            )
        return estimate(obs, t0, t1, cfg, ids, previous, more_after=more_after)

    # -- biases --------------------------------------------------------------------
    def _window_config(self, obs: Observations) -> EstimatorConfig:
        """The estimator settings of one window: the bias declaration resolved against the
        stations that have rows in it (and their fields)."""
        if self.bias_declaration.empty:
            return self.est_cfg
        biases, notes = self.bias_declaration.resolve(station_fields(obs))
        for note in notes:
            if note not in self.bias_notes:  # once per declaration entry
                self.bias_notes.add(note)
                self.get_logger().warning(note)
        return replace(self.est_cfg, biases=biases)

    # -- diagnostics ---------------------------------------------------------------
    def _reject(self, key: str, text: str, n: int = 1) -> None:
        self.counts[key] += n
        self.get_logger().warning(f'{text} ({self.counts[key]} so far)', throttle_duration_sec=5.0)

    def _publish_diagnostics(self) -> None:
        counts = Counter(self.buffer.counts)
        counts.update(self.counts)
        solved, failed = counts.get('windows_solved', 0), counts.get('windows_failed', 0)
        bad = counts.get('invalid_messages', 0) + counts.get('invalid_state', 0)
        level = DiagnosticStatus.OK if self.last_ok and not bad else DiagnosticStatus.WARN
        values: dict[str, object] = {
            'windows_solved': solved,
            'windows_failed': failed,
            **{k: v for k, v in sorted(counts.items()) if not k.startswith('windows_')},
            **self.last,
            'solving_window': self._solving_text(),
            'newest_data_time_s': self.buffer.latest_time(),
            'time_reference_s': ''
            if self.timebase is None
            else format_stamp(self.timebase.ref_ns, 0.0),
            **{f'buffer_{k}': v for k, v in self.buffer.sizes().items()},
            'stations': ' '.join(sorted(self.subs)),
            'stations_without_state': ' '.join(self.buffer.stations_without_pose()),
        }
        status = diagnostic_status(
            'estimator: windows',
            level,
            f'{solved} windows solved, {failed} failed'
            + (f', {bad} invalid messages' if bad else ''),
            values,
        )
        self.diag_pub.publish(diagnostic_array(self.get_clock().now().to_msg(), [status]))


def main(args: list[str] | None = None) -> None:
    run_node(EstimatorNode, args)


if __name__ == '__main__':
    main()
