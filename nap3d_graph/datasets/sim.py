"""Sequences written by our simulator (``nap3d-graph simulate``).

A simulated folder is a TUM RGB-D sequence (it reads through :class:`TumSequence` with no
special case) plus the simulator's extras: ``odometry.txt`` (drifting odometry, TUM format,
at the colour stamps), ``imu.txt`` (``timestamp ax ay az gx gy gz``, camera frame),
``scene.json`` (the room, which rebuilds the exact oracle field) and ``sim.json`` (the
settings). :class:`SimSequence` loads those too.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nap3d_graph.datasets.tum import TumSequence
from nap3d_graph.errors import DatasetError
from nap3d_graph.sims.scene import OracleField
from nap3d_graph.sims.scene_file import load_scene
from nap3d_graph.trajectory import interpolate_poses, read_tum_trajectory

__all__ = ["SimSequence"]


class SimSequence(TumSequence):
    """A simulated sequence: everything :class:`TumSequence` gives, and

    ``T_world_cam_odom`` (N, 4, 4) drifting odometry at the frame (colour) stamps,
    ``imu`` dict of ``stamps`` (M,), ``accel`` (M, 3) m/s^2 and ``gyro`` (M, 3) rad/s,
    ``scene`` (:class:`nap3d_graph.sims.scene.Scene`), ``config`` (the ``sim.json`` dict)
    and :meth:`oracle_field`. Same constructor as :class:`TumSequence`.
    """

    simulated = True

    def __init__(self, path, *args, **kwargs):
        folder = Path(path)
        scene_path = folder / "scene.json"
        if folder.is_dir() and not scene_path.is_file():
            raise DatasetError(
                f"{folder}: not a simulated sequence (no scene.json); read it with TumSequence"
            )
        super().__init__(path, *args, **kwargs)


        try:
            self.scene = load_scene(scene_path)
        except ValueError as exc:
            raise DatasetError(str(exc)) from None
        self.config = self._read_config(self.path / "sim.json")
        self.T_world_cam_odom = self._read_odometry(self.path / "odometry.txt")
        self.imu = self._read_imu(self.path / "imu.txt")

    def oracle_field(self):
        """The exact radiance field of the simulated room (``OracleField(scene)``)."""
        return OracleField(self.scene)

    def __repr__(self) -> str:
        return f"SimSequence({str(self.path)!r}, frames={len(self)}, undistort={self.undistort})"

    # --- extras ---

    @staticmethod
    def _read_config(path: Path) -> dict:
        try:
            config = json.loads(path.read_text())
        except FileNotFoundError:
            raise DatasetError(f"{path}: file not found") from None
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{path}: cannot read simulator settings ({exc})") from None
        if not isinstance(config, dict):
            raise DatasetError(f"{path}: expected a JSON object of simulator settings")
        return config

    def _read_odometry(self, path: Path) -> np.ndarray:
        if not path.is_file():
            raise DatasetError(f"{path}: file not found")
        stamps, T = read_tum_trajectory(path)
        # Written at the colour stamps, so this is exact; interpolation only guards against
        # a list that was edited (a frame between two odometry poses is still well defined).
        try:
            T_frames = interpolate_poses(stamps, T, self.timestamps, max_gap=np.inf)
        except DatasetError as exc:
            raise DatasetError(f"{path}: {exc}") from None
        missing = ~np.all(np.isfinite(T_frames), axis=(1, 2))
        if np.any(missing):
            raise DatasetError(
                f"{path}: odometry does not cover {int(missing.sum())} of {len(missing)} frames "
                f"(first at t={self.timestamps[missing][0]:.6f})"
            )
        return T_frames

    @staticmethod
    def _read_imu(path: Path) -> dict[str, np.ndarray]:
        if not path.is_file():
            raise DatasetError(f"{path}: file not found")
        try:
            rows = np.loadtxt(path, comments="#", ndmin=2, dtype=float)
        except ValueError as exc:
            raise DatasetError(f"{path}: cannot parse IMU samples ({exc})") from None
        if rows.shape[0] == 0 or rows.shape[1] != 7:
            raise DatasetError(
                f"{path}: expected rows 'timestamp ax ay az gx gy gz', got shape {rows.shape}"
            )
        if not np.all(np.isfinite(rows)):
            raise DatasetError(f"{path}: non-finite IMU values")
        if np.any(np.diff(rows[:, 0]) <= 0):
            raise DatasetError(f"{path}: IMU timestamps are not strictly increasing")
        return {"stamps": rows[:, 0].copy(), "accel": rows[:, 1:4].copy(), "gyro": rows[:, 4:7].copy()}
