"""How good can one correction be on a real recording? Each test frame aligned at its
ground-truth pose, and runs with ever denser keyframes.

A correction that starts at the *true* pose, with the camera's true motion for the rolling
shutter and the depth moved to the colour's instant along the ground truth, measures only
what the map and the sensor disagree on, which no run with that map averages away where it
is shared by neighbouring keyframes (the ground truth's own consistency between the map's
frames and the test frame, the depth camera's distortion seen from two viewpoints, the
field's rendering). With a view field (the map's
sharpest frames, re-projected) each test frame is also aligned to each of its ``--views``
nearest training frames *alone*, from that frame's own pose: if the views' errors were
independent, their mean would beat any one of them by sqrt(n); the share of the error they
have in common says how much of it no number of views can average away (they share the test
frame too: its depth, its blur, its own ground-truth pose). ``--also-field`` aligns the same
frames, with the same motion, to other maps (a grid, a splat field): what two maps' errors have
in common belongs to the test frame and the ground truth, what they do not to the maps.

Per test frame (every ``--step``-th of ``--frames``): the error of the corrected pose
against the ground truth (translation mm, rotation deg) aligned to the field's render, with
and without the rolling shutter's motion; per view alone; the camera's speed. Then
``--keyframe-every`` runs of ``nap3d-graph run`` (``--odom``, ``--matcher``) on the same
frames: ATE (no alignment) as keyframes get denser, down to every frame. Writes JSON.

    python benchmarks/correction_floor.py --field VIEW_FIELD.pt [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk] \\
        [--also-field grid=G.pt] [--frames 0.5:1] [--step 3] [--views 5] [--keyframe-every 1 2 5] \\
        [--out benchmarks/results/correction_floor_fr1_desk.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from provenance import write_result

from nap3d_graph.camera import warp_depth
from nap3d_graph.conventions import inv_T, log_se3, pose_error
from nap3d_graph.datasets import open_sequence, source_of
from nap3d_graph.fields import load_field
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.correct import correct_pose
from nap3d_graph.nap3d.rolling_shutter import RowMotion
from nap3d_graph.run.library_threads import library_threads

#: Above this speed (m/s) a frame counts as fast (fr1/desk's second half: 0.02-0.94 m/s).
FAST_M_PER_S = 0.4


def frame_range(spec: str, n: int) -> range:
    """``START:STOP`` as fractions of the recording (``0.5:1``) or frame numbers."""
    a, b = (float(x) for x in spec.split(":"))
    start, stop = (int(round(a * n)), int(round(b * n))) if max(a, b) <= 1.0 else (int(a), int(b))
    return range(max(start, 1), min(stop, n))  # frame 0 has no previous frame to take the motion from


def at_true_pose(sequence, i: int, timing: dict):
    """Frame i with its depth moved to its colour's instant along the ground truth, its
    ground-truth pose at that instant and its body twist (GTSAM order, per second) from the
    previous frame's ground truth (a backward step, as a run takes it from its odometry)."""
    stamps = np.asarray(sequence.timestamps, dtype=float)
    colour_offset = float(timing.get("colour_offset_s", 0.0))
    T_colour = sequence.ground_truth_at([stamps[i] + colour_offset])[0]
    T_before = sequence.ground_truth_at([stamps[i - 1] + colour_offset])[0]
    twist = log_se3(inv_T(T_before) @ T_colour) / (stamps[i] - stamps[i - 1])
    frame = sequence[i]
    depth_stamps = getattr(sequence, "depth_timestamps", None)
    if depth_stamps is not None and "depth_offset_s" in timing:
        T_depth = sequence.ground_truth_at([np.asarray(depth_stamps)[i] + float(timing["depth_offset_s"])])[0]
        frame = frame.with_depth(warp_depth(frame.depth_m, frame.intrinsics, inv_T(T_colour) @ T_depth,
                                            float(timing.get("depth_scale", 1.0))))
    return frame, T_colour, twist


def errors(correction, T_true: np.ndarray) -> tuple[np.ndarray, float]:
    """(translation error vector (3,) mm, rotation error deg); NaN where it failed."""
    if not correction.success:
        return np.full(3, np.nan), float("nan")
    t_err = (correction.T_world_cam_corrected[:3, 3] - T_true[:3, 3]) * 1000
    return t_err, pose_error(correction.T_world_cam_corrected, T_true)[1]


def measure_frame(sequence, i: int, field, config: AlignConfig, K, views: int, readout_s: float,
                  others: dict) -> dict:
    frame, T_true, twist = at_true_pose(sequence, i, field.meta.get("timing") or {})
    motion = RowMotion(twist, readout_s) if readout_s > 0 else None
    row: dict = {"frame": i, "speed_m_per_s": float(np.linalg.norm(twist[3:]))}
    for name, other in others.items():  # the same frame, the same motion, another map
        c = correct_pose(frame, other, T_true, iterations=1, config=config, render_intrinsics=K, motion=motion)
        t_err, r_err = errors(c, T_true)
        row[f"field:{name}"] = {"t_err_mm": t_err.tolist(), "r_err_deg": r_err, "inliers": c.alignment.num_inliers}
    for name, m in (("composite", motion), ("composite_no_shutter", None)):
        if name == "composite_no_shutter" and motion is None:
            continue
        c = correct_pose(frame, field, T_true, iterations=1, config=config, render_intrinsics=K, motion=m)
        t_err, r_err = errors(c, T_true)
        row[name] = {"t_err_mm": t_err.tolist(), "r_err_deg": r_err, "inliers": c.alignment.num_inliers}
    if hasattr(field, "only_views"):
        row["views"] = []
        for j in field.nearest_views(T_true, views):
            c = correct_pose(frame, field.only_views([j]), field.T_world_cam[j], iterations=1, config=config,
                             render_intrinsics=K, motion=motion)
            t_err, r_err = errors(c, T_true)
            row["views"].append({"view": int(j), "t_err_mm": t_err.tolist(), "r_err_deg": r_err})
    return row


def spread(values) -> dict:
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=float)
    if v.size == 0:
        return {"n": 0}
    return {"n": int(v.size), "median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
            "max": float(v.max()), "rms": float(np.sqrt(np.mean(v**2)))}


def shared_with(a: np.ndarray, b: np.ndarray) -> dict:
    """How much two maps' errors (N, 3) mm on the same frames have in common: per-axis
    correlation, and the share of the error power in their mean (0.5 when independent with
    equal spread, 1 when the same)."""
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    a, b = a[ok], b[ok]
    mean, half_diff = (a + b) / 2, (a - b) / 2
    return {"frames": int(ok.sum()), "correlation_xyz": [float(np.corrcoef(a[:, k], b[:, k])[0, 1]) for k in range(3)],
            "share_of_power_in_common": float(np.sum(mean**2) / (np.sum(mean**2) + np.sum(half_diff**2)))}


def summarise(rows: list[dict]) -> dict:
    out: dict = {}
    fast = np.array([r["speed_m_per_s"] > FAST_M_PER_S for r in rows])
    main_err = np.array([r["composite"]["t_err_mm"] for r in rows], dtype=float)
    for key in [k for k in rows[0] if k.startswith("field:")]:
        e = np.array([r[key]["t_err_mm"] for r in rows], dtype=float)
        t = np.linalg.norm(e, axis=1)
        out[key] = {"translation_mm": spread(t), "rotation_deg": spread([r[key]["r_err_deg"] for r in rows]),
                    "failed": int(np.sum(~np.isfinite(t))), "shared_with_composite": shared_with(main_err, e)}
    for name in ("composite", "composite_no_shutter"):
        if name not in rows[0]:
            continue
        t = np.array([np.linalg.norm(r[name]["t_err_mm"]) for r in rows])
        out[name] = {"translation_mm": spread(t), "rotation_deg": spread([r[name]["r_err_deg"] for r in rows]),
                     "failed": int(np.sum(~np.isfinite(t))),
                     "fast_translation_mm": spread(t[fast]), "slow_translation_mm": spread(t[~fast]),
                     "fast_frames": int(fast.sum()), "slow_frames": int((~fast).sum())}
    if "views" in rows[0]:
        singles, means, common, own = [], [], [], []
        counts = []
        for r in rows:
            e = np.array([v["t_err_mm"] for v in r["views"]], dtype=float).reshape(-1, 3)
            e = e[np.all(np.isfinite(e), axis=1)]
            if len(e) < 2:
                continue
            m = e.mean(axis=0)
            singles += list(np.linalg.norm(e, axis=1))
            means.append(float(np.linalg.norm(m)))
            common.append(float(m @ m))
            own += list(np.sum((e - m) ** 2, axis=1) * len(e) / (len(e) - 1))  # unbiased per-view scatter
            counts.append(len(e))
        n = float(np.mean(counts))
        # If the views' errors were independent, the mean's power would be the scatter's / n.
        independent_rms = float(np.sqrt(np.mean(own) / n))
        out["views_alone"] = {
            "frames": len(means), "views_per_frame": n,
            "single_translation_mm": spread(singles), "mean_of_views_translation_mm": spread(means),
            "mean_of_views_rms_if_independent_mm": independent_rms,
            "shared_share_of_error_power": float(np.mean(common) / (np.mean(common) + np.mean(own))),
        }
    return out


def run_density(data: Path, field: Path, frames: str, odom: str, matcher: str, every: int, out: Path) -> dict:
    from nap3d_graph.cli import main

    started = time.perf_counter()
    rc = main(["run", "--traj", source_of(data), "--data", str(data), "--frames", frames, "--field", str(field), "--odom", odom,
               "--matcher", matcher, "--keyframe-every", str(every), "--out", str(out)])
    if rc != 0:
        return {"error": f"exit {rc}"}
    metrics = json.loads((out / "latest" / "metrics.json").read_text())
    ate = metrics["estimate"]["ate_m"]
    return {"keyframe_every": every, "ate_m": ate["rmse"], "ate_median_m": ate["median"], "ate_max_m": ate["max"],
            "ate_causal_m": metrics.get("estimate_online", {}).get("ate_m", {}).get("rmse"),
            "ate_odometry_m": metrics["odometry"]["ate_m"]["rmse"], "keyframes": metrics["keyframes"],
            "accepted": metrics["corrections_accepted"], "seconds": time.perf_counter() - started}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--field", type=Path, required=True, help="a field built by train-field on the other frames")
    p.add_argument("--frames", default="0.5:1", help="the test frames (the field must not be built on them)")
    p.add_argument("--step", type=int, default=3, help="align every STEP-th test frame at its true pose")
    p.add_argument("--views", type=int, default=5, help="a view field: align to each of this many nearest views alone")
    p.add_argument("--also-field", action="append", default=[], metavar="NAME=FIELD.pt",
                   help="also align each test frame to this map at its true pose (no runs), and say how much its "
                        "errors share with --field's")
    p.add_argument("--matcher", default="xfeat")
    p.add_argument("--odom", default="vo")
    p.add_argument("--keyframe-every", type=int, nargs="*", default=[1, 2, 5], help="runs at these spacings")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/correction_floor_fr1_desk.json"))
    args = p.parse_args(argv)

    sequence = open_sequence(args.data)
    field = load_field(args.field)
    K = sequence.intrinsics.scaled(320, 240)
    config = AlignConfig(matcher=args.matcher)
    timing = field.meta.get("timing") or {}
    readout_s = float(timing.get("readout_s") or 0.0)
    others = {name: load_field(path) for name, path in (spec.split("=", 1) for spec in args.also_field)}
    test = frame_range(args.frames, len(sequence))
    rows = []
    with library_threads(1):
        for i in test[::args.step]:
            rows.append(row := measure_frame(sequence, i, field, config, K, args.views, readout_s, others))
            c = row["composite"]
            print(f"frame {i}: {np.linalg.norm(c['t_err_mm']):.1f} mm at the true pose "
                  f"({row['speed_m_per_s']:.2f} m/s)", flush=True)
    result = {"data": str(args.data), "field": str(args.field), "also_fields": args.also_field, "frames": args.frames, "step": args.step,
              "matcher": args.matcher, "readout_s": readout_s, "timing": timing,
              "ground_truth_agreement_mm": timing.get("agreement_mm"),
              "fast_above_m_per_s": FAST_M_PER_S, "at_true_pose": summarise(rows), "per_frame": rows, "runs": []}
    work = Path(tempfile.mkdtemp(prefix="correction_floor_"))
    for every in args.keyframe_every:
        result["runs"].append(r := run_density(args.data, args.field, args.frames, args.odom, args.matcher, every,
                                               work / str(every)))
        if "error" not in r:
            print(f"keyframe every {every}: ATE {r['ate_m'] * 100:.2f} cm (causal {r['ate_causal_m'] * 100:.2f}, "
                  f"odometry {r['ate_odometry_m'] * 100:.2f}), {r['accepted']}/{r['keyframes']} accepted", flush=True)
    s = result["at_true_pose"]
    print(json.dumps(s, indent=1))
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
