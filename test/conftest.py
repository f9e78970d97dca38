"""Shared fixtures of the ROS-side tests: DDS isolation, node subprocesses, in-process nodes.

DDS isolation is set up at import time (before any test module imports rclpy), so every
process a test starts inherits it:

* ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: nothing leaves the machine;
* ``ROS_DOMAIN_ID``: a per-run domain (``1 + pid % 100``, never 0) unless one is set, so
  parallel test runs do not hear each other;
* ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``: the middleware the project is tested with.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from xdist.scheduler import LoadScopeScheduling

ROOT = Path(__file__).resolve().parents[1]


def _isolate_dds() -> None:
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ['RMW_IMPLEMENTATION'] = 'rmw_fastrtps_cpp'
    if not os.environ.get('ROS_DOMAIN_ID'):
        os.environ['ROS_DOMAIN_ID'] = str(1 + os.getpid() % 100)
    # pytest-xdist workers inherit the controller's domain and must not share it: of n
    # workers, worker k takes the domain k * (100 // n) further (in 1..100; the fault
    # suite's second lane uses the domain after its own, so two workers never meet)
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')
    if worker.startswith('gw') and worker[2:].isdigit():
        base = int(os.environ['ROS_DOMAIN_ID'])
        step = 100 // max(2, int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '2')))
        os.environ['ROS_DOMAIN_ID'] = str((base - 1 + step * int(worker[2:])) % 100 + 1)


_isolate_dds()

CLEAN_EXIT_CODES = {0, -signal.SIGINT, 128 + signal.SIGINT}
"""Exit statuses of a node that shut down cleanly on SIGINT."""

TRACEBACK = 'Traceback (most recent call last)'


_DDS_MODULES: dict[str, bool] = {}


def _is_dds_module(module: str) -> bool:
    """Whether the test module at ``module`` (a path relative to the root) has a ``dds``
    test: read from its source, as the xdist controller has no test items."""
    if module not in _DDS_MODULES:
        path = ROOT / module
        _DDS_MODULES[module] = path.is_file() and 'pytest.mark.dds' in path.read_text()
    return _DDS_MODULES[module]


@pytest.hookimpl(optionalhook=True)  # xdist's hook: unknown with -p no:xdist
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """With ``--dist loadgroup`` (as scripts/test runs): the tests of a module that starts
    DDS processes (a ``dds`` test in it) go to one worker together, since they share module
    fixtures (a replay, a clean pass, the fault suite) that must be made once; every other
    test is scheduled on its own. Each worker has its own DDS domain
    (:func:`_isolate_dds`), so two such modules may run side by side.

    pytest-xdist's own ``xdist_group`` marks do not work with pytest 9 (xdist 3.8 writes the
    group into ``item._nodeid``, which pytest 9 no longer reads), so every DDS module ran
    its shared fixtures once per worker: the fault suite twice, about 220 s each."""
    if config.getvalue('dist') != 'loadgroup':
        return None
    return DdsModulesTogether(config, log)


class DdsModulesTogether(LoadScopeScheduling):
    """xdist's scope scheduling with a scope per DDS module and one per other test."""

    def _split_scope(self, nodeid: str) -> str:
        module = nodeid.split('::', 1)[0]
        return module if _is_dds_module(module) else nodeid


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    """Attach the output of every subprocess a failed test started to its report."""
    report = yield
    if report.failed:
        for proc in getattr(item, '_orbit_tracking_procs', ()):
            for stream in ('stderr', 'stdout'):
                path: Path = getattr(proc, f'{stream}_path')
                text = path.read_text(errors='replace') if path.exists() else ''
                if text.strip():
                    code = proc.poll()
                    state = 'running' if code is None else f'exit status {code}'
                    report.sections.append((f'{stream} of {proc.label} ({state})', text[-20_000:]))
    return report


def subprocess_env() -> dict[str, str]:
    """Environment of a node subprocess: the source tree first on PYTHONPATH, unbuffered."""
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(ROOT), env.get('PYTHONPATH', '')) if p)
    env['PYTHONUNBUFFERED'] = '1'
    env['RCUTILS_COLORIZED_OUTPUT'] = '0'
    return env


def node_command(module: str, namespace: str | None = None, **params: Any) -> list[str]:
    """``python -m orbit_tracking.ros.<module> --ros-args [-r __ns:=<namespace>] -p k:=v ...``."""
    cmd = [sys.executable, '-m', f'orbit_tracking.ros.{module}']
    if params or namespace:
        cmd.append('--ros-args')
    if namespace:
        cmd += ['-r', f'__ns:={namespace}']
    for key, value in params.items():
        if isinstance(value, bool):
            value = 'true' if value else 'false'
        elif isinstance(value, (list, tuple)):
            value = '[' + ','.join(str(v) for v in value) + ']'
        cmd += ['-p', f'{key}:={value}']
    return cmd


def stop_process(proc: subprocess.Popen[bytes], timeout: float = 10.0) -> int:
    """SIGINT, then SIGKILL if it does not exit within ``timeout``; returns the exit status."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=timeout)
    return int(proc.returncode)


@pytest.fixture
def start_process(
    request: pytest.FixtureRequest, tmp_path: Path
) -> Iterator[Callable[..., subprocess.Popen[bytes]]]:
    """Start a subprocess (a node, or any command) in the DDS-isolated environment.

    ``start_process(cmd, label=None)`` returns the :class:`subprocess.Popen`; its stdout and
    stderr go to files (``proc.stdout_path``, ``proc.stderr_path``, read them with
    ``proc.output()`` / ``proc.errors()``) so a chatty node never blocks on a full pipe.
    Use :func:`node_command` to build a node's command line. On teardown each process still
    running gets SIGINT, then SIGKILL; when the test failed, every process's stderr and
    stdout are attached to the failure report.
    """
    procs: list[subprocess.Popen[bytes]] = []
    request.node._orbit_tracking_procs = procs

    def start(cmd: Sequence[str], label: str | None = None) -> subprocess.Popen[bytes]:
        label = label or (cmd[2].rsplit('.', 1)[-1] if len(cmd) > 2 and cmd[1] == '-m' else cmd[0])
        stem = tmp_path / f'proc{len(procs)}_{Path(label).name}'
        out_path, err_path = stem.with_suffix('.stdout'), stem.with_suffix('.stderr')
        with open(out_path, 'wb') as out, open(err_path, 'wb') as err:
            proc = subprocess.Popen(
                list(cmd),
                cwd=ROOT,
                env=subprocess_env(),
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=err,
            )
        proc.label = label  # type: ignore[attr-defined]
        proc.stdout_path = out_path  # type: ignore[attr-defined]
        proc.stderr_path = err_path  # type: ignore[attr-defined]
        proc.output = lambda: out_path.read_text(errors='replace')  # type: ignore[attr-defined]
        proc.errors = lambda: err_path.read_text(errors='replace')  # type: ignore[attr-defined]
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        stop_process(proc)


@pytest.fixture
def rclpy_node() -> Iterator[Any]:
    """An in-process rclpy node in its own context, added to a single-threaded executor.

    Spin it with ``rclpy_node.executor.spin_once(timeout_sec=...)`` or the ``spin_until``
    fixture. The context is shut down after the test.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node(f'test_{uuid.uuid4().hex[:8]}', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield node
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def spin_until(
    node: Any, predicate: Callable[[], bool], timeout: float, what: str | Callable[[], str] = ''
) -> float:
    """Spin ``node``'s executor until ``predicate()`` holds; fail after ``timeout`` seconds.

    ``what`` (a string, or a callable evaluated on failure) describes the wait in the failure
    message. Returns the seconds it took.
    """
    start = time.monotonic()
    while not predicate():
        if time.monotonic() - start > timeout:
            text = what() if callable(what) else what
            pytest.fail(f'timed out after {timeout:.0f} s waiting for {text or predicate}')
        node.executor.spin_once(timeout_sec=0.05)
    return time.monotonic() - start


@pytest.fixture(name='spin_until')
def spin_until_fixture() -> Callable[..., float]:
    """:func:`spin_until` as a fixture: ``spin_until(node, predicate, timeout, what)``."""
    return spin_until


@pytest.fixture
def ros_namespace() -> str:
    """A fresh namespace (``/t<hex>``) for one test's nodes: the contract's topic names are
    relative, so nodes started in it cannot hear, or be heard by, another run that happens
    to share the DDS domain."""
    return f'/t{uuid.uuid4().hex[:10]}'


@pytest.fixture(name='node_command')
def node_command_fixture() -> Callable[..., list[str]]:
    """:func:`node_command` as a fixture: ``node_command('station_sim', scenario=...)``."""
    return node_command


@contextmanager
def default_context(**params: object) -> Iterator[None]:
    """rclpy's default context with node parameters, for a node built in this process and
    fed by calling its callbacks (no DDS traffic)."""
    import rclpy

    args = ['--ros-args'] + [a for k, v in params.items() for a in ('-p', f'{k}:={v}')]
    rclpy.init(args=args)
    try:
        yield
    finally:
        rclpy.try_shutdown()
