"""What settling on the given intrinsics (``PipelineConfig.intrinsics_check_every``) changes:
each setting run with the tracker (the default, 5) and fitting both camera models at every
keyframe (0), one after the other in one process.

Per setting and run: ATE (no alignment) and causal ATE, corrections accepted, the keyframe
measurement's median and p90 time, how many keyframes fitted the given intrinsics alone, and
how many kept the self-calibrated model; whether the two trajectories are the same to the
bit. Settings are ``DATA_NAME:FIELD:ODOM:MATCHER`` (second half corrected with a field built
on the first). Writes JSON.

    python benchmarks/intrinsics_tracker.py --setting fr1-desk:G.pt:dense:xfeat [--setting ...] \\
        [--data fr1-desk=../shared/data/tum/rgbd_dataset_freiburg1_desk] [--out benchmarks/results/intrinsics_tracker.json]
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result

from nap3d_graph.datasets import source_of

DEFAULT_DATA = {"fr1-desk": "../shared/data/tum/rgbd_dataset_freiburg1_desk",
                "redkitchen": "../shared/data/7scenes/redkitchen"}


def run_pair(data: Path, field: str, odom: str, matcher: str, out: Path) -> dict:
    """The run with the tracker (the default) and the same run reproduced from its config.yaml
    fitting both models at every keyframe: ``{5: summary, 0: summary}``."""
    from nap3d_graph.cli import main

    if main(["run", "--traj", source_of(data), "--data", str(data), "--frames", "0.5:1", "--field", field,
             "--odom", odom, "--matcher", matcher, "--out", str(out / "tracked")]) != 0:
        return {"error": "the run failed"}
    tracked = out / "tracked" / "latest"
    config = (tracked / "config.yaml").read_text()
    if "intrinsics_check_every: 5" not in config:
        return {"error": "the run's config.yaml does not hold intrinsics_check_every: 5"}
    (out / "config.yaml").write_text(config.replace("intrinsics_check_every: 5", "intrinsics_check_every: 0"))
    if main(["run", "--config", str(out / "config.yaml"), "--out", str(out / "both")]) != 0:
        return {"error": "the reproduced run failed"}
    return {5: summary(tracked, 5), 0: summary(out / "both" / "latest", 0)}


def summary(run: Path, check_every: int) -> dict:
    metrics = json.loads((run / "metrics.json").read_text())
    with open(run / "corrections.csv") as f:
        rows = list(csv.DictReader(f))
    measure = np.array([float(r["t_measure_s"]) for r in rows if r["t_measure_s"]]) * 1000
    models = [r["intrinsics_model"] for r in rows]
    return {"check_every": check_every, "ate_m": metrics["estimate"]["ate_m"]["rmse"],
            "ate_causal_m": metrics.get("estimate_online", {}).get("ate_m", {}).get("rmse"),
            "accepted": metrics["corrections_accepted"], "keyframes": len(rows),
            "measure_ms_median": float(np.median(measure)), "measure_ms_p90": float(np.percentile(measure, 90)),
            "fixed_only": sum(m.startswith("fixed (only") for m in models),
            "calibrated": sum(m.startswith("calibrated") for m in models),
            "estimate": (run / "estimate.txt").read_text()}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--setting", action="append", required=True, metavar="DATA_NAME:FIELD:ODOM:MATCHER")
    p.add_argument("--data", action="append", default=[], metavar="NAME=PATH", help="where a DATA_NAME is")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/intrinsics_tracker.json"))
    args = p.parse_args(argv)
    data = {**DEFAULT_DATA, **dict(spec.split("=", 1) for spec in args.data)}
    work = Path(tempfile.mkdtemp(prefix="intrinsics_tracker_"))
    results = []
    for k, setting in enumerate(args.setting):
        name, field, odom, matcher = setting.split(":")
        pair = run_pair(Path(data[name]), field, odom, matcher, work / str(k))
        if "error" in pair:
            results.append({"setting": setting, **pair})
            print(f"{setting}: {pair['error']}", flush=True)
            continue
        same = pair[5].pop("estimate") == pair[0].pop("estimate")
        results.append({"setting": setting, "same_trajectory": same, "tracked": pair[5], "both_always": pair[0]})
        a, b = pair[5], pair[0]
        print(f"{setting}: tracked ATE {a['ate_m'] * 100:.2f} cm ({a['accepted']}/{a['keyframes']}), "
              f"measure {a['measure_ms_median']:.0f} ms, {a['fixed_only']} fixed alone, {a['calibrated']} calibrated | "
              f"both always {b['ate_m'] * 100:.2f} cm ({b['accepted']}/{b['keyframes']}), "
              f"{b['measure_ms_median']:.0f} ms, {b['calibrated']} calibrated | "
              f"{'same trajectory' if same else 'trajectories differ'}", flush=True)
    write_result(args.out, {"settings": results}, args)


if __name__ == "__main__":
    main()
