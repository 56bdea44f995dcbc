"""Dense GICP between the rendered and the real depth (small_gicp), as a NAP3D peer.

Both depth images are back-projected (the rendered one only where the field is opaque),
voxel-downsampled and aligned by generalized ICP from the identity (the believed pose):
``T_target_source`` with the real cloud as target and the rendered one as source is
``T_real_rendered``. No image content is used, so it needs geometry that constrains all six
degrees of freedom and an initial error inside ICP's basin of convergence.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..camera import RenderedView, RGBDFrame, backproject_depth
from ..results import Alignment

__all__ = ["GicpConfig", "gicp_align"]


@dataclass(frozen=True)
class GicpConfig:
    """downsample_m: voxel size of both clouds; max_distance_m: correspondence gate;
    stride: pixel stride of the back-projection; min_opacity: rendered pixels kept."""

    downsample_m: float = 0.02
    max_distance_m: float = 0.15
    max_iterations: int = 40
    stride: int = 2
    min_opacity: float = 0.5
    min_points: int = 200
    threads: int = 1


def gicp_align(real: RGBDFrame, view: RenderedView, config: GicpConfig | None = None) -> Alignment:
    """``T_real_rendered`` by GICP; ``success=False`` with a reason when it cannot run or
    did not converge."""
    import small_gicp

    config = config or GicpConfig()
    t0 = time.perf_counter()
    rendered_depth = np.where(view.opacity >= config.min_opacity, view.depth_m, 0.0)
    real_points, _ = backproject_depth(real.depth_m, real.intrinsics, config.stride)
    view_points, _ = backproject_depth(rendered_depth, view.intrinsics, config.stride)
    if min(len(real_points), len(view_points)) < config.min_points:
        return Alignment.failure(f"too few depth points (real {len(real_points)}, rendered {len(view_points)})",
                                 method="gicp")
    result = small_gicp.align(real_points.astype(np.float64), view_points.astype(np.float64),
                              registration_type="GICP", downsampling_resolution=config.downsample_m,
                              max_correspondence_distance=config.max_distance_m, num_threads=config.threads,
                              max_iterations=config.max_iterations)
    seconds = time.perf_counter() - t0
    T = np.asarray(result.T_target_source, dtype=float)
    if not result.converged or not np.all(np.isfinite(T)):
        return Alignment.failure(f"GICP did not converge in {result.iterations} iterations", method="gicp",
                                 timings_s={"gicp": seconds})
    return Alignment(T_real_rendered=T, num_matches=int(result.num_inliers), num_inliers=int(result.num_inliers),
                     inlier_rmse_m=float(np.sqrt(result.error / max(result.num_inliers, 1))), success=True,
                     method="gicp", timings_s={"gicp": seconds}, diagnostics={"iterations": int(result.iterations)})
