"""Unit tests of orbit_tracking.core.sim.stream: batching and time ordering of the events that
the live simulators and the bag writer publish."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import SimulationResult, simulate
from orbit_tracking.core.sim.stream import EventStream, batch_rows


@cache
def _result(name: str) -> SimulationResult:
    return simulate(load_scenario(name))


def _assert_partition(rows: list[tuple[int, int]], n: int) -> None:
    assert rows[0][0] == 0 and rows[-1][1] == n
    for (a, b), (c, _) in zip(rows[:-1], rows[1:], strict=True):
        assert a < b == c


def test_batch_rows_without_period_groups_the_points_of_each_epoch() -> None:
    time = np.array([0.0, 0.0, 0.1, 0.2, 0.2, 0.2, 0.3])
    rows = batch_rows(time, 0.0)
    assert rows == [(0, 2), (2, 3), (3, 6), (6, 7)]
    assert batch_rows(np.empty(0), 0.0) == []


def test_batch_rows_with_period_keeps_each_batch_shorter_than_the_period() -> None:
    rng = np.random.default_rng(4)
    time = np.sort(rng.uniform(0.0, 10.0, 500))
    time[100:103] = time[100]  # several points at one epoch
    rows = batch_rows(time, 0.5)
    _assert_partition(rows, len(time))
    for a, b in rows:
        assert time[b - 1] - time[a] < 0.5
    # batches are maximal: the next point would make the batch reach the period
    for a, b in rows[:-1]:
        assert time[b] - time[a] >= 0.5 - 1e-9


def test_event_stream_is_time_ordered_and_carries_every_row_once() -> None:
    result = _result('seed003_q2')
    stream = EventStream(result, batch_period=1.0)
    times = np.array([e.time for e in stream])
    assert np.all(np.diff(times) >= 0.0)
    for sid, table in result.measurements.items():
        rows = [(e.start, e.stop) for e in stream if e.kind == 'measurement' and e.key == sid]
        _assert_partition(rows, len(table))
        for e in stream:
            if e.kind == 'measurement' and e.key == sid:
                # available once its last point has been measured
                assert e.time == table.time[e.stop - 1]
        states = [e for e in stream if e.kind == 'station_state' and e.key == sid]
        assert len(states) == len(result.station_states[sid])  # moving: one per epoch
    truth = [e for e in stream if e.kind == 'truth']
    assert len(truth) == len(result.truth[0])


def test_station_state_goes_out_before_measurements_of_the_same_epoch() -> None:
    stream = EventStream(_result('seed003_q2'))
    seen_state: set[tuple[str, float]] = set()
    for e in stream:
        if e.kind == 'station_state':
            seen_state.add((e.key, e.time))
        elif e.kind == 'measurement':
            assert (e.key, e.time) in seen_state


def test_fixed_stations_publish_their_state_once_at_the_start() -> None:
    result = _result('seed000_s1')
    stream = EventStream(result, stations=['cw03', 'opt02'], telemetry=False, truth=False)
    states = [e for e in stream if e.kind == 'station_state']
    assert [(e.key, e.time) for e in states] == [('cw03', 0.0), ('opt02', 0.0)]
    assert {e.kind for e in stream} == {'station_state', 'measurement'}
    n_meas = sum(e.stop - e.start for e in stream if e.kind == 'measurement')
    assert n_meas == len(result.measurements['cw03']) + len(result.measurements['opt02'])


def test_until_returns_each_event_once_in_order() -> None:
    stream = EventStream(_result('seed003_q2'), batch_period=0.5)
    got = []
    for t in np.arange(50.0, 171.0, 7.3):
        chunk = stream.until(float(t))
        assert all(e.time <= t for e in chunk)
        got += chunk
        if not stream.done:
            assert stream.next_time is not None and stream.next_time > t
    got += stream.until(np.inf)
    assert stream.done and stream.next_time is None
    assert got == stream.events
    stream.reset()
    assert stream.until(np.inf) == stream.events


def test_unknown_station_is_rejected() -> None:
    with pytest.raises(KeyError, match='sat42'):
        EventStream(_result('seed003_q2'), stations=['sat42'])
