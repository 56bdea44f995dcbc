"""Checks made before any work (the depth unit, with and without poses), and one of the code's own
shape (a keyframe's calls between modules)."""

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


def keyframe_calls_table() -> str:
    """One keyframe's step traced before and after the run's state became one object its parts
    are handed: modules visited, distinct calls between modules, re-entries, calls back up."""
    rows = []
    for name, when in (("keyframe_calls_0c5e976.json", "before (0c5e976): parts hold the pipeline"),
                       ("keyframe_calls.json", "now: parts take the run's state")):
        r = load(name)
        back = "; ".join(f"`{c}`" for c in r["calls_back"]) or "none"
        rows.append([f"{when} `{name}`", r["modules_visited"], r["edges"], r["returns_to_a_module_left"],
                     r["calls_back_up_the_stack"], back])
    return table(["tree (file)", "modules visited", "distinct calls between modules", "into a module already entered",
                  "back up into a module still on the stack", "those calls"], rows)


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
    Section("One keyframe's calls from Pipeline.step, traced", ("keyframe_calls_0c5e976.json", "keyframe_calls.json"),
            "python benchmarks/keyframe_calls.py --out ...", keyframe_calls_table,
            "The third keyframe of a simulated walk (recorded odometry, the exact field), run inline, its step traced "
            "as it runs. A call back up enters a module that is still waiting for what it called (a part calling "
            "into the run that called it). Most re-entries are calls into the shared lower modules (conventions, "
            "camera, the frame logs, the motion model) from several places, which layering allows."),
]
