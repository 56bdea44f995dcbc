"""Training poses refined against the map they build: a self-consistent map.

A field inherits every error of its training poses (motion capture at the wrong instant for a
rolling-shutter, motion-blurred Kinect; a tracker's drift): the same surface lands in
different places from different frames, and the map is smeared. Here the poses and the map
are alternated: the training frames are split into two interleaved folds; each fold's frames
are aligned with NAP3D (the run's own measurement, :func:`measure_keyframe`) against a splat
map built from the *other* fold, so no frame is aligned with itself; each measurement is
fused with the input pose under both covariances (the input's sigmas are the caller's
knowledge of its poses, the measurement's error beyond its own covariance is estimated from
the spread of the measurements, as :mod:`~nap3d_graph.fields.field_error` does); the maps are
rebuilt with the fused poses, and the rounds repeat. The gauge is held to the input: the
refined trajectory is rigidly aligned to the input one (evo's Umeyama), so the field stays
in the recording's ground-truth frame.

Why not nerfstudio's camera optimiser: it refines the poses through the photometric loss of a
trained network (minutes to hours on a GPU); this is the same idea with the alignment the
product already has, on a CPU.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from nap3d_graph.datasets.depth_timing import CaptureTiming
from nap3d_graph.datasets.posed import PosedSequence
from nap3d_graph.nap3d.keyframe import MeasureSettings

from ..conventions import exp_se3, inv_T, log_se3
from ..nap3d.config import AlignConfig
from .field_error import measure_frame, sigma_for_median_nees

__all__ = ["PoseRefinementConfig", "refine_training_poses", "PoseCorrectedSequence"]

log = logging.getLogger(__name__)


@dataclass
class PoseRefinementConfig:
    """rounds: map-then-align rounds. input_sigma_m / input_sigma_rad: the training poses'
    own error per axis (what the caller knows of its motion capture or tracker; 1 cm and
    0.5 deg by default). matcher: of the alignments. render_size: of the renders (the
    frames' own when None or larger)."""

    rounds: int = 2
    input_sigma_m: float = 0.01
    input_sigma_rad: float = 0.0087
    matcher: str = "sift"
    render_size: tuple[int, int] | None = (320, 240)
    history: list = field(default_factory=list)


class PoseCorrectedSequence(PosedSequence):
    """``sequence`` with each frame ``i`` of ``corrections`` posed at ``T_world_cam_gt[i] @ D_i`` (D_i: a
    body-frame correction (4, 4)); ``ground_truth_at(t)`` applies the correction of the frame
    nearest in time, so the capture-timing interpolation of a field build still works."""

    def __init__(self, sequence, corrections: dict[int, np.ndarray]):
        poses = np.array(sequence.T_world_cam_gt, dtype=float)
        for i, D in corrections.items():
            poses[i] = poses[i] @ D
        super().__init__(sequence, poses, "refined training poses")
        self.corrections = corrections
        self._order = np.array(sorted(corrections), dtype=int)

    def ground_truth_at(self, stamps) -> np.ndarray | None:
        base = self._base.ground_truth_at(stamps)
        if base is None or not len(self._order):
            return base
        stamps = np.asarray(stamps, dtype=float)
        all_stamps = np.asarray(self._base.timestamps, dtype=float)
        frame_stamps = all_stamps[self._order]
        gap = np.abs(stamps[:, None] - frame_stamps[None, :])
        nearest = gap.argmin(axis=1)
        # Only instants of a corrected frame's own capture (its depth a few ms off its colour):
        # a frame that was not refined (held out) keeps its input pose.
        reach = 0.5 * float(np.median(np.diff(all_stamps))) if len(all_stamps) > 1 else np.inf
        return np.stack([T @ self.corrections[int(self._order[k])] if gap[j, k] < reach else T
                         for j, (T, k) in enumerate(zip(base, nearest))])


def _spread_sigma(residuals: np.ndarray, covariances: np.ndarray, prior_var: float) -> float:
    """Isotropic sigma of the measurements' error beyond their covariance and the input's:
    median-based per 3-dof block (0 when covariance and input explain the spread)."""
    return sigma_for_median_nees(residuals, covariances + prior_var * np.eye(3))


def refine_training_poses(sequence, train_idx, timing: CaptureTiming | None = None,
                          config: PoseRefinementConfig | None = None, progress: bool = False):
    """Refined poses of frames ``train_idx`` of a posed ``sequence``: ``(corrections, report)``
    with ``corrections`` ``{frame index: D (4, 4)}`` (refined pose = input pose @ D; use
    :class:`PoseCorrectedSequence` to build with them) and a report of each round (median
    correction, frames measured, the measurements' extra sigma)."""
    timing = CaptureTiming.of(timing)

    from .splat import build_splat_field

    config = config or PoseRefinementConfig()
    fold_timing = timing or CaptureTiming()
    train_idx = np.asarray(train_idx, dtype=int)
    folds = [train_idx[0::2], train_idx[1::2]]
    T_in = np.asarray(sequence.T_world_cam_gt, dtype=float)
    prior = np.diag([config.input_sigma_rad**2] * 3 + [config.input_sigma_m**2] * 3)
    run_config = MeasureSettings(align=AlignConfig(matcher=config.matcher))  # the field as exact
    corrections = {int(i): np.eye(4) for i in train_idx}
    rounds = []
    for r in range(config.rounds):
        current = PoseCorrectedSequence(sequence, corrections)
        measured: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for a, b in ((0, 1), (1, 0)):
            fold_map, _ = build_splat_field(current, folds[a], depth_offset_s=fold_timing.depth_offset_s,
                                            colour_offset_s=fold_timing.colour_offset_s,
                                            depth_scale=fold_timing.depth_scale, progress=progress)
            for i in folds[b]:
                c = measure_frame(current, int(i), fold_map, current.T_world_cam_gt[i], run_config, timing,
                                  config.render_size)
                if c.success and np.all(np.isfinite(c.covariance)):
                    measured[int(i)] = (c.T_world_cam_corrected, np.asarray(c.covariance, dtype=float))
        if len(measured) < 5:
            log.warning("pose refinement round %d: only %d frames aligned; poses left as they are", r + 1,
                        len(measured))
            break
        corrections, info = _fuse(T_in, measured, prior, corrections)
        info.update({"round": r + 1, "frames_measured": len(measured), "frames": int(len(train_idx))})
        rounds.append(info)
        log.info("pose refinement round %d: %d of %d frames aligned, median correction %.1f mm / %.2f deg",
                 r + 1, len(measured), len(train_idx), info["median_correction_mm"], info["median_correction_deg"])
    return corrections, {"rounds": rounds, "input_sigma_m": config.input_sigma_m,
                         "input_sigma_rad": config.input_sigma_rad, "matcher": config.matcher}


def _fuse(T_in: np.ndarray, measured: dict, prior: np.ndarray, previous: dict) -> tuple[dict, dict]:
    """Each measured frame's pose fused with its input pose (a Kalman update in the input
    pose's tangent space, per 3-dof block), the rest kept as they were; then the whole set
    re-anchored to the input trajectory (rigid Umeyama on positions and the mean rotation
    correction), so the map stays in the recording's frame."""
    from evo.core.geometry import umeyama_alignment

    idx = sorted(measured)
    residuals = np.array([log_se3(inv_T(T_in[i]) @ measured[i][0]) for i in idx])
    covs = np.array([measured[i][1] for i in idx])
    extra_rad = _spread_sigma(residuals[:, :3], covs[:, :3, :3], prior[0, 0])
    extra_m = _spread_sigma(residuals[:, 3:], covs[:, 3:, 3:], prior[3, 3])
    extra = np.diag([extra_rad**2] * 3 + [extra_m**2] * 3)
    fused = dict(previous)
    for i, r, C in zip(idx, residuals, covs):
        gain = prior @ np.linalg.inv(prior + C + extra)
        fused[i] = exp_se3(gain @ r)
    # Gauge: the refined positions rigidly aligned onto the input ones.
    keys = sorted(fused)
    p_in = np.array([T_in[i][:3, 3] for i in keys])
    p_new = np.array([(T_in[i] @ fused[i])[:3, 3] for i in keys])
    R, t, _ = umeyama_alignment(p_new.T, p_in.T, with_scale=False)
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = R, t
    fused = {i: inv_T(T_in[i]) @ G @ T_in[i] @ fused[i] for i in keys}
    sizes = np.array([log_se3(fused[i]) for i in keys])
    return fused, {"median_correction_mm": float(np.median(np.linalg.norm(sizes[:, 3:], axis=1)) * 1000),
                   "median_correction_deg": float(np.degrees(np.median(np.linalg.norm(sizes[:, :3], axis=1)))),
                   "measurement_extra_sigma_m": float(extra_m), "measurement_extra_sigma_rad": float(extra_rad)}
