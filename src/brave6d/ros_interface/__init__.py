"""ROS interface stage: robot agents drive a served scene over ROS topics (issue #20).

Public API (lazy: ``import ros_interface`` loads neither torch nor any ROS library):

- the ROS-agnostic bridge over :class:`brave6d.serve.EpisodeManager` (:mod:`brave6d.ros_interface.bridge`):
  ``EpisodeBridge``, ``BridgeStep``, ``GroundTruthObject``, ``Estimate``, ``EpisodeResult``,
  ``BridgeError``;
- scoring a submission with BOP's AR (:mod:`brave6d.ros_interface.scoring`): ``EpisodeScorer``, ``EpisodeScore``;
- ROS conventions as numpy (:mod:`brave6d.ros_interface.frames`): ``FRAME_WORLD``, ``FRAME_CAMERA_OPTICAL``,
  ``GT_FRAME_PREFIX``, ``gt_frame``, ``matrix_to_pose``, ``pose_to_matrix`` (quaternions x, y, z, w),
  ``camera_info_arrays``, ``depth_to_rep118``, ``stamp_parts``;
- the benchmark's agents over ROS (:mod:`brave6d.ros_interface.episode_clients`): ``Ros2EpisodeClient``,
  ``Ros1EpisodeClient`` (``brave6d.evaluation.agents.EpisodeClient`` over the rclpy / rospy agent clients);
- the agents' interfaces wheel (:mod:`brave6d.ros_interface.ros2.interfaces`): ``build_ros2_interfaces_wheel``
  (writes ``brave6d_msgs`` as a pip wheel; needs the ROS 2 wheels, not ROS).

The nodes live in ``brave6d.ros_interface.ros1`` (rospy, ``brave6d ros1``) and ``brave6d.ros_interface.ros2``
(rclpy, ``brave6d ros2``); both build their messages from the bridge. See docs/ROS.md.
"""

from brave6d.core.lazy import lazy_exports

_LAZY = {
    "EpisodeBridge": ".bridge", "BridgeStep": ".bridge", "GroundTruthObject": ".bridge", "Estimate": ".bridge",
    "EpisodeResult": ".bridge", "BridgeError": ".bridge",
    "EpisodeScorer": ".scoring", "EpisodeScore": ".scoring",
    "FRAME_WORLD": ".frames", "FRAME_CAMERA_OPTICAL": ".frames", "GT_FRAME_PREFIX": ".frames",
    "gt_frame": ".frames", "matrix_to_pose": ".frames", "pose_to_matrix": ".frames",
    "camera_info_arrays": ".frames", "depth_to_rep118": ".frames", "stamp_parts": ".frames",
    "build_ros2_interfaces_wheel": ".ros2.interfaces",
    "Ros2EpisodeClient": ".episode_clients", "Ros1EpisodeClient": ".episode_clients",
}

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
