"""The README's one results table: the headline figure of each use, each row naming its
file (the full tables are in docs/results.md)."""

from __future__ import annotations

from report import RESULTS, cm, load, table


def _exists(*names: str) -> bool:
    return all((RESULTS / n).is_file() for n in names)


def _default_run() -> list[str]:
    r = load("default_run.json")
    return ["embedded default: simulated room, field trained on a survey, separate walk",
            f"{cm(r['ate_odometry_m'])} -> **{cm(r['ate_estimate_m'])}** (causal {cm(r['ate_causal_m'])}, "
            f"max {cm(r['ate_estimate_max_m'])})", f"{r['corrections_accepted']}/{r['keyframes']}", "`default_run.json`"]


def _drift_rooms() -> list[str]:
    r = load("drift_rooms.json")
    p = r["pooled"]["trained"]
    est, odo = p["ate_estimate_m"], p["ate_odometry_m"]
    return [f"{len(r['rooms'])} hold-out simulated rooms, grid field of {r['train_steps']} steps (mean, range)",
            f"{cm(odo['mean'])} -> **{cm(est['mean'])}** ({cm(est['min'])}-{cm(est['max'])})",
            f"{p['accepted_fraction'] * 100:.0f}%", "`drift_rooms.json`"]


def _study(folder: str, what: str, odometry: str = "vo") -> list[str]:
    r = load(f"{folder}/summary.json")["runs"][odometry]
    return [f"{what}, field on the first half, second half `--odom {odometry}`",
            f"{cm(r['ate_odometry_m'])} -> **{cm(r['ate_estimate_m'])}** (max {cm(r['ate_estimate_max_m'])})",
            f"{r['accepted']}/{r['keyframes']}", f"`{folder}/summary.json`"]


def _map(name: str, what: str) -> list[str]:
    """The self-posed map's query run against the ground-truth-posed map's; where the recording
    has a second ground truth (7-Scenes' SfM poses), both scored against it too."""
    r = load(name)
    survey, runs = r["survey"], r["runs"]
    self_posed, gt_posed = runs["self_posed"], runs["gt_posed"]
    figure = (f"{cm(self_posed.get('odometry_ate_m'))} -> **{cm(self_posed['ate_m'])}** (ground-truth-posed map: "
              f"{cm(gt_posed['ate_m'])})")
    survey_text = f"survey ATE {cm(survey['ate']['map']['rmse_m'])}"
    second = survey.get("ate_second_gt")
    if second and "sfm_posed" in runs:
        figure += (f"; against the SfM poses **{cm(self_posed['ate_second_gt_m'])}** (SfM-posed map: "
                   f"{cm(runs['sfm_posed']['ate_second_gt_m'])})")
        survey_text += f", {cm(second['rmse_m'])} against the SfM poses"
    return [f"{what}: map from the camera alone ({survey_text}), second half in it", figure,
            str(self_posed.get("accepted", "n/a")), f"`{name}`"]


def _eval_k() -> list[str]:
    """Cells where self-calibrating NAP3D's median translation and rotation beat the PnP that
    always calibrates, and the best PnP of the cell."""
    name = "eval_k_oracle_room31_pnp_calibrated/summary.json"
    cells = load(name)["cells"].values()

    def beats(cell, rivals) -> bool:
        ms = cell["methods"]
        return all(ms["nap3d-selfcal"][k]["median"] < min(ms[r][k]["median"] for r in rivals)
                   for k in ("trans_err_m", "rot_err_deg"))

    calibrated = sum(beats(c, ["pnp-calibrated"]) for c in cells)
    best = sum(beats(c, [m for m in c["methods"] if m.startswith("pnp")]) for c in cells)
    return ["Evaluation K (paper's protocol), exact field, hold-out room 31, blur x intrinsics-shift cells",
            f"self-calibrating NAP3D beats the always-calibrating PnP in {calibrated}/{len(cells)} cells, the best "
            f"PnP of each cell in {best}/{len(cells)} (median translation and rotation)", "n/a", f"`{name}`"]


def _relocalise() -> list[str]:
    r = load("map_relocalise_fr1_desk_grid.json")["relocalisation"]
    return ["finding the start in fr1/desk's self-made map (random second-half frames)",
            f"{r['within_5cm_3deg']}/{r['attempts']} within 5 cm / 3 deg, {r['accepted_farther_than_10cm']} beyond "
            f"10 cm, {r['seconds_median']:.2f} s (max {r['seconds_max']:.2f})", "n/a",
            "`map_relocalise_fr1_desk_grid.json`"]


def _start_anywhere() -> list[str]:
    r = load("map_start_anywhere_fr1_desk.json")
    placed = sum(bool(d["runs"]["self_posed"]["placed"]) for d in r["directions"])
    found = sum(d["relocalisation"]["covered_found_within_5cm_3deg"] for d in r["directions"])
    covered = sum(d["relocalisation"]["covered"] for d in r["directions"])
    far = sum(d["relocalisation"]["accepted_farther_than_10cm"] for d in r["directions"])
    runs = ", ".join(f"{d['survey']} half as survey: {d['runs']['self_posed']['ate_m'] * 100:.2f}"
                     + (f" (GT-posed map {d['runs']['gt_posed']['ate_m'] * 100:.2f})" if "gt_posed" in d["runs"] else "")
                     for d in r["directions"])
    return ["fr1/desk: the other half started from its own first frame in the self-made map, both directions",
            f"placed {placed}/{len(r['directions'])} runs; ATE {runs}; every {r['every']}th query frame relocalised: "
            f"{found}/{covered} covered frames within 5 cm / 3 deg, {far} beyond 10 cm", "n/a",
            "`map_start_anywhere_fr1_desk.json`"]


def headline_table() -> str:
    """At most ten rows: ATE in cm, odometry alone -> with NAP3D (and the few headline checks)."""
    rows = []
    if _exists("default_run.json"):
        rows.append(_default_run())
    if _exists("drift_rooms.json"):
        rows.append(_drift_rooms())
    if _exists("study_fr1_desk_views/summary.json"):
        rows.append(_study("study_fr1_desk_views", "TUM fr1/desk (real), view field, XFeat"))
    if _exists("study_7scenes_redkitchen/summary.json"):
        rows.append(_study("study_7scenes_redkitchen", "7-Scenes redkitchen (real), splat field, XFeat"))
    if _exists("map_survey_fr1_desk.json"):
        rows.append(_map("map_survey_fr1_desk.json", "TUM fr1/desk"))
    if _exists("map_survey_redkitchen.json"):
        rows.append(_map("map_survey_redkitchen.json", "7-Scenes redkitchen"))
    if _exists("map_relocalise_fr1_desk_grid.json"):
        rows.append(_relocalise())
    if _exists("map_start_anywhere_fr1_desk.json"):
        rows.append(_start_anywhere())
    if _exists("eval_k_oracle_room31_pnp_calibrated/summary.json"):
        rows.append(_eval_k())
    return table(["what", "figure (ATE in cm: odometry alone -> with NAP3D)", "corrections accepted", "file"], rows[:10])
