"""Fixtures that start real `r2g up` instances and always stop them, by pid."""
from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import json
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
R2G = ROOT / "target" / "release" / "r2g"
sys.path.insert(0, str(Path(__file__).parent))

# The Python suite runs on a non-default iceoryx2 root path, as deploy/ sets one: `r2g up` and its
# children, `robo` in this process, `r2g exec`'s proxy and the hostile programs' probes all follow
# R2G_IPC_CONFIG. Set before anything here opens iceoryx2 (the configuration is per process).
if "R2G_IPC_CONFIG" not in os.environ:
    _ipc = Path(tempfile.mkdtemp(prefix="r2g-pytest-ipc-"))
    (_ipc / "iceoryx2.toml").write_text(f'[global]\nroot-path = "{_ipc}/root/"\n')
    os.environ["R2G_IPC_CONFIG"] = str(_ipc / "iceoryx2.toml")
    atexit.register(shutil.rmtree, _ipc, True)


# `make test` (scripts/test.sh) sets R2G_TEST_STRICT=1: there a missing dependency that make
# installs (socat, pyrealsense2, r2g_camera, ...) fails the tests that need it instead of
# skipping them, so that a broken install cannot pass quietly.
STRICT = os.environ.get("R2G_TEST_STRICT") == "1"


def need_module(name: str, why: str):
    """The module, imported; else the calling test module is skipped (failed under make test)."""
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError as e:
        if STRICT:
            pytest.fail(f"{why} ({e}); make test needs it", pytrace=False)
        pytest.skip(f"{why} ({e})", allow_module_level=True)


def need_program(name: str, why: str) -> None:
    """Skips the calling test module when `name` is not on PATH (fails it under make test)."""
    if shutil.which(name) is None:
        if STRICT:
            pytest.fail(f"{why}; make test needs it", pytrace=False)
        pytest.skip(why, allow_module_level=True)


class Instance:
    def __init__(self, name: str, mode: str, gym: str = "pick_block_plate", extra: tuple[str, ...] = ()) -> None:
        if not R2G.is_file():
            raise RuntimeError(f"{R2G} missing: run `make build` first")
        self.name = name
        self.proc = subprocess.Popen(
            [str(R2G), "up", gym, "--instance", name, "--mode", mode, "--render-hz", "10", *extra],
            stdout=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            text=True,
        )
        deadline = time.monotonic() + 90
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if line.strip() != f"READY {name}" or time.monotonic() > deadline:
            self.stop()
            raise RuntimeError(f"r2g up did not get ready: {line!r}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@contextlib.contextmanager
def robo_instance(name: str) -> Iterator[None]:
    """`robo` in this process talks to instance `name` meanwhile (R2G_INSTANCE)."""
    previous = os.environ.get("R2G_INSTANCE")
    os.environ["R2G_INSTANCE"] = name
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("R2G_INSTANCE", None)
        else:
            os.environ["R2G_INSTANCE"] = previous


def _instance(mode: str, tag: str, gym: str = "pick_block_plate", extra: tuple[str, ...] = ()) -> Iterator[Instance]:
    inst = Instance(f"py{os.getpid()}{tag}", mode, gym, extra)
    try:
        with robo_instance(inst.name):
            yield inst
    finally:
        inst.stop()


@pytest.fixture(scope="module")
def wall() -> Iterator[Instance]:
    yield from _instance("wall", "w")


@pytest.fixture(scope="module")
def lockstep() -> Iterator[Instance]:
    yield from _instance("lockstep", "l")


@pytest.fixture(scope="module")
def fr3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Instance]:
    """pick_block_plate with FR3 limits and a workspace that ends 10 cm above the table."""
    text = (ROOT / "gyms" / "pick_block_plate" / "scene.toml").read_text()
    urdf = ROOT / "robots" / "panda" / "panda.urdf"
    text = text.replace('urdf = "../../robots/panda/panda.urdf"', f'urdf = "{urdf}"\nlimits = "fr3"')
    demo = ROOT / "gyms" / "pick_block_plate" / "demo.csv"
    text = text.replace('demonstration = "demo.csv"', f'demonstration = "{demo}"')
    text += "\n[safety]\nworkspace_min_m = [-0.2, -0.6, 0.1]\nworkspace_max_m = [1.1, 0.6, 1.0]\n"
    scene = tmp_path_factory.mktemp("fr3") / "scene.toml"
    scene.write_text(text)
    yield from _instance("lockstep", "f", str(scene))


def kin_fk(qs, *args: str) -> list[np.ndarray]:
    """4x4 base-frame poses from `r2g kin fk` (the controllers crate's kinematics), one per joint
    vector in ``qs``; ``args``: its options (--robot, --tcp, --frame)."""
    out = subprocess.run([str(R2G), "kin", "fk", *args], input="".join(json.dumps({"q": list(q)}) + "\n" for q in qs),
                         capture_output=True, text=True, timeout=60, check=True).stdout.strip().splitlines()
    poses = []
    for line in out:
        a = json.loads(line)
        x, y, z, w = a["quaternion"]
        T = np.eye(4)
        T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
        T[:3, 3] = a["position"]
        poses.append(T)
    return poses
