"""A trajectory that travels: stamps, poses and which poses are known, with its TUM and evo I/O.

:class:`Trajectory` holds ``stamps`` (N,) seconds and ``T_world_cam`` (N, 4, 4) (camera ->
world, OpenCV camera; the frame names say which world and camera), a pose NaN where it is
unknown (``valid``). TUM files (``timestamp tx ty tz qx qy qz qw``: what ``evo_ape tum`` reads)
are read and written here only (:meth:`Trajectory.read_tum`, :meth:`Trajectory.write_tum`, and
the functional :func:`read_tum_trajectory` / :func:`write_tum_trajectory`), and evo's
``PoseTrajectory3D`` is made here only (:meth:`Trajectory.to_evo`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from nap3d_graph.conventions import T_to_tum, tum_to_T
from nap3d_graph.errors import DatasetError
from nap3d_graph.textfiles import data_lines, parse_float

__all__ = ["Trajectory", "read_tum_trajectory", "write_tum_trajectory", "GT_MAX_GAP_S", "interpolate_poses"]

TUM_HEADER = "timestamp tx ty tz qx qy qz qw"


@dataclass(frozen=True)
class Trajectory:
    """Poses over time. ``stamps`` (N,) seconds; ``T_world_cam`` (N, 4, 4) maps ``camera``
    coordinates into ``world`` (NaN rows: unknown poses)."""

    stamps: np.ndarray
    T_world_cam: np.ndarray
    world: str = "world"
    camera: str = "cam"

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps, dtype=float).reshape(-1)
        T = np.asarray(self.T_world_cam, dtype=float)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) != len(stamps):
            raise DatasetError(f"a trajectory needs stamps (N,) and T_{self.world}_{self.camera} (N, 4, 4), got "
                               f"{stamps.shape} and {T.shape}")
        object.__setattr__(self, "stamps", stamps)
        object.__setattr__(self, "T_world_cam", T)

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: the poses that are known (finite) at a finite stamp."""
        return np.all(np.isfinite(self.T_world_cam), axis=(1, 2)) & np.isfinite(self.stamps)

    def only_valid(self) -> "Trajectory":
        keep = self.valid
        return Trajectory(self.stamps[keep], self.T_world_cam[keep], self.world, self.camera)

    def check(self, rotation_tol: float = 1e-6) -> "Trajectory":
        """Raise ``DatasetError`` unless the known poses are rigid (orthonormal rotation,
        determinant 1, last row 0 0 0 1) and their stamps strictly increase; returns itself."""
        T = self.T_world_cam[self.valid]
        R = T[:, :3, :3]
        if len(T) and (np.max(np.abs(R @ np.transpose(R, (0, 2, 1)) - np.eye(3))) > rotation_tol
                       or np.max(np.abs(np.linalg.det(R) - 1.0)) > rotation_tol
                       or np.max(np.abs(T[:, 3] - [0.0, 0.0, 0.0, 1.0])) > rotation_tol):
            raise DatasetError(f"T_{self.world}_{self.camera}: not rigid transforms")
        if np.any(np.diff(self.stamps[self.valid]) <= 0):
            raise DatasetError(f"T_{self.world}_{self.camera}: stamps do not strictly increase")
        return self

    @classmethod
    def read_tum(cls, path, world: str = "world", camera: str = "cam") -> "Trajectory":
        """A TUM trajectory file (``#`` comments), in file order."""
        path = Path(path)
        rows = []
        for number, fields in data_lines(path):
            if len(fields) != 8:
                raise DatasetError(
                    f"{path}:{number}: expected 8 columns 'timestamp tx ty tz qx qy qz qw', got {len(fields)}"
                )
            row = [parse_float(path, number, token) for token in fields]
            if np.linalg.norm(row[4:8]) < 1e-6:
                raise DatasetError(f"{path}:{number}: quaternion has zero norm")
            rows.append(row)
        if not rows:
            raise DatasetError(f"{path}: no poses in trajectory file")
        mat = np.asarray(rows, dtype=float)
        return cls(mat[:, 0].copy(), tum_to_T(mat[:, 1:8]), world, camera)

    def write_tum(self, path, header: str | None = None, skip_unknown: bool = False) -> Path:
        """Write the poses as a TUM file that ``evo_ape tum`` reads: time with 6 decimals
        (microseconds, as TUM does), translations and quaternions with 9. Unknown poses are
        refused, or left out with ``skip_unknown``; so are stamps that do not strictly increase
        as written (evo's ``PoseTrajectory3D.check`` wants them ascending without duplicates).
        ``header``: comment lines above the column names."""
        path = Path(path)
        trajectory = self.only_valid() if skip_unknown else self
        if not np.all(trajectory.valid):
            raise DatasetError(f"{path}: refusing to write non-finite timestamps or poses")
        _check_increasing(trajectory.stamps, f"{path}: ")
        text = TUM_HEADER if header is None else f"{header}\n{TUM_HEADER}"
        # evo reads with a single-space delimiter: no trailing blanks, one space between columns.
        np.savetxt(path, trajectory._tum_rows(), fmt=_TUM_FORMAT, delimiter=" ", header=text, comments="# ")
        return path

    def append_tum(self, handle) -> None:
        """Append the poses as TUM rows (the format of :meth:`write_tum`, no header) to an open
        text file: a long run writes its retired frames as it goes. Unknown poses are refused,
        and so are stamps that do not strictly increase (within the rows appended)."""
        if not np.all(self.valid):
            raise DatasetError("refusing to write non-finite timestamps or poses")
        _check_increasing(self.stamps, "")
        np.savetxt(handle, self._tum_rows(), fmt=_TUM_FORMAT, delimiter=" ")

    def _tum_rows(self) -> np.ndarray:
        return np.concatenate([self.stamps[:, None], T_to_tum(self.T_world_cam).reshape(-1, 7)], axis=1)

    def to_evo(self):
        """evo's ``PoseTrajectory3D`` of the known poses."""
        from evo.core.trajectory import PoseTrajectory3D

        known = self.only_valid()
        return PoseTrajectory3D(poses_se3=list(known.T_world_cam), timestamps=known.stamps)


_TUM_FORMAT = ["%.6f"] + ["%.9f"] * 7


def _check_increasing(stamps: np.ndarray, where: str) -> None:
    """Refuse (``DatasetError``, a ``ValueError``) stamps that do not strictly increase at the
    precision a TUM file keeps (microseconds): evo reads such a file, but its trajectory
    check fails ("not ascending or duplicates") and its association falls back to guessing."""
    written = np.array([float(_TUM_FORMAT[0] % t) for t in stamps])
    steps = np.diff(written)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        i = int(bad[0])
        raise DatasetError(f"{where}refusing to write stamps that do not strictly increase: {bad.size} of "
                           f"{len(stamps)} poses are at or before the one before them (first: pose {i} at "
                           f"{stamps[i]:.6f} s, pose {i + 1} at {stamps[i + 1]:.6f} s)")


def read_tum_trajectory(path) -> tuple[np.ndarray, np.ndarray]:
    """``(timestamps (N,), T_world_cam (N, 4, 4))`` of a TUM trajectory file, in file order."""
    trajectory = Trajectory.read_tum(path)
    return trajectory.stamps, trajectory.T_world_cam


def write_tum_trajectory(path, timestamps: np.ndarray, T_world_cam: np.ndarray) -> Path:
    """Write ``timestamps`` (N,) and ``T_world_cam`` (N, 4, 4) as a TUM trajectory file
    (:meth:`Trajectory.write_tum`); non-finite poses are refused."""
    try:
        trajectory = Trajectory(timestamps, T_world_cam)
    except DatasetError as exc:
        raise DatasetError(f"{path}: {exc}") from None
    return trajectory.write_tum(path)


#: Ground truth runs at 100 Hz; a larger hole than this between two poses is a gap.
GT_MAX_GAP_S = 0.1


def interpolate_poses(
    stamps_gt: np.ndarray,
    T_world_cam_gt: np.ndarray,
    query_stamps: np.ndarray,
    max_gap: float = GT_MAX_GAP_S,
) -> np.ndarray:
    """Interpolate poses at query times: linear in translation, SLERP in rotation.

    stamps_gt: (N,) seconds, any order, no duplicates. T_world_cam_gt: (N, 4, 4). query_stamps: (M,).
    Returns (M, 4, 4); a query outside ``[stamps_gt.min(), stamps_gt.max()]`` or between two
    poses more than ``max_gap`` seconds apart gets an all-NaN matrix.
    """
    stamps_gt = np.asarray(stamps_gt, dtype=float).reshape(-1)
    T_world_cam_gt = np.asarray(T_world_cam_gt, dtype=float)
    query = np.asarray(query_stamps, dtype=float).reshape(-1)
    if T_world_cam_gt.shape != (len(stamps_gt), 4, 4):
        raise DatasetError(f"need stamps (N,) and poses (N, 4, 4), got {stamps_gt.shape} and {T_world_cam_gt.shape}")
    out = np.full((len(query), 4, 4), np.nan)
    if len(stamps_gt) == 0 or len(query) == 0:
        return out
    order = np.argsort(stamps_gt, kind="stable")
    stamps_gt, T_world_cam_gt = stamps_gt[order], T_world_cam_gt[order]
    if np.any(np.diff(stamps_gt) <= 0):
        raise DatasetError("ground-truth timestamps contain duplicates")
    if len(stamps_gt) == 1:
        exact = query == stamps_gt[0]
        out[exact] = T_world_cam_gt[0]
        return out
    # Bracket [k, k+1] of each query; a query exactly at the last stamp uses the last bracket.
    k = np.clip(np.searchsorted(stamps_gt, query, side="right") - 1, 0, len(stamps_gt) - 2)
    t0, t1 = stamps_gt[k], stamps_gt[k + 1]
    # A query exactly on a ground-truth stamp is valid even when that pose borders a gap.
    on_stamp = (query == t0) | (query == t1)
    ok = (query >= stamps_gt[0]) & (query <= stamps_gt[-1]) & ((t1 - t0 <= max_gap) | on_stamp)
    if not np.any(ok):
        return out
    alpha = ((query[ok] - t0[ok]) / (t1[ok] - t0[ok]))[:, None]
    p0, p1 = T_world_cam_gt[k[ok], :3, 3], T_world_cam_gt[k[ok] + 1, :3, 3]
    slerp = Slerp(stamps_gt, Rotation.from_matrix(T_world_cam_gt[:, :3, :3]))
    T = np.zeros((int(ok.sum()), 4, 4))
    T[:, :3, :3] = slerp(query[ok]).as_matrix()
    T[:, :3, 3] = (1.0 - alpha) * p0 + alpha * p1
    T[:, 3, 3] = 1.0
    out[ok] = T
    return out
