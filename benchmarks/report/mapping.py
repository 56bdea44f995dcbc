"""The map built from the camera alone (``nap3d-graph map``) against maps pinned to ground
truth, and its checks (false loops, relocalisation, ORB-SLAM3 beside it)."""

from __future__ import annotations

import json
from pathlib import Path

from report import RESULTS, Section, cm, read, yes

MAP_SURVEY_FILES = ("map_survey_fr1_desk.json", "map_survey_redkitchen.json")
ORBSLAM3_FILES = ("orbslam3_fr1_desk.json", "orbslam3_fr1_desk_repeat.json")


def map_survey_table() -> str:
    """The self-posed map against the maps posed by each ground truth, per recording. The
    ratio is against the map posed by the ground truth the survey came nearer to, in that
    ground truth's frame."""
    rows = ["| recording (file) | survey ATE cm: map / odometry alone [2nd GT] | loops accepted / verified | query ATE "
            "cm (causal) [2nd GT]: self-posed map | GT-posed map | 2nd-GT-posed map | ratio to the nearer GT's map | "
            "relocalised within 5 cm / 3 deg [2nd GT]; >10 cm; s per attempt (median, max) | map s | run reports "
            "(self-posed, GT-posed, 2nd-GT-posed): gate d2 median, and what is past its bad line |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for name in MAP_SURVEY_FILES:
        path = RESULTS / name
        if not path.is_file():
            continue
        r = json.loads(path.read_text())
        survey, runs, reloc = r["survey"], r["runs"], r["relocalisation"]
        ate, second = survey["ate"], survey.get("ate_second_gt")

        def run_cell(key):
            run = runs.get(key)
            if run is None:
                return "n/a"
            if key == "sfm_posed":  # its world is the second ground truth's: scored there only
                return f"[{cm(run['ate_second_gt_m'])}] ([{cm(run['ate_second_gt_causal_m'])}])"
            extra = f" [{cm(run['ate_second_gt_m'])}]" if "ate_second_gt_m" in run else ""
            return f"{cm(run['ate_m'])} ({cm(run['ate_causal_m'])}){extra}"

        nearer_second = second is not None and second["rmse_m"] < ate["map"]["rmse_m"]
        ratio = (r["ratio_self_to_sfm_posed_in_sfm_frame"] if nearer_second and "sfm_posed" in runs
                 else r["ratio_self_to_gt_posed"])
        second_text = f" [{cm(second['rmse_m'])}]" if second else ""
        reloc_second = (f" [{reloc['within_5cm_3deg_second_gt']}]" if "within_5cm_3deg_second_gt" in reloc else "")
        rows.append(
            f"| {Path(r['data']).name} `{name}` "
            f"| {cm(ate['map']['rmse_m'])} / {cm(ate['odometry_only']['rmse_m'])}{second_text} "
            f"| {survey['loops']['accepted']} / {survey['loops']['verified']} "
            f"| {run_cell('self_posed')} | {run_cell('gt_posed')} | {run_cell('sfm_posed')} "
            f"| {ratio:.2f}{' (2nd GT)' if nearer_second else ''} "
            f"| {reloc['within_5cm_3deg']}/{reloc['attempts']}{reloc_second}; {reloc['accepted_farther_than_10cm']}; "
            f"{reloc['seconds_median']:.2f}, {reloc['seconds_max']:.2f} "
            f"| {sum(survey['stages_s'].values()):.0f} | {_reports_cell(runs)} |")
    return "\n".join(rows)


def _reports_cell(runs: dict) -> str:
    """Each run's report: its median gate d2 and the figures past their bad lines (the gate's
    consistency band is 0.87-16.8), '-' where the file predates the reports being recorded."""
    cells = []
    for key in ("self_posed", "gt_posed", "sfm_posed"):
        report = (runs.get(key) or {}).get("report")
        if report is None:
            continue
        d2 = report.get("gate_d2_median")
        bad = "; ".join(b.split(":")[0] for b in report["past_bad_line"]) or "nothing"
        cells.append(f"{d2:.2f}, {bad}" if d2 is not None else bad)
    return " / ".join(cells) or "-"


def _range_cm(summary: dict) -> str:
    return f"{summary['median'] * 100:.2f} ({summary['min'] * 100:.2f}-{summary['max'] * 100:.2f})"


def map_checks_table() -> str:
    """False loops from twin pictures, and ORB-SLAM3 beside the map on fr1/desk."""
    rows = ["| check (file) | figure |", "|---|---|"]
    path = RESULTS / "map_false_loops.json"
    if path.is_file():
        r = json.loads(path.read_text())
        ident, diff = r["identical"], r["different"]
        forced, relaxed = r["forced_twin_pairs"], r["forced_twin_pairs_relaxed"]
        rows.append(
            f"| twin pictures on opposite walls, simulated survey (`map_false_loops.json`) | false loops in the final "
            f"graph {ident['loops']['false_accepted']} of {ident['loops']['accepted']} accepted; survey ATE "
            f"{cm(ident['ate_map_m'])} cm against {cm(diff['ate_map_m'])} with two different pictures; "
            f"{forced['pairs_tried']} twin-view pairs forced: {forced['verified']} verified at "
            f"{forced['min_inliers']} inliers, at {relaxed['min_inliers']}: {relaxed['verified']} verified "
            f"({relaxed['verified_false']} false), {relaxed['kept_by_graph']} kept by the graph |")
    path = RESULTS / "map_relocalise_fr1_desk_grid.json"
    if path.is_file():
        r = json.loads(path.read_text())["relocalisation"]
        rows.append(
            f"| relocalisation in fr1/desk's map with its {r['field']} field, 40 random second-half frames, one thread"
            f"{', each with its twist by the visual odometry (as a run has it)' if r.get('with_twist') else ''} "
            f"(`map_relocalise_fr1_desk_grid.json`) | {r['within_5cm_3deg']}/{r['attempts']} within 5 cm / 3 deg, "
            f"{r['accepted_farther_than_10cm']} accepted beyond 10 cm, {r['refused']} refused; "
            f"{r['seconds_median']:.2f} s per attempt (p90 {r['seconds_p90']:.2f}, max {r['seconds_max']:.2f}) |")
    path = RESULTS / "orbslam3_fr1_desk.json"
    survey = RESULTS / "map_survey_fr1_desk.json"
    if path.is_file() and survey.is_file():
        o, m = json.loads(path.read_text())["summary"], json.loads(survey.read_text())
        rows.append(
            f"| fr1/desk first half, ORB-SLAM3 RGB-D with a vocabulary built from other images "
            f"(`orbslam3_fr1_desk.json`) against `nap3d-graph map` (`map_survey_fr1_desk.json`) | survey ATE cm, median "
            f"(range) of {o['a_survey_ate_rmse_m']['n']} runs: ORB-SLAM3 {_range_cm(o['a_survey_ate_rmse_m'])} "
            f"(lost at frame {o['a_survey_first_not_ok_frame']['median']:.0f}; before: "
            f"{_range_cm(o['a_survey_ate_before_first_loss_rmse_m'])}); map {cm(m['survey']['ate']['map']['rmse_m'])} |")
    return "\n".join(rows)


def _lost(states: dict) -> int:
    """Frames ORB-SLAM3 reported lost (RECENTLY_LOST or LOST; not the first frame's NO_IMAGES_YET)."""
    return sum(count for state, count in states.items() if "LOST" in state)


def orbslam3_trials_table() -> str:
    """Every ORB-SLAM3 trial of both files, each as it ran: frames tracked and lost, the
    first lost frame, the survey's ATE over what it saved and before its first loss, and
    (localisation mode) the query's ATE through the survey's alignment."""
    rows = ["| file | mode | trial | survey frames OK / lost | first lost | survey ATE cm (before first loss) | "
            "query frames OK / lost | query ATE cm via survey |", "|---|---|---:|---|---:|---|---|---:|"]
    for name in ORBSLAM3_FILES:
        path = RESULTS / name
        if not path.is_file():
            continue
        runs = json.loads(path.read_text())["runs"]
        for mode, trials in runs.items():
            for n, trial in enumerate(trials, 1):
                s, q = trial["survey"], trial.get("query")
                states = s["tracking_states"]
                first = s.get("first_not_ok_frame")
                before = s.get("ate_before_first_loss")
                query_cells = ("n/a", "n/a") if q is None else (
                    f"{q['tracking_states'].get('OK', 0)} / {q['lost_frames']}",
                    cm(q["ate_through_survey_alignment"]["rmse_m"]))
                rows.append(
                    f"| `{name}` | {mode} | {n} | {states.get('OK', 0)} / {_lost(states)} | "
                    f"{'none' if first is None else first} | {cm(s['ate']['rmse_m'])} "
                    f"({'n/a' if before is None else cm(before['rmse_m'])}) | {query_cells[0]} | {query_cells[1]} |")
    return "\n".join(rows)


#: Which data chose each default of the map and of starting in it (the values are read from the
#: code when the page is made). "Reported on it" marks a default chosen on a recording whose
#: figures the results page then reports: those figures are not held-out.
MAP_DEFAULT_TUNING = (
    ("mapping.build.MapSettings", "keyframe_every", "set when map was first written (no sweep recorded)"),
    ("mapping.build.MapSettings", "keyframe_distance_m", "set when map was first written (no sweep recorded)"),
    ("mapping.build.MapSettings", "keyframe_angle_deg", "set when map was first written (no sweep recorded)"),
    ("mapping.build.MapSettings", "vocabulary_k", "set when map was first written (no sweep recorded)"),
    ("mapping.build.MapSettings", "edge_floor_m", "set when map was first written (no sweep recorded)"),
    ("mapping.build.MapSettings", "edge_floor_rad", "set when map was first written (no sweep recorded)"),
    ("mapping.build.MapSettings", "gate_p", "a convention (chi-square 6 dof), not tuned"),
    ("mapping.build.MapSettings", "budget_minutes", "issue 48's target (300 frames in 5 minutes)"),
    ("mapping.build.MapSettings", "budget_reserve_s",
     "fr1/desk's whole recording, the stages after training (map_speed.json; reported on it)"),
    ("mapping.loops.LoopSettings", "min_inliers", "set when map was first written (no sweep recorded)"),
    ("mapping.loops.LoopSettings", "max_sigma_m", "set when map was first written (no sweep recorded)"),
    ("mapping.loops.LoopSettings", "max_sigma_deg", "set when map was first written (no sweep recorded)"),
    ("mapping.loops.LoopSettings", "proximity_m", "set when map was first written (no sweep recorded)"),
    ("mapping.bundle.BundleSettings", "disparity_to_pixel",
     "map_bundle sweeps on fr1/desk's first half and redkitchen against all three references "
     "(map_bundle_*.json; reported on them)"),
    ("mapping.bundle.BundleSettings", "baseline_m", "Kinect v1's specification (a .bag's own baseline replaces it)"),
    ("mapping.bundle.BundleSettings", "readout_s",
     "not tuned: None estimates each survey's readout from its own pixels, no ground truth read; the mechanism was "
     "found on fr1/desk's half maps (reported on them)"),
    ("mapping.bundle.BundleSettings", "admit_factor",
     "not tuned on a score: a margin over the kept loops' own reprojection spread (false loops land tens to hundreds "
     "of pixels off); the mechanism was found on fr1/desk's second half map (reported on it)"),
    ("mapping.bundle.BundleSettings", "readout_grid_s",
     "a search range, not tuned: no readout beyond a 30 Hz camera's frame period, with a step to spare"),
    ("mapping.relocalise.RelocaliseSettings", "min_agreeing",
     "fr1/desk's second half in its first half's map, where lone answers landed wrong (reported on it)"),
    ("mapping.relocalise.RelocaliseSettings", "top_k",
     "set when map was first written; 10 found no more on the tuning sets (map_relocalise_rules_*.json)"),
    ("mapping.relocalise.RelocaliseSettings", "neighbours",
     "simulated rooms 3, 5, 7 and fr1/xyz in maps of fr1/desk (map_relocalise_rules_*.json), held out from the "
     "results"),
    ("mapping.relocalise.RelocaliseSettings", "neighbour_m", "the benchmarks' own coverage radius (40 cm / 30 deg)"),
    ("mapping.relocalise.RelocaliseSettings", "shortlist",
     "chosen before any held-out score, on the mechanism; neutral on the tuning sets (map_relocalise_rules_*.json: "
     "nothing found or lost where the survey held)"),
    ("mapping.relocalise.RelocaliseSettings", "start_min_inliers",
     "simulated rooms 3, 5, 7 and fr1/xyz in maps of fr1/desk (map_relocalise_rules_*.json), held out from the "
     "results: more of room 3 found than at 30, nothing lost on fr1/xyz"),
    ("mapping.relocalise.RelocaliseSettings", "max_sigma_m", "set when map was first written (no sweep recorded)"),
    ("mapping.relocalise.RelocaliseSettings", "agree_m", "set with min_agreeing, on fr1/desk (reported on it)"),
    ("mapping.start.PlacementSettings", "confirmations", "the simulator and fr1/xyz (tests), held out from the results"),
    ("mapping.start.PlacementSettings", "agree_m", "the relocalisation's own agreement radius"),
)


def map_defaults_table() -> str:
    """Every default the map and a start in it depend on, its value as the code has it, and
    the data that chose it."""
    import importlib

    rows = ["| setting | default | chosen on |", "|---|---|---|"]
    for owner, name, why in MAP_DEFAULT_TUNING:
        module, cls = owner.rsplit(".", 1)
        value = getattr(getattr(importlib.import_module(f"nap3d_graph.{module}"), cls)(), name)
        rows.append(f"| `{cls}.{name}` | {value:g} | {why} |" if isinstance(value, (int, float))
                    else f"| `{cls}.{name}` | {value} | {why} |")
    rows.append(f"| `SevenScenesSequence(registration=...)` | {_sevenscenes_registration_default()} | 7-Scenes' "
                "kitchen, both halves (`map_registration_redkitchen.json`): its surveys kept the most loops and agreed "
                "best with their depth; **reported on that recording** |")
    return "\n".join(rows)


def _sevenscenes_registration_default() -> str:
    """The colour camera a 7-Scenes folder is read through unless told, as the code has it."""
    import inspect

    from nap3d_graph.datasets import SevenScenesSequence

    return str(inspect.signature(SevenScenesSequence.__init__).parameters["registration"].default)


def map_speed_table() -> str:
    """``nap3d-graph map`` from nothing with its defaults: wall time and each stage's."""
    rows = ["| recording | frames | field | wall s | within 5 min | odometry / keyframes / loops / graph s | "
            "field s: timing, train, error, total | survey ATE cm; orientation deg (median) |",
            "|---|---:|---|---:|---|---|---|---:|"]
    path = RESULTS / "map_speed.json"
    if not path.is_file():
        return "\n".join(rows)
    for r in json.loads(path.read_text())["runs"]:
        st, f = r["stages_s"], r["field_s"]
        rows.append(
            f"| {Path(r['data'].split(':')[0]).name}{'' if ':' not in r['data'] else ' ' + r['data'].split(':', 1)[1]} | "
            f"{r['frames']} | {r['model']} | {r['wall_s']:.0f} | {yes(r['wall_s'] <= 300.0)} | "
            f"{st['odometry']:.0f} / {st['keyframes']:.0f} / {st['loops']:.0f} / {st['graph']:.0f} | "
            f"{f['timing']:.0f}, {f['build_or_train']:.0f}, {f['field_error']:.0f}, {f['total']:.0f} | "
            f"{cm(r['survey_ate_m'])}; {_deg(r.get('survey_rotation_median_deg'))} |")
    return "\n".join(rows)


def _deg(value) -> str:
    return "n/a" if value is None else f"{value:.2f}"


START_ANYWHERE_FILES = ("map_start_anywhere_fr1_desk.json", "map_start_anywhere_redkitchen.json")


def start_anywhere_table() -> str:
    """Each direction of each recording's split: relocalisation of every n-th query frame and
    the query run from its own first frame; in brackets against a second ground truth (the
    SfM poses of 7-Scenes) where the file has one."""
    rows = ["| recording: survey -> query | survey ATE cm [SfM]; rolling shutter ms | relocalised: covered frames within 5 cm / 3 deg [SfM]; "
            "beyond 10 cm [SfM]; accepted where uncovered; s per attempt (median, p90, max) | fr1/xyz frames in the "
            "same map | run from its own first frame (ATEs: median over NAP3D's RANSAC seeds where several): placed at "
            "frame; ATE cm (causal) [SfM] | GT-posed map: ATE cm [SfM] | ratio [SfM] | SfM-posed map: ATE cm against "
            "SfM; ratio |", "|---|---|---|---|---|---|---|---|"]
    for name in START_ANYWHERE_FILES:
        path = RESULTS / name
        if not path.is_file():
            continue
        r = json.loads(path.read_text())
        recording = Path(r["data"]).name
        for d in r["directions"]:
            rl, run = d["relocalisation"], d["runs"]["self_posed"]
            xyz = d.get("relocalisation_rgbd_dataset_freiburg1_xyz")
            xyz_text = (f"{xyz['covered_found_within_5cm_3deg']}/{xyz['covered']}; {xyz['accepted_farther_than_10cm']}"
                        if xyz else "n/a")
            gt = d["runs"].get("gt_posed")
            second = "covered_found_within_5cm_3deg_second_gt" in rl

            def sfm(value, fmt=str):
                return f" [{fmt(value)}]" if second and value is not None else ""

            ratio = _ratio(d, "ratio_self_to_gt_posed") if gt else "n/a"
            rows.append(
                f"| {recording}: {d['survey']} -> {d['query']} | {cm(d['survey_ate_m'])}"
                f"{sfm(d.get('survey_ate_second_gt_m'), cm)}; {_ms(d.get('readout_s'))} "
                f"| {rl['covered_found_within_5cm_3deg']}{sfm(rl.get('covered_found_within_5cm_3deg_second_gt'))}"
                f"/{rl['covered']}; {rl['accepted_farther_than_10cm']}"
                f"{sfm(rl.get('accepted_farther_than_10cm_second_gt'))}; "
                f"{rl['accepted_uncovered']}; {rl['seconds_median']:.2f}, {rl['seconds_p90']:.2f}, {rl['seconds_max']:.2f} "
                f"| {xyz_text} "
                f"| {run['placed_at_frame'] if run['placed'] else 'never'}; {cm(run['ate_m'])} ({cm(run['ate_causal_m'])})"
                f"{sfm(run.get('ate_second_gt_m'), cm)} "
                f"| {cm(gt['ate_m']) if gt else 'n/a'}{sfm(gt.get('ate_second_gt_m') if gt else None, cm)} "
                f"| {ratio}{sfm(d.get('ratio_self_to_gt_posed_second_gt') and _ratio(d, 'ratio_self_to_gt_posed_second_gt'))} "
                f"| {_sfm_posed(d)} |")
    return "\n".join(rows)


def _ms(seconds) -> str:
    """A readout time in whole milliseconds; 'n/a' when the file predates it."""
    return "n/a" if seconds is None else f"{1000 * seconds:.0f}"


RULES_FILES = ("map_relocalise_rules_fr1_xyz.json", "map_relocalise_rules_sim.json")


def relocalise_rules_table() -> str:
    """Each variant of the relocaliser's rules on each tuning set: fr1/xyz in maps of fr1/desk,
    simulated rooms' traversals in maps of their mapping walks."""
    rows = ["| tuning set | rules | covered frames within 5 cm / 3 deg, all maps | per map | beyond 10 cm | refused | "
            "s per attempt: median, p90, max |", "|---|---|---|---|---|---|---|"]
    for r in filter(None, map(read, RULES_FILES)):
        tuning = (f"simulated rooms {', '.join(str(k) for k in r['simulated_rooms'])} (every {r['every']} frames)"
                  if "simulated_rooms" in r else f"{Path(r['query']).name} in {Path(r['data']).name}")
        for variant, t in r["totals"].items():
            per_map = ", ".join(f"{label}: {m['variants'][variant]['covered_found_within_5cm_3deg']}/"
                                f"{m['variants'][variant]['covered']}" for label, m in r["maps"].items())
            rows.append(f"| {tuning} | {variant} | {t['found']}/{t['covered']} | {per_map} | {t['beyond_10cm']} | "
                        f"{t['refused']}/{t['attempts']} | {t['seconds_median']:.2f}, {t['seconds_p90']:.2f}, "
                        f"{t['seconds_max']:.2f} |")
    return "\n".join(rows)


TURN_FILE = "ground_truths_turn_redkitchen.json"
SYSTEMATICS_FILE = "survey_systematics_fr1_desk.json"


def survey_systematics_table() -> str:
    """Each fr1/desk half map's survey ATE (evo) after an SE(3) alignment, after a Sim(3) one,
    and at the best of the clock offsets tried."""
    r = read(SYSTEMATICS_FILE)
    if not r:
        return "(not measured)"
    rows = ["| survey | frames | ATE cm, SE(3) | ATE cm, Sim(3) (scale) | best clock offset: ms, ATE cm | offsets tried, ms |",
            "|---|---|---|---|---|---|"]
    for name, m in r["maps"].items():
        tried = ", ".join(f"{float(o) * 1000:+.0f}" for o in m["offset_cm"])
        rows.append(f"| {name} half | {m['frames']} | {m['se3_cm']:.2f} | {m['sim3_cm']:.2f} ({m['sim3_scale']:.4f}) "
                    f"| {m['best_offset_s'] * 1000:+.0f}, {m['best_offset_cm']:.2f} | {tried} |")
    return "\n".join(rows)


FLOOR_FILES = ("survey_floor_fr1_desk.json", "survey_floor_redkitchen.json")


def _each_reference(ate_cm: dict) -> str:
    """``first [second]`` of a dict of ATEs in cm by reference name."""
    values = [f"{v:.2f}" for v in ate_cm.values()]
    return values[0] + (f" [{values[1]}]" if len(values) > 1 else "")


def survey_floor_table() -> str:
    """Each self-made map's keyframes as mapped, with the depth's disparity offset undone, at
    other focal lengths, and against references given a camera offset."""
    rows = ["| file | half | as mapped: ATE cm; pixel / disparity residual px | depth / images at the nearest and "
            "farthest bins, the median bin as 1 (median depth) | depth corrected: ATE cm; residuals px | focal scale: ATE cm; residuals px "
            "| reference camera offset: position ATE cm before → after; offset cm (x, y, z in the camera) "
            "| error cm: slow part (1 s) / fast rest; fastest-turning quarter / slowest (median deg/s) "
            "| the map's depth check: worst bin off, offset found (1/m), told; the same with an offset added |",
            "|---|---|---|---|---|---|---|---|---|"]
    for name in FLOOR_FILES:
        r = read(name)
        for half, m in r.get("maps", {}).items():
            base, depth, fit = m["as_mapped"], m["depth_offset"], m["depth_offset"]["fit"]
            near, far = fit["bins"][0], fit["bins"][-1]  # nearest first
            focal = "; ".join(f"x{f['scale']:g}: {_each_reference(f['ate_cm'])}, {f['residual_px']:.3f} / "
                              f"{f['residual_disparity_px']:.3f}" for f in m["focal"])
            offset = "; ".join(f"{o['ate_position_cm']:.2f} → {o['ate_with_offset_cm']:.2f}, "
                               f"({', '.join(f'{v:+.1f}' for v in o['offset_cm'])})"
                               for o in m["camera_offset"].values())
            structure = "; ".join(f"{e['slow_cm']:.2f} / {e['fast_cm']:.2f}; {e['fastest_quarter_cm']:.2f} "
                                  f"({e['fastest_quarter_deg_s']:.0f}) / {e['slowest_quarter_cm']:.2f} "
                                  f"({e['slowest_quarter_deg_s']:.0f})" for e in m.get("error_structure", {}).values())
            checks = "; ".join(f"{'as measured' if float(added) == 0 else f'+{added}'}: {c['worst']:.1%}, "
                               f"{c['intercept_per_m']:+.3f}, {'told' if c['bad'] else 'not told'}"
                               for added, c in m.get("depth_check", {}).items() if c.get("worst") is not None)
            rows.append(f"| `{name}` | {half} | {_each_reference(base['ate_cm'])}; {base['residual_px']:.3f} / "
                        f"{base['residual_disparity_px']:.3f} | {near[1]:.3f} at {near[0]:.2f} m, {far[1]:.3f} at "
                        f"{far[0]:.2f} m ({fit['median_depth_m']:.2f} m) | {_each_reference(depth['ate_cm'])}; "
                        f"{depth['residual_px']:.3f} / {depth['residual_disparity_px']:.3f} | {focal} | {offset} "
                        f"| {structure or 'n/a'} | {checks or 'n/a'} |")
    return "\n".join(rows) if len(rows) > 2 else "(not measured)"


BUNDLE_FILES = ("map_bundle_fr1_desk.json", "map_bundle_redkitchen.json")


def bundle_weight_table() -> str:
    """The survey's keyframes re-adjusted at each depth weight, the rolling shutter ignored and
    undone, against every reference the recording has."""
    rows = ["| file | disparity noise / pixels' | adjustment | readout ms | loops admitted | pixel residual px | "
            "ATE cm against: ground truth [second] |", "|---|---|---|---|---|---|---|"]
    for name in BUNDLE_FILES:
        r = read(name)
        if not r:
            continue
        rows.append(f"| `{name}` | n/a | pose graph alone | n/a | n/a | n/a | {_references_cm(r['pose_graph'])} |")
        for b in r["bundle"]:
            rows.append(f"| `{name}` | {b['disparity_to_pixel']:g} | {b.get('readout', 'global shutter')} "
                        f"| {_ms(b.get('readout_s', 0.0))} | {b.get('loops_admitted', 0)} | {b['residual_px']:.3f} "
                        f"| {_references_cm(b)} |")
    return "\n".join(rows)


def _references_cm(scores: dict) -> str:
    """``first [second]`` ATE in cm of a row scored against one or two references."""
    first = cm(scores["ground truth"]["rmse_m"])
    second = scores.get("second ground truth")
    return first + (f" [{cm(second['rmse_m'])}]" if second else "")


def ground_truths_turn_table() -> str:
    """7-Scenes' two ground truths against each other, and each self-made map against both:
    translation RMSE and the orientation errors after the SE(3) alignment."""
    r = read(TURN_FILE)
    if not r:
        return "(not measured)"
    rows = ["| trajectory | against | ATE cm | orientation deg: median, p90, max | one turn common to every camera, deg |",
            "|---|---|---|---|---|"]

    def row(name, against, e):
        rows.append(f"| {name} | {against} | {cm(e['rmse_m'])} | {e['rotation_median_deg']:.2f}, "
                    f"{e['rotation_p90_deg']:.2f}, {e['rotation_max_deg']:.2f} | {e['rotation_common_deg']:.2f} |")

    row("SfM poses, every shared frame", "KinectFusion", r["sfm_against_kinectfusion"])
    for frames, m in r["maps"].items():
        row(f"self-made map of frames {frames}", "KinectFusion", m["kinectfusion"])
        row(f"self-made map of frames {frames}", "SfM", m["sfm"])
    return "\n".join(rows)


def _sfm_posed(direction: dict) -> str:
    """The run on the map posed by the second ground truth, against it, and the self-made
    map's run over it ("n/a" without one)."""
    run = direction["runs"].get("sfm_posed")
    if run is None or run.get("ate_second_gt_m") is None:
        return "n/a"
    return f"{cm(run['ate_second_gt_m'])}; {_ratio(direction, 'ratio_self_to_sfm_posed_second_gt')}"


def _ratio(direction: dict, key: str) -> str:
    """A ratio of run ATEs (of their medians over the RANSAC seeds), with its range over the
    seeds where the file has several."""
    seeds = direction.get(f"{key}_per_seed") or []
    spread = f" ({min(seeds):.2f}-{max(seeds):.2f} over {len(seeds)} seeds)" if len(seeds) > 1 else ""
    return f"{direction[key]:.2f}{spread}"


def sevenscenes_registration_table() -> str:
    """7-Scenes' colour camera: the nominal one, and estimated with each pair's motion from the
    images or from the pose files; NAP3D real-vs-real under each, against the ground truth's
    relative poses."""
    r = json.loads((RESULTS / "sevenscenes_registration.json").read_text())
    rows = ["| pair motion from | colour f px | centre px | keypoints | residual px (nominal) | NAP3D pairs aligned | "
            "pair error cm: median, p90, max | deg: median, p90 |", "|---|---|---|---|---|---|---|---|"]
    for poses, label in (("nominal", "nothing estimated: the Kinect v1's nominal camera (the default)"),
                         ("images", "the depth images (depth-only ICP; registration='images': no pose file read)"),
                         ("recording", "the recording's pose files (its ground truth)")):
        if poses not in r["registrations"]:
            continue
        e = r["registrations"][poses]
        c, cm, deg = e["colour"], e["pair_error_cm"], e["pair_error_deg"]
        rows.append(f"| {label} | {c['fx']:.1f} | ({c['cx']:.1f}, {c['cy']:.1f}) | {e['matches']} | "
                    f"{_fit_residual(e)} | {e['pairs_aligned']}/{e['pairs']} | "
                    f"{cm['median']:.2f}, {cm['p90']:.2f}, {cm['max']:.2f} | {deg['median']:.3f}, {deg['p90']:.3f} |")
    return "\n".join(rows)


REGISTRATION_FILE = "map_registration_redkitchen.json"
REGISTRATION_LABELS = {"nominal": "nominal (the default)", "images": "from the images",
                       "poses": "from the pose files (reads ground truth)"}


def map_registration_table() -> str:
    """Each half of 7-Scenes' kitchen surveyed through each colour camera: the survey's own
    figures, then its odometry's and its poses' ATE against both references."""
    r = read(REGISTRATION_FILE)
    rows = ["| colour camera | half | f px, centre | loops kept / turned away / admitted | bundle residual mrad: "
            "pixel, disparity | readout ms | odometry ATE cm: KinectFusion / SfM | survey ATE cm: KinectFusion / SfM |",
            "|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        c = row["colour"]
        rows.append(f"| {REGISTRATION_LABELS.get(row['registration'], row['registration'])} | {row['frames']} | "
                    f"{c['fx']:.1f}, ({c['cx']:.1f}, {c['cy']:.1f}) | {row['loops_kept']} / "
                    f"{row['loops_turned_away']} / {row['loops_admitted']} | {row['residual_mrad']:.3f}, "
                    f"{row['residual_disparity_mrad']:.3f} | {_ms(row['readout_s'])} | "
                    f"{cm(row['odometry']['KinectFusion']['rmse_m'])} / {cm(row['odometry']['SfM']['rmse_m'])} | "
                    f"**{cm(row['survey']['KinectFusion']['rmse_m'])} / {cm(row['survey']['SfM']['rmse_m'])}** |")
    return "\n".join(rows)


REGISTRATION_FIELD_FILE = "map_registration_field_redkitchen.json"


def map_registration_field_table() -> str:
    """Each half of the kitchen mapped with its field through each colour camera: what the
    field says of the images on survey frames it did not train on, then the survey's ATE."""
    r = read(REGISTRATION_FIELD_FILE)
    rows = ["| colour camera | half | f px | loops kept / turned away | bundle residual mrad: pixel, disparity | "
            "held-out frames: PSNR dB (affine), median depth error cm | NAP3D of held-out frames: failed, median "
            "distance from the map's pose cm | survey ATE cm: KinectFusion / SfM |", "|---|---|---|---|---|---|---|---|"]
    for row in r["rows"]:
        held, nap = row["field"]["held_out"] or {}, row["field"]["held_out_nap3d"] or {}
        rows.append(f"| {REGISTRATION_LABELS.get(row['registration'], row['registration'])} | {row['frames']} | "
                    f"{row['colour']['fx']:.1f} | {row['loops_kept']} / {row['loops_turned_away']} | "
                    f"{row['residual_mrad']:.3f}, {row['residual_disparity_mrad']:.3f} | "
                    f"{held.get('psnr_affine_db', float('nan')):.2f}, {cm(held.get('depth_median_m'))} | "
                    f"{nap.get('failed', 'n/a')} of {nap.get('frames', 0)}, {cm(nap.get('median_m'))} | "
                    f"{cm(row['survey']['KinectFusion']['rmse_m'])} / {cm(row['survey']['SfM']['rmse_m'])} |")
    return "\n".join(rows)


def _fit_residual(entry: dict) -> str:
    """An estimated registration's residual (and the nominal camera's); n/a where none was fitted."""
    fitted, start = entry.get("residual_px"), entry.get("start_residual_px")
    if fitted is None or fitted != fitted:  # NaN: given, not fitted
        return "n/a (not fitted)"
    return f"{fitted:.2f} ({start:.2f})"


def _row_value(rows: list, prefix: str) -> str:
    return next((value for figure, value, *_ in rows if figure.startswith(prefix)), "n/a")


def report_faults_table() -> str:
    """Faults injected into a real map and real runs, each report's verdicts and figures."""
    r = json.loads((RESULTS / "report_faults_fr1_desk.json").read_text())
    rows = ["| case | report | past its bad line | loop residual median / p90 / max cm | verified loops turned away; "
            "missed by the final poses | mesh walls cm | held-out PSNR dB; NAP3D failed, median cm | accepted of "
            "covered; coverage; gate d2 median | placed | ATE cm (reference) |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for name, m in r["map"].items():
        v = m["values"]
        loop, held, nap = v.get("loop_residual", {}), v.get("held_out", {}), v.get("held_out_nap3d", {})
        field = (f"{held.get('psnr_affine_db', float('nan')):.1f}; {nap.get('failed', 'n/a')} of "
                 f"{nap.get('frames', 0) + nap.get('failed', 0)}, {cm(nap.get('median_m'))}" if held
                 else "no field (the map's was trained at other poses)")
        rows.append(f"| {name} | map | {'; '.join(m['past_bad_line']) or 'nothing'} | "
                    f"{cm(loop.get('median_m'))} / {cm(loop.get('p90_m'))} / {cm(loop.get('max_m'))} | "
                    f"{_turned_away_cell(v)} | {cm(v.get('wall_thickness_m'))} | {field} | | | "
                    f"{_map_fault_ate(m, v)} |")
    for name, run in r["runs"].items():
        if "rows" not in run:
            rows.append(f"| {name} | run | refused: {run.get('error', '')} | | | | | | | |")
            continue
        d2 = _row_value(run["rows"], "gate consistency").split(" over ")[0]
        placed = _row_value(run["rows"], "placed in the map")
        # Never placed, the run's poses are in its own frame: only an SE(3)-aligned ATE means anything.
        ate = (f"{cm(run.get('ate_se3_aligned_m'))} (SE(3)-aligned: never placed)" if placed == "never"
               else cm(run.get("ate_m")))
        rows.append(f"| {name} | run | {'; '.join(run['past_bad_line']) or 'nothing'} | | | | | "
                    f"{_row_value(run['rows'], 'corrections accepted')}; {_row_value(run['rows'], 'map coverage')}; "
                    f"{d2} | {placed} | {ate} |")
    warned = r.get("depth_unit_warning_before_work") or []
    rows.append("")
    rows.append("Before any work, the query read at 1000 units per metre: " +
                (f"warned (\"{warned[0].split(':')[0]}\")" if warned else "not warned") + ".")
    return "\n".join(rows)


def _turned_away_cell(values: dict) -> str:
    """'turned away; missed' of a map report's values ('-' where the file predates the figure)."""
    turned = values.get("turned_away")
    return "-" if turned is None else f"{turned['loops']}; {turned['missed']}"


def _map_fault_ate(case: dict, values: dict) -> str:
    """A map case's reference ATE: the keyframes' at the graph's and at the final poses where
    the case solved them again, else the survey's."""
    scores = case.get("scores")
    if scores is None:
        return f"{cm(values.get('survey_ate_m'))} (survey)"
    return (f"keyframes {cm(scores['keyframes_ate_graph_m'])} at the graph's poses, {cm(scores['keyframes_ate_final_m'])}"
            f" after the bundle ({scores['loops_kept']} loops kept, {scores['loops_admitted']} admitted)")


def correction_correlation_table() -> str:
    """Corrections against the ground truth in fields posed by it: honest, and alike from one
    keyframe to the next."""
    r = read("correction_correlation.json")
    rows = ["| run (fields posed by the ground truth, second half, --odom vo) | corrections | gate d2 median "
            "(band 0.87-16.8) | NEES against the ground truth under their own covariance: median, mean, p90 "
            "(honest: 5.35, 6) | error rms / covariance sigma, mrad (rx ry rz) and mm (tx ty tz) | lag-1 correlation "
            "of consecutive corrections' errors (rx ry rz tx ty tz) |",
            "|---|---|---|---|---|---|"]
    for name, c in (r.get("cases") or {}).items():
        n, rms, sig = c["nees_against_ground_truth"], c["error_rms_mrad_mm"], c["sigma_median_mrad_mm"]
        errors = " ".join(f"{rms[a]:.1f}/{sig[a]:.1f}" for a in rms)
        lag = " ".join(f"{v:.2f}" for v in c["lag1_correlation"].values())
        rows.append(f"| {name} ({Path(c['data']).name}) | {c['corrections']} | {c['gate_d2']['median']:.2f} | "
                    f"{n['median']:.2f}, {n['mean']:.2f}, {n['p90']:.2f} | {errors} | {lag} |")
    return "\n".join(rows)


def _spread_cell(spread: dict | None) -> str:
    """'median (p10, p90)' of a spread, '-' where the file has none."""
    return "-" if not spread else f"{spread['median']:.2f} ({spread['p10']:.2f}, {spread['p90']:.2f})"


def odometry_consistency_table() -> str:
    """NEES of the feature odometry against the ground truth over intervals of frames."""
    r = read("odometry_consistency.json")
    rows = [f"consistent: NEES median {r.get('chi2_6_median')}", "",
            "| recording (frames; steps without features) | interval, frames | NEES median (p10, p90): steps chained "
            "as independent | with the drift model | as the run chains them (frames' own noise cancelling) | with the "
            "drift model (the run's prediction) | error mm per axis, median | the old chain's sigma mm per axis, "
            "median | NEES median, chained steps with this share of each step's covariance its frames' own noise |",
            "|---|---|---|---|---|---|---|---|---|"]
    for name, rec in (r.get("recordings") or {}).items():
        for row in rec["intervals"]:
            a, d = row["nees_steps_alone"], row["nees_with_drift"]
            ra, rd = (_spread_cell(row.get(k)) for k in ("nees_run_interval_alone", "nees_run_interval_with_drift"))
            mark = " (the run's)" if row["frames"] == r.get("keyframe_every") else ""
            shares = ", ".join(f"{f}: {v['median']:.2f}" for f, v in (row.get("nees_by_frame_share") or {}).items())
            rows.append(f"| {name} ({rec['frames']}; {rec['steps_without_features']}) | {row['frames']}{mark} | "
                        f"{a['median']:.2f} ({a['p10']:.2f}, {a['p90']:.2f}) | {d['median']:.2f} ({d['p10']:.2f}, "
                        f"{d['p90']:.2f}) | {ra} | {rd} | {row['error_mm_per_axis']['median']:.1f} | "
                        f"{row['sigma_mm_per_axis']['median']:.1f} | {shares or '-'} |")
    return "\n".join(rows)


SECTIONS = [
    Section("A map from the camera alone against maps posed by ground truth (first half the survey, second half the "
            "query, --odom vo, XFeat, splat fields; in brackets against 7-Scenes' second ground truth, the SfM poses)",
            MAP_SURVEY_FILES, "python benchmarks/map_survey.py [--data D --out ...]", map_survey_table),
    Section("The map's checks: twin pictures, relocalisation, ORB-SLAM3 beside it",
            ("map_false_loops.json", "map_relocalise_fr1_desk_grid.json", "orbslam3_fr1_desk.json"),
            "python benchmarks/map_false_loops.py; python benchmarks/map_survey.py --only-relocalise ...; "
            "python benchmarks/orbslam3/compare.py", map_checks_table),
    Section("The relocaliser's rules on their tuning sets: every frame of fr1/xyz in maps of fr1/desk (the whole "
            "recording and each half; map's defaults, grid field), and simulated rooms' traversals in splat maps of "
            "their mapping walks; one thread, scored through the survey's alignment",
            RULES_FILES, "python benchmarks/map_relocalise_rules.py (--data D --query Q | --simulate ROOM ...) --work W "
            "--out ...",
            relocalise_rules_table,
            note="The default is the variant chosen here. fr1/xyz stays near the desk the surveys saw; a simulated "
                 "traversal leaves the mapping walk's path, so its frames stand as far from the survey's keyframes "
                 "as a new run's start does. Where a room's survey odometry lost the camera, its map holds part of "
                 "the walk (map.json's segment), and few of the traversal's frames are found whatever the rules. "
                 "The relocalisation figures elsewhere on this page are on data these rules never saw, except the "
                 "start-anywhere table's fr1/xyz column: that is a tuning set, in maps of fr1/desk's halves."),
    Section("The map's defaults and the data that chose them", (), "python benchmarks/tables.py --write",
            map_defaults_table,
            note="Read from the code when this page is made. A default chosen on a recording this page reports is "
                 "marked: its figures there are not held-out. Defaults set when the map was first written were "
                 "not swept on any recording."),
    Section("How long a map takes: `nap3d-graph map` from nothing with its defaults (grid field trained for what "
            "the 5-minute budget leaves) on two cores",
            ("map_speed.json",), "python benchmarks/map_speed.py --data D [--data D:START:STOP] --out ...",
            map_speed_table,
            note="The target is 300 frames in 5 minutes, field included. The grid trains for what the budget "
                 "leaves once the stages before it ran, so a recording shorter than 300 frames is not scaled up: "
                 "what its earlier stages did not spend, the training spends. What keeps the wall time under the "
                 "budget is the reserve for the stages after training (`MapSettings.budget_reserve_s`)."),
    Section("ORB-SLAM3 RGB-D on fr1/desk at 15 Hz, every trial of both files: the first half as the survey "
            "(mode survey: SLAM alone; mode localise: SLAM, then the second half localised in its saved atlas)",
            ORBSLAM3_FILES, "python benchmarks/orbslam3/compare.py --data D --vocab V --work W --out ...",
            orbslam3_trials_table,
            note="A frame that is not OK is lost (RECENTLY_LOST or LOST); the survey's ATE is over the frames its "
                 "saved trajectory holds, SE(3)-aligned; the query's through the survey's own alignment."),
    Section("Starting anywhere in the map: a recording split in halves (fr1/desk, 7-Scenes' kitchen), each half the "
            "survey in turn, the other relocalised (every 5th frame, one thread) and run from its own first frame "
            "(--odom vo, XFeat, splat fields); the placement rule was chosen on fr1/xyz and the simulator",
            START_ANYWHERE_FILES,
            "python benchmarks/map_start_anywhere.py --data D [--extra-query X] [--traj 7scenes --second-gt SFM] "
            "--work W --out ...", start_anywhere_table,
            note="Each relocalised frame is given the camera's twist by the visual odometry's step into it, as a run "
                 "in the map has it at a keyframe, so its rolling shutter and depth instant are undone (the "
                 "relocaliser's `twist`)."),
    Section("7-Scenes' two ground truths turn the cameras apart: the SfM poses against KinectFusion's, and the "
            "kitchen's self-made maps (the start-anywhere benchmark's halves) against both",
            (TURN_FILE,), "python benchmarks/ground_truths_turn.py --data D --second-gt SFM --map FRAMES=MAP ... --out ...",
            ground_truths_turn_table,
            note="A relocalisation is scored against a 3 deg bound; against a reference whose orientations "
                 "disagree with the images' by this much, a correct answer can miss it. That is why the kitchen's "
                 "relocalisation is reported against both references."),
    Section("Could one systematic error explain the fr1/desk survey's ATE? Each half's self-made map (the "
            "start-anywhere benchmark's) against the motion capture with evo: SE(3), Sim(3) (a wrong metre), and the "
            "survey's stamps shifted (a clock offset)",
            (SYSTEMATICS_FILE,), "python benchmarks/survey_systematics.py --data D --map NAME=MAP ... --out ...",
            survey_systematics_table,
            note="Neither a scale nor a clock offset takes the ATE far below the SE(3) figure: what is left is "
                 "per-frame error. One cause of it was systematic after all, and is now undone: the colour "
                 "camera's rolling shutter (the bundle adjustment's table below)."),
    Section("What else could hold the survey above 1 cm? Each self-made map (the start-anywhere benchmark's halves) "
            "with the depth's disparity offset fitted from the survey's own triangulation and undone, with its focal "
            "length scaled, against references given a camera offset, and where the rest of its error is; in brackets "
            "and after a semicolon: against 7-Scenes' SfM poses",
            FLOOR_FILES, "python benchmarks/survey_floor.py --data D [--second-gt SFM] --map NAME=MAP ... --out ...",
            survey_floor_table,
            note="The depth fit needs no ground truth: matches seen 8 degrees apart or more are triangulated from "
                 "their pixels and the map's poses, and the depth the sensor measured is compared with it. The "
                 "bundle adjustment is solved again with the depths corrected (the median depth kept), and the "
                 "focal lengths at the readout the map chose. The camera offset is fitted to each reference: "
                 "a real one would be the same vector in both halves of a recording."),
    Section("How much should the survey's bundle adjustment trust the depth, and does the rolling shutter change it? "
            "The keyframes of each first-half map re-adjusted at each weight of the disparity: the colour camera as a "
            "global shutter over the graph's loops, its rolling shutter undone, and that with the loops the graph "
            "turned away but whose matches agree admitted (map's default); in brackets against 7-Scenes' SfM poses",
            BUNDLE_FILES, "python benchmarks/map_bundle.py --map M --data D --frames 0:0.5 [--second-gt SFM] --out ...",
            bundle_weight_table,
            note="The map's depth weight (`BundleSettings.disparity_to_pixel`) was chosen on these sweeps before the "
                 "rolling shutter was undone, on the recordings the results page reports (the defaults table says "
                 "so)."),
    Section("Which colour camera a 7-Scenes survey is read through: each half of the kitchen mapped (field left "
            "out) through the Kinect v1's nominal colour camera and through the camera estimated from the images or "
            "from the pose files; the survey's own figures first, then both references",
            (REGISTRATION_FILE,),
            "python benchmarks/map_registration.py --data D --second-gt SFM --work W --out ...",
            map_registration_table,
            note="The survey's own figures need no ground truth: loops the pose graph kept and turned away, and how "
                 "well its colour and depth agree after the bundle adjustment (as angles, so cameras of different "
                 "focal lengths compare). The nominal camera became the default on this recording, the only "
                 "7-Scenes data here, so its figures are not held-out evidence for that choice."),
    Section("The same with each half's field (the map's defaults): what the field trained through each colour "
            "camera says of the survey frames it did not train on",
            (REGISTRATION_FIELD_FILE,),
            "python benchmarks/map_registration.py --data D --second-gt SFM --work W --field --registrations nominal "
            "images --out ...", map_registration_field_table,
            note="A colour camera read with the wrong focal length puts each frame's colour and its warped depth "
                 "apart; a field trained on them renders held-out frames worse and aligns them worse. These figures "
                 "need no ground truth; the ATE columns are the scores, beside them, not what chose."),
    Section("7-Scenes' colour camera from the images alone (redkitchen, 500 shared frames): each frame pair's motion "
            "by depth-only ICP instead of the pose files, and what it does to NAP3D real-vs-real (SIFT, frames 4 apart "
            "every 25, against the ground truth's relative pose)",
            ("sevenscenes_registration.json",),
            "python benchmarks/sevenscenes_registration.py --data D --out ...", sevenscenes_registration_table),
    Section("Do the reports tell a failure? Faults injected into fr1/desk's first-half map and its second half run in "
            "it (15 Hz, splat, XFeat): a blurred field, a false loop forced into the pose graph and the bundle adjustment "
            "run after it as map runs it (against the same solves without it), the query's depth read at 1000 units "
            "per metre, 7-Scenes' kitchen run in the desk's map, the corrections' covariances 10x too cautious and "
            "10x too confident; the bad lines were set from what each figure is (held-out PSNR: from fr1/desk's own "
            "maps)",
            ("report_faults_fr1_desk.json",),
            "python benchmarks/report_faults.py --desk D --kitchen K --map M --work W --out ...", report_faults_table,
            note="A false loop forced into the pose graph alone does not reach the map: the bundle adjustment solves "
                 "the keyframes again from the images and takes back the loops the bent graph turned away (the ATE "
                 "column). A look-alike place's loop brings matches that agree with the false pose into the bundle "
                 "too, and bends the map; the map turns away the true loops that disagree with the bend, and the "
                 "verified loops it turned away and misses are the figure that tells it (the mesh's walls move "
                 "too). The covariance cases scale the corrections' covariances (NAP3D's and the field's); the "
                 "gate's d2 weighs a correction against the odometry's prediction under both covariances, and "
                 "where the prediction is as uncertain as the corrections' errors, ten times smaller correction "
                 "covariances move the median d2 without taking it past the chi-square's 99% point: the report "
                 "cannot tell that case (docs/limits.md)."),
    Section("The feature odometry's covariance against the ground truth over intervals of frames (every frame of "
            "the recording, 320 px wide): the prediction the run's gate compares a correction with",
            ("odometry_consistency.json",),
            "python benchmarks/odometry_consistency.py --data D1 D2 D3 --out ...", odometry_consistency_table,
            note="A consistent covariance puts the NEES median at the chi-square's (6 dof); below it, the "
                 "covariance is too cautious. One step's covariance is about right on the real recordings; chained "
                 "as if the steps' errors were independent (the run before 4283ecb), it grows over an interval far "
                 "faster than the error does: a frame's own error enters the step into it and the step out of it "
                 "with opposite signs. The run now chains them as `motion/interval.py` (IntervalCovariance) says: "
                 "each step's disagreement with constant velocity is its two frames' own registration noise, which "
                 "cancels inside the interval and stays at its two ends, and the alignment's own covariance adds up "
                 "step by step. The run's default keyframe interval is marked. The last column chains the steps as "
                 "if a fixed share of each whole step's covariance were the frames' noise (frame_noise_chain): no "
                 "one share fits every recording, where the split by constant velocity needs no share. These "
                 "recordings are the interval model's tuning data: the simulated walk (`nap3d-graph simulate ... "
                 "--count 300 --path traverse --scene-seed 3 --seed 2`, 30 Hz), fr1/desk at 15 Hz, the kitchen's "
                 "first 500 frames and the fr1/xyz frames."),
    Section("Why a clean run's gate can still read too cautious: its corrections against the ground truth, in fields "
            "posed by it",
            ("correction_correlation.json",),
            "python benchmarks/correction_correlation.py --case NAME,TRAJ,DATA,FRAMES,FIELD ... --work W --out ...",
            correction_correlation_table,
            note="The gate weighs a correction's innovation (the correction against the odometry's prediction). "
                 "Against the ground truth the corrections' covariance is about honest, but consecutive "
                 "corrections' errors are alike: the field's error is shared by neighbouring keyframes, and the "
                 "prediction carries the previous correction's, so the innovation cancels what they share and "
                 "the gate's d2 reads lower than the corrections' errors are. The fields are map_survey.py's "
                 "ground-truth-posed ones (its --work's gt_field.pt)."),
]
