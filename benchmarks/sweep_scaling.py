"""A sweep on 1 and on 2 workers of a local Ray instance: the time ratio, and the same table.

Simulates two short traversals (ideal camera, 60 frames at 160x120), then runs the same
8-cell sweep (2 recordings x oracle / splat field x 2 seeds, with a field built per
recording) with ``--ray auto --workers 1`` and ``--workers 2``, each into a fresh folder,
timing the whole command in this process (the machine is shared: the ratio is the figure,
the seconds are beside it). Checks that both ``sweep.csv`` agree up to timings. Writes
``benchmarks/results/sweep_scaling.json``.

    python benchmarks/sweep_scaling.py [--pool local]
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import tempfile
import time
from pathlib import Path

from provenance import write_result

SPEC = """
recordings:
  - {{name: a, map: {a}, query: {a}}}
  - {{name: b, map: {b}, query: {b}}}
field: {{model: [oracle, splat]}}
run: {{odom: noisy, keyframe_every: 3, render_size: 160x120, odom_trans_sigma: 0.004, odom_rot_sigma: 0.004}}
seeds: [0, 1]
"""


def _rows(folder: Path) -> list[dict]:
    with open(folder / "sweep.csv") as handle:
        return [{k: v for k, v in row.items() if k not in ("seconds", "command")} for row in csv.DictReader(handle)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pool", choices=("ray", "local"), default="ray")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/sweep_scaling.json"))
    args = p.parse_args()

    from nap3d_graph.cli import main as cli
    from nap3d_graph.sims.sensors import DepthNoise
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    ideal = dict(width=160, height=120, timing=None, exposure=None, depth=DepthNoise(flying_fraction=0.0))
    result = {"benchmark": "sweep_scaling", "pool": args.pool, "frames_per_recording": args.frames,
              "machine": {"cpus": os.cpu_count(), "python": platform.python_version()}, "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        a = simulate_sequence(tmp / "a", SimConfig(frames=args.frames, seed=5, **ideal))
        b = simulate_sequence(tmp / "b", SimConfig(frames=args.frames, seed=6, **ideal))
        spec = tmp / "sweep.yaml"
        spec.write_text(SPEC.format(a=a, b=b))
        for workers in (1, 2):
            extra = ["--ray", "auto"] if args.pool == "ray" else []
            t0 = time.perf_counter()
            code = cli(["sweep", str(spec), "--out", str(tmp / f"w{workers}"), "--workers", str(workers), *extra])
            seconds = time.perf_counter() - t0
            if code != 0:
                raise SystemExit(f"the {workers}-worker sweep failed ({code})")
            result["runs"][f"workers_{workers}"] = {"seconds": seconds}
        same = _rows(tmp / "w1") == _rows(tmp / "w2")
        cells = len(_rows(tmp / "w1"))
    ratio = result["runs"]["workers_2"]["seconds"] / result["runs"]["workers_1"]["seconds"]
    result.update({"cells": cells, "fields": 2, "ratio_2_to_1_workers": ratio, "same_table_up_to_timings": same,
                   "target_ratio": 0.6})
    write_result(args.out, result, args)
    print(f"{cells} cells on {args.pool}: 1 worker {result['runs']['workers_1']['seconds']:.1f} s, 2 workers "
          f"{result['runs']['workers_2']['seconds']:.1f} s: ratio {ratio:.2f} (target <= 0.6); same table: {same}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
