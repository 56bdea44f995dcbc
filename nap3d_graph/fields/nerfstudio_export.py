"""Export posed RGB-D as a nerfstudio dataset (``transforms.json``, ``images/``, ``depth/``,
``masks/`` where the images have pixels without data),
and read its poses back. The conventions at this boundary are in
:mod:`nap3d_graph.fields.nerfstudio`; nerfstudio itself is not needed here.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from nap3d_graph.camera import Intrinsics, colour_coverage
from nap3d_graph.progress import progress_bar

from .base import FieldError
from .nerfstudio import (
    depth_to_png_mm,
    intrinsics_from_nerfstudio,
    nerfstudio_intrinsics,
    opencv_to_opengl_pose,
    opengl_to_opencv_pose,
)

__all__ = ["export_nerfstudio", "read_transforms_poses"]

log = logging.getLogger(__name__)


def export_nerfstudio(sequence, out_dir, every: int = 1, progress: bool = False) -> Path:
    """Write ``transforms.json``, ``images/`` (PNG) and ``depth/`` (uint16 mm PNG) for every
    ``every``-th frame of a posed RGB-D sequence; returns the path of ``transforms.json``.
    When the delivered images hold pixels without data (an undistorting reader's black
    corners, :func:`~nap3d_graph.camera.colour_coverage`), ``masks/coverage.png`` (255 where
    there is data, 0 where not) is every frame's ``mask_path``, so nerfstudio does not learn
    black corners.

    The world frame of the file is the sequence's (``T_world_cam_gt``), so a model trained on
    it maps back to our world with its ``dataparser_transforms.json`` alone. Train with e.g.
    ``ns-train depth-nerfacto --data OUT``.
    """
    import cv2


    every = int(every)
    if every < 1:
        raise FieldError(f"`every` must be at least 1, got {every}")
    poses = getattr(sequence, "T_world_cam_gt", None)
    if poses is None:
        raise FieldError("exporting for nerfstudio needs posed frames, but the sequence has no poses")
    poses = np.asarray(poses, dtype=np.float64)
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    intrinsics = sequence.intrinsics.without_distortion() if getattr(sequence, "undistort", True) else sequence.intrinsics
    meta = nerfstudio_intrinsics(intrinsics)
    coverage = colour_coverage(sequence)
    if coverage is not None:
        (out / "masks").mkdir(exist_ok=True)
        if not cv2.imwrite(str(out / "masks" / "coverage.png"), coverage.astype(np.uint8) * 255):
            raise FieldError(f"{out / 'masks' / 'coverage.png'}: cannot write the mask")
    frames = []
    indices = range(0, len(sequence), every)
    for i in progress_bar(indices, desc="export", unit="frame", disable=not progress):
        frame = sequence[i]
        if not np.all(np.isfinite(poses[i])):
            continue
        name = f"frame_{i:05d}.png"
        if not cv2.imwrite(str(out / "images" / name), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)):
            raise FieldError(f"{out / 'images' / name}: cannot write image")
        cv2.imwrite(str(out / "depth" / name), depth_to_png_mm(frame.depth_m))
        frames.append({
            "file_path": f"images/{name}",
            "depth_file_path": f"depth/{name}",
            "transform_matrix": opencv_to_opengl_pose(poses[i]).tolist(),
            "timestamp": float(frame.timestamp),
            # nerfstudio takes a mask for every frame or for none.
            **({} if coverage is None else {"mask_path": "masks/coverage.png"}),
        })
    if not frames:
        raise FieldError("no frames to export")
    document = {
        **meta,
        "frames": frames,
        # Not read by nerfstudio; says where this came from and how to map back.
        "nap3d_graph": {
            "source": str(getattr(sequence, "path", type(sequence).__name__)),
            "every": every,
            "world_frame": "the source sequence's world (T_world_cam_gt); cameras OpenGL in this file",
            "principal_point": "nerfstudio convention (pixel centres at i + 0.5): cx = cx_opencv + 0.5",
            "depth_unit_scale_factor": 0.001,
        },
    }
    path = out / "transforms.json"
    path.write_text(json.dumps(document, indent=1))
    log.info("exported %d frames to %s", len(frames), path)
    return path


def read_transforms_poses(path) -> tuple[np.ndarray, Intrinsics, list[dict]]:
    """Read a ``transforms.json`` back: ``T_world_cam`` (N, 4, 4) with OpenCV cameras, the
    intrinsics, and the raw frame entries."""
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
        frames = meta["frames"]
        T_gl = np.asarray([f["transform_matrix"] for f in frames], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FieldError(f"{path}: not a readable transforms.json ({exc})") from None
    return opengl_to_opencv_pose(T_gl), intrinsics_from_nerfstudio(meta), frames
