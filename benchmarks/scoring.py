"""Scores the benchmarks share (the library's own, SE(3)-aligned, is
:func:`nap3d_graph.evaluation.alignment.aligned_errors`)."""

from __future__ import annotations

import numpy as np

from nap3d_graph.conventions import pose_error


def unaligned_ate_m(T_est: np.ndarray, T_ref: np.ndarray) -> float:
    """RMS of the position errors (metres) of poses ``T_est`` against ``T_ref`` (N, 4, 4),
    frame by frame, with no alignment: how far a run is from the truth in the truth's frame."""
    return float(np.sqrt(np.mean([pose_error(a, b)[0] ** 2 for a, b in zip(T_est, T_ref)])))


def spread(values, stats: tuple[str, ...] = ("median", "p90"), digits: int = 3) -> dict:
    """``{"n": count, stat: value}`` of ``values``, each of ``stats`` ('median', 'mean', 'max'
    or 'pNN', a percentile) rounded to ``digits``."""
    v = np.asarray(values, dtype=float)
    out: dict = {"n": int(v.size)}
    for stat in stats:
        value = np.percentile(v, float(stat[1:])) if stat.startswith("p") else getattr(np, stat)(v)
        out[stat] = round(float(value), digits)
    return out
