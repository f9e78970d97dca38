"""Packaging for the ``orbit_tracking`` ament_python package.

Layout follows ros2/demos ``demo_nodes_py``: ``colcon build`` installs the console scripts into
``lib/orbit_tracking`` (see ``setup.cfg``), which is where ``ros2 run orbit_tracking <exe>``
looks for them.
"""

import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'orbit_tracking'
here = os.path.dirname(os.path.abspath(__file__))


def data(pattern: str) -> list[str]:
    """Files matching ``pattern`` (relative to this file), as relative paths, sorted."""
    return sorted(os.path.relpath(p, here) for p in glob(os.path.join(here, pattern)))


# ROS node executables (``ros2 run orbit_tracking <name>``) and the command line tool.
# Keep this a literal list: test/test_package_build.py parses it, checks it against the
# installed distribution and starts every entry whose module is in ``orbit_tracking.ros`` as
# a ROS node.
console_scripts = [
    'station_sim = orbit_tracking.ros.station_sim:main',
    'scenario_sim = orbit_tracking.ros.scenario_sim:main',
    'triangulation = orbit_tracking.ros.triangulation_node:main',
    'estimator = orbit_tracking.ros.estimator_node:main',
    'results = orbit_tracking.ros.results_node:main',
    'orbit-tracking = orbit_tracking.tools.cli:main',
]

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', data('config/*.yaml')),
        ('share/' + package_name + '/config/scenarios', data('config/scenarios/*.yaml')),
        ('share/' + package_name + '/launch', data('launch/*.py')),
    ],
    install_requires=['setuptools'],
    python_requires='>=3.11',
    zip_safe=True,
    maintainer='orbit_tracking maintainers',
    maintainer_email='maintainers@orbit-tracking.dev',
    description='Trajectory estimation of flight vehicles from many tracking sensors (ROS 2).',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={'console_scripts': console_scripts},
)
