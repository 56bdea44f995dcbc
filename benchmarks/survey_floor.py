"""What else could hold the survey above 1 cm? Three more systematic causes, each undone on a
finished map and the bundle adjustment solved again, scored against every reference the
recording has (issue 48: the survey's 1 cm goal is missed; ``survey_systematics.py`` ruled
out a wrong metre and a clock offset).

- **The depth's disparity offset.** A Kinect's depth is ``f b / (d + offset)``: a wrong offset
  makes far depth read long and near depth short. Fitted from the survey alone, no ground truth:
  every verified match seen from two keyframes at least 8 degrees apart is triangulated from
  its two pixels and the map's keyframe poses; in up to ten bins of the measured inverse depth,
  the median triangulated inverse depth is fitted with a line ``1/z_images = a / z_depth + b``
  (the map's own check, :func:`~nap3d_graph.mapping.depth_check.depth_against_images`).
  The depths are then corrected along that line, scaled so the median depth stays where the
  sensor put it (the metre is the depth's; only its shape changes), and the bundle solved
  again with the map's settings.
- **The focal length**, scaled by each ``--focal-scales``, the bundle solved again at the
  readout the map's own solve chose. The pixel and disparity residuals say whether the survey
  itself could choose it.
- **Where the rest is.** The as-mapped error (positions, SE(3)-aligned) split into its slow
  part (a 1 s moving average: bends and drift) and the fast rest (keyframe to keyframe), and
  its RMSE over the quarter of frames where the reference turns fastest against the slowest
  quarter.
- **The map's depth check** (``map.json``'s ``bundle.depth_against_images``, the report's line)
  on the same real matches as measured and with a disparity offset added to every depth: the
  offset it finds and whether it tells it.
- **The reference's camera offset.** A motion-capture or SfM camera sits a lever arm away
  from the one the estimate poses if its calibration is off. Fitted to each reference (a
  translation in the camera, with the alignment): how much of the ATE such an offset could
  hold, and whether the two halves of a recording agree on it (a real offset is one vector).

Reads the map folders that ``map_start_anywhere.py --work`` (or ``nap3d-graph map``) left;
writes JSON.

    python benchmarks/survey_floor.py --data ../shared/data/tum/rgbd_dataset_freiburg1_desk \\
        --map first=/tmp/anywhere_v3/survey_first/map --map second=/tmp/anywhere_v3/survey_second/map \\
        --out benchmarks/results/survey_floor_fr1_desk.json
    python benchmarks/survey_floor.py --data ../shared/data/7scenes/redkitchen \\
        --second-gt ../shared/data/7scenes/redkitchen/pseudo_gt_sfm.txt \\
        --map first=/tmp/anywhere7_v3/survey_first/map --map second=/tmp/anywhere7_v3/survey_second/map \\
        --out benchmarks/results/survey_floor_redkitchen.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from map_bundle import _graph, _references  # noqa: E402  (beside this file)
from provenance import write_result

from nap3d_graph.mapping.depth_check import depth_against_images

#: Disparity offsets (1/m) added to the real matches' depths to see the map's check tell them.
CHECK_OFFSETS_PER_M = (0.0, 0.02, 0.05)


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--map", action="append", required=True, help="NAME=MAP_DIR (repeat)")
    parser.add_argument("--second-gt", type=Path, default=None, help="7-Scenes' SfM pseudo ground truth")
    parser.add_argument("--focal-scales", type=float, nargs="+", default=[0.98, 1.02])
    parser.add_argument("--out", type=Path, required=True)
    return parser.parse_args()


def _along_line(z: np.ndarray, slope: float, intercept_per_m: float, scale: float = 1.0) -> np.ndarray:
    """Depths moved along ``1 / z_new = (slope / z + intercept_per_m) / scale``; NaN where that
    passes infinity, missing depths (<= 0) kept as they are."""
    z = np.asarray(z, dtype=float)
    out = z.copy()
    valid = z > 0
    inverse = (slope / z[valid] + intercept_per_m) / scale
    out[valid] = np.where(inverse > 0, 1.0 / np.maximum(inverse, 1e-12), np.nan)
    return out


def _with_depths(pairs: list, slope: float, intercept_per_m: float, scale: float = 1.0) -> list:
    """The pairs with both keyframes' depths moved along the line (:func:`_along_line`)."""
    return [dataclasses.replace(p, z_a=_along_line(p.z_a, slope, intercept_per_m, scale),
                                z_b=_along_line(p.z_b, slope, intercept_per_m, scale)) for p in pairs]


def corrected_pairs(pairs: list, fit: dict) -> list:
    """The pairs with every depth moved along the fitted line (:func:`depth_against_images`),
    scaled so the median depth is unchanged."""
    a, b, z_med = fit["slope"], fit["intercept_per_m"], fit["median_depth_m"]
    return _with_depths(pairs, a, b, scale=z_med * (a / z_med + b))


def through_offset(pairs: list, offset_per_m: float) -> list:
    """The pairs with their depths read through a disparity offset: ``1 / z_read = 1 / z -
    offset_per_m`` (far reads long for a positive offset)."""
    return _with_depths(pairs, 1.0, -offset_per_m)


def camera_offset_fit(T_est: np.ndarray, T_ref: np.ndarray, rounds: int = 50) -> tuple[np.ndarray, float]:
    """``(offset_m (3,), ATE m)``: the translation in the reference's camera that, added to it,
    best fits the estimate's positions after an SE(3) alignment (alternating: Umeyama for the
    alignment, least squares for the offset), and the positions' RMSE then."""
    from evo.core.geometry import umeyama_alignment

    p_est, offset = T_est[:, :3, 3], np.zeros(3)
    for _ in range(rounds):
        p_ref = T_ref[:, :3, 3] + T_ref[:, :3, :3] @ offset
        R, t, _ = umeyama_alignment(p_est.T, p_ref.T, False)
        moved = p_est @ R.T + t
        offset = np.linalg.lstsq(T_ref[:, :3, :3].reshape(-1, 3), (moved - T_ref[:, :3, 3]).reshape(-1), rcond=None)[0]
    p_ref = T_ref[:, :3, 3] + T_ref[:, :3, :3] @ offset
    R, t, _ = umeyama_alignment(p_est.T, p_ref.T, False)
    return offset, float(np.sqrt(np.mean(np.sum((p_est @ R.T + t - p_ref) ** 2, axis=1))))


def error_structure(stamps_s: np.ndarray, T_est: np.ndarray, T_ref: np.ndarray, window_s: float = 1.0) -> dict:
    """The estimate's position error (frames both pose, SE(3)-aligned on positions) as its RMSE,
    that of its slow part (moving average over ``window_s``) and of the rest, and the RMSE over
    the quarter of frames where the reference turns fastest and over the slowest quarter (with
    those quarters' median turn rates, deg/s), all in cm."""
    from evo.core.geometry import umeyama_alignment
    from scipy.ndimage import uniform_filter1d
    from scipy.spatial.transform import Rotation

    both = np.all(np.isfinite(T_est), axis=(1, 2)) & np.all(np.isfinite(T_ref), axis=(1, 2))
    est, ref, t = T_est[both], T_ref[both], np.asarray(stamps_s, dtype=float)[both]
    R, shift, _ = umeyama_alignment(est[:, :3, 3].T, ref[:, :3, 3].T, False)
    error = est[:, :3, 3] @ R.T + shift - ref[:, :3, 3]
    width = max(3, int(round(window_s / float(np.median(np.diff(t))))))
    slow = uniform_filter1d(error, width, axis=0, mode="nearest")
    turn = Rotation.from_matrix(np.einsum("nji,njk->nik", ref[:-1, :3, :3], ref[1:, :3, :3])).magnitude()
    rate = np.degrees(turn / np.diff(t))
    rate = np.r_[rate[0], 0.5 * (rate[:-1] + rate[1:]), rate[-1]]  # at each frame: the steps either side
    fast_q, slow_q = rate >= np.quantile(rate, 0.75), rate <= np.quantile(rate, 0.25)

    def rms(x) -> float:
        return float(100 * np.sqrt(np.mean(np.sum(np.atleast_2d(x) ** 2, axis=1))))

    return {"rmse_cm": rms(error), "slow_cm": rms(slow), "fast_cm": rms(error - slow), "window_s": window_s,
            "fastest_quarter_cm": rms(error[fast_q]), "fastest_quarter_deg_s": float(np.median(rate[fast_q])),
            "slowest_quarter_cm": rms(error[slow_q]), "slowest_quarter_deg_s": float(np.median(rate[slow_q]))}


def _residuals(report: dict) -> dict:
    last = report["noise_rounds"][-1]
    return {"residual_px": last["residual_px"], "residual_disparity_px": last["residual_disparity_px"],
            "readout_s": report.get("readout_s"), "loops_admitted": report.get("loops_admitted", 0)}


class _MapHalf:
    """A map folder with its recording: its frames placed from keyframe poses, scored against
    every reference, and its bundle adjustment solved again from its saved edges."""

    def __init__(self, map_dir: Path, data: Path, second_gt: Path | None):
        from nap3d_graph.datasets import open_sequence
        from nap3d_graph.mapping.build import MapSettings, _working_intrinsics
        from nap3d_graph.mapping.bundle import keyframe_twists
        from nap3d_graph.mapping.survey import SurveyOdometry

        self.map_dir = map_dir
        info = json.loads((map_dir / "map.json").read_text())
        self.settings = info["settings"]
        self.sequence = open_sequence(data, frames="%d:%d" % tuple(info["frame_range"]))
        self.references = _references(self.sequence, second_gt)
        self.keys = np.load(map_dir / "keyframes.npz")["indices"]
        self.survey = SurveyOdometry.load(map_dir / "odometry.npz")
        self.start, self.stop = info["segment"]["start"], info["segment"]["stop"]
        self.K = _working_intrinsics(self.sequence, MapSettings(width=self.settings["width"]))
        self.twists = keyframe_twists(self.survey.T_odom_cam, np.asarray(self.sequence.timestamps, dtype=float),
                                      self.keys)

    def frames(self, T_key: np.ndarray) -> np.ndarray:
        from nap3d_graph.mapping.build import place_frames

        return place_frames(self.survey.T_odom_cam, self.keys, T_key, self.start, self.stop)

    def score(self, T_key: np.ndarray) -> dict:
        """ATE in cm against each reference."""
        from nap3d_graph.evaluation.alignment import aligned_errors

        return {name: aligned_errors(self.sequence.timestamps, ref, self.frames(T_key)).summary()["rmse_m"] * 100
                for name, ref in self.references.items()}

    def adjust(self, K, bundle, depth_fit: dict | None = None):
        """``((T_map_key, report), verified loops)``: the graph and the bundle solved again
        (with the depths moved along ``depth_fit`` when given)."""
        from nap3d_graph.mapping.build import adjust_keyframes
        from nap3d_graph.mapping.loops import load_edges

        chain, loops, chain_matches = load_edges(self.map_dir / "edges.npz")  # fresh: adjusting changes loops' status
        graph, verified = _graph(self.survey, self.keys, chain, loops, self.settings)
        for lp, kept in zip(verified, graph.loop_kept):
            lp.status = "accepted" if kept else "rejected"
        if depth_fit is not None:
            chain_matches = corrected_pairs(chain_matches, depth_fit)
            for lp in verified:
                if lp.matches_kept is not None:
                    lp.matches_kept = corrected_pairs([lp.matches_kept], depth_fit)[0]
        return adjust_keyframes(graph.T_map_key, chain_matches, verified, K, bundle, self.twists), verified

    def used_pairs(self, verified: list) -> list:
        """Every pair an adjustment used: the chain's and the kept or admitted loops'."""
        from nap3d_graph.mapping.loops import load_edges

        _, _, chain_matches = load_edges(self.map_dir / "edges.npz")
        return chain_matches + [lp.matches_kept for lp in verified
                                if lp.status in ("accepted", "admitted") and lp.matches_kept is not None]


def _depth_steps(half: _MapHalf, T_base: np.ndarray, pairs: list) -> dict:
    """The depth's disparity offset fitted and undone (the bundle solved again), and the map's
    depth check on the same matches with offsets added on purpose."""
    from nap3d_graph.mapping.bundle import BundleSettings

    checks = {added: depth_against_images(through_offset(pairs, added), T_base, half.K) for added in CHECK_OFFSETS_PER_M}
    fit = checks[0.0]
    (T_depth, depth_report), _ = half.adjust(half.K, BundleSettings(), fit)
    return {"depth_offset": {"fit": fit, "ate_cm": half.score(T_depth), **_residuals(depth_report)},
            "depth_check": {f"{added:g}": {k: c.get(k) for k in ("observations", "intercept_per_m", "worst", "bad")}
                            for added, c in checks.items()}}


def _focal_steps(half: _MapHalf, focal_scales: list[float], readout_s: float) -> list:
    """The bundle solved again at each focal length scale, at the readout the map chose."""
    from nap3d_graph.mapping.bundle import BundleSettings

    rows = []
    for scale in focal_scales:
        K = dataclasses.replace(half.K, fx=half.K.fx * scale, fy=half.K.fy * scale)
        (T_focal, report), _ = half.adjust(K, BundleSettings(readout_s=readout_s))
        rows.append({"scale": scale, "ate_cm": half.score(T_focal), **_residuals(report)})
    return rows


def _reference_steps(half: _MapHalf, T_base: np.ndarray) -> dict:
    """Each reference given a camera offset, and where the as-mapped error is against it."""
    from nap3d_graph.evaluation.alignment import aligned_errors

    out: dict = {"camera_offset": {}, "error_structure": {}}
    T_frames = half.frames(T_base)
    for name, ref in half.references.items():
        ref = np.asarray(ref)
        both = np.all(np.isfinite(T_frames), axis=(1, 2)) & np.all(np.isfinite(ref), axis=(1, 2))
        offset, ate = camera_offset_fit(T_frames[both], ref[both])
        plain = aligned_errors(half.sequence.timestamps, ref, T_frames).summary()["rmse_position_only_alignment_m"]
        out["camera_offset"][name] = {"ate_position_cm": plain * 100, "ate_with_offset_cm": ate * 100,
                                      "offset_cm": [round(float(v) * 100, 2) for v in offset]}
        out["error_structure"][name] = error_structure(half.sequence.timestamps, T_frames, ref)
    return out


def survey_floor(map_dir: Path, data: Path, second_gt: Path | None, focal_scales: list[float]) -> dict:
    """Every figure above for one map folder."""
    from nap3d_graph.mapping.bundle import BundleSettings

    half = _MapHalf(map_dir, data, second_gt)
    (T_base, base_report), verified = half.adjust(half.K, BundleSettings())
    out = {"map": str(map_dir), "frames": int(half.stop - half.start), "keyframes": int(len(half.keys)),
           "as_mapped": {"ate_cm": half.score(T_base), **_residuals(base_report)}}
    print(map_dir, "as mapped", out["as_mapped"], flush=True)
    out.update(_depth_steps(half, T_base, half.used_pairs(verified)))
    print(map_dir, "depth", out["depth_offset"], out["depth_check"], flush=True)
    out["focal"] = _focal_steps(half, focal_scales, float(base_report["readout_s"]))
    print(map_dir, "focal", out["focal"], flush=True)
    out.update(_reference_steps(half, T_base))
    print(map_dir, "references", out["camera_offset"], out["error_structure"], flush=True)
    return out


def main() -> None:
    args = _arguments()
    maps = {}
    for spec in args.map:
        name, _, map_dir = spec.partition("=")
        maps[name] = survey_floor(Path(map_dir), args.data, args.second_gt, args.focal_scales)
    write_result(args.out, {"command": " ".join(sys.argv), "data": str(args.data), "maps": maps}, args)


if __name__ == "__main__":
    main()
