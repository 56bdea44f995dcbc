"""Covariance honesty, every estimator on the same corrections, Evaluations K and J, one correction beside its peers: sections of ``docs/results.md`` read from the benchmarks' result files
(``benchmarks/results/``). Every figure comes out of its file; a key a file lacks reads ``n/a``,
and so does every figure of a missing file.
"""

from __future__ import annotations

from report import Section, cm, count, frac, get, list_span, mm, num, number, pair, pct, read, span, table, yes

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
    trials = [number(r, "trials") for r in rooms]
    skipped = [number(r, "failures_skipped") for r in rooms]
    errors = [number(r, "trans_err_median_mm") for r in rooms]
    total = None if None in trials or not trials else sum(trials)
    lost = None if None in skipped or not skipped else sum(skipped)
    return [f"{key} `{name}`", get(d, "matcher") or "sift (the script's default)",
            "x".join(str(v) for v in size) or "n/a", pair(cm(number(s, "max_trans_m"), 0), num(number(s, "max_rot_deg"), 1)),
            count(number(s, "rounds")), pair(count(total), count(lost)), num(number(p, "mean", "pose")),
            span(number(p, "room_min_max", "pose", 0), number(p, "room_min_max", "pose", 1)),
            span(number(p, "band_95", "pose", 0), number(p, "band_95", "pose", 1)),
            pair(num(number(p, "mean", "rotation")), num(number(p, "mean", "translation"))),
            span(number(p, "band_95", "rotation", 0), number(p, "band_95", "rotation", 1)), list_span(errors)]


def covariance_table() -> str:
    """Every setting of both covariance files (exact field, hold-out rooms)."""
    rows = []
    for name in COVARIANCE_FILES:
        d = read(name)
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
    taken = frac(sum(number(s, "corrections") or 0 for s in seqs.values()),
                  sum(number(s, "keyframes") or 0 for s in seqs.values())) if seqs else "n/a"

    def row(figure, ref, cell):
        """One figure of every estimator."""
        return [label, figure, ref, *(cell(get(p, e)) if get(p, e) else "-" for e in ESTIMATORS)]

    return [row("ATE cm, mean", taken, lambda e: cm(number(e, "ate_rmse_m", "mean"))),
            row("ATE cm, min-max", "-", lambda e: span(number(e, "ate_rmse_m", "min"), number(e, "ate_rmse_m", "max"), cm)),
            row("max error cm, mean", "-", lambda e: cm(number(e, "ate_max_m", "mean"))),
            row("NEES, mean", "-", lambda e: num(number(e, "nees_mean", "mean"), 1)),
            row("NEES, min-max", "-", lambda e: span(number(e, "nees_mean", "min"), number(e, "nees_mean", "max"),
                                                      lambda v: num(v, 1))),
            row("ms per step, mean", "-", lambda e: num(number(e, "step_ms_mean", "mean"), 3)),
            [label, "sequences with ATE at or below the ESKF's", _bias_cell(p),
             *(_at_or_below(seqs, e) for e in ESTIMATORS)]]


def _bias_cell(pooled: dict) -> str:
    """IMU path: how many reference runs ended with every bias within 3 sigma of the truth (the largest, sigma)."""
    b = get(pooled, "bias_abs_z_final")
    if b is None:
        return "-"
    return f"bias within 3 sigma {frac(number(b, 'within_3_sigma'), number(b, 'sequences'))} (max {num(number(b, 'max'), 1)})"


def _at_or_below(seqs: dict, estimator: str) -> str:
    """In how many sequences ``estimator``'s ATE is at or below the error-state EKF's."""
    pairs = [(number(s, "rows", estimator, "ate_rmse_m"), number(s, "rows", "eskf", "ate_rmse_m")) for s in seqs.values()]
    pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
    if estimator == "eskf" or not pairs:
        return "-"
    return frac(sum(a <= b for a, b in pairs), len(pairs))


def _comparison_rows(folder: str) -> list[list[str]]:
    """One ``compare`` folder: ATE (max), NEES and corrections taken per estimator."""
    name = f"{folder}/comparison.json"
    d = read(name)
    rows = {r.get("estimator"): r for r in get(d, "rows") or []}
    src = get(d, "source")
    settings = [f"--odom {get(src, 'odometry')}"] if isinstance(src, dict) else []
    if number(src, "pipeline", "field_sigma_m") is not None:
        settings.append(f"--field-sigma {number(src, 'pipeline', 'field_sigma_m')}")
    label = f"{get(d, 'path') or 'n/a'} path{''.join(', ' + s for s in settings)} `{name}`"
    first = next(iter(rows.values()), {})
    band = span(number(first, "nees_band_low"), number(first, "nees_band_high"))

    def row(figure, ref, cell):
        """One figure of every estimator."""
        return [label, figure, ref, *(cell(rows[e]) if e in rows else "-" for e in ESTIMATORS)]

    return [row("ATE cm (max)", "-", lambda r: f"{cm(number(r, 'ate_rmse_m'))} ({cm(number(r, 'ate_max_m'))})"),
            row(f"NEES mean (band {band})", "-", lambda r: num(number(r, "nees_mean"), 1)),
            row("corrections taken", frac(number(d, "corrections_measured"), number(d, "keyframes")),
                lambda r: count(number(r, "corrections_taken")))]


def _nees_question_rows() -> list[list[str]]:
    """nees_question.json: per odometry, the corrections' own NEES beside each estimator's."""
    name = "nees_question.json"
    d = read(name)
    rows = []
    for odometry, o in (get(d, "odometries") or {}).items():
        est, c = get(o, "estimators") or {}, get(o, "corrections") or {}
        label = f"{odometry} odometry; {get(d, 'walk') or 'n/a'} `{name}`"
        band = span(number(next(iter(est.values()), {}), "band", 0), number(next(iter(est.values()), {}), "band", 1))
        rows.append([label, "ATE cm", "-", *(cm(number(est, e, "ate_rmse_m")) if e in est else "-" for e in ESTIMATORS)])
        rows.append([label, f"NEES mean (band {band})", num(number(c, "nees_mean"), 1),
                     *(num(number(est, e, "nees_mean"), 1) if e in est else "-" for e in ESTIMATORS)])
        axes = [number(c, "whitened_std_per_axis", i) for i in range(6)]
        largest = max((a for a in axes if a is not None), default=None)
        rows.append([label, "corrections: NEES median / largest whitened sigma",
                     pair(num(number(c, "nees_median"), 1), num(largest)), *("-" for _ in ESTIMATORS)])
    return rows


def estimators_table() -> str:
    """compare_rooms' pooled figures, then each ``compare`` folder, then nees_question's walk."""
    d = read("compare_rooms.json")
    rows = [r for path in (get(d, "paths") or {}) for r in _pooled_rows("compare_rooms.json", path, d)]
    rows += [r for folder in COMPARE_FOLDERS for r in _comparison_rows(folder)]
    return table(ESTIMATOR_HEADER, rows + _nees_question_rows())


# --- Evaluation K and J ---------------------------------------------------------------------------------


def _eval_k_table(name: str) -> str:
    """One Evaluation K summary: per blur x intrinsics cell, each method's median translation and success."""
    d = read(name)
    c = get(d, "config") or {}
    methods = get(c, "methods") or list(get(d, "methods") or {})
    setting = (f"{count(number(c, 'scenarios'))} scenarios, +-{cm(number(c, 'max_trans_m'), 0)} cm / "
               f"{num(number(c, 'max_rot_deg'), 0)} deg, shift {get(c, 'shift') or 'n/a'}")
    header = [f"cell (file; {setting})", "blur sigma", "intrinsics (focal x, centre px)",
              *(f"{m}: median mm (success)" for m in methods),
              *(f"nap3d-selfcal beats {rival}: translation, rotation" for rival in _rivals(methods))]
    rows = []
    for cell, v in (get(d, "cells") or {}).items():
        level = get(v, "intrinsics") or "n/a"
        noise = get(c, "intrinsics_noise", level) or []
        by_method = get(v, "methods") or {}
        cells = [f"{mm(number(by_method, m, 'trans_err_m', 'median'), 2)} ({pct(number(by_method, m, 'success_rate'))})" for m in methods]
        rows.append([f"{cell} `{name}`", num(number(v, "blur_sigma"), 1),
                     f"{level} ({num(number(noise, 0))}, {num(number(noise, 1), 0)})", *cells,
                     *(_selfcal_beats(by_method, rival) for rival in _rivals(methods))])
    return table(header, rows)


def _rivals(methods: list) -> list[str]:
    """The PnP variants self-calibrating NAP3D is held against: the self-calibrating PnP, the
    one that always calibrates where the file has it, and the best PnP of each cell."""
    rivals = [m for m in ("pnp-selfcal", "pnp-calibrated") if m in methods]
    return rivals + (["the best PnP"] if len(rivals) > 1 else [])


def _median(methods: dict, rival: str, key: str):
    if rival != "the best PnP":
        return number(methods, rival, key, "median")
    values = [number(methods, m, key, "median") for m in methods if m.startswith("pnp")]
    values = [v for v in values if v is not None]
    return min(values) if values else None


def _selfcal_beats(methods: dict, rival: str = "pnp-selfcal") -> str:
    """Whether self-calibrating NAP3D's median translation and rotation are below ``rival``'s."""
    def below(key):
        """Self-calibrating NAP3D's median below the rival's (None where either is missing)."""
        a, b = number(methods, "nap3d-selfcal", key, "median"), _median(methods, rival, key)
        return None if a is None or b is None else a < b

    return f"{yes(below('trans_err_m'))}, {yes(below('rot_err_deg'))}"


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
    rows = [[f"sublocation {sub} `{name}`", method, mm(number(r, "rmse_x_m"), 2), mm(number(r, "rmse_z_m"), 2),
             mm(number(r, "rmse_m"), 2), pct(number(r, "success_rate")), count(number(r, "median_inliers"))]
            for sub, methods in read(name).items() if isinstance(methods, dict)
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
    d = read(name)
    c = get(d, "config") or {}
    label, trials = f"{name.split('/')[0]} `{name}`", count(number(c, "trials"))
    pert = pair(cm(number(c, "max_trans_m"), 0), num(number(c, "max_rot_deg"), 0))
    rows = [[label, method, trials, pert, pct(number(r, "success_rate")), num(number(r, "trans_mm", "median"), 1),
             pair(num(number(r, "trans_mm", "p90"), 1), num(number(r, "trans_mm", "max"), 1)),
             pair(num(number(r, "rot_deg", "median")), num(number(r, "rot_deg", "p90"))), num(number(r, "ms_median"), 0),
             num(number(r, "trans_over_crb_median"))] for method, r in (get(d, "methods") or {}).items()]
    crb = get(d, "crb_trans_mm") or {}
    rows.append([label, "Cramer-Rao bound", trials, pert, "-", num(number(crb, "median"), 1),
                 pair(num(number(crb, "p90"), 1), num(number(crb, "max"), 1)), "-", "-", "-"])
    return rows


def _opacity_rows() -> list[list[str]]:
    """opacity_weighting.json: each field kind x variant, pooled over the rooms (success: pooled, rooms' range)."""
    name = "opacity_weighting.json"
    d = read(name)
    rooms, per_room = get(d, "rooms") or [], get(d, "per_room") or {}
    trials = number(d, "scenarios")
    rows = []
    for kind, variants in (get(d, "pooled") or {}).items():
        steps = f" ({count(number(d, 'train_steps'))} train steps)" if kind == "trained" else ""
        label = f"{kind}{steps} `{name}`"
        for variant, r in variants.items():
            rates = [number(per_room, str(room), kind, variant, "success_rate") for room in rooms]
            rows.append([label, variant, count(None if trials is None else trials * len(rooms)), "n/a",
                         f"{pct(number(r, 'success_rate'))} (rooms {list_span(rates, pct)})",
                         num(number(r, "trans_mm", "median"), 1),
                         pair(num(number(r, "trans_mm", "p90"), 1), num(number(r, "trans_mm", "max"), 1)),
                         pair(num(number(r, "rot_deg", "median")), num(number(r, "rot_deg", "p90"))), "n/a", "n/a"])
    return rows


def single_table() -> str:
    """NAP3D and its peers on the same perturbed frames, then the opacity-weighted Procrustes against the plain one."""
    rows = [r for f in PEER_FOLDERS for r in _peer_rows(f"{f}/summary.json")]
    return table(SINGLE_HEADER, rows + _opacity_rows())


SECTIONS: list[Section] = [
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
]
