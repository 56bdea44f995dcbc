"""Simulated rooms, speed, faults and estimators: the sections of ``docs/results.md`` read from the
benchmarks' result files (``benchmarks/results/``). Every figure comes out of its file; a key a
file lacks reads ``n/a``, and so does every figure of a missing file.
"""

from __future__ import annotations

import math

from report import Section, cm, get, load, mm, num, table

# --- reading and formatting ------------------------------------------------------------------


def _read(name: str) -> dict:
    """The parsed JSON of ``benchmarks/results/<name>``, or an empty dict where it is missing."""
    try:
        return load(name)
    except FileNotFoundError:
        return {}


def _x(data, *keys) -> float | None:
    """A number at ``keys`` (booleans excepted), or None where it is missing or not finite."""
    value = get(data, *keys)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return value


def _ms(seconds, digits: int = 1) -> str:
    """Seconds as milliseconds."""
    return "n/a" if seconds is None else f"{seconds * 1000:.{digits}f}"


def _int(value) -> str:
    """A count, ``n/a`` where missing."""
    return "n/a" if value is None else f"{value:.0f}"


def _pct(fraction) -> str:
    """A fraction as a whole percentage."""
    return "n/a" if fraction is None else f"{fraction * 100:.0f}%"


def _frac(part, whole) -> str:
    """``part/whole``, ``n/a`` where either is missing."""
    return "n/a" if part is None or whole is None else f"{part:.0f}/{whole:.0f}"


def _span(low, high, fmt=num) -> str:
    """``low-high`` through ``fmt``; one value where both read the same; ``n/a`` where either is missing."""
    if low is None or high is None:
        return "n/a"
    a, b = fmt(low), fmt(high)
    return a if a == b else f"{a}-{b}"


def _list_span(values, fmt=num) -> str:
    """The range of the numbers in ``values`` (a list), ``n/a`` where there is none."""
    numbers = [v for v in (values or []) if _x([v], 0) is not None]
    return _span(min(numbers), max(numbers), fmt) if numbers else "n/a"


def _pair(a: str, b: str) -> str:
    """Two formatted figures of one cell."""
    return f"{a} / {b}"


def _signed_pct(fraction, digits: int = 3) -> str:
    """A signed fraction as a percentage."""
    return "n/a" if fraction is None else f"{fraction * 100:+.{digits}f}%"


def _yes(flag) -> str:
    """A flag in words."""
    return "n/a" if flag is None else ("yes" if flag else "no")


# --- drift removal on simulated rooms ------------------------------------------------------------

DRIFT_FILES = ("default_run.json", "drift_rooms.json", "drift_rooms_views.json")
DRIFT_HEADER = ["run (file)", "field", "train steps", "field s (first run)", "cached run s", "held-out PSNR dB",
                "ATE cm", "causal ATE cm", "max error cm", "odometry alone cm", "exact field ATE cm", "accepted",
                "ms per keyframe", "render ms"]


def _default_run_row() -> list[str]:
    """The embedded default (`nap3d-graph run`): its first run builds the field, the second finds it cached."""
    name = "default_run.json"
    r = _read(name)
    return [f"embedded default `{name}`", "embedded default", "n/a", num(_x(r, "first_run_s"), 0),
            num(_x(r, "cached_run_s"), 1), "n/a", cm(_x(r, "ate_estimate_m")), cm(_x(r, "ate_causal_m")),
            cm(_x(r, "ate_estimate_max_m")), cm(_x(r, "ate_odometry_m")), "-",
            _frac(_x(r, "corrections_accepted"), _x(r, "keyframes")),
            _ms(_x(r, "seconds_per_keyframe", "total_per_keyframe")), _ms(_x(r, "seconds_per_keyframe", "render"))]


def _drift_room_rows(name: str) -> list[list[str]]:
    """One row per hold-out room: the trained field's run beside the exact field's."""
    d = _read(name)
    model, steps = get(d, "model") or "n/a", _int(_x(d, "train_steps"))
    rows = []
    for room, r in (get(d, "per_room") or {}).items():
        t = get(r, "trained") or {}
        rows.append([f"room {room} `{name}`", model, steps, num(_x(r, "field_seconds"), 0), "-",
                     num(_x(r, "field_held_out", "psnr_db"), 1), cm(_x(t, "ate_estimate_m")),
                     cm(_x(t, "ate_causal_m")), cm(_x(t, "ate_estimate_max_m")), cm(_x(t, "ate_odometry_m")),
                     cm(_x(r, "oracle", "ate_estimate_m")), _frac(_x(t, "accepted"), _x(t, "keyframes")),
                     _ms(_x(t, "seconds_per_keyframe"), 0), "n/a"])
    return rows


def _drift_pooled_rows(name: str) -> list[list[str]]:
    """The file's pooled figures over its rooms: the mean, then the range."""
    d = _read(name)
    p, o = get(d, "pooled", "trained") or {}, get(d, "pooled", "oracle") or {}
    model, steps = get(d, "model") or "n/a", _int(_x(d, "train_steps"))
    keys = ("ate_estimate_m", "ate_causal_m", "ate_estimate_max_m", "ate_odometry_m")
    mean = [cm(_x(p, k, "mean")) for k in keys] + [cm(_x(o, "ate_estimate_m", "mean"))]
    spread = [_span(_x(p, k, "min"), _x(p, k, "max"), cm) for k in keys]
    spread += [_span(_x(o, "ate_estimate_m", "min"), _x(o, "ate_estimate_m", "max"), cm)]
    return [[f"rooms, mean `{name}`", model, steps, "-", "-", "-", *mean, _pct(_x(p, "accepted_fraction")),
             _ms(_x(p, "seconds_per_keyframe", "mean"), 0), "n/a"],
            [f"rooms, min-max `{name}`", model, steps, "-", "-", "-", *spread, "-",
             _span(_x(p, "seconds_per_keyframe", "min"), _x(p, "seconds_per_keyframe", "max"),
                   lambda s: _ms(s, 0)), "n/a"]]


def drift_table() -> str:
    """The embedded default and the hold-out rooms, trained field (grid, views) against the exact room."""
    rows = [_default_run_row()]
    for name in DRIFT_FILES[1:]:
        rows += _drift_room_rows(name) + _drift_pooled_rows(name)
    return table(DRIFT_HEADER, rows)


# --- the field's error and its growth on the rooms -------------------------------------------------

GROWTH_HEADER = ["room (file)", "train steps", "field error mm / deg", "held-out frames / failed",
                 "error at the farthest gap mm (gap m)", "NEES mean: near / growth", "NEES median: near / growth",
                 "band of the mean", "ATE cm: near / growth", "causal cm: near / growth", "accepted: near / growth"]


def _growth_row(name: str, room: str, r: dict, steps: str) -> list[str]:
    """One room: its error near the frames used everywhere ('near') against its growth with the gap."""
    fe, near, grow, g = (get(r, k) or {} for k in ("field_error", "near_frames_everywhere", "with_growth", "growth"))
    rad = _x(fe, "sigma_rad")
    deg = num(None if rad is None else math.degrees(rad))
    return [f"room {room} `{name}`", steps, _pair(mm(_x(fe, "sigma_m")), deg),
            _pair(_int(_x(fe, "frames")), _int(_x(fe, "failed"))),
            f"{mm(_x(g, 'sigma_m', -1))} ({num(_x(g, 'gap_m', -1))})",
            _pair(num(_x(near, "nees_mean")), num(_x(grow, "nees_mean"))),
            _pair(num(_x(near, "nees_median")), num(_x(grow, "nees_median"))),
            _span(_x(near, "nees_band_95", 0), _x(near, "nees_band_95", 1)),
            _pair(cm(_x(near, "ate_estimate_m")), cm(_x(grow, "ate_estimate_m"))),
            _pair(cm(_x(near, "ate_causal_m")), cm(_x(grow, "ate_causal_m"))),
            f"{_pair(_int(_x(near, 'accepted')), _int(_x(grow, 'accepted')))} of {_int(_x(near, 'keyframes'))}"]


def growth_table() -> str:
    """Per hold-out room: the grid field's measured error, and the corrections' NEES without and with its growth."""
    name = "error_growth_rooms.json"
    d = _read(name)
    steps = _int(_x(d, "train_steps"))
    return table(GROWTH_HEADER, [_growth_row(name, room, r, steps) for room, r in (get(d, "per_room") or {}).items()])


# --- covariance honesty ------------------------------------------------------------------------------

COVARIANCE_FILES = ("covariance.json", "covariance_xfeat.json")
COVARIANCE_HEADER = ["setting (file)", "matcher", "render px", "perturbation cm / deg", "rounds", "trials / skipped",
                     "pose NEES", "rooms min-max", "band of the mean", "rotation / translation NEES", "3-dof band",
                     "median translation error mm, rooms min-max"]


def _covariance_row(name: str, d: dict, key: str) -> list[str]:
    """One setting/method of a covariance file, pooled over its rooms."""
    p, rooms = get(d, "pooled", key) or {}, (get(d, "per_room", key) or {}).values()
    s = get(p, "settings") or {}
    size = get(s, "size") or []
    trials = [_x(r, "trials") for r in rooms]
    skipped = [_x(r, "failures_skipped") for r in rooms]
    errors = [_x(r, "trans_err_median_mm") for r in rooms]
    total = None if None in trials or not trials else sum(trials)
    lost = None if None in skipped or not skipped else sum(skipped)
    return [f"{key} `{name}`", get(d, "matcher") or "sift (the script's default)",
            "x".join(str(v) for v in size) or "n/a", _pair(cm(_x(s, "max_trans_m"), 0), num(_x(s, "max_rot_deg"), 1)),
            _int(_x(s, "rounds")), _pair(_int(total), _int(lost)), num(_x(p, "mean", "pose")),
            _span(_x(p, "room_min_max", "pose", 0), _x(p, "room_min_max", "pose", 1)),
            _span(_x(p, "band_95", "pose", 0), _x(p, "band_95", "pose", 1)),
            _pair(num(_x(p, "mean", "rotation")), num(_x(p, "mean", "translation"))),
            _span(_x(p, "band_95", "rotation", 0), _x(p, "band_95", "rotation", 1)), _list_span(errors)]


def covariance_table() -> str:
    """Every setting of both covariance files (exact field, hold-out rooms)."""
    rows = []
    for name in COVARIANCE_FILES:
        d = _read(name)
        rows += [_covariance_row(name, d, key) for key in (get(d, "pooled") or {})]
    return table(COVARIANCE_HEADER, rows)


# --- every estimator on the same corrections --------------------------------------------------------

ESTIMATORS = ("odometry", "eskf", "navstate-ekf", "isam2-causal", "isam2-final", "batch-lm")
COMPARE_FOLDERS = ("compare_default_odometry", "compare_default_imu", "compare_fr1_desk_vo", "compare_fr1_desk_noisy",
                   "compare_fr1_desk_vo_field_sigma_0.02")
ESTIMATOR_FILES = ("compare_rooms.json", *(f"{f}/comparison.json" for f in COMPARE_FOLDERS), "nees_question.json")
ESTIMATOR_HEADER = ["source (file)", "figure", "reference run", *ESTIMATORS]


def _pooled_rows(name: str, path: str, d: dict) -> list[list[str]]:
    """compare_rooms.json, one path: pooled over its sequences (mean, then range) and the reference runs."""
    seqs = get(d, "paths", path, "per_sequence") or {}
    p = get(d, "paths", path, "pooled") or {}
    label = f"{path} path, {len(seqs)} sequences `{name}`"
    taken = _frac(sum(_x(s, "corrections") or 0 for s in seqs.values()),
                  sum(_x(s, "keyframes") or 0 for s in seqs.values())) if seqs else "n/a"

    def row(figure, ref, cell):
        """One figure of every estimator."""
        return [label, figure, ref, *(cell(get(p, e)) if get(p, e) else "-" for e in ESTIMATORS)]

    return [row("ATE cm, mean", taken, lambda e: cm(_x(e, "ate_rmse_m", "mean"))),
            row("ATE cm, min-max", "-", lambda e: _span(_x(e, "ate_rmse_m", "min"), _x(e, "ate_rmse_m", "max"), cm)),
            row("max error cm, mean", "-", lambda e: cm(_x(e, "ate_max_m", "mean"))),
            row("NEES, mean", "-", lambda e: num(_x(e, "nees_mean", "mean"), 1)),
            row("NEES, min-max", "-", lambda e: _span(_x(e, "nees_mean", "min"), _x(e, "nees_mean", "max"),
                                                      lambda v: num(v, 1))),
            row("ms per step, mean", "-", lambda e: num(_x(e, "step_ms_mean", "mean"), 3)),
            [label, "sequences with ATE at or below the ESKF's", _bias_cell(p),
             *(_at_or_below(seqs, e) for e in ESTIMATORS)]]


def _bias_cell(pooled: dict) -> str:
    """IMU path: how many reference runs ended with every bias within 3 sigma of the truth (the largest, sigma)."""
    b = get(pooled, "bias_abs_z_final")
    if b is None:
        return "-"
    return f"bias within 3 sigma {_frac(_x(b, 'within_3_sigma'), _x(b, 'sequences'))} (max {num(_x(b, 'max'), 1)})"


def _at_or_below(seqs: dict, estimator: str) -> str:
    """In how many sequences ``estimator``'s ATE is at or below the error-state EKF's."""
    pairs = [(_x(s, "rows", estimator, "ate_rmse_m"), _x(s, "rows", "eskf", "ate_rmse_m")) for s in seqs.values()]
    pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
    if estimator == "eskf" or not pairs:
        return "-"
    return _frac(sum(a <= b for a, b in pairs), len(pairs))


def _comparison_rows(folder: str) -> list[list[str]]:
    """One ``compare`` folder: ATE (max), NEES and corrections taken per estimator."""
    name = f"{folder}/comparison.json"
    d = _read(name)
    rows = {r.get("estimator"): r for r in get(d, "rows") or []}
    src = get(d, "source")
    settings = [f"--odom {get(src, 'odometry')}"] if isinstance(src, dict) else []
    if _x(src, "pipeline", "field_sigma_m") is not None:
        settings.append(f"--field-sigma {_x(src, 'pipeline', 'field_sigma_m')}")
    label = f"{get(d, 'path') or 'n/a'} path{''.join(', ' + s for s in settings)} `{name}`"
    first = next(iter(rows.values()), {})
    band = _span(_x(first, "nees_band_low"), _x(first, "nees_band_high"))

    def row(figure, ref, cell):
        """One figure of every estimator."""
        return [label, figure, ref, *(cell(rows[e]) if e in rows else "-" for e in ESTIMATORS)]

    return [row("ATE cm (max)", "-", lambda r: f"{cm(_x(r, 'ate_rmse_m'))} ({cm(_x(r, 'ate_max_m'))})"),
            row(f"NEES mean (band {band})", "-", lambda r: num(_x(r, "nees_mean"), 1)),
            row("corrections taken", _frac(_x(d, "corrections_measured"), _x(d, "keyframes")),
                lambda r: _int(_x(r, "corrections_taken")))]


def _nees_question_rows() -> list[list[str]]:
    """nees_question.json: per odometry, the corrections' own NEES beside each estimator's."""
    name = "nees_question.json"
    d = _read(name)
    rows = []
    for odometry, o in (get(d, "odometries") or {}).items():
        est, c = get(o, "estimators") or {}, get(o, "corrections") or {}
        label = f"{odometry} odometry; {get(d, 'walk') or 'n/a'} `{name}`"
        band = _span(_x(next(iter(est.values()), {}), "band", 0), _x(next(iter(est.values()), {}), "band", 1))
        rows.append([label, "ATE cm", "-", *(cm(_x(est, e, "ate_rmse_m")) if e in est else "-" for e in ESTIMATORS)])
        rows.append([label, f"NEES mean (band {band})", num(_x(c, "nees_mean"), 1),
                     *(num(_x(est, e, "nees_mean"), 1) if e in est else "-" for e in ESTIMATORS)])
        axes = [_x(c, "whitened_std_per_axis", i) for i in range(6)]
        largest = max((a for a in axes if a is not None), default=None)
        rows.append([label, "corrections: NEES median / largest whitened sigma",
                     _pair(num(_x(c, "nees_median"), 1), num(largest)), *("-" for _ in ESTIMATORS)])
    return rows


def estimators_table() -> str:
    """compare_rooms' pooled figures, then each ``compare`` folder, then nees_question's walk."""
    d = _read("compare_rooms.json")
    rows = [r for path in (get(d, "paths") or {}) for r in _pooled_rows("compare_rooms.json", path, d)]
    rows += [r for folder in COMPARE_FOLDERS for r in _comparison_rows(folder)]
    return table(ESTIMATOR_HEADER, rows + _nees_question_rows())


# --- Evaluation K and J ---------------------------------------------------------------------------------


def _eval_k_table(name: str) -> str:
    """One Evaluation K summary: per blur x intrinsics cell, each method's median translation and success."""
    d = _read(name)
    c = get(d, "config") or {}
    methods = get(c, "methods") or list(get(d, "methods") or {})
    setting = (f"{_int(_x(c, 'scenarios'))} scenarios, +-{cm(_x(c, 'max_trans_m'), 0)} cm / "
               f"{num(_x(c, 'max_rot_deg'), 0)} deg, shift {get(c, 'shift') or 'n/a'}")
    header = [f"cell (file; {setting})", "blur sigma", "intrinsics (focal x, centre px)",
              *(f"{m}: median mm (success)" for m in methods),
              *(f"nap3d-selfcal beats {rival}: translation, rotation" for rival in _rivals(methods))]
    rows = []
    for cell, v in (get(d, "cells") or {}).items():
        level = get(v, "intrinsics") or "n/a"
        noise = get(c, "intrinsics_noise", level) or []
        ms = get(v, "methods") or {}
        cells = [f"{mm(_x(ms, m, 'trans_err_m', 'median'), 2)} ({_pct(_x(ms, m, 'success_rate'))})" for m in methods]
        rows.append([f"{cell} `{name}`", num(_x(v, "blur_sigma"), 1),
                     f"{level} ({num(_x(noise, 0))}, {num(_x(noise, 1), 0)})", *cells,
                     *(_selfcal_beats(ms, rival) for rival in _rivals(methods))])
    return table(header, rows)


def _rivals(methods: list) -> list[str]:
    """The PnP variants self-calibrating NAP3D is held against: the self-calibrating PnP, the
    one that always calibrates where the file has it, and the best PnP of each cell."""
    rivals = [m for m in ("pnp-selfcal", "pnp-calibrated") if m in methods]
    return rivals + (["the best PnP"] if len(rivals) > 1 else [])


def _median(methods: dict, rival: str, key: str):
    if rival != "the best PnP":
        return _x(methods, rival, key, "median")
    values = [_x(methods, m, key, "median") for m in methods if m.startswith("pnp")]
    values = [v for v in values if v is not None]
    return min(values) if values else None


def _selfcal_beats(methods: dict, rival: str = "pnp-selfcal") -> str:
    """Whether self-calibrating NAP3D's median translation and rotation are below ``rival``'s."""
    def below(key):
        """Self-calibrating NAP3D's median below the rival's (None where either is missing)."""
        a, b = _x(methods, "nap3d-selfcal", key, "median"), _median(methods, rival, key)
        return None if a is None or b is None else a < b

    return f"{_yes(below('trans_err_m'))}, {_yes(below('rot_err_deg'))}"


def eval_k_calibrated_table() -> str:
    """Evaluation K with the PnP that always calibrates beside the self-calibrating one."""
    return _eval_k_table("eval_k_oracle_room31_pnp_calibrated/summary.json")


def eval_k_real_table() -> str:
    """Evaluation K with the intrinsics shifted on the real camera."""
    return _eval_k_table("eval_k_oracle_room31/summary.json")


def eval_k_both_table() -> str:
    """Evaluation K with the intrinsics shifted on both cameras."""
    return _eval_k_table("eval_k_oracle_room31_shift_both/summary.json")


def eval_j_table() -> str:
    """Evaluation J: per sublocation and method, the RMSE along x and z, success and inliers."""
    name = "eval_j_oracle_room31/summary.json"
    rows = [[f"sublocation {sub} `{name}`", method, mm(_x(r, "rmse_x_m"), 2), mm(_x(r, "rmse_z_m"), 2),
             mm(_x(r, "rmse_m"), 2), _pct(_x(r, "success_rate")), _int(_x(r, "median_inliers"))]
            for sub, methods in _read(name).items() if isinstance(methods, dict)
            for method, r in methods.items()]
    return table(["sublocation (file)", "method", "RMSE x mm", "RMSE z mm", "RMSE mm", "success", "median inliers"],
                 rows)


# --- one correction: its peers, opacity weights -----------------------------------------------------------

PEER_FOLDERS = ("peers_room31_oracle", "peers_room31_trained", "peers_fr1_desk")
SINGLE_FILES = (*(f"{f}/summary.json" for f in PEER_FOLDERS), "opacity_weighting.json")
SINGLE_HEADER = ["field (file)", "method", "trials", "perturbation cm / deg", "success", "translation median mm",
                 "translation p90 / max mm", "rotation median / p90 deg", "ms per correction",
                 "translation / Cramer-Rao bound, median"]


def _peer_rows(name: str) -> list[list[str]]:
    """One bench-peers summary: each method, then the Cramer-Rao bound of the matches."""
    d = _read(name)
    c = get(d, "config") or {}
    label, trials = f"{name.split('/')[0]} `{name}`", _int(_x(c, "trials"))
    pert = _pair(cm(_x(c, "max_trans_m"), 0), num(_x(c, "max_rot_deg"), 0))
    rows = [[label, method, trials, pert, _pct(_x(r, "success_rate")), num(_x(r, "trans_mm", "median"), 1),
             _pair(num(_x(r, "trans_mm", "p90"), 1), num(_x(r, "trans_mm", "max"), 1)),
             _pair(num(_x(r, "rot_deg", "median")), num(_x(r, "rot_deg", "p90"))), num(_x(r, "ms_median"), 0),
             num(_x(r, "trans_over_crb_median"))] for method, r in (get(d, "methods") or {}).items()]
    crb = get(d, "crb_trans_mm") or {}
    rows.append([label, "Cramer-Rao bound", trials, pert, "-", num(_x(crb, "median"), 1),
                 _pair(num(_x(crb, "p90"), 1), num(_x(crb, "max"), 1)), "-", "-", "-"])
    return rows


def _opacity_rows() -> list[list[str]]:
    """opacity_weighting.json: each field kind x variant, pooled over the rooms (success: pooled, rooms' range)."""
    name = "opacity_weighting.json"
    d = _read(name)
    rooms, per_room = get(d, "rooms") or [], get(d, "per_room") or {}
    trials = _x(d, "scenarios")
    rows = []
    for kind, variants in (get(d, "pooled") or {}).items():
        steps = f" ({_int(_x(d, 'train_steps'))} train steps)" if kind == "trained" else ""
        label = f"{kind}{steps} `{name}`"
        for variant, r in variants.items():
            rates = [_x(per_room, str(room), kind, variant, "success_rate") for room in rooms]
            rows.append([label, variant, _int(None if trials is None else trials * len(rooms)), "n/a",
                         f"{_pct(_x(r, 'success_rate'))} (rooms {_list_span(rates, _pct)})",
                         num(_x(r, "trans_mm", "median"), 1),
                         _pair(num(_x(r, "trans_mm", "p90"), 1), num(_x(r, "trans_mm", "max"), 1)),
                         _pair(num(_x(r, "rot_deg", "median")), num(_x(r, "rot_deg", "p90"))), "n/a", "n/a"])
    return rows


def single_table() -> str:
    """NAP3D and its peers on the same perturbed frames, then the opacity-weighted Procrustes against the plain one."""
    rows = [r for f in PEER_FOLDERS for r in _peer_rows(f"{f}/summary.json")]
    return table(SINGLE_HEADER, rows + _opacity_rows())


# --- real time on fr1/desk ------------------------------------------------------------------------------------

REALTIME_FILES = ("realtime_fr1_desk.json", "realtime_fr1_desk_xfeat.json")
REALTIME_HEADER = ["run (file)", "matcher, field", "camera Hz", "keyframe every (mean)", "frame/s",
                   "frame/s over repeats", "ratio to the run beside it, repeats", "behind the camera, max ms",
                   "corrections late, frames median / max", "measurement ms median / p90", "render ms median",
                   "ATE cm", "causal ATE cm", "accepted"]


def _realtime_mode(r: dict) -> str:
    """A run's settings in words."""
    words = ["overlapped" if r.get("overlap") else "inline"]
    if r.get("overlap") and r.get("library_threads") is None:
        words.append("BLAS pool as it comes")
    if (_x(r, "land_within_s") or 0) > 0:
        words.append("land within a frame")
    if r.get("render_ahead"):
        words.append(f"render ahead ({_pct(_x(r, 'rendered_ahead_fraction'))} made ahead)")
    if r.get("keyframe_when_idle"):
        words.append("keyframe when idle")
    if r.get("read_ahead") == 0:
        words.append("no read-ahead")
    return ", ".join(words)


def _realtime_row(name: str, d: dict, r: dict) -> list[str]:
    """One run setting (the median run of its repeats; ranges over the repeats beside)."""
    rate, speed = _x(d, "camera_rate_hz"), _x(r, "pace_speed")
    stages = get(r, "ms_per_keyframe") or {}
    render = next((v for v in (_x(stages, k, "median") for k in ("render", "render_beside", "render_ahead")) if v),
                  None)
    ratios = get(r, "vs_library_threads_1_repeats") or get(r, "overlapped_vs_inline_repeats")
    late = get(r, "frames_late")
    ate = _list_span(get(r, "ate_m_repeats"), cm) if get(r, "ate_m_repeats") else cm(_x(r, "ate_m"))
    causal = get(r, "causal_ate_m_repeats")
    return [f"{_realtime_mode(r)} `{name}`", f"{get(d, 'matcher') or 'n/a'}, {get(r, 'field') or 'n/a'}",
            "-" if speed is None or rate is None else num(rate * speed, 1),
            f"{_int(_x(r, 'keyframe_every'))} ({num(_x(r, 'keyframe_interval_mean'), 1)})",
            num(_x(r, "frames_per_s"), 1),
            _list_span(get(r, "frames_per_s_repeats"), lambda v: num(v, 1)) if "frames_per_s_repeats" in r else "-",
            _list_span(ratios) if ratios else "-",
            _ms(_x(r, "behind_camera_s", "max"), 0) if get(r, "behind_camera_s") else "-",
            _pair(num(_x(late, "median"), 1), _int(_x(late, "max"))) if late else "-",
            _pair(num(_x(stages, "measure", "median"), 0), num(_x(stages, "measure", "p90"), 0)), num(render, 0), ate,
            _list_span(causal, cm) if causal else cm(_x(r, "causal_ate_m")),
            _frac(_x(r, "accepted"), _x(r, "keyframes"))]


def realtime_table() -> str:
    """Every run setting of both real-time files."""
    rows = []
    for name in REALTIME_FILES:
        d = _read(name)
        rows += [_realtime_row(name, d, r) for r in get(d, "runs") or []]
    return table(REALTIME_HEADER, rows)


# --- odometry on fr1/desk ------------------------------------------------------------------------------------

ODOMETRY_HEADER = ["odometry (file)", "steps / failed", "step ms p50 / p90", "read ms p50", "detection ms p50",
                   "matching ms p50", "RANSAC / refinement ms p50", "dense solve ms p50", "frame/s",
                   "step against detecting once", "ATE cm", "final / max error cm"]


def _profile_rows() -> list[list[str]]:
    """odometry_profile_fr1_desk.json: one step's stages, one thread."""
    name = "odometry_profile_fr1_desk.json"
    d = _read(name)
    size = "x".join(str(v) for v in get(d, "resolution") or []) or "n/a"
    rows = []
    for kind, o in (get(d, "odometries") or {}).items():
        s = get(o, "stages") or {}

        def p50(stage, s=s):
            """A stage's median, ``-`` where this odometry has no such stage."""
            return num(_x(s, stage, "p50_ms"), 1) if stage in s else "-"

        rows.append([f"{kind}, {size} `{name}`", _pair(_int(_x(o, "steps")), "n/a"),
                     _pair(num(_x(o, "step", "p50_ms"), 1), num(_x(o, "step", "p90_ms"), 1)),
                     num(_x(o, "read", "p50_ms"), 1), p50("detect"), p50("match"), _pair(p50("ransac"), p50("refine")),
                     p50("solve"), num(_x(o, "frames_per_s_at_p50"), 1),
                     num(_x(o, "step_p50_vs_detecting_once")) if "step_p50_vs_detecting_once" in o else "-",
                     "n/a", "n/a"])
    return rows


def _vo_rows() -> list[list[str]]:
    """vo_fr1_desk.json: whole runs of each odometry alone, with its drift."""
    name = "vo_fr1_desk.json"
    rows = []
    for kind, o in (get(_read(name), "odometry") or {}).items():
        rows.append([f"{kind} `{name}`", _pair(_int(_x(o, "frames")), _int(_x(o, "failed_steps"))),
                     _pair(num(_x(o, "step_ms", "median"), 1), num(_x(o, "step_ms", "p90"), 1)),
                     num(_x(o, "read_ms", "median"), 1), "n/a", "n/a", "n/a", "n/a", num(_x(o, "frames_per_s"), 1),
                     "-", cm(_x(o, "ate_m")), _pair(cm(_x(o, "final_error_m")), cm(_x(o, "max_error_m")))])
    return rows


def odometry_table() -> str:
    """The odometries of fr1/desk's second half: one step profiled, and whole runs."""
    return table(ODOMETRY_HEADER, _profile_rows() + _vo_rows())


# --- estimators' cost and a long run's graph ----------------------------------------------------------------

GRAPH_HEADER = ["run (file)", "keyframes", "estimator", "ms per step: mean, or (graph) median of the last thousand",
                "ms per step: p99, or (graph) p90 of the last thousand",
                "final solve s", "memory MB, first / last check", "frames kept at the end", "ATE cm", "NEES mean"]


def _estimator_timing_rows() -> list[list[str]]:
    """estimators_timing.json: each estimator's time per step on synthetic streams (iSAM2: causal / final)."""
    name = "estimators_timing.json"
    rows = []
    for run, r in (get(_read(name), "runs") or {}).items():
        for est, e in (get(r, "estimators") or {}).items():
            res = list((get(e, "rows") or {}).values())
            rows.append([f"{run.replace('_', ' frames, ')} path `{name}`", _int(_x(r, "keyframes")), est,
                         num(_x(e, "step_ms_mean"), 3), num(_x(e, "step_ms_p99"), 3), num(_x(e, "final_s"), 3), "-",
                         "-", " / ".join(cm(_x(x, "ate_rmse_m")) for x in res) or "n/a",
                         " / ".join(num(_x(x, "nees_mean")) for x in res) or "n/a"])
    return rows


def _graph_window_rows() -> list[list[str]]:
    """graph_window.json: iSAM2 per keyframe (median over the last thousand), memory and the final solve."""
    name = "graph_window.json"
    rows = []
    for r in get(_read(name), "runs") or []:
        window = _x(r, "graph_window")
        label = (f"window {_int(window)}, {'retiring' if r.get('retire') else 'keeping'} the final frames"
                 if window else "every keyframe kept")
        per_k, rss = get(r, "isam_ms_median_per_1000_keyframes") or {}, list((get(r, "rss_mb_at") or {}).values())
        rows.append([f"{label} `{name}`", _int(_x(r, "keyframes")), "iSAM2",
                     num(_x(list(per_k.values()), -1), 2), num(_x(r, "isam_ms_p90_last_1000"), 2),
                     num(_x(r, "final_solve_s"), 2), _pair(num(_x(rss, 0), 1), num(_x(rss, -1), 1)),
                     _int(_x(r, "frames_in_final_result")), cm(_x(r, "ate_m")), "n/a"])
    return rows


def graph_table() -> str:
    """Estimators per step, then a long run's graph with and without its window."""
    return table(GRAPH_HEADER, _estimator_timing_rows() + _graph_window_rows())


# --- stage timings --------------------------------------------------------------------------------------------

STAGE_HEADER = ["stage (file)", "setting", "ms", "spread ms", "count"]


def _pipeline_rows() -> list[list[str]]:
    """pipeline.json: one keyframe's stages, and iSAM2's update as the graph grows."""
    name = "pipeline.json"
    d = _read(name)
    k = get(d, "per_keyframe_s") or {}
    setting = f"{get(d, 'field') or 'n/a'} field, {_int(_x(k, 'correction_iterations'))} correction round"
    count = f"{_frac(_x(k, 'accepted'), _x(k, 'keyframes'))} accepted"
    rows = [[f"keyframe: {stage.removesuffix('_per_keyframe')} `{name}`", setting, _ms(_x(k, stage)), "n/a", count]
            for stage in k if stage not in ("keyframes", "accepted", "correction_iterations")]
    for key, value in (get(d, "isam2") or {}).items():
        if key.endswith("_poses"):
            what, poses = key.split("_ms_at_")
            rows.append([f"iSAM2 {what.replace('_', ' ')} `{name}`", f"{poses.split('_')[0]} poses",
                         num(_x([value], 0), 3), "n/a", "-"])
    return rows


def _alignment_rows() -> list[list[str]]:
    """alignment.json: RANSAC alone, and one alignment's stages at two sizes."""
    name = "alignment.json"
    d = _read(name)
    r = get(d, "ransac_1000x500") or {}
    rows = [[f"RANSAC `{name}`", f"{_int(_x(r, 'correspondences'))} correspondences, {_int(_x(r, 'hypotheses'))} "
             "hypotheses", num(_x(r, "median_ms"), 2), f"min {num(_x(r, 'min_ms'), 2)}", "-"]]
    for key, s in d.items():
        if key.startswith("stages_"):
            count = f"{_int(_x(s, 'matches'))} matches, {_int(_x(s, 'inliers'))} inliers"
            rows += [[f"alignment: {stage.removesuffix('_ms')} `{name}`", key.removeprefix("stages_"),
                      num(_x(s, stage), 1), "n/a", count] for stage in s if stage.endswith("_ms")]
    return rows


def _small_timing_rows() -> list[list[str]]:
    """association.json (stamp association, both methods) and sim_render.json (the simulator's render)."""
    a, name = _read("association.json"), "association.json"
    rows = [[f"association: {m} `{name}`", f"{_int(_x(a, 'frames'))} frames", _ms(_x(a, m, "median_s"), 2),
             f"max {_ms(_x(a, m, 'max_s'), 2)}", f"{_int(_x(a, m, 'pairs'))} pairs"] for m in ("optimal", "greedy")]
    rows += [["simulator render `sim_render.json`", size, _ms(_x(r, "median_s"), 0), f"min {_ms(_x(r, 'min_s'), 0)}",
              "-"] for size, r in _read("sim_render.json").items()]
    return rows


def stage_table() -> str:
    """Stage timings: a keyframe's measurement, RANSAC, stamp association, the simulator's render."""
    return table(STAGE_HEADER, _pipeline_rows() + _alignment_rows() + _small_timing_rows())


# --- reading recordings ------------------------------------------------------------------------------------------

READER_HEADER = ["source (file)", "frames", "file MB", "frame/s", "frame/s min, or with opening", "ATE cm",
                 "causal cm", "odometry alone cm", "accepted", "depth max error mm", "poses' max difference mm"]


def _realsense_rows() -> list[list[str]]:
    """realsense_read.json: a simulated recording written by pyrealsense2's recorder, read back."""
    name = "realsense_read.json"
    d = _read(name)
    size = "x".join(str(v) for v in get(d, "size") or []) or "n/a"
    rows = []
    for key in ("read_raw", "open", "registered_depth", "end_to_end"):
        f = get(d, f"frames_per_s_{key}") or {}
        rows.append([f"RealSense {size}, {key.replace('_', ' ')} `{name}`", _int(_x(d, "frames")),
                     num(_x(d, "file_mb"), 1), num(_x(f, "median"), 1), f"min {num(_x(f, 'min'), 1)}",
                     "-", "-", "-", "-", "-", "-"])
    return rows


def _rosbag_rows() -> list[list[str]]:
    """rosbag_fr1_desk.json: fr1/desk as a folder and as ROS bags, read and run (--odom vo)."""
    name = "rosbag_fr1_desk.json"
    d = _read(name)
    rows = []
    for key, s in (get(d, "sources") or {}).items():
        r = get(d, "runs", key) or {}
        diff = _x(r, "max_pose_difference_to_folder_m")
        rows.append([f"{key} `{name}`", _int(_x(s, "frames") or _x(d, "frames")), num(_x(s, "bag_mb"), 1),
                     num(_x(s, "read_frames_per_s"), 0), f"with opening {num(_x(s, 'read_frames_per_s_with_open'), 0)}"
                     if "read_frames_per_s_with_open" in s else "-",
                     num(_x(r, "ate_cm")), num(_x(r, "causal_ate_cm")), num(_x(r, "odometry_ate_cm")),
                     _frac(_x(r, "accepted"), _x(r, "keyframes")), num(_x(s, "depth_max_abs_error_mm"), 2)
                     if "depth_max_abs_error_mm" in s else "-", mm(diff, 3) if diff is not None else "-"])
    return rows + [_rosbag_written_row(name, get(d, "runs") or {})]


def _rosbag_written_row(name: str, runs: dict) -> list[str]:
    """The ROS 1 run's written bag (against the run's estimate) and its rerun recording."""
    r = next((v for v in runs.values() if "rerun_recording" in v), {})
    rr = get(r, "rerun_recording") or {}
    return [f"written bag and rerun recording `{name}`", f"{_int(_x(rr, 'status_entries'))} statuses",
            num(_x(rr, "mb"), 1), "-", "-", "-", "-", "-",
            f"{_int(_x(rr, 'accepted_ellipsoids'))} ellipsoids", "-",
            _sci_mm(_x(r, "written_bag_max_pose_difference_to_estimate_m"))]


def _sci_mm(value_m) -> str:
    """Metres as millimetres in scientific notation (for differences near rounding)."""
    return "n/a" if value_m is None else f"{value_m * 1000:.1e}"


def reader_table() -> str:
    """Reading a RealSense recording and ROS bags, and running on the bags."""
    return table(READER_HEADER, _realsense_rows() + _rosbag_rows())


# --- a sweep on two workers, the grid on a GPU ----------------------------------------------------------------------

SCALE_HEADER = ["run (file)", "where", "budget", "seconds", "ratio to one worker", "render ms median",
                "depth against exact mm median", "depth against the GPU's mm median / p99",
                "opacity flips / colour levels against the GPU's"]


def _sweep_rows() -> list[list[str]]:
    """sweep_scaling.json: the same sweep on one and two workers."""
    name = "sweep_scaling.json"
    d = _read(name)
    budget = (f"{_int(_x(d, 'cells'))} cells, {_int(_x(d, 'fields'))} fields, {_int(_x(d, 'frames_per_recording'))} "
              "frames")
    rows = []
    for key, r in (get(d, "runs") or {}).items():
        workers = key.removeprefix("workers_")
        ratio = (f"{num(_x(d, 'ratio_2_to_1_workers'))} (same table: {_yes(get(d, 'same_table_up_to_timings'))})"
                 if workers == "2" else "-")
        rows.append([f"sweep, {workers} worker(s) `{name}`", get(d, "pool") or "n/a", budget,
                     num(_x(r, "seconds"), 1), ratio, "-", "-", "-", "-"])
    return rows


def _cuda_rows() -> list[list[str]]:
    """cuda_check_h200.json: the grid trained on the GPU, rendered there and on the CPU."""
    name = "cuda_check_h200.json"
    d = _read(name)
    rows = [[f"train `{name}`", f"{get(d, 'train_device') or 'n/a'} ({get(d, 'gpu') or 'n/a'}, torch "
             f"{get(d, 'torch') or 'n/a'})", f"{_int(_x(d, 'steps'))} steps", num(_x(d, "train_seconds"), 1),
             "-", "-", "-", "-", "-"]]
    for key, r in d.items():
        if isinstance(r, dict) and "render_ms_median" in r:
            rows.append([f"render, {key} `{name}`", get(r, "backend") or "n/a", "-", "-", "-",
                         num(_x(r, "render_ms_median"), 1), num(_x(r, "depth_err_vs_exact_mm_median"), 1),
                         _pair(num(_x(r, "vs_gpu_depth_mm_median"), 4), num(_x(r, "vs_gpu_depth_mm_p99"), 4)),
                         _pair(f"{_x(r, 'vs_gpu_opacity_flips') or 0:.1e}", f"{_x(r, 'vs_gpu_colour_levels') or 0:.1e}")
                         if _x(r, "vs_gpu_opacity_flips") is not None else "n/a"])
    return rows


def scale_table() -> str:
    """A sweep on one and two workers; the default field trained and rendered on a CUDA GPU."""
    return table(SCALE_HEADER, _sweep_rows() + _cuda_rows())


# --- faults -----------------------------------------------------------------------------------------------------

FAULT_HEADER = ["fault (file)", "room or walk", "case", "caught", "accepted", "error cm", "worst cm",
                "against clean", "gravity off deg median / max"]


def _fault_rows() -> list[list[str]]:
    """faults.json: per room, the clean run and each injected fault."""
    name = "faults.json"
    rows = []
    for room, r in (get(_read(name), "rooms") or {}).items():
        w, s, b = (get(r, k) or {} for k in ("wrong_corrections", "some_frames_scaled", "wrong_after_blind_stretch"))
        factor, e = next(((k.removeprefix("every_frame_scaled_"), v) for k, v in r.items()
                          if k.startswith("every_frame_scaled_")), ("n/a", {}))
        rows += [
            [f"none `{name}`", room, f"clean (odometry alone {cm(_x(r, 'odometry_ate_m'))})", "-",
             _frac(_x(r, "clean_accepted"), _x(r, "keyframes")), cm(_x(r, "clean_ate_m")), "-", "-",
             "-"],
            [f"wrong corrections `{name}`", room, f"{_int(_x(w, 'injected'))} injected",
             f"{_int(_x(w, 'gated_out'))} gated out, {_int(_x(w, 'accepted_then_weighed_out'))} weighed out", "-",
             cm(_x(w, "ate_m")), "-", num(_x(w, "ratio_to_clean")), "-"],
            [f"some depths scaled `{name}`", room, f"{_int(_x(s, 'injected'))} injected",
             f"{_int(_x(s, 'refused_for_scale'))} refused, {_int(_x(s, 'good_refused_for_scale'))} good refused",
             "-", cm(_x(s, "ate_m")), "-", num(_x(s, "ratio_to_clean")), "-"],
            [f"every depth scaled `{name}`", room, f"depths x{factor}: scale {num(_x(e, 'true_scale'), 4)}",
             f"found {num(_x(e, 'estimated_scale'), 4)} ({_signed_pct(_x(e, 'scale_error_rel'))})",
             _frac(_x(e, "accepted"), _x(r, "keyframes")), cm(_x(e, "ate_m")), "-", num(_x(e, "ratio_to_clean")), "-"],
            [f"wrong after a blind stretch `{name}`", room, "one wrong correction",
             f"gate took it: {_yes(get(b, 'wrong_accepted_by_gate'))}; weighed out: {_yes(get(b, 'weighed_out'))}",
             "-", cm(_x(b, "ate_m")), "-", "-", "-"]]
    return rows


def _fallback_rows() -> list[list[str]]:
    """imu_fallback.json: walks whose field covers only their start, IMU alone against the fallbacks."""
    name = "imu_fallback.json"
    d = _read(name)
    rows = []
    for r in get(d, "rows") or []:
        for case in ("imu_alone", "dense", "vo"):
            c = get(r, case) or {}
            spans = ", ".join(f"{a}-{b}" for a, b in get(c, "fallback_intervals") or [])
            rows.append([f"field covers the first {_int(_x(d, 'mapped_frames'))} frames `{name}`",
                         f"room {_int(_x(r, 'room'))}", case.replace("_", " ") if case == "imu_alone" else
                         f"{case} fallback", f"fallback frames {spans}" if spans else "-",
                         _frac(_x(c, "accepted"), _x(c, "keyframes")), cm(_x(c, "end_m"), 1),
                         cm(_x(c, "max_after_field_m"), 1), "-", "-"])
    return rows


def _gravity_rows() -> list[list[str]]:
    """gravity_frame.json: walks mapped into a turned frame, per start of gravity (ATE median, max)."""
    name = "gravity_frame.json"
    rows = []
    for frame, f in (get(_read(name), "frames") or {}).items():
        for case, c in f.items():
            if isinstance(c, dict) and "runs" in c:
                rows.append([f"gravity frame turned `{name}`", frame.replace("_", " "), case.replace("_", " "),
                             f"{_int(_x(c, 'runs_with_under_80pct_accepted'))} of {_int(_x(c, 'runs'))} runs "
                             "under 80% accepted", "-", cm(_x(c, "ate_median_m")), cm(_x(c, "ate_max_m")), "-",
                             _pair(num(_x(c, "gravity_off_median_deg")), num(_x(c, "gravity_off_max_deg")))])
    return rows


def fault_table() -> str:
    """Injected faults, walks that leave their field on the IMU path, and gravity in a turned frame."""
    return table(FAULT_HEADER, _fault_rows() + _fallback_rows() + _gravity_rows())


def imu_drift_table() -> str:
    """The IMU alone: Monte-Carlo RMS position error against its noise model's prediction."""
    name = "imu_drift.json"
    d = _read(name)
    rows = [[f"after {_int(_x(r, 't_s'))} s `{name}`", _int(_x(d, "seeds")), num(_x(r, "mc_rms_m"), 3),
             num(_x(r, "predicted_rms_m"), 3), num(_x(r, "ratio"), 3),
             _pair(num(_x(r, "predicted_initial_bias_m"), 3), num(_x(r, "predicted_white_noise_m"), 3)),
             num(_x(r, "predicted_bias_random_walk_m"), 4)] for r in get(d, "table") or []]
    return table(["time (file)", "seeds", "Monte-Carlo RMS m", "predicted m", "ratio",
                  "predicted from the initial bias / white noise m", "from the bias random walk m"], rows)


# --- the sections ---------------------------------------------------------------------------------------------------

SECTIONS: list[Section] = [
    Section(
        "Drift removal on simulated rooms: the embedded default and the hold-out rooms",
        DRIFT_FILES,
        "python benchmarks/default_run.py; python benchmarks/drift_rooms.py; "
        "python benchmarks/drift_rooms.py --model views --out benchmarks/results/drift_rooms_views.json",
        drift_table,
        "Each run corrects the room's walk with a field built on its survey, its measured error added; the exact "
        "field is the simulated room itself. Pooled rows are the file's own mean and range over its rooms.",
    ),
    Section(
        "The field's own error and its growth away from its frames, hold-out rooms",
        ("error_growth_rooms.json",),
        "python benchmarks/error_growth_rooms.py",
        growth_table,
        "'near' adds the error measured near the field's frames at every distance, 'growth' adds it at each "
        "correction's own distance; the band is the chi-square band of the NEES mean over the run's corrections.",
    ),
    Section(
        "Covariance honesty of one correction, exact field, hold-out rooms",
        COVARIANCE_FILES,
        "python benchmarks/covariance.py; python benchmarks/covariance.py --matcher xfeat --trials 60 "
        "--configs pipeline --out benchmarks/results/covariance_xfeat.json",
        covariance_table,
        "NEES of the pose (six degrees of freedom) and of its rotation and translation blocks (three each), pooled "
        "over the rooms; an honest covariance puts the mean inside the band.",
    ),
    Section(
        "EKF against graph: every estimator on the same corrections",
        ESTIMATOR_FILES,
        "python benchmarks/compare_rooms.py; nap3d-graph compare --traj tum --data D --frames 0.5:1 "
        "--field benchmarks/results/study_fr1_desk/field.pt --odom vo|noisy [--field-sigma 0.02] "
        "--out benchmarks/results/compare_fr1_desk_...; python benchmarks/nees_question.py",
        estimators_table,
        "One reference run measures the corrections; every estimator then runs on that stream. compare_rooms pools "
        "its simulated sequences (the embedded default's room with several walks, and the hold-out rooms); "
        "nees_question sets the corrections' own NEES beside the estimators'.",
    ),
    Section(
        "Evaluation K, exact field, room 31: intrinsics shifted on the real camera",
        ("eval_k_oracle_room31/summary.json",),
        "nap3d-graph eval-k data/room31_walk --field oracle --scenarios 40 "
        "--out benchmarks/results/eval_k_oracle_room31",
        eval_k_real_table,
        "Median translation error of each method per blur and intrinsics cell, its success rate beside it; a "
        "failure scores the uncorrected pose.",
    ),
    Section(
        "Evaluation K, exact field, room 31: the PnP that always calibrates",
        ("eval_k_oracle_room31_pnp_calibrated/summary.json",),
        "nap3d-graph eval-k data/room31_walk --field oracle --scenarios 40 "
        "--methods nap3d-plain,pnp,nap3d-refined,pnp-selfcal,nap3d-selfcal,pnp-calibrated "
        "--out benchmarks/results/eval_k_oracle_room31_pnp_calibrated",
        eval_k_calibrated_table,
        "The same protocol measured again with today's code and a sixth method: PnP with the intrinsics refined at "
        "every frame (pnp-selfcal calibrates only when NAP3D's test on pixels calls for it). Compare methods within "
        "one file: the older file above was written by older code.",
    ),
    Section(
        "Evaluation K, exact field, room 31: intrinsics shifted on both cameras",
        ("eval_k_oracle_room31_shift_both/summary.json",),
        "nap3d-graph eval-k data/room31_walk --field oracle --shift both --scenarios 20 "
        "--out benchmarks/results/eval_k_oracle_room31_shift_both",
        eval_k_both_table,
        "As above, with the render's camera shifted as the real one is, so self-calibration has less to find.",
    ),
    Section(
        "Evaluation J, exact field, room 31",
        ("eval_j_oracle_room31/summary.json",),
        "nap3d-graph eval-j --scene-seed 31 --out benchmarks/results/eval_j_oracle_room31",
        eval_j_table,
        "The paper's Tables I/II: RMSE of the estimated position along x and z over each sublocation's trials.",
    ),
    Section(
        "One correction: NAP3D against its peers, and opacity weights",
        SINGLE_FILES,
        "nap3d-graph bench-peers DATA --field oracle|FIELD --trials 40 --out benchmarks/results/peers_...; "
        "python benchmarks/opacity_weighting.py",
        single_table,
        "Every method corrects the same perturbed frames from the same renders; a failure scores the uncorrected "
        "pose. Opacity rows compare the Procrustes with and without the field's opacity weights on the same matches.",
    ),
    Section(
        "Real time on fr1/desk, the whole run (dense odometry), SIFT and XFeat",
        REALTIME_FILES,
        "python benchmarks/realtime_desk.py --field grid=G --field views=V; python benchmarks/realtime_desk.py "
        "--field grid=G --matcher xfeat --out benchmarks/results/realtime_fr1_desk_xfeat.json",
        realtime_table,
        "G and V are the grid and view fields of sweep_fields, built on the first half. Runs without a camera rate "
        "go as fast as they can; paced runs are fed at the recording's rate or twice it. Ranges are over repeats; "
        "the ratio is against the inline run (or, BLAS pool as it comes, the run holding it to one thread).",
    ),
    Section(
        "Odometry on fr1/desk's second half",
        ("odometry_profile_fr1_desk.json", "vo_fr1_desk.json"),
        "python benchmarks/odometry_profile.py; python benchmarks/vo_desk.py",
        odometry_table,
        "Profile rows time one step on one thread, stage by stage; vo_fr1_desk rows are whole runs of the odometry "
        "alone with its drift.",
    ),
    Section(
        "Estimators per step, and a long run's graph",
        ("estimators_timing.json", "graph_window.json"),
        "python benchmarks/estimators.py; python benchmarks/graph_window.py",
        graph_table,
        "Synthetic streams with drawn corrections, no rendering. iSAM2 rows of estimators_timing give causal / "
        "final; graph_window rows give iSAM2's median over the last thousand keyframes and memory at the first and "
        "last check.",
    ),
    Section(
        "Stage timings",
        ("pipeline.json", "alignment.json", "association.json", "sim_render.json"),
        "python benchmarks/pipeline.py; python benchmarks/alignment.py; python benchmarks/association.py; "
        "python benchmarks/sim_render.py",
        stage_table,
        "Single-threaded timings of one keyframe's stages, RANSAC, alignment, stamp association and the simulator's "
        "render.",
    ),
    Section(
        "Reading recordings: RealSense and ROS bags",
        ("realsense_read.json", "rosbag_fr1_desk.json"),
        "python benchmarks/realsense_read.py; python benchmarks/rosbag_desk.py",
        reader_table,
        "The bags hold fr1/desk in TUM's layout; their runs are against the folder's, the written bag's poses "
        "against the run's estimate.",
    ),
    Section(
        "Scaling out: a sweep on two workers, the grid field on a CUDA GPU",
        ("sweep_scaling.json", "cuda_check_h200.json"),
        "python benchmarks/sweep_scaling.py; "
        "python benchmarks/cuda_check.py --device cuda --out benchmarks/results/cuda_check_h200.json",
        scale_table,
        "The CUDA check trains the grid on the GPU and renders the same held-out poses there and on the CPU; its "
        "differences are against the GPU's render.",
    ),
    Section(
        "Faults: wrong corrections and depths, a field left behind, gravity in a turned frame",
        ("faults.json", "imu_fallback.json", "gravity_frame.json"),
        "python benchmarks/faults.py; python benchmarks/imu_fallback.py; python benchmarks/gravity_frame.py",
        fault_table,
        "Error is the ATE, except for imu_fallback where it is the last frame's error and worst is the largest "
        "after the field was left; gravity rows give the median and largest ATE over the walks.",
    ),
    Section(
        "The IMU alone against its noise model",
        ("imu_drift.json",),
        "python benchmarks/imu_drift.py --seeds 20",
        imu_drift_table,
        "RMS over seeds of the position error of the IMU integrated alone; the ratio agrees with the model within "
        "the chi distribution's spread for that many seeds.",
    ),
]
