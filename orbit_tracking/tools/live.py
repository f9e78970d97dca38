"""The main job's live pass over real DDS: the processing chain as separate processes, started
the way ``ros2 run`` starts them (and ``launch/tracking.launch.py`` starts the same
:data:`NODES`), with ``orbit-tracking record`` writing what they publish into a rosbag2.

::

    scenario_sim  -> stations/<id>/measurements, stations/<id>/state, telemetry/state, truth/state
    triangulation -> triangulation/fixes
    estimator     -> estimator/window_states, estimator/window_residuals, trajectory/biases
    results       -> trajectory/states, trajectory/path

:func:`run_live` starts the processing nodes and the recorder, waits until each reads what
it should, streams the scenario, waits for the estimator's last window and the results
node's last states, and stops everything; it watches the graph and the nodes' diagnostics
from this process with :class:`~orbit_tracking.tools.live_monitor.LiveMonitor`.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.tools.live_monitor import _STATUS, SIMULATOR, LiveMonitor

__all__ = [
    'LIVE_TOPICS',
    'NODES',
    'SIMULATOR',
    'LiveResult',
    'NodeSpec',
    'node_command',
    'node_parameters',
    'package_location',
    'run_live',
]

PACKAGE = 'orbit_tracking'


@dataclass(frozen=True)
class NodeSpec:
    """One node of the live chain.

    Attributes
    ----------
    executable : str
        Console script of ``setup.py``: ``ros2 run orbit_tracking <executable>``.
    module : str
        Its module under ``orbit_tracking.ros`` (``python -m`` from a source tree).
    params_file : str
        Parameter file under ``config/`` (installed into ``share/orbit_tracking/config``).
    overrides : mapping
        Parameters the main job sets on top of the file (``-p name:=value``).
    """

    executable: str
    module: str
    params_file: str
    overrides: Mapping[str, object] = field(default_factory=dict)


NODES: tuple[NodeSpec, ...] = (
    NodeSpec('triangulation', 'triangulation_node', 'triangulation.yaml'),
    NodeSpec('estimator', 'estimator_node', 'estimator.yaml'),
    NodeSpec('results', 'results_node', 'results.yaml'),
    NodeSpec(
        'scenario_sim',
        'scenario_sim',
        'scenario_sim.yaml',
        {
            'publish_truth': True,  # the report compares with it
            'publish_telemetry': True,  # the estimator fuses it
            'batch_period': 0.25,  # several epochs per message: far fewer messages per second
            # the triangulation node, the estimator and the recorder read every station
            'wait_for_subscribers': 3,
            'wait_timeout': 30.0,
            # it waits for readers of the station topics only; the recorder subscribes to
            # truth and telemetry in the same pass over the graph, so give it that time
            'start_delay': 3.0,
            'shutdown_when_done': False,  # stopped once everything downstream is through
        },
    ),
)
"""The nodes of the main job, in start order; ``launch/tracking.launch.py`` starts the same
executables with the same parameter files."""

LIVE_TOPICS: tuple[str, ...] = (
    '/stations/*/measurements',
    '/stations/*/state',
    '/telemetry/state',
    '/truth/state',
    '/triangulation/fixes',
    '/estimator/window_states',
    '/estimator/window_residuals',
    '/trajectory/states',
    '/trajectory/biases',
    '/diagnostics',
)
"""What the recorder of the live pass keeps (the per-target copies and the paths repeat
what is there)."""

_CLEAN_EXIT = {0, -signal.SIGINT, 128 + signal.SIGINT}


# -- starting processes ----------------------------------------------------------------------


@dataclass(frozen=True)
class PackageLocation:
    """Where the executables and parameter files come from.

    ``bin_dir`` is ``lib/orbit_tracking`` of the install space, or None to start the nodes
    with ``python -m`` from the source tree; ``config_dir`` holds the parameter files.
    """

    bin_dir: Path | None
    config_dir: Path
    source_root: Path | None = None

    def describe(self) -> str:
        if self.bin_dir is not None:
            return f'installed executables in {self.bin_dir}, parameters from {self.config_dir}'
        return (
            f'the source tree {self.source_root} (python -m orbit_tracking.ros.<node>), '
            f'parameters from {self.config_dir}'
        )


def package_location() -> PackageLocation:
    """The nodes come from the copy of the package this process runs: the install space
    (``ament_index_python``: ``<prefix>/lib/orbit_tracking/<executable>`` and
    ``<prefix>/share/orbit_tracking/config``, what ``ros2 run`` uses) when it runs from
    there, else the source tree it was imported from (``config/`` next to the package).

    Raises
    ------
    FileNotFoundError
        Neither an install space nor a source tree with ``config/``.
    """
    import orbit_tracking

    here = Path(os.path.abspath(orbit_tracking.__file__)).parent
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix

        try:
            prefix: Path | None = Path(os.path.abspath(get_package_prefix(PACKAGE)))
        except (PackageNotFoundError, OSError):  # OSError: no AMENT_PREFIX_PATH at all
            prefix = None
    except ImportError:
        prefix = None
    if prefix is not None and here.is_relative_to(prefix):
        bin_dir = prefix / 'lib' / PACKAGE
        config = prefix / 'share' / PACKAGE / 'config'
        if bin_dir.is_dir() and config.is_dir():
            return PackageLocation(bin_dir, config)
    root = here.parent
    if (root / 'config').is_dir():
        return PackageLocation(None, root / 'config', root)
    raise FileNotFoundError(
        f'orbit_tracking at {here} is neither in a colcon install space (source its '
        'setup.bash) nor in a source tree with config/'
    )


def _param_value(v: object) -> str:
    if isinstance(v, bool):
        return 'true' if v else 'false'
    if isinstance(v, float):
        return repr(v)  # always with a point: rclpy refuses an integer for a double
    if isinstance(v, list | tuple):
        return '[' + ','.join(_param_value(x) for x in v) + ']'
    return str(v)


def _program(where: PackageLocation, executable: str, module: str) -> list[str]:
    if where.bin_dir is not None:
        return [str(where.bin_dir / executable)]
    return [sys.executable, '-m', module]


def node_command(
    spec: NodeSpec, where: PackageLocation, overrides: Mapping[str, object] | None = None
) -> list[str]:
    """The command line of one node: the executable (or ``python -m``), then ``--ros-args
    --params-file <config>/<file>`` and ``-p name:=value`` for the spec's overrides and
    ``overrides``."""
    cmd = _program(where, spec.executable, f'orbit_tracking.ros.{spec.module}')
    cmd += ['--ros-args', '--params-file', str(where.config_dir / spec.params_file)]
    for k, v in {**spec.overrides, **(overrides or {})}.items():
        cmd += ['-p', f'{k}:={_param_value(v)}']
    return cmd


def node_parameters(
    spec: NodeSpec, where: PackageLocation, overrides: Mapping[str, object] | None = None
) -> dict[str, Any]:
    """The parameters a node is started with: its file's, then the overrides (the node's
    defaults fill in the rest)."""
    data = yaml.safe_load((where.config_dir / spec.params_file).read_text()) or {}
    params: dict[str, Any] = {}
    for section in data.values():
        params.update((section or {}).get('ros__parameters') or {})
    params.update(spec.overrides)
    params.update(overrides or {})
    return params


def _env(where: PackageLocation | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    env['PYTHONUNBUFFERED'] = '1'
    env['RCUTILS_COLORIZED_OUTPUT'] = '0'
    if where is not None and where.source_root is not None:
        # python -m must find this very source tree, whatever the working directory
        env['PYTHONPATH'] = os.pathsep.join(
            p for p in (str(where.source_root), env.get('PYTHONPATH', '')) if p
        )
    return env


def _node(module: str, params: dict[str, object]) -> list[str]:
    """``python -m orbit_tracking.ros.<module> --ros-args -p k:=v ...`` (no parameter
    file; the DDS benchmark's nodes)."""
    cmd = [sys.executable, '-m', f'orbit_tracking.ros.{module}', '--ros-args']
    for k, v in params.items():
        cmd += ['-p', f'{k}:={_param_value(v)}']
    return cmd


def _start(
    cmd: Sequence[str], log: Path, where: PackageLocation | None = None
) -> subprocess.Popen[bytes]:
    fh = open(log, 'wb')  # noqa: SIM115 - the child holds it; ours is closed right away
    try:
        return subprocess.Popen(
            list(cmd),
            env=_env(where),
            stdout=fh,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
        )
    finally:
        fh.close()


def _stop(proc: subprocess.Popen[bytes], timeout: float = 10.0) -> int:
    """SIGINT, then SIGKILL if it does not exit within ``timeout``; the exit status."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)
    return int(proc.returncode)


# -- the pass --------------------------------------------------------------------------------


@dataclass(frozen=True)
class LiveResult:
    """What the live pass did.

    Attributes
    ----------
    bag : Path
        The recording (:data:`LIVE_TOPICS`, labelled with the scenario like a simulated bag).
    log_dir : Path
        One log per process (``<executable>.log``, ``recorder.log``).
    wall_s : float
        Wall time of the pass.
    location : PackageLocation
        Where the executables and parameter files came from.
    commands : mapping of process name to its command line
    parameters : mapping of node executable to the parameters it was started with
    sent : mapping of station id to the measurement messages the simulator sent
    diagnostics : mapping of status name to the last key-values it published
    flush : str
        The results node's answer to ``~/flush``.
    states_published : int
        ``trajectory/states`` messages the results node reports.
    states_heard : int
        How many of them this process received.
    exit_codes : mapping of process name to exit status after SIGINT
    warnings : list of str
        What may have gone wrong without stopping the pass.
    """

    bag: Path
    log_dir: Path
    wall_s: float
    location: PackageLocation
    commands: Mapping[str, list[str]]
    parameters: Mapping[str, Mapping[str, Any]]
    sent: Mapping[str, int]
    diagnostics: Mapping[str, Mapping[str, str]]
    flush: str
    states_published: int
    states_heard: int
    exit_codes: Mapping[str, int]
    warnings: Sequence[str] = ()

    @property
    def unclean_exits(self) -> dict[str, int]:
        return {k: v for k, v in self.exit_codes.items() if v not in _CLEAN_EXIT}

    def lines(self) -> list[str]:
        """Human-readable summary."""
        est = self.diagnostics.get(_STATUS['estimator'], {})
        tri = self.diagnostics.get(_STATUS['triangulation'], {})
        out = [
            f'nodes from {self.location.describe()}; logs in {self.log_dir}',
            f'simulator sent {sum(self.sent.values())} measurement messages of '
            f'{len(self.sent)} stations; triangulation made {tri.get("fixes", "?")} fixes; '
            f'estimator solved {est.get("windows_solved", "?")} windows '
            f'({est.get("windows_failed", "?")} failed); results node published '
            f'{self.states_published} final states ({self.flush})',
            f'live pass over DDS in {self.wall_s:.1f} s; recorded to {self.bag}',
        ]
        out += [f'WARNING: {w}' for w in self.warnings]
        if self.states_heard != self.states_published:
            out.append(
                f'WARNING: {self.states_heard} of the {self.states_published} '
                'trajectory/states messages reached this process'
            )
        for name, code in self.unclean_exits.items():
            out.append(f'WARNING: {name} exited with status {code} on SIGINT (see {self.log_dir})')
        return out


def log_tail(path: Path, n: int = 3000) -> str:
    """The last ``n`` characters of a process log, without the list of extension modules
    that faulthandler prints after a crash's stack."""
    try:
        lines = path.read_text(errors='replace').splitlines()
    except OSError:
        return ''
    return '\n'.join(ln for ln in lines if not ln.startswith('Extension modules:'))[-n:]


def run_live(
    scenario: str,
    out: Path,
    rate_factor: float = 5.0,
    timeout: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> LiveResult:
    """Stream ``scenario`` (a name or YAML path, as the nodes take it) through
    :data:`NODES` over DDS and record the pass.

    1. start the processing nodes (every :data:`NODES` entry but the simulator) and
       ``orbit-tracking record`` (:data:`LIVE_TOPICS` into ``out/live_bag``);
    2. wait until each is up and reads what it should (the recorder every output topic);
    3. start ``scenario_sim`` at ``rate_factor`` times real time, with truth and telemetry;
       it waits for three readers (triangulation, estimator, recorder) of every station;
    4. wait until it has sent everything, the estimator has received every measurement
       message and solved its last window (cut at the newest stamp after ``flush_after``
       seconds of silence) and the results node has it; then call the results node's
       ``~/flush`` for the states it still holds;
    5. once those states are out, stop every process with SIGINT (the recorder last).

    Node logs go to ``out/logs``. ``timeout`` (default: the stream's wall time plus five
    minutes) bounds every wait.

    Raises
    ------
    RuntimeError
        A process exits early, or a wait runs out of time; the message names the process
        and ends with the tail of its log.
    """
    sc = load_scenario(scenario)
    say = progress or (lambda _text: None)
    stream_s = (sc.t_end - sc.t_start) / rate_factor
    timeout = timeout if timeout is not None else stream_s + 300.0
    logs = out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    bag = out / 'live_bag'
    where = package_location()
    run_overrides: dict[str, dict[str, object]] = {
        SIMULATOR: {'scenario': scenario, 'rate_factor': float(rate_factor)},
        # the scenario's epoch as time 0: the output times fall where the offline tool's do
        'estimator': {'time_reference': float(sc.epoch)},
        'results': {'time_reference': float(sc.epoch)},
    }
    commands = {
        s.executable: node_command(s, where, run_overrides.get(s.executable)) for s in NODES
    }
    parameters = {
        s.executable: node_parameters(s, where, run_overrides.get(s.executable)) for s in NODES
    }
    commands['recorder'] = _program(where, 'orbit-tracking', 'orbit_tracking.tools.cli') + [
        'record',
        '--out',
        str(bag),
        '--scenario',
        scenario,
        '--topics',
        *LIVE_TOPICS,
    ]
    t0 = time.monotonic()
    os.environ.update({k: v for k, v in _env().items() if k.startswith('ROS_')})
    procs: dict[str, subprocess.Popen[bytes]] = {}
    warnings: list[str] = []
    monitor = LiveMonitor()
    exit_codes: dict[str, int] = {}

    def log_of(name: str) -> Path:
        return logs / f'{name}.log'

    def check(what: str, deadline: float) -> None:
        for name, proc in procs.items():
            if proc.poll() is not None:
                raise RuntimeError(
                    f'live pass: {name} exited with status {proc.returncode} while waiting '
                    f'for {what}; end of {log_of(name)}:\n{log_tail(log_of(name))}'
                )
        if time.monotonic() > deadline:
            raise RuntimeError(f'live pass: timed out waiting for {what} (logs in {logs})')

    try:
        for s in NODES:
            if s.executable != SIMULATOR:
                procs[s.executable] = _start(commands[s.executable], log_of(s.executable), where)
        procs['recorder'] = _start(commands['recorder'], log_of('recorder'), where)
        say(f'started {", ".join(procs)}; waiting until they listen')
        deadline = time.monotonic() + min(timeout, 120.0)
        up = [n for n in _STATUS if n != SIMULATOR]
        while (missing := monitor.missing()) or (
            silent := [n for n in up if _STATUS[n] not in monitor.status]
        ):
            text = ', '.join(f'{e.node} {e.kind} {e.topic}' for e in missing[:4]) or (
                'the diagnostics of ' + ', '.join(silent)
            )
            check(text, deadline)
            monitor.spin(0.2)
        monitor.spin(0.5)  # endpoint matching follows graph discovery closely
        procs[SIMULATOR] = _start(commands[SIMULATOR], log_of(SIMULATOR), where)
        say(f'{SIMULATOR} streams {sc.name} at {rate_factor:g}x real time ({stream_s:.0f} s)')
        deadline = time.monotonic() + timeout
        # every topic of the simulator: measurements and state per station, truth, telemetry
        expected = 2 * len(sc.stations) + 1 + (1 if sc.telemetry else 0)
        while _STATUS[SIMULATOR] not in monitor.status:  # its diagnostics: streaming began
            unread = monitor.unrecorded(SIMULATOR)
            if unread is not None and len(unread[0]) == expected and not unread[1]:
                break
            check(f'{SIMULATOR} and the recorder', deadline)
            monitor.spin(0.1)
        else:
            unread = monitor.unrecorded(SIMULATOR)
            if unread is None or len(unread[0]) < expected or unread[1]:
                warnings.append(
                    f'{SIMULATOR} began streaming before the recorder read all its topics '
                    f'({", ".join(unread[1]) if unread else "?"}): the recording may lack '
                    'their first messages'
                )
        while monitor.messages.get(_STATUS[SIMULATOR]) != 'done':
            check(f'{SIMULATOR} to send every message', deadline)
            monitor.spin(0.2)
        say('every message sent; waiting for the estimator to solve the end of the stream')
        sent_total = sum(
            int(v)
            for k, v in monitor.status[_STATUS[SIMULATOR]].items()
            if k.endswith('_messages')
        )
        deadline = time.monotonic() + timeout
        settled: tuple[float, float] | None = None  # (since, windows) the end looked solved
        while True:
            solved = monitor.value('estimator', 'windows_solved', math.inf)
            at_end = (
                monitor.value('estimator', 'last_window_end')
                >= monitor.value('estimator', 'newest_data_time_s') - 1e-6
                and monitor.value('results', 'windows_received', 0.0) >= solved
            )
            got = monitor.value('estimator', 'measurement_messages', 0.0)
            if at_end and got >= sent_total:
                break
            # a window cut at the newest stamp before everything arrived (a stall longer than
            # flush_after) looks the same: wait for the rest, unless nothing moves any more
            if not at_end or settled is None or settled[1] != solved:
                settled = (time.monotonic(), solved) if at_end else None
            elif time.monotonic() - settled[0] > 15.0:
                warnings.append(
                    f'the estimator received {got:.0f} of the {sent_total} measurement '
                    'messages the simulator sent'
                )
                break
            check("the estimator's last window at the results node", deadline)
            monitor.spin(0.2)
        if not monitor.flush.wait_for_service(timeout_sec=10.0):
            raise RuntimeError('live pass: the results node offers no ~/flush service')
        future = monitor.flush.call_async(monitor._trigger.Request())
        deadline = time.monotonic() + 60.0
        while not future.done():
            check("the results node's ~/flush", deadline)
            monitor.spin(0.1)
        flush = str(future.result().message)
        # a diagnostics status published after the flush gives the total
        monitor.status.pop(_STATUS['results'], None)
        deadline = time.monotonic() + 30.0
        while not (
            _STATUS['results'] in monitor.status
            and monitor.value('results', 'states_held', 1.0) == 0.0
            and monitor.states >= monitor.value('results', 'states_published', math.inf)
        ):
            if time.monotonic() > deadline:  # said in lines(): heard != published
                break
            check('the final trajectory/states', math.inf)
            monitor.spin(0.2)
        monitor.spin(1.0)  # the recorder reads them as we did; let it write them
        published = int(monitor.value('results', 'states_published', 0.0))
        sent = {
            k[: -len('_messages')]: int(v)
            for k, v in monitor.status.get(_STATUS[SIMULATOR], {}).items()
            if k.endswith('_messages')
        }
        diagnostics = {name: dict(monitor.status.get(name, {})) for name in _STATUS.values()}
        heard = monitor.states
    finally:
        # the nodes first (in parallel), the recorder last: it keeps what they say on the way
        for name, proc in procs.items():
            if name != 'recorder' and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for name, proc in procs.items():
            if name != 'recorder':
                exit_codes[name] = _stop(proc)
        if 'recorder' in procs:
            exit_codes['recorder'] = _stop(procs['recorder'], timeout=30.0)
        monitor.close()
    return LiveResult(
        bag,
        logs,
        time.monotonic() - t0,
        where,
        commands,
        parameters,
        sent,
        diagnostics,
        flush,
        published,
        heard,
        exit_codes,
        warnings,
    )
