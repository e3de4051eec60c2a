"""ROS 2: the node, the message mapping, bags (see docs/ros2.md)."""
