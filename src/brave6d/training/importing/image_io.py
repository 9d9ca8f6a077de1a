"""Images of an imported capture: decode any common format, settle the EXIF orientation, resample.

- :func:`read_frame_image` decodes with Pillow (JPEG, PNG, TIFF, ...) to 8-bit RGB. A photo whose
  EXIF orientation turns it is used as stored when the stored size is what the source's camera
  describes (COLMAP reads the stored pixels), turned when only the turned size matches, and refused
  (naming the frame and both sizes) when neither does.
- :class:`Resampler` maps a frame from its source camera (any COLMAP model, fisheye included:
  pycolmap projects it) into the pinhole camera the scene gets, when one shared OpenCV camera cannot
  describe the source (fisheye lenses, frames with different intrinsics).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from brave6d.core.camera import CORNER_ORIGIN_OFFSET, PinholeCamera
from brave6d.core.errors import DataError
from brave6d.core.png_check import check_image_header
from brave6d.training.importing.source import SourceCamera

_EXIF_ORIENTATION = 0x0112


@dataclass(frozen=True)
class FrameImage:
    """A decoded frame: RGB uint8 (H, W, 3) and whether its EXIF orientation was applied."""

    rgb: NDArray[np.uint8]
    exif_turned: bool
    note: str | None = None  # something worth recording (an alpha channel dropped, an ambiguous square photo)


def read_frame_image(path: Path, size: tuple[int, int], name: str) -> FrameImage:
    """Decode ``path`` for the camera size ``size`` (width, height); errors name the frame ``name``."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    try:
        check_image_header(path)  # the pixel limit, from the header, before Pillow decodes anything
    except DataError as exc:
        raise DataError(f"frame {name}: {exc}") from None
    try:
        with Image.open(path) as im:
            im.load()
            orientation = int(im.getexif().get(_EXIF_ORIENTATION, 1) or 1)
            stored = im.size
            turned_image = ImageOps.exif_transpose(im) if orientation != 1 else im
            turned = turned_image.size
            notes = []
            if stored == tuple(size):
                chosen, exif_turned = im, False
                if orientation != 1 and turned == stored:
                    notes.append(f"EXIF orientation {orientation} not applied (a square photo: the stored pixels "
                                 "are what COLMAP reads)")
            elif turned == tuple(size):
                chosen, exif_turned = turned_image, True
            else:
                also = f" ({turned[0]}x{turned[1]} after its EXIF orientation {orientation})" if orientation != 1 else ""
                raise DataError(f"frame {name}: {path}: the image is {stored[0]}x{stored[1]}{also}, its camera says "
                                f"{size[0]}x{size[1]}")
            rgb = _to_rgb8(chosen, path, name, notes)
    except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError) as exc:
        raise DataError(f"frame {name}: {path}: cannot decode the image ({exc})") from None
    return FrameImage(rgb, exif_turned, "; ".join(notes) or None)


def _to_rgb8(im, path: Path, name: str, notes: list[str]) -> NDArray[np.uint8]:  # type: ignore[no-untyped-def]
    """8-bit RGB of any Pillow mode: 16-bit grey scaled down, alpha dropped (and noted)."""
    mode = im.mode
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(im, dtype=np.float64)
        top = 65535.0 if mode.startswith("I;16") else max(float(arr.max()), 1.0)
        grey = np.clip(np.rint(arr / top * 255.0), 0, 255).astype(np.uint8)
        notes.append(f"{mode} image scaled to 8 bits")
        return np.ascontiguousarray(np.repeat(grey[:, :, None], 3, axis=2))
    if mode in ("RGBA", "LA", "PA") or (mode == "P" and "transparency" in im.info):
        notes.append("alpha channel dropped")
    if mode == "F":
        raise DataError(f"frame {name}: {path}: a floating-point image is not a photo")
    return np.ascontiguousarray(np.asarray(im.convert("RGB"), dtype=np.uint8))


class Resampler:
    """Remaps images from a :class:`SourceCamera` into a target pinhole camera (bilinear; pixels
    with no source pixel are black). The maps are made once per source camera."""

    def __init__(self, target: PinholeCamera) -> None:
        if target.has_distortion:
            raise ValueError("the target camera must be a pinhole without distortion")
        self.target = target
        self._maps: dict[SourceCamera, tuple[NDArray[np.float32], NDArray[np.float32], float]] = {}

    def maps(self, source: SourceCamera) -> tuple[NDArray[np.float32], NDArray[np.float32], float]:
        """``(map_x, map_y, valid_share)`` for ``cv2.remap`` from ``source`` into the target."""
        if source not in self._maps:
            self._maps[source] = source_pixel_maps(source, self.target)
        return self._maps[source]

    def __call__(self, image: NDArray[np.uint8], source: SourceCamera) -> NDArray[np.uint8]:
        map_x, map_y, _ = self.maps(source)
        return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def source_pixel_maps(source: SourceCamera, target: PinholeCamera) -> tuple[NDArray[np.float32], NDArray[np.float32], float]:
    """For every target pixel, where its ray lands in the source image (OpenCV pixel coordinates);
    ``-1`` where it lands nowhere (behind a fisheye's reach, outside the image). Also the share of
    target pixels with a source pixel."""
    import pycolmap

    cam = pycolmap.Camera(model=source.model, width=source.width, height=source.height, params=list(source.params))
    grid = target.pixel_grid()
    rays = np.column_stack([(grid[:, 0] - target.cx) / target.fx, (grid[:, 1] - target.cy) / target.fy,
                            np.ones(len(grid))])
    with np.errstate(invalid="ignore"):
        uv = np.asarray(cam.img_from_cam(rays), dtype=np.float64).reshape(-1, 2) - CORNER_ORIGIN_OFFSET
        back = np.asarray(cam.cam_from_img(uv + CORNER_ORIGIN_OFFSET), dtype=np.float64).reshape(-1, 2)
    ok = np.isfinite(uv).all(axis=1) & np.isfinite(back).all(axis=1)
    # a distortion polynomial can fold back onto the image far off-axis: keep rays it maps back to themselves
    ok &= np.linalg.norm(np.where(ok[:, None], back, 0.0) - rays[:, :2], axis=1) < 1e-3 * (1.0 + np.linalg.norm(rays[:, :2], axis=1))
    ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= source.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= source.height - 0.5)
    uv[~ok] = -1.0
    shape = (target.height, target.width)
    return (uv[:, 0].reshape(shape).astype(np.float32), uv[:, 1].reshape(shape).astype(np.float32),
            float(ok.mean()) if len(ok) else 0.0)
