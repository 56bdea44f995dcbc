"""Is a run's covariance honest on real data with default settings? The field's own error,
measured by ``train-field`` on held-out frames, against the same run with the field taken as
exact (``--field-sigma 0``, the old default).

The field is built on the first half of TUM fr1/desk (``--field``, default: a splat field
with its error measured here); the second half, which it never saw, is corrected with
visual odometry. Per setting: the NEES of every successful correction against the ground
truth (6 dof: mean with the 95% band of a mean of k chi-square(6) values, median, p90), the
ATE (no alignment), corrections accepted. A field that records how its error grows away
from its frames (a view field; a grid or splat field built on a camera's recording, where
``train-field --error-growth`` is on by default) also runs with its error near its frames
used at every distance, what it was before. Writes JSON.

    python benchmarks/field_error_desk.py [--data ../shared/data/tum/rgbd_dataset_freiburg1_desk] \\
        [--field FIELD.pt] [--matcher xfeat] [--error-growth] [--out benchmarks/results/field_error_fr1_desk.json]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result


def run_one(data: Path, field, matcher: str, field_sigma, field_sigma_rad=None) -> dict:
    from scipy.stats import chi2

    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.evaluation.compare import correction_nees
    from nap3d_graph.evaluation.metrics import ate
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.nap3d.config import AlignConfig
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pipeline import Pipeline

    sequence = open_sequence(data, frames="0.5:1")
    odometry = make_odometry("vo", sequence, 0, 2e-3, 2e-3, matcher=matcher)
    config = PipelineConfig(field_sigma_m=field_sigma, field_sigma_rad=field_sigma_rad, align=AlignConfig(matcher=matcher),
                            progress=True)
    pipeline = Pipeline(sequence, field, odometry, config)
    result = pipeline.run()
    nees = correction_nees(result)
    k = len(nees)
    band = [chi2.ppf(0.025, 6 * k) / k, chi2.ppf(0.975, 6 * k) / k] if k else [None, None]
    posed = np.all(np.isfinite(result.T_world_cam_gt), axis=(1, 2))
    stamps = result.timestamps[posed]
    return {"field_sigma_m": pipeline.config.field_sigma_m, "field_sigma_rad": pipeline.config.field_sigma_rad,
            "field_error_by_view": pipeline.config.field_error_by_view,
            "corrections": k, "nees_mean": float(np.mean(nees)) if k else None,
            "nees_band_95": band, "nees_median": float(np.median(nees)) if k else None,
            "nees_p90": float(np.percentile(nees, 90)) if k else None, "chi2_6_median": float(chi2.ppf(0.5, 6)),
            "within_chi2_997": float(np.mean(nees < chi2.ppf(0.997, 6))) if k else None,
            "ate_odometry_m": ate(stamps, result.T_world_cam_gt[posed], result.T_world_cam_odometry[posed])["rmse"],
            "ate_estimate_m": ate(stamps, result.T_world_cam_gt[posed], result.T_world_cam_estimate[posed])["rmse"],
            "ate_causal_m": ate(stamps, result.T_world_cam_gt[posed], result.T_world_cam_online[posed])["rmse"],
            "keyframes": len(result.keyframes), "accepted": result.num_accepted}


def _add_growth(field, data: Path, matcher: str) -> dict | None:
    """The growth of ``field``'s error away from its training frames, measured on the frames
    it was built from (``meta["train_frames"]`` of frames 0:0.5) as train-field measures it."""
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields.build import ERROR_FRAMES
    from nap3d_graph.fields.error_growth import measure_error_growth
    from nap3d_graph.fields.training_data import split_posed_frames
    from nap3d_graph.nap3d.config import AlignConfig

    sequence = open_sequence(data, frames="0:0.5")
    _, error_idx = split_posed_frames(sequence, 1, ERROR_FRAMES)
    model = measure_error_growth(field.meta["field_error"], sequence, field.meta["train_frames"], error_idx,
                                 field.meta.get("timing"), AlignConfig(matcher=matcher))
    if model is not None:
        field.meta["field_error"]["by_view"] = model
        print("error by gap: " + ", ".join(f"{g:.2f} m -> {m * 1000:.1f} mm / {np.degrees(r):.2f} deg" for g, m, r
                                           in zip(model["gap_m"], model["sigma_m"], model["sigma_rad"])), flush=True)
        return {k: v for k, v in model.items() if k != "views"}
    return None


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("../shared/data/tum/rgbd_dataset_freiburg1_desk"))
    p.add_argument("--field", type=Path, default=None, help="a field built on frames 0:0.5 by train-field (default: "
                   "build a splat field here)")
    p.add_argument("--matcher", default="xfeat")
    p.add_argument("--error-growth", action="store_true",
                   help="a grid or splat field built without it (--error-growth off, or before it was the default "
                   "for a camera's recording): also measure how its error grows away from its training frames "
                   "on this checkpoint, and run with it")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/field_error_fr1_desk.json"))
    args = p.parse_args(argv)
    from nap3d_graph.cli import main as cli
    from nap3d_graph.fields import load_field

    field_path = args.field
    if field_path is None:
        field_path = Path(tempfile.mkdtemp(prefix="field_error_desk_")) / "splat.pt"
        assert cli(["train-field", str(args.data), "--frames", "0:0.5", "--model", "splat", "--matcher", args.matcher,
                    "--out", str(field_path), "--quiet"]) == 0
    field = load_field(field_path)
    result = {"data": str(args.data), "field": str(field_path), "frames": "0.5:1 (field from 0:0.5)",
              "odometry": "vo", "matcher": args.matcher, "field_error": field.meta.get("field_error"), "runs": {}}
    from nap3d_graph.fields.base import field_sigmas
    from nap3d_graph.fields.gap_error import has_error_by_view

    settings = [("measured (default)", (None, None)), ("exact (--field-sigma 0)", (0.0, None))]
    if has_error_by_view(field):  # its error grows with the distance from its frames: also without the growth
        near = "measured near the views, everywhere" if hasattr(field, "hiding_near") else \
            "measured near its frames, everywhere (--error-growth off)"
        settings.insert(1, (near, field_sigmas(field)))
    growth = "measured, growing away from its frames (--error-growth)"
    if args.error_growth and not hasattr(field, "hiding_near") and not has_error_by_view(field):
        settings.insert(1, (growth, (None, None)))
    for name, (sigma, sigma_rad) in settings:
        if name == growth:
            result["error_growth"] = _add_growth(field, args.data, args.matcher)
        result["runs"][name] = r = run_one(args.data, field, args.matcher, sigma, sigma_rad)
        print(f"{name:36s} NEES mean {r['nees_mean']:.1f} (band {r['nees_band_95'][0]:.2f}-{r['nees_band_95'][1]:.2f}), "
              f"median {r['nees_median']:.1f}; ATE {r['ate_estimate_m'] * 100:.2f} cm (odometry "
              f"{r['ate_odometry_m'] * 100:.2f}); accepted {r['accepted']}/{r['keyframes']}", flush=True)
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
