"""OakCamera against a fake depthai module that simulates an OAK device and records the pipeline."""

from __future__ import annotations

import json
from datetime import timedelta
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.capture.oak_camera import OakCamera
from brave6d.capture.protocols import Camera, CameraError

K_FULL = [[3000.0, 0.0, 2030.0], [0.0, 3001.0, 1520.0], [0.0, 0.0, 1.0]]  # 4056 x 3040 sensor
DIST14 = [0.11, -0.3, 0.001, -0.002, 0.2, 0.05, -0.04, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]


def _socket_enum() -> SimpleNamespace:
    return SimpleNamespace(CAM_A="CAM_A", CAM_B="CAM_B", CAM_C="CAM_C")


class FakeControl:
    """dai.CameraControl: records the manual settings it carries."""

    def __init__(self) -> None:
        self.values: dict[str, Any] = {}

    def setManualExposure(self, exposure_us: int, iso: int) -> FakeControl:  # noqa: N802 (depthai names)
        self.values.update(exposure_us=exposure_us, iso=iso)
        return self

    def setManualFocus(self, lens: int) -> FakeControl:  # noqa: N802
        self.values["lens_position"] = lens
        return self

    def setManualWhiteBalance(self, kelvin: int) -> FakeControl:  # noqa: N802
        self.values["white_balance_k"] = kelvin
        return self


class FakeFrame:
    def __init__(self, dai: FakeDai, t: float, settings: dict[str, Any], data: np.ndarray, seq: int) -> None:
        self._dai, self.t, self.settings, self.data, self.seq = dai, t, dict(settings), data, seq

    def getTimestamp(self, offset: str | None = None) -> timedelta:  # noqa: N802
        half = self.settings["exposure_us"] * 1e-6 / 2
        shift = {"START": -half, "MIDDLE": 0.0, "END": half, None: half}[offset]
        return timedelta(seconds=self.t + shift)

    def getExposureTime(self) -> timedelta:  # noqa: N802
        return timedelta(microseconds=self.settings["exposure_us"])

    def getSensitivity(self) -> int:  # noqa: N802
        return self.settings["iso"]

    def getLensPosition(self) -> int:  # noqa: N802
        return self.settings["lens_position"]

    def getColorTemperature(self) -> int:  # noqa: N802
        return self.settings["white_balance_k"]

    def getSequenceNum(self) -> int:  # noqa: N802
        return self.seq

    def getCvFrame(self) -> np.ndarray:  # noqa: N802
        return self.data.copy()

    def getFrame(self) -> np.ndarray:  # noqa: N802
        return self.data.copy()


class FakeQueue:
    def __init__(self, produce: Any) -> None:
        self.produce = produce
        self.backlog: list[FakeFrame] = []
        self.sent: list[FakeControl] = []

    def tryGet(self) -> FakeFrame | None:  # noqa: N802
        return self.backlog.pop(0) if self.backlog else self.produce()

    def send(self, msg: FakeControl) -> None:
        self.sent.append(msg)


class FakeOutput:
    def __init__(self, queue: FakeQueue) -> None:
        self.queue = queue

    def createOutputQueue(self, maxSize: int = 16, blocking: bool = False) -> FakeQueue:  # noqa: N802, N803
        return self.queue


class FakeCameraNode:
    def __init__(self, dai: FakeDai) -> None:
        self.dai = dai
        self.initialControl = FakeControl()
        self.socket: str | None = None
        self.requests: list[dict[str, Any]] = []
        self.control_queue = FakeQueue(lambda: None)
        self.inputControl = SimpleNamespace(createInputQueue=lambda *a, **k: self.control_queue)

    def build(self, socket: str) -> FakeCameraNode:
        self.socket = socket
        return self

    def requestOutput(self, size: tuple[int, int], type: Any = None, resizeMode: Any = None,  # noqa: N802, N803, A002
                      fps: float | None = None, enableUndistortion: bool | None = None) -> FakeOutput:  # noqa: N803
        self.requests.append({"size": size, "type": type, "resizeMode": resizeMode, "fps": fps,
                              "enableUndistortion": enableUndistortion})
        return FakeOutput(self.dai.rgb_queue)


class FakeStereo:
    PresetMode = SimpleNamespace(DEFAULT="DEFAULT")

    def __init__(self, dai: FakeDai) -> None:
        self.config: dict[str, Any] = {}
        self.depth = FakeOutput(dai.depth_queue)

    def build(self, **kwargs: Any) -> FakeStereo:
        self.config["build"] = kwargs
        return self

    def setDepthAlign(self, socket: str) -> None:  # noqa: N802
        self.config["align"] = socket

    def setOutputSize(self, w: int, h: int) -> None:  # noqa: N802
        self.config["output_size"] = (w, h)

    def setLeftRightCheck(self, on: bool) -> None:  # noqa: N802
        self.config["lr_check"] = on

    def setSubpixel(self, on: bool) -> None:  # noqa: N802
        self.config["subpixel"] = on


class FakeCalibration:
    def __init__(self, dai: FakeDai) -> None:
        self.dai = dai
        self.intrinsics_calls: list[tuple[Any, ...]] = []

    def getCameraIntrinsics(self, socket: str, w: int, h: int) -> list[list[float]]:  # noqa: N802
        self.intrinsics_calls.append((socket, w, h))
        # Scale the 4056x3040 calibration to w x h with a centre crop (keepAspectRatio), like depthai.
        s = max(w / 4056, h / 3040)
        crop_x, crop_y = (4056 * s - w) / 2, (3040 * s - h) / 2
        k = np.array(K_FULL)
        return [[k[0, 0] * s, 0.0, k[0, 2] * s - crop_x], [0.0, k[1, 1] * s, k[1, 2] * s - crop_y], [0, 0, 1]]

    def getDistortionCoefficients(self, socket: str) -> list[float]:  # noqa: N802
        return list(DIST14)

    def getDistortionModel(self, socket: str) -> str:  # noqa: N802
        return self.dai.lens_model

    def getLensPosition(self, socket: str) -> int:  # noqa: N802
        return 135


class FakePipeline:
    def __init__(self, dai: FakeDai) -> None:
        self.dai = dai
        self.nodes: list[Any] = []
        self.started = self.stopped = False
        self.device = SimpleNamespace(readCalibration=lambda: dai.calibration, getDeviceId=lambda: "18443010C1",
                                      getProductName=lambda: "OAK-D-PRO")

    def getDefaultDevice(self) -> Any:  # noqa: N802
        return self.device

    def create(self, cls: Any) -> Any:
        node = cls(self.dai)
        self.nodes.append(node)
        return node

    def start(self) -> None:
        self.started = True

    def stop(self) -> None:
        self.stopped = True


class FakeDai:
    """A fake ``depthai`` module: one OAK whose auto exposure/focus settle over the first frames."""

    __version__ = "3.12.0-fake"

    def __init__(self, *, devices: bool = True, width: int = 640, height: int = 400, fps: float = 10.0,
                 lens_model: str = "Perspective", stall_after: int | None = None, ignores_controls: bool = False) -> None:
        self.devices, self.width, self.height, self.fps = devices, width, height, fps
        self.lens_model, self.stall_after, self.ignores_controls = lens_model, stall_after, ignores_controls
        self.time = 100.0
        self.frames_made = 0
        self.depth_made = 0
        self.auto_reports: list[dict[str, Any]] = []
        self.manual: dict[str, Any] = {}
        self.pending: list[tuple[int, dict[str, Any]]] = []
        self.CameraBoardSocket = _socket_enum()
        self.ImgFrame = SimpleNamespace(Type=SimpleNamespace(BGR888i="BGR888i", RGB888i="RGB888i", NV12="NV12"))
        self.ImgResizeMode = SimpleNamespace(CROP="CROP", STRETCH="STRETCH", LETTERBOX="LETTERBOX")
        self.CameraExposureOffset = SimpleNamespace(START="START", MIDDLE="MIDDLE", END="END")
        self.CameraModel = SimpleNamespace(Perspective="Perspective", Fisheye="Fisheye")
        self.CameraControl = FakeControl
        self.Clock = SimpleNamespace(now=lambda: timedelta(seconds=self.time))
        self.node = SimpleNamespace(Camera=FakeCameraNode, StereoDepth=FakeStereo)
        self.calibration = FakeCalibration(self)
        self.rgb_queue = FakeQueue(self._rgb)
        self.depth_queue = FakeQueue(self._depth)
        self.pipeline: FakePipeline | None = None
        bgr = np.zeros((height, width, 3), np.uint8)
        bgr[..., 0], bgr[..., 1], bgr[..., 2] = 10, 20, 30  # B, G, R
        bgr[0, 0] = (1, 2, 3)
        self.bgr = bgr
        mm = np.full((height, width), 1234, np.uint16)
        mm[:10] = 0
        self.depth_mm = mm

    def Pipeline(self) -> FakePipeline:  # noqa: N802
        if not self.devices:
            raise RuntimeError("No available devices")
        self.pipeline = FakePipeline(self)
        return self.pipeline

    @property
    def camera_node(self) -> FakeCameraNode:
        assert self.pipeline is not None
        return next(n for n in self.pipeline.nodes if isinstance(n, FakeCameraNode))

    def _settings(self) -> dict[str, Any]:
        initial = self.camera_node.initialControl.values
        i = self.frames_made
        auto = {"exposure_us": 8000 + 4000 // (i + 1), "iso": 400 + 200 // (i + 1), "lens_position": 120 + 30 // (i + 1),
                "white_balance_k": 4500 + 500 // (i + 1)}
        for sent in self.camera_node.control_queue.sent[len(self.pending):]:
            self.pending.append((i + 2, sent.values))  # controls act two frames later
        for due, values in self.pending:
            if i >= due and not self.ignores_controls:
                self.manual.update(values)
        return {**auto, **initial, **self.manual}

    def _rgb(self) -> FakeFrame | None:
        if self.stall_after is not None and self.frames_made >= self.stall_after:
            return None
        self.time += 1.0 / self.fps
        settings = self._settings()
        self.auto_reports.append(settings)
        self.frames_made += 1
        return FakeFrame(self, self.time, settings, self.bgr, self.frames_made)

    def _depth(self) -> FakeFrame | None:
        if self.depth_made >= self.frames_made:
            return None
        self.depth_made += 1
        t = 100.0 + self.depth_made / self.fps
        return FakeFrame(self, t, {"exposure_us": 0, "iso": 0, "lens_position": -1, "white_balance_k": 0},
                         self.depth_mm, self.depth_made)


def open_camera(fake: FakeDai, **kwargs: Any) -> OakCamera:
    kwargs.setdefault("settle_frames", 5)
    return OakCamera(fake.width, fake.height, dai_module=fake, fps=fake.fps, frame_timeout_s=0.5,
                     lock_timeout_s=0.5, **kwargs)


# ----------------------------------------------------------------------------- tests
def test_pipeline_requests_rgb_size_type_and_aligned_depth() -> None:
    fake = FakeDai()
    cam = open_camera(fake)
    assert isinstance(cam, Camera)
    node = fake.camera_node
    assert node.socket == "CAM_A"
    assert node.requests == [{"size": (640, 400), "type": "BGR888i", "resizeMode": "CROP", "fps": 10.0,
                              "enableUndistortion": False}]
    stereo = next(n for n in fake.pipeline.nodes if isinstance(n, FakeStereo))  # type: ignore[union-attr]
    assert stereo.config["align"] == "CAM_A"
    assert stereo.config["output_size"] == (640, 400)
    assert fake.pipeline.started  # type: ignore[union-attr]
    cam.close()
    assert fake.pipeline.stopped  # type: ignore[union-attr]
    cam.close()  # idempotent


def test_no_depth_means_no_stereo_node() -> None:
    fake = FakeDai()
    cam = open_camera(fake, depth=False)
    assert not any(isinstance(n, FakeStereo) for n in fake.pipeline.nodes)  # type: ignore[union-attr]
    assert cam.capture().depth_m is None


def test_auto_settings_are_read_after_settling_and_locked() -> None:
    fake = FakeDai()
    cam = open_camera(fake, settle_frames=5)
    sent = fake.camera_node.control_queue.sent
    assert len(sent) == 1
    settled = fake.auto_reports[4]  # the 5th frame is the last one of the settling phase
    assert sent[0].values == settled
    assert fake.camera_node.initialControl.values == {}
    assert {k: cam.settings[k] for k in settled} == settled
    assert cam.settings["locked_from"] == {"exposure": "auto", "focus": "auto", "white_balance": "auto"}
    # Every frame after the lock reports the locked values: nothing drifts during the capture.
    for _ in range(3):
        frame = cam.capture()
        assert {k: frame.extras[k] for k in settled} == settled


def test_manual_settings_go_into_initial_control() -> None:
    fake = FakeDai()
    cam = open_camera(fake, manual_exposure_us=5000, iso=200, manual_focus=110, manual_white_balance_k=5200,
                      settle_frames=30)
    assert fake.camera_node.initialControl.values == {"exposure_us": 5000, "iso": 200, "lens_position": 110,
                                                      "white_balance_k": 5200}
    assert fake.camera_node.control_queue.sent == []  # nothing left to lock
    assert cam.settings["exposure_us"] == 5000 and cam.settings["lens_position"] == 110
    assert fake.frames_made <= 4  # no 30-frame settling phase: one frame, then the 3-frame lock check


def test_focus_at_the_calibrated_lens_position() -> None:
    fake = FakeDai()
    cam = open_camera(fake, manual_focus="calibration")
    assert fake.camera_node.initialControl.values == {"lens_position": 135}
    assert cam.settings["lens_position"] == 135 and cam.settings["calibration_lens_position"] == 135
    assert fake.camera_node.control_queue.sent[0].values["lens_position"] == 135


def test_exposure_without_iso_is_refused() -> None:
    with pytest.raises(BraveError, match="together"):
        OakCamera(manual_exposure_us=5000, dai_module=FakeDai())


def test_lock_that_never_takes_effect_is_an_error() -> None:
    fake = FakeDai(ignores_controls=True)
    with pytest.raises(CameraError, match="did not lock"):
        open_camera(fake)
    assert fake.pipeline.stopped  # type: ignore[union-attr]


def test_factory_intrinsics_are_converted_for_the_output_size() -> None:
    fake = FakeDai()
    cam = open_camera(fake)
    assert fake.calibration.intrinsics_calls == [("CAM_A", 640, 400)]
    K = cam.intrinsics.K
    s = 640 / 4056  # width-limited scale; 3040 * s = 479.7 rows, centre-cropped to 400
    assert cam.intrinsics.width == 640 and cam.intrinsics.height == 400
    assert K[0, 0] == pytest.approx(3000 * s) and K[1, 1] == pytest.approx(3001 * s)
    assert K[0, 2] == pytest.approx(2030 * s) and K[1, 2] == pytest.approx(1520 * s - (3040 * s - 400) / 2)
    assert cam.intrinsics.dist == tuple(DIST14)
    # The distortion really is OpenCV's rational model: projection matches cv2 with these coefficients.
    import cv2

    pts = np.array([[0.1, -0.05, 0.4], [-0.2, 0.1, 0.5]])
    expected, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.array(DIST14))
    assert np.allclose(cam.intrinsics.project(pts).uv, expected.reshape(-1, 2))


def test_fisheye_lens_is_refused() -> None:
    with pytest.raises(CameraError, match="perspective"):
        open_camera(FakeDai(lens_model="Fisheye"))


def test_capture_converts_bgr_to_rgb_and_depth_mm_to_m() -> None:
    fake = FakeDai()
    cam = open_camera(fake)
    frame = cam.capture()
    assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (400, 640, 3) and frame.rgb.flags.c_contiguous
    assert tuple(frame.rgb[5, 5]) == (30, 20, 10) and tuple(frame.rgb[0, 0]) == (3, 2, 1)
    assert frame.depth_m is not None and frame.depth_m.dtype == np.float32
    assert frame.depth_m[200, 300] == pytest.approx(1.234) and np.all(frame.depth_m[:10] == 0)
    assert abs(frame.extras["depth_timestamp"] - frame.timestamp) <= 0.5 / fake.fps + 0.01


def test_capture_skips_frames_exposed_before_the_call() -> None:
    fake = FakeDai()
    cam = open_camera(fake)
    stale = [FakeFrame(fake, fake.time - 0.5 + 0.1 * i, fake._settings(), fake.bgr, -1) for i in range(3)]
    fake.rgb_queue.backlog.extend(stale)
    requested = fake.time
    frame = cam.capture()
    assert frame.extras["sequence_num"] != -1
    exposure = frame.extras["exposure_us"] * 1e-6
    assert frame.timestamp - exposure / 2 >= requested  # exposure started after the request
    assert frame.timestamp == pytest.approx(cam.now())  # time stamp = mid-exposure, on now()'s clock


def test_no_device_gives_a_clear_camera_error() -> None:
    with pytest.raises(CameraError, match="no OAK camera found"):
        OakCamera(dai_module=FakeDai(devices=False))


def test_stalled_stream_times_out() -> None:
    fake = FakeDai()
    cam = open_camera(fake)
    fake.stall_after = fake.frames_made
    with pytest.raises(CameraError, match="no RGB frame"):
        cam.capture()


def test_camera_json_records_intrinsics_serial_and_settings(tmp_path: Path) -> None:
    fake = FakeDai()
    cam = open_camera(fake)
    path = cam.write_camera_json(tmp_path / "capture" / "camera.json")
    data = json.loads(path.read_text())
    assert data["model"] == "OAK-D-PRO" and data["serial"] == "18443010C1"
    assert PinholeCamera.from_json(data["intrinsics"]) == cam.intrinsics
    assert data["distortion"] == DIST14 and data["distortion_model"] == "opencv_rational_14"
    assert data["settings"]["exposure_us"] == cam.settings["exposure_us"]
    assert data["settings"]["lens_position"] == cam.settings["lens_position"]
    assert data["depth"] == {"enabled": True, "aligned_to": "CAM_A", "units": "m"}


def test_fake_only_uses_names_that_real_depthai_has() -> None:
    """Guards the fake against drifting from depthai 3.x: every API the camera calls exists."""
    dai = pytest.importorskip("depthai")
    for cls, names in {
        dai.node.Camera: ["build", "requestOutput", "initialControl", "inputControl"],
        dai.node.StereoDepth: ["build", "setDepthAlign", "setOutputSize", "setLeftRightCheck", "setSubpixel", "depth"],
        dai.CameraControl: ["setManualExposure", "setManualFocus", "setManualWhiteBalance"],
        dai.ImgFrame: ["getTimestamp", "getExposureTime", "getSensitivity", "getLensPosition",
                       "getColorTemperature", "getSequenceNum", "getCvFrame", "getFrame"],
        dai.CalibrationHandler: ["getCameraIntrinsics", "getDistortionCoefficients", "getDistortionModel",
                                 "getLensPosition"],
        dai.Pipeline: ["getDefaultDevice", "create", "start", "stop"],
        dai.MessageQueue: ["tryGet"],
        dai.Device: ["readCalibration", "getDeviceId", "getProductName"],
    }.items():
        missing = [n for n in names if not hasattr(cls, n)]
        assert not missing, f"{cls.__name__} lacks {missing}"
    assert hasattr(dai.ImgFrame.Type, "BGR888i") and hasattr(dai.ImgResizeMode, "CROP")
    assert hasattr(dai.CameraExposureOffset, "MIDDLE") and hasattr(dai.CameraModel, "Perspective")
    assert hasattr(dai.node.StereoDepth.PresetMode, "DEFAULT") and hasattr(dai.Clock, "now")
    assert "enableUndistortion" in (dai.node.Camera.requestOutput.__doc__ or "")


@pytest.mark.slow
def test_real_depthai_without_device_gives_camera_error() -> None:
    """The real depthai (no device on CI) must end in our clear CameraError (takes ~12 s)."""
    with pytest.raises(CameraError, match="no OAK camera found"):
        OakCamera()
