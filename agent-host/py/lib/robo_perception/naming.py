"""Colour and shape names: RGB -> HSV, the colour word of an object's pixels, related colours,
and the coarse shape word of a support-plane box."""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from .transforms import ArrayLike


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
    return str(_hsv_names(np.array([[h, s, v]], dtype=float))[0])


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


SHAPE_NAMES = ("box", "cylinder", "bowl", "plate", "flat", "bar", "panel", "object")


def shape_name(extents: ArrayLike, fill: float, hollow: bool = False, thin_fill: Optional[float] = None) -> str:
    """Coarse shape from a support-plane box and the footprint fill ratio.

    ``extents``: (long side, short side, height) in metres; ``fill``: hull area / rectangle area
    of the footprint (1 for a box, ~0.79 for a disc); ``hollow``: the top is lower in the middle
    than at the rim; ``thin_fill``: fill ratio of the points in the (long side, height) plane,
    used for slabs standing on edge. Returns one of box, cylinder, bowl, plate, flat, bar,
    panel, object. A *bar* is a small part much longer than it is wide (a handle, a rail, a
    peg; up to 6 cm wide, which a bar handle on its standoff posts is, seen from above); a *panel* is a thin slab standing on its edge that is not round (a door, a drawer
    front, a wall).
    """
    a, b, h = (float(x) for x in extents)
    d = sorted((a, b, h), reverse=True)
    if 0.04 <= d[0] <= 0.25 and d[1] <= 0.06 and d[2] <= 0.025 and d[0] >= 2.5 * d[1]:
        return "bar"
    round_top = fill < 0.9 and b > 0.6 * a
    if h < 0.02 and a > 0.03:
        return "plate" if (round_top and b > 0.75 * a) else "flat"
    if b < 0.025 and b < 0.3 * min(a, h):      # a slab standing on its edge
        if thin_fill is not None and thin_fill < 0.9:
            return "plate"
        return "panel" if min(a, h) >= 0.05 else "flat"
    if round_top or (fill < 0.9 and h >= 0.7 * b):
        if hollow and h < 0.8 * max(a, b):
            return "bowl"
        return "cylinder"
    if fill >= 0.9:
        return "box"
    return "object"


def _chromaticity(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB -> (N, 2) chromaticity (r, g shares), damped towards grey when dark."""
    c = rgb.astype(np.float32) + 8.0
    return c[:, :2] / c.sum(axis=1, keepdims=True)


def _hsv_names(hsv: np.ndarray) -> np.ndarray:
    """Colour words for every row of an (N, 3) HSV array (hue in degrees): black when dark, white
    or grey when unsaturated, else by hue, with dim reds, oranges and yellows called brown."""
    h, s, v = hsv[:, 0], hsv[:, 1], hsv[:, 2]
    grey = (s < 0.22) | ((v < 0.35) & (s < 0.35))
    conds = [v < 0.16, grey & (v >= 0.92), grey & (v > 0.22), grey,
             (h < 15) | (h >= 340), h < 45, h < 70, h < 165, h < 195, h < 255, h < 290]
    names = ["black", "white", "grey", "black",
             np.where(v < 0.45, "brown", "red"), np.where(v < 0.8, "brown", "orange"),
             np.where(v < 0.5, "brown", "yellow"), "green", "cyan", "blue", "purple"]
    return np.select(conds, [np.broadcast_to(np.asarray(n, dtype="<U6"), h.shape) for n in names], "pink")
