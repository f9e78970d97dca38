"""Reading a recorded bag for the offline tools: what the bag says about itself
(:class:`BagContext`), its messages decoded and validated in log-time order
(:func:`bag_inputs`, rejections counted by reason), the truth it carries, and the
observations an estimate needs (:func:`read_for_estimation`).

A bag that cannot serve as input (not a bag, unreadable, no input topic, or stations with
measurements and not one with a state) raises :class:`~orbit_tracking.ros.bag.BagError`
with one line saying so."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm import tqdm

from orbit_tracking.core.data.buffer import ObservationBuffer
from orbit_tracking.core.data.tables import TargetStates
from orbit_tracking.core.errors import ConfigError, MeasurementError
from orbit_tracking.core.sim.scenario import load_scenario, truth_biases
from orbit_tracking.core.triangulation.pipeline import TimedFix, TriangulationPipeline
from orbit_tracking.ros.bag import BagError, bag_custom_data, bag_topics, read_bag
from orbit_tracking.ros.conversions import (
    MeasurementBatch,
    TimeBase,
    cloud_to_measurements,
    clouds_to_measurements,
    msg_to_fix,
    odometry_to_station_state,
    odometry_to_target_state,
    read_message,
    stamp_ns,
)

__all__ = [
    'BagContext',
    'BagInput',
    'INPUT_TYPES',
    'bag_inputs',
    'input_topics',
    'bag_message_counts',
    'feed_pipeline',
    'read_for_estimation',
    'truth_states',
]


@dataclass
class BagContext:
    """What a bag says about itself: time base, world frame, gaps, and the truth if any
    (target states; the simulated station biases per (station, bias name), None when the
    bag does not say)."""

    timebase: TimeBase | None = None
    world_frame: str = ''
    scenario: str = ''
    gaps: list[tuple[float, float]] = field(default_factory=list)
    truth: dict[int, TargetStates] = field(default_factory=dict)
    truth_biases: dict[tuple[str, str], float] | None = None
    truth_biases_source: str = ''
    stations_without_state: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_custom_data(cls, path: str | Path) -> BagContext:
        """The context of a bag's ``custom_data``; a label that cannot be parsed is a
        :class:`BagError`."""
        data = bag_custom_data(path)
        ctx = cls()
        key = ''
        try:
            key = 'orbit_tracking.epoch'
            if key in data:
                ctx.timebase = TimeBase.from_seconds(float(data[key]))
            ctx.world_frame = data.get('orbit_tracking.world_frame', '')
            ctx.scenario = data.get('orbit_tracking.scenario', '')
            key = 'orbit_tracking.gaps'
            gaps = yaml.safe_load(data.get(key, '[]')) or []
            ctx.gaps = [(float(a), float(b)) for a, b in gaps]
            key = 'orbit_tracking.biases'
            if key in data:
                biases = yaml.safe_load(data[key]) or {}
                ctx.truth_biases = {
                    (str(sid), str(name)): float(v)
                    for sid, values in biases.items()
                    for name, v in values.items()
                }
                ctx.truth_biases_source = 'bag metadata (orbit_tracking.biases)'
        except (ValueError, TypeError, AttributeError, yaml.YAMLError) as exc:
            text = ' '.join(str(exc).split())
            raise BagError(f'{path}: metadata custom_data {key} cannot be read: {text}') from exc
        return ctx

    def state_lines(self) -> list[str]:
        """One line per station whose measurements had no station state to go with."""
        return [
            f'station {sid}: measurements but no state ({why}); its measurements were not used'
            for sid, why in sorted(self.stations_without_state.items())
        ]

    def scenario_truth_biases(self) -> None:
        """For a simulated bag written before its metadata kept the biases (it has truth
        and names a scenario of the package): take them from that scenario file."""
        if self.truth_biases is not None or not self.truth or not self.scenario:
            return
        try:
            sc = load_scenario(self.scenario)
        except (FileNotFoundError, ConfigError):
            return
        self.truth_biases = truth_biases(sc)
        self.truth_biases_source = f'scenario file {sc.source}'

    def tb(self, ns: int) -> TimeBase:
        if self.timebase is None:
            self.timebase = TimeBase.whole_second_of(ns)
        return self.timebase

    def in_gap(self, t: np.ndarray) -> np.ndarray:
        out = np.zeros(np.shape(t), dtype=bool)
        for a, b in self.gaps:
            out |= (t >= a) & (t <= b)
        return out


_TARGET_TOPICS = frozenset({'telemetry/state', 'triangulation/fixes', 'truth/state'})

INPUT_TYPES = {
    'measurements': 'sensor_msgs/msg/PointCloud2',
    'state': 'nav_msgs/msg/Odometry',
    'telemetry/state': 'nav_msgs/msg/Odometry',
    'truth/state': 'nav_msgs/msg/Odometry',
    'triangulation/fixes': 'geometry_msgs/msg/PoseWithCovarianceStamped',
}
"""Message type of each input topic (``stations/<id>/measurements`` as ``measurements``,
``stations/<id>/state`` as ``state``), as the contract has them."""


def _input_kind(topic: str) -> str:
    """``measurements``, ``state``, a target topic, or '' for a topic that is no input."""
    parts = topic.lstrip('/').split('/')
    if len(parts) == 3 and parts[0] == 'stations' and parts[2] in ('measurements', 'state'):
        return parts[2]
    return topic.lstrip('/') if topic.lstrip('/') in _TARGET_TOPICS else ''


_DATA_KINDS = frozenset({'measurements', 'telemetry/state', 'triangulation/fixes'})


def input_topics(bag: str | Path) -> dict[str, int]:
    """The input topics of a bag (names as recorded) with their message counts.

    Opening the bag checks it (:func:`~orbit_tracking.ros.bag.bag_topics`).

    Raises
    ------
    BagError
        The bag cannot be read, an input topic has another message type than the
        contract's, no measurement, telemetry or fix topic has a message, or every station
        with measurements lacks a ``stations/<id>/state`` topic with messages.
    """
    topics = bag_topics(bag)
    out: dict[str, int] = {}
    for topic, (msgtype, n) in sorted(topics.items()):
        kind = _input_kind(topic)
        if not kind:
            continue
        if msgtype != INPUT_TYPES[kind]:
            raise BagError(
                f'{bag}: topic {topic} has message type {msgtype}; an input of orbit-tracking '
                f'needs {INPUT_TYPES[kind]}'
            )
        out[topic] = n
    if not any(n for t, n in out.items() if _input_kind(t) in _DATA_KINDS):
        have = ', '.join(f'{t} ({n})' for t, (_, n) in sorted(topics.items())) or 'no topic'
        raise BagError(
            f'{bag} has no usable topic: no messages on stations/<id>/measurements, '
            f'telemetry/state or triangulation/fixes (it has {have})'
        )
    measured = _stations(out, 'measurements')
    with_state = _stations(out, 'state')
    if measured and not measured & with_state:
        raise BagError(_no_state_message(bag, {s: _why_no_state(s, out) for s in measured}))
    return out


def _stations(topics: dict[str, int], kind: str) -> set[str]:
    return {t.lstrip('/').split('/')[1] for t, n in topics.items() if n and _input_kind(t) == kind}


def _why_no_state(sid: str, topics: dict[str, int], invalid: int = 0) -> str:
    n = next((v for t, v in topics.items() if t.lstrip('/') == f'stations/{sid}/state'), None)
    if n is None:
        return f'no stations/{sid}/state topic'
    if not n and not invalid:
        return f'stations/{sid}/state has no messages'
    return f'none of the {invalid or n} messages of stations/{sid}/state is valid'


def _no_state_message(bag: str | Path, why: dict[str, str]) -> str:
    return (
        f'{bag}: no station state to place the measurements by: '
        + '; '.join(f'station {sid} has measurements but {w}' for sid, w in sorted(why.items()))
        + ' (station states come on stations/<id>/state as nav_msgs/Odometry)'
    )


@dataclass(frozen=True)
class BagInput:
    """One decoded input message of a bag."""

    kind: str  # measurements | station_state | telemetry | fix | truth
    data: Any


_DEFER_CHUNK = 4096
"""Measurement messages of one station held before they are decoded together (the
memory a long pass's messages would take held to the end is bounded this way)."""

_WIRE_TYPES = (INPUT_TYPES['measurements'], 'nav_msgs/msg/Odometry')
"""Message types read straight from their bytes (:mod:`orbit_tracking.ros.conversions.wire`)."""


def _from_wire(raw: bytes, msgtype: str, topic: str, bag: str | Path) -> Any:
    try:
        return read_message(raw, msgtype)
    except ValueError as exc:  # a corrupt message: one line, not a traceback
        raise BagError(
            f'{bag}: a message on {topic} cannot be read: {exc} (truncated or corrupt file?)'
        ) from exc


def bag_inputs(
    bag: str | Path,
    ctx: BagContext,
    counts: Counter[str],
    progress: bool,
    desc: str,
    defer_measurements: bool = False,
) -> Iterator[BagInput]:
    """Decode the input topics of a bag in log order, as the nodes receive them.

    Undecodable messages and messages whose station id differs from their topic's are
    counted in ``counts`` (``invalid_messages``, ``invalid_state``, ``station_mismatch``,
    ``invalid_fix``) and skipped; ``rejected_points`` counts bad points inside good
    messages. The first station state sets ``ctx.world_frame``. Stations with
    measurements but no valid state go to ``ctx.stations_without_state``.

    With ``defer_measurements`` the measurement messages are not given one by one in log
    order but at the end, decoded together: one :class:`MeasurementBatch` per station and
    field layout (for a reader that only collects them; the rows and counts are the same).

    Raises
    ------
    BagError
        See :func:`input_topics`; also when the bag fails half way through, or when in the
        end no station with measurements had a valid state.
    """
    topics = input_topics(bag)  # checks the bag before the progress bar starts
    measured: set[str] = set()
    with_state: set[str] = set()
    bad_state: Counter[str] = Counter()
    deferred: dict[str, list[Any]] = {}

    def accepted(b: MeasurementBatch, station: str) -> bool:
        if b.rejected:
            counts['rejected_points'] += b.rejected
        if b.station_id != station:
            counts['station_mismatch'] += b.messages
            return False
        measured.add(b.station_id)
        return True

    def decode_deferred(station: str, tb: TimeBase) -> Iterator[BagInput]:
        batches, errors = clouds_to_measurements(deferred.pop(station, []), tb)
        if errors:
            counts['invalid_messages'] += len(errors)
        for b in batches:
            if accepted(b, station):
                yield BagInput('measurements', b)

    bar = tqdm(total=sum(topics.values()), unit='msg', disable=not progress, desc=desc)
    try:
        for m in read_bag(bag, topics, raw_types=_WIRE_TYPES):
            bar.update(1)
            topic = m.topic.lstrip('/')
            parts = topic.split('/')
            msg = _from_wire(m.msg, m.msgtype, m.topic, bag) if isinstance(m.msg, bytes) else m.msg
            tb = ctx.tb(stamp_ns(msg.header.stamp))
            if len(parts) == 3 and parts[2] == 'measurements':
                if defer_measurements:
                    held = deferred.setdefault(parts[1], [])
                    held.append(msg)
                    if len(held) >= _DEFER_CHUNK:
                        yield from decode_deferred(parts[1], tb)
                    continue
                try:
                    b = cloud_to_measurements(msg, tb)
                except MeasurementError:
                    counts['invalid_messages'] += 1
                    continue
                if accepted(b, parts[1]):
                    yield BagInput('measurements', b)
            elif len(parts) == 3 and parts[2] == 'state':
                try:
                    st = odometry_to_station_state(msg, tb)
                except ValueError:
                    counts['invalid_state'] += 1
                    bad_state[parts[1]] += 1
                    continue
                if st.station_id != parts[1]:
                    counts['station_mismatch'] += 1
                    bad_state[parts[1]] += 1
                    continue
                ctx.world_frame = ctx.world_frame or msg.header.frame_id
                with_state.add(st.station_id)
                yield BagInput('station_state', st)
            elif topic == 'telemetry/state':
                try:
                    tel = odometry_to_target_state(msg, tb, check=True)
                except ValueError:
                    counts['invalid_telemetry'] += 1
                    continue
                yield BagInput('telemetry', tel)
            elif topic == 'triangulation/fixes':
                try:
                    yield BagInput('fix', msg_to_fix(msg, tb))
                except ValueError:
                    counts['invalid_fix'] += 1
            elif topic == 'truth/state':
                yield BagInput('truth', odometry_to_target_state(msg, tb))
        for station in list(deferred):
            # the time base was set by the bag's first message
            yield from decode_deferred(station, ctx.tb(0))
        ctx.stations_without_state = {
            sid: _why_no_state(sid, topics, bad_state[sid])
            for sid in sorted(measured - with_state)
        }
        if measured and not with_state:
            raise BagError(_no_state_message(bag, ctx.stations_without_state))
    except BagError:
        bar.leave = False  # the error line takes the bar's place
        raise
    finally:
        bar.close()


def truth_states(samples: list[Any]) -> dict[int, TargetStates]:
    """Truth samples (TargetStateSample) gathered per target, in time order."""
    rows: dict[int, list[Any]] = {}
    for s in samples:
        rows.setdefault(s.target_id, []).append(s)
    out = {}
    for tid, ss in rows.items():
        ss.sort(key=lambda s: s.time)
        t = np.array([s.time for s in ss])
        z = np.zeros((t.size, 3))
        out[tid] = TargetStates(
            tid, t, np.array([s.position for s in ss]), np.array([s.velocity for s in ss]), z, z
        )
    return out


def feed_pipeline(pipe: TriangulationPipeline, item: BagInput) -> list[TimedFix]:
    """Give one decoded input to a triangulation pipeline; the fixes it makes ready."""
    if item.kind == 'measurements':
        b = item.data
        pipe.add_measurements(b.station_id, b.fields, b.time, b.target_id, b.values, b.sigmas)
        return pipe.process()
    if item.kind == 'station_state':
        s = item.data
        pipe.add_pose(s.station_id, s.time, s.position, s.velocity, s.rotation, s.moving)
    return []


def read_for_estimation(
    bag: str | Path, ctx: BagContext, progress: bool
) -> tuple[ObservationBuffer, Counter[str]]:
    """Measurements, station states, telemetry and fixes of a bag into a buffer (what the
    node receives); the truth goes to ``ctx.truth``."""
    buf = ObservationBuffer()
    counts: Counter[str] = Counter()
    truth: list[Any] = []
    for item in bag_inputs(bag, ctx, counts, progress, 'read bag', defer_measurements=True):
        d = item.data
        if item.kind == 'measurements':
            buf.add_measurements(d.station_id, d.fields, d.time, d.target_id, d.values, d.sigmas)
        elif item.kind == 'station_state':
            buf.add_pose(d.station_id, d.time, d.position, d.velocity, d.rotation, d.moving)
        elif item.kind == 'telemetry':
            try:
                buf.add_telemetry(
                    d.target_id,
                    d.time,
                    d.position,
                    d.velocity,
                    np.sqrt(np.clip(np.diag(d.position_cov), 0.0, None)),
                    np.sqrt(np.clip(np.diag(d.velocity_cov), 0.0, None)),
                )
            except ValueError:
                counts['invalid_telemetry'] += 1
        elif item.kind == 'fix':
            try:
                buf.add_fix(0, *d)
            except ValueError:
                counts['invalid_fix'] += 1
        elif item.kind == 'truth':
            truth.append(d)
    ctx.truth.update(truth_states(truth))
    return buf, +counts


def bag_message_counts(bag: str | Path) -> dict[str, int]:
    """Messages per topic (leading ``/`` dropped), as the bag's index lists them."""
    out: dict[str, int] = {}
    for name, (_msgtype, n) in bag_topics(bag).items():
        out[name.lstrip('/')] = out.get(name.lstrip('/'), 0) + n
    return dict(sorted(out.items()))
