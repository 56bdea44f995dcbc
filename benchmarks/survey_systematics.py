"""What part of a self-made survey's error a systematic cause could explain (issue 48: the
survey ATE target is missed; is the rest one correctable error or per-frame error?).

For each map of a TUM recording, the survey's poses (``poses.txt``) against the motion
capture (``groundtruth.txt`` at 100 Hz), with evo: the ATE after an SE(3) alignment (what every
figure reports), after a Sim(3) alignment (a wrong metre: the depth's scale), and after an
SE(3) alignment with the survey's stamps shifted by each ``--offsets`` (a clock offset between
the camera and the motion capture). A cause that explains the error brings the ATE well
below the SE(3) figure; one that does not leaves it where it is.

    python benchmarks/survey_systematics.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --map first=/tmp/anywhere/survey_first/map --map second=/tmp/anywhere/survey_second/map \\
        --out benchmarks/results/survey_systematics_fr1_desk.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

from provenance import write_result


def ate_cm(reference, estimate, offset_s: float = 0.0, sim3: bool = False) -> tuple[float, float]:
    """``(ATE RMSE in cm, scale)`` of ``estimate`` against ``reference`` (evo trajectories),
    associated within 10 ms after adding ``offset_s`` to the estimate's stamps, aligned in SE(3)
    or, with ``sim3``, Sim(3)."""
    import copy

    from evo.core import metrics, sync

    ref, est = sync.associate_trajectories(reference, copy.deepcopy(estimate), max_diff=0.01, offset_2=offset_s)
    _, _, scale = est.align(ref, correct_scale=sim3)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return 100.0 * float(ape.get_statistic(metrics.StatisticsType.rmse)), float(scale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a TUM recording (its groundtruth.txt)")
    parser.add_argument("--map", action="append", required=True, help="NAME=MAP_DIR (repeat)")
    parser.add_argument("--offsets", default="-0.03,-0.02,-0.01,0,0.01,0.02,0.03",
                        help="clock offsets tried, seconds, comma-separated")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    from evo.tools import file_interface

    reference = file_interface.read_tum_trajectory_file(str(args.data / "groundtruth.txt"))
    offsets = [float(x) for x in args.offsets.split(",")]
    maps = {}
    for spec in args.map:
        name, _, map_dir = spec.partition("=")
        estimate = file_interface.read_tum_trajectory_file(str(Path(map_dir) / "poses.txt"))
        se3, _ = ate_cm(reference, estimate)
        sim3, scale = ate_cm(reference, estimate, sim3=True)
        shifted = {f"{o:+.3f}": ate_cm(reference, estimate, o)[0] for o in offsets}
        best = min(shifted, key=shifted.get)
        maps[name] = {"map": str(map_dir), "frames": int(estimate.num_poses), "se3_cm": se3, "sim3_cm": sim3,
                      "sim3_scale": scale, "offset_cm": shifted, "best_offset_s": float(best),
                      "best_offset_cm": shifted[best]}
        print(f"{name}: SE(3) {se3:.2f} cm, Sim(3) {sim3:.2f} cm (scale {scale:.4f}), best clock offset "
              f"{float(best) * 1000:+.0f} ms: {shifted[best]:.2f} cm")
    write_result(args.out, {"data": str(args.data), "maps": maps}, args)


if __name__ == "__main__":
    main()
