"""Stitching a stream of window solutions into final states, as they arrive (the live
results node's counterpart of :func:`~orbit_tracking.core.estimation.windows.stitch`).

The estimator publishes each solved window's states sampled at the output times (the
multiples of its ``output_step``). Consecutive windows overlap and the output hands over
from window ``a`` to the next window ``b`` across the middle half of their overlap, with
the blend of :func:`~orbit_tracking.core.estimation.windows.blend` (the offline tool's).

Finality rule
-------------
A state is *final* once no later window can change it. Windows are solved in time order
(each one ends later than the one before), and window ``b`` changes window ``a``'s
states only from the start of their hand-over ``h = b0 + (a1 - b0) / 4`` on (``h = b0``
when they do not overlap). So when ``b`` arrives, every time of the target before ``h`` is
final and emitted; the rest of ``b`` waits for the window after it, or for
:meth:`TrajectoryStitcher.flush` (end of the stream), which makes everything held final.
A time is emitted once: the states a later window holds at times already emitted (after a
flush, or a window that reaches unusually far back) are dropped and counted, so the same
epoch is never given two values.

Times are TimeBase seconds, as everywhere in the core; inside, they are matched on
integer nanoseconds so that the same output time from two windows is one time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbit_tracking.core.estimation.windows import Span, blend, handover_span

__all__ = ['FinalStates', 'SampledWindow', 'TimeLine', 'TrajectoryStitcher', 'split_window']

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Item = TypeVar('Item')

_NS = 1e9
_SPAN_TOLERANCE = 1e-6  # s: sample times within the window span, up to stamp rounding


def _keys(t: FloatArray) -> IntArray:
    return np.round(np.asarray(t, dtype=np.float64) * _NS).astype(np.int64)


@dataclass(frozen=True)
class SampledWindow:
    """One target's states in one window, sampled at output times.

    Attributes
    ----------
    target_id : int
    t0, t1 : float
        Window span [s].
    time : ndarray, shape (m,)
        Sample times [s], strictly increasing, inside ``[t0, t1]``.
    state : ndarray, shape (m, 6)
        World position [m] and velocity [m/s].
    covariance : ndarray, shape (m, 6, 6)
    """

    target_id: int
    t0: float
    t1: float
    time: FloatArray
    state: FloatArray
    covariance: FloatArray
    keys: IntArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        m = self.time.shape[0] if self.time.ndim == 1 else -1
        if m < 1 or self.state.shape != (m, 6) or self.covariance.shape != (m, 6, 6):
            raise ValueError(
                f'target {self.target_id}: a window needs time (m,) with m >= 1, state (m, 6) '
                f'and covariance (m, 6, 6); got {self.time.shape}, {self.state.shape} and '
                f'{self.covariance.shape}'
            )
        if not (math.isfinite(self.t0) and math.isfinite(self.t1) and self.t1 > self.t0):
            raise ValueError(
                f'window span must be finite with t1 > t0; got [{self.t0}, {self.t1}]'
            )
        keys = _keys(self.time)
        if np.any(np.diff(keys) <= 0):
            raise ValueError(f'target {self.target_id}: sample times must be strictly increasing')
        if self.time[0] < self.t0 - _SPAN_TOLERANCE or self.time[-1] > self.t1 + _SPAN_TOLERANCE:
            raise ValueError(
                f'target {self.target_id}: samples [{self.time[0]:.9g}, {self.time[-1]:.9g}] '
                f'reach outside the window [{self.t0:.9g}, {self.t1:.9g}]'
            )
        object.__setattr__(self, 'keys', keys)

    @property
    def span(self) -> Span:
        return (self.t0, self.t1)

    def states(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """States and covariances at sample times ``t``; NaN where there is no sample."""
        k = _keys(t)
        i = np.clip(np.searchsorted(self.keys, k), 0, self.keys.size - 1)
        hit = self.keys[i] == k
        x = np.full((k.size, 6), np.nan)
        c = np.full((k.size, 6, 6), np.nan)
        x[hit] = self.state[i[hit]]
        c[hit] = self.covariance[i[hit]]
        return x, c


def split_window(
    t0: float,
    t1: float,
    time: ArrayLike,
    target_id: ArrayLike,
    state: ArrayLike,
    covariance: ArrayLike,
) -> list[SampledWindow]:
    """One window's samples of every target (as ``estimator/window_states`` carries them)
    as one :class:`SampledWindow` per target, sorted by target id and time.

    Raises
    ------
    ValueError
        Inconsistent shapes, a time given twice for a target, samples outside the span.
    """
    t = np.atleast_1d(np.asarray(time, dtype=np.float64))
    ids = np.atleast_1d(np.asarray(target_id)).astype(np.int64)
    x = np.asarray(state, dtype=np.float64)
    c = np.asarray(covariance, dtype=np.float64)
    m = t.size
    if ids.shape != (m,) or x.shape != (m, 6) or c.shape != (m, 6, 6):
        raise ValueError(
            f'window samples need time (m,), target_id (m,), state (m, 6) and covariance '
            f'(m, 6, 6); got {t.shape}, {ids.shape}, {x.shape} and {c.shape}'
        )
    out = []
    for tid in np.unique(ids):
        sel = np.flatnonzero(ids == tid)
        sel = sel[np.argsort(t[sel], kind='stable')]
        out.append(SampledWindow(int(tid), float(t0), float(t1), t[sel], x[sel], c[sel]))
    return out


@dataclass(frozen=True)
class FinalStates:
    """States of one target that no later window can change.

    ``time`` (k,) [s], ``state`` (k, 6) world position [m] and velocity [m/s],
    ``covariance`` (k, 6, 6).
    """

    target_id: int
    time: FloatArray
    state: FloatArray
    covariance: FloatArray

    def __len__(self) -> int:
        return int(self.time.shape[0])


@dataclass
class _Track:
    windows: list[SampledWindow] = field(default_factory=list)
    done_key: int | None = None  # every sample time before it (ns) was emitted or dropped


class TrajectoryStitcher:
    """Hands over between overlapping windows as they arrive and emits final states
    (the rule is in the module docstring). One track per target.

    Attributes
    ----------
    last_end : float
        End of the newest window added (-inf before the first).
    counts : dict of str to int
        ``states_final`` (emitted), ``states_already_final`` (samples at times already
        emitted, dropped), ``missing_samples`` (times a window with weight there has no
        sample for: not emitted).
    """

    def __init__(self) -> None:
        self._tracks: dict[int, _Track] = {}
        self.last_end = -math.inf
        self.counts: dict[str, int] = {
            'states_final': 0,
            'states_already_final': 0,
            'missing_samples': 0,
        }

    def reset(self) -> None:
        """Forget every window and what was emitted (counters are kept)."""
        self._tracks.clear()
        self.last_end = -math.inf

    @property
    def targets(self) -> list[int]:
        return sorted(self._tracks)

    def held(self) -> int:
        """Samples held (not final yet), over all targets."""
        out = 0
        for tr in self._tracks.values():
            lo = np.iinfo(np.int64).min if tr.done_key is None else tr.done_key
            keys = [w.keys[w.keys >= lo] for w in tr.windows]
            out += int(np.unique(np.concatenate(keys)).size) if keys else 0
        return out

    def final_until(self, target_id: int) -> float:
        """Every time of the target before this [s] is final (-inf if none)."""
        tr = self._tracks.get(target_id)
        if tr is None or tr.done_key is None:
            return -math.inf
        return tr.done_key / _NS

    def add(self, windows: Sequence[SampledWindow]) -> list[FinalStates]:
        """Add one solved window (its targets' samples, all with the same span) and return
        the states that became final, per target.

        Raises
        ------
        ValueError
            The windows do not share one span, or the window does not end later than the
            previous one (time went backwards, or a window came twice: the caller decides
            whether to :meth:`reset`).
        """
        if not windows:
            return []
        span = windows[0].span
        if any(w.span != span for w in windows):
            raise ValueError('the targets of one window must share its span')
        if not span[1] > self.last_end:
            raise ValueError(
                f'window [{span[0]:.9g}, {span[1]:.9g}] does not end after the previous one '
                f'({self.last_end:.9g})'
            )
        self.last_end = span[1]
        out = []
        for w in windows:
            tr = self._tracks.setdefault(w.target_id, _Track())
            if tr.done_key is not None:
                late = int(np.count_nonzero(w.keys < tr.done_key))
                self.counts['states_already_final'] += late
            prev = tr.windows[-1] if tr.windows else None
            tr.windows.append(w)
            if prev is None:
                continue
            ho = handover_span(prev.span, w.span)
            horizon = w.t0 if ho is None else ho[0]
            # the hand-over start, rounded down to a whole nanosecond: later windows cannot
            # change a time before it
            fs = self._emit(tr, w.target_id, math.floor(horizon * _NS))
            if fs is not None:
                out.append(fs)
        return out

    def flush(self) -> list[FinalStates]:
        """End of the stream: every state held becomes final."""
        out = []
        for tid, tr in sorted(self._tracks.items()):
            if not tr.windows:
                continue
            end = max(int(w.keys[-1]) for w in tr.windows) + 1
            fs = self._emit(tr, tid, end)
            tr.windows = []
            if fs is not None:
                out.append(fs)
        return out

    def _emit(self, tr: _Track, tid: int, until_key: int) -> FinalStates | None:
        """Emit the held sample times in ``[done_key, until_key)``; drop windows that end
        before ``until_key``."""
        lo = np.iinfo(np.int64).min if tr.done_key is None else tr.done_key
        if until_key <= lo:
            return None
        keys = np.unique(np.concatenate([w.keys for w in tr.windows]))
        keys = keys[(keys >= lo) & (keys < until_key)]
        tr.done_key = until_key
        fs = None
        if keys.size:
            ws = sorted(tr.windows, key=lambda w: (w.t0, w.t1))
            t, x, cov = blend([w.span for w in ws], [w.states for w in ws], keys / _NS)
            ok = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
            # not covered by any span (blend leaves them out), or a sample is missing
            self.counts['missing_samples'] += keys.size - int(np.count_nonzero(ok))
            self.counts['states_final'] += int(np.count_nonzero(ok))
            if np.any(ok):
                fs = FinalStates(tid, t[ok], x[ok], cov[ok])
        tr.windows = [w for w in tr.windows if w.t1 * _NS >= until_key]
        return fs


class TimeLine(Generic[Item]):
    """Which incoming windows to use, so that one stray window cannot restart a trajectory.

    A window that *jumps* from the time line (it ends before the last window used, or
    starts more than ``max_jump`` seconds after its end) may be the first window of a new
    time line (a bag replayed in a loop, a new pass) or a stray message. It is held until
    the next window decides:

    * the next window continues from the held one (it ends after it and starts within
      it or up to ``max_jump`` after it, closer to its end than to the old time line's):
      both are used, the held one first (the new time line is confirmed);
    * the next window continues the old time line: the held one is dropped;
    * the stream ends (:meth:`release`): the held one is used.

    Parameters
    ----------
    max_jump : float
        Seconds after the last window's end beyond which a window start is a jump.
    """

    def __init__(self, max_jump: float) -> None:
        if not max_jump > 0.0:
            raise ValueError(f'max_jump must be > 0 s; got {max_jump}')
        self.max_jump = max_jump
        self.held: tuple[Span, Item] | None = None

    def offer(self, span: Span, item: Item, last_end: float) -> tuple[list[Item], Item | None]:
        """Decide about a window ``span`` with payload ``item``, ``last_end`` being the end
        of the last window used (-inf before the first).

        Returns
        -------
        use : list
            Payloads to use now, in this order (empty: ``item`` is held).
        dropped : payload or None
            A held payload that the time line did not confirm.
        """
        t0, t1 = span
        jump = math.isfinite(last_end) and (t1 < last_end or t0 > last_end + self.max_jump)
        held, self.held = self.held, None
        if held is not None:
            h0, h1 = held[0]
            follows = h1 < t1 and h0 <= t0 <= h1 + self.max_jump
            if follows and abs(t0 - h1) < abs(t0 - last_end):
                return [held[1], item], None  # it continues from the held one: confirmed
        dropped = None if held is None else held[1]
        if jump:
            self.held = (span, item)
            return [], dropped
        return [item], dropped

    def release(self) -> Item | None:
        """The held payload, if any, to be used at the end of the stream."""
        held, self.held = self.held, None
        return None if held is None else held[1]
