"""The fault classes of the fault-injection suite (:mod:`orbit_tracking.tools.bench.faults`):
bad messages a broken or hostile publisher can put on the input topics of the processing
nodes, some seventy of them in five groups.

Each :class:`FaultClass` names a builder of
:mod:`~orbit_tracking.tools.bench.fault_messages` (its bad message(s), made from the real
messages the replay has just published), the topics it publishes on and the nodes that must
judge it (``targets``). Every class expects the same effect: the message, or its bad
points, is rejected; each target node counts the rejection by reason in its
``/diagnostics``; no node dies or logs a traceback; and the trajectory is the clean
replay's. ``table`` marks the classes of issue 13's table (what a hostile publisher got
through before the fixes).

A class is injected at the same data time in every replay (:attr:`FaultClass.at`), in its
group's replay as when it runs alone, so that it does the same wherever it runs. The
undeclared stations come last in their groups: a node holds data back for a station
without state for a while (the triangulation node's ``state_wait_timeout``) and counts the
loss later, which must not fall into another class's injection. Classes whose rejection a
node may count only once later messages show it (stamps off the time line, an unknown
target) are each at a stop of their own, so that a count after a stop names its class.
:data:`CONTROL` is not a fault: a plausible measurement the nodes cannot tell from a real
one, which the suite must therefore see in the trajectory.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from builtin_interfaces.msg import Time
from sensor_msgs.msg import PointCloud2

from orbit_tracking.tools.bench.fault_messages import (
    CW,
    EST,
    FIXES,
    NODES,
    OPT,
    OPT2,
    RANGES,
    RES,
    RESIDUALS,
    ROGUE,
    ROGUE2,
    STATIONS,
    TELEMETRY,
    WINDOWS,
    Builder,
    Injection,
    Reference,
    assign,
    field_of,
    first_point,
    fix,
    mutated,
    offset,
    on,
    one_point,
    residuals,
    rogue_no_state,
    rogue_reset,
    set_variances,
    stamped,
    station_state,
    target_max,
    targets_300,
    telemetry,
    valued,
    window,
)

__all__ = [
    'CATALOGUE',
    'CONTROL',
    'GROUPS',
    'NODES',
    'PER_STOP',
    'SPAN',
    'SPANS',
    'FaultClass',
    'catalogue',
]


@dataclass(frozen=True)
class FaultClass:
    """One class of bad input.

    Attributes
    ----------
    name : str
    group : str
        Classes of one group share a replay (:data:`GROUPS`).
    what : str
        One line: what the bad message is.
    targets : tuple of str
        Nodes expected to reject it and count the rejection (of ``NODES``).
    topics : tuple of str
        Topics it publishes on (absolute), known before the replay starts so that the
        injector can wait until the nodes read them.
    build : Builder
        ``build(ref) -> list of Injection``.
    table : bool
        One of the classes of issue 13's table.
    at : float
        Data time [s after the epoch] at which the replay stops to inject it (see
        :data:`SPANS`).
    """

    name: str
    group: str
    what: str
    targets: tuple[str, ...]
    topics: tuple[str, ...]
    build: Builder = field(repr=False)
    table: bool = False
    at: float = 30.0


GROUPS = ('layout', 'values', 'time', 'inputs', 'windows')
"""Replay groups: the classes of one group share a replay."""

SPAN = (23.0, 44.0)
"""Data times [s] over which a group's classes are spread (the theodolites measure until
45 s)."""

SPANS = {'windows': (36.0, 44.0)}
"""Spans of the groups that do not use :data:`SPAN`: bad windows and residuals come once the
estimator has published its first window (solved when the data reach 34 s; the replay also
waits for it, which a loaded machine may deliver seconds later), as on a running system."""

PER_STOP = 3
"""Classes injected at one stop of the replay."""

_BIG_SEC = 2_000_000_000
"""A stamp [s] in 2033: far ahead of any data of the pass (int32 ``sec`` ends in 2038)."""

# topics
M_CW = (f'/stations/{CW}/measurements',)
M_OPT = (f'/stations/{OPT}/measurements',)
S_OPT = (f'/stations/{OPT}/state',)
TEL, FIX, WIN, RSD = (TELEMETRY,), (FIXES,), (WINDOWS,), (RESIDUALS,)
E, R = (EST,), (RES,)


def _nanosec_overflow(ref: Reference) -> list[Injection]:
    real = ref.measurements(OPT).header.stamp
    return on(OPT, one_point(ref, OPT, stamp=Time(sec=real.sec, nanosec=2**32 - 1)))


def _without(name: str) -> Callable[[PointCloud2], None]:
    return lambda m: assign(m, fields=[f for f in m.fields if f.name != name])


# fmt: off
_ROWS: dict[str, list[tuple[Any, ...]]] = {
    'layout': [
        ('wrong_datatype', 'range field FLOAT32', STATIONS, M_CW, mutated(CW, 'range_float32')),
        ('wrong_count', 'range field with count 2', STATIONS, M_CW, mutated(CW, 'range_count_2')),
        ('field_beyond_point_step', 'target_id field reaching past point_step', STATIONS, M_CW,
         mutated(CW, 'beyond_point_step')),
        ('point_step_zero', 'point_step 0', STATIONS, M_CW, mutated(CW, 'point_step_zero')),
        ('width_height_overflow', 'width = height = 2^32 - 1, one point of data', STATIONS,
         M_CW, mutated(CW, 'width_height_overflow')),
        ('huge_point_count', 'width 1e9, one point of data', STATIONS, M_CW,
         mutated(CW, 'huge_width')),
        ('data_truncated', 'data one byte short', STATIONS, M_CW, mutated(CW, 'truncated')),
        ('missing_sigma_field', 'range_rate without sigma_range_rate', STATIONS, M_CW,
         mutated(CW, 'without_sigma_field')),
        ('no_value_field', 'sigma fields only', STATIONS, M_CW,
         mutated(CW, 'without_value_fields')),
        ('empty_frame_id', 'header.frame_id empty', STATIONS, M_CW, mutated(CW, 'empty_frame_id')),
        ('frame_id_not_topic', f'frame_id cw05 on stations/{CW}/measurements', STATIONS, M_CW,
         mutated(CW, 'other_station')),
        ('zero_points', 'width 0, no data', STATIONS, M_CW, mutated(CW, 'zero_points')),
        ('big_endian_flag', 'is_bigendian set on little-endian bytes', STATIONS, M_OPT,
         mutated(OPT, 'big_endian_flag')),
        ('extra_trailing_bytes', '16 bytes after the last point', STATIONS, M_OPT,
         mutated(OPT, 'trailing_bytes'), True),
        ('row_step_too_small', 'two points, row_step of one', STATIONS, M_OPT,
         mutated(OPT, 'row_step_too_small'), True),
        ('padded_rows', 'height 2, rows padded by 8 bytes', STATIONS, M_OPT,
         mutated(OPT, 'padded_rows'), True),
        ('duplicate_field_names', 'a second range field over sigma_range', STATIONS, M_CW,
         mutated(CW, 'duplicate_range_field'), True),
    ],
    'values': [
        ('sigma_nan', 'elevation sigma NaN', STATIONS, M_OPT,
         valued(OPT, sigma_elevation=math.nan)),
        ('sigma_zero', 'azimuth sigma 0', STATIONS, M_OPT, valued(OPT, sigma_azimuth=0.0)),
        ('sigma_negative', 'range sigma -1 m', STATIONS, M_CW, valued(CW, sigma_range=-1.0)),
        ('sigma_inf', 'range-rate sigma inf', STATIONS, M_CW,
         valued(CW, sigma_range_rate=math.inf)),
        ('sigma_tiny', 'range sigma 1e-300 m', STATIONS, M_CW, valued(CW, sigma_range=1e-300)),
        ('value_inf', 'range +inf', STATIONS, M_CW, valued(CW, range=math.inf)),
        ('range_negative', 'range -1000 m', RANGES, M_CW, valued(CW, range=-1000.0)),
        ('range_1e300', 'range 1e300 m', RANGES, M_CW, valued(CW, range=1e300), True),
        ('range_500km_sigma_1m', 'range 500 km with sigma 1 m', RANGES, M_CW,
         valued(CW, range=5e5, sigma_range=1.0), True),
        ('range_rate_1e12', 'range rate 1e12 m/s', RANGES, M_CW, valued(CW, range_rate=1e12)),
        ('elevation_above_half_pi', 'elevation 2 rad', STATIONS, M_OPT,
         valued(OPT, elevation=2.0)),
        ('azimuth_1e9', 'azimuth 1e9 rad', STATIONS, M_OPT, valued(OPT, azimuth=1e9)),
    ],
    'time': [
        ('stamp_far_future', 'stamp in 2033', STATIONS, M_CW, stamped(CW, _BIG_SEC)),
        ('stamp_before_1970', 'stamp sec -1', STATIONS, M_CW, stamped(CW, -1, 0)),
        ('time_offset_nan', 'time_offset NaN', STATIONS, M_CW, offset(CW, math.nan)),
        ('stamp_zero', 'stamp 0', STATIONS, M_CW, stamped(CW, 0, 0)),
        ('nanosec_ge_1e9', 'nanosec 2^32 - 1 (reads as +4.29 s)', STATIONS, M_OPT,
         _nanosec_overflow, True),
        ('time_offset_1e6', 'time_offset 1e6 s (11 days)', STATIONS, M_CW, offset(CW, 1e6)),
        ('stamp_1s_after_epoch', 'stamp 1 s after 1970', STATIONS, M_CW, stamped(CW, 1, 0)),
        ('time_offset_1e18', 'time_offset 1e18 s', STATIONS, M_CW, offset(CW, 1e18), True),
        ('time_offset_1e300', 'time_offset 1e300 s', STATIONS, M_CW, offset(CW, 1e300), True),
        ('time_offset_minus_1e18', 'time_offset -1e18 s', STATIONS, M_CW, offset(CW, -1e18)),
        ('unknown_station_reset',
         f'undeclared station {ROGUE}: current stamp, then 1 s after 1970', STATIONS,
         (f'/stations/{ROGUE}/measurements',), rogue_reset, True),
    ],
    'inputs': [
        ('target_id_max', 'target_id 0xFFFFFFFF', STATIONS, M_OPT, target_max),
        ('state_nan_position', 'station state with NaN position', STATIONS, S_OPT,
         station_state(lambda m: assign(m.pose.pose.position, x=math.nan))),
        ('state_non_unit_quaternion', 'station state with quaternion norm 2', STATIONS, S_OPT,
         station_state(lambda m: assign(m.pose.pose.orientation, x=0.0, y=0.0, z=0.0, w=2.0))),
        ('target_ids_300', '300 distinct target ids on two theodolites', STATIONS,
         (*M_OPT, f'/stations/{OPT2}/measurements'), targets_300, True),
        ('state_zero_quaternion', 'station state with a zero quaternion', STATIONS, S_OPT,
         station_state(lambda m: assign(m.pose.pose.orientation, x=0.0, y=0.0, z=0.0, w=0.0))),
        ('state_wrong_frame', 'station state in frame eci', STATIONS, S_OPT,
         station_state(lambda m: assign(m.header, frame_id='eci'))),
        ('telemetry_far_future', 'telemetry stamped in 2033', E, TEL,
         telemetry(lambda m: assign(m.header.stamp, sec=_BIG_SEC))),
        ('state_wrong_child_frame', f'state naming {OPT2} on stations/{OPT}/state', STATIONS,
         S_OPT, station_state(lambda m: assign(m, child_frame_id=OPT2))),
        ('state_inf_velocity', 'station state with infinite velocity', STATIONS, S_OPT,
         station_state(lambda m: assign(m.twist.twist.linear, x=math.inf))),
        ('fix_far_future', 'fix stamped in 2033', E, FIX,
         fix(lambda m: assign(m.header.stamp, sec=_BIG_SEC))),
        ('telemetry_nan_position', 'telemetry with NaN position', E, TEL,
         telemetry(lambda m: assign(m.pose.pose.position, y=math.nan))),
        ('telemetry_negative_covariance', 'telemetry with position variance -100 m2', E, TEL,
         telemetry(lambda m: set_variances(m.pose, [-100.0]))),
        ('telemetry_nan_covariance', 'telemetry with NaN velocity variance', E, TEL,
         telemetry(lambda m: set_variances(m.twist, [math.nan]))),
        ('telemetry_bad_child_frame', "telemetry with child_frame_id 'robot'", E, TEL,
         telemetry(lambda m: assign(m, child_frame_id='robot'))),
        ('telemetry_wrong_frame', 'telemetry in frame eci', E, TEL,
         telemetry(lambda m: assign(m.header, frame_id='eci'))),
        ('fix_non_psd_covariance', 'fix with an indefinite covariance', E, FIX,
         fix(lambda m: set_variances(m.pose, [100.0, -100.0, 100.0]))),
        ('fix_nan_position', 'fix with NaN position', E, FIX,
         fix(lambda m: assign(m.pose.pose.position, z=math.nan))),
        ('unknown_station_no_state', f'undeclared station {ROGUE2}, one point, never a state',
         STATIONS, (f'/stations/{ROGUE2}/measurements',), rogue_no_state),
    ],
    'windows': [
        ('window_far_future', 'a plausible window 3 years ahead', R, WIN, window(shift_s=1e8),
         True),
        ('window_negative_variance', 'window with variance -1 m2', R, WIN,
         window(first_point('c_00', -1.0))),
        ('window_mismatched_lengths', 'window_length differing between points', R, WIN,
         window(first_point('window_length', 3.0))),
        ('window_nan_state', 'window state with NaN x', R, WIN,
         window(first_point('x', math.nan))),
        ('window_missing_field', 'window without c_55', R, WIN,
         window(after=_without('c_55'))),
        ('window_wrong_datatype', 'window with x FLOAT32', R, WIN,
         window(after=lambda m: assign(field_of(m, 'x'), datatype=7))),
        ('window_data_short', 'window data 8 bytes short', R, WIN,
         window(after=lambda m: assign(m, data=bytes(m.data)[:-8]))),
        ('window_empty', 'window without states', R, WIN,
         window(after=lambda m: assign(m, width=0, row_step=0, data=b''))),
        ('window_wrong_frame', 'window in frame eci', R, WIN,
         window(after=lambda m: assign(m.header, frame_id='eci'))),
        ('window_300_targets', 'plausible window with 300 target ids', R, WIN,
         window(targets=300), True),
        ('residuals_missing_keys', 'window residuals without rows and window_end', R, RSD,
         residuals({'rows': None, 'window_end': None})),
        ('residuals_unparseable', "window residuals with rows 'many'", R, RSD,
         residuals({'rows': 'many'})),
        ('residuals_empty_name', 'window residuals of station ""', R, RSD, residuals(name='')),
        ('residuals_far_future', 'window residuals of a window 3 years ahead', R, RSD,
         residuals(shift_s=1e8)),
        ('residuals_negative_count', 'window residuals with range_count -5', R, RSD,
         residuals({'range_count': '-5'})),
    ],
}
# fmt: on
"""Per group: (name, what, targets, topics, builder[, in issue 13's table])."""


def catalogue() -> list[FaultClass]:
    """Every fault class, in group order, each with its injection time: a group's classes
    :data:`PER_STOP` at a time at stops spread evenly over its span."""
    out = []
    for group in GROUPS:
        rows = _ROWS[group]
        lo, hi = SPANS.get(group, SPAN)
        stops = max((len(rows) + PER_STOP - 1) // PER_STOP, 1)
        for i, (name, what, targets, topics, build, *table) in enumerate(rows):
            at = lo + (hi - lo) * (i // PER_STOP) / max(stops - 1, 1)
            out.append(FaultClass(name, group, what, targets, topics, build, bool(table), at))
    return out


CATALOGUE: tuple[FaultClass, ...] = tuple(catalogue())
"""Every fault class of the suite."""

CONTROL = FaultClass(
    'control_plausible_point',
    'control',
    f'a plausible {CW} point, every value two sigmas off a real one: used, as it must be',
    E,
    M_CW,
    lambda ref: on(CW, one_point(ref, CW)),
    at=30.0,
)
"""Not a fault: the suite's own check that a message the nodes take changes the trajectory
and counts nothing, so that a class that passes means something."""
