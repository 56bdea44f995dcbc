"""How long the simulator takes to render one RGB-D frame (noise-free RGB + z-depth).

    python benchmarks/sim_render.py [--out benchmarks/results/sim_render.json]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def main() -> None:
    from nap3d_graph.sims.scene import make_scene
    from nap3d_graph.sims.sequence import default_intrinsics
    from nap3d_graph.sims.trajectories import make_trajectory

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/sim_render.json"))
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    scene = make_scene(0)
    traj = make_trajectory("traverse", scene, np.random.default_rng(0), 10.0)
    result = {}
    for w, h in ((640, 480), (320, 240)):
        K = default_intrinsics(w, h)
        scene.render(traj.T_world_cam(0.0), K)  # warm-up
        times = []
        for i in range(args.repeats):
            t0 = time.perf_counter()
            scene.render(traj.T_world_cam(10.0 * i / args.repeats), K)
            times.append(time.perf_counter() - t0)
        result[f"{w}x{h}"] = {"median_s": float(np.median(times)), "min_s": float(np.min(times))}
        print(f"render {w}x{h}: {np.median(times):.3f} s per frame (median of {args.repeats})")
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
