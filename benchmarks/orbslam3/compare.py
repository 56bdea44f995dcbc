"""ORB-SLAM3 (RGB-D, through pyorbslam3) on the frames and ATE protocol of ``map_survey.py``.

Frames come from the project's reader (``open_sequence(data, frames="0:0.5")`` for the
survey, ``"0.5:1"`` for the query): the same associated pairs, timestamps and interpolated
ground truth as ``nap3d-graph map``. Colour is the reader's undistorted RGB (so the
settings file has zero distortion), depth the stored Kinect depth (not remapped), passed
in the file's units (5000 per metre, ``RGBD.DepthMapFactor: 5000``).

(a) survey: RGB-D SLAM on the first half; after ``shutdown`` the saved trajectory
    (``SaveTrajectoryTUM``, every tracked frame) is SE(3)-aligned to the ground truth with
    ``nap3d_graph.evaluation.alignment.aligned_errors`` (as map_survey.py does); tracking
    frame/s = frames / time spent inside ``track_rgbd``.
(b) localisation: a fresh system maps the first half, ``activate_localization_mode()``,
    then tracks the second half; the second half's poses are put in the ground truth's frame
    through the *first half's* alignment of that same run (``T_ref_est``, no second
    alignment) and scored; frames whose tracking state is not OK, and frames missing from
    the saved trajectory, are counted as lost.

Each run is its own process (ORB-SLAM3 keeps static state and is multi-threaded, so runs
differ); frames are fed at the recording's rate (as ORB-SLAM3's rgbd_tum example does)
unless ``--no-pace``.

    python benchmarks/orbslam3/compare.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --vocab /tmp/orbslam3/ORBvoc_built.txt --out benchmarks/results/orbslam3_fr1_desk.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SETTINGS = """%YAML:1.0
File.version: "1.0"
Camera.type: "PinHole"
# {comment}
Camera1.fx: {fx}
Camera1.fy: {fy}
Camera1.cx: {cx}
Camera1.cy: {cy}
Camera1.k1: {k1}
Camera1.k2: {k2}
Camera1.p1: {p1}
Camera1.p2: {p2}
Camera1.k3: {k3}
Camera.width: {width}
Camera.height: {height}
Camera.fps: {fps}
Camera.RGB: 1
# close/far threshold in baselines; Stereo.b * fx = Camera.bf = 40
Stereo.ThDepth: 40.0
Stereo.b: {b}
RGBD.DepthMapFactor: 5000.0
ORBextractor.nFeatures: 1000
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
Viewer.KeyFrameSize: 0.05
Viewer.KeyFrameLineWidth: 1.0
Viewer.GraphLineWidth: 0.9
Viewer.PointSize: 2.0
Viewer.CameraSize: 0.08
Viewer.CameraLineWidth: 3.0
Viewer.ViewpointX: 0.0
Viewer.ViewpointY: -0.7
Viewer.ViewpointZ: -1.8
Viewer.ViewpointF: 500.0
"""


# TUM's published freiburg1 colour calibration (fx fy cx cy k1 k2 p1 p2 k3)
FR1 = (517.306408, 516.469215, 318.643040, 255.313989, 0.262383, -0.953104, -0.005358, 0.002628, 1.163314)


def write_settings(path: Path, seq, fps: float, raw: bool) -> dict:
    K = seq.intrinsics
    if raw:
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = FR1
        comment = "stored (distorted) colour images: TUM's freiburg1 calibration, ORB-SLAM3 undistorts keypoints"
    else:
        fx, fy, cx, cy, (k1, k2, p1, p2, k3) = float(K.fx), float(K.fy), float(K.cx), float(K.cy), (0.0,) * 5
        comment = "undistorted colour from nap3d_graph's reader: its intrinsics, distortion 0"
    vals = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3,
            "comment": comment, "width": int(K.width), "height": int(K.height), "fps": int(round(fps)),
            "b": 40.0 / fx}
    path.write_text(SETTINGS.format(**vals))
    return vals


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from nap3d_graph.conventions import make_T, quat_xyzw_to_R

    rows = [list(map(float, ln.split())) for ln in Path(path).read_text().splitlines()
            if ln.strip() and not ln.startswith("#")]
    if not rows:
        return np.zeros(0), np.zeros((0, 4, 4))
    a = np.array(rows)
    T = np.stack([make_T(quat_xyzw_to_R(r[4:8]), r[1:4]) for r in a])
    return a[:, 0], T


def poses_at(stamps: np.ndarray, t_file: np.ndarray, T_file: np.ndarray, tol: float = 2e-3) -> np.ndarray:
    """(N, 4, 4) poses at ``stamps`` from a saved trajectory; NaN where the file has none."""
    out = np.full((len(stamps), 4, 4), np.nan)
    if len(t_file) == 0:
        return out
    j = np.clip(np.searchsorted(t_file, stamps), 1, len(t_file) - 1)
    j = np.where(np.abs(t_file[j - 1] - stamps) < np.abs(t_file[j] - stamps), j - 1, j)
    ok = np.abs(t_file[j] - stamps) <= tol
    out[ok] = T_file[j[ok]]
    return out


# ---------------------------------------------------------------- one run (own process)

def load_frames(seq, raw: bool):
    if raw:  # the stored files of the same associated pairs
        import cv2

        rgb = [cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) for p in seq.rgb_paths]
        depth = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float32) for p in seq.depth_paths]
        return rgb, depth, np.asarray(seq.timestamps, dtype=float)
    rgb = [np.ascontiguousarray(seq[i].rgb) for i in range(len(seq))]
    depth = [np.ascontiguousarray(seq[i].depth_m * 5000.0, dtype=np.float32) for i in range(len(seq))]
    return rgb, depth, np.asarray(seq.timestamps, dtype=float)


def track(slam, rgb, depth, stamps, pace: bool):
    import pyorbslam3 as pos

    states, poses, secs = [], np.full((len(stamps), 4, 4), np.nan), np.zeros(len(stamps))
    for i in range(len(stamps)):
        t0 = time.perf_counter()
        r = slam.track_rgbd(rgb[i], depth[i], stamps[i])
        secs[i] = time.perf_counter() - t0
        states.append(r.state.name if hasattr(r.state, "name") else str(r.state))
        if r.pose_valid and r.pose_wc is not None:
            poses[i] = np.asarray(r.pose_wc, dtype=float)
        if pace and i + 1 < len(stamps):
            wait = (stamps[i + 1] - stamps[i]) - secs[i]
            if wait > 0:
                time.sleep(wait)
    del pos
    return states, poses, secs


def worker(args) -> int:
    import pyorbslam3 as pos

    from nap3d_graph.datasets import open_sequence

    work = Path(args.work)
    survey = open_sequence(args.data, frames=f"0:{args.split}")
    s_rgb, s_depth, s_t = load_frames(survey, args.input == "raw")
    out = {"survey_stamps": s_t}
    if args.mode == "localise":
        query = open_sequence(args.data, frames=f"{args.split}:1")
        q_rgb, q_depth, q_t = load_frames(query, args.input == "raw")
        out["query_stamps"] = q_t
    t0 = time.perf_counter()
    slam = pos.Slam(args.vocab, str(work / "settings.yaml"), pos.Sensor.RGBD)
    out["vocab_load_s"] = time.perf_counter() - t0
    st, P, secs = track(slam, s_rgb, s_depth, s_t, not args.no_pace)
    out.update(survey_states=np.array(st), survey_online=P, survey_track_s=secs)
    if args.mode == "localise":
        slam.activate_localization_mode()
        st, P, secs = track(slam, q_rgb, q_depth, q_t, not args.no_pace)
        out.update(query_states=np.array(st), query_online=P, query_track_s=secs)
    slam.shutdown()
    traj = work / f"traj_{args.mode}_{args.run_index}.txt"
    slam.save_trajectory_tum(str(traj))
    t_file, T_file = read_tum(traj)
    out["survey_saved"] = poses_at(s_t, t_file, T_file)
    if args.mode == "localise":
        out["query_saved"] = poses_at(q_t, t_file, T_file)
    np.savez(work / f"run_{args.mode}_{args.run_index}.npz", **out)
    return 0


# ---------------------------------------------------------------- driver

def stats(values):
    v = np.array([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if len(v) == 0:
        return None
    return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max()), "n": int(len(v))}


def errors_through(T_ref_est, T_gt, T_est) -> dict | None:
    ok = np.all(np.isfinite(T_gt), axis=(1, 2)) & np.all(np.isfinite(T_est), axis=(1, 2))
    if not ok.any():
        return None
    e = np.linalg.norm((T_ref_est @ T_est[ok])[:, :3, 3] - T_gt[ok, :3, 3], axis=1)
    return {"rmse_m": float(np.sqrt(np.mean(e**2))), "median_m": float(np.median(e)),
            "p90_m": float(np.percentile(e, 90)), "max_m": float(e.max()), "frames": int(ok.sum())}


def score(mode: str, d, gt_s, gt_q) -> dict:
    from nap3d_graph.evaluation.alignment import aligned_errors

    s_t = d["survey_stamps"]
    res = {"vocab_load_s": round(float(d["vocab_load_s"]), 2)}
    secs = d["survey_track_s"]
    states = list(d["survey_states"])
    res["survey"] = {
        "frames": len(s_t), "frames_in_saved_trajectory": int(np.isfinite(d["survey_saved"][:, 0, 0]).sum()),
        "tracking_states": {s: states.count(s) for s in sorted(set(states))},
        "tracking_fps": float(len(secs) / secs.sum()), "track_ms_median": float(1e3 * np.median(secs)),
    }
    al = aligned_errors(s_t, gt_s, d["survey_saved"])
    res["survey"]["ate"] = None if al is None else al.summary()
    al_online = aligned_errors(s_t, gt_s, d["survey_online"])
    res["survey"]["ate_online"] = None if al_online is None else al_online.summary()
    if al is not None:
        res["survey"]["T_gt_est"] = al.T_ref_est.tolist()
    # diagnostic: the frames before tracking first failed (one map), aligned on their own
    bad = [i for i, s in enumerate(states) if s not in ("OK", "NO_IMAGES_YET", "NOT_INITIALIZED")]
    first = bad[0] if bad else len(states)
    res["survey"]["first_not_ok_frame"] = None if not bad else int(first)
    al_pre = aligned_errors(s_t[:first], gt_s[:first], d["survey_saved"][:first]) if first >= 3 else None
    res["survey"]["ate_before_first_loss"] = None if al_pre is None else al_pre.summary()
    active_from = (bad[-1] + 1) if bad else 0
    al_act = aligned_errors(s_t[active_from:], gt_s[active_from:], d["survey_saved"][active_from:]) \
        if len(states) - active_from >= 3 else None
    if mode == "localise":
        q_t = d["query_stamps"]
        qs = list(d["query_states"])
        secs = d["query_track_s"]
        saved = d["query_saved"]
        res["query"] = {
            "frames": len(q_t),
            "tracking_states": {s: qs.count(s) for s in sorted(set(qs))},
            "lost_frames": int(sum(s != "OK" for s in qs)),
            "frames_missing_from_saved_trajectory": int((~np.isfinite(saved[:, 0, 0])).sum()),
            "tracking_fps": float(len(secs) / secs.sum()),
            "ate_through_survey_alignment": None if al is None else errors_through(al.T_ref_est, gt_q, saved),
            "ate_online_through_survey_alignment": None if al is None else
            errors_through(al.T_ref_est, gt_q, d["query_online"]),
            # diagnostic: through the alignment of the survey frames tracked after the survey's
            # last failure, i.e. those in the map that is active when localisation starts
            "active_map_survey_frames": int(len(states) - active_from),
            "ate_through_active_map_survey_alignment": None if al_act is None else
            errors_through(al_act.T_ref_est, gt_q, saved),
            # diagnostic only (not the protocol): the query aligned on its own
            "ate_own_alignment_diagnostic": (lambda a: None if a is None else a.summary())(
                aligned_errors(q_t, gt_q, saved)),
        }
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--vocab", required=True)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--split", type=float, default=0.5)
    ap.add_argument("--fps", type=float, default=15.0, help="Camera.fps (the folder keeps every second pair: ~15 Hz)")
    ap.add_argument("--input", choices=["raw", "undistorted"], default="raw",
                    help="raw: the stored images with TUM's distortion in the settings (ORB-SLAM3's own "
                         "TUM setup); undistorted: the reader's undistorted colour, distortion 0")
    ap.add_argument("--no-pace", action="store_true", help="feed frames as fast as tracking goes")
    ap.add_argument("--work", help="folder for settings, trajectories and per-run arrays (default: a temp dir)")
    ap.add_argument("--rescore", action="store_true",
                    help="do not run ORB-SLAM3: score the per-run arrays already in --work")
    ap.add_argument("--mode", choices=["survey", "localise"], help=argparse.SUPPRESS)
    ap.add_argument("--run-index", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.mode:
        return worker(args)

    import pyorbslam3

    from nap3d_graph.datasets import open_sequence

    t_start = time.time()
    work = Path(args.work or tempfile.mkdtemp(prefix="orbslam3_"))
    work.mkdir(parents=True, exist_ok=True)
    survey = open_sequence(args.data, frames=f"0:{args.split}")
    query = open_sequence(args.data, frames=f"{args.split}:1")
    settings = write_settings(work / "settings.yaml", survey, args.fps, args.input == "raw")
    gt_s, gt_q = np.asarray(survey.T_world_cam_gt, float), np.asarray(query.T_world_cam_gt, float)

    base = [sys.executable, str(Path(__file__).resolve()), "--data", args.data, "--vocab", args.vocab,
            "--split", str(args.split), "--work", str(work), "--fps", str(args.fps),
            "--input", args.input]
    if args.no_pace:
        base.append("--no-pace")
    runs = {"survey": [], "localise": []}
    for mode in ("survey", "localise"):
        for i in range(args.runs):
            t0 = time.time()
            log, npz = work / f"run_{mode}_{i}.log", work / f"run_{mode}_{i}.npz"
            if args.rescore:  # score the arrays an earlier invocation left in --work
                p = subprocess.CompletedProcess([], 0 if npz.exists() else 1, "", "no arrays to rescore")
            else:
                p = subprocess.run(base + ["--mode", mode, "--run-index", str(i)], capture_output=True, text=True)
                log.write_text(p.stdout + "\n--- stderr ---\n" + p.stderr)
            if p.returncode != 0 or not npz.exists():
                runs[mode].append({"failed": f"exit {p.returncode}, see {log}", "stderr_tail": p.stderr[-500:]})
                print(f"{mode} run {i}: FAILED (exit {p.returncode})")
                continue
            r = score(mode, np.load(npz), gt_s, gt_q)
            r["wall_s"] = None if args.rescore else round(time.time() - t0, 1)
            runs[mode].append(r)
            s_ate = (r["survey"]["ate"] or {}).get("rmse_m")
            line = f"{mode} run {i}: survey ATE {s_ate if s_ate is None else round(s_ate, 4)} m, " \
                   f"{r['survey']['tracking_fps']:.1f} frame/s"
            if mode == "localise":
                q = r["query"]
                q_ate = (q["ate_through_survey_alignment"] or {}).get("rmse_m")
                line += f"; query ATE {q_ate if q_ate is None else round(q_ate, 4)} m, lost {q['lost_frames']}/{q['frames']}"
            print(line, flush=True)

    def pick(mode, *keys):
        vals = []
        for r in runs[mode]:
            v = r
            for k in keys:
                v = None if v is None else v.get(k)
            vals.append(v)
        return vals

    vocab_meta = Path(args.vocab + ".json")
    vocab = json.loads(vocab_meta.read_text()) if vocab_meta.exists() else {"file": args.vocab}
    vocab = {k: v for k, v in vocab.items() if k != "image_paths"} | {
        "image_paths": vocab.get("image_paths")}
    result = {
        "command": " ".join(["benchmarks/orbslam3/compare.py"] + (sys.argv[1:] if argv is None else list(argv))),
        "system": "ORB-SLAM3 RGB-D via pyorbslam3", "pyorbslam3_version": getattr(pyorbslam3, "__version__", None)
        or __import__("importlib.metadata").metadata.version("pyorbslam3"),
        "data": args.data, "survey_frames": f"0:{args.split}", "query_frames": f"{args.split}:1",
        "frames": {"survey": len(survey), "query": len(query)},
        "input": {"raw": "stored RGB and depth files of the reader's associated pairs; TUM fr1 distortion in settings",
                  "undistorted": "nap3d_graph reader: undistorted RGB, stored depth (5000/m), zero distortion in settings"
                  }[args.input],
        "paced_at_recording_rate": not args.no_pace,
        "rescored_from_earlier_arrays": bool(args.rescore),
        "settings": settings,
        "summary": {
            "a_survey_ate_rmse_m": stats(pick("survey", "survey", "ate", "rmse_m")),
            "a_survey_tracking_fps": stats(pick("survey", "survey", "tracking_fps")),
            "a_survey_first_not_ok_frame": stats(pick("survey", "survey", "first_not_ok_frame")),
            "a_survey_ate_before_first_loss_rmse_m": stats(pick("survey", "survey", "ate_before_first_loss", "rmse_m")),
            "b_survey_ate_rmse_m": stats(pick("localise", "survey", "ate", "rmse_m")),
            "b_query_ate_rmse_m_through_survey_alignment": stats(pick("localise", "query", "ate_through_survey_alignment", "rmse_m")),
            "b_query_lost_frames": stats(pick("localise", "query", "lost_frames")),
            "b_query_ate_through_active_map_survey_alignment_rmse_m": stats(pick("localise", "query", "ate_through_active_map_survey_alignment", "rmse_m")),
            "b_query_ate_own_alignment_diagnostic_rmse_m": stats(pick("localise", "query", "ate_own_alignment_diagnostic", "rmse_m")),
            "b_query_tracking_fps": stats(pick("localise", "query", "tracking_fps")),
        },
        "runs": runs,
        "vocabulary": vocab,
        "work": str(work),
        "seconds": round(time.time() - t_start, 1),
    }
    print(json.dumps(result["summary"], indent=1))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
