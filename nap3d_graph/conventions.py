"""Frames, SE(3) helpers and every convention conversion, in one place.

Conventions (see DESIGN.md):

* ``T_a_b`` is a 4x4 homogeneous matrix that maps coordinates in frame ``b`` into frame
  ``a``: ``p_a = T_a_b @ p_b``. ``T_world_cam`` maps camera points into the world.
* Camera frames are OpenCV (x right, y down, z forward). OpenGL/nerfstudio cameras are
  x right, y up, z back; :func:`T_opencv_to_opengl` converts poses at that boundary only.
* Tangent vectors follow GTSAM's Pose3: ``xi = [omega(3), v(3)]`` with the right
  perturbation ``T @ Exp(xi)``, translation part in the body frame.
* Quaternions: TUM files store ``qx qy qz qw``; :func:`quat_xyzw_to_R` and
  :func:`R_to_quat_xyzw` are the only conversions.
* Depth images hold z-depth (along the optical axis); :func:`z_depth_to_ray_length`
  converts to the distance along each pixel's ray.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "skew",
    "adjoint",
    "compose_covariance",
    "make_T",
    "inv_T",
    "compose",
    "transform_points",
    "T_to_pose3",
    "as_T",
    "pose3_to_T",
    "T_to_tum",
    "tum_to_T",
    "quat_xyzw_to_R",
    "R_to_quat_xyzw",
    "exp_se3",
    "log_se3",
    "exp_so3",
    "log_so3",
    "OPENCV_FROM_OPENGL",
    "T_opencv_to_opengl",
    "T_opengl_to_opencv",
    "z_depth_to_ray_length",
    "ray_length_to_z_depth",
    "pixel_ray_norms",
    "rotation_angle_deg",
    "pose_error",
]

#: Flips y and z: maps an OpenGL camera point to the OpenCV camera frame (its own inverse).
OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def skew(p: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices (..., 3, 3) of vectors (..., 3): ``skew(a) @ b = a x b``."""
    p = np.asarray(p, dtype=float)
    S = np.zeros(p.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -p[..., 2], p[..., 1]
    S[..., 1, 0], S[..., 1, 2] = p[..., 2], -p[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -p[..., 1], p[..., 0]
    return S


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from a 3x3 rotation and a 3-vector translation."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def rigid_transform_problem(T, tolerance: float = 1e-6) -> str:
    """Why ``T`` is not a rigid transform (4x4, finite, last row 0 0 0 1, rotation part
    orthonormal with determinant +1 to ``tolerance``), or "" when it is one."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return "it has non-finite entries"
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tolerance):
        return f"its last row is {T[3].round(6).tolist()}, not [0, 0, 0, 1]"
    R = T[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if off > tolerance or np.linalg.det(R) <= 0:
        return f"its rotation part is not a rotation (|R^T R - I| = {off:.3g}, det {np.linalg.det(R):.3g})"
    return ""


def inv_T(T_a_b: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform, ``T_b_a``; works on (4,4) or stacked (N,4,4)."""
    T_a_b = np.asarray(T_a_b, dtype=float)
    R_t = np.swapaxes(T_a_b[..., :3, :3], -1, -2)
    out = np.zeros_like(T_a_b)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R_t, T_a_b[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def compose(*transforms: np.ndarray) -> np.ndarray:
    """``compose(T_a_b, T_b_c, ...) == T_a_b @ T_b_c @ ...``."""
    out = np.eye(4)
    for T in transforms:
        out = out @ np.asarray(T, dtype=float)
    return out


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` to points ``p_b`` of shape (..., 3); returns (..., 3) in frame a."""
    p_b = np.asarray(p_b, dtype=float)
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


# --- rotations -------------------------------------------------------------------------


def quat_xyzw_to_R(q_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``[qx, qy, qz, qw]`` (..., 4) to rotation matrices (..., 3, 3)."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()


def R_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) to ``[qx, qy, qz, qw]`` with ``qw >= 0``."""
    q = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    # A quaternion and its negative are the same rotation; fix the sign for stable files.
    return np.where(q[..., 3:4] < 0, -q, q)


def exp_so3(omega: np.ndarray) -> np.ndarray:
    """Rotation vector (..., 3) in radians to rotation matrix (..., 3, 3)."""
    return Rotation.from_rotvec(np.asarray(omega, dtype=float)).as_matrix()


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) to rotation vector (..., 3) in radians."""
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Angle of rotation(s) (..., 3, 3) in degrees."""
    return np.degrees(np.linalg.norm(log_so3(R), axis=-1))


# --- SE(3) tangent space in GTSAM's order ------------------------------------------------


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """GTSAM ``Pose3.Expmap``: ``xi = [omega, v]`` (6,) to a 4x4 transform."""
    import gtsam

    return gtsam.Pose3.Expmap(np.asarray(xi, dtype=float).reshape(6)).matrix()


def log_se3(T: np.ndarray) -> np.ndarray:
    """GTSAM ``Pose3.Logmap``: 4x4 transform to ``xi = [omega, v]`` (6,)."""
    import gtsam

    return np.asarray(gtsam.Pose3.Logmap(T_to_pose3(T)))


def pose_error(T_world_cam_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation error (m) and rotation error (deg) between two poses of the same frame."""
    dT = inv_T(T_true) @ np.asarray(T_world_cam_est, dtype=float)
    return float(np.linalg.norm(T_world_cam_est[:3, 3] - T_true[:3, 3])), float(rotation_angle_deg(dT[:3, :3]))


# --- gtsam ------------------------------------------------------------------------------


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def T_to_pose3(T: np.ndarray):
    """4x4 numpy transform to ``gtsam.Pose3`` (rotation re-orthonormalised)."""
    import gtsam

    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"expected a finite 4x4 transform, got shape {T.shape}")
    return gtsam.Pose3(gtsam.Rot3(_orthonormalize(T[:3, :3])), T[:3, 3].copy())


def pose3_to_T(pose) -> np.ndarray:
    """``gtsam.Pose3`` to a 4x4 numpy transform."""
    return np.asarray(pose.matrix(), dtype=float)


def as_T(pose) -> np.ndarray:
    """A pose as a 4x4 float array, whether given as one or as a ``gtsam.Pose3`` (what a
    GTSAM loop holds): the one place the public API accepts either."""
    if hasattr(pose, "matrix") and callable(pose.matrix):
        return pose3_to_T(pose)
    return np.asarray(pose, dtype=float)


# --- TUM --------------------------------------------------------------------------------


def T_to_tum(T: np.ndarray) -> np.ndarray:
    """(4,4) or (N,4,4) transforms to TUM ``tx ty tz qx qy qz qw`` rows, (7,) or (N,7)."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], R_to_quat_xyzw(T[..., :3, :3])], axis=-1)


def tum_to_T(row: np.ndarray) -> np.ndarray:
    """TUM ``tx ty tz qx qy qz qw`` rows, (7,) or (N,7), to (4,4) or (N,4,4)."""
    row = np.asarray(row, dtype=float)
    q = row[..., 3:7] / np.linalg.norm(row[..., 3:7], axis=-1, keepdims=True)
    T = np.zeros(row.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_xyzw_to_R(q)
    T[..., :3, 3] = row[..., :3]
    T[..., 3, 3] = 1.0
    return T


# --- camera frames ----------------------------------------------------------------------


def T_opencv_to_opengl(T_world_cam_cv: np.ndarray) -> np.ndarray:
    """Camera-to-world pose with an OpenCV camera -> the same pose with an OpenGL camera."""
    return np.asarray(T_world_cam_cv, dtype=float) @ OPENCV_FROM_OPENGL


def T_opengl_to_opencv(T_world_cam_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world pose with an OpenGL camera -> the same pose with an OpenCV camera."""
    return np.asarray(T_world_cam_gl, dtype=float) @ OPENCV_FROM_OPENGL


# --- depth ------------------------------------------------------------------------------


def pixel_ray_norms(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> np.ndarray:
    """Length of each pixel's ray direction ``((u-cx)/fx, (v-cy)/fy, 1)``, shape (H, W).

    Pixel centres are at integer coordinates (OpenCV convention).
    """
    u = (np.arange(width) - cx) / fx
    v = (np.arange(height) - cy) / fy
    return np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)


def z_depth_to_ray_length(depth_m: np.ndarray, ray_norms: np.ndarray) -> np.ndarray:
    """z-depth (H, W) to the distance along each pixel's ray (H, W)."""
    return np.asarray(depth_m) * ray_norms


def ray_length_to_z_depth(ray_m: np.ndarray, ray_norms: np.ndarray) -> np.ndarray:
    """Distance along each pixel's ray (H, W) to z-depth (H, W)."""
    return np.asarray(ray_m) / ray_norms


def adjoint(T: np.ndarray) -> np.ndarray:
    """GTSAM's 6x6 adjoint of a pose (tangent order [rotation, translation])."""
    return np.asarray(T_to_pose3(T).AdjointMap())


def compose_covariance(cov_a: np.ndarray, T_b: np.ndarray, cov_b: np.ndarray) -> np.ndarray:
    """Covariance of ``T_a @ T_b`` (right perturbations) from those of ``T_a`` and ``T_b``:
    ``Ad(T_b^-1) cov_a Ad(T_b^-1)^T + cov_b``."""
    A = adjoint(inv_T(T_b))
    out = A @ cov_a @ A.T + cov_b
    return 0.5 * (out + out.T)
