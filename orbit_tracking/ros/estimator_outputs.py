"""What the ``estimator`` node publishes for a window its solve worker finished.

:class:`WindowOutputs` is a part of :class:`~orbit_tracking.ros.estimator_node.EstimatorNode`
(its base class, holding no state of its own): a solved window's states with covariance on
``estimator/window_states``, its station biases on ``trajectory/biases``, its residual
statistics on ``estimator/window_residuals``, its INFO line and status values; a failed
window's ERROR line and count. It uses the node's publishers, counters and settings.
"""

from __future__ import annotations

import time
import traceback
from collections import Counter
from typing import Any

import numpy as np

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.residuals import window_residual_stats
from orbit_tracking.core.estimation.results import Estimate
from orbit_tracking.core.estimation.windows import Span, output_times
from orbit_tracking.ros.conversions import (
    TimeBase,
    biases_to_diagnostics,
    window_residuals_to_msg,
    window_states_to_cloud,
)
from orbit_tracking.ros.solve_worker import Job

__all__ = ['WindowOutputs']


class WindowOutputs:
    """The estimator node's outputs of a finished window (a base class of the node)."""

    # set by EstimatorNode.__init__
    counts: Counter[str]
    last: dict[str, object]
    last_ok: bool
    previous: dict[int, Any]
    residuals_after: float | None
    model: str
    world_frame: str
    win_cfg: Any
    worker: Any
    window_pub: Any
    residual_pub: Any
    bias_pub: Any
    # and from the node: get_logger() (rclpy), _reject(key, text)

    def _finish(self, job: Job) -> bool:
        """Publish a solved window (or count its failure); whether it was published."""
        span, tb, obs, withheld = job.context
        t0, t1 = span
        wall = job.started
        try:
            est = job.future.result()
            if not est.success:  # inconsistent or not converged: withheld, never final
                return self._failed(span, wall, f'not published: {est.message}', withheld)
            self._publish_window(est, tb)
            self._publish_biases(est, tb)
            self._publish_residuals(est, obs, tb)
        except OrbitTrackingError as exc:
            return self._failed(span, wall, f'{type(exc).__name__}: {exc}', withheld)
        except Exception as exc:  # a bug in one window must not take the node down
            self.get_logger().error(''.join(traceback.format_exception(exc)))
            return self._failed(
                span, wall, f'internal error {type(exc).__name__}: {exc}', withheld
            )
        dt = time.monotonic() - wall
        if self.model == 'spline':  # a rocket flight cannot seed the next window's spline
            self.previous = dict(est.targets)
        self.counts['windows_solved'] += 1
        self._remember(span, est, dt, withheld)
        used = sum(v for k, v in est.used.items() if not k.startswith('telemetry_'))
        rejected = sum(est.rejected.values())
        text = (
            f'window [{t0:.2f}, {t1:.2f}] s (stamps {tb.to_ns(t0) * 1e-9:.2f}-'
            f'{tb.to_ns(t1) * 1e-9:.2f}): {est.message}; {est.iterations} GN iterations, '
            f'chi2/dof {est.chi2_dof:.3f}, {used} measured values used, {rejected} rejected'
            + (f', {sum(withheld.values())} rows without station state' if withheld else '')
            + f', {est.n_parameters} parameters; solved in {dt:.2f} s '
            f'(knots {est.knot_time:.2f} s, Gauss-Newton {est.solve_time:.2f} s)'
        )
        self.get_logger().info(text)
        return True

    def _failed(self, span: Span, wall: float, reason: str, withheld: Counter[str]) -> bool:
        self.counts['windows_failed'] += 1
        self.last_ok = False
        self.last = {
            'last_window_start': span[0],
            'last_window_end': span[1],
            'last_window_status': f'failed: {reason}',
            'last_solve_wall_s': time.monotonic() - wall,
            **{f'withheld_no_station_state_{s}': n for s, n in sorted(withheld.items())},
        }
        self.get_logger().error(
            f'window [{span[0]:.2f}, {span[1]:.2f}] s failed ({reason}); '
            f'{self.counts["windows_failed"]} failed so far'
        )
        return False

    def _remember(self, span: Span, est: Estimate, dt: float, withheld: Counter[str]) -> None:
        self.last_ok = est.success
        self.last = {
            'last_window_start': span[0],
            'last_window_end': span[1],
            'last_window_status': est.message,
            'last_iterations': est.iterations,
            'last_halvings': est.halvings,
            'last_chi2_dof': est.chi2_dof,
            'last_condition': est.condition,
            'last_parameters': est.n_parameters,
            'last_solve_wall_s': dt,
            'last_knot_time_s': est.knot_time,
            'last_gauss_newton_time_s': est.solve_time,
            **{f'used_{s}': n for s, n in sorted(est.used.items())},
            **{f'rejected_{s}_{why}': n for (s, why), n in sorted(est.rejected.items())},
            **{f'withheld_no_station_state_{s}': n for s, n in sorted(withheld.items())},
        }

    def _publish_window(self, est: Estimate, tb: TimeBase) -> None:
        times, tids, states, covs = [], [], [], []
        for tid, sol in sorted(est.targets.items()):
            t = output_times(max(est.t0, sol.t0), min(est.t1, sol.t1), self.win_cfg.output_step)
            if t.size == 0:
                continue
            x, c = sol.states(t)
            var = np.diagonal(c, axis1=1, axis2=2)
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(c)) and np.all(var >= 0.0)):
                raise OrbitTrackingError(
                    f'target {tid}: the solution has non-finite states or negative variances '
                    f'(smallest {np.nanmin(var):.3g}): not published'
                )
            times.append(t)
            tids.append(np.full(t.size, tid, dtype=np.uint32))
            states.append(x)
            covs.append(c)
        if not times:
            raise OrbitTrackingError('window holds no output time')
        self.window_pub.publish(
            window_states_to_cloud(
                self.world_frame or 'earth',
                est.t0,
                np.concatenate(times),
                np.concatenate(tids),
                np.vstack(states),
                np.concatenate(covs),
                tb,
                t1=est.t1,
            )
        )

    def _publish_residuals(self, est: Estimate, obs: Observations, tb: TimeBase) -> None:
        """``estimator/window_residuals``: per-station whitened-residual statistics of the
        rows after the previous window's end (so that summing windows counts each
        measurement once); never fails the window."""
        after = self.residuals_after
        if after is not None and not est.t0 < after < est.t1:
            after = None  # no overlap (a pause), or time went back
        try:
            stats = window_residual_stats(est, obs, after)
            self.residual_pub.publish(window_residuals_to_msg(stats, est.t0, est.t1, after, tb))
        except Exception as exc:  # statistics are a report: the window stands without them
            self._reject('residuals_failed', f'window residuals not published: {exc!r}')
        self.residuals_after = est.t1

    def _publish_biases(self, est: Estimate, tb: TimeBase) -> None:
        """``trajectory/biases`` (transient local): the window's station biases, if any."""
        if est.biases:
            self.bias_pub.publish(biases_to_diagnostics(est.biases, est.t0, est.t1, tb))

    def _solving_text(self) -> str:
        """The window on the worker and for how long, or '' when it is idle."""
        job = self.worker.job
        if job is None:
            return ''
        (t0, t1), *_ = job.context
        return f'[{t0:.2f}, {t1:.2f}] s for {job.running_s:.1f} s'
