"""Frame-to-frame odometry on real data: speed and drift of ``--odom vo`` and ``--odom dense``.

On a TUM recording (default: the second half of fr1/desk, the part the study corrects),
each odometry runs alone from the ground truth's first pose: milliseconds per frame for
reading the frame and for the odometry step (median, p90), frames per second end to end on
this machine, and the odometry's drift (evo-style ATE without alignment, and the final
error). Writes ``benchmarks/results/vo_fr1_desk.json``.

    python benchmarks/vo_desk.py [DATA] [--frames 0.5:1]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from provenance import write_result

from nap3d_graph.conventions import pose_error
from nap3d_graph.datasets import open_sequence
from nap3d_graph.motion.odometry import make_odometry


def run(sequence, kind: str) -> dict:
    odometry = make_odometry(kind, sequence)
    read_s, step_s = [], []
    t0 = time.perf_counter()
    first = sequence[0]
    read_s.append(time.perf_counter() - t0)
    odometry.prime(first)
    T = [odometry.initial_pose()]
    failed = 0
    for i in range(1, len(sequence)):
        t0 = time.perf_counter()
        frame = sequence[i]
        t1 = time.perf_counter()
        inc = odometry.increment(i, frame)
        step_s.append(time.perf_counter() - t1)
        read_s.append(t1 - t0)
        failed += not inc.ok
        T.append(T[-1] @ inc.T_prev_cur)
    errors = np.array([pose_error(a, b)[0] for a, b in zip(T, sequence.T_world_cam_gt)])
    total = np.asarray(read_s[1:]) + np.asarray(step_s)
    return {"frames": len(sequence), "failed_steps": int(failed),
            "read_ms": {"median": 1000 * float(np.median(read_s)), "p90": 1000 * float(np.percentile(read_s, 90))},
            "step_ms": {"median": 1000 * float(np.median(step_s)), "p90": 1000 * float(np.percentile(step_s, 90))},
            "frames_per_s": float(1.0 / np.median(total)),
            "ate_m": float(np.sqrt(np.mean(errors**2))), "final_error_m": float(errors[-1]),
            "max_error_m": float(errors.max())}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", nargs="?", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--frames", default="0.5:1")
    p.add_argument("--kinds", nargs="+", default=["dense", "vo"])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/vo_fr1_desk.json"))
    args = p.parse_args()
    sequence = open_sequence(args.data, frames=args.frames)
    result = {"data": args.data.name, "frames": args.frames, "odometry": {}}
    for kind in args.kinds:
        r = result["odometry"][kind] = run(sequence, kind)
        print(f"{kind:6s}: {r['step_ms']['median']:.0f} ms per step (+{r['read_ms']['median']:.0f} ms reading), "
              f"{r['frames_per_s']:.1f} frame/s; drift ATE {r['ate_m'] * 100:.1f} cm, final {r['final_error_m'] * 100:.1f} cm, "
              f"{r['failed_steps']} failed steps")
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
