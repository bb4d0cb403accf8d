"""Articulated parts: a hinged part's (door, lid) face, opening angle, hinge axis and outward
normal, and a sliding part's (drawer) travel, measured from RGB-D through `segment_scene`.

Entry points: `measure_hinged` -> `HingedPart`, `measure_sliding` -> `SlidingPart`; both take a
raw observation (or a list of them) or a `SceneSegmentation`. `fit_face` fits the vertical face
of one cluster (a door, a drawer front) on its own.

How a hinged part is measured: the part is a slab whose face is vertical; its horizontal line is
fitted to the cluster's points (RANSAC, then least squares), the face's ends are the hinge end
(nearest the fixed body it hangs on, e.g. the cabinet's carcass) and the free end. The angle is
measured against the body's own box: at the hinge corner of the body's footprint rectangle the two
side faces meet, one is the front the part covers when shut (``closed_normal``) and the other runs
along it (``closed_along``, from the hinge across the front). So the angle needs the body in view
once; later observations (the hand in front, the wrist camera up close) pass ``reference=`` that
first measurement: its hinge and shut frame are kept (fixtures do not move) and the angle is the
one whose board, swept about that hinge, holds most of the points in view, whatever the clusters.

A sliding part's front is the outermost face across its axis (the side of the body facing the
robot), its travel the front's distance out of the body's front (or moved since a reference).

Frames and units as everywhere in robo_perception: base frame, metres, radians (the angle also in
degrees). Heights (``bottom``, ``top``) are above the support plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Union

import numpy as np

from .report import warn
from .geometry import estimate_normals
from .segmentation import ObjectCluster, SceneSegmentation, segment_scene
from .transforms import ArrayLike

# A face point counts as on the fitted face within this distance (m): simulated depth is exact,
# a real camera's a few millimetres noisy; 4 mm keeps the top edge of an 18 mm board off the face.
FACE_TOLERANCE_M = 0.004
# Thickness used when neither the second face nor the top edge of the part is in view (m).
DEFAULT_THICKNESS_M = 0.018
# When no panel apart from a body is found, the views are segmented again with this finer colour
# split (segment_scene's default is 0.06): a blue-grey door on a grey carcass can fuse with it.
RESEGMENT_COLOR_SPLIT = 0.03


@dataclass
class PartFace:
    """The vertical face of a door, lid or drawer front, base frame.

    ``normal``: unit, horizontal, pointing away from the body (outwards); ``along``: unit,
    horizontal, in the face (for a hinged part from the hinge end towards the free end);
    ``center``: centre of the outer face; ``ends``: (2, 3) the outer face's two vertical edges at
    the support plane (for a hinged part: hinge end, free end); ``corners``: (4, 3) the outer
    face's corners (the ends at ``bottom`` and at ``top``); ``width``: horizontal size, m;
    ``bottom``, ``top``: heights above the support plane, m; ``thickness``: the slab's thickness
    (m) and ``thickness_source``: "second face", "top edge", "assumed", "reference" or "given";
    ``seen``: which face the cameras saw most of ("outer", "inner"; "unknown" when measured about
    a reference's hinge); ``inliers``: points on the fitted face."""

    center: np.ndarray
    normal: np.ndarray
    along: np.ndarray
    ends: np.ndarray
    corners: np.ndarray
    width: float
    bottom: float
    top: float
    thickness: float
    thickness_source: str
    seen: str
    inliers: int


@dataclass
class HingedPart:
    """A hinged part measured from RGB-D (base frame, metres).

    ``angle_deg`` / ``angle_rad``: how far it is open, 0 = shut, positive = open (it may read a
    degree or so below 0 when shut). ``hinge_point``: a point on the hinge axis, at the support
    plane (the hinge end of the part's inner face: overlay doors turn about that edge);
    ``hinge_axis``: unit, such that turning about it by a positive angle (right-hand rule) opens
    the part; ``outward_normal``: the normal of the outer face now (what you push on to close it
    faces this way; pushing it shut moves every point of it along ``-outward_normal``);
    ``closed_normal``: that normal when shut; ``closed_along``: from the hinge along the shut
    part; ``radius``: hinge axis to free edge, m; ``free_edge``: the free edge at the support
    plane; ``face``: the outer face (`PartFace`); ``part``, ``body``, ``handle``: the clusters
    used (``body``/``handle`` may be None); ``reference_used``: the closed frame came from an
    earlier measurement; ``details``: how each value was found."""

    angle_deg: float
    angle_rad: float
    hinge_point: np.ndarray
    hinge_axis: np.ndarray
    outward_normal: np.ndarray
    closed_normal: np.ndarray
    closed_along: np.ndarray
    radius: float
    free_edge: np.ndarray
    face: PartFace
    part: ObjectCluster
    body: Optional[ObjectCluster] = None
    handle: Optional[ObjectCluster] = None
    reference_used: bool = False
    details: dict = field(default_factory=dict)

    def normal_at(self, angle_deg: Optional[float] = None) -> np.ndarray:
        """The outer face's normal with the part at ``angle_deg`` (default: now)."""
        a = math.radians(self.angle_deg if angle_deg is None else angle_deg)
        return math.cos(a) * self.closed_normal - math.sin(a) * self.closed_along

    def point_at(self, r: float, height: float, angle_deg: Optional[float] = None, standoff: float = 0.0
                 ) -> np.ndarray:
        """Base-frame point on the outer face ``r`` m from the hinge axis (along the part) and
        ``height`` m above the support plane, with the part at ``angle_deg`` (default: now),
        moved ``standoff`` m out along that angle's outward normal. Following this point from one
        angle to another traces the arc the part sweeps (for a push that turns it)."""
        a = math.radians(self.angle_deg if angle_deg is None else angle_deg)
        along = math.cos(a) * self.closed_along + math.sin(a) * self.closed_normal
        return (self.hinge_point + r * along + (self.face.thickness + standoff) * self.normal_at(angle_deg)
                + height * self.hinge_axis_up)

    @property
    def hinge_axis_up(self) -> np.ndarray:
        """The hinge axis pointing up (away from the support plane)."""
        return self.hinge_axis if self.details.get("axis_sign", 1.0) > 0 else -self.hinge_axis

    def describe(self) -> str:
        h, n = self.hinge_point, self.outward_normal
        return (f"hinged part open {self.angle_deg:.1f} deg; hinge at ({h[0]:.3f}, {h[1]:.3f}), axis "
                f"({self.hinge_axis[0]:.2f}, {self.hinge_axis[1]:.2f}, {self.hinge_axis[2]:.2f}); outer face normal "
                f"({n[0]:.2f}, {n[1]:.2f}, {n[2]:.2f}), {self.radius:.3f} m wide, top {self.face.top:.3f} m"
                + ("" if self.body is not None or self.reference_used else
                   " (no body seen: angle unknown)" if math.isnan(self.angle_deg) else
                   " (no body seen: front= given, angle assumed <= 90 deg)"))


@dataclass
class SlidingPart:
    """A sliding part (drawer) measured from RGB-D (base frame, metres).

    ``travel_m``: how far it is out. With ``reference`` (an earlier measurement): how far its
    front moved out since then along ``axis``. Otherwise the gap between the front's back (inner)
    face and the body's front (an overlay front rests a few millimetres proud when shut, so this
    reads that much more than the slide's joint); 0.0 when the front is the body's own front face
    (both one box, as a shut drawer usually is: ``details`` says so); None with no body in view.
    ``axis``: unit, horizontal, the direction that pulls it out (the front's outward normal);
    ``front_from_body_m``: the outer face's distance in front of the body's front plane (None
    with a reference or no body); ``face``, ``part``, ``body``, ``handle``, ``details`` as for
    `HingedPart`."""

    travel_m: Optional[float]
    axis: np.ndarray
    front_from_body_m: Optional[float]
    face: PartFace
    part: ObjectCluster
    body: Optional[ObjectCluster] = None
    handle: Optional[ObjectCluster] = None
    details: dict = field(default_factory=dict)

    def describe(self) -> str:
        a = self.axis
        t = "unknown" if self.travel_m is None else f"{self.travel_m:.3f} m"
        return (f"sliding part out {t} along ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f}); front face centre "
                f"({self.face.center[0]:.3f}, {self.face.center[1]:.3f}, {self.face.center[2]:.3f}), "
                f"{self.face.width:.3f} m wide, top {self.face.top:.3f} m")


# ------------------------------------------------------------------------------------------
# Faces
# ------------------------------------------------------------------------------------------

@dataclass
class _Slab:
    """A fitted vertical face in plane coordinates: ``n2``/``u2`` unit 2D (normal, along),
    ``c``: line offset (n2 . xy = c), ``umin``/``umax``: its ends along u2, ``hmin``/``hmax``
    heights, ``second``: signed offset of a parallel second face (or None), ``top_side``: sign
    and size of the top edge's spread off the face (or None), ``inliers``: count, ``fraction``
    of the cluster's points on the face."""

    n2: np.ndarray
    u2: np.ndarray
    c: float
    umin: float
    umax: float
    hmin: float
    hmax: float
    second: Optional[float]
    top_spread: Optional[float]
    inliers: int
    fraction: float
    spread: float


def _plane_coords(points: np.ndarray, scene: SceneSegmentation) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xy in the plane basis (N, 2), height above the plane (N,), basis 3x3 columns e1, e2, up)."""
    B = scene.plane.basis()
    L = points @ B
    return L[:, :2], L[:, 2] + scene.plane.offset, B


def _fit_line(xy: np.ndarray, tol: float, rng: np.random.Generator, iterations: int = 300
              ) -> Optional[tuple[np.ndarray, float, np.ndarray]]:
    """RANSAC line through 2D points, refined by least squares: (unit normal, offset, inliers)."""
    if len(xy) < 20:
        return None
    S = xy[rng.choice(len(xy), size=min(3000, len(xy)), replace=False)]
    i = rng.integers(0, len(S), size=(iterations, 2))
    d = S[i[:, 1]] - S[i[:, 0]]
    ln = np.linalg.norm(d, axis=1)
    ok = ln > 0.02
    if not ok.any():
        return None
    d, base = d[ok] / ln[ok, None], S[i[ok, 0]]
    n = np.c_[-d[:, 1], d[:, 0]]
    c = np.einsum("ij,ij->i", n, base)
    counts = (np.abs(S @ n.T - c) < tol).sum(axis=0)
    k = int(np.argmax(counts))
    normal, off = n[k], float(c[k])
    for _ in range(3):
        inl = np.abs(xy @ normal - off) < tol
        if inl.sum() < 10:
            return None
        Q = xy[inl]
        mu = Q.mean(axis=0)
        _, _, vt = np.linalg.svd(Q - mu, full_matrices=False)
        normal = vt[1] if np.dot(vt[1], normal) >= 0 else -vt[1]
        off = float(np.dot(normal, mu))
    inl = np.abs(xy @ normal - off) < tol
    return normal, off, inl


def _fit_slab(points: np.ndarray, scene: SceneSegmentation, tol: float = FACE_TOLERANCE_M, seed: int = 0
              ) -> Optional[_Slab]:
    xy, h, _ = _plane_coords(points, scene)
    line = _fit_line(xy, tol, np.random.default_rng(seed))
    if line is None:
        return None
    n2, c, inl = line
    u2 = np.array([-n2[1], n2[0]])
    u = xy[inl] @ u2
    umin, umax = (float(v) for v in np.percentile(u, [0.5, 99.5]))
    hmin, hmax = (float(v) for v in np.percentile(h[inl], [0.5, 99.5]))
    s = xy @ n2 - c
    # a second, parallel face (both sides of a board in view): the densest 6 mm band 8-45 mm off
    second = None
    best = 0
    for sign in (1.0, -1.0):
        off = s * sign
        band = off[(off > 0.008) & (off < 0.045)]
        if len(band) < 50:
            continue
        hist, edges = np.histogram(band, bins=np.arange(0.008, 0.0455, 0.001))
        win = np.convolve(hist, np.ones(6, dtype=int), mode="valid")
        j = int(np.argmax(win))
        if win[j] > max(best, 0.15 * inl.sum()):
            sel = (off > edges[j]) & (off < edges[j] + 0.006)
            mu = float(np.median(off[sel]))
            uu = xy[sel] @ u2
            if np.ptp(uu) > 0.05 and np.ptp(h[sel]) > 0.05:
                best, second = int(win[j]), sign * mu
    # the top edge (seen from above): its points span the board's thickness
    top_spread = None
    near_top = (h > hmax - 0.01) & (np.abs(s) < 0.045)
    if near_top.sum() >= 20:
        lo, hi = np.percentile(s[near_top], [3, 97])
        if hi - lo > 0.006:
            top_spread = float(hi) if abs(hi) > abs(lo) else float(lo)
    spread = float(np.subtract(*np.percentile(np.abs(s), [95, 5])))
    return _Slab(n2=n2, u2=u2, c=c, umin=umin, umax=umax, hmin=hmin, hmax=hmax, second=second,
                 top_spread=top_spread, inliers=int(inl.sum()), fraction=float(inl.mean()), spread=spread)


def _is_panel(slab: Optional[_Slab]) -> bool:
    """A face of a door, lid or drawer front: mostly one vertical plane at least 8 x 6 cm, and thin
    (95 % of the points within 6 cm of it: a carcass or a block is not a panel)."""
    return (slab is not None and slab.fraction >= 0.35 and slab.umax - slab.umin >= 0.08
            and slab.hmax - slab.hmin >= 0.06 and slab.spread <= 0.06)


def _seen_side(part: ObjectCluster, n2: np.ndarray, c: float, scene: SceneSegmentation) -> float:
    """+1 when the cameras that saw most of the part look at its +n2 side, else -1."""
    origins = part.camera_origins
    if origins is None or len(origins) == 0:
        origins = np.array([v.origin for v in scene.views]) if scene.views else np.zeros((1, 3))
        votes = np.ones(len(origins))
    else:
        cams = part.point_camera if part.point_camera is not None else np.zeros(len(part.points), dtype=int)
        votes = np.bincount(cams, minlength=len(origins)).astype(float)
    B = scene.plane.basis()
    side = np.sign((np.asarray(origins, dtype=float) @ B)[:, :2] @ n2 - c)
    return 1.0 if float(np.dot(votes, side)) >= 0 else -1.0


def _face(part: ObjectCluster, slab: _Slab, outward2: np.ndarray, scene: SceneSegmentation,
          thickness: Optional[float]) -> tuple[PartFace, float, float]:
    """The outer face from a slab whose outward direction is ``outward2`` (2D, +-n2).
    Returns (face, outer offset along outward2, inner offset along outward2)."""
    sgn = 1.0 if np.dot(outward2, slab.n2) >= 0 else -1.0
    seen_off = sgn * slab.c
    if thickness is not None:
        t, source = float(thickness), "given"
    elif slab.second is not None:
        t, source = abs(slab.second), "second face"
    elif slab.top_spread is not None:
        t, source = abs(slab.top_spread), "top edge"
    else:
        t, source = DEFAULT_THICKNESS_M, "assumed"
    # which face was fitted: the rest of the board (second face, top edge) lies on its inner side
    # when it is the outer face; with neither, the side the cameras looked from
    other = slab.second if slab.second is not None else slab.top_spread
    if other is not None:
        seen_outer = sgn * other < 0
    else:
        seen_outer = _seen_side(part, slab.n2, slab.c, scene) * sgn > 0
    outer = seen_off if seen_outer else seen_off + t
    inner = outer - t
    B = scene.plane.basis()
    e1, e2, up = B[:, 0], B[:, 1], B[:, 2]
    n3 = sgn * (slab.n2[0] * e1 + slab.n2[1] * e2)
    u3 = slab.u2[0] * e1 + slab.u2[1] * e2
    origin = -scene.plane.offset * up          # the plane's point under the basis origin
    foot = origin + outer * n3
    ends = np.array([foot + slab.umin * u3, foot + slab.umax * u3])
    corners = np.array([ends[0] + slab.hmin * up, ends[1] + slab.hmin * up, ends[1] + slab.hmax * up,
                        ends[0] + slab.hmax * up])
    face = PartFace(center=corners.mean(axis=0), normal=n3, along=u3, ends=ends, corners=corners,
                    width=slab.umax - slab.umin, bottom=slab.hmin, top=slab.hmax, thickness=t,
                    thickness_source=source, seen="outer" if seen_outer else "inner", inliers=slab.inliers)
    return face, outer, inner


def fit_face(part: ObjectCluster, scene: SceneSegmentation, outward: Optional[ArrayLike] = None,
             thickness: Optional[float] = None) -> Optional[PartFace]:
    """The vertical face of one cluster (a door, a lid, a drawer front), or None when its points
    are not mostly one vertical plane at least 8 x 6 cm. ``outward``: which way the outer face
    points (a direction; default: towards the cameras that saw the part)."""
    slab = _fit_slab(part.points, scene)
    if not _is_panel(slab):
        return None
    assert slab is not None
    if outward is None:
        o2 = slab.n2 * _seen_side(part, slab.n2, slab.c, scene)
    else:
        B = scene.plane.basis()
        o2 = (np.asarray(outward, dtype=float) @ B)[:2]
    return _face(part, slab, o2, scene, thickness)[0]


# ------------------------------------------------------------------------------------------
# Choosing the part, the body and the handle
# ------------------------------------------------------------------------------------------

def _scene_of(obs: Any, scene_kwargs: Optional[Mapping[str, Any]]) -> SceneSegmentation:
    if isinstance(obs, SceneSegmentation):
        return obs
    return segment_scene(obs, **dict(scene_kwargs or {}))


def _candidates(scene: SceneSegmentation, part: Union[None, str, ObjectCluster]) -> list[ObjectCluster]:
    if isinstance(part, ObjectCluster):
        return [part]
    if isinstance(part, str):
        from .prompts import rank_objects
        return [o for o, _ in rank_objects(scene, part)]
    return sorted(scene.objects, key=lambda o: -len(o.points))


def _pick_part(scene: SceneSegmentation, part: Union[None, str, ObjectCluster], near: Optional[ArrayLike],
               hinge: Optional[np.ndarray] = None) -> Optional[tuple[ObjectCluster, _Slab]]:
    cands = _candidates(scene, part)
    fitted = []
    for o in cands:
        slab = _fit_slab(o.points, scene)
        if isinstance(part, ObjectCluster) or _is_panel(slab):
            if slab is not None:
                fitted.append((o, slab))
    if not fitted:
        return None
    if near is not None:
        p = np.asarray(near, dtype=float)
        return min(fitted, key=lambda f: float(np.min(np.linalg.norm(f[0].points[::20] - p, axis=1))))
    if hinge is not None:                     # the panel with an end at the reference's hinge
        h2 = (hinge @ scene.plane.basis())[:2]

        def gap(f: tuple) -> float:
            sl = f[1]
            ends = [sl.umin * sl.u2 + sl.c * sl.n2, sl.umax * sl.u2 + sl.c * sl.n2]
            return min(float(np.linalg.norm(e - h2)) for e in ends)
        return min(fitted, key=gap)
    if isinstance(part, str):
        return fitted[0]                      # the prompt's ranking
    return max(fitted, key=lambda f: f[1].inliers)


def _xy_distance(points: np.ndarray, p: np.ndarray, scene: SceneSegmentation) -> float:
    """Smallest distance along the plane from ``p`` to the points (a subsample)."""
    B = scene.plane.basis()
    Q = points[:: max(1, len(points) // 4000)] @ B
    return float(np.min(np.linalg.norm(Q[:, :2] - (p @ B)[:2], axis=1)))


def _part_and_body(scene: SceneSegmentation, part: Union[None, str, ObjectCluster], near: Optional[ArrayLike],
                   body: Union[None, str, ObjectCluster]) -> Optional[tuple]:
    """(part, its slab, body or None, the face's two ends at the plane (2, 3)) or None."""
    picked = _pick_part(scene, part, near)
    if picked is None:
        return None
    p, slab = picked
    ends3 = np.array([_point3(slab.umin * slab.u2 + slab.c * slab.n2, scene),
                      _point3(slab.umax * slab.u2 + slab.c * slab.n2, scene)])
    return p, slab, _pick_body(scene, p, ends3, body), ends3


def _pick_body(scene: SceneSegmentation, part: ObjectCluster, ends: np.ndarray,
               body: Union[None, str, ObjectCluster]) -> Optional[ObjectCluster]:
    if isinstance(body, ObjectCluster):
        return body
    cands = [o for o in _candidates(scene, body) if o is not part]
    best, best_key = None, None
    for o in cands:
        if o.dims[0] * o.dims[1] < 0.01:         # a handle or a small object, not a carcass
            continue
        d = min(_xy_distance(o.points, e, scene) for e in ends)
        if d > 0.04:
            continue
        # the largest footprint: a carcass seen in pieces (its inside through an open door) is
        # measured by its whole box, whose sides are the ones the part closes against
        key = -o.dims[0] * o.dims[1]
        if best_key is None or key < best_key:
            best, best_key = o, key
    return best


def _pick_handle(scene: SceneSegmentation, part: ObjectCluster, outward3: np.ndarray) -> Optional[ObjectCluster]:
    """A small cluster (a bar, a knob) standing off the part's ``outward3`` side within 8 cm."""
    best, best_d = None, 0.08
    for o in scene.objects:
        if o is part or o.dims[0] * o.dims[1] >= 0.01:
            continue
        if float(np.dot(o.centroid - part.centroid, outward3)) < 0.0:
            continue
        d = _xy_distance(part.points, o.centroid, scene)
        if d < best_d:
            best, best_d = o, d
    return best


def _body_axes(body: ObjectCluster, scene: SceneSegmentation) -> tuple[np.ndarray, np.ndarray, str]:
    """The body's two horizontal axes in plane coordinates (2D, unit) and how they were found:
    from the normals of its vertical faces (walls of a carcass, its inside through an open door:
    the dominant direction modulo 90 deg, which a partly seen body gives as well as a whole one),
    else its footprint box."""
    B = scene.plane.basis()
    A = body.obb.axes.T @ B
    a1 = A[0, :2] / np.linalg.norm(A[0, :2])
    P = body.points
    if len(P) > 20000:
        P = P[:: len(P) // 20000 + 1]
    origins = None
    if body.camera_origins is not None and body.point_camera is not None:
        cams = body.point_camera if len(P) == len(body.points) else body.point_camera[:: len(body.points) // 20000 + 1]
        origins = np.asarray(body.camera_origins, dtype=float)[cams]
    N, curv = estimate_normals(P, 0.01, origins)
    Nl = N @ B
    vert = (np.abs(Nl[:, 2]) < 0.3) & (curv < 0.02)
    if vert.sum() >= 100:
        z = np.exp(4j * np.arctan2(Nl[vert, 1], Nl[vert, 0])).sum()
        if abs(z) / vert.sum() > 0.8:
            psi = float(np.angle(z)) / 4.0
            cands = [np.array([math.cos(psi + k * math.pi / 2), math.sin(psi + k * math.pi / 2)]) for k in range(4)]
            e1 = max(cands, key=lambda e: float(np.dot(e, a1)))
            return e1, np.array([-e1[1], e1[0]]), "normals of its vertical faces"
    return a1, np.array([-a1[1], a1[0]]), "its footprint box"


def _body_frame(body: ObjectCluster, hinge_xy: np.ndarray, scene: SceneSegmentation
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """At the body footprint's corner nearest ``hinge_xy``: the corner (2D), the outward normals
    (2D) of its two side faces, and how the axes were found."""
    B = scene.plane.basis()
    a1, a2, how = _body_axes(body, scene)
    xy = (body.points @ B)[:, :2]
    p1, p2 = xy @ a1, xy @ a2
    lo1, hi1 = np.percentile(p1, [0.5, 99.5])
    lo2, hi2 = np.percentile(p2, [0.5, 99.5])
    h1, h2 = float(np.dot(hinge_xy, a1)), float(np.dot(hinge_xy, a2))
    c1 = hi1 if abs(h1 - hi1) < abs(h1 - lo1) else lo1
    c2 = hi2 if abs(h2 - hi2) < abs(h2 - lo2) else lo2
    s1 = 1.0 if c1 == hi1 else -1.0
    s2 = 1.0 if c2 == hi2 else -1.0
    return c1 * a1 + c2 * a2, s1 * a1, s2 * a2, how


def _to3(v2: np.ndarray, scene: SceneSegmentation) -> np.ndarray:
    B = scene.plane.basis()
    return v2[0] * B[:, 0] + v2[1] * B[:, 1]


def _point3(p2: np.ndarray, scene: SceneSegmentation) -> np.ndarray:
    """A plane point from its plane coordinates."""
    B = scene.plane.basis()
    return p2[0] * B[:, 0] + p2[1] * B[:, 1] - scene.plane.offset * B[:, 2]


# ------------------------------------------------------------------------------------------
# Hinged parts
# ------------------------------------------------------------------------------------------

def _about_hinge(scene: SceneSegmentation, ref: HingedPart, part: Union[None, str, ObjectCluster],
                 thickness: Optional[float]) -> Optional[HingedPart]:
    """The angle about a known hinge: of every angle the part could have, the one whose slab
    (the board between the hinge line and its thickness, out to its radius) holds most of the
    scene's points; then the line through those points. Needs no body and no whole cluster: the
    hand may hide part of the board, split it, or join it to the carcass in one cluster."""
    B = scene.plane.basis()
    if isinstance(part, ObjectCluster):
        objs = [part]
    elif isinstance(part, str):
        objs = _candidates(scene, part)
    else:
        objs = list(scene.objects)
    if not objs:
        warn("measure_hinged: nothing in view", scene)
        return None
    P = np.vstack([o.points for o in objs])
    owner = np.concatenate([np.full(len(o.points), k) for k, o in enumerate(objs)])
    L = P @ B
    h = L[:, 2] + scene.plane.offset
    hinge2 = (ref.hinge_point @ B)[:2]
    f2 = (ref.closed_normal @ B)[:2]
    w2 = (ref.closed_along @ B)[:2]
    f2, w2 = f2 / np.linalg.norm(f2), w2 / np.linalg.norm(w2)
    t = float(thickness) if thickness is not None else ref.face.thickness
    rel = L[:, :2] - hinge2
    rho = np.linalg.norm(rel, axis=1)
    keep = (rho > 0.04) & (rho < ref.radius + 0.01) & (h > ref.face.bottom + 0.01) & (h < ref.face.top + 0.005)
    if keep.sum() < 100:
        warn("measure_hinged: too few points near the reference's hinge", scene)
        return None
    rel, rho, idx = rel[keep], rho[keep], np.flatnonzero(keep)
    th = np.degrees(np.arctan2(rel @ f2, rel @ w2))
    # a point at polar (rho, th) lies in the slab of angle phi when 0 <= rho sin(th - phi) <= t
    lo = th - np.degrees(np.arcsin(np.clip((t + 0.003) / rho, 0, 1)))
    hi = th + np.degrees(np.arcsin(np.clip(0.001 / rho, 0, 1)))
    step = 0.25
    grid = np.arange(-10.0, 190.0 + step, step)
    i0 = np.clip(np.ceil((lo - grid[0]) / step).astype(int), 0, len(grid))
    i1 = np.clip(np.floor((hi - grid[0]) / step).astype(int) + 1, 0, len(grid))
    acc = np.zeros(len(grid) + 1)
    np.add.at(acc, i0, 1.0)
    np.add.at(acc, i1, -1.0)
    votes = np.cumsum(acc)[:-1]
    k = int(np.argmax(votes))
    if votes[k] < 100:
        warn(f"measure_hinged: no board about the reference's hinge (best {int(votes[k])} points)", scene)
        return None
    phi = math.radians(grid[k])
    inl = (rho * np.sin(np.radians(th) - phi) >= -0.001) & (rho * np.sin(np.radians(th) - phi) <= t + 0.003)
    Q = rel[inl]
    # refine: the line through the board's points (its direction), taken from the hinge side
    mu = Q.mean(axis=0)
    _, _, vt = np.linalg.svd(Q - mu, full_matrices=False)
    d2 = vt[0] if np.dot(vt[0], mu) >= 0 else -vt[0]
    ang = math.atan2(float(np.dot(d2, f2)), float(np.dot(d2, w2)))
    if abs(math.degrees(ang) - grid[k]) > 3.0:     # a refinement that wandered off is not one
        ang = phi
    along2 = math.cos(ang) * w2 + math.sin(ang) * f2
    n_out2 = math.cos(ang) * f2 - math.sin(ang) * w2
    a = Q @ along2
    reach = float(np.percentile(a, 99.5))
    hq = h[idx[inl]]
    bottom, top = (float(v) for v in np.percentile(hq, [0.5, 99.5]))
    up = B[:, 2]
    hinge3 = ref.hinge_point.copy()
    n3, u3 = _to3(n_out2, scene), _to3(along2, scene)
    ends = np.array([hinge3 + t * n3, hinge3 + t * n3 + ref.radius * u3])
    corners = np.array([ends[0] + bottom * up, ends[1] + bottom * up, ends[1] + top * up, ends[0] + top * up])
    face = PartFace(center=corners.mean(axis=0), normal=n3, along=u3, ends=ends, corners=corners,
                    width=ref.radius, bottom=bottom, top=top, thickness=t,
                    thickness_source="reference" if thickness is None else "given",
                    seen="unknown", inliers=int(inl.sum()))
    counts = np.bincount(owner[idx[inl]], minlength=len(objs))
    p = objs[int(np.argmax(counts))]
    details = {"frame": "from the reference measurement", "board_points": int(inl.sum()),
               "board_reach_m": round(reach, 3), "vote_deg": float(grid[k]), "axis_sign": ref.details.get("axis_sign", 1.0)}
    if reach < 0.6 * ref.radius:
        details["note"] = f"only {reach:.3f} m of the board seen (hidden or cut off)"
    return HingedPart(angle_deg=math.degrees(ang), angle_rad=ang, hinge_point=hinge3, hinge_axis=ref.hinge_axis.copy(),
                      outward_normal=n3, closed_normal=ref.closed_normal.copy(), closed_along=ref.closed_along.copy(),
                      radius=ref.radius, free_edge=ends[1], face=face, part=p, body=ref.body,
                      handle=None, reference_used=True, details=details)


def measure_hinged(obs: Any, part: Union[None, str, ObjectCluster] = None,
                   body: Union[None, str, ObjectCluster] = None, *, reference: Optional[HingedPart] = None,
                   front: Optional[ArrayLike] = None, near: Optional[ArrayLike] = None,
                   thickness: Optional[float] = None, scene_kwargs: Optional[Mapping[str, Any]] = None
                   ) -> Optional[HingedPart]:
    """Measure a hinged part (a door or lid on a vertical hinge) in an observation.

    ``obs``: a raw ``get_state(cameras, raw=True)`` dict, a list of them, or a
    `SceneSegmentation` (``scene_kwargs`` go to `segment_scene` when it runs here).
    ``part``: the part's cluster, a prompt ("blue door"), or None: the largest vertical panel in
    view (with ``near=(x, y, z)``: the one nearest that point). ``body``: what it hangs on (a
    cluster or a prompt; None: the largest object next to either vertical edge of the part).
    ``reference``: an earlier `HingedPart` of the same part; its hinge and closed frame are used
    (the body need not be in view). ``front``: the direction the shut part's outer face points
    (e.g. towards the robot, ``(-1, 0, 0)``): settles which side of the body is its front when
    the part is open more than 90 deg. ``thickness``: the part's thickness when known (m).

    Returns None when no panel is found (a `PerceptionWarning` says why).
    """
    scene = _scene_of(obs, scene_kwargs)
    if reference is not None:
        return _about_hinge(scene, reference, part, thickness)
    details: dict = {}
    found = _part_and_body(scene, part, near, body)
    if (found is None or found[2] is None) and not isinstance(part, ObjectCluster) and scene.views:
        # a door of a colour close to its carcass's may come out in one cluster with it: split finer
        finer = segment_scene(scene.views, color_split=RESEGMENT_COLOR_SPLIT, tracker=None, plane=scene.plane)
        again = _part_and_body(finer, part, near, body)
        if again is not None and (found is None or again[2] is not None):
            found, scene = again, finer
            details["segmentation"] = f"split again by colour ({RESEGMENT_COLOR_SPLIT}): the part was not apart from its body"
    if found is None:
        warn("measure_hinged: no vertical panel (door, lid) in view"
             + (f" matching {part!r}" if isinstance(part, str) else ""), scene)
        return None
    p, slab, b, ends3 = found
    details.update(face_points=slab.inliers, face_fraction=round(slab.fraction, 3))
    B = scene.plane.basis()
    end_a, end_b = slab.umin * slab.u2 + slab.c * slab.n2, slab.umax * slab.u2 + slab.c * slab.n2
    up = B[:, 2]
    f2 = w2 = None
    # which end is the hinge: the end nearer the body, else the end farther from the handle
    handle = _pick_handle(scene, p, _to3(slab.n2, scene))
    if handle is None:
        handle = _pick_handle(scene, p, -_to3(slab.n2, scene))
    knob = None
    if handle is None:                      # a handle seen as part of the panel: points standing off it
        xy = _plane_coords(p.points, scene)[0]
        off = np.abs(xy @ slab.n2 - slab.c)
        prot = (off > 0.03) & (off < 0.08)
        if prot.sum() >= 30 and np.ptp(xy[prot] @ slab.u2) < 0.1:
            knob = xy[prot].mean(axis=0)
    da = _xy_distance(b.points, ends3[0], scene) if b is not None else math.inf
    db = _xy_distance(b.points, ends3[1], scene) if b is not None else math.inf
    if b is not None and abs(da - db) > 0.015:
        hinge_is_a = da < db
        details["hinge_end"] = f"nearer the body ({min(da, db):.3f} m vs {max(da, db):.3f} m)"
    elif handle is not None or knob is not None:
        hc = (handle.centroid @ B)[:2] if handle is not None else knob
        hinge_is_a = np.linalg.norm(end_a - hc) > np.linalg.norm(end_b - hc)
        details["hinge_end"] = "farther from the handle"
    else:
        if b is not None:               # the free end stands farther out of the body's box
            bc = (b.obb.center @ B)[:2]
            hinge_is_a = np.linalg.norm(end_a - bc) <= np.linalg.norm(end_b - bc)
        else:
            hinge_is_a = True
        details["hinge_end"] = "nearer the body's centre (both ends about as near the body: uncertain)"
        warn("measure_hinged: cannot tell the hinge end of the part from its free end (it is about shut, "
             "or no body is in view); pass reference= from an earlier measurement", scene)
    hinge_end, free_end = (end_a, end_b) if hinge_is_a else (end_b, end_a)
    d2 = free_end - hinge_end
    d2 = d2 / max(np.linalg.norm(d2), 1e-9)
    # the fitted line's direction is more precise than the two ends
    d2 = slab.u2 if np.dot(slab.u2, d2) >= 0 else -slab.u2

    front2 = None
    if front is not None:
        front2 = (np.asarray(front, dtype=float) @ B)[:2]
        front2 = front2 / max(np.linalg.norm(front2), 1e-9)
    if b is not None:
        corner, a1, a2, how = _body_frame(b, hinge_end, scene)
        details["body_axes"] = how
        hyps = []
        for f_, s_ in ((a1, a2), (a2, a1)):
            w_ = -s_
            ang = math.degrees(math.atan2(float(np.dot(d2, f_)), float(np.dot(d2, w_))))
            hyps.append((ang, f_, w_))
        valid = [h for h in hyps if -10.0 <= h[0] <= 180.0] or hyps
        if front2 is not None:
            ang, f2, w2 = max(valid, key=lambda h: float(np.dot(h[1], front2)))
            details["frame"] = "body box at the hinge corner; front chosen by front="
        else:
            ang, f2, w2 = min(valid, key=lambda h: abs(h[0]))
            details["frame"] = ("body box at the hinge corner" if len(valid) == 1 else
                                "body box at the hinge corner; of two readings the smaller angle")
        details["body_corner"] = _point3(corner, scene)
    elif front2 is not None:
        f2 = front2
        w2 = np.array([f2[1], -f2[0]])
        if np.dot(w2, d2) < 0:
            w2 = -w2
        details["frame"] = "no body in view: front= given, the angle assumed <= 90 deg"
    else:
        warn("measure_hinged: no body in view and no front= or reference=: the angle is unknown (NaN); "
             "the outward normal is the side the cameras saw", scene)
        details["frame"] = "none: no body, no front=, no reference="
    if f2 is None or w2 is None:
        nan3 = np.full(3, np.nan)
        o2 = slab.n2 * _seen_side(p, slab.n2, slab.c, scene)
        face, outer, inner = _face(p, slab, o2, scene, thickness)
        return HingedPart(angle_deg=math.nan, angle_rad=math.nan, hinge_point=_point3(hinge_end, scene),
                          hinge_axis=nan3, outward_normal=face.normal, closed_normal=nan3, closed_along=nan3,
                          radius=face.width, free_edge=_point3(free_end, scene), face=face, part=p, body=None,
                          handle=handle, details=details)
    ang = math.atan2(float(np.dot(d2, f2)), float(np.dot(d2, w2)))
    n_out2 = math.cos(ang) * f2 - math.sin(ang) * w2
    face, outer, inner = _face(p, slab, n_out2, scene, thickness)
    # the hinge axis: through the inner face's hinge end
    sgn = 1.0 if np.dot(n_out2, slab.n2) >= 0 else -1.0
    hinge_on_inner = hinge_end + (inner - sgn * slab.c) * sgn * slab.n2
    hinge_point = _point3(hinge_on_inner, scene)
    # right-hand rule: turning closed_along towards closed_normal opens it; that axis is w x f
    w3, f3 = _to3(w2, scene), _to3(f2, scene)
    axis = np.cross(w3, f3)
    axis /= np.linalg.norm(axis)
    details["axis_sign"] = float(np.sign(np.dot(axis, up)) or 1.0)
    free3 = _point3(free_end + (outer - sgn * slab.c) * sgn * slab.n2, scene)
    radius = float(np.linalg.norm(((free3 - hinge_point) @ B)[:2]))
    details.update(thickness_source=face.thickness_source, seen=face.seen)
    return HingedPart(angle_deg=math.degrees(ang), angle_rad=ang, hinge_point=hinge_point, hinge_axis=axis,
                      outward_normal=face.normal, closed_normal=f3, closed_along=w3, radius=radius,
                      free_edge=free3, face=face, part=p, body=b, handle=handle, details=details)


# ------------------------------------------------------------------------------------------
# Sliding parts
# ------------------------------------------------------------------------------------------

def _front_band(points: np.ndarray, normals: np.ndarray, axis2: np.ndarray, B: np.ndarray
                ) -> Optional[tuple[float, np.ndarray]]:
    """The outermost face across ``axis2`` (2D) at least 8 cm wide and 6 cm tall: its offset
    along the axis and the mask of its points."""
    Nl = normals @ B
    L = points @ B
    facing = np.abs(Nl[:, :2] @ axis2) > 0.95
    if facing.sum() < 50:
        return None
    sv = L[:, :2] @ axis2
    u2 = np.array([-axis2[1], axis2[0]])
    order = np.argsort(-sv[facing])
    idx = np.flatnonzero(facing)[order]
    tried = set()
    for i in idx[:: max(1, len(idx) // 400)]:
        key = round(float(sv[i]) / 0.004)
        if key in tried:
            continue
        tried.add(key)
        band = facing & (np.abs(sv - sv[i]) < FACE_TOLERANCE_M)
        if band.sum() < 100:
            continue
        u = L[band, :2] @ u2
        h = L[band, 2]
        if np.ptp(np.percentile(u, [1, 99])) >= 0.08 and np.ptp(np.percentile(h, [1, 99])) >= 0.06:
            return float(np.median(sv[band])), band
    return None


def measure_sliding(obs: Any, part: Union[None, str, ObjectCluster] = None,
                    body: Union[None, str, ObjectCluster] = None, *, axis: Optional[ArrayLike] = None,
                    reference: Optional[SlidingPart] = None, thickness: Optional[float] = None,
                    scene_kwargs: Optional[Mapping[str, Any]] = None) -> Optional[SlidingPart]:
    """Measure a sliding part (a drawer) in an observation: its front's face, the direction it
    pulls out and how far it is out.

    ``body``: the carcass it runs in (a cluster or a prompt; None: of the objects at least
    10 x 10 cm, the one reaching farthest back from the robot: a carcass is at least as deep as
    its drawer). ``axis``: the direction it pulls out (default: the side of the body's box facing
    the robot base, found from the normals of its vertical faces). ``part``: restricts the front
    to that cluster (a cluster or a prompt); None: the outermost face across the axis, at least
    8 x 6 cm, of any object overlapping the body's width (a handle is smaller). ``reference``: an
    earlier `SlidingPart` of the same drawer: the travel is then how far the front moved out
    since (same axis). Returns None when no front is found (a `PerceptionWarning` says why).
    """
    scene = _scene_of(obs, scene_kwargs)
    B = scene.plane.basis()
    details: dict = {}
    objs = [o for o in scene.objects if o.dims[0] * o.dims[1] >= 0.01]
    if isinstance(body, ObjectCluster):
        b: Optional[ObjectCluster] = body
    elif isinstance(body, str):
        b = next(iter(_candidates(scene, body)), None)
    elif reference is not None and axis is None:
        ax2 = (reference.axis @ B)[:2]
        b = min(objs, key=lambda o: float(np.min((o.points @ B)[:, :2] @ ax2)), default=None)
    else:
        b = None
    if axis is not None:
        a = np.asarray(axis, dtype=float).reshape(-1)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"measure_sliding: axis must be 3 finite numbers (base frame), got {axis!r}")
        ax2 = (a @ B)[:2]
        if np.linalg.norm(ax2) < 1e-6:
            raise ValueError(f"measure_sliding: axis {axis!r} has no direction along the table's plane "
                             "(a drawer slides along it: give the direction it pulls out)")
        details["axis"] = "axis= given"
    elif reference is not None:
        ax2 = (reference.axis @ B)[:2]
        details["axis"] = "from the reference"
    else:
        big = b if b is not None else (max(objs, key=lambda o: o.dims[0] * o.dims[1]) if objs else None)
        if big is None:
            warn("measure_sliding: no object of 10 x 10 cm or more in view (the body of a drawer)", scene)
            return None
        a1, a2, how = _body_axes(big, scene)
        to_base = -(big.obb.center @ B)[:2]
        ax2 = max((a1, -a1, a2, -a2), key=lambda a: float(np.dot(a, to_base)))
        details["axis"] = f"the side of the body facing the robot base ({how})"
    ax2 = ax2 / np.linalg.norm(ax2)
    if b is None:
        b = min(objs, key=lambda o: float(np.min((o.points @ B)[:, :2] @ ax2)), default=None)
    u2 = np.array([-ax2[1], ax2[0]])
    if isinstance(part, (ObjectCluster, str)):
        cands = [part] if isinstance(part, ObjectCluster) else _candidates(scene, part)[:1]
    else:
        lo_u = hi_u = None
        if b is not None:
            bu = (b.points @ B)[:, :2] @ u2
            lo_u, hi_u = np.percentile(bu, [1, 99])
        cands = []
        for o in scene.objects:
            ou = (o.points @ B)[:, :2] @ u2
            if lo_u is None or min(hi_u, ou.max()) - max(lo_u, ou.min()) > 0.05:
                cands.append(o)
    if not cands:
        warn("measure_sliding: no drawer front in view" + (f" matching {part!r}" if isinstance(part, str) else ""),
             scene)
        return None
    P = np.vstack([o.points for o in cands])
    owner = np.concatenate([np.full(len(o.points), k) for k, o in enumerate(cands)])
    origins = []
    for o in cands:
        if o.camera_origins is not None and o.point_camera is not None:
            origins.append(np.asarray(o.camera_origins, dtype=float)[o.point_camera])
        else:
            origins.append(np.tile(np.mean([v.origin for v in scene.views], axis=0) if scene.views
                                   else np.zeros(3), (len(o.points), 1)))
    N, _ = estimate_normals(P, 0.01, np.vstack(origins))
    found = _front_band(P, N, ax2, B)
    if found is None:
        warn("measure_sliding: no face across the drawer's axis at least 8 x 6 cm in view", scene)
        return None
    front, band = found
    counts = np.bincount(owner[band], minlength=len(cands))
    p = cands[int(np.argmax(counts))]
    L = P[band] @ B
    uu, hh = L[:, :2] @ u2, L[:, 2]
    umin, umax = (float(v) for v in np.percentile(uu, [0.5, 99.5]))
    hmin, hmax = (float(v) for v in np.percentile(hh, [0.5, 99.5]))
    # the board's thickness: the top edge behind the face, seen from above
    Lp = P @ B
    sv = Lp[:, :2] @ ax2
    near_top = (Lp[:, 2] > hmax - 0.01) & (sv < front + 0.002) & (sv > front - 0.045) & \
        (Lp[:, :2] @ u2 > umin) & (Lp[:, :2] @ u2 < umax)
    if thickness is not None:
        t, source = float(thickness), "given"
    elif near_top.sum() >= 20 and front - float(np.percentile(sv[near_top], 3)) > 0.006:
        t, source = front - float(np.percentile(sv[near_top], 3)), "top edge"
    else:
        t, source = DEFAULT_THICKNESS_M, "assumed"
    # whether the cameras saw the outer face: the face's points' normals point along the axis
    seen_outer = float(np.median((N[band] @ B)[:, :2] @ ax2)) > 0
    outer = front if seen_outer else front + t      # the outer face stands a board in front of the inner
    ax3 = _to3(ax2, scene)
    u3 = _to3(u2, scene)
    up = B[:, 2]
    foot = _point3(outer * ax2, scene)
    ends = np.array([foot + umin * u3, foot + umax * u3])
    corners = np.array([ends[0] + hmin * up, ends[1] + hmin * up, ends[1] + hmax * up, ends[0] + hmax * up])
    face = PartFace(center=corners.mean(axis=0), normal=ax3, along=u3, ends=ends, corners=corners,
                    width=umax - umin, bottom=hmin, top=hmax, thickness=t, thickness_source=source,
                    seen="outer" if seen_outer else "inner", inliers=int(band.sum()))
    travel: Optional[float] = None
    front_from_body: Optional[float] = None
    if reference is not None:
        travel = outer - float(np.dot((reference.face.center @ B)[:2], ax2))
        details["travel"] = "the front's move along the axis since the reference"
    elif b is not None:
        bs = (b.points @ B)[:, :2] @ ax2
        body_front = float(np.percentile(bs, 99.5))
        if p is b or body_front > outer - t * 1.5:
            travel, front_from_body = 0.0, 0.0
            details["travel"] = ("the front is the body's own front face (one box): read as shut; a drawer out "
                                 "less than about its front's thickness may read so too")
        else:
            front_from_body = outer - body_front
            travel = front_from_body - t
            details["travel"] = "the front's distance out of the body's front, less the front's thickness"
    else:
        details["travel"] = "no body in view and no reference"
    return SlidingPart(travel_m=travel, axis=ax3, front_from_body_m=front_from_body, face=face, part=p, body=b,
                       handle=_pick_handle(scene, p, ax3), details=details)


__all__ = ["PartFace", "HingedPart", "SlidingPart", "fit_face", "measure_hinged", "measure_sliding",
           "FACE_TOLERANCE_M", "DEFAULT_THICKNESS_M"]
