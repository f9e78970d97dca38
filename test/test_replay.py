"""``orbit-tracking replay`` (``--loop``, ``--clock``), the processing nodes' reset when time
goes back, and a smoke run of the DDS throughput benchmark."""

from __future__ import annotations

import dataclasses
import math
import signal
import sys
import time
import types

import numpy as np
import pytest
from conftest import default_context

from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.core.sim.stream import EventStream
from orbit_tracking.tools.cli import main as cli_main

EPOCH_NS = 1_700_000_000 * 1_000_000_000

SHORT_Q2 = """\
base: seed003_q2
name: q2_short
description: seed003_q2 cut to 20 s (replay tests)
span: [50.0, 70.0]
"""


def _stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _events(scenario, t_end: float | None = None):
    """``(event, message)`` of a scenario (optionally cut at ``t_end``), in time order, as a
    live simulator or a bag replay delivers them."""
    from orbit_tracking.ros.conversions import TimeBase
    from orbit_tracking.ros.messages import event_message

    sc = load_scenario(scenario)
    if t_end is not None:
        sc = dataclasses.replace(sc, t_end=t_end)
    result = simulate(sc)
    tb = TimeBase.from_seconds(sc.epoch)
    return [(ev, event_message(result, ev, tb)) for ev in EventStream(result, truth=False)]


def _feed(node, ev, msg) -> None:
    """Hand a message to a node's subscription callback, as its executor would."""
    if ev.kind == 'measurement':
        node._on_measurements(msg, ev.key)
    elif ev.kind == 'station_state':
        node._on_state(msg, ev.key)
    else:
        node._on_telemetry(msg)


def test_triangulation_node_resets_once_per_loop_and_repeats_its_fixes(tmp_path):
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    (tmp_path / 'q2.yaml').write_text(SHORT_Q2)
    events = _events(tmp_path / 'q2.yaml')

    def stream(ev) -> str:
        return ev.key if ev.kind == 'measurement' else f'{ev.key}/{ev.kind}'

    with default_context(lag=0.5):
        node = TriangulationNode()
        got: list = []
        node.fix_pub = types.SimpleNamespace(publish=got.append)
        try:
            for ev, msg in events:
                _feed(node, ev, msg)
            # the bag again: time goes back, one stream after another; one voice is not
            # enough, most of the active streams must go back before the node resets
            fed = 0
            while node.counts['time_resets'] == 0:
                _feed(node, *events[fed])
                fed += 1
            assert fed >= 2, 'the first stream to go back reset the node on its own'
            assert node.counts['time_resets'] == 1
            first_pass = len(got)  # with the held epochs, fixed at the reset
            # a message of the first pass that arrives after the second began, on a topic
            # that has not gone back yet (topics are not ordered with respect to each other)
            back = {stream(ev) for ev, _ in events[:fed]}
            straggler = next(
                (ev, m)
                for ev, m in reversed(events)
                if ev.kind == 'measurement' and stream(ev) not in back
            )
            _feed(node, *straggler)
            assert node.counts['stale_after_reset'] == 1
            for ev, msg in events[fed:]:
                _feed(node, ev, msg)
            for ev, msg in events:  # a third pass: the second one's held epochs are fixed
                _feed(node, ev, msg)
                if node.counts['time_resets'] == 2:
                    break
            assert node.counts['time_resets'] == 2
        finally:
            node.destroy_node()
    assert first_pass > 90  # 20 s at 5 Hz
    # the second pass gives exactly the fixes of the first: nothing of it leaked over
    assert [_stamp(m) for m in got[first_pass:]] == [_stamp(m) for m in got[:first_pass]]
    pos = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in got])
    np.testing.assert_allclose(pos[first_pass:], pos[:first_pass], rtol=0, atol=1e-6)


def test_estimator_node_solves_the_held_window_and_starts_anew_when_time_goes_back():
    from orbit_tracking.ros.conversions import TimeBase, cloud_to_window_states
    from orbit_tracking.ros.estimator_node import EstimatorNode

    keep = ('cw01', 'cw03', 'cw07', 'opt01', 'opt02')  # enough for the fit, quick to solve
    events = [(ev, m) for ev, m in _events('seed000_s1', t_end=6.0) if ev.key in keep + ('0',)]
    params = {'window_length': 4.0, 'window_overlap': 1.0, 'latency': 0.5}
    with default_context(**params, time_reference=EPOCH_NS * 1e-9):
        node = EstimatorNode()
        got: list = []
        node.window_pub = types.SimpleNamespace(publish=got.append)
        try:
            for _ in range(2):
                for i, (ev, msg) in enumerate(events):
                    _feed(node, ev, msg)
                    if i % 50 == 0:
                        node._solve_due(final=False)  # the node's timer
            node._solve_due(final=True, block=True)  # the end of the stream
            assert node.counts['time_resets'] == 1
        finally:
            node.destroy_node()
    tb = TimeBase(EPOCH_NS)
    windows = [cloud_to_window_states(m, tb) for m in got]
    spans = [(round(w.t0, 3), round(w.t1, 3)) for w in windows]
    # [0, 4] closed by the data, the rest by the reset (the end of the first pass); then
    # the same again from a clean start
    assert len(spans) == 4 and spans[0] == (0.0, 4.0) and spans[2:] == spans[:2], spans
    np.testing.assert_allclose(windows[2].state, windows[0].state, rtol=0, atol=1e-6)
    np.testing.assert_allclose(windows[3].state, windows[1].state, rtol=0, atol=1e-6)


@pytest.mark.dds
def test_replay_in_a_loop_resets_the_triangulation_node_and_publishes_the_bag_clock(
    tmp_path, start_process, node_command, rclpy_node, spin_until
):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    from orbit_tracking.ros import qos

    (tmp_path / 'q2.yaml').write_text(SHORT_Q2)
    bag = tmp_path / 'bag'
    assert cli_main(['simulate', '--scenario', str(tmp_path / 'q2.yaml'), '--out', str(bag)]) == 0
    tri = start_process(node_command('triangulation_node', lag=0.5, flush_after=1.0))
    fixes: list[int] = []
    clock: list[int] = []
    resets: list[int] = []
    rclpy_node.create_subscription(
        PoseWithCovarianceStamped,
        'triangulation/fixes',
        lambda m: fixes.append(_stamp(m)),
        qos.STATE_STREAM,
    )
    # best effort, as rclpy's own /clock reader (use_sim_time) and the player's writer
    clock_qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    rclpy_node.create_subscription(
        Clock, '/clock', lambda m: clock.append(_stamp_of(m)), clock_qos
    )

    def on_diag(msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name == 'triangulation: fixes':
                values = {kv.key: kv.value for kv in s.values}
                resets.append(int(values.get('time_resets', '0')))

    rclpy_node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, qos.DIAGNOSTICS)
    spin_until(
        rclpy_node,
        lambda: rclpy_node.count_publishers('triangulation/fixes') > 0,
        20,
        'the triangulation node to appear',
    )
    player = start_process(
        [sys.executable, '-m', 'orbit_tracking.tools.cli', 'replay', str(bag), '--rate', '10']
        + ['--loop', '--clock', '--topics', 'stations/*', '--wait-for-subscribers', '1'],
        label='replay',
    )

    def after_reset() -> int:
        """Fixes published after the first one whose stamp went back."""
        back = next((i for i in range(1, len(fixes)) if fixes[i] < fixes[i - 1]), None)
        return 0 if back is None else len(fixes) - back

    def clock_went_back() -> bool:
        return any(b < a - 10 * 10**9 for a, b in zip(clock, clock[1:], strict=False))

    # 20 s of data at 10x: a loop every 2 s. The /clock reader is matched on its own
    # discovery, which under load can come after the first loop: wait for a loop it saw.
    spin_until(
        rclpy_node,
        lambda: bool(resets) and resets[-1] >= 1 and after_reset() >= 50 and clock_went_back(),
        30,
        lambda: (
            f'a reset, 50 fixes after it and /clock going back; resets {resets[-1:]}, '
            f'{len(fixes)} fixes, clock went back: {clock_went_back()}'
        ),
    )
    player.send_signal(signal.SIGINT)
    assert player.wait(timeout=10) == 0
    assert 'loop(s) restarted' in player.output()
    assert 'time went back' in tri.errors() and 'reset #1' in tri.errors()
    assert 'Traceback' not in tri.errors() + player.errors()
    # fixes of every pass: the stamps of the first pass again after the reset
    first = fixes[: len(fixes) - after_reset()]
    again = fixes[len(first) :]
    assert again[:20] == first[:20]
    # /clock follows the stamps of the bag and goes back at a loop
    c = np.array(clock)
    t0, t1 = EPOCH_NS + 50 * 10**9, EPOCH_NS + 70 * 10**9
    assert c.size > 20 and np.all((c >= t0) & (c <= t1))
    assert np.any(np.diff(c) < -10 * 10**9)
    assert np.all(np.diff(c)[np.diff(c) > -10 * 10**9] >= 0)


def _stamp_of(clock_msg) -> int:
    return clock_msg.clock.sec * 1_000_000_000 + clock_msg.clock.nanosec


def test_replay_of_a_missing_or_broken_bag_is_a_clean_error(tmp_path, capsys):
    assert cli_main(['replay', str(tmp_path / 'nope')]) == 2
    (tmp_path / 'x.yaml').write_text('a: 1\n')
    assert cli_main(['replay', str(tmp_path / 'x.yaml'), '--loop']) == 2
    assert capsys.readouterr().err.count('orbit-tracking replay: error:') == 2


@pytest.mark.dds
def test_dds_benchmark_runs_end_to_end_with_tiny_settings():
    from orbit_tracking.tools.bench.dds import bench_dds, dds_table

    rows = bench_dds(rates=[800.0], span=3.0, windows=(2.0, 0.5, 0.5), progress=False)
    (r,) = rows
    assert r.sent > 500 and r.messages == r.sent  # single-point messages
    assert r.tri_received == r.sent and r.est_received == r.sent  # reliable, keep-all
    assert r.windows >= 2 and r.fixes > 0
    text = dds_table(rows, 'seed000_s1', 3.0, (2.0, 0.5, 0.5), 1.0, 'bench')
    assert text.count('\n| 800 |') == 1 and 'Highest offered rate' in text


def test_bench_parser_offers_the_dds_suite_outside_all():
    from orbit_tracking.tools.cli import build_parser

    args = build_parser().parse_args(['bench', '--suite', 'dds', '--rates', '100', '200'])
    assert args.rates == [100.0, 200.0] and args.span == 30.0
    assert (
        build_parser().parse_args(['play', 'x']).func
        is build_parser().parse_args(['replay', 'x']).func
    )


def test_late_station_states_are_waited_for_not_dropped(tmp_path):
    """The station-state topic queued 8 s of data time behind the measurements (a busy
    node reads one message per topic per turn): every epoch still gets its states, and
    the node gives the fixes of a pass in stamp order."""
    from orbit_tracking.core.triangulation.alignment import AlignConfig
    from orbit_tracking.core.triangulation.pipeline import TriangulationPipeline
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    (tmp_path / 'q2.yaml').write_text(SHORT_Q2)
    events = _events(tmp_path / 'q2.yaml')
    states = [e for e in events if e[0].kind == 'station_state']
    others = [e for e in events if e[0].kind != 'station_state']
    # interleave: each measurement goes out with the states of 8 s earlier
    order, i = [], 0
    for ev, msg in others:
        while i < len(states) and states[i][0].time <= ev.time - 8.0:
            order.append(states[i])
            i += 1
        order.append((ev, msg))
    order += states[i:]
    with default_context(lag=0.5):
        node = TriangulationNode()
        got: list = []
        node.fix_pub = types.SimpleNamespace(publish=got.append)
        try:
            for ev, msg in order:
                _feed(node, ev, msg)
            node.last_data -= 1e3  # the data stopped long ago: fix what the lag holds
            node._flush_if_idle()
            assert node.pipeline.counts['no_station_state'] == 0
        finally:
            node.destroy_node()
    res = simulate(load_scenario(tmp_path / 'q2.yaml'))
    offline = TriangulationPipeline(AlignConfig(lag=0.5))
    for sid, st in res.station_states.items():
        for k in range(st.time.size):
            offline.add_pose(sid, st.time[k], st.position[k], st.velocity[k], st.rotation[k], True)
    for sid, m in res.measurements.items():
        offline.add_measurements(sid, m.fields, m.time, m.target_id, m.values, m.sigmas)
    assert len(got) == len(offline.flush()) > 50
    stamps = [_stamp(m) for m in got]
    assert stamps == sorted(stamps)


def test_a_stream_is_quiet_only_after_the_node_waited_for_it():
    """``silent_after`` counts time spent waiting for data, not time spent working."""
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    with default_context(silent_after=0.2):
        node = TriangulationNode()
        try:
            node._in_time('a', EPOCH_NS)
            node._in_time('b', EPOCH_NS + 3_000_000_000)
            node._timebase(EPOCH_NS)
            assert node._delivering() == {'a': 0.0, 'b': 3.0}
            with node._working():  # a long solve: queued messages are not silence
                time.sleep(0.3)
                assert set(node._delivering()) == {'a', 'b'}
            assert set(node._delivering()) == {'a', 'b'}
            node._in_time('b', EPOCH_NS + 3_500_000_000)
            time.sleep(0.25)  # waiting: 'a' and 'b' both went quiet
            assert node._delivering() == {}
            node._in_time('b', EPOCH_NS + 4_000_000_000)
            assert node._delivering() == {'b': 4.0}
        finally:
            node.destroy_node()


def test_one_stream_going_back_alone_resets_nothing_and_loses_only_its_own_data():
    """The attack of issue 13: a station nobody declared sends the current stamp, then a
    stamp 1 s after the epoch. The others go on; only its held message is dropped."""
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    s = 1_000_000_000
    with default_context(silent_after=0.5):
        node = TriangulationNode()
        try:
            for k in range(3):
                for stream in ('a', 'b', 'c'):
                    assert node._in_time(stream, EPOCH_NS + k * s // 10)
            used: list[int] = []
            assert node._in_time('evil', EPOCH_NS)  # a new stream: taken on its own clock
            assert not node._in_time('evil', s, lambda: used.append(1))  # held, not used
            assert node.counts['time_back_held'] == 1  # seen at once
            for k in range(3, 6):
                for stream in ('a', 'b', 'c'):
                    assert node._in_time(stream, EPOCH_NS + k * s // 10)
            assert node.counts['time_resets'] == 0 and used == []
            time.sleep(0.6)  # 'evil' falls quiet: what it held is dropped
            node._in_time('a', EPOCH_NS + s)
            node._check_reset()
            assert node.counts['time_back_unconfirmed'] == 1 and node._back == {}
            assert node.counts['time_resets'] == 0 and node.counts['stale_after_reset'] == 0
        finally:
            node.destroy_node()


@pytest.mark.parametrize('first_lost', [False, True], ids=['both', 'only_1970'])
def test_a_lone_voice_in_a_pause_resets_nothing(first_lost):
    """The same attack while every real stream is quiet (between passes, a replay
    stopped): the rogue is still one voice among the streams active before the pause.
    Before, it was the majority of an empty room: the node reset to 1970 and then
    dropped every real message as stale."""
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    s = 1_000_000_000
    with default_context(silent_after=0.3):
        node = TriangulationNode()
        try:
            for k in range(3):
                for stream in ('a', 'b', 'c'):
                    assert node._in_time(stream, EPOCH_NS + k * s // 10)
            time.sleep(0.4)  # the pause: nobody is active
            assert node._active() == []
            if not first_lost:
                assert node._in_time('evil', EPOCH_NS + s // 5)
            assert not node._in_time('evil', s, lambda: None)
            assert node.counts['time_resets'] == 0
            time.sleep(0.4)
            node._check_reset()
            assert node.counts['time_back_unconfirmed'] == 1
            for stream in ('a', 'b', 'c'):  # the pass resumes: taken, nothing stale
                assert node._in_time(stream, EPOCH_NS + 3 * s)
            assert node.counts['time_resets'] == 0 and node.counts['stale_after_reset'] == 0
        finally:
            node.destroy_node()


def test_a_loop_after_a_pause_still_resets_once():
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    s = 1_000_000_000
    with default_context(silent_after=0.3):
        node = TriangulationNode()
        try:
            for stream in ('a', 'b', 'c'):
                node._in_time(stream, EPOCH_NS + 20 * s)
            time.sleep(0.4)
            assert not node._in_time('a', EPOCH_NS, lambda: None)
            assert node.counts['time_resets'] == 0  # one of three
            assert not node._in_time('b', EPOCH_NS, lambda: None)
            assert node.counts['time_resets'] == 1
            assert node._in_time('c', EPOCH_NS)
        finally:
            node.destroy_node()


def test_a_new_stream_starting_far_behind_the_others_is_held_as_gone_back():
    """A station first heard with a stamp 1 s after the epoch (its first message lost, or
    its clock at 1970) is not taken on a time line of its own; when most streams follow
    it (a replay started anew) the reset uses what it held."""
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    s = 1_000_000_000
    with default_context(silent_after=0.5):
        node = TriangulationNode()
        try:
            for stream in ('a', 'b', 'c'):
                assert node._in_time(stream, EPOCH_NS + 20 * s)
            used: list[str] = []
            assert not node._in_time('evil', s, lambda: used.append('evil'))
            assert node._in_time('late', EPOCH_NS - 500 * s)  # 520 s behind: still taken
            time.sleep(0.6)
            for stream in ('a', 'b', 'c', 'late'):
                node._in_time(stream, EPOCH_NS + 21 * s)
            node._check_reset()
            assert node.counts['time_back_unconfirmed'] == 1 and used == []
            assert node.counts['time_resets'] == 0
            # the same start, then most streams go back to it: one reset, the held data used
            assert not node._in_time('new', EPOCH_NS - 10_000 * s, lambda: used.append('new'))
            for stream in ('a', 'b', 'c'):
                node._in_time(stream, EPOCH_NS - 10_000 * s, lambda st=stream: used.append(st))
            assert node.counts['time_resets'] == 1
            assert used[0] == 'new' and sorted(used) == ['a', 'b', 'new']
        finally:
            node.destroy_node()


def test_most_streams_going_back_reset_once_and_the_held_messages_are_used():
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    s = 1_000_000_000
    with default_context():
        node = TriangulationNode()
        try:
            for stream in ('a', 'b', 'c'):
                node._in_time(stream, EPOCH_NS + 20 * s)
            used: list[str] = []
            assert not node._in_time('a', EPOCH_NS, lambda: used.append('a'))
            assert node.counts['time_resets'] == 0  # one of three: held
            assert not node._in_time('b', EPOCH_NS, lambda: used.append('b'))
            assert node.counts['time_resets'] == 1  # two of three: the new time line
            assert used == ['a', 'b']
            assert not node._in_time('c', EPOCH_NS + 19 * s)  # the old line: stale
            assert node.counts['stale_after_reset'] == 1
            assert node._in_time('c', EPOCH_NS)
        finally:
            node.destroy_node()


def test_a_stamp_years_ahead_on_one_stream_is_held_and_dropped_not_taken_as_newest():
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    s = 1_000_000_000
    with default_context():
        node = TriangulationNode()
        try:
            for stream in ('a', 'b', 'c'):
                node._in_time(stream, EPOCH_NS + 20 * s)
            used: list[int] = []
            assert not node._in_time('a', EPOCH_NS + 10**9 * s, lambda: used.append(1))
            assert node._in_time('a', EPOCH_NS + 21 * s)  # back with the others
            assert used == [] and node.counts['time_ahead_unconfirmed'] == 1
            assert node._streams['a'][1] == EPOCH_NS + 21 * s
            # most streams ahead together (a new pass while the old is still heard): taken
            got: list[str] = []
            for stream in ('a', 'b'):
                node._in_time(stream, EPOCH_NS + 5000 * s, lambda st=stream: got.append(st))
            assert got == ['a', 'b'] and node.counts['time_resets'] == 0
            assert node._in_time('c', EPOCH_NS + 5000 * s)
        finally:
            node.destroy_node()


def test_a_lone_stream_going_back_is_the_majority():
    from orbit_tracking.ros.triangulation_node import TriangulationNode

    with default_context():
        node = TriangulationNode()
        try:
            node._in_time('a', EPOCH_NS + 20_000_000_000)
            used: list[int] = []
            assert not node._in_time('a', EPOCH_NS, lambda: used.append(1))
            assert node.counts['time_resets'] == 1 and used == [1]
        finally:
            node.destroy_node()


def test_estimator_windows_wait_for_a_late_station(tmp_path):
    """A station's topic 8 s of data time behind the others holds the estimator's horizon
    (windows are due on it), instead of its data being cut off by the newest stamp."""
    from orbit_tracking.ros.estimator_node import EstimatorNode

    (tmp_path / 'q2.yaml').write_text(SHORT_Q2)
    events = _events(tmp_path / 'q2.yaml')
    late = [e for e in events if e[0].kind == 'measurement' and e[0].key == 'sat09']
    others = [e for e in events if not (e[0].kind == 'measurement' and e[0].key == 'sat09')]
    with default_context(window_length=10.0, window_overlap=2.0):
        node = EstimatorNode()
        node._solve_due = lambda final, block=False: []  # the horizon only; no solve
        try:
            i = 0
            for ev, msg in others:
                while i < len(late) and late[i][0].time <= ev.time - 8.0:
                    _feed(node, *late[i])
                    i += 1
                _feed(node, ev, msg)
            newest = node.buffer.latest_time()  # internal time: from the first stamp
            lag = late[-1][0].time - late[i - 1][0].time
            assert lag > 7.0
            assert node._horizon() == pytest.approx(newest - lag, abs=0.3)
        finally:
            node.destroy_node()


def test_estimator_without_telemetry_waits_for_the_first_fix(tmp_path):
    """No telemetry: the rough trajectory is the fixes. While a triangulation node is up
    but has sent none yet (started late, starved of CPU), windows are not due."""
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from orbit_tracking.ros.conversions import TimeBase, fix_to_msg
    from orbit_tracking.ros.estimator_node import EstimatorNode

    (tmp_path / 'q2.yaml').write_text(SHORT_Q2)
    events = _events(tmp_path / 'q2.yaml')
    with default_context(window_length=10.0, window_overlap=2.0):
        node = EstimatorNode()
        node._solve_due = lambda final, block=False: []  # the horizon only; no solve
        other = rclpy.create_node('fake_triangulation')
        try:
            for ev, msg in events:
                _feed(node, ev, msg)
            assert node._horizon() > 15.0  # nobody publishes fixes: nothing to wait for
            other.create_publisher(PoseWithCovarianceStamped, 'triangulation/fixes', 10)
            deadline = time.monotonic() + 10.0
            while node.count_publishers('triangulation/fixes') < 1:
                assert time.monotonic() < deadline, 'the publisher never appeared'
                time.sleep(0.05)
            assert node._horizon() == -math.inf
            tb = TimeBase.from_seconds(load_scenario(tmp_path / 'q2.yaml').epoch)
            node._on_fix(fix_to_msg('eci', 52.0, np.ones(3), np.eye(3), tb))
            # from then on the fixes are a stream like the others: the late one holds
            assert node._horizon() == pytest.approx(52.0 - 50.0)
        finally:
            other.destroy_node()
            node.destroy_node()
