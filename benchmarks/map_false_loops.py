"""False loops from a repeated texture: a simulated room with one picture hung on two
opposite walls, surveyed, mapped with ``nap3d-graph map``; the same room with two different
pictures there is the control.

A loop is false when its measured relative pose is more than 20 cm or 10 deg from the
ground truth's. Counted among the verified loops (what NAP3D's real-vs-real alignment let
through) and among those the robust pose graph kept; the survey's ATE with the twin pictures
against the control's.

    python benchmarks/map_false_loops.py --out benchmarks/results/map_false_loops.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def false_loops(map_dir: Path, sequence) -> dict:
    from nap3d_graph.conventions import inv_T, log_se3
    from nap3d_graph.mapping.build import _load_edges

    _, loops, _ = _load_edges(map_dir / "edges.npz")
    import csv

    status = {(int(r["keyframe_a"]), int(r["keyframe_b"])): r["status"]
              for r in csv.DictReader(open(map_dir / "loops.csv"))}
    G = sequence.T_world_cam_gt
    rows = []
    for lp in loops:
        if not np.all(np.isfinite(lp.covariance)):
            continue
        e = log_se3(inv_T(lp.T_a_b) @ (inv_T(G[lp.i]) @ G[lp.j]))
        wrong = bool(np.linalg.norm(e[3:]) > 0.2 or np.degrees(np.linalg.norm(e[:3])) > 10)
        distance = float(np.linalg.norm(G[lp.i][:3, 3] - G[lp.j][:3, 3]))
        rows.append({"frames": [lp.i, lp.j], "status": status[(lp.a, lp.b)], "false": wrong, "source": lp.source,
                     "error_m": float(np.linalg.norm(e[3:])), "gt_distance_m": distance, "inliers": lp.inliers})
    return {"verified": len(rows), "false_verified": sum(r["false"] for r in rows),
            "accepted": sum(r["status"] == "accepted" for r in rows),
            "false_accepted": sum(r["false"] and r["status"] == "accepted" for r in rows),
            "false_rejected_by_graph": sum(r["false"] and r["status"] == "rejected" for r in rows),
            "false_loops": [r for r in rows if r["false"]]}


def main() -> None:
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.mapping.build import MapSettings, build_map
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene-seed", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--frames", type=int, default=480)
    parser.add_argument("--fps", type=float, default=7.5)
    parser.add_argument("--matcher", default="sift")
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="false_loops_"))
    result: dict = {"command": " ".join(sys.argv), "scene_seed": args.scene_seed, "seed": args.seed,
                    "frames": args.frames, "fps": args.fps, "matcher": args.matcher, "size": "320x240"}
    for posters in ("identical", "different"):
        folder = work / f"survey_{posters}"
        if not (folder / "groundtruth.txt").is_file():
            simulate_sequence(folder, SimConfig(frames=args.frames, path="mapping", scene_seed=args.scene_seed,
                                                seed=args.seed, width=320, height=240, fps=args.fps,
                                                twin_posters=posters))
        sequence = open_sequence(folder)
        t0 = time.perf_counter()
        mapped = build_map(sequence, work / f"map_{posters}", MapSettings(matcher=args.matcher), progress=False,
                           build_field_stage=False)
        result[posters] = {"seconds": round(time.perf_counter() - t0, 1), "survey_ate": mapped.info["survey_ate"],
                           "loops": false_loops(work / f"map_{posters}", sequence)}
        for key in ("map", "pose_graph_only", "odometry_only"):
            result[posters][f"ate_{key}_m"] = mapped.info["survey_ate"][key]["rmse_m"]
        del result[posters]["survey_ate"]
        print(posters, {k: v for k, v in result[posters]["loops"].items() if k != "false_loops"},
              {k: v for k, v in result[posters].items() if k.startswith("ate")})
    result["ate_ratio_identical_to_different"] = (result["identical"]["ate_map_m"]
                                                  / result["different"]["ate_map_m"])
    args.out.write_text(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
