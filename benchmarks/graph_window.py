"""The graph of a long run, bounded or not: iSAM2 time per keyframe and memory up to 50,000 poses.

A synthetic walk (30 Hz, every frame a keyframe) goes through the real :class:`Pipeline`
graph: odometry with injected noise, and at every keyframe a NAP3D-like correction (the true
pose perturbed by its stated 1 cm / 0.5 deg covariance) through the same gate, factor and
iSAM2 updates a run uses; only the image work is left out (the measurement is drawn, not
rendered and aligned), since this measures the graph. Three runs: a bounded window whose
final frames are handed to ``on_retire`` (written to TUM files as they come, and forgotten:
the run's memory should stay flat), the same window keeping everything, and every keyframe
kept (``--graph-window 0``, the default). For each, the median iSAM2 milliseconds per keyframe
over each block of 1,000 keyframes, the process's resident memory at each 10,000 (each run in
its own process, so one run's freed memory does not hide another's growth), the final solve's
seconds and the ATE. Writes ``benchmarks/results/graph_window.json``.

    python benchmarks/graph_window.py [--keyframes 50000] [--window 200]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from provenance import write_result

from nap3d_graph.conventions import exp_se3, pose_error
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.results import Alignment, Correction
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.sims.trajectories import ImagelessWalk

CORRECTION_SIGMAS = np.r_[np.full(3, np.radians(0.5)), np.full(3, 0.01)]


class DrawnCorrections(Pipeline):
    """The run's graph with each keyframe's correction drawn around the truth (no field: no
    frame is read)."""

    def _correct_keyframe(self, i: int, frame) -> None:
        rng = np.random.default_rng(i)
        T_true = self.sequence.T_world_cam_gt[i]
        T_measured = T_true @ exp_se3(rng.normal(0.0, CORRECTION_SIGMAS))
        covariance = np.diag(CORRECTION_SIGMAS**2)
        alignment = Alignment(covariance=covariance, num_matches=200, num_inliers=150, success=True)
        T_pred = self.state.T_world_kf_pred
        correction = Correction(T_pred, T_measured, covariance, alignment, 1, True)
        self.apply_correction(self.state.pending(), i, correction, T_pred, frame)


def rss_mb() -> float:
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class SquaredErrors:
    """The ATE of a run's pieces, summed as they come (nothing kept)."""

    def __init__(self):
        self.sum_sq, self.frames = 0.0, 0

    def add(self, piece) -> None:
        self.sum_sq += sum(pose_error(a, b)[0] ** 2 for a, b in zip(piece.T_world_cam_estimate, piece.T_world_cam_gt))
        self.frames += len(piece.timestamps)

    @property
    def ate_m(self) -> float:
        return float(np.sqrt(self.sum_sq / self.frames))


class RetiredToFiles:
    """``on_retire``: the retired frames appended to TUM files as a long run would keep them."""

    def __init__(self, folder: Path, errors: SquaredErrors):
        self.handles = {name: open(folder / f"{name}.txt", "w") for name in ("estimate", "odometry", "estimate_online")}
        self.errors = errors

    def __call__(self, segment) -> None:
        for name, trajectory in segment.trajectories().items():
            if name in self.handles:
                trajectory.append_tum(self.handles[name])
        self.errors.add(segment)

    def close(self) -> None:
        for handle in self.handles.values():
            handle.close()


def run(walk: ImagelessWalk, window: int, retire: bool) -> dict:
    config = PipelineConfig(keyframe_every=1, graph_window=window, progress=False, final_gnc=True)
    folder = tempfile.TemporaryDirectory()
    errors = SquaredErrors()
    sink = RetiredToFiles(Path(folder.name), errors) if retire else None
    pipeline = DrawnCorrections(walk, None, make_odometry("noisy", walk, 1, 2e-3, 2e-3), config, on_retire=sink)
    memory, isam_ms = {}, []

    def on_keyframe(record):
        isam_ms.append(record.timings_s.get("isam", 0.0) * 1000.0)
        if len(isam_ms) % 10_000 == 0:
            memory[len(isam_ms)] = rss_mb()

    t0 = time.perf_counter()
    pipeline.start()
    for i in range(len(walk)):
        pipeline.step(i, on_keyframe=on_keyframe)
    run_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = pipeline.result(len(walk))
    final_s = time.perf_counter() - t0
    blocks = {str(k + 1000): float(np.median(isam_ms[k:k + 1000])) for k in range(0, len(isam_ms), 1000)}
    errors.add(result)  # the frames not retired (all of them without a sink)
    ate = errors.ate_m
    if sink is not None:
        sink.close()
    folder.cleanup()
    return {"graph_window": window, "retire": retire, "frames_in_final_result": len(result.timestamps),
            "keyframes": len(isam_ms), "run_s": run_s, "final_solve_s": final_s,
            "isam_ms_median_per_1000_keyframes": blocks, "isam_ms_p90_last_1000": float(np.percentile(isam_ms[-1000:], 90)),
            "rss_mb_at": {str(k): v for k, v in memory.items()}, "accepted": result.num_accepted, "ate_m": ate,
            "graph_variables_at_end": int(pipeline.state.graph.isam.calculateEstimate().size())}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--keyframes", type=int, default=50_000)
    p.add_argument("--window", type=int, default=200)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/graph_window.json"))
    args = p.parse_args()
    walk = ImagelessWalk(args.keyframes)
    result = {"benchmark": "graph_window", "keyframes": args.keyframes,
              "machine": {"cpus": os.cpu_count(), "python": platform.python_version()}, "runs": []}
    for window, retire in ((args.window, True), (args.window, False), (0, False)):
        # A fresh process per run: the resident memory then is this run's alone.
        with multiprocessing.get_context("spawn").Pool(1) as pool:
            out = pool.apply(run, (walk, window, retire))
        result["runs"].append(out)
        last = list(out["isam_ms_median_per_1000_keyframes"].values())
        print(f"window {window or 'all'}{', retired' if retire else ''}: iSAM2 {last[9] if len(last) > 9 else last[-1]:.3f} ms per keyframe at "
              f"10k, {last[-1]:.3f} at {out['keyframes']} (p90 {out['isam_ms_p90_last_1000']:.3f}); RSS "
              f"{out['rss_mb_at']} MB; final solve {out['final_solve_s']:.1f} s; ATE {out['ate_m'] * 100:.2f} cm; "
              f"{out['graph_variables_at_end']} variables at the end", flush=True)
        write_result(args.out, result, args)


if __name__ == "__main__":
    main()
