"""Figures of a run and of a comparison (matplotlib, Agg backend): the trajectories seen
across their plane, and the translation error over time, in one palette for both."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["pyplot", "plot_top_view", "plot_error_over_time", "plot_trajectories", "plot_errors", "view_axes", "colour_of",
           "error_axis_floor"]

#: One colour per trajectory name, the same in every figure (run and compare alike).
COLOURS = {
    "ground truth": "black",
    "odometry": "tab:orange",
    "odometry only": "tab:orange",
    "estimate": "tab:blue",
    "with NAP3D": "tab:blue",
    "estimate_online": "tab:cyan",
    "with NAP3D, causal": "tab:cyan",
    "isam2-final": "tab:blue",
    "isam2-causal": "tab:cyan",
    "eskf": "tab:purple",
    "navstate-ekf": "tab:brown",
    "batch-lm": "tab:olive",
}
_AXES = "xyz"


def colour_of(name: str) -> str | None:
    """The palette's colour for a trajectory name (None: matplotlib's next)."""
    return COLOURS.get(name)


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def view_axes(points: np.ndarray) -> tuple[int, int]:
    """The two world axes (indices into x, y, z) along which ``points`` (N, 3) spread most:
    the plane the trajectory lies in, whatever the world's up axis is (a z-up room seen from
    above, a y-down one from above too). The lower index first, so x-y stays x-y."""
    finite = points[np.all(np.isfinite(points), axis=1)]
    spread = np.ptp(finite, axis=0) if len(finite) else np.ones(3)
    first, second = sorted(np.argsort(spread)[-2:])
    return int(first), int(second)


def error_axis_floor(errors_cm: list[np.ndarray]) -> float:
    """Bottom of a log error axis: half the 2nd percentile of the positive errors, so an
    error that starts at exactly 0 (the odometry at its first frame) does not stretch the
    axis to 1e-10."""
    positive = np.concatenate([e[np.isfinite(e) & (e > 0)] for e in errors_cm] or [np.zeros(0)])
    return float(0.5 * np.percentile(positive, 2)) if positive.size else 1e-3


def plot_trajectories(path: Path, trajectories: dict, T_world_cam_gt: np.ndarray | None = None, markers: dict | None = None,
                      title: str = "trajectories") -> Path:
    """Trajectories ``{name: (N, 4, 4)}`` (and the ground truth) in the plane they span most
    (:func:`view_axes`); ``markers``: ``{label: (points (M, 3), style, colour)}``."""
    plt = pyplot()
    reference = T_world_cam_gt[:, :3, 3] if T_world_cam_gt is not None else next(iter(trajectories.values()))[:, :3, 3]
    a, b = view_axes(reference)
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    if T_world_cam_gt is not None:
        posed = np.all(np.isfinite(T_world_cam_gt), axis=(1, 2))
        ax.plot(T_world_cam_gt[posed, a, 3], T_world_cam_gt[posed, b, 3], "-", color=COLOURS["ground truth"], lw=2.2, label="ground truth")
    for name, T in trajectories.items():
        ax.plot(T[:, a, 3], T[:, b, 3], "-", color=colour_of(name), lw=1.3, label=name)
    for label, (points, style, colour) in (markers or {}).items():
        if len(points):
            ax.plot(points[:, a], points[:, b], style, ms=5, color=colour, label=label)
    ax.set_xlabel(f"{_AXES[a]} (m)")
    ax.set_ylabel(f"{_AXES[b]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{title}, seen along {_AXES[3 - a - b]}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_errors(path: Path, t: np.ndarray, trajectories: dict, T_world_cam_gt: np.ndarray, markers: dict | None = None,
                title: str = "translation error") -> Path:
    """Translation error (cm, log axis) of each trajectory against ``T_world_cam_gt`` over time ``t``;
    ``markers``: ``{label: (times (M,), errors_cm (M,), style, colour)}``."""
    plt = pyplot()
    posed = np.all(np.isfinite(T_world_cam_gt), axis=(1, 2))
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    curves = []
    for name, T in trajectories.items():
        err = np.full(len(t), np.nan)
        err[posed] = np.linalg.norm(T[posed, :3, 3] - T_world_cam_gt[posed, :3, 3], axis=1) * 100
        curves.append(err)
        ax.plot(t, err, lw=1.2, color=colour_of(name), label=name)
    for label, (times, errors, style, colour) in (markers or {}).items():
        if len(times):
            ax.plot(times, errors, style, ms=5, color=colour, label=label)
    ax.set(xlabel="time (s)", ylabel="translation error (cm)", title=title)
    ax.set_yscale("log")
    ax.set_ylim(bottom=error_axis_floor(curves))
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _run_trajectories(result) -> dict:
    trajectories = {"odometry only": result.T_world_cam_odometry, "with NAP3D": result.T_world_cam_estimate}
    if getattr(result, "T_world_cam_online", None) is not None:
        trajectories["with NAP3D, causal"] = result.T_world_cam_online
    return trajectories


def _keyframes(result) -> tuple[list[int], list[int]]:
    accepted = [k.frame_index for k in result.keyframes if k.accepted]
    return accepted, [k.frame_index for k in result.keyframes if not k.accepted]


def plot_top_view(path: Path, result) -> Path:
    """Ground truth, odometry, the estimate and the causal estimate in the plane they span,
    keyframes marked by whether their correction was accepted."""
    est = result.T_world_cam_estimate[:, :3, 3]
    accepted, refused = _keyframes(result)
    markers = {"keyframe, accepted": (est[accepted], "o", "tab:green"),
               "keyframe, refused": (est[refused], "x", "tab:red")}
    return plot_trajectories(path, _run_trajectories(result), result.T_world_cam_gt, markers, title="trajectories")


def plot_error_over_time(path: Path, result) -> Path | None:
    """Translation error (cm) of odometry, estimate and causal estimate over time, keyframes
    marked on the estimate (accepted, refused); None without ground truth."""
    if result.T_world_cam_gt is None:
        return None
    t = result.timestamps - result.timestamps[0]
    gt, est = result.T_world_cam_gt[:, :3, 3], result.T_world_cam_estimate[:, :3, 3]
    err = np.linalg.norm(est - gt, axis=1) * 100
    accepted, refused = _keyframes(result)
    markers = {"keyframe, accepted": (t[accepted], err[accepted], "o", "tab:green"),
               "keyframe, refused": (t[refused], err[refused], "x", "tab:red")}
    return plot_errors(path, t, _run_trajectories(result), result.T_world_cam_gt, markers)
