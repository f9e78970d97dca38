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


# -- SIGINT / SIGTERM (StopRequest) --------------------------------------------------------

SIGNALLED = textwrap.dedent(
    """
    import os, sys, time
    from rclpy.node import Node
    from orbit_tracking.ros import runner

    WHERE, SECONDS = sys.argv[1], float(sys.argv[2])  # where the callback spends its time
    # code compiled under a file name of the core (numerical work) or of the ROS layer
    BUSY = compile(
        'def busy(seconds):\\n'
        '    end = time.monotonic() + seconds\\n'
        '    while time.monotonic() < end:\\n'
        '        sum(range(1000))\\n',
        os.path.join(runner._PACKAGE, WHERE, 'busy_for_test.py'),
        'exec',
    )
    space = {'time': time}
    exec(BUSY, space)

    class Busy(Node):
        def __init__(self):
            super().__init__('runner_signal_test')
            if WHERE == 'construction':
                print('building', flush=True)
                time.sleep(SECONDS)
            self.create_timer(0.05, self.tick)

        def tick(self):
            print('busy', flush=True)
            if WHERE != 'construction':
                space['busy'](SECONDS)
            print('callback finished', flush=True)

    t0 = time.monotonic()
    runner.run_node(Busy, [])
    print(f'returned after {time.monotonic() - t0:.2f} s', flush=True)
    """
)


def _signalled(where: str, seconds: float, signals: list[int], after: str = 'busy'):
    """Run the script, send ``signals`` (0.3 s apart) once it printed ``after``; return
    (exit status, stdout, stderr, seconds from the first signal to the exit)."""
    import signal as _signal  # noqa: F401  (the caller's signal numbers)
    import time

    env = dict(os.environ, PYTHONPATH=f'{ROOT}{os.pathsep}{os.environ.get("PYTHONPATH", "")}')
    proc = subprocess.Popen(
        [sys.executable, '-c', SIGNALLED, where, str(seconds)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if line.strip() == after:
            break
    time.sleep(0.2)
    t0 = time.monotonic()
    for i, s in enumerate(signals):
        if i:
            time.sleep(0.3)
        proc.send_signal(s)
    try:
        out, err = proc.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, ''.join(lines) + out, err, time.monotonic() - t0


@pytest.mark.dds
@pytest.mark.parametrize('signum', [2, 15])  # SIGINT, SIGTERM
def test_a_signal_interrupts_numerical_work_in_the_core_at_once(signum: int) -> None:
    code, out, err, took = _signalled('core', 60.0, [signum])
    assert code == 0, err
    assert 'callback finished' not in out
    assert 'returned after' in out
    assert 'Traceback' not in err
    assert took < 20.0, f'{took:.1f} s to stop'  # not the 60 s of work


@pytest.mark.dds
def test_a_signal_lets_a_callback_outside_the_core_finish_then_stops() -> None:
    code, out, err, took = _signalled('ros', 3.0, [2])
    assert code == 0, err
    assert out.count('callback finished') == 1  # this one, and no callback after it
    assert out.count('busy') == 1
    assert 'returned after' in out
    assert took < 30.0


@pytest.mark.dds
def test_a_second_signal_interrupts_anywhere() -> None:
    code, out, err, took = _signalled('ros', 60.0, [2, 2])
    assert code == 0, err
    assert 'callback finished' not in out
    assert took < 20.0, f'{took:.1f} s to stop'


@pytest.mark.dds
def test_a_signal_while_the_node_is_built_stops_it_once_built() -> None:
    code, out, err, took = _signalled('construction', 2.0, [2], after='building')
    assert code == 0, err
    assert 'busy' not in out  # no callback ran
    assert 'returned after' in out
    assert 'Traceback' not in err


def test_only_the_cores_numerical_frames_are_interruptible() -> None:
    from orbit_tracking.ros import runner

    def frame_in(rel: str, inner: str | None = None):
        src = 'import sys\ndef f(g):\n    return g() if g else sys._getframe()\n'
        space: dict = {}
        exec(compile(src, os.path.join(runner._PACKAGE, rel), 'exec'), space)
        g = None
        if inner is not None:
            space_inner: dict = {}
            exec(compile(src, inner, 'exec'), space_inner)
            g = lambda: space_inner['f'](None)  # noqa: E731
        return space['f'](g)

    assert runner.interruptible(frame_in('core/estimation/x.py'))
    assert runner.interruptible(frame_in('core/estimation/x.py', '/usr/lib/numpy/core/x.py'))
    assert not runner.interruptible(frame_in('core/data/journal.py'))
    assert not runner.interruptible(frame_in('ros/results_node.py'))
    assert not runner.interruptible(
        frame_in('core/estimation/x.py', '/venv/site-packages/rclpy/publisher.py')
    )
    assert not runner.interruptible(
        frame_in('core/estimation/x.py', '/venv/site-packages/geometry_msgs/msg/_point.py')
    )
    assert not runner.interruptible(None)
