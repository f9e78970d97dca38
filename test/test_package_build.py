"""Build orbit_tracking in a fresh colcon workspace, as a ROS 2 user would, and use the result.

The package is copied to ``<tmp>/ws/src/orbit_tracking`` and built with the colcon of the
current interpreter (``python -m colcon build``). The checks then run in bash subprocesses that
source ``<tmp>/ws/install/setup.bash`` in an environment cleared of any other workspace, so they
see exactly what ``ros2 run orbit_tracking <exe>`` would see:

(a) ament_index_python finds the package (only true when colcon-ros built it as ament_python);
(b) its share directory holds package.xml, config/, launch/ and the resource-index marker;
(c) every console script of setup.py is an executable in ``lib/orbit_tracking``;
(d) every ROS node executable starts with ``--ros-args ...`` and keeps running (or exits 0)
    without a Python traceback, then shuts down cleanly on SIGINT.

The console scripts are read from setup.py's ``console_scripts`` list (the one place they are
defined); those whose entry point lives in ``orbit_tracking.ros`` are the ROS nodes.
"""

from __future__ import annotations

import ast
import contextlib
import fnmatch
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = 'orbit_tracking'

# Required by the project's interface (ros2 run targets and the CLI).
REQUIRED_SCRIPTS = {'station_sim', 'scenario_sim', 'triangulation', 'orbit-tracking'}
NODE_MODULE_PREFIX = f'{PKG}.ros.'

# A node counts as started once it is on the ROS graph (seen from this process over DDS) and
# still running STAY_UP_S later. Five Python nodes importing numpy/scipy at once on a loaded
# 2-core machine have taken more than 8 s to get there, so the wait is for the graph, not a
# fixed time; STARTUP_TIMEOUT_S only bounds a node that never appears.
STARTUP_TIMEOUT_S = 90.0
STAY_UP_S = 2.0
SHUTDOWN_WAIT_S = 10.0  # time allowed to exit after SIGINT
CLEAN_SIGINT_CODES = {0, -signal.SIGINT, 128 + signal.SIGINT}
TRACEBACK = 'Traceback (most recent call last)'

# Not copied into the test workspace.
TOP_LEVEL_SKIP = {'.git', '.venv', 'build', 'install', 'log', 'runs', 'out', '.setup.lock'}
SKIP_ANYWHERE = (
    '__pycache__',
    '*.pyc',
    '*.egg-info',
    '.pytest_cache',
    '.mypy_cache',
    '.ruff_cache',
)


def _setup_py_console_scripts() -> dict[str, str]:
    """``{name: 'module:function'}`` from the ``console_scripts = [...]`` list in setup.py."""
    tree = ast.parse((ROOT / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == 'console_scripts' for t in node.targets
        ):
            entries = ast.literal_eval(node.value)
            return dict((part.strip() for part in entry.split('=', 1)) for entry in entries)
    raise AssertionError('setup.py has no `console_scripts = [...]` list')


CONSOLE_SCRIPTS = _setup_py_console_scripts()
NODE_EXECUTABLES = sorted(
    name for name, target in CONSOLE_SCRIPTS.items() if target.startswith(NODE_MODULE_PREFIX)
)


@dataclass
class Workspace:
    root: Path
    env: dict[str, str]
    build_output: str

    @property
    def prefix(self) -> Path:
        return self.root / 'install' / PKG

    @property
    def share(self) -> Path:
        return self.prefix / 'share' / PKG

    @property
    def lib(self) -> Path:
        return self.prefix / 'lib' / PKG

    def sourced_command(self, script: str) -> list[str]:
        setup = shlex.quote(str(self.root / 'install' / 'setup.bash'))
        return ['bash', '-c', f'set -eo pipefail; source {setup}; set -u; {script}']

    def run(self, script: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
        """Run a bash snippet after sourcing the workspace; fail the test if it fails."""
        proc = subprocess.run(
            self.sourced_command(script),
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        if proc.returncode != 0:
            pytest.fail(
                f'{script!r} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}',
                pytrace=False,
            )
        return proc


def _ignore(directory: str, names: list[str]) -> set[str]:
    skipped = {n for n in names for p in SKIP_ANYWHERE if fnmatch.fnmatch(n, p)}
    if Path(directory).resolve() == ROOT:
        skipped |= TOP_LEVEL_SKIP.intersection(names)
    return skipped


def _clean_env(base: Path) -> dict[str, str]:
    """This process's environment minus any sourced workspace, with this venv first on PATH."""
    env = dict(os.environ)
    for var in (
        'AMENT_PREFIX_PATH',
        'COLCON_PREFIX_PATH',
        'CMAKE_PREFIX_PATH',
        'PYTHONPATH',
        'COLCON_CURRENT_PREFIX',
    ):
        env.pop(var, None)
    env['PATH'] = os.pathsep.join([str(Path(sys.executable).parent), env.get('PATH', '')])
    env.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 1))
    env['ROS_LOG_DIR'] = str(base / 'ros_log')
    env['PYTHONUNBUFFERED'] = '1'
    return env


@pytest.fixture(scope='module')
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    base = tmp_path_factory.mktemp('pkgbuild')
    ws = base / 'ws'
    shutil.copytree(ROOT, ws / 'src' / PKG, ignore=_ignore, symlinks=True)
    env = _clean_env(base)
    proc = subprocess.run(
        [
            sys.executable,
            '-m',
            'colcon',
            '--log-base',
            'log',
            'build',
            '--base-paths',
            'src',
            '--build-base',
            'build',
            '--install-base',
            'install',
        ],
        cwd=ws,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    output = proc.stdout + proc.stderr
    if proc.returncode != 0:
        pytest.fail(f'colcon build failed ({proc.returncode}):\n{output}', pytrace=False)
    return Workspace(root=ws, env=env, build_output=output)


pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]


def test_colcon_builds_ament_python_package(workspace: Workspace) -> None:
    out = workspace.build_output
    assert 'Failed to parse ROS package manifest' not in out, (
        'catkin_pkg rejected package.xml, so colcon built a plain Python package:\n' + out
    )
    assert (workspace.share / 'hook' / 'ament_prefix_path.dsv').is_file(), (
        'no AMENT_PREFIX_PATH hook: colcon did not treat the package as ament_python'
    )
    # colcon-ros warns when setup.py does not install these itself.
    assert "doesn't explicitly install" not in out, out


def test_ament_index_finds_package(workspace: Workspace) -> None:  # (a)
    proc = workspace.run(
        'python -c "from ament_index_python.packages import get_package_share_directory as g;'
        f" print(g('{PKG}'))\""
    )
    assert proc.stdout.strip() == str(workspace.share)


def test_share_directory_contents(workspace: Workspace) -> None:  # (b)
    share = workspace.share
    assert (share / 'package.xml').is_file()
    assert (share / 'package.xml').read_bytes() == (ROOT / 'package.xml').read_bytes()
    marker = workspace.prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / PKG
    assert marker.is_file()
    assert (share / 'config').is_dir()
    # Everything setup.py globs is installed (files added later are picked up too).
    for pattern in ('config/*.yaml', 'config/scenarios/*.yaml', 'launch/*.py'):
        for src in ROOT.glob(pattern):
            installed = share / src.relative_to(ROOT)
            assert installed.is_file(), f'{src.relative_to(ROOT)} not installed to {installed}'


def test_console_scripts_installed(workspace: Workspace) -> None:  # (c)
    missing = REQUIRED_SCRIPTS - CONSOLE_SCRIPTS.keys()
    assert not missing, f'setup.py console_scripts lacks {sorted(missing)}'
    for name in CONSOLE_SCRIPTS:
        exe = workspace.lib / name
        assert exe.is_file(), f'{exe} missing'
        assert os.access(exe, os.X_OK), f'{exe} not executable'
    # The installed distribution (found through the sourced PYTHONPATH) declares the same ones.
    proc = workspace.run(
        'python -c "import importlib.metadata as m, json;'
        f" d = m.distribution('{PKG}');"
        " print(json.dumps({'at': str(d.locate_file('')),"
        " 'eps': {e.name: e.value for e in d.entry_points if e.group == 'console_scripts'}}))\""
    )
    info = json.loads(proc.stdout)
    assert Path(info['at']).is_relative_to(workspace.prefix), info['at']
    assert info['eps'] == CONSOLE_SCRIPTS


@dataclass
class NodeRun:
    cmd: list[str]
    returncode: int | None  # exit code, None if it had to be killed
    running_at_deadline: bool
    stderr: str


def _wait_on_graph(namespace: str, procs: dict[str, subprocess.Popen[bytes]]) -> None:
    """Until every process has either exited or shown its node ``pkgtest_<name>`` in
    ``namespace`` on the graph, or STARTUP_TIMEOUT_S has passed."""
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    probe = rclpy.create_node(f'pkgtest_probe_{os.getpid()}', context=context)
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline:
            seen = {n for n, ns in probe.get_node_names_and_namespaces() if ns == namespace}
            if all(p.poll() is not None or f'pkgtest_{name}' in seen for name, p in procs.items()):
                return
            time.sleep(0.2)
    finally:
        probe.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.fixture(scope='module')
def node_runs(workspace: Workspace) -> dict[str, NodeRun]:
    """Start every node executable at once, wait until each is on the ROS graph (or has
    exited), SIGINT the survivors, collect results."""
    namespace = f'/pkgtest{os.getpid()}_{time.monotonic_ns() % 100000}'
    log_dir = workspace.root / 'node_logs'
    log_dir.mkdir()
    setup = shlex.quote(str(workspace.root / 'install' / 'setup.bash'))
    cmds: dict[str, list[str]] = {}
    procs: dict[str, subprocess.Popen[bytes]] = {}
    with contextlib.ExitStack() as stack:
        for name in NODE_EXECUTABLES:
            cmds[name] = [
                str(workspace.lib / name),
                '--ros-args',
                '-r',
                f'__node:=pkgtest_{name}',
                '-r',
                f'__ns:={namespace}',
                '-p',
                'use_sim_time:=false',
                '--log-level',
                'warn',
            ]
            out = stack.enter_context(open(log_dir / f'{name}.out', 'wb'))
            err = stack.enter_context(open(log_dir / f'{name}.err', 'wb'))
            # `exec` so that the PID we signal is the node's own.
            procs[name] = subprocess.Popen(
                ['bash', '-c', f'source {setup} && exec "$0" "$@"', *cmds[name]],
                env=workspace.env,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=err,
                start_new_session=True,
            )

        _wait_on_graph(namespace, procs)
        time.sleep(STAY_UP_S)
        running = {name: p.poll() is None for name, p in procs.items()}
        for name, p in procs.items():
            if running[name]:
                p.send_signal(signal.SIGINT)

        codes: dict[str, int | None] = {}
        for name, p in procs.items():
            try:
                codes[name] = p.wait(timeout=SHUTDOWN_WAIT_S)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
                codes[name] = None

    return {
        name: NodeRun(
            cmd=cmds[name],
            returncode=codes[name],
            running_at_deadline=running[name],
            stderr=(log_dir / f'{name}.err').read_text(errors='replace'),
        )
        for name in procs
    }


@pytest.mark.dds
@pytest.mark.parametrize('name', NODE_EXECUTABLES)
def test_node_executable_starts(node_runs: dict[str, NodeRun], name: str) -> None:  # (d)
    run = node_runs[name]
    what = f'`{shlex.join(run.cmd)}`'
    tail = '\n'.join(run.stderr.splitlines()[-40:])
    if not run.running_at_deadline:
        problem = (
            None
            if run.returncode == 0 and TRACEBACK not in run.stderr
            else f'exited with {run.returncode} before it had been up {STAY_UP_S:.0f} s'
        )
    elif run.returncode is None:
        problem = f'did not exit within {SHUTDOWN_WAIT_S:.0f} s of SIGINT (killed)'
    elif TRACEBACK in run.stderr:
        problem = f'printed a traceback (exit code {run.returncode} after SIGINT)'
    elif run.returncode not in CLEAN_SIGINT_CODES:
        problem = f'exited with {run.returncode} after SIGINT'
    else:
        problem = None
    if problem:
        pytest.fail(f'{what} {problem}; stderr:\n{tail}', pytrace=False)


def test_node_executables_declared() -> None:
    required = {'station_sim', 'scenario_sim', 'triangulation'}
    assert required <= set(NODE_EXECUTABLES), (
        f'node executables in setup.py ({NODE_EXECUTABLES}) must include {sorted(required)} '
        f'with entry points in {NODE_MODULE_PREFIX}*'
    )
