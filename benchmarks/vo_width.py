"""The feature odometry at the render's width (``--odom vo --vo-width 320``) against the frames
as read: speed and accuracy of the whole run.

On a recording's second half (the field built on the first half, ``--field``), for each
matcher: the odometry alone (drift: ATE without alignment; milliseconds per step, median and
p90), then whole runs with the field, inline and overlapped (``--overlap``), as fast as they
go: ATE of the smoothed and of the causal trajectory, corrections accepted, frames per second,
and how many times a real frame's features were detected (at 320 the odometry's are handed to
each keyframe's correction, one detection per frame). With ``--paced``, each matcher at the
narrow width also runs fed as its camera delivered the frames (``CameraPace``, as ``run
--pace``), overlapped and landing within a frame, a keyframe every 5 frames: how late it took
the frames, and its ATE and causal ATE. Speeds are ratios within this process (the machine is
shared), absolute figures beside. Writes JSON.

    python benchmarks/vo_width.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --field FIELD.pt [--matcher sift xfeat] [--width 320] [--paced] --out OUT.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from provenance import write_result
from scoring import unaligned_ate_m


def odometry_alone(sequence, matcher: str, width: int | None) -> dict:
    from nap3d_graph.motion.odometry import make_odometry

    odometry = make_odometry("vo", sequence, matcher=matcher, vo_width=width)
    odometry.prime(sequence[0])
    T, step_s = [odometry.initial_pose()], []
    for i in range(1, len(sequence)):
        frame = sequence[i]
        t0 = time.perf_counter()
        inc = odometry.increment(i, frame)
        step_s.append(time.perf_counter() - t0)
        T.append(T[-1] @ inc.T_prev_cur)
    return {"ate_m": unaligned_ate_m(np.array(T), sequence.T_world_cam_gt),
            "step_ms": {"median": 1000 * float(np.median(step_s)), "p90": 1000 * float(np.percentile(step_s, 90))}}


def paced_run(sequence, field, matcher: str, width: int | None) -> dict:
    """Fed at the camera's rate, overlapped, a correction done within 0.9 of a frame period of a
    frame's arrival landing at that frame (``run --pace --land-within frame``)."""
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pacing import CameraPace
    from nap3d_graph.run.pipeline import Pipeline

    period_s = float(np.median(np.diff(sequence.timestamps)))
    config = PipelineConfig(align=AlignConfig(matcher=matcher), overlap=True, land_within_s=0.9 * period_s,
                            progress=False)
    pace = CameraPace(sequence.timestamps)
    result = Pipeline(sequence, field, make_odometry("vo", sequence, matcher=matcher, vo_width=width),
                      config).run(stop=pace)
    gt = sequence.T_world_cam_gt
    return {"camera_rate_hz": 1.0 / period_s, **pace.summary(), "ate_m": unaligned_ate_m(result.T_world_cam_estimate, gt),
            "ate_causal_m": unaligned_ate_m(result.T_world_cam_online, gt),
            "accepted": sum(k.accepted for k in result.keyframes), "keyframes": len(result.keyframes)}


def whole_run(sequence, field, matcher: str, width: int | None, overlap: bool) -> dict:
    import nap3d_graph.nap3d.correct as correct_module
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pipeline import Pipeline

    detect, calls = correct_module.detect_features, []

    def counted(*args, **kwargs):  # every real frame's detection, the odometry's and the corrections'
        calls.append(1)
        return detect(*args, **kwargs)

    correct_module.detect_features = counted
    try:
        config = PipelineConfig(align=AlignConfig(matcher=matcher), overlap=overlap, progress=False)
        odometry = make_odometry("vo", sequence, matcher=matcher, vo_width=width)
        t0 = time.perf_counter()
        result = Pipeline(sequence, field, odometry, config).run()
        wall_s = time.perf_counter() - t0
    finally:
        correct_module.detect_features = detect
    gt = sequence.T_world_cam_gt
    return {"overlap": overlap, "frames_per_s": len(sequence) / wall_s,
            "ate_m": unaligned_ate_m(result.T_world_cam_estimate, gt), "ate_causal_m": unaligned_ate_m(result.T_world_cam_online, gt),
            "ate_odometry_m": unaligned_ate_m(result.T_world_cam_odometry, gt),
            "accepted": sum(k.accepted for k in result.keyframes), "keyframes": len(result.keyframes),
            "real_frame_detections": len(calls)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--frames", default="0.5:1")
    p.add_argument("--field", type=Path, required=True, help="a field built on the other frames")
    p.add_argument("--matcher", nargs="+", default=["sift", "xfeat"])
    p.add_argument("--width", type=int, default=320, help="the odometry's width to compare with the frames as read")
    p.add_argument("--paced", action="store_true", help="also feed each matcher at --width at the camera's rate")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/vo_width_fr1_desk.json"))
    args = p.parse_args()

    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields import load_field

    sequence = open_sequence(args.data, frames=args.frames)
    field = load_field(args.field)
    out = {"data": args.data.name, "frames": args.frames, "field": str(args.field), "runs": []}
    for matcher in args.matcher:
        for width in (None, args.width):
            row = {"matcher": matcher, "vo_width": width, "odometry_alone": odometry_alone(sequence, matcher, width),
                   "inline": whole_run(sequence, field, matcher, width, False),
                   "overlapped": whole_run(sequence, field, matcher, width, True)}
            out["runs"].append(row)
            alone, inline, overlapped = row["odometry_alone"], row["inline"], row["overlapped"]
            print(f"{matcher:6s} width {width or 'as read'}: odometry alone {100 * alone['ate_m']:.2f} cm, "
                  f"{alone['step_ms']['median']:.0f} ms/step; inline {inline['frames_per_s']:.1f} frame/s, ATE "
                  f"{100 * inline['ate_m']:.2f} cm (causal {100 * inline['ate_causal_m']:.2f}), "
                  f"{inline['accepted']}/{inline['keyframes']}, {inline['real_frame_detections']} detections; "
                  f"overlapped {overlapped['frames_per_s']:.1f} frame/s, ATE {100 * overlapped['ate_m']:.2f} cm "
                  f"(causal {100 * overlapped['ate_causal_m']:.2f})", flush=True)
        plain, narrow = out["runs"][-2], out["runs"][-1]
        for mode in ("inline", "overlapped"):
            narrow[mode]["frames_per_s_vs_as_read"] = narrow[mode]["frames_per_s"] / plain[mode]["frames_per_s"]
        if args.paced:
            paced = narrow["paced"] = paced_run(sequence, field, matcher, args.width)
            print(f"{matcher:6s} width {args.width} fed at {paced['camera_rate_hz']:.0f} Hz, overlapped: up to "
                  f"{1000 * paced['behind_camera_s']['max']:.0f} ms behind the camera "
                  f"({paced['frames_over_a_period_late']} frames over a period late), ATE {100 * paced['ate_m']:.2f} cm "
                  f"(causal {100 * paced['ate_causal_m']:.2f}), {paced['accepted']}/{paced['keyframes']}", flush=True)
    write_result(args.out, out, args)


if __name__ == "__main__":
    main()
