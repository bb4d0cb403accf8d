"""`r2g reconstruct`'s shapes for objects no single primitive fits, checked against free space.

The source cameras do not only see surfaces: every depth pixel also says that the ray from the
camera to that surface passed through empty space. `FreeSpace` answers, for points of the world,
whether some source view saw through them. With it:

* `decompose`: a convex hull of an object's fused points is accepted when no view saw through
  it; otherwise its points are cut in two by the plane (along the world axes and the points'
  principal axes, at several positions) that leaves the least seen-empty space inside the two
  halves' hulls, and each half is checked again, down to a minimum part size. Each accepted part
  is a box when it fills its oriented bounding box, else a convex mesh. A mug's handle hole, a
  rack's slots or the wedge under a slanted peg are seen empty by the side views, so the hulls
  that would close them are cut.
* `container_fit`: an open-topped round body (a cup, a mug without its handle) found by a robust
  circle fit of the points seen from outside, whose middle is seen empty: a floor disc and wall
  boxes like the bowls, with whatever lies outside the circle (a handle) decomposed as above.
* `box_container_fit`: the same for an open-topped rectangular body (a bin, a tray): walls on
  the outline of its minimum-area rectangle, nothing standing inside them, its middle seen empty.
* `disc_fit`: a flat cloud standing on edge (a plate in a rack) whose outline in its own plane is
  a circle: a cylinder whose axis is the cloud's normal.

Everything is deterministic (no random sampling). Thin parts seen from one side only get a
minimum thickness (`MIN_THICK_M`), added on both sides of the seen surface.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np

MIN_THICK_M = 0.004
"""A part thinner than this (a board or a divider seen from one side) is thickened to it."""
EMPTY_MARGIN_M = 0.004
EMPTY_MARGIN_REL = 0.005
"""A point counts as seen empty when it lies at least this far (plus this fraction of the
depth, for sensor noise) in front of the surface a view saw along the same ray."""
NOISE_MARGIN_SIGMAS = 3.0
"""With measured depth noise, the margin grows by this many of its standard deviations."""
EMPTY_TOL_M3 = 0.4e-6
"""A hull is accepted when the seen-empty space inside it is under 0.4 cm^3."""
MAX_DECOMPOSE_M3 = 0.01
"""Objects whose hull is larger than 10 litres (cabinets, a microwave: furniture, which without
the optional model stays a static piece anyway) are not cut into parts; it would cost minutes."""
MIN_PART_POINTS = 30
SUBSAMPLE = 1200
"""Cuts are chosen on at most about this many of a part's points."""
MAX_PARTS = 32
VOXELS = 12000
"""At most about this many sample points per hull for the free-space test."""


class FreeSpace:
    """The space the source views saw through. `views`: objects with ``depth`` (H, W metres,
    NaN where unknown, e.g. the robot's pixels), ``intrinsics`` {fx, fy, cx, cy} and
    ``base_from_camera`` (4x4)."""

    def __init__(self, views: list, noise_m: float = 0.0) -> None:
        from scipy.ndimage import minimum_filter

        # A depth with noise of standard deviation `noise_m` (along the rays) says less: the
        # margin grows by NOISE_MARGIN_SIGMAS of it.
        self.margin = EMPTY_MARGIN_M + NOISE_MARGIN_SIGMAS * max(0.0, float(noise_m))
        self.cams = []
        for v in views:
            d = np.nan_to_num(np.asarray(v.depth, dtype=np.float64), nan=0.0, posinf=0.0)
            # The nearest surface within one pixel: a point on an object's outline is not called
            # empty because its pixel happens to fall on the background; unknown (0) wins.
            dn = minimum_filter(d, size=3, mode="nearest")
            T = np.asarray(v.base_from_camera, dtype=float)
            K = v.intrinsics
            self.cams.append((T[:3, :3], T[:3, 3], float(K["fx"]), float(K["fy"]), float(K["cx"]), float(K["cy"]), dn))

    def empty(self, P: np.ndarray) -> np.ndarray:
        """(N,) bool: some view saw a surface farther along the ray through the point."""
        out = np.zeros(len(P), dtype=bool)
        for R, t, fx, fy, cx, cy, dn in self.cams:
            Pc = (P - t) @ R
            z = Pc[:, 2]
            ok = z > 0.05
            u = np.full(len(P), -1, dtype=np.int64)
            v = np.full(len(P), -1, dtype=np.int64)
            u[ok] = np.rint(fx * Pc[ok, 0] / z[ok] + cx).astype(np.int64)
            v[ok] = np.rint(fy * Pc[ok, 1] / z[ok] + cy).astype(np.int64)
            H, W = dn.shape
            ok &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
            d = np.zeros(len(P))
            d[ok] = dn[v[ok], u[ok]]
            out |= ok & (d > 0) & (z < d - self.margin - EMPTY_MARGIN_REL * d)
        return out


# --------------------------------------------------------------------------------------------
# Hulls and their sample points
# --------------------------------------------------------------------------------------------

def thicken(P: np.ndarray) -> np.ndarray:
    """Points whose principal extent along their thinnest axis is under MIN_THICK_M get copies
    moved out along that axis so the set is that thick."""
    if len(P) < 3:
        return P
    c = P.mean(0)
    _, _, Vt = np.linalg.svd(P - c, full_matrices=False)
    n = Vt[-1]
    s = (P - c) @ n
    ext = float(s.max() - s.min())
    if ext >= MIN_THICK_M:
        return P
    mid = (s.max() + s.min()) / 2
    half = MIN_THICK_M / 2
    base = P - np.outer(s - mid, n)
    return np.concatenate([base + half * n, base - half * n])


def hull_of(P: np.ndarray) -> Optional[Any]:
    from scipy.spatial import ConvexHull, QhullError

    try:
        return ConvexHull(thicken(P))
    except (QhullError, ValueError):
        return None


INSIDE_CHUNK = 1_000_000
"""`inside` tests points against the hull's faces in chunks of at most about this many
point-face pairs, so its memory stays bounded (tens of MB) whatever the number of points."""


def inside(hull: Any, X: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    eq = hull.equations
    X = np.asarray(X, dtype=float)
    rows = max(1, INSIDE_CHUNK // max(1, len(eq)))
    out = np.empty(len(X), dtype=bool)
    for k in range(0, len(X), rows):
        out[k:k + rows] = (X[k:k + rows] @ eq[:, :3].T + eq[:, 3] <= tol).all(axis=1)
    return out


GRID_FACTOR = 4
"""The grid laid over a hull's box has at most this many times `VOXELS` points."""


def _grid_axes(lo: np.ndarray, hi: np.ndarray, step: float) -> list:
    return [np.arange(a + step / 2, b, step) if b - a > step else np.array([(a + b) / 2]) for a, b in zip(lo, hi)]


def samples_in(hull: Any, max_n: int = VOXELS) -> tuple[np.ndarray, float]:
    """A regular grid of points inside the hull (deterministic), and the cell volume: about
    `max_n` points inside, never more than GRID_FACTOR * max_n in the box the grid is laid over.
    That box is the hull's box along the world axes where the grid over it stays within that
    bound (most objects stand square to them); otherwise (a thin board standing at an angle, a
    slanted rod) its box along its own principal axes, with a step grown until the bound holds."""
    V = hull.points[hull.vertices]
    vol = max(float(hull.volume), 1e-12)
    step = max(0.002, (vol / max_n) ** (1 / 3))
    limit = GRID_FACTOR * max_n
    lo, hi = V.min(0), V.max(0)
    axes = _grid_axes(lo, hi, step)
    if math.prod(len(a) for a in axes) <= limit:
        G = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return G[inside(hull, G)], step ** 3
    c = V.mean(0)
    _, _, Vt = np.linalg.svd(V - c, full_matrices=False)
    L = (V - c) @ Vt.T
    lo, hi = L.min(0), L.max(0)
    box = max(float(np.prod(hi - lo)), vol)
    step = max(step, (box / limit) ** (1 / 3))
    axes = _grid_axes(lo, hi, step)
    # Axes thinner than a step still get one sample each: grow the step until the bound holds.
    while math.prod(len(a) for a in axes) > limit:
        step *= 1.2
        axes = _grid_axes(lo, hi, step)
    G = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) @ Vt + c
    return G[inside(hull, G)], step ** 3


# --------------------------------------------------------------------------------------------
# Decomposition
# --------------------------------------------------------------------------------------------

def _split_candidates(P: np.ndarray) -> list[np.ndarray]:
    axes = [np.eye(3)[i] for i in range(3)]
    c = P.mean(0)
    _, _, Vt = np.linalg.svd(P - c, full_matrices=False)
    for a in Vt:
        if all(abs(float(a @ b)) < 0.99 for b in axes):
            axes.append(a)
    return axes


def not_ours(hull: Any, fs: FreeSpace, foreign: Optional[np.ndarray] = None) -> tuple[np.ndarray, float]:
    """The sample points of a hull that cannot belong to the object: seen empty, or on the seen
    surface of another object (`foreign` points inside the hull, e.g. a plate standing in its
    holder's slot, which hides the slot from the cameras). Returns (points, cell volume)."""
    G, cell = samples_in(hull)
    E = G[fs.empty(G)] if len(G) else np.zeros((0, 3))
    if foreign is not None and len(foreign):
        F = foreign[inside(hull, foreign)]
        if len(F):
            import robo_perception as rp

            F = rp.voxel_downsample(F, cell ** (1 / 3))[0] if len(F) > 1 else F
            E = np.concatenate([E, F])
    return E, cell


def decompose(P: np.ndarray, fs: FreeSpace, foreign: Optional[np.ndarray] = None, max_parts: int = MAX_PARTS,
              solid: Optional[np.ndarray] = None) -> dict:
    """Convex parts of the points `P` (world, with what is under them already added) whose hulls
    hold no space a view saw empty and no other object's points (`foreign`), within the
    tolerances, and none of `solid` (samples filling other objects' fitted solids, grown by a
    clearance): one such sample weighs as much as the whole tolerance, because a part reaching
    into a solid starts the simulation interpenetrated and the contact pushes the other object
    away (a holder's cradle under a plate's curved rim: the hull of columns under the arc cuts
    into the rim until the cradle is sliced finely enough). Returns {"parts": [point arrays],
    "empty": [the not-ours sample points of the first hull], "cell_m3": its cell volume, "cuts":
    how many cuts were made, "residual_m3": not-ours volume left in the accepted parts,
    "solid_samples_left": solid samples still inside an accepted part}."""
    root = hull_of(P)
    if root is None:
        return {"parts": [P], "empty": np.zeros((0, 3)), "cell_m3": 0.0, "cuts": 0, "residual_m3": 0.0,
                "solid_samples_left": 0}
    E_all, cell = not_ours(root, fs, foreign)
    S_all = solid[inside(root, solid)] if solid is not None and len(solid) else np.zeros((0, 3))
    if len(S_all):
        E_all = np.concatenate([E_all, S_all])
    heavy = max(cell, EMPTY_TOL_M3)
    done: list = []
    cuts = 0
    residual = 0.0
    solid_left = 0

    def seen_empty(Q: np.ndarray, E: np.ndarray, S: np.ndarray = S_all) -> tuple[float, float, Any, int]:
        """(not-ours weight: seen-empty cells + heavy solid samples, hull volume, hull, solid
        samples inside)."""
        h = hull_of(Q)
        if h is None:
            return 0.0, 0.0, None, 0
        n = int(inside(h, E).sum()) if len(E) else 0
        m = int(inside(h, S).sum()) if len(S) else 0
        return n * cell + m * (heavy - cell), float(h.volume), h, m

    # The part holding the most seen-empty space is cut first, so the part budget goes where the
    # hulls are most wrong.
    todo = [(seen_empty(P, E_all), P)]
    while todo:
        todo.sort(key=lambda x: -x[0][0])
        (e, vol, h, m), Q = todo.pop(0)
        small = len(Q) < 2 * MIN_PART_POINTS
        if h is None or e < EMPTY_TOL_M3 or small or len(done) + len(todo) + 2 > max_parts:
            done.append(Q)
            residual += e - m * heavy
            solid_left += m
            continue
        best = None
        # Cuts at quantiles of the points, and through the seen-empty space inside the hull
        # (where a cut belongs: between the dividers of a rack, across a handle's hole). The
        # cut is chosen on an even subsample of at most SUBSAMPLE points (for speed), then
        # applied to all of them.
        Eh = E_all[inside(h, E_all)] if len(E_all) else E_all
        Sh = S_all[inside(h, S_all)] if len(S_all) else S_all
        Qs = Q[::max(1, len(Q) // SUBSAMPLE)]
        stride = max(1, len(Eh) // (2 * SUBSAMPLE))
        Eh = Eh[::stride]
        for a in _split_candidates(Q):
            s = Qs @ a
            at = list(np.quantile(s, np.linspace(0.1, 0.9, 9)))
            if len(Eh):
                at += list(np.quantile(Eh @ a, np.linspace(0.1, 0.9, 9)))
            for cut in sorted(set(float(c) for c in at)):
                A, B = Qs[s <= cut], Qs[s > cut]
                if len(A) < MIN_PART_POINTS // 2 or len(B) < MIN_PART_POINTS // 2:
                    continue
                sa, sb = seen_empty(A, Eh, Sh), seen_empty(B, Eh, Sh)
                score = ((sa[0] + sb[0]) * stride, sa[1] + sb[1])
                if best is None or score < best[0]:
                    best = (score, a, cut)
        if best is None or best[0][0] >= e:
            done.append(Q)
            residual += e - m * heavy
            solid_left += m
            continue
        s = Q @ best[1]
        A, B = Q[s <= best[2]], Q[s > best[2]]
        if len(A) < MIN_PART_POINTS or len(B) < MIN_PART_POINTS:
            done.append(Q)
            residual += e - m * heavy
            solid_left += m
            continue
        cuts += 1
        todo += [(seen_empty(A, E_all), A), (seen_empty(B, E_all), B)]
    return {"parts": done, "empty": E_all, "cell_m3": cell, "cuts": cuts, "residual_m3": residual,
            "solid_samples_left": solid_left}


def grounded(P: np.ndarray, fs: FreeSpace, base_z: float, step: float = 0.004, keep_every: int = 5) -> np.ndarray:
    """The points and, under each (on a 5 mm grid), a column of points down to `base_z` (what the
    object stands on) unless some view saw part of that column empty: the underside no camera
    sees is taken as solid, as a convex hull with its shadow would be, but not where the frames
    show a gap (under a slanted peg, under a handle)."""
    import robo_perception as rp

    S = rp.voxel_downsample(P, 0.005)[0] if len(P) > 50 else P
    n = np.maximum(0, np.floor((S[:, 2] - base_z) / step).astype(int))
    if not n.any():
        return P
    k = np.arange(1, int(n.max()) + 1)
    C = np.repeat(S[:, None, :], len(k), axis=1)
    C[:, :, 2] = S[:, 2:3] - step * k[None, :]
    valid = k[None, :] <= n[:, None]
    C[:, :, 2] = np.maximum(C[:, :, 2], base_z)
    emp = np.zeros(valid.shape, dtype=bool)
    emp[valid] = fs.empty(C[valid])
    clear = ~emp.any(axis=1)
    # Every sample is checked, every `keep_every`-th kept (with the bottom one): the hull of a
    # column needs its ends, and a cut across it some points in between.
    every = valid & ((k[None, :] % keep_every) == 0)
    cols = C[clear][every[clear]]
    base = S[clear].copy()
    base[:, 2] = base_z
    Q = np.concatenate([P, cols, base])
    return rp.voxel_downsample(Q, 0.004)[0] if len(Q) > 6000 else Q


def box_of(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre, half extents, rotation matrix with the box axes as columns): the smaller of the
    points' principal-axes box and their upright minimum-area-rectangle box."""
    import robo_perception as rp

    c0 = P.mean(0)
    _, _, Vt = np.linalg.svd(P - c0, full_matrices=False)
    cands = [Vt.T]
    _, axes, _, _ = rp.min_area_rect(P[:, :2])
    a = np.array([axes[0, 0], axes[0, 1], 0.0])
    a /= np.linalg.norm(a) or 1.0
    cands.append(np.column_stack([a, np.cross([0.0, 0.0, 1.0], a), [0.0, 0.0, 1.0]]))
    best = None
    for Rm in cands:
        if np.linalg.det(Rm) < 0:
            Rm = Rm.copy()
            Rm[:, 2] *= -1
        s = P @ Rm
        lo, hi = s.min(0), s.max(0)
        half = np.maximum((hi - lo) / 2, MIN_THICK_M / 2)
        vol = float(np.prod(half))
        if best is None or vol < best[0]:
            best = (vol, Rm @ ((lo + hi) / 2), half, Rm)
    return best[1], best[2], best[3]


def quat_matrix(q: list) -> np.ndarray:
    """The rotation matrix of a quaternion [w, x, y, z] (normalised first)."""
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def quat_of(Rm: np.ndarray) -> list:
    """Rotation matrix -> [w, x, y, z]."""
    m = Rm
    t = m[0, 0] + m[1, 1] + m[2, 2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return (q if q[0] >= 0 else -q).tolist()


def mesh_of(hull: Any, origin: np.ndarray) -> dict:
    """A convex hull as {"vertices", "faces"} (outward winding), relative to `origin`."""
    used = np.unique(hull.simplices)
    remap = {int(v): i for i, v in enumerate(used)}
    V = hull.points[used] - origin
    faces = []
    for s, eq in zip(hull.simplices, hull.equations):
        a, b, c = (remap[int(i)] for i in s)
        n = np.cross(V[b] - V[a], V[c] - V[a])
        if np.dot(n, eq[:3]) < 0:
            b, c = c, b
        faces.append((a, b, c))
    return {"vertices": V.tolist(), "faces": faces}


BOX_FILL = 0.75
"""A part whose hull fills this much of its oriented box is written as that box."""


def _in_box(X: np.ndarray, c: np.ndarray, half: np.ndarray, Rm: np.ndarray) -> int:
    return int((np.abs((X - c) @ Rm) <= half).all(1).sum()) if len(X) else 0


def part_specs(parts: list, origin: np.ndarray, solid: Optional[np.ndarray] = None) -> tuple[list, float]:
    """Accepted part point sets -> scene parts relative to `origin` (boxes where they fill their
    box and the box reaches into none of `solid`, else convex meshes carried under "_mesh"), and
    their total volume."""
    out, volume = [], 0.0
    for Q in parts:
        h = hull_of(Q)
        c, half, Rm = box_of(thicken(Q))
        bvol = 8 * float(np.prod(half))
        clear = solid is None or h is None or not _in_box(solid, c, half, Rm)
        if h is None or (h.volume >= BOX_FILL * bvol and clear):
            out.append({"shape": "box", "size_m": [round(float(v), 5) for v in half],
                        "position_m": [round(float(v), 5) for v in c - origin],
                        "quat_wxyz": [round(float(v), 6) for v in quat_of(Rm)]})
            volume += bvol
        else:
            out.append({"shape": "mesh", "_mesh": mesh_of(h, origin)})
            volume += float(h.volume)
    return out, volume


# --------------------------------------------------------------------------------------------
# Round containers and discs on edge
# --------------------------------------------------------------------------------------------

def _circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    A = np.column_stack([2 * xy[:, 0], 2 * xy[:, 1], np.ones(len(xy))])
    sol, *_ = np.linalg.lstsq(A, (xy ** 2).sum(1), rcond=None)
    c = sol[:2]
    return c, math.sqrt(max(sol[2] + c @ c, 1e-12))


def trimmed_circle(xy: np.ndarray, keep: float = 0.9, rounds: int = 8, tol: float = 0.03
                   ) -> tuple[np.ndarray, float, np.ndarray]:
    """A circle fitted to most of the points: each round drops the points farthest from the
    current circle (deterministic). Returns (centre, radius, inlier mask within tol * radius)."""
    sel = np.ones(len(xy), dtype=bool)
    c, rad = _circle(xy)
    for _ in range(rounds):
        res = np.abs(np.linalg.norm(xy - c, axis=1) - rad)
        lim = max(float(np.quantile(res[sel], keep)), tol * rad / 2)
        sel = res <= lim
        if sel.sum() < 10:
            break
        c, rad = _circle(xy[sel])
    res = np.abs(np.linalg.norm(xy - c, axis=1) - rad)
    return c, rad, res <= tol * rad


ROUND_FILL = 0.9
"""A container's footprint must fill less than this of its minimum-area rectangle (as the
footprint test of round objects in r2g_reconstruct.py)."""


def container_fit(P: np.ndarray, plane_z: float, fs: FreeSpace) -> Optional[dict]:
    """An open-topped round body in the points (a cup, a mug): most points on a vertical circle
    (its walls, seen from outside and inside), its middle seen empty above the floor. Returns
    {"centre", "radius" (outer), "height", "rest": the points outside the walls} or None."""
    import robo_perception as rp

    S = rp.voxel_downsample(P, 0.003)[0] if len(P) > 400 else P
    # The walls run the whole height; the floor inside (seen by a camera looking into the open
    # top) lies in the lowest fifth and is left out of the circle and its count.
    S = S[S[:, 2] > plane_z + 0.2 * (float(S[:, 2].max()) - plane_z)]
    if len(S) < 60:
        return None
    c, rad, inl = trimmed_circle(S[:, :2], tol=0.12)
    if not (0.015 <= rad <= 0.15) or inl.mean() < 0.6:
        return None
    # The band is wide (a wall seen from outside and inside is 12 % of a cup's radius), wide
    # enough for most points of a square bin's walls too (their footprint, corners cut off by
    # the band, is an octagon). So the whole footprint must be round: filling under ROUND_FILL
    # of its minimum-area rectangle (a circle fills 0.79, less with a handle; a square 1).
    _, _, ext, area = rp.min_area_rect(S[:, :2])
    fill = area / max(float(ext[0] * ext[1]), 1e-12)
    if fill >= ROUND_FILL:
        return None
    d = np.linalg.norm(S[:, :2] - c, axis=1)
    outer = float(np.quantile(d[inl], 0.95))
    top = float(np.quantile(S[inl, 2], 0.99)) - plane_z
    if top < 0.02:
        return None
    # The upper middle (70-90 % of the height, within 60 % of the radius) must be seen empty:
    # cameras looking down see into an open top there (deeper down the rim hides the inside),
    # and a solid body's top surface hides all of it.
    ring = np.linspace(0, 2 * math.pi, 12, endpoint=False)
    pts = [[c[0] + f * outer * math.cos(t), c[1] + f * outer * math.sin(t), plane_z + z * top]
           for f in (0.0, 0.3, 0.6) for t in (ring if f else ring[:1]) for z in (0.7, 0.8, 0.9)]
    frac = float(fs.empty(np.array(pts)).mean())
    if frac < 0.6:
        return None
    rest = P[np.linalg.norm(P[:, :2] - c, axis=1) > outer + 0.003]
    return {"centre": c, "radius": outer, "height": top, "rest": rest, "inliers": float(inl.mean()),
            "middle_seen_empty": frac, "footprint_fill": float(fill)}


def box_container_fit(P: np.ndarray, plane_z: float, fs: FreeSpace) -> Optional[dict]:
    """An open-topped rectangular body in the points (a bin, a tray): a footprint that fills its
    minimum-area rectangle (at least ROUND_FILL; round ones are `container_fit`'s), every point
    either near the rectangle's outline (its walls, each of the four seen) or low (its floor),
    and its upper middle seen empty as in `container_fit`. Returns {"centre", "axes" (2x2, the
    rectangle's sides as columns), "half" (outer half extents), "height", "band",
    "middle_seen_empty", "footprint_fill"} or None."""
    import robo_perception as rp

    S = rp.voxel_downsample(P, 0.003)[0] if len(P) > 400 else P
    if len(S) < 60:
        return None
    c, axes, ext, area = rp.min_area_rect(S[:, :2])
    fill = area / max(float(ext[0] * ext[1]), 1e-12)
    half = np.asarray(ext, dtype=float) / 2
    if fill < ROUND_FILL or not (0.015 <= half.min() and half.max() <= 0.25):
        return None
    h = S[:, 2] - plane_z
    top = float(np.quantile(h, 0.99))
    if top < 0.02:
        return None
    L = (S[:, :2] - c) @ axes
    band = max(0.006, 0.1 * float(half.min()))
    if half.min() < 2 * band:
        return None
    d = np.min(half[None, :] - np.abs(L), axis=1)
    # Nothing stands inside the walls above the floor: no divider, no peg, no solid top.
    inner_high = (d > band) & (h > max(0.012, 0.25 * top))
    if inner_high.mean() > 0.03:
        return None
    high = h > 0.5 * top
    for k in range(2):
        for sign in (-1.0, 1.0):
            side = high & (np.abs(sign * L[:, k] - half[k]) < band)
            if side.sum() < 10:
                return None
    pts = []
    ring = np.linspace(0, 2 * math.pi, 12, endpoint=False)
    for f in (0.0, 0.3, 0.6):
        for t in (ring if f else ring[:1]):
            for z in (0.7, 0.8, 0.9):
                loc = np.array([f * half[0] * math.cos(t), f * half[1] * math.sin(t)])
                xy = c + axes @ loc
                pts.append([xy[0], xy[1], plane_z + z * top])
    frac = float(fs.empty(np.array(pts)).mean())
    if frac < 0.6:
        return None
    return {"centre": np.asarray(c, dtype=float), "axes": np.asarray(axes, dtype=float), "half": half, "height": top,
            "band": band, "middle_seen_empty": frac, "footprint_fill": float(fill)}


def disc_fit(P: np.ndarray) -> Optional[dict]:
    """A flat cloud standing on edge (its normal, the thin axis, within about 20 degrees of
    horizontal: |n_z| < 0.35) whose outline in its own plane is a circle: {"centre", "radius",
    "half_thickness", "normal", "residual", "outline_inliers"} or None."""
    import robo_perception as rp

    if len(P) < 60:
        return None
    c0 = P.mean(0)
    _, _, Vt = np.linalg.svd(P - c0, full_matrices=False)
    s = (P - c0) @ Vt.T
    # 5-95 %: a few points of what holds the disc (a holder's rails) may have joined its cloud.
    lo, hi = np.quantile(s, 0.05, axis=0), np.quantile(s, 0.95, axis=0)
    ext = hi - lo
    n = Vt[2]
    if not (ext[2] < 0.25 * ext[1] and ext[2] < 0.03 and abs(n[2]) < 0.35):
        return None
    outline = rp.convex_hull_2d(s[:, :2])
    if len(outline) < 3:
        return None
    pts = []
    for a, b in zip(outline, np.roll(outline, -1, axis=0)):
        k = max(1, int(np.linalg.norm(b - a) / 0.002))
        pts.append(a + (np.arange(k)[:, None] / k) * (b - a))
    O = np.concatenate(pts)
    c2, rad, inl = trimmed_circle(O, keep=0.8, tol=0.03)
    res = float(np.sqrt(np.mean((np.linalg.norm(O[inl] - c2, axis=1) - rad) ** 2)) / rad) if inl.any() else 1.0
    if inl.mean() < 0.6 or res > 0.02 or rad < 0.02:
        return None
    centre = c0 + Vt[0] * c2[0] + Vt[1] * c2[1] + Vt[2] * (lo[2] + hi[2]) / 2
    n = n if n[1] >= 0 else -n
    return {"centre": centre, "radius": rad, "half_thickness": max(float(ext[2]) / 2, MIN_THICK_M / 2),
            "normal": n, "residual": res, "outline_inliers": float(inl.mean())}


def z_to(n: np.ndarray) -> list:
    """[w, x, y, z] of the shortest rotation taking +z to the unit vector n."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, n)
    s = float(np.linalg.norm(axis))
    ang = math.atan2(s, float(z @ n))
    if s < 1e-9:
        return [1.0, 0.0, 0.0, 0.0] if n[2] > 0 else [0.0, 1.0, 0.0, 0.0]
    axis /= s
    return [math.cos(ang / 2)] + (axis * math.sin(ang / 2)).tolist()


def support_columns(S: np.ndarray, fs: FreeSpace, base_z: float, lo: np.ndarray, hi: np.ndarray,
                    clearance: float = 0.004, step: float = 0.004, reach: float = 0.015) -> list:
    """The columns of what must hold up a resting object no camera sees under: `S` fills the
    object's fitted solid; below its underside (less `clearance`), within the supporting
    object's horizontal extent lo..hi, a column down towards `base_z`, cut above its first
    sample (from the top) that a view saw empty. Returns [(x, y, bottom z, top z)], one per
    `step` grid cell that keeps a column. A plate standing in a holder hides the holder's
    chocks; these columns give the holder a cradle under the plate's rim instead of nothing
    (`cradle_boxes` turns them into parts)."""
    S = S[(S[:, 0] >= lo[0]) & (S[:, 0] <= hi[0]) & (S[:, 1] >= lo[1]) & (S[:, 1] <= hi[1])]
    if not len(S):
        return []
    cell = np.floor(S[:, :2] / step).astype(np.int64)
    order = np.lexsort((S[:, 2], cell[:, 1], cell[:, 0]))
    cs = cell[order]
    first = np.ones(len(cs), dtype=bool)
    first[1:] = (cs[1:] != cs[:-1]).any(1)
    low = S[order][first]
    # Only under the lowest stretch of the underside (within `reach` of its lowest point): what
    # it can rest on, not the room beside a disc's rising rim.
    low = low[low[:, 2] <= low[:, 2].min() + reach]
    out = []
    for p in low:
        top = p[2] - clearance
        if top <= base_z:
            continue
        z = np.arange(top, base_z - 1e-9, -step)
        out.append(np.column_stack([np.full(len(z), p[0]), np.full(len(z), p[1]), z]))
    if not out:
        return []
    C = np.concatenate(out)
    emp = fs.empty(C)
    # Each column (samples from the top down) ends above its first seen-empty sample: what lies
    # below a gap a view saw through does not hold the object up (as in `grounded`).
    keep, k = [], 0
    for col in out:
        e = emp[k:k + len(col)]
        k += len(col)
        first = int(np.argmax(e)) if e.any() else len(col)
        bottom = base_z if first == len(col) else float(col[first - 1, 2]) if first else None
        if bottom is not None and col[0, 2] - bottom > 0.001:
            keep.append((float(col[0, 0]), float(col[0, 1]), bottom, float(col[0, 2])))
    return keep


def cradle_boxes(columns: list, step: float = 0.004, tol: float = 0.0015, max_boxes: int = 12) -> list:
    """Support columns [(x, y, bottom, top)] -> a few boxes [(centre, half sizes)] in world
    axes, each no higher than the lowest column top it covers (the hull of columns under a
    curved rim would rise above the arc between them, its chords). A box covers its whole grid
    cells while its top comes from one sample in each, so under a steep stretch of the rim a
    corner can still reach a fraction of a millimetre above it: the caller lowers the boxes
    against the object's grown solid (`cradle_parts`). Cells of the `step` grid are merged along
    x where tops and bottoms agree within `tol` (and the merged box keeps at least 1 mm of
    height), then rows with the same run along y; `tol` doubles until at most `max_boxes`
    remain or it passes 5 cm (cells that do not touch always stay apart)."""
    if not columns:
        return []
    cells: dict = {}
    for x, y, b, t in columns:
        key = (int(math.floor(x / step)), int(math.floor(y / step)))
        if key in cells:
            ob, ot = cells[key]
            cells[key] = (max(ob, b), min(ot, t))
        else:
            cells[key] = (b, t)
    while True:
        runs = []  # (ix0, ix1, iy0, iy1, bottom, top)
        for iy in sorted({k[1] for k in cells}):
            row = sorted(k[0] for k in cells if k[1] == iy)
            cur = None
            for ix in row:
                b, t = cells[(ix, iy)]
                if (cur and ix == cur[1] + 1 and abs(t - cur[5]) <= tol and abs(b - cur[4]) <= tol
                        and max(b, cur[4]) < min(t, cur[5]) - 1e-3):
                    cur = [cur[0], ix, iy, iy, max(cur[4], b), min(cur[5], t)]
                else:
                    if cur:
                        runs.append(cur)
                    cur = [ix, ix, iy, iy, b, t]
            if cur:
                runs.append(cur)
        merged: list = []
        for run in sorted(runs, key=lambda q: (q[0], q[1], q[2])):
            m = next((q for q in merged if q[0] == run[0] and q[1] == run[1] and q[3] + 1 == run[2]
                      and abs(q[5] - run[5]) <= tol and abs(q[4] - run[4]) <= tol
                      and max(q[4], run[4]) < min(q[5], run[5]) - 1e-3), None)
            if m:
                m[3], m[4], m[5] = run[2], max(m[4], run[4]), min(m[5], run[5])
            else:
                merged.append(list(run))
        if len(merged) <= max_boxes or tol > 0.05:
            break
        tol *= 2
    out = []
    for ix0, ix1, iy0, iy1, b, t in merged:
        if t - b < 1e-4:
            continue
        lo = np.array([ix0 * step, iy0 * step, b])
        hi = np.array([(ix1 + 1) * step, (iy1 + 1) * step, t])
        out.append(((lo + hi) / 2, (hi - lo) / 2))
    return out

