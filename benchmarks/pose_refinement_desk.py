"""Training-pose refinement on real data: TUM fr1/desk, a field (``--model``, default splat)
built on the first half with the motion-capture poses as they are and with them refined by
each method (``train-field --refine-poses N --refine-method M``: ``map``, each frame aligned
to a map of the others, ``--rounds`` rounds; ``depth``, neighbouring depths aligned with ICP
and a pose graph, 2 rounds), the second half corrected by each with each odometry
(``--odom``, default vo). Per field: the training frames' multi-view depth agreement before
and after, the held-out PSNR and depth error, the field's own error; per run: ATE (no
alignment) with max, causal ATE, corrections accepted, median inliers. Writes JSON.

    python benchmarks/pose_refinement_desk.py [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk] \\
        [--model splat] [--methods map] [--odom vo] [--rounds 3] [--matcher xfeat] \\
        [--out benchmarks/results/pose_refinement_fr1_desk.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from provenance import write_result


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--rounds", type=int, default=3, help="rounds of the map method (the depth method: 2)")
    p.add_argument("--model", default="splat", choices=("splat", "views", "grid"))
    p.add_argument("--methods", nargs="+", default=["map"], choices=("map", "depth"))
    p.add_argument("--odom", nargs="+", default=["vo"], choices=("vo", "dense"))
    p.add_argument("--matcher", default="xfeat")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/pose_refinement_fr1_desk.json"))
    args = p.parse_args(argv)
    from keyframes_desk import run_one  # same folder: one run's figures from its results

    from nap3d_graph.cli import main as cli

    work = Path(tempfile.mkdtemp(prefix="pose_refinement_desk_"))
    result = {"data": str(args.data), "frames": "field from 0:0.5, runs on 0.5:1", "odometry": args.odom[0],
              "odometries": args.odom, "model": args.model, "matcher": args.matcher, "fields": {}}
    variants = [("poses as given", 0, "depth")]
    for method in args.methods:
        rounds = args.rounds if method == "map" else 2
        variants.append((f"refined, {rounds} rounds" if method == "map" else f"{method}, {rounds} rounds", rounds,
                         method))
    for name, rounds, method in variants:
        field = work / f"refine{rounds}_{method}.pt"
        assert cli(["train-field", str(args.data), "--frames", "0:0.5", "--model", args.model, "--matcher", args.matcher,
                    "--refine-poses", str(rounds), "--refine-method", method, "--out", str(field), "--quiet"]) == 0
        report = json.loads(field.with_suffix(".report.json").read_text())
        held = report["held_out"]
        entry = {"pose_refinement": report.get("pose_refinement"), "held_out_psnr_db": held["psnr_db"],
                 "held_out_psnr_affine_db": held["psnr_affine_db"], "held_out_depth_err_m": held["depth_abs_err_m"],
                 "timing_agreement_mm": (report.get("timing") or {}).get("agreement_mm"),
                 "field_error": report.get("field_error")}
        entry["runs"] = {odom: run_one(args.data, field, odom, args.matcher, [], work / f"run{rounds}_{method}_{odom}")
                         for odom in args.odom}
        entry["run"] = entry["runs"][args.odom[0]]
        result["fields"][name] = entry
        refinement = entry["pose_refinement"] or {}
        runs = "; ".join(f"{odom}: ATE {r['ate_estimate_m'] * 100:.2f} cm (max {r['ate_estimate_max_m'] * 100:.1f}), "
                         f"accepted {r['accepted']}/{r['keyframes']}, inliers {r['median_inliers']}"
                         for odom, r in entry["runs"].items())
        print(f"{name:20s} agreement {refinement.get('agreement_before_mm', entry['timing_agreement_mm'])} -> "
              f"{refinement.get('agreement_after_mm', '-')} mm, PSNR {held['psnr_db']:.2f} dB; {runs}", flush=True)
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
