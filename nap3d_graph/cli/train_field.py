"""``nap3d-graph train-field``: a grid radiance field from a posed RGB-D sequence."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from nap3d_graph.arguments import positive_int
from nap3d_graph.datasets import open_sequence
from nap3d_graph.fields.build import DepthUnitError, FieldSettings, build_field

from .binding import SectionDefaults, add_options, flag_options, section_values
from .common import (
    UsageError,
    add_frames_argument,
    add_topics_argument,
    add_unit_arguments,
    warn_depth_units,
    writable_file_parent,
)
from .sources import chosen_matcher, warn_guessed_camera

#: train-field's settings that have a flag: each field of FieldSettings declares it.
FIELD_SECTIONS: dict[str, type] = {"field": FieldSettings}
FIELD_OPTIONS = flag_options(FIELD_SECTIONS)


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
    """The field's model, its budget and the frames it trains on (FieldSettings' flags)."""
    add_options(p, FIELD_OPTIONS, SectionDefaults(FIELD_SECTIONS))
    add_unit_arguments(p)
    add_frames_argument(p, "training and evaluation (the checkpoint records which were trained on)")
    p.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: torch's choice)")


def _refinement_and_check_arguments(p) -> None:
    """Pose refinement before training, the field's error and the depth unit's check."""
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
    given = section_values(args, FIELD_OPTIONS)["field"]
    settings = FieldSettings(**{**given, "timing": "auto" if args.timing == "auto" else None, "progress": not args.quiet,
                                "error_growth": {"on": True, "off": False}.get(args.error_growth, "auto")})
    try:
        field, report = build_field(sequence, settings=settings)
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
