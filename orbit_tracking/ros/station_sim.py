"""``station_sim``: one simulated station of a scenario, publishing real DDS topics.

Example::

    ros2 run orbit_tracking station_sim --ros-args -p scenario:=seed003_q2 -p station_id:=sat06
"""

from __future__ import annotations

from orbit_tracking.ros.runner import run_node
from orbit_tracking.ros.simulator import SimulatorNode

__all__ = ['main']


def main(args: list[str] | None = None) -> None:
    run_node(lambda: SimulatorNode('station_sim', single_station=True), args)


if __name__ == '__main__':
    main()
