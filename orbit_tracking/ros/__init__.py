"""Thin ROS 2 nodes and the message conversions they share.

The package itself exports no names: import them from its modules (for example
:mod:`orbit_tracking.ros.conversions`, :mod:`orbit_tracking.ros.qos`).
"""

__all__: list[str] = []
