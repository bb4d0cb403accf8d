"""Local RGB-D perception for `robo` stage programs (numpy + standard library only).

Three layers, each usable on its own:

* **Geometry** - frame conversions (pose <-> 4x4, axis-angle <-> matrix, base <-> camera),
  back-projection of pixels and depth images into the robot base frame, oriented bounding
  boxes (PCA or minimum-area in a support plane), RANSAC plane fitting, normals.
* **Segmentation** - removes the support plane, clusters what stands on it with a voxel-grid
  connected-components pass (optionally split where the colour changes), names each cluster's
  colour and shape, and selects one from a text prompt ("red block", "the bowl on the left",
  "the largest object") or from a pixel. Several cameras (e.g. agentview + wrist) are fused.
* **Grasps** - parallel-jaw candidates on a cluster (top-down slices and antipodal normal
  pairs), checked against the gripper stroke, the fingers' and hand's sweep through the cloud
  and the support plane, scored and returned as TCP poses ``[x, y, z, ax, ay, az]`` in the base
  frame with a pre-grasp pose, ready for ``post_actions`` ee_pose waypoints.

Conventions (those of `robo`): metres, radians, base frame +x forward, +y left, +z up; camera
optical frame x right, y down, z forward; ``camera_extrinsics`` are ``base_from_camera``.
The TCP frame of the Franka Hand: z is the approach direction (out of the fingertips), y is the
axis the fingers move along, x = y cross z. Pointing straight down at yaw 0 is ``[pi, 0, 0]``.

Typical use inside a stage program::

    from robo import get_state
    import robo_perception as rp
    state = get_state(["agentview", "wrist"], raw=True)
    scene = rp.segment_scene(state)
    block = rp.select(scene, "red block")
    grasps = rp.propose_grasps(block, scene, reference_pose=state["ee_pose"])
    best = grasps[0]   # best.pregrasp, best.pose, best.width, best.gripper_open
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Optional, Sequence, Union

import numpy as np

__all__ = [
    # constants
    "GRIPPER_MAX_WIDTH", "HandGeometry", "FRANKA_HAND",
    # frames
    "axis_angle_to_matrix", "matrix_to_axis_angle", "pose_to_matrix", "matrix_to_pose",
    "invert_transform", "transform_points", "base_to_camera", "camera_to_base",
    "rotation_distance", "interpolate_poses", "waypoints", "width_to_gripper", "gripper_to_width",
    # camera geometry
    "CameraView", "views_from_state", "pixel_to_point", "depth_to_points", "project_points",
    # shapes
    "OrientedBox", "Plane", "obb_pca", "obb_in_plane", "convex_hull_2d", "min_area_rect",
    "fit_plane_ransac", "voxel_downsample", "estimate_normals",
    # segmentation
    "ObjectCluster", "SceneSegmentation", "segment_scene", "select", "rank_objects", "segment",
    "color_name", "shape_name", "parse_prompt",
    # grasps
    "Grasp", "propose_grasps", "grasp_rotation",
]

ArrayLike = Union[Sequence[float], np.ndarray]

# --------------------------------------------------------------------------------------------
# Gripper model
# --------------------------------------------------------------------------------------------

GRIPPER_MAX_WIDTH = 0.08
"""Franka Hand stroke: distance between the fingers when fully open (m)."""


@dataclass(frozen=True)
class HandGeometry:
    """Simplified parallel-jaw hand in the TCP frame (z = approach, y = finger axis).

    Lengths in metres. ``tip_beyond_tcp``: how far the fingertips reach past the TCP along the
    approach. The hand body is a box behind the fingers; ``envelope_*`` describes the rounded
    guard around the fingertips that the runtime checks against the table (Panda URDF:
    capsule of radius 2 cm along y, its centre 3.4 mm behind the TCP).
    """

    max_width: float = GRIPPER_MAX_WIDTH
    finger_thickness: float = 0.012      # along y
    finger_half_depth: float = 0.010     # half the pad size along x
    finger_length: float = 0.054         # along z
    tip_beyond_tcp: float = 0.009
    body_half_x: float = 0.045
    body_half_y: float = 0.095
    body_start_behind_tcp: float = 0.0234   # the hand body begins this far behind the TCP
    envelope_radius: float = 0.020
    envelope_half_length: float = 0.050     # half length of the capsule's straight part (y)
    envelope_behind_tcp: float = 0.0034


FRANKA_HAND = HandGeometry()


def width_to_gripper(width: float, hand: HandGeometry = FRANKA_HAND) -> float:
    """Finger opening (m) -> `robo` gripper command (-1 fully open ... +1 closed)."""
    w = min(max(float(width), 0.0), hand.max_width)
    return 1.0 - 2.0 * w / hand.max_width


def gripper_to_width(g: float, hand: HandGeometry = FRANKA_HAND) -> float:
    """`robo` gripper value (-1 open ... +1 closed) -> finger opening in metres."""
    g = min(max(float(g), -1.0), 1.0)
    return 0.5 * (1.0 - g) * hand.max_width


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# Cameras and back-projection
# --------------------------------------------------------------------------------------------

@dataclass
class CameraView:
    """One RGB-D image with its calibration, as returned by ``get_state(..., raw=True)``.

    ``rgb``: (H, W, 3) uint8; ``depth``: (H, W) float32 planar depth in metres;
    ``intrinsics``: {fx, fy, cx, cy, width, height}; ``base_from_camera``: 4x4.
    ``ee_pose``/``gripper`` (measured, optional) let segmentation ignore the robot's own hand.
    """

    name: str
    rgb: np.ndarray
    depth: np.ndarray
    intrinsics: Mapping[str, float]
    base_from_camera: np.ndarray
    ee_pose: Optional[list] = None
    gripper: Optional[float] = None

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.depth.shape[0]), int(self.depth.shape[1])

    @property
    def origin(self) -> np.ndarray:
        """Camera centre in the base frame."""
        return np.asarray(self.base_from_camera, dtype=float)[:3, 3]


def views_from_state(state: Union[Mapping[str, Any], Sequence[Any]],
                     cameras: Optional[Sequence[str]] = None) -> list[CameraView]:
    """Turn a raw `get_state` dict (or a list of them, or CameraViews) into CameraViews.

    Only cameras that delivered depth are used; ``cameras`` restricts the names.
    """
    if isinstance(state, CameraView):
        return [state]
    if isinstance(state, Mapping):
        states: list[Any] = [state]
    else:
        states = list(state)
    views: list[CameraView] = []
    for s in states:
        if isinstance(s, CameraView):
            if cameras is None or s.name in cameras:
                views.append(s)
            continue
        depth = s.get("depth") or {}
        images = s.get("image") or {}
        g = s.get("gripper")
        g = float(g[0]) if isinstance(g, (list, tuple)) and g else (float(g) if g is not None else None)
        for name, d in depth.items():
            if cameras is not None and name not in cameras:
                continue
            rgb = images.get(name)
            if not isinstance(rgb, np.ndarray):
                raise ValueError(f"camera {name!r}: call get_state(..., raw=True) to get numpy images")
            views.append(CameraView(name=name, rgb=rgb, depth=np.asarray(d),
                                    intrinsics=dict(s["camera_intrinsics"][name]),
                                    base_from_camera=np.asarray(s["camera_extrinsics"][name], dtype=float),
                                    ee_pose=list(s["ee_pose"]) if s.get("ee_pose") is not None else None,
                                    gripper=g))
    if not views:
        raise ValueError("no camera with depth in the observation(s)")
    return views


def pixel_to_point(u: float, v: float, depth: Union[float, np.ndarray], intrinsics: Mapping[str, float],
                   base_from_camera: ArrayLike) -> Optional[np.ndarray]:
    """Pixel (column u, row v) + depth -> 3D point in the base frame.

    ``depth`` is either the depth value (m) or the whole depth image (then read at [v, u]).
    Returns None when the depth is not finite or not positive.
    """
    if isinstance(depth, np.ndarray) and depth.ndim == 2:
        d = float(depth[int(round(v)), int(round(u))])
    else:
        d = float(depth)
    if not (math.isfinite(d) and d > 0.0):
        return None
    K = intrinsics
    p = np.array([(u - K["cx"]) * d / K["fx"], (v - K["cy"]) * d / K["fy"], d])
    return transform_points(base_from_camera, p)


def depth_to_points(depth: np.ndarray, intrinsics: Mapping[str, float], base_from_camera: ArrayLike,
                    mask: Optional[np.ndarray] = None, min_depth: float = 0.05, max_depth: float = 3.0,
                    stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Depth image (+ optional boolean mask) -> (points (N, 3) in the base frame, flat pixel index).

    The pixel index is ``v * width + u`` so that results can be painted back into (H, W) masks.
    Pixels with non-finite depth or depth outside [min_depth, max_depth] are skipped.
    """
    d = np.asarray(depth, dtype=np.float32)
    H, W = d.shape
    if stride > 1:
        sel = np.zeros((H, W), dtype=bool)
        sel[::stride, ::stride] = True
    else:
        sel = np.ones((H, W), dtype=bool)
    with np.errstate(invalid="ignore"):
        sel &= np.isfinite(d) & (d > min_depth) & (d < max_depth)
    if mask is not None:
        sel &= np.asarray(mask, dtype=bool)
    idx = np.flatnonzero(sel)
    z = d.reshape(-1)[idx].astype(np.float64)
    u = (idx % W).astype(np.float64)
    v = (idx // W).astype(np.float64)
    K = intrinsics
    x = (u - K["cx"]) * z / K["fx"]
    y = (v - K["cy"]) * z / K["fy"]
    T = np.asarray(base_from_camera, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    P = np.empty((idx.size, 3))
    P[:, 0] = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
    P[:, 1] = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
    P[:, 2] = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
    return P, idx


def project_points(points_base: ArrayLike, intrinsics: Mapping[str, float],
                   base_from_camera: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Base-frame points -> (pixel coordinates (N, 2) as (u, v), camera depth z (N,))."""
    Pc = base_to_camera(np.atleast_2d(np.asarray(points_base, dtype=float)), base_from_camera)
    z = Pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics["fx"] * Pc[:, 0] / z + intrinsics["cx"]
        v = intrinsics["fy"] * Pc[:, 1] / z + intrinsics["cy"]
    return np.stack([u, v], axis=1), z


# --------------------------------------------------------------------------------------------
# Planes, boxes, normals
# --------------------------------------------------------------------------------------------

@dataclass
class Plane:
    """Plane ``normal . p + offset = 0``; ``normal`` is unit length and points to the free side
    (up for a table)."""

    normal: np.ndarray
    offset: float

    def distance(self, points: ArrayLike) -> np.ndarray:
        """Signed distance of points (positive on the side the normal points to)."""
        return np.asarray(points, dtype=float) @ self.normal + self.offset

    def project(self, points: ArrayLike) -> np.ndarray:
        P = np.asarray(points, dtype=float)
        return P - np.outer(self.distance(P), self.normal) if P.ndim == 2 else P - self.distance(P) * self.normal

    def basis(self) -> np.ndarray:
        """3x3 with columns (e1, e2, normal): e1 is base x projected into the plane when possible."""
        n = self.normal
        ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = ref - np.dot(ref, n) * n
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        return np.stack([e1, e2, n], axis=1)

    @property
    def height_at_origin(self) -> float:
        """For a near-horizontal plane: its z at x = y = 0 in the base frame."""
        return -self.offset / self.normal[2] if abs(self.normal[2]) > 1e-9 else float("nan")


@dataclass
class OrientedBox:
    """Oriented bounding box: ``center`` (3,), ``axes`` 3x3 (columns are the unit box axes, in
    the base frame), ``extents`` (3,) full side lengths along those axes."""

    center: np.ndarray
    axes: np.ndarray
    extents: np.ndarray

    @property
    def volume(self) -> float:
        return float(np.prod(self.extents))

    def corners(self) -> np.ndarray:
        """(8, 3) corners in the base frame."""
        s = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)])
        return self.center + (s * self.extents) @ self.axes.T

    def to_local(self, points: ArrayLike) -> np.ndarray:
        return (np.asarray(points, dtype=float) - self.center) @ self.axes

    def contains(self, points: ArrayLike, margin: float = 0.0) -> np.ndarray:
        return np.all(np.abs(self.to_local(points)) <= self.extents / 2.0 + margin, axis=1)


def obb_pca(points: ArrayLike) -> OrientedBox:
    """Oriented bounding box from the principal axes of the points (largest extent first)."""
    P = np.asarray(points, dtype=float)
    mu = P.mean(axis=0)
    C = np.cov((P - mu).T) if len(P) > 2 else np.eye(3)
    _, vecs = np.linalg.eigh(C)
    axes = vecs[:, ::-1].copy()
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    L = (P - mu) @ axes
    lo, hi = L.min(axis=0), L.max(axis=0)
    return OrientedBox(center=mu + axes @ ((lo + hi) / 2.0), axes=axes, extents=hi - lo)


def convex_hull_2d(xy: ArrayLike) -> np.ndarray:
    """Convex hull (counter-clockwise, no repeated first point) of 2D points, monotone chain."""
    P = np.unique(np.round(np.asarray(xy, dtype=float), 5), axis=0)
    if len(P) <= 2:
        return P
    pts = [tuple(p) for p in P]  # already sorted by x then y (np.unique sorts rows)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


def _polygon_area(poly: np.ndarray) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _hull_input(xy: np.ndarray, cell: float = 0.002) -> np.ndarray:
    """Reduce 2D points to the extreme ones per grid column/row (hull-preserving up to `cell`)."""
    if len(xy) < 200:
        return xy
    q = np.floor(xy / cell).astype(np.int64)
    keep = []
    for a in (0, 1):
        key = q[:, a]
        order = np.lexsort((xy[:, 1 - a], key))
        k = key[order]
        first = np.r_[True, k[1:] != k[:-1]]
        last = np.r_[k[1:] != k[:-1], True]
        keep.append(order[first])
        keep.append(order[last])
    return xy[np.unique(np.concatenate(keep))]


def min_area_rect(xy: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Minimum-area enclosing rectangle of 2D points (rotating the hull's edges).

    Returns (centre (2,), axes 2x2 (columns, the longer side first), extents (2,), hull area).
    """
    P = np.asarray(xy, dtype=float)
    hull = convex_hull_2d(_hull_input(P))
    if len(hull) < 3:
        lo, hi = P.min(axis=0), P.max(axis=0)
        ext = hi - lo
        axes = np.eye(2)
        if ext[1] > ext[0]:
            axes, ext = axes[:, ::-1], ext[::-1]
        return (lo + hi) / 2.0, axes, ext, 0.0
    edges = np.roll(hull, -1, axis=0) - hull
    ang = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2.0))
    c, s = np.cos(ang), np.sin(ang)
    # project hull points on (c, s) and (-s, c) for every candidate angle
    a = hull[:, 0][None, :] * c[:, None] + hull[:, 1][None, :] * s[:, None]
    b = -hull[:, 0][None, :] * s[:, None] + hull[:, 1][None, :] * c[:, None]
    area = (a.max(1) - a.min(1)) * (b.max(1) - b.min(1))
    i = int(np.argmin(area))
    u = np.array([c[i], s[i]])
    w = np.array([-s[i], c[i]])
    ea, eb = a[i].max() - a[i].min(), b[i].max() - b[i].min()
    centre = u * (a[i].max() + a[i].min()) / 2.0 + w * (b[i].max() + b[i].min()) / 2.0
    if eb > ea:
        u, w, ea, eb = w, -u, eb, ea
    return centre, np.stack([u, w], axis=1), np.array([ea, eb]), _polygon_area(hull)


def obb_in_plane(points: ArrayLike, plane: Plane, extend_to_plane: Union[bool, float] = 0.02
                 ) -> tuple[OrientedBox, float]:
    """Box aligned with a support plane: minimum-area rectangle of the points' footprint in the
    plane, and their height range above it.

    ``extend_to_plane``: if True, or a number and the lowest point is less than that far above
    the plane, the box is extended down to the plane (the underside of a resting object is never
    seen). Returns (box, fill) where fill = footprint hull area / rectangle area (about 1 for a
    box, pi/4 for a cylinder seen from above). Axes: (long side, short side, plane normal).
    """
    P = np.asarray(points, dtype=float)
    B = plane.basis()
    L = P @ B
    h = L[:, 2] + plane.offset  # height above the plane
    centre2, axes2, ext2, hull_area = min_area_rect(L[:, :2])
    hmin, hmax = float(h.min()), float(h.max())
    if extend_to_plane is True or (extend_to_plane is not False and hmin < float(extend_to_plane)):
        hmin = 0.0
    u = B[:, 0] * axes2[0, 0] + B[:, 1] * axes2[1, 0]
    w = B[:, 0] * axes2[0, 1] + B[:, 1] * axes2[1, 1]
    n = B[:, 2]
    if np.dot(np.cross(u, w), n) < 0:
        w = -w
    axes = np.stack([u, w, n], axis=1)
    c_plane = B[:, 0] * centre2[0] + B[:, 1] * centre2[1] - plane.offset * n
    center = c_plane + n * (hmin + hmax) / 2.0
    ext = np.array([ext2[0], ext2[1], hmax - hmin])
    fill = hull_area / max(ext2[0] * ext2[1], 1e-12)
    return OrientedBox(center=center, axes=axes, extents=ext), float(fill)


def fit_plane_ransac(points: ArrayLike, threshold: float = 0.006, iterations: int = 200,
                     up: Optional[ArrayLike] = (0.0, 0.0, 1.0), max_tilt_deg: float = 25.0,
                     sample_size: int = 6000, seed: int = 0) -> tuple[Plane, np.ndarray]:
    """RANSAC plane fit, refined by least squares on the inliers.

    ``up``: if given, only planes whose normal is within ``max_tilt_deg`` of it are accepted
    (the support surface), and the returned normal points along it. Among near-equal candidates
    the one with most inliers wins. Returns (plane, inlier mask over all points).
    """
    P = np.asarray(points, dtype=float)
    if len(P) < 3:
        raise ValueError("need at least 3 points for a plane")
    rng = np.random.default_rng(seed)
    S = P[rng.choice(len(P), size=min(sample_size, len(P)), replace=False)]
    tri = S[rng.integers(0, len(S), size=(iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nn = np.linalg.norm(n, axis=1)
    ok = nn > 1e-9
    n[ok] /= nn[ok, None]
    if up is not None:
        upv = np.asarray(up, dtype=float)
        upv = upv / np.linalg.norm(upv)
        cosang = n @ upv
        n[cosang < 0] *= -1.0
        ok &= np.abs(cosang) >= math.cos(math.radians(max_tilt_deg))
    if not ok.any():
        raise ValueError("no plane candidate matched the up direction")
    n, tri = n[ok], tri[ok]
    d = -np.einsum("ij,ij->i", n, tri[:, 0])
    counts = (np.abs(S @ n.T + d) < threshold).sum(axis=0)
    best = int(np.argmax(counts))
    normal, off = n[best], d[best]
    # refine twice: least squares (SVD) on the inliers of the full cloud
    for _ in range(2):
        inl = np.abs(P @ normal + off) < threshold
        Q = P[inl]
        if len(Q) > 30000:
            Q = Q[rng.choice(len(Q), 30000, replace=False)]
        mu = Q.mean(axis=0)
        _, _, vt = np.linalg.svd(Q - mu, full_matrices=False)
        nrm = vt[2]
        ref = np.asarray(up, dtype=float) if up is not None else normal
        if np.dot(nrm, ref) < 0:
            nrm = -nrm
        normal, off = nrm, -float(np.dot(nrm, mu))
    inl = np.abs(P @ normal + off) < threshold
    return Plane(normal=normal, offset=float(off)), inl


_NEIGHBOUR_OFFSETS_HALF = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                                    if (i, j, k) > (0, 0, 0)], dtype=np.int64)
_NEIGHBOUR_OFFSETS_ALL = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                                  dtype=np.int64)
_KEY_BITS = 19
_KEY_OFF = 1 << (_KEY_BITS - 1)


def _voxel_keys(q: np.ndarray) -> np.ndarray:
    q = q + _KEY_OFF
    return (q[..., 0] << (2 * _KEY_BITS)) | (q[..., 1] << _KEY_BITS) | q[..., 2]


def _voxelize(points: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (sorted unique voxel keys (M,), voxel integer coords (M, 3), point -> voxel index (N,))."""
    q = np.floor(points / size).astype(np.int64)
    keys = _voxel_keys(q)
    uk, first, inv = np.unique(keys, return_index=True, return_inverse=True)
    return uk, q[first], inv.reshape(-1)


def _lookup(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Index of each key in sorted_keys, or -1."""
    pos = np.searchsorted(sorted_keys, keys)
    pos = np.minimum(pos, len(sorted_keys) - 1)
    return np.where(sorted_keys[pos] == keys, pos, -1)


def voxel_downsample(points: ArrayLike, size: float, values: Optional[np.ndarray] = None
                     ) -> tuple[np.ndarray, Optional[np.ndarray], np.ndarray]:
    """Average points (and optional per-point values) per voxel of side ``size``.

    Returns (centroids (M, 3), averaged values or None, point -> voxel index (N,)).
    """
    P = np.asarray(points, dtype=float)
    _, _, inv = _voxelize(P, size)
    M = int(inv.max()) + 1 if len(inv) else 0
    cnt = np.bincount(inv, minlength=M).astype(float)
    C = np.stack([np.bincount(inv, P[:, i], M) for i in range(3)], axis=1) / cnt[:, None]
    V = None
    if values is not None:
        vals = np.asarray(values, dtype=float).reshape(len(P), -1)
        V = np.stack([np.bincount(inv, vals[:, i], M) for i in range(vals.shape[1])], axis=1) / cnt[:, None]
    return C, V, inv


def estimate_normals(points: ArrayLike, radius: float = 0.008, viewpoints: Optional[ArrayLike] = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Surface normals by local PCA over a voxel neighbourhood (voxel side ``radius``, 27 cells).

    ``viewpoints``: (3,) or (N, 3) sensor positions; normals are flipped to face them.
    Returns (normals (N, 3), curvature (N,) = smallest eigenvalue / sum of eigenvalues).
    """
    P = np.asarray(points, dtype=float)
    uk, vq, inv = _voxelize(P, radius)
    M = len(uk)
    cnt = np.bincount(inv, minlength=M).astype(float)
    S1 = np.stack([np.bincount(inv, P[:, i], M) for i in range(3)], axis=1)
    S2 = np.stack([np.bincount(inv, P[:, i] * P[:, j], M) for i in range(3) for j in range(3)], axis=1)
    N = cnt.copy()
    A1 = S1.copy()
    A2 = S2.copy()
    for off in _NEIGHBOUR_OFFSETS_ALL:
        if not off.any():
            continue
        j = _lookup(uk, _voxel_keys(vq + off))
        ok = j >= 0
        N[ok] += cnt[j[ok]]
        A1[ok] += S1[j[ok]]
        A2[ok] += S2[j[ok]]
    mu = A1 / N[:, None]
    C = A2.reshape(M, 3, 3) / N[:, None, None] - mu[:, :, None] * mu[:, None, :]
    w, v = np.linalg.eigh(C)
    nv = v[:, :, 0]
    curv = w[:, 0] / np.maximum(w.sum(axis=1), 1e-15)
    normals = nv[inv]
    if viewpoints is not None:
        vp = np.asarray(viewpoints, dtype=float)
        flip = np.einsum("ij,ij->i", normals, (vp if vp.ndim == 2 else vp[None, :]) - P) < 0
        normals[flip] *= -1.0
    return normals, curv[inv]


def _connected_components(n: int, ei: np.ndarray, ej: np.ndarray) -> np.ndarray:
    """Labels (n,) of the connected components of an undirected graph; label = smallest member."""
    lab = np.arange(n)
    if len(ei) == 0:
        return lab
    while True:
        a, b = lab[ei], lab[ej]
        diff = a != b
        if not diff.any():
            return lab
        a, b = a[diff], b[diff]
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        np.minimum.at(lab, hi, lo)
        while True:  # pointer jumping until every node points at a root
            nxt = lab[lab]
            if np.array_equal(nxt, lab):
                break
            lab = nxt


# --------------------------------------------------------------------------------------------
# Colours and shapes
# --------------------------------------------------------------------------------------------

def _rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) RGB in [0, 1] -> (N, 3) HSV with hue in degrees."""
    r, g, b = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    mx, mn = rgb.max(axis=1), rgb.min(axis=1)
    d = mx - mn
    h = np.zeros(len(rgb))
    nz = d > 1e-9
    rm = nz & (mx == r)
    gm = nz & (mx == g) & ~rm
    bm = nz & ~rm & ~gm
    h[rm] = np.mod((g[rm] - b[rm]) / d[rm], 6.0)
    h[gm] = (b[gm] - r[gm]) / d[gm] + 2.0
    h[bm] = (r[bm] - g[bm]) / d[bm] + 4.0
    s = np.where(mx > 1e-9, d / np.maximum(mx, 1e-9), 0.0)
    return np.stack([h * 60.0, s, mx], axis=1)


COLOR_NAMES = ("red", "orange", "yellow", "green", "cyan", "blue", "purple", "pink", "brown",
               "white", "grey", "black")

_RELATED_COLORS = {
    ("red", "orange"), ("red", "pink"), ("red", "brown"), ("orange", "yellow"), ("orange", "brown"),
    ("yellow", "green"), ("green", "cyan"), ("cyan", "blue"), ("blue", "purple"),
    ("purple", "pink"), ("white", "grey"), ("grey", "black"), ("brown", "yellow"),
}


def _color_similarity(a: str, b: str) -> float:
    if a == b:
        return 1.0
    return 0.4 if (a, b) in _RELATED_COLORS or (b, a) in _RELATED_COLORS else 0.0


def _hsv_name(h: float, s: float, v: float) -> str:
    """Colour word for hue (deg), saturation and (bright-pixel) value, all of a lit object."""
    if v < 0.16:
        return "black"
    if s < 0.22 or (v < 0.35 and s < 0.35):
        if v >= 0.92:
            return "white"
        return "grey" if v > 0.22 else "black"
    if h < 15 or h >= 340:
        return "brown" if v < 0.45 else "red"
    if h < 45:
        return "brown" if v < 0.8 else "orange"
    if h < 70:
        return "brown" if v < 0.5 else "yellow"
    if h < 165:
        return "green"
    if h < 195:
        return "cyan"
    if h < 255:
        return "blue"
    if h < 290:
        return "purple"
    return "pink"


def color_name(rgb: ArrayLike) -> str:
    """Name of the dominant colour of RGB samples ((N, 3) or (3,), uint8 0-255 or float 0-1).

    Lighting makes most of an object's pixels darker than its paint, so the value is taken from
    the brightest pixels (90th percentile), the saturation is the median over the brighter half
    and the hue the saturation-weighted circular mean over it.
    """
    a = np.asarray(rgb, dtype=float).reshape(-1, 3)
    if a.size and a.max() > 1.0:
        a = a / 255.0
    hsv = _rgb_to_hsv(a)
    v = float(np.percentile(hsv[:, 2], 90))
    bright = hsv[:, 2] >= float(np.percentile(hsv[:, 2], 50))
    s = float(np.median(hsv[bright, 1]))
    w = hsv[bright, 1] * hsv[bright, 2] + 1e-9
    ang = np.radians(hsv[bright, 0])
    h = math.degrees(math.atan2(float(np.sum(w * np.sin(ang))), float(np.sum(w * np.cos(ang))))) % 360.0
    return _hsv_name(h, s, v)


SHAPE_NAMES = ("box", "cylinder", "bowl", "plate", "flat", "object")


def shape_name(extents: ArrayLike, fill: float, hollow: bool = False, thin_fill: Optional[float] = None) -> str:
    """Coarse shape from a support-plane box and the footprint fill ratio.

    ``extents``: (long side, short side, height) in metres; ``fill``: hull area / rectangle area
    of the footprint (1 for a box, ~0.79 for a disc); ``hollow``: the top is lower in the middle
    than at the rim; ``thin_fill``: fill ratio of the points in the (long side, height) plane,
    used for slabs standing on edge. Returns one of box, cylinder, bowl, plate, flat, object.
    """
    a, b, h = (float(x) for x in extents)
    round_top = fill < 0.9 and b > 0.6 * a
    if h < 0.02 and a > 0.03:
        return "plate" if (round_top and b > 0.75 * a) else "flat"
    if b < 0.025 and b < 0.3 * min(a, h):      # a slab standing on its edge
        if thin_fill is not None and thin_fill < 0.9:
            return "plate"
        return "flat"
    if round_top or (fill < 0.9 and h >= 0.7 * b):
        if hollow and h < 0.8 * max(a, b):
            return "bowl"
        return "cylinder"
    if fill >= 0.9:
        return "box"
    return "object"


# --------------------------------------------------------------------------------------------
# Segmentation
# --------------------------------------------------------------------------------------------

@dataclass
class ObjectCluster:
    """One segmented object.

    ``points``/``colors``: its fused 3D points (base frame) and RGB (uint8); ``centroid``: their
    mean; ``center``: centre of the support-plane box (the box is extended down to the plane when
    the object rests on it, so this estimates the object's geometric centre); ``obb``: that box
    (axes: long side, short side, plane normal); ``obb_pca``: PCA box of the visible points;
    ``masks``: {camera: (H, W) bool}; ``height``/``bottom``: highest/lowest point above the
    support plane; ``held``: it lies between the (measured) fingers; ``point_camera``: index of
    the view each point came from, ``camera_origins``: those views' centres (for normals).
    """

    id: int
    points: np.ndarray
    colors: np.ndarray
    centroid: np.ndarray
    center: np.ndarray
    obb: OrientedBox
    obb_pca: OrientedBox
    color_name: str
    shape_name: str
    masks: dict
    fill: float
    hollow: bool
    height: float
    bottom: float
    pixel_count: dict = field(default_factory=dict)
    held: bool = False
    point_camera: Optional[np.ndarray] = None
    camera_origins: Optional[np.ndarray] = None

    @property
    def extents(self) -> np.ndarray:
        return self.obb.extents

    @property
    def size(self) -> float:
        """Box volume with every side counted as at least 1 cm (so flat things still compare)."""
        return float(np.prod(np.maximum(self.obb.extents, 0.01)))

    def describe(self) -> str:
        c = self.center
        e = self.obb.extents
        held = " (held)" if self.held else ""
        return (f"#{self.id} {self.color_name} {self.shape_name}{held} at ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}) "
                f"size {e[0]:.3f}x{e[1]:.3f}x{e[2]:.3f} m, {len(self.points)} pts")


@dataclass
class SceneSegmentation:
    """Result of `segment_scene`: the support plane, the objects (largest first), per-camera
    views and point bookkeeping, and timings in milliseconds."""

    plane: Plane
    objects: list
    views: list
    timings_ms: dict
    plane_masks: dict

    def by_id(self, i: int) -> Optional[ObjectCluster]:
        for o in self.objects:
            if o.id == i:
                return o
        return None

    def summary(self) -> str:
        n = self.plane.normal
        lines = [f"plane n=({n[0]:.3f},{n[1]:.3f},{n[2]:.3f}) z0={self.plane.height_at_origin:.4f} "
                 f"({self.timings_ms.get('total', 0):.0f} ms)"]
        lines += ["  " + o.describe() for o in self.objects]
        return "\n".join(lines)


def _hand_exclusion(points: np.ndarray, ee_pose: Optional[Sequence[float]], gripper: Optional[float],
                    hand: HandGeometry, margin: float = 0.006) -> np.ndarray:
    """Mask of points on the robot's own hand (and the wrist just behind it)."""
    if ee_pose is None:
        return np.zeros(len(points), dtype=bool)
    T = pose_to_matrix(ee_pose)
    L = (points - T[:3, 3]) @ T[:3, :3]  # TCP frame: z approach, y finger axis
    x, y, z = L[:, 0], L[:, 1], L[:, 2]
    half_open = 0.5 * gripper_to_width(gripper if gripper is not None else -1.0, hand)
    ay = np.abs(y)
    # fingers: from their inner faces outwards
    fingers = ((np.abs(x) <= hand.finger_half_depth + margin)
               & (ay >= half_open - 0.004) & (ay <= half_open + hand.finger_thickness + margin)
               & (z <= hand.tip_beyond_tcp + margin) & (z >= -hand.finger_length - 0.012))
    # guard capsule around the fingertips, outside the space between the fingers
    env_c = -hand.envelope_behind_tcp
    dy = np.maximum(ay - hand.envelope_half_length, 0.0)
    env = (np.sqrt(x ** 2 + (z - env_c) ** 2 + dy ** 2) <= hand.envelope_radius + margin) & (ay >= half_open - 0.004)
    # hand body and the wrist right behind it
    body = ((np.abs(x) <= hand.body_half_x + margin) & (ay <= hand.body_half_y + margin)
            & (z <= -hand.body_start_behind_tcp + margin) & (z >= -0.16))
    wrist = (x ** 2 + y ** 2 <= 0.09 ** 2) & (z < -0.10) & (z > -0.30)
    return fingers | env | body | wrist


def _chromaticity(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB -> (N, 2) chromaticity (r, g shares), damped towards grey when dark."""
    c = rgb.astype(np.float32) + 8.0
    return c[:, :2] / c.sum(axis=1, keepdims=True)


def _euclidean_groups(points: np.ndarray, voxel: float, min_points: int,
                      labels: Optional[np.ndarray] = None) -> list[np.ndarray]:
    """Connected components of occupied voxels (26-neighbourhood) -> point index arrays of the
    groups with at least ``min_points`` points. With ``labels`` (small ints per point), only
    points with the same label are connected."""
    q = np.floor(points / voxel).astype(np.int64)
    keys = _voxel_keys(q)
    if labels is not None:
        keys = keys + (labels.astype(np.int64) << (3 * _KEY_BITS))
    uk, first, inv = np.unique(keys, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    vq = q[first]
    vl = (uk >> (3 * _KEY_BITS)) << (3 * _KEY_BITS)
    eis, ejs = [], []
    for off in _NEIGHBOUR_OFFSETS_HALF:
        j = _lookup(uk, _voxel_keys(vq + off) + vl)
        i = np.flatnonzero(j >= 0)
        eis.append(i)
        ejs.append(j[i])
    lab = _connected_components(len(uk), np.concatenate(eis), np.concatenate(ejs))
    plab = lab[inv]
    order = np.argsort(plab, kind="stable")
    sl = plab[order]
    starts = np.flatnonzero(np.r_[True, sl[1:] != sl[:-1]])
    ends = np.r_[starts[1:], len(sl)]
    return [order[a:b] for a, b in zip(starts, ends) if b - a >= min_points]


def _color_modes(chroma: np.ndarray, bin_size: float, min_points: int) -> Optional[np.ndarray]:
    """Split a cluster's chromaticities into modes: dense cells of a 2D histogram (cell side
    ``bin_size`` / 2) joined with their 8 neighbours; sparse cells (anti-aliased edges, specks)
    join the nearest mode. Returns per-point mode labels, or None when there is a single mode."""
    n = len(chroma)
    cell = bin_size / 2.0
    q = np.floor(chroma / cell).astype(np.int64)
    key = q[:, 0] * 4096 + q[:, 1]
    uk, first, inv = np.unique(key, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    cnt = np.bincount(inv)
    dense = cnt >= max(8, int(0.015 * n))
    if dense.sum() < 2:
        return None
    cq = q[first]
    di = np.flatnonzero(dense)
    dk = uk[di]
    eis, ejs = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            if (dx, dy) <= (0, 0):
                continue
            nk = (cq[di, 0] + dx) * 4096 + (cq[di, 1] + dy)
            pos = np.minimum(np.searchsorted(dk, nk), len(dk) - 1)
            hit = dk[pos] == nk
            eis.append(np.flatnonzero(hit))
            ejs.append(pos[hit])
    lab = _connected_components(len(di), np.concatenate(eis), np.concatenate(ejs))
    roots, mode_of_dense = np.unique(lab, return_inverse=True)
    if len(roots) < 2:
        return None
    # mode mean chromaticity and size; modes smaller than min_points are not kept as modes
    cell_mode = np.full(len(uk), -1)
    cell_mode[di] = mode_of_dense
    pm = cell_mode[inv]
    sizes = np.bincount(pm[pm >= 0], minlength=len(roots))
    keep = np.flatnonzero(sizes >= min_points)
    keep = keep[np.argsort(-sizes[keep])][:32]
    if len(keep) < 2:
        return None
    means = np.stack([chroma[pm == m].mean(axis=0) for m in keep])
    d = np.linalg.norm(chroma[:, None, :] - means[None, :, :], axis=2)
    return np.argmin(d, axis=1)


def _merge_held(pieces: list, P: np.ndarray, C: np.ndarray, view: CameraView, hand: HandGeometry
                ) -> tuple[list, list]:
    """Flag the pieces lying between the fingers and merge those of the same colour (a held
    object is cut into pieces where the fingers and their guard hide it)."""
    T = pose_to_matrix(view.ee_pose)
    half_open = 0.5 * gripper_to_width(view.gripper if view.gripper is not None else -1.0, hand)
    held = []
    for part in pieces:
        L = (P[part] - T[:3, 3]) @ T[:3, :3]
        inside = ((np.abs(L[:, 0]) < 0.04) & (np.abs(L[:, 1]) < half_open + 0.006)
                  & (L[:, 2] > -0.06) & (L[:, 2] < 0.05))
        held.append(bool(half_open > 0.003 and inside.mean() > 0.5))
    groups: dict = {}
    out, flags = [], []
    for part, h in zip(pieces, held):
        if h:
            name = color_name(C[part])
            if name in ("white", "grey"):
                # the guard around the fingertips showing through or beside the held object
                L = (P[part] - T[:3, 3]) @ T[:3, :3]
                r = np.hypot(L[:, 0], L[:, 2] + hand.envelope_behind_tcp)
                if np.mean(np.abs(r - hand.envelope_radius) < 0.004) > 0.8:
                    continue
            groups.setdefault(name, []).append(part)
        else:
            out.append(part)
            flags.append(False)
    for parts in groups.values():
        out.append(np.concatenate(parts))
        flags.append(True)
    return out, flags


def segment_scene(observations: Union[Mapping[str, Any], Sequence[Any], CameraView],
                  cameras: Optional[Sequence[str]] = None, *, voxel: float = 0.006,
                  color_split: Optional[float] = 0.06, plane_threshold: float = 0.006,
                  min_height: float = 0.005, max_object_height: float = 0.35,
                  min_points: int = 40, max_depth: float = 2.5, ignore_hand: bool = True,
                  hand: HandGeometry = FRANKA_HAND, plane: Optional[Plane] = None,
                  grow_masks: bool = True) -> SceneSegmentation:
    """Segment the objects standing on the support plane.

    ``observations``: a raw ``get_state(..., raw=True)`` dict, a list of them, or CameraViews.
    Every camera with depth is used (``cameras`` restricts the names) and the clouds are fused.

    Steps: back-project -> RANSAC support plane (normal near base +z) -> keep points between
    ``min_height`` and 1 m above it, within the plane's footprint -> drop the robot's own hand
    (from ``ee_pose``/``gripper`` in the state) -> voxel grid of side ``voxel`` ->
    26-connected components over occupied voxels (Euclidean clustering) -> a cluster whose
    chromaticities (r, g shares, so shading does not matter) form several dense modes at least
    ``color_split`` apart is split by colour and re-clustered per colour (None: no split) ->
    clusters with fewer than ``min_points`` points, or reaching above ``max_object_height``
    (the arm), are dropped -> per cluster: masks, boxes, colour and shape names -> with
    ``grow_masks``, each image mask grows over the adjacent pixels of the object's colour that
    the height cut gave to the plane (a bowl's inner floor, the bottom millimetres of a side);
    the cluster's 3D points stay those above the cut.
    """
    t0 = time.perf_counter()
    views = views_from_state(observations, cameras)
    clouds, pix, cams = [], [], []
    for ci, v in enumerate(views):
        P, idx = depth_to_points(v.depth, v.intrinsics, v.base_from_camera, max_depth=max_depth)
        clouds.append(P)
        pix.append(idx)
        cams.append(np.full(len(idx), ci, dtype=np.int32))
    P = np.concatenate(clouds)
    pidx = np.concatenate(pix)
    pcam = np.concatenate(cams)
    t1 = time.perf_counter()

    if plane is None:
        plane, _ = fit_plane_ransac(P, threshold=plane_threshold)
    h = plane.distance(P)
    on_plane = np.abs(h) < plane_threshold
    plane_masks = {}
    for ci, v in enumerate(views):
        m = np.zeros(v.shape[0] * v.shape[1], dtype=bool)
        sel = pcam == ci
        m[pidx[sel][on_plane[sel]]] = True
        plane_masks[v.name] = m.reshape(v.shape)
    t2 = time.perf_counter()

    keep = (h > min_height) & (h < 1.0)
    # only over the plane's footprint (robust extent of its inliers, plus a margin)
    B = plane.basis()
    inl2 = P[on_plane][:: max(1, int(on_plane.sum()) // 20000)] @ B[:, :2]
    lo = np.percentile(inl2, 0.5, axis=0) - 0.02
    hi = np.percentile(inl2, 99.5, axis=0) + 0.02
    Q2 = P @ B[:, :2]
    keep &= np.all((Q2 >= lo) & (Q2 <= hi), axis=1)
    if ignore_hand:
        for ci, v in enumerate(views):
            if v.ee_pose is not None:
                # each observation carries the hand pose it was taken with
                sel = np.flatnonzero(keep & (pcam == ci))
                keep[sel[_hand_exclusion(P[sel], v.ee_pose, v.gripper, hand)]] = False
    sel = np.flatnonzero(keep)
    Po, ho = P[sel], h[sel]
    rgb_all = [np.asarray(v.rgb).reshape(-1, 3) for v in views]
    Co = np.empty((len(sel), 3), dtype=np.uint8)
    for ci in range(len(views)):
        m = pcam[sel] == ci
        Co[m] = rgb_all[ci][pidx[sel][m]]
    t3 = time.perf_counter()

    objects: list[ObjectCluster] = []
    pieces: list[np.ndarray] = []
    if len(sel) >= min_points:
        chroma = _chromaticity(Co)
        for g in _euclidean_groups(Po, voxel, min_points):
            parts = [g]
            if color_split is not None:
                modes = _color_modes(chroma[g], color_split, min_points)
                if modes is not None:
                    parts = [g[sub] for sub in _euclidean_groups(Po[g], voxel, min_points, modes)]
            for part in parts:
                if float(ho[part].max()) > max_object_height:
                    continue  # reaches up out of the workspace of objects: the robot arm
                pieces.append(part)
    held_flags = [False] * len(pieces)
    hand_view = next((v for v in views if v.ee_pose is not None), None)
    if ignore_hand and hand_view is not None and pieces:
        pieces, held_flags = _merge_held(pieces, Po, Co, hand_view, hand)
    for part, held in zip(pieces, held_flags):
        o = _make_cluster(len(objects), Po[part], Co[part], ho[part], sel[part], pidx, pcam, views, plane)
        o.held = held
        objects.append(o)
    objects.sort(key=lambda o: -len(o.points))
    for k, o in enumerate(objects):
        o.id = k
    if grow_masks and objects:
        _grow_masks(objects, views, h, pidx, pcam, plane_threshold, min_height, color_split or 0.06)
    t4 = time.perf_counter()
    timings = {"backproject": 1e3 * (t1 - t0), "plane": 1e3 * (t2 - t1), "filter": 1e3 * (t3 - t2),
               "cluster": 1e3 * (t4 - t3), "total": 1e3 * (t4 - t0)}
    return SceneSegmentation(plane=plane, objects=objects, views=views, timings_ms=timings,
                             plane_masks=plane_masks)


def _grow_masks(objects: list, views: list, h: np.ndarray, pidx: np.ndarray, pcam: np.ndarray,
                plane_threshold: float, min_height: float, color_tol: float, max_iter: int = 96) -> None:
    """Grows each object's image masks (4-connected) into pixels just above the plane (cut by
    ``min_height``) whose chromaticity matches the object's, never into another object's mask."""
    for ci, v in enumerate(views):
        H, W = v.shape
        hmap = np.full(H * W, np.nan, dtype=np.float32)
        sel = pcam == ci
        hmap[pidx[sel]] = h[sel]
        with np.errstate(invalid="ignore"):
            low = ((hmap > -plane_threshold) & (hmap <= min_height)).reshape(H, W)
        if not low.any():
            continue
        chroma = _chromaticity(np.asarray(v.rgb).reshape(-1, 3)).reshape(H, W, 2)
        taken = np.zeros((H, W), dtype=bool)
        for o in objects:
            taken |= o.masks.get(v.name, taken)
        for o in objects:
            m = o.masks.get(v.name)
            if m is None or not m.any():
                continue
            ys, xs = np.nonzero(m)
            pad = 6
            y0, y1 = max(0, ys.min() - pad), min(H, ys.max() + pad + 1)
            x0, x1 = max(0, xs.min() - pad), min(W, xs.max() + pad + 1)
            ref = np.median(chroma[ys, xs], axis=0)
            c = chroma[y0:y1, x0:x1]
            cand = (low[y0:y1, x0:x1] & ~taken[y0:y1, x0:x1]
                    & (np.abs(c - ref).max(axis=2) < color_tol))
            if not cand.any():
                continue
            g = m[y0:y1, x0:x1].copy()
            for _ in range(max_iter):
                d = g.copy()
                d[1:] |= g[:-1]
                d[:-1] |= g[1:]
                d[:, 1:] |= g[:, :-1]
                d[:, :-1] |= g[:, 1:]
                d = g | (d & cand)
                if d.sum() == g.sum():
                    break
                g = d
            added = g & ~m[y0:y1, x0:x1]
            if added.any():
                grown = m.copy()
                grown[y0:y1, x0:x1] |= added
                o.masks[v.name] = grown
                taken[y0:y1, x0:x1] |= added


def _make_cluster(k: int, P: np.ndarray, C: np.ndarray, h: np.ndarray, gsel: np.ndarray, pidx: np.ndarray,
                  pcam: np.ndarray, views: list, plane: Plane) -> ObjectCluster:
    masks, counts = {}, {}
    for ci, v in enumerate(views):
        m = np.zeros(v.shape[0] * v.shape[1], dtype=bool)
        s = pcam[gsel] == ci
        m[pidx[gsel][s]] = True
        masks[v.name] = m.reshape(v.shape)
        counts[v.name] = int(s.sum())
    box, fill = obb_in_plane(P, plane)
    pca = obb_pca(P)
    a, b, hh = box.extents
    # hollow: the middle of the footprint is clearly lower than the top of the rim
    L = box.to_local(P)
    r = np.sqrt((L[:, 0] / max(a, 1e-6)) ** 2 + (L[:, 1] / max(b, 1e-6)) ** 2)
    inner, outer = r < 0.2, r > 0.38
    top = float(h.max())
    hollow = bool(inner.sum() >= 10 and outer.sum() >= 10 and hh > 0.02
                  and np.percentile(h[inner], 80) < 0.6 * top and np.percentile(h[outer], 90) > 0.8 * top)
    thin_fill = None
    if b < 0.03:
        ring = P @ box.axes
        _, _, ext2, area2 = min_area_rect(np.stack([ring[:, 0], ring[:, 2]], axis=1))
        thin_fill = area2 / max(ext2[0] * ext2[1], 1e-12)
    shape = shape_name(box.extents, fill, hollow, thin_fill)
    return ObjectCluster(id=k, points=P, colors=C, centroid=P.mean(axis=0), center=box.center, obb=box,
                         obb_pca=pca, color_name=color_name(C), shape_name=shape, masks=masks, fill=fill,
                         hollow=hollow, height=top, bottom=float(h.min()), pixel_count=counts,
                         point_camera=pcam[gsel].copy(), camera_origins=np.array([v.origin for v in views]))


# --------------------------------------------------------------------------------------------
# Prompts
# --------------------------------------------------------------------------------------------

_COLOR_WORDS = {
    "red": "red", "crimson": "red", "scarlet": "red", "orange": "orange", "yellow": "yellow",
    "gold": "yellow", "golden": "yellow", "green": "green", "lime": "green", "cyan": "cyan",
    "teal": "cyan", "turquoise": "cyan", "blue": "blue", "navy": "blue", "purple": "purple",
    "violet": "purple", "magenta": "pink", "pink": "pink", "brown": "brown", "wooden": "brown",
    "white": "white", "cream": "white", "grey": "grey", "gray": "grey", "silver": "grey",
    "black": "black", "dark": "black",
}
_SHAPE_WORDS = {
    "block": "box", "blocks": "box", "cube": "box", "box": "box", "brick": "box", "cuboid": "box",
    "cylinder": "cylinder", "can": "cylinder", "cup": "cylinder", "mug": "cylinder", "bottle": "cylinder",
    "glass": "cylinder", "jar": "cylinder", "tube": "cylinder", "bowl": "bowl", "bowls": "bowl", "basin": "bowl",
    "plate": "plate", "plates": "plate", "dish": "plate", "disc": "plate", "disk": "plate", "saucer": "plate",
    "flat": "flat", "sheet": "flat", "board": "flat", "card": "flat", "pad": "flat",
}
_SHAPE_RELATED = {("plate", "flat"), ("box", "flat"), ("bowl", "cylinder"), ("box", "object"),
                  ("cylinder", "object"), ("bowl", "plate")}
_SPATIAL_WORDS = {
    "left": "left", "leftmost": "left", "right": "right", "rightmost": "right",
    "front": "front", "forward": "front", "ahead": "front", "back": "back", "behind": "back",
    "rear": "back", "nearest": "nearest", "closest": "nearest", "near": "nearest", "close": "nearest",
    "farthest": "farthest", "furthest": "farthest", "far": "farthest", "largest": "largest",
    "biggest": "largest", "big": "largest", "large": "largest", "bigger": "largest", "larger": "largest",
    "smallest": "smallest", "small": "smallest", "little": "smallest", "tiny": "smallest",
    "smaller": "smallest", "tallest": "tallest", "tall": "tallest", "highest": "tallest",
    "top": "tallest", "lowest": "lowest", "shortest": "lowest", "middle": "middle", "center": "middle",
    "centre": "middle",
}


def parse_prompt(prompt: str) -> dict:
    """Split a text prompt into colour, shape and spatial words (see module docs)."""
    words = re.findall(r"[a-z]+", prompt.lower())
    colors = [_COLOR_WORDS[w] for w in words if w in _COLOR_WORDS]
    shapes = [_SHAPE_WORDS[w] for w in words if w in _SHAPE_WORDS]
    spatial = [_SPATIAL_WORDS[w] for w in words if w in _SPATIAL_WORDS]
    if "dark" in words and len(colors) > 1:
        colors = [c for c in colors if c != "black"]
    return {"colors": colors, "shapes": shapes, "spatial": spatial, "words": words}


def _spatial_key(word: str, objs: list, origin: np.ndarray) -> np.ndarray:
    c = np.array([o.center for o in objs])
    if word == "left":
        return c[:, 1]
    if word == "right":
        return -c[:, 1]
    if word == "front":
        return c[:, 0]
    if word == "back":
        return -c[:, 0]
    dist = np.linalg.norm(c[:, :2] - origin[:2], axis=1)
    if word == "nearest":
        return -dist
    if word == "farthest":
        return dist
    size = np.array([o.size for o in objs])
    if word == "largest":
        return size
    if word == "smallest":
        return -size
    if word == "tallest":
        return np.array([o.height for o in objs])
    if word == "lowest":
        return -np.array([o.height for o in objs])
    if word == "middle":
        return -np.abs(c[:, 1] - np.median(c[:, 1]))
    return np.zeros(len(objs))


def rank_objects(scene: SceneSegmentation, prompt: str, origin: ArrayLike = (0.0, 0.0, 0.0),
                 min_score: float = 0.3) -> list[tuple[ObjectCluster, float]]:
    """Objects that fit the prompt, best first, with a score in [0, 1].

    Score = colour match (1 same name, 0.4 a neighbouring name such as orange/brown or
    white/grey, 0 otherwise) x shape match (1 same, 0.6 related, 0.35 other: shapes of partly
    seen objects are unreliable, colours less so); objects under ``min_score`` are left out, so
    "purple cube" finds nothing when there is only a blue plate.
    Spatial words order the best-scoring objects: left = +y, right = -y, front = +x, back = -x
    (base frame), nearest/farthest from ``origin`` (the robot base by default), largest/smallest
    by box volume, tallest/lowest by top height, middle by y."""
    q = parse_prompt(prompt)
    objs = list(scene.objects)
    if not objs:
        return []
    score = np.ones(len(objs))
    if q["colors"]:
        cs = np.array([max(_color_similarity(c, o.color_name) for c in q["colors"]) for o in objs])
        score *= cs
    if q["shapes"]:
        ss = []
        for o in objs:
            best = 0.35
            for s in q["shapes"]:
                if s == o.shape_name:
                    best = 1.0
                elif (s, o.shape_name) in _SHAPE_RELATED or (o.shape_name, s) in _SHAPE_RELATED:
                    best = max(best, 0.6)
            ss.append(best)
        score *= np.array(ss)
    cand = [i for i in range(len(objs)) if score[i] >= min_score]
    if not cand:
        return []
    top = max(score[i] for i in cand)
    # spatial words order the candidates that match best (and keep the rest after them)
    origin = np.asarray(origin, dtype=float)
    if q["spatial"]:
        best = [i for i in cand if score[i] >= top - 1e-9]
        rest = sorted([i for i in cand if score[i] < top - 1e-9], key=lambda i: -score[i])
        sub = [objs[i] for i in best]
        keys = np.zeros(len(sub))
        for w in q["spatial"]:
            k = _spatial_key(w, sub, origin)
            rng = float(k.max() - k.min())
            keys = keys * 1e3 + ((k - k.min()) / rng if rng > 0 else 0 * k)
        ordered = [best[i] for i in np.argsort(-keys, kind="stable")]
        return [(objs[i], float(score[i])) for i in ordered + rest]
    cand.sort(key=lambda i: (-score[i], -len(objs[i].points)))
    return [(objs[i], float(score[i])) for i in cand]


def select(scene: SceneSegmentation, prompt: Optional[str] = None, point: Optional[tuple] = None,
           camera: Optional[str] = None, origin: ArrayLike = (0.0, 0.0, 0.0),
           snap_radius: float = 0.03) -> Optional[ObjectCluster]:
    """Pick one object by text prompt and/or pixel.

    ``point=(u, v)`` (column, row) in ``camera`` (default: the first view) selects the cluster
    whose mask contains that pixel, or else the cluster nearest (within ``snap_radius``) to the
    pixel's back-projected 3D point. With a prompt, the best-ranked object is returned; with
    neither, the largest. Returns None if nothing matches.
    """
    if point is not None:
        view = scene.views[0] if camera is None else next(v for v in scene.views if v.name == camera)
        u, v = int(round(point[0])), int(round(point[1]))
        H, W = view.shape
        if not (0 <= u < W and 0 <= v < H):
            return None
        hits = [o for o in scene.objects if o.masks[view.name][v, u]]
        if prompt:
            ranked = [o for o, _ in rank_objects(scene, prompt, origin)]
            hits = [o for o in ranked if o in hits] or hits
        if hits:
            return hits[0]
        p = pixel_to_point(u, v, view.depth, view.intrinsics, view.base_from_camera)
        if p is None:
            return None
        best, bd = None, snap_radius
        for o in scene.objects:
            d = float(np.min(np.linalg.norm(o.points[:: max(1, len(o.points) // 3000)] - p, axis=1)))
            if d < bd:
                best, bd = o, d
        return best
    if prompt:
        r = rank_objects(scene, prompt, origin)
        return r[0][0] if r else None
    if not scene.objects:
        return None
    return max(scene.objects, key=lambda o: o.size)


def segment(observations: Union[Mapping[str, Any], Sequence[Any]], prompt: Optional[str] = None,
            point: Optional[tuple] = None, camera: Optional[str] = None, **kwargs: Any
            ) -> tuple[Optional[ObjectCluster], SceneSegmentation]:
    """`segment_scene` then `select` in one call: returns (object or None, scene)."""
    scene = segment_scene(observations, **kwargs)
    return select(scene, prompt, point, camera), scene


# --------------------------------------------------------------------------------------------
# Grasps
# --------------------------------------------------------------------------------------------

@dataclass
class Grasp:
    """A parallel-jaw grasp. ``pose``/``pregrasp``: TCP ``[x, y, z, ax, ay, az]`` in the base frame;
    ``width``: object width between the pads (m); ``open_width``: opening to approach with;
    ``gripper_open``: the `robo` gripper command for that opening; ``score`` in [0, 1];
    ``kind``: "top_down" or "antipodal"; ``approach``/``closing``: unit vectors (base frame);
    ``position``: TCP position; ``clearance``: fingertip height above the support plane."""

    pose: list
    pregrasp: list
    width: float
    open_width: float
    gripper_open: float
    score: float
    kind: str
    approach: np.ndarray
    closing: np.ndarray
    position: np.ndarray
    clearance: float
    details: dict = field(default_factory=dict)

    @property
    def matrix(self) -> np.ndarray:
        return pose_to_matrix(self.pose)

    def lifted(self, dz: float) -> list:
        """The grasp pose moved ``dz`` metres straight up (base z)."""
        p = list(self.pose)
        p[2] += dz
        return p


def grasp_rotation(closing: ArrayLike, approach: ArrayLike, reference: Optional[np.ndarray] = None) -> np.ndarray:
    """TCP rotation with y = closing and z = approach; of the two signs of the closing axis (the
    same parallel-jaw grasp turned half a turn), the one nearest ``reference`` (a 3x3 rotation,
    e.g. of the measured ``ee_pose``), else nearest pointing down at yaw 0."""
    approach = np.asarray(approach, dtype=float)
    closing = np.asarray(closing, dtype=float)
    a = approach / np.linalg.norm(approach)
    d = closing - np.dot(closing, a) * a
    d /= np.linalg.norm(d)
    best, bd = None, 1e9
    down = axis_angle_to_matrix([math.pi, 0.0, 0.0])
    for sgn in (1.0, -1.0):
        y = sgn * d
        R = np.stack([np.cross(y, a), y, a], axis=1)
        # nearest to the reference; on a tie, nearest to pointing down at yaw 0
        dist = (rotation_distance(reference, R) if reference is not None else 0.0) + 0.01 * rotation_distance(down, R)
        if dist < bd:
            best, bd = R, dist
    return best


def _gripper_clear(L: np.ndarray, open_width: float, hand: HandGeometry, margin: float) -> bool:
    """No point (in the TCP frame) inside the space the open fingers and the hand body sweep
    while moving along +z (the approach) into place."""
    x, y, z = L[:, 0], L[:, 1], L[:, 2]
    ay = np.abs(y)
    fingers = ((np.abs(x) <= hand.finger_half_depth + margin) & (ay >= open_width / 2.0)
               & (ay <= open_width / 2.0 + hand.finger_thickness + margin) & (z <= hand.tip_beyond_tcp + margin))
    body = ((np.abs(x) <= hand.body_half_x) & (ay <= hand.body_half_y) & (z <= -hand.body_start_behind_tcp + margin))
    return not bool(fingers.any() or body.any())


def _lowest_gripper_height(T: np.ndarray, open_width: float, plane: Plane, hand: HandGeometry) -> float:
    """Lowest height above the plane of the fingertips and the fingertip guard."""
    R, t = T[:3, :3], T[:3, 3]
    pts = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for yy in (open_width / 2.0, open_width / 2.0 + hand.finger_thickness):
                pts.append(t + R @ np.array([sx * hand.finger_half_depth, sy * yy, hand.tip_beyond_tcp]))
    low = float(np.min(plane.distance(np.array(pts))))
    c = t - R[:, 2] * hand.envelope_behind_tcp
    ends = np.array([c + R[:, 1] * hand.envelope_half_length, c - R[:, 1] * hand.envelope_half_length])
    low = min(low, float(np.min(plane.distance(ends))) - hand.envelope_radius)
    return low


def propose_grasps(obj: ObjectCluster, scene: Optional[SceneSegmentation] = None, *,
                   plane: Optional[Plane] = None, reference_pose: Optional[ArrayLike] = None,
                   hand: HandGeometry = FRANKA_HAND, width_margin: float = 0.008,
                   plane_margin: float = 0.004, pregrasp_offset: float = 0.10, grasp_depth: float = 0.025,
                   max_candidates: int = 20, antipodal: bool = True, seed: int = 0) -> list[Grasp]:
    """Grasp candidates for ``obj``, best first.

    Top-down: the approach is straight down the plane normal; candidate centres are the box
    centre and points of the object's upper surface, candidate closing directions the box axes,
    the radial direction from the centre and six fixed yaws. For each, the points in the finger
    pads' slab give the width of the part that would be pinched (the contiguous run through the
    centre), the TCP goes ``grasp_depth`` below the local top (never lower than the hand allows).
    Antipodal: pairs of points whose estimated normals oppose each other along the line joining
    them; the approach is the direction perpendicular to that line closest to straight down.

    Every candidate is kept only if the width plus ``width_margin`` on each side fits the stroke,
    the fingers and hand (opened to ``open_width``) sweep no point of this object or the others in
    ``scene``, and the fingertips and their guard stay ``plane_margin`` above the support plane.
    Scores combine alignment (closing along the short side / normals opposing), centredness,
    width margin and grasp depth. ``reference_pose`` (e.g. the measured ``ee_pose``) picks the
    yaw of the two equivalent ones that turns the hand the least; default pointing down, yaw 0.
    """
    if plane is None:
        if scene is None:
            raise ValueError("propose_grasps needs the scene or the support plane")
        plane = scene.plane
    Rref = pose_to_matrix(reference_pose)[:3, :3] if reference_pose is not None else axis_angle_to_matrix([math.pi, 0, 0])
    P = obj.points
    vp_pts = None
    if obj.point_camera is not None and obj.camera_origins is not None:
        vp_pts = obj.camera_origins[obj.point_camera]
    Q, VQ, _ = voxel_downsample(P, 0.003, vp_pts)
    obstacles = [Q]
    if scene is not None:
        for o in scene.objects:
            if o is not obj:
                near = np.linalg.norm(o.points[:, :2] - obj.center[:2], axis=1) < 0.25
                if near.any():
                    obstacles.append(voxel_downsample(o.points[near], 0.004)[0])
    O = np.concatenate(obstacles)
    n = plane.normal
    down = -n
    hQ = plane.distance(Q)
    box = obj.obb
    ext = box.extents
    diag = 0.5 * math.hypot(ext[0], ext[1]) + 1e-6
    elongated = ext[0] > 1.2 * ext[1]
    max_w = hand.max_width - 2.0 * width_margin
    body_drop = hand.body_start_behind_tcp - 0.003
    min_tcp = plane_margin + max(hand.tip_beyond_tcp, hand.envelope_radius - hand.envelope_behind_tcp)
    rng = np.random.default_rng(seed)
    cands: list[Grasp] = []

    def finish(T: np.ndarray, width: float, kind: str, score: float, details: dict) -> None:
        open_w = min(hand.max_width, width + 2.0 * width_margin + 0.016)
        L = (O - T[:3, 3]) @ T[:3, :3]
        if not _gripper_clear(L, open_w, hand, 0.002):
            return
        low = _lowest_gripper_height(T, open_w, plane, hand)
        if low < plane_margin - 1e-6:
            return
        pre = T.copy()
        pre[:3, 3] -= T[:3, 2] * pregrasp_offset
        cands.append(Grasp(pose=matrix_to_pose(T), pregrasp=matrix_to_pose(pre), width=float(width),
                           open_width=float(open_w), gripper_open=width_to_gripper(open_w, hand),
                           score=float(score), kind=kind, approach=T[:3, 2].copy(), closing=T[:3, 1].copy(),
                           position=T[:3, 3].copy(), clearance=float(low), details=details))

    # ---- top-down ----------------------------------------------------------------------
    B = plane.basis()
    upper = Q[hQ > 0.5 * hQ.max()]
    centres = [box.center - n * (plane.distance(box.center))]
    if len(upper):
        pick = rng.choice(len(upper), size=min(24, len(upper)), replace=False)
        centres += [p - n * plane.distance(p) for p in upper[pick]]
    base_dirs = [box.axes[:, 0], box.axes[:, 1]]
    for k in range(6):
        ang = k * math.pi / 6.0
        base_dirs.append(B[:, 0] * math.cos(ang) + B[:, 1] * math.sin(ang))
    c0 = centres[0]
    for ci, c in enumerate(centres):
        dirs = list(base_dirs)
        radial = c - c0
        if np.linalg.norm(radial) > 0.01:
            radial = radial / np.linalg.norm(radial)
            dirs = [radial, np.cross(n, radial)] + dirs
        for d in dirs:
            d = d - np.dot(d, n) * n
            d /= np.linalg.norm(d)
            e = np.cross(d, down)
            rel = Q - c
            s = rel @ d
            t = rel @ e
            slab = np.abs(t) <= hand.finger_half_depth
            near_c = slab & (np.abs(s) <= 0.012)
            if not near_c.any():
                continue
            top = float(hQ[near_c].max())
            tcp_h = max(min_tcp, top - min(grasp_depth, 0.5 * top))
            # the hand body must clear everything under it
            under = (np.abs(t) <= hand.body_half_x) & (np.abs(s) <= hand.body_half_y)
            tcp_h = max(tcp_h, float(hQ[under].max()) - body_drop) if under.any() else tcp_h
            if tcp_h > top - 0.004:
                continue  # would not reach any material
            rel_pts = slab & (hQ >= tcp_h - hand.tip_beyond_tcp)
            ss = np.sort(s[rel_pts])
            if len(ss) < 3:
                continue
            gaps = np.flatnonzero(np.diff(ss) > 0.012)
            seg_lo = np.r_[0, gaps + 1]
            seg_hi = np.r_[gaps, len(ss) - 1]
            # the run containing the centre (or the nearest one within 6 mm)
            dist = np.where((ss[seg_lo] <= 0) & (ss[seg_hi] >= 0), 0.0,
                            np.minimum(np.abs(ss[seg_lo]), np.abs(ss[seg_hi])))
            r = int(np.argmin(dist))
            if dist[r] > 0.006:
                continue
            lo, hi = float(ss[seg_lo[r]]), float(ss[seg_hi[r]])
            width = hi - lo + 0.003
            if width > max_w or width < 0.002:
                continue
            centre = c + d * (lo + hi) / 2.0   # middle of the pinched run, on the plane
            T = np.eye(4)
            T[:3, :3] = grasp_rotation(d, down, Rref)
            T[:3, 3] = centre - n * plane.distance(centre) + n * tcp_h
            off = np.linalg.norm((T[:3, 3] - c0) - np.dot(T[:3, 3] - c0, n) * n)
            centred = max(0.0, 1.0 - off / diag)
            align = abs(float(np.dot(d, box.axes[:, 1]))) if elongated else 1.0
            margin_s = (max_w - width) / max_w
            depth_s = min(1.0, (top - tcp_h) / grasp_depth)
            turn_s = 1.0 - rotation_distance(Rref, T[:3, :3]) / math.pi
            score = 0.3 * align + 0.25 * centred + 0.2 * margin_s + 0.15 * depth_s + 0.1 * turn_s
            finish(T, width, "top_down", score, {"top": top, "tcp_height": tcp_h, "centre_index": ci})

    # ---- antipodal -----------------------------------------------------------------------
    if antipodal and len(Q) >= 10:
        # normals face the camera(s) that saw each point; without that, away from the centre
        vp = VQ if VQ is not None else obj.centroid + 2.0 * (Q - obj.centroid)
        N, curv = estimate_normals(Q, radius=0.006, viewpoints=vp)
        flat = curv < 0.05
        idx = np.flatnonzero(flat)
        if len(idx) > 2:
            seeds = rng.choice(idx, size=min(120, len(idx)), replace=False)
            cos_lim = math.cos(math.radians(20))
            for i in seeds:
                dvec = Q[idx] - Q[i]
                dist = np.linalg.norm(dvec, axis=1)
                ok = (dist > 0.004) & (dist < max_w)
                if not ok.any():
                    continue
                u = dvec[ok] / dist[ok, None]
                ni, nj = N[i], N[idx[ok]]
                c1 = -(u @ ni)            # i's normal points away from j
                c2 = np.einsum("ij,ij->i", nj, u)  # j's normal points away from i
                good = (c1 > cos_lim) & (c2 > cos_lim)
                if not good.any():
                    continue
                jj = np.flatnonzero(good)[np.argmax((c1 + c2)[good])]
                j = idx[ok][jj]
                d = Q[j] - Q[i]
                width = float(np.linalg.norm(d)) + 0.003
                d = d / np.linalg.norm(d)
                a = down - np.dot(down, d) * d
                if np.linalg.norm(a) < 0.3:
                    continue  # closing nearly vertical: no approach from above
                a /= np.linalg.norm(a)
                T = np.eye(4)
                T[:3, :3] = grasp_rotation(d, a, Rref)
                mid = 0.5 * (Q[i] + Q[j])
                T[:3, 3] = mid
                h_t = plane.distance(mid)
                if h_t < min_tcp:
                    T[:3, 3] = mid + n * (min_tcp - h_t)
                off = np.linalg.norm((mid - c0) - np.dot(mid - c0, n) * n)
                centred = max(0.0, 1.0 - off / diag)
                align = 0.5 * float(c1[jj] + c2[jj])
                margin_s = (max_w - width) / max_w
                turn_s = 1.0 - rotation_distance(Rref, T[:3, :3]) / math.pi
                # pairs rest on estimated normals: trusted a little less than top-down slices
                score = 0.95 * (0.35 * align + 0.25 * centred + 0.15 * margin_s + 0.15 * float(np.dot(a, down))
                                + 0.1 * turn_s)
                finish(T, width, "antipodal", score, {"pair": (Q[i].tolist(), Q[j].tolist())})

    cands.sort(key=lambda g: -g.score)
    # drop near-duplicates (same place and same closing axis)
    out: list[Grasp] = []
    for g in cands:
        if all(np.linalg.norm(g.position - o.position) > 0.005 or abs(float(np.dot(g.closing, o.closing))) < 0.98
               for o in out):
            out.append(g)
        if len(out) >= max_candidates:
            break
    return out
