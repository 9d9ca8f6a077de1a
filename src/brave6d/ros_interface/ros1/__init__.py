"""ROS 1 (rospy, Debian's packages) for the bridge: ``brave6d ros1`` and its agents.

Modules, one job each: ``ros_env`` (reaching Debian's ROS 1: dist-packages appended to sys.path,
missing packages named), ``messages`` (the ``brave6d_msgs`` types generated with genpy, no catkin),
``convert`` (bridge values <-> ROS messages), ``node`` (the ``brave6d_sim`` node), ``cli``
(``brave6d ros1``), ``master`` (a loopback rosmaster for runs, tests and benchmarks), ``client``
(an agent's blocking calls, and replaying a list of actions), ``example_agent``. Nothing here is
imported by ``import ros_interface``; rospy loads only inside these modules' functions.
"""
