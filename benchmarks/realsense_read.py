"""How fast a RealSense recording reads: frames per second, raw and with registered depth.

Simulates a traversal (640x480 by default, 15 Hz, 200 Hz IMU), writes it as a ``.db3``
through pyrealsense2's ``software_device`` and ``recorder`` (as ``simulate --realsense``
does), then times, each over ``--repeats`` runs (median and max): reading every frame and
IMU sample at the sensor level (:func:`read_recording`), opening it as a sequence
(pairing, IMU resampling), and iterating every frame with its depth registered to the
colour camera (what a run does per frame). Writes ``benchmarks/results/realsense_read.json``.

    python benchmarks/realsense_read.py [--frames 90] [--width 640 --height 480]
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def _timed(fn, repeats: int) -> tuple[list[float], object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times, out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=90)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/realsense_read.json"))
    args = p.parse_args()

    from nap3d_graph.datasets import RealSenseRecording
    from nap3d_graph.datasets.realsense_io import read_recording
    from nap3d_graph.datasets.realsense_sim import write_realsense_recording
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_sequence(Path(tmp) / "walk", SimConfig(frames=args.frames, fps=15.0, width=args.width,
                                                               height=args.height, scene_seed=12, seed=1),
                                progress=True)
        t0 = time.perf_counter()
        recording = write_realsense_recording(sim, Path(tmp) / "walk.db3", progress=True)
        write_s = time.perf_counter() - t0
        size_mb = recording.stat().st_size / 1e6
        raw_times, raw = _timed(lambda: read_recording(recording), args.repeats)
        open_times, seq = _timed(lambda: RealSenseRecording(recording), args.repeats)
        iterate_times, _ = _timed(lambda: [frame.depth_m for frame in seq], args.repeats)

    n = len(raw.colour[0])
    imu = len(raw.gyro[0])

    def rate(times, count):
        return {"median": count / float(np.median(times)), "min": count / float(np.max(times))}

    result = {
        "benchmark": "realsense_read",
        "frames": n, "depth_frames": len(raw.depth[0]), "imu_samples": imu, "size": [args.width, args.height],
        "file_mb": round(size_mb, 1), "write_s": round(write_s, 2),
        "read_raw_s": raw_times, "open_sequence_s": open_times, "iterate_registered_s": iterate_times,
        "frames_per_s_read_raw": rate(raw_times, n),
        "frames_per_s_open": rate(open_times, n),
        "frames_per_s_registered_depth": rate(iterate_times, n),
        "frames_per_s_end_to_end": rate(np.asarray(open_times) + np.asarray(iterate_times), n),
        "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
    }
    write_result(args.out, result, args)
    print(f"{n} frames {args.width}x{args.height} + {imu} IMU samples ({size_mb:.0f} MB): "
          f"read {result['frames_per_s_read_raw']['median']:.0f} frame/s, opened as a sequence "
          f"{result['frames_per_s_open']['median']:.0f} frame/s, registered depth "
          f"{result['frames_per_s_registered_depth']['median']:.1f} frame/s, end to end "
          f"{result['frames_per_s_end_to_end']['median']:.1f} frame/s -> {args.out}")


if __name__ == "__main__":
    main()
