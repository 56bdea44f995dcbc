"""Where one odometry step's time goes, per stage, on real TUM fr1/desk (second half).

Each frame is read (PNG decode, depth to metres) and stepped by each visual odometry: the
dense RGB-D odometry (``--odom dense``: resize, pyramid, solve, depth check) and the feature
odometry (``--odom vo``: detect, match, RANSAC, refine) with SIFT and with XFeat, which
detects each frame once and reuses its features as the next step's view (measured beside
the same odometry detecting both images every step, ``*_detect_twice``). Reported:
p50 / p90 (ms) of each stage and of the whole step, and the frames per second the odometry
alone allows. One thread for torch and OpenCV, as the run's odometry has on a loaded machine.

    python benchmarks/odometry_profile.py [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk]
        [--out benchmarks/results/odometry_profile_fr1_desk.json]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def profile(sequence, odometry) -> dict:
    stages: dict[str, list[float]] = {}
    totals, reads = [], []
    for i in range(len(sequence)):
        t0 = time.perf_counter()
        frame = sequence[i]
        reads.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        if i == 0:
            odometry.prime(frame)
            continue
        inc = odometry.increment(i, frame)
        totals.append(time.perf_counter() - t0)
        for stage, seconds in inc.timings_s.items():
            stages.setdefault(stage, []).append(seconds)

    def ms(values) -> dict:
        values = np.asarray(values) * 1000.0
        return {"p50_ms": round(float(np.median(values)), 2), "p90_ms": round(float(np.percentile(values, 90)), 2)}

    step = ms(totals)
    return {"steps": len(totals), "step": step, "read": ms(reads), "stages": {k: ms(v) for k, v in stages.items()},
            "frames_per_s_at_p50": round(1000.0 / (step["p50_ms"] + ms(reads)["p50_ms"]), 1)}


def main() -> None:
    import cv2
    import torch

    from nap3d_graph.datasets import TumSequence
    from nap3d_graph.motion.odometry import DenseVisualOdometry, VisualOdometry
    from nap3d_graph.nap3d.config import AlignConfig

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--frames", default="0.5:1")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/odometry_profile_fr1_desk.json"))
    args = p.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    sequence = TumSequence(args.data, frames=args.frames)
    # Warm up both matchers first: OpenCV's SIFT measured ~1.6x faster in this process once
    # torch had run (seen on this machine, cause not pinned down), so every odometry below is
    # timed in the same state, whichever runs first.
    from nap3d_graph.nap3d.matching import detect_features

    for matcher in ("xfeat", "sift"):
        detect_features(sequence[0].rgb, matcher=matcher)
    out = {"command": "python benchmarks/odometry_profile.py", "data": str(args.data), "frames": args.frames,
           "resolution": [sequence.intrinsics.width, sequence.intrinsics.height], "odometries": {}}
    # The feature odometry detects each frame once (reusing its features as the next step's
    # view); "_detect_twice" is the same odometry detecting both images every step, as before.
    for name, odometry in (("dense", DenseVisualOdometry()),
                           ("vo_sift", VisualOdometry(config=AlignConfig(min_opacity=0.5, matcher="sift"))),
                           ("vo_xfeat", VisualOdometry(config=AlignConfig(min_opacity=0.5, matcher="xfeat"))),
                           ("vo_sift_detect_twice", VisualOdometry(config=AlignConfig(min_opacity=0.5, matcher="sift"),
                                                                   reuse_features=False)),
                           ("vo_xfeat_detect_twice", VisualOdometry(config=AlignConfig(min_opacity=0.5,
                                                                                       matcher="xfeat"),
                                                                    reuse_features=False))):
        result = profile(sequence, odometry)
        base = out["odometries"].get(name.removesuffix("_detect_twice"))
        if base is not None and base is not result:
            result["step_p50_vs_detecting_once"] = round(result["step"]["p50_ms"] / base["step"]["p50_ms"], 2)
        out["odometries"][name] = result
        stages = ", ".join(f"{k} {v['p50_ms']:.1f}/{v['p90_ms']:.1f}" for k, v in result["stages"].items())
        print(f"{name:9s} step {result['step']['p50_ms']:.1f} ms p50 / {result['step']['p90_ms']:.1f} p90, read "
              f"{result['read']['p50_ms']:.1f}; {stages} (ms p50/p90); {result['frames_per_s_at_p50']} frame/s")
    write_result(args.out, out, args)


if __name__ == "__main__":
    main()
