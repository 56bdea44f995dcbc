"""Checks made before any work: the depth unit, with and without poses."""

from __future__ import annotations

import numpy as np

from report import RESULTS, Section, load, table


def depth_unit_table() -> str:
    """Each recording as recorded and with each TUM unit mistake: the scale the check found
    against the right one, the views' disagreement as read and at the found scale."""
    if not (RESULTS / "depth_unit.json").is_file():
        return "n/a"
    rows = []
    for r in load("depth_unit.json")["rows"]:
        found = r["found_scale"]
        d = r["disagreement"] or {}
        as_read = d.get("x1")
        at_found = d.get(f"x{found:g}") if found is not None else None
        rows.append([f"{r['recording']} `depth_unit.json`", r["mistake"], f"x{r['expected_scale']:g}",
                     "n/a" if found is None else f"x{found:g}", "yes" if r["right"] else "**no**",
                     "n/a" if as_read is None else f"{100 * as_read:.1f}",
                     "n/a" if at_found is None else f"{100 * at_found:.1f}", r["pairs"], f"{r['seconds']:.1f}"])
    return table(["recording (file)", "depth read", "right scale", "found", "right", "disagreement as read %",
                  "at the found scale %", "frame pairs", "s"], rows)


def depth_unit_without_poses_table() -> str:
    """Each real recording as it is and read in a wrong unit: whether every command's first
    look at the depth (no poses) warned, and what it saw."""
    r = load("depth_unit_without_poses.json")
    rows = []
    for name, c in r["cases"].items():
        kinect = c["kinect_units_per_m"]
        rows.append([name, "yes" if c["mistake"] else "no", "warned" if c["told"] else "no warning",
                     "yes" if c["right"] else "**no**", f"{c['median_m']:.3f}", f"{c['near_m']:.3f}",
                     f"{np.median(kinect):.0f}" if kinect else "not resolved"])
    rows.append([f"**mistakes told {r['mistakes_told']}/{r['mistakes']}, false alarms {r['false_alarms']}**",
                 "", "", "", "", "", ""])
    return table(["recording, read as", "a mistake", "before any work", "right", "median depth m", "10th percentile m",
                  "Kinect v1 steps at (units per metre)"], rows)


SECTIONS = [
    Section("The depth unit, checked before a field is built", ("depth_unit.json",),
            "python benchmarks/depth_unit.py --data D1 --data D2 --data D3", depth_unit_table,
            "Median relative disagreement of frame pairs moved into each other by the recording's poses; a scale "
            "other than x1 is reported only when it agrees clearly better."),
    Section("The depth unit without poses: every command's first look at a few frames' depth",
            ("depth_unit_without_poses.json",),
            "python benchmarks/depth_unit_without_poses.py --tum T --sevenscenes S --bag B --out ...",
            depth_unit_without_poses_table,
            "A warning when a tenth of the depth is nearer than 0.2 m (what a D435 sees from) or the stored values "
            "show a Kinect v1's disparity steps (1/(8 x 580 x 0.075) m per square metre of depth) at another unit "
            "than the one read; both lines come from the sensors' specifications, not from these recordings."),
]
