"""Drift removal on the simulated rooms and the field's error there: sections of ``docs/results.md`` read from the benchmarks' result files
(``benchmarks/results/``). Every figure comes out of its file; a key a file lacks reads ``n/a``,
and so does every figure of a missing file.
"""

from __future__ import annotations

import math

from report import Section, cm, count, frac, get, mm, ms, num, number, pair, pct, read, span, table

# --- drift removal on simulated rooms ------------------------------------------------------------

DRIFT_FILES = ("default_run.json", "drift_rooms.json", "drift_rooms_views.json")
DRIFT_HEADER = ["run (file)", "field", "train steps", "field s (first run)", "cached run s", "held-out PSNR dB",
                "ATE cm", "causal ATE cm", "max error cm", "odometry alone cm", "exact field ATE cm", "accepted",
                "ms per keyframe", "render ms"]


def _default_run_row() -> list[str]:
    """The embedded default (`nap3d-graph run`): its first run builds the field, the second finds it cached."""
    name = "default_run.json"
    r = read(name)
    return [f"embedded default `{name}`", "embedded default", "n/a", num(number(r, "first_run_s"), 0),
            num(number(r, "cached_run_s"), 1), "n/a", cm(number(r, "ate_estimate_m")), cm(number(r, "ate_causal_m")),
            cm(number(r, "ate_estimate_max_m")), cm(number(r, "ate_odometry_m")), "-",
            frac(number(r, "corrections_accepted"), number(r, "keyframes")),
            ms(number(r, "seconds_per_keyframe", "total_per_keyframe")), ms(number(r, "seconds_per_keyframe", "render"))]


def _drift_room_rows(name: str) -> list[list[str]]:
    """One row per hold-out room: the trained field's run beside the exact field's."""
    d = read(name)
    model, steps = get(d, "model") or "n/a", count(number(d, "train_steps"))
    rows = []
    for room, r in (get(d, "per_room") or {}).items():
        t = get(r, "trained") or {}
        rows.append([f"room {room} `{name}`", model, steps, num(number(r, "field_seconds"), 0), "-",
                     num(number(r, "field_held_out", "psnr_db"), 1), cm(number(t, "ate_estimate_m")),
                     cm(number(t, "ate_causal_m")), cm(number(t, "ate_estimate_max_m")), cm(number(t, "ate_odometry_m")),
                     cm(number(r, "oracle", "ate_estimate_m")), frac(number(t, "accepted"), number(t, "keyframes")),
                     ms(number(t, "seconds_per_keyframe"), 0), "n/a"])
    return rows


def _drift_pooled_rows(name: str) -> list[list[str]]:
    """The file's pooled figures over its rooms: the mean, then the range."""
    d = read(name)
    p, o = get(d, "pooled", "trained") or {}, get(d, "pooled", "oracle") or {}
    model, steps = get(d, "model") or "n/a", count(number(d, "train_steps"))
    keys = ("ate_estimate_m", "ate_causal_m", "ate_estimate_max_m", "ate_odometry_m")
    mean = [cm(number(p, k, "mean")) for k in keys] + [cm(number(o, "ate_estimate_m", "mean"))]
    spread = [span(number(p, k, "min"), number(p, k, "max"), cm) for k in keys]
    spread += [span(number(o, "ate_estimate_m", "min"), number(o, "ate_estimate_m", "max"), cm)]
    return [[f"rooms, mean `{name}`", model, steps, "-", "-", "-", *mean, pct(number(p, "accepted_fraction")),
             ms(number(p, "seconds_per_keyframe", "mean"), 0), "n/a"],
            [f"rooms, min-max `{name}`", model, steps, "-", "-", "-", *spread, "-",
             span(number(p, "seconds_per_keyframe", "min"), number(p, "seconds_per_keyframe", "max"),
                   lambda s: ms(s, 0)), "n/a"]]


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
    rad = number(fe, "sigma_rad")
    deg = num(None if rad is None else math.degrees(rad))
    return [f"room {room} `{name}`", steps, pair(mm(number(fe, "sigma_m")), deg),
            pair(count(number(fe, "frames")), count(number(fe, "failed"))),
            f"{mm(number(g, 'sigma_m', -1))} ({num(number(g, 'gap_m', -1))})",
            pair(num(number(near, "nees_mean")), num(number(grow, "nees_mean"))),
            pair(num(number(near, "nees_median")), num(number(grow, "nees_median"))),
            span(number(near, "nees_band_95", 0), number(near, "nees_band_95", 1)),
            pair(cm(number(near, "ate_estimate_m")), cm(number(grow, "ate_estimate_m"))),
            pair(cm(number(near, "ate_causal_m")), cm(number(grow, "ate_causal_m"))),
            f"{pair(count(number(near, 'accepted')), count(number(grow, 'accepted')))} of {count(number(near, 'keyframes'))}"]


def growth_table() -> str:
    """Per hold-out room: the grid field's measured error, and the corrections' NEES without and with its growth."""
    name = "error_growth_rooms.json"
    d = read(name)
    steps = count(number(d, "train_steps"))
    return table(GROWTH_HEADER, [_growth_row(name, room, r, steps) for room, r in (get(d, "per_room") or {}).items()])


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
]
