"""The tick path allocates nothing, while it serves chunks, resets and rejections."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import tempfile
import time

import robo
from conftest import ROOT

SCENE = str(ROOT / "gyms" / "pick_block_plate" / "scene.toml")
BIN = ROOT / "target" / "release"


def test_no_allocation_inside_ticks_while_serving_requests() -> None:
    name = f"alloc{os.getpid()}"
    stats = os.path.join(tempfile.mkdtemp(), "stats.json")
    sim = subprocess.Popen([str(BIN / "r2g-sim"), SCENE, "--instance", name, "--render-hz", "5"], stdin=subprocess.DEVNULL)
    control = subprocess.Popen(
        [str(BIN / "r2g-control"), SCENE, "--instance", name, "--stats-out", stats], stdin=subprocess.DEVNULL
    )
    previous = os.environ.get("R2G_INSTANCE")
    os.environ["R2G_INSTANCE"] = name
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                start = robo.get_state([])["joint"]
                break
            except ConnectionError:
                assert time.monotonic() < deadline, "runtime never came up"
                time.sleep(0.2)
        goal = [0.2, -0.6, 0.1, -2.2, 0.0, 1.7, 0.9]
        chunk = [[s + (g - s) * (k + 1) / 10 for s, g in zip(start, goal)] + [1.0] for k in range(10)]
        assert robo.post_actions({"actions": chunk, "type": "joint", "freq": ""}) == 1
        assert robo.post_actions({"actions": [[9.0] * 8], "type": "joint", "freq": ""}) == 0
        assert robo.reset() == 1
        assert robo.post_actions({"actions": chunk, "type": "joint", "freq": "50"}) == 1
        # ee_pose chunks, whose checks solve IK along the path on the planner thread: one out of
        # reach (refused with the reason, nothing moved) and one that runs.
        assert robo.reset() == 1
        ee = robo.get_state([])["ee_pose"]
        far = [[ee[0] + 0.04 * (k + 1), ee[1], ee[2]] + ee[3:] + [-1.0] for k in range(50)]
        assert robo.post_actions({"actions": far, "type": "ee_pose", "freq": ""}) == 0
        assert "not reachable" in robo.get_state([])["control_feedback"]["reason"]
        near = [[ee[0], ee[1] + 0.01 * (k + 1), ee[2]] + ee[3:] + [1.0] for k in range(5)]
        assert robo.post_actions({"actions": near, "type": "ee_pose", "freq": ""}) == 1
    finally:
        if previous is None:
            os.environ.pop("R2G_INSTANCE", None)
        else:
            os.environ["R2G_INSTANCE"] = previous
        control.send_signal(signal.SIGTERM)
        control.wait(timeout=15)
        sim.send_signal(signal.SIGTERM)
        sim.wait(timeout=15)
    with open(stats) as f:
        figures = json.load(f)
    assert figures["ticks"] > 1000
    assert figures["tick_allocations"] == 0, figures
    # Every chunk was checked off the tick, on the planner thread.
    assert figures["acceptance"] == "planner"
    assert figures["planning"]["count"] == 5, figures["planning"]
