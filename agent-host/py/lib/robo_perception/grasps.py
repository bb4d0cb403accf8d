"""Grasps: `Grasp`, the TCP rotation of a parallel-jaw grasp, the gripper's sweep and plane
clearance checks, and `propose_grasps` (top-down slices and antipodal normal pairs)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .geometry import Plane, estimate_normals
from .hand import FRANKA_HAND, HandGeometry, width_to_gripper
from .segmentation import ObjectCluster, SceneSegmentation
from .transforms import ArrayLike, axis_angle_to_matrix, matrix_to_pose, pose_to_matrix, rotation_distance
from .voxels import voxel_downsample


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
                   max_candidates: int = 20, antipodal: bool = True, seed: int = 0,
                   near: Optional[ArrayLike] = None, near_radius: float = 0.03,
                   closing: Optional[ArrayLike] = None, closing_tolerance_deg: float = 20.0) -> list[Grasp]:
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

    Steering: ``near`` (a base-frame point, m) keeps only grasps whose TCP lies within
    ``near_radius`` of it, measured along the support plane (a region: the rim nearest the
    robot, one end of a handle, the middle of a bar); ``closing`` (a base-frame direction) keeps
    only grasps whose fingers close along it, either sign, within ``closing_tolerance_deg``.
    Candidates are generated there and in that direction, so a steered call finds grasps an
    unsteered one would have ranked below its ``max_candidates``. An empty list means no grasp
    of the object satisfies the steering and the checks above.
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
                close_by = np.linalg.norm(o.points[:, :2] - obj.center[:2], axis=1) < 0.25
                if close_by.any():
                    obstacles.append(voxel_downsample(o.points[close_by], 0.004)[0])
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
    near_p = None
    if near is not None:
        near_p = np.asarray(near, dtype=float).reshape(3)
        if not np.all(np.isfinite(near_p)) or not near_radius > 0:
            raise ValueError(f"near must be a finite point and near_radius > 0 (got {near}, {near_radius})")
    close_d = None
    if closing is not None:
        close_d = np.asarray(closing, dtype=float).reshape(3)
        if not np.all(np.isfinite(close_d)) or np.linalg.norm(close_d) < 1e-9:
            raise ValueError(f"closing must be a finite non-zero direction (got {closing})")
        close_d = close_d / np.linalg.norm(close_d)
    cos_close = math.cos(math.radians(closing_tolerance_deg))

    def steered(T: np.ndarray) -> bool:
        if near_p is not None:
            r = T[:3, 3] - near_p
            if np.linalg.norm(r - np.dot(r, n) * n) > near_radius:
                return False
        return close_d is None or abs(float(np.dot(T[:3, 1], close_d))) >= cos_close

    def finish(T: np.ndarray, width: float, kind: str, score: float, details: dict) -> None:
        if not steered(T):
            return
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
    if near_p is not None:
        # sample the upper surface inside the region (and the region's centre) instead
        r = upper - near_p
        upper = upper[np.linalg.norm(r - np.outer(r @ n, n), axis=1) <= near_radius]
        centres.append(near_p - n * plane.distance(near_p))
    if len(upper):
        pick = rng.choice(len(upper), size=min(24, len(upper)), replace=False)
        centres += [p - n * plane.distance(p) for p in upper[pick]]
    base_dirs = [box.axes[:, 0], box.axes[:, 1]]
    if close_d is not None and np.linalg.norm(close_d - np.dot(close_d, n) * n) > 1e-6:
        base_dirs.insert(0, close_d)
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
