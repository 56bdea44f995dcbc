"""The relocaliser's rules on their tuning set: every frame of fr1/xyz located in maps of
fr1/desk (issue 48: defaults chosen on named tuning data, reported on other data).

fr1/xyz is another recording of the same office, and TUM's fr1 recordings share the motion
capture's frame, so each answer is scored against fr1/xyz's ground truth moved into the map by
the survey's own alignment (``survey_ate.json``'s ``T_gt_map``). Each variant of
``RelocaliseSettings`` is tried on every frame; the figures are those of
``map_start_anywhere.py`` (covered frames found within 5 cm / 3 deg, answers beyond 10 cm,
seconds per attempt on one thread). The maps are built with ``nap3d-graph map``'s defaults
of each ``--frames`` range of fr1/desk (default: the whole recording and each half), or
reused from ``--work``.

    python benchmarks/map_relocalise_rules.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --query ../shared/data/tum/rgbd_dataset_freiburg1_xyz --work /tmp/rules \\
        --out benchmarks/results/map_relocalise_rules_fr1_xyz.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
from map_start_anywhere import relocalisation
from map_survey import cli
from provenance import write_result

from nap3d_graph.conventions import inv_T

#: The variants tried: a name and the settings changed from the relocaliser's defaults.
VARIANTS = {
    "retrieval order alone (neighbours 0)": {"neighbours": 0},
    "a verified answer's neighbours next (neighbours 2)": {"neighbours": 2},
    "neighbours 2, ten retrieval candidates (top_k 10)": {"neighbours": 2, "top_k": 10},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="the survey recording (fr1/desk)")
    parser.add_argument("--query", type=Path, required=True, help="the tuning queries (fr1/xyz)")
    parser.add_argument("--frames", action="append", default=None,
                        help="a range of --data to map, or 'all' (repeat; default: all, 0:0.5 and 0.5:1)")
    parser.add_argument("--work", type=Path, required=True, help="folder for the maps (reused when there)")
    parser.add_argument("--matcher", default="xfeat")
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.mapping.relocalise import RelocaliseSettings

    query = open_sequence(args.query)
    maps, totals = {}, {name: {"covered": 0, "found": 0, "beyond_10cm": 0, "refused": 0, "seconds": []}
                        for name in VARIANTS}
    for frames in args.frames or ["all", "0:0.5", "0.5:1"]:
        map_dir = args.work / f"map_{frames.replace(':', '_')}"
        cli("map", str(args.data), *(() if frames == "all" else ("--frames", frames)), "--out", str(map_dir),
            "--matcher", args.matcher, "--quiet")
        info = json.loads((map_dir / "map.json").read_text())
        T_map_gt = inv_T(np.asarray(info["survey_ate"]["T_gt_map"]))
        field_obj = resolve_field(str(map_dir))
        maps[frames] = {"model": info["stages"]["field"]["model"], "keyframes": info["keyframes"], "variants": {}}
        for name, change in VARIANTS.items():
            settings = dataclasses.replace(RelocaliseSettings(), **change)
            r = relocalisation(map_dir, query, args.every, args.matcher, T_map_gt, settings=settings,
                               field_obj=field_obj)
            maps[frames]["variants"][name] = {"settings": dataclasses.asdict(settings), **r}
            t = totals[name]
            t["covered"] += r["covered"]
            t["found"] += r["covered_found_within_5cm_3deg"]
            t["beyond_10cm"] += r["accepted_farther_than_10cm"]
            t["refused"] += sum(not a["success"] for a in r["per_attempt"])
            t["seconds"] += [a["seconds"] for a in r["per_attempt"]]
            print(f"map {frames}, {name}: {r['covered_found_within_5cm_3deg']}/{r['covered']} covered found within "
                  f"5 cm / 3 deg, {r['accepted_farther_than_10cm']} beyond 10 cm, {r['seconds_median']:.2f} s median")
    for t in totals.values():
        seconds = np.asarray(t.pop("seconds"))
        t.update(seconds_median=float(np.median(seconds)), seconds_p90=float(np.percentile(seconds, 90)),
                 seconds_max=float(seconds.max()), attempts=int(seconds.size))
    write_result(args.out, {"data": str(args.data), "query": str(args.query), "every": args.every, "maps": maps,
                            "totals": totals}, args)


if __name__ == "__main__":
    main()
