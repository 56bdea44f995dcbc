"""Do the reports tell a failure without ground truth? Faults injected into a real map and
real runs, each against the figure meant to reveal it.

On fr1/desk at 15 Hz (shared data): the first half is the survey (its map, built here unless
``--map`` gives one), the second half the query. Cases:

- clean: the map's report, and the second half run in the map: nothing past a bad line;
- blurred field: the map's splats' colours averaged over 12 cm cubes (a blurred field), its
  held-out PSNR and the run's corrections;
- false loops: the pose graph solved again with one wrong loop forced in as a non-robust edge,
  then the bundle adjustment over the images as ``map`` runs it (the loops the bent graph turned
  away decided again): two keyframes far apart said to be 10 cm from where they are (a pose
  alone: the bundle never sees it), and a look-alike place's loop, its matches in the bundle
  too (a kept loop moved 10 cm, its matches made to agree); the map's figures at the final
  poses, and the keyframes' ATE at the graph's and at the final poses (scoring only);
- covariances 10x too cautious and 10x too confident: the second half run in the clean map with
  NAP3D's covariance inflation and the field's error sigmas scaled (covariance x10, x0.1); the
  run's two-sided gate consistency;
- depth in the wrong unit: the query read at 1000 units per metre (x5 too far): the warning
  before any work, and the run's corrections;
- map of another room: 7-Scenes' kitchen run in the desk's map: never placed.

The ground truth only scores afterwards (the ATE column), never the verdicts.

    python benchmarks/report_faults.py --desk ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --kitchen ../shared/data/7scenes/redkitchen --work /tmp/faults \\
        --out benchmarks/results/report_faults_fr1_desk.json
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


def cli(*args: str) -> tuple[int, str]:
    """Run ``nap3d-graph ARGS`` in a fresh process; (exit code, stderr)."""
    done = subprocess.run([sys.executable, "-m", "nap3d_graph", *args], capture_output=True, text=True)
    if done.returncode not in (0, 2):
        print(done.stderr[-2000:], file=sys.stderr)
    return done.returncode, done.stderr


def run_case(data: Path, frames: str, map_dir: Path, out: Path, extra=()) -> dict:
    """The query run in ``map_dir``; its report's verdicts and figures."""
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    rc, err = cli("run", "--data", str(data), "--frames", frames, "--field", str(map_dir), "--out", str(out), *extra)
    entry: dict = {"exit": rc, "seconds": round(time.perf_counter() - t0, 1),
                   "warnings": [line for line in err.splitlines() if line.startswith("warning: ")][:5]}
    metrics_path = out / "latest" / "metrics.json"
    if rc != 0 or not metrics_path.is_file():
        entry["error"] = err.strip().splitlines()[-1] if err.strip() else "no output"
        return entry
    metrics = json.loads(metrics_path.read_text())
    from nap3d_graph.run.report import read_run_report

    report = read_run_report(out / "latest")
    entry.update({"past_bad_line": report.bad, "rows": [list(r) for r in report.rows],
                  "ate_m": ((metrics.get("estimate") or {}).get("ate_m") or {}).get("rmse"),
                  "ate_se3_aligned_m": (metrics.get("estimate") or {}).get("ate_se3_aligned_m")})
    return entry


def blurred_map(map_dir: Path, out: Path, cell_m: float) -> Path:
    """A copy of ``map_dir`` whose splat field is blurred: each splat takes the mean colour of
    the splats in its ``cell_m`` cube (a box blur of the field's texture; depth untouched)."""
    import torch

    from nap3d_graph.fields import load_field

    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(map_dir, out)
    field = load_field(out / "field.pt")
    points, colours = field.points.numpy(), field.colors.numpy()
    _, cell = np.unique(np.floor(points / cell_m).astype(np.int64), axis=0, return_inverse=True)
    cell = cell.ravel()
    counts = np.bincount(cell)
    means = np.stack([np.bincount(cell, weights=colours[:, c]) / counts for c in range(colours.shape[1])], axis=1)
    field.colors = torch.as_tensor(means[cell].astype(np.float32))
    field.save(out / "field.pt")
    return out


def _held_out(map_dir: Path, sequence) -> dict:
    """The field's figures on the survey frames it did not train on, measured again."""
    from nap3d_graph.datasets.posed import PosedSequence
    from nap3d_graph.fields import load_field
    from nap3d_graph.fields.evaluation import evaluate_field
    from nap3d_graph.trajectory import read_tum_trajectory

    report = json.loads((map_dir / "field.report.json").read_text())
    frames = report["held_out"]["frames"]
    stamps, T = read_tum_trajectory(map_dir / "poses.txt")
    posed = PosedSequence(sequence, _by_stamp(sequence, stamps, T), "map")
    field = load_field(map_dir / "field.pt")
    size = tuple(report["held_out"]["render_size"])
    report["held_out"] = evaluate_field(field, posed, frames, None, size=size)
    # NAP3D of the held-out frames against the field, as map measures it.
    from nap3d_graph.datasets.depth_timing import CaptureTiming
    from nap3d_graph.fields.build import ERROR_FRAMES
    from nap3d_graph.fields.field_error import measure_field_error
    from nap3d_graph.fields.training_data import split_posed_frames
    from nap3d_graph.nap3d.config import AlignConfig

    _, error_idx = split_posed_frames(posed, 1, ERROR_FRAMES)
    report["field_error"] = measure_field_error(field, posed, error_idx, CaptureTiming.of(field.meta.get("timing")),
                                                AlignConfig(matcher=report["field_error"].get("matcher", "xfeat")),
                                                size)
    (map_dir / "field.report.json").write_text(json.dumps(report, indent=1, default=float))
    return report


def _by_stamp(sequence, stamps: np.ndarray, T: np.ndarray) -> np.ndarray:
    out = np.full((len(sequence), 4, 4), np.nan)
    index = {round(float(s), 6): k for k, s in enumerate(stamps)}
    for i, s in enumerate(sequence.timestamps):
        k = index.get(round(float(s), 6))
        if k is not None:
            out[i] = T[k]
    return out


def twin_loop(verified: list, intrinsics, error_m: float):
    """A false loop as a look-alike place gives one: the kept loop with the most matches between
    the keyframes farthest apart in the survey, its relative pose moved ``error_m`` (along x) and
    its matches re-made to agree with the moved pose (keyframe a's matched points seen from b as
    if b stood where the false pose puts it: identical structure, displaced). ``(loop, Edge,
    PairMatches)``: the true loop it replaces, the false loop as a non-robust edge and its matches."""
    from nap3d_graph.camera import backproject, project
    from nap3d_graph.conventions import exp_se3, inv_T
    from nap3d_graph.mapping.bundle import PairMatches
    from nap3d_graph.mapping.pose_graph import Edge

    candidates = [lp for lp in verified if lp.status == "accepted" and lp.matches_kept is not None
                  and len(lp.matches_kept.z_a) >= 30]
    true = max(candidates, key=lambda lp: (abs(lp.b - lp.a), len(lp.matches_kept.z_a)))
    T_false = true.T_a_b @ exp_se3(np.array([0, 0, 0, error_m, 0, 0]))
    m = true.matches_kept
    points_a = backproject(m.uv_a, m.z_a, intrinsics)
    points_b = points_a @ inv_T(T_false)[:3, :3].T + inv_T(T_false)[:3, 3]
    uv_b, z_b = project(points_b, intrinsics)
    seen = (z_b > 0) & (uv_b[:, 0] >= 0) & (uv_b[:, 0] < intrinsics.width) & (uv_b[:, 1] >= 0) & (
        uv_b[:, 1] < intrinsics.height)
    matches = PairMatches(true.a, true.b, m.uv_a[seen], uv_b[seen], m.z_a[seen], z_b[seen])
    return true, Edge(true.a, true.b, T_false, np.diag([1e-6] * 6), "alignment"), matches


def false_loop_map(map_dir: Path, out: Path, error_m: float, survey, matches: bool = False) -> tuple[Path, dict]:
    """A copy of ``map_dir`` whose keyframe poses were solved again as ``map`` solves them: the
    pose graph with the loops it verified and, when ``error_m`` > 0, one false loop forced in as
    a non-robust edge, then (where the map had one) the bundle adjustment over the survey's
    images (``error_m`` 0: the same solves without it, the reference). The false loop: without
    ``matches``, the first and the middle keyframe said to be ``error_m`` from where the map has
    them (the bundle never sees it); with ``matches``, a look-alike place's loop
    (:func:`twin_loop`) whose matches enter the bundle too. Also returns the keyframes' ATE at the
    graph's and at the final poses against ``survey``'s ground truth (scoring only)."""
    import csv

    from nap3d_graph.evaluation.alignment import aligned_errors
    from nap3d_graph.mapping.build import MapSettings, graph_and_bundle
    from nap3d_graph.mapping.loops import load_edges
    from nap3d_graph.mapping.survey import SurveyOdometry

    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(map_dir, out)
    chain, loops, chain_matches = load_edges(out / "edges.npz")
    T_key = np.load(out / "keyframe_poses.npy")
    keys = np.load(out / "keyframes.npz")["indices"]
    info = json.loads((out / "map.json").read_text())
    with (out / "loops.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    for lp, row in zip(loops, rows):
        lp.status = row["status"]
    verified = [lp for lp in loops if lp.status in ("accepted", "rejected", "admitted")]
    settings = MapSettings(bundle="bundle" in info)
    forced, forced_matches = _false_loop(verified, T_key, survey, settings, error_m, matches)
    graph, T_final, bundle = graph_and_bundle(survey, keys, SurveyOdometry.load(out / "odometry.npz"),
                                              [*chain, *forced], verified, [*chain_matches, *forced_matches],
                                              settings)
    np.save(out / "keyframe_poses.npy", T_final)
    info["mesh"] = _mesh_at(out, survey, keys, T_final, info)
    for name in ("field.pt", "field.report.json"):  # trained at the map's poses, not these: no stale figure
        (out / name).unlink(missing_ok=True)
    info["loops"].update(accepted=sum(lp.status == "accepted" for lp in verified),
                         admitted=sum(lp.status == "admitted" for lp in verified))
    if bundle is not None:
        info["bundle"] = bundle
    (out / "map.json").write_text(json.dumps(info, indent=1, default=float))
    _write_statuses(out / "loops.csv", rows, loops)
    stamps, T_gt = np.asarray(survey.timestamps)[keys], np.asarray(survey.T_world_cam_gt)[keys]
    scores = {"keyframes_ate_graph_m": aligned_errors(stamps, T_gt, graph.T_map_key).summary()["rmse_m"],
              "keyframes_ate_final_m": aligned_errors(stamps, T_gt, T_final).summary()["rmse_m"],
              "loops_kept": sum(lp.status == "accepted" for lp in verified),
              "loops_admitted": sum(lp.status == "admitted" for lp in verified), "loops_verified": len(verified),
              **({"twin_matches": len(forced_matches[0].z_a)} if forced_matches else {})}
    return out, scores


def _write_statuses(path: Path, rows: list[dict], loops: list) -> None:
    """``loops.csv`` again with each loop's decision as these solves took them."""
    import csv

    for row, lp in zip(rows, loops):
        row["status"] = lp.status
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _mesh_at(folder: Path, survey, keys: np.ndarray, T_map_key: np.ndarray, info: dict) -> dict:
    """The survey fused again at these keyframe poses (its frames placed as ``map`` places
    them): ``map.ply`` and its walls, as ``map.json`` records them."""
    from nap3d_graph.datasets.depth_timing import CaptureTiming
    from nap3d_graph.datasets.posed import PosedSequence
    from nap3d_graph.mapping.build import place_kept_frames
    from nap3d_graph.mapping.mesh import fuse_mesh
    from nap3d_graph.mapping.survey import SurveyOdometry

    segment = info["segment"]
    T_map_cam = place_kept_frames(SurveyOdometry.load(folder / "odometry.npz"), keys, T_map_key, segment["start"],
                                  segment["stop"], [tuple(g) for g in segment.get("rejoined", [])])
    report = folder / "field.report.json"  # the depth moved to the colour's instant as map fuses it
    timing = CaptureTiming.of(json.loads(report.read_text()).get("timing")) if report.is_file() else None
    return fuse_mesh(PosedSequence(survey, T_map_cam, "map"), folder / "map.ply", timing=timing).to_dict()


def _false_loop(verified: list, T_key: np.ndarray, survey, settings, error_m: float, matches: bool
                ) -> tuple[list, list]:
    """The false loop's edges and matches to force in (none for ``error_m`` 0): a look-alike
    place's loop replacing the true one it copies (taken out of ``verified``), or without
    ``matches`` the first and the middle keyframe said to be ``error_m`` apart from the map."""
    from nap3d_graph.conventions import exp_se3, inv_T
    from nap3d_graph.mapping.build import _working_intrinsics
    from nap3d_graph.mapping.pose_graph import Edge

    if error_m <= 0:
        return [], []
    if matches:
        true, edge, pair = twin_loop(verified, _working_intrinsics(survey, settings), error_m)
        verified.remove(true)
        true.status, true.reason = "refused", "replaced by the fault benchmark's false loop"
        return [edge], [pair]
    a, b = 0, len(T_key) // 2
    T_ab = inv_T(T_key[a]) @ T_key[b] @ exp_se3(np.array([0, 0, 0, error_m, 0, 0]))
    return [Edge(a, b, T_ab, np.diag([1e-6] * 6), "alignment")], []


def scaled_covariance_config(map_dir: Path, factor: float, out: Path) -> Path:
    """A run config (``--config``) whose corrections' covariances are ``factor`` times the
    defaults': NAP3D's covariance inflation (its matcher's, XFeat) and the field's error
    sigmas the map's field records, scaled (the field's error by view is then off)."""
    import yaml

    from nap3d_graph.fields import load_field
    from nap3d_graph.fields.base import field_sigmas
    from nap3d_graph.nap3d.config import MATCHER_NOISE

    noise = {k: v * factor for k, v in MATCHER_NOISE["xfeat"].items() if k.startswith("covariance_inflation")}
    sigma_m, sigma_rad = field_sigmas(load_field(map_dir / "field.pt"))
    settings = {"alignment": {"matcher": "xfeat", "nap3d": noise, "field_sigma_m": sigma_m * factor**0.5,
                              "field_sigma_rad": sigma_rad * factor**0.5}}
    out.write_text(yaml.safe_dump({"settings": settings}))  # a run's config.yaml holds its tree under 'settings'
    return out


def main() -> None:
    from nap3d_graph.datasets import open_sequence
    from nap3d_graph.datasets.depth_unit import inspect_depth_unit
    from nap3d_graph.mapping.report import map_report

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--desk", type=Path, required=True, help="TUM fr1/desk (15 Hz, shared data)")
    parser.add_argument("--kitchen", type=Path, required=True, help="7-Scenes redkitchen (another room)")
    parser.add_argument("--map", type=Path, default=None, help="a map of the desk's first half (default: built in --work)")
    parser.add_argument("--blur-m", type=float, default=0.12,
                        help="the blurred field's cube: each splat takes its cube's mean colour (default 0.12 m)")
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    map_dir = args.map or args.work / "map"
    if args.map is None and not (map_dir / "field.pt").is_file():
        rc, err = cli("map", str(args.desk), "--frames", "0:0.5", "--model", "splat", "--out", str(map_dir), "--quiet")
        assert rc == 0, err
    survey = open_sequence(args.desk, frames="0:0.5")
    result: dict = {"desk": str(args.desk), "kitchen": str(args.kitchen), "map": {}, "runs": {}}

    def map_case(name: str, folder: Path) -> None:
        report = map_report(folder)
        result["map"][name] = {"past_bad_line": report.bad, "rows": [list(r) for r in report.rows],
                               "values": report.values}
        print(f"map {name}: past the bad line: {report.bad or 'nothing'}")

    result["blur_m"] = args.blur_m
    map_case("clean", map_dir)
    blurred = blurred_map(map_dir, args.work / "map_blurred", args.blur_m)
    _held_out(blurred, survey)
    map_case("blurred field", blurred)
    for name, error_m, matches in (("graph and bundle solved again (reference for the false loops)", 0.0, False),
                                   ("false loop forced into the pose graph", 0.10, False),
                                   ("false loop with a look-alike place's matches, in graph and bundle", 0.10, True)):
        folder, scores = false_loop_map(map_dir, args.work / f"map_false_loop_{error_m:g}{'_matches' * matches}",
                                        error_m, survey, matches)
        map_case(name, folder)
        result["map"][name]["scores"] = scores
        print(f"  {scores}")

    look = inspect_depth_unit(open_sequence(args.desk, frames="0.5:1", depth_scale=1000))
    result["depth_unit_warning_before_work"] = list(look.warnings)
    print(f"query read at 1000 per metre: {look.warnings}")

    cases = {"clean": (args.desk, "0.5:1", map_dir, ()),
             "blurred field": (args.desk, "0.5:1", blurred, ()),
             "depth in the wrong unit": (args.desk, "0.5:1", map_dir, ("--depth-scale", "1000")),
             "map of another room": (args.kitchen, "0:150", map_dir, ()),
             **{f"covariances {name}": (args.desk, "0.5:1", map_dir, ("--config", str(scaled_covariance_config(
                 map_dir, factor, args.work / f"covariance_x{factor:g}.yaml"))))
                for name, factor in (("10x too cautious", 10.0), ("10x too confident", 0.1))}}
    for name, (data, frames, folder, extra) in cases.items():
        entry = run_case(data, frames, folder, args.work / f"run_{name.replace(' ', '_')}", extra)
        result["runs"][name] = entry
        print(f"run {name}: past the bad line: {entry.get('past_bad_line', entry.get('error'))}; ATE "
              f"{entry.get('ate_m')}")
    write_result(args.out, result, args)


if __name__ == "__main__":
    main()
