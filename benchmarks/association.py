"""How long colour/depth timestamp association takes on long streams.

5,000 frames of 30 Hz colour with depth 15 ms early and jitter (each colour frame has its
own depth frame within 20 ms, often a second one too): the optimal one-to-one pairing and
TUM's greedy one. The aim is well under 0.5 s each, so opening a long sequence is instant.

    python benchmarks/association.py [--frames 5000] [--out benchmarks/results/association.json]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def main() -> None:
    from nap3d_graph.datasets.association import associate

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/association.json"))
    args = parser.parse_args()
    rng = np.random.default_rng(3)
    a = np.arange(args.frames) / 30 + rng.uniform(-0.002, 0.002, args.frames)
    b = a - 0.015 + rng.uniform(-0.003, 0.003, args.frames)
    result = {"frames": args.frames, "aim_s": 0.5}
    for method in ("optimal", "greedy"):
        times, pairs = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            pairs = associate(a, b, 0.02, association=method)
            times.append(time.perf_counter() - t0)
        result[method] = {"median_s": float(np.median(times)), "max_s": float(np.max(times)), "pairs": len(pairs)}
        print(f"{method:8s} association of {args.frames} frames: {np.median(times) * 1000:.1f} ms median "
              f"(max {np.max(times) * 1000:.1f} ms, {len(pairs)} pairs)")
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
