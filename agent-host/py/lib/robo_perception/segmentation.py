"""Segmentation: `ObjectCluster`, `SceneSegmentation` and `segment_scene` (support plane, height
cut, hand exclusion, Euclidean clustering, colour split, held objects, per-cluster boxes and
names, mask growing)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from .camera import CameraView, depth_to_points, views_from_state
from .geometry import OrientedBox, Plane, fit_plane_ransac, min_area_rect, obb_in_plane, obb_pca
from .hand import FRANKA_HAND, HandGeometry, gripper_to_width
from .naming import _chromaticity, _color_similarity, color_name, shape_name
from .report import warn
from .robot import PANDA, RobotDescription, robot_mask
from .tracking import default_tracker
from .transforms import pose_to_matrix
from .voxels import _connected_components, _euclidean_groups


@dataclass
class ObjectCluster:
    """One segmented object.

    ``points``/``colors``: its fused 3D points (base frame) and RGB (uint8); ``centroid``: their
    mean; ``center``: centre of the support-plane box (the box is extended down to the plane when
    the object rests on it, so this estimates the object's geometric centre); ``obb``: that box
    (axes: long side, short side, plane normal); ``obb_pca``: PCA box of the visible points;
    ``masks``: {camera: (H, W) bool}; ``point_camera``: index of the view each point came from,
    ``camera_origins``: those views' centres (for normals).

    Heights are metres above the support plane, along its normal: ``top`` the highest point,
    ``bottom`` the lowest one seen (at least the 5 mm cut for an object resting on the plane);
    ``height`` the object's own vertical size (the box's third side: from the plane to the top
    for a resting object, top minus bottom for a lifted one). ``dims``: the box's sides (long,
    short, vertical), m; ``size``: its volume, m^3 (sides counted as at least 1 cm).

    ``held``: the robot holds it, from evidence (``held_evidence``): the measured gripper stopped
    between open and closed, and the object is between or right beside the finger pads, or hangs
    lifted off the plane next to the TCP, or (with a tracker) moved with the TCP since the last
    observation. ``track_id``: its number for the whole episode when a tracker is in use (the
    names then stay those of the first sighting; ``seen_as`` is what this observation alone
    would have called it).
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
    top: float = 0.0
    held_evidence: dict = field(default_factory=dict)
    track_id: Optional[int] = None
    seen_as: str = ""

    @property
    def dims(self) -> np.ndarray:
        """The support-plane box's sides (long, short, vertical), m."""
        return self.obb.extents

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
        ident = f"#{self.id}" if self.track_id is None else f"#{self.id} track {self.track_id}"
        return (f"{ident} {self.color_name} {self.shape_name}{held} at ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}) "
                f"size {e[0]:.3f}x{e[1]:.3f}x{e[2]:.3f} m, top {self.top:.3f} m, {len(self.points)} pts")


@dataclass
class SceneSegmentation:
    """Result of `segment_scene`: the support plane, the objects (largest first), per-camera
    views and point bookkeeping, and timings in milliseconds."""

    plane: Plane
    objects: list
    views: list
    timings_ms: dict
    plane_masks: dict
    warnings: list = field(default_factory=list)
    unseen: list = field(default_factory=list)

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
        lines += [f"  unseen now: track {t.id} {t.color_name} {t.shape_name}, last at "
                  f"({t.center[0]:.3f}, {t.center[1]:.3f}, {t.center[2]:.3f})" for t in self.unseen]
        lines += ["  warning: " + w for w in self.warnings]
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


def _absorb_fragments(parts: list, P: np.ndarray, C: np.ndarray, voxel: float, reach: float = 2.0,
                      drop: bool = True) -> list:
    """After a colour split: a fragment (under 400 points and under 15 % of the largest piece)
    whose colour is the same as or next to that of a larger touching piece joins it (a shaded
    strip of an orange bowl inside a blue one is "brown", not another object); one under 150
    points that joins nothing is dropped (mixed pixels where two objects meet, not an object).
    ``reach``: how near (in voxels) counts as touching; ``drop``: whether lone small fragments go."""
    if len(parts) < 2:
        return parts
    sizes = [len(p) for p in parts]
    big = max(sizes)
    names = [color_name(C[p]) for p in parts]
    out = list(parts)
    for i in sorted(range(len(parts)), key=lambda k: sizes[k]):
        if not (sizes[i] < 400 and sizes[i] < 0.15 * big) or out[i] is None:
            continue
        best, bd = None, reach * voxel
        frag = P[out[i]]
        for j, other in enumerate(out):
            if j == i or other is None or len(other) <= sizes[i] or _color_similarity(names[i], names[j]) == 0.0:
                continue
            sub = P[other][:: max(1, len(other) // 4000)]
            d = float(np.min(np.linalg.norm(frag[:: max(1, len(frag) // 200), None, :] - sub[None, :, :], axis=2)))
            if d < bd:
                best, bd = j, d
        if best is not None:
            out[best] = np.concatenate([out[best], out[i]])
            out[i] = None
        elif drop and sizes[i] < 150:
            out[i] = None
    return [p for p in out if p is not None]


SLIVER_POINTS = 150
"""Held pieces smaller than this (points) join a piece within 2 cm of them (see `_merge_held`)."""


def _merge_held(pieces: list, P: np.ndarray, C: np.ndarray, view: CameraView, hand: HandGeometry
                ) -> tuple[list, list]:
    """Flag the pieces lying between the fingers and merge those of the same colour (a held
    object is cut into pieces where the fingers hide it; chromaticity, so that a shaded part of
    it counts as its colour); a small sliver seen between the pads (fewer than
    ``SLIVER_POINTS``, its colour unreliable in the fingers' shadow) joins the piece within 2 cm
    of it, the rest of the object the pads hold."""
    T = pose_to_matrix(view.ee_pose)
    half_open = 0.5 * gripper_to_width(view.gripper if view.gripper is not None else -1.0, hand)
    held, slivers = [], []
    for part in pieces:
        L = (P[part] - T[:3, 3]) @ T[:3, :3]
        inside = ((np.abs(L[:, 0]) < 0.04) & (np.abs(L[:, 1]) < half_open + 0.006)
                  & (L[:, 2] > -0.06) & (L[:, 2] < 0.05))
        held.append(bool(half_open > 0.003 and inside.mean() > 0.5))
        slivers.append(bool(inside.mean() > 0.5 and len(part) < SLIVER_POINTS))
    groups: dict = {}
    out, flags = [], []
    big = [p for p, sl in zip(pieces, slivers) if not sl]
    for part, h, sl in zip(pieces, held, slivers):
        if sl and big:
            # a sliver between the pads (the pads hide the rest of what they hold): part of the
            # piece within 2 cm of it, if any
            gaps = [float(np.sqrt(((P[part][:, None, :] - P[b][None, ::7, :]) ** 2).sum(-1)).min()) for b in big]
            if min(gaps) < 0.02:
                continue
        if h:
            name = color_name(C[part])
            if name in ("white", "grey"):
                # the guard around the fingertips showing through or beside the held object
                L = (P[part] - T[:3, 3]) @ T[:3, :3]
                r = np.hypot(L[:, 0], L[:, 2] + hand.envelope_behind_tcp)
                if np.mean(np.abs(r - hand.envelope_radius) < 0.004) > 0.8:
                    continue
            c = _chromaticity(C[part]).mean(axis=0)
            key = next((k for k in groups if float(np.hypot(*(np.asarray(k) - c))) < 0.06), tuple(c))
            groups.setdefault(key, []).append(part)
        else:
            out.append(part)
            flags.append(False)
    for parts in groups.values():
        out.append(np.concatenate(parts))
        flags.append(True)
    # the slivers skipped above join their nearest piece
    for part, sl in zip(pieces, slivers):
        if sl and big:
            gaps = [float(np.sqrt(((P[part][:, None, :] - P[o][None, ::7, :]) ** 2).sum(-1)).min()) for o in out]
            k = int(np.argmin(gaps))
            if gaps[k] < 0.02:
                out[k] = np.concatenate([out[k], part])
            else:
                out.append(part)
                flags.append(False)
    return out, flags


def segment_scene(observations: Union[Mapping[str, Any], Sequence[Any], CameraView],
                  cameras: Optional[Sequence[str]] = None, *, voxel: float = 0.006,
                  color_split: Optional[float] = 0.06, plane_threshold: float = 0.006,
                  min_height: float = 0.005, max_object_height: float = 0.35,
                  min_points: int = 40, max_depth: float = 2.5, ignore_hand: bool = True,
                  hand: HandGeometry = FRANKA_HAND, plane: Optional[Plane] = None,
                  grow_masks: bool = True, tracker: Any = "auto", robot: RobotDescription = PANDA
                  ) -> SceneSegmentation:
    """Segment the objects standing on the support plane.

    ``observations``: a raw ``get_state(..., raw=True)`` dict, a list of them, or CameraViews.
    Every camera with depth is used (``cameras`` restricts the names) and the clouds are fused.

    Steps: back-project -> RANSAC support plane (normal near base +z) -> keep points between
    ``min_height`` and 1 m above it, within the plane's footprint -> with ``ignore_hand`` (the
    self-filter switch), drop the points on the robot: the whole arm and hand posed from the
    measured ``joint``/``gripper`` of each view (`robo_perception.robot.robot_mask`), or without
    joints only the hand near ``ee_pose`` -> voxel grid of side ``voxel`` ->
    26-connected components over occupied voxels (Euclidean clustering) -> a cluster whose
    chromaticities (r, g shares, so shading does not matter) form several dense modes at least
    ``color_split`` apart is split by colour and re-clustered per colour (None: no split) ->
    clusters with fewer than ``min_points`` points, or reaching above ``max_object_height``
    (the arm), are dropped -> per cluster: masks, boxes, colour and shape names -> with
    ``grow_masks``, each image mask grows over the adjacent pixels of the object's colour that
    the height cut gave to the plane (a bowl's inner floor, the bottom millimetres of a side);
    the cluster's 3D points stay those above the cut -> ``held`` from evidence -> the support
    plane is checked for plausibility (tilted more than 8 deg, carried by few points, or more
    than 2 cm from the last one the tracker saw: a `PerceptionWarning`, also kept in
    ``scene.warnings``) -> with a tracker, identities and names carried over (see
    `robo_perception.tracking`). ``tracker``: "auto" (the file named by $R2G_PERCEPTION_TRACKS,
    as in the sandbox, else none), a `Tracker`, or None. ``robot``: the description the
    self-filter poses (`robo_perception.robot.PANDA` by default).
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
            # each observation carries the joints (or at least the hand pose) it was taken with
            sel = np.flatnonzero(keep & (pcam == ci))
            if v.joint is not None:  # self-filter: the whole robot, posed from the measured joints
                keep[sel[robot_mask(P[sel], v.joint, v.gripper, robot=robot)]] = False
            elif v.ee_pose is not None:  # fallback: the hand near the TCP only
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
                    parts = _absorb_fragments([g[sub] for sub in _euclidean_groups(Po[g], voxel, min_points, modes)],
                                              Po, Co, voxel)
            for part in parts:
                if float(ho[part].max()) > max_object_height:
                    continue  # reaches up out of the workspace of objects: the robot arm
                pieces.append(part)
    # a small piece of an object that something in front (a finger) cut off from the rest: it
    # joins a larger piece of a similar colour within 3 cm
    pieces = _absorb_fragments(pieces, Po, Co, voxel, reach=0.03 / voxel, drop=False)
    hand_view = next((v for v in views if v.ee_pose is not None), None)
    if ignore_hand and hand_view is not None and pieces:
        pieces, _ = _merge_held(pieces, Po, Co, hand_view, hand)
    for part in pieces:
        objects.append(_make_cluster(len(objects), Po[part], Co[part], ho[part], sel[part], pidx, pcam, views, plane))
    objects.sort(key=lambda o: -len(o.points))
    for k, o in enumerate(objects):
        o.id = k
    if grow_masks and objects:
        _grow_masks(objects, views, h, pidx, pcam, plane_threshold, min_height, color_split or 0.06)
    for o in objects:
        _held_evidence(o, hand_view, plane, hand)
    scene_warnings = _plane_warnings(plane, on_plane)
    t4 = time.perf_counter()
    timings = {"backproject": 1e3 * (t1 - t0), "plane": 1e3 * (t2 - t1), "filter": 1e3 * (t3 - t2),
               "cluster": 1e3 * (t4 - t3), "total": 1e3 * (t4 - t0)}
    scene = SceneSegmentation(plane=plane, objects=objects, views=views, timings_ms=timings,
                              plane_masks=plane_masks)
    if tracker == "auto":
        tracker = default_tracker()
    if tracker is not None:
        states = [observations] if isinstance(observations, Mapping) else (
            list(observations) if isinstance(observations, Sequence) else [])
        stamps = [float(s["timestamp"]) for s in states if isinstance(s, Mapping) and "timestamp" in s]
        prev = tracker.plane
        if prev is not None and stamps and tracker.time <= max(stamps):
            z_prev = -prev[3] / prev[2] if abs(prev[2]) > 1e-6 else 0.0
            if abs(plane.height_at_origin - z_prev) > 0.02:
                scene_warnings.append(f"the support plane (z0 = {plane.height_at_origin:.3f} m) is "
                                      f"{abs(plane.height_at_origin - z_prev) * 100:.1f} cm from the last one "
                                      f"(z0 = {z_prev:.3f} m): check the cameras' views before trusting objects")
        if not scene_warnings:
            tracker.plane = [*map(float, plane.normal), float(plane.offset)]
        tracker.update(scene, max(stamps) if stamps else None, hand_view.ee_pose if hand_view is not None else None)
    for w in scene_warnings:
        warn(w, scene)
    return scene


def _plane_warnings(plane: Plane, on_plane: np.ndarray) -> list:
    """Why the fitted support plane might not be the table: tilted, or carried by few points."""
    out = []
    tilt = math.degrees(math.acos(min(1.0, abs(float(plane.normal[2])))))
    if tilt > 8.0:
        out.append(f"the support plane is tilted {tilt:.0f} deg from horizontal (normal "
                   f"{np.round(plane.normal, 3).tolist()}, z0 = {plane.height_at_origin:.3f} m): probably not the "
                   "table (a camera facing sideways?); objects may be missing or wrong")
    frac = float(on_plane.mean()) if len(on_plane) else 0.0
    if frac < 0.05:
        out.append(f"only {100 * frac:.1f} % of the points lie on the support plane: the table may be out of view")
    return out


def _held_evidence(o: ObjectCluster, view: Optional[CameraView], plane: Plane, hand: HandGeometry) -> None:
    """Fill ``o.held_evidence`` and ``o.held`` from the measured gripper and the points near the
    pads (see ObjectCluster)."""
    ev: dict = {"gripper_closed_on_something": False, "between_pads": 0, "spans_gap": False,
                "lifted_near_tcp": False, "moves_with_tcp": None}
    o.held_evidence = ev
    o.held = False
    if view is None or view.ee_pose is None or view.gripper is None:
        return
    g = float(view.gripper)
    # the fingers left the fully open stop and did not meet: something may have stopped them
    ev["gripper_closed_on_something"] = bool(-0.92 < g < 0.97)
    T = pose_to_matrix(view.ee_pose)
    L = (o.points - T[:3, 3]) @ T[:3, :3]
    gap = gripper_to_width(g, hand)
    zone = ((np.abs(L[:, 0]) <= hand.finger_half_depth + 0.02) & (np.abs(L[:, 1]) <= 0.5 * gap + 0.012)
            & (L[:, 2] >= -0.07) & (L[:, 2] <= hand.tip_beyond_tcp + 0.02))
    ev["between_pads"] = int(zone.sum())
    # closed on it: what lies between the pads fills the gap they stopped at (a part-open
    # gripper around an object, not yet closed, leaves room on both sides)
    if ev["between_pads"] >= 5:
        y = L[zone, 1]
        ev["spans_gap"] = bool(float(y.max() - y.min()) >= gap - 0.006)
    near = float(np.min(np.linalg.norm(o.points - T[:3, 3], axis=1))) if len(o.points) else math.inf
    ev["lifted_near_tcp"] = bool(o.bottom > 0.012 and near < 0.04)
    o.held = bool(ev["gripper_closed_on_something"] and (ev["spans_gap"] or ev["lifted_near_tcp"]))


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
                         hollow=hollow, height=float(hh), bottom=float(h.min()), top=top, pixel_count=counts,
                         point_camera=pcam[gsel].copy(), camera_origins=np.array([v.origin for v in views]))
