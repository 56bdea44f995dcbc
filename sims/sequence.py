"""Write a simulated RGB-D sequence in the TUM RGB-D layout.

The folder reads back through :class:`nap3d_graph.datasets.TumSequence` with no special
case: ``rgb.txt``, ``depth.txt``, ``rgb/``, ``depth/`` (uint16, 5000 per metre, 0 = missing),
``groundtruth.txt`` (100 Hz plus the frame instants, so interpolation at a frame is exact)
and ``intrinsics.json``. The camera behaves like TUM's Kinect (:class:`CameraTiming`):
depth is captured 30 ms before the colour and stamped 15 ms after its capture, so its stamp
is ~15 ms before the colour's and association is needed; colour is blurred by the camera's
own motion during its exposure and its exposure and white balance drift from frame to frame
(:class:`ExposureNoise`); depth has flying pixels at edges. ``sim.json`` records all of it,
so a compensation can be checked against the exact truth. Extra files: ``odometry.txt`` (TUM,
drifting odometry at the colour stamps), ``imu.txt`` (``timestamp ax ay az gx gy gz``,
camera frame), ``imu_bias.txt`` (the biases those samples carry), ``scene.json`` (rebuilds the oracle
field) and ``sim.json`` (settings).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from nap3d_graph.camera import Intrinsics
from nap3d_graph.progress import progress_bar
from nap3d_graph.trajectory import Trajectory

from .building import make_building
from .floor_paths import floor_survey, floor_traverse
from .scene import make_scene, with_twin_posters
from .sensors import (
    CameraTiming,
    DepthNoise,
    ExposureNoise,
    ImuNoise,
    OdometryNoise,
    add_depth_noise,
    add_rgb_noise,
    blur_poses,
    drifting_odometry,
    exposure_gains,
    simulate_imu,
)
from .trajectories import make_trajectory

__all__ = ["SimConfig", "simulate_sequence", "default_intrinsics", "DEPTH_SCALE", "TIME_ORIGIN_S"]

log = logging.getLogger(__name__)

DEPTH_SCALE = 5000.0  # TUM: uint16 units per metre
TIME_ORIGIN_S = 1_700_000_000.0  # epoch-like stamps, as real recordings have
_GT_RATE_HZ = 100.0


def default_intrinsics(width: int = 640, height: int = 480) -> Intrinsics:
    """A Kinect-like pinhole camera (TUM's default 525 px focal length at 640x480)."""
    return Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480).scaled(width, height)


@dataclass
class SimConfig:
    frames: int = 150
    scene_seed: int = 0
    seed: int = 0
    path: str = "traverse"
    fps: float | None = None
    width: int = 640
    height: int = 480
    rgb_noise_sigma: float = 0.01
    depth: DepthNoise = field(default_factory=DepthNoise)
    timing: CameraTiming | None = field(default_factory=CameraTiming)
    exposure: ExposureNoise | None = field(default_factory=ExposureNoise)
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    imu: ImuNoise = field(default_factory=ImuNoise)
    #: "identical": one picture on two opposite walls (:func:`~nap3d_graph.sims.scene.with_twin_posters`);
    #: "different": two pictures there (its control); None: neither.
    twin_posters: str | None = None
    #: A floor of this many rooms in a row (:func:`~nap3d_graph.sims.building.make_building`,
    #: every third room a twin) instead of one room; None: one room (``scene_seed``'s).
    rooms: int | None = None
    #: A traverse across a floor: from ``start_room`` to ``end_room`` (None: the far end), first
    #: looking ``look_aside_deg`` to its left at the side wall (see :mod:`~nap3d_graph.sims.floor_paths`).
    start_room: int = 0
    end_room: int | None = None
    look_aside_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.fps is None:
            # A traversal is recorded at the camera's 15 Hz. A survey keeps every fourth frame of
            # a 15 Hz recording: its path (two loops round the room, sweeping +-80 deg) then takes
            # a realistic minute per 240 frames, turning ~50 deg/s, and the motion blur of its
            # frames stays what a careful user gets, not the smear of a 200 deg/s sweep.
            self.fps = 15.0 if self.path == "traverse" else 15.0 / 4

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in ("frames", "scene_seed", "seed", "path", "fps", "width",
                                             "height", "rgb_noise_sigma")}
        d["depth"] = self.depth.__dict__.copy()
        d["timing"] = None if self.timing is None else self.timing.to_dict()
        d["exposure"] = None if self.exposure is None else self.exposure.to_dict()
        d["odometry"] = self.odometry.to_dict()
        d["imu"] = self.imu.to_dict()
        if self.twin_posters is not None:  # only when set: every other sequence's record stays as it was
            d["twin_posters"] = self.twin_posters
        if self.rooms is not None:
            d.update(rooms=self.rooms, start_room=self.start_room, end_room=self.end_room,
                     look_aside_deg=self.look_aside_deg)
        return d


def _trajectory(config: SimConfig, scene, rng: np.random.Generator, duration_s: float):
    """The camera's path: through one room (:mod:`.trajectories`) or across a floor (:mod:`.floor_paths`)."""
    if config.rooms is None:
        return make_trajectory(config.path, scene, rng, duration_s)
    if config.path == "mapping":
        return floor_survey(scene, rng, duration_s)
    if config.path == "traverse":
        return floor_traverse(scene, rng, duration_s, config.start_room, config.end_room, config.look_aside_deg)
    raise ValueError(f"unknown path kind {config.path!r}; use 'traverse' or 'mapping'")


def _write_list(path: Path, header: str, stamps: np.ndarray, folder: str) -> None:
    lines = [f"# {header}", "# file: simulated by nap3d-graph", "# timestamp filename"]
    lines += [f"{t:.6f} {folder}/{t:.6f}.png" for t in stamps]
    path.write_text("\n".join(lines) + "\n")


def _render_and_write(job) -> None:
    """Render one sensor frame and write its two PNGs (runs in a worker process): colour
    averaged over the exposure's poses and scaled by the frame's gains, depth at its own
    capture pose."""
    import cv2

    scene, (colour_poses, gap_sigma), T_world_depth, gains, intrinsics, rgb_sigma, depth_noise, seed, rgb_path, \
        depth_path = job
    rng = np.random.default_rng(seed)
    rgb01 = np.mean([scene.render(T, intrinsics)[0] for T in colour_poses], axis=0)
    if gap_sigma > 0:
        rgb01 = cv2.GaussianBlur(rgb01, (0, 0), gap_sigma)
    rgb01 = np.clip(rgb01 * gains, 0.0, 1.0)
    depth_m = scene.render_depth(T_world_depth, intrinsics)
    rgb = add_rgb_noise(rgb01, rgb_sigma, rng)
    depth_noisy = add_depth_noise(depth_m, depth_noise, rng)
    depth_u16 = np.clip(np.round(depth_noisy * DEPTH_SCALE), 0, 65535).astype(np.uint16)
    if not (cv2.imwrite(rgb_path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)) and cv2.imwrite(depth_path, depth_u16)):
        raise OSError(f"could not write {rgb_path} / {depth_path}")


class _SerialPool:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def map(self, fn, jobs, chunksize=1):
        return map(fn, jobs)


def _ignore_sigint() -> None:
    """Workers leave SIGINT to the parent, which stops the pool (a worker that dies of it
    mid-task can leave the pool waiting for it forever)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _pool(workers: int):
    """A process pool of ``workers`` (fork, so nothing is re-imported), or a serial one."""
    if workers <= 1:
        return _SerialPool()
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("fork"),
                               initializer=_ignore_sigint)


def _stop_pool(pool) -> None:
    """Cancel what has not started and end the workers now (an interruption must not hang)."""
    if isinstance(pool, _SerialPool):
        return
    processes = list(getattr(pool, "_processes", {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    for process in processes:
        process.join(timeout=5)


def simulate_sequence(out_dir: str | Path, config: SimConfig | None = None, progress: bool = False,
                      workers: int | None = None, stop: Callable[[], bool] | None = None) -> Path:
    """Render a sequence into ``out_dir`` (created) and return its path.

    ``workers`` processes render frames in parallel (default: the CPU count, at most 4);
    the output does not depend on it. ``stop``: asked after each rendered frame; when it says
    so, the workers are ended and ``KeyboardInterrupt`` is raised, as an interruption would
    (a caller's signal handler sets a flag instead of raising inside whatever runs then: an
    exception raised inside a finalizer of the process pool is printed and dropped, and the
    interruption with it).
    """
    import os

    workers = min(os.cpu_count() or 1, 4) if workers is None else int(workers)
    config = config or SimConfig()
    if config.frames < 2:
        raise ValueError(f"need at least 2 frames, got {config.frames}")
    out = Path(out_dir)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)

    scene = _scene(config)
    # Separate streams: the path, the image noise, the odometry and the IMU each get their
    # own generator, so changing one model does not reshuffle the others.
    path_rng, image_rng, odom_rng, imu_rng, stamp_rng, exposure_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(config.seed).spawn(6))
    duration = (config.frames - 1) / config.fps
    trajectory = _trajectory(config, scene, path_rng, duration)
    intrinsics = default_intrinsics(config.width, config.height)
    t_rel, rgb_stamps, depth_capture_rel, depth_stamps = _frame_clocks(config, stamp_rng)
    gains = exposure_gains(config.frames, config.exposure, exposure_rng)

    _render_frames(out, config, scene, trajectory, intrinsics, (t_rel, rgb_stamps, depth_capture_rel, depth_stamps),
                   gains, image_rng, workers, progress, stop)
    _write_list(out / "rgb.txt", "color images", rgb_stamps, "rgb")
    _write_list(out / "depth.txt", "depth maps", depth_stamps, "depth")
    _write_ground_truth(out, trajectory, t_rel, depth_capture_rel, duration)
    T_odom, _ = drifting_odometry(trajectory.poses(t_rel), rgb_stamps, config.odometry, odom_rng)
    Trajectory(rgb_stamps, T_odom).write_tum(out / "odometry.txt", header="drifting odometry (simulated), T_world_cam")
    _write_imu(out, trajectory, duration, config.imu, imu_rng)
    (out / "intrinsics.json").write_text(json.dumps(intrinsics.to_dict(), indent=1))
    scene.save(out / "scene.json")
    (out / "sim.json").write_text(json.dumps({"generator": "nap3d-graph simulate", **config.to_dict(),
                                              "duration_s": duration,
                                              # The truth a compensation is checked against.
                                              "depth_capture_stamps": (TIME_ORIGIN_S + depth_capture_rel).tolist(),
                                              "exposure_gains": np.round(gains, 6).tolist()}, indent=1))
    log.info("simulated %d frames of %s path into %s", config.frames, config.path, out)
    return out


def _scene(config: SimConfig):
    """One room (``scene_seed``'s, with twin posters when asked) or a floor of ``rooms``."""
    scene = make_scene(config.scene_seed) if config.rooms is None else make_building(config.rooms, config.scene_seed)
    if config.twin_posters is not None:
        if config.rooms is not None:
            raise ValueError("twin_posters hang in one room; a floor of rooms has twin rooms instead")
        if config.twin_posters not in ("identical", "different"):
            raise ValueError(f"twin_posters must be 'identical', 'different' or None, got {config.twin_posters!r}")
        scene = with_twin_posters(scene, config.scene_seed, identical=config.twin_posters == "identical")
    return scene


def _frame_clocks(config: SimConfig, stamp_rng: np.random.Generator) -> tuple:
    """``(t_rel, rgb_stamps, depth_capture_rel, depth_stamps)`` (each (N,), seconds): the frame
    instants from the start, the colour stamps, when each depth was captured and its stamp."""
    t_rel = np.arange(config.frames) / config.fps
    rgb_stamps = TIME_ORIGIN_S + t_rel
    timing = config.timing
    if timing is None:  # an ideal camera: both images at the frame instant, stamps a little apart
        depth_capture_rel = t_rel
        depth_stamps = rgb_stamps + stamp_rng.uniform(-0.008, 0.008, config.frames)
    else:
        depth_capture_rel = t_rel + timing.depth_capture_offset_s
        depth_stamps = (TIME_ORIGIN_S + depth_capture_rel + timing.depth_stamp_lag_s
                        + stamp_rng.uniform(-timing.stamp_jitter_s, timing.stamp_jitter_s, config.frames))
    return t_rel, rgb_stamps, depth_capture_rel, depth_stamps


def _render_frames(out: Path, config: SimConfig, scene, trajectory, intrinsics: Intrinsics, clocks: tuple,
                   gains: np.ndarray, image_rng: np.random.Generator, workers: int, progress: bool,
                   stop: Callable[[], bool] | None) -> None:
    """Every frame's colour and depth PNGs, on ``workers`` processes (see :func:`simulate_sequence`)."""
    t_rel, rgb_stamps, depth_capture_rel, depth_stamps = clocks
    # One noise seed per frame, so the images do not depend on which worker renders them.
    frame_seeds = image_rng.integers(0, 2**63 - 1, config.frames)
    jobs = [(scene, blur_poses(trajectory, float(t_rel[k]), config.timing, intrinsics),
             trajectory.T_world_cam(float(depth_capture_rel[k])), gains[k], intrinsics, config.rgb_noise_sigma,
             config.depth, int(frame_seeds[k]), str(out / "rgb" / f"{rgb_stamps[k]:.6f}.png"),
             str(out / "depth" / f"{depth_stamps[k]:.6f}.png"))
            for k in range(config.frames)]
    pool = _pool(workers)
    try:
        for _ in progress_bar(pool.map(_render_and_write, jobs, chunksize=4), total=len(jobs), desc="render",
                      unit="frame", disable=not progress):
            if stop is not None and stop():
                raise KeyboardInterrupt("stopped")
    except BaseException:
        _stop_pool(pool)
        raise
    else:
        if not isinstance(pool, _SerialPool):
            pool.shutdown(wait=True)


def _write_ground_truth(out: Path, trajectory, t_rel: np.ndarray, depth_capture_rel: np.ndarray,
                        duration: float) -> None:
    """``groundtruth.txt``: 100 Hz on its own clock, plus the exact frame instants; it starts
    early enough to cover the depth captured before the first colour frame."""
    start = min(0.0, float(depth_capture_rel.min()))
    gt_rel = np.arange(start - 0.05, duration + 0.05, 1.0 / _GT_RATE_HZ) + 0.0037
    gt_rel = np.clip(np.union1d(gt_rel, t_rel), start, duration)
    gt_rel = np.unique(np.round(gt_rel, 6))
    Trajectory(TIME_ORIGIN_S + gt_rel, trajectory.poses(gt_rel)).write_tum(out / "groundtruth.txt",
               "ground truth trajectory (simulated), T_world_cam, OpenCV camera, world +Z up")


def _write_imu(out: Path, trajectory, duration: float, noise: ImuNoise, imu_rng: np.random.Generator) -> None:
    """``imu.txt`` (camera frame) and ``imu_bias.txt`` (the biases its samples carry, so an
    estimate of them can be checked)."""
    imu = simulate_imu(trajectory, 0.0, duration, noise, imu_rng)
    imu_rows = np.column_stack([TIME_ORIGIN_S + imu["stamps"], imu["accel"], imu["gyro"]])
    np.savetxt(out / "imu.txt", imu_rows, fmt=["%.6f"] + ["%.9f"] * 6,
               header="IMU in the camera frame (OpenCV axes), specific force m/s^2 and rate rad/s\n"
                      "timestamp ax ay az gx gy gz")
    bias_rows = np.column_stack([TIME_ORIGIN_S + imu["stamps"], imu["accel_bias"], imu["gyro_bias"]])[::20]
    np.savetxt(out / "imu_bias.txt", bias_rows, fmt=["%.6f"] + ["%.9f"] * 6,
               header="true IMU biases (simulated, every 20th sample), m/s^2 and rad/s\n"
                      "timestamp bax bay baz bgx bgy bgz")
