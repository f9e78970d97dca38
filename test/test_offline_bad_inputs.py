"""The offline commands on bad input (issue 13): every bag or path that is not a usable bag
ends ``triangulate``, ``estimate``, ``report --bag`` and ``replay`` with one line on
stderr and exit status 2, never a traceback, also when the storage file fails half way
through; every command that writes a folder refuses a non-empty one without ``--force``,
in the same words; a bag whose stations have measurements but no state says so; and
``triangulate`` runs to the end of a pass in which a station stops measuring (it used to
stop there and crash with ``OverflowError``).

The bad-bag matrix runs the CLI's ``main`` in this process (one real process per command
shows the same); the other checks run ``python -m orbit_tracking.tools.cli`` as processes.
The bad bags are built in ``tmp_path`` from the small bags of ``test/data/bags``.
"""

from __future__ import annotations

import contextlib
import io
import math
import shutil
import struct
import subprocess
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import ROOT, TRACEBACK, subprocess_env
from rosbags.rosbag2 import Reader

from orbit_tracking.core.triangulation.alignment import AlignConfig, Aligner
from orbit_tracking.ros.bag import BagWriter, bag_custom_data
from orbit_tracking.tools.cli import main as cli_main
from orbit_tracking.tools.triangulate import _independent_stride

BAGS = ROOT / 'test' / 'data' / 'bags'
SMALL = BAGS / 'seed003_q2_60_90'
"""Two satellites (sat06, sat09) with measurements and states, truth; 901 messages."""
TWO_CHUNKS = BAGS / 'seed000_s1_20_50'
"""4265 messages in two MCAP chunks: the second is read only half way through the bag."""

BAG_COMMANDS = ('triangulate', 'estimate', 'report', 'replay')
"""Every subcommand that reads a bag."""


@dataclass
class Run:
    code: int
    stdout: str
    stderr: str

    def error_line(self, command: str) -> str:
        """The one line of stderr, checked to be the CLI's error line."""
        assert TRACEBACK not in self.stderr, self.stderr
        lines = self.stderr.splitlines()
        assert len(lines) == 1, self.stderr
        assert lines[0].startswith(f'orbit-tracking {command}: error: '), lines[0]
        return lines[0]


def cli(*args: str | Path, timeout: float = 120.0) -> Run:
    """``orbit-tracking ARGS`` as a process, from the source tree, in the test environment
    (DDS isolated by conftest)."""
    proc = subprocess.run(
        [sys.executable, '-m', 'orbit_tracking.tools.cli', *map(str, args)],
        cwd=ROOT,
        env=subprocess_env(),
        stdin=subprocess.DEVNULL,
        capture_output=True,  # bytes: a progress bar's carriage returns stay as they are
        timeout=timeout,
    )
    return Run(proc.returncode, proc.stdout.decode(), proc.stderr.decode())


def cli_in_process(*args: str | Path) -> Run:
    """``orbit-tracking ARGS`` through its ``main`` in this process (the bad-bag matrix:
    a process each would cost a second of imports per case); an exception escaping
    ``main`` is reported as a traceback on stderr with status 1, as a process would."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli_main([str(a) for a in args])
        except SystemExit as exc:
            code = int(exc.code or 0)
        except BaseException:
            err.write(traceback.format_exc())
            code = 1
    return Run(code, out.getvalue(), err.getvalue())


def visible_lines(text: str) -> list[str]:
    """What a terminal shows of ``text``: each line as its last carriage return leaves it
    (a progress bar that was cleared leaves nothing)."""
    return [line.rsplit('\r', 1)[-1] for line in text.split('\n') if line.rsplit('\r', 1)[-1]]


# -- building bad bags -----------------------------------------------------------------


def copy_bag(src: Path, dst: Path, transform: Callable[[str, str], str | None]) -> Path:
    """A new bag with ``src``'s messages and labels; ``transform(topic, msgtype)`` gives
    each message's new topic (None: left out)."""
    with Reader(src) as reader, BagWriter(dst) as writer:
        for key, value in bag_custom_data(src).items():
            writer.set_custom_data(key, value)
        for conn, t_ns, raw in reader.messages():
            topic = transform(conn.topic, conn.msgtype)
            if topic is not None:
                writer.write_raw(topic, conn.msgtype, bytes(raw), t_ns)
    return dst


def mcap_records(data: bytes) -> list[tuple[int, int]]:
    """``(offset, opcode)`` of the top-level records of an MCAP file, up to its footer."""
    out = []
    pos = 8  # magic
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        out.append((pos, op))
        if op == 0x02:  # footer
            break
        pos += 9 + length
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _missing(tmp: Path) -> Path:
    return tmp / 'no_such_bag'


def _no_metadata(tmp: Path) -> Path:
    bag = _copy(SMALL, tmp / 'bag')
    (bag / 'metadata.yaml').unlink()
    return bag


def _unparsable_metadata(tmp: Path) -> Path:
    bag = _copy(SMALL, tmp / 'bag')
    meta = bag / 'metadata.yaml'
    meta.write_text(meta.read_text()[:500] + '\n  - [unclosed: {\n')
    return bag


def _empty_metadata(tmp: Path) -> Path:
    bag = _copy(SMALL, tmp / 'bag')
    (bag / 'metadata.yaml').write_text('')
    return bag


def _foreign_metadata(tmp: Path) -> Path:
    bag = _copy(SMALL, tmp / 'bag')
    (bag / 'metadata.yaml').write_text('name: not a bag\nitems: [1, 2]\n')
    return bag


def _missing_mcap(tmp: Path) -> Path:
    bag = _copy(SMALL, tmp / 'bag')
    (bag / 'bag.mcap').unlink()
    return bag


def _truncated_mcap(tmp: Path) -> Path:
    bag = _copy(SMALL, tmp / 'bag')
    mcap = bag / 'bag.mcap'
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    return bag


def _empty_mcap(tmp: Path) -> Path:
    bag = _copy(SMALL, tmp / 'bag')
    (bag / 'bag.mcap').write_bytes(b'')
    return bag


def _bad_half_way(tmp: Path) -> Path:
    """The record length of the first message in the second chunk made absurd: the reader
    opens the file and yields the first chunk's messages, then fails."""
    bag = _copy(TWO_CHUNKS, tmp / 'bag')
    mcap = bag / 'bag.mcap'
    data = bytearray(mcap.read_bytes())
    chunks = [pos for pos, op in mcap_records(data) if op == 0x06]
    assert len(chunks) == 2
    body = chunks[1] + 9  # start, end, uncompressed size, crc, compression, records length
    (n,) = struct.unpack_from('<I', data, body + 28)
    assert data[body + 32 : body + 32 + n] == b''  # not compressed
    first = body + 32 + n + 8
    assert data[first] == 0x05  # a message record
    struct.pack_into('<Q', data, first + 1, 2**40)
    mcap.write_bytes(bytes(data))
    return bag


def _skipped_half_way(tmp: Path) -> Path:
    """The second chunk's records overwritten by one record of an unknown kind, its index
    intact: the reader skips it without complaint, so fewer messages come out than the
    bag lists."""
    bag = _copy(TWO_CHUNKS, tmp / 'bag')
    mcap = bag / 'bag.mcap'
    data = bytearray(mcap.read_bytes())
    records = mcap_records(data)
    i = [k for k, (_, op) in enumerate(records) if op == 0x06][1]
    body = records[i][0] + 9
    (n,) = struct.unpack_from('<I', data, body + 28)
    start = body + 32 + n + 8
    (length,) = struct.unpack_from('<Q', data, start - 8)  # of the chunk's records
    data[start] = 0x7F  # not an MCAP opcode
    struct.pack_into('<Q', data, start + 1, length - 9)
    mcap.write_bytes(bytes(data))
    return bag


def _empty_file(tmp: Path) -> Path:
    path = tmp / 'bag.mcap'
    path.write_bytes(b'')
    return path


def _lone_mcap_file(tmp: Path) -> Path:
    """A valid MCAP file moved out of its bag folder: no metadata.yaml beside it."""
    path = tmp / 'orphan.mcap'
    shutil.copy(SMALL / 'bag.mcap', path)
    return path


def _not_a_bag(tmp: Path) -> Path:
    folder = tmp / 'notes'
    folder.mkdir()
    (folder / 'readme.txt').write_text('no bag here\n')
    return folder


def _no_usable_topic(tmp: Path) -> Path:
    return copy_bag(SMALL, tmp / 'bag', lambda t, _: t if t == '/truth/state' else None)


def _no_messages(tmp: Path) -> Path:
    with BagWriter(tmp / 'bag'):
        pass
    return tmp / 'bag'


def _wrong_message_type(tmp: Path) -> Path:
    """Odometry where the contract has PointCloud2."""
    renamed = {'/stations/sat06/measurements': None, '/stations/sat06/state': 'x'}
    return copy_bag(
        SMALL,
        tmp / 'bag',
        lambda t, _: (
            '/stations/sat06/measurements' if renamed.get(t, t) == 'x' else renamed.get(t, t)
        ),
    )


BAD_BAGS: dict[str, tuple[Callable[[Path], Path], str]] = {
    'missing_folder': (_missing, 'no bag folder'),
    'folder_without_metadata': (_no_metadata, 'has no metadata.yaml'),
    'unparsable_metadata': (_unparsable_metadata, 'is not valid YAML'),
    'empty_metadata': (_empty_metadata, 'metadata.yaml is empty'),
    'metadata_of_no_bag': (_foreign_metadata, 'has no rosbag2_bagfile_information'),
    'metadata_names_a_missing_mcap': (_missing_mcap, 'bag.mcap, which is missing'),
    'truncated_mcap': (_truncated_mcap, 'truncated'),
    'empty_mcap_in_the_folder': (_empty_mcap, 'bag.mcap is empty'),
    'mcap_bad_half_way': (_bad_half_way, 'message 2401 of 4265 cannot be read'),
    'mcap_skipped_half_way': (_skipped_half_way, 'only 2400 of the 4265 messages'),
    'empty_file': (_empty_file, 'is an empty file'),
    'mcap_file_without_its_folder': (_lone_mcap_file, 'no metadata.yaml beside it'),
    'folder_that_is_no_bag': (_not_a_bag, 'has no metadata.yaml'),
    'no_usable_topic': (_no_usable_topic, 'no usable topic'),
    'bag_without_messages': (_no_messages, 'has no messages'),
    'wrong_message_type': (_wrong_message_type, 'needs sensor_msgs/msg/PointCloud2'),
}
"""Bad bag -> (builder, words of the one error line)."""


REPLAYABLE = frozenset({'no_usable_topic', 'wrong_message_type'})
"""Bags that are no input of the offline tools but that ``replay`` plays as they are."""

CASES = [
    (bad, command)
    for bad in BAD_BAGS
    for command in BAG_COMMANDS
    if not (command == 'replay' and bad in REPLAYABLE)
]


@pytest.fixture(scope='module')
def estimate_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An estimate output folder of the small bag (for ``report --bag``)."""
    out = tmp_path_factory.mktemp('estimate') / 'run'
    run = cli('estimate', SMALL, '--out', out, '--quiet')
    assert run.code == 0, run.stderr
    return out


@pytest.fixture(scope='module')
def bad_bag_runs(
    tmp_path_factory: pytest.TempPathFactory, estimate_folder: Path
) -> dict[tuple[str, str], tuple[Run, Path]]:
    """Every bad bag through every command that reads a bag, two processes at a time."""
    jobs = {}
    bags = {}
    for name, command in CASES:
        if name not in bags:
            tmp = tmp_path_factory.mktemp(name)
            bags[name] = (tmp, BAD_BAGS[name][0](tmp))
        tmp, bag = bags[name]
        out = tmp / f'out_{command}'
        args: list[str | Path] = {
            'triangulate': ['triangulate', bag, '--out', out, '--quiet'],
            'estimate': ['estimate', bag, '--out', out, '--quiet'],
            'report': ['report', estimate_folder, '--bag', bag, '--out', out],
            'replay': ['replay', bag, '--rate', '1000'],
        }[command]
        jobs[(name, command)] = (args, out)
    return {key: (cli_in_process(*args), out) for key, (args, out) in jobs.items()}


@pytest.mark.parametrize(('bad', 'command'), CASES)
def test_a_bad_bag_is_one_line_and_exit_status_2(bad_bag_runs, bad, command):
    run, out = bad_bag_runs[(bad, command)]
    line = run.error_line(command)
    assert run.code == 2, line
    assert BAD_BAGS[bad][1] in line
    assert not out.exists()  # nothing written from a bad bag


@pytest.mark.parametrize('command', BAG_COMMANDS)
def test_a_bad_bag_ends_the_process_with_one_line_and_exit_status_2(
    tmp_path, estimate_folder, command
):
    """The same as a real process (the matrix above runs ``main`` in this process)."""
    bag = _truncated_mcap(tmp_path)
    out = tmp_path / 'out'
    args: list[str | Path] = {
        'triangulate': ['triangulate', bag, '--out', out, '--quiet'],
        'estimate': ['estimate', bag, '--out', out, '--quiet'],
        'report': ['report', estimate_folder, '--bag', bag, '--out', out],
        'replay': ['replay', bag, '--rate', '1000'],
    }[command]
    run = cli(*args)
    line = run.error_line(command)
    assert run.code == 2 and 'truncated' in line and not out.exists()


def test_a_bag_failing_half_way_leaves_one_line_on_the_terminal(tmp_path):
    """With progress bars on: the bar is cleared, the error line takes its place."""
    bag = _bad_half_way(tmp_path)
    for command in ('triangulate', 'estimate'):
        run = cli(command, bag, '--out', tmp_path / f'out_{command}')
        assert run.code == 2
        assert TRACEBACK not in run.stderr
        shown = visible_lines(run.stderr)
        assert len(shown) == 1, repr(run.stderr)
        assert shown[0].startswith(f'orbit-tracking {command}: error: ')
        assert 'message 2401 of 4265 cannot be read' in shown[0]


def test_the_mcap_file_of_a_bag_stands_for_its_folder(tmp_path):
    """Accepted: the folder's metadata (time base, scenario, gaps) is what the file lacks,
    and the folder is what is read, so the outputs equal those of the folder."""
    by_file = cli('triangulate', SMALL / 'bag.mcap', '--out', tmp_path / 'file', '--quiet')
    by_folder = cli('triangulate', SMALL, '--out', tmp_path / 'folder', '--quiet')
    assert by_file.code == 0 and by_folder.code == 0, by_file.stderr + by_folder.stderr
    file_fixes = (tmp_path / 'file' / 'fixes.csv').read_text()
    assert file_fixes == (tmp_path / 'folder' / 'fixes.csv').read_text()
    assert len(file_fixes.splitlines()) > 100
    summary = yaml.safe_load((tmp_path / 'file' / 'summary.yaml').read_text())
    assert summary['bag'] == str(SMALL)


# -- the --force rule -------------------------------------------------------------------

REFUSAL = '{out} exists and is not empty; pass --force to replace it or choose another --out'

WRITERS: dict[str, list[str | Path]] = {
    'simulate': ['simulate', '--scenario', 'seed003_q2', '--quiet', '--batch-period', '5'],
    'triangulate': ['triangulate', SMALL, '--quiet'],
    'estimate': ['estimate', SMALL, '--quiet'],
    'demo': ['demo', '--scenario', 'seed003_q2', '--quiet'],
    'record': ['record', '--duration', '1'],
}
"""Every command that writes a folder (given as --out)."""


@pytest.mark.parametrize('command', list(WRITERS))
def test_a_non_empty_output_folder_is_refused_in_the_same_words(tmp_path, command):
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'keep.txt').write_text('precious')
    run = cli(*WRITERS[command], '--out', out)
    line = run.error_line(command)
    assert run.code == 2
    assert line == f'orbit-tracking {command}: error: ' + REFUSAL.format(out=out)
    assert [p.name for p in out.iterdir()] == ['keep.txt']


@pytest.mark.parametrize('command', ['simulate', 'triangulate', 'estimate'])
def test_force_replaces_the_folder_and_an_empty_one_needs_no_force(tmp_path, command):
    out = tmp_path / 'out'
    out.mkdir()
    first = cli(*WRITERS[command], '--out', out)  # empty: used as it is
    assert first.code == 0, first.stderr
    (out / 'keep.txt').write_text('stale')
    again = cli(*WRITERS[command], '--out', out, '--force')
    assert again.code == 0, again.stderr
    assert not (out / 'keep.txt').exists()
    assert (out / 'metadata.yaml' if command == 'simulate' else out / 'summary.yaml').is_file()


@pytest.mark.dds
def test_record_with_force_replaces_the_folder(tmp_path):
    out = tmp_path / 'rec'
    out.mkdir()
    (out / 'keep.txt').write_text('stale')
    run = cli('record', '--out', out, '--duration', '1', '--force', timeout=60)
    assert run.code == 0, run.stderr
    assert (out / 'metadata.yaml').is_file() and not (out / 'keep.txt').exists()


def test_force_never_replaces_the_input_bag(tmp_path):
    bag = _copy(SMALL, tmp_path / 'bag')
    for target in (bag, tmp_path):
        run = cli('estimate', bag, '--out', target, '--force', '--quiet')
        assert run.code == 2
        assert 'holds the input' in run.error_line('estimate')
    assert sorted(p.name for p in bag.iterdir()) == ['bag.mcap', 'metadata.yaml']


# -- stations with measurements but no state --------------------------------------------


def test_no_station_state_is_named_not_no_data(tmp_path):
    """sat09 without a state topic, sat06's states stamped with sat09's id (none valid)."""
    bag = copy_bag(
        SMALL,
        tmp_path / 'bag',
        lambda t, _: {
            '/stations/sat09/state': '/stations/sat06/state',
            '/stations/sat06/state': None,
        }.get(t, t),
    )
    for command in ('triangulate', 'estimate'):
        run = cli(command, bag, '--out', tmp_path / command, '--quiet')
        assert run.code == 2
        line = run.error_line(command)
        assert 'no data' not in line
        assert 'station sat09 has measurements but no stations/sat09/state topic' in line
        assert (
            'station sat06 has measurements but none of the 150 messages of '
            'stations/sat06/state is valid'
        ) in line


def test_no_state_topic_at_all_is_said_before_reading(tmp_path):
    bag = copy_bag(
        SMALL,
        tmp_path / 'bag',
        lambda t, _: None if t.startswith('/stations/sat') and t.endswith('/state') else t,
    )
    run = cli('estimate', bag, '--out', tmp_path / 'out', '--quiet')
    assert run.code == 2
    line = run.error_line('estimate')
    for sid in ('sat06', 'sat09'):
        assert f'station {sid} has measurements but no stations/{sid}/state topic' in line


def test_one_station_without_state_is_reported_and_the_others_used(tmp_path):
    bag = copy_bag(
        SMALL, tmp_path / 'bag', lambda t, _: None if t == '/stations/sat06/state' else t
    )
    run = cli('triangulate', bag, '--out', tmp_path / 'tri', '--quiet')
    assert run.code == 0, run.stderr
    note = (
        'station sat06: measurements but no state (no stations/sat06/state topic); its '
        'measurements were not used'
    )
    assert note in run.stdout.splitlines()
    summary = yaml.safe_load((tmp_path / 'tri' / 'summary.yaml').read_text())
    assert summary['stations_without_state'] == {'sat06': 'no stations/sat06/state topic'}
    run = cli('estimate', bag, '--out', tmp_path / 'est', '--quiet')
    assert run.code == 2  # one satellite alone gives no rough trajectory to start from
    line = run.error_line('estimate')
    assert 'no window could be solved' in line and note in line


# -- triangulate through a station that stops measuring ---------------------------------


def test_independent_stride_ignores_unknown_intervals():
    assert _independent_stride(0.04, [0.1, 0.04]) == 5
    assert _independent_stride(0.04, [0.1, math.inf]) == 5  # a series of two samples
    assert _independent_stride(0.04, [math.nan, 0.04]) == 2
    assert _independent_stride(0.04, [math.inf]) == 1
    assert _independent_stride(0.04, []) == 1
    assert _independent_stride(math.inf, [0.1]) == 1
    assert _independent_stride(0.0, [0.1]) == 1


def _feed(aligner: Aligner, sid: str, times: np.ndarray) -> None:
    aligner.add_measurements(
        sid,
        ('azimuth', 'elevation'),
        times,
        np.zeros(times.size, dtype=np.uint32),
        np.tile([0.3, 0.4], (times.size, 1)),
        np.full((times.size, 2), 1e-4),
    )


def _epochs(fast: tuple[float, float], slow_end: float) -> list[float]:
    """Epoch times of an aligner fed in one-second steps, as a node or the offline tool
    does: station ``fast`` at 25 Hz over ``fast``, ``slow`` at 10 Hz from 0."""
    aligner = Aligner(AlignConfig(lag=0.0))
    for sid in ('fast', 'slow'):
        for t in (0.0, slow_end):
            aligner.add_pose(sid, t, np.zeros(3), np.zeros(3), np.eye(3), False)
    out = []
    for second in range(int(math.ceil(slow_end))):
        t0, t1 = float(second), float(second + 1)
        slow = np.arange(round(t0 * 10), round(min(t1, slow_end) * 10)) / 10 + 0.03
        fast_t = np.arange(round(t0 * 25), round(t1 * 25)) / 25 + 0.011
        _feed(aligner, 'slow', slow)
        _feed(aligner, 'fast', fast_t[(fast_t >= fast[0]) & (fast_t < fast[1])])
        out += [e.time for e in aligner.process(until=t1)]
    out += [e.time for e in aligner.flush()]
    return out


def test_epochs_run_on_after_a_station_stops_and_never_go_back():
    t = np.array(_epochs((4.0, 10.0), 20.0))
    assert np.all(np.diff(t) > 0)  # a faster station starting: no epoch again, or before
    assert t[-1] > 19.9  # the faster station ending: the epochs go on to the data's end
    assert np.allclose(np.diff(t[t > 4.1]), 0.04)  # on the grid of the fastest station


@pytest.fixture(scope='module')
def station_stops_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """40 s of seed004_sea: the ship's radar throughout, its theodolite (25 Hz) only
    from 8 s to 20 s, as when the aircraft flies into and out of its range."""
    tmp = tmp_path_factory.mktemp('sea')
    sc = yaml.safe_load((ROOT / 'config' / 'scenarios' / 'seed004_sea.yaml').read_text())
    sc.update(name='sea_theodolite_8_20', span=[0.0, 40.0])
    eo = next(s for s in sc['stations'] if s['id'] == 'eo')
    eo.update(
        max_range_m=150000.0, dropouts=[{'start': 0.0, 'end': 8.0}, {'start': 20.0, 'end': 40.0}]
    )
    path = tmp / 'scenario.yaml'
    path.write_text(yaml.safe_dump(sc, sort_keys=False))
    run = cli('simulate', '--scenario', path, '--out', tmp / 'bag', '--quiet')
    assert run.code == 0, run.stderr
    return tmp / 'bag'


def test_triangulate_runs_to_the_end_when_a_station_stops(station_stops_bag, tmp_path):
    run = cli('triangulate', station_stops_bag, '--out', tmp_path / 'tri', '--quiet')
    assert run.code == 0, run.stderr
    fixes = np.genfromtxt(tmp_path / 'tri' / 'fixes.csv', delimiter=',', names=True)
    t = fixes['time'] - 1_700_000_000
    assert np.all(np.diff(t) > 0)
    assert t[-1] > 39.8  # the radar's last sample is at 39.93 s
    after = t > 20.5
    assert after.sum() > 400 and np.all(fixes['n_lines'][after] == 1)  # the radar alone
    summary = yaml.safe_load((tmp_path / 'tri' / 'summary.yaml').read_text())
    assert summary['evaluation'][0]['n'] == t.size
    assert summary['evaluation'][0]['stride'] == 5  # 2 x 0.1 s radar interval / 0.04 s
    assert summary['nees'][0]['consistent']
