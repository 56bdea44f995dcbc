"""A map grown across days against the map of the whole recording (issue 61, part 3).

Protocol: a recording split in two halves, as two days' surveys of one place.

1. ``map`` of the whole recording; the second half run in it from its own first frame
   (``run --odom vo``, start found in the map) and scored in the ground truth's frame through
   the survey's alignment.
2. ``map`` of the first half; ``map SECOND_HALF --extend`` it; the same run of the second half
   in the grown map, scored through the first half's alignment (the grown map's frame is the
   first day's). Beside it: the second half's own poses in the grown map against the ground
   truth (through the same alignment), and the same frames' poses in the whole map.
3. ``map OTHER --extend`` the first half's map with a survey of another place
   (``--other``): refused in one line (exit 2), the map's files unchanged.

Neither the rules of the extension nor any default were chosen on this recording (the rules
on the tests' simulated room 3, ``tests/test_extend.py``).

    python benchmarks/map_extend.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --other ../shared/data/7scenes/redkitchen --other-frames 0:120 --work /tmp/extend \\
        --out benchmarks/results/map_extend_fr1_desk.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from map_survey import cli, run_query
from provenance import write_result

from nap3d_graph.conventions import inv_T


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--traj", default="tum")
    parser.add_argument("--split", type=int, default=None, help="first frame of the second half (default: the middle)")
    parser.add_argument("--other", type=Path, required=True, help="a survey of another place (the refusal)")
    parser.add_argument("--other-frames", default="0:120")
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--reuse-runs", action="store_true", help="read the runs already in --work instead of running them")
    return parser.parse_args()


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(folder)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def _map(data: Path, frames: str, out: Path) -> float:
    if (out / "report.md").is_file():
        return float("nan")
    return cli("map", str(data), "--frames", frames, "--out", str(out), "--quiet")


def _poses_error(T_gt_map: np.ndarray, stamps, T_map_cam, gt_of_stamp: dict) -> dict:
    """The poses (map frame) against the ground truth moved into the map, metres: rmse, p90, max."""
    errors = []
    for t, T in zip(stamps, T_map_cam):
        gt = gt_of_stamp.get(round(float(t), 6))
        if gt is not None and np.all(np.isfinite(gt)):
            errors.append(float(np.linalg.norm((inv_T(T_gt_map) @ gt)[:3, 3] - T[:3, 3])))
    e = np.asarray(errors)
    return {"frames": len(e), "rmse_m": float(np.sqrt(np.mean(e ** 2))), "p90_m": float(np.percentile(e, 90)),
            "max_m": float(e.max())}


def _run(args, field: Path, frames: str, out: Path) -> dict:
    result = run_query(args.data, args.traj, frames, field, out)
    placement = (json.loads((out / "latest" / "metrics.json").read_text()).get("map") or {}).get("placement") or {}
    return {**{k: v for k, v in result.items() if not k.startswith("_")},
            "placed_at_frame": placement.get("placed_at_frame")}


def whole_map(args, n: int, second: str, gt_of_stamp: dict) -> dict:
    """1. The whole recording's map, its second half's poses in it, the second half run in it."""
    from nap3d_graph.trajectory import read_tum_trajectory

    whole = args.work / "whole"
    seconds = _map(args.data, f"0:{n}", whole)
    info = json.loads((whole / "map.json").read_text())
    stamps, T_whole = read_tum_trajectory(whole / "poses.txt")
    in_second = np.isin(np.round(stamps, 6), np.round(list(gt_of_stamp), 6))
    return {"map_seconds": seconds, "survey_ate_m": info["survey_ate"]["map"]["rmse_m"],
            "second_half_poses": _poses_error(np.asarray(info["survey_ate"]["T_gt_map"]), stamps[in_second],
                                              T_whole[in_second], gt_of_stamp),
            "run": _run(args, whole, second, args.work / "run_whole")}


def grown_map(args, day1: Path, first: str, second: str, gt_of_stamp: dict) -> dict:
    """2. The first half's map grown by the second half, the second half's poses in it, the same run."""
    from nap3d_graph.trajectory import read_tum_trajectory

    day1_s = _map(args.data, first, day1)
    grown = args.work / "grown"
    extend_s = float("nan")
    if not (grown / "map.json").is_file():
        extend_s = cli("map", str(args.data), "--frames", second, "--extend", str(day1), "--out", str(grown),
                       "--quiet")
    info = json.loads((grown / "map.json").read_text())
    record = info["extensions"][-1]
    stamps, T_grown = read_tum_trajectory(grown / record["folder"] / "poses_in_map.txt")
    return {"first_map_seconds": day1_s, "extend_seconds": extend_s,
            "first_survey_ate_m": info["survey_ate"]["map"]["rmse_m"],
            "extension": {k: record[k] for k in ("keyframes", "pairs", "refused", "look-alike", "accepted",
                                                 "rejected", "unseen_frames", "new_submaps", "seconds")},
            "second_half_poses": _poses_error(np.asarray(info["survey_ate"]["T_gt_map"]), stamps, T_grown,
                                              gt_of_stamp),
            "run": _run(args, grown, second, args.work / "run_grown")}


def other_place(args, day1: Path) -> dict:
    """3. A survey of another place: refused in one line, the map unchanged, nothing written."""
    before = _digest(day1)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "nap3d_graph", "map", str(args.other), "--frames", args.other_frames,
                           "--extend", str(day1), "--out", str(args.work / "other"), "--quiet"],
                          capture_output=True, text=True)
    return {"data": str(args.other), "frames": args.other_frames, "exit": done.returncode,
            "message": (done.stderr.strip().splitlines() or [""])[-1], "seconds": round(time.perf_counter() - t0, 1),
            "map_unchanged": _digest(day1) == before, "out_written": (args.work / "other").exists()}


def main() -> None:
    from nap3d_graph.datasets import open_sequence

    args = parse_args()
    if args.reuse_runs:
        import map_survey

        map_survey.REUSE_RUNS = True
    args.work.mkdir(parents=True, exist_ok=True)
    n = len(open_sequence(args.data))
    split = args.split or n // 2
    first, second = f"0:{split}", f"{split}:{n}"
    query = open_sequence(args.data, frames=second)
    gt_of_stamp = dict(zip(np.round(query.timestamps, 6), query.T_world_cam_gt))
    result: dict = {"data": str(args.data), "halves": [first, second], "tuning": "extension rules chosen on the "
                    "tests' simulated room 3 (tests/test_extend.py); nothing chosen on this recording"}
    day1 = args.work / "first"
    result["whole"] = whole_map(args, n, second, gt_of_stamp)
    result["grown"] = grown_map(args, day1, first, second, gt_of_stamp)
    ratio = result["grown"]["run"]["ate_m"] / result["whole"]["run"]["ate_m"]
    result["run_ate_ratio"] = ratio
    result["within_5_percent"] = bool(ratio <= 1.05)
    result["other_place"] = other_place(args, day1)
    print(json.dumps(result, indent=1, default=float))
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
