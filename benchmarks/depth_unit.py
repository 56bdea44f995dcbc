"""The depth unit check (``train-field --depth-unit check``, the default) on real recordings:
each read as it is and with the two TUM unit mistakes simulated (every depth x0.2: millimetre
PNGs read at 5000 per metre; x5: TUM's PNGs read at 1000 per metre), the scale the check finds
and the views' median relative disagreement at each tried scale, and how long it takes.

    python benchmarks/depth_unit.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --data ../shared/data/7scenes/redkitchen --data ../shared/data/tum/rgbd_dataset_freiburg1_xyz

Writes ``benchmarks/results/depth_unit.json``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from provenance import write_result

from nap3d_graph.datasets import open_sequence
from nap3d_graph.datasets.depth_unit import check_depth_unit
from nap3d_graph.sims.faults import ScaledDepth

#: The unit mistakes simulated: every depth multiplied by this factor on reading.
MISTAKES = {"as recorded": 1.0, "x0.2 (millimetres read at 5000 per metre)": 0.2,
            "x5 (TUM's PNGs read at 1000 per metre)": 5.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, action="append", required=True, help="a recording with ground truth")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/depth_unit.json"))
    args = parser.parse_args()
    rows = []
    for data in args.data:
        sequence = open_sequence(data)
        for mistake, factor in MISTAKES.items():
            t0 = time.perf_counter()
            every_frame = {i: factor for i in range(len(sequence))}
            check = check_depth_unit(ScaledDepth(sequence, every_frame))
            seconds = time.perf_counter() - t0
            expected = 1.0 / factor
            row = {"recording": data.name, "mistake": mistake, "factor": factor, "expected_scale": expected,
                   "found_scale": None if check is None else check.scale,
                   "right": check is not None and abs(check.scale - expected) < 1e-9,
                   "pairs": None if check is None else check.pairs,
                   "disagreement": None if check is None else {f"x{s:g}": v for s, v in check.disagreement.items()},
                   "seconds": round(seconds, 2)}
            rows.append(row)
            print(f"{data.name:40s} {mistake:45s} found x{row['found_scale']} (expected x{expected:g}) "
                  f"in {seconds:.1f} s")
    write_result(args.out, {"rows": rows, "right": sum(r["right"] for r in rows), "checks": len(rows)}, args)


if __name__ == "__main__":
    main()
