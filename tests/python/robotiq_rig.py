"""A Robotiq 2F-85 on a serial line without hardware, for tests and `bench/py/rig_bench.py`.

A pseudo-terminal pair made by socat is the serial line: `rig/py/robotiq_sim.py` (OUR gripper
simulator, written from the published register map on pymodbus's RTU server) serves one end,
r2g-robotiq opens the other. An `r2g up` instance of pick_block_plate (simulated arm, wall mode)
names that gripper in its robot config. Everything here is synthetic: no real gripper answers.
Every process is started here and stopped here, by pid.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from conftest import R2G, ROOT

SIM = ROOT / "rig" / "py" / "robotiq_sim.py"
PYTHON = ROOT / ".venv" / "bin" / "python"


def stop(proc: subprocess.Popen | None, timeout: float = 10) -> None:
    if proc is not None and proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class Rig:
    """socat's pty pair, the gripper simulator on one end, and an instance whose r2g-robotiq
    drives the other end."""

    def __init__(self, tmp: Path, name: str, activation_s: float = 0.3, extra_env: dict | None = None,
                 position: int = 0, profile: str = "simulation") -> None:
        if shutil.which("socat") is None:
            raise RuntimeError("socat is missing: scripts/install-deps.sh installs it (make test does)")
        self.tmp, self.name = tmp, name
        self.position, self.profile = position, profile
        # r2g-robotiq's figures, kept current while it runs (R2G_ROBOTIQ_STATS_OUT).
        self.stats_path = tmp / "robotiq-stats.json"
        self.socat = self.sim = self.up = None
        self.sim_log = open(tmp / "robotiq-sim.log", "w")
        self.up_log = open(tmp / "r2g-up.log", "w")
        try:
            self._start(activation_s, extra_env or {})
        except BaseException:
            self.close()
            raise

    def _start(self, activation_s: float, extra_env: dict) -> None:
        self.gripper_end, self.driver_end = self.tmp / "gripper", self.tmp / "driver"
        self.activation_s = activation_s
        self.start_line()
        self.start_gripper()
        config = {
            "profile": self.profile,
            "gripper": {"driver": "robotiq_2f85", "port": str(self.driver_end), "force": 100},
        }
        self.config = self.tmp / "robot.json"
        self.config.write_text(json.dumps(config))
        env = dict(os.environ, R2G_ROBOTIQ_STATS_OUT=str(self.stats_path), **extra_env)
        self.up = subprocess.Popen(
            [str(R2G), "up", "pick_block_plate", "--instance", self.name, "--mode", "wall", "--render-hz", "0",
             "--robot-config", str(self.config)],
            stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, stderr=self.up_log, text=True, env=env,
        )
        line = self.up.stdout.readline()
        assert line.strip() == f"READY {self.name}", f"r2g up did not get ready: {line!r} ({self.tmp / 'r2g-up.log'})"

    def start_line(self) -> None:
        """(Re)creates the pty pair: the serial line, as a USB adapter plugged in."""
        self.socat = subprocess.Popen(
            ["socat", f"pty,raw,echo=0,link={self.gripper_end}", f"pty,raw,echo=0,link={self.driver_end}"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + 10
        while not (self.gripper_end.exists() and self.driver_end.exists()):
            assert time.monotonic() < deadline, "socat made no pty pair within 10 s"
            time.sleep(0.02)

    def start_gripper(self) -> None:
        """The simulated gripper, powered up (not activated) on the gripper's end of the line."""
        self.sim = subprocess.Popen(
            [str(PYTHON), str(SIM), "--port", str(self.gripper_end), "--activation-s", str(self.activation_s),
             "--position", str(self.position)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.sim_log, text=True,
        )
        line = self.sim.stdout.readline()
        assert line.strip() == "READY", f"the gripper simulator did not start: {line!r} ({self.tmp / 'robotiq-sim.log'})"

    def replug(self) -> None:
        """The line and the gripper come back (a new pty pair; the simulator restarts on it, as a
        gripper whose adapter and power were cut: not activated)."""
        stop(self.sim)
        self.start_line()
        self.start_gripper()

    def unplug(self) -> None:
        """The serial line disappears (socat ends: both ptys close, their links go)."""
        stop(self.socat)
        self.socat = None

    def control(self, **msg) -> dict:
        """One command to the simulator (object_at, fault, kflt, corrupt_crc, silent; none: just
        ask); its reply: where the fingers are (`position`, counts) and `activations`."""
        self.sim.stdin.write(json.dumps(msg) + "\n")
        self.sim.stdin.flush()
        reply = json.loads(self.sim.stdout.readline())
        assert reply.get("ok"), f"simulator refused {msg}: {reply}"
        return reply

    def stats(self) -> dict:
        """r2g-robotiq's figures as it last wrote them ({} before it wrote any)."""
        try:
            return json.loads(self.stats_path.read_text())
        except (FileNotFoundError, ValueError):
            return {}

    def log(self) -> str:
        self.up_log.flush()
        return (self.tmp / "r2g-up.log").read_text()

    def close(self) -> None:
        stop(self.up, 20)
        if self.sim is not None and self.sim.poll() is None:
            try:
                self.sim.stdin.close()
            except OSError:
                pass
        stop(self.sim)
        stop(self.socat)
        self.sim_log.close()
        self.up_log.close()


def wait_for(what: str, cond, timeout: float = 10.0, every: float = 0.02):
    deadline = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} did not happen within {timeout} s")
        time.sleep(every)


def gripper_move(robo, closed: float) -> tuple[int, float, dict]:
    """One chunk that only moves the fingers (the arm holds where it is): (result, seconds from
    post to the reply, the state right after)."""
    q = list(robo.get_state([])["joint"])
    t0 = time.monotonic()
    ok = robo.post_actions({"actions": [q + [closed]], "type": "joint", "freq": ""})
    dt = time.monotonic() - t0
    return ok, dt, robo.get_state([])


if __name__ == "__main__":
    sys.exit("a helper module: see tests/python/test_robotiq.py and bench/py/rig_bench.py")
