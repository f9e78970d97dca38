"""The estimator node's buffer (core/buffer.py): out-of-order and repeated rows, rows
waiting for their station's state, pruning."""

from __future__ import annotations

import math

import numpy as np
import pytest

from orbit_tracking.core.data.buffer import ObservationBuffer
from orbit_tracking.core.data.observations import Observations
from orbit_tracking.core.errors import MeasurementError
from orbit_tracking.core.sim.scenario import load_scenario
from orbit_tracking.core.sim.simulator import simulate


@pytest.fixture(scope='module')
def pass_q2():
    """Two observing satellites (moving stations) of seed 003."""
    return simulate(load_scenario('seed003_q2'))


def _feed(buf: ObservationBuffer, result) -> None:
    """Every station state and measurement row of a simulation, in order."""
    for sid, st in result.station_states.items():
        for i in range(len(st)):
            buf.add_pose(
                sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], st.moving
            )
    for sid, m in result.measurements.items():
        buf.add_measurements(sid, m.fields, m.time, m.target_id, m.values, m.sigmas)


def _shuffled_feed(buf: ObservationBuffer, result, rng: np.random.Generator) -> int:
    """Every measurement row in small chunks of random order, some twice; returns the
    number of repeated rows."""
    repeated = 0
    for sid, m in result.measurements.items():
        idx = rng.permutation(len(m))
        for chunk in np.array_split(idx, max(1, len(m) // 7)):
            buf.add_measurements(
                sid, m.fields, m.time[chunk], m.target_id[chunk], m.values[chunk], m.sigmas[chunk]
            )
        again = idx[: len(m) // 10]
        buf.add_measurements(
            sid, m.fields, m.time[again], m.target_id[again], m.values[again], m.sigmas[again]
        )
        repeated += again.size
    return repeated


def test_buffer_sorts_out_of_order_rows_and_drops_exact_repeats(pass_q2):
    res = pass_q2
    buf = ObservationBuffer()
    for sid, st in res.station_states.items():
        for i in range(len(st)):
            buf.add_pose(
                sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], st.moving
            )
    repeated = _shuffled_feed(buf, res, np.random.default_rng(0))
    got = buf.observations()
    want = Observations.from_simulation(res)
    assert buf.counts['duplicate'] == repeated
    assert [s.table.station_id for s in got.stations] == [
        s.table.station_id for s in want.stations
    ]
    for g, w in zip(got.stations, want.stations, strict=True):
        assert np.array_equal(g.table.time, w.table.time)
        assert np.array_equal(g.table.values, w.table.values, equal_nan=True)
        assert np.array_equal(g.table.sigmas, w.table.sigmas)
        assert g.table.fields == w.table.fields and g.table.kind == 'satellite'
        # interpolated satellite positions agree with the simulator's to well below a metre
        assert np.allclose(g.pose.position, w.pose.position, atol=0.05)
    assert buf.latest_time() == max(float(m.time.max()) for m in res.measurements.values())


def test_rows_without_station_state_are_withheld_kept_and_counted_when_pruned():
    res = simulate(load_scenario('seed000_s1'))
    buf = ObservationBuffer()
    _feed(buf, res)
    m = res.measurements['cw01']
    buf.add_measurements('ghost', m.fields, m.time, m.target_id, m.values, m.sigmas)
    obs = buf.observations(0.0, 10.0)
    n_ghost = int(np.count_nonzero(m.time <= 10.0))
    assert buf.withheld == {'ghost': n_ghost}
    assert 'ghost' not in {s.table.station_id for s in obs.stations}
    assert buf.stations_without_pose() == ['ghost']
    st = res.station_states['cw01']
    buf.add_pose('ghost', 0.0, st.position[0], st.velocity[0], st.rotation[0], False)
    obs = buf.observations(0.0, 10.0)
    assert not buf.withheld
    assert len(next(s for s in obs.stations if s.table.station_id == 'ghost').table) == n_ghost
    # rows pruned before any state covered them are counted, not silently lost
    buf.add_measurements(
        'late_station', m.fields, m.time[:5], m.target_id[:5], m.values[:5], m.sigmas[:5]
    )
    buf.prune(20.0)
    assert buf.counts['no_station_state'] == 5
    assert buf.first_time() >= 20.0
    assert (
        buf.add_measurements(
            'cw01', m.fields, m.time[:3], m.target_id[:3], m.values[:3], m.sigmas[:3]
        )
        == 0
    )
    assert buf.counts['too_late'] == 3


def test_rows_of_a_moving_station_beyond_its_last_state_wait_for_the_next_state(pass_q2):
    res = pass_q2
    sid = next(iter(res.measurements))
    m, st = res.measurements[sid], res.station_states[sid]
    buf = ObservationBuffer()
    buf.add_measurements(sid, m.fields, m.time, m.target_id, m.values, m.sigmas)
    half = len(st) // 2
    for i in range(half):
        buf.add_pose(sid, st.time[i], st.position[i], st.velocity[i], st.rotation[i], True)
    obs = buf.observations()
    held = int(np.count_nonzero(m.time > st.time[half - 1] + 1e-9))
    assert buf.withheld[sid] == held and held > 0
    assert len(obs.stations[0].table) == len(m) - held


def test_stations_with_changing_fields_get_the_union_with_nan_where_not_measured():
    buf = ObservationBuffer()
    buf.add_pose('pr01', 0.0, np.zeros(3), np.zeros(3), np.eye(3), False)
    buf.add_measurements(
        'pr01',
        ('range', 'azimuth', 'elevation'),
        [1.0],
        [0],
        [[1e4, 0.1, 0.2]],
        [[1.0, 1e-3, 1e-3]],
    )
    buf.add_measurements(
        'pr01',
        ('range', 'range_rate', 'azimuth', 'elevation'),
        [0.5],
        [0],
        [[9e3, 50.0, 0.1, 0.2]],
        [[1.0, 0.1, 1e-3, 1e-3]],
    )
    tab = buf.observations().stations[0].table
    assert tab.fields == ('range', 'range_rate', 'azimuth', 'elevation')
    assert tab.kind == 'pulse_radar'
    assert np.array_equal(tab.time, [0.5, 1.0])
    assert math.isnan(tab.values[1, 1]) and tab.values[0, 1] == 50.0


def test_buffer_rejects_malformed_input_with_a_sentence():
    buf = ObservationBuffer()
    with pytest.raises(MeasurementError, match='unknown or repeated fields'):
        buf.add_measurements('s', ('range', 'speed'), [0.0], [0], [[1.0, 2.0]], [[1.0, 1.0]])
    with pytest.raises(MeasurementError, match=r'must be \(2, 1\)'):
        buf.add_measurements('s', ('range',), [0.0, 1.0], [0, 0], [[1.0]], [[1.0]])
    with pytest.raises(ValueError, match='finite positive sigmas'):
        buf.add_telemetry(0, 0.0, np.zeros(3), np.zeros(3), -np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match='not positive definite'):
        buf.add_fix(0, 0.0, np.zeros(3), np.zeros((3, 3)))


def test_telemetry_and_fixes_come_back_sorted_without_repeated_epochs():
    buf = ObservationBuffer()
    for t in (2.0, 0.0, 1.0, 1.0):
        buf.add_telemetry(3, t, [t, 0, 0], [1, 0, 0], [1, 1, 1], [0.1, 0.1, 0.1])
        buf.add_fix(3, t, [t, 0, 0], np.eye(3))
    obs = buf.observations(0.5, 5.0)
    assert np.array_equal(obs.telemetry[3].time, [1.0, 2.0])
    assert np.array_equal(obs.fixes[3].position[:, 0], [1.0, 2.0])
    assert buf.counts['duplicate_telemetry'] == 1 and buf.counts['duplicate_fix'] == 1
