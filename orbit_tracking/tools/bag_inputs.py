"""Reading a recorded bag for the offline tools: what the bag says about itself
(:class:`BagContext`), its messages decoded and validated in log-time order
(:func:`bag_inputs`, rejections counted by reason), the truth it carries, and the
observations an estimate needs (:func:`read_for_estimation`)."""

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
from orbit_tracking.ros.bag import bag_custom_data, read_bag
from orbit_tracking.ros.conversions import (
    TimeBase,
    cloud_to_measurements,
    msg_to_fix,
    odometry_to_station_state,
    odometry_to_target_state,
    stamp_ns,
)

__all__ = [
    'BagContext',
    'BagInput',
    'bag_inputs',
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

    @classmethod
    def from_custom_data(cls, path: str | Path) -> BagContext:
        data = bag_custom_data(path)
        ctx = cls()
        if 'orbit_tracking.epoch' in data:
            ctx.timebase = TimeBase.from_seconds(float(data['orbit_tracking.epoch']))
        ctx.world_frame = data.get('orbit_tracking.world_frame', '')
        ctx.scenario = data.get('orbit_tracking.scenario', '')
        ctx.gaps = [tuple(g) for g in yaml.safe_load(data.get('orbit_tracking.gaps', '[]')) or []]
        if 'orbit_tracking.biases' in data:
            biases = yaml.safe_load(data['orbit_tracking.biases']) or {}
            ctx.truth_biases = {
                (str(sid), str(name)): float(v)
                for sid, values in biases.items()
                for name, v in values.items()
            }
            ctx.truth_biases_source = 'bag metadata (orbit_tracking.biases)'
        return ctx

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


@dataclass(frozen=True)
class BagInput:
    """One decoded input message of a bag."""

    kind: str  # measurements | station_state | telemetry | fix | truth
    data: Any


def bag_inputs(
    bag: str | Path, ctx: BagContext, counts: Counter[str], progress: bool, desc: str
) -> Iterator[BagInput]:
    """Decode the input topics of a bag in log order, as the nodes receive them.

    Undecodable messages and messages whose station id differs from their topic's are
    counted in ``counts`` (``invalid_messages``, ``invalid_state``, ``station_mismatch``,
    ``invalid_fix``) and skipped; ``rejected_points`` counts bad points inside good
    messages. The first station state sets ``ctx.world_frame``.
    """
    for m in tqdm(read_bag(bag), unit='msg', disable=not progress, desc=desc):
        topic = m.topic.lstrip('/')
        parts = topic.split('/')
        station = len(parts) == 3 and parts[0] == 'stations'
        if not station and topic not in _TARGET_TOPICS:
            continue  # e.g. /clock, /diagnostics, outputs: not inputs, no time base from them
        tb = ctx.tb(stamp_ns(m.msg.header.stamp))
        if len(parts) == 3 and parts[0] == 'stations' and parts[2] == 'measurements':
            try:
                b = cloud_to_measurements(m.msg, tb)
            except MeasurementError:
                counts['invalid_messages'] += 1
                continue
            if b.rejected:
                counts['rejected_points'] += b.rejected
            if b.station_id != parts[1]:
                counts['station_mismatch'] += 1
                continue
            yield BagInput('measurements', b)
        elif len(parts) == 3 and parts[0] == 'stations' and parts[2] == 'state':
            try:
                st = odometry_to_station_state(m.msg, tb)
            except ValueError:
                counts['invalid_state'] += 1
                continue
            if st.station_id != parts[1]:
                counts['station_mismatch'] += 1
                continue
            ctx.world_frame = ctx.world_frame or m.msg.header.frame_id
            yield BagInput('station_state', st)
        elif topic == 'telemetry/state':
            yield BagInput('telemetry', odometry_to_target_state(m.msg, tb))
        elif topic == 'triangulation/fixes':
            try:
                yield BagInput('fix', msg_to_fix(m.msg, tb))
            except ValueError:
                counts['invalid_fix'] += 1
        elif topic == 'truth/state':
            yield BagInput('truth', odometry_to_target_state(m.msg, tb))


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
    for item in bag_inputs(bag, ctx, counts, progress, 'read bag'):
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
    """Messages per topic (leading ``/`` dropped), from the bag's ``metadata.yaml``."""
    meta = yaml.safe_load((Path(bag) / 'metadata.yaml').read_text())
    info = meta.get('rosbag2_bagfile_information', {})
    out: dict[str, int] = {}
    for t in info.get('topics_with_message_count') or []:
        name = str(t['topic_metadata']['name']).lstrip('/')
        out[name] = out.get(name, 0) + int(t['message_count'])
    return dict(sorted(out.items()))
