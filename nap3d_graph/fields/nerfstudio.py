"""The nerfstudio bridge: export posed RGB-D as a nerfstudio dataset, and render trained
nerfstudio models through the field protocol.

Conventions at this boundary (and only here):

* nerfstudio cameras are OpenGL (x right, y up, z back); ours are OpenCV. A camera-to-world
  pose converts by flipping the camera's y and z axes (:func:`opencv_to_opengl_pose`).
* nerfstudio puts pixel centres at ``i + 0.5`` (``Cameras.get_image_coords(pixel_offset=0.5)``,
  COLMAP's convention); ours are at integer ``i`` (OpenCV). ``transforms.json`` therefore
  stores ``cx + 0.5`` and ``cy + 0.5`` (:func:`nerfstudio_intrinsics`).
* Training maps the ``transforms.json`` world into the model frame with the dataparser
  transform and scale saved in ``dataparser_transforms.json``: ``T_model = T_dp @ T_world``,
  then the translation times ``scale`` (:func:`world_to_model_pose`).
* A model's ``depth`` / ``expected_depth`` is the distance along the *unit* ray, in scaled
  model units: ``z [m] = depth / ray_norm / scale`` with ``ray_norm = |((u-cx)/fx, (v-cy)/fy, 1)|``
  (:func:`model_depth_to_z_m`). Its ``accumulation`` is our opacity.
* Depth PNGs are uint16 millimetres (nerfstudio's default ``depth_unit_scale_factor`` 1e-3),
  0 = missing (:func:`depth_to_png_mm`).

nerfstudio itself is an optional extra, imported only inside :func:`load_nerfstudio_field`.
Its traps (see DESIGN.md) are handled there: checkpoints need ``weights_only=False`` on
torch >= 2.6 (we load the user's own checkpoint ourselves); building a model builds LPIPS,
which downloads AlexNet weights (replaced by a stub: rendering never uses it); depth-nerfacto
without depth files runs ZoeDepth, a download (we refuse up front and say why); a checkpoint
trained with tiny-cuda-nn does not load into the torch fallback (clear message).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nap3d_graph.camera import Intrinsics, RenderedView
from nap3d_graph.conventions import (
    T_opencv_to_opengl,
    T_opengl_to_opencv,
    inv_T,
    ray_length_to_z_depth,
    z_depth_to_ray_length,
)

from .base import FieldError

__all__ = [
    "INSTALL_HINT",
    "DataparserTransform",
    "opencv_to_opengl_pose",
    "opengl_to_opencv_pose",
    "nerfstudio_intrinsics",
    "intrinsics_from_nerfstudio",
    "read_dataparser_transforms",
    "world_to_model_pose",
    "model_to_world_pose",
    "model_depth_to_z_m",
    "z_m_to_model_depth",
    "depth_to_png_mm",
    "png_mm_to_depth",
    "NerfstudioField",
    "load_nerfstudio_field",
]

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'nap3d-graph[nerfstudio]'  (or: pip install nerfstudio)"


# --- pure conversions ---------------------------------------------------------------------------


# The camera-frame flip lives in conventions (the one place); these names are what a
# nerfstudio user looks for: transforms.json stores OpenGL (x right, y up, z back) poses.
opencv_to_opengl_pose = T_opencv_to_opengl
opengl_to_opencv_pose = T_opengl_to_opencv


def nerfstudio_intrinsics(intrinsics: Intrinsics) -> dict:
    """``transforms.json`` camera keys for an undistorted pinhole camera.

    nerfstudio's pixel centres are at ``i + 0.5``, ours at ``i``: the principal point moves
    by half a pixel.
    """
    if any(d != 0.0 for d in intrinsics.distortion):
        raise FieldError("export needs undistorted images (the sequence still reports lens distortion)")
    return {
        "camera_model": "OPENCV",
        "fl_x": float(intrinsics.fx),
        "fl_y": float(intrinsics.fy),
        "cx": float(intrinsics.cx) + 0.5,
        "cy": float(intrinsics.cy) + 0.5,
        "w": int(intrinsics.width),
        "h": int(intrinsics.height),
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
    }


def intrinsics_from_nerfstudio(meta: dict) -> Intrinsics:
    """Our :class:`Intrinsics` from ``transforms.json`` keys (inverse of :func:`nerfstudio_intrinsics`)."""
    try:
        return Intrinsics(float(meta["fl_x"]), float(meta["fl_y"]), float(meta["cx"]) - 0.5,
                          float(meta["cy"]) - 0.5, int(meta["w"]), int(meta["h"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise FieldError(f"transforms.json camera is incomplete ({exc})") from None


@dataclass(frozen=True)
class DataparserTransform:
    """nerfstudio's world -> model mapping: ``T_model = transform @ T_world``, then the
    translation times ``scale``. ``transform`` is 4x4 (the file stores its top 3x4 rows)."""

    transform: np.ndarray
    scale: float

    def __post_init__(self) -> None:
        T = np.asarray(self.transform, dtype=np.float64)
        if T.shape == (3, 4):
            T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise FieldError(f"dataparser transform must be a finite 3x4 or 4x4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
            raise FieldError("dataparser transform is not a rotation plus translation")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise FieldError(f"dataparser scale must be positive, got {self.scale}")
        object.__setattr__(self, "transform", T)
        object.__setattr__(self, "scale", float(self.scale))


def read_dataparser_transforms(path) -> DataparserTransform:
    """Read ``dataparser_transforms.json`` (``{"transform": 3x4, "scale": s}``) next to a
    nerfstudio ``config.yml``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        return DataparserTransform(np.asarray(data["transform"], dtype=np.float64), float(data["scale"]))
    except FileNotFoundError:
        raise FieldError(f"{path}: not found (nerfstudio writes it beside config.yml when training starts)") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FieldError(f"{path}: not a valid dataparser_transforms.json ({exc})") from None


def world_to_model_pose(T_world_cam_cv: np.ndarray, dataparser: DataparserTransform) -> np.ndarray:
    """Our pose (OpenCV camera, world frame of ``transforms.json``) -> nerfstudio's
    ``camera_to_worlds`` in the model frame (OpenGL camera, scaled translation)."""
    T = dataparser.transform @ opencv_to_opengl_pose(T_world_cam_cv)
    T = T.copy()
    T[..., :3, 3] *= dataparser.scale
    return T


def model_to_world_pose(T_model_cam_gl: np.ndarray, dataparser: DataparserTransform) -> np.ndarray:
    """Inverse of :func:`world_to_model_pose`."""
    T = np.asarray(T_model_cam_gl, dtype=np.float64).copy()
    T[..., :3, 3] /= dataparser.scale
    return opengl_to_opencv_pose(inv_T(dataparser.transform) @ T)


def model_depth_to_z_m(depth_model: np.ndarray, ray_norms: np.ndarray, scale: float) -> np.ndarray:
    """nerfstudio ray-length depth in model units (H, W) -> z-depth in metres (H, W).

    ``ray_norms``: per-pixel ``|((u-cx)/fx, (v-cy)/fy, 1)|`` (:meth:`Intrinsics.ray_norms`).
    """
    return ray_length_to_z_depth(np.asarray(depth_model, dtype=np.float64), ray_norms) / float(scale)


def z_m_to_model_depth(z_m: np.ndarray, ray_norms: np.ndarray, scale: float) -> np.ndarray:
    """Inverse of :func:`model_depth_to_z_m`."""
    return z_depth_to_ray_length(np.asarray(z_m, dtype=np.float64), ray_norms) * float(scale)


def depth_to_png_mm(depth_m: np.ndarray) -> np.ndarray:
    """z-depth metres (H, W), 0/NaN missing -> uint16 millimetres, 0 missing (65.535 m max)."""
    depth = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    depth = np.where(depth > 0, depth, 0.0)
    return np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)


def png_mm_to_depth(depth_mm: np.ndarray) -> np.ndarray:
    """uint16 millimetres -> float32 metres (0 stays missing)."""
    return np.asarray(depth_mm).astype(np.float32) / np.float32(1000.0)


# --- trained models -------------------------------------------------------------------------------


class NerfstudioField:
    """A trained nerfstudio model behind the field protocol.

    model: the pipeline's model (``pipeline.model``); dataparser: its world -> model mapping;
    cameras_factory: ``f(camera_to_worlds (1, 3, 4) tensor, fx, fy, cx, cy, width, height)``
    building a nerfstudio ``Cameras`` (default: nerfstudio's); bounds: (2, 3) world box.
    ``depth_key`` picks the model output used as depth: ``"expected_depth"`` (default, the
    weighted mean termination distance, which the paper found more accurate: averaging
    smooths the noise that the median ``"depth"`` is exposed to) or ``"depth"``. A missing
    output is an error, never a silent substitute: neither the other depth nor an opacity
    of 1 where the model gives no ``accumulation`` is safe to align against.
    """

    def __init__(self, model, dataparser: DataparserTransform, name: str = "nerfstudio",
                 bounds: np.ndarray | None = None, depth_key: str = "expected_depth", cameras_factory=None):
        self.model = model
        self.dataparser = dataparser
        self.name = name
        self._bounds = None if bounds is None else np.asarray(bounds, dtype=np.float64).reshape(2, 3)
        self.depth_key = depth_key
        self._cameras_factory = cameras_factory or _nerfstudio_cameras

    @property
    def bounds(self) -> np.ndarray:
        if self._bounds is None:
            return np.array([[-np.inf] * 3, [np.inf] * 3])
        return self._bounds

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> RenderedView:
        import torch

        intrinsics = intrinsics.without_distortion()
        T_model = world_to_model_pose(np.asarray(T_world_cam, dtype=np.float64), self.dataparser)
        ns = nerfstudio_intrinsics(intrinsics)
        c2w = torch.as_tensor(T_model[:3, :4], dtype=torch.float32)[None]
        camera = self._cameras_factory(c2w, ns["fl_x"], ns["fl_y"], ns["cx"], ns["cy"], ns["w"], ns["h"])
        with torch.no_grad():
            if hasattr(self.model, "get_outputs_for_camera"):
                outputs = self.model.get_outputs_for_camera(camera)
            else:  # nerfstudio < 1.0
                bundle = camera.generate_rays(camera_indices=0, keep_shape=True)
                outputs = self.model.get_outputs_for_camera_ray_bundle(bundle)
        h, w = intrinsics.height, intrinsics.width

        def image(key: str, channels: int) -> np.ndarray:
            if key not in outputs:
                hint = " (choose another with depth_key=...)" if key == self.depth_key else ""
                raise FieldError(f"nerfstudio model output has no {key!r}{hint}; it has {sorted(outputs)}")
            value = outputs[key].detach().float().cpu().numpy()
            return value.reshape(h, w, channels) if channels > 1 else value.reshape(h, w)

        rgb = np.clip(image("rgb", 3), 0.0, 1.0)
        z = model_depth_to_z_m(image(self.depth_key, 1), intrinsics.ray_norms(), self.dataparser.scale)
        opacity = np.clip(image("accumulation", 1), 0.0, 1.0)
        z = np.where(np.isfinite(z) & (opacity > 1e-3), z, 0.0)
        return RenderedView(
            rgb=np.round(rgb * 255.0).astype(np.uint8),
            depth_m=z.astype(np.float32),
            opacity=opacity.astype(np.float32),
            intrinsics=intrinsics,
        )


def _nerfstudio_cameras(c2w, fx, fy, cx, cy, width, height):
    from nerfstudio.cameras.cameras import Cameras, CameraType

    return Cameras(camera_to_worlds=c2w, fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height,
                   camera_type=CameraType.PERSPECTIVE)


def _require_nerfstudio() -> None:
    if importlib.util.find_spec("nerfstudio") is None:
        raise FieldError(f"rendering a nerfstudio model needs nerfstudio, which is not installed: {INSTALL_HINT}")


@contextlib.contextmanager
def _no_lpips_download():
    """Stub LPIPS in nerfstudio's model modules while a model is built: constructing it
    downloads AlexNet weights, and rendering never uses it."""
    import torch

    class _NoLPIPS(torch.nn.Module):
        def __init__(self, *args, **kwargs):
            super().__init__()

        def forward(self, *args, **kwargs):  # pragma: no cover - never called when rendering
            raise RuntimeError("LPIPS is disabled in nap3d-graph's nerfstudio adapter")

    patched = []
    for name, module in list(sys.modules.items()):
        if name.startswith("nerfstudio.") and hasattr(module, "LearnedPerceptualImagePatchSimilarity"):
            patched.append((module, module.LearnedPerceptualImagePatchSimilarity))
            module.LearnedPerceptualImagePatchSimilarity = _NoLPIPS
    try:
        yield
    finally:
        for module, original in patched:
            module.LearnedPerceptualImagePatchSimilarity = original


def _check_depth_files(data_dir: Path) -> None:
    """depth-nerfacto runs ZoeDepth (a download) for frames without depth: refuse instead."""
    transforms = data_dir / "transforms.json"
    if not transforms.is_file():
        return
    try:
        frames = json.loads(transforms.read_text()).get("frames", [])
    except (OSError, ValueError):
        raise FieldError(f"{transforms}: not readable JSON") from None
    for frame in frames:
        rel = frame.get("depth_file_path")
        if rel is None or not (data_dir / rel).is_file():
            raise FieldError(
                f"{transforms}: frame {frame.get('file_path')} has no depth file "
                f"({rel or 'no depth_file_path'}); depth-nerfacto would download and run ZoeDepth "
                "to estimate it -- export the data with `nap3d-graph export-nerfstudio` so every frame has depth"
            )


def _latest_checkpoint(config_path: Path, config) -> Path:
    candidates = [config_path.parent / "nerfstudio_models"]
    with contextlib.suppress(Exception):
        candidates.append(Path(config.get_checkpoint_dir()))
    for folder in candidates:
        ckpts = sorted(folder.glob("step-*.ckpt")) if folder.is_dir() else []
        if ckpts:
            return ckpts[-1]
    raise FieldError(f"{config_path}: no nerfstudio_models/step-*.ckpt beside the config")


def load_nerfstudio_field(config_path, data_dir=None, device=None,
                          depth_key: str = "expected_depth") -> NerfstudioField:
    """Open a trained nerfstudio model (its ``config.yml``) as a field.

    ``data_dir``: the training data folder when it moved since training (nerfstudio needs it
    to rebuild the pipeline). ``device``: CUDA when available, else CPU. Raises
    :class:`FieldError` with an install hint when nerfstudio is missing.
    """
    config_path = Path(config_path)
    if not config_path.is_file():
        raise FieldError(f"{config_path}: no such nerfstudio config")
    _require_nerfstudio()
    dataparser = read_dataparser_transforms(config_path.parent / "dataparser_transforms.json")

    import torch
    import yaml

    try:
        # The config is nerfstudio's own YAML with python tags: it rebuilds their config classes.
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    except Exception as exc:
        raise FieldError(f"{config_path}: not a loadable nerfstudio config ({str(exc).splitlines()[0]})") from None
    datamanager = config.pipeline.datamanager
    if data_dir is not None:
        datamanager.data = Path(data_dir)
        if getattr(datamanager, "dataparser", None) is not None:
            datamanager.dataparser.data = Path(data_dir)
    data = Path(getattr(datamanager, "data", None) or getattr(datamanager.dataparser, "data", ""))
    if not data.exists():
        raise FieldError(f"{config_path}: training data {data} not found; pass data_dir= the exported folder")
    if data.is_dir():
        _check_depth_files(data)
    device = torch.device(device) if device else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    checkpoint = _latest_checkpoint(config_path, config)
    try:
        with _no_lpips_download():
            pipeline = config.pipeline.setup(device=device, test_mode="inference")
        pipeline.eval()
        # torch >= 2.6 defaults to weights_only=True, which nerfstudio checkpoints (pickled
        # numpy scalars, optimizer state) do not pass; this is the user's own training output.
        state = torch.load(checkpoint, map_location=device, weights_only=False)
        pipeline.load_pipeline(state["pipeline"], state.get("step", 0))
    except FieldError:
        raise
    except (ImportError, RuntimeError, KeyError) as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if "tinycudann" in message or "tcnn" in message or ".params" in message:
            raise FieldError(
                f"{checkpoint}: trained with tiny-cuda-nn, whose weights do not load into nerfstudio's torch "
                "fallback; install tinycudann (CUDA) or retrain with --pipeline.model.implementation torch"
            ) from None
        raise FieldError(f"{checkpoint}: cannot load the nerfstudio model ({message[:300]})") from None
    bounds = _model_bounds(pipeline, dataparser)
    method = getattr(config, "method_name", None) or "model"
    return NerfstudioField(pipeline.model, dataparser, name=f"nerfstudio:{method}", bounds=bounds, depth_key=depth_key)


def _model_bounds(pipeline, dataparser: DataparserTransform) -> np.ndarray | None:
    """World box of the model's scene box (model units, OpenGL world) mapped back to metres."""
    try:
        aabb = pipeline.datamanager.train_dataparser_outputs.scene_box.aabb.detach().cpu().numpy()
    except AttributeError:
        return None
    corners = np.array([[aabb[i][0], aabb[j][1], aabb[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    T_inv = inv_T(dataparser.transform)
    world = (corners / dataparser.scale) @ T_inv[:3, :3].T + T_inv[:3, 3]
    return np.stack([world.min(axis=0), world.max(axis=0)])

