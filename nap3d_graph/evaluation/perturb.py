"""Pose perturbations of the paper's protocols."""

from __future__ import annotations

import numpy as np

from nap3d_graph.conventions import exp_se3

__all__ = ["random_perturbation"]


def random_perturbation(rng: np.random.Generator, max_trans_m: float = 0.10, max_rot_deg: float = 5.0) -> np.ndarray:
    """A 4x4 right perturbation ``T_true_est`` like the paper's Evaluation K: translation
    uniform in +-``max_trans_m`` per axis, rotation vector uniform in +-``max_rot_deg`` per
    axis and scaled down to at most ``max_rot_deg`` in angle."""
    rot = np.radians(rng.uniform(-max_rot_deg, max_rot_deg, 3))
    norm = np.linalg.norm(rot)
    if norm > np.radians(max_rot_deg):
        rot *= np.radians(max_rot_deg) / norm
    return exp_se3(np.r_[rot, rng.uniform(-max_trans_m, max_trans_m, 3)])
