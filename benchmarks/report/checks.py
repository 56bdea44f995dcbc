"""Checks made before any work: the depth unit."""

from __future__ import annotations

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


SECTIONS = [
    Section("The depth unit, checked before a field is built", ("depth_unit.json",),
            "python benchmarks/depth_unit.py --data D1 --data D2 --data D3", depth_unit_table,
            "Median relative disagreement of frame pairs moved into each other by the recording's poses; a scale "
            "other than x1 is reported only when it agrees clearly better."),
]
