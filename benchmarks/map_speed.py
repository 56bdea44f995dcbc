"""How long ``nap3d-graph map`` takes, field included, as a user runs it (issue 48, item 4:
300 frames in <= 5 minutes on two cores).

Each recording is mapped from nothing (a fresh folder) with the command's defaults, in a
subprocess, and its stages' seconds are read back from ``map.json`` and
``field.report.json``; the wall time includes start-up, the ground-truth scoring and the
report.

    python benchmarks/map_speed.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --data ../shared/data/7scenes/redkitchen:0:300 --data ../shared/data/7scenes/redkitchen:200:500 \\
        --out benchmarks/results/map_speed.json

The grid's training fills what the whole map's budget (``MapSettings.budget_minutes``) leaves,
so the wall time of a recording shorter than 300 frames is not scaled up: what its stages
before the field did not spend, the training spends.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from provenance import write_result


def one(spec: str, work: Path, extra: list[str]) -> dict:
    """Map ``spec`` (``PATH`` or ``PATH:START:STOP``) in a fresh folder; its figures."""
    path, _, frames = spec.partition(":")
    out = work / (Path(path).name + (f"_{frames.replace(':', '_')}" if frames else ""))
    command = [sys.executable, "-m", "nap3d_graph", "map", path, "--out", str(out), "--quiet", *extra]
    if frames:
        command += ["--frames", frames]
    t0 = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    info = json.loads((out / "map.json").read_text())
    field = json.loads((out / "field.report.json").read_text())
    frames_mapped = info["segment"]["stop"] - info["segment"]["start"]
    result = {"data": spec, "frames": frames_mapped, "model": field["model"], "wall_s": round(wall, 1),
              "stages_s": {k: v["seconds"] for k, v in info["stages"].items()},
              "field_s": {"timing": field.get("timing_seconds"), "build_or_train": field.get("train_seconds"),
                          "field_error": (field.get("field_error") or {}).get("seconds"),
                          "total": field.get("total_seconds")},
              "survey_ate_m": (info.get("survey_ate") or {}).get("map", {}).get("rmse_m"),
              "survey_rotation_median_deg": (info.get("survey_ate") or {}).get("map", {}).get("rotation_median_deg"),
              # The grid trains for what the 5-minute budget leaves once the stages before it ran, so a
              # map of fewer frames does not finish sooner in proportion: its wall time is the figure.
              "within_5_minutes": wall <= 300.0}
    print(f"{spec}: {frames_mapped} frames in {wall:.0f} s ({result['stages_s']})")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", action="append", required=True, help="PATH or PATH:START:STOP (repeat)")
    parser.add_argument("--work", type=Path, default=None, help="folder for the maps (default: temporary)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("extra", nargs="*", help="more arguments for every map command (after --)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        runs = [one(spec, work, args.extra) for spec in args.data]
    write_result(args.out, {"cores": os.cpu_count(), "runs": runs}, args)


if __name__ == "__main__":
    main()
