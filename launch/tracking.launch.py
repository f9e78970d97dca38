"""Launch the scenario simulator and the triangulation node (for a full ROS 2 install).

ros2 launch orbit_tracking tracking.launch.py scenario:=seed003_q2 rate_factor:=5.0
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory('orbit_tracking'), 'config')
    scenario = LaunchConfiguration('scenario')
    rate_factor = LaunchConfiguration('rate_factor')
    return LaunchDescription(
        [
            DeclareLaunchArgument('scenario', default_value='seed000_s1'),
            DeclareLaunchArgument('rate_factor', default_value='1.0'),
            Node(
                package='orbit_tracking',
                executable='scenario_sim',
                name='scenario_sim',
                parameters=[
                    os.path.join(config, 'scenario_sim.yaml'),
                    {'scenario': scenario, 'rate_factor': rate_factor},
                ],
                output='screen',
            ),
            Node(
                package='orbit_tracking',
                executable='triangulation',
                name='triangulation',
                parameters=[os.path.join(config, 'triangulation.yaml')],
                output='screen',
            ),
        ]
    )
