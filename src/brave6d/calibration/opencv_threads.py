"""OpenCV on one thread while a calibration computes: the same board images give the same bits.

With OpenCV's thread pool, ``calibrateCameraExtended`` and the ChArUco detector gave intrinsics that
differed in the 10th-13th digit between runs on identical images (three runs, three results; three
results alike on one thread). Those digits reach the planned robot poses, a few captured pixels, the
sparse model and, through training's sensitivity, the trained splat, so two demo runs of one code
ended with different splats (docs/BENCHMARKS.md). The calibration's images are small; one thread costs
little.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import cv2

from brave6d.core.process_setting import HeldSetting

F = TypeVar("F", bound=Callable[..., Any])


_OPENCV_THREADS = HeldSetting(cv2.getNumThreads, cv2.setNumThreads, 1)


@contextmanager
def opencv_one_thread() -> Iterator[None]:
    """OpenCV's parallel loops on one thread for the duration; overlapping sections share OpenCV's
    one process-wide thread count (:class:`~brave6d.core.process_setting.HeldSetting`): restored
    when the last of them leaves, never under one still running."""
    with _OPENCV_THREADS.held():
        yield


def on_one_opencv_thread(fn: F) -> F:
    """``fn`` run under :func:`opencv_one_thread`."""
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with opencv_one_thread():
            return fn(*args, **kwargs)
    return wrapper  # type: ignore[return-value]
