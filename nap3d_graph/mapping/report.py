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
- **bundle reprojection residual**: the bundle adjustment's median reprojection error at
  its final noise; beyond 1.5 px the poses and the landmarks disagree (a wrong camera, a
  wrong depth unit, a bent map).
- **field on held-out survey frames**: the field rendered at survey frames it was not
  trained on, against those frames: PSNR (after a per-frame affine colour fit), median depth
  error and the share of the frame it covers, and NAP3D of those frames against the field
  (how many fail, how far from the map's pose they land). Below 12 dB it does not look like
  the place (the line is set from fr1/desk's splat maps, 14-17 dB: a crude field of a real
  room); a median depth error beyond 3 cm or less than 70% covered, NAP3D has too little of
  the field to align with; more than half failing or a median beyond 3 cm, the field cannot
  correct a run.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from nap3d_graph.run.report import FigureReport

__all__ = ["MapReport", "map_report", "write_map_report", "LOOP_RESIDUAL_BAD", "REPROJECTION_BAD_PX",
           "HELD_OUT_PSNR_BAD_DB", "HELD_OUT_DEPTH_BAD_M", "COVERED_BAD", "HELD_OUT_NAP3D_BAD_M"]

log = logging.getLogger(__name__)

#: A median loop residual beyond these (metres, degrees): the loops and the map disagree.
LOOP_RESIDUAL_BAD = (0.02, 1.0)
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


def loop_residuals(folder: Path) -> np.ndarray:
    """(L, 2): each accepted loop's translation (m) and rotation (deg) disagreement with the
    map's final keyframe poses (measurements in ``edges.npz``, which loops the graph kept in
    ``loops.csv``, in the same order; poses in ``keyframe_poses.npy``); (0, 2) when none."""
    import csv

    from nap3d_graph.conventions import inv_T, pose_error

    edges, poses, table = folder / "edges.npz", folder / "keyframe_poses.npy", folder / "loops.csv"
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
                for (a, b, *_), T_ab, kept in zip(d["loop_abij"], d["loop_T"], status) if kept == "accepted"]
    return np.asarray(rows, dtype=float).reshape(-1, 2)


def _loops(report: MapReport, info: dict, folder: Path) -> None:
    loops = info.get("loops", {})
    kept = int(loops.get("accepted", 0))
    report.values["loops"] = loops
    report.add("loops: candidates, verified, kept by the robust graph",
               f"{loops.get('candidates', 0)}, {loops.get('verified', 0)}, {kept}", "some kept", kept > 0)
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
    report.add("bundle adjustment: median depth residual (as disparity)", f"{last['residual_disparity_px']:.2f} px; "
               f"depth noise at 1 m {bundle.get('depth_sigma_at_1m_mm', float('nan')):.0f} mm", "the sensor's noise",
               None)


def _field(report: MapReport, folder: Path) -> None:
    path = folder / "field.report.json"
    if not path.is_file():
        report.add("field", "not built (--no-field)", "built", None)
        return
    held = json.loads(path.read_text()).get("held_out") or {}
    if not held.get("frames"):
        report.add("field on held-out survey frames", "none held out (too short a survey)", "some", None)
        return
    psnr = float(held.get("psnr_affine_db", held.get("psnr_db", float("nan"))))
    depth = float((held.get("depth_abs_err_m") or {}).get("median", float("nan")))
    covered = float(held.get("opaque_fraction", float("nan")))
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


def map_report(folder) -> MapReport:
    """The map's figures without ground truth, read from its folder."""
    folder = Path(folder)
    info = json.loads((folder / "map.json").read_text())
    report = MapReport()
    _loops(report, info, folder)
    _bundle(report, info)
    _field(report, folder)
    ate = (info.get("survey_ate") or {}).get("map")
    if ate:
        odometry = info["survey_ate"].get("odometry_only", {})
        report.values["survey_ate_m"] = ate["rmse_m"]
        report.add("survey ATE against the ground truth (where there is one)",
                   f"{ate['rmse_m'] * 100:.2f} cm (odometry alone {odometry.get('rmse_m', float('nan')) * 100:.2f})",
                   "the reference the figures above are checked against", None)
    return report


def write_map_report(folder) -> MapReport:
    """Write ``report.md`` into the map folder; returns the report."""
    folder = Path(folder)
    report = map_report(folder)
    report.write(folder / "report.md", "Is the map good?", "![the map from above, loops drawn](map.png)")
    return report
