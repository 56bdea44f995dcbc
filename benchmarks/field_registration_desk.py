"""Where does a field's held-out PSNR stop? Misregistration against colour error.

For each held-out frame of a field built by ``train-field`` (the frames its
``FIELD.report.json`` evaluated), the field renders at the frame's colour pose (its capture
timing, 320x240) as ``train-field`` evaluates it. Per frame, over the pixels the real image
holds data for (not the undistortion's black corners): the raw PSNR; the PSNR over the
pixels the field renders with depth (opaque); the dense optical flow (OpenCV's Farneback)
from the real frame to the render, its median and p90 magnitude over opaque pixels (how far,
in pixels, the render's texture sits from the image's: pose, timing and depth errors of the
frames the field was built from, against the motion capture); and the PSNR after the render
is warped by that flow, the ceiling a renderer reaches with these poses as given. A render
whose PSNR is low but whose flow-warped PSNR is high is limited by registration, not by its
colours. Writes JSON.

    python benchmarks/field_registration_desk.py --field NAME=FIELD.pt [--field ...] \\
        [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk] [--out OUT.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from provenance import write_result


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    from nap3d_graph.fields.evaluation import psnr

    err = (a.astype(np.float64) / 255.0 - b.astype(np.float64) / 255.0) ** 2
    return psnr(float(err[mask].mean() if mask is not None else err.mean()))


def registration(sequence, field, frames: list[int], size: tuple[int, int]) -> list[dict]:
    """Per held-out frame: PSNR raw / opaque / flow-warped, flow median and p90 (px)."""
    import cv2

    from nap3d_graph.camera import colour_coverage
    from nap3d_graph.datasets.depth_timing import CaptureTiming
    from nap3d_graph.fields.evaluation import _poses

    K = sequence.intrinsics.without_distortion().scaled(*size)
    T_colour, _, _ = _poses(sequence, frames, CaptureTiming.of(field.meta.get("timing")))
    h, w = K.height, K.width
    scored = colour_coverage(sequence, (w, h))
    scored = np.ones((h, w), bool) if scored is None else scored
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    rows = []
    for k, i in enumerate(frames):
        real = cv2.resize(sequence[int(i)].rgb, (w, h), interpolation=cv2.INTER_AREA)
        view = field.render(T_colour[k], K)
        opaque = (view.opacity > 0.5) & scored
        flow = cv2.calcOpticalFlowFarneback(cv2.cvtColor(real, cv2.COLOR_RGB2GRAY),
                                            cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY), None,
                                            0.5, 3, 15, 3, 5, 1.2, 0)
        magnitude = np.linalg.norm(flow, axis=2)[opaque]
        warped = cv2.remap(view.rgb, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR)
        rows.append({"index": int(i), "psnr_db": _psnr(view.rgb, real, scored), "psnr_opaque_db": _psnr(view.rgb, real, opaque),
                     "psnr_flow_warped_db": _psnr(warped, real, scored),
                     "opaque_fraction": float(opaque[scored].mean()),
                     "flow_px_median": float(np.median(magnitude)) if magnitude.size else None,
                     "flow_px_p90": float(np.percentile(magnitude, 90)) if magnitude.size else None})
    return rows


def _spread(rows: list[dict], key: str) -> dict:
    values = np.array([r[key] for r in rows if r[key] is not None], dtype=float)
    return {"median": float(np.median(values)), "min": float(values.min()), "max": float(values.max())}


def main() -> None:
    from nap3d_graph.cli.train_field import report_path_for
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields import load_field

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--field", action="append", required=True, metavar="NAME=FIELD.pt",
                   help="a field built by train-field (its FIELD.report.json beside it names the held-out frames)")
    p.add_argument("--size", default="320x240", help="render size WxH (default 320x240, the pipeline's)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/field_registration_fr1_desk.json"))
    args = p.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    sequence = open_sequence(args.data)
    out = {"data": str(args.data), "render_size": list(size), "fields": {}}
    for item in args.field:
        name, _, path = item.partition("=")
        path = Path(path)
        report = json.loads(report_path_for(path).read_text())
        frames = report["held_out"]["frames"]
        rows = registration(sequence, load_field(path), frames, size)
        summary = {key: _spread(rows, key) for key in ("psnr_db", "psnr_opaque_db", "psnr_flow_warped_db",
                                                       "flow_px_median", "flow_px_p90")}
        out["fields"][name] = {"field": str(path), "frames": frames, "summary": summary, "per_frame": rows}
        s = summary
        print(f"{name:6s} PSNR raw {s['psnr_db']['median']:.1f} dB, opaque {s['psnr_opaque_db']['median']:.1f} "
              f"({s['psnr_opaque_db']['min']:.1f}-{s['psnr_opaque_db']['max']:.1f}), flow-warped "
              f"{s['psnr_flow_warped_db']['median']:.1f} ({s['psnr_flow_warped_db']['min']:.1f}-"
              f"{s['psnr_flow_warped_db']['max']:.1f}); flow median {s['flow_px_median']['median']:.2f} px "
              f"({s['flow_px_median']['min']:.2f}-{s['flow_px_median']['max']:.2f}), p90 "
              f"{s['flow_px_p90']['median']:.1f} px (per frame medians over {len(rows)} frames)", flush=True)
    write_result(args.out, out, args)


if __name__ == "__main__":
    main()
