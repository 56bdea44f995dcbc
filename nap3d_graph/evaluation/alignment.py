"""A trajectory SE(3)-aligned to a reference (evo's Umeyama fit, no scale), and its errors.

Used where two trajectories do not share a frame: a self-posed map (its frame is its first
camera) against the recording's ground truth. The transform itself is kept, so a run on that
map can be scored in the ground truth's frame through the *survey's* alignment, with no
alignment of its own that would hide its drift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["AlignedErrors", "aligned_errors"]


@dataclass
class AlignedErrors:
    """``T_ref_est`` (4, 4): the reference frame <- the estimate's frame; ``stamps`` (M,) and
    ``errors_m`` (M,): the translation error of each frame both trajectories pose."""

    T_ref_est: np.ndarray
    stamps: np.ndarray
    errors_m: np.ndarray

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.errors_m**2)))

    def summary(self) -> dict:
        e = self.errors_m
        return {"rmse_m": self.rmse_m, "median_m": float(np.median(e)), "p90_m": float(np.percentile(e, 90)),
                "max_m": float(e.max()), "frames": int(len(e))}


def aligned_errors(stamps: np.ndarray, T_ref: np.ndarray, T_est: np.ndarray) -> AlignedErrors | None:
    """The estimate (N, 4, 4) aligned to the reference (N, 4, 4) over the frames both pose
    (finite), by evo's Umeyama fit without scale; None when fewer than 3 frames are posed."""
    from evo.core.geometry import umeyama_alignment

    from nap3d_graph.conventions import make_T

    T_ref, T_est = np.asarray(T_ref, dtype=float), np.asarray(T_est, dtype=float)
    both = np.all(np.isfinite(T_ref), axis=(1, 2)) & np.all(np.isfinite(T_est), axis=(1, 2))
    if both.sum() < 3:
        return None
    p_est, p_ref = T_est[both, :3, 3], T_ref[both, :3, 3]
    R, t, _ = umeyama_alignment(p_est.T, p_ref.T, False)
    T_ref_est = make_T(R, t)
    moved = p_est @ R.T + t
    return AlignedErrors(T_ref_est, np.asarray(stamps, dtype=float)[both], np.linalg.norm(moved - p_ref, axis=1))
