"""Events in a rough trajectory's velocity: where its acceleration jumps, ramps or bends.

Seed 000 repeats a knot where the acceleration jumps (engine cut-off, ignition), so that
the spline may follow the jump (:mod:`.knots`). Not every abrupt change of acceleration is
a jump: an aircraft enters and leaves a turn through a control ramp of a second or two,
its acceleration continuous and its jerk jumping at the two ends of the ramp. Taken for a
jump in the middle of the ramp (and found two or three times along it, since the
detector's windows are longer than the ramp at 1 Hz), the spline had an acceleration jump
where there was none and could not bend where the jerk did jump; it rang between the
samples, its velocity 0.2-0.7 m/s off where its covariance claimed 0.03 m/s. Given knots
of multiplicity ``p - 2`` (the jerk may jump) at the true ramp ends instead (an oracle),
the 35 aircraft draws of the robustness families had a fifth of those states.
:func:`find_changes` therefore tells them apart, in two passes:

1. **Acceleration candidates**: a quadratic is fitted to the velocity over ``window`` on
   each side of every sample; a jump of their slopes (the acceleration) by more than
   ``min_jump`` and ``sigma`` times its noise marks a candidate. A steady jerk gives the
   same acceleration from both sides and is no candidate; nor is a sample whose windows
   reach across a hole in the sampling (the edges of an outage are not events).
2. **Jump, ramp or bend**, at the strongest candidate: the velocity within two windows
   of it (not past halfway to another change) is fitted by a cubic plus a **bend** at
   ``tau`` (the jerk jumps: ``(t - tau)_+^2``), a **jump** (acceleration and jerk:
   ``(t - tau)_+`` as well) or a **ramp** from ``tau1`` to ``tau2`` (``(t - tau1)_+^2``
   and ``(t - tau2)_+^2``), on grids of times (the ramp's refined once). The simplest
   that no other beats by :data:`RAMP_CHI2` in units of the velocity noise is taken (see
   :func:`_classify`); an acceleration candidate is a jump or a ramp. A jump's time is
   refined by a continuous broken line on a grid of a twentieth of the sampling interval.
3. The candidates within a window of it are dropped (a ramp's whole run of them), and the
   next strongest is taken.
4. **Jerk candidates**: the same with the jumps of the quadratics' curvature (the jerk,
   over two windows each side) where no change found so far reaches: ramps too long for
   the acceleration's statistic to see, and bends; a jump found here is dropped.
5. **Doubtful changes**: a candidate that fitted no change, and the strongest sample of
   every run where the acceleration's statistic exceeds :data:`DOUBT` of its threshold
   out of reach of the changes found. They get no knots (the threshold is there to keep
   noise from freeing the spline); the window's covariance carries a consider term
   around them as around the changes found (``event_manoeuvre_density``). With 5 Hz
   telemetry of 0.2 m/s noise a turn ramp's end is found about as often as it is only
   doubtful, and the states beside an unknotted end were off by tenths of a metre per
   second at centimetres of sigma.
6. **Weak changes**: the strongest sample of every run where the jerk's statistic, without
   its floor and above what a steady turn of the same normal acceleration gives
   (:data:`TURN_MARGIN`), exceeds
   :data:`JERK_DOUBT` noise sigmas out of reach of all of the above, with the jerk's jump
   there: a gentle turn ramp's end. No knots; a consider term sized by the jump
   (``weak_manoeuvre_gain``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ['Changes', 'detector_reach', 'find_changes']

FloatArray = NDArray[np.float64]

RAMP_CHI2 = 25.0
"""How much better (chi-square, velocity noise units) a change with more terms must fit."""

MIN_RAMP = 0.25
"""Shortest ramp [s] (and never shorter than a sampling interval): two kinks closer than
this are an acceleration jump, or two (a cut-off and an ignition 0.3 s apart)."""

KINK_FLOOR = 2.5
"""A jerk jump below this many ``min_jump / window`` is no candidate: in a steady turn the
acceleration turns with the velocity, and quadratic fits a few seconds apart (at 1 Hz)
differ by 2-3 m/s^3 without any kink; the turn ramps of the aircraft draws are 7-15."""

JERK_DOUBT = 2.5
"""Noise sigmas of the jerk's statistic (no floor) above which a run out of reach of the
changes and doubts found marks a weak change (:attr:`Changes.weak`). Aircraft leaving a
gentle turn (1.9-2.8 m/s^2 over 1.2-1.4 s) showed 4-8 sigmas there, below the 10-sigma
threshold, and the states beside them were off by 0.1-0.2 m/s at 0.03-0.06 m/s sigmas."""

WHITE_MEDIAN = float(np.sqrt(2.366 / 3.0))
"""Median of the jerk's statistic in noise sigmas for white velocity noise (the root of a
chi-square of 3 degrees of freedom over 3). Separate-velocity telemetry of the ascent draws
(errors correlated over seconds) ran at twice that, and marked a weak change every two
seconds; its statistic is taken in units of its median when that is higher."""

TURN_MARGIN = 2.0
"""The weak changes' statistic is counted above this many times a steady turn's own jerk
change (aircraft draw 1005's 2.5 g turns: 0.4-0.7 m/s^3 in 5 Hz GPS at 0.03 m/s, marks all
along the turn, which doubled the velocity sigmas where the spline followed the turn)."""

DOUBT = 0.5
"""Share of its threshold above which the acceleration's statistic marks a doubtful
change (the threshold is at least ``event_sigma`` noise sigmas, 10 by default: half of it
is still five)."""

_COARSE = 32
"""Grid points over the search span in the first pass of the jump-or-ramp fit."""


@dataclass(frozen=True)
class Changes:
    """Acceleration ``jumps`` (a knot of multiplicity ``p - 1`` each) and the ends of
    acceleration ramps, ``kinks`` (where the jerk jumps: multiplicity ``p - 2``), [s]."""

    jumps: tuple[float, ...] = ()
    kinks: tuple[float, ...] = ()
    doubtful: tuple[float, ...] = ()
    """Where a change may be but none was found: the acceleration's statistic above
    :data:`DOUBT` of its threshold away from the changes found, or a candidate that fitted
    no change (no knots there; the covariance's consider term around events covers them)."""
    weak: tuple[tuple[float, float], ...] = ()
    """``(time, jerk jump [m/s^3])`` where the jerk's statistic, without its floor, exceeds
    :data:`JERK_DOUBT` noise sigmas out of reach of every change and doubt above (the
    strongest sample of each run): a gentle ramp's end the thresholds let pass. No knots;
    the covariance's consider term around it is sized by the jump."""

    @property
    def times(self) -> list[float]:
        """Every event time, sorted."""
        return sorted(self.jumps + self.kinks)


def _half_width(dt: float, window: float) -> int:
    """Samples on each side of a candidate that the detector's fits take."""
    return max(3, int(round(window / dt)))


def detector_reach(dt: float, window: float) -> float:
    """How far [s] the detector's fits reach on each side of a change, for samples every
    ``dt`` seconds and the fit window ``window``: a change whose fits would take samples
    across a hole is never found (``0`` when ``dt`` is not positive)."""
    return _half_width(dt, window) * dt if dt > 0.0 else 0.0


def find_changes(
    t: FloatArray,
    v: FloatArray,
    noise: float,
    min_jump: float,
    sigma: float,
    window: float,
) -> Changes:
    """Acceleration jumps, ramps and kinks in velocity samples ``v`` (n, 3) at times
    ``t`` with white noise ``noise`` [m/s] (see the module docstring)."""
    n = t.size
    if n < 10:
        return Changes()
    dt = float(np.median(np.diff(t)))
    k = _half_width(dt, window)
    if n < 2 * k + 1:
        return Changes()
    jumps: list[float] = []
    kinks: list[float] = []
    doubtful: list[float] = []
    reach = k * dt
    # samples whose windows see a change already found: those of the acceleration's
    # statistic (one window each side), and of the jerk's (two)
    seen = (np.zeros(n, dtype=bool), np.zeros(n, dtype=bool))
    # acceleration jumps first (and what they turn out to be), then the kinks left over:
    # the jerk's statistic also peaks half a window from a jump, and between two jumps
    *scores, jerk_sigmas, jerk_jump = _scores(t, v, k, dt, noise, min_jump, sigma, window)
    for p, score in enumerate(scores):
        taken = seen[p]
        above = (score > 1.0) & ~taken
        peak = above & (score >= np.roll(score, 1)) & (score >= np.roll(score, -1))
        cand = np.flatnonzero(above)
        while cand.size:
            i = cand[np.argmax(score[cand])]
            tc = float(t[i])
            # the fit reaches a window past the times searched, but not past halfway to
            # another change (seed 000's cut-off and ignition 1.5 s apart); the jerk's
            # candidates are searched over its two windows, and only the changes found
            # stop them (its peaks come in pairs, at a ramp's two ends)
            grid = reach * (p + 1)
            others = np.concatenate([t[peak] if p == 0 else [], jumps, kinks])
            before = others[others < tc - reach]
            after = others[others > tc + reach]
            lo = max(tc - grid - reach, 0.5 * (tc + before.max()) if before.size else -np.inf)
            hi = min(tc + grid + reach, 0.5 * (tc + after.min()) if after.size else np.inf)
            kind, times = _classify(t, v, tc, grid, dt, noise, (lo, hi))
            if kind in ('kink', 'none') and p == 0:
                kind = 'jump'  # the acceleration jumps here: a jump or a ramp, not a bend
            if kind == 'jump' and p == 0:
                # refined around the candidate, where the jump's statistic peaks
                times = (_refine_jump(t, v, tc, window, dt),)
                jumps.append(times[0])
            elif kind in ('jump', 'none'):
                kind, times = 'none', (tc,)  # no jump the first pass missed, nor a bend
                doubtful.append(tc)
            else:
                kinks.extend(times)
            # the samples within reach of it see it (of the candidate, for a jump: a second
            # jump may follow within a window, 0.55 s later in ascent draw 17, and is then
            # found at the edge of that reach); a ramp's or kink's whole run of candidates
            # too. The jerk's statistic sees it from two windows away.
            if kind == 'jump':
                taken[np.abs(t - tc) <= reach] = True
            else:
                run = np.flatnonzero(np.diff(cand) > 1)
                first = cand[np.concatenate([[0], run + 1])]
                last = cand[np.concatenate([run, [cand.size - 1]])]
                r = int(np.searchsorted(last, i))
                taken[first[r] : last[r] + 1] = True
                taken[(t >= times[0] - reach) & (t <= times[-1] + reach)] = True
            if kind != 'none':
                seen[1][(t >= times[0] - 2.0 * reach) & (t <= times[-1] + 2.0 * reach)] = True
            peak &= ~taken
            cand = cand[~taken[cand]]
    # the acceleration's statistic between DOUBT and its threshold, out of reach of the
    # changes found: the strongest sample of each run
    score = scores[0]
    near = _within(t, (*jumps, *kinks), 2.0 * reach)
    above_doubt = np.flatnonzero((score > DOUBT) & ~near)
    if above_doubt.size:
        runs = np.split(above_doubt, np.flatnonzero(np.diff(above_doubt) > 1) + 1)
        doubtful.extend(float(t[r[np.argmax(score[r])]]) for r in runs)
    # the jerk's statistic without its floor, out of the jerk's reach of all of those
    near = _within(t, (*jumps, *kinks, *doubtful), 2.0 * reach)
    # velocity errors that are not white (a separate velocity source, an INS) leave the
    # noise level too low and the statistic high everywhere: counted in units of its own
    # median where it is that of white noise or above
    quiet = (jerk_jump > 0.0) & ~near
    if np.count_nonzero(quiet) >= 20:
        jerk_sigmas = jerk_sigmas / max(1.0, float(np.median(jerk_sigmas[quiet])) / WHITE_MEDIAN)
    weak_runs = np.flatnonzero((jerk_sigmas > JERK_DOUBT) & ~near)
    weak: list[tuple[float, float]] = []
    if weak_runs.size:
        for wr in np.split(weak_runs, np.flatnonzero(np.diff(weak_runs) > 1) + 1):
            top = int(wr[np.argmax(jerk_sigmas[wr])])
            weak.append((float(t[top]), float(jerk_jump[top])))
    return Changes(
        tuple(sorted(jumps)), tuple(sorted(kinks)), tuple(sorted(set(doubtful))), tuple(weak)
    )


def _within(t: FloatArray, times: Sequence[float], reach: float) -> NDArray[np.bool_]:
    """The samples ``t`` within ``reach`` of any of ``times``."""
    near = np.zeros(t.size, dtype=bool)
    for e in times:
        near |= np.abs(t - e) <= reach
    return near


def _scores(
    t: FloatArray,
    v: FloatArray,
    k: int,
    dt: float,
    noise: float,
    min_jump: float,
    sigma: float,
    window: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """At every sample, the jumps of acceleration and of jerk between quadratic fits to
    the ``k`` samples on each side (``2 k`` for the jerk, which needs the longer lever),
    each over its threshold (``min_jump`` [m/s^2] or :data:`KINK_FLOOR` ``min_jump / window``
    [m/s^3], and ``sigma`` times its noise); then the jerk's jump in noise sigmas and in
    m/s^3. All 0 where the windows do not fit, or reach across a hole in the sampling."""
    n = t.size
    holes = np.concatenate([[0], np.cumsum(np.diff(t) > 1.5 * dt)])  # holes before each
    out = []
    k2 = min(2 * k, (n - 1) // 2)
    speed2 = np.maximum(np.sum(v * v, axis=1), 1e-12)
    for row, kk, floor in ((1, k, min_jump), (2, k2, KINK_FLOOR * min_jump / window)):
        # quadratic fits on each side, differentiated at the candidate: a steady jerk
        # gives the same acceleration and jerk from both sides, a jump or a kink does not
        tau = (np.arange(kk + 1) - kk) * dt
        pinv = np.linalg.pinv(np.column_stack([np.ones(kk + 1), tau, tau**2]))
        w_left = pinv[row] * float(row)  # row 1: the slope; row 2: half the curvature
        w_right = w_left[::-1] * (-1.0 if row == 1 else 1.0)  # mirrored: forward in time
        d_l = np.full((n, 3), np.nan)
        d_r = np.full((n, 3), np.nan)
        for c in range(3):
            d_l[kk:, c] = np.convolve(v[:, c], w_left[::-1], mode='valid')
            d_r[: n - kk, c] = np.convolve(v[:, c], w_right[::-1], mode='valid')
        jump = np.linalg.norm(d_r - d_l, axis=1)
        sig = noise * float(np.sqrt(w_left @ w_left))
        threshold = max(floor, sigma * np.sqrt(2.0) * sig * np.sqrt(3))
        jump = np.nan_to_num(jump)
        jump[:kk] = 0.0
        jump[n - kk :] = 0.0
        # the fits take the samples as evenly spaced: a sample whose windows reach across
        # a hole (a telemetry outage, a dropout) compares fits over the wrong times, and
        # the outage's edges came out as events (spurious acceleration jumps that freed
        # the spline across the outage from the jerk prior). No event is claimed there;
        # the measurements' knot test can still find one.
        i = np.arange(kk, n - kk)
        jump[i[holes[i + kk] != holes[i - kk]]] = 0.0
        out.append(jump / threshold)
        if row == 1:
            # the acceleration normal to the velocity: what turns the velocity
            acc = np.nan_to_num(0.5 * (d_l + d_r))
            normal = np.linalg.norm(np.cross(acc, v), axis=1) / np.sqrt(speed2)
        else:
            # in a steady turn the normal acceleration turns with the velocity, and the jerk
            # with it: fits a lever apart differ by |d3v/dt3| * lever = a_n^3 / |v|^2 * lever
            # (a thrust along the velocity turns nothing)
            excess = np.maximum(jump - TURN_MARGIN * normal**3 / speed2 * kk * dt, 0.0)
            out.extend((excess / (np.sqrt(6.0) * sig) if sig > 0.0 else 0.0 * jump, jump))
    return out[0], out[1], out[2], out[3]


def _sse(vs: FloatArray, base: FloatArray, extra: FloatArray) -> float:
    a = np.column_stack([base, extra])
    coef, *_ = np.linalg.lstsq(a, vs, rcond=None)
    return float(np.sum((vs - a @ coef) ** 2))


def _classify(
    t: FloatArray,
    v: FloatArray,
    tc: float,
    reach: float,
    dt: float,
    noise: float,
    span: tuple[float, float],
) -> tuple[str, tuple[float, ...]]:
    """What changes near the candidate ``tc``, fitted to the samples within ``span``: a
    ``kink`` (the jerk jumps at one time), a ``jump`` (the acceleration jumps) or a
    ``ramp`` (the jerk jumps at its two ends), with its time(s), searched within ``reach``
    of it; or ``none`` (no time) when a bend is all and fits no better than the cubic alone.
    The simplest that no other beats by :data:`RAMP_CHI2` (velocity noise units); a ramp
    also explains a quarter of a jump's misfit and lasts :data:`MIN_RAMP` and at least a
    sampling interval."""
    m = (t >= span[0]) & (t <= span[1])
    ts, vs = t[m], v[m]
    if ts.size < 10:
        return 'jump', (tc,)
    s = (ts - tc) / reach
    base = np.column_stack([np.ones_like(s), s, s**2, s**3])
    coef, *_ = np.linalg.lstsq(base, vs, rcond=None)
    e_none = float(np.sum((vs - base @ coef) ** 2))

    def up(tau: float) -> FloatArray:
        return np.asarray(np.maximum(ts - tau, 0.0) / reach)

    def one(tau: float, jump: bool) -> float:
        u = up(tau)
        return _sse(vs, base, np.column_stack([u, u**2]) if jump else (u**2)[:, None])

    def two(t1: float, t2: float) -> float:
        return _sse(vs, base, np.column_stack([up(t1) ** 2, up(t2) ** 2]))

    line = np.linspace(tc - reach, tc + reach, 8 * _COARSE + 1)
    e_kink, t_kink = min((one(float(g), False), float(g)) for g in line)
    e_jump, t_jump = min((one(float(g), True), float(g)) for g in line)
    c = RAMP_CHI2 * noise**2
    kind, e = ('jump', e_jump) if e_jump < e_kink - c else ('kink', e_kink)
    e_ramp, t1, t2 = _pair(two, tc, reach)
    ramp_ok = (
        t2 - t1 >= max(dt, MIN_RAMP)
        and e_ramp < e - c
        and (kind == 'kink' or e_ramp <= 0.75 * e_jump)
    )
    if ramp_ok:
        return 'ramp', (t1, t2)
    if kind == 'kink':
        # a bend that no better than the cubic alone has no time to speak of (1-2 Hz
        # quantised GPS put them 1-2 s from the true ramp ends)
        return ('kink', (t_kink,)) if e_kink < e_none - c else ('none', ())
    return kind, (t_jump,)


def _pair(
    sse: Callable[[float, float], float], tc: float, reach: float
) -> tuple[float, float, float]:
    """The least misfit ``sse(t1, t2)`` over ``tc - reach <= t1 < t2 <= tc +
    reach``: a grid of :data:`_COARSE` steps, refined once by eighths around its best."""
    h = 2.0 * reach / _COARSE
    grid = tc - reach + h * np.arange(_COARSE + 1)
    e0, a0, b0 = min(
        (sse(float(grid[a]), float(grid[b])), float(grid[a]), float(grid[b]))
        for a in range(grid.size)
        for b in range(a + 1, grid.size)
    )
    fine = h / 8.0 * np.arange(-8, 9)
    return min(
        [(e0, a0, b0)]
        + [
            (sse(a0 + da, b0 + db), a0 + da, b0 + db)
            for da in fine
            for db in fine
            if b0 + db - a0 - da > h / 16.0
        ]
    )


def _refine_jump(t: FloatArray, v: FloatArray, tc: float, w: float, dt: float) -> float:
    """Time of an acceleration jump near ``tc``: the break of a continuous broken line
    fitted to the velocity within ``w`` of it, on a grid of a twentieth of ``dt``."""
    m = (t >= tc - w) & (t <= tc + w)
    ts, vs = t[m], v[m]
    best, best_tau = np.inf, tc
    for tau in np.linspace(tc - dt, tc + dt, 41):
        # continuous broken line: v = v0 + a1 min(t - tau, 0) + a2 max(t - tau, 0)
        a = np.column_stack([np.ones_like(ts), np.minimum(ts - tau, 0.0), np.maximum(ts - tau, 0)])
        coef, *_ = np.linalg.lstsq(a, vs, rcond=None)
        sse = float(np.sum((vs - a @ coef) ** 2))
        if sse < best:
            best, best_tau = sse, float(tau)
    return best_tau
