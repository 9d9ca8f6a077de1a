"""Open a robot + camera pair from command-line style names: ``sim`` or ``ur:HOST`` with ``sim`` or ``oak``.

The simulated pair is wired so that the camera sees the arm's *actual* pose (robot pose error,
trajectory at the image time) through the simulator's true hand-eye transform, while the runner
records what the robot *reports* — exactly the gap calibration and training must live with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from brave6d.core.errors import BraveError
from brave6d.core.spec import SceneSpec
from brave6d.capture.protocols import Camera, Robot


@dataclass
class Rig:
    """A connected robot and camera; close both with :meth:`close` (or use as a context manager)."""

    robot: Robot
    camera: Camera

    def close(self) -> None:
        try:
            self.camera.close()
        finally:
            self.robot.close()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_rig(spec: SceneSpec, robot: str = "sim", camera: str = "sim", *, board: bool = False,
             supersample: int | None = None) -> Rig:
    """Open the pair named by ``robot`` (``sim`` | ``ur:HOST``) and ``camera`` (``sim`` | ``oak``).

    ``board``: include the ChArUco board in the simulated scene (calibration capture).
    ``supersample``: simulated rays per pixel side. Default: 2 for the board (small markers need
    anti-aliasing to be detected at 0.5 m and grazing angles), else 1 with 3x3 rays on silhouette
    pixels only (about 1.5 % of the pixels: clean edges for training at almost no cost).
    """
    if robot == "sim" or camera == "sim":
        if (robot, camera) != ("sim", "sim"):
            raise BraveError(f"--robot {robot} --camera {camera}: the simulated camera renders the simulated "
                             "robot's true pose, so both must be 'sim' (or use a real pair: ur:HOST with oak)")
        return _open_sim(spec, board, supersample)
    if not robot.startswith("ur:") or not robot[3:]:
        raise BraveError(f"--robot {robot!r}: expected 'sim' or 'ur:HOST' (e.g. ur:192.168.1.10)")
    if camera != "oak":
        raise BraveError(f"--camera {camera!r}: expected 'sim' or 'oak'")
    from brave6d.capture.oak_camera import OakCamera
    from brave6d.capture.ur_robot import URRobot

    real_robot = URRobot(robot[3:], spec.robot)
    try:
        real_camera = OakCamera(width=spec.camera.width, height=spec.camera.height, depth=spec.capture.depth)
    except BaseException:
        real_robot.close()
        raise
    return Rig(real_robot, real_camera)


def _open_sim(spec: SceneSpec, board: bool, supersample: int | None) -> Rig:
    from brave6d.capture.sim_camera import SimCamera
    from brave6d.capture.sim_robot import SimRobot

    if spec.simulation is None:
        raise BraveError(f"{spec.source}: field 'simulation' is required for --robot sim --camera sim")
    tcp_T_cam = spec.simulation.true_tcp_T_camera.matrix()
    sim_robot = SimRobot(spec.robot, effects=spec.simulation.effects, seed=spec.simulation.seed)

    def true_world_T_cam(t: float) -> np.ndarray:
        return sim_robot.true_base_T_tcp(t) @ tcp_T_cam

    if supersample is None:
        supersample, edge = (2, 1) if board else (1, 3)
    else:
        edge = 1
    sim_camera = SimCamera.from_spec(spec, true_world_T_cam, sim_robot.now, calibration=board,
                                     supersample=supersample, edge_supersample=edge)
    return Rig(sim_robot, sim_camera)
