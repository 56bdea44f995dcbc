"""The relocaliser's rules on their tuning sets: every frame of fr1/xyz located in maps of
fr1/desk, and simulated rooms' traversals in maps of their mapping walks (issue 48: defaults
chosen on named tuning data, reported on other data).

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

With ``--simulate ROOM`` (repeat) the tuning set is simulated instead: each room's mapping
walk (120 frames at 3.75 Hz, 320x240) is the survey, mapped with a splat field and SIFT (what
``map`` picks for a simulated recording), and a traversal of the same room (150 frames at
15 Hz, another seed) the queries, every ``--every``-th frame. fr1/xyz stays near the desk the
surveys saw; a traversal leaves the mapping walk's path, so its frames stand as far from the
survey's keyframes as a new run's start does.

    python benchmarks/map_relocalise_rules.py --simulate 3 --simulate 5 --simulate 7 --every 3 \\
        --work /tmp/rules_sim --out benchmarks/results/map_relocalise_rules_sim.json
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
    "retrieval order alone (neighbours 0)": {"neighbours": 0, "shortlist": 0},
    "a verified answer's neighbours next (neighbours 2)": {"neighbours": 2, "shortlist": 0},
    "neighbours 2, ten retrieval candidates (top_k 10)": {"neighbours": 2, "top_k": 10, "shortlist": 0},
    "neighbours 2, descriptor's 20 re-ranked by shared matches (shortlist 20)": {"neighbours": 2, "shortlist": 20},
    "shortlist 20, a real-vs-real start from 12 inliers (start_min_inliers 12)": {"neighbours": 2, "shortlist": 20,
                                                                                 "start_min_inliers": 12},
}


def _measure(map_dir: Path, query, args, label: str, maps: dict, totals: dict) -> None:
    """Every variant on ``query`` in the map ``map_dir``, into ``maps[label]`` and ``totals``."""
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.mapping.relocalise import RelocaliseSettings

    info = json.loads((map_dir / "map.json").read_text())
    T_map_gt = inv_T(np.asarray(info["survey_ate"]["T_gt_map"]))
    field_obj = resolve_field(str(map_dir))
    maps[label] = {"model": info["stages"]["field"]["model"], "keyframes": info["keyframes"], "variants": {}}
    for name, change in VARIANTS.items():
        settings = dataclasses.replace(RelocaliseSettings(), **change)
        r = relocalisation(map_dir, query, args.every, args.matcher, T_map_gt, settings=settings, field_obj=field_obj)
        maps[label]["variants"][name] = {"settings": dataclasses.asdict(settings), **r}
        t = totals[name]
        t["covered"] += r["covered"]
        t["found"] += r["covered_found_within_5cm_3deg"]
        t["beyond_10cm"] += r["accepted_farther_than_10cm"]
        t["refused"] += sum(not a["success"] for a in r["per_attempt"])
        t["seconds"] += [a["seconds"] for a in r["per_attempt"]]
        print(f"{label}, {name}: {r['covered_found_within_5cm_3deg']}/{r['covered']} covered found within "
              f"5 cm / 3 deg, {r['accepted_farther_than_10cm']} beyond 10 cm, {r['seconds_median']:.2f} s median")


def _simulated(room: int, work: Path) -> tuple[Path, Path]:
    """``(survey, query)`` folders of simulated room ``room`` (made once in ``work``)."""
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    folders = []
    for name, config in (("survey", SimConfig(frames=120, scene_seed=room, seed=0, path="mapping", width=320,
                                              height=240)),
                         ("query", SimConfig(frames=150, scene_seed=room, seed=1, path="traverse", width=320,
                                             height=240))):
        folder = work / f"room{room}" / name
        if not (folder / "groundtruth.txt").is_file():
            simulate_sequence(folder, config)
        folders.append(folder)
    return folders[0], folders[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="the survey recording (fr1/desk)")
    parser.add_argument("--query", type=Path, default=None, help="the tuning queries (fr1/xyz)")
    parser.add_argument("--simulate", type=int, action="append", default=None,
                        help="a simulated room as the tuning set instead (repeat)")
    parser.add_argument("--frames", action="append", default=None,
                        help="a range of --data to map, or 'all' (repeat; default: all, 0:0.5 and 0.5:1)")
    parser.add_argument("--work", type=Path, required=True, help="folder for the maps (reused when there)")
    parser.add_argument("--matcher", default=None, help="default: xfeat for a recording, sift for a simulated room")
    parser.add_argument("--model", default=None, help="the maps' field (default: grid, splat for a simulated room)")
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.simulate is None and (args.data is None or args.query is None):
        parser.error("give --data and --query, or --simulate ROOM")
    args.matcher = args.matcher or ("sift" if args.simulate else "xfeat")
    args.model = args.model or ("splat" if args.simulate else "grid")

    from nap3d_graph.datasets import open_sequence

    maps, totals = {}, {name: {"covered": 0, "found": 0, "beyond_10cm": 0, "refused": 0, "seconds": []}
                        for name in VARIANTS}
    if args.simulate:
        for room in args.simulate:
            survey, query = _simulated(room, args.work)
            map_dir = args.work / f"room{room}" / "map"
            cli("map", str(survey), "--out", str(map_dir), "--matcher", args.matcher, "--model", args.model, "--quiet")
            _measure(map_dir, open_sequence(query), args, f"room {room}", maps, totals)
    else:
        query = open_sequence(args.query)
        for frames in args.frames or ["all", "0:0.5", "0.5:1"]:
            map_dir = args.work / f"map_{frames.replace(':', '_')}"
            cli("map", str(args.data), *(() if frames == "all" else ("--frames", frames)), "--out", str(map_dir),
                "--matcher", args.matcher, "--model", args.model, "--quiet")
            _measure(map_dir, query, args, frames, maps, totals)
    for t in totals.values():
        seconds = np.asarray(t.pop("seconds"))
        t.update(seconds_median=float(np.median(seconds)), seconds_p90=float(np.percentile(seconds, 90)),
                 seconds_max=float(seconds.max()), attempts=int(seconds.size))
    source = {"simulated_rooms": args.simulate} if args.simulate else {"data": str(args.data), "query": str(args.query)}
    write_result(args.out, {**source, "every": args.every, "model": args.model, "matcher": args.matcher, "maps": maps,
                            "totals": totals}, args)


if __name__ == "__main__":
    main()
