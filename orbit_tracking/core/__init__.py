"""ROS-free numerical core: frames, dynamics, measurement models, simulation, estimation.

Nothing in this package imports ``rclpy`` or any ``*_msgs`` module.
"""
