"""Anchor frames and binding: where a motion rule puts the TCP, given an object seen now.

An *anchor* is a feature of one object's oriented box (``robo_perception.OrientedBox`` of the
support-plane box: axes long side, short side, plane normal):

- ``centre``: the box centre;
- ``top_face``: the centre of its top face;
- ``support_plane``: where its vertical axis meets the support plane (the bottom face's centre);
- ``major_axis``: the end of its long axis (the box centre moved half the long side along x).

The anchor frame's z is the support plane's normal (up), its x the box's long axis laid into
the plane, y = z × x. A box looks the same turned half a turn (and a quarter turn when its
footprint is nearly square; any turn when it is round), so which x is meant is settled by a
*reference*, the TCP pose measured when the stage begins: x is the candidate pointing most
toward the TCP's position in the plane (for a round object, exactly toward it); when the TCP
is within 2 cm of straight above the anchor, toward where the TCP's own x axis points. Every
rule of a stage is bound with the same reference, so they agree on the frame; extraction
relates a round's targets with the TCP measured at that round's start, so binding gives them
back. Everything here is a function of (object box, plane normal, reference pose): move all
three rigidly and every bound target moves with them (tested to 1e-9).

A rule places the TCP at ``offset_m`` in the anchor frame, turned ``yaw_rad`` about the anchor's
z from the anchor's x, tilted by ``tilt_rad`` (a rotation vector; [pi, 0, 0] points the TCP's
approach axis straight down). The parallel gripper is symmetric under half a turn about its
approach axis: of the two, the target nearest the reference is taken.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from robo_perception.hand import FRANKA_HAND
from robo_perception.transforms import (axis_angle_to_matrix, matrix_to_axis_angle, pose_to_matrix,
                                        rotation_distance)

FEATURES = ("centre", "top_face", "support_plane", "major_axis")
SQUARE_RATIO = 0.85  # short / long side at or above this: a quarter turn looks the same
ROUND_RATIO = 0.95   # ... and at or above this (and no visible corners): treated as round


class AnchorError(ValueError):
    """A rule cannot be bound: its object was not found, or is ambiguous, or its feature is unknown."""


@dataclass
class Anchor:
    """What binding needs of one object: its box (centre, axes, full extents, base frame) and the
    support plane's unit normal. ``symmetry``: "box" (half turn), "square" (quarter turn) or
    "round" (any turn: the frame's x points from the anchor toward the reference TCP)."""

    center: np.ndarray
    axes: np.ndarray
    extents: np.ndarray
    normal: np.ndarray
    symmetry: str = "box"
    name: str = ""

    @staticmethod
    def from_cluster(cluster, plane_normal: Sequence[float], name: str = "") -> "Anchor":
        box = cluster.obb
        ext = np.asarray(box.extents, dtype=float)
        ratio = float(ext[1] / ext[0]) if ext[0] > 1e-9 else 1.0
        round_shape = getattr(cluster, "shape_name", "") in ("disc", "cylinder", "bowl", "plate", "ball", "cup", "mug")
        symmetry = "round" if (ratio >= ROUND_RATIO or (round_shape and ratio >= SQUARE_RATIO)) else (
            "square" if ratio >= SQUARE_RATIO else "box")
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
    d = None
    if reference is not None:
        d = _in_plane(reference[:3, 3] - a.center, z)
        if float(np.linalg.norm(d)) < NEAR_ABOVE_M:
            d = _in_plane(reference[:3, 0], z)
        if float(np.linalg.norm(d)) < 1e-9:
            d = None
    if a.symmetry == "round":
        x = _unit(d if d is not None else _in_plane(a.axes[:, 0], z))
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


def bind(rule: dict, anchor: Anchor, reference: Optional[Sequence[float]] = None) -> np.ndarray:
    """``base_from_tcp`` (4x4) that ``rule`` asks for with ``anchor`` as seen now. ``reference``:
    the TCP pose measured when the stage began (``[x, y, z, ax, ay, az]`` or 4x4); it settles the
    anchor's symmetric frames, and of the two gripper turns (the same grasp) the one nearer its
    orientation is taken."""
    ref = _as_matrix(reference)
    T = frame(anchor, rule["anchor"]["feature"], ref) @ tcp_in_anchor(rule) @ np.linalg.inv(actor_from_tcp(rule))
    if ref is not None:
        turned = T @ HALF_TURN_Z
        if rotation_distance(ref[:3, :3], turned[:3, :3]) < rotation_distance(ref[:3, :3], T[:3, :3]) - 1e-12:
            T = turned
    return T


def relate(target: np.ndarray, anchor: Anchor, feature: str, reference: Optional[Sequence[float]] = None,
           actor: str = "tcp") -> dict:
    """The rule fields (actor, anchor feature, offset_m, yaw_rad, tilt_rad) that put the TCP at
    ``target`` (4x4, base frame) from this anchor with this reference: the inverse of `bind`
    (up to the gripper's half turn)."""
    at = actor_from_tcp({"actor": actor})
    L = np.linalg.inv(frame(anchor, feature, _as_matrix(reference))) @ np.asarray(target, dtype=float) @ at
    return {"actor": actor, "anchor": {"feature": feature}, "offset_m": [float(v) for v in L[:3, 3]],
            **_split_yaw(L[:3, :3])}


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
