"""Smooth camera trajectories through a simulated room, with exact derivatives for the IMU.

A trajectory is a continuous function of time ``t`` (seconds) to ``T_world_cam`` (OpenCV
camera, world +Z up). Two kinds:

* ``traverse``: a gently curving walk from one end of the free floor area to the other,
  looking roughly ahead; it never comes back to a place it has passed.
* ``mapping``: a survey for training a field: the camera circles the free area twice at two
  heights, looking outward at the walls and furniture with a sweeping yaw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nap3d_graph.conventions import exp_se3, exp_so3, log_so3

from .scene import Scene

__all__ = ["Trajectory", "traverse_trajectory", "mapping_trajectory", "make_trajectory", "R_world_cam_from_angles",
           "ImagelessWalk", "smooth_noise"]

# Camera looking along world +X, level: x_cam = -Y_world (right), y_cam = -Z_world (down).
_R_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def R_world_cam_from_angles(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Camera orientation: heading ``yaw`` about world +Z, ``pitch`` about the camera's x axis
    (positive tilts the optical axis *down*), ``roll`` about its optical axis. Radians."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    # A rotation of -pitch about x_cam (y down): positive pitch tilts the optical axis down. (Its
    # first docstring said up; the single-room paths were written to that and look up, see
    # mapping_trajectory. Kept as it is: every simulated recording measured so far depends on it.)
    return Rz @ _R_LEVEL @ exp_so3(np.array([-pitch, 0.0, 0.0])) @ exp_so3(np.array([0.0, 0.0, roll]))


@dataclass
class Trajectory:
    """``position(t)`` (3,) and ``angles(t)`` (yaw, pitch, roll) as smooth functions of time."""

    position_fn: object
    angles_fn: object
    duration_s: float
    kind: str

    def T_world_cam(self, t: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = R_world_cam_from_angles(*self.angles_fn(t))
        T[:3, 3] = self.position_fn(t)
        return T

    def poses(self, stamps: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses at times (N,)."""
        return np.stack([self.T_world_cam(float(t)) for t in stamps])

    # Central differences on analytic functions: step 1e-3 s keeps truncation error
    # (~h^2) and round-off (~eps/h^2) both far below the IMU noise.
    def acceleration_world(self, t: float, h: float = 1e-3) -> np.ndarray:
        return (self.position_fn(t + h) - 2 * self.position_fn(t) + self.position_fn(t - h)) / h**2

    def velocity_world(self, t: float, h: float = 1e-4) -> np.ndarray:
        return (self.position_fn(t + h) - self.position_fn(t - h)) / (2 * h)

    def angular_velocity_cam(self, t: float, h: float = 1e-4) -> np.ndarray:
        """Body (camera-frame) angular velocity in rad/s: ``R^T dR/dt``."""
        R0 = R_world_cam_from_angles(*self.angles_fn(t - h))
        R1 = R_world_cam_from_angles(*self.angles_fn(t + h))
        return log_so3(R0.T @ R1) / (2 * h)


def smooth_noise(rng: np.random.Generator, n_terms: int = 3):
    """A random smooth function of a scalar in about [-1, 1]: a few low-frequency sines."""
    freqs = rng.uniform(0.5, 2.0, n_terms)
    phases = rng.uniform(0, 2 * np.pi, n_terms)
    amps = rng.dirichlet(np.ones(n_terms))
    return lambda s: float(np.sum(amps * np.sin(freqs * s + phases)))


def traverse_trajectory(scene: Scene, rng: np.random.Generator, duration_s: float = 12.0) -> Trajectory:
    """A walk along the longer axis of the free area in ``duration_s``, never revisiting a place."""
    (x0, x1), (y0, y1) = scene.free_xy_m
    long_x = (x1 - x0) >= (y1 - y0)
    start = np.array([x0 + 0.1, (y0 + y1) / 2]) if long_x else np.array([(x0 + x1) / 2, y0 + 0.1])
    end = np.array([x1 - 0.1, (y0 + y1) / 2]) if long_x else np.array([(x0 + x1) / 2, y1 - 0.1])
    if rng.random() < 0.5:
        start, end = end, start
    axis = end - start
    length = float(np.linalg.norm(axis))
    axis /= length
    lateral = np.array([-axis[1], axis[0]])
    half_width = 0.4 * ((y1 - y0) if long_x else (x1 - x0)) / 2
    wiggle = smooth_noise(rng)
    yaw_sweep = smooth_noise(rng)
    bob = smooth_noise(rng)
    heading = float(np.arctan2(axis[1], axis[0]))
    duration = float(duration_s)
    height = float(rng.uniform(1.2, 1.5))

    def s_of(t: float) -> float:
        # Ease in and out so velocity and acceleration start and end at zero.
        u = np.clip(t / duration, 0.0, 1.0)
        return length * (u - np.sin(2 * np.pi * u) / (2 * np.pi))

    def position(t: float) -> np.ndarray:
        s = s_of(t)
        xy = start + axis * s + lateral * half_width * wiggle(2.0 * s / length * np.pi)
        return np.array([xy[0], xy[1], height + 0.05 * bob(t)])

    def angles(t: float) -> tuple[float, float, float]:
        s = s_of(t)
        return (heading + np.radians(35.0) * yaw_sweep(1.5 * s), np.radians(8.0) * bob(0.7 * t + 1.0),
                np.radians(3.0) * bob(0.5 * t + 2.0))

    return Trajectory(position, angles, duration, "traverse")


def mapping_trajectory(scene: Scene, rng: np.random.Generator, duration_s: float = 30.0) -> Trajectory:
    """Two loops around the free area in ``duration_s``, rising between two heights,
    looking outward with a yaw sweep."""
    (x0, x1), (y0, y1) = scene.free_xy_m
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    rx, ry = 0.45 * (x1 - x0), 0.45 * (y1 - y0)
    loops = 2.0
    duration = float(duration_s)
    phase0 = float(rng.uniform(0, 2 * np.pi))
    sweep = smooth_noise(rng)
    heights = (float(rng.uniform(1.0, 1.2)), float(rng.uniform(1.5, 1.7)))

    def angle_of(t: float) -> float:
        return phase0 + 2 * np.pi * loops * t / duration

    def position(t: float) -> np.ndarray:
        a = angle_of(t)
        u = np.clip(t / duration, 0.0, 1.0)
        z = heights[0] + (heights[1] - heights[0]) * 0.5 * (1 - np.cos(np.pi * u))
        return np.array([centre[0] + rx * np.cos(a), centre[1] + ry * np.sin(a), z])

    def angles(t: float) -> tuple[float, float, float]:
        a = angle_of(t)
        # Outward, swinging +-80 deg so walls, furniture and the far side are all seen.
        yaw = a + np.radians(80.0) * sweep(3.0 * a)
        # Up 2 to 34 deg (written to look down, with the sign the convention's first docstring
        # gave; kept, since every single-room figure was measured on this path).
        pitch = np.radians(-18.0) + np.radians(16.0) * np.sin(1.7 * a)
        return (yaw, pitch, 0.0)

    return Trajectory(position, angles, duration, "mapping")


def make_trajectory(kind: str, scene: Scene, rng: np.random.Generator, duration_s: float) -> Trajectory:
    if kind == "traverse":
        return traverse_trajectory(scene, rng, duration_s)
    if kind == "mapping":
        return mapping_trajectory(scene, rng, duration_s)
    raise ValueError(f"unknown path kind {kind!r}; use 'traverse' or 'mapping'")


class ImagelessWalk:
    """A long random walk as a sequence without images: ``timestamps`` (``fps`` Hz) and
    ``T_world_cam_gt`` (1 cm forward per frame, 2 mrad/2 mm jitter), for runs that read no
    frame (no field, injected odometry noise): the graph's cost on 50,000 keyframes in
    seconds. Reading a frame raises."""

    def __init__(self, n: int, fps: float = 30.0, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.timestamps = np.arange(n) / fps
        self.depth_timestamps = self.timestamps.copy()
        T = [np.eye(4)]
        for _ in range(n - 1):
            T.append(T[-1] @ exp_se3(np.r_[rng.normal(0, 0.002, 3), 0.01, rng.normal(0, 0.002, 2)]))
        self.T_world_cam_gt = np.stack(T)
        self.path = self.name = "imageless walk"

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i):
        raise RuntimeError("an imageless walk has no frames to read")
