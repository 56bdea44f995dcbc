"""Tables generated from ``benchmarks/results/*.json``, for the README: every figure in them
comes out of its file, never typed (a test regenerates them and fails when the committed
README differs).

    python benchmarks/tables.py            # print the tables
    python benchmarks/tables.py --write    # write them into README.md between their markers
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

#: README marker name -> (function, result files it reads)
MAP_SURVEY_FILES = ("map_survey_fr1_desk.json", "map_survey_redkitchen.json")


def _cm(value) -> str:
    return "n/a" if value is None else f"{value * 100:.2f}"


def map_survey_table() -> str:
    """The self-posed map against the ground-truth-posed one, per recording."""
    rows = ["| recording (file) | survey ATE cm: map / odometry alone [2nd GT] | loops accepted / verified | query ATE cm, "
            "self-posed map (causal) [2nd GT] | same, ground-truth-posed map [2nd GT] | ratio | relocalised within 5 cm "
            "/ 3 deg; >10 cm; s per attempt (median, max) | map s |",
            "|---|---|---|---|---|---|---|---|"]
    for name in MAP_SURVEY_FILES:
        path = RESULTS / name
        if not path.is_file():
            continue
        r = json.loads(path.read_text())
        survey = r["survey"]
        ate = survey["ate"]
        second = survey.get("ate_second_gt")
        s_self, s_gt = r["runs"]["self_posed"], r["runs"]["gt_posed"]
        reloc = r["relocalisation"]

        second_text = f" [{_cm(second['rmse_m'])}]" if second else ""

        def with_second(value, key, run):
            extra = f" [{_cm(run[key])}]" if key in run else ""
            return f"{_cm(value)}{extra}"

        rows.append(
            f"| {Path(r['data']).name} `{name}` "
            f"| {_cm(ate['map']['rmse_m'])} / {_cm(ate['odometry_only']['rmse_m'])}"
            f"{second_text} "
            f"| {survey['loops']['accepted']} / {survey['loops']['verified']} "
            f"| {with_second(s_self['ate_m'], 'ate_second_gt_m', s_self)} ({_cm(s_self['ate_causal_m'])}) "
            f"| {with_second(s_gt['ate_m'], 'ate_second_gt_m', s_gt)} ({_cm(s_gt['ate_causal_m'])}) "
            f"| {r['ratio_self_to_gt_posed']:.2f} "
            f"| {reloc['within_5cm_3deg']}/{reloc['attempts']}; {reloc['accepted_farther_than_10cm']}; "
            f"{reloc['seconds_median']:.2f}, {reloc['seconds_max']:.2f} "
            f"| {sum(survey['stages_s'].values()):.0f} |")
    return "\n".join(rows)


TABLES = {"map_survey": map_survey_table}


def render_readme(text: str) -> str:
    """README text with every generated block replaced by its table."""
    for name, make in TABLES.items():
        pattern = re.compile(rf"(<!-- table {name}: .*? -->\n).*?(\n<!-- end table {name} -->)", re.S)
        text = pattern.sub(lambda m, make=make: m.group(1) + make() + m.group(2), text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write", action="store_true", help="write the tables into README.md")
    args = parser.parse_args()
    readme = ROOT / "README.md"
    if args.write:
        readme.write_text(render_readme(readme.read_text()))
    for make in TABLES.values():
        print(make())


if __name__ == "__main__":
    main()
