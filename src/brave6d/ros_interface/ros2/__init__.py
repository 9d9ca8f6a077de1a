"""ROS 2 (``brave6d ros2``): the bridge's episodes as a real rclpy node (the ``ros2`` extra: ROS 2
Kilted wheels, Fast DDS), services for commands and standard topics for what each step shows.

Modules, one job each: ``interfaces`` (generates and installs ``brave6d_msgs`` and ``tf2_msgs`` with
the rosidl wheels), ``transport`` (where the node can be reached: loopback by default),
``convert`` (bridge values <-> rclpy messages), ``node`` (the node: services and topics table,
request checks), ``agent`` (a Python rclpy agent of the node), ``example_agent`` (the docs' minimal
agent, plain rclpy), ``cli`` (``brave6d ros2``). Loaded only when used: importing this package loads
no ROS library.
"""
