"""``nap3d-graph run`` / ``run_graph.py``: a drift-correction run, or the embedded default.

With no data given, the embedded default runs end to end with nothing downloaded: a
simulated room, a mapping survey and a separate traversal that never revisits a place
(both cached, keyed by their settings), a torch field trained on the survey (cached, keyed
by the scene and the training budget), drifting odometry with NAP3D corrections through
iSAM2, and a short table of the outcome.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .common import (StopOnSignal, UsageError, add_frames_argument, non_negative_float, parse_pose, positive_float,
                     positive_int, probability, warn_trained_frames, writable_dir)

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    from nap3d_graph.default_run import DEFAULT_TRAIN_STEPS

    p = sub.add_parser(
        "run",
        help="drift correction: odometry + NAP3D factors in iSAM2 (no arguments: the embedded default)",
        description=__doc__ + "\nEvery run writes a results folder: config.yaml, estimate.txt, odometry.txt, "
        "groundtruth.txt (TUM), corrections.csv, metrics.json (evo ATE/RPE) and plots; OUT/latest points at it.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--traj", choices=("sim", "tum", "realsense"), default="sim",
                   help="the data source: sim (a folder from 'nap3d-graph simulate'), tum (a TUM RGB-D folder) "
                   "or realsense (not supported yet); default sim")
    p.add_argument("--data", type=Path, help="the sequence folder; omit (with --traj sim) for the embedded default")
    add_frames_argument(p, "the run (a field should not have been trained on them)")
    p.add_argument("--field", help="'oracle' (the exact simulated room of --data), a field checkpoint (.pt, from "
                   "'nap3d-graph train-field'), a nerfstudio config.yml, or 'none' (odometry only)")
    p.add_argument("--odom", choices=("recorded", "noisy", "vo"),
                   help="odometry: recorded (the sequence's odometry.txt; default for sim), noisy (noise injected "
                   "on ground-truth increments; default for tum) or vo (frame-to-frame RGB-D odometry)")
    p.add_argument("--initial-pose", metavar="'tx ty tz qx qy qz qw'",
                   help="where the camera starts in the field's frame (for --odom vo on a recording without ground "
                   "truth; default: the ground truth's first pose)")
    p.add_argument("--initial-pose-file", type=Path, metavar="TUM_FILE",
                   help="the same from the first line of a TUM trajectory file")
    p.add_argument("--odom-rot-sigma", type=positive_float, default=2e-3,
                   help="per-frame rotation noise of the odometry, rad (injected with --odom noisy, and the "
                   "odometry factors' sigma); default 0.002")
    p.add_argument("--odom-trans-sigma", type=positive_float, default=2e-3,
                   help="per-frame translation noise of the odometry, m; default 0.002")
    p.add_argument("--keyframe-every", type=positive_int, default=5,
                   help="a keyframe (and a correction) every N frames (default 5)")
    p.add_argument("--keyframe-distance", type=non_negative_float, default=0.0,
                   help="also a keyframe after this many metres of odometry (0: off)")
    p.add_argument("--keyframe-angle", type=non_negative_float, default=0.0,
                   help="also a keyframe after this many degrees of rotation (0: off)")
    p.add_argument("--iterations", type=positive_int, default=1,
                   help="render-align rounds per correction (default 1; 2 re-renders at the corrected pose: "
                   "a little more accurate, twice the time)")
    p.add_argument("--render-size", default="320x240", help="WxH the field renders at (default 320x240)")
    p.add_argument("--anchor", action="store_true",
                   help="estimate the field's frame in the world (map anchor M(0)) instead of assuming it is the "
                   "odometry's world frame")
    p.add_argument("--gate-p", type=probability, default=0.997,
                   help="chi-square gate probability, in (0, 1) (default 0.997)")
    p.add_argument("--max-frames", type=positive_int, help="stop after this many frames")
    p.add_argument("--seed", type=int, default=0, help="seed of injected odometry noise (default 0)")
    p.add_argument("--out", type=Path, default=Path("results"), help="results root (default ./results)")
    p.add_argument("--cache", type=Path, default=None,
                   help="cache of the embedded default's data and field (default $NAP3D_GRAPH_CACHE or "
                   "~/.cache/nap3d-graph)")
    p.add_argument("--train-steps", type=positive_int, default=DEFAULT_TRAIN_STEPS,
                   help=f"field training budget of the embedded default, in steps (default {DEFAULT_TRAIN_STEPS}, "
                   "about two minutes on two cores)")
    p.set_defaults(func=run)


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--render-size must look like 320x240, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise UsageError(f"--render-size must be positive, got {text!r}")
    return w, h


def _inputs(args):
    """(sequence folder, field, field description, run name) from the arguments."""
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.default_run import default_cache_dir, embedded_default_inputs
    from nap3d_graph.fields import resolve_field

    if args.data is None:
        if args.traj != "sim":
            raise UsageError(f"--traj {args.traj} needs --data PATH")
        cache = args.cache or default_cache_dir()
        data, field_obj, field_path, _ = embedded_default_inputs(cache, args.train_steps, progress=True, say=print)
        if args.field not in (None, "default"):
            field_obj = resolve_field(args.field, open_sequence(data))
            field_path = args.field
        return data, field_obj, str(field_path), "default"
    if args.field is None:
        raise UsageError("--data needs --field (a checkpoint, 'oracle' for simulated data, or 'none')")
    return args.data, None, args.field, args.traj


def run(args) -> int:
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.odometry import make_odometry
    from nap3d_graph.pipeline import Pipeline, PipelineConfig
    from nap3d_graph.run_output import RunWriter

    t0 = time.perf_counter()
    if args.traj == "realsense":
        raise UsageError("--traj realsense: reading RealSense recordings is not supported in this version; "
                         "record to a TUM-layout folder and use --traj tum")
    width, height = _parse_size(args.render_size)
    initial_pose = parse_pose(args.initial_pose, args.initial_pose_file)
    writable_dir(args.out)  # before the run, not after it
    data, field_obj, field_desc, name = _inputs(args)
    sequence = open_sequence(data, frames=args.frames)
    if args.data is not None:
        field_obj = resolve_field(args.field, sequence)
    trained_on = warn_trained_frames(field_obj, sequence.timestamps, "frames of this run")
    odom_kind = args.odom or ("recorded" if getattr(sequence, "T_world_cam_odom", None) is not None else "noisy")
    try:
        odometry = make_odometry(odom_kind, sequence, args.seed, args.odom_rot_sigma, args.odom_trans_sigma,
                                 initial_pose=initial_pose)
    except ValueError as exc:  # the data cannot give that odometry: say which and what to use
        raise UsageError(str(exc)) from None
    config = PipelineConfig(keyframe_every=args.keyframe_every, keyframe_distance_m=args.keyframe_distance,
                            keyframe_angle_deg=args.keyframe_angle, correction_iterations=args.iterations,
                            render_width=width, render_height=height, use_anchor=args.anchor, gate_p=args.gate_p,
                            max_frames=args.max_frames, progress=True)
    record = {"traj": args.traj, "data": str(data), "frames": args.frames, "frame_range": list(sequence.frame_range),
              "field": field_desc, "frames_the_field_was_trained_on": trained_on, "odometry": odom_kind,
              "initial_pose": None if initial_pose is None else initial_pose.tolist(),
              "odom_rot_sigma_rad": args.odom_rot_sigma, "odom_trans_sigma_m": args.odom_trans_sigma,
              "seed": args.seed, "pipeline": {k: v for k, v in vars(config).items() if k != "align"},
              "align": vars(config.align)}
    writer = RunWriter(args.out, name, record, getattr(sequence, "rgb_line_index", None))
    try:
        with StopOnSignal() as stop:
            result = Pipeline(sequence, field_obj, odometry, config).run(on_keyframe=writer.add_keyframe, stop=stop)
    finally:
        writer.close()
    metrics = writer.finish(result, partial=result.partial)
    print(summary_table(metrics, time.perf_counter() - t0))
    print(f"results: {writer.dir}  (also {Path(args.out) / 'latest'})")
    if result.partial:
        print(f"interrupted after {len(result.timestamps)} of {len(sequence)} frames: the results are partial "
              "(metrics.json says so)", file=__import__("sys").stderr)
        return 130
    return 0


def summary_table(metrics: dict, seconds: float) -> str:
    lines = ["", f"{'':<22}{'ATE rmse':>12}{'ATE 1st half':>14}{'ATE 2nd half':>14}{'RPE rmse':>12}"]
    for name, label in (("odometry", "odometry only"), ("estimate", "with NAP3D"),
                        ("estimate_online", "with NAP3D, causal")):
        m = metrics.get(name)
        if m is None:
            continue
        rpe = m["rpe_m"].get("rmse")
        lines.append(f"{label:<22}{m['ate_m']['rmse'] * 100:10.2f}cm{(m['ate_first_half_m'] or 0) * 100:12.2f}cm"
                     f"{(m['ate_second_half_m'] or 0) * 100:12.2f}cm" + (f"{rpe * 100:10.2f}cm" if rpe else ""))
    if "ground_truth" in metrics:
        lines.append(f"no ground truth: no ATE/RPE (median inliers per keyframe {metrics['median_inliers']:.0f})")
    if "odometry" in metrics and "estimate" in metrics:
        ratio = metrics["odometry"]["ate_m"]["rmse"] / max(metrics["estimate"]["ate_m"]["rmse"], 1e-12)
        lines.append(f"ATE reduced {ratio:.1f}x")
    timing = metrics["seconds_per_keyframe_median"]
    lines.append(f"corrections: {metrics['corrections_accepted']} accepted, "
                 f"{metrics['corrections_rejected_or_skipped']} rejected or skipped, of {metrics['keyframes']} keyframes")
    if "total_per_keyframe" in timing:
        stages = ", ".join(f"{k} {v * 1000:.0f}" for k, v in timing.items() if k != "total_per_keyframe")
        lines.append(f"time per keyframe: {timing['total_per_keyframe']:.2f} s median ({stages} ms)")
    lines.append(f"total time: {seconds:.0f} s")
    return "\n".join(lines)
