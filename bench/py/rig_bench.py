"""The rig's figures without hardware (issue 18), each against its simulated counterpart in the
same run. Synthetic throughout: the gripper is OUR simulator (rig/py/robotiq_sim.py) on a socat
pty, the camera host replays sim-host renders through librealsense's software device.

    .venv/bin/python bench/py/rig_bench.py [--rounds 10] [--seconds 5]

- gripper: open / close on an object / open round trips through `robo` (post → reply), the same
  moves with the simulated gripper of r2g-sim as the baseline, r2g-robotiq's own Modbus poll
  round trip and move times (its stats line), and how long after the port vanishes mid-grasp
  the running chunk fails;
- cameras: one instance where sim-host renders `agentview` and a camera host publishes `wrist`
  (replayed at the same rate): frame rate seen by `robo` and frame age when read (robot time of
  the state minus the frame's time: capture → agent, on the runtime's clock), side by side.

Prints a table, then one JSON object as the last line.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "python"))

import robo  # noqa: E402
from conftest import Instance, robo_instance  # noqa: E402
from robotiq_rig import Rig, gripper_move, wait_for  # noqa: E402
from test_camera_host import stop, up  # noqa: E402


def q(v: list[float], f: float) -> float:
    return float(np.percentile(v, f)) if v else float("nan")


def gripper_rounds(rounds: int, object_at=None, rig: Rig | None = None) -> dict:
    out = {"open_ms": [], "close_ms": [], "holding": 0}
    for _ in range(rounds):
        ok, dt, _ = gripper_move(robo, -1.0)
        assert ok == 1
        out["open_ms"].append(dt * 1e3)
        ok, dt, s = gripper_move(robo, 1.0)
        assert ok == 1, s["control_feedback"]
        out["close_ms"].append(dt * 1e3)
        out["holding"] += s["control_feedback"]["grasp"]["status"] == "holding"
    gripper_move(robo, -1.0)
    return out


def bench_gripper(tmp: Path, rounds: int) -> dict:
    res = {}
    # Baseline: r2g-sim's simulated fingers closing on the free air (no object in reach).
    inst = Instance(f"rb{os.getpid()}s", "wall")
    try:
        with robo_instance(inst.name):
            res["sim"] = gripper_rounds(rounds)
    finally:
        inst.stop()
    name = f"rb{os.getpid()}r"
    rig = Rig(tmp, name)
    try:
        with robo_instance(name):
            wait_for("activation", lambda: robo.get_state([])["fault"] is None)
            rig.control(object_at=120)
            res["robotiq"] = gripper_rounds(rounds)
            # The port vanishes 0.25 s into a close.
            gripper_move(robo, -1.0)
            t = {}
            timer = threading.Timer(0.25, lambda: (t.setdefault("t", time.monotonic()), rig.unplug()))
            timer.start()
            qq = list(robo.get_state([])["joint"])
            qq[6] += 0.3
            ok = robo.post_actions({"actions": [qq + [1.0]], "type": "joint", "freq": 1.0})
            timer.join()
            fb = robo.get_state([])["control_feedback"]
            res["unplug"] = {"ok": ok, "fail_after_ms": (time.monotonic() - t["t"]) * 1e3, "reason": fb["reason"]}
    finally:
        rig.close()
    m = re.findall(r"r2g-robotiq: stats (\{.*\})", (tmp / "r2g-up.log").read_text())
    res["driver"] = json.loads(m[-1]) if m else None
    return res


def frame_stats(cam: str, seconds: float) -> dict:
    stamps, ages = set(), []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        s = robo.get_state([cam], raw=True)
        ts = s["image_timestamp"][cam]
        if ts not in stamps:
            stamps.add(ts)
            ages.append((s["timestamp"] - ts) * 1e3)
        time.sleep(0.005)
    return {"fps": (len(stamps) - 1) / seconds, "age_ms_p50": q(ages, 50), "age_ms_p99": q(ages, 99)}


def bench_cameras(tmp: Path, seconds: float, hz: int) -> dict:
    inst = Instance(f"rb{os.getpid()}g", "wall")
    try:
        with robo_instance(inst.name):
            s = robo.get_state(["wrist"], raw=True)
    finally:
        inst.stop()
    k = s["camera_intrinsics"]["wrist"]
    np.savez(tmp / "wrist.npz", rgb=s["image"]["wrist"], depth_m=s["depth"]["wrist"],
             fx=k["fx"], fy=k["fy"], cx=k["cx"], cy=k["cy"])
    ft = np.asarray(s["calibration"]["tcp"]["flange_from_tcp"])
    (tmp / "wrist.json").write_text(json.dumps({"flange_from_camera": ft.tolist()}))
    name = f"rb{os.getpid()}c"
    p = up(tmp, name, {"wrist": {"driver": "replay", "file": "wrist.npz", "fps": hz}}, render_hz=hz)
    try:
        line = p.stdout.readline()
        assert line.strip() == f"READY {name}", line
        with robo_instance(name):
            return {"sim_host agentview": frame_stats("agentview", seconds),
                    "camera host wrist": frame_stats("wrist", seconds)}
    finally:
        stop(p)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--hz", type=int, default=15)
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="rig-bench-"))
    g = bench_gripper(tmp, a.rounds)
    c = bench_cameras(tmp, a.seconds, a.hz)
    print("gripper round trips through robo (post -> reply), ms   p50     p99")
    for side in ("sim", "robotiq"):
        for move in ("open_ms", "close_ms"):
            v = g[side][move]
            print(f"  {side:8s} {move[:-3]:6s}                               {q(v, 50):7.1f} {q(v, 99):7.1f}")
    print(f"  robotiq closes reporting an object: {g['robotiq']['holding']}/{a.rounds}")
    d = g["driver"] or {}
    if d:
        print(f"  r2g-robotiq Modbus poll round trip us: p50 {d['poll_us']['p50']} p99 {d['poll_us']['p99']} "
              f"max {d['poll_us']['max']}; crc errors {d['crc_errors']}, timeouts {d['timeouts']}")
    print(f"  port gone mid-grasp: chunk failed {g['unplug']['fail_after_ms']:.0f} ms later: {g['unplug']['reason']}")
    print(f"cameras over {a.seconds:.0f} s at {a.hz} Hz         fps   age p50 ms  age p99 ms")
    for cam, v in c.items():
        print(f"  {cam:22s} {v['fps']:6.1f} {v['age_ms_p50']:10.1f} {v['age_ms_p99']:10.1f}")
    print(json.dumps({"gripper": g, "cameras": c}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
