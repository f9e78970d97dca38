"""``bench --suite speed``: how long a whole pass takes, against the truth-tuned Kalman
filter + RTS smoother on the same bag in the same run (issue 18).

One bag of the scenario (seed000_s1 by default) is simulated into a temporary folder; then
- ``orbit-tracking estimate BAG`` runs as its own process, ``repeats`` times, timed from
  process start to exit (its files written): the end-to-end figure a user sees;
- its summary gives each window's solve and knot-selection time and the errors against
  the bag's truth (outside and inside the gaps);
- the baseline reads the same bag (timed) and smooths it with the jerk density that gives
  the smallest position error against the truth (tuning not timed), evaluated at the same
  output times with the same code;
- a profile of one more ``estimate`` (cProfile, in its own process) gives the top lines by
  cumulative time, printed with the table so that the figures say where the time goes.
"""

from __future__ import annotations

import pstats
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

__all__ = ['SPEED_SCENARIO', 'SpeedResult', 'bench_speed', 'profile_lines', 'speed_table']

SPEED_SCENARIO = 'seed000_s1'


@dataclass
class SpeedResult:
    """Figures of one speed run."""

    scenario: str
    messages: int
    values_used: int
    estimate_wall_s: list[float]
    windows: list[dict[str, float]]
    ours: dict[str, dict[str, float]]
    kalman_read_s: float = float('nan')
    kalman_smooth_s: float = float('nan')
    kalman_q: float = float('nan')
    kalman: dict[str, dict[str, float]] = field(default_factory=dict)
    kalman_failure: str = ''
    profile: str = ''


def _estimate_cmd(bag: Path, out: Path) -> list[str]:
    return [
        sys.executable,
        '-m',
        'orbit_tracking.tools.cli',
        'estimate',
        str(bag),
        '--out',
        str(out),
        '--force',
        '--quiet',
    ]


def _run_estimate(bag: Path, out: Path) -> float:
    start = time.perf_counter()
    proc = subprocess.run(_estimate_cmd(bag, out), capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f'estimate failed ({proc.returncode}): {proc.stderr[-2000:]}')
    return wall


def profile_lines(cmd: list[str], prof: Path, top: int) -> str:
    """Run the Python command ``cmd`` (``[python, ...]``) under cProfile, writing ``prof``;
    its ``top`` functions of ours and of the libraries we drive, by cumulative time."""
    cmd = [cmd[0], '-m', 'cProfile', '-o', str(prof), *cmd[1:]]
    subprocess.run(cmd, capture_output=True, check=True)
    stats = pstats.Stats(str(prof))
    rows = []
    for (file, line, name), (_cc, nc, _tt, ct, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        if 'orbit_tracking' in file or 'rosbags' in file or 'cvxpy' in file:
            short = file.split('site-packages/')[-1].split('orbit_tracking/', 1)[-1]
            rows.append((ct, nc, f'{short}:{line}({name})'))
    rows.sort(reverse=True)
    total = max(r[0] for r in rows) if rows else 0.0
    lines = [f'{"cumulative s":>12} {"calls":>7}  function (of {total:.2f} s profiled)']
    lines += [f'{ct:12.3f} {nc:7d}  {where}' for ct, nc, where in rows[:top]]
    return '\n'.join(lines)


def _kalman(bag: Path, trajectory: Path, res: SpeedResult) -> None:
    """The truth-tuned KF+RTS baseline on the bag, evaluated like ours at the times of our
    ``trajectory.csv``."""
    from orbit_tracking.core.baselines.kalman import KalmanConfig, smooth, tune_on_truth
    from orbit_tracking.core.errors import OrbitTrackingError
    from orbit_tracking.tools.bag_inputs import BagContext, read_for_estimation
    from orbit_tracking.tools.evaluation import evaluate_tracks

    start = time.perf_counter()
    ctx = BagContext.from_custom_data(bag)
    buf, _ = read_for_estimation(bag, ctx, False)
    obs = buf.observations()
    res.kalman_read_s = time.perf_counter() - start
    tid = min(ctx.truth)
    # our output times (stamp seconds in the file) on the bag's time base, to the microsecond
    stamps = np.loadtxt(trajectory, delimiter=',', skiprows=1, usecols=0, dtype=str)
    ref = ctx.timebase.ref_ns if ctx.timebase is not None else 0
    ns = [
        int(a) * 10**9 + int((b + '0' * 9)[:9]) for a, _, b in (s.partition('.') for s in stamps)
    ]
    t = np.array([(k - ref) * 1e-9 for k in ns]).round(6)
    tr = ctx.truth[tid]
    truth = np.stack([np.interp(t, tr.time, tr.position[:, k]) for k in range(3)], axis=1)

    def rms(q: float) -> float:
        x, _ = smooth(obs, tid, t, KalmanConfig(jerk_psd=q)).states(t)
        return float(np.sqrt(np.mean(np.sum((x[:, :3] - truth) ** 2, axis=1))))

    try:
        q, _ = tune_on_truth(rms)
        start = time.perf_counter()
        track = smooth(obs, tid, t, KalmanConfig(jerk_psd=q))
        res.kalman_smooth_s = time.perf_counter() - start
    except OrbitTrackingError as exc:
        res.kalman_failure = str(exc)
        return
    res.kalman_q = q
    x, cov = track.states(t)
    res.kalman = evaluate_tracks(ctx, {tid: (t, x, cov)}).get(tid, {})


def bench_speed(
    scenario: str = SPEED_SCENARIO, repeats: int = 3, progress: bool = True
) -> SpeedResult:
    """Run the speed benchmark on one simulated bag of ``scenario``."""
    from orbit_tracking.core.sim.scenario import load_scenario
    from orbit_tracking.tools.simulate import simulate_to_bag

    say = print if progress else (lambda *_: None)
    with tempfile.TemporaryDirectory(prefix='speed_') as tmp:
        root = Path(tmp)
        bag = root / 'bag'
        n = simulate_to_bag(load_scenario(scenario), bag, progress=False)
        say(f'speed: simulated {n} messages of {scenario}')
        walls = []
        for k in range(repeats):
            walls.append(_run_estimate(bag, root / 'est'))
            say(f'speed: estimate run {k + 1}/{repeats}: {walls[-1]:.2f} s')
        summary = yaml.safe_load((root / 'est' / 'summary.yaml').read_text())
        windows = [
            {
                'start': float(w['start']),
                'end': float(w['end']),
                'solve_s': float(w['solve_time_s']),
                'knot_s': float(w['knot_time_s']),
            }
            for w in summary['windows']
        ]
        tid = min(summary['evaluation'])
        res = SpeedResult(
            scenario=scenario,
            messages=n,
            values_used=sum(sum(w['used'].values()) for w in summary['windows']),
            estimate_wall_s=walls,
            windows=windows,
            ours=summary['evaluation'][tid],
        )
        say('speed: Kalman filter + RTS smoother, tuned on truth ...')
        _kalman(bag, root / 'est' / 'trajectory.csv', res)
        say('speed: profile ...')
        res.profile = profile_lines(_estimate_cmd(bag, root / 'prof_est'), root / 'prof', 25)
    return res


def _acc(ev: dict[str, dict[str, float]], where: str) -> str:
    e = ev.get(where)
    if not e:
        return '–'
    return (
        f'{e["rms_position_m"]:.3f} m, {e["rms_velocity_m_s"]:.4f} m/s, '
        f'NEES {e["mean_nees_position"]:.2f}'
    )


def speed_table(res: SpeedResult) -> str:
    """Markdown: the figures against issue 18's targets, and the profile."""
    wall = statistics.median(res.estimate_wall_s)
    kf_total = res.kalman_read_s + res.kalman_smooth_s
    ratio = kf_total / wall if wall > 0 else float('nan')
    worst_win = max(w['solve_s'] for w in res.windows)
    # knot selection covers the three axes of a window
    worst_knot = max(w['knot_s'] for w in res.windows) / 3.0
    lines = [
        f'Scenario `{res.scenario}`: {res.messages} messages, {res.values_used} measured values '
        f'used in {len(res.windows)} windows.',
        '',
        '| figure | ours | KF + RTS (tuned on truth) | target |',
        '|---|---|---|---|',
        f'| end to end (process start to files written), median of '
        f'{len(res.estimate_wall_s)} | {wall:.2f} s | {kf_total:.2f} s (read '
        f'{res.kalman_read_s:.2f} s + smooth {res.kalman_smooth_s:.2f} s, in process) '
        f'| < 1 s |',
        f'| speed-up over the baseline | {ratio:.1f}× | 1× | ≥ 10× |',
        f'| slowest window (solve) | {worst_win:.2f} s | – | < 0.3 s |',
        f'| knot selection per axis (slowest window; the first loads cvxpy) '
        f'| {worst_knot:.2f} s | – | < 0.1 s |',
        f'| error outside gaps (RMS pos, vel; mean NEES) | {_acc(res.ours, "outside_gaps")} '
        f'| {_acc(res.kalman, "outside_gaps")} | equal or better |',
        f'| error inside gaps | {_acc(res.ours, "inside_gaps")} '
        f'| {_acc(res.kalman, "inside_gaps")} | equal or better |',
    ]
    if res.kalman_failure:
        lines.append(f'\nThe baseline failed: {res.kalman_failure}')
    else:
        lines.append(f'\nBaseline jerk density tuned on truth: q = {res.kalman_q:.3g} m²/s⁵.')
    lines += [
        '',
        'Windows: '
        + '; '.join(
            f'{w["start"]:.0f}–{w["end"]:.0f} s solve {w["solve_s"]:.2f} s '
            f'(knots {w["knot_s"]:.2f} s)'
            for w in res.windows
        )
        + '.',
        '',
        'Where the time of one `estimate` goes (cProfile, cumulative, our code and the '
        'libraries it drives; the process total includes imports):',
        '',
        '```',
        res.profile,
        '```',
    ]
    return '\n'.join(lines)
