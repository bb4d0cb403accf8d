"""Frames: axis-angle <-> rotation matrix, pose ``[x, y, z, ax, ay, az]`` <-> 4x4, rigid
transforms of points, base <-> camera, rotation distance, straight-line pose interpolation and
``ee_pose`` waypoints. Also the ``ArrayLike`` alias the other modules use."""

from __future__ import annotations

import math
from typing import Iterable, Sequence, Union

import numpy as np


ArrayLike = Union[Sequence[float], np.ndarray]


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def axis_angle_to_matrix(rotvec: ArrayLike) -> np.ndarray:
    """Axis-angle vector (direction = axis, norm = angle) -> 3x3 rotation matrix (Rodrigues)."""
    r = np.asarray(rotvec, dtype=float).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        return np.eye(3) + _skew(r)
    k = _skew(r / theta)
    return np.eye(3) + math.sin(theta) * k + (1.0 - math.cos(theta)) * (k @ k)


def matrix_to_axis_angle(R: ArrayLike) -> np.ndarray:
    """3x3 rotation matrix -> axis-angle vector with angle in [0, pi]. Stable near 0 and pi."""
    R = np.asarray(R, dtype=float).reshape(3, 3)
    cos_t = (np.trace(R) - 1.0) / 2.0
    cos_t = min(1.0, max(-1.0, cos_t))
    theta = math.acos(cos_t)
    if theta < 1e-7:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    if theta > math.pi - 1e-4:
        # R = 2 k k^T - I near a half turn: take the best-conditioned column of (R + I) / 2.
        B = (R + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(B)))
        k = B[:, i] / math.sqrt(max(B[i, i], 1e-12))
        k /= np.linalg.norm(k)
        # fix the sign with the (small) antisymmetric part when it carries information
        s = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
        if float(np.dot(s, k)) < 0.0:
            k = -k
        return k * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w / (2.0 * math.sin(theta)) * theta


def pose_to_matrix(pose: ArrayLike) -> np.ndarray:
    """``[x, y, z, ax, ay, az]`` (axis-angle) -> 4x4 homogeneous transform."""
    p = np.asarray(pose, dtype=float).reshape(-1)
    T = np.eye(4)
    T[:3, :3] = axis_angle_to_matrix(p[3:6])
    T[:3, 3] = p[:3]
    return T


def matrix_to_pose(T: ArrayLike) -> list[float]:
    """4x4 homogeneous transform -> ``[x, y, z, ax, ay, az]`` as plain floats."""
    T = np.asarray(T, dtype=float)
    return [float(v) for v in np.concatenate([T[:3, 3], matrix_to_axis_angle(T[:3, :3])])]


def invert_transform(T: ArrayLike) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    T = np.asarray(T, dtype=float)
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def transform_points(T: ArrayLike, points: ArrayLike) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points (or one (3,) point)."""
    T = np.asarray(T, dtype=float)
    P = np.asarray(points, dtype=float)
    return P @ T[:3, :3].T + T[:3, 3]


def camera_to_base(points_cam: ArrayLike, base_from_camera: ArrayLike) -> np.ndarray:
    """Camera optical-frame points -> base-frame points."""
    return transform_points(base_from_camera, points_cam)


def base_to_camera(points_base: ArrayLike, base_from_camera: ArrayLike) -> np.ndarray:
    """Base-frame points -> camera optical-frame points."""
    return transform_points(invert_transform(base_from_camera), points_base)


def rotation_distance(R1: ArrayLike, R2: ArrayLike) -> float:
    """Angle (rad) of the rotation taking R1 to R2."""
    R = np.asarray(R1, dtype=float).T @ np.asarray(R2, dtype=float)
    return math.acos(min(1.0, max(-1.0, (np.trace(R) - 1.0) / 2.0)))


def interpolate_poses(start: ArrayLike, goal: ArrayLike, max_step_m: float = 0.04,
                      max_step_rad: float = 0.3) -> list[list[float]]:
    """Straight-line TCP path from ``start`` to ``goal`` (both ``[x,y,z,ax,ay,az]``).

    Returns the intermediate poses *and* the goal (not the start), spaced so that no step moves
    more than ``max_step_m`` or turns more than ``max_step_rad``; orientation follows the
    shortest rotation. Keep the limits below the runtime's ``max_tcp_step_m`` /
    ``max_tcp_step_rad`` (0.05 m / 0.35 rad in the shipped config): the first waypoint is
    measured from the *measured* pose, so pass the measured pose as ``start``.
    """
    Ts, Tg = pose_to_matrix(start), pose_to_matrix(goal)
    dp = Tg[:3, 3] - Ts[:3, 3]
    Rrel = Ts[:3, :3].T @ Tg[:3, :3]
    rv = matrix_to_axis_angle(Rrel)
    ang = float(np.linalg.norm(rv))
    n = max(1, int(math.ceil(max(np.linalg.norm(dp) / max_step_m, ang / max_step_rad) - 1e-9)))
    out = []
    for k in range(1, n + 1):
        s = k / n
        T = np.eye(4)
        T[:3, :3] = Ts[:3, :3] @ axis_angle_to_matrix(rv * s)
        T[:3, 3] = Ts[:3, 3] + dp * s
        out.append(matrix_to_pose(T))
    out[-1] = [float(v) for v in goal][:3] + out[-1][3:]
    return out


def waypoints(poses: Iterable[ArrayLike], gripper: float) -> list[list[float]]:
    """Append a gripper value to each pose: ready for ``{"type": "ee_pose", "actions": ...}``."""
    return [[float(v) for v in list(p)[:6]] + [float(gripper)] for p in poses]
