"""Does a trained field's error, grown away from its training frames (``train-field
--error-growth``), keep the corrections honest on simulated rooms no test or calibration used?

For each room (scene seeds 31-34 by default) the survey and a separate traversal are simulated
as the embedded default does, a grid field is trained on the survey as the embedded default
builds it (its error near its frames measured), and the traversal is corrected with the
default settings twice: with the error near the frames used everywhere (the default), and
with its growth measured by a view field of the survey's training frames
(:func:`~nap3d_graph.fields.error_growth.measure_error_growth`). Per room and pooled: the
corrections' NEES (mean against the 95% band of a mean of k chi-square(6) values, median),
the ATE (smoothed and causal, no alignment) and corrections accepted. ``--workdir`` keeps the
simulated rooms and fields (``drift_rooms.py`` writes the same ones) for a later run. Writes JSON.

    python benchmarks/error_growth_rooms.py [--rooms 31 32 33 34] [--workdir DIR] \\
        [--out benchmarks/results/error_growth_rooms.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from provenance import write_result


def _room(room: int, workdir: Path, steps: int):
    """(survey, walk, field) of a room, simulated and trained as the embedded default does
    (reused from ``workdir`` when there)."""
    from nap3d_graph.datasets import SimSequence
    from nap3d_graph.fields import load_field
    from nap3d_graph.fields.build import build_field
    from nap3d_graph.run.default import DEFAULT_MAPPING, DEFAULT_TRAVERSE
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    folders = {}
    for name, settings in (("survey", DEFAULT_MAPPING), ("walk", DEFAULT_TRAVERSE)):
        folders[name] = workdir / f"room{room}_{name}"
        if not (folders[name] / "scene.json").exists():
            simulate_sequence(folders[name], SimConfig(scene_seed=room, **settings), progress=True)
    survey = SimSequence(folders["survey"])
    field_path = workdir / f"room{room}_field.pt"
    if field_path.exists():
        field = load_field(field_path)
    else:
        field, report = build_field(survey, "grid", steps=steps, progress=True)
        field.save(field_path)
        field_path.with_suffix(".json").write_text(json.dumps(report, indent=1, default=float))
    return survey, SimSequence(folders["walk"]), field


def _run(walk, field) -> dict:
    from scipy.stats import chi2

    from nap3d_graph.evaluation.compare import correction_nees
    from nap3d_graph.evaluation.metrics import ate
    from nap3d_graph.motion.odometry import make_odometry
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pipeline import Pipeline

    result = Pipeline(walk, field, make_odometry("recorded", walk), PipelineConfig(progress=False)).run()
    nees = correction_nees(result)
    k = len(nees)
    T_gt = result.T_world_cam_gt
    return {"corrections": k, "nees_mean": float(np.mean(nees)) if k else None,
            "nees_band_95": [chi2.ppf(0.025, 6 * k) / k, chi2.ppf(0.975, 6 * k) / k] if k else None,
            "nees_median": float(np.median(nees)) if k else None,
            "ate_odometry_m": ate(result.timestamps, T_gt, result.T_world_cam_odometry)["rmse"],
            "ate_estimate_m": ate(result.timestamps, T_gt, result.T_world_cam_estimate)["rmse"],
            "ate_causal_m": ate(result.timestamps, T_gt, result.T_world_cam_online)["rmse"],
            "keyframes": len(result.keyframes), "accepted": result.num_accepted}


def main(argv=None) -> None:
    from nap3d_graph.fields.build import ERROR_FRAMES
    from nap3d_graph.fields.error_growth import measure_error_growth
    from nap3d_graph.fields.training_data import split_posed_frames
    from nap3d_graph.run.default import DEFAULT_TRAIN_STEPS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rooms", type=int, nargs="+", default=[31, 32, 33, 34])
    p.add_argument("--train-steps", type=int, default=DEFAULT_TRAIN_STEPS)
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/error_growth_rooms.json"))
    args = p.parse_args(argv)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="error_growth_rooms_"))
    workdir.mkdir(parents=True, exist_ok=True)
    out: dict = {"rooms": args.rooms, "train_steps": args.train_steps, "per_room": {}}
    for room in args.rooms:
        survey, walk, field = _room(room, workdir, args.train_steps)
        row = {"field_error": {k: v for k, v in (field.meta.get("field_error") or {}).items() if k != "by_view"},
               "near_frames_everywhere": _run(walk, field)}
        _, error_idx = split_posed_frames(survey, 1, ERROR_FRAMES)
        model = measure_error_growth(field.meta["field_error"], survey, field.meta["train_frames"], error_idx,
                                     field.meta.get("timing"))
        if model is not None:
            field.meta["field_error"]["by_view"] = model
        row["growth"] = None if model is None else {k: v for k, v in model.items() if k != "views"}
        row["with_growth"] = _run(walk, field) if model is not None else None
        out["per_room"][room] = row
        for name in ("near_frames_everywhere", "with_growth"):
            r = row[name]
            if r:
                print(f"room {room} {name:22s}: NEES mean {r['nees_mean']:.2f} (band {r['nees_band_95'][0]:.2f}-"
                      f"{r['nees_band_95'][1]:.2f}), median {r['nees_median']:.2f}; ATE {r['ate_estimate_m'] * 100:.2f}"
                      f" cm (causal {r['ate_causal_m'] * 100:.2f}, odometry {r['ate_odometry_m'] * 100:.2f}); "
                      f"{r['accepted']}/{r['keyframes']} accepted", flush=True)
        write_result(args.out, out, args)


if __name__ == "__main__":
    main()
