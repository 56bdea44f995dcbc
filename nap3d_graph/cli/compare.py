"""``nap3d-graph compare``: EKF vs graph fusion on identical inputs.

One reference drift-correction run measures the stream every estimator then consumes: the
odometry (or the IMU), the keyframes and every NAP3D correction with its covariance. On it
run the odometry alone, the filterpy error-state EKF, GTSAM's NavStateImuEKF (IMU path),
iSAM2 (causal: what it knew at each frame; final) and batch Levenberg-Marquardt. Writes
comparison.csv / comparison.json (ATE, RPE, max error, NEES at keyframes against ground
truth, time per step), trajectories/<estimator>.txt and groundtruth.txt (TUM, for evo),
trajectories.png and errors.png, and prints the table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from nap3d_graph.evaluation.compare import compare, comparison_rows, format_table, write_comparison

from .common import PartialOutput, UsageError, empty_or_new_dir
from .options import add_output_folder
from .sources import add_source_arguments, prepare

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    p = sub.add_parser("compare", help="EKF vs graph: every estimator on the same odometry and NAP3D corrections",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_source_arguments(p)
    add_output_folder(p, default=Path("results/compare"))
    p.set_defaults(func=run)


def run(args) -> int:
    from nap3d_graph.estimators import stream_from_run

    t0 = time.perf_counter()
    if args.graph_window:
        raise UsageError("--graph-window does not apply to compare: its estimators are fed the whole run")
    empty_or_new_dir(args.out, args.force)
    prepared = prepare(args)
    if prepared.sequence.T_world_cam_gt is None:
        raise UsageError(f"{args.data}: no ground truth, and a comparison scores every estimator against it")
    with PartialOutput(args.out, "nap3d-graph compare ... --out " + str(args.out)):
        # The configuration first: an interrupted comparison still says what it was.
        (args.out / "config.json").write_text(json.dumps(prepared.record, indent=1, default=str))
        print("reference run (measures the corrections every estimator uses) ...")
        result = prepared.pipeline().run()
        imu = getattr(prepared.odometry, "stream", None)
        stream = stream_from_run(result, prepared.sequence, prepared.config, imu=imu,
                                 velocity0=getattr(prepared.odometry, "velocity0", None))
        print(f"{len(stream.corrections)} corrections measured at {len(stream.keyframes)} keyframes; running the "
              "estimators")
        results = compare(stream)
        rows = comparison_rows(stream, results)
        write_comparison(args.out, stream, results, rows, meta={"source": prepared.record})
    print(format_table(rows))
    print("ATE/RPE: evo, no alignment; NEES: keyframes, 6 dof, expected 6 (band: 95% were errors independent); "
          f"ms/step: per frame; final s: the solve after the last frame. Total {time.perf_counter() - t0:.0f} s")
    print(f"results: {args.out}/ (comparison.csv, comparison.json, trajectories/, trajectories.png, errors.png)")
    return 0
