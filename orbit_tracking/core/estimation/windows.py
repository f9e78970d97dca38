"""Sliding estimation windows: which spans to solve, solving them in turn, and stitching
the overlapping window solutions into one trajectory.

A pass is estimated in windows of ``length`` seconds that overlap by ``overlap`` seconds:
window ``k + 1`` starts at ``t1_k - overlap``. Each window is solved with the previous
window's solution as its start (``previous=`` of
:func:`~orbit_tracking.core.estimation.estimator.estimate`). The live node solves a window once the
newest stamp is ``latency`` seconds past its end; at the end of the stream the last
window is cut at the newest stamp.

Where two windows overlap the output hands over from the earlier solution ``a`` to the
later one ``b`` across the middle half of the overlap ``[s + d/4, e - d/4]`` (``d = e - s``):

    x(t) = w(t) x_a(t) + (1 - w(t)) x_b(t),
    P(t) = w(t) P_a(t) + (1 - w(t)) P_b(t) + w(t) (1 - w(t)) (x_a - x_b)(x_a - x_b)^T

with ``w`` falling linearly from 1 to 0. The covariance mix bounds the covariance of the
blend for any correlation between the two windows (``Cov(w a + (1-w) b) <= w Pa + (1-w) Pb``
by convexity), so it is conservative; the last term is the spread of the mixture (its
second moment about the blend), so two windows that disagree by more than their
covariances say so where they hand over (a model chosen differently in each: silent
states of the 35-draw robustness families went from 306 to 300, aircraft, and 190 to
181, ascent). Outside the hand-over a single
window is used.

Times are float seconds relative to a TimeBase, as everywhere in the core.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import OrbitTrackingError
from orbit_tracking.core.estimation.config import EstimatorConfig
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.core.estimation.results import Estimate, TargetSolution
from orbit_tracking.core.time import format_stamp, parse_stamp

__all__ = [
    'TRAJECTORY_CSV_COLUMNS',
    'Span',
    'WindowConfig',
    'WindowScheduler',
    'blend',
    'handover_span',
    'handover_weights',
    'output_times',
    'plan_windows',
    'read_trajectory_csv',
    'solve_windows',
    'stitch',
    'write_trajectory_csv',
]

FloatArray = NDArray[np.float64]
Span = tuple[float, float]

TRAJECTORY_CSV_COLUMNS = (
    'time',
    'x',
    'y',
    'z',
    'vx',
    'vy',
    'vz',
    'sx',
    'sy',
    'sz',
    'svx',
    'svy',
    'svz',
)
"""Columns of ``trajectory.csv`` (docs/CONTRACT.md)."""


@dataclass(frozen=True)
class WindowConfig:
    """Window settings of the sliding estimation.

    Attributes
    ----------
    length : float
        Window length [s].
    overlap : float
        Seconds shared by consecutive windows, at most half the length (so that no
        instant lies in more than two regular windows).
    latency : float
        Data seconds to wait past a window's end before solving it (late and
        out-of-order measurements).
    output_step : float
        Spacing [s] of the output times; outputs are the multiples of it (in TimeBase
        seconds) inside the covered span.
    """

    length: float = 60.0
    overlap: float = 20.0
    latency: float = 2.0
    output_step: float = 0.1

    def __post_init__(self) -> None:
        for name in ('length', 'overlap', 'latency', 'output_step'):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f'window {name} must be finite; got {v}')
        if self.length <= 0.0:
            raise ValueError(f'window length must be > 0 s; got {self.length}')
        if not 0.0 <= self.overlap <= 0.5 * self.length:
            raise ValueError(
                f'window overlap must lie in [0, length / 2] = [0, {0.5 * self.length:g}] s; '
                f'got {self.overlap}'
            )
        if self.latency < 0.0:
            raise ValueError(f'window latency must be >= 0 s; got {self.latency}')
        if not 0.0 < self.output_step <= self.length:
            raise ValueError(
                f'output_step must lie in (0, length] = (0, {self.length:g}] s; '
                f'got {self.output_step}'
            )


class WindowScheduler:
    """Decides the next window span from the data time span seen so far.

    Rules:

    * the first window starts at the first data time;
    * window ``k + 1`` starts at ``t1_k - overlap``, unless the data resume only more than
      half a window after that (a pause between passes): then it starts at the first new
      data;
    * a full window ``[t0, t0 + length]`` is due once the newest data time has passed its
      end by ``latency``;
    * at the end of the stream (or when asked to solve what is there) the window is cut at
      the newest data time; its start is pulled back (never before ``t1_k - length / 2``)
      so that it is at least half a window long when the data allow;
    * every window handed out ends after the previous one and moves the next start
      forward; when float rounding would not allow that (data times so large that adding a
      window length changes nothing), no window is handed out, so a caller looping until
      ``None`` always ends.

    Parameters
    ----------
    cfg : WindowConfig
    """

    def __init__(self, cfg: WindowConfig | None = None) -> None:
        self.cfg = cfg or WindowConfig()
        self.next_t0: float | None = None
        """Start of the next window (None before the first one)."""
        self.last: Span | None = None
        """The last window handed out."""

    def next_window(self, first: float, latest: float, final: bool = False) -> Span | None:
        """The next window to solve now, or None.

        Parameters
        ----------
        first : float
            Earliest data time not before :attr:`next_t0` (the earliest data time at all
            before the first window).
        latest : float
            Newest data time.
        final : bool
            The stream has ended (or the caller wants what is there solved now): a window
            is cut at ``latest`` instead of waiting for ``length + latency``.
        """
        if not (math.isfinite(first) and math.isfinite(latest)) or latest < first:
            return None
        c = self.cfg
        contiguous = self.next_t0 is not None and first < self.next_t0 + 0.5 * c.length
        t0 = self.next_t0 if contiguous and self.next_t0 is not None else first
        t1 = t0 + c.length
        if not t1 - t0 > 0.5 * c.length:
            return None  # times so large that a window length is lost in rounding
        if latest >= t1 + (0.0 if final else c.latency):
            return self._hand_out((t0, t1))
        if not final or (self.last is not None and latest <= self.last[1]):
            return None
        floor = self.last[1] - 0.5 * c.length if contiguous and self.last is not None else first
        t0 = min(t0, max(latest - 0.5 * c.length, floor))
        if not latest > t0:
            return None
        return self._hand_out((t0, latest))

    @property
    def keep_from(self) -> float:
        """Earliest time a later window may still start (data before it can be let go):
        the last window's end minus half a window (see the pull-back rule)."""
        return -math.inf if self.last is None else self.last[1] - 0.5 * self.cfg.length

    def _hand_out(self, span: Span) -> Span | None:
        """Record ``span`` as handed out; None (nothing handed out) if it would not move
        the windows forward, so that no caller can loop on the same window."""
        if self.last is not None and not span[1] > self.last[1]:
            return None
        nxt = span[1] - self.cfg.overlap
        if self.next_t0 is not None and not nxt > self.next_t0:
            return None
        self.last = span
        self.next_t0 = nxt
        return span


def plan_windows(times: ArrayLike, cfg: WindowConfig | None = None) -> list[Span]:
    """Every window over a finished data set (what the live node would solve).

    Parameters
    ----------
    times : array_like, shape (n,)
        Data times [s] (any order).
    """
    t = np.sort(np.asarray(times, dtype=np.float64).ravel())
    t = t[np.isfinite(t)]
    if t.size == 0:
        return []
    sched = WindowScheduler(cfg)
    latest = float(t[-1])
    spans: list[Span] = []
    while True:
        start = -math.inf if sched.next_t0 is None else sched.next_t0
        i = int(np.searchsorted(t, start, side='left'))
        if i >= t.size:
            break
        span = sched.next_window(float(t[i]), latest, final=True)
        if span is None:
            break
        spans.append(span)
    return spans


def _data_times(obs: Observations) -> FloatArray:
    ts = [s.table.time for s in obs.stations if len(s.table)]
    return np.concatenate(ts) if ts else np.zeros(0)


def solve_windows(
    obs: Observations,
    cfg_est: EstimatorConfig | None = None,
    cfg_win: WindowConfig | None = None,
    progress: Callable[[int, int, Span, Estimate | OrbitTrackingError], None] | None = None,
    target_ids: Sequence[int] | None = None,
) -> list[Estimate]:
    """Solve every window of ``obs`` in time order (the offline counterpart of the node).

    Each window starts from the previous successful window's solution (``previous=``).
    A window that cannot be solved (any :class:`OrbitTrackingError`) is skipped; a window
    that is not a success is returned (its ``success`` False) but the next one does not
    start from it.

    Parameters
    ----------
    obs : Observations
    cfg_est : EstimatorConfig
    cfg_win : WindowConfig
    progress : callable, optional
        ``progress(index, n_windows, span, estimate_or_error)`` after each window.
    target_ids : sequence of int, optional
        Targets to estimate (default: every target with measurements in a window).

    Returns
    -------
    list of Estimate
        The solved windows, in time order.
    """
    spans = plan_windows(_data_times(obs), cfg_win)
    out: list[Estimate] = []
    previous: dict[int, TargetSolution] = {}
    for i, (t0, t1) in enumerate(spans):
        result: Estimate | OrbitTrackingError
        try:
            result = estimate(obs, t0, t1, cfg_est, target_ids, previous or None)
        except OrbitTrackingError as exc:
            result = exc
        else:
            out.append(result)
            if result.success:  # a failed window is no start for the next
                previous = dict(result.targets)
        if progress is not None:
            progress(i, len(spans), (t0, t1), result)
    return out


def output_times(t0: float, t1: float, step: float) -> FloatArray:
    """The multiples of ``step`` in [t0, t1] (empty if none)."""
    if not step > 0.0:
        raise ValueError(f'output step must be > 0; got {step}')
    k0 = math.ceil(t0 / step - 1e-9)
    k1 = math.floor(t1 / step + 1e-9)
    if k1 < k0:
        return np.zeros(0)
    return np.arange(k0, k1 + 1, dtype=np.float64) * step


def handover_span(a: Span, b: Span) -> Span | None:
    """Middle half ``[s + d/4, e - d/4]`` of the overlap ``[s, e]`` of consecutive spans
    ``a``, ``b`` (``s = b[0]``, ``e = min(a[1], b[1])``, ``d = e - s``): where the output
    hands over from ``a`` to ``b``. None if they do not overlap."""
    s, e = b[0], min(a[1], b[1])
    if not e > s:
        return None
    d = e - s
    return (s + 0.25 * d, e - 0.25 * d)


def handover_weights(spans: Sequence[Span], t: ArrayLike) -> FloatArray:
    """Weights (n_spans, m) of the window solutions at times ``t``.

    Spans must be sorted by start. The weights of each time sum to 1 wherever some span
    covers it (0 elsewhere); between consecutive overlapping spans they change linearly
    across the middle half of the overlap (see the module docstring).
    """
    tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
    n = len(spans)
    w = np.zeros((n, tt.size))
    inside = np.zeros((n, tt.size), dtype=bool)
    for k, (a0, a1) in enumerate(spans):
        inside[k] = (tt >= a0 - 1e-9) & (tt <= a1 + 1e-9)
        wk = np.ones(tt.size)
        up = handover_span(spans[k - 1], spans[k]) if k > 0 else None
        if up is not None:
            u0, u1 = up
            wk *= np.clip((tt - u0) / max(u1 - u0, 1e-12), 0.0, 1.0)
        down = handover_span(spans[k], spans[k + 1]) if k + 1 < n else None
        if down is not None:
            d0, d1 = down
            wk *= np.clip((d1 - tt) / max(d1 - d0, 1e-12), 0.0, 1.0)
        w[k] = np.where(inside[k], wk, 0.0)
    total = w.sum(axis=0)
    # unusual layouts (a window inside another, three-way overlaps): equal shares
    lost = (total <= 0.0) & inside.any(axis=0)
    w[:, lost] = inside[:, lost]
    total = w.sum(axis=0)
    return np.divide(w, total, out=np.zeros_like(w), where=total > 0.0)


def stitch(
    estimates: Sequence[Estimate], times: ArrayLike, target_id: int | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One trajectory from overlapping window solutions.

    Parameters
    ----------
    estimates : sequence of Estimate
        Window solutions (any order); those that are not a success are left out (their
        span is missing from the trajectory unless another window covers it).
    times : array_like, shape (m,)
        Requested output times [s]; those no window covers are left out.
    target_id : int, optional
        Default: the lowest target id solved in any window.

    Returns
    -------
    times : ndarray, shape (k,)
        The requested times covered by a window.
    x : ndarray, shape (k, 6)
        World position [m] and velocity [m/s]; blended as in the module docstring (the
        blended velocity leaves out the tiny ``(x_a - x_b) dw/dt`` term).
    cov : ndarray, shape (k, 6, 6)
        ``sum w_k (P_k + (x_k - x)(x_k - x)^T)``.
    """
    estimates = [e for e in estimates if e.success]  # a failed window is not published
    if target_id is None:
        ids = sorted({tid for e in estimates for tid in e.targets})
        if not ids:
            return np.zeros(0), np.zeros((0, 6)), np.zeros((0, 6, 6))
        target_id = ids[0]
    sols = sorted(
        (e.targets[target_id] for e in estimates if target_id in e.targets),
        key=lambda s: (s.t0, s.t1),
    )
    # evaluate strictly inside the spline span (rounding at the ends)
    return blend(
        [(s.t0, s.t1) for s in sols],
        [partial(_clipped_states, s) for s in sols],
        times,
    )


def _clipped_states(sol: TargetSolution, t: FloatArray) -> tuple[FloatArray, FloatArray]:
    return sol.states(np.clip(t, sol.t0, sol.t1))


def blend(
    spans: Sequence[Span],
    states: Sequence[Callable[[FloatArray], tuple[FloatArray, FloatArray]]],
    times: ArrayLike,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Blend window solutions with the hand-over weights (:func:`handover_weights`).

    The blend of :func:`stitch`, for solutions given as functions: the offline tool
    evaluates spline solutions, the live results node looks up the sampled states of
    ``estimator/window_states``.

    Parameters
    ----------
    spans : sequence of Span
        Window spans ``(t0, t1)`` [s], sorted by start.
    states : sequence of callable
        ``states[k](t)`` gives window ``k``'s states (m, 6) and covariances (m, 6, 6) at
        times ``t`` (m,) inside its span; only called where its weight is positive.
    times : array_like, shape (m,)
        Requested times [s]; those no span covers are left out.

    Returns
    -------
    times : ndarray, shape (k,)
        The requested times covered by a span.
    x : ndarray, shape (k, 6)
        ``sum w_k x_k``: position [m] and velocity [m/s] (the blended velocity leaves out
        the tiny ``(x_a - x_b) dw/dt`` term).
    cov : ndarray, shape (k, 6, 6)
        ``sum w_k (P_k + (x_k - x)(x_k - x)^T)``: the mixture's second moment about ``x``.
    """
    if len(states) != len(spans):
        raise ValueError(
            f'blend needs one states function per span; got {len(states)} for {len(spans)} spans'
        )
    tt = np.atleast_1d(np.asarray(times, dtype=np.float64))
    w = handover_weights(spans, tt)
    covered = w.sum(axis=0) > 0.0
    tt, w = tt[covered], w[:, covered]
    x = np.zeros((tt.size, 6))
    cov = np.zeros((tt.size, 6, 6))
    parts = []
    for k, fk in enumerate(states):
        use = w[k] > 0.0
        if not np.any(use):
            continue
        xk, pk = fk(tt[use])
        x[use] += w[k, use, None] * xk
        cov[use] += w[k, use, None, None] * pk
        parts.append((k, use, xk))
    for k, use, xk in parts:  # the mixture's spread: windows that disagree say so
        d = xk - x[use]
        cov[use] += w[k, use, None, None] * d[:, :, None] * d[:, None, :]
    return tt, x, cov


def write_trajectory_csv(
    path: str | Path, times: ArrayLike, x: ArrayLike, cov: ArrayLike, ref_ns: int = 0
) -> int:
    """Write ``trajectory.csv`` (columns :data:`TRAJECTORY_CSV_COLUMNS`).

    Parameters
    ----------
    times : array_like, shape (m,)
        TimeBase seconds; written as the stamp ``ref_ns + t`` in decimal seconds with all
        nine digits exact.
    x : array_like, shape (m, 6)
        World position [m] and velocity [m/s].
    cov : array_like, shape (m, 6, 6)
        Their covariance; the ``s*`` columns are the square roots of its diagonal.

    Returns
    -------
    int
        Rows written.
    """
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    xs = np.asarray(x, dtype=np.float64)
    cs = np.asarray(cov, dtype=np.float64)
    m = t.size
    if xs.shape != (m, 6) or cs.shape != (m, 6, 6):
        raise ValueError(
            f'trajectory needs x (m, 6) and cov (m, 6, 6) for {m} times; got {xs.shape} '
            f'and {cs.shape}'
        )
    sig = np.sqrt(np.clip(np.diagonal(cs, axis1=1, axis2=2), 0.0, None))
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(TRAJECTORY_CSV_COLUMNS)
        for i in range(m):
            w.writerow(
                [
                    format_stamp(ref_ns, float(t[i])),
                    *(f'{v:.6f}' for v in xs[i, :3]),
                    *(f'{v:.9f}' for v in xs[i, 3:]),
                    *(f'{v:.9g}' for v in sig[i]),
                ]
            )
    return m


def read_trajectory_csv(path: str | Path) -> dict[str, NDArray[Any]]:
    """Columns of a ``trajectory.csv`` as float arrays, plus ``stamp_ns`` (exact integer
    nanoseconds of ``time``), ``state`` (m, 6) and ``sigma`` (m, 6).

    Raises
    ------
    ValueError
        The header is not exactly :data:`TRAJECTORY_CSV_COLUMNS`.
    """
    with open(path, newline='') as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or tuple(header) != TRAJECTORY_CSV_COLUMNS:
            raise ValueError(
                f'{path}: header must be {",".join(TRAJECTORY_CSV_COLUMNS)}; got {header}'
            )
        rows = list(reader)
    out: dict[str, NDArray[Any]] = {
        k: np.array([float(r[j]) for r in rows]) for j, k in enumerate(TRAJECTORY_CSV_COLUMNS)
    }
    out['stamp_ns'] = np.array([parse_stamp(r[0]) for r in rows], dtype=np.int64)
    out['state'] = np.column_stack([out[k] for k in TRAJECTORY_CSV_COLUMNS[1:7]])
    out['sigma'] = np.column_stack([out[k] for k in TRAJECTORY_CSV_COLUMNS[7:]])
    return out
