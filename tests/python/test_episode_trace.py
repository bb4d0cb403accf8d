"""A live episode through `r2g up --trace-dir`: the agent only posts actions through `robo`;
sim-host records the native trace and the evaluator judges each episode when it ends."""
from __future__ import annotations

import csv
import json
import os
import subprocess
from pathlib import Path

import robo
from conftest import R2G, ROOT, Instance


def test_a_live_lockstep_episode_is_judged_from_its_native_trace(tmp_path: Path) -> None:
    demo = ROOT / "gyms" / "pick_block_plate" / "demo.csv"
    with demo.open() as f:
        rows = [[float(x) for x in r] for r in csv.reader(f) if r and not r[0].startswith("q")]
    inst = Instance(f"py{os.getpid()}t", "lockstep", extra=("--trace-dir", str(tmp_path)))
    previous = os.environ.get("R2G_INSTANCE")
    os.environ["R2G_INSTANCE"] = inst.name
    try:
        for _ in range(2):  # episodes 1 and 2: the same actions
            # Chunks of 256, as `r2g replay` posts them.
            for start in range(0, len(rows), 256):
                assert robo.post_actions({"actions": rows[start : start + 256], "type": "joint", "freq": ""}) == 1
            # Nothing privileged came back: the state has no object poses.
            assert "objects" not in robo.get_state(cameras=[])
            robo.reset()
        # Episode 3: doing nothing at all.
    finally:
        inst.stop()  # ends episode 2
        if previous is None:
            os.environ.pop("R2G_INSTANCE", None)
        else:
            os.environ["R2G_INSTANCE"] = previous
    first = json.loads((tmp_path / "episode-1.eval.json").read_text())
    assert first["success"] is True, first
    assert first["checks"]["on:block:plate"]["pass"] is True
    trace = json.loads((tmp_path / "episode-1.trace.json").read_text())
    assert trace["objects"] == ["block", "plate"] and len(trace["samples"]) == first["samples"]
    # Lockstep across the real processes: same scene, same actions, the same trace.
    second = json.loads((tmp_path / "episode-2.eval.json").read_text())
    assert second["success"] is True and second["trace_sha256"] == first["trace_sha256"], second
    idle = json.loads((tmp_path / "episode-3.eval.json").read_text())
    assert idle["success"] is False, idle
    assert idle["criteria_sha256"] == first["criteria_sha256"]
    # The in-process replay (same controller and physics, no shared memory) records the same
    # samples; it only holds 1 s longer at the end.
    out = tmp_path / "replay"
    done = subprocess.run([str(R2G), "replay", "pick_block_plate", "--out", str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    replayed = json.loads((out / "pick_block_plate-seed0.trace.json").read_text())["samples"]
    live = trace["samples"]
    assert len(replayed) > len(live) > 1000
    assert replayed[: len(live)] == live, "live lockstep and in-process replay diverge"
