"""Training settings of a grid field (:func:`~nap3d_graph.fields.training.train_field`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from nap3d_graph.camera import DEPTH_SIGMA_Z2_PER_M

__all__ = ["TrainConfig"]


@dataclass
class TrainConfig:
    """Training settings; every field has a default that works for a room-sized scene.

    Geometry: ``voxel_size_m`` (density grid; colour is ``color_voxel_ratio`` times finer),
    ``coarse_voxel_size_m`` (an optional first stage on a coarser grid, for
    ``coarse_fraction`` of the budget; off by default since ``init_from_depth`` starts the
    grid from the back-projected depth). Budget: ``minutes`` of optimisation
    (loading and evaluation not counted), or ``max_steps`` if set. Frames: every ``every``-th
    frame is used for training; ``eval_frames`` held-out frames are evaluated.
    Sampling: ``rays_per_step``, ``free_samples`` and ``window_samples`` per ray; the window
    half-width is ``max(window_min_m, window_sigmas * depth_sigma_z2 * z^2)``.
    ``threads``: torch CPU threads during training (1: see ``nap3d_graph.torch_threads``; None keeps
    torch's setting). ``slab_m``: ``(ax, ay, az, from_m, to_m)`` or None: only depth points ``p``
    (training frame, metres) with ``from_m <= a . p <= to_m`` train the grid and set its bounds
    (a submap's part of a floor; ``from_m`` / ``to_m`` None: unbounded on that side).
    """

    voxel_size_m: float = 0.03
    color_voxel_ratio: float = 1.5
    coarse_voxel_size_m: float | None = None
    coarse_fraction: float = 0.2
    minutes: float = 5.0
    max_steps: int | None = None
    every: int = 1
    eval_frames: int = 8
    seed: int = 0
    rays_per_step: int = 4096
    patch_size: int = 8
    free_samples: int = 8
    window_samples: int = 16
    window_min_m: float = 0.04
    window_sigmas: float = 3.0
    depth_sigma_z2: float = DEPTH_SIGMA_Z2_PER_M
    min_depth_m: float = 0.1
    max_depth_m: float = 8.0
    bounds_margin_m: float = 0.15
    lr_density: float = 1.0
    lr_color: float = 0.1
    lr_final_ratio: float = 0.1
    weight_rgb: float = 1.0
    weight_window: float = 1.0
    weight_near: float = 5.0
    weight_empty: float = 1.0
    weight_opacity: float = 0.01
    color_weight_eps: float = 2e-3
    init_from_depth: bool = True
    init_density_raw: float = 14.0
    init_min_weight: float = 1.0
    init_stride: int = 2
    device: str | None = None
    threads: int | None = 1
    slab_m: tuple | None = None

    def to_dict(self) -> dict:
        return asdict(self)
