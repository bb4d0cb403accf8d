"""Anchor frames and binding: where a motion rule puts the TCP, given an object seen now.

An *anchor* is a feature of one object's oriented box (``robo_perception.OrientedBox`` of the
support-plane box: axes long side, short side, plane normal):

- ``centre``: the box centre;
- ``top_face``: the centre of its top face;
- ``support_plane``: where its vertical axis meets the support plane (the bottom face's centre);
- ``major_axis``: the end of its long axis (the box centre moved half the long side along x);
- ``in_hand``: the object as the hand holds it (a drawer's handle being pulled): the TCP's own
  frame when the stage begins, laid level (origin at the TCP, z the plane normal, x the TCP's x
  laid into the plane). Perception of a part seen through the fingers is too rough to pull it
  by; the hand that grasped it by its rules is where it is. Bound only while the gripper holds
  something.

The anchor frame's z is the support plane's normal (up), its x the box's long axis laid into
the plane, y = z × x. A box looks the same turned half a turn (and a quarter turn when its
footprint is nearly square; any turn when it is round), so which x is meant is settled by a
*reference*, the TCP pose measured when the stage begins: x is the candidate pointing most
toward the TCP's position in the plane (for a round object, exactly toward it); when the TCP
is within 2 cm of straight above the anchor, toward where the TCP's own x axis points. A
*line* (a long thin box: a tape line, a bar handle; short side under half the long one)
is mostly faced across its length, where "toward the TCP" would be a coin toss between its two
ends: when the reference lies within 70 degrees of straight across, x is the candidate whose
y points toward the reference (so "past the line", away from the TCP, is -y). Every
rule of a stage is bound with the same reference, so they agree on the frame; extraction
relates a round's targets with the TCP measured at that round's start, so binding gives them
back. Everything here is a function of (object box, plane normal, reference pose): move all
three rigidly and every bound target moves with them (tested to 1e-9).

A rule places the TCP at ``offset_m`` in the anchor frame, turned ``yaw_rad`` about the anchor's
z from the anchor's x, tilted by ``tilt_rad`` (a rotation vector; [pi, 0, 0] points the TCP's
approach axis straight down). The parallel gripper is symmetric under half a turn about its
approach axis: of the two, the target nearest the reference is taken.

A rule may name a ``second_anchor`` ({"object", "feature", "along": {"x": 0.0}}): along each
named axis of the anchor frame the actor's coordinate is measured from that second feature
instead of from the anchor - "3 cm past the line (anchor: the line, offset y = -0.03), level with
the block along the line (second anchor: the block, along x = 0)". The frame, and so the hand's
orientation, stays the anchor's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from robo_perception.hand import FRANKA_HAND
from robo_perception.transforms import (axis_angle_to_matrix, matrix_to_axis_angle, pose_to_matrix,
                                        rotation_distance)

FEATURES = ("centre", "top_face", "support_plane", "major_axis", "in_hand")
SQUARE_RATIO = 0.85  # short / long side at or above this: a quarter turn looks the same
LINE_RATIO = 0.5  # short / long side under this: a line, a bar (faced across its length)
LINE_ALONG_COS = math.cos(math.radians(20.0))  # a reference within 20 deg of a line's own axis faces its end
AXES = ("x", "y", "z")
# Shapes perception calls round: any turn about the vertical looks the same. A square box is
# not round however equal its sides: its faces settle the frame (a grasp across them).
ROUND_SHAPES = ("disc", "cylinder", "bowl", "plate", "ball", "sphere", "cup", "mug")


class AnchorError(ValueError):
    """A rule cannot be bound: its object was not found, or is ambiguous, or its feature is unknown."""


@dataclass
class Anchor:
    """What binding needs of one object: its box (centre, axes, full extents, base frame) and the
    support plane's unit normal. ``symmetry``: "box" (half turn), "line" (half turn, faced
    across), "square" (quarter turn) or "round" (any turn: the frame's x points from the anchor
    toward the reference TCP)."""

    center: np.ndarray
    axes: np.ndarray
    extents: np.ndarray
    normal: np.ndarray
    symmetry: str = "box"
    name: str = ""

    @staticmethod
    def from_cluster(cluster, plane_normal: Sequence[float], name: str = "", lines: bool = True) -> "Anchor":
        box = cluster.obb
        ext = np.asarray(box.extents, dtype=float)
        ratio = float(ext[1] / ext[0]) if ext[0] > 1e-9 else 1.0
        round_shape = getattr(cluster, "shape_name", "") in ROUND_SHAPES
        if round_shape and ratio >= SQUARE_RATIO:
            symmetry = "round"
        elif ratio >= SQUARE_RATIO:
            symmetry = "square"
        else:
            # `lines`: the line frame (skill schema 2 on); a schema-1 skill binds as it was extracted.
            symmetry = "line" if (lines and ratio < LINE_RATIO) else "box"
        return Anchor(np.asarray(box.center, dtype=float), np.asarray(box.axes, dtype=float), ext,
                      np.asarray(plane_normal, dtype=float), symmetry, name)

    def transformed(self, T: np.ndarray) -> "Anchor":
        """The same object moved by the rigid transform T (4x4)."""
        R, t = T[:3, :3], T[:3, 3]
        return Anchor(R @ self.center + t, R @ self.axes, self.extents.copy(), R @ self.normal, self.symmetry, self.name)


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise AnchorError("a degenerate direction (zero length)")
    return v / n


def _in_plane(v: np.ndarray, z: np.ndarray) -> np.ndarray:
    return v - float(np.dot(v, z)) * z


def feature_origin(a: Anchor, feature: str, z: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The anchor point of ``feature`` (base frame) for the frame (x, z)."""
    half_up = 0.5 * a.extents[2]
    if feature == "centre":
        return a.center.copy()
    if feature == "top_face":
        return a.center + half_up * z
    if feature == "support_plane":
        return a.center - half_up * z
    if feature == "major_axis":
        return a.center + 0.5 * a.extents[0] * x
    raise AnchorError(f"unknown anchor feature {feature!r} (known: {', '.join(FEATURES)})")


NEAR_ABOVE_M = 0.02  # a TCP this close to straight above the anchor gives no direction by its position


def frame(a: Anchor, feature: str, reference: Optional[np.ndarray]) -> np.ndarray:
    """``base_from_anchor`` (4x4) of this anchor and feature, the symmetric candidates settled
    by ``reference`` (4x4 TCP pose; None: the box's own first axis)."""
    z = _unit(a.normal)
    if feature == "in_hand":
        if reference is None:
            raise AnchorError("the in_hand feature is the TCP's frame when the stage begins: it needs that reference")
        x = _unit(_in_plane(reference[:3, 0], z)) if float(np.linalg.norm(_in_plane(reference[:3, 0], z))) > 1e-6 \
            else _unit(_in_plane(reference[:3, 1], z))
        T = np.eye(4)
        T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
        T[:3, 3] = reference[:3, 3]
        return T
    d = None
    if reference is not None:
        d = _in_plane(reference[:3, 3] - a.center, z)
        if float(np.linalg.norm(d)) < NEAR_ABOVE_M:
            d = _in_plane(reference[:3, 0], z)
        if float(np.linalg.norm(d)) < 1e-9:
            d = None
    if a.symmetry == "round":
        x = _unit(d if d is not None else _in_plane(a.axes[:, 0], z))
    elif a.symmetry == "line" and d is not None and \
            abs(float(np.dot(_unit(_in_plane(a.axes[:, 0], z)), _unit(d)))) < LINE_ALONG_COS:
        x0 = _unit(_in_plane(a.axes[:, 0], z))
        x = max((x0, -x0), key=lambda c: float(np.dot(np.cross(z, c), d)))
    else:
        x0 = _unit(_in_plane(a.axes[:, 0], z))
        turns = (0, 1, 2, 3) if a.symmetry == "square" else (0, 2)
        xs = [axis_angle_to_matrix(z * (k * math.pi / 2.0)) @ x0 for k in turns]
        x = xs[0] if d is None else max(xs, key=lambda c: float(np.dot(c, d)))
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = feature_origin(a, feature, z, x)
    return T


def tcp_in_anchor(rule: dict) -> np.ndarray:
    """``anchor_from_tcp`` (4x4) of a rule: offset, then yaw about anchor z, then the tilt."""
    T = np.eye(4)
    T[:3, :3] = axis_angle_to_matrix([0.0, 0.0, float(rule.get("yaw_rad", 0.0))]) @ axis_angle_to_matrix(
        rule.get("tilt_rad", [math.pi, 0.0, 0.0]))
    T[:3, 3] = np.asarray(rule["offset_m"], dtype=float)
    return T


HALF_TURN_Z = np.diag([-1.0, -1.0, 1.0, 1.0])  # the gripper's own symmetry, about its approach axis
ACTORS = ("tcp", "fingertips")


def actor_from_tcp(rule: dict) -> np.ndarray:
    """Where the rule's acting entity sits in the TCP frame: the TCP itself, or the fingertips'
    midpoint `tip_beyond_tcp` further along the approach axis (robo_perception's hand model)."""
    T = np.eye(4)
    actor = rule.get("actor", "tcp")
    if actor == "fingertips":
        T[2, 3] = FRANKA_HAND.tip_beyond_tcp
    elif actor != "tcp":
        raise AnchorError(f"unknown actor {actor!r} (known: {', '.join(ACTORS)})")
    return T


def _as_matrix(pose: Optional[Sequence[float]]) -> Optional[np.ndarray]:
    if pose is None:
        return None
    m = np.asarray(pose, dtype=float)
    return m if m.shape == (4, 4) else pose_to_matrix(m)


def _along(along: dict) -> list[tuple[int, float]]:
    """A second anchor's {"x": m, ...} as (axis index, m), refusing what is not an axis."""
    out = []
    for k, v in (along or {}).items():
        if k not in AXES:
            raise AnchorError(f"second_anchor.along names {k!r}; the anchor frame's axes are x, y, z")
        out.append((AXES.index(k), float(v)))
    if not out:
        raise AnchorError("second_anchor.along names no axis (x, y or z with a distance in m)")
    return out


def bind(rule: dict, anchor: Anchor, reference: Optional[Sequence[float]] = None,
         second: Optional[Anchor] = None) -> np.ndarray:
    """``base_from_tcp`` (4x4) that ``rule`` asks for with ``anchor`` as seen now. ``reference``:
    the TCP pose measured when the stage began (``[x, y, z, ax, ay, az]`` or 4x4); it settles the
    anchor's symmetric frames, and of the two gripper turns (the same grasp) the one nearer its
    orientation is taken. ``second``: the rule's second anchor object as seen now (needed when
    the rule has a ``second_anchor``)."""
    ref = _as_matrix(reference)
    F = frame(anchor, rule["anchor"]["feature"], ref)
    A = F @ tcp_in_anchor(rule)
    spec = rule.get("second_anchor")
    if spec:
        if second is None:
            raise AnchorError(f"rule {rule.get('id', '?')!r} has a second anchor ({spec.get('object')!r}): "
                              "bind it with that object as seen now")
        origin = frame(second, spec.get("feature", "centre"), ref)[:3, 3]
        p = F[:3, :3].T @ (A[:3, 3] - F[:3, 3])
        o2 = F[:3, :3].T @ (origin - F[:3, 3])
        for i, v in _along(spec.get("along")):
            p[i] = o2[i] + v
        A[:3, 3] = F[:3, :3] @ p + F[:3, 3]
    T = A @ np.linalg.inv(actor_from_tcp(rule))
    if ref is not None:
        turned = T @ HALF_TURN_Z
        if rotation_distance(ref[:3, :3], turned[:3, :3]) < rotation_distance(ref[:3, :3], T[:3, :3]) - 1e-12:
            T = turned
    return T


def relate(target: np.ndarray, anchor: Anchor, feature: str, reference: Optional[Sequence[float]] = None,
           actor: str = "tcp", second: Optional[Anchor] = None, second_feature: str = "centre",
           along: Sequence[str] = ()) -> dict:
    """The rule fields (actor, anchor feature, offset_m, yaw_rad, tilt_rad) that put the TCP at
    ``target`` (4x4, base frame) from this anchor with this reference: the inverse of `bind`
    (up to the gripper's half turn). With ``second`` and ``along`` (axes of the anchor frame),
    also the ``second_anchor`` fields (feature, along) that measure those coordinates from the
    second object's feature."""
    at = actor_from_tcp({"actor": actor})
    ref = _as_matrix(reference)
    F = frame(anchor, feature, ref)
    L = np.linalg.inv(F) @ np.asarray(target, dtype=float) @ at
    out = {"actor": actor, "anchor": {"feature": feature}, "offset_m": [float(v) for v in L[:3, 3]],
           **_split_yaw(L[:3, :3])}
    if second is not None and along:
        o2 = F[:3, :3].T @ (frame(second, second_feature, ref)[:3, 3] - F[:3, 3])
        out["second_anchor"] = {"feature": second_feature,
                                "along": {k: float(L[AXES.index(k), 3] - o2[AXES.index(k)]) for k in along}}
    return out


def same_grasp(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(position error m, rotation error rad) between two TCP poses, counting the gripper's half
    turn about its approach axis as the same pose."""
    rot = min(rotation_distance(A[:3, :3], B[:3, :3]), rotation_distance(A[:3, :3], (B @ HALF_TURN_Z)[:3, :3]))
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), rot


def _split_yaw(R: np.ndarray) -> dict:
    """R = Rz(yaw) @ tilt with the tilt's own yaw removed: for a TCP pointing straight down the
    tilt is exactly [pi, 0, 0] and yaw carries the whole turn."""
    down = axis_angle_to_matrix([math.pi, 0.0, 0.0])
    # yaw that best aligns Rz(yaw) @ down with R (closed form on the x-y block of R @ down^T)
    M = R @ down.T
    yaw = math.atan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1])
    tilt = axis_angle_to_matrix([0.0, 0.0, -yaw]) @ R
    return {"yaw_rad": float(yaw), "tilt_rad": [float(v) for v in matrix_to_axis_angle(tilt)]}
