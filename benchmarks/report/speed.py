"""Speed: real time on fr1/desk, odometry, the graph, stage timings, reading recordings, a sweep on two workers and the grid on a GPU: sections of ``docs/results.md`` read from the benchmarks' result files
(``benchmarks/results/``). Every figure comes out of its file; a key a file lacks reads ``n/a``,
and so does every figure of a missing file.
"""

from __future__ import annotations

from report import Section, cm, count, frac, get, list_span, mm, ms, num, number, pair, pct, read, table, yes

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
    if (number(r, "land_within_s") or 0) > 0:
        words.append("land within a frame")
    if r.get("render_ahead"):
        words.append(f"render ahead ({pct(number(r, 'rendered_ahead_fraction'))} made ahead)")
    if r.get("keyframe_when_idle"):
        words.append("keyframe when idle")
    if r.get("read_ahead") == 0:
        words.append("no read-ahead")
    return ", ".join(words)


def _realtime_row(name: str, d: dict, r: dict) -> list[str]:
    """One run setting (the median run of its repeats; ranges over the repeats beside)."""
    rate, speed = number(d, "camera_rate_hz"), number(r, "pace_speed")
    stages = get(r, "ms_per_keyframe") or {}
    render = next((v for v in (number(stages, k, "median") for k in ("render", "render_beside", "render_ahead")) if v),
                  None)
    ratios = get(r, "vs_library_threads_1_repeats") or get(r, "overlapped_vs_inline_repeats")
    late = get(r, "frames_late")
    ate = list_span(get(r, "ate_m_repeats"), cm) if get(r, "ate_m_repeats") else cm(number(r, "ate_m"))
    causal = get(r, "causal_ate_m_repeats")
    return [f"{_realtime_mode(r)} `{name}`", f"{get(d, 'matcher') or 'n/a'}, {get(r, 'field') or 'n/a'}",
            "-" if speed is None or rate is None else num(rate * speed, 1),
            f"{count(number(r, 'keyframe_every'))} ({num(number(r, 'keyframe_interval_mean'), 1)})",
            num(number(r, "frames_per_s"), 1),
            list_span(get(r, "frames_per_s_repeats"), lambda v: num(v, 1)) if "frames_per_s_repeats" in r else "-",
            list_span(ratios) if ratios else "-",
            ms(number(r, "behind_camera_s", "max"), 0) if get(r, "behind_camera_s") else "-",
            pair(num(number(late, "median"), 1), count(number(late, "max"))) if late else "-",
            pair(num(number(stages, "measure", "median"), 0), num(number(stages, "measure", "p90"), 0)), num(render, 0), ate,
            list_span(causal, cm) if causal else cm(number(r, "causal_ate_m")),
            frac(number(r, "accepted"), number(r, "keyframes"))]


def realtime_table() -> str:
    """Every run setting of both real-time files."""
    rows = []
    for name in REALTIME_FILES:
        d = read(name)
        rows += [_realtime_row(name, d, r) for r in get(d, "runs") or []]
    return table(REALTIME_HEADER, rows)


# --- odometry on fr1/desk ------------------------------------------------------------------------------------

ODOMETRY_HEADER = ["odometry (file)", "steps / failed", "step ms p50 / p90", "read ms p50", "detection ms p50",
                   "matching ms p50", "RANSAC / refinement ms p50", "dense solve ms p50", "frame/s",
                   "step against detecting once", "ATE cm", "final / max error cm"]


def _profile_rows() -> list[list[str]]:
    """odometry_profile_fr1_desk.json: one step's stages, one thread."""
    name = "odometry_profile_fr1_desk.json"
    d = read(name)
    size = "x".join(str(v) for v in get(d, "resolution") or []) or "n/a"
    rows = []
    for kind, o in (get(d, "odometries") or {}).items():
        s = get(o, "stages") or {}

        def p50(stage, s=s):
            """A stage's median, ``-`` where this odometry has no such stage."""
            return num(number(s, stage, "p50_ms"), 1) if stage in s else "-"

        rows.append([f"{kind}, {size} `{name}`", pair(count(number(o, "steps")), "n/a"),
                     pair(num(number(o, "step", "p50_ms"), 1), num(number(o, "step", "p90_ms"), 1)),
                     num(number(o, "read", "p50_ms"), 1), p50("detect"), p50("match"), pair(p50("ransac"), p50("refine")),
                     p50("solve"), num(number(o, "frames_per_s_at_p50"), 1),
                     num(number(o, "step_p50_vs_detecting_once")) if "step_p50_vs_detecting_once" in o else "-",
                     "n/a", "n/a"])
    return rows


def _vo_rows() -> list[list[str]]:
    """vo_fr1_desk.json: whole runs of each odometry alone, with its drift."""
    name = "vo_fr1_desk.json"
    rows = []
    for kind, o in (get(read(name), "odometry") or {}).items():
        rows.append([f"{kind} `{name}`", pair(count(number(o, "frames")), count(number(o, "failed_steps"))),
                     pair(num(number(o, "step_ms", "median"), 1), num(number(o, "step_ms", "p90"), 1)),
                     num(number(o, "read_ms", "median"), 1), "n/a", "n/a", "n/a", "n/a", num(number(o, "frames_per_s"), 1),
                     "-", cm(number(o, "ate_m")), pair(cm(number(o, "final_error_m")), cm(number(o, "max_error_m")))])
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
    for run, r in (get(read(name), "runs") or {}).items():
        for est, e in (get(r, "estimators") or {}).items():
            res = list((get(e, "rows") or {}).values())
            rows.append([f"{run.replace('_', ' frames, ')} path `{name}`", count(number(r, "keyframes")), est,
                         num(number(e, "step_ms_mean"), 3), num(number(e, "step_ms_p99"), 3), num(number(e, "final_s"), 3), "-",
                         "-", " / ".join(cm(number(x, "ate_rmse_m")) for x in res) or "n/a",
                         " / ".join(num(number(x, "nees_mean")) for x in res) or "n/a"])
    return rows


def _graph_window_rows() -> list[list[str]]:
    """graph_window.json: iSAM2 per keyframe (median over the last thousand), memory and the final solve."""
    name = "graph_window.json"
    rows = []
    for r in get(read(name), "runs") or []:
        window = number(r, "graph_window")
        label = (f"window {count(window)}, {'retiring' if r.get('retire') else 'keeping'} the final frames"
                 if window else "every keyframe kept")
        per_k, rss = get(r, "isam_ms_median_per_1000_keyframes") or {}, list((get(r, "rss_mb_at") or {}).values())
        rows.append([f"{label} `{name}`", count(number(r, "keyframes")), "iSAM2",
                     num(number(list(per_k.values()), -1), 2), num(number(r, "isam_ms_p90_last_1000"), 2),
                     num(number(r, "final_solve_s"), 2), pair(num(number(rss, 0), 1), num(number(rss, -1), 1)),
                     count(number(r, "frames_in_final_result")), cm(number(r, "ate_m")), "n/a"])
    return rows


def graph_table() -> str:
    """Estimators per step, then a long run's graph with and without its window."""
    return table(GRAPH_HEADER, _estimator_timing_rows() + _graph_window_rows())


# --- stage timings --------------------------------------------------------------------------------------------

STAGE_HEADER = ["stage (file)", "setting", "ms", "spread ms", "count"]


def _pipeline_rows() -> list[list[str]]:
    """pipeline.json: one keyframe's stages, and iSAM2's update as the graph grows."""
    name = "pipeline.json"
    d = read(name)
    k = get(d, "per_keyframe_s") or {}
    setting = f"{get(d, 'field') or 'n/a'} field, {count(number(k, 'correction_iterations'))} correction round"
    accepted = f"{frac(number(k, 'accepted'), number(k, 'keyframes'))} accepted"
    rows = [[f"keyframe: {stage.removesuffix('_per_keyframe')} `{name}`", setting, ms(number(k, stage)), "n/a", accepted]
            for stage in k if stage not in ("keyframes", "accepted", "correction_iterations")]
    for key, value in (get(d, "isam2") or {}).items():
        if key.endswith("_poses"):
            what, poses = key.split("_ms_at_")
            rows.append([f"iSAM2 {what.replace('_', ' ')} `{name}`", f"{poses.split('_')[0]} poses",
                         num(number([value], 0), 3), "n/a", "-"])
    return rows


def _alignment_rows() -> list[list[str]]:
    """alignment.json: RANSAC alone, and one alignment's stages at two sizes."""
    name = "alignment.json"
    d = read(name)
    r = get(d, "ransac_1000x500") or {}
    rows = [[f"RANSAC `{name}`", f"{count(number(r, 'correspondences'))} correspondences, {count(number(r, 'hypotheses'))} "
             "hypotheses", num(number(r, "median_ms"), 2), f"min {num(number(r, 'min_ms'), 2)}", "-"]]
    for key, s in d.items():
        if key.startswith("stages_"):
            found = f"{count(number(s, 'matches'))} matches, {count(number(s, 'inliers'))} inliers"
            rows += [[f"alignment: {stage.removesuffix('_ms')} `{name}`", key.removeprefix("stages_"),
                      num(number(s, stage), 1), "n/a", found] for stage in s if stage.endswith("_ms")]
    return rows


def _small_timing_rows() -> list[list[str]]:
    """association.json (stamp association, both methods) and sim_render.json (the simulator's render)."""
    a, name = read("association.json"), "association.json"
    rows = [[f"association: {m} `{name}`", f"{count(number(a, 'frames'))} frames", ms(number(a, m, "median_s"), 2),
             f"max {ms(number(a, m, 'max_s'), 2)}", f"{count(number(a, m, 'pairs'))} pairs"] for m in ("optimal", "greedy")]
    rows += [["simulator render `sim_render.json`", size, ms(number(r, "median_s"), 0), f"min {ms(number(r, 'min_s'), 0)}",
              "-"] for size, r in read("sim_render.json").items()]
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
    d = read(name)
    size = "x".join(str(v) for v in get(d, "size") or []) or "n/a"
    rows = []
    for key in ("read_raw", "open", "registered_depth", "end_to_end"):
        f = get(d, f"frames_per_s_{key}") or {}
        rows.append([f"RealSense {size}, {key.replace('_', ' ')} `{name}`", count(number(d, "frames")),
                     num(number(d, "file_mb"), 1), num(number(f, "median"), 1), f"min {num(number(f, 'min'), 1)}",
                     "-", "-", "-", "-", "-", "-"])
    return rows


def _rosbag_rows() -> list[list[str]]:
    """rosbag_fr1_desk.json: fr1/desk as a folder and as ROS bags, read and run (--odom vo)."""
    name = "rosbag_fr1_desk.json"
    d = read(name)
    rows = []
    for key, s in (get(d, "sources") or {}).items():
        r = get(d, "runs", key) or {}
        diff = number(r, "max_pose_difference_to_folder_m")
        rows.append([f"{key} `{name}`", count(number(s, "frames") or number(d, "frames")), num(number(s, "bag_mb"), 1),
                     num(number(s, "read_frames_per_s"), 0), f"with opening {num(number(s, 'read_frames_per_s_with_open'), 0)}"
                     if "read_frames_per_s_with_open" in s else "-",
                     num(number(r, "ate_cm")), num(number(r, "causal_ate_cm")), num(number(r, "odometry_ate_cm")),
                     frac(number(r, "accepted"), number(r, "keyframes")), num(number(s, "depth_max_abs_error_mm"), 2)
                     if "depth_max_abs_error_mm" in s else "-", mm(diff, 3) if diff is not None else "-"])
    return rows + [_rosbag_written_row(name, get(d, "runs") or {})]


def _rosbag_written_row(name: str, runs: dict) -> list[str]:
    """The ROS 1 run's written bag (against the run's estimate) and its rerun recording."""
    r = next((v for v in runs.values() if "rerun_recording" in v), {})
    rr = get(r, "rerun_recording") or {}
    return [f"written bag and rerun recording `{name}`", f"{count(number(rr, 'status_entries'))} statuses",
            num(number(rr, "mb"), 1), "-", "-", "-", "-", "-",
            f"{count(number(rr, 'accepted_ellipsoids'))} ellipsoids", "-",
            _sci_mm(number(r, "written_bag_max_pose_difference_to_estimate_m"))]


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
    d = read(name)
    budget = (f"{count(number(d, 'cells'))} cells, {count(number(d, 'fields'))} fields, {count(number(d, 'frames_per_recording'))} "
              "frames")
    rows = []
    for key, r in (get(d, "runs") or {}).items():
        workers = key.removeprefix("workers_")
        ratio = (f"{num(number(d, 'ratio_2_to_1_workers'))} (same table: {yes(get(d, 'same_table_up_to_timings'))})"
                 if workers == "2" else "-")
        rows.append([f"sweep, {workers} worker(s) `{name}`", get(d, "pool") or "n/a", budget,
                     num(number(r, "seconds"), 1), ratio, "-", "-", "-", "-"])
    return rows


def _cuda_rows() -> list[list[str]]:
    """cuda_check_h200.json: the grid trained on the GPU, rendered there and on the CPU."""
    name = "cuda_check_h200.json"
    d = read(name)
    rows = [[f"train `{name}`", f"{get(d, 'train_device') or 'n/a'} ({get(d, 'gpu') or 'n/a'}, torch "
             f"{get(d, 'torch') or 'n/a'})", f"{count(number(d, 'steps'))} steps", num(number(d, "train_seconds"), 1),
             "-", "-", "-", "-", "-"]]
    for key, r in d.items():
        if isinstance(r, dict) and "render_ms_median" in r:
            rows.append([f"render, {key} `{name}`", get(r, "backend") or "n/a", "-", "-", "-",
                         num(number(r, "render_ms_median"), 1), num(number(r, "depth_err_vs_exact_mm_median"), 1),
                         pair(num(number(r, "vs_gpu_depth_mm_median"), 4), num(number(r, "vs_gpu_depth_mm_p99"), 4)),
                         pair(f"{number(r, 'vs_gpu_opacity_flips') or 0:.1e}", f"{number(r, 'vs_gpu_colour_levels') or 0:.1e}")
                         if number(r, "vs_gpu_opacity_flips") is not None else "n/a"])
    return rows


def scale_table() -> str:
    """A sweep on one and two workers; the default field trained and rendered on a CUDA GPU."""
    return table(SCALE_HEADER, _sweep_rows() + _cuda_rows())


SECTIONS: list[Section] = [
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
        "alone with its drift. Since commit 5def546 a VO step on few inliers has its translation fused with the "
        "depth's own step (the file's version before commit ae45104 has the odometry without it): that it fuses the "
        "translation only was chosen looking at this half's steps, so this half is tuning data for it.",
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
]
