"""The grid field on a CUDA GPU: trains there, renders there with the torch path, and agrees
with the same field rendered on the CPU (by the compiled kernels when numba is installed,
and by torch).

A small simulated survey (room 0's mapping path, 128x96) is written to a temporary folder; a
grid field is trained on it for ``--steps`` steps on ``--device``; held-out poses of a separate walk through the room are
rendered at 320x240 by the GPU field and by its copy moved to the CPU. Reports per backend:
render milliseconds (median over the poses after one warm-up), and against the GPU render the
median / p99 depth difference where both are opaque, the share of pixels whose opacity
disagrees about 0.5, the mean colour difference (levels of 255); and the depth error of every
backend against the simulator's exact depth. Writes JSON.

    python benchmarks/cuda_check.py --out cuda_check.json [--device cuda] [--steps 300]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from provenance import write_result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--poses", type=int, default=12)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    import dataclasses

    import torch

    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields.train_config import TrainConfig
    from nap3d_graph.fields.training import train_field
    from nap3d_graph.sims.scene import make_scene
    from nap3d_graph.sims.sequence import SimConfig, default_intrinsics, simulate_sequence
    from nap3d_graph.sims.trajectories import make_trajectory

    out: dict = {"device": args.device, "torch": torch.__version__, "steps": args.steps,
                 "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "survey"
        simulate_sequence(folder, SimConfig(frames=100, path="mapping", scene_seed=0, seed=5, width=128, height=96))
        survey = open_sequence(folder)
        t0 = time.perf_counter()
        field, report = train_field(survey, TrainConfig(max_steps=args.steps, device=args.device), progress=False)
        out["train_seconds"] = time.perf_counter() - t0
        out["train_device"] = str(field.device)
        out["train_psnr_db"] = report.get("held_out", {}).get("psnr_db") if isinstance(report, dict) else None
    scene = make_scene(0)
    traj = make_trajectory("traverse", scene, np.random.default_rng(1), 20.0)
    K = default_intrinsics(320, 240)
    poses = [traj.T_world_cam(t) for t in np.linspace(1.0, 19.0, args.poses)]
    truth = [scene.render(T, K)[1] for T in poses]
    cpu_torch = field.to("cpu")
    cpu_torch.render_config = dataclasses.replace(cpu_torch.render_config, backend="torch")
    fields = {f"{args.device} torch": field, "cpu compiled": field.to("cpu"), "cpu torch": cpu_torch}
    renders: dict = {}
    for name, f in fields.items():
        f.render(poses[0], K)  # warm-up (CUDA context, numba compilation)
        times, views = [], []
        for T in poses:
            if str(getattr(f, "device", "cpu")).startswith("cuda"):
                torch.cuda.synchronize()
            t = time.perf_counter()
            views.append(f.render(T, K))
            times.append(time.perf_counter() - t)
        renders[name] = views
        depth_err = [np.median(np.abs(v.depth_m - z)[(v.opacity > 0.5) & (z > 0)]) for v, z in zip(views, truth)]
        out[name] = {"render_ms_median": float(np.median(times) * 1000),
                     "backend": views[-1].extras.get("render_stats", {}).get("backend"),
                     "depth_err_vs_exact_mm_median": float(np.median(depth_err) * 1000)}
    reference = renders[f"{args.device} torch"]
    for name, views in renders.items():
        dz, p99, flips, colour = [], [], [], []
        for a, b in zip(reference, views):
            both = (a.opacity > 0.5) & (b.opacity > 0.5)
            d = np.abs(a.depth_m[both] - b.depth_m[both])
            dz.append(np.median(d) if d.size else np.nan)
            p99.append(np.percentile(d, 99) if d.size else np.nan)
            flips.append(np.mean((a.opacity > 0.5) != (b.opacity > 0.5)))
            colour.append(np.mean(np.abs(a.rgb.astype(float) - b.rgb.astype(float))))
        out[name].update({"vs_gpu_depth_mm_median": float(np.nanmedian(dz) * 1000),
                          "vs_gpu_depth_mm_p99": float(np.nanmax(p99) * 1000),
                          "vs_gpu_opacity_flips": float(np.mean(flips)), "vs_gpu_colour_levels": float(np.mean(colour))})
    write_result(args.out, out, args)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
