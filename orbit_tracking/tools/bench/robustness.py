"""The robustness benchmark of issue 14: randomised draws, every figure against each draw's
Cramér–Rao bound, stated as median / 95th percentile / worst case.

``orbit-tracking bench --suite robustness --draws N [--kind ascent|aircraft|all] [--seed S]
[--jobs J] [--write-docs]`` draws ``N`` scenarios (with ``all``, half of each kind, the
ascents first), seeds ``S, S + 1, ...`` per kind, from the families of
:mod:`orbit_tracking.core.sim.families`, which are generated separately from the reference
scenarios. Each draw is simulated, bounded and scored by
:func:`~orbit_tracking.tools.bench.robustness_draw.run_draw` in a pool of ``J`` processes
(progress printed per draw). The KF's jerk density is tuned on the truth of draws 0-2 of
each kind first, then fixed. The Markdown this module prints (and ``--write-docs`` puts
between the ``robustness`` markers of docs/BENCHMARKS.md) holds, per kind, the summary
tables, the issue's targets with where the run stands, and the worst draws with the
command that reproduces each alone.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import platform
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np

from orbit_tracking.core.sim.families import KINDS
from orbit_tracking.tools.bench.robustness_draw import (
    BOUND_OF,
    KALMAN_GATE,
    KALMAN_TUNING_SEEDS,
    METHODS,
    NEES_STEP_S,
    SILENT_SIGMA,
    DrawResult,
    MethodResult,
    run_draw,
    tune_kalman,
)

__all__ = ['RobustnessRun', 'plan_draws', 'robustness_tables', 'run_robustness']

OURS, OURS_STATIONS, KALMAN = METHODS
WORST_SHOWN = 5
T = TypeVar('T')
R = TypeVar('R')
_THREAD_VARIABLES = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')


@dataclass
class RobustnessRun:
    """Every draw's result, the tuned KF jerk density per kind and how the run went."""

    draws: list[DrawResult]
    kalman_q: dict[str, float]
    command: str
    jobs: int
    elapsed_s: float = 0.0
    tuning_s: float = 0.0
    notes: list[str] = field(default_factory=list)


def plan_draws(draws: int, kind: str = 'all', seed: int = 0) -> list[tuple[str, int]]:
    """The ``(kind, seed)`` of every draw: ``draws`` in all, split evenly over the kinds
    (the first kinds take the remainder), seeds ``seed, seed + 1, ...`` within a kind."""
    if kind != 'all' and kind not in KINDS:
        raise ValueError(f'kind must be all or one of {KINDS}; got {kind!r}')
    kinds = KINDS if kind == 'all' else (kind,)
    if draws < 1 or seed < 0:
        raise ValueError(f'draws must be >= 1 and seed >= 0; got {draws}, {seed}')
    per = [draws // len(kinds) + (i < draws % len(kinds)) for i in range(len(kinds))]
    return [(k, seed + i) for k, n in zip(kinds, per, strict=True) for i in range(n)]


Task = tuple[str, int, float, float | None, float | None]
"""(kind, seed, KF jerk density, time limit, span) of one draw."""


def _draw_task(task: Task) -> DrawResult:
    kind, seed, q, limit, span = task
    return run_draw(kind, seed, q, time_limit=limit, span_s=span)


def _tune_task(kind: str) -> tuple[str, float]:
    return kind, tune_kalman(kind)


@contextmanager
def _executor(jobs: int) -> Iterator[ProcessPoolExecutor]:
    """``jobs`` fresh worker processes, spawned with one BLAS thread each: on two busy
    cores, OpenBLAS threads waiting on each other make a small solve a hundred times
    slower. (The variables stay set while the executor lives: it starts its workers
    lazily.)"""
    saved = {k: os.environ.get(k) for k in _THREAD_VARIABLES}
    os.environ.update({k: '1' for k in _THREAD_VARIABLES})
    ex = ProcessPoolExecutor(jobs, mp_context=mp.get_context('spawn'))
    try:
        yield ex
    finally:
        ex.shutdown(wait=True, cancel_futures=True)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _run_all(
    fn: Callable[[T], R],
    items: Sequence[T],
    jobs: int,
    failed: Callable[[T, str], R],
    done: Callable[[R], None],
) -> list[R]:
    """``fn`` of every item, ``jobs`` at a time in worker processes (in this process for
    ``jobs = 0``). An exception becomes ``failed(item, message)``; an item whose worker
    process dies (a crash in compiled code, memory) is tried once more alone, then recorded
    the same way, so one draw can never stop the suite."""
    out: dict[int, R] = {}

    def record(i: int, r: R) -> None:
        out[i] = r
        done(r)

    if jobs <= 0:
        for i, x in enumerate(items):
            try:
                record(i, fn(x))
            except Exception as exc:  # noqa: BLE001 - recorded, never fatal
                record(i, failed(x, f'{type(exc).__name__}: {exc}'))
        return [out[i] for i in range(len(items))]
    retry: list[int] = []
    with _executor(jobs) as ex:
        futures = {ex.submit(fn, x): i for i, x in enumerate(items)}
        for f in as_completed(futures):
            i = futures[f]
            try:
                record(i, f.result())
            except BrokenProcessPool:
                retry.append(i)
            except Exception as exc:  # noqa: BLE001
                record(i, failed(items[i], f'{type(exc).__name__}: {exc}'))
    for i in sorted(retry):
        with _executor(1) as ex:
            try:
                record(i, ex.submit(fn, items[i]).result())
            except BrokenProcessPool:
                record(i, failed(items[i], 'its worker process died (twice)'))
            except Exception as exc:  # noqa: BLE001
                record(i, failed(items[i], f'{type(exc).__name__}: {exc}'))
    return [out[i] for i in range(len(items))]


def _line(i: int, n: int, r: DrawResult) -> str:
    """One progress line per draw."""
    head = f'[{i:>4}/{n}] {r.kind} seed {r.seed}: {r.wall_s:5.1f} s'
    if r.error:
        return f'{head}  DRAW FAILED: {r.error[:120]}'
    parts = []
    for m in r.methods:
        if not m.ran:
            parts.append(f'{m.method} FAILED ({m.error[:60]})')
        else:
            parts.append(
                f'{m.method} gap {_f(m.pos_ratio_gap, ".2f")}x out {_f(m.pos_ratio_out, ".2f")}x'
                + (
                    f' silent {m.silent_states} ({m.silent} position, '
                    f'{m.silent_velocity} velocity)'
                    if m.silent_states
                    else ''
                )
                + (
                    f' windows failed {m.windows_failed + m.windows_raised}'
                    if m.windows_failed + m.windows_raised
                    else ''
                )
            )
    return f'{head}  ' + '; '.join(parts)


def run_robustness(
    draws: int,
    kind: str = 'all',
    seed: int = 0,
    jobs: int = 2,
    progress: Callable[[str], None] | None = print,
    kalman_q: dict[str, float] | None = None,
    time_limit: float | None = 120.0,
    command: str | None = None,
    span_s: float | None = None,
) -> RobustnessRun:
    """Run the suite (see the module docstring).

    Parameters
    ----------
    kalman_q : dict, optional
        The KF's jerk density per kind; default: tuned on the truth (:func:`~orbit_tracking.
        tools.bench.robustness_draw.tune_kalman`).
    time_limit : float, optional
        Seconds a method may run on one draw before it counts as failed there.
    span_s : float, optional
        Span of every draw instead of the family's (short runs for tests).
    """
    plan = plan_draws(draws, kind, seed)
    kinds = sorted({k for k, _ in plan}, key=KINDS.index)
    command = command or (
        f'orbit-tracking bench --suite robustness --draws {draws} --kind {kind} --seed {seed} '
        f'--jobs {jobs}'
    )
    start = time.monotonic()
    say = progress or (lambda _s: None)
    q = dict(kalman_q or {})
    todo = [k for k in kinds if k not in q]
    notes: list[str] = []
    if todo:
        say(
            f'tuning the KF jerk density on the truth of draws '
            f'{", ".join(map(str, KALMAN_TUNING_SEEDS))} of {", ".join(todo)} ...'
        )

        def untuned(kind: str, why: str) -> tuple[str, float]:
            notes.append(f'the KF could not be tuned for {kind} ({why}); q = 1 m²/s⁵ used')
            return kind, 1.0

        q.update(dict(_run_all(_tune_task, todo, jobs, untuned, lambda _r: None)))
        say('  ' + ', '.join(f'{k}: q = {q[k]:.3g} m²/s⁵' for k in todo))
    tuning = time.monotonic() - start
    tasks: list[Task] = [(k, s, q[k], time_limit, span_s) for k, s in plan]
    count = [0]

    def failed(task: Task, why: str) -> DrawResult:
        return DrawResult(task[0], task[1], error=why)

    def done(r: DrawResult) -> None:
        count[0] += 1
        say(_line(count[0], len(tasks), r))

    results = _run_all(_draw_task, tasks, jobs, failed, done)
    results.sort(key=lambda r: (KINDS.index(r.kind), r.seed))
    return RobustnessRun(results, q, command, jobs, time.monotonic() - start, tuning, notes)


# -- tables ------------------------------------------------------------------------------


def _f(x: float, fmt: str = '.3g') -> str:
    return format(x, fmt) if isinstance(x, (int, float)) and math.isfinite(x) else '—'


def _stats(values: Sequence[float]) -> tuple[float, float, float]:
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=float)
    if v.size == 0:
        return (math.nan, math.nan, math.nan)
    return float(np.median(v)), float(np.percentile(v, 95)), float(v.max())


def _mpw(values: Sequence[float], fmt: str = '.2f') -> str:
    """``median / p95 / worst``."""
    m, p, w = _stats(values)
    return f'{_f(m, fmt)} / {_f(p, fmt)} / {_f(w, fmt)}'


def _share(flags: Sequence[bool]) -> str:
    """``k/n`` as a percentage to a tenth, rounded down: 92 of 97 is 94.8 %, never a
    rounded 95 % that reads as a target met."""
    if not flags:
        return '—'
    k, n = sum(flags), len(flags)
    return f'{math.floor(1000 * k / n) / 10:.1f} % ({k}/{n})'


def _methods(rs: Sequence[DrawResult], name: str) -> list[MethodResult]:
    out = []
    for r in rs:
        m = r.method(name)
        if m is not None:
            out.append(m)
    return out


def _accuracy_table(rs: Sequence[DrawResult]) -> list[str]:
    lines = [
        '| method (bound) | ran | bound infinite (gap / out) | gap pos RMS/CRB | '
        'out pos RMS/CRB | gap vel RMS/CRB | out vel RMS/CRB | gap pos RMS [m] | '
        'out pos RMS [m] |',
        '|---|---|---|---|---|---|---|---|---|',
    ]
    for name in METHODS:
        ms = _methods(rs, name)
        ok = [m for m in ms if m.ran]
        # a ratio is undefined where the bound is infinite (an unobserved direction)
        inf_gap = sum(math.isfinite(m.pos_rms_gap) and math.isnan(m.pos_ratio_gap) for m in ok)
        inf_out = sum(math.isfinite(m.pos_rms_out) and math.isnan(m.pos_ratio_out) for m in ok)
        lines.append(
            f'| {name} ({BOUND_OF[name]}) | {len(ok)}/{len(ms)} | {inf_gap} / {inf_out} | '
            f'{_mpw([m.pos_ratio_gap for m in ok])} | {_mpw([m.pos_ratio_out for m in ok])} | '
            f'{_mpw([m.vel_ratio_gap for m in ok])} | {_mpw([m.vel_ratio_out for m in ok])} | '
            f'{_mpw([m.pos_rms_gap for m in ok], ".3g")} | '
            f'{_mpw([m.pos_rms_out for m in ok], ".3g")} |'
        )
    return lines


def _health_table(rs: Sequence[DrawResult]) -> list[str]:
    lines = [
        '| method | mean NEES | NEES in its 95 % band | NEES in the band for correlated errors '
        '| mean velocity NEES | velocity NEES in its 95 % band '
        '| coverage of the span | windows '
        'unsuccessful / raised | silent failures (states: position or velocity; position / '
        'velocity alone) | wall per draw [s] | slowest window [s] |',
        '|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for name in METHODS:
        ok = [m for m in _methods(rs, name) if m.ran]
        lines.append(
            f'| {name} | {_mpw([m.nees_mean for m in ok])} | '
            f'{_share([m.nees_in_band for m in ok])} | '
            f'{_share([m.nees_in_correlated_band for m in ok])} | '
            f'{_mpw([m.vel_nees_mean for m in ok])} | '
            f'{_share([m.vel_nees_in_band for m in ok])} | '
            f'{_mpw([m.coverage for m in ok])} | '
            f'{sum(m.windows_failed for m in ok)} / {sum(m.windows_raised for m in ok)} of '
            f'{sum(m.windows for m in ok)} | {sum(m.silent_states for m in ok)} '
            f'({sum(m.silent for m in ok)} / {sum(m.silent_velocity for m in ok)}) of '
            f'{sum(m.states for m in ok)} | {_mpw([m.wall_s for m in ok], ".1f")} | '
            f'{_mpw([m.max_window_s for m in ok], ".1f")} |'
        )
    return lines


def _rms_or_inf(m: MethodResult | None, key: str) -> float:
    if m is None or not m.ran:
        return math.inf
    v = float(getattr(m, key))
    return v if math.isfinite(v) else math.inf


def _beats(rs: Sequence[DrawResult], a: str, b: str, key: str) -> list[bool]:
    """Per draw with a figure: ``a``'s RMS below ``b``'s (a failed method counts as
    infinitely wrong; draws where neither has the figure are left out)."""
    out = []
    for r in rs:
        x, y = _rms_or_inf(r.method(a), key), _rms_or_inf(r.method(b), key)
        if math.isinf(x) and math.isinf(y):
            continue
        out.append(x < y)
    return out


GAP_TARGET = 1.5
"""Issue 14's target: gap position RMS at most this many times the draw's bound."""

OUTSIDE_TARGET = 1.3
"""... and outside the gaps."""


def _rms_targets(ms: Sequence[MethodResult]) -> tuple[list[bool], list[bool]]:
    """Per result that has the figure: its gap position RMS within :data:`GAP_TARGET` of
    its bound, and (a second list) its outside one within :data:`OUTSIDE_TARGET`."""
    gap = [m.pos_ratio_gap <= GAP_TARGET for m in ms if math.isfinite(m.pos_ratio_gap)]
    out = [m.pos_ratio_out <= OUTSIDE_TARGET for m in ms if math.isfinite(m.pos_ratio_out)]
    return gap, out


def _targets(rs: Sequence[DrawResult]) -> list[str]:
    ours = [r.method(OURS) for r in rs]
    ran = [m for m in ours if m is not None and m.ran]
    n = len(rs)
    silent = sum(m.silent_states for m in ran)
    silent_parts = (sum(m.silent for m in ran), sum(m.silent_velocity for m in ran))
    gap, out = _rms_targets(ran)
    band = [m.nees_in_band for m in ran]
    band_c = [m.nees_in_correlated_band for m in ran]
    ideal = [m.nees_ideal_in_band for m in ran if math.isfinite(m.nees_ideal_in_band)]
    beat_gap = _beats(rs, OURS, KALMAN, 'pos_rms_gap')
    beat_out = _beats(rs, OURS, KALMAN, 'pos_rms_out')
    slowest = max((m.max_window_s for m in ran if math.isfinite(m.max_window_s)), default=math.nan)
    failed = n - len(ran)
    return [
        '| target of issue 14 (`ours`, the default) | this run |',
        '|---|---|',
        f'| silent failures: 0 over >= 200 draws | {silent} states over {n} draws '
        f'(position {silent_parts[0]}, velocity {silent_parts[1]})'
        + (f' ({failed} draws where `ours` did not run at all)' if failed else '')
        + ' |',
        f'| gap pos RMS <= {GAP_TARGET:g} x CRB in >= 95 % of draws | {_share(gap)} |',
        f'| outside pos RMS <= {OUTSIDE_TARGET:g} x CRB in >= 95 % of draws | {_share(out)} |',
        f'| mean NEES inside its 95 % band in >= 90 % of draws | {_share(band)} |',
        '| (the same band: share of draws an honest estimator as good as the bound would '
        'have inside it, its chance per draw averaged) | '
        f'{_f(100 * float(np.mean(ideal)) if ideal else math.nan, ".1f")} % |',
        "| (mean NEES inside the 95 % band of samples correlated as the bound's errors) | "
        f'{_share(band_c)} |',
        f'| better than KF+RTS in >= 95 % of draws (gap / outside pos RMS) | '
        f'{_share(beat_gap)} / {_share(beat_out)} |',
        f'| no window over 3 s wall | slowest window {_f(slowest, ".1f")} s |',
    ]


def _by_telemetry_table(rs: Sequence[DrawResult]) -> list[str]:
    """The targets of `ours` per telemetry error model of the draws (the draws without
    telemetry as ``none``): where the silent failures and the NEES outside its band come
    from, which the totals hide."""
    groups: dict[str, list[MethodResult]] = {}
    for r in rs:
        m = r.method(OURS)
        if r.error or m is None or not m.ran:
            continue
        groups.setdefault(r.telemetry_model or 'none', []).append(m)
    lines = [
        '| telemetry error model | draws | silent failures (states; draws with any) | '
        f'gap pos RMS <= {GAP_TARGET:g} x CRB | outside pos RMS <= {OUTSIDE_TARGET:g} x CRB | '
        'NEES in its 95 % band | '
        'NEES in the band for correlated errors | velocity NEES in its 95 % band | '
        'windows unsuccessful |',
        '|---|---|---|---|---|---|---|---|---|',
    ]
    for model in sorted(groups):
        ms = groups[model]
        gap, out = _rms_targets(ms)
        lines.append(
            f'| {model} | {len(ms)} | {sum(m.silent_states for m in ms)}; '
            f'{sum(m.silent_states > 0 for m in ms)} | {_share(gap)} | {_share(out)} | '
            f'{_share([m.nees_in_band for m in ms])} | '
            f'{_share([m.nees_in_correlated_band for m in ms])} | '
            f'{_share([m.vel_nees_in_band for m in ms])} | '
            f'{sum(m.windows_failed + m.windows_raised for m in ms)} of '
            f'{sum(m.windows for m in ms)} |'
        )
    return lines


def _worst(rs: Sequence[DrawResult]) -> list[str]:
    def badness(r: DrawResult) -> float:
        m = r.method(OURS)
        if r.error or m is None or not m.ran:
            return math.inf
        ratios = [x for x in (m.pos_ratio_gap, m.pos_ratio_out) if math.isfinite(x)]
        return max(ratios, default=0.0) + 1e3 * m.silent_states

    worst = sorted(rs, key=badness, reverse=True)[:WORST_SHOWN]
    lines = []
    for r in worst:
        m = r.method(OURS)
        if r.error:
            what = f'draw failed: {r.error[:200]}'
        elif m is None or not m.ran:
            what = f'`ours` failed: {m.error[:200] if m else "not run"}'
        else:
            what = (
                f'`ours` gap {_f(m.pos_rms_gap)} m ({_f(m.pos_ratio_gap, ".2f")} x CRB), '
                f'outside {_f(m.pos_rms_out)} m ({_f(m.pos_ratio_out, ".2f")} x CRB), '
                f'NEES {_f(m.nees_mean, ".2f")}, {m.silent_states} silent '
                f'({m.silent} position, {m.silent_velocity} velocity), '
                f'{m.windows_failed + m.windows_raised} of {m.windows} windows failed'
                + (f' ({m.window_messages[0][:160]})' if m.window_messages else '')
            )
        lines.append(
            f'- **{r.kind} seed {r.seed}** — {what}. Drawn: {r.summary or "—"}. '
            f'Alone: `orbit-tracking bench --suite robustness --kind {r.kind} --seed {r.seed} '
            f'--draws 1`'
        )
    return lines


def _bounds_table(rs: Sequence[DrawResult]) -> list[str]:
    ok = [r for r in rs if not r.error]
    lines = [
        '| bound | gap pos [m] | out pos [m] | gap vel [m/s] | out vel [m/s] |',
        '|---|---|---|---|---|',
    ]
    for name in ('stations', 'stations+telemetry'):
        cols = [[r.bounds[name][i] for r in ok if name in r.bounds] for i in range(4)]
        lines.append(f'| {name} | ' + ' | '.join(_mpw(c, '.3g') for c in cols) + ' |')
    rep_p = [r.oracle[0] for r in ok]
    rep_v = [r.oracle[2] for r in ok]
    knots = [sum(r.oracle_knots) for r in ok]
    lines += [
        '',
        f'Oracle spline (median / p95 / worst): largest miss of the truth {_mpw(rep_p, ".2g")} m '
        f'and {_mpw(rep_v, ".2g")} m/s (tolerance 0.01 m, 0.001 m/s); interior knots, three '
        f'axes together, {_mpw(knots, ".0f")}; bound computed in '
        f'{_mpw([r.bound_s for r in ok], ".1f")} s.',
    ]
    return lines


def robustness_tables(run: RobustnessRun) -> str:
    """Markdown of a run: per kind the accuracy, consistency and target tables and the
    worst draws; then how it was measured."""
    counts = ', '.join(
        f'{sum(r.kind == k for r in run.draws)} {k}'
        for k in KINDS
        if any(r.kind == k for r in run.draws)
    )
    out = [
        f'{len(run.draws)} draws ({counts}). '
        'Figures are median / 95th percentile / worst over the draws; each RMS is over the '
        "truth samples (20 Hz) a method covers between the draw's first and last station "
        "value, inside the draw's gaps (ascent: incomplete segments; aircraft: GPS "
        'outages) or outside them, and each ratio divides it by the bound of the same '
        'samples (a method with a motion model or fewer parameters than the oracle, '
        'biased, can come below 1 where the data are weak). The bound '
        '(`orbit_tracking/core/crb.py`) is the Cramér–Rao bound of an oracle that knows '
        'the model structure: a degree-4 spline per axis whose knots come from the truth '
        '(within 1 cm and 1 mm/s), every station value with its true sigma (gross errors '
        'left out), and for `ours` the telemetry whitened by the true covariance of its '
        'error model. '
        f'NEES: mean position NEES of one sample every {NEES_STEP_S:g} s, counted as '
        'independent, against the two-sided 95 % chi-square band for that count (the '
        "target's band); the samples are not independent (a telemetry error the stations "
        'cannot separate lasts the whole span), so beside it the band of the mean NEES of '
        "samples whose errors are correlated as the bound's at the same times, and how "
        'often an honest estimator as good as the bound would be inside the independent '
        'band (`orbit_tracking/core/metrics.py`, `correlated_nees_band`); the velocity '
        'NEES of the same samples against the same independent band. Silent '
        f'failures: output states (0.1 s) whose position or whose velocity error is beyond '
        f'{SILENT_SIGMA:g} of its own covariance in any direction (Mahalanobis distance; '
        'every output state: failed windows are withheld). KF+RTS: jerk '
        'density tuned on the truth of draws '
        f'{", ".join(map(str, KALMAN_TUNING_SEEDS))} of each kind, then fixed '
        f'({", ".join(f"{k} q = {v:.3g} m²/s⁵" for k, v in run.kalman_q.items())}), '
        f'innovation gate at tail probability {KALMAN_GATE:g}.',
    ]
    out += [f'Note: {n}.' for n in run.notes]
    for kind in KINDS:
        rs = [r for r in run.draws if r.kind == kind]
        if not rs:
            continue
        failed = [r for r in rs if r.error]
        out += ['', f'### {kind} ({len(rs)} draws)', '']
        if failed:
            out += [
                f'{len(failed)} draws could not be simulated or bounded: '
                + '; '.join(f'seed {r.seed}: {r.error[:120]}' for r in failed),
                '',
            ]
        out += _accuracy_table(rs) + [''] + _health_table(rs) + ['']
        beat = [
            f'`{a}` better than KF+RTS (position RMS): gap '
            f'{_share(_beats(rs, a, KALMAN, "pos_rms_gap"))}, outside '
            f'{_share(_beats(rs, a, KALMAN, "pos_rms_out"))}'
            for a in (OURS, OURS_STATIONS)
        ]
        out += ['; '.join(beat) + '.', '']
        out += _targets(rs) + ['', f'`{OURS}` by telemetry error model:', '']
        out += _by_telemetry_table(rs) + ['', 'Bounds:', ''] + _bounds_table(rs)
        out += ['', f'Worst draws of `ours` ({kind}):', ''] + _worst(rs)
    walls = [r.wall_s for r in run.draws]
    out += [
        '',
        f'Measured by `{run.command}` on {platform.machine()} '
        f'({platform.python_implementation()} {platform.python_version()}, {os.cpu_count()} '
        f'cores{_commit()}) in {run.elapsed_s:.0f} s ({run.tuning_s:.0f} s of KF tuning); '
        f'wall per draw (all methods and the bound, one process) {_mpw(walls, ".1f")} s.',
    ]
    return '\n'.join(out)


def _commit() -> str:
    root = Path(__file__).resolve().parents[3]
    try:
        rev = subprocess.run(
            ['git', 'rev-parse', '--short', 'HEAD'],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ['git', 'status', '--porcelain', '--untracked-files=no'],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ''
    return f', commit {rev}' + (' with uncommitted changes' if dirty else '') if rev else ''
