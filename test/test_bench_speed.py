"""The speed benchmark's table (``bench --suite speed``): the figures it is given, against
issue 18's targets, and the profile reader on a real profile of an ``estimate`` process."""

from __future__ import annotations

import sys

from orbit_tracking.tools.bench.speed import SpeedResult, profile_lines, speed_table


def _result(**kw: object) -> SpeedResult:
    ev = {
        'outside_gaps': {
            'rms_position_m': 0.03,
            'rms_velocity_m_s': 0.006,
            'mean_nees_position': 2.4,
        },
        'inside_gaps': {
            'rms_position_m': 0.05,
            'rms_velocity_m_s': 0.005,
            'mean_nees_position': 1.1,
        },
    }
    base = dict(
        scenario='seed000_s1',
        messages=21615,
        values_used=44041,
        estimate_wall_s=[9.0, 4.0, 5.0],
        windows=[
            {'start': 0.0, 'end': 60.0, 'solve_s': 1.5, 'knot_s': 0.6},
            {'start': 40.0, 'end': 94.0, 'solve_s': 1.2, 'knot_s': 0.3},
        ],
        ours=ev,
        kalman_read_s=2.0,
        kalman_smooth_s=8.0,
        kalman_q=0.003,
        kalman={'outside_gaps': ev['outside_gaps']},
        profile='(profile)',
    )
    base.update(kw)
    return SpeedResult(**base)  # type: ignore[arg-type]


def test_the_table_states_median_wall_ratio_and_the_slowest_window() -> None:
    text = speed_table(_result())
    assert '| 5.00 s | 10.00 s (read 2.00 s + smooth 8.00 s' in text  # median of 9, 4, 5
    assert '| speed-up over the baseline | 2.0× | 1× | ≥ 10× |' in text
    assert '| slowest window (solve) | 1.50 s |' in text
    assert '(slowest window; the first loads cvxpy) | 0.20 s |' in text
    assert 'q = 0.003' in text and '(profile)' in text
    # the baseline had no states inside the gaps: a dash, not a number
    assert text.count('0.050 m, 0.0050 m/s, NEES 1.10 | – |') == 1


def test_a_failed_baseline_is_said() -> None:
    text = speed_table(_result(kalman={}, kalman_failure='diverged', kalman_q=float('nan')))
    assert 'The baseline failed: diverged' in text


def test_the_profile_of_a_command_lists_our_functions_by_cumulative_time(tmp_path) -> None:
    cmd = [sys.executable, '-m', 'orbit_tracking.tools.cli', 'scenarios']
    text = profile_lines(cmd, tmp_path / 'p.prof', 5)
    lines = text.splitlines()
    assert len(lines) == 6
    assert 'tools/cli.py' in lines[1]
    times = [float(line.split()[0]) for line in lines[1:]]
    assert times == sorted(times, reverse=True) and times[0] > 0
