"""``nap3d-graph run`` / ``run_graph.py``: a drift-correction run, or the embedded default.

With no data given, the embedded default runs end to end with nothing downloaded: a
simulated room, a mapping survey and a separate traversal that never revisits a place
(both cached, keyed by their settings), a torch field trained on the survey (cached, keyed
by the scene and the training budget), drifting odometry with NAP3D corrections through
iSAM2, and a short table of the outcome.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from nap3d_graph.datasets import DatasetError
from nap3d_graph.rerun_sdk import VizError, check_viz_target
from nap3d_graph.run.bag import check_bag_path, write_run_bag
from nap3d_graph.run.output import RunWriter, refusal_hint_for
from nap3d_graph.run.pacing import CameraPace
from nap3d_graph.run.viz import RunRecorder

from .binding import add_options
from .common import StopOnSignal, UsageError, writable_dir
from .run_config import apply_run_config
from .run_options import RUN_OPTIONS
from .sources import add_source_arguments, detected_source, prepare, validated_settings

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    p = sub.add_parser(
        "run",
        help="drift correction: odometry + NAP3D factors in iSAM2 (no arguments: the embedded default)",
        description=__doc__ + "\nEvery run writes a results folder: config.yaml, estimate.txt (smoothed), "
        "estimate_online.txt (causal: what the robot had at each frame), odometry.txt, groundtruth.txt (TUM), "
        "corrections.csv, metrics.json (evo ATE/RPE) and plots; OUT/latest points at it.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_source_arguments(p)
    add_options(p, RUN_OPTIONS)
    p.add_argument("--config", type=Path, metavar="CONFIG.yaml",
                   help="reproduce a run from the config.yaml it wrote: its options and settings, except the options "
                   "given here (a flag given wins, whatever its value)")
    p.set_defaults(func=run, parser=p)


def run(args) -> int:
    t0 = time.perf_counter()
    _check_options(args)
    prepared = prepare(args)
    pipeline, writer, result, pace, recorder = _run(args, prepared)
    extra = {} if pace is None else {"paced": pace.summary()}
    extra.update(_map_metrics(prepared.record["resolved"].get("start"), pipeline, result))
    metrics = writer.finish(result, partial=result.partial, extra=extra or None)
    if pace is not None:
        _say_pace(args.pace, metrics, pipeline.config)
    _finish_extras(args, prepared, result, recorder)
    return _say_results(args, prepared, writer, metrics, result, time.perf_counter() - t0)


def _check_options(args) -> None:
    """A ``--config`` applied, the source resolved and every option checked before anything is
    written or read (one-line errors)."""
    if args.config is not None:
        apply_run_config(args, args.config)
    args.traj = detected_source(args)
    validated_settings(args)  # every flag combination refused in one line before anything is written
    writable_dir(args.out)  # before the run, not after it
    if args.write_bag is not None:
        _check_bag_path(args.write_bag)
    if args.viz is not None:
        _check_viz(args.viz)


def _run(args, prepared):
    """The run, its keyframes written as they come (and recorded for rerun with ``--viz``),
    paced with ``--pace``, stopped cleanly on Ctrl-C; ``(pipeline, writer, result, pace,
    recorder)``."""
    writer = RunWriter(args.out, prepared.name, prepared.record, getattr(prepared.sequence, "rgb_line_index", None))
    pipeline = prepared.pipeline()
    recorder, on_keyframe, pace = None, writer.add_keyframe, None
    if args.viz is not None:
        recorder = RunRecorder(args.viz, prepared.name, getattr(prepared.sequence, "intrinsics", None))

        def on_keyframe(record):
            writer.add_keyframe(record)
            measured = pipeline.last_correction_frame == record.frame_index
            recorder.keyframe(record, pipeline.last_correction if measured else None)
    try:
        with StopOnSignal() as stop:
            pace = None if args.pace is None else CameraPace(prepared.sequence.timestamps, args.pace, then=stop)
            result = pipeline.run(on_keyframe=on_keyframe, stop=stop if pace is None else pace)
    finally:
        writer.close()
        if recorder is not None and sys.exc_info()[0] is not None:
            recorder.close()  # what was recorded stays readable
    return pipeline, writer, result, pace, recorder


def _finish_extras(args, prepared, result, recorder) -> None:
    """The rerun recording closed (``--viz``) and the ROS bag written (``--write-bag``)."""
    if recorder is not None:
        recorder.finish(result)
        recorder.close()
        print(f"rerun recording: {args.viz}" + (" (open it with: rerun " + str(args.viz) + ")"
                                                 if args.viz != "spawn" else ""))
    if args.write_bag is not None:
        _write_bag(args.write_bag, prepared.sequence, result)


def _say_results(args, prepared, writer, metrics: dict, result, seconds: float) -> int:
    """The summary, hints, where the results and the report are; the exit status (130 for an
    interrupted run)."""
    print(summary_table(metrics, seconds, with_field=prepared.field is not None))
    for hint in (refusal_hint(metrics), pace_hint(metrics)):
        if hint:
            print(f"warning: {hint}", file=sys.stderr)
    print(f"results: {writer.dir}  (also {Path(args.out) / 'latest'})")
    bad = metrics.get("report", {}).get("past_bad_line")
    print(f"report: {writer.dir / 'report.md'} (" + ("look at: " + "; ".join(bad) if bad else
                                                     "nothing past its bad line") + ")")
    if result.partial:
        print(f"interrupted after {len(result.timestamps)} of {len(prepared.sequence)} frames: the results are partial "
              "(metrics.json says so)", file=sys.stderr)
        return 130
    return 0


def _say_pace(pace: float, metrics: dict, config) -> None:
    """One line on how late a paced run took the frames, and how it ran."""
    late = metrics["paced"].get("behind_camera_s") or {}
    mode = (f"overlapped, waiting up to {config.land_within_s * 1000:.0f} ms for a correction"
            + (f", a keyframe whenever the second thread is idle ({config.keyframe_when_idle} or more frames apart)"
               if config.keyframe_when_idle else "") if config.overlap else "inline")
    print(f"paced at {pace:g}x the camera's rate ({mode}): the run took the frames up to "
          f"{late.get('max', 0) * 1000:.0f} ms late ({metrics['paced'].get('frames_over_a_period_late', 0)} over "
          "a frame period)")


def _write_bag(path: Path, sequence, result) -> None:
    """The run's poses, paths and /tf into a ROS bag at ``path``."""
    world = getattr(sequence, "world_frame", None) or "world"
    write_run_bag(path, result, world_frame=world)
    print(f"bag: {path} (/nap3d/causal/pose, /nap3d/smoothed/pose, paths and /tf in frame {world!r})")


def _check_bag_path(path: Path) -> None:
    try:
        check_bag_path(path)
    except DatasetError as exc:
        raise UsageError(str(exc)) from None


def _check_viz(target: str) -> None:
    try:
        check_viz_target(target)
    except VizError as exc:
        raise UsageError(str(exc)) from None


def refusal_hint(metrics: dict) -> str:
    """A warning when most keyframes (at least 60%) were refused, for one reason (at least
    60% of the refusals): what the reason usually means. Empty otherwise."""
    reasons, keyframes = metrics.get("refused_reasons") or {}, metrics.get("keyframes", 0)
    refused = sum(reasons.values())
    if keyframes < 3 or refused < 0.6 * keyframes or not reasons:
        return ""
    kind, count = next(iter(reasons.items()))
    if count < 0.6 * refused or kind == "no field":
        return ""
    why = refusal_hint_for(kind) or "see corrections.csv"
    return f"{count} of {keyframes} corrections were refused for '{kind}': {why}"


def pace_hint(metrics: dict) -> str:
    """A warning when a paced run fell behind its camera (more than a tenth of its frames taken
    over a frame period late): how long a keyframe's measurement took, and what keeps up.
    Empty otherwise."""
    paced = metrics.get("paced") or {}
    frames, late = paced.get("frames", 0), paced.get("frames_over_a_period_late", 0)
    if not frames or late <= 0.1 * frames:
        return ""
    stages = metrics.get("seconds_per_keyframe_median") or {}
    wall_s, camera_hz = metrics.get("wall_time_s") or 0.0, paced.get("camera_hz")
    rate = (f" at {frames / wall_s:.1f} frame/s against the camera's {camera_hz:.1f} Hz"
            if wall_s > 0 and camera_hz else "")
    took = ""
    if stages.get("measure"):
        render = f", its render {stages['render'] * 1000:.0f} ms" if stages.get("render") else ""
        took = f" (a keyframe's measurement took {stages['measure'] * 1000:.0f} ms median{render})"
    return (f"the run fell behind the camera{rate}: {late} of {frames} frames taken over a frame period late{took}; "
            "a view field (train-field --model views) renders 320x240 in about 25 ms, or take keyframes less "
            "often (--keyframe-every)")


def _map_metrics(start: dict | None, pipeline, result) -> dict:
    """metrics.json's entries of a run in a self-made map: where it started, whether and when
    it was placed, its recoveries, and how it is scored (said in one line too)."""
    if not start:
        return {}
    extra: dict = {"map": {**start, "recoveries": pipeline.recoveries}}
    if result.placement is not None:
        extra["map"]["placement"] = result.placement
        print(f"map: {pipeline.placement.describe()}")
    untied = _untied_frames(start, result.placement)
    if untied:
        extra["scored"] = f"SE(3)-aligned only: {untied} (ate_m is null)"
    return extra


def _untied_frames(start: dict, placement: dict | None) -> str:
    """Why the run's poses and its ground truth are in frames no survey alignment ties
    (empty when they are tied): then only an SE(3)-aligned ATE means anything."""
    if placement is not None and not placement.get("placed"):
        return "the run was never placed in the map (its poses are in its own frame)"
    if str(start.get("ground_truth_frame", "")).startswith("unknown"):
        return "the map's survey had no ground truth to tie its frame to this run's"
    return ""


def summary_table(metrics: dict, seconds: float, with_field: bool = True) -> str:
    lines = [""]
    if "scored" in metrics and "estimate" in metrics:
        return _aligned_summary(metrics, seconds, with_field)
    if "estimate" in metrics:
        lines.append(f"{'':<22}{'ATE rmse':>12}{'ATE 1st half':>14}{'ATE 2nd half':>14}{'RPE rmse':>12}")
    for name, label in _trajectory_labels(with_field):
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
    reasons = metrics.get("refused_reasons") or {}
    why = f" ({', '.join(f'{n} {kind}' for kind, n in reasons.items())})" if reasons else ""
    lines.append(f"corrections: {metrics['corrections_accepted']} accepted, "
                 f"{metrics['corrections_rejected_or_skipped']} rejected or skipped{why}, of {metrics['keyframes']} "
                 "keyframes")
    if "total_per_keyframe" in timing:
        stages = ", ".join(f"{k} {v * 1000:.0f}" for k, v in timing.items() if k != "total_per_keyframe")
        lines.append(f"time per keyframe: {timing['total_per_keyframe']:.2f} s median ({stages} ms)")
    lines.append(f"total time: {seconds:.0f} s")
    return "\n".join(lines)


def _trajectory_labels(with_field: bool) -> tuple[tuple[str, str], ...]:
    """(metrics.json key, the summary's label) of each trajectory."""
    label, causal = ("with NAP3D", "with NAP3D, causal") if with_field else ("graph (no field)", "graph, causal")
    return ("odometry", "odometry only"), ("estimate", label), ("estimate_online", causal)


def _aligned_summary(metrics: dict, seconds: float, with_field: bool) -> str:
    """The summary when the run's frame and the ground truth's are not tied: each
    trajectory's ATE after its own SE(3) alignment, and why."""
    lines = ["", f"scored {metrics['scored']}", f"{'':<22}{'ATE (SE(3)-aligned)':>22}"]
    for name, label in _trajectory_labels(with_field):
        m = metrics.get(name)
        if m is not None and m.get("ate_se3_aligned_m") is not None:
            lines.append(f"{label:<22}{m['ate_se3_aligned_m'] * 100:20.2f}cm")
    lines.append(f"corrections: {metrics['corrections_accepted']} accepted, "
                 f"{metrics['corrections_rejected_or_skipped']} rejected or skipped, of {metrics['keyframes']} keyframes")
    lines.append(f"total time: {seconds:.0f} s")
    return "\n".join(lines)
