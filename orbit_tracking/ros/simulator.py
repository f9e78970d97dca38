"""The simulator node shared by ``station_sim`` (one station) and ``scenario_sim`` (all).

It simulates the scenario once at start-up (the core's arrays), then streams the events
in time order at ``rate_factor`` times real time: measurements on
``stations/<id>/measurements``, station states on ``stations/<id>/state``, and optionally
telemetry, truth and ``/clock``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.task import Future
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2

from orbit_tracking.core.sim.scenario import Scenario, load_scenario
from orbit_tracking.core.sim.simulator import (
    SimulationResult,
    World,
    simulate_station,
    simulate_telemetry,
    simulate_truth,
)
from orbit_tracking.core.sim.stream import Event, EventStream
from orbit_tracking.ros import qos
from orbit_tracking.ros.conversions import TimeBase, diagnostic_array, diagnostic_status
from orbit_tracking.ros.messages import event_message
from orbit_tracking.ros.parameters import declare
from orbit_tracking.ros.runner import StreamGate

__all__ = ['SimulatorNode']


class SimulatorNode(Node):
    """Streams a simulated scenario over DDS.

    Parameters
    ----------
    node_name : str
    single_station : bool
        ``station_sim`` mode: a required ``station_id`` parameter, no telemetry/truth by
        default.
    """

    def __init__(self, node_name: str, single_station: bool) -> None:
        super().__init__(node_name)
        self.done = Future()
        name = declare(
            self,
            'scenario',
            'seed000_s1',
            'Scenario name (config/scenarios) or YAML path.',
            read_only=True,
        )
        if single_station:
            station_ids: Sequence[str] = [
                declare(
                    self,
                    'station_id',
                    'cw01',
                    "Id of the scenario station to simulate (one of the scenario file's).",
                    read_only=True,
                )
            ]
        else:
            station_ids = declare(
                self,
                'stations',
                [''],
                'Station ids to simulate; empty or [""] means every station of the scenario.',
                read_only=True,
            )
        self.rate_factor = declare(
            self,
            'rate_factor',
            1.0,
            'Scenario seconds streamed per wall-clock second.',
            min_value=0.01,
            max_value=10000.0,
        )
        self.batch_period = declare(
            self,
            'batch_period',
            0.0,
            'Scenario seconds of epochs packed into one measurement message (time_offset per '
            'point); 0 sends one message per epoch. Batch when streaming far above real time.',
            read_only=True,
            min_value=0.0,
            max_value=60.0,
        )
        publish_truth = declare(
            self,
            'publish_truth',
            not single_station,
            'Publish truth/state (simulation only).',
            read_only=True,
        )
        publish_telemetry = declare(
            self,
            'publish_telemetry',
            not single_station,
            'Publish telemetry/state if the scenario has telemetry.',
            read_only=True,
        )
        self.publish_clock = declare(
            self,
            'publish_clock',
            False,
            'Publish /clock with the scenario stamps.',
            read_only=True,
        )
        epoch = declare(
            self,
            'epoch',
            0.0,
            "Stamp [s] of scenario time 0; 0 uses the scenario file's epoch.",
            read_only=True,
            min_value=0.0,
        )
        start_delay = declare(
            self,
            'start_delay',
            0.5,
            'Wall seconds to wait before streaming.',
            min_value=0.0,
            max_value=3600.0,
        )
        wait_for_subscribers = declare(
            self,
            'wait_for_subscribers',
            0,
            'Before streaming, wait until every measurement topic (and moving-station state '
            'topic) has at least this many subscribers.',
            min_value=0,
            max_value=100,
        )
        wait_timeout = declare(
            self,
            'wait_timeout',
            30.0,
            'Longest wait for subscribers [s] before streaming anyway.',
            min_value=0.0,
            max_value=3600.0,
        )
        self.shutdown_when_done = declare(
            self,
            'shutdown_when_done',
            False,
            'Exit once every event is streamed (latched states are kept until then).',
        )

        self.scenario: Scenario = load_scenario(name)
        sc = self.scenario
        if single_station and not station_ids[0]:
            raise ValueError(
                f'station_id is empty; stations of {sc.name}: {[s.id for s in sc.stations]}'
            )
        ids = [s for s in station_ids if s] or [s.id for s in sc.stations]
        known = {s.id for s in sc.stations}
        unknown = [s for s in ids if s not in known]
        if unknown:
            raise ValueError(
                f'scenario {sc.name} has no station(s) {unknown}; stations: {sorted(known)}'
            )
        self.timebase = TimeBase.from_seconds(epoch if epoch > 0.0 else sc.epoch)
        t_sim = time.monotonic()
        world = World(sc)
        meas, states = {}, {}
        for sid in ids:
            meas[sid], states[sid] = simulate_station(world, sc.station(sid))
        tel = (
            simulate_telemetry(world, sc.telemetry) if (publish_telemetry and sc.telemetry) else {}
        )
        truth = simulate_truth(world) if publish_truth else {}
        self.result = SimulationResult(sc, meas, states, truth, tel)
        self.stream = EventStream(self.result, ids, self.batch_period)
        self.get_logger().info(
            f'scenario {sc.name}: {len(ids)} station(s), '
            f'{sum(len(m) for m in meas.values())} points, '
            f'{len(self.stream)} messages over {sc.t_end - sc.t_start:.1f} s '
            f'at {self.rate_factor:g}x real time (simulated in {time.monotonic() - t_sim:.2f} s)'
        )

        self.meas_pubs: dict[str, Publisher] = {
            sid: self.create_publisher(
                PointCloud2, f'stations/{sid}/measurements', qos.MEASUREMENTS_PUB
            )
            for sid in ids
        }
        self.state_pubs: dict[str, Publisher] = {
            sid: self.create_publisher(
                Odometry,
                f'stations/{sid}/state',
                qos.STATION_STATE_MOVING if states[sid].moving else qos.STATION_STATE_FIXED,
            )
            for sid in ids
        }
        self.truth_pub = (
            self.create_publisher(Odometry, 'truth/state', qos.STATE_STREAM) if truth else None
        )
        self.tel_pub = (
            self.create_publisher(Odometry, 'telemetry/state', qos.STATE_STREAM) if tel else None
        )
        self.clock_pub = (
            self.create_publisher(Clock, '/clock', qos.CLOCK) if self.publish_clock else None
        )
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', qos.DIAGNOSTICS)
        self.sent = dict.fromkeys(ids, 0)
        self._gate = StreamGate(start_delay, wait_for_subscribers, wait_timeout)
        self._start_wall: float | None = None
        self._last_diag = 0.0
        self.timer = self.create_timer(0.005, self._tick)

    # -- streaming -----------------------------------------------------------------
    def _ready(self, now: float) -> bool:
        # readers of the measurements and of moving stations' (volatile) states
        pubs = list(self.meas_pubs.values()) + [
            self.state_pubs[sid]
            for sid in self.meas_pubs
            if self.result.station_states[sid].moving
        ]
        return self._gate.ready(now, pubs)

    def _tick(self) -> None:
        now = time.monotonic()
        if self._start_wall is None:
            if not self._ready(now):
                return
            self._start_wall = now
            self.get_logger().info('streaming started')
        sc = self.scenario
        t_now = sc.t_start + (now - self._start_wall) * self.rate_factor
        for ev in self.stream.until(min(t_now, sc.t_end)):
            self._publish(ev)
        if self.clock_pub is not None:
            # once every event is out the pass is over: the clock shows its end
            t_clock = sc.t_end if self.stream.done else min(t_now, sc.t_end)
            self.clock_pub.publish(Clock(clock=self.timebase.to_stamp(t_clock)))
        if now - self._last_diag >= 1.0 or self.stream.done:
            self._last_diag = now
            self._publish_diagnostics(min(t_now, sc.t_end))
        if self.stream.done and not self.done.done():
            self.get_logger().info(
                'all events streamed: '
                + ', '.join(f'{k}: {v} messages' for k, v in self.sent.items())
            )
            self.done.set_result(True)
            if not self.shutdown_when_done:
                self.timer.cancel()

    def _publish(self, ev: Event) -> None:
        msg = event_message(self.result, ev, self.timebase)
        if ev.kind == 'measurement':
            self.meas_pubs[ev.key].publish(msg)
            self.sent[ev.key] += 1
        elif ev.kind == 'station_state':
            self.state_pubs[ev.key].publish(msg)
        elif ev.kind == 'truth' and self.truth_pub is not None:
            self.truth_pub.publish(msg)
        elif ev.kind == 'telemetry' and self.tel_pub is not None:
            self.tel_pub.publish(msg)

    def _publish_diagnostics(self, t: float) -> None:
        sc = self.scenario
        level = DiagnosticStatus.OK
        status = diagnostic_status(
            f'{self.get_name()}: simulator',
            level,
            'done' if self.stream.done else 'streaming',
            {
                'scenario': sc.name,
                'scenario_time': t,
                'progress': (t - sc.t_start) / (sc.t_end - sc.t_start),
                **{f'{k}_messages': v for k, v in self.sent.items()},
            },
        )
        self.diag_pub.publish(diagnostic_array(self.get_clock().now().to_msg(), [status]))
