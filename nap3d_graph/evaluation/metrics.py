"""Trajectory metrics through evo: ATE (absolute pose error) and RPE, as ``evo_ape`` /
``evo_rpe`` compute them (no alignment: the estimate and the ground truth share the world
frame, and drift is exactly what an alignment would hide)."""

from __future__ import annotations

import numpy as np

from nap3d_graph.trajectory import Trajectory

from .alignment import aligned_errors

__all__ = ["to_evo", "ate", "rpe", "trajectory_metrics"]


def to_evo(timestamps: np.ndarray, T_world_cam: np.ndarray):
    """An evo ``PoseTrajectory3D`` from stamps (N,) and poses (N, 4, 4) (:meth:`Trajectory.to_evo`)."""
    return Trajectory(timestamps, T_world_cam).to_evo()


def _stats(metric) -> dict:
    return {k: float(v) for k, v in metric.get_all_statistics().items()}


def ate(timestamps, T_ref, T_world_cam_est) -> dict:
    """APE of the translation part in metres: rmse, mean, median, std, min, max, sse."""
    from evo.core import metrics

    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((to_evo(timestamps, T_ref), to_evo(timestamps, T_world_cam_est)))
    return _stats(ape)


def rpe(timestamps, T_ref, T_world_cam_est, delta_m: float = 0.5) -> dict:
    """RPE of the translation part (m) over segments of ``delta_m`` metres travelled."""
    from evo.core import metrics

    try:
        relative = metrics.RPE(metrics.PoseRelation.translation_part, delta=delta_m,
                               delta_unit=metrics.Unit.meters, all_pairs=False)
        relative.process_data((to_evo(timestamps, T_ref), to_evo(timestamps, T_world_cam_est)))
        return _stats(relative) | {"delta_m": delta_m}
    except Exception as exc:  # evo raises when the path is shorter than one segment
        return {"error": str(exc), "delta_m": delta_m}


def trajectory_metrics(timestamps, T_world_cam_gt, trajectories: dict[str, np.ndarray], rpe_delta_m: float = 0.5) -> dict:
    """ATE and RPE of each named trajectory against the ground truth, plus the ATE of the
    first and the second half of the frames (is the error flat as the path grows?).

    Frames without ground truth (NaN poses) have no error and are left out of every figure;
    ``frames_with_ground_truth`` says how many counted."""
    T_world_cam_gt = np.asarray(T_world_cam_gt, dtype=float)
    posed = np.all(np.isfinite(T_world_cam_gt), axis=(1, 2))
    timestamps = np.asarray(timestamps)[posed]
    T_world_cam_gt = T_world_cam_gt[posed]
    trajectories = {name: np.asarray(T)[posed] for name, T in trajectories.items()}
    n = len(timestamps)
    half = n // 2
    out = {}
    for name, T in trajectories.items():
        out[name] = {
            "ate_m": ate(timestamps, T_world_cam_gt, T),
            "rpe_m": rpe(timestamps, T_world_cam_gt, T, rpe_delta_m),
            "ate_first_half_m": ate(timestamps[:half], T_world_cam_gt[:half], T[:half])["rmse"] if half >= 2 else None,
            "ate_second_half_m": ate(timestamps[half:], T_world_cam_gt[half:], T[half:])["rmse"] if n - half >= 2 else None,
            "frames_with_ground_truth": int(n),
            "ate_se3_aligned_m": _aligned_rmse(timestamps, T_world_cam_gt, T),
        }
    return out


def _aligned_rmse(timestamps, T_ref, T_est) -> float | None:
    """ATE RMSE (m) after the run's own SE(3) alignment (evo's Umeyama fit): beside the
    unaligned ATE, it says how much of the error is one rigid offset of the whole run."""
    aligned = aligned_errors(timestamps, T_ref, T_est)
    return None if aligned is None else aligned.rmse_m
