"""Sliding windows (core/windows.py): which spans are solved, how overlapping solutions are
handed over, and the trajectory.csv file."""

from __future__ import annotations

import csv
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.estimation.bspline import SplineAxis, SplineTrajectory
from orbit_tracking.core.estimation.config import EstimationError, EstimatorConfig
from orbit_tracking.core.estimation.estimator import estimate
from orbit_tracking.core.estimation.knots import KnotSelection
from orbit_tracking.core.estimation.results import Estimate, TargetSolution
from orbit_tracking.core.estimation.windows import (
    TRAJECTORY_CSV_COLUMNS,
    WindowConfig,
    WindowScheduler,
    handover_weights,
    output_times,
    plan_windows,
    read_trajectory_csv,
    solve_windows,
    stitch,
    write_trajectory_csv,
)
from orbit_tracking.core.metrics import hermite_states
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate

EPOCH_NS = 1_700_000_000 * 1_000_000_000

SHORT_SCENARIO = """\
base: seed000_s1
name: short_s1
description: seed000_s1 cut to 30 s, with a 6 s incomplete segment (tests)
span: [0.0, 30.0]
evaluation: {gaps: [{start: 12.0, end: 18.0}], output_step_s: 1.0}
stations:
"""
DROPPING = ('cw01', 'cw02', 'cw04', 'cw05', 'cw06', 'cw08', 'cw09')
DROPPING_OPTICAL = ('opt01', 'opt02', 'opt03', 'opt04')


def write_short_scenario(folder: Path, telemetry: bool = True) -> Path:
    """seed000_s1 cut to 30 s; as in the full scenario only cw03 and cw07 measure in the gap
    (12-18 s here). Used by these tests and the estimator node's."""
    text = SHORT_SCENARIO + ''.join(
        f'  - {{id: {s}, dropouts: [{{start: 12.0, end: 18.0}}]}}\n'
        for s in (*DROPPING, *DROPPING_OPTICAL)
    )
    if not telemetry:
        text = text.replace('name: short_s1\n', 'name: short_s1_no_telemetry\ntelemetry: null\n')
    path = folder / ('short_s1.yaml' if telemetry else 'short_s1_no_telemetry.yaml')
    path.write_text(text)
    return path


# -- configuration and scheduling ----------------------------------------------------------


@pytest.mark.parametrize(
    'kwargs',
    [
        {'length': 0.0},
        {'length': 10.0, 'overlap': 6.0},
        {'overlap': -1.0},
        {'latency': -0.5},
        {'output_step': 0.0},
        {'length': math.inf},
    ],
)
def test_window_config_rejects_inconsistent_settings(kwargs):
    with pytest.raises(ValueError, match='window|output_step'):
        WindowConfig(**kwargs)


def test_scheduler_hands_out_overlapping_windows_once_the_latency_has_passed():
    sched = WindowScheduler(WindowConfig(length=60.0, overlap=20.0, latency=2.0))
    got = []
    for latest in np.arange(5.0, 150.0, 0.5):
        first = 5.0 if sched.next_t0 is None else sched.next_t0
        span = sched.next_window(first, float(latest))
        if span is not None:
            got.append((float(latest), span))
    assert got == [(67.0, (5.0, 65.0)), (107.0, (45.0, 105.0)), (147.0, (85.0, 145.0))]


def test_scheduler_cuts_the_last_window_at_the_end_of_data_and_pulls_its_start_back():
    sched = WindowScheduler(WindowConfig(length=60.0, overlap=20.0, latency=2.0))
    assert sched.next_window(0.0, 63.0) == (0.0, 60.0)
    # the stream ends 5 s after that window: the cut window is half a window long
    assert sched.next_window(40.0, 65.0, final=True) == (35.0, 65.0)
    assert sched.next_window(45.0, 65.0, final=True) is None  # nothing new
    # a stream shorter than one window gives one window over all of it
    short = WindowScheduler(WindowConfig(length=60.0, overlap=20.0))
    assert short.next_window(1.0, 30.0) is None
    assert short.next_window(1.0, 30.0, final=True) == (1.0, 30.0)


def test_scheduler_starts_at_the_new_data_after_a_pause_between_passes():
    sched = WindowScheduler(WindowConfig(length=60.0, overlap=20.0, latency=2.0))
    assert sched.next_window(0.0, 62.0) == (0.0, 60.0)
    # no data between 60 s and 500 s: the next window starts where the data resume
    assert sched.next_window(500.0, 562.0) == (500.0, 560.0)
    assert sched.next_window(540.0, 600.0) is None


@pytest.mark.parametrize('huge', [1e18, -1e18, 1e300])
def test_scheduler_cannot_stall_on_times_a_window_length_does_not_change(huge):
    """Issue 13: a time of 1e18 s made ``t0 + length == t0`` and the node's loop handed out
    the same window forever."""
    cfg = WindowConfig(length=60.0, overlap=20.0, latency=2.0)
    sched = WindowScheduler(cfg)
    assert sched.next_window(0.0, 63.0) == (0.0, 60.0)
    # what a caller does: ask until None; it must end, and never repeat a window
    spans = []
    for final in (False, True):
        while (span := sched.next_window(huge, huge, final)) is not None:
            assert span not in spans and len(spans) < 3
            spans.append(span)
    assert spans == []
    planned = plan_windows([0.0, 10.0, huge], cfg)  # ends
    assert all(b - a >= 30.0 for a, b in planned) and len(planned) <= 2
    assert plan_windows([huge, huge], cfg) == []


def test_scheduler_never_hands_out_a_window_that_does_not_move_forward():
    sched = WindowScheduler(WindowConfig(length=60.0, overlap=20.0, latency=2.0))
    assert sched.next_window(0.0, 63.0) == (0.0, 60.0)
    before = (sched.last, sched.next_t0)
    assert sched._hand_out((0.0, 60.0)) is None  # the same window again
    assert sched._hand_out((10.0, 50.0)) is None  # ends earlier
    assert (sched.last, sched.next_t0) == before


def test_plan_windows_covers_the_data_with_the_configured_overlap():
    t = np.arange(0.0, 100.0, 0.05)
    spans = plan_windows(t[::-1], WindowConfig(length=30.0, overlap=10.0))
    assert spans[0][0] == 0.0 and spans[-1][1] == pytest.approx(t[-1])
    for (a0, a1), (b0, b1) in zip(spans, spans[1:], strict=False):
        assert a1 - a0 == pytest.approx(30.0)
        assert a1 - b0 == pytest.approx(10.0) or b0 < a1 - 10.0  # the last one is pulled back
        assert b1 > a1
    assert spans[-1][1] - spans[-1][0] >= 15.0
    assert plan_windows([], WindowConfig()) == []


def test_output_times_are_the_multiples_of_the_step_inside_the_span():
    t = output_times(0.25, 1.0, 0.1)
    assert np.allclose(t, [0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0])
    assert output_times(0.31, 0.39, 0.1).size == 0


# -- stitching ------------------------------------------------------------------------------


def _linear_window(t0: float, t1: float, offset: float, sigma: float) -> Estimate:
    """A window whose solution is ``x(t) = v t + offset`` on every axis with coefficient
    sigma ``sigma`` (a degree-1 spline: coefficients are the end positions)."""
    axis = SplineAxis.from_interior([], t0, t1, 1)
    traj = SplineTrajectory((axis, axis, axis), np.zeros(3), np.eye(3))
    v = np.array([10.0, -20.0, 5.0])
    coef = np.concatenate([[v[c] * t0 + offset, v[c] * t1 + offset] for c in range(3)])
    sel = KnotSelection(traj, coef, (), (0, 0, 0), (0, 0, 0), 0, 0.0, 0.0, 'test')
    sol = TargetSolution(0, traj, coef, sigma**2 * np.eye(6), sel, ())
    return Estimate(
        True, 'test', t0, t1, {0: sol}, 1, 0, 0.0, 1.0, 1.0, 6, Counter(), Counter(), {}, 0.0, 0.0
    )


def test_stitch_blends_linearly_across_the_middle_half_of_the_overlap():
    a = _linear_window(0.0, 60.0, offset=0.0, sigma=0.1)
    b = _linear_window(40.0, 100.0, offset=1.0, sigma=0.3)
    t = output_times(0.0, 100.0, 0.5)
    tt, x, cov = stitch([b, a], t)
    assert np.array_equal(tt, t)
    xa, pa = a.targets[0].states(np.clip(t, 0.0, 60.0))
    xb, pb = b.targets[0].states(np.clip(t, 40.0, 100.0))
    w = np.clip((55.0 - t) / 10.0, 0.0, 1.0)  # overlap 40-60 s: hand-over 45-55 s
    assert np.allclose(x, w[:, None] * xa + (1 - w[:, None]) * xb, atol=1e-9)
    # the covariances mixed, and the windows' 1 m disagreement as the mixture's spread
    d = xa - xb
    spread = (w * (1 - w))[:, None, None] * d[:, :, None] * d[:, None, :]
    mix = w[:, None, None] * pa + (1 - w[:, None, None]) * pb
    assert np.allclose(cov, mix + spread, atol=1e-12)
    mid = np.argmin(np.abs(t - 50.0))
    assert cov[mid, 0, 0] - mix[mid, 0, 0] == pytest.approx(0.25 * d[mid, 0] ** 2)
    assert abs(d[mid, 0]) == pytest.approx(1.0)
    assert np.allclose(x[t <= 45.0], xa[t <= 45.0]) and np.allclose(x[t >= 55.0], xb[t >= 55.0])
    # the 1 m disagreement is spread over the 10 s hand-over: steps of 5 cm, not one 1 m jump
    jump = np.abs(np.diff(x[:, 0]) - 10.0 * 0.5)
    assert jump.max() == pytest.approx(0.05, abs=1e-9)
    hard = np.where(t < 50.0, xa[:, 0], xb[:, 0])
    assert np.abs(np.diff(hard) - 5.0).max() == pytest.approx(1.0, abs=1e-9)


def test_stitch_leaves_out_times_no_window_covers_and_weights_sum_to_one():
    a = _linear_window(0.0, 10.0, 0.0, 0.1)
    b = _linear_window(20.0, 30.0, 0.0, 0.1)
    tt, x, _ = stitch([a, b], output_times(0.0, 30.0, 1.0))
    assert np.array_equal(tt, [*range(0, 11), *range(20, 31)])
    w = handover_weights([(0.0, 12.0), (8.0, 20.0), (9.0, 15.0)], np.linspace(0, 20, 201))
    assert np.allclose(w.sum(axis=0), 1.0)
    assert np.all(w >= 0.0)


@pytest.fixture(scope='module')
def short_pass(tmp_path_factory):
    """The short seed 000 pass solved in 12 s windows overlapping by 4 s (no telemetry
    fused: its covariance is the one checked against truth here)."""
    sc = load_scenario(write_short_scenario(tmp_path_factory.mktemp('scenario')))
    res = simulate(sc)
    obs = Observations.from_simulation(res)
    spans = []
    ests = solve_windows(
        obs,
        EstimatorConfig(use_telemetry=False),
        WindowConfig(length=12.0, overlap=4.0),
        progress=lambda i, n, span, r: spans.append((span, r)),
    )
    return res, ests, spans


def test_solve_windows_solves_every_planned_window_in_order(short_pass):
    _res, ests, spans = short_pass
    assert [s for s, _ in spans] == [(0.0, 12.0), (8.0, 20.0), (16.0, 28.0), (24.0, 30.0)]
    assert all(isinstance(r, Estimate) and r.success for _, r in spans)
    assert [(e.t0, e.t1) for e in ests] == [s for s, _ in spans]


def test_stitched_pass_is_continuous_at_the_seams_and_agrees_with_truth(short_pass):
    res, ests, _ = short_pass
    dt = 0.1
    t, x, cov = stitch(ests, output_times(0.0, 30.0, dt))
    assert t[0] == 0.0 and t[-1] == pytest.approx(30.0) and t.size == 301
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    # A jump is what a step adds beyond the motion (trapezoid rule on the velocity; for
    # this smooth flight that residual is far below a millimetre). Across a hand-over of
    # length h the two windows' disagreement (within ~4 sigma of their difference) is
    # spread over h / dt steps.
    step = np.diff(x[:, :3], axis=0) - 0.5 * dt * (x[1:, 3:] + x[:-1, 3:])
    h = 0.5 * 4.0
    tol = 4.0 * np.sqrt(2.0) * np.maximum(sig[1:, :3], sig[:-1, :3]) * dt / h + 1e-3
    assert np.all(np.abs(step) <= tol), f'largest jump / tolerance {np.max(np.abs(step) / tol)}'
    truth = res.truth[0]
    ep = x[:, :3] - hermite_states(truth.time, truth.position, truth.velocity, t)
    ev = x[:, 3:] - np.stack([np.interp(t, truth.time, truth.velocity[:, c]) for c in range(3)], 1)
    assert np.all(np.abs(ep) <= 5.0 * sig[:, :3])
    assert np.all(np.abs(ev) <= 5.0 * sig[:, 3:] + 2e-3)  # + linear interpolation of truth


# -- trajectory.csv -------------------------------------------------------------------------


def test_trajectory_csv_round_trip_keeps_exact_stamps_and_the_contract_columns(tmp_path):
    rng = np.random.default_rng(3)
    t = output_times(0.0, 2.0, 0.1) + 123456.0
    x = rng.normal(0.0, 1e6, (t.size, 6))
    a = rng.normal(0.0, 1.0, (t.size, 6, 6))
    cov = a @ np.transpose(a, (0, 2, 1)) + 1e-3 * np.eye(6)
    path = tmp_path / 'trajectory.csv'
    assert write_trajectory_csv(path, t, x, cov, EPOCH_NS) == t.size
    with open(path, newline='') as fh:
        header = next(csv.reader(fh))
    contract = 'time,x,y,z,vx,vy,vz,sx,sy,sz,svx,svy,svz'.split(',')
    assert header == contract and tuple(header) == TRAJECTORY_CSV_COLUMNS
    back = read_trajectory_csv(path)
    assert np.array_equal(back['stamp_ns'], EPOCH_NS + np.round(t * 1e9).astype(np.int64))
    assert path.read_text().splitlines()[1].startswith('1700123456.000000000,')
    assert np.allclose(back['state'][:, :3], x[:, :3], rtol=0.0, atol=5e-7)
    assert np.allclose(back['state'][:, 3:], x[:, 3:], rtol=0.0, atol=5e-10)
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    assert np.allclose(back['sigma'], sig, rtol=1e-8)


def test_read_trajectory_csv_rejects_other_columns(tmp_path):
    path = tmp_path / 'fixes.csv'
    path.write_text('time,x,y,z\n1.0,2.0,3.0,4.0\n')
    with pytest.raises(ValueError, match='header must be'):
        read_trajectory_csv(path)


def test_write_trajectory_csv_names_the_offending_shapes(tmp_path):
    with pytest.raises(ValueError, match=r'\(3, 5\)'):
        write_trajectory_csv(
            tmp_path / 't.csv', np.zeros(3), np.zeros((3, 5)), np.zeros((3, 6, 6))
        )


# -- a window whose data stop short of an edge ----------------------------------------------


@pytest.mark.parametrize('cut', [0.3, 1.5])
def test_a_window_is_solved_over_the_span_its_data_cover_when_they_stop_short(short_pass, cut):
    """Station rows that end ``cut`` s before the window's end (a restarted estimator, a pass
    whose data stop): beyond ``edge_gap`` (0.5 s) the window is solved over the span they
    cover, and says so; within it the window keeps its span. Either way the states agree
    with truth within their sigma."""
    res, _ests, _spans = short_pass
    obs = Observations.from_simulation(res)
    cfg = EstimatorConfig(use_telemetry=False)
    last = max(float(s.table.time[-1]) for s in obs.window(0.0, 12.0 - cut).stations)
    e = estimate(obs.window(0.0, 12.0 - cut), 0.0, 12.0, cfg)
    assert e.success, e.message
    if cut > cfg.edge_gap:
        assert (e.t0, e.t1) == (0.0, last)
        assert f'solved over [0.00, {last:.2f}] s' in e.message
    else:
        assert (e.t0, e.t1) == (0.0, 12.0) and 'solved over' not in e.message
    sol = e.targets[0]
    t = output_times(sol.t0, sol.t1, 0.5)
    x, cov = sol.states(t)
    truth = res.truth[0]
    ep = x[:, :3] - hermite_states(truth.time, truth.position, truth.velocity, t)
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))[:, :3]
    assert np.all(np.abs(ep) <= 5.0 * sig)


def test_a_window_whose_data_fill_no_span_is_an_estimation_error(short_pass):
    res, _ests, _spans = short_pass
    obs = Observations.from_simulation(res).window(5.0, 5.0)
    with pytest.raises(EstimationError, match='span only'):
        estimate(obs, 0.0, 12.0, EstimatorConfig(use_telemetry=False))
