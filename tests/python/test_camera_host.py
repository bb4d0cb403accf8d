"""The camera host on librealsense's software device: the RealSense code path (sensors, frame
queues, depth in the colour image, metres) without hardware. Synthetic: the frames fed to the
software device are sim-host's own renders of pick_block_plate (taken through `robo` from a
plain instance), and their calibration files are written from that render's intrinsics and
extrinsics. A second instance then names the cameras as devices in its robot config: `r2g up`
starts one camera host per camera, sim-host stops rendering those names, and `robo` reads the
hosts' frames unchanged. The UVC path is not exercised (no V4L2 device can be made here).
"""
from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

import robo
from conftest import R2G, ROOT, Instance, robo_instance

pytest.importorskip("pyrealsense2", reason="pyrealsense2 missing (requirements.txt installs it)")
pytest.importorskip("r2g_camera", reason="r2g_camera missing (make builds it)")

SCENE = ROOT / "gyms" / "pick_block_plate" / "scene.toml"


def block_centre() -> np.ndarray:
    import tomllib

    scene = tomllib.loads(SCENE.read_text())
    block = next(o for o in scene["objects"] if o["name"] == "block")
    return np.array(block["position_m"], dtype=float)  # base frame: the base sits at the origin


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One sim-host render of both cameras, as files a camera host replays."""
    tmp = tmp_path_factory.mktemp("camhost")
    inst = Instance(f"py{os.getpid()}cr", "wall")
    try:
        with robo_instance(inst.name):
            s = robo.get_state(["agentview", "wrist"], raw=True)
    finally:
        inst.stop()
    out = {"tmp": tmp, "state": s}
    for cam in ("agentview", "wrist"):
        k = s["camera_intrinsics"][cam]
        np.savez(tmp / f"{cam}.npz", rgb=s["image"][cam], depth_m=s["depth"][cam],
                 fx=k["fx"], fy=k["fy"], cx=k["cx"], cy=k["cy"])
        intr = {key: k[key] for key in ("width", "height", "fx", "fy", "cx", "cy")}
        E = np.asarray(s["camera_extrinsics"][cam])
        if cam == "agentview":
            cal = {"base_from_camera": E.tolist(), **intr}
        else:
            # The wrist camera's hand-eye calibration, from this render: flange_from_camera =
            # inv(base_from_flange) · base_from_camera, base_from_flange = ee_pose · inv(flange_from_tcp).
            cal = {"flange_from_camera": (np.linalg.inv(base_from_flange(s)) @ E).tolist(), **intr}
        (tmp / f"{cam}.json").write_text(json.dumps(cal))
    return out


def base_from_tcp(state: dict) -> np.ndarray:
    p, rv = np.asarray(state["ee_pose"][:3]), np.asarray(state["ee_pose"][3:])
    angle = np.linalg.norm(rv)
    K = np.zeros((3, 3))
    if angle > 0:
        a = rv / angle
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def base_from_flange(state: dict) -> np.ndarray:
    ft = np.asarray(state["calibration"]["tcp"]["flange_from_tcp"])
    return base_from_tcp(state) @ np.linalg.inv(ft)


def up(tmp: Path, name: str, cameras: dict, render_hz: int = 10) -> subprocess.Popen:
    cfg = {"profile": "simulation",
           "calibration": {"cameras": {c: f"{c}.json" for c in cameras}},
           "cameras": cameras}
    (tmp / f"{name}.json").write_text(json.dumps(cfg))
    return subprocess.Popen(
        [str(R2G), "up", "pick_block_plate", "--instance", name, "--mode", "wall", "--render-hz", str(render_hz),
         "--robot-config", str(tmp / f"{name}.json")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)


def stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@pytest.fixture(scope="module")
def hosted(rendered: dict) -> Iterator[subprocess.Popen]:
    tmp = rendered["tmp"]
    name = f"py{os.getpid()}ch"
    p = up(tmp, name, {"agentview": {"driver": "replay", "file": "agentview.npz", "fps": 15},
                       "wrist": {"driver": "replay", "file": "wrist.npz", "fps": 15}})
    line = p.stdout.readline()
    if line.strip() != f"READY {name}":
        stop(p)
        pytest.fail(f"r2g up with camera hosts did not get ready: {line!r}\n{p.stderr.read()[-3000:]}")
    try:
        with robo_instance(name):
            yield p
    finally:
        stop(p)


def test_frames_reach_robo_with_intrinsics_extrinsics_and_the_runtimes_clock(rendered: dict, hosted) -> None:
    s = robo.get_state(["agentview", "wrist"], raw=True)
    src = np.load(rendered["tmp"] / "agentview.npz")
    assert np.array_equal(s["image"]["agentview"], src["rgb"]), "RGB byte for byte through librealsense"
    d, d0 = s["depth"]["agentview"], src["depth_m"]
    assert d.dtype == np.float32 and d.shape == d0.shape
    # Z16 at 1 mm per count holds 65.535 m: the render's far background is cut there, as a
    # RealSense never reports such distances anyway.
    near = d0 < 65.0
    assert near.mean() > 0.5
    assert np.max(np.abs(d - d0)[near]) <= 0.0005 + 1e-5, "depth within half a millimetre count"
    k, k0 = s["camera_intrinsics"]["agentview"], rendered["state"]["camera_intrinsics"]["agentview"]
    assert all(abs(k[c] - k0[c]) < 1e-9 for c in ("fx", "fy", "cx", "cy", "width", "height"))
    assert np.allclose(s["camera_extrinsics"]["agentview"], rendered["state"]["camera_extrinsics"]["agentview"], atol=1e-9)
    # On the runtime's clock: within a few frame periods of the robot time now.
    assert abs(s["image_timestamp"]["agentview"] - s["timestamp"]) < 0.5, (s["image_timestamp"], s["timestamp"])
    # The wrist camera's pose follows the hand: compose it from the TCP now, and after a move.
    for _ in range(2):
        s = robo.get_state(["wrist"], raw=True)
        cal = json.loads((rendered["tmp"] / "wrist.json").read_text())
        want = base_from_flange(s) @ np.asarray(cal["flange_from_camera"])
        got = np.asarray(s["camera_extrinsics"]["wrist"])
        assert np.allclose(got, want, atol=2e-3), (got, want)
        q = list(s["joint"])
        q[0] += 0.15
        assert robo.post_actions({"actions": [q + [-1.0]], "type": "joint", "freq": ""}) == 1


def test_a_known_target_back_projects_onto_itself(rendered: dict, hosted) -> None:
    """The block's centre, projected with the hosted camera's calibration, lands on the block:
    the depth there back-projects (robo's intrinsics and extrinsics) to a point on its surface."""
    s = robo.get_state(["agentview"], raw=True)
    k = s["camera_intrinsics"]["agentview"]
    E = np.asarray(s["camera_extrinsics"]["agentview"])
    c = block_centre()
    pc = np.linalg.inv(E) @ np.append(c, 1.0)
    u, v = k["fx"] * pc[0] / pc[2] + k["cx"], k["fy"] * pc[1] / pc[2] + k["cy"]
    z = float(s["depth"]["agentview"][int(round(v)), int(round(u))])
    assert z > 0
    p_cam = np.array([(round(u) - k["cx"]) / k["fx"] * z, (round(v) - k["cy"]) / k["fy"] * z, z, 1.0])
    p = (E @ p_cam)[:3]
    err = float(np.linalg.norm(p - c))
    print(f"block centre {c.round(3)}, back-projected surface point {p.round(3)}: {err * 1e3:.1f} mm apart")
    assert err < 0.04, err


def test_a_frame_size_that_is_not_the_calibrations_fails_the_start_with_the_reason(rendered: dict) -> None:
    tmp = rendered["tmp"]
    src = np.load(tmp / "agentview.npz")
    np.savez(tmp / "small.npz", rgb=src["rgb"][::2, ::2].copy(), depth_m=src["depth_m"][::2, ::2].copy(),
             fx=src["fx"] / 2, fy=src["fy"] / 2, cx=src["cx"] / 2, cy=src["cy"] / 2)
    name = f"py{os.getpid()}cs"
    p = up(tmp, name, {"agentview": {"driver": "replay", "file": "small.npz", "fps": 15,
                                     "width": 640, "height": 480}})
    try:
        out, err = p.communicate(timeout=90)
    finally:
        stop(p)
    assert p.returncode != 0 and "READY" not in out
    assert "320x240, configured 640x480" in err, err[-2000:]
    assert "camera host 'agentview'" in err and "before the instance was ready" in err, err[-2000:]
    assert "Traceback" not in err and "panicked" not in err


def test_a_camera_that_stops_gives_no_stale_image_and_nothing_else_stops(hosted) -> None:
    """Its host dies (SIGKILL, the child of the `r2g up` this module started): after the arm moves,
    `robo` says that camera sent no image instead of showing the old one; the other camera, the
    arm and the instance go on."""
    children = Path(f"/proc/{hosted.pid}/task/{hosted.pid}/children").read_text().split()
    def argv(pid: str) -> list[str]:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")

    host = next(int(c) for c in children
                if any(a.endswith("r2g_camera_host.py") for a in argv(c)) and "agentview" in argv(c))
    os.kill(host, 9)
    s = robo.get_state([])
    q = list(s["joint"])
    q[0] -= 0.1
    assert robo.post_actions({"actions": [q + [-1.0]], "type": "joint", "freq": ""}) == 1
    with pytest.raises(Exception, match="no image from camera 'agentview'"):
        robo.get_state(["agentview"], raw=True)
    assert robo.get_state(["wrist"], raw=True)["image"]["wrist"].shape == (480, 640, 3)
    assert hosted.poll() is None
