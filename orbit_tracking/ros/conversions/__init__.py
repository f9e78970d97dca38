"""Messages <-> core types: the only package where ROS messages and the numerical core meet.

Layouts follow ``docs/CONTRACT.md``:

* measurements: ``sensor_msgs/PointCloud2``, one point per (epoch, target), FLOAT64
  value and ``sigma_<field>`` fields, ``time_offset`` (FLOAT64, s) and ``target_id``
  (UINT32), little-endian, ``height = 1``, dense;
* station states, telemetry, truth and fitted states: ``nav_msgs/Odometry``;
* triangulation fixes: ``geometry_msgs/PoseWithCovarianceStamped``;
* a window's fitted states (internal, ``estimator/window_states``): ``PointCloud2`` with
  :data:`WINDOW_STATE_FIELDS`;
* a window's residual statistics (internal, ``estimator/window_residuals``):
  ``diagnostic_msgs/DiagnosticArray``, one status per station;
* a window's station biases (``trajectory/biases``): ``diagnostic_msgs/DiagnosticArray``,
  one status per station with ``<name>_bias`` and ``<name>_bias_sigma`` keys.

Times: the core computes in float seconds relative to a :class:`TimeBase` (an integer
number of nanoseconds, by default the scenario epoch), so that float64 keeps
sub-nanosecond resolution across a long pass.

Submodules (every public name is re-exported here; import from this package):

* :mod:`~orbit_tracking.ros.conversions.time`: :class:`TimeBase`, :func:`stamp_ns`;
* :mod:`~orbit_tracking.ros.conversions.measurements`: :class:`MeasurementBatch`,
  :func:`measurements_to_cloud` (:func:`measurements_to_cdr` already serialised),
  :func:`cloud_to_measurements`,
  :func:`clouds_to_measurements` (many messages in one pass);
* :mod:`~orbit_tracking.ros.conversions.wire`: :func:`parse_cloud`, :func:`parse_odometry`
  (a ``PointCloud2`` or ``Odometry`` read from its serialised bytes, without rclpy),
  :func:`read_message` (those, or rclpy's deserialisation), :func:`cloud_cdr`,
  :class:`WireCloud`, :class:`WireOdometry`;
* :mod:`~orbit_tracking.ros.conversions.states`: :class:`StationStateSample`,
  :class:`TargetStateSample`, station and target states <-> ``Odometry``, target frame
  ids, fixes <-> ``PoseWithCovarianceStamped``;
* :mod:`~orbit_tracking.ros.conversions.windows`: :data:`WINDOW_STATE_FIELDS`,
  :class:`WindowStates`, :class:`WindowResiduals` and their messages;
* :mod:`~orbit_tracking.ros.conversions.diagnostics`: :func:`diagnostic_status`,
  :func:`diagnostic_array`, :func:`biases_to_diagnostics`, :func:`diagnostics_to_biases`;
* ``_common``: private helpers shared by the above (float array type, field datatypes).
"""

from __future__ import annotations

from orbit_tracking.ros.conversions.diagnostics import (
    biases_to_diagnostics,
    diagnostic_array,
    diagnostic_status,
    diagnostics_to_biases,
)
from orbit_tracking.ros.conversions.measurements import (
    MeasurementBatch,
    cloud_to_measurements,
    clouds_to_measurements,
    measurements_to_cdr,
    measurements_to_cloud,
)
from orbit_tracking.ros.conversions.states import (
    StationStateSample,
    TargetStateSample,
    fix_to_msg,
    msg_to_fix,
    odometry_to_station_state,
    odometry_to_target_state,
    station_state_to_odometry,
    target_frame_id,
    target_id_from_frame,
    target_state_to_odometry,
)
from orbit_tracking.ros.conversions.time import TimeBase, checked_stamp_ns, stamp_ns
from orbit_tracking.ros.conversions.windows import (
    MAX_WINDOW_POINTS,
    WINDOW_STATE_FIELDS,
    WindowResiduals,
    WindowStates,
    cloud_to_window_states,
    msg_to_window_residuals,
    window_residuals_to_msg,
    window_states_to_cloud,
)
from orbit_tracking.ros.conversions.wire import (
    WireCloud,
    WireOdometry,
    cloud_cdr,
    parse_cloud,
    parse_odometry,
    read_message,
)

__all__ = [
    'MAX_WINDOW_POINTS',
    'MeasurementBatch',
    'StationStateSample',
    'TargetStateSample',
    'TimeBase',
    'WINDOW_STATE_FIELDS',
    'WindowResiduals',
    'WindowStates',
    'WireCloud',
    'WireOdometry',
    'biases_to_diagnostics',
    'checked_stamp_ns',
    'cloud_to_measurements',
    'cloud_to_window_states',
    'cloud_cdr',
    'clouds_to_measurements',
    'diagnostic_array',
    'diagnostic_status',
    'diagnostics_to_biases',
    'fix_to_msg',
    'measurements_to_cdr',
    'measurements_to_cloud',
    'msg_to_fix',
    'msg_to_window_residuals',
    'odometry_to_station_state',
    'odometry_to_target_state',
    'parse_cloud',
    'parse_odometry',
    'read_message',
    'stamp_ns',
    'station_state_to_odometry',
    'target_frame_id',
    'target_id_from_frame',
    'target_state_to_odometry',
    'window_residuals_to_msg',
    'window_states_to_cloud',
]
