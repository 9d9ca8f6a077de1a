"""ROS 2 over DDS (``brave6d ros2``): the bridge's episodes as ROS 2 topics, spoken with Cyclone
DDS directly (no ``rclpy``), byte-compatible with ROS 2 Humble/Jazzy.

Modules, one job each: ``messages`` (ROS 2 message types as Cyclone DDS structs, rmw type names),
``dds`` (topic-name mangling, ROS 2 QoS profiles, a loopback-only domain), ``convert`` (bridge
values <-> messages), ``node`` (the node: topics table, command handling), ``agent`` (a Python
DDS agent of the node), ``example_agent`` (one episode end to end), ``cli`` (``brave6d ros2``).
Loaded only when used: importing this package loads no DDS library.
"""
