"""Thin ROS 2 nodes and the message conversions they share."""
