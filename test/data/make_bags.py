"""Regenerate the regression bags of ``test/test_regression_bags.py`` (see README.md here).

Each bag is recorded over real DDS, as a range engineer would record a pass:
``scenario_sim`` streams a short scenario (``scenarios/<name>.yaml``) at real time and
``orbit-tracking record`` writes what it receives; both run as separate processes. The
recording is then checked message by message against the same scenario simulated straight
into a bag (``simulate_to_bag``, no DDS): every topic must hold exactly the simulator's
messages in their order, nothing lost, nothing extra, and the bag the same scenario labels
(``custom_data``). A recording that fails the check is retried (twice at most) and never
kept.

Run it with the project's Python (after ``source scripts/env.sh``; about 45 s per bag)::

    python test/data/make_bags.py [--only NAME ...] [--force]

It writes ``bags/<name>/`` (rosbag2, MCAP) and ``manifest.yaml`` (scenario, seed, the
software commit, the command lines, per-topic counts, stamps and checksums).
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
if str(ROOT) not in sys.path:  # this source tree's orbit_tracking, not an installed copy
    sys.path.insert(0, str(ROOT))
BAGS = HERE / 'bags'
MANIFEST = HERE / 'manifest.yaml'

RECORDED_TOPICS = (
    '/stations/*/measurements',
    '/stations/*/state',
    '/telemetry/state',
    '/truth/state',
)
"""What the bags hold: the processing nodes' inputs and the scenario's truth."""


@dataclass(frozen=True)
class BagSpec:
    """One regression bag: a scenario file streamed at ``rate_factor`` with measurement
    messages of ``batch_period`` scenario seconds."""

    name: str
    batch_period: float = 0.1
    rate_factor: float = 1.0

    @property
    def scenario(self) -> Path:
        return HERE / 'scenarios' / f'{self.name}.yaml'


SPECS = (BagSpec('seed000_s1_20_50'), BagSpec('seed003_q2_60_90'))


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    env.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(ROOT), env.get('PYTHONPATH', '')) if p)
    env['PYTHONUNBUFFERED'] = '1'
    env['RCUTILS_COLORIZED_OUTPUT'] = '0'
    return env


def _commands(spec: BagSpec, out: Path) -> tuple[list[str], list[str]]:
    """The recorder's and the simulator's command lines."""
    scenario = str(spec.scenario.relative_to(ROOT))
    record = [sys.executable, '-m', 'orbit_tracking.tools.cli', 'record', '--out', str(out)]
    # --scenario labels the bag (custom_data) as simulate labels its bags
    record += ['--scenario', scenario, '--storage', 'mcap', '--idle', '3']
    record += ['--topics', *RECORDED_TOPICS]
    params = {
        'scenario': scenario,
        'rate_factor': spec.rate_factor,
        'batch_period': spec.batch_period,
        'publish_truth': True,
        'publish_telemetry': True,
        # the recorder subscribes to topics as it discovers them (every 0.5 s): give it
        # time to find telemetry and truth too (only the measurement topics are waited for)
        'start_delay': 3.0,
        'wait_for_subscribers': 1,
        'wait_timeout': 60.0,
        'shutdown_when_done': True,
    }
    sim = [sys.executable, '-m', 'orbit_tracking.ros.scenario_sim', '--ros-args']
    for key, value in params.items():
        text = ('true' if value else 'false') if isinstance(value, bool) else str(value)
        sim += ['-p', f'{key}:={text}']
    return record, sim


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def _wait_for_node(name: str, proc: subprocess.Popen[bytes], timeout: float) -> None:
    """Block until a node called ``name`` is in the ROS graph."""
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node('make_bags_monitor', context=context)
        start = time.monotonic()
        while name not in node.get_node_names():
            if proc.poll() is not None:
                raise RuntimeError(f'{name} exited with status {proc.returncode}')
            if time.monotonic() - start > timeout:
                raise RuntimeError(f'{name} did not come up in {timeout:.0f} s')
            time.sleep(0.1)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def record(spec: BagSpec, out: Path, logs: Path, timeout: float = 180.0) -> None:
    """Stream ``spec``'s scenario through ``scenario_sim`` into ``orbit-tracking record``.

    The recorder starts first: the simulator waits for readers of its measurement topics
    only, so a recorder still starting up could subscribe to truth or telemetry late.

    Raises
    ------
    RuntimeError
        A process failed or did not finish within ``timeout`` seconds.
    """
    rec_cmd, sim_cmd = _commands(spec, out)
    env = _env()
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        for label, cmd in (('recorder', rec_cmd), ('scenario_sim', sim_cmd)):
            with open(logs / f'{label}.log', 'wb') as log:
                procs[label] = subprocess.Popen(
                    cmd, cwd=ROOT, env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=log
                )
            if label == 'recorder':
                _wait_for_node('orbit_tracking_recorder', procs[label], 60.0)
        start = time.monotonic()
        for label in ('scenario_sim', 'recorder'):
            left = max(timeout - (time.monotonic() - start), 1.0)
            try:
                code = procs[label].wait(left)
            except subprocess.TimeoutExpired:
                raise RuntimeError(f'{label} did not finish in {timeout:.0f} s') from None
            if code != 0:
                raise RuntimeError(f'{label} exited with status {code}')
    finally:
        for proc in procs.values():
            _stop(proc)


def _content(value: object) -> object:
    """A message's content as nested tuples (exact values), comparable and sortable."""
    fields = getattr(value, 'get_fields_and_field_types', None)
    if fields is not None:
        return tuple((name, _content(getattr(value, name))) for name in fields())
    if isinstance(value, str | bytes | int | float | bool):
        return value
    if hasattr(value, 'tobytes'):  # array.array, numpy arrays: the exact bytes
        return bytes(value.tobytes())  # type: ignore[attr-defined]
    return tuple(_content(v) for v in value)  # type: ignore[attr-defined]


def _messages_by_topic(bag: Path) -> dict[str, list[object]]:
    """Each topic's messages as content tuples, in the bag's order. (The bytes a DDS writer
    sends differ from rclpy's in alignment padding; the content does not.)"""
    from orbit_tracking.ros.bag import read_bag

    out: dict[str, list[object]] = defaultdict(list)
    for m in read_bag(bag):
        out['/' + m.topic.lstrip('/')].append(_content(m.msg))
    return out


def verify(spec: BagSpec, bag: Path, scratch: Path) -> None:
    """The recorded bag holds exactly the messages (and the scenario labels) of the scenario
    simulated without DDS.

    Raises
    ------
    RuntimeError
        Naming the topics whose messages differ.
    """
    from orbit_tracking.core.sim.scenario import load_scenario
    from orbit_tracking.tools.simulate import simulate_to_bag

    ref = scratch / 'reference'
    simulate_to_bag(load_scenario(spec.scenario), ref, 'mcap', spec.batch_period, True, False)
    from orbit_tracking.ros.bag import bag_custom_data

    got, want = _messages_by_topic(bag), _messages_by_topic(ref)
    bad = []
    if bag_custom_data(bag) != bag_custom_data(ref):
        bad.append(f'custom_data {bag_custom_data(bag)} instead of {bag_custom_data(ref)}')
    for topic in sorted(set(got) | set(want)):
        a, b = got.get(topic, []), want.get(topic, [])
        if a != b:  # one topic's messages arrive in order: the same sequence
            missing = sum(1 for m in b if m not in a)
            extra = sum(1 for m in a if m not in b)
            bad.append(
                f'{topic}: {len(a)} recorded, {len(b)} simulated ({missing} missing, '
                f'{extra} not simulated)'
            )
    if bad:
        raise RuntimeError('the recording differs from the simulation: ' + '; '.join(bad))


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, 'rb') as fh:
        for block in iter(lambda: fh.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


def _git(*args: str) -> str:
    return subprocess.run(
        ['git', *args], cwd=ROOT, capture_output=True, text=True, check=False
    ).stdout.strip()


def describe(spec: BagSpec, bag: Path) -> dict[str, object]:
    """Manifest entry of a recorded bag."""
    from orbit_tracking.core.sim.scenario import load_scenario
    from orbit_tracking.ros.bag import read_bag

    sc = load_scenario(spec.scenario)
    stamps: dict[str, list[int]] = defaultdict(list)
    log_times = []
    for m in read_bag(bag):
        stamps[m.topic].append(m.msg.header.stamp.sec * 1_000_000_000 + m.msg.header.stamp.nanosec)
        log_times.append(m.log_time_ns)
    topics = {
        topic: {'messages': len(s), 'first_stamp_ns': min(s), 'last_stamp_ns': max(s)}
        for topic, s in sorted(stamps.items())
    }
    rec_cmd, sim_cmd = _commands(spec, Path('bags') / spec.name)
    dirty = _git('status', '--porcelain', '--', 'orbit_tracking', 'config')
    return {
        'scenario': str(spec.scenario.relative_to(ROOT)),
        'base_scenario': yaml.safe_load(spec.scenario.read_text())['base'],
        'span_s': [sc.t_start, sc.t_end],
        'epoch_s': sc.epoch,
        'world_frame': sc.world_frame,
        'random_seed': sc.random_seed,
        'batch_period_s': spec.batch_period,
        'rate_factor': spec.rate_factor,
        'recorded_wall_s': round((max(log_times) - min(log_times)) * 1e-9, 2),
        'commit': _git('rev-parse', 'HEAD') + (' (with uncommitted changes)' if dirty else ''),
        'recorded_at': datetime.datetime.now(datetime.UTC).isoformat(timespec='seconds'),
        'machine': f'{platform.machine()}, {os.cpu_count()} cores, '
        f'{os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")}',
        'commands': {
            'record': ' '.join(['python', *rec_cmd[1:]]),
            'scenario_sim': ' '.join(['python', *sim_cmd[1:]]),
        },
        'topics': topics,
        'files': {
            p.name: {'bytes': p.stat().st_size, 'sha256': _sha256(p)}
            for p in sorted(bag.iterdir())
        },
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--only', nargs='*', help='bag names to regenerate (default all)')
    p.add_argument('--force', action='store_true', help='replace existing bags')
    p.add_argument('--attempts', type=int, default=3, help='recordings tried per bag')
    args = p.parse_args(argv)
    # this process watches the graph too: the same DDS settings as its children
    os.environ.update({k: v for k, v in _env().items() if k.startswith(('ROS_', 'RMW_'))})
    specs = [s for s in SPECS if not args.only or s.name in args.only]
    unknown = set(args.only or ()) - {s.name for s in SPECS}
    if unknown:
        p.error(f'unknown bag(s) {sorted(unknown)}; known: {[s.name for s in SPECS]}')
    manifest = yaml.safe_load(MANIFEST.read_text()) if MANIFEST.exists() else {}
    manifest = manifest or {}
    for spec in specs:
        dest = BAGS / spec.name
        if dest.exists() and not args.force:
            p.error(f'{dest} exists; use --force to replace it')
        for attempt in range(1, args.attempts + 1):
            with tempfile.TemporaryDirectory(prefix=f'make_bags_{spec.name}_') as tmp:
                scratch = Path(tmp)
                bag = scratch / 'bag'
                print(f'{spec.name}: recording over DDS (attempt {attempt})', flush=True)
                try:
                    record(spec, bag, scratch)
                    verify(spec, bag, scratch)
                except RuntimeError as exc:
                    print(f'{spec.name}: {exc}', file=sys.stderr)
                    for log in sorted(scratch.glob('*.log')):
                        tail = log.read_text(errors='replace')[-3000:]
                        print(f'--- {log.name} ---\n{tail}', file=sys.stderr)
                    continue
                if dest.exists():
                    shutil.rmtree(dest)
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copytree(bag, dest)
            manifest[spec.name] = describe(spec, dest)
            size = sum(f.stat().st_size for f in dest.iterdir())
            print(f'{spec.name}: wrote {dest.relative_to(ROOT)} ({size / 1e6:.2f} MB)')
            break
        else:
            print(
                f'{spec.name}: no complete recording in {args.attempts} attempts', file=sys.stderr
            )
            return 1
    header = (
        '# Written by test/data/make_bags.py: where each regression bag came from.\n'
        '# Do not edit; regenerate the bags instead (see README.md).\n'
    )
    MANIFEST.write_text(header + yaml.safe_dump(manifest, sort_keys=False, width=100))
    return 0


if __name__ == '__main__':
    sys.exit(main())
