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

from nap3d_graph.conventions import T_to_tum, tum_to_T
from nap3d_graph.errors import DatasetError
from nap3d_graph.textfiles import data_lines, parse_float

__all__ = ["Trajectory", "read_tum_trajectory", "write_tum_trajectory"]

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
