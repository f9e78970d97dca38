"""The input journal (core/data/journal.py, core/data/journaled_buffer.py): records survive a
torn tail, a corrupt CRC and a SIGKILL of the writer; compaction keeps exactly what a later
window needs; the file stays under its bound; a buffer replayed from the journal cuts the
same observations as the buffer that wrote it."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from itertools import product

import numpy as np
import pytest

from orbit_tracking.core.data.buffer import ObservationBuffer
from orbit_tracking.core.data.journal import (
    MAGIC,
    MIN_JOURNAL_BYTES,
    Journal,
    JournalError,
    JournalRecord,
    encode_record,
    records_to_keep,
    scan_journal,
)
from orbit_tracking.core.data.journaled_buffer import (
    JournaledBuffer,
    pack_arrays,
    replay_records,
    unpack_arrays,
)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _rec(i: int, t: float | None = None, kind: str = 'm', key: str = 'a', n: int = 20):
    return JournalRecord(kind, key, float(i if t is None else t), bytes([i % 251]) * n)


def _write(path, records):
    path.write_bytes(MAGIC + b''.join(encode_record(r) for r in records))


# -- the file -----------------------------------------------------------------------------------


def test_records_read_back_in_order_after_reopening(tmp_path):
    path = tmp_path / 'j' / 'x.journal'
    j = Journal(path, MIN_JOURNAL_BYTES)
    recs = [_rec(i, key=f'k{i % 3}') for i in range(50)]
    recs.append(JournalRecord('state', '', -math.inf, b'{"a": 1}', sticky=True))
    for r in recs:
        j.append(r)
    assert j.records() == recs
    j.close()
    j2 = Journal(path, MIN_JOURNAL_BYTES)
    assert list(j2.recovered.records) == recs and j2.recovered.problem == ''
    assert j2.size == path.stat().st_size
    j2.close()


def test_a_torn_tail_is_left_out_at_every_cut_and_cut_off_before_appending(tmp_path):
    """A write cut short anywhere in the last record (frame, payload) loses that record
    only; reopening truncates the file there, so what is appended next is read back."""
    recs = [_rec(i) for i in range(5)]
    whole = MAGIC + b''.join(encode_record(r) for r in recs)
    last = len(encode_record(recs[-1]))
    path = tmp_path / 'x.journal'
    for cut in range(1, last):
        path.write_bytes(whole[: len(whole) - cut])
        scan = scan_journal(path)
        assert list(scan.records) == recs[:4], cut
        assert scan.discarded_bytes == last - cut
        assert scan.problem == ('torn record frame' if last - cut < 8 else 'torn record')
        j = Journal(path, MIN_JOURNAL_BYTES)
        assert j.counts['tail_bytes_discarded'] == last - cut
        j.append(_rec(9))
        j.close()
        assert list(scan_journal(path).records) == [*recs[:4], _rec(9)]
        assert scan_journal(path).problem == ''
    # torn within the magic: an empty journal, started anew
    path.write_bytes(MAGIC[:2])
    assert scan_journal(path).problem == 'torn file header'
    j = Journal(path, MIN_JOURNAL_BYTES)
    assert j.recovered.records == () and path.read_bytes() == MAGIC
    j.close()


@pytest.mark.parametrize('where', ['payload', 'crc', 'length'])
def test_a_corrupt_record_stops_the_scan_there_without_raising(tmp_path, where):
    recs = [_rec(i) for i in range(6)]
    path = tmp_path / 'x.journal'
    _write(path, recs)
    data = bytearray(path.read_bytes())
    start = len(MAGIC) + sum(len(encode_record(r)) for r in recs[:3])
    if where == 'payload':
        data[start + 8 + 15] ^= 0x40
    elif where == 'crc':
        data[start + 5] ^= 0x01
    else:
        data[start : start + 4] = (2**31).to_bytes(4, 'little')
    path.write_bytes(bytes(data))
    scan = scan_journal(path)
    assert list(scan.records) == recs[:3]
    assert scan.problem == ('bad record length' if where == 'length' else 'CRC mismatch')
    assert scan.valid_bytes == start and scan.discarded_bytes == len(data) - start


def test_a_file_that_is_not_a_journal_is_refused_not_overwritten(tmp_path):
    path = tmp_path / 'x.journal'
    path.write_bytes(b'hello world')
    with pytest.raises(JournalError, match='not an orbit_tracking journal'):
        Journal(path, MIN_JOURNAL_BYTES)
    assert path.read_bytes() == b'hello world'


def test_one_process_at_a_time_holds_a_journal(tmp_path):
    path = tmp_path / 'x.journal'
    j = Journal(path, MIN_JOURNAL_BYTES)
    with pytest.raises(JournalError, match=f'in use by another process \\(pid {os.getpid()}\\)'):
        Journal(path, MIN_JOURNAL_BYTES)
    j.close()
    Journal(path, MIN_JOURNAL_BYTES).close()


_WRITER = textwrap.dedent(
    """
    import sys
    from orbit_tracking.core.data.journal import Journal, JournalRecord
    j = Journal(sys.argv[1], 1 << 20, fsync_interval=3600.0)
    i = 0
    while True:
        j.append(JournalRecord('m', 'a', float(i), bytes([i % 251]) * 200))
        print(i, flush=True)
        i += 1
    """
)


def test_sigkill_of_the_writer_loses_no_appended_record_and_frees_the_journal(tmp_path):
    """Every record a writer had appended (and said so) before SIGKILL is read back, intact
    and in order, although it never fsynced; the lock dies with the process."""
    path = tmp_path / 'x.journal'
    env = dict(os.environ, PYTHONPATH=ROOT)
    proc = subprocess.Popen(
        [sys.executable, '-c', _WRITER, str(path)], stdout=subprocess.PIPE, env=env
    )
    assert proc.stdout is not None
    said = -1
    deadline = time.monotonic() + 30
    while said < 500 and time.monotonic() < deadline:
        said = int(proc.stdout.readline())
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    assert said >= 500
    j = Journal(path, 1 << 20)  # the lock went with the process
    got = j.recovered.records
    assert len(got) >= said + 1
    assert [r.time for r in got] == [float(i) for i in range(len(got))]
    assert all(r.data == bytes([i % 251]) * 200 for i, r in enumerate(got))
    j.close()


def test_fsync_runs_at_most_once_per_interval_and_at_once_when_asked(tmp_path):
    now = [0.0]
    j = Journal(
        tmp_path / 'x.journal', MIN_JOURNAL_BYTES, fsync_interval=1.0, clock=lambda: now[0]
    )
    for i in range(10):
        now[0] = 0.25 * i  # 0 .. 2.25 s
        j.append(_rec(i))
    assert j.counts['fsyncs'] == 2  # at 1.0 and 2.0 s
    j.append(_rec(10), sync=True)
    assert j.counts['fsyncs'] == 3
    assert not j.sync(force=True)  # nothing new
    j.close()


# -- what is kept -------------------------------------------------------------------------------


def _reference_keep(entries, keep_from):
    """records_to_keep without a budget, by its definition, one record at a time."""
    out = []
    for i, (kind, key, t, _sticky, _) in enumerate(entries):
        if t >= keep_from:
            out.append(True)
            continue
        group = [
            (e[2], j)
            for j, e in enumerate(entries)
            if e[3] and (e[0], e[1]) == (kind, key) and e[2] < keep_from
        ]
        out.append(bool(entries[i][3]) and max(group) == (t, i))
    return out


def test_compaction_keeps_what_a_later_window_needs():
    rng = np.random.default_rng(7)
    for _ in range(200):
        n = int(rng.integers(1, 30))
        entries = [
            (
                str(rng.choice(['pose', 'measurements', 'state'])),
                str(rng.choice(['a', 'b'])),
                float(rng.choice([-math.inf, *rng.integers(0, 10, 3)])),
                bool(rng.random() < 0.5),
                int(rng.integers(10, 100)),
            )
            for _ in range(n)
        ]
        keep_from = float(rng.integers(0, 10))
        keep, dropped = records_to_keep(entries, keep_from)
        assert keep == _reference_keep(entries, keep_from) and dropped == 0


def test_compaction_rewrites_the_file_with_the_needed_records_in_order(tmp_path):
    path = tmp_path / 'x.journal'
    j = Journal(path, MIN_JOURNAL_BYTES)
    recs = []
    for i in range(20):
        recs.append(_rec(i, t=float(i), kind='measurements', key='cw01'))
        recs.append(JournalRecord('pose', 'sat', float(i), b'p%d' % i, sticky=True))
    recs.insert(0, JournalRecord('pose', 'fixed', 0.0, b'only', sticky=True))
    recs.append(JournalRecord('state', '', -math.inf, b'{"n": 1}', sticky=True))
    recs.append(JournalRecord('state', '', -math.inf, b'{"n": 2}', sticky=True))
    for r in recs:
        j.append(r)
    before = j.size
    released, dropped = j.compact(12.5)
    want = [
        r
        for r in recs
        if r.time >= 12.5 or r.data in (b'only', b'p12', b'{"n": 2}')  # newest sticky before
    ]
    assert j.records() == want and dropped == 0 and released == len(recs) - len(want)
    assert j.size == path.stat().st_size < before
    assert not (tmp_path / 'x.journal.tmp').exists()
    j.append(_rec(99, t=30.0))
    j.close()
    assert list(scan_journal(path).records) == [*want, _rec(99, t=30.0)]


def test_the_file_stays_under_its_bound_dropping_the_oldest_needed_records(tmp_path):
    """Nothing is released (keep_from never moves), so the bound drops the oldest inputs;
    the newest record of each sticky group survives, and the newest inputs are all there."""
    path = tmp_path / 'x.journal'
    bound = MIN_JOURNAL_BYTES
    j = Journal(path, bound)
    j.append(JournalRecord('pose', 'fixed', 0.0, b'fixed pose', sticky=True))
    j.append(JournalRecord('state', '', -math.inf, b'{}', sticky=True))
    frame = len(encode_record(_rec(0, n=500)))
    n = 4 * bound // frame
    biggest = 0
    for i in range(1, n):
        j.append(_rec(i, n=500))
        biggest = max(biggest, path.stat().st_size)
        assert path.stat().st_size == j.size
    assert biggest <= bound
    assert j.counts['records_dropped'] > 0 and j.counts['compactions'] >= 3
    got = j.records()
    assert got[0].data == b'fixed pose' and got[1].data == b'{}'
    times = [r.time for r in got[2:]]
    assert times == list(np.arange(n - len(times), n, dtype=float))  # the newest, in order
    assert len(times) * frame >= bound // 2
    j.close()


def test_clear_forgets_every_record(tmp_path):
    j = Journal(tmp_path / 'x.journal', MIN_JOURNAL_BYTES)
    for i in range(5):
        j.append(_rec(i))
    j.clear()
    assert j.records() == [] and (tmp_path / 'x.journal').read_bytes() == MAGIC
    j.close()


# -- array payloads -----------------------------------------------------------------------------


def test_arrays_pack_and_unpack_exactly_and_malformed_data_is_refused():
    a = {
        'time': np.array([1.0, 2.5, np.nan]),
        'target_id': np.array([0, 7, 2**32 - 1], dtype=np.uint32),
        'values': np.arange(6.0).reshape(3, 2),
        'flag': np.array(True),
    }
    meta, b = unpack_arrays(pack_arrays({'fields': ['range', 'azimuth']}, **a))
    assert meta == {'fields': ['range', 'azimuth']}
    for k, v in a.items():
        np.testing.assert_array_equal(b[k], v)
        assert b[k].dtype == v.dtype and b[k].shape == v.shape
    data = pack_arrays({}, x=np.arange(4.0))
    with pytest.raises(ValueError, match='runs past the end'):
        unpack_arrays(data[:-1])
    with pytest.raises(ValueError, match='left over'):
        unpack_arrays(data + b'\0')
    with pytest.raises(ValueError, match='cannot be packed'):
        pack_arrays({}, x=np.array(['a']))
    evil = data.replace(b'"<f8"', b'"|O8"')
    with pytest.raises(ValueError, match='dtype'):
        unpack_arrays(evil)


# -- the journaled buffer -----------------------------------------------------------------------


def _feed(buf: ObservationBuffer, rng: np.random.Generator) -> None:
    """A pass in pieces: two fixed stations, one moving, telemetry and fixes, out of order
    and with repeats, as a live node receives them."""
    rot = np.eye(3)
    buf.add_pose('cw01', 0.0, [1e3, 0, 0], [0, 0, 0], rot, False)
    buf.add_pose('opt01', 0.0, [0, 1e3, 0], [0, 0, 0], rot, False)
    for k in range(120):
        t0 = 0.25 * k + rng.uniform(0.0, 0.05)
        t = t0 + np.arange(5) * 0.05
        buf.add_measurements(
            'cw01',
            ('range', 'range_rate'),
            t,
            0,
            rng.normal(size=(5, 2)) + [1e4, 10.0],
            np.full((5, 2), [1.0, 0.01]),
        )
        buf.add_measurements(
            'opt01',
            ('azimuth', 'elevation'),
            t[::-1],
            np.array([0, 1, 0, 1, 0]),
            rng.normal(size=(5, 2)) * 1e-3,
            np.full((5, 2), 1e-4),
        )
        if k % 4 == 0:
            buf.add_pose('sat', t0, [7e6 + t0, 0, 0], [7.5e3, 0, 0], rot, True)
        buf.add_telemetry(0, t0, [t0, 0, 1e3], [1, 0, 0], [5, 5, 5], [0.1, 0.1, 0.1])
        buf.add_fix(0, t0, [t0, 0, 1e3], np.eye(3) * 4.0)
        if k % 10 == 9:  # a repeated message
            buf.add_telemetry(0, t0, [t0, 0, 1e3], [1, 0, 0], [5, 5, 5], [0.1, 0.1, 0.1])


def _same_observations(a: ObservationBuffer, b: ObservationBuffer, t0: float, t1: float) -> None:
    oa, ob = a.observations(t0, t1), b.observations(t0, t1)
    assert [s.table.station_id for s in oa.stations] == [s.table.station_id for s in ob.stations]
    assert oa.stations, 'no rows in the window'
    for sa, sb in zip(oa.stations, ob.stations, strict=True):
        assert sa.table.fields == sb.table.fields
        for name in ('time', 'target_id', 'values', 'sigmas'):
            np.testing.assert_array_equal(getattr(sa.table, name), getattr(sb.table, name))
        for name in ('position', 'velocity', 'rotation'):
            np.testing.assert_array_equal(getattr(sa.pose, name), getattr(sb.pose, name))
    for name, fields in (
        ('telemetry', ('time', 'position', 'velocity', 'position_sigma', 'velocity_sigma')),
        ('fixes', ('time', 'position', 'covariance')),
    ):
        xa, xb = getattr(oa, name), getattr(ob, name)
        assert sorted(xa) == sorted(xb) and xa
        for k in xa:
            for f in fields:
                np.testing.assert_array_equal(getattr(xa[k], f), getattr(xb[k], f))


def test_a_buffer_replayed_from_its_journal_cuts_the_same_observations(tmp_path):
    """Fill a journaled buffer, prune and compact it as the node does after a window; a
    fresh buffer replayed from the journal file (and pruned the same) gives the same
    observations of every later window, bit for bit."""
    rng = np.random.default_rng(3)
    path = tmp_path / 'x.journal'
    j = Journal(path, 1 << 20)
    ctx = {'ref_ns': 1_700_000_000 * 10**9, 'world_frame': 'earth'}
    live = JournaledBuffer(j, lambda: ctx)
    _feed(live, rng)
    keep_from = 12.0
    live.prune(keep_from)
    released, dropped = j.compact(keep_from)
    assert released > 0 and dropped == 0
    assert live.sizes()['journal_records'] == j.n_records
    j.close()

    j2 = Journal(path, 1 << 20)
    again = ObservationBuffer()
    summary = replay_records(again, j2.recovered.records)
    again.prune(keep_from)
    assert summary.context == ctx and not any(k.startswith('failed') for k in summary.counts)
    assert summary.poses['cw01'][4] is False and summary.poses['sat'][4] is True
    assert summary.counts['measurement_rows'] > 0 and summary.last_time == pytest.approx(
        30.0, abs=0.5
    )
    for t0, t1 in product([12.0, 15.0, 20.0], [22.0, 30.0, 40.0]):
        _same_observations(live, again, t0, t1)
    assert again.latest_time() == live.latest_time()
    j2.close()


def test_a_record_the_buffer_refuses_on_replay_is_counted_not_fatal(tmp_path):
    j = Journal(tmp_path / 'x.journal', MIN_JOURNAL_BYTES)
    j.append(JournalRecord('fix', '0', 1.0, b'garbage'))
    j.append(JournalRecord('telemetry', 'x', 1.0, pack_arrays({}, position=np.zeros(3))))
    j.append(JournalRecord('what', '', 1.0, b''))
    summary = replay_records(ObservationBuffer(), j.records())
    assert summary.counts == {'failed_fix': 1, 'failed_telemetry': 1, 'unknown_what': 1}
    assert summary.data_records == 0
    j.close()


# -- the node side (ros/journal.py) -------------------------------------------------------------


def test_journal_paths_differ_for_every_node_domain_and_namespace(tmp_path):
    from orbit_tracking.ros.journal import journal_path

    names = ['/estimator', '/a/estimator', '/b/estimator', '/a/b/estimator', '/a/estimator2']
    paths = {journal_path(tmp_path, n, d) for n in names for d in (0, 7)}
    assert len(paths) == 2 * len(names)
    assert (
        journal_path(tmp_path, '/a/b/estimator', 7) == tmp_path / 'domain7/a/b/estimator.journal'
    )
    with pytest.raises(ValueError, match='no name'):
        journal_path(tmp_path, '/', 0)
