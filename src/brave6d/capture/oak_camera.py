"""Luxonis OAK camera on depthai v3, behind the :class:`~brave6d.capture.protocols.Camera` protocol.

What the capture needs from the real camera, and how it is done:

* RGB from ``CAM_A`` at the chosen size: ``Camera.requestOutput((w, h), BGR888i, CROP,
  fps, enableUndistortion=False)`` -- raw images, so they carry the lens distortion that the
  factory coefficients (and later the ChArUco calibration) describe. Converted to RGB.
* optional stereo depth aligned to RGB: ``StereoDepth`` (auto-created mono cameras) with
  ``setDepthAlign(CAM_A)`` and ``setOutputSize(w, h)``; uint16 millimetres -> float32 metres.
* focus, exposure and white balance LOCKED for the whole capture, so intrinsics (focus moves
  the lens) and colours stay constant. Values given to the constructor go into
  ``initialControl``; values not given run auto for ``settle_frames`` frames, then the values
  the last frame reports are read and sent back as manual settings, and the camera waits until
  frames report them. ``manual_focus="calibration"`` uses the lens position of the factory
  calibration (the one the factory intrinsics belong to).
* factory intrinsics: ``readCalibration().getCameraIntrinsics(CAM_A, w, h)`` (CROP keeps the
  aspect ratio, as that call assumes) and the 14 ``getDistortionCoefficients(CAM_A)``
  (OpenCV rational model); only the perspective model is supported. :meth:`write_camera_json`
  writes them with the serial and the locked settings.
* time stamps: the RGB frame's ``getTimestamp(MIDDLE)`` (mid-exposure, host-synchronised
  steady clock, the same clock as :meth:`OakCamera.now`). ``capture()`` returns the first
  frame whose exposure STARTED after the call, never a stale queued frame (images taken
  before the arm settled are a known failure).

* no device: ``Device.getAllAvailableDevices()`` is asked first, so the refusal is one line within
  a second (``dai.Pipeline()`` alone retries for about 12 s).

depthai is imported lazily. Everything except the device's own nodes (Camera, StereoDepth) also runs
on any pipeline's outputs (:meth:`OakCamera.on_outputs`): the tests drive it through a host-only
pipeline with real ``dai.ImgFrame`` and ``dai.CalibrationHandler`` objects.
"""

from __future__ import annotations

import logging
import time
from datetime import timedelta
from pathlib import Path
from types import ModuleType
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from brave6d.core.atomic import atomic_write_json, depth_mm_u16_to_m
from brave6d.core.camera import PinholeCamera
from brave6d.core.errors import BraveError
from brave6d.core.extras import require
from brave6d.capture.protocols import CameraError, Frame

log = logging.getLogger(__name__)

FocusSetting = int | Literal["calibration"] | None

#: A frame reports the locked exposure when within 1 % or 30 us (sensors round to line times),
#: the locked ISO when within 2 % or 5; the lock holds after this many such frames in a row.
_EXPOSURE_TOL = (0.01, 30.0)
_ISO_TOL = (0.02, 5.0)
_LOCK_FRAMES = 3
_POLL_S = 0.002


def _seconds(value: Any) -> float:
    """depthai timestamps/durations are ``datetime.timedelta``; accept plain numbers too."""
    return value.total_seconds() if isinstance(value, timedelta) else float(value)


class OakCamera:
    """An OAK (RVC2) camera: RGB at ``width`` x ``height``, optional aligned depth, locked settings.

    Raises :class:`~brave6d.capture.protocols.CameraError` when no device is connected or the device
    misbehaves (with a message that says what to check).
    """

    def __init__(self, width: int = 640, height: int = 400, depth: bool = True, fps: float = 10.0,
                 manual_exposure_us: int | None = None, iso: int | None = None,
                 manual_focus: FocusSetting = None, manual_white_balance_k: int | None = None,
                 *, settle_frames: int = 30, lock_timeout_s: float = 5.0, frame_timeout_s: float = 3.0,
                 stereo_size: tuple[int, int] = (640, 400), dai_module: ModuleType | Any | None = None) -> None:
        self._setup(width, height, depth, fps, manual_exposure_us, iso, settle_frames, lock_timeout_s,
                    frame_timeout_s, dai_module)
        try:
            self._open_device(manual_exposure_us, iso, manual_focus, manual_white_balance_k, stereo_size)
        except BaseException:
            self.close()
            raise

    @classmethod
    def on_outputs(cls, pipeline: Any, calibration: Any, rgb: Any, control: Any, depth: Any = None, *,
                   width: int, height: int, fps: float = 10.0, serial: str = "", model: str = "OAK",
                   manual_exposure_us: int | None = None, iso: int | None = None,
                   manual_focus: FocusSetting = None, manual_white_balance_k: int | None = None,
                   settle_frames: int = 30, lock_timeout_s: float = 5.0, frame_timeout_s: float = 3.0,
                   dai_module: ModuleType | Any | None = None) -> OakCamera:
        """The camera on the outputs of a pipeline that is not started yet: ``rgb`` (BGR888i frames),
        ``control`` (an input taking ``dai.CameraControl``), optional ``depth`` (uint16 mm aligned to
        RGB), with ``calibration`` (a ``dai.CalibrationHandler``). Everything but the device's own
        nodes runs as with a connected OAK: a host-only pipeline (``dai.Pipeline(createImplicitDevice=
        False)`` with host nodes) exercises it without hardware."""
        cam = cls.__new__(cls)
        cam._setup(width, height, depth is not None, fps, manual_exposure_us, iso, settle_frames, lock_timeout_s,
                   frame_timeout_s, dai_module)
        try:
            cam._pipeline = pipeline
            cam._read_calibration(calibration, serial, model)
            focus = cam._resolve_focus(manual_focus)
            cam._attach(rgb, control, depth)
            cam._start(manual_exposure_us, iso, focus, manual_white_balance_k)
        except BaseException:
            cam.close()
            raise
        return cam

    def _setup(self, width: int, height: int, depth: bool, fps: float, manual_exposure_us: int | None,
               iso: int | None, settle_frames: int, lock_timeout_s: float, frame_timeout_s: float,
               dai_module: ModuleType | Any | None) -> None:
        if width < 16 or height < 16:
            raise BraveError(f"oak camera: image size {width}x{height} is too small")
        if (manual_exposure_us is None) != (iso is None):
            raise BraveError("oak camera: give manual_exposure_us and iso together (or neither for auto-then-lock)")
        if manual_exposure_us is not None and manual_exposure_us <= 0:
            raise BraveError(f"oak camera: manual_exposure_us must be positive, got {manual_exposure_us}")
        self.width, self.height, self.depth, self.fps = int(width), int(height), bool(depth), float(fps)
        self._settle_frames = int(settle_frames)
        self._lock_timeout_s = float(lock_timeout_s)
        self._frame_timeout_s = float(frame_timeout_s)
        self._pipeline: Any = None
        self._depth_queue: Any = None
        self._closed = False
        self._dai = dai_module if dai_module is not None else _import_depthai()

    # ------------------------------------------------------------------ opening
    def _open_device(self, exposure_us: int | None, iso: int | None, focus: FocusSetting,
                     white_balance_k: int | None, stereo_size: tuple[int, int]) -> None:
        dai = self._dai
        if not _try(dai.Device.getAllAvailableDevices):
            # at once, in one line: dai.Pipeline() would retry for about 12 s before saying the same
            raise CameraError("no OAK camera found (depthai lists no available device): check the USB cable, "
                              "power and the udev rules, and that no other program holds the camera")
        try:
            self._pipeline = dai.Pipeline()
        except RuntimeError as exc:
            if "no available devices" in str(exc).lower():
                raise CameraError("no OAK camera found (depthai: 'No available devices'): check the USB cable, "
                                  "power and the udev rules, and that no other program holds the camera") from None
            raise CameraError(f"cannot open the OAK camera: {exc}") from None
        device = self._pipeline.getDefaultDevice()
        socket = dai.CameraBoardSocket.CAM_A
        self._read_calibration(device.readCalibration(), str(_try(device.getDeviceId) or ""),
                               str(_try(device.getProductName) or "") or "OAK")
        focus = self._resolve_focus(focus)
        cam = self._pipeline.create(dai.node.Camera).build(socket)
        if exposure_us is not None and iso is not None:
            cam.initialControl.setManualExposure(int(exposure_us), int(iso))
        if focus is not None:
            cam.initialControl.setManualFocus(int(focus))
        if white_balance_k is not None:
            cam.initialControl.setManualWhiteBalance(int(white_balance_k))
        rgb_out = cam.requestOutput((self.width, self.height), type=dai.ImgFrame.Type.BGR888i,
                                    resizeMode=dai.ImgResizeMode.CROP, fps=self.fps, enableUndistortion=False)
        depth_out = None
        if self.depth:
            stereo = self._pipeline.create(dai.node.StereoDepth).build(
                autoCreateCameras=True, presetMode=dai.node.StereoDepth.PresetMode.DEFAULT, size=stereo_size,
                fps=self.fps)
            stereo.setLeftRightCheck(True)
            stereo.setSubpixel(True)
            stereo.setDepthAlign(socket)
            stereo.setOutputSize(self.width, self.height)
            depth_out = stereo.depth
        self._attach(rgb_out, cam.inputControl, depth_out)
        self._start(exposure_us, iso, focus, white_balance_k)

    def _read_calibration(self, calib: Any, serial: str, model: str) -> None:
        socket = self._dai.CameraBoardSocket.CAM_A
        self.intrinsics_source = "factory calibration (getCameraIntrinsics)"
        self._intrinsics = factory_intrinsics(calib, self.width, self.height, self._dai)
        self._calibration_lens_position = _try(lambda: int(calib.getLensPosition(socket)))
        self.serial, self.model = serial, model

    def _resolve_focus(self, focus: FocusSetting) -> int | None:
        if focus != "calibration":
            return focus
        if self._calibration_lens_position is None or self._calibration_lens_position < 0:
            raise CameraError("oak camera: manual_focus='calibration' but the device reports no calibrated "
                              "lens position")
        return self._calibration_lens_position

    def _attach(self, rgb_out: Any, control_in: Any, depth_out: Any) -> None:
        self._rgb_queue = rgb_out.createOutputQueue(maxSize=4, blocking=False)
        self._control_queue = control_in.createInputQueue()
        self._depth_queue = depth_out.createOutputQueue(maxSize=4, blocking=False) if depth_out is not None else None

    def _start(self, exposure_us: int | None, iso: int | None, focus: int | None, white_balance_k: int | None) -> None:
        dai = self._dai
        try:
            self._pipeline.start()
        except RuntimeError as exc:
            raise CameraError(f"oak camera: the pipeline did not start: {exc}") from None
        if any(v is not None for v in (exposure_us, focus, white_balance_k)):
            # the device took these as initialControl as well; any other source only this way
            control = dai.CameraControl()
            if exposure_us is not None and iso is not None:
                control.setManualExposure(int(exposure_us), int(iso))
            if focus is not None:
                control.setManualFocus(int(focus))
            if white_balance_k is not None:
                control.setManualWhiteBalance(int(white_balance_k))
            self._control_queue.send(control)
        self.settings = self._lock_settings(exposure_us, iso, focus, white_balance_k)

    def _lock_settings(self, exposure_us: int | None, iso: int | None, focus: int | None,
                       white_balance_k: int | None) -> dict[str, Any]:
        """Let auto modes settle, then lock every setting not given; return the locked values."""
        dai = self._dai
        manual = {"exposure": exposure_us is not None, "focus": focus is not None,
                  "white_balance": white_balance_k is not None}
        frame = None
        for _ in range(max(1, self._settle_frames if not all(manual.values()) else 1)):
            frame = self._next(self._rgb_queue, "RGB")
        assert frame is not None
        reported = _frame_settings(frame)
        locked = {
            "exposure_us": exposure_us if exposure_us is not None else reported["exposure_us"],
            "iso": iso if iso is not None else reported["iso"],
            "lens_position": focus if focus is not None else reported["lens_position"],
            "white_balance_k": white_balance_k if white_balance_k is not None else reported["white_balance_k"],
        }
        if not all(manual.values()):
            control = dai.CameraControl()
            control.setManualExposure(int(locked["exposure_us"]), int(locked["iso"]))
            if locked["lens_position"] is not None and locked["lens_position"] >= 0:
                control.setManualFocus(int(locked["lens_position"]))
            if locked["white_balance_k"] is not None and locked["white_balance_k"] > 0:
                control.setManualWhiteBalance(int(locked["white_balance_k"]))
            self._control_queue.send(control)
        self._wait_for_settings(locked)
        return {**locked, "locked_from": {k: ("manual" if v else "auto") for k, v in manual.items()},
                "calibration_lens_position": self._calibration_lens_position}

    def _wait_for_settings(self, locked: dict[str, Any]) -> None:
        deadline = time.monotonic() + self._lock_timeout_s
        last: dict[str, Any] = {}
        in_a_row = 0
        while time.monotonic() < deadline:
            last = _frame_settings(self._next(self._rgb_queue, "RGB"))
            in_a_row = in_a_row + 1 if _settings_match(locked, last) else 0
            if in_a_row >= _LOCK_FRAMES:
                return
        raise CameraError(f"oak camera: exposure/focus did not lock within {self._lock_timeout_s:.1f} s "
                          f"(asked {locked}, frames report {last})")

    # ------------------------------------------------------------------ Camera protocol
    @property
    def intrinsics(self) -> PinholeCamera:
        """Factory intrinsics of the RGB output (with its 14 distortion coefficients)."""
        return self._intrinsics

    def now(self) -> float:
        """The host-synchronised depthai clock (seconds), the clock of :attr:`Frame.timestamp`."""
        return _seconds(self._dai.Clock.now())

    def capture(self) -> Frame:
        """The first RGB frame exposed after this call (and the depth frame closest to it)."""
        if self._closed:
            raise CameraError("oak camera: capture() after close()")
        dai = self._dai
        requested = self.now()
        deadline = time.monotonic() + self._frame_timeout_s
        while True:
            rgb_frame = self._next(self._rgb_queue, "RGB", deadline)
            if _seconds(rgb_frame.getTimestamp(dai.CameraExposureOffset.START)) >= requested:
                break
        bgr = np.asarray(rgb_frame.getCvFrame())
        if bgr.shape != (self.height, self.width, 3) or bgr.dtype != np.uint8:
            raise CameraError(f"oak camera: RGB frame is {bgr.dtype} {bgr.shape}, expected uint8 "
                              f"({self.height}, {self.width}, 3)")
        rgb = rgb_from_bgr(bgr)
        timestamp = _seconds(rgb_frame.getTimestamp(dai.CameraExposureOffset.MIDDLE))
        extras: dict[str, Any] = {"sequence_num": int(rgb_frame.getSequenceNum()), **_frame_settings(rgb_frame)}
        depth_m = None
        if self._depth_queue is not None:
            depth_frame = self._matching_depth(timestamp, deadline)
            mm = np.asarray(depth_frame.getFrame())
            if mm.shape != (self.height, self.width) or mm.dtype != np.uint16:
                raise CameraError(f"oak camera: depth frame is {mm.dtype} {mm.shape}, expected uint16 "
                                  f"({self.height}, {self.width}) aligned to RGB")
            depth_m = depth_mm_u16_to_m(mm)
            extras["depth_timestamp"] = _seconds(depth_frame.getTimestamp())
        return Frame(rgb=rgb, depth_m=depth_m, timestamp=timestamp, extras=extras)

    def _matching_depth(self, timestamp: float, deadline: float) -> Any:
        """The depth frame closest in time to ``timestamp`` (within half a frame period)."""
        tolerance = 0.5 / self.fps + 0.002
        assert self._depth_queue is not None
        while True:
            frame = self._next(self._depth_queue, "depth", deadline)
            dt = _seconds(frame.getTimestamp()) - timestamp
            if abs(dt) <= tolerance:
                return frame
            if dt > tolerance:
                raise CameraError(f"oak camera: no depth frame within {tolerance * 1000:.0f} ms of the RGB frame "
                                  f"(next one is {dt * 1000:.0f} ms later)")

    def _next(self, queue: Any, what: str, deadline: float | None = None) -> Any:
        end = deadline if deadline is not None else time.monotonic() + self._frame_timeout_s
        while True:
            msg = queue.tryGet()
            if msg is not None:
                return msg
            if time.monotonic() > end:
                raise CameraError(f"oak camera: no {what} frame within {self._frame_timeout_s:.1f} s "
                                  "(device disconnected or pipeline stalled?)")
            time.sleep(_POLL_S)

    def close(self) -> None:
        """Stop the pipeline and release the device (safe to call twice)."""
        if self._closed:
            return
        self._closed = True
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
                if self._pipeline.isRunning() is False:
                    self._pipeline.wait()  # its threads joined: a pipeline freed while they run crashes Python
            except Exception as exc:  # closing must not mask the original error
                log.warning("oak camera: stopping the pipeline failed: %s", exc)

    # ------------------------------------------------------------------ camera.json
    def camera_info(self) -> dict[str, Any]:
        """Everything camera.json records: model, serial, intrinsics, distortion, locked settings."""
        return {
            "model": self.model, "serial": self.serial, "socket": "CAM_A",
            "width": self.width, "height": self.height, "fps": self.fps,
            "intrinsics": self._intrinsics.to_json(), "intrinsics_source": self.intrinsics_source,
            "distortion_model": "opencv_rational_14" if len(self._intrinsics.dist) == 14 else "opencv",
            "distortion": list(self._intrinsics.dist),
            "depth": {"enabled": self.depth, "aligned_to": "CAM_A" if self.depth else None, "units": "m"},
            "settings": self.settings,
            "depthai_version": str(getattr(self._dai, "__version__", "unknown")),
        }

    def write_camera_json(self, path: Path | str) -> Path:
        """Write :meth:`camera_info` atomically to ``path``."""
        return atomic_write_json(path, self.camera_info())


# ----------------------------------------------------------------------------- helpers
def factory_intrinsics(calib: Any, width: int, height: int, dai: ModuleType | Any) -> PinholeCamera:
    """CAM_A's intrinsics for a ``width`` x ``height`` output from a ``dai.CalibrationHandler`` (depthai
    scales the stored camera matrix itself) and its distortion coefficients (OpenCV rational model);
    only the perspective lens model is supported."""
    socket = dai.CameraBoardSocket.CAM_A
    model = _try(lambda: calib.getDistortionModel(socket))
    if model is not None and model != dai.CameraModel.Perspective:
        raise CameraError(f"oak camera: CAM_A uses the {model} lens model; only the perspective (OpenCV "
                          "rational) model is supported")
    try:
        K = np.asarray(calib.getCameraIntrinsics(socket, width, height), dtype=np.float64)
        dist = np.asarray(calib.getDistortionCoefficients(socket), dtype=np.float64).ravel()
    except RuntimeError as exc:
        raise CameraError(f"oak camera: cannot read the factory calibration of CAM_A: {exc}") from None
    if len(dist) > 14:
        dist = dist[:14]
    if len(dist) not in (4, 5, 8, 12, 14):
        raise CameraError(f"oak camera: unexpected number of distortion coefficients ({len(dist)})")
    try:
        return PinholeCamera.from_K(K, width, height, dist)
    except BraveError as exc:
        raise CameraError(f"oak camera: factory intrinsics are unusable: {exc}") from None


def _import_depthai() -> ModuleType:
    return require("depthai", "robot", "--camera oak")


def _try(fn: Any) -> Any:
    """Optional device queries: None when the firmware or model does not support them."""
    try:
        return fn()
    except (RuntimeError, AttributeError, TypeError):
        return None


def _frame_settings(frame: Any) -> dict[str, Any]:
    """Exposure (us), ISO, lens position (-1 = fixed focus) and white balance a frame reports."""
    return {
        "exposure_us": int(round(_seconds(frame.getExposureTime()) * 1e6)),
        "iso": int(frame.getSensitivity()),
        "lens_position": _try(lambda: int(frame.getLensPosition())),
        "white_balance_k": _try(lambda: int(frame.getColorTemperature())),
    }


def _settings_match(locked: dict[str, Any], reported: dict[str, Any]) -> bool:
    def close(a: float, b: float, tol: tuple[float, float]) -> bool:
        return abs(a - b) <= max(tol[0] * abs(a), tol[1])

    if not (close(locked["exposure_us"], reported["exposure_us"], _EXPOSURE_TOL)
            and close(locked["iso"], reported["iso"], _ISO_TOL)):
        return False
    lens = locked["lens_position"]
    if lens is not None and lens >= 0 and reported.get("lens_position") not in (None, -1):
        return abs(int(reported["lens_position"]) - int(lens)) <= 1
    return True


def rgb_from_bgr(bgr: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """BGR (OpenCV/depthai) -> RGB, contiguous."""
    return np.ascontiguousarray(bgr[:, :, ::-1])
