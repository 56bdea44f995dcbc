"""Training-pose refinement on real data: TUM fr1/desk, splat field built on the first half
with the motion-capture poses as they are and with them refined (``train-field
--refine-poses``), the second half corrected with visual odometry by each. Per field: the
training frames' multi-view depth agreement before and after, the held-out PSNR and depth
error, the field's own error; per run: ATE (no alignment) with max, causal ATE, corrections
accepted, median inliers. Writes JSON.

    python benchmarks/pose_refinement_desk.py [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk] \\
        [--rounds 3] [--matcher xfeat] [--out benchmarks/results/pose_refinement_fr1_desk.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--matcher", default="xfeat")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/pose_refinement_fr1_desk.json"))
    args = p.parse_args(argv)
    from keyframes_desk import run_one  # same folder: one run's figures from its results

    from nap3d_graph.cli import main as cli

    work = Path(tempfile.mkdtemp(prefix="pose_refinement_desk_"))
    result = {"data": str(args.data), "frames": "field from 0:0.5, runs on 0.5:1", "odometry": "vo",
              "matcher": args.matcher, "fields": {}}
    for name, rounds in (("poses as given", 0), (f"refined, {args.rounds} rounds", args.rounds)):
        field = work / f"refine{rounds}.pt"
        assert cli(["train-field", str(args.data), "--frames", "0:0.5", "--model", "splat", "--matcher", args.matcher,
                    "--refine-poses", str(rounds), "--out", str(field), "--quiet"]) == 0
        report = json.loads(field.with_suffix(".report.json").read_text())
        held = report["held_out"]
        entry = {"pose_refinement": report.get("pose_refinement"), "held_out_psnr_db": held["psnr_db"],
                 "held_out_psnr_affine_db": held["psnr_affine_db"], "held_out_depth_err_m": held["depth_abs_err_m"],
                 "timing_agreement_mm": (report.get("timing") or {}).get("agreement_mm"),
                 "field_error": report.get("field_error")}
        entry["run"] = r = run_one(args.data, field, "vo", args.matcher, [], work / f"run{rounds}")
        result["fields"][name] = entry
        refinement = entry["pose_refinement"] or {}
        print(f"{name:20s} agreement {refinement.get('agreement_before_mm', entry['timing_agreement_mm'])} -> "
              f"{refinement.get('agreement_after_mm', '-')} mm, PSNR {held['psnr_db']:.2f} dB, ATE "
              f"{r['ate_estimate_m'] * 100:.2f} cm (max {r['ate_estimate_max_m'] * 100:.1f}), accepted "
              f"{r['accepted']}/{r['keyframes']}, inliers {r['median_inliers']}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
