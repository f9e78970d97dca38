"""Simulate a scenario straight into a rosbag2: the same messages the live simulators
publish, with the same QoS recorded in the bag's metadata, no DDS involved."""

from __future__ import annotations

from pathlib import Path

import yaml
from tqdm import tqdm

from orbit_tracking.core.sim.scenario import Scenario, truth_biases
from orbit_tracking.core.sim.simulator import simulate
from orbit_tracking.core.sim.stream import EventStream
from orbit_tracking.ros import qos
from orbit_tracking.ros.bag import BagWriter
from orbit_tracking.ros.conversions import TimeBase
from orbit_tracking.ros.messages import event_cdr, event_topic

__all__ = ['scenario_custom_data', 'simulate_to_bag']


def scenario_custom_data(scenario: Scenario, truth: bool = True) -> dict[str, str]:
    """The ``custom_data`` that labels a bag of ``scenario``: its name, epoch, world frame,
    gaps and (with ``truth``) the simulated station biases (``orbit_tracking.biases``, YAML:
    station -> bias name -> value), so evaluation tools find the truth without any other
    file. Written by :func:`simulate_to_bag` and by ``orbit-tracking record --scenario``."""
    data = {
        'orbit_tracking.scenario': scenario.name,
        'orbit_tracking.epoch': repr(scenario.epoch),
        'orbit_tracking.world_frame': scenario.world_frame,
        'orbit_tracking.gaps': yaml.safe_dump([list(g) for g in scenario.gaps]),
    }
    if truth:  # the simulated systematic errors, so that estimated biases can be scored
        biases: dict[str, dict[str, float]] = {}
        for (sid, name), value in truth_biases(scenario).items():
            biases.setdefault(sid, {})[name] = value
        data['orbit_tracking.biases'] = yaml.safe_dump(biases)
    return data


def simulate_to_bag(
    scenario: Scenario,
    out: str | Path,
    storage: str = 'mcap',
    batch_period: float = 0.0,
    truth: bool = True,
    progress: bool = True,
) -> int:
    """Write a scenario's measurements, station states, telemetry and (optionally) truth
    to a new bag folder ``out``. Returns the number of messages written.

    The bag's ``custom_data`` is :func:`scenario_custom_data`.
    """
    result = simulate(scenario)
    stream = EventStream(result, batch_period=batch_period, truth=truth)
    timebase = TimeBase.from_seconds(scenario.epoch)
    moving = {sid for sid, s in result.station_states.items() if s.moving}
    with BagWriter(out, storage) as bag:
        for key, value in scenario_custom_data(scenario, truth).items():
            bag.set_custom_data(key, value)
        for ev in tqdm(
            stream, total=len(stream), unit='msg', disable=not progress, desc=scenario.name
        ):
            if ev.kind == 'measurement':
                profile = qos.MEASUREMENTS_PUB
            elif ev.kind == 'station_state':
                profile = qos.STATION_STATE_MOVING if ev.key in moving else qos.STATION_STATE_FIXED
            else:
                profile = qos.STATE_STREAM
            msgtype, raw = event_cdr(result, ev, timebase)
            bag.write_raw(event_topic(ev), msgtype, raw, timebase.to_ns(ev.time), profile)
        return bag.count
