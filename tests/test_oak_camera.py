"""OakCamera on depthai's own objects: a ``dai.CalibrationHandler`` filled as an OAK-D stores its
calibration, real ``dai.ImgFrame`` messages, ``dai.CameraControl`` and ``dai.MessageQueue`` through a
host-only pipeline (``dai.Pipeline(createImplicitDevice=False)``) whose host node stands where the
OAK's sensor would be. What needs the device itself (its Camera and StereoDepth nodes) is checked
against the names depthai has; without a device the refusal is one line within seconds."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.capture.protocols import Camera, CameraError

dai = pytest.importorskip("depthai")

from brave6d.capture.oak_camera import OakCamera, factory_intrinsics  # noqa: E402

CAM_A = dai.CameraBoardSocket.CAM_A
K_FULL = [[3000.0, 0.0, 2030.0], [0.0, 3001.0, 1520.0], [0.0, 0.0, 1.0]]  # the IMX378's 4056 x 3040
DIST14 = [0.11, -0.3, 0.001, -0.002, 0.2, 0.05, -0.04, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
W, H, FPS = 160, 100, 30.0


def oak_calibration(camera_type: object = None, lens_position: int = 135) -> object:
    """CAM_A as an OAK-D stores it: intrinsics at the sensor's full resolution, the 14 coefficients of
    OpenCV's rational model, the perspective lens type and the lens position it was calibrated at."""
    calib = dai.CalibrationHandler()
    calib.setBoardInfo("OAK-D-PRO", "R3M2E3")
    calib.setProductName("OAK-D-PRO")
    calib.setCameraIntrinsics(CAM_A, K_FULL, 4056, 3040)
    calib.setDistortionCoefficients(CAM_A, DIST14)
    calib.setCameraType(CAM_A, dai.CameraModel.Perspective if camera_type is None else camera_type)
    calib.setLensPosition(CAM_A, lens_position)
    return calib


class Sensor(dai.node.ThreadedHostNode):
    """Where the OAK's sensor would be: real ImgFrames (BGR888i colour, RAW16 depth in mm) time-stamped
    on depthai's clock, with the exposure/ISO/lens position they were taken with; CameraControl
    messages take effect two frames later, as on the device."""

    def __init__(self) -> None:
        super().__init__()
        self.rgb = self.createOutput()
        self.depth = self.createOutput()
        self.control = self.createInput()
        self.ignores_controls = False
        self.stalled = False
        self.depth_skew_s = 0.0
        self.made = 0
        self.reports: list[dict[str, int]] = []
        self.controls: list[dict[str, int]] = []
        bgr = np.zeros((H, W, 3), np.uint8)
        bgr[..., 0], bgr[..., 1], bgr[..., 2] = 10, 20, 30  # B, G, R
        bgr[0, 0] = (1, 2, 3)
        self.bgr = bgr
        mm = np.full((H, W), 1234, np.uint16)
        mm[:10] = 0
        self.mm = mm

    def run(self) -> None:
        manual: dict[str, int] = {}
        pending: list[tuple[int, dict[str, int]]] = []
        while self.isRunning():
            if self.stalled:
                time.sleep(0.01)
                continue
            ctrl = self.control.tryGet()
            while ctrl is not None:
                sent = {"exposure_us": round(ctrl.getExposureTime().total_seconds() * 1e6),
                        "iso": int(ctrl.getSensitivity()), "lens_position": int(ctrl.getLensPosition())}
                sent = {k: v for k, v in sent.items() if v > 0}
                self.controls.append(sent)
                pending.append((self.made + 2, sent))
                ctrl = self.control.tryGet()
            for due, values in list(pending):
                if self.made >= due:
                    pending.remove((due, values))
                    if not self.ignores_controls:
                        manual.update(values)
            i = self.made
            settings = {"exposure_us": 8000 + 4000 // (i + 1), "iso": 400 + 200 // (i + 1),
                        "lens_position": 120 + 30 // (i + 1), **manual}
            self.reports.append(settings)
            start = dai.Clock.now()
            frame = dai.ImgFrame()
            frame.setCvFrame(self.bgr, dai.ImgFrame.Type.BGR888i)
            frame.setSequenceNum(i)
            cam = frame.cam
            cam.exposureTimeUs, cam.sensitivityIso = settings["exposure_us"], settings["iso"]
            cam.lensPosition, cam.wbColorTemp = settings["lens_position"], 5200
            frame.cam = cam
            exposure = frame.getExposureTime()
            time.sleep(exposure.total_seconds())  # the frame exists once its exposure has ended
            frame.setTimestamp(start + exposure)  # stamped at the end of the exposure, as the device does
            self.rgb.send(frame)
            depth = dai.ImgFrame()
            depth.setCvFrame(self.mm, dai.ImgFrame.Type.RAW16)
            depth.setSequenceNum(i)
            depth.setTimestamp(start + exposure / 2 + _td(self.depth_skew_s))
            self.depth.send(depth)
            self.made += 1
            time.sleep(max(0.0, 1.0 / FPS - exposure.total_seconds()))


def _td(seconds: float):  # noqa: ANN202
    from datetime import timedelta

    return timedelta(seconds=seconds)


class Rig:
    """A host-only pipeline with the sensor node, and the OakCamera on its outputs."""

    def __init__(self, depth: bool = True, calibration: object = None, ignores_controls: bool = False,
                 **kwargs: object) -> None:
        self.pipeline = dai.Pipeline(createImplicitDevice=False)
        self.sensor = self.pipeline.create(Sensor)
        self.sensor.ignores_controls = ignores_controls
        kwargs.setdefault("settle_frames", 5)
        self.camera = OakCamera.on_outputs(
            self.pipeline, calibration if calibration is not None else oak_calibration(), self.sensor.rgb,
            self.sensor.control, self.sensor.depth if depth else None, width=W, height=H, fps=FPS,
            serial="18443010C1", model="OAK-D-PRO", frame_timeout_s=1.0, lock_timeout_s=1.5, **kwargs)

    def close(self) -> None:
        self.camera.close()


@pytest.fixture
def rig() -> Rig:
    r = Rig()
    yield r
    r.close()


# ----------------------------------------------------------------------------- calibration
def test_factory_intrinsics_are_depthais_scaling_of_the_stored_calibration() -> None:
    calib = oak_calibration()
    cam = factory_intrinsics(calib, 640, 400, dai)
    s = 640 / 4056  # width-limited: 3040 * s = 479.7 rows, centre-cropped to 400 (the CROP resize mode)
    K = cam.K
    assert (cam.width, cam.height) == (640, 400)
    assert K[0, 0] == pytest.approx(3000 * s, rel=1e-6) and K[1, 1] == pytest.approx(3001 * s, rel=1e-6)
    assert K[0, 2] == pytest.approx(2030 * s, rel=1e-6)
    assert K[1, 2] == pytest.approx(1520 * s - (3040 * s - 400) / 2, rel=1e-6)
    assert cam.dist == pytest.approx(DIST14, abs=1e-7)  # stored as float32 on the device
    import cv2

    pts = np.array([[0.1, -0.05, 0.4], [-0.2, 0.1, 0.5]])
    expected, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.asarray(cam.dist))
    assert np.allclose(cam.project(pts).uv, expected.reshape(-1, 2))  # OpenCV's rational model, all 14


def test_a_fisheye_lens_is_refused() -> None:
    with pytest.raises(CameraError, match="perspective"):
        factory_intrinsics(oak_calibration(dai.CameraModel.Fisheye), 640, 400, dai)


# ----------------------------------------------------------------------------- through a host-only pipeline
def test_auto_settings_settle_then_lock_and_stay(rig: Rig) -> None:
    cam = rig.camera
    assert isinstance(cam, Camera)
    assert len(rig.sensor.controls) == 1  # one CameraControl: the values read after settling
    sent = rig.sensor.controls[0]
    assert sent["exposure_us"] == cam.settings["exposure_us"] and sent["iso"] == cam.settings["iso"]
    assert sent["lens_position"] == cam.settings["lens_position"]
    assert cam.settings["locked_from"] == {"exposure": "auto", "focus": "auto", "white_balance": "auto"}
    for _ in range(3):  # nothing drifts during the capture
        frame = cam.capture()
        assert (frame.extras["exposure_us"], frame.extras["iso"], frame.extras["lens_position"]) == \
            (sent["exposure_us"], sent["iso"], sent["lens_position"])


def test_capture_converts_bgr_to_rgb_and_depth_mm_to_m(rig: Rig) -> None:
    frame = rig.camera.capture()
    assert frame.rgb.dtype == np.uint8 and frame.rgb.shape == (H, W, 3) and frame.rgb.flags.c_contiguous
    assert tuple(frame.rgb[5, 5]) == (30, 20, 10) and tuple(frame.rgb[0, 0]) == (3, 2, 1)
    assert frame.depth_m is not None and frame.depth_m.dtype == np.float32
    assert frame.depth_m[50, 80] == pytest.approx(1.234) and np.all(frame.depth_m[:10] == 0)
    assert abs(frame.extras["depth_timestamp"] - frame.timestamp) < 1e-3


def test_a_frame_is_exposed_after_the_call_and_stamped_mid_exposure(rig: Rig) -> None:
    cam = rig.camera
    time.sleep(0.3)  # the queue (4 deep, non-blocking) now holds frames exposed before the call
    requested = cam.now()
    frame = cam.capture()
    exposure = frame.extras["exposure_us"] * 1e-6
    assert frame.timestamp - exposure / 2 >= requested  # its exposure started after the request
    assert frame.timestamp - exposure / 2 - requested < 3.0 / FPS  # and it is the first such frame
    assert frame.timestamp <= cam.now()  # on the clock of now(): depthai's steady clock


def test_manual_settings_need_no_settling() -> None:
    r = Rig(manual_exposure_us=5000, iso=200, manual_focus=110, manual_white_balance_k=5200, settle_frames=30)
    try:
        assert r.camera.settings["exposure_us"] == 5000 and r.camera.settings["lens_position"] == 110
        assert r.camera.settings["locked_from"] == {"exposure": "manual", "focus": "manual", "white_balance": "manual"}
        assert r.sensor.controls[0] == {"exposure_us": 5000, "iso": 200, "lens_position": 110}
        assert r.sensor.made < 20  # no 30-frame settling phase
    finally:
        r.close()


def test_focus_at_the_calibrated_lens_position() -> None:
    r = Rig(manual_focus="calibration")
    try:
        assert r.camera.settings["lens_position"] == 135 and r.camera.settings["calibration_lens_position"] == 135
        assert r.sensor.controls[0]["lens_position"] == 135
    finally:
        r.close()


def test_a_lock_that_never_takes_effect_is_an_error() -> None:
    with pytest.raises(CameraError, match="did not lock within 1.5 s"):
        Rig(ignores_controls=True)


def test_a_stalled_stream_times_out(rig: Rig) -> None:
    rig.sensor.stalled = True
    time.sleep(0.2)
    with pytest.raises(CameraError, match="no RGB frame within 1.0 s"):
        rig.camera.capture()


def test_depth_from_another_moment_is_refused(rig: Rig) -> None:
    rig.sensor.depth_skew_s = 0.5  # the depth frames belong to half a second later
    time.sleep(0.2)
    with pytest.raises(CameraError, match="no depth frame within"):
        rig.camera.capture()


def test_no_depth_means_no_depth_frame() -> None:
    r = Rig(depth=False)
    try:
        assert r.camera.capture().depth_m is None and not r.camera.depth
    finally:
        r.close()


def test_camera_json_records_intrinsics_serial_and_settings(rig: Rig, tmp_path: Path) -> None:
    path = rig.camera.write_camera_json(tmp_path / "capture" / "camera.json")
    data = json.loads(path.read_text())
    assert data["model"] == "OAK-D-PRO" and data["serial"] == "18443010C1"
    assert PinholeCamera.from_json(data["intrinsics"]) == rig.camera.intrinsics
    assert data["distortion"] == pytest.approx(DIST14, abs=1e-7) and data["distortion_model"] == "opencv_rational_14"
    assert data["settings"]["exposure_us"] == rig.camera.settings["exposure_us"]
    assert data["depth"] == {"enabled": True, "aligned_to": "CAM_A", "units": "m"}
    assert data["depthai_version"] == dai.__version__


def test_close_stops_the_pipeline_and_capture_refuses(rig: Rig) -> None:
    rig.camera.close()
    rig.camera.close()  # idempotent
    assert not rig.pipeline.isRunning()
    with pytest.raises(CameraError, match="after close"):
        rig.camera.capture()


# ----------------------------------------------------------------------------- the device's own part
def test_exposure_without_iso_is_refused() -> None:
    with pytest.raises(BraveError, match="together"):
        OakCamera(manual_exposure_us=5000)


def test_without_a_device_the_refusal_is_one_line_within_seconds() -> None:
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK is connected here")
    t0 = time.monotonic()
    with pytest.raises(CameraError, match="no OAK camera found") as err:
        OakCamera()
    assert time.monotonic() - t0 < 3.0  # not depthai's ~12 s of retrying
    assert "\n" not in str(err.value)


def test_the_device_path_calls_only_names_real_depthai_has() -> None:
    """The nodes only a device runs: every API the camera calls on them exists in this depthai."""
    for cls, names in {
        dai.node.Camera: ["build", "requestOutput", "initialControl", "inputControl"],
        dai.node.StereoDepth: ["build", "setDepthAlign", "setOutputSize", "setLeftRightCheck", "setSubpixel", "depth"],
        dai.CameraControl: ["setManualExposure", "setManualFocus", "setManualWhiteBalance"],
        dai.Pipeline: ["getDefaultDevice", "create", "start", "stop"],
        dai.Device: ["readCalibration", "getDeviceId", "getProductName", "getAllAvailableDevices"],
    }.items():
        missing = [n for n in names if not hasattr(cls, n)]
        assert not missing, f"{cls.__name__} lacks {missing}"
    assert hasattr(dai.ImgFrame.Type, "BGR888i") and hasattr(dai.ImgResizeMode, "CROP")
    assert hasattr(dai.node.StereoDepth.PresetMode, "DEFAULT")
    assert "enableUndistortion" in (dai.node.Camera.requestOutput.__doc__ or "")

