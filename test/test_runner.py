"""``run_node``: a RuntimeError out of ``spin`` is a shutdown only if the context goes down.

Under load, a SIGINT that lands inside rclpy's C++ message conversion surfaces as a
RuntimeError before rclpy's signal thread has shut the context down (a CI failure of the
estimator's start/stop test). Each case runs in its own interpreter, as a node does.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
from conftest import ROOT

SCRIPT = textwrap.dedent(
    """
    import sys, threading, time
    import rclpy
    from rclpy.node import Node
    from orbit_tracking.ros import runner

    runner.SHUTDOWN_GRACE_S = 0.5
    SHUTDOWN_AFTER_S = float(sys.argv[1])  # < 0: the context stays up

    class Failing(Node):
        def __init__(self):
            super().__init__('runner_test')
            self.create_timer(0.05, self.tick)

        def tick(self):
            if SHUTDOWN_AFTER_S >= 0:
                threading.Timer(SHUTDOWN_AFTER_S, rclpy.try_shutdown).start()
            raise RuntimeError('Unable to convert call argument 0 to Python object')

    runner.run_node(Failing, [])
    print('clean exit')
    """
)


def _run(shutdown_after_s: float) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=f'{ROOT}{os.pathsep}{os.environ.get("PYTHONPATH", "")}')
    return subprocess.run(
        [sys.executable, '-c', SCRIPT, str(shutdown_after_s)],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.dds
@pytest.mark.parametrize('shutdown_after_s', [0.0, 0.2])
def test_runtime_error_during_a_late_shutdown_is_a_clean_exit(shutdown_after_s: float) -> None:
    proc = _run(shutdown_after_s)
    assert proc.returncode == 0, proc.stderr
    assert 'clean exit' in proc.stdout
    assert 'Traceback' not in proc.stderr


@pytest.mark.dds
def test_runtime_error_with_the_context_up_is_raised() -> None:
    proc = _run(-1.0)
    assert proc.returncode != 0
    assert 'Unable to convert call argument' in proc.stderr
    assert 'clean exit' not in proc.stdout


HANGING_CLEANUP = textwrap.dedent(
    """
    import time
    from rclpy.node import Node
    from orbit_tracking.ros import runner

    runner.CLEANUP_LIMIT_S = 1.0

    class Stuck(Node):
        def __init__(self):
            super().__init__('runner_stuck_test')
            self.create_timer(0.05, self.stop)

        def stop(self):
            raise KeyboardInterrupt

        def destroy_node(self):
            time.sleep(60.0)  # as rclpy's destroy_node once hung in CI

    runner.run_node(Stuck, [])
    print('returned')
    """
)


@pytest.mark.dds
def test_a_hanging_cleanup_ends_the_process_with_a_stack_dump() -> None:
    env = dict(os.environ, PYTHONPATH=f'{ROOT}{os.pathsep}{os.environ.get("PYTHONPATH", "")}')
    proc = subprocess.run(
        [sys.executable, '-c', HANGING_CLEANUP],
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 1, proc.stderr
    assert 'returned' not in proc.stdout
    assert 'destroy_node' in proc.stderr  # where it hung
