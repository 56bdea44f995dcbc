"""``nap3d-graph map``: a map of a place from a survey posed by the camera alone.

No ground truth is read to build it: the survey's poses come from the frames' own odometry,
loop closures verified with NAP3D real-vs-real, a robust pose graph (GTSAM GNC), then the
field of ``--model`` is trained at those poses. Where the recording has ground truth,
``survey_ate.json`` says how far the map's poses are from it (SE(3)-aligned), and runs on this
map score themselves in the ground truth's frame through that one alignment.
"""

from __future__ import annotations

import os
from pathlib import Path

from nap3d_graph.arguments import positive_int
from nap3d_graph.datasets import open_sequence
from nap3d_graph.fields.submaps import SubmapSettings
from nap3d_graph.mapping.build import MapSettings, build_map
from nap3d_graph.mapping.extend import MapExtensionRefused, extend_map
from nap3d_graph.mapping.viz import write_map_recording
from nap3d_graph.pools import make_pool
from nap3d_graph.rerun_sdk import VizError, check_viz_target

from .binding import SectionDefaults, add_options, flag_options, section_values
from .common import (
    UsageError,
    add_frames_argument,
    add_topics_argument,
    add_unit_arguments,
    warn_depth_units,
)
from .sources import chosen_matcher, warn_guessed_camera

#: The map's settings that have a flag: each field declares it (MapSettings, SubmapSettings).
MAP_SECTIONS: dict[str, type] = {"map": MapSettings, "submaps": SubmapSettings}
MAP_OPTIONS = flag_options(MAP_SECTIONS)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "map", help="a map from a survey posed by the camera alone (no ground truth): poses, loops, field",
        description=__doc__ + "\nMAP_DIR receives: poses.txt (TUM, every frame of the survey in the map's frame: the "
        "first frame's camera), odometry.txt (the odometry alone), loops.csv (every candidate pair: inliers, verified, "
        "accepted or why not), map.png, field.pt and field.report.json, keyframes.npz (what --initial-pose auto "
        "retrieves from), map.json, and survey_ate.json where the recording has ground truth. Interrupted, the same "
        "command resumes from the last finished stage. Use the map with: nap3d-graph run --field MAP_DIR ...")
    p.add_argument("data", type=Path, help="the survey: a TUM-layout or 7-Scenes folder, a ROS bag, or a RealSense "
                   "recording (.bag/.db3); its ground truth, if any, is ignored until the map is made")
    p.add_argument("--out", type=Path, default=None,
                   help="the map folder (created; an unfinished one resumes). With --extend: where the grown map is "
                   "written (default: it replaces MAP, swapped in whole once finished)")
    p.add_argument("--extend", type=Path, default=None, metavar="MAP",
                   help="grow an existing map by this survey (another day, another room): the survey is posed on its "
                   "own, found in MAP by verified matches against its keyframes, joined to it in one graph (MAP's "
                   "poses held), and new submap fields are trained where it saw space MAP did not have; refused in one "
                   "line, MAP untouched, when the survey is not found in MAP or fits two places of it")
    add_topics_argument(p)
    add_unit_arguments(p)
    add_frames_argument(p, "the survey")
    add_options(p, MAP_OPTIONS, SectionDefaults(MAP_SECTIONS))
    p.add_argument("--no-field", action="store_true", help="stop after the poses (no field)")
    _add_floor_arguments(p)
    p.add_argument("--device", default=None, help="torch device for the grid (default: cuda if available, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def _add_floor_arguments(p) -> None:
    """What a floor's map adds: submaps, where they train, the mesh and the rerun recording."""
    p.add_argument("--viz", metavar="MAP.rrd", default=None,
                   help="also write the map as a rerun recording (the survey's path, keyframes coloured by submap, "
                   "loops, the mesh, the report): open it with `rerun MAP.rrd`; needs pip install 'nap3d-graph[viz]'")
    p.add_argument("--workers", type=positive_int, default=None, metavar="N",
                   help="submap fields trained, and the loop candidates of a long survey (200 pairs or more) verified, "
                   "side by side on N workers (default: this machine's cores; 1: one after another in this process)")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="train the submap fields and verify the loop candidates as Ray tasks: 'auto' starts Ray on this "
                   "machine with --workers CPUs, "
                   "an address joins that cluster (ray start --head there); default: processes on this machine. "
                   "Needs pip install 'nap3d-graph[ray]'")
    p.add_argument("--no-mesh", action="store_true",
                   help="do not fuse map.ply (by default the survey's depth is fused at the map's poses into a coloured "
                   "mesh for MeshLab, CloudCompare or rerun, and the report says how thick its walls are: a doubled "
                   "wall is a wrong survey; needs Open3D, pip install 'nap3d-graph[mesh]', else skipped with a line)")


def run(args) -> int:
    if args.out is None and args.extend is None:
        raise UsageError("--out is required (the map folder to make), or --extend MAP (the map to grow)")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file, not a folder")
    sequence = open_sequence(args.data, frames=args.frames, topics=args.topics, depth_scale=args.depth_scale,
                             stamps=args.stamps, fps=args.fps)
    if len(sequence) < 3:
        raise UsageError(f"{args.data}: a survey needs at least 3 frames, got {len(sequence)}")
    warn_depth_units(sequence)
    warn_guessed_camera(sequence)
    given = section_values(args, MAP_OPTIONS)
    settings = MapSettings(**{**given["map"], "matcher": chosen_matcher(args.matcher, sequence),
                              "minutes": None if args.steps else args.minutes,
                              "budget_minutes": args.budget_minutes or None},  # 0: no budget
                           submaps=SubmapSettings(**given["submaps"]))
    if args.viz is not None:
        try:
            check_viz_target(args.viz)  # before the work: a bad target costs nothing
        except VizError as exc:
            raise UsageError(str(exc)) from None
        if args.viz == "spawn":
            raise UsageError("`map --viz` writes a recording: give a path ending in .rrd")
    pool = _pool(args)
    if args.extend is not None:
        return _extend(args, sequence, settings, pool)
    try:
        result = build_map(sequence, args.out, settings, progress=not args.quiet, say=print,
                           build_field_stage=not args.no_field, device=args.device, mesh=not args.no_mesh, pool=pool)
    except FileExistsError as exc:
        raise UsageError(str(exc)) from None
    finally:
        pool.close()
    print(summary(result.info, args.out))
    if args.viz is not None:
        print(f"rerun recording: {write_map_recording(args.out, args.viz)} (open it with: rerun {args.viz})")
    return 0


def _extend(args, sequence, settings, pool) -> int:
    """``map NEW --extend MAP``: the map grown by the survey (:mod:`nap3d_graph.mapping.extend`)."""
    try:
        result = extend_map(sequence, args.extend, args.out, settings, progress=not args.quiet, say=print,
                            device=args.device, pool=pool, mesh=not args.no_mesh)
    except (MapExtensionRefused, FileExistsError) as exc:
        raise UsageError(f"map --extend {args.extend}: {exc}") from None
    finally:
        pool.close()
    record = result.info["extensions"][-1]
    print(f"map: {result.folder} grown by {args.data} (extension {record['number']}: {record['keyframes']} keyframes, "
          f"placed by {record['accepted']} verified pair(s) with the map, {record['look-alike']} pointing elsewhere "
          f"set aside; {record['unseen_frames']} frames of new space, "
          + (f"new submap field(s) {record['new_submaps']}" if record["new_submaps"] else "no new field")
          + f"; {record['seconds']:.0f} s). Its own poses in the map: {result.folder / record['folder'] / 'poses_in_map.txt'}")
    return 0


def _pool(args):
    """Where submap fields train and many loop candidates are verified: Ray with --ray-address,
    else processes on this machine (started only when there is work for them)."""
    workers = args.workers or max(1, os.cpu_count() or 1)
    try:
        return make_pool(workers, args.ray_address)
    except RuntimeError as exc:  # Ray not installed, or no cluster at that address
        raise UsageError(str(exc)) from None


def summary(info: dict, out: Path) -> str:
    loops = info["loops"]
    segment = info["segment"]
    lines = [f"map: {out}  ({info['keyframes']} keyframes over frames {segment['start']}:{segment['stop']}; loops: "
             f"{loops['candidates']} candidates, {loops['verified']} verified, {loops['accepted']} accepted, "
             f"{loops['rejected']} rejected by the graph)"]
    ate = info.get("survey_ate")
    if ate:
        lines.append(f"survey poses against the recording's ground truth (SE(3)-aligned, read only now): ATE "
                     f"{ate['map']['rmse_m'] * 100:.2f} cm (p90 {ate['map']['p90_m'] * 100:.2f}, max "
                     f"{ate['map']['max_m'] * 100:.2f}); the odometry alone {ate['odometry_only']['rmse_m'] * 100:.2f} cm"
                     + _orientation(ate["map"]))
        if "warning" in ate:
            lines.append(f"warning: {ate['warning']}")
    stages = info.get("stages", {})
    if "field" in stages:
        if stages["field"].get("submap_count"):
            lines.append(f"field: {stages['field']['submap_count']} submaps in {out / 'submaps'} (index "
                         f"{out / 'submaps.json'}; {stages['field']['model']}, {stages['field']['seconds']:.0f} s)")
        else:
            lines.append(f"field: {out / 'field.pt'} ({stages['field']['model']}, {stages['field']['seconds']:.0f} s)")
    if (info.get("mesh") or {}).get("file"):
        lines.append(f"mesh: {out / info['mesh']['file']} ({info['mesh']['vertices']} vertices; open it in MeshLab, "
                     "CloudCompare or rerun)")
    bad = (info.get("report") or {}).get("past_bad_line")
    if bad is not None:
        lines.append(f"report: {out / 'report.md'} (" + ("look at: " + "; ".join(bad) if bad else
                                                         "nothing past its bad line") + ")")
    total = sum(s.get("seconds", 0.0) for s in stages.values())
    lines.append(f"time: {total:.0f} s in all stages; use it with: nap3d-graph run --field {out} --data ... (the start "
                 "is found in the map: --initial-pose auto)")
    return "\n".join(lines)


def _orientation(ate: dict) -> str:
    """The survey's orientation errors, where the map's ``survey_ate`` holds them."""
    if "rotation_median_deg" not in ate:
        return ""
    return (f"; orientation {ate['rotation_median_deg']:.2f} deg median (p90 {ate['rotation_p90_deg']:.2f}), "
            f"{ate['rotation_common_deg']:.2f} deg of it one turn common to every camera")
