"""Injected faults on simulated walks the tests never use: what reaches the trajectory.

For each room (default 32, 33, 34; 60 frames at 6 Hz, 192x144, exact field, drifting
recorded odometry) the clean run is compared with: 20% of corrections wrong by 5-50 cm and
2-20 deg; 20% of keyframes with depth 3-5% off in scale; every frame's depth 3.5% off (the
run must calibrate it); one correction 16 cm wrong after a 3 s stretch the field does not
cover. Writes ``benchmarks/results/faults.json`` (ATE of each run, its ratio to the clean
run, how many faults were refused or weighed out, the estimated depth scale).

    python benchmarks/faults.py [--rooms 32 33 34]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result
from scoring import unaligned_ate_m

from nap3d_graph.conventions import exp_se3, pose_error
from nap3d_graph.datasets import SimSequence
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.sims.faults import ScaledDepth
from nap3d_graph.sims.sensors import OdometryNoise
from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

CONFIG = PipelineConfig(keyframe_every=3, render_width=None, render_height=None, odom_drift_m_per_s=0.03,
                        odom_drift_rad_per_s=0.02, progress=False)


def ate(result) -> float:
    return unaligned_ate_m(result.T_world_cam_estimate, result.T_world_cam_gt)


def _run(seq, hook=None, sequence=None):
    return Pipeline(sequence or seq, seq.oracle_field(), make_odometry("recorded", seq), CONFIG,
                    correction_hook=hook).run()


def room_faults(seq, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    clean = _run(seq)
    keyframes = clean.keyframe_indices
    out = {"clean_ate_m": ate(clean), "clean_accepted": clean.num_accepted, "keyframes": len(keyframes),
           "odometry_ate_m": float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in
                                                    zip(clean.T_world_cam_odometry, clean.T_world_cam_gt)])))}

    wrong = set(rng.choice(keyframes[1:], size=int(round(0.2 * (len(keyframes) - 1))), replace=False).tolist())

    def inject(i, c):
        if i not in wrong or not c.success:
            return c
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        offset = np.r_[axis / np.linalg.norm(axis) * np.radians(rng.uniform(2, 20)),
                       direction / np.linalg.norm(direction) * rng.uniform(0.05, 0.5)]
        return dataclasses.replace(c, T_world_cam_corrected=c.T_world_cam_corrected @ exp_se3(offset))

    faulty = _run(seq, inject)
    accepted_wrong = {k.frame_index for k in faulty.keyframes if k.frame_index in wrong and k.accepted}
    out["wrong_corrections"] = {"injected": len(wrong), "gated_out": len(wrong) - len(accepted_wrong),
                                "accepted_then_weighed_out": len(accepted_wrong & set(faulty.gnc_outliers)),
                                "ate_m": ate(faulty), "ratio_to_clean": ate(faulty) / out["clean_ate_m"]}

    bad = rng.choice(keyframes[2:], size=int(round(0.2 * (len(keyframes) - 2))), replace=False)
    factors = {int(i): float(rng.uniform(1.03, 1.05)) for i in bad}
    scaled = _run(seq, sequence=ScaledDepth(seq, factors))
    refused = {k.frame_index for k in scaled.keyframes if not k.accepted and "depth scale" in k.reason}
    out["some_frames_scaled"] = {"injected": len(factors), "refused_for_scale": len(refused & set(factors)),
                                 "good_refused_for_scale": len(refused - set(factors)), "ate_m": ate(scaled),
                                 "ratio_to_clean": ate(scaled) / out["clean_ate_m"]}

    every = _run(seq, sequence=ScaledDepth(seq, {i: 1.035 for i in range(len(seq))}))
    out["every_frame_scaled_1.035"] = {"estimated_scale": every.depth_scale, "true_scale": 1 / 1.035,
                                       "scale_error_rel": every.depth_scale * 1.035 - 1, "accepted": every.num_accepted,
                                       "ate_m": ate(every), "ratio_to_clean": ate(every) / out["clean_ate_m"]}

    blind, target = set(keyframes[4:10]), keyframes[10]

    def blind_then_wrong(i, c):
        if i in blind:
            return dataclasses.replace(c, success=False, reason="the field does not cover this view (benchmark)")
        if i == target and c.success:
            return dataclasses.replace(c, T_world_cam_corrected=c.T_world_cam_corrected @ exp_se3([0, 0, 0, 0.16, 0, 0]))
        return c

    late = _run(seq, blind_then_wrong)
    out["wrong_after_blind_stretch"] = {"wrong_accepted_by_gate": any(k.frame_index == target and k.accepted
                                                                      for k in late.keyframes),
                                        "weighed_out": target in set(late.gnc_outliers), "ate_m": ate(late)}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rooms", type=int, nargs="+", default=[32, 33, 34])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/faults.json"))
    args = p.parse_args()
    rooms = {}
    with tempfile.TemporaryDirectory() as tmp:
        for room in args.rooms:
            drift = OdometryNoise(bias_init=(0.0, 0.0, 0.01, 0.025, 0.0, 0.01), heading_bias_rad_s=0.015)
            path = simulate_sequence(Path(tmp) / f"room{room}", SimConfig(frames=60, fps=6.0, width=192, height=144,
                                                                          scene_seed=room, seed=8, odometry=drift,
                                                                          timing=None))
            rooms[room] = r = room_faults(SimSequence(path), seed=room)
            print(f"room {room}: clean {r['clean_ate_m'] * 100:.2f} cm (odometry {r['odometry_ate_m'] * 100:.1f}); "
                  f"wrong corrections x{r['wrong_corrections']['ratio_to_clean']:.2f}; some frames scaled "
                  f"x{r['some_frames_scaled']['ratio_to_clean']:.2f} ({r['some_frames_scaled']['refused_for_scale']}/"
                  f"{r['some_frames_scaled']['injected']} refused); every frame 3.5% off x"
                  f"{r['every_frame_scaled_1.035']['ratio_to_clean']:.2f}, scale error "
                  f"{r['every_frame_scaled_1.035']['scale_error_rel'] * 100:+.2f}%")
    keys = ("wrong_corrections", "some_frames_scaled", "every_frame_scaled_1.035")
    summary = {k: {"ratio_to_clean_max": max(r[k]["ratio_to_clean"] for r in rooms.values()),
                   "ratio_to_clean_mean": float(np.mean([r[k]["ratio_to_clean"] for r in rooms.values()]))}
               for k in keys}
    summary["scale_error_rel_max_abs"] = max(abs(r["every_frame_scaled_1.035"]["scale_error_rel"])
                                             for r in rooms.values())
    write_result(args.out, {"benchmark": "faults", "rooms": rooms, "summary": summary}, args)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
