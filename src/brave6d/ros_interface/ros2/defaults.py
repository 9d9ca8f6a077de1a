"""Defaults of the ROS 2 node, importable without rclpy (``brave6d ros2 --help`` stays light).
They mirror the ROS 1 node's: the node name as the namespace, a 10 Hz twist."""

#: Namespace of the node's services and topics (ROS 1's private names ``~x`` of node ``brave6d_sim``).
DEFAULT_NAMESPACE = "/brave6d_sim"
#: Seconds a ``move`` with ``duration: 0`` lasts (ROS 1's ``cmd_twist`` default too: a 10 Hz control loop).
DEFAULT_TWIST_DURATION_S = 0.1
