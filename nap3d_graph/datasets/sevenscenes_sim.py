"""Write a simulated recording in the 7-Scenes layout, with depth *not* registered to colour.

A Kinect v1 as 7-Scenes has it: colour and depth come from two cameras, the depth camera
``T_colour_depth`` from the colour one with its own focal length, and the poses written are
the depth camera's. What :class:`~nap3d_graph.datasets.SevenScenesSequence` must undo, with
the truth known (``sim.json``). No image noise or motion blur: what is tested is the layout
and the registration.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nap3d_graph.camera import Intrinsics
from nap3d_graph.datasets.sevenscenes import (
    NOMINAL_COLOUR_CAMERA,
    NOMINAL_DEPTH_CAMERA,
    SEVENSCENES_FPS,
    write_sevenscenes_frame,
)
from nap3d_graph.sims.scene import make_scene
from nap3d_graph.sims.trajectories import make_trajectory

__all__ = ["simulate_sevenscenes"]


def simulate_sevenscenes(out_dir, frames: int = 40, scene_seed: int = 11, seed: int = 0, frame_step: int = 2,
                         colour: Intrinsics = NOMINAL_COLOUR_CAMERA, depth: Intrinsics = NOMINAL_DEPTH_CAMERA,
                         T_colour_depth: np.ndarray | None = None, write_intrinsics: bool = True) -> Path:
    """Render ``frames`` frames of a traversal of room ``scene_seed`` into ``out_dir`` (created):
    frame numbers 0, ``frame_step``, 2 ``frame_step``... at 30 Hz, colour (PNG) through
    ``colour`` at the colour camera's pose, depth through ``depth`` at
    ``T_world_depth = T_world_colour @ T_colour_depth``, whose pose is written. With
    ``write_intrinsics`` the depth camera goes into ``camera-intrinsics.txt``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    T_colour_depth = np.eye(4) if T_colour_depth is None else np.asarray(T_colour_depth, dtype=float)
    scene = make_scene(scene_seed)
    numbers = np.arange(frames) * frame_step
    t = numbers / SEVENSCENES_FPS
    trajectory = make_trajectory("traverse", scene, np.random.default_rng(seed), float(t[-1]))
    for k, T_world_colour in zip(numbers, trajectory.poses(t)):
        rgb01, _, _ = scene.render(T_world_colour, colour)
        T_world_depth = T_world_colour @ T_colour_depth
        depth_m = scene.render_depth(T_world_depth, depth)
        write_sevenscenes_frame(out, int(k), np.round(rgb01 * 255).astype(np.uint8), depth_m, T_world_depth)
    if write_intrinsics:
        np.savetxt(out / "camera-intrinsics.txt", depth.K, fmt="%.18e")
    (out / "sim.json").write_text(json.dumps({"generator": "nap3d_graph.datasets.sevenscenes_sim", "scene_seed": scene_seed,
                                              "seed": seed, "frames": frames, "frame_step": frame_step,
                                              "colour": colour.to_dict(), "depth": depth.to_dict(),
                                              "T_colour_depth": T_colour_depth.tolist()}, indent=1))
    return out
