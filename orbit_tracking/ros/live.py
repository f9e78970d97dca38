"""A live pass over real DDS: the scenario simulator, the triangulation node and a
recorder as separate processes, as a range engineer would run them with ``ros2 run``."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orbit_tracking.ros.bag import read_bag

__all__ = ['LiveResult', 'run_live']


@dataclass(frozen=True)
class LiveResult:
    """Fix messages recorded from ``triangulation/fixes`` during the live pass."""

    stamps_ns: np.ndarray
    positions: np.ndarray
    measurement_points: int
    wall_s: float
    log_dir: Path


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    env['PYTHONUNBUFFERED'] = '1'
    return env


def _node(module: str, params: dict[str, object]) -> list[str]:
    cmd = [sys.executable, '-m', f'orbit_tracking.ros.{module}', '--ros-args']
    for k, v in params.items():
        val = ('true' if v else 'false') if isinstance(v, bool) else str(v)
        cmd += ['-p', f'{k}:={val}']
    return cmd


def _start(cmd: Sequence[str], log: Path) -> subprocess.Popen[bytes]:
    fh = open(log, 'wb')  # noqa: SIM115 - closed when the process is reaped
    return subprocess.Popen(
        list(cmd), env=_env(), stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
    )


def _stop(proc: subprocess.Popen[bytes], timeout: float = 10.0) -> None:
    if proc.poll() is None:
        proc.send_signal(2)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)


def _wait_for_recorder(
    tri: subprocess.Popen[bytes], rec: subprocess.Popen[bytes], timeout: float
) -> None:
    """Block until the recorder reads ``/triangulation/fixes``, so no fix is lost before
    the simulator starts (the simulator itself waits for its own readers)."""
    import rclpy

    os.environ.update({k: v for k, v in _env().items() if k.startswith('ROS_')})
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node('orbit_tracking_live_monitor', context=context)
        start = time.monotonic()
        while (
            node.count_subscribers('/triangulation/fixes') < 1
            or node.count_publishers('/triangulation/fixes') < 1
        ):
            if tri.poll() is not None or rec.poll() is not None:
                raise RuntimeError(
                    'live pass: the triangulation node or the recorder exited early'
                )
            if time.monotonic() - start > timeout:
                raise RuntimeError(
                    'live pass: the recorder did not subscribe to /triangulation/fixes'
                )
            time.sleep(0.1)
        time.sleep(0.5)  # endpoint matching follows graph discovery closely; leave it a moment
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def run_live(
    scenario: str, out: Path, rate_factor: float = 20.0, timeout: float = 300.0
) -> LiveResult:
    """Stream ``scenario`` through ``scenario_sim`` -> ``triangulation`` and record the
    measurements and fixes to ``out/live_bag``; node logs go to ``out/logs``.

    Raises
    ------
    RuntimeError
        If a process fails or the pass does not finish within ``timeout`` seconds.
    """
    logs = out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    bag = out / 'live_bag'
    t0 = time.monotonic()
    tri = _start(
        _node('triangulation_node', {'lag': 0.5, 'flush_after': 1.0}), logs / 'triangulation.log'
    )
    rec = _start(
        [
            sys.executable,
            '-m',
            'orbit_tracking.cli',
            'record',
            '--out',
            str(bag),
            '--idle',
            '4',
            '--topics',
            '/triangulation/fixes',
            '/stations/*/measurements',
            '/stations/*/state',
        ],
        logs / 'recorder.log',
    )
    _wait_for_recorder(tri, rec, timeout=60.0)
    batch = 0.25 if rate_factor >= 10.0 else 0.0
    sim = _start(
        _node(
            'scenario_sim',
            {
                'scenario': scenario,
                'rate_factor': rate_factor,
                'batch_period': batch,
                'wait_for_subscribers': 2,
                'wait_timeout': 30.0,
                'shutdown_when_done': True,
                'publish_truth': False,
                'publish_telemetry': False,
            },
        ),
        logs / 'scenario_sim.log',
    )
    procs = {'scenario_sim': sim, 'recorder': rec, 'triangulation': tri}
    try:
        for name, proc in (('scenario_sim', sim), ('recorder', rec)):
            remaining = timeout - (time.monotonic() - t0)
            try:
                code = proc.wait(max(remaining, 1.0))
            except subprocess.TimeoutExpired:
                raise RuntimeError(
                    f'live pass: {name} did not finish in {timeout:.0f} s (logs in {logs})'
                ) from None
            if code != 0:
                raise RuntimeError(
                    f'live pass: {name} exited with status {code} (see {logs / (name + ".log")})'
                )
    finally:
        for p in procs.values():
            _stop(p)
    stamps, pos, points = [], [], 0
    for m in read_bag(bag):
        if m.topic.lstrip('/') == 'triangulation/fixes':
            stamps.append(m.msg.header.stamp.sec * 1_000_000_000 + m.msg.header.stamp.nanosec)
            p = m.msg.pose.pose.position
            pos.append((p.x, p.y, p.z))
        elif m.topic.endswith('/measurements'):
            points += m.msg.width * m.msg.height
    order = np.argsort(stamps)
    return LiveResult(
        np.asarray(stamps, dtype=np.int64)[order],
        np.asarray(pos, dtype=np.float64).reshape(-1, 3)[order],
        points,
        time.monotonic() - t0,
        logs,
    )
