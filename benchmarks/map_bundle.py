"""How much should the survey's bundle adjustment trust the depth? A sweep over the
disparity's noise (in units of the pixels', :class:`~nap3d_graph.mapping.bundle.BundleSettings`)
on a map folder's own verified matches, scored against every ground truth the recording has,
each weight three ways: the colour camera taken as a global shutter over the loops the pose
graph kept (how ``map`` adjusted before), its rolling shutter undone with the readout the
survey's pixels choose, and that with the loops the graph turned away but whose matches agree
admitted (``map``'s default, :func:`~nap3d_graph.mapping.build.adjust_keyframes`).

The pose graph's poses and the odometry's are scored beside it. Reads the map folder that
``nap3d-graph map`` (or ``map_survey.py --work``) left; writes JSON.

    python benchmarks/map_bundle.py --map MAP_DIR --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --frames 0:0.5 --out benchmarks/results/map_bundle_fr1_desk.json
    python benchmarks/map_bundle.py --map MAP_DIR --data ../shared/data/7scenes/redkitchen --frames 0:0.5 \\
        --second-gt ../shared/data/7scenes/redkitchen/pseudo_gt_sfm.txt --out benchmarks/results/map_bundle_redkitchen.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from map_survey import read_sfm_pseudo_gt, second_gt_for  # noqa: E402  (beside this file)
from provenance import write_result

#: The adjustments compared at each depth weight (overrides of BundleSettings).
VARIANTS = {"global shutter": {"readout_s": 0.0, "admit_factor": 0.0},
            "rolling shutter": {"admit_factor": 0.0},
            "rolling shutter, turned-away loops that agree admitted": {}}


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--map", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--frames", default=None)
    parser.add_argument("--second-gt", type=Path, default=None)
    parser.add_argument("--ratios", type=float, nargs="+", default=[0.1, 0.3, 1.0, 3.0, 10.0, 30.0])
    parser.add_argument("--out", type=Path, required=True)
    return parser.parse_args()


def _references(sequence, second_gt: Path | None) -> dict:
    """Every ground truth of the sequence's frames (N, 4, 4) by name."""
    references = {"ground truth": np.asarray(sequence.T_world_cam_gt)}
    if second_gt is not None:
        references["second ground truth"] = second_gt_for(sequence, read_sfm_pseudo_gt(second_gt))
    return references


def _graph(survey, keys, chain, loops, settings: dict):
    """The map's pose graph solved again from its edges: ``(graph, verified loops)``."""
    from nap3d_graph.mapping.pose_graph import Edge, floor_covariance, solve

    verified = [lp for lp in loops if lp.status == "verified"]
    loop_edges = [Edge(lp.a, lp.b, lp.T_a_b, floor_covariance(lp.covariance, settings["edge_floor_rad"],
                                                              settings["edge_floor_m"]), "loop") for lp in verified]
    return solve(survey.T_odom_cam[keys], chain, loop_edges, settings["gate_p"]), verified


def _row(ratio: float, variant: str, report: dict, scores: dict) -> dict:
    return {"disparity_to_pixel": ratio, "readout": variant, "readout_s": report.get("readout_s"),
            "loops_admitted": report.get("loops_admitted", 0),
            "depth_sigma_at_1m_mm": report.get("depth_sigma_at_1m_mm"),
            "residual_px": report["noise_rounds"][-1]["residual_px"],
            "residual_disparity_px": report["noise_rounds"][-1]["residual_disparity_px"], **scores}


def main() -> None:
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.evaluation.alignment import aligned_errors
    from nap3d_graph.mapping.build import MapSettings, _working_intrinsics, adjust_keyframes, place_frames
    from nap3d_graph.mapping.bundle import BundleSettings, keyframe_twists
    from nap3d_graph.mapping.loops import load_edges
    from nap3d_graph.mapping.survey import SurveyOdometry

    args = _arguments()
    sequence = open_sequence(args.data, frames=args.frames)
    info = json.loads((args.map / "map.json").read_text())
    settings = info["settings"]
    references = _references(sequence, args.second_gt)
    chain, loops, chain_matches = load_edges(args.map / "edges.npz")
    keys = np.load(args.map / "keyframes.npz")["indices"]
    survey = SurveyOdometry.load(args.map / "odometry.npz")
    start, stop = info["segment"]["start"], info["segment"]["stop"]

    def score(T_key) -> dict:
        T = place_frames(survey.T_odom_cam, keys, T_key, start, stop)
        return {name: aligned_errors(sequence.timestamps, ref, T).summary() for name, ref in references.items()}

    graph, verified = _graph(survey, keys, chain, loops, settings)
    T_odom = np.full((len(sequence), 4, 4), np.nan)
    T_odom[start:stop] = survey.T_odom_cam[start:stop]
    result = {"command": " ".join(sys.argv), "map": str(args.map), "data": str(args.data), "frames": args.frames,
              "odometry": {name: aligned_errors(sequence.timestamps, ref, T_odom).summary()
                           for name, ref in references.items()},
              "pose_graph": score(graph.T_map_key), "bundle": []}
    if len(references) > 1:
        result["ground_truths_against_each_other"] = aligned_errors(sequence.timestamps, references["second ground truth"],
                                                                    references["ground truth"]).summary()
    K = _working_intrinsics(sequence, MapSettings(width=settings["width"]))
    twists = keyframe_twists(survey.T_odom_cam, np.asarray(sequence.timestamps, dtype=float), keys)
    for ratio in args.ratios:
        for variant, overrides in VARIANTS.items():
            for lp, kept in zip(verified, graph.loop_kept):  # each variant starts from the graph's choice
                lp.status = "accepted" if kept else "rejected"
            T_key, report = adjust_keyframes(graph.T_map_key, chain_matches, verified, K,
                                             BundleSettings(disparity_to_pixel=ratio, **overrides), twists)
            row = _row(ratio, variant, report, score(T_key))
            result["bundle"].append(row)
            print(ratio, variant, {k: round(v["rmse_m"] * 100, 2) for k, v in row.items() if isinstance(v, dict)})
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
