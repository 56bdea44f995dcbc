"""Is the map good? ``report.md`` in the map folder, from figures that need no ground truth
(where the survey has ground truth, its ATE is added as the reference they are checked
against in ``benchmarks/report_faults.py``).

The figures and the lines past which they say something went wrong:

- **loops kept**: verified loop closures the robust graph kept. None kept: the map's poses
  are the odometry's alone and drift as it does.
- **loop residual**: how far each kept loop's measured relative pose is from the final
  poses (median over loops). A consistent map agrees with its own loops to about NAP3D's
  accuracy (millimetres); beyond 2 cm or 1 deg the loops and the map disagree (a false loop
  forced in, a bad edge).
- **verified loops turned away**: loops that passed verification (look-alike places already
  refused) but that neither the robust graph kept nor the bundle adjustment admitted, counted
  where the final poses miss them by more than 5 cm or 3 deg. A wrong loop that verification let
  through is turned away like this, and it is rare (none of the simulated twin rooms' pictures
  verified: ``benchmarks/results/map_false_loops.json``); a map bent by a false loop turns away
  the true loops that disagree with the bend, several at once. More than 2, and more than 2% of
  the verified loops: the map and its own verified loops disagree. Set knowing the fault
  benchmark's look-alike loop (7 turned away, all missed by the bend) and the clean maps of
  fr1/desk and the simulated floors (at most one turned away, none missed).
- **bundle reprojection residual**: the bundle adjustment's median reprojection error at
  its final noise; beyond 1.5 px the poses and the landmarks disagree (a wrong camera, a
  wrong depth unit, a bent map).
- **depth against the images**: the depth the sensor measured at the survey's matches against
  their depth triangulated from the images and the final poses, in bins from near to far
  (:mod:`.depth_check`); a bin more than 5% off the median bin's ratio, or a fitted disparity
  offset beyond 0.03 per metre (3% of the depth per metre of it): the depth's shape and the
  images disagree (a depth camera's calibration, a wrong focal length or registration).
- **field on held-out survey frames**: the field rendered at survey frames it was not
  trained on, against those frames: PSNR (after a per-frame affine colour fit), median depth
  error and the share of the frame it covers, and NAP3D of those frames against the field
  (how many fail, how far from the map's pose they land). Below 12 dB it does not look like
  the place (the line is set from fr1/desk's splat maps, 14-17 dB: a crude field of a real
  room); a median depth error beyond 3 cm or less than 70% covered, NAP3D has too little of
  the field to align with; more than half failing or a median beyond 3 cm, the field cannot
  correct a run.
- **walls of the mesh**: how far apart frames that see the same part of one of the largest planes
  of the fused mesh put it (90th percentile over pairs of frames, compared cell by cell:
  :mod:`.mesh`): millimetres on a consistent survey; beyond 3 cm the survey put one surface in
  two places (a doubled wall).
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np

from nap3d_graph.conventions import inv_T, pose_error
from nap3d_graph.evaluation.alignment import aligned_errors
from nap3d_graph.fields.submaps import SUBMAPS_INDEX, Submap
from nap3d_graph.figure_report import FigureReport
from nap3d_graph.textfiles import write_json_atomic

from .depth_check import DEPTH_OFFSET_BAD_PER_M, DEPTH_SHAPE_BAD
from .folder import MapFolder
from .mesh import WALL_THICKNESS_BAD_M

__all__ = ["MapReport", "map_report", "write_map_report", "write_outputs", "LOOP_RESIDUAL_BAD", "TURNED_AWAY_BAD",
           "TURNED_AWAY_MISS", "REPROJECTION_BAD_PX",
           "HELD_OUT_PSNR_BAD_DB", "HELD_OUT_DEPTH_BAD_M", "COVERED_BAD", "HELD_OUT_NAP3D_BAD_M"]

log = logging.getLogger(__name__)

#: A median loop residual beyond these (metres, degrees): the loops and the map disagree.
LOOP_RESIDUAL_BAD = (0.02, 1.0)
#: A verified loop turned away that the final poses miss by more than this (metres, degrees)...
TURNED_AWAY_MISS = (0.05, 3.0)
#: ... counts against the map beyond this many, or this share of the verified loops.
TURNED_AWAY_BAD = (2, 0.02)
#: The bundle's median reprojection error beyond this (pixels).
REPROJECTION_BAD_PX = 1.5
#: Held-out PSNR below this (dB, affine colour fit): the field does not look like the place.
HELD_OUT_PSNR_BAD_DB = 12.0
#: Held-out median depth error beyond this (metres).
HELD_OUT_DEPTH_BAD_M = 0.03
#: Held-out share of the frame the field covers below this.
COVERED_BAD = 0.7
#: NAP3D of held-out survey frames against the field landing further than this from the map's
#: pose (median; metres), or more than half of them failing: the field cannot correct a run.
HELD_OUT_NAP3D_BAD_M = 0.03


class MapReport(FigureReport):
    """The figures of one map; ``values``: its numbers, for metrics and benchmarks."""

    def __init__(self):
        super().__init__()
        self.values: dict = {}


def loop_residuals(folder: Path, statuses: tuple[str, ...] = ("accepted",)) -> np.ndarray:
    """(L, 2): the translation (m) and rotation (deg) disagreement with the map's final keyframe
    poses of each loop whose status in ``loops.csv`` is one of ``statuses`` (default: the loops
    the graph kept; measurements in ``edges.npz``, in the same order; poses in
    ``keyframe_poses.npy``); (0, 2) when none."""
    files = MapFolder(Path(folder))
    edges, poses, table = files.edges, files.keyframe_poses, files.loops_table
    if not (edges.is_file() and poses.is_file() and table.is_file()):
        return np.zeros((0, 2))
    with table.open(newline="") as f:
        status = [row["status"] for row in csv.DictReader(f)]
    T_map_key = np.load(poses)
    with np.load(edges) as d:
        if len(d["loop_abij"]) != len(status):
            log.warning("%s: loops.csv and edges.npz list different loops; no loop residuals", folder)
            return np.zeros((0, 2))
        rows = [pose_error(T_ab, inv_T(T_map_key[a]) @ T_map_key[b])
                for (a, b, *_), T_ab, kept in zip(d["loop_abij"], d["loop_T"], status) if kept in statuses]
    return np.asarray(rows, dtype=float).reshape(-1, 2)


def _loops(report: MapReport, info: dict, folder: Path) -> None:
    loops = info.get("loops", {})
    kept = int(loops.get("accepted", 0))
    report.values["loops"] = loops
    report.add("loops: candidates, verified, kept by the robust graph (and admitted by the bundle adjustment)",
               f"{loops.get('candidates', 0)}, {loops.get('verified', 0)}, {kept} ({loops.get('admitted', 0)})",
               "some kept", kept > 0)
    residuals = loop_residuals(folder)
    if len(residuals):
        median_m, median_deg = (float(v) for v in np.median(residuals, axis=0))
        p90_m = float(np.percentile(residuals[:, 0], 90))
        report.values["loop_residual"] = {"median_m": median_m, "p90_m": p90_m, "median_deg": median_deg,
                                          "max_m": float(residuals[:, 0].max())}
        report.add("loop residual at the final poses (median, p90; median angle)",
                   f"{median_m * 100:.2f}, {p90_m * 100:.2f} cm; {median_deg:.2f} deg",
                   f"<= {LOOP_RESIDUAL_BAD[0] * 100:.0f} cm and {LOOP_RESIDUAL_BAD[1]:.0f} deg",
                   median_m <= LOOP_RESIDUAL_BAD[0] and median_deg <= LOOP_RESIDUAL_BAD[1])
    _turned_away(report, folder, int(loops.get("verified", 0)))


def _turned_away(report: MapReport, folder: Path, verified: int) -> None:
    """The verified loops the map turned away (neither the robust graph nor the bundle took
    them; look-alike places are refused before, and not counted) that its final poses miss by
    more than ``TURNED_AWAY_MISS`` (see the module's text)."""
    residuals = loop_residuals(folder, ("rejected",))
    missed = int(np.sum((residuals[:, 0] > TURNED_AWAY_MISS[0]) | (residuals[:, 1] > TURNED_AWAY_MISS[1])))
    allowed = max(TURNED_AWAY_BAD[0], TURNED_AWAY_BAD[1] * verified)
    report.values["turned_away"] = {"loops": len(residuals), "missed": missed, "allowed": allowed}
    report.add(f"verified loops the map turned away, and those its final poses miss by more than "
               f"{TURNED_AWAY_MISS[0] * 100:.0f} cm or {TURNED_AWAY_MISS[1]:.0f} deg",
               f"{len(residuals)}, {missed} missed (of {verified} verified)",
               f"at most {TURNED_AWAY_BAD[0]} or {TURNED_AWAY_BAD[1]:.0%} of the verified missed", missed <= allowed)


def _bundle(report: MapReport, info: dict) -> None:
    bundle = info.get("bundle") or {}
    rounds = bundle.get("noise_rounds") or []
    if not rounds:
        return
    last = rounds[-1]
    report.values["bundle"] = {"residual_px": last["residual_px"], "residual_disparity_px": last["residual_disparity_px"],
                               "depth_sigma_at_1m_mm": bundle.get("depth_sigma_at_1m_mm")}
    report.add("bundle adjustment: median reprojection residual", f"{last['residual_px']:.2f} px "
               f"({bundle.get('landmarks', 0)} landmarks)", f"<= {REPROJECTION_BAD_PX} px",
               last["residual_px"] <= REPROJECTION_BAD_PX)
    scatter = ((bundle.get("depth_against_images") or {}).get("scatter_at_1m_mm"))
    measured = (f"; the sensor's depth scatters {scatter:.0f} mm about the images' triangulation at 1 m (an upper "
                "bound of its noise)" if scatter is not None else "")
    report.add("bundle adjustment: median depth residual (as disparity)", f"{last['residual_disparity_px']:.2f} px; "
               f"the adjustment weighs a depth at 1 m as {bundle.get('depth_sigma_at_1m_mm', float('nan')):.0f} mm "
               "uncertain (its fitted weight, not the sensor's noise)" + measured, "the sensor's noise", None)


def _depth_check(report: MapReport, info: dict) -> None:
    check = (info.get("bundle") or {}).get("depth_against_images")
    if not check:
        return
    if "reason" in check:
        report.add("depth against the images' triangulation", f"not measured: {check['reason']}", "measured", None)
        return
    (near_m, near), (far_m, far) = check["bins"][0], check["bins"][-1]
    report.values["depth_against_images"] = {"worst": check["worst"], "near": [near_m, near], "far": [far_m, far]}
    sigma = check.get("intercept_sigma_per_m")
    offset = f"offset {check['intercept_per_m']:+.3f}" + (f" +- {sigma:.3f}" if sigma is not None else "") + " /m"
    if check.get("offset_measurable") is False:
        offset += (f" (not measurable from this survey: its depths {near_m:.2f}-{far_m:.2f} m span too little to tell "
                   "an offset from none; judged on the bins alone)")
    report.add("depth against the images' triangulation (depth / images, the median bin as the metre; the "
               "disparity offset fitted)",
               f"{near:.3f} at {near_m:.2f} m, {far:.3f} at {far_m:.2f} m; worst bin {check['worst']:.1%} off; "
               f"{offset} ({check['observations']} observations)",
               f"every bin within {DEPTH_SHAPE_BAD:.0%}, the offset within {DEPTH_OFFSET_BAD_PER_M:.2f} /m where "
               "measurable", not check["bad"])


def _number(value) -> float:
    """A figure read from a report, NaN where it is missing (None)."""
    return float("nan") if value is None else float(value)


def _field(report: MapReport, folder: Path) -> None:
    path = MapFolder(Path(folder)).field_report
    if not path.is_file():
        report.add("field", "not built (--no-field)", "built", None)
        return
    held = json.loads(path.read_text()).get("held_out") or {}
    if not held.get("frames"):
        report.add("field on held-out survey frames", "none held out (too short a survey)", "some", None)
        return
    psnr = _number(held.get("psnr_affine_db", held.get("psnr_db")))
    # No median where the field covered none of the held-out frames: the report says so, not a crash.
    depth = _number((held.get("depth_abs_err_m") or {}).get("median"))
    covered = _number(held.get("opaque_fraction"))
    report.values["held_out"] = {"frames": len(held["frames"]), "psnr_affine_db": psnr, "depth_median_m": depth,
                                 "covered": covered}
    n = len(held["frames"])
    report.add(f"field on {n} held-out survey frames: PSNR (affine colour fit)", f"{psnr:.1f} dB",
               f">= {HELD_OUT_PSNR_BAD_DB:.0f} dB", psnr >= HELD_OUT_PSNR_BAD_DB)
    report.add("field on held-out survey frames: median depth error", f"{depth * 100:.2f} cm",
               f"<= {HELD_OUT_DEPTH_BAD_M * 100:.0f} cm", depth <= HELD_OUT_DEPTH_BAD_M)
    report.add("field on held-out survey frames: share of the frame covered", f"{covered:.0%}",
               f">= {COVERED_BAD:.0%}", covered >= COVERED_BAD)
    measured = json.loads(path.read_text()).get("field_error") or {}
    if measured.get("frames"):
        failed = int(measured.get("failed", 0))
        tried = int(measured["frames"]) + failed
        moved = float(measured.get("translation_error_m_median", float("nan")))
        report.values["held_out_nap3d"] = {"frames": tried, "failed": failed, "median_m": moved}
        report.add("NAP3D on held-out survey frames against the field (failed; median distance from the map's pose)",
                   f"{failed} of {tried} failed; " + (f"{moved * 100:.2f} cm" if np.isfinite(moved) else
                                                      "too few to measure"),
                   f"most align, within {HELD_OUT_NAP3D_BAD_M * 100:.0f} cm",
                   False if failed > tried / 2 else None if not np.isfinite(moved) else moved <= HELD_OUT_NAP3D_BAD_M)


def _mesh(report: MapReport, info: dict) -> None:
    mesh = info.get("mesh")
    if mesh is None:
        return
    if not mesh.get("file"):
        report.add("mesh (map.ply)", f"not written: {mesh.get('reason', '')}", "written", None)
        return
    walls = mesh.get("wall_thickness") or {}
    thickness = walls.get("thickness_m")
    if thickness is None:
        report.add("mesh walls: how far apart frames put each large plane (worst)",
                   f"not measured: {walls.get('reason', '')}", "measured", None)
        return
    report.values["wall_thickness_m"] = thickness
    report.add(f"mesh walls: how far apart frames that see the same part of each of the {len(walls['planes'])} "
               "largest planes put it (p90 over pairs; worst plane, median plane)", f"{thickness * 100:.1f} cm; {walls['median_plane_m'] * 100:.1f} cm",
               f"within {WALL_THICKNESS_BAD_M * 100:.0f} cm", thickness <= WALL_THICKNESS_BAD_M)


def map_report(folder) -> MapReport:
    """The map's figures without ground truth, read from its folder."""
    folder = Path(folder)
    info = MapFolder.read(folder).info
    report = MapReport()
    _loops(report, info, folder)
    _bundle(report, info)
    _depth_check(report, info)
    _field(report, folder)
    _mesh(report, info)
    ate = (info.get("survey_ate") or {}).get("map")
    if ate:
        odometry = info["survey_ate"].get("odometry_only", {})
        report.values["survey_ate_m"] = ate["rmse_m"]
        report.add("survey ATE against the ground truth (where there is one)",
                   f"{ate['rmse_m'] * 100:.2f} cm (odometry alone {odometry.get('rmse_m', float('nan')) * 100:.2f})"
                   + (f"; orientation {ate['rotation_median_deg']:.2f} deg median"
                      if "rotation_median_deg" in ate else ""),
                   "the reference the figures above are checked against", None)
    return report


def write_map_report(folder) -> MapReport:
    """Write ``report.md`` into the map folder; returns the report."""
    files = MapFolder(Path(folder))
    report = map_report(files.root)
    report.write(files.report, "Is the map good?", f"![the map from above, loops drawn]({files.plot.name})")
    return report


# --- written once the survey's poses are final ------------------------------------------


def write_outputs(folder: MapFolder, sequence, survey, segment: tuple[int, int], T_map_cam: np.ndarray,
                  T_map_key: np.ndarray, T_graph_cam: np.ndarray | None, loops: list, verified: list) -> None:
    """The map's last outputs, once its poses are final: ``survey_ate.json`` where the
    recording has ground truth (read only now), the loop counts in ``map.json``, ``map.png``
    and ``report.md`` (its verdict in ``map.json`` too). ``T_graph_cam``: the frames placed by
    the pose graph before the bundle adjustment (None without one)."""
    start, stop = segment
    info = folder.info
    info["survey_ate"] = _survey_ate(folder, sequence, T_map_cam, survey, start, stop, T_graph_cam)
    accepted = sum(lp.status == "accepted" for lp in verified)
    admitted = sum(lp.status == "admitted" for lp in verified)
    info["loops"] = {"candidates": len(loops), "verified": len(verified), "accepted": accepted,
                     "admitted": admitted, "rejected": len(verified) - accepted - admitted}
    info["keyframes"] = int(len(T_map_key))
    folder.save()
    _plot(folder.plot, T_map_cam, T_map_key, verified, sequence, info.get("survey_ate"), _submaps_of(folder.root))
    info["report"] = {"file": folder.report.name, "past_bad_line": write_map_report(folder.root).bad}
    folder.save()


def _survey_ate(folder: MapFolder, sequence, T_map_cam: np.ndarray, survey, start: int, stop: int,
                T_graph_cam: np.ndarray | None = None) -> dict | None:
    """``survey_ate.json`` where the recording has ground truth: the map's poses and the
    odometry's alone against it, each SE(3)-aligned, with per-frame errors and the transform
    ``T_gt_map`` that runs use to score in the ground truth's frame."""
    T_gt = getattr(sequence, "T_world_cam_gt", None)
    if T_gt is None:
        return None

    stamps = np.asarray(sequence.timestamps, dtype=float)
    T_odom = np.full_like(T_map_cam, np.nan)
    T_odom[start:stop] = survey.T_odom_cam[start:stop]
    mapped = aligned_errors(stamps, T_gt, T_map_cam)
    if mapped is None:
        return None
    odometry = aligned_errors(stamps, T_gt, T_odom)
    graph_only = None if T_graph_cam is None else aligned_errors(stamps, T_gt, T_graph_cam)
    report = {"ground_truth": "the recording's own (never read to build the map)",
              "map": mapped.summary(), "odometry_only": None if odometry is None else odometry.summary(),
              "pose_graph_only": None if graph_only is None else graph_only.summary(),
              "T_gt_map": mapped.T_ref_est.tolist(),
              "per_frame": {"timestamp": mapped.stamps.tolist(), "error_m": mapped.errors_m.round(6).tolist()}}
    if odometry is not None and mapped.rmse_m > odometry.rmse_m:
        report["warning"] = (f"the map's poses are worse than the odometry's alone ({mapped.rmse_m * 100:.2f} against "
                             f"{odometry.rmse_m * 100:.2f} cm ATE): a wrong loop or a bad edge bent it")
        log.warning(report["warning"])
    write_json_atomic(folder.survey_ate, report, default=float)
    return {k: report[k] for k in ("map", "odometry_only", "pose_graph_only", "T_gt_map")} | (
        {"warning": report["warning"]} if "warning" in report else {})


def _submaps_of(root: Path) -> list:
    """The map's submaps (:mod:`nap3d_graph.fields.submaps`) from its index, or none."""
    index = Path(root) / SUBMAPS_INDEX
    if not index.is_file():
        return []
    return [Submap.from_dict(d) for d in json.loads(index.read_text())["submaps"]]


def _plot(path: Path, T_map_cam: np.ndarray, T_map_key: np.ndarray, loops: list, sequence, ate,
          submaps: list | None = None) -> None:
    """Top view (the first camera's x and z) of the path, keyframes and loop edges (accepted
    green, rejected red), the ground truth moved into the map where known, and each submap's
    part of the floor (the survey frames of its core, shaded)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    posed = np.all(np.isfinite(T_map_cam), axis=(1, 2))
    for k, submap in enumerate(submaps or []):
        p = T_map_cam[submap.frames, :3, 3]
        core = np.array([submap.distance_m(x) == 0.0 for x in p], dtype=bool)
        ax.scatter(p[core, 0], p[core, 2], s=40, color=plt.cm.tab10(k % 10), alpha=0.18, lw=0,
                   label=f"submap {k} ({len(submap.frames)} frames)")
    if ate and sequence.T_world_cam_gt is not None:
        T_gt_in_map = inv_T(np.asarray(ate["T_gt_map"])) @ np.asarray(sequence.T_world_cam_gt)
        ok = np.all(np.isfinite(T_gt_in_map), axis=(1, 2))
        ax.plot(T_gt_in_map[ok, 0, 3], T_gt_in_map[ok, 2, 3], color="0.6", lw=2, label="ground truth (aligned)")
    ax.plot(T_map_cam[posed, 0, 3], T_map_cam[posed, 2, 3], "b-", lw=1, label="map poses")
    ax.plot(T_map_key[:, 0, 3], T_map_key[:, 2, 3], "b.", ms=4)
    for label, status, colour in (("accepted loops", "accepted", "g"), ("admitted by the bundle", "admitted", "c"),
                                  ("rejected loops", "rejected", "r")):
        first = True
        for lp in loops:
            if lp.status != status:
                continue
            a, b = T_map_key[lp.a, :3, 3], T_map_key[lp.b, :3, 3]
            ax.plot([a[0], b[0]], [a[2], b[2]], colour + "-", lw=0.6, alpha=0.7, label=label if first else None)
            first = False
    title = "map: survey poses from the camera alone"
    if ate:
        title += f"\nATE {ate['map']['rmse_m'] * 100:.2f} cm (odometry alone {ate['odometry_only']['rmse_m'] * 100:.2f})"
    ax.set_title(title)
    ax.set_xlabel("x (m, first camera)")
    ax.set_ylabel("z (m, first camera)")
    ax.axis("equal")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
