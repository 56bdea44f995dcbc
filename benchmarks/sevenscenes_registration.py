"""7-Scenes' colour camera estimated from the images alone, against the estimate from the
recording's pose files, and what each does to real-vs-real NAP3D.

7-Scenes does not register depth to colour, so `SevenScenesSequence` estimates the colour
camera (focal length, principal point) from matched colour keypoints between frame pairs
0.3-0.8 s apart. Each pair's relative motion used to come from the recording's pose files
(its ground truth: `map` then read ground truth); it now comes from the depth images alone
(depth-only ICP over the frames between, refined directly). Neither is the default any more:
the Kinect v1's nominal colour camera is (``benchmarks/map_registration.py`` says why). This
script estimates both, takes the nominal camera beside them and then, as the judge, aligns frame pairs 4 apart real-vs-real with NAP3D (SIFT) under each
registration and compares with the ground truth's relative pose (read here only).

    python benchmarks/sevenscenes_registration.py --data ../shared/data/7scenes/redkitchen \\
        --out benchmarks/results/sevenscenes_registration.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def _pair_errors(sequence, step: int, gap: int, config) -> np.ndarray:
    """(P, 2): translation (m) and rotation (deg) error of NAP3D real-vs-real against the ground
    truth's relative pose, for frames ``a`` and ``a + gap`` every ``step`` frames (NaN: refused)."""
    from nap3d_graph.conventions import inv_T, pose_error
    from nap3d_graph.mapping.loops import Keyframe, verify_pair
    from nap3d_graph.nap3d.matching import detect_features

    errors = []
    for a in range(0, len(sequence) - gap, step):
        frames = sequence[a], sequence[a + gap]
        keys = [Keyframe(a + k * gap, f, detect_features(f.rgb, config.max_features, matcher=config.matcher))
                for k, f in enumerate(frames)]
        T_ab, _, alignment = verify_pair(keys[0], keys[1], config)
        if not alignment.success:
            errors.append((np.nan, np.nan))
            continue
        T_gt = inv_T(sequence.T_world_cam_gt[a]) @ sequence.T_world_cam_gt[a + gap]
        errors.append(pose_error(T_ab, T_gt))
    return np.asarray(errors, dtype=float)


def main() -> None:
    from nap3d_graph.datasets import SevenScenesSequence
    from nap3d_graph.nap3d.config import AlignConfig

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a 7-Scenes sequence folder")
    parser.add_argument("--step", type=int, default=25, help="a pair every STEP frames (default 25)")
    parser.add_argument("--gap", type=int, default=4, help="frames between a pair's two (default 4)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    base = SevenScenesSequence(args.data, registration="none", cache_dir=False)
    config = AlignConfig(matcher="sift")
    result: dict = {"data": str(args.data), "frames": len(base), "pair_step": args.step, "pair_gap": args.gap,
                    "registrations": {}}
    for poses in ("nominal", "images", "recording"):
        t0 = time.perf_counter()
        registration = (SevenScenesSequence(args.data, registration="nominal").registration if poses == "nominal"
                        else base.estimate_registration(poses=poses))
        seconds = time.perf_counter() - t0
        sequence = SevenScenesSequence(args.data, registration=registration, cache_dir=False)
        errors = _pair_errors(sequence, args.step, args.gap, config)
        ok = np.isfinite(errors[:, 0])
        entry = {**registration.to_dict(), "seconds": round(seconds, 1), "pairs": int(len(errors)),
                 "pairs_aligned": int(ok.sum()),
                 "pair_error_cm": {"median": float(np.median(errors[ok, 0]) * 100),
                                   "p90": float(np.percentile(errors[ok, 0], 90) * 100),
                                   "max": float(errors[ok, 0].max() * 100)},
                 "pair_error_deg": {"median": float(np.median(errors[ok, 1])),
                                    "p90": float(np.percentile(errors[ok, 1], 90))}}
        result["registrations"][poses] = entry
        print(f"poses from the {poses}: {registration.describe()} in {seconds:.0f} s; NAP3D real-vs-real "
              f"{ok.sum()}/{len(errors)} pairs, {entry['pair_error_cm']['median']:.2f} cm median "
              f"(p90 {entry['pair_error_cm']['p90']:.2f}, max {entry['pair_error_cm']['max']:.2f}), "
              f"{entry['pair_error_deg']['median']:.3f} deg")
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
