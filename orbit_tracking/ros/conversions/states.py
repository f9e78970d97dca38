"""Station and target states (``nav_msgs/Odometry``) and triangulation fixes
(``geometry_msgs/PoseWithCovarianceStamped``) <-> core arrays.

* station states: pose (position [m], orientation) in the world frame, twist (velocity
  [m/s], angular velocity [rad/s]) in the station frame, ``child_frame_id`` = station id;
* target states (telemetry, truth, fitted): identity orientation, so the twist is the world
  velocity [m/s]; ``child_frame_id`` = ``target_<id>`` (:func:`target_frame_id`);
* fixes: world position [m] with its 3x3 covariance [m^2].

Rotation and angular-rate variances that are not estimated are -1 (REP convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from numpy.typing import NDArray

from orbit_tracking.core import frames
from orbit_tracking.core.models.limits import MAX_TARGET_ID, state_problem
from orbit_tracking.ros.conversions._common import FloatArray
from orbit_tracking.ros.conversions.time import TimeBase

__all__ = [
    'StationStateSample',
    'TargetStateSample',
    'fix_to_msg',
    'msg_to_fix',
    'odometry_to_station_state',
    'odometry_to_target_state',
    'station_state_to_odometry',
    'target_frame_id',
    'target_id_from_frame',
    'target_state_to_odometry',
]

_UNKNOWN_ROTATION = -1.0  # REP-conventional "not estimated" variance


@dataclass(frozen=True)
class StationStateSample:
    """A station pose decoded from ``stations/<id>/state``."""

    station_id: str
    time: float
    position: FloatArray
    velocity: FloatArray
    rotation: FloatArray
    angular_velocity: FloatArray

    @property
    def moving(self) -> bool:
        """A station with any velocity or turn rate is treated as moving (its states are
        interpolated in time); a still one keeps its latest pose for every epoch."""
        return bool(
            np.linalg.norm(self.velocity) > 1e-6 or np.linalg.norm(self.angular_velocity) > 1e-9
        )


def station_state_to_odometry(
    station_id: str,
    world_frame: str,
    t: float,
    position: FloatArray,
    velocity: FloatArray,
    rotation: FloatArray,
    angular_velocity: FloatArray,
    timebase: TimeBase,
) -> Odometry:
    """Station pose as Odometry: pose in the world frame, twist in the station frame."""
    msg = Odometry()
    msg.header.stamp = timebase.to_stamp(t)
    msg.header.frame_id = world_frame
    msg.child_frame_id = station_id
    _set_point(msg.pose.pose.position, position)
    q = frames.matrix_to_quaternion(rotation)
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    v_body = rotation.T @ velocity
    _set_vector(msg.twist.twist.linear, v_body)
    _set_vector(msg.twist.twist.angular, angular_velocity)
    return msg


def odometry_to_station_state(msg: Odometry, timebase: TimeBase) -> StationStateSample:
    """Decode a station state; raises ``ValueError`` on a non-unit quaternion or NaN."""
    p = _point(msg.pose.pose.position)
    o = msg.pose.pose.orientation
    rot = frames.quaternion_to_matrix([o.x, o.y, o.z, o.w])
    v = rot @ _vector(msg.twist.twist.linear)
    w = _vector(msg.twist.twist.angular)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v))):
        raise ValueError(f'station state of {msg.child_frame_id!r} has non-finite values')
    problem = state_problem(p, v)
    if problem:
        raise ValueError(f'station state of {msg.child_frame_id!r}: {problem}')
    if not msg.child_frame_id:
        raise ValueError('station state has an empty child_frame_id (station id)')
    return StationStateSample(
        msg.child_frame_id, timebase.to_seconds(msg.header.stamp), p, v, rot, w
    )


@dataclass(frozen=True)
class TargetStateSample:
    """A target state (truth, telemetry, fitted) decoded from Odometry."""

    target_id: int
    time: float
    position: FloatArray
    velocity: FloatArray
    position_cov: FloatArray
    velocity_cov: FloatArray


def target_frame_id(target_id: int) -> str:
    """``child_frame_id`` of a target's states: ``target_<id>``."""
    return f'target_{int(target_id)}'


def target_id_from_frame(frame: str) -> int:
    """Inverse of :func:`target_frame_id`; plain ``target`` is target 0."""
    if frame == 'target':
        return 0
    digits = frame[7:] if frame.startswith('target_') else ''
    if digits.isascii() and digits.isdigit() and len(digits) <= 10:
        tid = int(digits)
        if tid <= MAX_TARGET_ID:
            return tid
    raise ValueError(
        f"target frame must be 'target' or 'target_<id>' with an id up to {MAX_TARGET_ID}; "
        f'got {frame[:80]!r}'
    )


def target_state_to_odometry(
    target_id: int,
    world_frame: str,
    t: float,
    position: FloatArray,
    velocity: FloatArray,
    position_cov: FloatArray,
    velocity_cov: FloatArray,
    timebase: TimeBase,
) -> Odometry:
    """Target state as Odometry: identity orientation so the twist is the world velocity;
    rotation and angular-rate variances are -1 (not estimated)."""
    msg = Odometry()
    msg.header.stamp = timebase.to_stamp(t)
    msg.header.frame_id = world_frame
    msg.child_frame_id = target_frame_id(target_id)
    _set_point(msg.pose.pose.position, position)
    msg.pose.pose.orientation.w = 1.0
    _set_vector(msg.twist.twist.linear, velocity)
    msg.pose.covariance = _cov6(position_cov)
    msg.twist.covariance = _cov6(velocity_cov)
    return msg


def odometry_to_target_state(
    msg: Odometry, timebase: TimeBase, check: bool = False
) -> TargetStateSample:
    """Decode a target state. With ``check`` (data from the wire: telemetry), raise
    ``ValueError`` on an implausible position, velocity or variance
    (:func:`~orbit_tracking.core.models.limits.state_problem`)."""
    pc = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
    vc = np.asarray(msg.twist.covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
    p, v = _point(msg.pose.pose.position), _vector(msg.twist.twist.linear)
    if check:
        problem = state_problem(p, v, np.diag(pc), np.diag(vc))
        if problem:
            raise ValueError(f'{msg.child_frame_id}: {problem}')
    return TargetStateSample(
        target_id_from_frame(msg.child_frame_id),
        timebase.to_seconds(msg.header.stamp),
        p,
        v,
        pc,
        vc,
    )


def fix_to_msg(
    world_frame: str, t: float, position: FloatArray, cov: FloatArray, timebase: TimeBase
) -> PoseWithCovarianceStamped:
    """A position fix with its 3x3 covariance (rotation block: -1 on the diagonal)."""
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = timebase.to_stamp(t)
    msg.header.frame_id = world_frame
    _set_point(msg.pose.pose.position, position)
    msg.pose.pose.orientation.w = 1.0
    msg.pose.covariance = _cov6(cov)
    return msg


def msg_to_fix(
    msg: PoseWithCovarianceStamped, timebase: TimeBase
) -> tuple[float, FloatArray, FloatArray]:
    """``(t, position (3,), covariance (3, 3))`` of a fix; ``ValueError`` on an implausible
    position or variance (:func:`~orbit_tracking.core.models.limits.state_problem`)."""
    cov = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
    p = _point(msg.pose.pose.position)
    problem = state_problem(p, position_var=np.diag(cov))
    if problem:
        raise ValueError(f'fix: {problem}')
    return timebase.to_seconds(msg.header.stamp), p, cov


def _cov6(cov3: FloatArray) -> NDArray[np.float64]:
    c = np.zeros((6, 6))
    c[:3, :3] = np.asarray(cov3, dtype=np.float64).reshape(3, 3)
    c[3, 3] = c[4, 4] = c[5, 5] = _UNKNOWN_ROTATION
    return c.ravel()


def _set_point(p: object, xyz: FloatArray) -> None:
    p.x, p.y, p.z = (float(v) for v in xyz)  # type: ignore[attr-defined]


def _set_vector(v: object, xyz: FloatArray) -> None:
    v.x, v.y, v.z = (float(c) for c in xyz)  # type: ignore[attr-defined]


def _point(p: object) -> FloatArray:
    return np.array([p.x, p.y, p.z], dtype=np.float64)  # type: ignore[attr-defined]


_vector = _point
