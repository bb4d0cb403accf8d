"""Placing: TCP poses that put a held object's bottom onto a support's surface or a container's
floor, keeping the hand's current orientation (the object arrives as it hangs now)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .report import warn
from .segmentation import ObjectCluster, SceneSegmentation
from .transforms import ArrayLike, pose_to_matrix


@dataclass
class Placement:
    """Where to put a held object. Poses are TCP ``[x, y, z, ax, ay, az]`` in the base frame with
    the rotation of the ``tcp_pose`` given: ``pose`` leaves the object's bottom ``clearance``
    above the surface (open the gripper there); ``preplace`` is ``approach_height`` higher along
    the support plane's normal (go there first, then straight down); ``retreat`` is
    ``retreat_height`` above ``pose`` (leave that way after opening). ``surface`` is the surface's
    height above the support plane (m), ``target`` the base-frame point the object's bottom
    centre is put on, ``object_bottom``/``object_height`` the estimates used (m above the plane /
    m); ``details`` says how each was found."""

    pose: list
    preplace: list
    retreat: list
    surface: float
    target: np.ndarray
    object_bottom: float
    object_height: float
    details: dict = field(default_factory=dict)


def _surface_of(support: ObjectCluster, scene: SceneSegmentation, inside: bool, at: np.ndarray) -> tuple:
    """Height above the plane the object will stand on: a container's floor (its lowest seen
    points in the middle of the footprint) or the top of a solid support around ``at``."""
    plane = scene.plane
    h = plane.distance(support.points)
    L = support.obb.to_local(support.points)
    a, b = max(support.obb.extents[0], 1e-6), max(support.obb.extents[1], 1e-6)
    r = np.sqrt((L[:, 0] / a) ** 2 + (L[:, 1] / b) ** 2)
    if inside:
        inner = r < 0.3
        if inner.sum() >= 10:
            return float(np.percentile(h[inner], 10)), "container floor: 10th percentile of the points in the middle"
        return float(support.bottom), "container floor: not seen, its lowest point used"
    rel = support.points - at
    d = np.linalg.norm(rel - np.outer(rel @ plane.normal, plane.normal), axis=1)
    local = d < 0.03
    if local.sum() >= 10:
        return float(np.percentile(h[local], 95)), "surface: 95th percentile of the support's points within 3 cm"
    return float(support.top), "surface: the support's top (no points within 3 cm of the target)"


def place_poses(held: ObjectCluster, support: Optional[ObjectCluster], scene: SceneSegmentation,
                tcp_pose: ArrayLike, *, at: Optional[ArrayLike] = None, inside: Optional[bool] = None,
                object_height: Optional[float] = None, center_offset: Optional[ArrayLike] = None,
                clearance: float = 0.01,
                approach_height: float = 0.10, retreat_height: float = 0.10) -> Placement:
    """Place and pre-place poses for the held object ``held`` (observed now, in ``scene``).

    ``support``: the object to put it on or in, or None for the support plane itself (then
    ``at`` is required). ``at``: the base-frame point (x, y[, z]) where the object's bottom centre
    should go; default the support's centre. ``inside``: put it on the container's floor rather
    than its top; default: whether the support is hollow (a bowl). ``object_height``: the held
    object's own height measured before it was picked up (``obj.height`` then); without it the
    bottom is the lowest point seen now, which the fingers may hide. ``tcp_pose``: the measured
    ``ee_pose`` of this observation (the object's offset from the TCP is taken from it).
    ``center_offset``: the object's centre minus the TCP position, base frame, when known better
    than from the part visible now (e.g. ``obj.center - grasp.position`` of the pick; a held
    object often shows only a slice beside the fingers).

    The TCP keeps its rotation; its position moves so that the object's bottom centre lands on
    ``at`` at ``clearance`` above the surface. Warns (a PerceptionWarning) when the object's
    footprint is wider than a container's opening or ``held`` is not flagged as held."""
    plane = scene.plane
    n = plane.normal
    T = pose_to_matrix(tcp_pose)
    tcp = T[:3, 3]
    if not held.held:
        warn(f"place_poses: {held.describe()} is not flagged held (evidence {held.held_evidence}); "
             "the poses assume it moves with the hand", scene)
    if support is None and at is None:
        raise ValueError("place_poses: without a support object, say where with at=(x, y)")
    if inside is None:
        inside = bool(support is not None and support.hollow)
    # where the object's bottom centre goes (on the plane, before the surface height)
    if at is not None:
        a = np.asarray(at, dtype=float).ravel()
        if a.size not in (2, 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"place_poses: at must be a finite (x, y) or (x, y, z), got {at}")
        goal = np.array([a[0], a[1], a[2] if a.size == 3 else 0.0])
    else:
        goal = np.asarray(support.center, dtype=float).copy()
    goal = goal - n * plane.distance(goal)
    details = {}
    if support is None:
        surface, details["surface"] = 0.0, "the support plane"
    else:
        surface, details["surface"] = _surface_of(support, scene, inside, goal)
        if inside:
            opening = float(support.obb.extents[1])
            if float(held.obb.extents[0]) > opening - 0.005:
                warn(f"place_poses: the held object's footprint ({held.obb.extents[0]:.3f} m) may not fit the "
                     f"container's opening ({opening:.3f} m)", scene)
    # the held object's bottom, and its offset from the TCP along the plane
    bottom = float(held.bottom)
    details["bottom"] = "lowest point seen now"
    if object_height is not None:
        from_top = float(held.top) - float(object_height)
        if from_top < bottom:
            bottom = from_top
            details["bottom"] = "top seen now minus the height measured before the pick"
    height = float(object_height) if object_height is not None else float(held.top - held.bottom)
    tcp_h = float(plane.distance(tcp))
    off = held.center - tcp if center_offset is None else np.asarray(center_offset, dtype=float).reshape(3)
    details["offset"] = "centre seen now minus the TCP" if center_offset is None else "given"
    off = off - np.dot(off, n) * n
    pos = goal - off + n * (surface + clearance + (tcp_h - bottom))
    rv = list(np.asarray(tcp_pose, dtype=float)[3:6])
    pose = [*map(float, pos), *map(float, rv)]
    pre = [*map(float, pos + n * approach_height), *map(float, rv)]
    ret = [*map(float, pos + n * retreat_height), *map(float, rv)]
    return Placement(pose=pose, preplace=pre, retreat=ret, surface=surface,
                     target=goal + n * surface, object_bottom=bottom, object_height=height, details=details)


@dataclass
class Marking:
    """A coloured mark on the support plane (tape, a painted line, a target zone): the base-frame
    ``points`` of its pixels (all cameras), ``center``: the centre of its rectangle ``obb`` (the
    minimum-area rectangle of those points in the plane, on the plane; axes long, short, normal;
    its long side ``length``, short side ``width``), the ``color_name``, and ``seen_whole``: both
    ends of its long side were seen with table beyond them in some camera (False: a camera's
    border, the robot or an object cuts it, so ``length`` and the centre along it are only what
    is in view)."""

    points: np.ndarray
    center: np.ndarray
    obb: object
    color_name: str
    seen_whole: bool = True

    @property
    def length(self) -> float:
        return float(self.obb.extents[0])

    @property
    def width(self) -> float:
        return float(self.obb.extents[1])

    def describe(self) -> str:
        c, e = self.center, self.obb.extents
        cut = "" if self.seen_whole else ", cut off in view"
        return (f"{self.color_name} marking at ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}) "
                f"size {e[0]:.3f}x{e[1]:.3f} m{cut}, {len(self.points)} pts")


def _eroded(mask: np.ndarray, r: int) -> np.ndarray:
    """Pixels of ``mask`` whose whole (2r+1)^2 neighbourhood is in it (outside the image counts
    as not in it)."""
    out = mask.copy()
    for axis in (0, 1):
        src = out.copy()
        n = src.shape[axis]
        for k in range(1, r + 1):
            for sgn in (-1, 1):
                sh = np.zeros_like(src)
                a = [slice(None)] * 2
                b = [slice(None)] * 2
                if sgn > 0:
                    a[axis], b[axis] = slice(0, n - k), slice(k, n)
                else:
                    a[axis], b[axis] = slice(k, n), slice(0, n - k)
                sh[tuple(a)] = src[tuple(b)]
                out &= sh
    return out


def _end_seen(p: np.ndarray, views: list, plane) -> bool:
    """Whether some camera sees the table at base point ``p`` (on the plane): inside its image,
    not covered, not in view of the image border."""
    from .camera import project_points
    for v in views:
        uv, z = project_points(p, v.intrinsics, v.base_from_camera)
        H, W = v.shape
        u, w = int(round(float(uv[0, 0]))), int(round(float(uv[0, 1])))
        if z[0] <= 0 or u < 3 or w < 3 or u >= W - 3 or w >= H - 3:
            continue
        d = float(np.asarray(v.depth)[w, u])
        if np.isfinite(d) and abs(d - float(z[0])) < 0.006:
            return True
    return False


def find_markings(scene: SceneSegmentation, color: str, min_points: int = 20) -> list:
    """Marks of colour ``color`` (a colour word, e.g. "yellow") lying on the support plane -
    pixels the segmentation gave to the plane whose colour has that name - grouped by 1 cm
    proximity, largest first. Flat marks are part of the plane, never objects.

    Only pixels well inside the table count: at least 2 pixels from anything that is not table
    (an object's outline, where the colours of the object and the table blend into a third, the
    robot, the image border) and not under an object's footprint (the lowest millimetres of its
    sides, which the 5 mm cut gives to the plane). ``center`` is the middle of the mark's
    rectangle, not the mean of its pixels, so a camera that sees more of one end does not pull
    it (the same tape measured from different views agrees within a few millimetres when both
    see all of it; ``seen_whole`` says whether they did)."""
    from .camera import depth_to_points
    from .geometry import obb_in_plane
    from .naming import _hsv_names, _rgb_to_hsv
    from .prompts import parse_prompt
    from .voxels import _euclidean_groups
    want = parse_prompt(color)["colors"]
    if not want:
        raise ValueError(f"find_markings: {color!r} names no colour")
    pts = []
    for v in scene.views:
        m = scene.plane_masks.get(v.name)
        if m is None or not m.any():
            continue
        m = _eroded(m, 2)
        for o in scene.objects:
            om = o.masks.get(v.name)
            if om is not None and om.any():
                m &= ~_dilated(om, 2)
        if not m.any():
            continue
        rgb = np.asarray(v.rgb).reshape(-1, 3)[m.ravel()].astype(float) / 255.0
        hsv = _rgb_to_hsv(rgb)
        sat = (hsv[:, 1] > 0.35) & (hsv[:, 2] > 0.3)
        if not sat.any():
            continue
        names = _hsv_names(hsv[sat])
        keep = np.zeros(m.size, dtype=bool)
        keep[np.flatnonzero(m.ravel())[np.flatnonzero(sat)[np.isin(names, want)]]] = True
        if keep.any():
            P, _ = depth_to_points(v.depth, v.intrinsics, v.base_from_camera, mask=keep.reshape(m.shape))
            pts.append(P)
    if not pts:
        return []
    P = np.concatenate(pts)
    # not under an object standing on the plane (its sides' lowest millimetres)
    for o in scene.objects:
        if o.support != "plane":
            continue
        L = o.obb.to_local(P)
        P = P[~np.all(np.abs(L[:, :2]) <= 0.5 * o.obb.extents[:2] + 0.003, axis=1)]
    out = []
    for g in _euclidean_groups(P, 0.01, min_points):
        box, _ = obb_in_plane(P[g], scene.plane)
        c = scene.plane.project(box.center)
        box.center = c
        ax = box.axes[:, 0]
        ends = [c + s * (0.5 * box.extents[0] + 0.008) * ax for s in (-1.0, 1.0)]
        whole = all(_end_seen(e[None], scene.views, scene.plane) for e in ends)
        out.append(Marking(points=P[g], center=c, obb=box, color_name=want[0], seen_whole=whole))
    out.sort(key=lambda mk: -len(mk.points))
    return out


def _dilated(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` grown by ``r`` pixels (a square neighbourhood)."""
    return ~_eroded(~mask, r)
