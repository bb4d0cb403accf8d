"""Cameras and back-projection: `CameraView` (one RGB-D image with its calibration), views from
a raw `get_state`, pixel/depth image -> base-frame points and base-frame points -> pixels."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from .transforms import ArrayLike, base_to_camera, transform_points


@dataclass
class CameraView:
    """One RGB-D image with its calibration, as returned by ``get_state(..., raw=True)``.

    ``rgb``: (H, W, 3) uint8; ``depth``: (H, W) float32 planar depth in metres;
    ``intrinsics``: {fx, fy, cx, cy, width, height}; ``base_from_camera``: 4x4.
    ``ee_pose``/``gripper`` (measured, optional) let segmentation ignore the robot's own hand;
    ``joint`` (the 7 measured arm joints, optional) lets it remove the whole robot (the self-filter
    of `robo_perception.robot`). All three must be those the image was taken with.
    ``grasp``: the gripper's own view of its fingers then (``state["control_feedback"]["grasp"]
    ["status"]``: "holding" when they stopped short of a closing command), or None when the
    observation does not say; `held` needs "holding" when it is known. ``image_time`` and
    ``state_time``: when the image was taken and when the joints were measured (s, the state's
    ``image_timestamp[name]`` and ``timestamp``), or None; `segment_scene` leaves out a view
    whose image is much older than its joints (the robot may have moved in between).
    """

    name: str
    rgb: np.ndarray
    depth: np.ndarray
    intrinsics: Mapping[str, float]
    base_from_camera: np.ndarray
    ee_pose: Optional[list] = None
    gripper: Optional[float] = None
    joint: Optional[list] = None
    grasp: Optional[str] = None
    image_time: Optional[float] = None
    state_time: Optional[float] = None

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
        stamps = s.get("image_timestamp") or {}
        fb = s.get("control_feedback")
        grasp = (fb.get("grasp") or {}).get("status") if isinstance(fb, Mapping) else None
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
                                    gripper=g,
                                    joint=[float(q) for q in s["joint"]] if s.get("joint") is not None else None,
                                    grasp=str(grasp) if grasp is not None else None,
                                    image_time=float(stamps[name]) if stamps.get(name) is not None else None,
                                    state_time=float(s["timestamp"]) if s.get("timestamp") is not None else None))
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
