"""The real frame's rolling shutter: its rows were read one after another while the camera
moved, so each real point is moved to where the camera was at the middle of the readout.

A rolling-shutter colour camera (the Kinect's, most webcams') reads its rows over
``readout_s`` (about a frame period at its highest rate): a keypoint on row ``v`` of an image
``H`` rows high was seen ``dt = (v / H - 0.5) * readout_s`` after the middle row. With the
camera's body twist ``xi`` (per second, GTSAM order ``[omega, v]``, right perturbation: the
camera at ``t + dt`` is ``T(t) @ Exp(xi dt)``), a point ``y`` measured in the camera at
``t + dt`` is ``Exp(xi dt) @ y`` in the camera at the middle row: the one instant a
global-shutter render and the frame's stamp (with the capture timing already applied) refer
to. Depth at the keypoint is taken as read with the colour row (the depth image is
registered to colour). Uncorrected, a camera moving at 0.7 m/s shifts the bottom rows'
points 2 cm against the top rows' over a 30 ms readout, which a rigid fit cannot absorb.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from ..camera import Intrinsics, RGBDFrame, project, warp_depth
from ..conventions import exp_se3
from .correspondences import Correspondences

if TYPE_CHECKING:
    from ..datasets.depth_timing import CaptureTiming

__all__ = ["RowMotion", "to_mid_readout", "exp_apply", "at_colour_time", "at_one_instant"]


@dataclass(frozen=True)
class RowMotion:
    """How the real camera moved while its rows were read.

    twist: (6,) body twist per second (GTSAM order: rotation rad/s, translation m/s, camera
    frame); readout_s: seconds from the first row to the last (0: a global shutter).
    """

    twist: np.ndarray
    readout_s: float

    def __post_init__(self):
        twist = np.asarray(self.twist, dtype=float).reshape(-1)
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            raise ValueError(f"twist must be 6 finite numbers, got {self.twist!r}")
        if not np.isfinite(self.readout_s) or self.readout_s < 0:
            raise ValueError(f"readout_s must be >= 0 seconds, got {self.readout_s}")
        object.__setattr__(self, "twist", twist)


def to_mid_readout(corr: Correspondences, motion: RowMotion, intrinsics: Intrinsics) -> Correspondences:
    """``corr`` with each real point ``y`` (and its keypoint ``uv_real``) moved from its row's
    instant to the middle row's (see the module docstring). ``intrinsics``: the real frame's
    camera (its height sets the rows' instants). Exact SE(3) exponential per point."""
    if motion.readout_s == 0.0 or len(corr) == 0 or corr.reason:
        return corr
    dt = (corr.uv_real[:, 1] / float(intrinsics.height) - 0.5) * motion.readout_s  # (N,) s
    y = exp_apply(motion.twist[None, :] * dt[:, None], corr.y)
    uv, _ = project(y, intrinsics)
    return replace(corr, y=y, uv_real=uv)


def exp_apply(xi: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``Exp(xi_i) @ p_i`` for N twists (N, 6) ([omega, v], GTSAM's Pose3 exponential) and
    points (N, 3): ``R p + V v`` with Rodrigues' R and its left Jacobian V."""
    w, v = xi[:, :3], xi[:, 3:]
    theta2 = np.sum(w * w, axis=1)
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    # sin(t)/t, (1 - cos t)/t^2, (t - sin t)/t^3, by their series where t is tiny.
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (safe - np.sin(safe)) / safe**3)
    wp = np.cross(w, p)
    wv = np.cross(w, v)
    rotated = p + a[:, None] * wp + b[:, None] * np.cross(w, wp)
    return rotated + v + b[:, None] * wv + c[:, None] * np.cross(w, wv)


def at_colour_time(frame: RGBDFrame, timing: CaptureTiming | None, twist: np.ndarray | None, depth_scale: float):
    """``(frame, twist_used)``: the frame with its depth (scaled by ``depth_scale``) moved to
    its colour's capture instant along ``twist``; as it is (only scaled) and ``None`` when the
    capture timing, the twist or the depth stamp is unknown."""
    if timing is None or twist is None or frame.depth_timestamp is None:
        if depth_scale != 1.0:
            frame = frame.with_depth(frame.depth_m * np.float32(depth_scale))
        return frame, None
    dt = (frame.depth_timestamp + timing.depth_offset_s) - (frame.timestamp + timing.colour_offset_s)
    depth = warp_depth(frame.depth_m, frame.intrinsics, exp_se3(twist * dt), depth_scale)
    return frame.with_depth(depth), twist


def at_one_instant(frame: RGBDFrame, timing: CaptureTiming | None, twist: np.ndarray | None, readout_s: float,
                   depth_scale: float) -> tuple[RGBDFrame, RowMotion | None, np.ndarray]:
    """What aligning a moving camera's frame as one instant needs: ``(frame, motion, shift)``,
    the frame with its depth at its colour's instant (:func:`at_colour_time`), the
    :class:`RowMotion` its alignment undoes (None: a global shutter or no twist) and the (4, 4)
    that moves a pose measured at the colour's instant to the frame's stamp (the identity when
    the depth was not moved)."""
    frame, used = at_colour_time(frame, timing, twist, depth_scale)
    motion = RowMotion(twist, readout_s) if readout_s > 0 and twist is not None else None
    shift = exp_se3(-used * timing.colour_offset_s) if used is not None and timing is not None else np.eye(4)
    return frame, motion, shift
