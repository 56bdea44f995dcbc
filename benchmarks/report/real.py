"""Sections of ``docs/results.md`` measured on the real recordings (TUM fr1/desk, 7-Scenes
redkitchen): the field built on a recording's first half, its second half corrected. Every
figure is read from the result file the row names.
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import PurePosixPath

from report import RESULTS, Section, cm, get, load, mm, ms, num, pair, table

NA = "n/a"
STUDIES = ("study_fr1_desk", "study_fr1_desk_views", "study_7scenes_redkitchen")
FIELD_ERROR_FILES = ("field_error_fr1_desk.json", "field_error_fr1_desk_splat.json", "field_error_fr1_desk_views.json",
                     "field_error_fr1_desk_grid.json", "field_error_fr1_desk_grid_seed1.json",
                     "field_error_fr1_desk_grid_seed2.json", "field_error_redkitchen_grid.json")
POSE_REFINEMENT_FILES = ("pose_refinement_fr1_desk.json", "pose_refinement_fr1_desk_views.json")
FIELD_MODELS_FILES = ("field_models_fr1_desk.json", "field_models_redkitchen.json")
FLOOR_FILES = ("correction_floor_fr1_desk.json", "correction_floor_redkitchen.json")
GT_FILES = ("ground_truth_consistency_fr1_desk.json", "ground_truth_consistency_redkitchen.json")
VO_WIDTH_FILES = ("vo_width_fr1_desk.json", "vo_width_redkitchen.json")
SHUTTER_FILES = ("rolling_shutter_fr1_desk.json", "rolling_shutter_redkitchen.json")
SWEEPS = ("sweep_real", "sweep_fields", "sweep_grid_seeds")
EVAL_K_ORDER = ("nap3d-refined", "nap3d-selfcal", "nap3d-plain", "pnp", "pnp-selfcal")


# --- reading ---------------------------------------------------------------------------------

def _dict(d, *keys) -> dict:
    """``get``, or an empty dict where that is missing or not a dict."""
    value = get(d, *keys)
    return value if isinstance(value, dict) else {}


def _list(d, *keys) -> list:
    """``get``, or an empty list where that is missing or not a list."""
    value = get(d, *keys)
    return value if isinstance(value, list) else []


def _first(*values):
    """The first value that is not None."""
    return next((v for v in values if v is not None), None)


def _csv(name: str) -> list[dict]:
    """The rows of ``benchmarks/results/<name>`` (a CSV file with a header)."""
    with open(RESULTS / name, newline="") as f:
        return list(csv.DictReader(f))


def _float(text):
    """A CSV cell as a number, None where it is empty or not a number."""
    try:
        return float(text)
    except (TypeError, ValueError):
        return None


def _field_label(path) -> str:
    """The field a path names: its type, and the seed and training steps a grid's name records."""
    if not path:
        return NA
    name = PurePosixPath(str(path)).name
    m = re.search(r"model=([a-z]+)(?:_seed=(\d+))?_steps=(\d+)", name)
    if m is None:
        stem = PurePosixPath(name).stem
        return f"field of {PurePosixPath(str(path)).parent.name}" if stem == "field" else stem
    model, seed, steps = m.groups()
    label = f"{model}, {steps} steps" if model == "grid" else model
    return f"{label}, seed {seed}" if seed is not None else label


def _opt(command: str, option: str):
    """The value after ``option`` in a command line, None where it is absent."""
    m = re.search(rf"{re.escape(option)}\s+(\S+)", command or "")
    return m.group(1) if m else None


# --- cells -----------------------------------------------------------------------------------

def _code(name: str) -> str:
    return f"`{name}`"


def _int(value) -> str:
    return NA if value is None else str(value)


def _frac(part, whole) -> str:
    """``part/whole`` (accepted of keyframes), ``n/a`` where either is missing."""
    return NA if part is None or whole is None else f"{part}/{whole}"


def _pct(fraction, digits: int = 0) -> str:
    return NA if fraction is None else f"{fraction * 100:.{digits}f}"


def _deg(rad, digits: int = 2) -> str:
    return NA if rad is None else f"{math.degrees(rad):.{digits}f}"


def _range(low, high, fmt=num) -> str:
    return NA if low is None or high is None else f"{fmt(low)}-{fmt(high)}"


def _cm_of(value_cm, digits: int = 2) -> str:
    """A figure already in centimetres."""
    return num(value_cm, digits)


# --- matchers and keyframes ------------------------------------------------------------------

def _run_cells(r: dict) -> list[str]:
    """ATE columns of one run record (odometry, corrected with median, max, causal, accepted)."""
    return [cm(get(r, "ate_odometry_m")),
            pair(cm(get(r, "ate_estimate_m")), cm(get(r, "ate_estimate_median_m"))),
            cm(get(r, "ate_estimate_max_m"), 1), cm(get(r, "ate_causal_m")),
            _frac(get(r, "accepted"), get(r, "keyframes"))]


def _refused(reasons) -> str:
    """Refused corrections by reason, ``n/a`` where the file does not count them."""
    if not isinstance(reasons, dict):
        return NA
    return "; ".join(f"{why}: {n}" for why, n in reasons.items()) or "none"


def matchers_table() -> str:
    """One row per matcher and per keyframe setting, the same field and odometry."""
    header = ["file", "field", "matcher, odometry", "setting", "odometry ATE cm", "ATE cm / median", "max cm",
              "causal cm", "accepted", "refused (reason: count)", "median inliers", "postponed keyframes",
              "keyframes on doubt", "measurement s per keyframe"]
    rows = []
    m = load("matchers_fr1_desk.json")
    for matcher, r in _dict(m, "matchers").items():
        rows.append([_code("matchers_fr1_desk.json"), _field_label(get(m, "field")),
                     f"{matcher}, {get(m, 'odometry')}", "as they come (default)"] + _run_cells(r)
                    + [_refused(get(r, "refused_reasons")), num(get(r, "median_inliers"), 1), NA, NA,
                       num(get(r, "seconds_per_keyframe_median", "measure"))])
    k = load("keyframes_fr1_desk.json")
    for setting, r in _dict(k, "settings").items():
        rows.append([_code("keyframes_fr1_desk.json"), _field_label(get(k, "field")),
                     f"{get(k, 'matcher')}, {get(k, 'odometry')}", setting] + _run_cells(r)
                    + [NA, num(get(r, "median_inliers"), 1), _int(get(r, "postponed")),
                       _int(get(r, "doubt_keyframes")), NA])
    return table(header, rows)


# --- the study -------------------------------------------------------------------------------

def _joined(runs: dict, cell) -> str:
    """One cell over a study's runs, in their order, separated by semicolons."""
    return "; ".join(cell(r) for r in runs.values()) or NA


def _study_row(folder: str) -> list[str]:
    """A study folder: its field (build, held-out scores, own error) and its runs."""
    s, rep = load(f"{folder}/summary.json"), load(f"{folder}/field_report.json")
    f, runs = _dict(s, "field"), _dict(s, "runs")
    return [_code(f"{folder}/summary.json"), f"{get(f, 'model')}, {get(s, 'config', 'matcher')}",
            f"{num(get(rep, 'train_seconds'), 0)} ({_int(get(rep, 'steps'))})", num(get(f, "build_seconds"), 0),
            pair(num(get(f, "psnr_db")), num(get(f, "psnr_affine_db"))),
            pair(cm(get(f, "depth_median_m")), cm(get(f, "depth_p90_m"))),
            pair(mm(get(rep, "field_error", "sigma_m")), _deg(get(rep, "field_error", "sigma_rad"))),
            ms(get(f, "timing", "readout_s"), 0),
            "; ".join(runs) or NA,
            _joined(runs, lambda r: cm(get(r, "ate_odometry_m"))),
            _joined(runs, lambda r: cm(get(r, "ate_estimate_m"))),
            _joined(runs, lambda r: cm(get(r, "ate_estimate_max_m"), 1)),
            _joined(runs, lambda r: _frac(get(r, "accepted"), get(r, "keyframes"))),
            _joined(runs, lambda r: num(get(r, "median_inliers"), 1)),
            _joined(runs, lambda r: num(get(r, "seconds_per_keyframe")))]


def study_table() -> str:
    """One row per study folder; columns over its runs list them in order, separated by ``;``."""
    header = ["file", "field, matcher", "training s (steps)", "build s in all", "held-out PSNR dB / affine fit",
              "held-out depth error cm median / p90", "field's own error mm / deg", "readout ms", "odometries",
              "odometry ATE cm", "ATE cm", "max cm", "accepted", "median inliers", "s per keyframe"]
    return table(header, [_study_row(folder) for folder in STUDIES])


def eval_k_table() -> str:
    """Evaluation K on each study's field, one row per estimator."""
    header = ["file", "scenarios", "estimator", "successful %", "translation mm median / p90",
              "rotation deg median / p90", "NEES mean"]
    rows = []
    for folder in STUDIES:
        s = load(f"{folder}/summary.json")
        ek = _dict(s, "eval_k")
        for name in [n for n in EVAL_K_ORDER if n in ek] + [n for n in ek if n not in EVAL_K_ORDER]:
            e = ek[name]
            rows.append([_code(f"{folder}/summary.json"), _int(get(s, "config", "eval_k_scenarios")), name,
                         _pct(get(e, "success_rate")),
                         pair(mm(get(e, "trans_median_m")), mm(get(e, "trans_p90_m"))),
                         pair(num(get(e, "rot_median_deg")), num(get(e, "rot_p90_deg"))),
                         num(get(e, "nees_mean"), 1)])
    return table(header, rows)


# --- the field's own error -------------------------------------------------------------------

def _farthest(r: dict, run: dict) -> str:
    """The error's growth a run adds: the farthest gap measured and the error there."""
    if not get(run, "field_error_by_view"):
        return "off"
    by_view = _dict(r, "field_error", "by_view")
    return pair(num(get(by_view, "gap_m", -1)), mm(get(by_view, "sigma_m", -1)))


def _nees_row(name: str, r: dict, setting: str, run: dict) -> list[str]:
    """One file's run with one setting of the field's error."""
    band = _list(run, "nees_band_95") or [None, None]
    return [_code(name), f"{_field_label(get(r, 'field'))} ({_int(get(r, 'field_error', 'frames'))} held out)",
            f"{get(r, 'matcher')}, {get(r, 'odometry')}", setting,
            pair(mm(get(run, "field_sigma_m")), _deg(get(run, "field_sigma_rad"))), _farthest(r, run),
            _int(get(run, "corrections")), num(get(run, "nees_mean"), 1), _range(band[0], band[-1]),
            pair(num(get(run, "nees_median"), 1), num(get(run, "nees_p90"), 1)), _pct(get(run, "within_chi2_997")),
            pair(cm(get(run, "ate_estimate_m")), cm(get(run, "ate_causal_m"))),
            _frac(get(run, "accepted"), get(run, "keyframes"))]


def nees_table() -> str:
    """The corrections' NEES with the field's measured error (and its growth), near-frame error
    only, and the field taken as exact: one row per file and setting."""
    header = ["file", "field (held-out frames)", "matcher, odometry", "setting", "field's error mm / deg",
              "growth: farthest gap m / error there mm", "corrections", "NEES mean", "95% band of the mean",
              "NEES median / p90", "within the 99.7% gate %", "ATE cm / causal", "accepted"]
    rows = []
    for name in FIELD_ERROR_FILES:
        r = load(name)
        rows += [_nees_row(name, r, setting, run) for setting, run in _dict(r, "runs").items()]
    return table(header, rows)


# --- training-pose refinement ----------------------------------------------------------------

def _refinement_cells(f: dict) -> list[str]:
    """How a field's training poses were refined: method, input sigma, agreement, last correction."""
    pr = get(f, "pose_refinement")
    if pr is None:
        return ["none", NA, NA, num(get(f, "timing_agreement_mm")), NA]
    sigma_m = _first(get(pr, "input_sigma_m"), get(pr, "config", "input_sigma_m"))
    sigma_rad = _first(get(pr, "input_sigma_rad"), get(pr, "config", "input_sigma_rad"))
    last = _dict(pr, "rounds", -1)
    return [f"{get(pr, 'method')}, {len(_list(pr, 'rounds'))} rounds", pair(mm(sigma_m), _deg(sigma_rad)),
            num(get(pr, "seconds"), 0), num(get(pr, "agreement_after_mm")),
            pair(num(get(last, "median_correction_mm"), 1), num(get(last, "median_correction_deg")))]


def pose_refinement_table() -> str:
    """Training-pose refinement: one row per file, refinement and odometry."""
    header = ["file", "field, matcher", "refinement", "input poses' sigma mm / deg", "refinement s",
              "depth agreement mm", "last round's median correction mm / deg", "held-out PSNR dB", "odometry",
              "ATE cm / max", "causal cm", "accepted"]
    rows = []
    for name in POSE_REFINEMENT_FILES:
        r = load(name)
        for f in _dict(r, "fields").values():
            for odom, run in _dict(f, "runs").items():
                rows.append([_code(name), f"{get(r, 'model')}, {get(r, 'matcher')}"] + _refinement_cells(f)
                            + [num(get(f, "held_out_psnr_db")), odom,
                               pair(cm(get(run, "ate_estimate_m")), cm(get(run, "ate_estimate_max_m"), 1)),
                               cm(get(run, "ate_causal_m")), _frac(get(run, "accepted"), get(run, "keyframes"))])
    return table(header, rows)


# --- held-out frames: colour and registration ------------------------------------------------

def _median_range(summary: dict, key: str, digits: int = 1) -> list[str]:
    """Median and range (over the held-out frames) of one figure."""
    s = _dict(summary, key)
    return [num(get(s, "median"), digits), _range(get(s, "min"), get(s, "max"), lambda v: num(v, digits))]


def registration_table() -> str:
    """Each field's held-out PSNR and how far its texture sits from the image's (optical flow)."""
    header = ["file", "field", "frames, render px", "PSNR dB median", "range", "over rendered pixels dB", "range",
              "flow px median", "range", "flow p90 px median", "flow-warped PSNR dB", "range"]
    name = "field_registration_fr1_desk.json"
    r = load(name)
    size = "x".join(str(v) for v in _list(r, "render_size")) or NA
    rows = []
    for field, f in _dict(r, "fields").items():
        s = _dict(f, "summary")
        label = _field_label(get(f, "field"))
        label = label if label.startswith(field) else f"{field} ({label})"
        rows.append([_code(name), label, f"{len(_list(f, 'frames'))}, {size}"]
                    + _median_range(s, "psnr_db") + _median_range(s, "psnr_opaque_db")
                    + _median_range(s, "flow_px_median", 2) + [num(get(s, "flow_px_p90", "median"), 1)]
                    + _median_range(s, "psnr_flow_warped_db"))
    return table(header, rows)


# --- field types -----------------------------------------------------------------------------

def field_models_table() -> str:
    """Each field type, each second-half keyframe measured from a perturbed render of it."""
    header = ["file", "field", "perturbation", "keyframes (failed)", "translation mm median / p90", "max mm",
              "rotation deg median / p90", "median inliers", "render ms", "held-out PSNR dB", "own error mm / deg",
              "lag-1 correlation", "nearest view m", "build s"]
    rows = []
    for name in FIELD_MODELS_FILES:
        r = load(name)
        for f in _dict(r, "fields").values():
            t, rot = _dict(f, "translation_mm"), _dict(f, "rotation_deg")
            rows.append([_code(name), _field_label(get(f, "field")), str(_first(get(r, "perturbation"), NA)),
                         f"{_int(get(f, 'frames'))} ({_int(get(f, 'failed'))})",
                         pair(num(get(t, "median"), 1), num(get(t, "p90"), 1)), num(get(t, "max"), 1),
                         pair(num(get(rot, "median")), num(get(rot, "p90"))), num(get(f, "inliers_median"), 1),
                         num(get(f, "render_ms_median"), 0), num(get(f, "held_out_psnr_db")),
                         pair(mm(get(f, "field_error", "sigma_m")), _deg(get(f, "field_error", "sigma_rad"))),
                         num(get(f, "lag1_correlation")), num(get(f, "nearest_view_gap_m_median")),
                         num(get(f, "build_seconds"), 0)])
    return table(header, rows)


# --- the correction floor --------------------------------------------------------------------

def _floor_maps(r: dict) -> list[tuple[str, dict]]:
    """(label, record) of each map the test frames were aligned to, the ``--field`` first."""
    main = _field_label(get(r, "field"))
    labels = {"composite": f"{main} (--field)", "composite_no_shutter": f"{main}, rolling shutter not undone"}
    for spec in _list(r, "also_fields"):
        key, _, path = str(spec).partition("=")
        labels[f"field:{key}"] = f"{_field_label(path)} (--also-field)"
    at = {k: v for k, v in _dict(r, "at_true_pose").items() if k != "views_alone"}
    order = [k for k in ("composite", "composite_no_shutter") if k in at] + [k for k in at if not k.startswith("comp")]
    return [(labels.get(k, k), at[k]) for k in order]


def _floor_row(name: str, r: dict, label: str, e: dict) -> list[str]:
    """One map's (or real training frames') translation errors at the true pose."""
    t = _dict(e, "translation_mm")
    fast, slow = get(e, "fast_translation_mm", "median"), get(e, "slow_translation_mm", "median")
    corr = get(e, "shared_with_composite", "correlation_xyz")
    return [_code(name), f"{_int(get(r, 'step'))}, {get(r, 'matcher')}",
            pair(ms(get(r, "readout_s"), 0), num(get(r, "fast_above_m_per_s"), 1)), label, _int(get(t, "n")),
            pair(num(get(t, "median"), 1), num(get(t, "p90"), 1)), num(get(t, "rms"), 1), num(get(t, "max"), 1),
            num(get(e, "rotation_deg", "median")), NA if fast is None else pair(num(fast, 1), num(slow, 1)),
            NA if not corr else _range(min(corr), max(corr)),
            _pct(get(e, "shared_with_composite", "share_of_power_in_common")), num(get(e, "rms_if_independent"), 1)]


def _floor_alone_rows(name: str, r: dict) -> list[list[str]]:
    """Each test frame aligned to its nearest real training frames, one at a time and averaged."""
    alone = _dict(r, "at_true_pose", "views_alone")
    mean = {"translation_mm": get(alone, "mean_of_views_translation_mm"),
            "shared_with_composite": {"share_of_power_in_common": get(alone, "shared_share_of_error_power")},
            "rms_if_independent": get(alone, "mean_of_views_rms_if_independent_mm")}
    return [_floor_row(name, r, "one training frame alone", {"translation_mm": get(alone, "single_translation_mm")}),
            _floor_row(name, r, f"mean of the {num(get(alone, 'views_per_frame'), 0)} nearest training frames", mean)]


def floor_table() -> str:
    """Test frames aligned at their ground-truth pose to each map, and to real training frames alone."""
    header = ["file", "test frames every, matcher", "readout ms / fast above m/s", "aligned to", "frames",
              "translation mm median / p90", "rms mm", "max mm", "rotation deg median", "fast / slow frames median mm",
              "correlation with --field's error per axis", "error power in common %", "rms were they independent mm"]
    rows = []
    for name in FLOOR_FILES:
        r = load(name)
        rows += [_floor_row(name, r, label, e) for label, e in _floor_maps(r)] + _floor_alone_rows(name, r)
    return table(header, rows)


def floor_runs_table() -> str:
    """Whole runs with the ``--field`` and denser keyframes."""
    header = ["file", "field", "keyframe every", "odometry ATE cm", "ATE cm / median", "max cm", "causal cm",
              "accepted", "s"]
    rows = []
    for name in FLOOR_FILES:
        r = load(name)
        for run in _list(r, "runs"):
            rows.append([_code(name), _field_label(get(r, "field")), _int(get(run, "keyframe_every")),
                         cm(get(run, "ate_odometry_m")), pair(cm(get(run, "ate_m")), cm(get(run, "ate_median_m"))),
                         cm(get(run, "ate_max_m"), 1), cm(get(run, "ate_causal_m")),
                         _frac(get(run, "accepted"), get(run, "keyframes")), num(get(run, "seconds"), 0)])
    return table(header, rows)


# --- the ground truth against itself ---------------------------------------------------------

def _cosines(r: dict) -> str:
    """Median cosine between these errors and each field's, per field."""
    against = _dict(r, "against_fields")
    return "; ".join(f"{k} {num(get(v, 'median_cosine'))}" for k, v in against.items()) or NA


def _gt_rows(name: str, r: dict) -> list[list[str]]:
    """The second half against the first half's nearest real frames, then within one half by gap."""
    t = _dict(r, "translation_mm")
    label = f"first half's {_int(get(r, 'nearest'))} nearest frames (one frame in {_int(get(r, 'step'))})"
    rows = [[_code(name), label,
             f"{_int(get(r, 'measured'))} ({_int(get(r, 'failed'))})", num(get(r, "gap_m_median")), NA,
             pair(num(get(t, "median"), 1), num(get(t, "p90"), 1)), num(get(t, "max"), 1),
             num(get(r, "rotation_deg_median")), NA, _cosines(r)]]
    bb = _dict(r, "by_baseline")
    offsets = ", ".join(str(o) for o in _list(bb, "offsets"))
    for b in _list(bb, "bins"):
        gap = _list(b, "gap_m") or [None, None]
        rows.append([_code(name), f"second-half frames {offsets} apart", f"{_int(get(b, 'pairs'))} pairs",
                     _range(gap[0], gap[-1]), num(get(b, "baseline_m_median"), 3),
                     pair(num(get(b, "translation_mm_median"), 1), num(get(b, "translation_mm_p90"), 1)), NA,
                     num(get(b, "rotation_deg_median")), num(get(b, "inliers_median"), 0), NA])
    return rows


def ground_truth_table() -> str:
    """Real frames measured against real frames at their recorded poses (no map between them)."""
    header = ["file", "measured against", "frames (failed)", "gap m", "baseline m median",
              "translation mm median / p90", "max mm", "rotation deg median", "median inliers",
              "median cosine with each field's error"]
    rows = []
    for name in GT_FILES:
        rows += _gt_rows(name, load(name))
    return table(header, rows)


# --- feature odometry width ------------------------------------------------------------------

def _paced_cells(p) -> list[str]:
    """Fed at the camera's rate: how far behind, frames late, causal ATE."""
    if not p:
        return [NA, NA, NA]
    return [pair(ms(get(p, "behind_camera_s", "p90"), 0), ms(get(p, "behind_camera_s", "max"), 0)),
            _int(get(p, "frames_over_a_period_late")), cm(get(p, "ate_causal_m"))]


def vo_width_table() -> str:
    """The feature odometry at the render's width against the frames as read, per matcher."""
    header = ["file", "field", "matcher", "odometry width px", "odometry step ms median / p90",
              "odometry alone ATE cm", "frame/s inline / overlapped", "inline x as read", "ATE cm",
              "causal cm inline / overlapped", "accepted", "paced: behind ms p90 / max", "paced: frames late",
              "paced: causal cm"]
    rows = []
    for name in VO_WIDTH_FILES:
        r = load(name)
        for run in _list(r, "runs"):
            alone, inline, over = _dict(run, "odometry_alone"), _dict(run, "inline"), _dict(run, "overlapped")
            rows.append([_code(name), _field_label(get(r, "field")), str(get(run, "matcher")),
                         "as read" if get(run, "vo_width") is None else str(get(run, "vo_width")),
                         pair(num(get(alone, "step_ms", "median"), 0), num(get(alone, "step_ms", "p90"), 0)),
                         cm(get(alone, "ate_m")),
                         pair(num(get(inline, "frames_per_s"), 1), num(get(over, "frames_per_s"), 1)),
                         num(get(inline, "frames_per_s_vs_as_read")), cm(get(inline, "ate_m")),
                         pair(cm(get(inline, "ate_causal_m")), cm(get(over, "ate_causal_m"))),
                         _frac(get(inline, "accepted"), get(inline, "keyframes"))]
                        + _paced_cells(get(run, "paced")))
    return table(header, rows)


# --- rolling shutter -------------------------------------------------------------------------

def _readout(run: dict) -> str:
    """The readout asked for and the one the run used, ms."""
    used = ms(_first(get(run, "readout_used_s"), get(run, "readout_s")), 0)
    return f"auto: {used}" if get(run, "readout_s") is None else used


def rolling_shutter_table() -> str:
    """Each field and odometry with the readout off and on."""
    header = ["file", "field", "odometry, matcher", "readout ms", "odometry ATE cm", "ATE cm / causal", "accepted",
              "keyframe error mm median / p90", "fast / slow half median mm", "NEES mean", "95% band of the mean",
              "NEES median"]
    rows = []
    for name in SHUTTER_FILES:
        for run in _dict(load(name), "runs").values():
            ke, band = _dict(run, "keyframe_error_mm"), _list(run, "nees_band_95") or [None, None]
            rows.append([_code(name), _field_label(get(run, "field")),
                         f"{get(run, 'odometry')}, {get(run, 'matcher')}", _readout(run),
                         cm(get(run, "ate_odometry_m")),
                         pair(cm(get(run, "ate_estimate_m")), cm(get(run, "ate_causal_m"))),
                         _frac(get(run, "accepted"), get(run, "keyframes")),
                         pair(num(get(ke, "median"), 1), num(get(ke, "p90"), 1)),
                         pair(num(get(ke, "fast_half_median"), 1), num(get(ke, "slow_half_median"), 1)),
                         num(get(run, "nees_mean"), 1), _range(band[0], band[-1]), num(get(run, "nees_median"), 1)])
    return table(header, rows)


# --- intrinsics tracker ----------------------------------------------------------------------

def _tracker_row(s: dict) -> list[str]:
    """One setting, settled on the given intrinsics against fitting both models at every keyframe."""
    recording, _, rest = str(_first(get(s, "setting"), "")).partition(":")
    field, odom, matcher = (rest.rsplit(":", 2) + [NA, NA])[:3]
    t, b = _dict(s, "tracked"), _dict(s, "both_always")
    return [_code("intrinsics_tracker.json"), recording, _field_label(field), f"{odom}, {matcher}",
            pair(_int(get(t, "check_every")), _int(get(b, "check_every"))),
            "yes" if get(s, "same_trajectory") else "no",
            pair(cm(get(t, "ate_m")), cm(get(b, "ate_m"))),
            pair(cm(get(t, "ate_causal_m")), cm(get(b, "ate_causal_m"))),
            f"{pair(_int(get(t, 'accepted')), _int(get(b, 'accepted')))} of {_int(get(t, 'keyframes'))}",
            pair(num(get(t, "measure_ms_median"), 1), num(get(b, "measure_ms_median"), 1)),
            pair(num(get(t, "measure_ms_p90"), 1), num(get(b, "measure_ms_p90"), 1)),
            _int(get(t, "fixed_only")), pair(_int(get(t, "calibrated")), _int(get(b, "calibrated")))]


def intrinsics_table() -> str:
    """Settled (``tracked``) against both camera models at every keyframe (``both``), per setting."""
    header = ["file", "recording", "field", "odometry, matcher", "check every: tracked / both", "same trajectory",
              "ATE cm tracked / both", "causal cm tracked / both", "accepted tracked / both",
              "measurement ms median tracked / both", "p90 tracked / both", "keyframes fitting the given camera alone",
              "self-calibrated chosen tracked / both"]
    return table(header, [_tracker_row(s) for s in _list(load("intrinsics_tracker.json"), "settings")])


# --- sweeps ----------------------------------------------------------------------------------

def _sweep_rows(folder: str) -> list[list[str]]:
    """A sweep's cells as its ``sweep.csv`` lists them, with its summary's cell counts."""
    summary = load(f"{folder}/summary.json")
    counts = f"{_int(get(summary, 'ok'))}/{_int(get(summary, 'cells'))} ({_int(get(summary, 'failed'))} failed)"
    rows = []
    for c in _csv(f"{folder}/sweep.csv"):
        command = _first(get(c, "command"), "")
        rows.append([_code(f"{folder}/sweep.csv"), counts, get(c, "recording") or NA,
                     _field_label(_opt(command, "--field")), f"{_opt(command, '--matcher')}, {_opt(command, '--odom')}",
                     get(c, "status") or NA, _cm_of(_float(get(c, "ate_odometry_cm"))),
                     _cm_of(_float(get(c, "ate_estimate_cm"))), _cm_of(_float(get(c, "ate_causal_cm"))),
                     _cm_of(_float(get(c, "ate_estimate_max_cm")), 1),
                     _frac(get(c, "accepted"), get(c, "keyframes")), num(_float(get(c, "seconds")), 0)])
    return rows


def sweeps_table() -> str:
    """Every cell of the sweeps over the real recordings."""
    header = ["file", "cells ok (failed)", "recording", "field", "matcher, odometry", "status", "odometry ATE cm",
              "ATE cm", "causal cm", "max cm", "accepted", "s"]
    return table(header, [row for folder in SWEEPS for row in _sweep_rows(folder)])


# --- sections --------------------------------------------------------------------------------

SECTIONS: list[Section] = [
    Section(
        "Matchers and keyframe selection, fr1/desk (splat field of `sweep_fields`, second half corrected)",
        ("matchers_fr1_desk.json", "keyframes_fr1_desk.json"),
        "python benchmarks/matchers_desk.py --field S; python benchmarks/keyframes_desk.py --field S",
        matchers_table,
        "The odometry matches with the run's matcher, so its ATE differs between matchers. A window picks the "
        "sharpest frame near a due keyframe; keyframes on doubt follow the odometry losing track."),
    Section(
        "The study: field on the first half, second half corrected",
        tuple(f"{f}/{part}" for f in STUDIES for part in ("summary.json", "field_report.json")),
        "nap3d-graph study DATA --matcher sift; nap3d-graph study DATA --model views --matcher xfeat --odom vo,dense; "
        "nap3d-graph study DATA --model splat --matcher xfeat --scenarios 20",
        study_table,
        "Training steps are those a grid records (a splat or view field has none). Columns over the runs follow "
        "the odometries' order. Held-out frames are scored where the image holds colour data."),
    Section(
        "Evaluation K on the study fields",
        tuple(f"{f}/summary.json" for f in STUDIES),
        "nap3d-graph study ... (its eval_k step)",
        eval_k_table,
        "A failure scores the uncorrected pose. `-selfcal` estimators also fit the camera's intrinsics."),
    Section(
        "Corrections' NEES with the field's measured error, its growth, and the field taken as exact",
        FIELD_ERROR_FILES,
        "python benchmarks/field_error_desk.py [--data D] [--field S|V|G] --out ...",
        nees_table,
        "The band is where the mean NEES of that many corrections falls for a consistent covariance; the growth "
        "column is the error at the farthest gap from the field's frames that `train-field` measured."),
    Section(
        "Training-pose refinement, fr1/desk",
        POSE_REFINEMENT_FILES,
        "python benchmarks/pose_refinement_desk.py; python benchmarks/pose_refinement_desk.py --model views "
        "--methods depth map --odom vo dense --out ...",
        pose_refinement_table,
        "Depth agreement is the training frames' multi-view agreement with the poses as used; the held-out frames "
        "keep their motion-capture poses."),
    Section(
        "Held-out PSNR and registration of the fields, fr1/desk",
        ("field_registration_fr1_desk.json",),
        "python benchmarks/field_registration_desk.py --field views=V --field splat=S --field grid=G",
        registration_table,
        "Per-frame medians and ranges over the held-out frames of the training half; the flow is dense optical "
        "flow from the render to the image, and the flow-warped PSNR scores the render moved by it."),
    Section(
        "Field types: each second-half keyframe measured from a perturbed render",
        FIELD_MODELS_FILES,
        "python benchmarks/field_models.py --data D --field views=V --field splat=S --field grid=G --out ...",
        field_models_table,
        "The nearest-view gap is recorded for view fields only."),
    Section(
        "What one correction can reach: test frames aligned at their ground-truth pose",
        FLOOR_FILES,
        "python benchmarks/correction_floor.py --field V --also-field grid=G --also-field splat=S "
        "[--data D --out ...]",
        floor_table,
        "Fast frames are those above the speed threshold the file records. Training frames alone are each test "
        "frame's nearest real frames of the first half, at their recorded poses."),
    Section(
        "Denser keyframes with the view field",
        FLOOR_FILES,
        "python benchmarks/correction_floor.py --field V ... [--keyframe-every 1 2 5]",
        floor_runs_table),
    Section(
        "The recordings' ground truth against itself",
        GT_FILES,
        "python benchmarks/ground_truth_consistency.py --data D --field VIEWS.pt --compare field_models_*.json "
        "--by-baseline OFFSETS",
        ground_truth_table,
        "No map between the frames: each is aligned to real frames at their recorded poses. The first row of a "
        "file is the second half against the first; the others stay within the second half, binned by gap "
        "(camera plus viewing-centre distance)."),
    Section(
        "Feature odometry at the render's width",
        VO_WIDTH_FILES,
        "python benchmarks/vo_width.py --field V --paced; python benchmarks/vo_width.py --data D --field G --out ...",
        vo_width_table,
        "Whole runs as fast as they go; paced runs are fed at the camera's rate, overlapped, landing within a "
        "frame."),
    Section(
        "Rolling-shutter readout",
        SHUTTER_FILES,
        "python benchmarks/rolling_shutter.py --data D --field views=V --field grid=G --field splat=S "
        "--readout 0 auto; redkitchen: --readout 0 0.033",
        rolling_shutter_table,
        "`auto` takes the readout `train-field` estimated; keyframe error is each keyframe's own error against "
        "the ground truth."),
    Section(
        "Settling on the given intrinsics",
        ("intrinsics_tracker.json",),
        "python benchmarks/intrinsics_tracker.py --setting NAME:FIELD:ODOM:MATCHER ...",
        intrinsics_table,
        "Each setting run with `intrinsics_check_every` as tracked, then reproduced fitting both camera models "
        "at every keyframe."),
    Section(
        "Sweeps over the real recordings",
        tuple(f"{f}/{part}" for f in SWEEPS for part in ("summary.json", "sweep.csv")),
        "nap3d-graph sweep benchmarks/NAME.yaml --out benchmarks/results/NAME "
        "(NAME: sweep_real, sweep_fields, sweep_grid_seeds)",
        sweeps_table,
        "Each cell's field is built on the recording's first half and its second half corrected; one run seed "
        "(visual odometry draws no noise)."),
]
