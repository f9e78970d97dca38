"""Messages of simulation events, shared by the live simulators and the bag writer."""

from __future__ import annotations

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.sim.simulator import SimulationResult
from orbit_tracking.core.sim.stream import Event
from orbit_tracking.ros.conversions import (
    TimeBase,
    measurements_to_cdr,
    measurements_to_cloud,
    station_state_to_odometry,
    target_state_to_odometry,
)

__all__ = ['event_cdr', 'event_message', 'event_topic']


def event_topic(ev: Event) -> str:
    """Relative topic name of an event's message."""
    if ev.kind == 'measurement':
        return f'stations/{ev.key}/measurements'
    if ev.kind == 'station_state':
        return f'stations/{ev.key}/state'
    return 'truth/state' if ev.kind == 'truth' else 'telemetry/state'


def event_message(
    result: SimulationResult, ev: Event, timebase: TimeBase
) -> PointCloud2 | Odometry:
    """The message an event stands for."""
    world = result.scenario.world_frame
    a, b = ev.start, ev.stop
    if ev.kind == 'measurement':
        m = result.measurements[ev.key]
        return measurements_to_cloud(
            ev.key, m.fields, m.time[a:b], m.target_id[a:b], m.values[a:b], m.sigmas[a:b], timebase
        )
    if ev.kind == 'station_state':
        s = result.station_states[ev.key]
        return station_state_to_odometry(
            ev.key,
            world,
            float(s.time[a]),
            s.position[a],
            s.velocity[a],
            s.rotation[a],
            s.angular_velocity[a],
            timebase,
        )
    src = result.truth if ev.kind == 'truth' else result.telemetry
    ts = src[int(ev.key)]
    return target_state_to_odometry(
        ts.target_id,
        world,
        float(ts.time[a]),
        ts.position[a],
        ts.velocity[a],
        np.diag(ts.position_sigma[a] ** 2),
        np.diag(ts.velocity_sigma[a] ** 2),
        timebase,
    )


def event_cdr(result: SimulationResult, ev: Event, timebase: TimeBase) -> tuple[str, bytes]:
    """The message type and serialised bytes of an event's message, for a bag writer
    (measurements packed straight into bytes, :func:`measurements_to_cdr`)."""
    if ev.kind == 'measurement':
        m = result.measurements[ev.key]
        a, b = ev.start, ev.stop
        raw = measurements_to_cdr(
            ev.key, m.fields, m.time[a:b], m.target_id[a:b], m.values[a:b], m.sigmas[a:b], timebase
        )
        return 'sensor_msgs/msg/PointCloud2', raw
    return 'nav_msgs/msg/Odometry', bytes(serialize_message(event_message(result, ev, timebase)))
