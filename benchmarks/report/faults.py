"""Faults, the IMU's drift and its fallback, gravity: sections of ``docs/results.md`` read from the benchmarks' result files
(``benchmarks/results/``). Every figure comes out of its file; a key a file lacks reads ``n/a``,
and so does every figure of a missing file.
"""

from __future__ import annotations

from report import Section, cm, count, frac, get, num, number, pair, read, signed_pct, table, yes

# --- faults -----------------------------------------------------------------------------------------------------

FAULT_HEADER = ["fault (file)", "room or walk", "case", "caught", "accepted", "error cm", "worst cm",
                "against clean", "gravity off deg median / max"]


def _fault_rows() -> list[list[str]]:
    """faults.json: per room, the clean run and each injected fault."""
    name = "faults.json"
    rows = []
    for room, r in (get(read(name), "rooms") or {}).items():
        w, s, b = (get(r, k) or {} for k in ("wrong_corrections", "some_frames_scaled", "wrong_after_blind_stretch"))
        factor, e = next(((k.removeprefix("every_frame_scaled_"), v) for k, v in r.items()
                          if k.startswith("every_frame_scaled_")), ("n/a", {}))
        rows += [
            [f"none `{name}`", room, f"clean (odometry alone {cm(number(r, 'odometry_ate_m'))})", "-",
             frac(number(r, "clean_accepted"), number(r, "keyframes")), cm(number(r, "clean_ate_m")), "-", "-",
             "-"],
            [f"wrong corrections `{name}`", room, f"{count(number(w, 'injected'))} injected",
             f"{count(number(w, 'gated_out'))} gated out, {count(number(w, 'accepted_then_weighed_out'))} weighed out", "-",
             cm(number(w, "ate_m")), "-", num(number(w, "ratio_to_clean")), "-"],
            [f"some depths scaled `{name}`", room, f"{count(number(s, 'injected'))} injected",
             f"{count(number(s, 'refused_for_scale'))} refused, {count(number(s, 'good_refused_for_scale'))} good refused",
             "-", cm(number(s, "ate_m")), "-", num(number(s, "ratio_to_clean")), "-"],
            [f"every depth scaled `{name}`", room, f"depths x{factor}: scale {num(number(e, 'true_scale'), 4)}",
             f"found {num(number(e, 'estimated_scale'), 4)} ({signed_pct(number(e, 'scale_error_rel'))})",
             frac(number(e, "accepted"), number(r, "keyframes")), cm(number(e, "ate_m")), "-", num(number(e, "ratio_to_clean")), "-"],
            [f"wrong after a blind stretch `{name}`", room, "one wrong correction",
             f"gate took it: {yes(get(b, 'wrong_accepted_by_gate'))}; weighed out: {yes(get(b, 'weighed_out'))}",
             "-", cm(number(b, "ate_m")), "-", "-", "-"]]
    return rows


def _fallback_rows() -> list[list[str]]:
    """imu_fallback.json: walks whose field covers only their start, IMU alone against the fallbacks."""
    name = "imu_fallback.json"
    d = read(name)
    rows = []
    for r in get(d, "rows") or []:
        for case in ("imu_alone", "dense", "vo"):
            c = get(r, case) or {}
            spans = ", ".join(f"{a}-{b}" for a, b in get(c, "fallback_intervals") or [])
            rows.append([f"field covers the first {count(number(d, 'mapped_frames'))} frames `{name}`",
                         f"room {count(number(r, 'room'))}", case.replace("_", " ") if case == "imu_alone" else
                         f"{case} fallback", f"fallback frames {spans}" if spans else "-",
                         frac(number(c, "accepted"), number(c, "keyframes")), cm(number(c, "end_m"), 1),
                         cm(number(c, "max_after_field_m"), 1), "-", "-"])
    return rows


def _gravity_rows() -> list[list[str]]:
    """gravity_frame.json: walks mapped into a turned frame, per start of gravity (ATE median, max)."""
    name = "gravity_frame.json"
    rows = []
    for frame, f in (get(read(name), "frames") or {}).items():
        for case, c in f.items():
            if isinstance(c, dict) and "runs" in c:
                rows.append([f"gravity frame turned `{name}`", frame.replace("_", " "), case.replace("_", " "),
                             f"{count(number(c, 'runs_with_under_80pct_accepted'))} of {count(number(c, 'runs'))} runs "
                             "under 80% accepted", "-", cm(number(c, "ate_median_m")), cm(number(c, "ate_max_m")), "-",
                             pair(num(number(c, "gravity_off_median_deg")), num(number(c, "gravity_off_max_deg")))])
    return rows


def fault_table() -> str:
    """Injected faults, walks that leave their field on the IMU path, and gravity in a turned frame."""
    return table(FAULT_HEADER, _fault_rows() + _fallback_rows() + _gravity_rows())


def imu_drift_table() -> str:
    """The IMU alone: Monte-Carlo RMS position error against its noise model's prediction."""
    name = "imu_drift.json"
    d = read(name)
    rows = [[f"after {count(number(r, 't_s'))} s `{name}`", count(number(d, "seeds")), num(number(r, "mc_rms_m"), 3),
             num(number(r, "predicted_rms_m"), 3), num(number(r, "ratio"), 3),
             pair(num(number(r, "predicted_initial_bias_m"), 3), num(number(r, "predicted_white_noise_m"), 3)),
             num(number(r, "predicted_bias_random_walk_m"), 4)] for r in get(d, "table") or []]
    return table(["time (file)", "seeds", "Monte-Carlo RMS m", "predicted m", "ratio",
                  "predicted from the initial bias / white noise m", "from the bias random walk m"], rows)


SECTIONS: list[Section] = [
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
