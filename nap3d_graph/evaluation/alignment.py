"""A trajectory SE(3)-aligned to a reference, and its errors.

The alignment fits positions and orientations together: Umeyama's least squares over the
positions (evo's fit, no scale) plus ``orientation_weight_m2`` times the chordal distance of
every orientation. Positions alone leave the rotation loose on a short or straight path (on
fr1/xyz's 12 frames, 8 cm of motion, the position-only fit turned the frame by 126 degrees),
and that rotation moves every later run scored through it; the orientations pin it. evo's
position-only RMSE is reported beside it.

Used where two trajectories do not share a frame: a self-posed map (its frame is its first
camera) against the recording's ground truth. The transform itself is kept, so a run on that
map can be scored in the ground truth's frame through the *survey's* alignment, with no
alignment of its own that would hide its drift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nap3d_graph.conventions import make_T

__all__ = ["AlignedErrors", "aligned_errors"]


@dataclass
class AlignedErrors:
    """``T_ref_est`` (4, 4): the reference frame <- the estimate's frame; ``stamps`` (M,) and
    ``errors_m`` (M,): the translation error of each frame both trajectories pose;
    ``position_only_rmse_m``: evo's RMSE with its position-only Umeyama fit; ``rotation_errors``
    (M, 3): each frame's orientation error after the alignment, in its own camera frame
    (radians, the rotation vector of ``R_est_aligned^T R_ref``)."""

    T_ref_est: np.ndarray
    stamps: np.ndarray
    errors_m: np.ndarray
    position_only_rmse_m: float = float("nan")
    rotation_errors: np.ndarray | None = None

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.errors_m**2)))

    def summary(self) -> dict:
        """The translation errors' RMSE, median, p90 and max; with orientations, theirs in
        degrees and ``rotation_common_deg``: the size of their mean in the camera frame, the
        part of them that is one fixed turn of every camera (a camera-to-marker calibration
        of the reference, or a survey bent the same way throughout), which no alignment of
        the whole trajectory removes."""
        e = self.errors_m
        out = {"rmse_m": self.rmse_m, "median_m": float(np.median(e)), "p90_m": float(np.percentile(e, 90)),
               "max_m": float(e.max()), "frames": int(len(e)),
               "rmse_position_only_alignment_m": self.position_only_rmse_m}
        if self.rotation_errors is not None and len(self.rotation_errors):
            deg = np.degrees(np.linalg.norm(self.rotation_errors, axis=1))
            out.update(rotation_median_deg=float(np.median(deg)), rotation_p90_deg=float(np.percentile(deg, 90)),
                       rotation_max_deg=float(deg.max()),
                       rotation_common_deg=float(np.degrees(np.linalg.norm(self.rotation_errors.mean(axis=0)))))
        return out


def aligned_errors(stamps: np.ndarray, T_ref: np.ndarray, T_est: np.ndarray, orientation_weight_m2: float = 0.1
                   ) -> AlignedErrors | None:
    """The estimate (N, 4, 4) aligned to the reference (N, 4, 4) over the frames both pose
    (finite), positions and orientations together (module docstring); None when fewer than
    3 frames are posed."""
    from evo.core.geometry import umeyama_alignment
    from scipy.spatial.transform import Rotation


    T_ref, T_est = np.asarray(T_ref, dtype=float), np.asarray(T_est, dtype=float)
    both = np.all(np.isfinite(T_ref), axis=(1, 2)) & np.all(np.isfinite(T_est), axis=(1, 2))
    if both.sum() < 3:
        return None
    p_est, p_ref = T_est[both, :3, 3], T_ref[both, :3, 3]
    R_est, R_ref = T_est[both, :3, :3], T_ref[both, :3, :3]
    # min sum |p_ref - R p_est - t|^2 + w sum |R_ref - R R_est|_F^2: R from one SVD (Umeyama's
    # cross-covariance plus the orientations' sum), t from the centroids.
    a, b = p_est - p_est.mean(0), p_ref - p_ref.mean(0)
    M = b.T @ a + orientation_weight_m2 * np.einsum("nij,nkj->ik", R_ref, R_est)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    t = p_ref.mean(0) - R @ p_est.mean(0)
    moved = p_est @ R.T + t
    R_evo, t_evo, _ = umeyama_alignment(p_est.T, p_ref.T, False)
    position_only = np.linalg.norm(p_est @ R_evo.T + t_evo - p_ref, axis=1)
    R_moved = np.einsum("ij,njk->nik", R, R_est)
    rotation_errors = Rotation.from_matrix(np.einsum("nji,njk->nik", R_moved, R_ref)).as_rotvec()
    return AlignedErrors(make_T(R, t), np.asarray(stamps, dtype=float)[both], np.linalg.norm(moved - p_ref, axis=1),
                         float(np.sqrt(np.mean(position_only**2))), rotation_errors)
