"""What `get_state()["external_force_n"]` shows, and when it reads zero (simulation).

Runs small chunks in shipped gyms and prints, after each chunk, what a program reads: the chunk's
result and `external_force_n` (base frame, N). With `--mode wall` a second thread also polls
`get_state([])` every few milliseconds *during* each chunk and for 0.3 s after it (a stage
program cannot: `post_actions` blocks until the chunk has ended), to show what happened in
between: the largest force during the chunk and what the value did afterwards.

pick_block_plate: at rest; the closed fingers pressed 4 mm into the block's top and held (a
second chunk to the same pose); lifted clear; the block grasped and lifted 5 cm (its weight);
set down and released; the block pushed 6 cm along the table by the closed fingers, the chunk
ending with the hand stopped where the block left it.
close_cabinet: the door pushed shut along the demonstration's keyframes (closed fingers on its
outer face, 10 degrees per chunk; the door's angle from the native trace), then pressed 1 cm
past shut, against the door's stop.

Usage: contact_force.py [--mode lockstep|wall] [--gyms pick_block_plate,close_cabinet]
(R2G_BIN: the r2g binary.) Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT / "tests" / "python"), str(ROOT / "agent-host" / "py" / "lib")]
import render_truth as rt  # noqa: E402
import robo_perception as rp  # noqa: E402


class Gym:
    def __init__(self, gym: str, mode: str, trace_dir: Path):
        self.instance = f"force{os.getpid()}_{gym}"
        self.scene = tomllib.loads((rt.GYMS_DIR / gym / "scene.toml").read_text())
        self.trace_dir = trace_dir
        self.proc = subprocess.Popen([str(rt.R2G), "up", gym, "--instance", self.instance, "--mode", mode,
                                      "--trace-dir", str(trace_dir)], stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith("READY"):
            self.stop()
            raise RuntimeError(f"{gym}: r2g up did not get ready: {line!r}")
        os.environ["R2G_INSTANCE"] = self.instance

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class Poller:
    """Wall mode: get_state([]) from its own thread (its own robo connection) while a chunk runs."""

    def __init__(self, instance: str):
        self.instance = instance
        self.samples: list[tuple[float, list[float]]] = []
        self.on = False
        self.quit = False
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self) -> None:
        import robo
        while not self.quit:
            if self.on:
                s = robo.get_state([])
                self.samples.append((s["timestamp"], list(s["external_force_n"])))
            time.sleep(0.003)

    def window(self):
        self.samples = []
        self.on = True

    def close_window(self) -> list:
        self.on = False
        time.sleep(0.01)
        return self.samples


def norm(f) -> float:
    return float(np.linalg.norm(f))


def run_chunk(label: str, poses, gripper: float, rows: list, poller, freq: str = "", repeat_last: int = 0) -> dict:
    import robo
    acts = rp.waypoints(poses, gripper) + rp.waypoints(poses[-1:], gripper) * repeat_last
    if poller:
        poller.window()
    robo.post_actions({"type": "ee_pose", "freq": freq, "actions": acts})
    during = None
    if poller:
        time.sleep(0.3)  # what the value does after the chunk (wall time keeps running)
        during = poller.close_window()
    s = robo.get_state([])
    fb = s["control_feedback"]
    row = {"step": label, "result": fb["status"], "reason": fb["reason"][:70] if fb["status"] != "executed" else "",
           "t_s": s["timestamp"], "force_n": [round(v, 2) for v in s["external_force_n"]],
           "tcp_z": round(s["ee_pose"][2], 4), "gripper": round(s["gripper"][0], 3)}
    if during:
        end = s["timestamp"]
        inside = [norm(f) for t, f in during if t <= end - 0.3]
        row["max_during_n"] = round(max(inside), 2) if inside else None
        row["polled"] = len(during)
    rows.append(row)
    return row


def here():
    import robo
    return list(robo.get_state([])["ee_pose"])


def path_to(xyz, yaw=0.0, step=0.01):
    goal = list(xyz) + rt.down(yaw)
    return rp.interpolate_poses(here(), goal, step, 0.3)


def block_scenarios(mode: str, rows: list, poller) -> None:
    import robo
    assert robo.reset() == 1
    s = robo.get_state([])
    rows.append({"step": "at rest after reset", "result": "", "reason": "", "t_s": s["timestamp"],
                 "force_n": [round(v, 2) for v in s["external_force_n"]], "tcp_z": round(s["ee_pose"][2], 4),
                 "gripper": round(s["gripper"][0], 3)})
    bx, by = 0.5, -0.12  # scene.toml: block centre, 4 cm cube on the table (top at 0.04 m)
    run_chunk("closed fingers above the block (TCP 10 cm up)", path_to([bx, by, 0.10], step=0.04), 1.0, rows, poller)
    # fingertips reach 9 mm past the TCP: TCP at 0.049 m touches the top; 0.045 m presses 4 mm into it
    run_chunk("press fingertips 4 mm into the block's top", path_to([bx, by, 0.045], step=0.01), 1.0, rows, poller)
    run_chunk("hold: same pose again", [here()[:3] + rt.down(0.0)], 1.0, rows, poller, repeat_last=10)
    run_chunk("lift 5 cm off the block", path_to([bx, by, 0.10], step=0.01), 1.0, rows, poller)
    run_chunk("open above the block", [here()], -1.0, rows, poller, repeat_last=10)
    run_chunk("down around the block (TCP 2.2 cm)", path_to([bx, by, 0.022], step=0.01), -1.0, rows, poller)
    run_chunk("close on the block", [here()], 1.0, rows, poller, repeat_last=20)
    run_chunk("lift the block 5 cm", path_to([bx, by, 0.07], step=0.01), 1.0, rows, poller)
    run_chunk("set it down (TCP 2.2 cm)", path_to([bx, by, 0.022], step=0.01), 1.0, rows, poller)
    run_chunk("release", [here()], -1.0, rows, poller, repeat_last=20)
    run_chunk("up, open", path_to([bx, by, 0.10], step=0.04), -1.0, rows, poller)
    run_chunk("close the fingers in the air", [here()], 1.0, rows, poller, repeat_last=20)
    run_chunk("closed fingers down behind it (x -4 cm, TCP 3 cm)", path_to([bx - 0.04, by, 0.03], step=0.02), 1.0, rows, poller)
    run_chunk("push the block 6 cm along +x, stop", path_to([bx + 0.02, by, 0.03], step=0.01), 1.0, rows, poller)
    run_chunk("stay (same pose)", [here()], 1.0, rows, poller, repeat_last=10)


def door_scenarios(mode: str, rows: list, poller) -> None:
    import robo
    assert robo.reset() == 1
    kf = tomllib.loads((rt.GYMS_DIR / "close_cabinet" / "keyframes.toml").read_text())["keyframes"]
    for k in kf[:13]:  # down beside the door, push it round in 10-degree chunks, to shut
        p = k["position_m"]
        run_chunk(k["note"], rp.interpolate_poses(here(), list(p) + rt.down(0.0), 0.01, 0.3), 1.0, rows, poller)
    p = kf[12]["position_m"]
    run_chunk("press 1 cm past shut (the door's stop)", rp.interpolate_poses(here(), [p[0] + 0.01, p[1], p[2]] + rt.down(0.0), 0.005, 0.3), 1.0, rows, poller)
    run_chunk("hold: same pose again", [here()], 1.0, rows, poller, repeat_last=10)
    run_chunk("back away 5 cm", rp.interpolate_poses(here(), [p[0] - 0.05, p[1], p[2]] + rt.down(0.0), 0.01, 0.3), 1.0, rows, poller)


def door_angles(rows: list, trace: dict, scene: dict) -> None:
    if not trace.get("joints"):
        return
    for r in rows:
        _, fixtures = rt.trace_state(scene, trace, t=r["t_s"])
        name = trace["joints"][0]
        r["door_deg"] = round(math.degrees(fixtures[name]), 1)


def block_positions(rows: list, trace: dict, scene: dict) -> None:
    for r in rows:
        objects, _ = rt.trace_state(scene, trace, t=r["t_s"])
        r["block_xyz"] = [round(v, 4) for v in objects["block"][:3]]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", default="lockstep", choices=["lockstep", "wall"])
    ap.add_argument("--gyms", default="pick_block_plate,close_cabinet")
    a = ap.parse_args()
    out = {}
    for gym in a.gyms.split(","):
        rows: list = []
        with tempfile.TemporaryDirectory() as td:
            g = Gym(gym, a.mode, Path(td))
            poller = Poller(g.instance) if a.mode == "wall" else None
            try:
                (block_scenarios if gym == "pick_block_plate" else door_scenarios)(a.mode, rows, poller)
                import robo
                before = len(list(Path(td).glob("episode-*.trace.json")))
                robo.reset()
                trace = None
                for _ in range(200):
                    t = sorted(Path(td).glob("episode-*.trace.json"), key=lambda p: int(p.name.split("-")[1].split(".")[0]))
                    if len(t) > before:
                        try:
                            trace = json.loads(t[-1].read_text())
                            break
                        except json.JSONDecodeError:
                            pass
                    time.sleep(0.1)
            finally:
                if poller:
                    poller.quit = True
                g.stop()
            if trace is not None:
                (door_angles if gym != "pick_block_plate" else block_positions)(rows, trace, g.scene)
        out[gym] = rows
        print(f"\n{gym} ({a.mode}): what a program reads after each chunk")
        for r in rows:
            extra = f" door {r['door_deg']:5.1f}°" if "door_deg" in r else ""
            extra += f" block at {r['block_xyz']}" if "block_xyz" in r else ""
            during = f" max during {r['max_during_n']:6.2f} N ({r['polled']} polls)" if r.get("max_during_n") is not None else ""
            print(f"  {r['step']:<52} {r['result']:<9} F = {str(r['force_n']):<24} |F| {norm(r['force_n']):6.2f} N"
                  f"  z {r['tcp_z']:.4f} g {r['gripper']:+.2f}{extra}{during} {r['reason']}")
    print(json.dumps({"mode": a.mode, "gyms": out}))


if __name__ == "__main__":
    main()
