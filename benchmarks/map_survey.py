"""A map from the camera alone against one pinned to the ground truth, on a real recording.

Protocol (issue 42): the first part of a recording (``--split``) is the survey, the rest the
query.

1. ``nap3d-graph map`` on the survey (its ground truth never read to build it): the survey
   poses' ATE against the ground truth (SE(3)-aligned), and against ``--second-gt`` where a
   second ground truth exists (7-Scenes' SfM pseudo ground truth), with the odometry alone beside.
2. A field of the same model trained on the survey at its ground-truth poses
   (``train-field``), the comparison map.
3. The query corrected on each map with ``run --odom vo``: on the self-posed map it starts
   with ``--initial-pose auto`` and is scored in the ground truth's frame through the
   *survey's* alignment (no alignment of its own); on the ground-truth-posed map it starts
   at the ground truth's first pose. With a second ground truth, both runs are scored
   against it too, each through its survey's alignment to it.
4. Relocalisation: ``--relocalise`` random query frames (seeded) found in the self-posed
   map: share within 5 cm / 3 deg of the ground truth moved into the map, any accepted farther
   than 10 cm, seconds per attempt (one core: torch and BLAS held to one thread).

    python benchmarks/map_survey.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --out benchmarks/results/map_survey_fr1_desk.json
    python benchmarks/map_survey.py --data ../shared/data/7scenes/redkitchen --traj 7scenes \\
        --second-gt ../shared/data/7scenes/redkitchen/pseudo_gt_sfm.txt --out benchmarks/results/map_survey_redkitchen.json
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
from provenance import write_result

from nap3d_graph.conventions import inv_T, log_se3, quat_xyzw_to_R


def read_sfm_pseudo_gt(path: Path) -> dict[int, np.ndarray]:
    """7-Scenes' SfM pseudo ground truth: frame number -> T_world_cam (4, 4) of the colour
    camera (the file holds world-to-camera, quaternion w x y z, translation)."""
    out = {}
    for line in Path(path).read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, qw, qx, qy, qz, tx, ty, tz = line.split()[:8]
        T_cam_world = np.eye(4)
        T_cam_world[:3, :3] = quat_xyzw_to_R(np.array([qx, qy, qz, qw], dtype=float))
        T_cam_world[:3, 3] = [float(tx), float(ty), float(tz)]
        out[int(name.split("-")[1])] = inv_T(T_cam_world)
    return out


def second_gt_for(sequence, table: dict[int, np.ndarray]) -> np.ndarray:
    numbers = np.rint(np.asarray(sequence.timestamps) * 30.0).astype(int)
    return np.stack([table.get(int(k), np.full((4, 4), np.nan)) for k in numbers])


def cli(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "nap3d_graph", *args], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


REUSE_RUNS = False  # --reuse-runs: a run folder already in --work is read, not run again


def run_query(data, traj, frames, field, out: Path, extra=(), seed: int = 0) -> dict:
    """One ``run`` of the query on ``field``; ``seed``: NAP3D's RANSAC seed (0: the default),
    given through a ``--config`` file (the run's own ``--seed`` is its injected noise's)."""
    seconds = float("nan")
    if seed:
        out.mkdir(parents=True, exist_ok=True)
        (out / "ransac_seed.yaml").write_text(f"settings:\n  alignment:\n    nap3d:\n      seed: {int(seed)}\n")
        extra = (*extra, "--config", str(out / "ransac_seed.yaml"))
    if not (REUSE_RUNS and (out / "latest" / "metrics.json").is_file()):
        seconds = cli("run", "--traj", traj, "--data", str(data), "--frames", frames, "--field", str(field),
                      "--odom", "vo", "--out", str(out), *extra)
    metrics = json.loads((out / "latest" / "metrics.json").read_text())
    config = (out / "latest" / "config.yaml").read_text()
    from nap3d_graph.run.report import read_run_report
    from nap3d_graph.trajectory import read_tum_trajectory

    report = read_run_report(out / "latest")
    d2 = [k.gate_d2 for k in report.keyframes if np.isfinite(k.gate_d2)]

    stamps, T_est = read_tum_trajectory(out / "latest" / "estimate.txt")
    _, T_online = read_tum_trajectory(out / "latest" / "estimate_online.txt")
    return {"ate_m": metrics["estimate"]["ate_m"]["rmse"], "ate_causal_m": metrics["estimate_online"]["ate_m"]["rmse"],
            "ate_se3_aligned_m": metrics["estimate"].get("ate_se3_aligned_m"),
            "odometry_ate_m": metrics["odometry"]["ate_m"]["rmse"],
            "accepted": metrics.get("corrections_accepted"), "seconds": round(seconds, 1),
            "start": _start_of(config),
            "report": {"past_bad_line": report.bad, "gate_d2_median": float(np.median(d2)) if d2 else None,
                       "gate_d2_measured": len(d2)},
            "_stamps": stamps, "_T": T_est, "_T_online": T_online}


def _start_of(config_text: str) -> dict | str:
    """How the run started: the relocalisation's record, or 'ground truth'."""
    import yaml

    config = yaml.safe_load(config_text) or {}
    start = config.get("start") or (config.get("resolved") or {}).get("start") or {}
    found = start.get("initial_pose")
    if not found:
        return "ground truth"
    if isinstance(found, str):  # found by the run itself (start anywhere): metrics.json's map.placement
        return found
    return {k: found[k] for k in ("keyframe", "inliers", "sigma_m", "sigma_deg", "agreeing", "seconds")}


def errors_in(T_ref_of_stamp, stamps, T_est, T_ref_est) -> float:
    T_ref = T_ref_of_stamp(stamps)
    p = (T_ref_est @ T_est)[:, :3, 3]
    ok = np.all(np.isfinite(T_ref), axis=(1, 2))
    return float(np.sqrt(np.mean(np.sum((p[ok] - T_ref[ok, :3, 3]) ** 2, axis=1))))


def second_alignment(args, survey, T_map_survey):
    """The survey's poses (N, 4, 4; NaN where unposed) SE(3)-aligned to the second ground truth
    (:func:`~nap3d_graph.evaluation.alignment.aligned_errors`: its fit and its errors)."""
    from nap3d_graph.evaluation.alignment import aligned_errors

    return aligned_errors(survey.timestamps, second_gt_for(survey, read_sfm_pseudo_gt(args.second_gt)), T_map_survey)


def second_reference(args, survey, query, T_map_survey):
    """``(T_ref_cam of the query (N, 4, 4), T_ref_map)`` for the second ground truth, or None."""
    if args.second_gt is None:
        return None
    return (second_gt_for(query, read_sfm_pseudo_gt(args.second_gt)),
            second_alignment(args, survey, T_map_survey).T_ref_est)


def map_trajectory(map_dir: Path, name: str, sequence) -> np.ndarray:
    """A map folder's TUM file (``poses.txt``, ``odometry.txt``) as (N, 4, 4) over the
    sequence's frames, NaN where it has no pose."""
    from nap3d_graph.trajectory import read_tum_trajectory

    stamps, T = read_tum_trajectory(map_dir / name)
    out = np.full((len(sequence), 4, 4), np.nan)
    out[np.searchsorted(np.asarray(sequence.timestamps), stamps - 1e-6)] = T
    return out


class QueryTwist:
    """A query frame's body twist per second (GTSAM order) as a run in the map knows it when it
    relocalises that frame: its visual odometry's step from the frame before (the run's own
    ``--odom vo``, ``matcher``). None for the first frame, a failed step, or when ``off``."""

    def __init__(self, query, matcher: str, off: bool = False):
        from nap3d_graph.motion.odometry import make_odometry

        self.query, self.off = query, off
        self.odometry = None if off else make_odometry("vo", query, initial_pose=np.eye(4), matcher=matcher)

    def __call__(self, i: int, frame) -> np.ndarray | None:
        """The twist at frame ``i``, ``frame`` being that frame already read."""
        from nap3d_graph.conventions import log_se3

        if self.odometry is None or i < 1:
            return None
        dt = float(self.query.timestamps[i] - self.query.timestamps[i - 1])
        self.odometry.prime(self.query[i - 1])
        step = self.odometry.increment(i, frame)
        return log_se3(step.T_prev_cur) / dt if step.ok and dt > 0 else None


def relocalisation(map_dir: Path, info: dict, query, args, second=None) -> dict:
    """``args.relocalise`` random query frames (seeded) found in the map, on one thread;
    ``second``: ``(T_ref_cam (N, 4, 4), T_ref_map)``, a second ground truth of the query
    frames and the survey's alignment to it, to score them against it too."""
    import torch

    torch.set_num_threads(1)
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.mapping.relocalise import Relocaliser
    from nap3d_graph.nap3d.config import AlignConfig

    field = resolve_field(str(map_dir))
    K = query.intrinsics
    relocaliser = Relocaliser(map_dir, field, AlignConfig(matcher=args.matcher), K.scaled(320, 240))
    T_map_gt = inv_T(np.asarray(info["survey_ate"]["T_gt_map"]))
    rng = np.random.default_rng(args.seed)
    picks = rng.choice(len(query), size=min(args.relocalise, len(query)), replace=False)
    twist = QueryTwist(query, args.matcher, off=args.no_twist)
    attempts = []
    for i in sorted(picks):
        frame = query[int(i)]
        found = relocaliser.locate(frame, twist(int(i), frame))
        row = {"frame": int(i), "success": found.success, "seconds": found.seconds, "reason": found.reason}
        if found.success and np.all(np.isfinite(query.T_world_cam_gt[i])):
            e = log_se3(inv_T(T_map_gt @ query.T_world_cam_gt[i]) @ found.T_map_cam)
            row.update(error_m=float(np.linalg.norm(e[3:])), error_deg=float(np.degrees(np.linalg.norm(e[:3]))),
                       inliers=found.inliers, agreeing=found.agreeing, tried=found.tried)
            if second is not None and np.all(np.isfinite(second[0][i])):
                e2 = log_se3(inv_T(inv_T(second[1]) @ second[0][i]) @ found.T_map_cam)
                row.update(error_second_gt_m=float(np.linalg.norm(e2[3:])),
                           error_second_gt_deg=float(np.degrees(np.linalg.norm(e2[:3]))))
        attempts.append(row)
    good = [a for a in attempts if a["success"] and a.get("error_m", 1) <= 0.05 and a.get("error_deg", 9) <= 3]
    far = [a for a in attempts if a["success"] and a.get("error_m", 0) > 0.10]
    seconds = np.array([a["seconds"] for a in attempts])
    extra = {}
    if second is not None:
        good2 = [a for a in attempts if a["success"] and a.get("error_second_gt_m", 1) <= 0.05
                 and a.get("error_second_gt_deg", 9) <= 3]
        extra = {"within_5cm_3deg_second_gt": len(good2),
                 "accepted_farther_than_10cm_second_gt": sum(a["success"] and a.get("error_second_gt_m", 0) > 0.10
                                                             for a in attempts)}
    return {**extra, "with_twist": not args.no_twist, "attempts": len(attempts), "within_5cm_3deg": len(good),
            "share_within": len(good) / max(len(attempts), 1),
            "accepted_farther_than_10cm": len(far), "refused": sum(not a["success"] for a in attempts),
            "seconds_median": float(np.median(seconds)), "seconds_p90": float(np.percentile(seconds, 90)),
            "seconds_max": float(seconds.max()), "threads": 1, "field": info["stages"]["field"]["model"],
            "per_attempt": attempts}


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--traj", default="tum")
    parser.add_argument("--split", type=float, default=0.5)
    parser.add_argument("--model", default="splat", help="the field of both maps (default splat: seconds)")
    parser.add_argument("--matcher", default="xfeat")
    parser.add_argument("--second-gt", type=Path, default=None)
    parser.add_argument("--relocalise", type=int, default=40)
    parser.add_argument("--no-twist", action="store_true",
                        help="relocalise each frame as one instant (default: with its twist by the run's odometry)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=None, help="folder for the maps and runs (default: temporary)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--reuse-runs", action="store_true", help="read the runs already in --work")
    parser.add_argument("--only-relocalise", action="store_true",
                        help="measure the relocalisation again (alone on the machine) with the map in --work, and "
                        "replace it in --out; everything else in --out stays")
    return parser.parse_args()


def halves(args):
    """``(survey_frames, query_frames, survey, query)``: the two halves' frame ranges and sequences."""
    from nap3d_graph.datasets import open_sequence

    survey_frames, query_frames = f"0:{args.split}", f"{args.split}:1"
    return (survey_frames, query_frames, open_sequence(args.data, frames=survey_frames),
            open_sequence(args.data, frames=query_frames))


def map_poses(map_dir: Path, info: dict, survey) -> np.ndarray:
    """(N, 4, 4) the map's pose of every survey frame (NaN outside its tracked segment)."""
    from nap3d_graph.trajectory import read_tum_trajectory

    _, T_map_survey = read_tum_trajectory(map_dir / "poses.txt")
    T_map_full = np.full((len(survey), 4, 4), np.nan)
    T_map_full[info["segment"]["start"]:info["segment"]["stop"]] = T_map_survey
    return T_map_full


def relocalise_only(args, work: Path) -> None:
    """``--only-relocalise``: the relocalisation measured again with the map in ``work``,
    replaced in ``--out``."""
    survey_frames, query_frames, survey, query = halves(args)
    result = (json.loads(args.out.read_text()) if args.out.is_file()
              else {"data": str(args.data), "survey_frames": survey_frames, "query_frames": query_frames,
                    "matcher": args.matcher})
    info = json.loads((work / "map" / "map.json").read_text())
    T_map_full = map_poses(work / "map", info, survey)
    result["relocalisation"] = relocalisation(work / "map", info, query, args,
                                              second_reference(args, survey, query, T_map_full))
    result["relocalisation"]["command"] = " ".join(sys.argv)
    write_result(args.out, result, args)
    print({k: v for k, v in result["relocalisation"].items() if k != "per_attempt"})


def self_posed_map(args, map_dir: Path, survey_frames: str, result: dict) -> dict:
    """1. The self-posed map (resumed, or reused whole, from --work); its figures go to
    ``result``. Returns its map.json."""
    result["map_seconds"] = round(cli("map", str(args.data), "--frames", survey_frames, "--out", str(map_dir),
                                      "--model", args.model, "--matcher", args.matcher, "--quiet"), 1)
    info = json.loads((map_dir / "map.json").read_text())
    result["survey"] = {"ate": info["survey_ate"], "loops": info["loops"], "keyframes": info["keyframes"],
                        "segment": info["segment"], "stages_s": {k: v["seconds"] for k, v in info["stages"].items()}}
    return info


def second_truth(args, survey, query, T_map_full: np.ndarray, result: dict) -> dict | None:
    """The second ground truth of both halves (``"survey"`` (N, 4, 4), ``"query"`` (M, 4, 4))
    and the map's alignment to it (``"T_ref_map"``), the survey scored against it in
    ``result``; None without ``--second-gt``."""
    if args.second_gt is None:
        return None
    from nap3d_graph.evaluation.alignment import aligned_errors

    table = read_sfm_pseudo_gt(args.second_gt)
    second = {"survey": second_gt_for(survey, table), "query": second_gt_for(query, table)}
    survey_errors = aligned_errors(survey.timestamps, second["survey"], T_map_full)
    result["survey"]["ate_second_gt"] = survey_errors.summary()
    second["T_ref_map"] = survey_errors.T_ref_est
    T_kf = np.asarray(survey.T_world_cam_gt)
    result["ground_truths_disagree_on_survey_m"] = aligned_errors(survey.timestamps, second["survey"], T_kf).summary()
    return second


def gt_posed_field(args, work: Path, survey_frames: str, result: dict) -> Path:
    """2. The map pinned to the ground truth (a benchmark run again in the same --work reuses it)."""
    gt_field = work / "gt_field.pt"
    if not gt_field.is_file():
        result["gt_field_seconds"] = round(cli("train-field", str(args.data), "--frames", survey_frames, "--out",
                                               str(gt_field), "--model", args.model, "--matcher", args.matcher,
                                               "--quiet"), 1)
    return gt_field


def sfm_posed_run(args, work: Path, survey, query_frames: str, second: dict, result: dict, seed: int = 0) -> dict:
    """The query on the map pinned to the second ground truth, trained as train-field would.
    Its world is the SfM frame: it starts at the SfM pose of the first query frame and is
    scored against the SfM poses as they are (its "ate_m" against KinectFusion's means nothing)."""
    from nap3d_graph.conventions import T_to_tum
    from nap3d_graph.datasets.posed import PosedSequence
    from nap3d_graph.fields.build import build_field

    sfm_field = work / "sfm_field.pt"
    if not sfm_field.is_file():
        t0 = time.perf_counter()
        field_obj, _ = build_field(PosedSequence(survey, second["survey"], "second ground truth"), args.model,
                                   matcher=args.matcher, progress=False)
        field_obj.save(sfm_field)
        result["sfm_field_seconds"] = round(time.perf_counter() - t0, 1)
    start = " ".join(f"{v:.9f}" for v in T_to_tum(second["query"][0]))  # tx ty tz qx qy qz qw
    return run_query(args.data, args.traj, query_frames, sfm_field, work / f"run_sfm_start{seed_suffix(seed)}",
                     ("--matcher", args.matcher, "--initial-pose", start), seed)


def seed_suffix(seed: int) -> str:
    """A run folder's suffix for RANSAC seed ``seed`` (none for the default 0)."""
    return f"_seed{seed}" if seed else ""


def score_against_second(runs: dict, survey, query, second: dict) -> None:
    """Each run's ATE against the second ground truth, moved there through its map's own
    alignment to it (the SfM-posed map is in its frame already)."""
    from nap3d_graph.evaluation.alignment import aligned_errors
    from nap3d_graph.trajectory import interpolate_poses

    def sfm_at(stamps):
        return interpolate_poses(np.asarray(query.timestamps), second["query"], stamps, max_gap=0.2)

    T_sfm_map = second["T_ref_map"]
    T_sfm_kf = aligned_errors(survey.timestamps, second["survey"], np.asarray(survey.T_world_cam_gt)).T_ref_est
    for name, T_ref_frame in (("self_posed", T_sfm_map), ("gt_posed", T_sfm_kf), ("sfm_posed", np.eye(4))):
        r = runs[name]
        r["ate_second_gt_m"] = errors_in(sfm_at, r["_stamps"], r["_T"], T_ref_frame)
        r["ate_second_gt_causal_m"] = errors_in(sfm_at, r["_stamps"], r["_T_online"], T_ref_frame)


def query_runs(args, work: Path, map_dir: Path, gt_field: Path, survey, query, query_frames: str,
               second: dict | None, result: dict) -> dict:
    """3. The query on both maps (and on the second ground truth's, with one), scored."""
    runs = {"self_posed": run_query(args.data, args.traj, query_frames, map_dir, work / "run_self",
                                    ("--matcher", args.matcher)),
            "gt_posed": run_query(args.data, args.traj, query_frames, gt_field, work / "run_gt",
                                  ("--matcher", args.matcher))}
    if second is not None:
        runs["sfm_posed"] = sfm_posed_run(args, work, survey, query_frames, second, result)
        score_against_second(runs, survey, query, second)
    for r in runs.values():
        for k in ("_stamps", "_T", "_T_online"):
            r.pop(k)
    return runs


def main() -> None:
    args = parse_args()
    global REUSE_RUNS
    REUSE_RUNS = args.reuse_runs
    work = args.work or Path(tempfile.mkdtemp(prefix="map_survey_"))
    if args.only_relocalise:
        relocalise_only(args, work)
        return
    survey_frames, query_frames, survey, query = halves(args)
    result: dict = {"command": " ".join(sys.argv), "data": str(args.data), "survey_frames": survey_frames,
                    "query_frames": query_frames, "model": args.model, "matcher": args.matcher, "odometry": "vo"}
    map_dir = work / "map"
    info = self_posed_map(args, map_dir, survey_frames, result)
    T_map_full = map_poses(map_dir, info, survey)
    second = second_truth(args, survey, query, T_map_full, result)
    gt_field = gt_posed_field(args, work, survey_frames, result)
    runs = result["runs"] = query_runs(args, work, map_dir, gt_field, survey, query, query_frames, second, result)
    result["ratio_self_to_gt_posed"] = runs["self_posed"]["ate_m"] / runs["gt_posed"]["ate_m"]
    if "sfm_posed" in runs:
        result["ratio_self_to_sfm_posed_in_sfm_frame"] = (runs["self_posed"]["ate_second_gt_m"]
                                                          / runs["sfm_posed"]["ate_second_gt_m"])
    # 4. relocalisation from random query frames
    result["relocalisation"] = relocalisation(map_dir, info, query, args,
                                              None if second is None else (second["query"], second["T_ref_map"]))
    write_result(args.out, result, args)
    print(json.dumps({k: v for k, v in result.items() if k != "relocalisation"}, indent=1, default=float)[:4000])
    print({k: v for k, v in result["relocalisation"].items() if k != "per_attempt"})


if __name__ == "__main__":
    main()
