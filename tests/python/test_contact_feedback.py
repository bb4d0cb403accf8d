"""The force felt during a chunk comes back in its `control_feedback["contact"]` (peak and mean
magnitude of the filtered external force, N, and the waypoint at the peak): a free move, a push
of a light object (push_to_line's 60 g block) and a press onto a fixed part (close_cabinet's
carcass top) tell three different stories, though the reading after each chunk is 0 for the
first two. Measured here: free 0 N; the push 3-4 N mean, 7-17 N peak (several times the
0.47 N the block's sliding friction takes, block-table friction being max(0.6, 0.8): the
fingers' friction, 1.2 in sim-host/src/mjcf.rs, drags the rocking block's face down into the
table, F = mu_t m g / (1 - mu_t mu_f) ~ 12 N once both friction limits are reached; a replay
with frictionless fingers peaks at 0.5 N); the press
77 N mean, 164 N peak. Live lockstep instances, real MuJoCo contact; the
bounds are wide (physics, not timing)."""
from __future__ import annotations

import math
from typing import Iterator

import pytest
import robo

from conftest import _instance


def line(start: list[float], goal: list[float], g: float, step: float = 0.005) -> list[list[float]]:
    n = max(1, math.ceil(math.dist(start[:3], goal[:3]) / step))
    return [[s + (e - s) * k / n for s, e in zip(start[:3], goal[:3])] + list(goal[3:]) + [g] for k in range(1, n + 1)]


def move(goal_xyz: list[float], g: float) -> dict:
    """One ee_pose chunk to goal (orientation kept); the chunk's control_feedback."""
    ee = robo.get_state([])["ee_pose"]
    robo.post_actions({"actions": line(ee, goal_xyz + ee[3:], g), "type": "ee_pose", "freq": ""})
    return robo.get_state([])["control_feedback"]


@pytest.fixture(scope="module")
def push_gym() -> Iterator:
    yield from _instance("lockstep", "cf1", gym="push_to_line")


@pytest.fixture(scope="module")
def cabinet_gym() -> Iterator:
    yield from _instance("lockstep", "cf2", gym="close_cabinet")


def test_a_free_move_and_a_light_push_read_apart(push_gym) -> None:
    assert robo.reset() == 1
    free = move([0.36, -0.05, 0.30], 1.0)  # in the air, the fingers shut as the task starts
    assert free["status"] == "executed", free
    assert free["contact"]["peak_n"] < 0.05, free["contact"]
    if free["contact"]["peak_n"] == 0.0:
        assert free["contact"]["peak_waypoint"] is None, free["contact"]  # nothing felt: no waypoint
    above = move([0.36, -0.05, 0.025], 1.0)  # behind the block (its near face at x = 0.395)
    assert above["status"] == "executed" and above["contact"]["peak_n"] < 0.05, above
    # Push 8 cm along +x: the closed fingers meet the block after about 2 cm and slide it.
    push = move([0.44, -0.05, 0.025], 1.0)
    c = push["contact"]
    assert 0.15 < c["mean_n"] < 15.0 and 0.2 < c["peak_n"] < 40.0, c
    assert c["start_n"] < 0.05, c  # it started from nothing: the whole peak is the push's
    assert c["peak_waypoint"] >= 3, c  # felt once the fingers reached the block, not at the start
    after = robo.get_state([])["external_force_n"]
    assert math.hypot(*after) < 0.05, after  # after the chunk nothing presses: the reading alone would say 0


def test_a_press_onto_a_fixed_part_reads_far_above_a_push(cabinet_gym) -> None:
    assert robo.reset() == 1
    above = move([0.72, -0.10, 0.35], 1.0)  # over the carcass top (z 0.30), fingers shut
    assert above["status"] == "executed" and above["contact"]["peak_n"] < 0.05, above
    press = move([0.72, -0.10, 0.292], 1.0)  # 8 mm into the top board: it stops the hand
    c = press["contact"]
    assert c["peak_n"] > 60.0 and c["mean_n"] > 20.0, press
    assert c["peak_waypoint"] >= 1, c
    # A move straight back up starts where the press left off: start_n carries it, so what that
    # chunk added (peak_n - start_n) is about nothing, though its peak alone reads tens of newtons.
    back = move([0.72, -0.10, 0.35], 1.0)
    b = back["contact"]
    assert back["status"] == "executed" and b["start_n"] > 20.0, back
    assert b["peak_n"] - b["start_n"] < 1.0, b
