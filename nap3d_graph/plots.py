"""Figures of a run (matplotlib, Agg backend): top view and translation error over time."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_top_view", "plot_error_over_time"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_top_view(path: Path, result) -> Path:
    """Ground truth, odometry and estimate seen from above (world x-y, metres), keyframes
    marked by whether their correction was accepted."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    if result.T_world_cam_gt is not None:
        gt = result.T_world_cam_gt[:, :3, 3]
        ax.plot(gt[:, 0], gt[:, 1], "k-", lw=2, label="ground truth")
    odo = result.T_world_cam_odometry[:, :3, 3]
    est = result.T_world_cam_estimate[:, :3, 3]
    ax.plot(odo[:, 0], odo[:, 1], "-", color="tab:orange", lw=1.5, label="odometry only")
    ax.plot(est[:, 0], est[:, 1], "-", color="tab:blue", lw=1.5, label="with NAP3D")
    accepted = [k.frame_index for k in result.keyframes if k.accepted]
    rejected = [k.frame_index for k in result.keyframes if not k.accepted]
    if accepted:
        ax.plot(est[accepted, 0], est[accepted, 1], "o", ms=4, color="tab:green", label="keyframe, accepted")
    if rejected:
        ax.plot(est[rejected, 0], est[rejected, 1], "x", ms=6, color="tab:red", label="keyframe, rejected/skipped")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("top view")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_error_over_time(path: Path, result) -> Path | None:
    """Translation error (cm) of odometry and estimate against ground truth over time."""
    if result.T_world_cam_gt is None:
        return None
    plt = _pyplot()
    t = result.timestamps - result.timestamps[0]
    gt = result.T_world_cam_gt[:, :3, 3]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for T, label, colour in ((result.T_world_cam_odometry, "odometry only", "tab:orange"),
                             (result.T_world_cam_estimate, "with NAP3D", "tab:blue")):
        ax.plot(t, 100 * np.linalg.norm(T[:, :3, 3] - gt, axis=1), color=colour, label=label)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("translation error (cm)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
