"""A drift-correction study of one recording in one call: train on a part, correct the rest.

``run_study(data, out)``: build a field on the first part of the recording (``split``, by
default the first half), then on the rest, which the field never saw:

1. drift correction with frame-to-frame visual odometry (``--odom vo``);
2. drift correction with noise injected on the ground-truth increments (``--odom noisy``);
3. Evaluation K with the trained field (by default its CLEAN / no-blur cell: the field's
   own accuracy, without the paper's synthetic degradations).

It writes one folder: ``field.pt`` and ``field_report.json``, ``runs/vo/`` and
``runs/noisy/`` (the usual run folders), ``eval_k/``, and ``summary.md`` / ``summary.json``,
the table a user reads first. This is how a user checks the method on their own recording.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

__all__ = ["odometry_list", "StudyConfig", "StudyRecordings", "StudySettings", "run_study", "summary_markdown"]

from nap3d_graph.arguments import RUN_MATCHER, TOPICS_OPTION, matcher_option, positive_int, setting
from nap3d_graph.conventions import pose_error
from nap3d_graph.datasets import open_sequence
from nap3d_graph.datasets.depth_timing import resolve_capture_timing
from nap3d_graph.fields.build import build_field
from nap3d_graph.fields.field_error import measure_frame
from nap3d_graph.motion.odometry import make_odometry
from nap3d_graph.nap3d.config import AlignConfig
from nap3d_graph.nap3d.matching import choose_matcher
from nap3d_graph.provenance import provenance
from nap3d_graph.run.config import PipelineConfig
from nap3d_graph.run.output import write_results
from nap3d_graph.run.pipeline import Pipeline
from nap3d_graph.run.settings import SettingsTree

log = logging.getLogger(__name__)


def odometry_list(text: str) -> tuple[str, ...]:
    """``--odom``'s comma-separated odometries."""
    return tuple(o.strip() for o in text.split(",") if o.strip())


@dataclass
class StudyConfig:
    split: float = setting(0.5, "--split", type=float,
        help="fraction of the frames the field is built on (default %(default)s)")
    model: str = setting("grid", "--model", choices=("grid", "splat", "views"),
        help="field model (default %(default)s; see train-field --help)")
    train_steps: int | None = setting(None, "--train-steps", type=positive_int,
        help="grid: training steps (default: 5 minutes)")
    keyframe_every: int = setting(5, "--keyframe-every", type=positive_int,
        help="a correction every N frames (default %(default)s)")
    odometries: tuple[str, ...] = setting(("vo", "noisy"), "--odom", setting=odometry_list, option=",".join,
        help="odometries to run, comma-separated (default %(default)s)")
    eval_k_scenarios: int = setting(40, "--scenarios", type=positive_int,
        help="Evaluation K scenarios (default %(default)s)")
    eval_k_full: bool = setting(False, "--eval-k-full", action="store_true",
        help="all 16 cells of Evaluation K (blur x intrinsics), not only CLEAN / no blur")
    seed: int = setting(0, "--seed", type=int,
        help="seed of the training, the odometry noise and Evaluation K's scenarios (default %(default)s)")
    # "auto": choose_matcher's choice by the recording the field is built from.
    matcher: str = setting(RUN_MATCHER, "--matcher", **matcher_option(RUN_MATCHER))
    progress: bool = True
    # ROS bags: which topics to read (BagTopics' text).
    topics: str | None = setting(None, "--topics", **TOPICS_OPTION)

    def __post_init__(self) -> None:
        if not 0.05 <= self.split <= 0.95:
            raise ValueError(f"split must be in [0.05, 0.95], got {self.split}")


@dataclass
class StudyRecordings:
    """What a study reads: one recording split in time (``data``), or a map recording (its
    ``map_frames``) and a query recording (its ``query_frames``) of the same place."""

    data: str | None = setting(None, "data", type=Path, nargs="?",
        help="a recording with ground truth (TUM layout, simulated, 7-Scenes), split in time; or use --map and "
             "--query")
    map: str | None = setting(None, "--map", dest="map_data", type=Path, metavar="REC_A",
        help="the recording the field is built from (with --query)")
    map_frames: str | None = setting(None, "--map-frames", metavar="START:STOP",
        help="--map: its frames to use (default all)")
    query: str | None = setting(None, "--query", type=Path, metavar="REC_B",
        help="the recording corrected with --map's field")
    query_frames: str | None = setting(None, "--query-frames", metavar="START:STOP",
        help="--query: its frames to correct (default all)")


@dataclass
class StudySettings(SettingsTree):
    """A study's settings tree: its recordings and its :class:`StudyConfig` (``config.yaml``'s
    ``settings``, read back by ``study --config``)."""

    SECTIONS = {"recordings": StudyRecordings, "study": StudyConfig}

    recordings: StudyRecordings = field(default_factory=StudyRecordings)
    study: StudyConfig = field(default_factory=StudyConfig)


def _write_config(path: Path, data, query, map_frames, query_frames, config: StudyConfig) -> None:
    """What the study was given, as ``study --config`` reads it back (the recordings as
    absolute paths)."""
    import yaml

    recordings = StudyRecordings(data=None if query is not None else str(Path(data).resolve()),
                                 map=str(Path(data).resolve()) if query is not None else None, map_frames=map_frames,
                                 query=None if query is None else str(Path(query).resolve()), query_frames=query_frames)
    tree = StudySettings(recordings, config).to_dict()
    path.write_text(yaml.safe_dump({"settings": tree}, sort_keys=False))


def _stage(name: str, progress: bool) -> None:
    if progress:
        print(f"== {name}", flush=True)


def run_study(data: str | Path, out: str | Path, config: StudyConfig | None = None, query: str | Path | None = None,
              map_frames: str | None = None, query_frames: str | None = None) -> dict:
    """Run the study into ``out``; returns the summary dict. With ``data`` alone, the field is
    built on its first part and the rest is corrected; with ``query`` (a second recording of
    the same place), the field is built on ``data`` (its ``map_frames``, default all) and
    ``query`` (its ``query_frames``) is corrected: a map made yesterday, a robot today. The
    two must share a world frame: checked on a few query frames aligned at their
    ground-truth pose (``summary["shared_world"]``), with a warning when they do not."""
    config = config or StudyConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    if query is None:
        train_frames, test_frames = f"0:{config.split}", f"{config.split}:1"
        test_data = data
    else:
        train_frames, test_frames, test_data = map_frames, query_frames, query  # None: all frames
    summary: dict = {"data": str(data), "train_frames": train_frames or "all", "test_frames": test_frames or "all",
                     "config": asdict(config)}
    _write_config(out / "config.yaml", data, query, map_frames, query_frames, config)
    if query is not None:
        summary["query"] = str(query)

    _stage(f"1/{2 + len(config.odometries)} field ({config.model}) on frames {train_frames or 'all'}", config.progress)
    train = open_sequence(data, frames=train_frames, topics=config.topics)
    matcher, why = choose_matcher(config.matcher, train)
    if matcher != config.matcher:
        log.info("matcher: %s (%s)", matcher, why)
        config = replace(config, matcher=matcher)
        summary["config"]["matcher"] = matcher
    field, report = build_field(train, config.model, steps=config.train_steps, seed=config.seed,
                                progress=config.progress, matcher=config.matcher)
    field.save(out / "field.pt")
    (out / "field_report.json").write_text(json.dumps(report, indent=1, default=float))
    summary["field"] = _field_summary(report)

    test = open_sequence(test_data, frames=test_frames, topics=config.topics)
    if query is not None:
        summary["shared_world"] = shared_world_check(field, test, config)
    summary["runs"] = {}
    for k, odom in enumerate(config.odometries, start=2):
        _stage(f"{k}/{2 + len(config.odometries)} drift correction, --odom {odom}, frames {test_frames or 'all'}",
               config.progress)
        summary["runs"][odom] = _drift_run(test, field, odom, out / "runs" / odom, config)

    _stage(f"{2 + len(config.odometries)}/{2 + len(config.odometries)} Evaluation K on frames {test_frames or 'all'}",
           config.progress)
    summary["eval_k"] = _eval_k(test, field, out / "eval_k", config)
    summary["seconds"] = round(time.perf_counter() - started, 1)
    record = {"provenance": provenance(asdict(config)), **summary}
    (out / "summary.json").write_text(json.dumps(record, indent=1, default=float))
    (out / "summary.md").write_text(summary_markdown(summary))
    return summary


def shared_world_check(field, sequence, config: StudyConfig, frames: int = 6) -> dict:
    """Do a map and a query recording share a world frame? A few query frames, spread over
    it, are aligned with the map's render at their own ground-truth pose: in a shared frame
    the corrections are centimetres at most; in another frame they fail (the view is not
    where the field has anything) or are large. Logs a warning when they do not agree."""
    run_config = PipelineConfig(field_sigma_m=0.0, align=AlignConfig(matcher=choose_matcher(config.matcher, sequence)[0]))
    T_world_cam_gt = sequence.T_world_cam_gt
    if T_world_cam_gt is None:
        return {"shared": None, "why": "the query has no ground truth"}
    sizes, failed = [], 0
    for i in np.linspace(0, len(sequence) - 1, min(frames, len(sequence))).round().astype(int):
        if not np.all(np.isfinite(T_world_cam_gt[i])):
            continue
        c = measure_frame(sequence, int(i), field, T_world_cam_gt[i], run_config, with_twist=False)
        if c.success:
            sizes.append(pose_error(c.T_world_cam_corrected, T_world_cam_gt[i])[0])
        else:
            failed += 1
    median = float(np.median(sizes)) if sizes else float("nan")
    shared = bool(sizes) and len(sizes) >= failed and median < 0.1
    result = {"shared": shared, "frames_aligned": len(sizes), "frames_failed": failed,
              "median_correction_m": median}
    if not shared:
        log.warning("the map and the query recordings do not seem to share a world frame: of %d query frames "
                    "aligned at their own ground-truth pose, %d failed and the others moved %.2f m (median); "
                    "corrections will not land", len(sizes) + failed, failed, median)
    return result


def _field_summary(report: dict) -> dict:
    held = report.get("held_out") or {}
    depth = held.get("depth_abs_err_m") or {}
    return {"model": report.get("model"), "timing": report.get("timing"),
            "psnr_db": held.get("psnr_db"), "psnr_affine_db": held.get("psnr_affine_db"),
            "depth_median_m": depth.get("median"), "depth_p90_m": depth.get("p90"),
            "opaque_fraction": held.get("opaque_fraction"), "render_seconds": held.get("render_seconds"),
            "build_seconds": report.get("total_seconds")}


def _drift_run(sequence, field, odom: str, folder: Path, config: StudyConfig) -> dict:
    odometry = make_odometry(odom, sequence, config.seed, matcher=config.matcher)
    pipeline_config = PipelineConfig(keyframe_every=config.keyframe_every, progress=config.progress,
                                     align=AlignConfig(matcher=config.matcher))
    pipeline = Pipeline(sequence, field, odometry, pipeline_config)
    pipeline_config = pipeline.config  # with the field's measured error resolved
    result = pipeline.run()
    record = {"study": True, "odometry": odom, "data": str(sequence.path), "frame_range": list(sequence.frame_range),
              "pipeline": {k: (v.to_dict() if hasattr(v, "to_dict") else v) for k, v in vars(pipeline_config).items()
                           if k != "align"},
              "align": vars(pipeline_config.align)}
    run_dir, metrics = write_results(result, folder, record, odom)
    inliers = [k.inliers for k in result.keyframes if k.inliers]
    return {"folder": str(run_dir.relative_to(folder.parent.parent)),
            "ate_odometry_m": metrics["odometry"]["ate_m"]["rmse"],
            "ate_estimate_m": metrics["estimate"]["ate_m"]["rmse"],
            "ate_estimate_max_m": metrics["estimate"]["ate_m"]["max"],
            "keyframes": len(result.keyframes), "accepted": result.num_accepted,
            "accepted_fraction": result.num_accepted / max(len(result.keyframes), 1),
            "median_inliers": float(np.median(inliers)) if inliers else 0.0,
            "seconds_per_keyframe": metrics["seconds_per_keyframe_median"].get("total_per_keyframe")}


def _eval_k(sequence, field, folder: Path, config: StudyConfig) -> dict:
    from nap3d_graph.evaluation.eval_k import EvalKConfig, run_eval_k

    cells = {} if config.eval_k_full else {"blur_sigmas": (0.0,), "intrinsics_noise": {"CLEAN": (1.0, 0.0)}}
    k_config = EvalKConfig(scenarios=config.eval_k_scenarios, seed=config.seed, timing=resolve_capture_timing(field, sequence)[0],
                           align=AlignConfig(matcher=config.matcher), **cells)
    summary = run_eval_k(sequence, field, folder, k_config, progress=config.progress)
    cell = summary["cells"]["blur0/CLEAN"]["methods"]
    return {m: {"success_rate": s["success_rate"], "trans_median_m": s["trans_err_m"]["median"],
                "trans_p90_m": s["trans_err_m"]["p90"], "rot_median_deg": s["rot_err_deg"]["median"],
                "rot_p90_deg": s["rot_err_deg"]["p90"], "rmse_3d_mean_m": s["rmse_3d_m"]["mean"],
                "nees_mean": s["nees"]["mean"]} for m, s in cell.items()}


def _fmt(value, scale: float = 1.0, digits: int = 2, unit: str = "") -> str:
    return "n/a" if value is None else f"{value * scale:.{digits}f}{unit}"


def summary_markdown(summary: dict) -> str:
    """The study's table as Markdown (the same figures as ``summary.json``)."""
    f = summary["field"]
    if summary.get("query"):
        shared = summary.get("shared_world") or {}
        said = ("they share a world frame" if shared.get("shared") else
                "**they do not seem to share a world frame**" if shared.get("shared") is False else
                "whether they share a world frame is not known")
        heading = [f"# Study: map {summary['data']} (frames {summary['train_frames']}), query {summary['query']} "
                   f"(frames {summary['test_frames']})", "",
                   f"Field ({f['model']}) built on the map recording; everything below is on the query recording: "
                   f"{said} (query frames aligned at their true pose: {shared.get('frames_aligned', 0)} aligned, "
                   f"{shared.get('frames_failed', 0)} failed, median correction "
                   f"{_fmt(shared.get('median_correction_m'), 100, unit=' cm')}).", "",
                   "## Field (held-out frames of the map recording)"]
    else:
        heading = [f"# Study of {summary['data']}", "",
                   f"Field ({f['model']}) built on frames {summary['train_frames']}; everything below is on frames "
                   f"{summary['test_frames']}, which it never saw.", "", "## Field (held-out frames of the training part)"]
    lines = [*heading,
             "", "| PSNR raw | PSNR after affine colour fit | depth error median / p90 | opaque | render |",
             "|---|---|---|---|---|",
             f"| {_fmt(f['psnr_db'], unit=' dB')} | {_fmt(f['psnr_affine_db'], unit=' dB')} | "
             f"{_fmt(f['depth_median_m'], 100, unit=' cm')} / {_fmt(f['depth_p90_m'], 100, unit=' cm')} | "
             f"{_fmt(f['opaque_fraction'], 100, 0, '%')} | {_fmt(f['render_seconds'], 1, 3, ' s')} |", ""]
    if f.get("timing"):
        t = f["timing"]
        lines += [f"Capture timing estimated from the data: depth {t['depth_offset_s'] * 1000:+.0f} ms from its stamp, "
                  f"colour {t['colour_offset_s'] * 1000:+.0f} ms, depth scale {t['depth_scale']:.3f}"
                  + (f", colour rows read over {t['readout_s'] * 1000:.0f} ms (rolling shutter; the runs align "
                     "each keyframe as of its middle row)" if t.get("readout_s") else ", a global shutter") + ".", ""]
    lines += ["## Drift correction", "",
              "| odometry | ATE odometry | ATE with NAP3D | max error | corrections accepted | median inliers | "
              "s per keyframe |", "|---|---|---|---|---|---|---|"]
    for odom, r in summary["runs"].items():
        lines.append(f"| {odom} | {_fmt(r['ate_odometry_m'], 100, unit=' cm')} | "
                     f"{_fmt(r['ate_estimate_m'], 100, unit=' cm')} | {_fmt(r['ate_estimate_max_m'], 100, unit=' cm')} | "
                     f"{r['accepted']}/{r['keyframes']} ({r['accepted_fraction'] * 100:.0f}%) | "
                     f"{r['median_inliers']:.0f} | {_fmt(r['seconds_per_keyframe'], 1, 2)} |")
    lines += ["", "## Evaluation K (CLEAN intrinsics, no blur; a failure scores the uncorrected pose)", "",
              "| method | success | translation median / p90 | rotation median / p90 | 3D RMSE mean | NEES |",
              "|---|---|---|---|---|---|"]
    for method, e in summary["eval_k"].items():
        lines.append(f"| {method} | {_fmt(e['success_rate'], 100, 0, '%')} | {_fmt(e['trans_median_m'], 1000, 1)} / "
                     f"{_fmt(e['trans_p90_m'], 1000, 1)} mm | {_fmt(e['rot_median_deg'], 1, 3)} / "
                     f"{_fmt(e['rot_p90_deg'], 1, 3)} deg | {_fmt(e['rmse_3d_mean_m'], 1000, 1, ' mm')} | "
                     f"{_fmt(e['nees_mean'], 1, 1)} |")
    lines += ["", f"Total time: {summary['seconds']:.0f} s."]
    return "\n".join(lines) + "\n"
