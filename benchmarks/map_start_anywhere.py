"""Starting anywhere in a map made by the camera alone, both directions of a split recording.

Protocol (issue 48): a recording split in two halves; each half in turn is the survey
(``nap3d-graph map``, its ground truth never read to build it) and the other the query.

1. Relocalisation: every ``--every``-th query frame located in the map (one thread). A frame
   counts as covered when a survey keyframe lies within 40 cm / 30 deg of its ground truth
   moved into the map by the survey's alignment; figures: the share of covered frames found
   within 5 cm / 3 deg, answers accepted farther than 10 cm (covered or not), seconds per
   attempt. ``--extra-query`` adds another recording of the same place (its ground truth
   taken to share the survey's frame, as TUM's fr1 recordings do).
2. The query run in the map from its own first frame (``run --odom vo``, the start found in
   the map and confirmed by the next keyframe): whether and when it was placed, its ATE in
   the ground truth's frame through the survey's alignment, beside the same run on a field of
   the same model trained on the survey at its ground-truth poses (started at the ground
   truth), unless ``--no-gt-map``.

    python benchmarks/map_start_anywhere.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --extra-query ../shared/data/tum/rgbd_dataset_freiburg1_xyz --work /tmp/anywhere \\
        --out benchmarks/results/map_start_anywhere_fr1_desk.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from map_survey import (
    QueryTwist,
    cli,
    errors_in,
    map_trajectory,
    read_sfm_pseudo_gt,
    run_query,
    second_alignment,
    second_gt_for,
    second_reference,
    seed_suffix,
    sfm_posed_run,
)
from provenance import write_result

from nap3d_graph.conventions import inv_T, log_se3

HALVES = {"first": "0:0.5", "second": "0.5:1"}


def _pose_gap(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    e = log_se3(inv_T(T_a) @ T_b)
    return float(np.linalg.norm(e[3:])), float(np.degrees(np.linalg.norm(e[:3])))


def covered(T_map_cam: np.ndarray, T_map_key: np.ndarray, metres: float = 0.40, degrees: float = 30.0) -> bool:
    """Whether a survey keyframe lies within ``metres`` and ``degrees`` of the camera."""
    return any(d <= metres and a <= degrees for d, a in (_pose_gap(T_map_cam, T) for T in T_map_key))


def relocalisation(map_dir: Path, query, every: int, matcher: str, T_map_gt: np.ndarray, second=None,
                   settings=None, field_obj=None, twist: bool = True) -> dict:
    """``second``: ``(T_ref_cam (N, 4, 4) of the query, T_ref_map)``, a second ground truth and
    the survey's alignment to it: each answer scored against it too. ``settings``: the
    relocaliser's rules (default: its own); ``field_obj``: the map's field already loaded; ``twist``: each frame
    relocalised with its twist by the run's odometry (:class:`map_survey.QueryTwist`), as a run does."""
    import torch

    torch.set_num_threads(1)
    from nap3d_graph.mapping.start import map_relocaliser

    relocaliser = map_relocaliser(map_dir, field_obj, matcher, query.intrinsics.scaled(320, 240))
    if settings is not None:
        relocaliser.settings = settings
    T_map_key = relocaliser.T_map_key
    twist_of = QueryTwist(query, matcher, off=not twist)
    rows = []
    for i in range(0, len(query), every):
        T_gt = np.asarray(query.T_world_cam_gt[i])
        if not np.all(np.isfinite(T_gt)):
            continue
        T_true = T_map_gt @ T_gt
        frame = query[i]
        found = relocaliser.locate(frame, twist_of(i, frame))
        row = {"frame": i, "covered": covered(T_true, T_map_key), "success": found.success,
               "seconds": round(found.seconds, 3), "wide_baseline": found.wide_baseline}
        if found.success:
            row["error_m"], row["error_deg"] = _pose_gap(T_true, found.T_map_cam)
            if second is not None and np.all(np.isfinite(second[0][i])):
                row["error_second_gt_m"], row["error_second_gt_deg"] = _pose_gap(inv_T(second[1]) @ second[0][i],
                                                                                 found.T_map_cam)
        else:
            row["reason"] = found.reason
        rows.append(row)
    cov = [r for r in rows if r["covered"]]
    good = [r for r in cov if r["success"] and r["error_m"] <= 0.05 and r["error_deg"] <= 3.0]
    seconds = np.array([r["seconds"] for r in rows])
    extra = {} if second is None else {"covered_found_within_5cm_3deg_second_gt": sum(
        r["success"] and r.get("error_second_gt_m", 1) <= 0.05 and r.get("error_second_gt_deg", 9) <= 3.0 for r in cov),
        "accepted_farther_than_10cm_second_gt": sum(r["success"] and r.get("error_second_gt_m", 0) > 0.10 for r in rows)}
    return {**extra, "with_twist": twist, "attempts": len(rows), "covered": len(cov), "covered_found_within_5cm_3deg": len(good),
            "share_of_covered": len(good) / max(len(cov), 1),
            "accepted_farther_than_10cm": sum(r["success"] and r["error_m"] > 0.10 for r in rows),
            "accepted_uncovered": sum(r["success"] and not r["covered"] for r in rows),
            "seconds_median": float(np.median(seconds)), "seconds_p90": float(np.percentile(seconds, 90)),
            "seconds_max": float(seconds.max()), "threads": 1, "per_attempt": rows}


def direction(args, survey_half: str) -> dict:
    """One direction: the survey half mapped, the other half relocalised in it and run from
    its own first frame (beside the ground-truth-posed map unless ``--no-gt-map``)."""
    from nap3d_graph.datasets import open_sequence

    query_half = "second" if survey_half == "first" else "first"
    work = args.work / f"survey_{survey_half}"
    map_dir, info, out = _map(args, survey_half, query_half, work)
    T_map_gt = inv_T(np.asarray(info["survey_ate"]["T_gt_map"]))
    survey, query = open_sequence(args.data, frames=HALVES[survey_half]), open_sequence(args.data,
                                                                                         frames=HALVES[query_half])
    T_map_survey = map_trajectory(map_dir, "poses.txt", survey)
    second = second_reference(args, survey, query, T_map_survey)
    if second is not None:
        out["survey_ate_second_gt_m"] = float(second_alignment(args, survey, T_map_survey).summary()["rmse_m"])
    out["relocalisation"] = relocalisation(map_dir, query, args.every, args.matcher, T_map_gt, second)
    for extra in args.extra_query:
        out[f"relocalisation_{Path(extra).name}"] = relocalisation(map_dir, open_sequence(extra), args.every,
                                                                   args.matcher, T_map_gt)
    per_seed = [_seed_runs(args, survey_half, query_half, work, map_dir, survey, query, second, out, seed)
                for seed in range(args.seeds)]
    runs = _over_seeds(per_seed)
    for ratio, (name, key) in {"ratio_self_to_gt_posed": ("gt_posed", "ate_m"),
                               "ratio_self_to_gt_posed_second_gt": ("gt_posed", "ate_second_gt_m"),
                               "ratio_self_to_sfm_posed_second_gt": ("sfm_posed", "ate_second_gt_m")}.items():
        if name in runs and key in runs[name]:
            out[ratio] = runs["self_posed"][key] / runs[name][key]
            out[f"{ratio}_per_seed"] = [r["self_posed"][key] / r[name][key] for r in per_seed]
    out["runs"] = runs
    return out


def _seed_runs(args, survey_half: str, query_half: str, work: Path, map_dir: Path, survey, query, second,
               out: dict, seed: int) -> dict:
    """Every run kind with NAP3D's RANSAC seed ``seed``, scored (against the second ground
    truth too, with one)."""
    runs = _runs(args, survey_half, query_half, work, map_dir, seed)
    if second is not None and not args.no_gt_map:
        runs["sfm_posed"] = _sfm_posed_run(args, work, survey, query, query_half, out, seed)
    if second is not None:
        _score_second(args, runs, survey, query, second)
    for r in runs.values():
        for k in ("_stamps", "_T", "_T_online"):
            r.pop(k, None)
    return runs


def _over_seeds(per_seed: list[dict]) -> dict:
    """Each run kind's figures over the RANSAC seeds: the ATEs as their median with every
    seed's value beside it (``*_per_seed``), the rest as the first seed's."""
    runs = {}
    for name, first in per_seed[0].items():
        runs[name] = dict(first)
        for key in ("ate_m", "ate_causal_m", "ate_second_gt_m", "ate_second_gt_causal_m"):
            if key in first:
                values = [r[name][key] for r in per_seed]
                runs[name][key] = float(np.median(values))
                runs[name][f"{key}_per_seed"] = values
        if "placed_at_frame" in first:
            runs[name]["placed_at_frame_per_seed"] = [r[name]["placed_at_frame"] for r in per_seed]
    return runs


def _map(args, survey_half: str, query_half: str, work: Path) -> tuple[Path, dict, dict]:
    """The survey half mapped (reused when the folder holds it): ``(map folder, map.json,
    the direction's first figures)``."""
    map_dir = work / "map"
    t0 = time.perf_counter()
    cli("map", str(args.data), "--frames", HALVES[survey_half], "--out", str(map_dir), "--model", args.model,
        "--matcher", args.matcher, "--quiet")
    info = json.loads((map_dir / "map.json").read_text())
    out = {"survey": survey_half, "query": query_half, "map_seconds_this_call": round(time.perf_counter() - t0, 1),
           "survey_ate_m": info["survey_ate"]["map"]["rmse_m"], "keyframes": info["keyframes"], "loops": info["loops"],
           "readout_s": info.get("bundle", {}).get("readout_s")}
    return map_dir, info, out


def _runs(args, survey_half: str, query_half: str, work: Path, map_dir: Path, seed: int = 0) -> dict:
    """The query run in the self-made map (with how it was placed) and, unless
    ``--no-gt-map``, on a field trained at the survey's ground-truth poses; ``seed``: NAP3D's
    RANSAC seed in both."""
    self_dir = work / f"run_self{seed_suffix(seed)}"
    runs = {"self_posed": run_query(args.data, args.traj, HALVES[query_half], map_dir, self_dir,
                                    ("--matcher", args.matcher), seed)}
    metrics = json.loads((self_dir / "latest" / "metrics.json").read_text())
    placement = metrics["map"].get("placement") or {}
    runs["self_posed"]["placed"] = placement.get("placed")
    runs["self_posed"]["placed_at_frame"] = placement.get("placed_at_frame")
    runs["self_posed"]["relocalisations_tried"] = placement.get("relocalisations_tried")
    runs["self_posed"]["recoveries"] = sum(r.get("step") == "recovered" for r in metrics["map"].get("recoveries", []))
    if not args.no_gt_map:
        gt_field = work / "gt_field.pt"
        if not gt_field.is_file():
            cli("train-field", str(args.data), "--frames", HALVES[survey_half], "--out", str(gt_field), "--model",
                args.model, "--matcher", args.matcher, "--quiet")
        runs["gt_posed"] = run_query(args.data, args.traj, HALVES[query_half], gt_field,
                                     work / f"run_gt{seed_suffix(seed)}", ("--matcher", args.matcher), seed)
    return runs


def _sfm_posed_run(args, work: Path, survey, query, query_half: str, out: dict, seed: int = 0) -> dict:
    """The query on a field trained at the survey's second ground truth (7-Scenes' SfM
    poses), started at the query's first SfM pose: the map the issue's SfM figures compare with."""
    table = read_sfm_pseudo_gt(args.second_gt)
    poses = {"survey": second_gt_for(survey, table), "query": second_gt_for(query, table)}
    return sfm_posed_run(args, work, survey, HALVES[query_half], poses, out, seed)


def _score_second(args, runs: dict, survey, query, second) -> None:
    """Each run against the second ground truth, through its map's alignment to it (the
    ground-truth-posed map's frame is the first ground truth's)."""
    from nap3d_graph.evaluation.alignment import aligned_errors
    from nap3d_graph.trajectory import interpolate_poses

    def second_at(stamps):
        return interpolate_poses(np.asarray(query.timestamps), second[0], stamps, max_gap=0.2)

    frames = {"self_posed": second[1]}
    if "gt_posed" in runs:
        table = read_sfm_pseudo_gt(args.second_gt)
        frames["gt_posed"] = aligned_errors(survey.timestamps, second_gt_for(survey, table),
                                            np.asarray(survey.T_world_cam_gt)).T_ref_est
    if "sfm_posed" in runs:
        frames["sfm_posed"] = np.eye(4)  # trained and started in the SfM frame itself
    for name, T_ref_frame in frames.items():
        runs[name]["ate_second_gt_m"] = errors_in(second_at, runs[name]["_stamps"], runs[name]["_T"], T_ref_frame)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--traj", default="tum", help="the recording's source for the runs (tum, 7scenes, auto)")
    parser.add_argument("--second-gt", type=Path, default=None,
                        help="a second ground truth (7-Scenes' SfM poses): everything scored against it too")
    parser.add_argument("--extra-query", type=Path, action="append", default=[])
    parser.add_argument("--model", default="splat")
    parser.add_argument("--matcher", default="xfeat")
    parser.add_argument("--every", type=int, default=5)
    parser.add_argument("--work", type=Path, required=True, help="folder for the maps and runs (reused when there)")
    parser.add_argument("--no-gt-map", action="store_true", help="skip the ground-truth-posed comparison map")
    parser.add_argument("--seeds", type=int, default=3,
                        help="NAP3D RANSAC seeds each run is repeated with (0, 1, ...): ATEs are their median, every "
                             "seed's beside it (a run's ATE moves by several percent with the seed alone)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    result = {"command": " ".join(sys.argv), "data": str(args.data), "model": args.model, "matcher": args.matcher,
              "every": args.every, "tuning": "placement rule (confirm by the next keyframe, 5 cm / 3 deg) chosen on "
              "fr1/xyz and the simulator (tests); relocaliser rules as before this benchmark",
              "directions": [direction(args, half) for half in ("first", "second")]}
    write_result(args.out, result, args)
    for d in result["directions"]:
        brief = {k: v for k, v in d["relocalisation"].items() if k != "per_attempt"}
        print(d["survey"], "->", d["query"], brief, {k: {kk: vv for kk, vv in v.items() if kk != "start"}
                                                     for k, v in d["runs"].items()})


if __name__ == "__main__":
    main()
