"""The run's options, bound to its settings tree (:class:`~nap3d_graph.run.settings.RunSettings`)
by one table of :class:`~nap3d_graph.cli.binding.Option` (its flag, the ``section.setting``
it sets, how argparse reads it; its default is the setting's, taken from the tree). ``run`` and
``compare`` add :data:`SOURCE_OPTIONS` (``compare`` writes its own ``--out``), ``run`` also
:data:`RUN_OPTIONS`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from nap3d_graph.datasets import SOURCES

from .binding import Option
from .common import (
    DEPTH_SCALE_OPTION,
    FPS_OPTION,
    RUN_MATCHER,
    STAMPS_OPTION,
    TOPICS_OPTION,
    frames_option,
    matcher_option,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    probability,
)

__all__ = ["SOURCE_OPTIONS", "RUN_OPTIONS", "LAND_WITHIN_FRAME_SHARE"]

#: ``--land-within frame``: this share of the camera's frame period (the rest of the step:
#: the graph update and handing the pose over).
LAND_WITHIN_FRAME_SHARE = 0.9


def _gravity(text: str):
    """'check', 'auto', a magnitude (m/s^2) or a vector 'gx gy gz' (m/s^2, the field's frame)."""
    if text.strip() in ("auto", "check"):
        return text.strip()
    parts = text.replace(",", " ").split()
    try:
        values = [float(v) for v in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be 'check', 'auto', a magnitude or 'gx gy gz', got {text!r}") from None
    if len(values) == 1 and values[0] > 0:
        return values[0]
    if len(values) == 3 and 1.0 < float(np.linalg.norm(values)) < 100.0:
        return values
    raise argparse.ArgumentTypeError(f"must be a positive magnitude, 'auto' or a vector 'gx gy gz' (m/s^2), got {text!r}")


def _auto_or_non_negative(text: str) -> float | None:
    """'auto' (None: the field's own value) or a number >= 0."""
    return None if text == "auto" else non_negative_float(text)


def _land_within(text: str) -> float | str:
    return "frame" if text == "frame" else non_negative_float(text)


SOURCE_OPTIONS: tuple[Option, ...] = (
    Option("--traj", "source.traj", choices=("auto", *SOURCES), help="the data source (default auto: the one --data's path says, a simulator's folder, a TUM-layout or 7-Scenes folder, a RealSense or ROS bag; sim without --data): sim (a folder from 'nap3d-graph simulate'), tum (a TUM RGB-D folder), "
                   "realsense (a .bag/.db3 recording, or 'live': a connected camera) or 7scenes (a 7-Scenes sequence "
                   "folder: depth is warped into its colour camera, whose focal length and centre are estimated from the "
                   "data), "
                   "or rosbag (a ROS 1 .bag or a ROS 2 bag folder: colour, depth, camera info, IMU and ground truth "
                   "from /tf or a pose topic; see --topics)"),
    Option("--data", "source.data", type=Path, help="the sequence folder, or for realsense a recording or 'live', or for "
                   "rosbag the .bag file or ROS 2 bag folder; omit (with --traj sim) for the embedded default"),
    Option("--topics", "source.topics", **TOPICS_OPTION),
    Option("--groundtruth", "source.groundtruth", type=Path, metavar="TUM_FILE", help="realsense: camera poses of the recording's frames, for ATE/RPE (without it the results "
                   "report correction statistics)"),
    Option("--realsense-config", "source.realsense_config", type=Path, metavar="YAML", help="realsense: IMU extrinsics (T_depth_imu) and noise, which recordings do not store (default: "
                   "RECORDING.yaml beside the file if there is one, else D435i values)"),
    Option("--record", "source.record", type=Path, metavar="FILE.bag", help="realsense live: keep what the camera streamed in this file (default: a temporary file)"),
    Option("--seconds", "source.seconds", type=positive_float, help="realsense live: how long to capture before correcting (default %(default)g)"),
    Option("--depth-scale", "source.depth_scale", **DEPTH_SCALE_OPTION),
    Option("--stamps", "source.stamps", **STAMPS_OPTION),
    Option("--fps", "source.fps", **FPS_OPTION),
    Option("--frames", "source.frames", **frames_option("the run (a field should not have been trained on them)")),
    Option("--field", "alignment.field", help="'oracle' (the exact simulated room of --data), a field checkpoint (.pt, from "
                   "'nap3d-graph train-field'), a nerfstudio config.yml, or 'none' (odometry only)"),
    Option("--odom", "odometry.kind", choices=("recorded", "noisy", "vo", "dense", "imu"), help="motion between keyframes: recorded (the sequence's odometry.txt; default for sim), noisy "
                   "(noise injected on ground-truth increments; default for tum), vo (frame-to-frame RGB-D odometry with "
                   "NAP3D's matcher), dense (OpenCV's dense RGB-D odometry at 320 px wide: the camera's rate, about "
                   "the same drift on fr1/desk) or imu (the sequence's IMU preintegrated into CombinedImuFactors; biases estimated; default for "
                   "a realsense recording with an IMU)"),
    Option("--vo-width", "odometry.vo_width", type=positive_int, metavar="PX", help="--odom vo: detect and align each frame resized to PX pixels wide (default: as read). At the "
                   "render's width (320 by default) each keyframe's correction reuses the features the odometry "
                   "detected: a higher frame rate, the odometry alone drifting more (measured against the frames as "
                   "read in docs/results.md, 'Feature odometry at the render's width'). --pace with --odom vo "
                   "takes the render's width unless told"),
    Option("--imu-noise", "odometry.imu_noise", metavar="'AN GN AW GW'", help="IMU noise densities: accel m/s^2/sqrt(Hz), gyro rad/s/sqrt(Hz), accel bias walk m/s^3/sqrt(Hz), "
                   "gyro bias walk rad/s^2/sqrt(Hz) (default: the simulator's, 2e-3 2.4e-4 1e-4 2e-6)"),
    Option("--imu-extrinsics", "odometry.imu_extrinsics", metavar="'tx ty tz qx qy qz qw'", help="T_cam_imu: the IMU frame in the camera frame (default identity, as simulated)"),
    Option("--gravity", "odometry.gravity", type=_gravity, metavar="check|auto|G|'gx gy gz'", help="--odom imu: gravity in the field's frame as the run's graph starts it; the graph then refines "
                   "its tilt (a few degrees; the EKFs of compare keep it as given). 'check' (default): z-up (-9.81 "
                   "m/s^2 along z), unless the accelerometer over the first 0.5 s, with the starting pose, puts it more "
                   "than 10 deg away (a field's frame from COLMAP or nerfstudio, a y-down room): then the "
                   "accelerometer's direction, said on the terminal. 'auto': always the accelerometer's direction. A "
                   "magnitude (m/s^2): z-up, only warned about. Or the vector in m/s^2"),
    Option("--fallback-odom", "odometry.fallback", choices=("dense", "vo", "none"), help="--odom imu: the frame odometry the run falls back on between keyframes after 3 keyframes "
                   "refused in a row (the views left the field, say: the IMU alone then drifts by metres within "
                   "seconds), until a correction lands again (default %(default)s; none: the IMU alone)"),
    Option("--timing", "alignment.timing", choices=("auto", "none"), help="auto: move each keyframe's depth to its colour's capture instant with the capture timing the "
                   "field records, or, for a field that records none (the oracle, nerfstudio), the timing estimated "
                   "from this sequence's ground truth; none: take the stamps as they are"),
    Option("--initial-pose", "source.initial_pose", metavar="auto|'tx ty tz qx qy qz qw'", help="where the camera starts in the field's frame, for --odom vo / dense. auto: found in the map "
                   "(the map's keyframes most like the first frame, the field rendered there, NAP3D aligned and "
                   "verified; a clear error when none verifies); the default with a map from 'nap3d-graph map' "
                   "(its frame is not the ground truth's). Otherwise the default is the ground truth's first pose, "
                   "and with --field none and no ground truth the identity"),
    Option("--initial-pose-file", "source.initial_pose_file", type=Path, metavar="TUM_FILE", help="the same from the first line of a TUM trajectory file"),
    Option("--odom-rot-sigma", "odometry.rot_sigma_rad", type=positive_float, help="per-frame rotation noise of the odometry, rad (injected with --odom noisy, and the "
                   "odometry factors' sigma); default %(default)g"),
    Option("--odom-trans-sigma", "odometry.trans_sigma_m", type=positive_float, help="per-frame translation noise of the odometry, m; default %(default)g"),
    Option("--keyframe-every", "keyframes.every", type=positive_int, help="a keyframe (and a correction) every N frames (default %(default)s)"),
    Option("--keyframe-distance", "keyframes.distance_m", type=non_negative_float, help="also a keyframe after this many metres of odometry (0: off)"),
    Option("--keyframe-angle", "keyframes.angle_deg", type=non_negative_float, help="also a keyframe after this many degrees of rotation (0: off)"),
    Option("--keyframe-window", "keyframes.window", type=non_negative_int, metavar="N", help="a due keyframe is taken at the first sharp frame (variance of the Laplacian at least 0.8 of "
                   "the median since the last keyframe) among the next N, the last of them if none is: motion blur "
                   "starves the matcher (0 or 1: the due frame; default %(default)s)"),
    Option("--keyframe-on-doubt", "keyframes.on_doubt", action=argparse.BooleanOptionalAction, help="also a keyframe right after the odometry guessed a step (visual odometry lost track), so "
                   "the jump is corrected at once"),
    Option("--keyframe-when-idle", "keyframes.when_idle", type=non_negative_int, metavar="N", help="with --overlap: also a keyframe at any frame N or more after the last while the second thread "
                   "is idle, so corrections come as often as it can measure them (--keyframe-every is then the "
                   "longest interval; which frames are keyframes depends on the machine's speed, or with run --pace "
                   "on the camera's rate). Default: 1 for an overlapped run --pace (the live settings), else 0: off"),
    Option("--rolling-shutter", "alignment.rolling_shutter_s", type=_auto_or_non_negative, metavar="S|auto", help="the colour camera's rolling-shutter readout, first row to last, in seconds: "
                   "each keyframe's matched points are moved along the odometry's velocity to the middle row's "
                   "instant before the alignment. Default auto: the readout train-field estimated from the "
                   "recording's ground truth with its capture timing (fr1/desk's Kinect: 24 ms; 0, a global shutter, "
                   "where the data showed none or the field records no timing); 0: a global shutter"),
    Option("--iterations", "alignment.iterations", type=positive_int, help="render-align rounds per correction (default %(default)s; 2 re-renders at the corrected pose: "
                   "a little more accurate, twice the time)"),
    Option("--render-size", "alignment.render_size", help="WxH the field renders at (default %(default)s)"),
    Option("--matcher", "alignment.matcher", **matcher_option(RUN_MATCHER)),
    Option("--gate-p", "graph.gate_p", type=probability, help="chi-square gate probability, in (0, 1) (default %(default)g)"),
    Option("--field-sigma", "alignment.field_sigma_m", type=_auto_or_non_negative, metavar="M|auto", help="the field's own geometric error in metres, added to every correction's covariance "
                   "(rotation: M / 2 m per radian). Default auto: what the field measured of itself when "
                   "train-field built it (0 for the exact oracle and fields that record none); 0: take the field "
                   "as exact"),
    Option("--overlap", "threads.overlap", action=argparse.BooleanOptionalAction, help="measure each keyframe's correction on a second thread while the odometry goes on; it "
                   "enters the graph when ready (faster on two cores; not bit-for-bit repeatable; not with --odom imu). "
                   "Default: on for run --pace (frames fed as the camera delivers them: with the live settings, "
                   "--land-within frame and --keyframe-when-idle 1, as accurate as inline and more often corrected), "
                   "off for a replay that goes as fast as it can (inline is repeatable there, and an overlapped "
                   "run's causal trajectory would depend on the machine's speed)"),
    Option("--render-ahead", "threads.render_ahead", action="store_true", help="with --overlap: render the next keyframe at its one-step guessed pose while the second "
                   "thread is idle, so its correction lands sooner (for slow fields or fast cameras; its "
                   "corrections can be slightly worse where the motion turns fast)"),
    Option("--land-within", "threads.land_within", type=_land_within, metavar="S|frame", help="with --overlap: wait up to S seconds after a frame arrives for the correction in flight, "
                   "so one that is done by then lands at that frame and not a later one; 'frame' waits "
                   f"{LAND_WITHIN_FRAME_SHARE:g} of the camera's frame period (only while a live run would idle "
                   "for the next frame; with run --pace, as a live camera feeds it). Default: 'frame' for run "
                   "--overlap --pace (the run would idle then anyway), else 0: never wait"),
    Option("--graph-window", "graph.window", type=non_negative_int, metavar="N", help="keep the last N keyframes in iSAM2 (>= 3), marginalising older ones and fixing their "
                   "poses, so a long run's graph and its updates stay bounded (default %(default)s: every keyframe, the whole "
                   "trajectory smoothed at the end; not with --odom imu or --anchor)"),
    Option("--max-frames", "source.max_frames", type=positive_int, help="stop after this many frames"),
    Option("--seed", "odometry.seed", type=int, help="seed of injected odometry noise (default %(default)s)"),
    Option("--cache", "source.cache", type=Path, help="cache of the embedded default's data and field (default $NAP3D_GRAPH_CACHE or "
                   "~/.cache/nap3d-graph)"),
    Option("--train-steps", "source.train_steps", type=positive_int, help="field training budget of the embedded default, in steps (default %(default)s, "
                   "about two minutes on two cores)"),

)

#: The options only ``run`` has (``compare`` runs inline from the start, writes its own folder).
RUN_OPTIONS: tuple[Option, ...] = (
    Option("--anchor", "graph.anchor", action="store_true", help="estimate the field's frame in the world (map anchor M(0)) instead of assuming it is the "
                   "odometry's world frame"),
    Option("--pace", "source.pace", type=positive_float, nargs="?", const=1.0, metavar="SPEED", help="feed the frames as the camera delivered them (SPEED times its rate; default 1): the causal "
                   "trajectory is then the one a robot riding along would have had, which for --overlap depends on "
                   "the camera's rate, not on how fast a replay goes. Takes the live settings unless told otherwise "
                   "(--overlap --land-within frame --keyframe-when-idle 1; --no-overlap runs inline). metrics.json "
                   "records how late the run took the frames"),
    Option("--out", "output.out", type=Path, help="results root (default ./%(default)s)"),
    Option("--write-bag", "output.write_bag", type=Path, metavar="OUT.bag|OUT_DIR", help="also write the trajectories as a ROS bag in the input's time, to play next to the input in "
                   "RViz: causal, smoothed and odometry poses (PoseStamped), paths (nav_msgs/Path) and /tf from the "
                   "world to the corrected camera. A .bag path is a ROS 1 bag, any other a ROS 2 bag folder (MCAP when "
                   "it ends in .mcap)"),
    Option("--viz", "output.viz", metavar="RUN.rrd|spawn", help="also record the run for the rerun viewer (extra 'viz': rerun-sdk): trajectories, each "
                   "keyframe's image, render and inlier matches, the corrections' covariance ellipsoids, accepted or "
                   "refused with the reason, on one timeline. RUN.rrd: a file to open with 'rerun RUN.rrd'; spawn: "
                   "open the viewer now (needs a display)"),
)
