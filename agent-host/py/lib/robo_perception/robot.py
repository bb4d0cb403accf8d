"""The robot's own body: a description of the Franka Panda with the Franka Hand (joint frames and
the capsules and boxes that make up its shape), forward kinematics from the measured joints, and
`robot_mask`, the self-filter that tells which 3D points lie on the robot.

Segmentation uses the mask to drop the arm and the hand before it looks for objects, so no part
of the robot is ever reported as an object. Everything is in the robot base frame. The numbers
follow the project's Panda description (``robots/panda/panda.urdf``, which a stage program cannot
read, hence the copy here; a test compares the two). The shapes are the description's collision
capsules and finger boxes, and capsules that enclose the meshes the cameras see (the real Panda
and Franka Hand meshes, drawn since they replaced the capsules in the pictures; made by
``robots/envelopes.py``, checked against every mesh vertex by a test). A capsule is a segment of
``length`` along its local z with radius ``radius`` around it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from .hand import FRANKA_HAND, HandGeometry, gripper_to_width
from .transforms import ArrayLike, matrix_to_pose

SELF_FILTER_MARGIN = 0.005
"""How far outside the robot's shapes a point still counts as the robot (m)."""
SELF_FILTER_FINGER_MARGIN = 0.002
"""The same on the fingers' inner faces, where a held object touches them (m)."""
SELF_FILTER_GUARD_MARGIN = 0.0003
"""The same outside the fingertip guard between the fingers, where a held object's faces run
along the guard's surface (m)."""

_HALF_PI = math.pi / 2.0
_QUARTER_PI = math.pi / 4.0


@dataclass(frozen=True)
class RobotJoint:
    """A joint placing ``child`` in ``parent``'s frame: translate by ``xyz``, turn by the fixed-axis
    roll-pitch-yaw ``rpy``, then move by the joint value about (revolute) or along (prismatic)
    ``axis``. ``kind`` "fixed" joints do not move."""

    name: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    kind: str = "revolute"


@dataclass(frozen=True)
class RobotCapsule:
    """A capsule of a link: centre ``xyz`` and orientation ``rpy`` in the link frame, its straight
    part ``length`` long along the local z, radius ``radius``. ``guard``: the rounded guard across
    the fingertips, whose middle passes through the space between the fingers (there only its
    surface counts, so that a held object inside it is not taken for the robot). ``drawn``: not
    in the description; it encloses (part of) the link's drawn mesh."""

    link: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    radius: float
    length: float
    guard: bool = False
    drawn: bool = False


@dataclass(frozen=True)
class RobotDescription:
    """Kinematic tree (``joints`` listed parents first, from ``base_link``), body shapes and the
    gripper. ``arm_joints``: the measured joints in ``state["joint"]`` order; ``finger_joints``:
    the prismatic fingers, each opened by half the finger opening; ``finger_box_center`` and
    ``finger_box_size``: the box of each finger in its own frame (its inner face at local y = 0);
    ``tcp_link``: the frame of ``ee_pose``; ``hand``: the gripper model (stroke, guard);
    ``finger_drawn_size``: the box of a finger's drawn mesh (inner face and base as the finger
    box's, centred across), which the self-filter's finger box grows to."""

    joints: tuple[RobotJoint, ...]
    capsules: tuple[RobotCapsule, ...]
    arm_joints: tuple[str, ...]
    finger_joints: tuple[str, ...]
    finger_box_center: tuple[float, float, float]
    finger_box_size: tuple[float, float, float]
    tcp_link: str
    base_link: str = "link0"
    hand: HandGeometry = FRANKA_HAND
    finger_drawn_size: Optional[tuple[float, float, float]] = None

    def filter_finger_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Centre and size of the finger box the self-filter uses: the finger box grown to the
        drawn finger, its inner face (local y = 0) and base kept."""
        size = np.asarray(self.finger_box_size, dtype=float)
        centre = np.asarray(self.finger_box_center, dtype=float)
        if self.finger_drawn_size is None:
            return centre, size
        grown = np.maximum(size, self.finger_drawn_size)
        lo = centre - 0.5 * size
        return np.array([centre[0], lo[1] + 0.5 * grown[1], lo[2] + 0.5 * grown[2]]), grown

    def joint(self, name: str) -> RobotJoint:
        """The joint called ``name``."""
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(name)


def _finger_box(hand: HandGeometry) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """A finger's box (centre, size) in its frame from the hand model: the inner face at the
    joint's origin, the box reaching `finger_length` out along the approach."""
    size = (2.0 * hand.finger_half_depth, hand.finger_thickness, hand.finger_length)
    return (0.0, 0.5 * size[1], 0.5 * size[2]), size


_FINGER_CENTER, _FINGER_SIZE = _finger_box(FRANKA_HAND)

PANDA = RobotDescription(
    joints=(
        RobotJoint("joint1", "link0", "link1", (0.0, 0.0, 0.333)),
        RobotJoint("joint2", "link1", "link2", (0.0, 0.0, 0.0), (-_HALF_PI, 0.0, 0.0)),
        RobotJoint("joint3", "link2", "link3", (0.0, -0.316, 0.0), (_HALF_PI, 0.0, 0.0)),
        RobotJoint("joint4", "link3", "link4", (0.0825, 0.0, 0.0), (_HALF_PI, 0.0, 0.0)),
        RobotJoint("joint5", "link4", "link5", (-0.0825, 0.384, 0.0), (-_HALF_PI, 0.0, 0.0)),
        RobotJoint("joint6", "link5", "link6", (0.0, 0.0, 0.0), (_HALF_PI, 0.0, 0.0)),
        RobotJoint("joint7", "link6", "link7", (0.088, 0.0, 0.0), (_HALF_PI, 0.0, 0.0)),
        RobotJoint("flange", "link7", "link8", (0.0, 0.0, 0.107), kind="fixed"),
        RobotJoint("hand_joint", "link8", "hand", (0.0, 0.0, 0.0), (0.0, 0.0, -_QUARTER_PI), kind="fixed"),
        RobotJoint("tcp_joint", "hand", "hand_tcp", (0.0, 0.0, 0.1034), kind="fixed"),
        RobotJoint("finger_joint1", "hand", "finger_left", (0.0, 0.0, 0.0584), axis=(0.0, 1.0, 0.0),
                   kind="prismatic"),
        RobotJoint("finger_joint2", "hand", "finger_right", (0.0, 0.0, 0.0584), (0.0, 0.0, math.pi),
                   axis=(0.0, 1.0, 0.0), kind="prismatic"),
    ),
    capsules=(
        RobotCapsule("link0", (-0.075, 0.0, 0.06), (0.0, _HALF_PI, 0.0), 0.06, 0.03),
        RobotCapsule("link1", (0.0, 0.0, -0.1915), (0.0, 0.0, 0.0), 0.06, 0.283),
        RobotCapsule("link2", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.06, 0.12),
        RobotCapsule("link3", (0.0, 0.0, -0.145), (0.0, 0.0, 0.0), 0.06, 0.15),
        RobotCapsule("link4", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.06, 0.12),
        RobotCapsule("link5", (0.0, 0.0, -0.26), (0.0, 0.0, 0.0), 0.06, 0.1),
        RobotCapsule("link5", (0.0, 0.08, -0.13), (0.0, 0.0, 0.0), 0.025, 0.14),
        RobotCapsule("link6", (0.0, 0.0, -0.03), (0.0, 0.0, 0.0), 0.05, 0.08),
        RobotCapsule("link7", (0.0, 0.0, 0.01), (0.0, 0.0, _QUARTER_PI), 0.04, 0.14),
        RobotCapsule("link7", (0.03 * math.sqrt(2.0), 0.03 * math.sqrt(2.0), 0.082), (0.0, _HALF_PI, _QUARTER_PI),
                     0.03, 0.01),
        RobotCapsule("hand", (0.0, 0.0, 0.04), (_HALF_PI, 0.0, 0.0), 0.04, 0.1),
        RobotCapsule("hand", (0.0, 0.0, 0.1034 - FRANKA_HAND.envelope_behind_tcp), (_HALF_PI, 0.0, 0.0),
                     FRANKA_HAND.envelope_radius, 2.0 * FRANKA_HAND.envelope_half_length, guard=True),
        # the drawn meshes (robots/envelopes.py)
        RobotCapsule("link0", (-0.0286, 0.0, 0.0331), (0.0, 2.1561, -3.1396), 0.106, 0.068, drawn=True),
        RobotCapsule("link1", (-0.0004, -0.0273, -0.07), (0.0, 0.3511, -1.5483), 0.078, 0.152, drawn=True),
        RobotCapsule("link2", (-0.0003, -0.0701, 0.0269), (0.0, 1.217, 1.5702), 0.078, 0.154, drawn=True),
        RobotCapsule("link3", (0.0423, 0.0219, -0.0411), (0.0, 2.3066, -2.6701), 0.071, 0.123, drawn=True),
        RobotCapsule("link4", (-0.0406, 0.0418, 0.0215), (0.0, 1.9167, 2.3407), 0.071, 0.125, drawn=True),
        RobotCapsule("link5", (0.0, 0.0371, -0.1204), (0.0, 0.2137, 1.5769), 0.069, 0.251, drawn=True),
        RobotCapsule("link6", (0.0957, -0.0235, -0.0025), (0.0, 1.3988, -2.2154), 0.049, 0.038, drawn=True),
        RobotCapsule("link6", (0.0403, 0.0129, 0.0075), (0.0, 1.3939, -2.7826), 0.060, 0.082, drawn=True),
        RobotCapsule("link7", (0.0138, 0.014, 0.0771), (0.0, 1.7212, -2.3607), 0.051, 0.054, drawn=True),
        RobotCapsule("hand", (0.0, -0.0766, 0.013), (0.0, 0.0949, -1.5712), 0.031, 0.064, drawn=True),
        RobotCapsule("hand", (0.0006, 0.0234, 0.0271), (0.0, 1.5424, 1.6038), 0.046, 0.101, drawn=True),
    ),
    arm_joints=("joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "joint7"),
    finger_joints=("finger_joint1", "finger_joint2"),
    finger_box_center=_FINGER_CENTER,
    finger_box_size=_FINGER_SIZE,
    tcp_link="hand_tcp",
    finger_drawn_size=(0.0212, 0.0265, 0.054),
)
"""The Franka Panda with the Franka Hand, as the gyms simulate it (robots/panda/panda.urdf)."""


def rpy_to_matrix(rpy: ArrayLike) -> np.ndarray:
    """Fixed-axis roll, pitch, yaw -> 3x3 rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    r, p, y = (float(a) for a in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _origin(xyz: ArrayLike, rpy: ArrayLike) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(rpy)
    T[:3, 3] = np.asarray(xyz, dtype=float)
    return T


def _joint_motion(j: RobotJoint, q: float) -> np.ndarray:
    T = np.eye(4)
    if j.kind == "fixed" or q == 0.0:
        return T
    a = np.asarray(j.axis, dtype=float)
    if j.kind == "prismatic":
        T[:3, 3] = a * q
        return T
    # revolute: Rodrigues about the unit axis
    k = a / np.linalg.norm(a)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    T[:3, :3] = np.eye(3) + math.sin(q) * K + (1.0 - math.cos(q)) * (K @ K)
    return T


def link_poses(joints: Sequence[float], gripper: Optional[float] = None,
               robot: RobotDescription = PANDA) -> dict[str, np.ndarray]:
    """Forward kinematics: each link's 4x4 pose in the base frame from the measured arm joints
    (``state["joint"]``, rad) and the gripper value (``state["gripper"][0]``, -1 open ... +1
    closed, or the list ``state["gripper"]``; None: fully open)."""
    q = [float(v) for v in joints]
    if len(q) != len(robot.arm_joints):
        raise ValueError(f"expected {len(robot.arm_joints)} joint values, got {len(q)}")
    values: dict[str, float] = dict(zip(robot.arm_joints, q))
    if isinstance(gripper, (list, tuple, np.ndarray)):   # state["gripper"] is a one-element list
        gripper = float(np.asarray(gripper, dtype=float).ravel()[0])
    half = 0.5 * gripper_to_width(-1.0 if gripper is None else gripper, robot.hand)
    for f in robot.finger_joints:
        values[f] = half
    poses = {robot.base_link: np.eye(4)}
    for j in robot.joints:
        poses[j.child] = poses[j.parent] @ _origin(j.xyz, j.rpy) @ _joint_motion(j, values.get(j.name, 0.0))
    return poses


def tcp_matrix(joints: Sequence[float], robot: RobotDescription = PANDA) -> np.ndarray:
    """4x4 TCP pose in the base frame from the measured arm joints."""
    return link_poses(joints, None, robot)[robot.tcp_link]


def tcp_pose(joints: Sequence[float], robot: RobotDescription = PANDA) -> list[float]:
    """TCP pose ``[x, y, z, ax, ay, az]`` (as ``state["ee_pose"]``) from the measured arm joints."""
    return matrix_to_pose(tcp_matrix(joints, robot))


@dataclass
class RobotShapes:
    """The robot's shapes posed in the base frame: capsule segments (start ``a``, unit direction
    ``u``, ``length``, ``radius``, ``guard`` flags; one row each), the TCP pose, each finger's
    frame (4x4) and the finger opening (m)."""

    a: np.ndarray
    u: np.ndarray
    length: np.ndarray
    radius: np.ndarray
    guard: np.ndarray
    tcp: np.ndarray
    fingers: list
    opening: float


def robot_shapes(joints: Sequence[float], gripper: Optional[float] = None,
                 robot: RobotDescription = PANDA) -> RobotShapes:
    """Poses every capsule of ``robot`` for the given joints (see `link_poses`)."""
    poses = link_poses(joints, gripper, robot)
    a, u = [], []
    for c in robot.capsules:
        T = poses[c.link] @ _origin(c.xyz, c.rpy)
        axis = T[:3, 2]
        a.append(T[:3, 3] - 0.5 * c.length * axis)
        u.append(axis)
    return RobotShapes(a=np.array(a), u=np.array(u), length=np.array([c.length for c in robot.capsules]),
                       radius=np.array([c.radius for c in robot.capsules]),
                       guard=np.array([c.guard for c in robot.capsules]), tcp=poses[robot.tcp_link],
                       fingers=[poses[robot.joint(f).child] for f in robot.finger_joints],
                       opening=gripper_to_width(-1.0 if gripper is None else gripper, robot.hand))


def _capsule_d2(P: np.ndarray, shapes: RobotShapes) -> np.ndarray:
    """(N, K) squared distance of each point to each capsule's axis segment."""
    o = shapes.a.mean(axis=0)                                     # near the robot: less cancellation
    X = P - o
    A = shapes.a - o
    t = X @ shapes.u.T                                            # (N, K) along each axis ...
    t -= np.einsum("kj,kj->k", A, shapes.u)                       # ... from its start
    d2 = X @ (-2.0 * A.T)
    d2 += np.einsum("ij,ij->i", X, X)[:, None]
    d2 += np.einsum("kj,kj->k", A, A)[None, :]                    # |P - a|^2
    tc = np.clip(t, 0.0, shapes.length[None, :])
    t *= -2.0
    t += tc
    t *= tc
    d2 += t                                                       # |P - a - tc u|^2
    return d2


def capsule_distances(points: ArrayLike, shapes: RobotShapes) -> np.ndarray:
    """(N, K) distance of each point to each capsule's axis segment (subtract ``shapes.radius`` for
    the distance to the surface)."""
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    return np.sqrt(np.maximum(_capsule_d2(P, shapes), 0.0))


def _on_robot(P: np.ndarray, s: RobotShapes, robot: RobotDescription, margin: float,
              finger_margin: float, guard_margin: float) -> np.ndarray:
    """The exact test of `robot_mask` for points ``P`` (N, 3) against posed ``s``. Every part
    of it grows with the margins and changes by at most 1 m per metre the point moves, which is
    what lets `robot_mask` decide whole cubes of points from their centres."""
    d2 = _capsule_d2(P, s)                                        # squared, to the axes
    solid = ~s.guard
    reach = s.radius[solid] + margin
    hit = np.any(d2[:, solid] <= np.where(reach >= 0.0, reach * reach, -1.0)[None, :], axis=1)
    if s.guard.any():
        g = np.sqrt(np.maximum(d2[:, s.guard], 0.0)) - s.radius[s.guard][None, :]  # to its surface
        T = s.tcp                                                 # TCP frame: y along the fingers
        y = (P - T[:3, 3]) @ T[:3, 1]
        between = np.abs(y) < 0.5 * s.opening - finger_margin
        inside = np.where(between[:, None], (g <= guard_margin) & (g >= -margin), g <= margin)
        hit |= np.any(inside, axis=1)
    # fingers: each finger's box in its own frame, its inner face (local y low) grown less
    c, size = robot.filter_finger_box()
    h = 0.5 * size
    lo_b = c - h - np.array([margin, finger_margin, margin])
    hi_b = c + h + margin
    for f in s.fingers:
        F = (P - f[:3, 3]) @ f[:3, :3]
        hit |= np.all((F >= lo_b) & (F <= hi_b), axis=1)
    return hit


def robot_mask(points: ArrayLike, joints: Sequence[float], gripper: Optional[float] = None,
               margin: float = SELF_FILTER_MARGIN, finger_margin: float = SELF_FILTER_FINGER_MARGIN,
               guard_margin: float = SELF_FILTER_GUARD_MARGIN, robot: RobotDescription = PANDA,
               cell: float = 0.003) -> np.ndarray:
    """Boolean mask of the ``points`` (N, 3; base frame) that lie on the robot: within ``margin``
    of any link capsule or the hand body, or on a finger (its box grown by ``margin``, but only by
    ``finger_margin`` on the inner face that touches a held object).

    The robot is posed from the measured ``joints`` (7, rad) and ``gripper`` (-1 open ... +1
    closed; None: taken as fully open). Between the fingers only the surface of the fingertip
    guard counts (up to ``guard_margin`` outside it), so an object held there is kept.

    Speed: points are binned in cubes of side ``cell``; a cube whose centre passes the test
    with every margin shrunk by the cube's half diagonal is on the robot as a whole, one whose
    centre fails it with the margins grown by as much is off it, and only the points of the
    remaining cubes are tested one by one (the result is the same as testing every point).
    ``cell`` 0: test every point.
    """
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.zeros(len(P), dtype=bool)
    if len(P) == 0:
        return out
    s = robot_shapes(joints, gripper, robot)
    # the whole robot lies in the box around its capsules and fingers; only points there count
    reach = (s.radius + margin)[:, None]
    b = s.a + s.u * s.length[:, None]
    lo = np.minimum(s.a, b) - reach
    hi = np.maximum(s.a, b) + reach
    fsize = float(np.linalg.norm(robot.filter_finger_box()[1])) + margin
    corners = [f[:3, 3] for f in s.fingers]
    lo = np.vstack([lo] + [c - fsize for c in corners]).min(axis=0)
    hi = np.vstack([hi] + [c + fsize for c in corners]).max(axis=0)
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    near = np.flatnonzero((x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2]))
    if len(near) == 0:
        return out
    Q = P[near]
    first = None
    if cell > 0.0 and len(Q) >= 1000:
        key = ((Q - lo) * (1.0 / cell)).astype(np.int64)          # >= 0 here, so truncation floors
        dims = key.max(axis=0) + 1
        flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
        _, first, inv = np.unique(flat, return_index=True, return_inverse=True)
        if len(first) > 0.4 * len(Q):                             # sparse: cubes do not pay
            first = None
    if first is None:
        out[near] = _on_robot(Q, s, robot, margin, finger_margin, guard_margin)
        return out
    inv = inv.reshape(-1)
    centres = lo + (key[first] + 0.5) * cell
    hd = 0.5 * math.sqrt(3.0) * cell                              # half the cube's diagonal
    surely = _on_robot(centres, s, robot, margin - hd, finger_margin - hd, guard_margin - hd)
    maybe = surely.copy()
    rest = np.flatnonzero(~surely)
    maybe[rest] = _on_robot(centres[rest], s, robot, margin + hd, finger_margin + hd, guard_margin + hd)
    res = surely[inv]
    check = np.flatnonzero(maybe[inv] & ~res)
    if len(check):
        res[check] = _on_robot(Q[check], s, robot, margin, finger_margin, guard_margin)
    out[near] = res
    return out


def robot_distance(points: ArrayLike, joints: Sequence[float], gripper: Optional[float] = None,
                   robot: RobotDescription = PANDA, exact_within: Optional[float] = None) -> np.ndarray:
    """(N,) distance (m) from each base-frame point to the robot's solid shapes posed from the
    measured ``joints``/``gripper``: the link and hand capsules (their surfaces) and the finger
    boxes; 0 inside one. The fingertip guard is left out (between the fingers it is empty space).
    The capsules enclose the drawn meshes with some room, so a point touching the robot reads a
    few millimetres; `segment_scene` uses this for an object's ``in_contact``.

    ``exact_within``: only points within this distance of the box around all the shapes are
    measured exactly; the others get their distance to that box (a lower bound), which is much
    cheaper for large clouds far from the robot. None: every point exactly."""
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(P) == 0:
        return np.zeros(0)
    s = robot_shapes(joints, gripper, robot)
    c, size = robot.filter_finger_box()
    h = 0.5 * size
    out = np.zeros(len(P))
    idx = np.arange(len(P))
    if exact_within is not None:
        b = s.a + s.u * s.length[:, None]
        r = s.radius[:, None]
        fr = float(np.linalg.norm(size))
        lo = np.vstack([np.minimum(s.a, b) - r] + [f[:3, 3] - fr for f in s.fingers]).min(axis=0)
        hi = np.vstack([np.maximum(s.a, b) + r] + [f[:3, 3] + fr for f in s.fingers]).max(axis=0)
        box_d = np.linalg.norm(np.maximum(np.maximum(lo - P, P - hi), 0.0), axis=1)
        idx = np.flatnonzero(box_d <= exact_within)
        out = box_d
        if len(idx) == 0:
            return out
    Q = P[idx]
    solid = ~s.guard
    d = np.sqrt(np.maximum(_capsule_d2(Q, s)[:, solid], 0.0)) - s.radius[solid][None, :]
    near = np.maximum(d.min(axis=1), 0.0)
    for f in s.fingers:
        F = (Q - f[:3, 3]) @ f[:3, :3]
        near = np.minimum(near, np.linalg.norm(np.maximum(np.abs(F - c) - h, 0.0), axis=1))
    out = out.copy() if exact_within is not None else out
    out[idx] = near
    return out
