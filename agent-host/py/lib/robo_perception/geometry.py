"""Planes, boxes, normals: `Plane`, `OrientedBox`, PCA boxes, 2D convex hull and minimum-area
rectangle, boxes aligned with a support plane, RANSAC plane fitting and surface normals."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

from .transforms import ArrayLike
from .voxels import _NEIGHBOUR_OFFSETS_ALL, _lookup, _voxel_keys, _voxelize


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


def obb_in_plane(points: ArrayLike, plane: Plane, extend_to_plane: Union[bool, float] = 0.02,
                 bottom: Optional[float] = None) -> tuple[OrientedBox, float]:
    """Box aligned with a support plane: minimum-area rectangle of the points' footprint in the
    plane, and their height range above it.

    ``bottom``: where the box's bottom is, as a height above the plane (what the object stands
    on: 0 for the plane itself, another object's surface); it then replaces the lowest point.
    Without it, ``extend_to_plane``: if True, or a number and the lowest point is less than that
    far above the plane, the box is extended down to the plane (the underside of a resting
    object is never seen). Returns (box, fill) where fill = footprint hull area / rectangle area
    (about 1 for a box, pi/4 for a cylinder seen from above). Axes: (long side, short side, plane
    normal).
    """
    P = np.asarray(points, dtype=float)
    B = plane.basis()
    L = P @ B
    h = L[:, 2] + plane.offset  # height above the plane
    centre2, axes2, ext2, hull_area = min_area_rect(L[:, :2])
    hmin, hmax = float(h.min()), float(h.max())
    if bottom is not None:
        hmin = min(float(bottom), hmax)
    elif extend_to_plane is True or (extend_to_plane is not False and hmin < float(extend_to_plane)):
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
