"""How far apart two ground truths of one recording turn its cameras: 7-Scenes' KinectFusion
poses against its SfM poses, and each self-made map against both (issue 48: figures against
both references; a relocalisation is scored against a 3 deg bound).

Each pair is SE(3)-aligned (positions and orientations, :func:`~nap3d_graph.evaluation.alignment.aligned_errors`)
and its summary kept: the translation errors, the orientation errors after the alignment, and
``rotation_common_deg``, the part of those that is one fixed turn of every camera. A reference
that poses another camera than the colour images' (KinectFusion tracked the depth camera)
shows it there; no alignment of the whole trajectory removes it, so every pose scored against
that reference carries it.

    python benchmarks/ground_truths_turn.py --data ../shared/data/7scenes/redkitchen \\
        --second-gt ../shared/data/7scenes/redkitchen/pseudo_gt_sfm.txt \\
        --map 0:0.5=/tmp/anywhere7/survey_first/map --map 0.5:1=/tmp/anywhere7/survey_second/map \\
        --out benchmarks/results/ground_truths_turn_redkitchen.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from map_survey import map_poses, read_sfm_pseudo_gt, second_gt_for
from provenance import write_result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--second-gt", type=Path, required=True, help="7-Scenes' SfM poses (pseudo_gt_sfm.txt)")
    parser.add_argument("--map", action="append", default=[], help="FRAMES=MAP_DIR: a map of those frames (repeat)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.evaluation.alignment import aligned_errors

    table = read_sfm_pseudo_gt(args.second_gt)
    whole = open_sequence(args.data)
    out = {"data": str(args.data), "sfm_against_kinectfusion": aligned_errors(
        whole.timestamps, second_gt_for(whole, table), np.asarray(whole.T_world_cam_gt)).summary(), "maps": {}}
    for spec in args.map:
        frames, _, map_dir = spec.partition("=")
        sequence = open_sequence(args.data, frames=frames)
        T_map_full = map_poses(Path(map_dir), json.loads((Path(map_dir) / "map.json").read_text()), sequence)
        out["maps"][frames] = {
            "kinectfusion": aligned_errors(sequence.timestamps, np.asarray(sequence.T_world_cam_gt), T_map_full).summary(),
            "sfm": aligned_errors(sequence.timestamps, second_gt_for(sequence, table), T_map_full).summary()}
    write_result(args.out, out, args)
    s = out["sfm_against_kinectfusion"]
    print(f"SfM against KinectFusion: {s['rmse_m'] * 100:.2f} cm, orientation {s['rotation_median_deg']:.2f} deg median, "
          f"{s['rotation_common_deg']:.2f} deg common")


if __name__ == "__main__":
    main()
