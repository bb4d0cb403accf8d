"""Relations between objects as the simulator's judge means them, measured from what the cameras
see: `on(obj, support)` and `inside(obj, container)` -> `Relation`.

The judge (robot-skill/api/SIMULATION.md, "How success is judged") decides **on** from contact:
the object ends touching its support, above the support's lowest point; and **inside** from the
object's origin: it ends within the container's cavity (a box inside its walls, from its
underside up to its rim). Contact cannot be seen; what can is where the object's bottom sits
against the support's surface under it, and where the object's centre and bottom lie against
the container's walls, floor and rim. Both functions measure those, with the tolerances they
state, and say why they answer as they do. An object the hand still holds is judged by where it
is, but the answer says it is held (a task needs it released as well).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Union

import numpy as np

from .segmentation import HIDDEN_BOTTOM_M, RESTING_M, SUPPORT_HIDDEN_M, SUPPORT_TOLERANCE_M, ObjectCluster, SceneSegmentation

ON_GAP_M = SUPPORT_HIDDEN_M
"""How far above the support's surface an object's lowest point seen may be for `on` (m): its
bottom edge hidden by its own side or a neighbour."""
ON_SINK_M = SUPPORT_TOLERANCE_M
"""How far below it (m): outline pixels read either surface."""
INSIDE_SHRINK = 2.0 / 3.0
"""`inside`: the centre must lie within the container's footprint shrunk about its centre to this
share of its sides (for a round bowl or cup, about the square inside its inner wall, the cavity
the judge uses)."""


@dataclass
class Relation:
    """The answer of `on` or `inside`. ``holds``: the relation holds as far as the cameras can
    tell (also ``bool(relation)``); ``kind``: "on" or "inside"; ``gap_m``: on: the object's
    lowest point seen minus the support's surface under it (m; 0 when it sits on it, the
    plane's cut of 5 mm for the table); inside: the object's bottom minus the container's
    floor or bottom (m); ``overlap``: the share of the object's footprint rectangle over the
    support's or container's (0-1); ``center_in``: whether the object's centre lies over the
    support's footprint (on) or within its shrunk footprint (inside); ``below_rim_m`` (inside):
    the container's top minus the object's bottom (m; positive when the bottom is below the
    rim); ``held``: the hand holds the object; ``why``: one line saying what decided it;
    ``details``: the numbers used."""

    holds: bool
    kind: str
    gap_m: float
    overlap: float
    center_in: bool
    held: bool
    why: str
    below_rim_m: Optional[float] = None
    details: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return self.holds


def _footprint_overlap(a: ObjectCluster, b: ObjectCluster, n: int = 15) -> float:
    """Share of ``a``'s footprint rectangle over ``b``'s (a grid of n x n points on ``a``'s)."""
    s = np.linspace(-0.5, 0.5, n)
    g = np.stack(np.meshgrid(s, s), axis=-1).reshape(-1, 2) * a.obb.extents[:2]
    P = a.obb.center + g @ a.obb.axes[:, :2].T
    L = b.obb.to_local(P)
    return float(np.mean(np.all(np.abs(L[:, :2]) <= 0.5 * b.obb.extents[:2] + 1e-9, axis=1)))


def _surface_below(obj: ObjectCluster, support: ObjectCluster, plane_distance) -> Optional[float]:
    """The support's surface under ``obj``: the highest of its points near ``obj``'s footprint
    (1.5 cm around it) that are no higher than ``obj``'s lowest point plus `ON_SINK_M`
    (90th percentile), or None when it shows none there."""
    L = obj.obb.to_local(support.points)
    near = np.all(np.abs(L[:, :2]) <= 0.5 * obj.obb.extents[:2] + 0.015, axis=1)
    if near.sum() < 10:
        return None
    h = plane_distance(support.points[near])
    below = h <= obj.lowest_seen + ON_SINK_M
    if below.sum() < 10:
        return None
    return float(np.percentile(h[below], 90))


def on(obj: ObjectCluster, support: Optional[Union[ObjectCluster, str]], scene: SceneSegmentation) -> Relation:
    """Whether ``obj`` rests on ``support`` (an object of ``scene``, or None / "table" / "plane"
    for the support plane), as the judge's **on** means it: touching it from above.

    Holds when the object's lowest point seen is at the support's surface under it (from
    `ON_SINK_M` below to `ON_GAP_M` above it; for the table, at most `RESTING_M` above the plane,
    the 5 mm cut plus a few millimetres, or below `HIDDEN_BOTTOM_M` when nothing holds it and
    segmentation stood it on the plane) and its centre lies over the support's footprint. An
    object beside the support, touching only its side, is not on it (its bottom is not above the
    support's lowest point); one hanging over it with room below is not on it either."""
    dist = scene.plane.distance
    held = bool(obj.held)
    if support is None or (isinstance(support, str) and support in ("table", "plane")):
        gap = float(obj.lowest_seen)
        # as segmentation decides `support == "plane"`: down on it, or (nothing holding it)
        # standing there with its lowest centimetre hidden by a neighbour or the fingers
        hidden = not held and obj.support == "plane" and RESTING_M < gap < HIDDEN_BOTTOM_M
        ok = gap <= RESTING_M or hidden
        why = (f"its lowest point seen is {1e3 * gap:.1f} mm above the table "
               + ("(resting on it)" if gap <= RESTING_M else
                  "(nothing holds it up: resting on it, its bottom hidden)" if hidden else
                  f"(more than {1e3 * RESTING_M:.0f} mm: not touching it)"))
        return Relation(holds=ok, kind="on", gap_m=gap, overlap=1.0, center_in=True, held=held,
                        why=why + (", and the hand holds it" if held else ""), details={"support": "plane"})
    if not isinstance(support, ObjectCluster):
        raise TypeError(f"on: support must be an object of the scene, None or 'table', got {support!r}")
    overlap = _footprint_overlap(obj, support)
    c = support.obb.to_local(obj.center[None])[0]
    center_in = bool(np.all(np.abs(c[:2]) <= 0.5 * support.obb.extents[:2]))
    surf = _surface_below(obj, support, dist)
    details = {"support_id": support.id, "surface_m": surf, "lowest_seen_m": float(obj.lowest_seen),
               "support_top_m": float(support.top), "support_bottom_m": float(support.bottom)}
    if surf is None:
        why = ("its centre is not over the support's footprint" if not center_in
               else "the support shows no surface under the object at or below its lowest point")
        return Relation(holds=False, kind="on", gap_m=float("nan"), overlap=overlap, center_in=center_in, held=held,
                        why=why + (", and the hand holds it" if held else ""), details=details)
    gap = float(obj.lowest_seen - surf)
    # above the support's own base: by the cut's few millimetres, or half the support's
    # thickness for a support thinner than twice that (a 5 mm mat)
    base_margin = min(RESTING_M, 0.5 * max(float(support.top) - float(support.bottom), 0.0))
    above_base = float(obj.lowest_seen) > float(support.bottom) + base_margin
    ok = bool(-ON_SINK_M <= gap <= ON_GAP_M and center_in and above_base)
    if ok:
        why = f"its lowest point is {1e3 * gap:+.1f} mm from the support's surface under it, its centre over it"
    elif not center_in:
        why = "its centre is not over the support's footprint"
    elif not above_base:
        why = "its bottom is at the support's own base (beside it, not on it)"
    elif gap > ON_GAP_M:
        why = f"its lowest point is {1e3 * gap:.1f} mm above the support's surface (not touching)"
    else:
        why = f"its lowest point is {1e3 * -gap:.1f} mm below the support's surface under it"
    return Relation(holds=ok, kind="on", gap_m=gap, overlap=overlap, center_in=center_in, held=held,
                    why=why + (", and the hand holds it" if held else ""), details=details)


def inside(obj: ObjectCluster, container: ObjectCluster, scene: SceneSegmentation) -> Relation:
    """Whether ``obj`` is inside ``container`` as the judge's **inside** means it: its origin
    within the container's cavity.

    Holds when the object's centre lies within the container's footprint shrunk to
    `INSIDE_SHRINK` of its sides about its centre, and its bottom lies between the container's
    bottom and its top (the rim): down in the cavity, not resting on the rim nor hovering over
    the opening. (The judge's cavity is the task author's box; for the shipped bowls and cups it
    is the square inside the inner wall, about what the shrunk footprint is.)"""
    dist = scene.plane.distance
    held = bool(obj.held)
    c = container.obb.to_local(obj.center[None])[0]
    half = 0.5 * INSIDE_SHRINK * container.obb.extents[:2]
    center_in = bool(np.all(np.abs(c[:2]) <= half))
    overlap = _footprint_overlap(obj, container)
    bottom = float(obj.bottom)
    floor = _surface_below(obj, container, dist) if container.hollow else None
    base = float(container.bottom) if floor is None else floor
    below_rim = float(container.top) - bottom
    down = bool(bottom >= base - ON_SINK_M and bottom <= float(container.top) - 0.005)
    ok = bool(center_in and down)
    details = {"container_id": container.id, "center_local_m": [float(c[0]), float(c[1])],
               "half_sides_m": [float(half[0]), float(half[1])], "floor_m": floor,
               "container_top_m": float(container.top), "container_bottom_m": float(container.bottom)}
    if ok:
        why = (f"its centre is within the container's inner footprint and its bottom "
               f"{1e3 * below_rim:.0f} mm below the rim")
    elif not center_in:
        why = (f"its centre is {1e3 * float(np.max(np.abs(c[:2]) - half)):.0f} mm outside the container's inner "
               "footprint")
    elif bottom > float(container.top) - 0.005:
        why = "its bottom is not below the container's rim (on the rim or above the opening)"
    else:
        why = "its bottom is below the container's floor"
    return Relation(holds=ok, kind="inside", gap_m=float(bottom - base), overlap=overlap, center_in=center_in,
                    held=held, why=why + (", and the hand holds it" if held else ""), below_rim_m=below_rim,
                    details=details)
