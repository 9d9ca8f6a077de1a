"""Open a robot + camera pair from command-line style names: ``sim`` or ``ur:HOST`` with ``sim`` or ``oak``.

The simulated pair is wired so that the camera sees the arm's *actual* pose (robot pose error,
trajectory at the image time) through the simulator's true hand-eye transform, while the runner
records what the robot *reports* — exactly the gap calibration and training must live with.

The rehearsal pair, ``ur:HOST`` with ``sim``, is the real client (ur-rtde, :class:`URRobot`) driving
``brave6d ur-emulator`` at HOST, and a simulated camera that renders from the pose the EMULATOR
holds (asked over its side channel at the image time, on the controller's clock): the emulator is
the truth, the project records what ur-rtde reports. It refuses a HOST without that side channel,
so a simulated camera is never paired with a real arm.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from brave6d.core.errors import BraveError
from brave6d.core.spec import SceneSpec
from brave6d.capture.protocols import Camera, Robot


@dataclass
class Rig:
    """A connected robot and camera; close both with :meth:`close` (or use as a context manager)."""

    robot: Robot
    camera: Camera
    #: what else the pair holds open (the rehearsal camera's link to the emulator)
    closers: tuple[Callable[[], None], ...] = field(default=())

    def close(self) -> None:
        try:
            self.camera.close()
        finally:
            try:
                self.robot.close()
            finally:
                for close in self.closers:
                    close()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_rig(spec: SceneSpec, robot: str = "sim", camera: str = "sim", *, board: bool = False,
             supersample: int | None = None) -> Rig:
    """Open the pair named by ``robot`` (``sim`` | ``ur:HOST``) and ``camera`` (``sim`` | ``oak``):
    sim + sim, ur:HOST + oak (the lab), or ur:HOST + sim (a rehearsal against ``brave6d ur-emulator``).

    ``board``: include the ChArUco board in the simulated scene (calibration capture).
    ``supersample``: simulated rays per pixel side. Default: 2 for the board (small markers need
    anti-aliasing to be detected at 0.5 m and grazing angles), else 1 with 3x3 rays on silhouette
    pixels only (about 1.5 % of the pixels: clean edges for training at almost no cost).
    """
    if robot != "sim" and (not robot.startswith("ur:") or not robot[3:]):
        raise BraveError(f"--robot {robot!r}: expected 'sim' or 'ur:HOST' (e.g. ur:192.168.1.10)")
    if camera not in ("sim", "oak"):
        raise BraveError(f"--camera {camera!r}: expected 'sim' or 'oak'")
    if robot == "sim":
        if camera != "sim":
            raise BraveError(f"--robot sim --camera {camera}: a real camera cannot see the simulated robot; use "
                             "--camera sim, or a real pair (ur:HOST with oak)")
        return _open_sim(spec, board, supersample)
    if camera == "sim":
        return _open_rehearsal(spec, robot[3:], board, supersample)
    from brave6d.capture.oak_camera import OakCamera
    from brave6d.capture.ur_robot import URRobot

    real_robot = URRobot(robot[3:], spec.robot)
    try:
        real_camera = OakCamera(width=spec.camera.width, height=spec.camera.height, depth=spec.capture.depth)
    except BaseException:
        real_robot.close()
        raise
    return Rig(real_robot, real_camera)


def _supersampling(board: bool, supersample: int | None) -> tuple[int, int]:
    """(rays per pixel side, rays per side on silhouette pixels); see :func:`open_rig`."""
    if supersample is None:
        return (2, 1) if board else (1, 3)
    return supersample, 1


def _open_rehearsal(spec: SceneSpec, host: str, board: bool, supersample: int | None) -> Rig:
    from brave6d.capture.sim_camera import SimCamera
    from brave6d.capture.ur_emulator.link import EmulatorLink, EmulatorLinkError
    from brave6d.capture.ur_emulator.servers import check_loopback
    from brave6d.capture.ur_robot import URRobot

    if spec.simulation is None:
        raise BraveError(f"{spec.source}: field 'simulation' is required for --camera sim (the simulated camera's "
                         "scene and true mounting)")
    try:
        check_loopback(host)
    except BraveError:
        raise BraveError(f"--robot ur:{host} --camera sim: a simulated camera cannot film a real arm (the lab pair is "
                         "--camera oak); rehearse against a UR emulator on a loopback address: brave6d ur-emulator "
                         "--address 127.0.0.2") from None
    link = EmulatorLink(host, timeout_s=2.0)
    try:
        status = link.status()
    except EmulatorLinkError:
        link.close()
        raise BraveError(f"--robot ur:{host} --camera sim: no brave6d UR emulator answers at {host} (start one with "
                         f"'brave6d ur-emulator --address {host} --spec SCENE'); a simulated camera cannot film a "
                         "real arm") from None
    if status.get("model") != spec.robot.model:
        link.close()
        raise BraveError(f"--robot ur:{host}: the emulator there is a {str(status.get('model')).upper()}, the spec's "
                         f"robot.model is {spec.robot.model} (start it with --spec SCENE or "
                         f"--model {spec.robot.model})")
    try:
        robot = URRobot(host, spec.robot)
    except BaseException:
        link.close()
        raise
    flange_T_cam = spec.simulation.true_tcp_T_camera.matrix()  # URRobot sets the controller's TCP to the flange

    def true_world_T_cam(t: float) -> np.ndarray:
        return link.true_base_T_flange(t) @ flange_T_cam

    try:
        ss, edge = _supersampling(board, supersample)
        camera = SimCamera.from_spec(spec, true_world_T_cam, link.now, calibration=board, supersample=ss,
                                     edge_supersample=edge)
    except BaseException:
        robot.close()
        link.close()
        raise
    return Rig(robot, camera, closers=(link.close,))


def _open_sim(spec: SceneSpec, board: bool, supersample: int | None) -> Rig:
    from brave6d.capture.sim_camera import SimCamera
    from brave6d.capture.sim_robot import SimRobot

    if spec.simulation is None:
        raise BraveError(f"{spec.source}: field 'simulation' is required for --robot sim --camera sim")
    tcp_T_cam = spec.simulation.true_tcp_T_camera.matrix()
    sim_robot = SimRobot(spec.robot, effects=spec.simulation.effects, seed=spec.simulation.seed)

    def true_world_T_cam(t: float) -> np.ndarray:
        return sim_robot.true_base_T_tcp(t) @ tcp_T_cam

    ss, edge = _supersampling(board, supersample)
    sim_camera = SimCamera.from_spec(spec, true_world_T_cam, sim_robot.now, calibration=board,
                                     supersample=ss, edge_supersample=edge)
    return Rig(sim_robot, sim_camera)
