"""Bag replay regression: passes recorded from the simulator over DDS (``test/data/bags``,
written by ``test/data/make_bags.py``) replayed with ``orbit-tracking replay`` through the
running ``triangulation``, ``estimator`` and ``results`` nodes, each its own process, over
real DDS. The stitched ``trajectory/states`` must agree with the truth recorded in the bag
within its own published covariance, and must not depend on the replay speed.

The bags' topic names are absolute (``/stations/...``, as ``ros2 bag record`` stores them),
so the nodes run in the root namespace; the DDS domain of the test run keeps them apart
from other runs (see conftest.py).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import TRACEBACK, stop_process
from scipy import stats

DATA = Path(__file__).resolve().parent / 'data'
EPOCH = 1_700_000_000
"""Stamp [s] of scenario time 0 in both bags: every node's ``time_reference``."""

BAGS = ('seed000_s1_20_50', 'seed003_q2_60_90')
PLAYED = ('/stations/*', '/telemetry/state')
"""Topics replayed: the nodes' inputs (not the truth)."""

OUTPUT_STEP = 0.1
"""Spacing of the published states [s]: the truth's (10 Hz) in both bags."""

WINDOWS = {
    'window_length': 12.0,
    'window_overlap': 4.0,
    'latency': 2.0,
    'output_step': OUTPUT_STEP,
}
"""The estimator's windows: four, with three hand-overs, over the 30 s of each bag."""

PROCESSING = ('triangulation', 'estimator', 'results')
"""The processing nodes (executables, node names), in the root namespace."""

OVERRIDES: dict[str, dict[str, object]] = {
    'triangulation': {'time_reference': float(EPOCH)},
    'estimator': {'time_reference': float(EPOCH), **WINDOWS},
    # the test flushes the tail on request (~/flush), once the last window is in
    'results': {'time_reference': float(EPOCH), 'flush_after': 3600.0},
}
"""Parameters set on top of each node's ``config/<node>.yaml``."""

FAST, SLOW = 10.0, 1.0
"""Replay rates compared."""

ALPHA = 0.01
"""False-alarm probability of each statistical check, were the errors as the covariance
says."""

_RUNS: dict[tuple[str, float], Replay] = {}
"""Replays already run in this session, shared by the tests (a replay at 1x takes 30 s)."""


# -- what a replay gives ------------------------------------------------------------------


@dataclass
class Replay:
    """What a replay of one bag through the nodes published, as received here.

    ``stamps`` (n,) int ns; ``state`` (n, 6) position [m] and velocity [m/s];
    ``pos_cov``, ``vel_cov`` (n, 3, 3); ``windows`` the decoded
    ``estimator/window_states``; ``fixes`` the stamps [ns] of ``triangulation/fixes``.
    """

    bag: str
    rate: float
    stamps: np.ndarray
    state: np.ndarray
    pos_cov: np.ndarray
    vel_cov: np.ndarray
    windows: list[Any]
    fixes: np.ndarray
    wall_s: float
    logs: dict[str, str] = field(default_factory=dict)


def _stamp(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _bag_inputs(bag: Path) -> tuple[int, float, bool]:
    """Messages replayed, the newest measurement epoch [s after EPOCH] and whether the bag
    has telemetry."""
    from orbit_tracking.ros.bag import read_bag
    from orbit_tracking.ros.conversions import TimeBase, cloud_to_measurements

    tb = TimeBase.from_seconds(EPOCH)
    n, newest, telemetry = 0, -math.inf, False
    for m in read_bag(bag):
        if m.topic.startswith('/stations/'):
            n += 1
            if m.topic.endswith('/measurements'):
                newest = max(newest, float(cloud_to_measurements(m.msg, tb).time.max()))
        elif m.topic == '/telemetry/state':
            n += 1
            telemetry = True
    return n, newest, telemetry


def _truth(bag: Path) -> dict[int, np.ndarray]:
    """The bag's ``truth/state``: stamp [ns] -> position and velocity (6,)."""
    from orbit_tracking.ros.bag import read_bag

    out = {}
    for m in read_bag(bag, ['/truth/state']):
        p, v = m.msg.pose.pose.position, m.msg.twist.twist.linear
        out[_stamp(m.msg.header)] = np.array([p.x, p.y, p.z, v.x, v.y, v.z])
    return out


def _wait(
    node: Any,
    predicate: Callable[[], bool],
    timeout: float,
    what: Callable[[], str],
    procs: dict[str, Any],
) -> None:
    """Spin until ``predicate()``; fail at once if a node process exits or the estimator
    reports a failed window meanwhile (no later window would make up for it)."""
    start = time.monotonic()
    checked = start
    while not predicate():
        now = time.monotonic()
        dead = {
            k: p.returncode for k, p in procs.items() if k in PROCESSING and p.poll() is not None
        }
        if dead:
            pytest.fail(f'node process(es) exited {dead} while waiting for {what()}')
        if now - checked > 1.0 and 'estimator' in procs:
            checked = now
            failed = [
                line for line in procs['estimator'].errors().splitlines() if ' failed (' in line
            ]
            if failed:
                pytest.fail(f'the estimator failed a window while waiting for {what()}: {failed}')
        if now - start > timeout:
            pytest.fail(f'timed out after {timeout:.0f} s waiting for {what()}')
        node.executor.spin_once(timeout_sec=0.05)


def replay(name: str, rate: float, start_process: Any, rclpy_node: Any) -> Replay:
    """Replay bag ``name`` at ``rate`` through triangulation -> estimator -> results and
    collect the stitched trajectory; the node processes are stopped at the end."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from orbit_tracking.core.estimation.windows import handover_span, output_times
    from orbit_tracking.ros import qos
    from orbit_tracking.ros.conversions import (
        TimeBase,
        cloud_to_window_states,
        odometry_to_target_state,
    )
    from orbit_tracking.tools.live import NODES, node_command, package_location

    bag = DATA / 'bags' / name
    n_played, newest, has_telemetry = _bag_inputs(bag)
    tb = TimeBase.from_seconds(EPOCH)
    t_start = time.monotonic()
    # the nodes of a previous replay (same topics) must be gone from the graph
    _wait(
        rclpy_node,
        lambda: not set(PROCESSING) & set(rclpy_node.get_node_names()),
        30,
        lambda: f'the nodes of the previous replay to leave: {rclpy_node.get_node_names()}',
        {},
    )
    # started as the main job starts them (orbit_tracking.tools.live): the installed executable
    # as ros2 run does when this runs from an install space, else python -m from the
    # source tree; each with its config/<node>.yaml and the overrides
    where = package_location()
    spec = {s.executable: s for s in NODES}
    procs = {
        exe: start_process(node_command(spec[exe], where, OVERRIDES[exe]), label=exe)
        for exe in PROCESSING
    }
    states: list[Odometry] = []
    windows: list[PointCloud2] = []
    fixes: list[int] = []
    subs = [
        rclpy_node.create_subscription(
            Odometry, '/trajectory/states', states.append, qos.MEASUREMENTS_SUB
        ),
        rclpy_node.create_subscription(
            PointCloud2, '/estimator/window_states', windows.append, qos.MEASUREMENTS_SUB
        ),
        rclpy_node.create_subscription(
            PoseWithCovarianceStamped,
            '/triangulation/fixes',
            lambda m: fixes.append(_stamp(m.header)),
            qos.MEASUREMENTS_SUB,
        ),
    ]
    if has_telemetry:
        # a second reader besides the estimator, so that the player's wait for two readers
        # per topic covers telemetry too
        subs.append(
            rclpy_node.create_subscription(
                Odometry, '/telemetry/state', lambda _m: None, qos.MEASUREMENTS_SUB
            )
        )
    client = rclpy_node.create_client(Trigger, '/results/flush')
    try:
        graph = {
            ('pub', '/triangulation/fixes'): 1,
            ('sub', '/triangulation/fixes'): 2,  # the estimator and us
            ('pub', '/estimator/window_states'): 1,
            ('sub', '/estimator/window_states'): 2,  # the results node and us
            ('pub', '/trajectory/states'): 1,
        }

        def count(kind: str, topic: str) -> int:
            f = rclpy_node.count_publishers if kind == 'pub' else rclpy_node.count_subscribers
            return int(f(topic))

        _wait(
            rclpy_node,
            lambda: all(count(*k) >= n for k, n in graph.items()),
            90,
            lambda: f'the nodes to come up: {[(k, count(*k)) for k in graph]}',
            procs,
        )
        # the player waits (up to 90 s) until the triangulation and estimator nodes, which
        # subscribe to station topics as they appear, read every one of them
        procs['replay'] = start_process(
            [sys.executable, '-m', 'orbit_tracking.tools.cli', 'replay', str(bag)]
            + ['--rate', str(rate), '--topics', *PLAYED]
            + ['--wait-for-subscribers', '2', '--wait-timeout', '90'],
            label='replay',
        )
        t_windows: list[float] = []

        def last_window_end() -> float:
            while len(t_windows) < len(windows):
                t_windows.append(cloud_to_window_states(windows[len(t_windows)], tb).t1)
            return max(t_windows, default=-math.inf)

        _wait(
            rclpy_node,
            lambda: procs['replay'].poll() is not None and last_window_end() >= newest - 1e-6,
            120 + 40 / rate,
            lambda: (
                f'the replay to end and the last window, cut at {newest:.3f} s; windows '
                f'so far end at {[round(t, 3) for t in t_windows]}'
            ),
            procs,
        )
        assert procs['replay'].returncode == 0
        assert f'played {n_played} messages' in procs['replay'].output()

        # every state the stitch can give: the output times of every window (one target)
        decoded = [cloud_to_window_states(m, tb) for m in windows]
        spans = [(w.t0, w.t1) for w in decoded]
        assert spans == sorted(spans) and len(spans) >= 3, spans
        grid = np.unique(np.concatenate([output_times(a, b, OUTPUT_STEP) for a, b in spans]))
        h0 = handover_span(spans[-2], spans[-1])[0]
        before_last = int(np.count_nonzero(grid < h0))
        _wait(
            rclpy_node,
            lambda: len(states) >= before_last,
            60,
            lambda: f'the {before_last} states made final by the last window; got {len(states)}',
            procs,
        )
        assert client.wait_for_service(timeout_sec=20.0)
        future = client.call_async(Trigger.Request())
        _wait(rclpy_node, future.done, 30, lambda: 'the results ~/flush response', procs)
        _wait(
            rclpy_node,
            lambda: len(states) >= grid.size,
            30,
            lambda: f'all {grid.size} states; got {len(states)}',
            procs,
        )
        end = time.monotonic() + 0.5  # and not one more
        while time.monotonic() < end:
            rclpy_node.executor.spin_once(timeout_sec=0.05)
        wall = time.monotonic() - t_start
        for label, proc in procs.items():
            if label != 'replay':
                assert proc.poll() is None, f'{label} exited with status {proc.returncode}'
    finally:
        for sub in subs:
            rclpy_node.destroy_subscription(sub)
        rclpy_node.destroy_client(client)
        for proc in procs.values():
            stop_process(proc)
    logs = {k: p.errors() + p.output() for k, p in procs.items()}
    for label, text in logs.items():
        assert TRACEBACK not in text, f'{label}:\n{text[-5000:]}'
    stamps = np.array([_stamp(m.header) for m in states], dtype=np.int64)
    assert np.all(np.diff(stamps) > 0), 'states not published once each, in time order'
    np.testing.assert_array_equal(stamps, np.array([tb.to_ns(t) for t in grid]))
    solved = [line for line in logs['estimator'].splitlines() if 'GN iterations' in line]
    assert len(solved) == len(decoded), solved
    # a window the solver did not finish cleanly is logged as a warning
    assert all(line.startswith('[INFO]') for line in solved), solved
    samples = [odometry_to_target_state(m, tb) for m in states]
    return Replay(
        name,
        rate,
        stamps,
        np.array([np.concatenate([s.position, s.velocity]) for s in samples]),
        np.array([s.position_cov for s in samples]),
        np.array([s.velocity_cov for s in samples]),
        decoded,
        np.array(sorted(fixes), dtype=np.int64),
        wall,
        logs,
    )


def replayed(name: str, rate: float, *fixtures: Any) -> Replay:
    """A replay of this session, or a new one."""
    key = (name, rate)
    if key not in _RUNS:
        _RUNS[key] = replay(name, rate, *fixtures)
    return _RUNS[key]


# -- the checks -----------------------------------------------------------------------------


@pytest.mark.dds
@pytest.mark.timeout(400)
@pytest.mark.parametrize('name', BAGS)
def test_replayed_trajectory_agrees_with_the_bag_truth_within_its_covariance(
    name, start_process, rclpy_node
):
    """Every component of every state within a normal bound of its own sigma (Bonferroni
    over all of them) and the mean position and velocity NEES in their chi-square band."""
    run = replayed(name, FAST, start_process, rclpy_node)
    truth = _truth(DATA / 'bags' / name)
    missing = [s for s in run.stamps if s not in truth]
    assert not missing, f'no truth at {len(missing)} output stamps, e.g. {missing[:3]}'
    err = run.state - np.array([truth[s] for s in run.stamps])
    sig = np.sqrt(
        np.concatenate(
            [
                np.diagonal(run.pos_cov, axis1=1, axis2=2),
                np.diagonal(run.vel_cov, axis1=1, axis2=2),
            ],
            axis=1,
        )
    )
    z = np.abs(err) / sig
    n = z.size
    # every component: two-sided normal bound, Bonferroni over all of them
    z_bound = stats.norm.isf(ALPHA / (2 * n))
    nees_p = np.einsum('ni,nij,nj->n', err[:, :3], np.linalg.inv(run.pos_cov), err[:, :3])
    nees_v = np.einsum('ni,nij,nj->n', err[:, 3:], np.linalg.inv(run.vel_cov), err[:, 3:])
    # mean NEES (3 dof each) over the pass. Errors of one window are smooth in time, so
    # the states are far from independent: the band takes one independent draw per
    # window, mean ~ chi2(3 k) / k for k windows
    k = len(run.windows)
    band = stats.chi2.ppf([ALPHA / 2, 1 - ALPHA / 2], 3 * k) / k
    worst = np.unravel_index(np.argmax(z), z.shape)
    rms = np.sqrt(np.mean(err**2, axis=0))
    report = (
        f'{name} at {run.rate:g}x: {len(run.stamps)} states in {k} windows; max |z| '
        f'{z.max():.2f} (bound {z_bound:.2f}; component {worst[1]} at '
        f'{(run.stamps[worst[0]] - EPOCH * 10**9) * 1e-9:.1f} s); mean NEES position '
        f'{nees_p.mean():.2f}, velocity {nees_v.mean():.2f} (band {band[0]:.2f}-{band[1]:.2f}); '
        f'RMS error position {np.sqrt(np.sum(rms[:3] ** 2)):.3f} m, velocity '
        f'{np.sqrt(np.sum(rms[3:] ** 2)):.4f} m/s; replay {run.wall_s:.0f} s'
    )
    print(report)
    assert z.max() <= z_bound, report
    assert band[0] <= nees_p.mean() <= band[1], report
    assert band[0] <= nees_v.mean() <= band[1], report


@pytest.mark.dds
@pytest.mark.timeout(400)
@pytest.mark.parametrize('name', BAGS)
def test_replay_at_1x_and_10x_gives_the_same_trajectory(name, start_process, rclpy_node):
    """The nodes compute from stamps, not from arrival times: the replay speed changes
    nothing (the same windows, states and covariances to 1e-9)."""
    fast = replayed(name, FAST, start_process, rclpy_node)
    slow = replayed(name, SLOW, start_process, rclpy_node)
    diff = _differences(slow, fast)
    print(diff)
    assert [(w.t0, w.t1) for w in slow.windows] == [(w.t0, w.t1) for w in fast.windows], diff
    np.testing.assert_array_equal(slow.stamps, fast.stamps, err_msg=diff)
    for what in ('state', 'pos_cov', 'vel_cov'):
        a, b = getattr(slow, what), getattr(fast, what)
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9, err_msg=f'{what}: {diff}')


def _differences(a: Replay, b: Replay) -> str:
    """Where two replays differ: windows (span, largest state and covariance difference),
    fixes, and the stitched states."""
    lines = [f'{a.bag}: {a.rate:g}x ({a.wall_s:.0f} s) vs {b.rate:g}x ({b.wall_s:.0f} s)']
    for i, (wa, wb) in enumerate(zip(a.windows, b.windows, strict=False)):
        line = f'  window {i}: [{wa.t0:.3f}, {wa.t1:.3f}] vs [{wb.t0:.3f}, {wb.t1:.3f}]'
        if wa.time.shape == wb.time.shape:
            dx = np.abs(wa.state - wb.state)
            dc = np.abs(wa.covariance - wb.covariance)
            line += (
                f', max |d position| {dx[:, :3].max():.3g} m, |d velocity| '
                f'{dx[:, 3:].max():.3g} m/s, |d cov| {dc.max():.3g}'
            )
        lines.append(line)
    if len(a.windows) != len(b.windows):
        lines.append(f'  {len(a.windows)} vs {len(b.windows)} windows')
    same = a.fixes.shape == b.fixes.shape and np.array_equal(a.fixes, b.fixes)
    lines.append(
        f'  fixes: {a.fixes.size} vs {b.fixes.size}'
        + ('' if same else f' (stamps differ: {np.setxor1d(a.fixes, b.fixes).size} not in both)')
    )
    if a.stamps.shape == b.stamps.shape:
        d = np.abs(a.state - b.state)
        rel = d / np.maximum(np.abs(a.state), 1e-300)
        t = (a.stamps - EPOCH * 10**9) * 1e-9
        bad = np.any(d > 1e-9, axis=1)
        lines.append(
            f'  states: max |d position| {d[:, :3].max():.3g} m (relative '
            f'{rel[:, :3].max():.2g}), |d velocity| {d[:, 3:].max():.3g} m/s, |d position cov| '
            f'{np.abs(a.pos_cov - b.pos_cov).max():.3g} m2, |d velocity cov| '
            f'{np.abs(a.vel_cov - b.vel_cov).max():.3g} m2/s2; '
            f'{int(bad.sum())} of {bad.size} states differ by more than 1e-9'
            + (f', from {t[bad].min():.1f} s to {t[bad].max():.1f} s' if bad.any() else '')
        )
    else:
        lines.append(f'  {a.stamps.size} vs {b.stamps.size} states')
    return '\n'.join(lines)
