"""A floor of a building, 1, 3 and 6 rooms (issue 61): what a map, a run and a placement do as
the floor grows, on simulated floors no test or tuning used (floor seed 1; the tests use 0).

Two parts, each its own JSON:

* ``--part placement`` (minutes): the survey indexed at its true poses and the simulator's exact
  field (no survey or field error: relocalisation and placement alone). Every fourth frame of
  a traverse across the floor is relocalised (time per attempt, found within 5 cm / 3 deg, in
  the wrong room, refused as ambiguous); then runs that start in a room with a twin, looking
  first at a side wall both twins have, are placed from their own start with the rules before
  issue 61 (no rival check, one confirming keyframe), with the rival check alone, and with the
  defaults (rivals a room away, 1 m of confirmed travel): where and when each was placed, and
  whether ever in the twin.
* ``--part map`` (an hour and more on two cores): ``nap3d-graph map`` of each floor's survey,
  as a user runs it (defaults, a subprocess timed by ``/usr/bin/time`` for its peak memory),
  held-out PSNR of its field per room, then ``nap3d-graph run --odom vo`` of a traverse
  across the floor from its own start in that map (ATE tied through the survey's alignment,
  the largest error, peak memory).

    python benchmarks/building.py --part placement --rooms 1 3 6 --out benchmarks/results/building_placement.json
    python benchmarks/building.py --part map --rooms 1 3 6 --frames-per-room 150 \
        --out benchmarks/results/building_map.json
    python benchmarks/building.py --part map --rooms 3 --frames-per-room 150 --one-field \
        --out benchmarks/results/building_map_one_field.json
    python benchmarks/building.py --part workers --rooms 3 --frames-per-room 150 \
        --out benchmarks/results/building_workers.json

``--part workers``: the field stage alone on the 3-room floor's survey at its true poses, its
submap fields trained one after another, on 2 worker processes and as 2 Ray tasks (fixed
steps): wall time, and whether the fields are the same.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from provenance import write_result

FLOOR_SEED = 1  # the tests' floors are seed 0
SURVEY_SEED, TRAVERSE_SEED, START_SEEDS = 3, 4, (5, 6, 7)
SURVEY_FPS = 3.75  # every fourth frame of a 15 Hz recording, as the one-room survey
TRAVERSE_FPS = 7.5
WALK_SPEED_MPS = 0.5
#: Placement rules compared on the twin starts: before issue 61, its rival check alone, and its
#: defaults (rivals a room away refuse an answer; 1 m of confirmed travel; the look-alike places the
#: index's survey met ruled out first: the two others do not know them).
VARIANTS = (("before", 0.0, 0.0, False), ("rivals_only", 1.0, 0.0, False), ("after", 1.0, 1.0, True))


def _simulate(folder: Path, **settings):
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.sims.sequence import SimConfig, simulate_sequence

    if not (folder / "sim.json").is_file():
        simulate_sequence(folder, SimConfig(**settings), progress=True)
    return open_sequence(folder)


def _floor_data(args, rooms: int, work: Path):
    """The floor's survey (``frames_per_room`` per room) and a traverse from its first room to
    its last at walking pace."""
    from nap3d_graph.sims.building import make_building

    floor = make_building(rooms, FLOOR_SEED)
    size = {"width": args.width, "height": args.height, "scene_seed": FLOOR_SEED, "rooms": rooms}
    survey = _simulate(work / f"floor{rooms}_{args.frames_per_room}f_survey", frames=args.frames_per_room * rooms,
                       path="mapping",
                       fps=SURVEY_FPS, seed=SURVEY_SEED, **size)
    length_m = float(floor.walls_x[-1]) - 2.4
    frames = max(int(length_m / WALK_SPEED_MPS * TRAVERSE_FPS), 30)
    traverse = _simulate(work / f"floor{rooms}_traverse", frames=frames, path="traverse", fps=TRAVERSE_FPS,
                         seed=TRAVERSE_SEED, **size)
    return floor, survey, traverse, length_m


def _spread(values) -> dict:
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"n": 0}
    return {"n": int(v.size), "median": round(float(np.median(v)), 4), "p90": round(float(np.percentile(v, 90)), 4),
            "max": round(float(v.max()), 4)}


# --- placement ---------------------------------------------------------------------------------


def relocalise_traverse(floor, index: Path, traverse, every: int) -> dict:
    """Every ``every``-th traverse frame relocalised in the posed index with the exact field."""
    from nap3d_graph.mapping.relocalise import Relocaliser, pose_gap

    field = traverse.oracle_field()
    relocaliser = Relocaliser(index, field)
    seconds, errors_m, rows = [], [], {"found_within_5cm_3deg": 0, "found_farther": 0, "wrong_room": 0,
                                       "ambiguous": 0, "refused": 0}
    for i in range(0, len(traverse), every):
        t0 = time.perf_counter()
        found = relocaliser.locate(traverse[i])
        seconds.append(time.perf_counter() - t0)
        T_true = traverse.T_world_cam_gt[i]
        if not found.success:
            rows["refused"] += 1
            continue
        if found.ambiguous:
            rows["ambiguous"] += 1
        metres, degrees = pose_gap(found.T_map_cam, T_true)
        errors_m.append(metres)
        if floor.room_of(found.T_map_cam[:3, 3]) != floor.room_of(T_true[:3, 3]):
            rows["wrong_room"] += 1
        elif metres <= 0.05 and degrees <= 3.0:
            rows["found_within_5cm_3deg"] += 1
        else:
            rows["found_farther"] += 1
    return {"attempts": len(seconds), **rows, "seconds": _spread(seconds), "error_m": _spread(errors_m)}


def place_from_start(floor, index: Path, walk, rival_m: float, travel_m: float, look_alikes: bool) -> dict:
    """A run of ``walk`` from its own start (the simulator's drifting odometry, the exact field)
    placed in the index with the rival check at ``rival_m`` (0: off), ``travel_m`` of
    confirmed travel (0: one confirming keyframe, as before issue 61) and, with
    ``look_alikes``, the look-alike places the index's survey met to be ruled out first."""
    from nap3d_graph.conventions import inv_T
    from nap3d_graph.mapping.relocalise import Relocaliser, RelocaliseSettings
    from nap3d_graph.mapping.start import PlacementSettings
    from nap3d_graph.motion.odometry import RecordedOdometry
    from nap3d_graph.run.config import PipelineConfig
    from nap3d_graph.run.pipeline import Pipeline

    field = walk.oracle_field()
    T_gt, T_odom = np.asarray(walk.T_world_cam_gt), np.asarray(walk.T_world_cam_odom)
    pipeline = Pipeline(walk, field, RecordedOdometry(inv_T(T_odom[0]) @ T_odom), PipelineConfig(keyframe_every=3))
    relocaliser = Relocaliser(index, field, settings=RelocaliseSettings(rival_m=rival_m))
    if not look_alikes:
        relocaliser.look_alike_offsets = []
    pipeline.start_in_map(relocaliser, PlacementSettings(confirm_travel_m=travel_m))
    run = pipeline.run()
    placement = run.placement
    errors = np.linalg.norm(run.T_world_cam_estimate[:, :3, 3] - T_gt[:, :3, 3], axis=1)
    out = {"placed": bool(placement["placed"]), "placed_at_frame": placement["placed_at_frame"],
           "relocalisations_tried": placement["relocalisations_tried"],
           "ambiguous_refusals": sum(str(e.get("reason", "")).startswith("ambiguous") for e in placement["events"]),
           "candidates_in_the_twin": sum(e["step"] == "relocalise" and e["success"]
                                         and floor.room_of(e["at_m"]) != floor.room_of(T_gt[e["frame"], :3, 3])
                                         for e in placement["events"]),
           "odometry_max_error_m": round(float(np.linalg.norm(T_odom[:, :3, 3] - T_gt[:, :3, 3], axis=1).max()), 4)}
    if placement["placed"]:
        at = placement["placed_at_frame"]
        out.update(placed_in_the_twin=bool(errors[at] > 1.0), ate_m=round(float(np.sqrt(np.mean(errors**2))), 4),
                   max_error_m=round(float(errors.max()), 4),
                   placed_after_m=round(float(np.linalg.norm(T_gt[at, :3, 3] - T_gt[0, :3, 3])), 3))
    return out


def twin_starts(args, floor, index: Path, work: Path) -> list[dict]:
    """Runs that start in each room with an earlier twin, looking at a side wall both have."""
    out = []
    for room in range(floor.rooms):
        if not any(q < room for q in floor.twins(room)):
            continue
        end = room - 1  # towards the room between the twins: its door is what tells them apart
        for seed in START_SEEDS:
            walk = _simulate(work / f"floor{floor.rooms}_start{room}_seed{seed}", frames=75, path="traverse",
                             fps=TRAVERSE_FPS * 0.6, seed=seed, width=args.width, height=args.height,
                             scene_seed=FLOOR_SEED, rooms=floor.rooms, start_room=room, end_room=end,
                             look_aside_deg=80.0)
            row = {"start_room": room, "twin": floor.twins(room), "seed": seed}
            for name, rival_m, travel_m, look_alikes in VARIANTS:
                row[name] = place_from_start(floor, index, walk, rival_m, travel_m, look_alikes)
                print(f"  start in room {room} seed {seed} {name}: {row[name]}")
            out.append(row)
    return out


def placement_part(args, work: Path) -> dict:
    from nap3d_graph.mapping.build import index_posed_survey

    floors = {}
    for rooms in args.rooms:
        floor, survey, traverse, length_m = _floor_data(args, rooms, work)
        index = work / f"floor{rooms}_{args.frames_per_room}f_index"
        if not (index / "keyframe_poses.npy").is_file():
            index_posed_survey(survey, index, survey.T_world_cam_gt, progress=True)
        keyframes = len(np.load(index / "keyframe_poses.npy"))
        print(f"floor of {rooms} room(s): {len(survey)} survey frames, {keyframes} keyframes, traverse "
              f"{length_m:.1f} m in {len(traverse)} frames")
        row = {"survey_frames": len(survey), "keyframes": keyframes, "traverse_m": round(length_m, 2),
               "traverse_frames": len(traverse), "relocalisation": relocalise_traverse(floor, index, traverse, 4)}
        print(f"  relocalisation: {row['relocalisation']}")
        row["twin_starts"] = twin_starts(args, floor, index, work)
        floors[str(rooms)] = row
    one = floors.get("1", {}).get("relocalisation", {}).get("seconds", {}).get("median")
    ratios = {k: round(v["relocalisation"]["seconds"]["median"] / one, 3) for k, v in floors.items() if one}
    return {"floor_seed": FLOOR_SEED, "size": [args.width, args.height], "frames_per_room": args.frames_per_room,
            "floors": floors, "relocalisation_seconds_ratio_to_one_room": ratios}


# --- map ---------------------------------------------------------------------------------------


def _timed(command: list[str], log: Path) -> dict:
    """``command`` under ``/usr/bin/time``: its wall seconds, peak memory (GB: the largest one
    process held, workers included) and the peak of all its processes together (sampled every
    half second with psutil: two workers training side by side count twice)."""
    import psutil

    timing = log.with_suffix(".time")
    t0 = time.perf_counter()
    tree_peak = 0
    with open(log, "w") as out:
        process = subprocess.Popen(["/usr/bin/time", "-f", "%M", "-o", str(timing), *command], stdout=out,
                                   stderr=subprocess.STDOUT)
        root = psutil.Process(process.pid)
        while process.poll() is None:
            try:
                tree = [root, *root.children(recursive=True)]
                tree_peak = max(tree_peak, sum(_rss(p) for p in tree))
            except psutil.Error:
                pass
            time.sleep(0.5)
    if process.returncode:
        raise subprocess.CalledProcessError(process.returncode, command)
    return {"wall_s": round(time.perf_counter() - t0, 1),
            "peak_memory_gb": round(int(timing.read_text().split()[-1]) / 1024**2, 3),
            "peak_memory_all_processes_gb": round(tree_peak / 1024**3, 3)}


def _rss(process) -> int:
    try:
        return process.memory_info().rss
    except Exception:  # a process that ended between the listing and the reading
        return 0


def per_room_psnr(floor, map_dir: Path, survey) -> dict:
    """Held-out PSNR (dB) of the map's field per room: survey frames it did not train on, at the
    map's poses, grouped by the room the camera stood in."""
    from nap3d_graph.datasets.posed import PosedSequence
    from nap3d_graph.fields import resolve_field
    from nap3d_graph.fields.evaluation import evaluate_field
    from nap3d_graph.trajectory import read_tum_trajectory

    field = resolve_field(str(map_dir))
    stamps, T_map_cam = read_tum_trajectory(map_dir / "poses.txt")
    index_of = {round(float(t), 6): i for i, t in enumerate(survey.timestamps)}
    frames = [index_of[round(float(t), 6)] for t in stamps]
    T_all = np.full((len(survey), 4, 4), np.nan)
    T_all[frames] = T_map_cam
    trained = set(field.meta.get("train_frames", []))
    held = [i for i in frames if i not in trained][::3]
    posed = PosedSequence(survey, T_all, "map")
    result = evaluate_field(field, posed, held, size=(survey.intrinsics.width, survey.intrinsics.height))
    by_room: dict[int, list[float]] = {}
    for i, row in zip(held, result["per_frame"]):
        by_room.setdefault(floor.room_of(survey.T_world_cam_gt[i][:3, 3]), []).append(row["psnr_db"])
    return {str(r): {"median_db": round(float(np.median(v)), 2), "frames": len(v)} for r, v in sorted(by_room.items())}


def _traverse_run(traverse, map_dir: Path, run_dir: Path, log: Path, repeats: int = 1) -> dict:
    """``nap3d-graph run --odom vo`` of the traverse in the map from its own start, ``repeats``
    times: time and peak memory (the median over the repeats, each repeat's listed: a run's peak
    varies from one repeat of the same command to the next, its native heap growing differently),
    its ATE (and max) through the survey's alignment, the odometry's, where it was placed (of the
    first repeat; ``same_estimate_each_repeat`` says whether the others matched it)."""
    command = [sys.executable, "-m", "nap3d_graph", "run", "--data", str(traverse.path), "--field", str(map_dir),
               "--odom", "vo", "--out", str(run_dir)]
    timed, estimates, row = [], [], {}
    for _ in range(repeats):
        shutil.rmtree(run_dir, ignore_errors=True)
        timed.append(_timed(command, log))
        estimates.append((run_dir / "latest" / "estimate.txt").read_text())
        row = row or _traverse_figures(run_dir / "latest")
    row.update({key: float(np.median([t[key] for t in timed])) for key in timed[0]})
    row.update({f"{key}_each": [t[key] for t in timed] for key in ("wall_s", "peak_memory_gb")},
               same_estimate_each_repeat=len(set(estimates)) == 1)
    return row


def _traverse_figures(run: Path) -> dict:
    """A traverse run's ATE (and max) through the survey's alignment, the odometry's, where it
    was placed, its corrections accepted."""
    metrics = json.loads((run / "metrics.json").read_text())
    placement = (metrics.get("map") or {}).get("placement") or {}
    return dict(ate_m=((metrics["estimate"].get("ate_m") or {}).get("rmse")),
                odometry_ate_m=((metrics["odometry"].get("ate_m") or {}).get("rmse")),
                max_error_m=((metrics["estimate"].get("ate_m") or {}).get("max")),
                placed_at_frame=placement.get("placed_at_frame"), accepted=metrics.get("corrections_accepted"),
                **_ate_around_placement(run, placement.get("placed_at_frame")))


def _ate_around_placement(run: Path, placed_at: int | None) -> dict:
    """The run's ATE (m, against its tied ground truth, ``groundtruth.txt``) over the frames
    before its placement and from it on: the first hang on what the run measured before it
    was placed, the others on the corrections."""
    from nap3d_graph.trajectory import read_tum_trajectory

    if placed_at is None:
        return {}
    stamps_gt, T_gt = read_tum_trajectory(run / "groundtruth.txt")
    stamps, T_est = read_tum_trajectory(run / "estimate.txt")
    # The frames with ground truth: estimate rows k (the run's frame indices), ground-truth rows j.
    _, k, j = np.intersect1d(np.round(stamps, 6), np.round(stamps_gt, 6), return_indices=True)
    errors = np.linalg.norm(T_est[k, :3, 3] - T_gt[j, :3, 3], axis=1)
    before = k < placed_at

    def rmse(e: np.ndarray):
        return round(float(np.sqrt(np.mean(e**2))), 4) if e.size else None

    return {"ate_before_placement_m": rmse(errors[before]), "ate_from_placement_m": rmse(errors[~before])}


def _map_row(args, floor, survey, map_dir: Path, log: Path) -> dict:
    """``nap3d-graph map`` of the survey as a user runs it: time, memory, stages, the survey's
    ATE, the field's held-out PSNR (whole and per room)."""
    before = ["--submap-frames", str(10**6)] if args.one_field else []
    row = _timed([sys.executable, "-m", "nap3d_graph", "map", str(survey.path), "--out", str(map_dir), "--quiet",
                  *before], log)
    info = json.loads((map_dir / "map.json").read_text())
    report = json.loads((map_dir / "field.report.json").read_text())
    row.update(seconds_per_frame=round(row["wall_s"] / len(survey), 3),
               stages_s={k: v["seconds"] for k, v in info["stages"].items()},
               train_seconds=report.get("train_seconds"),
               survey_ate_m=(info.get("survey_ate") or {}).get("map", {}).get("rmse_m"),
               # Frames placed: the survey's but those dropped or lost inside a rejoined run.
               kept_frames=len(survey) - (info.get("segment") or {}).get("dropped_frames", len(survey)),
               held_out_psnr_db=(report.get("held_out") or {}).get("psnr_db"),
               held_out_psnr_per_room=per_room_psnr(floor, map_dir, survey),
               # Where the memory went: the map process's peak by each stage's end, each submap
               # worker's by the end of its submap (a worker may have trained one before it).
               stages_peak_memory_gb={k: v.get("peak_memory_gb") for k, v in info["stages"].items()},
               submap_peak_memory_gb={k: v["report"].get("peak_memory_gb")
                                      for k, v in info["stages"].get("field", {}).get("submaps", {}).items()},
               submaps=info["stages"].get("field", {}).get("submap_count", 1))
    return row


def map_part(args, work: Path) -> dict:
    """Each floor mapped, then crossed; with ``--runs-only`` the maps of an earlier map part (in
    ``--work``, their figures in ``--out``) are kept and only the traverses are run again."""
    floors = {}
    label = "one_field" if args.one_field else "submaps"
    earlier = json.loads(args.out.read_text()) if args.runs_only else None
    for rooms in args.rooms:
        floor, survey, traverse, length_m = _floor_data(args, rooms, work)
        name = f"floor{rooms}_{args.frames_per_room}f_{label}"
        map_dir, run_dir = work / f"{name}_map", work / f"{name}_run"
        row: dict = {"survey_frames": len(survey), "traverse_m": round(length_m, 2), "traverse_frames": len(traverse)}
        if earlier is not None:
            row["map"] = earlier["floors"][str(rooms)]["map"]
            shutil.rmtree(run_dir, ignore_errors=True)
        else:
            row["map"] = _map_row(args, floor, survey, map_dir, work / f"{name}_map.log")
        row["run"] = _traverse_run(traverse, map_dir, run_dir, work / f"{name}_run.log", args.run_repeats)
        print(f"floor of {rooms} room(s): {json.dumps(row)}")
        floors[str(rooms)] = row
    out = {"floor_seed": FLOOR_SEED, "size": [args.width, args.height], "frames_per_room": args.frames_per_room,
           "field": label, "floors": floors}
    if earlier is not None:  # the maps' own record: where their figures were measured
        out["maps_provenance"] = earlier.get("maps_provenance") or earlier["provenance"]
    return out


# --- workers ------------------------------------------------------------------------------------


def workers_part(args, work: Path) -> dict:
    """The field stage alone (the survey at its true poses, cut into submaps), the same fields
    trained one after another in this process, on 2 worker processes and as 2 Ray tasks: wall
    time and whether the checkpoints are the same (fixed steps)."""
    import torch

    from nap3d_graph.fields import resolve_field
    from nap3d_graph.mapping.build import MapSettings
    from nap3d_graph.mapping.folder import MapFolder
    from nap3d_graph.mapping.submap_fields import train_submap_fields
    from nap3d_graph.mapping.submaps import plan_submaps
    from nap3d_graph.pools import LocalPool, RayPool, SerialPool

    rooms = args.rooms[0]
    _, survey, _, _ = _floor_data(args, rooms, work)
    T = np.asarray(survey.T_world_cam_gt)
    settings = MapSettings(steps=args.steps)
    plan = plan_submaps(T, settings.submaps)
    out: dict = {"rooms": rooms, "survey_frames": len(survey), "submaps": len(plan), "steps": args.steps, "pools": {}}
    fields = {}
    for name, make in (("serial", SerialPool), ("2 processes", lambda: LocalPool(2)),
                       ("2 Ray tasks", lambda: RayPool("auto", 2))):
        root = work / f"workers_{rooms}_{name.replace(' ', '_')}"
        if root.exists():
            import shutil

            shutil.rmtree(root)
        folder = MapFolder.open(root, {"data": str(survey.path)}, ("data",))
        t0 = time.perf_counter()
        pool = make()
        try:
            train_submap_fields(survey, T, folder, plan, settings, settings.submaps, {"steps": args.steps}, None, pool,
                                "cpu")
        finally:
            pool.close()
        seconds = time.perf_counter() - t0
        fields[name] = resolve_field(str(root))
        out["pools"][name] = {"wall_s": round(seconds, 1)}
        print(f"{name}: {seconds:.0f} s")
    def grid(f):  # a submap trained in a level frame of its own is framed: compare its grid
        return getattr(f, "field", f)

    base = fields["serial"]
    for name, field in fields.items():
        same = all(torch.equal(v, grid(b).state_dict()[k]) for a, b in zip(field.fields, base.fields)
                   for k, v in grid(a).state_dict().items() if isinstance(v, torch.Tensor))
        out["pools"][name].update(same_fields_as_serial=bool(same),
                                  ratio_to_serial=round(out["pools"][name]["wall_s"] / out["pools"]["serial"]["wall_s"],
                                                        3))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("placement", "map", "workers"), required=True)
    parser.add_argument("--steps", type=int, default=600, help="workers part: grid steps per submap field")
    parser.add_argument("--rooms", type=int, nargs="+", default=[1, 3, 6])
    parser.add_argument("--frames-per-room", type=int, default=270,
                        help="survey frames per room (the one-room survey's 270 at 3.75 Hz)")
    parser.add_argument("--one-field", action="store_true",
                        help="map part: one field for the whole floor (before submaps: --submap-frames beyond the survey)")
    parser.add_argument("--runs-only", action="store_true",
                        help="map part: keep the maps (in --work) and their figures (in --out) of an earlier map part "
                             "and run the traverses in them again")
    parser.add_argument("--run-repeats", type=int, default=3,
                        help="map part: each traverse run this many times (its time and peak memory: the median)")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--work", type=Path, default=Path("/tmp/nap3d_building"))
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    parts = {"placement": placement_part, "map": map_part, "workers": workers_part}
    result = parts[args.part](args, args.work)
    write_result(args.out, {"command": " ".join(sys.argv), **result}, args)


if __name__ == "__main__":
    main()
