"""Launch the processing chain (for a full ROS 2 install): the scenario simulator, the
triangulation node, the sliding-window estimator and the results node, each with its
parameter file of ``config/``. The same nodes and files as ``orbit-tracking demo``
(``orbit_tracking.tools.live.NODES``; test/test_launch.py keeps the two in step).

    ros2 launch orbit_tracking tracking.launch.py scenario:=seed003_q2 rate_factor:=5.0

Record the outputs with ``ros2 bag record`` (or ``orbit-tracking record``); the final
trajectory is on ``trajectory/states`` and ``trajectory/path``.

The processing nodes are respawned one second after they die. With
``journal_dir:=/var/lib/orbit_tracking`` (any directory this run alone uses) the estimator
and the results node journal there (a file each) and a respawned one loses nothing
(docs/NODES.md, "Restart without loss").
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory('orbit_tracking'), 'config')
    scenario = LaunchConfiguration('scenario')
    rate_factor = ParameterValue(LaunchConfiguration('rate_factor'), value_type=float)
    journal_dir = ParameterValue(LaunchConfiguration('journal_dir'), value_type=str)
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                'scenario',
                default_value='seed000_s1',
                description='scenario name (config/scenarios) or YAML path',
            ),
            DeclareLaunchArgument(
                'rate_factor',
                default_value='1.0',
                description='scenario seconds streamed per wall second',
            ),
            DeclareLaunchArgument(
                'journal_dir',
                default_value='',
                description="journal directory of the estimator and results node ('' = none)",
            ),
            # the processing nodes first, so that they listen when the simulator streams
            Node(
                package='orbit_tracking',
                executable='triangulation',
                name='triangulation',
                parameters=[os.path.join(config, 'triangulation.yaml')],
                output='screen',
                respawn=True,
                respawn_delay=1.0,
            ),
            Node(
                package='orbit_tracking',
                executable='estimator',
                name='estimator',
                parameters=[
                    os.path.join(config, 'estimator.yaml'),
                    {'journal_dir': journal_dir},
                ],
                output='screen',
                respawn=True,
                respawn_delay=1.0,
            ),
            Node(
                package='orbit_tracking',
                executable='results',
                name='results',
                parameters=[os.path.join(config, 'results.yaml'), {'journal_dir': journal_dir}],
                output='screen',
                respawn=True,
                respawn_delay=1.0,
            ),
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
        ]
    )
