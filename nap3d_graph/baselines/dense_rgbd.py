"""Dense direct RGB-D alignment of the rendered view to the real frame (OpenCV 5's
``cv2.Odometry``, ``OdometryType_RGB_DEPTH``: photometric and ICP terms over an image
pyramid, the method of DVO), as a NAP3D peer.

``compute(src, dst)`` returns the motion that maps the source camera's points into the
destination camera's: with the rendered view as source and the real frame as destination,
that is ``T_real_rendered``. Like any direct method it needs the initial error small against
the image pyramid's reach.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..camera import RenderedView, RGBDFrame
from ..conventions import pose_error
from ..results import Alignment

__all__ = ["DenseRgbdConfig", "dense_rgbd_align"]


@dataclass(frozen=True)
class DenseRgbdConfig:
    """min_opacity: rendered pixels kept (the rest get no depth); max_translation_m /
    max_rotation_deg: a result beyond these is called a failure (a diverged solve)."""

    min_opacity: float = 0.5
    max_translation_m: float = 0.5
    max_rotation_deg: float = 20.0


def _gray(rgb: np.ndarray) -> np.ndarray:
    import cv2

    rgb = rgb if rgb.dtype == np.uint8 else np.clip(np.asarray(rgb) * 255.0, 0, 255).astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def dense_rgbd_align(real: RGBDFrame, view: RenderedView, config: DenseRgbdConfig | None = None) -> Alignment:
    """``T_real_rendered`` by dense RGB-D odometry; ``success=False`` with a reason when the
    solve fails or diverges."""
    import cv2


    config = config or DenseRgbdConfig()
    t0 = time.perf_counter()
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(real.intrinsics.K.astype(np.float32))
    odometry = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
    depth_view = np.where(view.opacity >= config.min_opacity, np.nan_to_num(view.depth_m), 0.0).astype(np.float32)
    src = cv2.OdometryFrame(depth_view, _gray(view.rgb))
    dst = cv2.OdometryFrame(np.nan_to_num(real.depth_m).astype(np.float32), _gray(real.rgb))
    odometry.prepareFrames(src, dst)
    T = np.eye(4)
    try:
        ok, T = odometry.compute(src, dst, T)
    except cv2.error as exc:
        return Alignment.failure(f"cv2.Odometry failed: {str(exc).splitlines()[0]}", method="dense-rgbd")
    seconds = time.perf_counter() - t0
    T = np.asarray(T, dtype=float)
    if not ok or not np.all(np.isfinite(T)):
        return Alignment.failure("dense RGB-D alignment did not converge", method="dense-rgbd",
                                 timings_s={"dense": seconds})
    moved_m, turned_deg = pose_error(T, np.eye(4))
    if moved_m > config.max_translation_m or turned_deg > config.max_rotation_deg:
        return Alignment.failure(f"dense RGB-D alignment diverged ({moved_m:.2f} m, {turned_deg:.1f} deg)",
                                 method="dense-rgbd", timings_s={"dense": seconds})
    return Alignment(T_real_rendered=T, success=True, method="dense-rgbd", timings_s={"dense": seconds})
