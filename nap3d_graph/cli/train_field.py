"""``nap3d-graph train-field``: a grid radiance field from a posed RGB-D sequence."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from nap3d_graph.arguments import RUN_MATCHER, non_negative_int, positive_float, positive_int
from nap3d_graph.datasets import open_sequence
from nap3d_graph.fields.build import DepthUnitError, build_field

from .common import (
    UsageError,
    add_frames_argument,
    add_matcher_argument,
    add_topics_argument,
    add_unit_arguments,
    warn_depth_units,
    writable_file_parent,
)
from .sources import chosen_matcher, warn_guessed_camera


def add_parser(sub) -> None:
    p = sub.add_parser(
        "train-field",
        help="train a grid radiance field on a posed RGB-D sequence",
        description="Train a dense voxel-grid radiance field (RGB + density, CPU or CUDA) on a posed "
        "RGB-D sequence (TUM folder or simulated room) and write the checkpoint plus FIELD.report.json "
        "(held-out PSNR, depth errors, opacity, unit check, the field's own error) beside it. An existing "
        "checkpoint is not replaced without --force.",
    )
    _source_arguments(p)
    _training_arguments(p)
    _refinement_and_check_arguments(p)
    p.set_defaults(func=run)


def _source_arguments(p) -> None:
    """What is trained on and where the checkpoint goes."""
    p.add_argument("data", type=Path, help="sequence folder (TUM layout, with ground-truth poses), a ROS bag with its "
                   "ground truth in /tf or a pose topic (.bag or ROS 2 folder; see --topics), or a RealSense "
                   "recording (.bag/.db3) with --poses")
    add_topics_argument(p)
    p.add_argument("--poses", type=Path, metavar="TUM_FILE",
                   help="for a RealSense recording: the camera poses of its frames (TUM file)")
    p.add_argument("--out", type=Path, required=True, help="checkpoint to write (FIELD.pt; its report goes to "
                   "FIELD.report.json)")
    p.add_argument("--force", action="store_true", help="replace an existing checkpoint and its report")


def _training_arguments(p) -> None:
    """The field's model, its budget and the frames it trains on."""
    p.add_argument("--model", choices=("grid", "splat", "views"), default="grid",
                   help="grid (default, chosen by measurement: see the README): a voxel-grid radiance field trained "
                   "with torch; splat: surface splats fused from the frames, no training (seconds, not minutes); "
                   "views: the survey's sharpest frames re-projected into the asked view, no training")
    p.add_argument("--timing", choices=("auto", "none"), default="auto",
                   help="auto: estimate when depth and colour were captured relative to the poses, and the colour "
                   "camera's rolling-shutter readout, from the data (for recordings with depth stamps and ground "
                   "truth; the depth scale is left to the run's calibration); none: use the stamps")
    p.add_argument("--minutes", type=positive_float, default=5.0,
                   help="grid: optimisation budget in minutes (default 5)")
    p.add_argument("--steps", type=positive_int, default=None,
                   help="optimisation budget in steps instead of minutes: the same field on any machine "
                   "(--minutes is ignored when given)")
    add_unit_arguments(p)
    add_frames_argument(p, "training and evaluation (the checkpoint records which were trained on)")
    p.add_argument("--every", type=positive_int, default=1,
                   help="train on every K-th frame, hold out the rest for evaluation (default 1: every "
                   "tenth frame is held out)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--voxel-size", type=positive_float, default=None,
                   help="voxel in metres (default: 0.006 for splat, 0.03 for grid)")
    p.add_argument("--eval-frames", type=non_negative_int, default=8, help="held-out frames to evaluate (default 8)")
    p.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: torch's choice)")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    add_matcher_argument(p, RUN_MATCHER)


def _refinement_and_check_arguments(p) -> None:
    """Pose refinement before training, the field's error and the depth unit's check."""
    p.add_argument("--refine-poses", type=non_negative_int, default=0, metavar="ROUNDS",
                   help="refine the training frames' poses first, for ROUNDS rounds (default 0: the poses as given; "
                   "see --refine-method). The report gives each round and the multi-view depth agreement before "
                   "and after")
    p.add_argument("--refine-method", choices=("depth", "map"), default="depth",
                   help="depth (default): each frame's depth aligned with its neighbours' (ICP), the poses solved in "
                   "a graph that holds each to its input pose; map: each frame aligned (as a run would) with a splat "
                   "map of the other half of the frames, fused with its input pose, the maps rebuilt")
    p.add_argument("--error-growth", nargs="?", const="on", default="auto", choices=("auto", "on", "off"),
                   help="grid / splat: also measure how the field's error grows away from its training frames, with "
                   "a view field of the same frames (seconds), and record it: runs then add to each correction the "
                   "error at its own distance from the frames, not the error near them everywhere (a view field "
                   "always measures its own). auto (default): on for a camera's recording, off for a simulated one. "
                   "On fr1/desk and redkitchen it took the grid's corrections' NEES from 9-37 to 5.4-7.8, at the "
                   "chi-square band, the ATE the same or better; on the simulator's rooms, whose poses are exact, "
                   "it did not help (README)")
    p.add_argument("--no-field-error", action="store_true",
                   help="do not measure the field's own error (by default each held-out frame is aligned with the "
                   "render at its true pose, as a run would, and what the corrections miss beyond their covariance "
                   "is recorded: runs of this field add it to every correction; --matcher picks the matcher "
                   "of those alignments, use the runs' own)")
    p.add_argument("--depth-unit", choices=("check", "trust"), default="check",
                   help="check (default): before any work, stop when the depth agrees across the posed frames only "
                        "at another unit's scale (e.g. millimetre PNGs read at TUM's 5000 per metre, 5x short); "
                        "trust: build with the depth as read")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    import torch

    if args.out.suffix != ".pt":
        raise UsageError(f"--out must name a .pt checkpoint, got {args.out}")
    writable_file_parent(args.out)  # before minutes of training, not after
    if args.out.exists() and not args.force:
        raise UsageError(f"{args.out} exists (a trained field); choose another name, or add --force to replace it")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    sequence = open_sequence(args.data, frames=args.frames, groundtruth=args.poses, topics=args.topics,
                             depth_scale=args.depth_scale, stamps=args.stamps, fps=args.fps)
    warn_depth_units(sequence)

    warn_guessed_camera(sequence)
    args.matcher = chosen_matcher(args.matcher, sequence)
    try:
        field, report = build_field(sequence, args.model, steps=args.steps, minutes=args.minutes, every=args.every,
                                    eval_frames=args.eval_frames, seed=args.seed, voxel_size_m=args.voxel_size,
                                    timing="auto" if args.timing == "auto" else None, device=args.device,
                                    progress=not args.quiet, measure_error=not args.no_field_error,
                                    matcher=args.matcher, refine_poses=args.refine_poses,
                                    refine_method=args.refine_method,
                                    error_growth={"on": True, "off": False}.get(args.error_growth, "auto"),
                                    depth_unit=args.depth_unit)
    except DepthUnitError as exc:  # before any training: say it in the command's words
        raise UsageError(f"{exc.check.message()}; fix the depth files, or add --depth-unit trust to train with the "
                         "depth as read") from None
    report["data"] = str(args.data)
    report["frames"] = args.frames
    report["checkpoint"] = str(args.out)
    field.save(args.out)
    report_path = report_path_for(args.out)
    report_path.write_text(json.dumps(report, indent=1, default=float))
    print(summary(field, report, args.out, report_path))
    check = ((report.get("held_out") or {}).get("unit_check")) or {}
    if check.get("a") is not None and (abs(check["a"] - 1.0) > 0.1 or (check.get("r2") or 0) < 0.8):
        print(f"warning: the sensor's depth does not follow the field's (sensor = {check['a']:.3f} x field "
              f"{check.get('b', 0):+.3f} m, R^2 = {check.get('r2', float('nan')):.2f}; the paper's unit check wants "
              "a = 1, R^2 near 1): check the depth unit, the poses and the intrinsics", file=sys.stderr)
    return 0


def report_path_for(checkpoint: Path) -> Path:
    """``FIELD.report.json`` beside ``FIELD.pt``: one report per field, so two fields in one
    folder keep theirs."""
    return checkpoint.with_suffix(".report.json")


def summary(field, report: dict, out, report_path) -> str:
    held = report.get("held_out") or {}
    depth = held.get("depth_abs_err_m") or {}
    lines = [f"wrote {out} ({field!r}) and {report_path}"]
    timing = report.get("timing")
    if timing:
        lines.append(f"timing: depth captured {timing['depth_offset_s'] * 1000:+.0f} ms from its stamp, colour "
                     f"{timing['colour_offset_s'] * 1000:+.0f} ms, depth scale {timing['depth_scale']:.3f} (frames "
                     f"agree to {timing['agreement_mm']:.1f} mm, {timing['agreement_at_colour_stamps_mm']:.1f} mm "
                     "with the colour stamps)")
        if timing.get("readout_s"):
            lines.append(f"rolling shutter: colour rows read over {timing['readout_s'] * 1000:.0f} ms (matched "
                         f"keypoints reproject to {timing['colour_error_px']:.2f} px, {timing['global_shutter_error_px']:.2f}"
                         " px as a global shutter); runs align each keyframe as of its middle row")
    if report.get("colour_without_data"):
        lines.append(f"colour: {report['colour_without_data'] * 100:.1f}% of each image holds no data (the "
                     "undistortion's black corners): no colour is taken from there, and the PSNR does not score it")
    if held:
        lines.append(
            f"held-out ({held['render_size'][0]}x{held['render_size'][1]}): PSNR {held['psnr_db']:.2f} dB "
            f"({held['psnr_affine_db']:.2f} after an affine colour fit), depth error median "
            f"{_cm(depth.get('median'))} / p90 {_cm(depth.get('p90'))} ({held['depth_reference']}), opaque on "
            f"{held['opaque_fraction'] * 100:.0f}% of the surface, render {held['render_seconds']:.3f} s")
    refinement = report.get("pose_refinement")
    if refinement and refinement.get("rounds"):
        last = refinement["rounds"][-1]
        lines.append(f"training poses refined in {len(refinement['rounds'])} rounds: median correction "
                     f"{last['median_correction_mm']:.1f} mm / {last['median_correction_deg']:.2f} deg; multi-view "
                     f"depth agreement {refinement.get('agreement_before_mm', float('nan')):.2f} -> "
                     f"{refinement.get('agreement_after_mm', float('nan')):.2f} mm")
    error = report.get("field_error")
    if error and "nees_median_before" in error:  # measured: enough held-out frames aligned
        lines.append(f"field error ({error['frames']} held-out frames aligned at their true pose, {error['matcher']}): "
                     f"{error['sigma_m'] * 1000:.1f} mm, {error['sigma_rad'] * 57.2958:.2f} deg beyond the "
                     f"corrections' covariance (their NEES median {error['nees_median_before']:.1f} -> "
                     f"{error['nees_median_after']:.1f}); runs of this field add it to every correction")
        by_view = error.get("by_view")
        if by_view:
            steps = ", ".join(f"{g:.2f} m: {m * 1000:.1f} mm / {r * 57.2958:.2f} deg"
                              for g, m, r in zip(by_view["gap_m"], by_view["sigma_m"], by_view["sigma_rad"]))
            source = (" (its own near its frames, with the growth a view field of them measured)"
                      if by_view.get("growth_from") == "views" else "")
            lines.append(f"field error away from the views{source} (nearest view at {steps}); runs add it at each "
                         "correction's own distance from the views")
    elif error:
        lines.append(f"field error: not measured ({error['frames']} held-out frames aligned, too few; "
                     f"{error['failed']} failed); runs take the field as exact")
    return "\n".join(lines)


def _cm(value) -> str:
    return "n/a" if value is None else f"{value * 100:.2f} cm"
