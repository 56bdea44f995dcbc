"""Drift removal on simulated rooms that no test or calibration used: mean and spread.

For each room (scene seeds 31-34 by default): the survey and a separate traversal are
simulated exactly as the embedded default does for room 0 (240 + 240 frames at 320x240,
15 Hz, the simulator's drifting odometry), a grid field is trained on the survey for the
default step budget exactly as the embedded default builds its field (``build_field``, grid,
capture timing estimated; saved as ``WORKDIR/room<N>_field.pt`` for other benchmarks; another
type with ``--model``, saved as ``room<N>_<model>_field.pt``), and the
pipeline runs along the traversal with its default settings, once with the trained field and
once with the exact (oracle) field. Reported per room and pooled (mean, min, max): ATE of the
odometry alone, with NAP3D (smoothed) and causal (evo, no alignment), the ATE of each half,
corrections accepted, and the median time per keyframe.

    python benchmarks/drift_rooms.py [--rooms 31 32 33 34] [--model grid] [--out benchmarks/results/drift_rooms.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result


def run_room(room: int, workdir: Path, steps: int, model: str = "grid") -> dict:
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.datasets.depth_timing import estimate_timing
    from nap3d_graph.evaluation.metrics import trajectory_metrics
    from nap3d_graph.fields import load_field
    from nap3d_graph.fields.build import build_field
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.default import DEFAULT_MAPPING, DEFAULT_TRAVERSE
    from nap3d_graph.run.output import keyframe_timing_summary
    from nap3d_graph.run.pipeline import Pipeline
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    folders = {}
    for name, settings in (("survey", DEFAULT_MAPPING), ("walk", DEFAULT_TRAVERSE)):
        folders[name] = workdir / f"room{room}_{name}"
        if not (folders[name] / "scene.json").exists():
            simulate_sequence(folders[name], SimConfig(scene_seed=room, **settings), progress=True)
    walk = SimSequence(folders["walk"])
    field_path = workdir / (f"room{room}_field.pt" if model == "grid" else f"room{room}_{model}_field.pt")
    if field_path.exists():
        field, report = load_field(field_path), json.loads(field_path.with_suffix(".json").read_text())
    else:
        field, report = build_field(SimSequence(folders["survey"]), model, steps=steps, progress=True)
        field.save(field_path)
        field_path.with_suffix(".json").write_text(json.dumps(report, indent=1, default=float))
    held = report.get("held_out") or {}
    out = {"field_held_out": {k: held.get(k) for k in ("psnr_db", "psnr_affine_db", "depth_abs_err_m",
                                                       "opaque_fraction", "opacity_on_surfaces")},
           "field_seconds": report.get("train_seconds")}
    # The trained field records the survey's capture timing; the oracle records none, so it
    # gets the traversal's own estimate (as 'nap3d-graph run --field oracle' does).
    for name, f, timing in (("trained", field, None), ("oracle", walk.oracle_field(), estimate_timing(walk))):
        result = Pipeline(walk, f, make_odometry("recorded", walk), PipelineConfig(progress=True, timing=timing)).run()
        metrics = trajectory_metrics(result.timestamps, result.T_world_cam_gt,
                                     {"odometry": result.T_world_cam_odometry, "estimate": result.T_world_cam_estimate,
                                      "estimate_online": result.T_world_cam_online})
        timing = keyframe_timing_summary(result)
        out[name] = {
            "ate_odometry_m": metrics["odometry"]["ate_m"]["rmse"],
            "ate_estimate_m": metrics["estimate"]["ate_m"]["rmse"],
            "ate_estimate_max_m": metrics["estimate"]["ate_m"]["max"],
            "ate_causal_m": metrics["estimate_online"]["ate_m"]["rmse"],
            "ate_first_half_m": metrics["estimate"]["ate_first_half_m"],
            "ate_second_half_m": metrics["estimate"]["ate_second_half_m"],
            "keyframes": len(result.keyframes),
            "accepted": result.num_accepted,
            "seconds_per_keyframe": timing.get("total_per_keyframe"),
        }
        print(f"room {room} {name:8s}: odometry {out[name]['ate_odometry_m'] * 100:.2f} cm -> NAP3D "
              f"{out[name]['ate_estimate_m'] * 100:.2f} cm (max {out[name]['ate_estimate_max_m'] * 100:.2f}, causal "
              f"{out[name]['ate_causal_m'] * 100:.2f}), "
              f"{out[name]['accepted']}/{out[name]['keyframes']} accepted", flush=True)
    return out


def pooled(per_room: dict, field: str) -> dict:
    keys = ("ate_odometry_m", "ate_estimate_m", "ate_estimate_max_m", "ate_causal_m", "ate_first_half_m",
            "ate_second_half_m", "seconds_per_keyframe")
    out = {}
    for key in keys:
        values = np.array([r[field][key] for r in per_room.values()], dtype=float)
        out[key] = {"mean": float(values.mean()), "min": float(values.min()), "max": float(values.max())}
    out["accepted_fraction"] = float(sum(r[field]["accepted"] for r in per_room.values())
                                     / sum(r[field]["keyframes"] for r in per_room.values()))
    ratios = [r[field]["ate_odometry_m"] / r[field]["ate_estimate_m"] for r in per_room.values()]
    out["reduction"] = {"mean": float(np.mean(ratios)), "min": float(np.min(ratios)), "max": float(np.max(ratios))}
    return out


def main(argv=None) -> None:
    from nap3d_graph.run.default import DEFAULT_TRAIN_STEPS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rooms", type=int, nargs="+", default=[31, 32, 33, 34])
    p.add_argument("--train-steps", type=int, default=DEFAULT_TRAIN_STEPS)
    p.add_argument("--model", default="grid", help="field type built on each survey (train-field --model)")
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/drift_rooms.json"))
    args = p.parse_args(argv)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="nap3d_drift_"))
    per_room = {room: run_room(room, workdir, args.train_steps, args.model) for room in args.rooms}
    result = {"rooms": args.rooms, "model": args.model, "train_steps": args.train_steps, "per_room": per_room,
              "pooled": {field: pooled(per_room, field) for field in ("trained", "oracle")}}
    for field, s in result["pooled"].items():
        print(f"{field:8s}: ATE with NAP3D {s['ate_estimate_m']['mean'] * 100:.2f} cm mean "
              f"({s['ate_estimate_m']['min'] * 100:.2f}-{s['ate_estimate_m']['max'] * 100:.2f}), odometry "
              f"{s['ate_odometry_m']['mean'] * 100:.2f} cm, {s['accepted_fraction'] * 100:.0f}% accepted")
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
