"""Photometric pose refinement through the project's differentiable grid field, as iNeRF
does (Yen-Chen et al., 2021), as a NAP3D peer.

The camera pose is ``T_world_cam(xi) = T_world_cam_est @ exp(xi^)`` with ``xi`` (6,) a twist
in the believed camera's frame (``[rho, phi]``: translation first, as in the exponential map
``torch.linalg.matrix_exp`` of the 4x4 twist matrix). Each of a fixed number of Adam steps
casts a batch of rays through pixels of the real frame at the current pose, volume-renders
their colour in the :class:`~nap3d_graph.fields.grid.GridField` (density and colour read
with ``grid_sample``, which is differentiable in the sample positions, so the gradient
reaches the pose) and lowers the mean squared colour error against the real pixels.

What follows iNeRF: rays sampled in "interest regions" (keypoints of the real image, dilated),
Adam on the pose twist with an exponentially decaying learning rate, a fixed iteration budget,
colour only (no depth term). What a CPU needs on top: each ray is sampled only in a window
around the depth the field rendered there at the believed pose, re-centred every step on
the ray's current expected depth (a full ray would cost 10x the samples for the same
gradient); pixels the field renders with low opacity are not used. ``exposure=True``
(default) fits a per-channel gain and offset of the real image onto the rendered colours
each step, in closed form and without gradient (as direct methods such as DSO do): TUM's
Kinect changes exposure, the field holds one.

The method has no covariance (``Alignment.covariance`` stays infinite).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ..camera import RenderedView, RGBDFrame
from ..conventions import inv_T, pose_error
from ..fields.grid import GridField
from ..results import Alignment
from ..torch_threads import torch_threads

__all__ = ["PhotometricConfig", "photometric_align"]


@dataclass(frozen=True)
class PhotometricConfig:
    """iterations: Adam steps (the fixed budget); rays_per_step: pixels per step, drawn from
    the interest region; lr: Adam's initial step on the twist (metres and radians), decayed
    by ``lr_decay`` over the whole budget; keypoints / dilate_px: the interest region, SIFT
    keypoints of the real image dilated by a square of that half-width; samples: points per
    ray in a window of half-width ``window_m`` around the ray's expected depth;
    min_opacity: rendered pixels below this are not used; exposure: fit the real image's
    per-channel gain and offset to the render; max_translation_m / max_rotation_deg: a
    result beyond these is a failure (diverged); seed: the ray sampler's."""

    iterations: int = 150
    rays_per_step: int = 1024
    lr: float = 0.004
    lr_decay: float = 0.1
    keypoints: int = 800
    dilate_px: int = 2
    samples: int = 24
    window_m: float = 0.12
    min_opacity: float = 0.9
    exposure: bool = True
    max_translation_m: float = 0.5
    max_rotation_deg: float = 20.0
    seed: int = 0
    threads: int | None = 1


def photometric_align(real: RGBDFrame, view: RenderedView, field, T_world_cam_est: np.ndarray,
                      config: PhotometricConfig | None = None) -> Alignment:
    """``T_real_rendered`` by photometric refinement of the pose ``T_world_cam_est`` (4, 4,
    world <- camera) at which ``view`` was rendered; ``success=False`` with a reason when the
    field is not differentiable, the interest region is too small or the solve diverges."""
    config = config or PhotometricConfig()
    if not isinstance(field, GridField):
        return Alignment.failure(f"the photometric peer needs a differentiable grid field, not "
                                 f"{getattr(field, 'name', type(field).__name__)!r}", method="photometric")
    t0 = time.perf_counter()
    uv, depth0 = _interest_pixels(real, view, config)
    if uv.shape[0] < 64:
        return Alignment.failure(f"only {uv.shape[0]} interest pixels the field renders opaque (need 64)",
                                 method="photometric", timings_s={"photometric": time.perf_counter() - t0})
    with torch_threads(config.threads if field.device.type == "cpu" else None):
        T_world_cam = _optimise(real, field, np.asarray(T_world_cam_est, dtype=float), uv, depth0, config)
    seconds = time.perf_counter() - t0
    if T_world_cam is None:
        return Alignment.failure("photometric refinement produced a non-finite pose", method="photometric",
                                 timings_s={"photometric": seconds})
    T_real_rendered = inv_T(T_world_cam) @ T_world_cam_est
    moved_m, turned_deg = pose_error(T_real_rendered, np.eye(4))
    if moved_m > config.max_translation_m or turned_deg > config.max_rotation_deg:
        return Alignment.failure(f"photometric refinement diverged ({moved_m:.2f} m, {turned_deg:.1f} deg)",
                                 method="photometric", timings_s={"photometric": seconds})
    return Alignment(T_real_rendered=T_real_rendered, success=True, method="photometric",
                     num_matches=int(uv.shape[0]), timings_s={"photometric": seconds})


def _interest_pixels(real: RGBDFrame, view: RenderedView, config: PhotometricConfig):
    """Pixels (M, 2) int (u, v) of the real frame near its SIFT keypoints where the view (at
    the believed pose) is opaque, and the view's depth there (M,) metres."""
    import cv2

    gray = cv2.cvtColor(real.rgb, cv2.COLOR_RGB2GRAY)
    keypoints = cv2.SIFT_create(nfeatures=config.keypoints).detect(gray, None)
    h, w = gray.shape
    mask = np.zeros((h, w), np.uint8)
    if keypoints:
        uv = np.round(cv2.KeyPoint_convert(keypoints)).astype(int)
        uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)]
        mask[uv[:, 1], uv[:, 0]] = 1
    size = 2 * config.dilate_px + 1
    mask = cv2.dilate(mask, np.ones((size, size), np.uint8))
    v, u = np.nonzero(mask)
    # The view may be rendered smaller than the real frame: read it at the scaled pixel.
    vh, vw = view.depth_m.shape
    vu = np.clip(np.round(u * vw / w).astype(int), 0, vw - 1)
    vv = np.clip(np.round(v * vh / h).astype(int), 0, vh - 1)
    depth = np.nan_to_num(view.depth_m[vv, vu])
    keep = (view.opacity[vv, vu] >= config.min_opacity) & (depth > 0)
    return np.stack([u[keep], v[keep]], axis=1), depth[keep].astype(np.float32)


def _twist_matrix(xi: torch.Tensor) -> torch.Tensor:
    """(6,) ``[rho, phi]`` -> (4, 4) element of se(3)."""
    rho, phi = xi[:3], xi[3:]
    zero = torch.zeros((), dtype=xi.dtype)
    hat = torch.stack([
        torch.stack([zero, -phi[2], phi[1], rho[0]]),
        torch.stack([phi[2], zero, -phi[0], rho[1]]),
        torch.stack([-phi[1], phi[0], zero, rho[2]]),
        torch.stack([zero, zero, zero, zero]),
    ])
    return hat


def _optimise(real: RGBDFrame, field, T_world_cam_est: np.ndarray, uv: np.ndarray, depth0: np.ndarray,
              config: PhotometricConfig) -> np.ndarray | None:
    """Adam on the twist; returns the refined ``T_world_cam`` (4, 4) or None if non-finite."""
    K = real.intrinsics
    device = field.device
    generator = torch.Generator().manual_seed(config.seed)
    # Camera-frame directions with unit z (t along a ray is then the z-depth).
    dirs_cam = torch.as_tensor(np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy,
                                         np.ones(len(uv))], axis=1), dtype=torch.float32, device=device)
    target = torch.as_tensor(real.rgb[uv[:, 1], uv[:, 0]], dtype=torch.float32, device=device) / 255.0
    depth = torch.as_tensor(depth0, device=device)
    # Pose relative to the grid's first vertex in float64, so float32 keeps precision.
    T_local = torch.as_tensor(T_world_cam_est, dtype=torch.float64).clone()
    T_local[:3, 3] -= torch.as_tensor(field.grid_min, dtype=torch.float64)
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    optimiser = torch.optim.Adam([xi], lr=config.lr)
    gamma = config.lr_decay ** (1.0 / max(config.iterations, 1))
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimiser, gamma)
    offsets = torch.linspace(-1.0, 1.0, config.samples, device=device)
    dt = 2.0 * config.window_m / (config.samples - 1)
    for _ in range(config.iterations):
        pick = torch.randint(len(uv), (min(config.rays_per_step, len(uv)),), generator=generator)
        T = (T_local @ torch.linalg.matrix_exp(_twist_matrix(xi))).to(torch.float32).to(device)
        dirs = dirs_cam[pick] @ T[:3, :3].T
        t = depth[pick, None] + config.window_m * offsets[None, :]
        points = T[:3, 3] + t[..., None] * dirs[:, None, :]
        colour, opacity, expected = _volume_render(field, points, dirs, dt, t)
        used = opacity.detach() > 0.5
        if int(used.sum()) < 16:
            break
        pred = colour[used] / opacity[used, None]
        observed = target[pick][used]
        if config.exposure:
            observed = _exposure_matched(observed, pred.detach())
        loss = torch.mean((pred - observed) ** 2)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        scheduler.step()
        with torch.no_grad():
            # Re-centre each ray's window on where its surface now is.
            depth[pick[used]] = expected[used].detach()
    with torch.no_grad():
        T = T_local @ torch.linalg.matrix_exp(_twist_matrix(xi))
        T[:3, 3] += torch.as_tensor(field.grid_min, dtype=torch.float64)
        T = T.numpy()
    return T if np.all(np.isfinite(T)) else None


def _volume_render(field, points: torch.Tensor, dirs: torch.Tensor, dt: float, t: torch.Tensor):
    """Colour (N, 3), opacity (N,) and expected z-depth (N,) of rays with sample points
    ``points`` (N, S, 3) local metres at z-depths ``t`` (N, S), spacing ``dt``."""
    sigma = field.sigma_from_raw(field.raw_density_local(points))
    tau = sigma * dt * dirs.norm(dim=-1, keepdim=True)
    trans = torch.exp(-(torch.cumsum(tau, dim=1) - tau))
    weights = trans * (1.0 - torch.exp(-tau))
    rgb = field.rgb_local(points)
    opacity = weights.sum(dim=1)
    colour = (weights[..., None] * rgb).sum(dim=1)
    expected = (weights * t).sum(dim=1) / opacity.clamp(min=1e-6)
    return colour, opacity, expected


def _exposure_matched(observed: torch.Tensor, rendered: torch.Tensor) -> torch.Tensor:
    """The observed colours (N, 3) after the per-channel affine map that best fits them to
    the rendered ones (least squares; a near-constant channel keeps gain 1)."""
    mean_o, mean_r = observed.mean(dim=0), rendered.mean(dim=0)
    var_o = ((observed - mean_o) ** 2).mean(dim=0)
    cov = ((observed - mean_o) * (rendered - mean_r)).mean(dim=0)
    gain = torch.where(var_o > 1e-6, cov / var_o.clamp(min=1e-6), torch.ones_like(var_o))
    gain = gain.clamp(0.5, 2.0)
    return (observed - mean_o) * gain + mean_r
