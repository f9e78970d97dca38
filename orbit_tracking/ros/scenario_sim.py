"""``scenario_sim``: every station of a scenario (plus telemetry and truth) in one process.

Example::

    ros2 run orbit_tracking scenario_sim --ros-args -p scenario:=seed000_s1 -p rate_factor:=5.0
"""

from __future__ import annotations

from orbit_tracking.ros.runner import run_node
from orbit_tracking.ros.simulator import SimulatorNode

__all__ = ['main']


def main(args: list[str] | None = None) -> None:
    run_node(lambda: SimulatorNode('scenario_sim', single_station=False), args)


if __name__ == '__main__':
    main()
