"""The embedded default as a new user meets it: first run on an empty cache, then again.

Runs ``nap3d-graph run`` (no arguments) twice in a fresh cache and results folder, times
both, and keeps the run's own ``metrics.json`` figures (ATE of odometry and estimate, each
half, corrections accepted, time per keyframe). The first run simulates the room's survey
and traversal and trains the field; the second reuses them.

    python benchmarks/default_run.py [--out benchmarks/results/default_run.json]
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


def run_once(cache: Path, results: Path) -> tuple[float, dict]:
    env = dict(os.environ, NAP3D_GRAPH_CACHE=str(cache), MPLBACKEND="Agg")
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "nap3d_graph.cli", "run", "--out", str(results)], env=env, check=True)
    seconds = time.perf_counter() - started
    return seconds, json.loads((results / "latest" / "metrics.json").read_text())


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/default_run.json"))
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        cache, results = Path(tmp) / "cache", Path(tmp) / "results"
        first_s, metrics = run_once(cache, results)
        cached_s, again = run_once(cache, results)
    same = json.dumps(metrics["estimate"]["ate_m"], sort_keys=True) == json.dumps(again["estimate"]["ate_m"],
                                                                                    sort_keys=True)
    result = {
        "first_run_s": first_s,
        "cached_run_s": cached_s,
        "second_run_same_ate": same,
        "ate_odometry_m": metrics["odometry"]["ate_m"]["rmse"],
        "ate_estimate_m": metrics["estimate"]["ate_m"]["rmse"],
        "ate_estimate_max_m": metrics["estimate"]["ate_m"]["max"],
        "ate_causal_m": metrics["estimate_online"]["ate_m"]["rmse"],
        "ate_causal_max_m": metrics["estimate_online"]["ate_m"]["max"],
        "ate_first_half_m": metrics["estimate"]["ate_first_half_m"],
        "ate_second_half_m": metrics["estimate"]["ate_second_half_m"],
        "odometry_first_half_m": metrics["odometry"]["ate_first_half_m"],
        "odometry_second_half_m": metrics["odometry"]["ate_second_half_m"],
        "corrections_accepted": metrics["corrections_accepted"],
        "keyframes": metrics["keyframes"],
        "seconds_per_keyframe": metrics["seconds_per_keyframe_median"],
    }
    print(json.dumps(result, indent=1))
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
