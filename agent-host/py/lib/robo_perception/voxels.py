"""Voxel grids: integer voxel keys, voxelisation and lookup, voxel down-sampling, connected
components of a graph and Euclidean clustering of points over occupied voxels (26-neighbourhood)."""

from __future__ import annotations

from typing import Optional

import numpy as np

from .transforms import ArrayLike


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
