"""Gripper model: the Franka Hand's stroke and finger/body geometry in the TCP frame, and the
conversion between a finger opening in metres and the `robo` gripper command."""

from __future__ import annotations

from dataclasses import dataclass


GRIPPER_MAX_WIDTH = 0.08
"""Franka Hand stroke: distance between the fingers when fully open (m)."""


@dataclass(frozen=True)
class HandGeometry:
    """Simplified parallel-jaw hand in the TCP frame (z = approach, y = finger axis).

    Lengths in metres. ``tip_beyond_tcp``: how far the fingertips reach past the TCP along the
    approach. The hand body is a box behind the fingers; ``envelope_*`` describes the rounded
    guard around the fingertips that the runtime checks against the table (Panda URDF:
    capsule of radius 2 cm along y, its centre 3.4 mm behind the TCP).
    """

    max_width: float = GRIPPER_MAX_WIDTH
    finger_thickness: float = 0.012      # along y
    finger_half_depth: float = 0.010     # half the pad size along x
    finger_length: float = 0.054         # along z
    tip_beyond_tcp: float = 0.009
    body_half_x: float = 0.045
    body_half_y: float = 0.095
    body_start_behind_tcp: float = 0.0234   # the hand body begins this far behind the TCP
    envelope_radius: float = 0.020
    envelope_half_length: float = 0.050     # half length of the capsule's straight part (y)
    envelope_behind_tcp: float = 0.0034


FRANKA_HAND = HandGeometry()


def width_to_gripper(width: float, hand: HandGeometry = FRANKA_HAND) -> float:
    """Finger opening (m) -> `robo` gripper command (-1 fully open ... +1 closed)."""
    w = min(max(float(width), 0.0), hand.max_width)
    return 1.0 - 2.0 * w / hand.max_width


def gripper_to_width(g: float, hand: HandGeometry = FRANKA_HAND) -> float:
    """`robo` gripper value (-1 open ... +1 closed) -> finger opening in metres."""
    g = min(max(float(g), -1.0), 1.0)
    return 0.5 * (1.0 - g) * hand.max_width
