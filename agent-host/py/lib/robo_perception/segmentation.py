"""Segmentation: `ObjectCluster`, `SceneSegmentation` and `segment_scene` (support plane, height
cut, hand exclusion, Euclidean clustering, colour split, held objects, per-cluster boxes and
names, mask growing)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from .camera import CameraView, depth_to_points, project_points, views_from_state
from .geometry import OrientedBox, Plane, fit_plane_ransac, min_area_rect, obb_in_plane, obb_pca
from .hand import FRANKA_HAND, HandGeometry, gripper_to_width
from .naming import _chromaticity, _color_similarity, color_name, shape_name
from .report import warn
from .robot import PANDA, RobotDescription, robot_distance, robot_mask
from .tracking import default_tracker
from .transforms import pose_to_matrix
from .voxels import _connected_components, _euclidean_groups, _voxel_keys


STALE_S = 0.25
"""A view whose image is older than its joints by more than this (s) is left out: two frame
periods of a 10 Hz camera and its latency; a frame of the settled state is never older."""


@dataclass
class ObjectCluster:
    """One segmented object.

    ``points``/``colors``: its fused 3D points (base frame) and RGB (uint8); ``centroid``: their
    mean; ``center``: centre of the support-plane box (the box reaches down to what the object
    stands on, so this estimates the object's geometric centre); ``obb``: that box (axes: long
    side, short side, plane normal); ``obb_pca``: PCA box of the visible points; ``masks``:
    {camera: (H, W) bool}; ``point_camera``: index of the view each point came from,
    ``point_pixel``: its pixel there (v * W + u); ``camera_origins``: those views' centres (for
    normals).

    Heights are metres above the support plane, along its normal: ``top`` the highest point
    seen; ``lowest_seen`` the lowest point seen (never below the 5 mm cut over the plane);
    ``bottom`` the box's bottom: 0 when the object stands on the plane, the surface of the object
    it stands on (``support``), or its lowest point seen when nothing is under it (held up,
    lifted). ``support``: "plane", the ``id`` of the object it rests on in this scene, or None.
    ``height`` the box's vertical side (top minus bottom). ``dims``: the box's sides (long,
    short, vertical), m; ``size``: its volume, m^3 (sides counted as at least 1 cm).

    ``held``: the robot holds it, from evidence (``held_evidence``): the gripper closed on
    something and stopped short of shut ("holding"), and the object fills the gap between the
    pads, or hangs lifted off its support next to the TCP. ``in_contact``: its nearest point seen
    is within 1 cm of the robot's shapes. ``pushed`` (with a tracker): it moved more than 1 cm
    since the last observation while not held then nor now. ``track_id``: its number for the
    whole episode when a tracker is in use (the names then stay those of the first sighting;
    ``seen_as`` is what this observation alone would have called it).
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
    lowest_seen: float = 0.0
    support: Optional[Union[int, str]] = None
    in_contact: bool = False
    pushed: bool = False
    point_pixel: Optional[np.ndarray] = None

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
        flags = [w for w, on in (("held", self.held), ("pushed", self.pushed),
                                 ("in contact", self.in_contact and not self.held)) if on]
        flag = f" ({', '.join(flags)})" if flags else ""
        ident = f"#{self.id}" if self.track_id is None else f"#{self.id} track {self.track_id}"
        on = {"plane": "on the table", None: "nothing under it"}.get(self.support, f"on #{self.support}")  # type: ignore[arg-type]
        return (f"{ident} {self.color_name} {self.shape_name}{flag} at ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}) "
                f"size {e[0]:.3f}x{e[1]:.3f}x{e[2]:.3f} m, top {self.top:.3f} m, bottom {self.bottom:.3f} m "
                f"({on}), {len(self.points)} pts")


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


PATCH_SHARE = 0.4
"""A colour piece joins a touching piece of the same cluster when at least this share of its
outline runs on along that piece's surface without a step in depth (see
`_join_surface_patches`)."""


def _join_surface_patches(split: list, P: np.ndarray, pix: np.ndarray, cam: np.ndarray, views: list,
                          voxel: float) -> list:
    """Joins colour pieces that depth shows to be one surface: ``split`` is [(cluster, point
    indices)] after the colour split. A piece A joins a piece B of the same cluster when

    * most of A's voxels (over half) are B's too: the same surface, coloured differently by the
      two cameras or the light; or
    * A is a patch in B's surface: where their pixels meet, the surface runs on without a step
      in depth (3D gap under 6 mm plus 3 pixel footprints) for at least `PATCH_SHARE` of A's
      outline (the outline against what does not cover A), and nowhere does one stand in front
      of the other. A shadow on a door, a shaded face of a block, a painted patch: no height
      above the surface they lie on. A block on a plate, a handle on its door stand in front of
      what is behind them, and stay apart.

    Decided by depth, never by colour. Returns the pieces, joined."""
    n = len(split)
    if n < 2:
        return split
    group = np.array([gi for gi, _ in split])
    if len(np.unique(group)) == n:
        return split
    lab = np.full(len(P), -1, dtype=np.int64)
    for k, (_, part) in enumerate(split):
        lab[part] = k
    cont = np.zeros(n * n)
    front = np.zeros(n * n)
    border = np.zeros(n)
    for ci, v in enumerate(views):
        m = (cam == ci) & (lab >= 0)
        if not m.any():
            continue
        H, W = v.shape
        L = np.full(H * W, -1, dtype=np.int64)
        L[pix[m]] = lab[m]
        X = np.zeros((H * W, 3))
        X[pix[m]] = P[m]
        Z = np.asarray(v.depth, dtype=float).ravel()
        Z = np.where(np.isfinite(Z) & (Z > 0.0), Z, np.inf)
        fx = float(v.intrinsics["fx"])
        ys, xs = np.divmod(pix[m], W)
        y0, y1, x0, x1 = max(0, ys.min() - 1), min(H, ys.max() + 2), max(0, xs.min() - 1), min(W, xs.max() + 2)
        idx = np.arange(H * W).reshape(H, W)[y0:y1, x0:x1]
        for p, q in ((idx[:, :-1].ravel(), idx[:, 1:].ravel()), (idx[:-1, :].ravel(), idx[1:, :].ravel())):
            for a, b in ((p, q), (q, p)):
                A = L[a]
                k = np.flatnonzero((A >= 0) & (L[b] != A))
                a, b, A = a[k], b[k], A[k]
                Bl = L[b]
                za, zb = Z[a], Z[b]
                tau = 0.006 + 3.0 * za / fx
                ok = ~(zb < za - tau)                     # b does not cover a
                border += np.bincount(A[ok], minlength=n)
                k = np.flatnonzero(ok & (Bl >= 0))
                if not len(k):
                    continue
                pair = A[k] * n + Bl[k]
                near = np.linalg.norm(X[a[k]] - X[b[k]], axis=1) < tau[k]
                cont += np.bincount(pair[near], minlength=n * n)
                front += np.bincount(pair[~near & (za[k] < zb[k])], minlength=n * n)
    cont = cont.reshape(n, n)
    front = front.reshape(n, n)
    # shared voxels
    keys = [np.unique(_voxel_keys(np.floor(P[part] / voxel).astype(np.int64))) for _, part in split]
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    sizes = [len(part) for _, part in split]
    for a in sorted(range(n), key=lambda i: sizes[i]):
        best, score = None, 0.0
        for b in range(n):
            if b == a or group[b] != group[a]:
                continue
            shared = float(np.isin(keys[a], keys[b], assume_unique=True).mean()) if len(keys[a]) else 0.0
            c = cont[a, b] + cont[b, a]
            patch = (cont[a, b] >= 8 and cont[a, b] >= PATCH_SHARE * border[a]
                     and front[a, b] + front[b, a] <= 2 + 0.05 * c)
            sc = max(shared if shared > 0.5 else 0.0, cont[a, b] / max(border[a], 1.0) if patch else 0.0)
            if sc > score:
                best, score = b, sc
        if best is not None:
            parent[root(a)] = root(best)
    out: dict = {}
    for k, (gi, part) in enumerate(split):
        out.setdefault(root(k), (gi, []))[1].append(part)
    return [(gi, np.concatenate(parts)) for gi, parts in out.values()]


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
                  grow_masks: bool = True, tracker: Any = "auto", robot: RobotDescription = PANDA,
                  stale_s: Optional[float] = STALE_S) -> SceneSegmentation:
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
    pieces that depth shows to be one surface are joined again (`_join_surface_patches`: a
    shadow or a shaded face is no height above the surface it lies on) -> clusters with fewer
    than ``min_points`` points, or reaching above ``max_object_height`` (the arm), are dropped ->
    pieces of one object kept apart by something in front are joined (`_join_across_occlusion`)
    -> parts standing off a thin vertical slab (a handle on a door) become objects of their own
    (`_peel_slabs`) -> held pieces cut by the fingers are merged -> per cluster: masks, boxes,
    colour and shape names -> with ``grow_masks``, each image mask grows over the adjacent
    pixels of the object's colour that the height cut gave to the plane (a bowl's inner floor,
    the bottom millimetres of a side); the cluster's 3D points stay those above the cut ->
    ``held`` and ``in_contact`` from evidence -> what each object stands on, its box refitted
    from there (`_assign_supports`) -> the support plane is checked for plausibility (tilted more than 8 deg, carried by few points, or more
    than 2 cm from the last one the tracker saw: a `PerceptionWarning`, also kept in
    ``scene.warnings``) -> with a tracker, identities and names carried over (see
    `robo_perception.tracking`). ``tracker``: "auto" (the file named by $R2G_PERCEPTION_TRACKS,
    as in the sandbox, else none), a `Tracker`, or None. ``robot``: the description the
    self-filter poses (`robo_perception.robot.PANDA` by default). ``stale_s``: a view whose
    image was taken more than this many seconds before its joints were measured is left out
    (the robot may have moved in between, and the self-filter poses it from those joints), with
    a `PerceptionWarning`; when every view is that old they are all kept, with a warning that
    robot parts may be reported as objects. None: never.
    """
    t0 = time.perf_counter()
    views = views_from_state(observations, cameras)
    views, view_warnings = _drop_stale(views, stale_s)
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
        split: list = []
        for gi, g in enumerate(_euclidean_groups(Po, voxel, min_points)):
            parts = [g]
            if color_split is not None:
                modes = _color_modes(chroma[g], color_split, min_points)
                if modes is not None:
                    parts = _absorb_fragments([g[sub] for sub in _euclidean_groups(Po[g], voxel, min_points, modes)],
                                              Po, Co, voxel)
            split += [(gi, part) for part in parts]
        # colour told apart what depth says is one surface (a shadow, a shaded face): joined
        split = _join_surface_patches(split, Po, pidx[sel], pcam[sel], views, voxel)
        for _, part in split:
            if float(ho[part].max()) > max_object_height:
                continue  # reaches up out of the workspace of objects: the robot arm
            pieces.append(part)
    # a small piece of an object that something in front (a finger) cut off from the rest: it
    # joins a larger piece of a similar colour within 3 cm
    pieces = _absorb_fragments(pieces, Po, Co, voxel, reach=0.03 / voxel, drop=False)
    # pieces of one object that something in front keeps apart (a finger before a block's face,
    # a door's two faces each seen by one camera), then parts standing off a door
    pieces = _join_across_occlusion(pieces, Po, Co, views, voxel)
    pieces = _peel_slabs(pieces, Po, plane, voxel, min_points)
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
        _held_evidence(o, hand_view, plane, hand, robot if ignore_hand else None)
    _assign_supports(objects, plane, views)
    for o in objects:
        _lifted_is_off_its_support(o)
    scene_warnings = view_warnings + _plane_warnings(plane, on_plane)
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


RESTING_M = 0.009
"""An object whose lowest point seen is at most this high (m; the 5 mm cut plus a few
millimetres) stands on the plane."""
HIDDEN_BOTTOM_M = 0.02
"""An object nothing holds whose lowest point seen is below this (m) rests on the plane with its
lowest centimetre hidden (by a neighbour, the fingers)."""
SUPPORT_TOLERANCE_M = 0.006
"""How far an object's lowest point seen may lie below the surface of the object under it (m):
the surfaces are seen from different angles, the pixels on their outlines read either one."""
SUPPORT_HIDDEN_M = 0.012
"""How far above that surface it may lie (m): the bottom edge hidden by the object's own rim."""
CONTACT_M = 0.01
"""An object whose nearest point seen is this close to the robot's shapes is `in_contact` (m)."""


def _fit_box(P: np.ndarray, h: np.ndarray, plane: Plane, bottom: float) -> tuple:
    """The support-plane box from ``bottom`` (height above the plane) to the top, its fill,
    whether the object is hollow, and its shape name."""
    box, fill = obb_in_plane(P, plane, bottom=bottom)
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
        thin_fill = _outline_roundness(np.stack([ring[:, 0], ring[:, 2]], axis=1))
    shape = shape_name(box.extents, fill, hollow, thin_fill)
    if shape not in ("bar", "panel", "plate") and _standing_slab(P, plane):
        shape = "panel"     # a slab on edge seen with something in front of its foot or face
    return box, fill, hollow, shape


def _outline_roundness(xy: np.ndarray) -> float:
    """For a slab standing on edge, its outline in its own plane: the fill ratio of its hull in its
    rectangle (about pi/4 for a disc), raised to 1 when at least three of the rectangle's corners
    hold points (a rectangle with a part hidden is not round; a disc with its foot hidden in a
    rack fills two)."""
    _, axes, ext, area = min_area_rect(xy)
    fill = area / max(float(ext[0] * ext[1]), 1e-12)
    if ext[0] < 1e-6 or ext[1] < 1e-6:
        return fill
    c = np.asarray(xy, dtype=float) @ axes
    lo, hi = c.min(axis=0), c.max(axis=0)
    k = 0.12 * (hi - lo)
    corners = 0
    for sx in (0, 1):
        for sy in (0, 1):
            inx = (c[:, 0] <= lo[0] + k[0]) if sx == 0 else (c[:, 0] >= hi[0] - k[0])
            iny = (c[:, 1] <= lo[1] + k[1]) if sy == 0 else (c[:, 1] >= hi[1] - k[1])
            corners += int(np.any(inx & iny))
    return 1.0 if corners >= 3 else fill


def _slab_fit(P: np.ndarray, plane: Plane, tolerance: float = 0.012) -> Optional[tuple]:
    """A thin slab standing on the plane (a door, a side wall): the vertical plane through the
    points' thinnest horizontal direction. Returns (unit normal (3,), offset, share of the points
    within ``tolerance`` of it, width, height of those), or None for fewer than 200 points."""
    if len(P) < 200:
        return None
    Q = P[:: max(1, len(P) // 4000)]
    B = plane.basis()
    xy = Q @ B[:, :2]
    h = Q @ B[:, 2] + plane.offset
    mu = xy.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((xy - mu).T))
    d = (xy - mu) @ vecs[:, 0]
    centre = float(np.median(d))
    near = np.abs(d - centre) <= tolerance
    if not near.any():
        return None
    along = (xy[near] - mu) @ vecs[:, 1]
    width = float(np.percentile(along, 99) - np.percentile(along, 1))
    tall = float(np.percentile(h[near], 99) - np.percentile(h[near], 1))
    normal = B[:, :2] @ vecs[:, 0]
    offset = float(centre + mu @ vecs[:, 0])      # normal . p = offset on the slab's mid plane
    return normal, offset, float(near.mean()), width, tall


def _standing_slab(P: np.ndarray, plane: Plane) -> bool:
    """A thin vertical slab whatever sticks to it: 90 % of the points within 1.2 cm of one
    vertical plane, the slab at least 8 cm wide and 8 cm tall."""
    f = _slab_fit(P, plane)
    return f is not None and f[2] >= 0.9 and f[3] >= 0.08 and f[4] >= 0.08


def _peel_slabs(pieces: list, P: np.ndarray, plane: Plane, voxel: float, min_points: int) -> list:
    """A piece that is mostly a standing slab (a door: 80 % of its points in one vertical layer
    at most 2.5 cm thick, its densest face and the other face when the cameras saw both, 60 %
    within 4 mm of those faces, 8 cm wide and tall) gives up what stands more than 6 mm off that layer (1.2 cm when one face
    is seen) as pieces of their own: a handle on its posts, which the light can make the door's
    colour."""
    out = []
    for part in pieces:
        f = _slab_fit(P[part], plane, 0.03) if len(part) >= 500 else None
        if f is None or f[3] < 0.08 or f[4] < 0.08:
            out.append(part)
            continue
        normal, offset = f[0], f[1]
        d = P[part] @ normal - offset
        hist, edges = np.histogram(d, bins=np.arange(-0.06, 0.0605, 0.002))
        pair = hist[:-1] + hist[1:]                     # two bins: 4 mm layers
        m1 = int(np.argmax(pair))
        if pair[m1] < 0.25 * len(part):
            out.append(part)            # no dense face: a round side, not a slab
            continue
        centre = edges[m1 + 1]
        lo_d = hi_d = centre
        need = max(200.0, 0.005 * len(part))

        def valley(k: int) -> float:
            a, b = sorted((k, m1))
            return float(np.median(pair[a + 1:b])) if b - a > 1 else 0.0
        other = [k for k in range(len(pair)) if 4 <= abs(k - m1) <= 12 and pair[k] >= need
                 and pair[k] >= pair[max(k - 1, 0)] and pair[k] >= pair[min(k + 1, len(pair) - 1)]
                 and pair[k] >= 2.0 * valley(k)]
        for k in other:
            lo_d, hi_d = min(lo_d, edges[k + 1]), max(hi_d, edges[k + 1])
        slack = 0.006 if other else 0.012
        outside = (d < lo_d - slack) | (d > hi_d + slack)
        faces = np.abs(d[:, None] - np.array([centre] + [edges[k + 1] for k in other])[None, :]).min(axis=1)
        if outside.mean() > 0.2 or np.mean(faces <= 0.004) < 0.6:
            out.append(part)            # not thin: a cup's round side, a box
            continue
        off = np.flatnonzero(outside)
        if len(off) < min_points:
            out.append(part)
            continue
        taken = np.zeros(len(part), dtype=bool)
        for g in _euclidean_groups(P[part[off]], voxel, min_points):
            out.append(part[off[g]])
            taken[off[g]] = True
        out.append(part[~taken])
    return out


def _join_across_occlusion(pieces: list, P: np.ndarray, C: np.ndarray, views: list, voxel: float,
                           max_gap: float = 0.025) -> list:
    """Joins two pieces of the same (or a related) colour name whose nearest points are more than
    1.5 voxels (not touching) and at most ``max_gap`` apart when no camera sees through the gap between them: every point of it lies
    behind a surface in every view that sees it (a finger in front of a block's face, the two
    faces of a door each seen by one camera); up to 2.4 times as far for two pieces of the same
    colour name of 1000 points or more (a door cut in two by the hand in front of it); a sliver
    (under `SLIVER_POINTS`: an edge in shade, whose colour says little) of any colour. Two objects with room between them that a camera sees stay apart."""
    if len(pieces) < 2:
        return pieces
    names = [color_name(C[p]) for p in pieces]
    parent = list(range(len(pieces)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def hidden(x: np.ndarray) -> bool:
        seen_by = np.zeros(len(x), dtype=bool)
        for v in views:
            uv, z = project_points(x, v.intrinsics, v.base_from_camera)
            H, W = v.shape
            u, w = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            inside = (z > 0) & (u >= 0) & (u < W) & (w >= 0) & (w < H)
            if not inside.any():
                continue
            D = np.asarray(v.depth, dtype=float)[w[inside], u[inside]]
            D = np.where(np.isfinite(D) & (D > 0), D, np.inf)
            if np.any(D > z[inside] + 0.005):
                return False                            # this camera looks through the gap
            seen_by[inside] = True
        return bool(seen_by.all())

    for i in range(len(pieces)):
        Pi = P[pieces[i]][:: max(1, len(pieces[i]) // 400)]
        for j in range(i + 1, len(pieces)):
            # a sliver's colour says little (an edge in shade); it joins across a short hidden gap
            sliver = min(len(pieces[i]), len(pieces[j])) < SLIVER_POINTS
            if root(i) == root(j) or (_color_similarity(names[i], names[j]) < 0.4 and not sliver):
                continue
            # two large pieces of one colour: a hand in front can hide a wider strip of a door
            gap_max = 2.4 * max_gap if (names[i] == names[j] and min(len(pieces[i]), len(pieces[j])) >= 1000) \
                else max_gap
            Pj = P[pieces[j]][:: max(1, len(pieces[j]) // 2000)]
            lo = np.maximum(Pi.min(axis=0), Pj.min(axis=0))
            hi = np.minimum(Pi.max(axis=0), Pj.max(axis=0))
            if np.any(lo - hi > gap_max):
                continue
            d2 = ((Pi[:, None, :] - Pj[None, :, :]) ** 2).sum(-1)
            k = int(np.argmin(d2))
            a, b = Pi[k // d2.shape[1]], Pj[k % d2.shape[1]]
            gap = float(np.sqrt(d2.flat[k]))
            if gap > gap_max or gap < 1.5 * voxel:
                continue        # touching pieces the colour split parted are `_join_surface_patches`'s
            t = np.linspace(0.15, 0.85, 7)[:, None]
            if hidden(a + t * (b - a)):
                parent[root(i)] = root(j)
    out: dict = {}
    for k, part in enumerate(pieces):
        out.setdefault(root(k), []).append(part)
    return [np.concatenate(v) for v in out.values()]


def _make_cluster(k: int, P: np.ndarray, C: np.ndarray, h: np.ndarray, gsel: np.ndarray, pidx: np.ndarray,
                  pcam: np.ndarray, views: list, plane: Plane, bottom: Optional[float] = None) -> ObjectCluster:
    """One object from its points. ``bottom``: the box's bottom (height above the plane); None:
    the plane when the lowest point seen is within `RESTING_M` of it, else that point."""
    masks, counts = {}, {}
    for ci, v in enumerate(views):
        m = np.zeros(v.shape[0] * v.shape[1], dtype=bool)
        s = pcam[gsel] == ci
        m[pidx[gsel][s]] = True
        masks[v.name] = m.reshape(v.shape)
        counts[v.name] = int(s.sum())
    lowest = float(h.min())
    support: Optional[Union[int, str]] = None
    if bottom is None:
        support = "plane" if lowest <= RESTING_M else None
        bottom = 0.0 if support == "plane" else lowest
    box, fill, hollow, shape = _fit_box(P, h, plane, bottom)
    pca = obb_pca(P)
    return ObjectCluster(id=k, points=P, colors=C, centroid=P.mean(axis=0), center=box.center, obb=box,
                         obb_pca=pca, color_name=color_name(C), shape_name=shape, masks=masks, fill=fill,
                         hollow=hollow, height=float(box.extents[2]), bottom=float(bottom), top=float(h.max()),
                         pixel_count=counts, point_camera=pcam[gsel].copy(), point_pixel=pidx[gsel].copy(),
                         camera_origins=np.array([v.origin for v in views]), lowest_seen=lowest, support=support)


def _set_bottom(o: ObjectCluster, plane: Plane, bottom: float, support: Optional[Union[int, str]]) -> None:
    """Refit ``o``'s box from ``bottom`` up (what it stands on was found), and its names."""
    h = plane.distance(o.points)
    box, fill, hollow, shape = _fit_box(o.points, h, plane, bottom)
    o.obb, o.center, o.fill, o.hollow, o.shape_name = box, box.center, fill, hollow, shape
    o.height, o.bottom, o.support = float(box.extents[2]), float(bottom), support


def _surface_under(o: ObjectCluster, s: ObjectCluster, plane: Plane) -> Optional[float]:
    """Height of ``s``'s surface under ``o`` (m above the plane), when ``o``'s centre lies over
    ``s``'s footprint and ``s`` shows points there no higher than ``o``'s lowest point (its top
    around ``o``, or the floor beside it in a container); else None."""
    c = s.obb.to_local(o.center[None])[0]
    if np.any(np.abs(c[:2]) > 0.5 * s.obb.extents[:2]):
        return None
    L = o.obb.to_local(s.points)
    grow = 0.015
    near = np.all(np.abs(L[:, :2]) <= 0.5 * o.obb.extents[:2] + grow, axis=1)
    if near.sum() < 10:
        return None
    h = plane.distance(s.points[near])
    below = h <= o.lowest_seen + SUPPORT_TOLERANCE_M
    if below.sum() < 10:
        return None
    return float(np.percentile(h[below], 90))


def _give_outline(s: ObjectCluster, o: ObjectCluster, plane: Plane, views: Sequence[CameraView]) -> None:
    """``o`` rests on ``s``: the points ``s`` has inside ``o``'s footprint (3 mm around it) and
    more than 1 mm above ``s``'s surface there are ``o``'s (pixels on its outline whose colour
    blends both); they move to ``o``, so that ``s`` keeps its own top and box."""
    L = o.obb.to_local(s.points)
    inside = np.all(np.abs(L[:, :2]) <= 0.5 * o.obb.extents[:2] + 0.003, axis=1)
    move = inside & (plane.distance(s.points) > o.bottom + 0.001)
    if not move.any() or move.all():
        return
    keep = ~move
    for name in ("points", "colors", "point_camera", "point_pixel"):
        a, b = getattr(s, name), getattr(o, name)
        if a is None or b is None:
            continue
        setattr(o, name, np.concatenate([b, a[move]]))
        setattr(s, name, a[keep])
    if s.point_camera is not None and s.point_pixel is not None:
        for ci, v in enumerate(views):
            sel = o.point_camera[-int(move.sum()):] == ci
            px = o.point_pixel[-int(move.sum()):][sel]
            if v.name in s.masks and len(px):
                s.masks[v.name].ravel()[px] = False
                o.masks[v.name].ravel()[px] = True
            s.pixel_count[v.name] = int((s.point_camera == ci).sum())
            o.pixel_count[v.name] = int((o.point_camera == ci).sum())
    h = plane.distance(s.points)
    s.top, s.lowest_seen, s.centroid = float(h.max()), float(h.min()), s.points.mean(axis=0)
    o.top, o.centroid = float(plane.distance(o.points).max()), o.points.mean(axis=0)
    _set_bottom(s, plane, s.bottom, s.support)


def _assign_supports(objects: list, plane: Plane, views: Sequence[CameraView]) -> None:
    """What each object stands on: the highest object surface under it that its lowest point
    reaches (within `SUPPORT_TOLERANCE_M` below, `SUPPORT_HIDDEN_M` above), else the plane when
    its lowest point is there (or, nothing holding it, within `HIDDEN_BOTTOM_M`), else nothing.
    Boxes are refitted from there, so none reaches through what it stands on; the supports'
    own boxes are their own points' (something resting on them adds nothing)."""
    for o in objects:
        best = None
        for s in objects:
            if s is o or s.held or s.lowest_seen > o.lowest_seen:
                continue
            surf = _surface_under(o, s, plane)
            if surf is None or surf > float(s.top) + 1e-6 or (o.lowest_seen <= RESTING_M and surf < RESTING_M):
                continue    # (an object down on the table next to a surface as low is on the table)
            if -SUPPORT_TOLERANCE_M <= o.lowest_seen - surf <= SUPPORT_HIDDEN_M and (best is None or surf > best[0]):
                best = (surf, s.id)
        if best is not None:
            _set_bottom(o, plane, best[0], best[1])
            _give_outline(next(s for s in objects if s.id == best[1]), o, plane, views)
        elif o.lowest_seen <= RESTING_M or (not o.held and o.lowest_seen < HIDDEN_BOTTOM_M):
            if o.support != "plane":
                _set_bottom(o, plane, 0.0, "plane")
        elif o.support is not None:
            _set_bottom(o, plane, o.lowest_seen, None)


def _drop_stale(views: list, stale_s: Optional[float]) -> tuple[list, list]:
    """The views whose image is not much older than their joints, and warnings about the rest
    (see `segment_scene`)."""
    if stale_s is None:
        return views, []
    old = [v for v in views if v.image_time is not None and v.state_time is not None
           and v.state_time - v.image_time > stale_s]
    if not old:
        return views, []
    ages = ", ".join(f"{v.name} {v.state_time - v.image_time:.2f} s" for v in old)
    fresh = [v for v in views if v not in old]
    if fresh:
        return fresh, [f"camera images older than the joints they came with ({ages}): the robot may have moved "
                       f"since, so those views are left out; observe again for them"]
    return views, [f"every camera image is older than the joints it came with ({ages}): the robot may have "
                   f"moved since, and parts of it may be reported as objects; observe again"]


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


def _held_evidence(o: ObjectCluster, view: Optional[CameraView], plane: Plane, hand: HandGeometry,
                   robot: Optional[RobotDescription] = None) -> None:
    """Fill ``o.held_evidence``, ``o.held`` and ``o.in_contact`` from the gripper's state, the
    measured gripper and the points near the pads (see ObjectCluster)."""
    ev: dict = {"grasp_status": None, "gripper_closed_on_something": False, "between_pads": 0, "spans_gap": False,
                "lifted_near_tcp": False, "robot_gap_m": None, "moves_with_tcp": None, "moved_m": None}
    o.held_evidence = ev
    o.held = False
    o.in_contact = False
    if view is None:
        return
    if view.joint is not None and len(o.points):
        gap_m = float(robot_distance(o.points, view.joint, view.gripper, robot or PANDA, exact_within=0.05).min())
        ev["robot_gap_m"] = gap_m
        o.in_contact = gap_m <= CONTACT_M
    if view.ee_pose is None or view.gripper is None:
        return
    g = float(view.gripper)
    ev["grasp_status"] = view.grasp
    # the fingers closed on something and stopped short of shut: the gripper says so when the
    # observation carries its state; otherwise only the measured opening is known (between open
    # and shut), which cannot tell fingers stopped by an object from fingers commanded part-open
    # ("unknown": the gripper has not reported yet, which says nothing either way)
    if view.grasp is not None and view.grasp != "unknown":
        ev["gripper_closed_on_something"] = view.grasp == "holding"
    else:
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
    ev["lifted_near_tcp"] = bool(o.lowest_seen > 0.012 and near < 0.04)
    o.held = bool(ev["gripper_closed_on_something"] and (ev["spans_gap"] or ev["lifted_near_tcp"]))


def _lifted_is_off_its_support(o: ObjectCluster) -> None:
    """An object `_held_evidence` took as held only because it is up near the TCP is not
    held when it stands on something (another object, or the plane): raised off the table is not
    lifted when something holds it up (a block on a plate beside the closed hand)."""
    ev = o.held_evidence
    if o.held and not ev.get("spans_gap") and o.support is not None \
            and o.lowest_seen - o.bottom <= SUPPORT_TOLERANCE_M:
        ev["lifted_near_tcp"] = False
        ev["resting_on"] = o.support
        o.held = False


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


