"""The minimal ROS 2 agent of docs/ROS.md: plain rclpy and the node's own interfaces, nothing else
from brave6d. Against ``brave6d ros2 BUNDLE`` on this machine, with no ROS variable set:

    python -m brave6d.ros_interface.ros2.example_agent      # or copy this file and run it

It resets, waits for the first view's images (RGB and depth, sensor-data QoS), backs off 5 cm
along the optical axis with one ``move``, then submits the target's pose taken from its
ground-truth tf frame ``gt/<name>_<gt_id>``: an oracle that shows the plumbing, not a pose
estimator (a real agent estimates from the images). The node publishes ``gt/`` frames only in
training mode: run it as ``brave6d ros2 BUNDLE --training`` for this agent (in the default, scored
mode it stops, saying so). Prints the scored result as JSON.
"""

import json
import sys
import time

import numpy as np
import rclpy
from brave6d_msgs.msg import ObjectEstimate
from brave6d_msgs.srv import Move, Reset, Submit
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
from tf2_msgs.msg import TFMessage

NS = "/brave6d_sim"


def matrix(t, q):
    """4x4 from a translation (x, y, z) and a unit quaternion (x, y, z, w)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = [t.x, t.y, t.z]
    return T


def quaternion(R):
    """A rotation matrix's unit quaternion (x, y, z, w), stable for every rotation (largest term first)."""
    w2, x2, y2, z2 = (1 + R[0, 0] + R[1, 1] + R[2, 2], 1 + R[0, 0] - R[1, 1] - R[2, 2],
                      1 - R[0, 0] + R[1, 1] - R[2, 2], 1 - R[0, 0] - R[1, 1] + R[2, 2])
    big = max(w2, x2, y2, z2)
    s = 2 * np.sqrt(big)
    if big == w2:
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif big == x2:
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif big == y2:
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q) / np.linalg.norm(q)
    return tuple(float(v) for v in q)


def main() -> int:
    rclpy.init()
    node = rclpy.create_node("minimal_agent")
    seen = {}  # (sec, nanosec) stamp -> {"rgb": Image, "depth": Image, "tf": {frame: 4x4}}

    def keep(part, stamp, value):
        seen.setdefault((stamp.sec, stamp.nanosec), {})[part] = value

    node.create_subscription(Image, f"{NS}/rgb/image_raw", lambda m: keep("rgb", m.header.stamp, m),
                             qos_profile_sensor_data)
    node.create_subscription(Image, f"{NS}/depth/image_raw", lambda m: keep("depth", m.header.stamp, m),
                             qos_profile_sensor_data)
    node.create_subscription(TFMessage, "/tf", lambda m: keep("tf", m.transforms[0].header.stamp, {
        t.child_frame_id: matrix(t.transform.translation, t.transform.rotation) for t in m.transforms}), 100)

    clients = {name: node.create_client(srv_type, f"{NS}/{name}")
               for name, srv_type in (("reset", Reset), ("move", Move), ("submit", Submit))}
    for name, client in clients.items():
        if not client.wait_for_service(timeout_sec=30.0):
            raise SystemExit(f"no service {NS}/{name}: is 'brave6d ros2 BUNDLE' running?")
    # a service can be listed a moment before its answers reach this client (DDS matches the reply
    # channel separately): let discovery settle before the first request
    settle = time.monotonic() + 1.0
    while time.monotonic() < settle:
        rclpy.spin_once(node, timeout_sec=0.1)

    def call(name, request, timeout_s=60.0):
        future = clients[name].call_async(request)
        rclpy.spin_until_future_complete(node, future, timeout_sec=timeout_s)
        response = future.result()
        if response is None or not response.success:
            raise SystemExit(f"{name} refused: {getattr(response, 'message', 'no answer')}")
        return response

    def view(step):
        """The images and tf the node published under the step's stamp (they come before its answer)."""
        key = (step.stamp.sec, step.stamp.nanosec)
        deadline = time.monotonic() + 30.0
        while len(seen.get(key, {})) < 3:
            if time.monotonic() > deadline:
                raise SystemExit(f"step {step.step}: images or tf did not arrive")
            rclpy.spin_once(node, timeout_sec=0.1)
        return seen[key]

    first = call("reset", Reset.Request()).step
    if not first.target_frame:  # a scored node publishes no ground truth (its next reset closes this episode)
        raise SystemExit("this oracle reads the target's gt/ frame on /tf, which the node publishes only in "
                         "training mode: start it with 'brave6d ros2 BUNDLE --training'")
    images = view(first)
    rgb = np.frombuffer(images["rgb"].data, np.uint8).reshape(images["rgb"].height, images["rgb"].width, 3)
    print(f"episode {first.episode_id}: target {first.target_frame}, image {rgb.shape[1]}x{rgb.shape[0]}",
          file=sys.stderr)
    request = Move.Request(duration=1.0)
    request.twist.twist.linear.z = -0.05  # back off 5 cm/s for 1 s along the optical axis
    step = call("move", request).step
    tf = view(step)["tf"]
    cam_T_obj = np.linalg.inv(tf["brave6d_camera_optical_frame"]) @ tf[step.target_frame]
    estimate = ObjectEstimate(obj_id=step.target_obj_id, score=1.0)
    estimate.pose.position.x, estimate.pose.position.y, estimate.pose.position.z = map(float, cam_T_obj[:3, 3])
    o = estimate.pose.orientation
    o.x, o.y, o.z, o.w = quaternion(cam_T_obj[:3, :3])
    result = call("submit", Submit.Request(estimates=[estimate]))
    print(json.dumps(json.loads(result.result_json), indent=2))
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
