"""The camera host's device side (`Source` in camera-host/py/r2g_camera_host.py) on its own:
no instance, no `r2g_camera`. The RealSense path runs on librealsense's software device
(`ReplaySource`, fed by its thread from synthetic frames we generate); the UVC path's YUYV
conversion and size check run on synthetic bytes (no V4L2 device can be made here)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, need_module

need_module("pyrealsense2", "pyrealsense2 missing (requirements.txt installs it)")
sys.path.insert(0, str(ROOT / "camera-host" / "py"))
import r2g_camera_host as host  # noqa: E402

W, H = 32, 24


def replay_file(path: Path, w: int = W, h: int = H, frames: int = 2) -> Path:
    rgb = np.zeros((frames, h, w, 3), np.uint8)
    for i in range(frames):
        rgb[i, ..., 0] = np.arange(w, dtype=np.uint8)[None, :]  # red: the column
        rgb[i, ..., 1] = i  # green: the frame
    depth = np.full((h, w), 0.75, np.float32)
    np.savez(path, rgb=rgb, depth_m=depth, fx=30.0, fy=30.0, cx=w / 2, cy=h / 2)
    return path


def read_some(src: host.Source, timeout_s: float = 3.0) -> host.Frame:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        f = src.read(0.2)
        if f is not None:
            return f
    raise AssertionError(f"no frame within {timeout_s} s ({src.problem})")


def test_a_replay_goes_through_the_realsense_path(tmp_path: Path) -> None:
    src = host.ReplaySource(replay_file(tmp_path / "r.npz"), W, H, 30, depth=True)
    src.open()
    try:
        rgb, depth, k, captured_ns, domain = read_some(src)
        assert rgb.shape == (H, W, 3) and np.array_equal(rgb[0, :, 0], np.arange(W))
        assert depth is not None and depth.dtype == np.float32 and np.allclose(depth, 0.75, atol=5e-4)
        assert k == (30.0, 30.0, W / 2, H / 2)
        assert domain == "system_time" and abs(captured_ns - time.monotonic_ns()) < 2e9
    finally:
        src.close()


def test_a_stalled_camera_gives_no_frame_and_comes_back_when_reopened(tmp_path: Path) -> None:
    """The device stops delivering while the host lives (its feeder stops): no frame, never the
    last one again; closed and opened again, frames come anew."""
    src = host.ReplaySource(replay_file(tmp_path / "r.npz"), W, H, 30, depth=True)
    src.open()
    try:
        read_some(src)
        src.stop_feeding.set()
        src.feeder.join(timeout=2)
        time.sleep(0.2)
        while src.read(0.05) is not None:  # what was queued before the stall
            pass
        assert src.read(0.5) is None
        src.close()
        src.open()
        _, _, _, captured_ns, _ = read_some(src)
        assert abs(captured_ns - time.monotonic_ns()) < 1e9, "an old frame after the reopen"
    finally:
        src.close()


def test_a_camera_back_at_another_size_is_refused_with_the_sizes(tmp_path: Path) -> None:
    """Its calibration is for W x H: a device that comes back offering another mode is not used."""
    src = host.ReplaySource(replay_file(tmp_path / "r.npz"), W, H, 30, depth=True)
    src.open()
    read_some(src)
    src.close()
    # The same device, now streaming 16 x 12 (what a reconnect in another mode looks like here).
    other = host.ReplaySource(replay_file(tmp_path / "small.npz", 16, 12), 16, 12, 30, depth=True)
    src.rgb, src.counts = other.rgb, other.counts
    with pytest.raises(host.ConfigError, match=r"no color rgb8 stream at 32x24 and 30 fps \(it offers 16x12@30\)"):
        src.open()
    src.close()
    # And a replay of the wrong size is refused at once.
    with pytest.raises(host.SizeChanged, match="16x12, configured 32x24"):
        host.ReplaySource(tmp_path / "small.npz", W, H, 30, depth=True)


@pytest.mark.parametrize("arrays, message", [
    (None, "cannot read the replay file"),
    ({"rgb": np.zeros((H, W, 3), np.uint8)}, "lacks fx, fy, cx, cy"),
    ({"rgb": np.zeros((H, W, 3), np.float32), "fx": 1, "fy": 1, "cx": 0, "cy": 0}, "rgb must be uint8"),
    ({"rgb": np.zeros((H, W, 3), np.uint8), "fx": [1, 2], "fy": 1, "cx": 0, "cy": 0}, "must be scalars"),
    ({"rgb": np.zeros((H, W, 3), np.uint8), "fx": 1, "fy": 1, "cx": 0, "cy": 0, "depth_scale": -1.0},
     "depth_scale must be a positive"),
    ({"rgb": np.zeros((H, W, 3), np.uint8), "fx": 1, "fy": 1, "cx": 0, "cy": 0,
      "depth_m": np.zeros((H, W + 1), np.float32)}, "depth_m must be float metres"),
    ({"rgb": np.zeros((3, H, W, 3), np.uint8), "fx": 1, "fy": 1, "cx": 0, "cy": 0,
      "depth_m": np.zeros((2, H, W), np.float32)}, "depth_m has 2 frames, rgb 3"),
])
def test_bad_replay_files_are_refused_with_the_reason(tmp_path: Path, arrays: dict | None, message: str) -> None:
    path = tmp_path / "bad.npz"
    if arrays is None:
        path.write_bytes(b"not an npz at all")
    else:
        np.savez(path, **arrays)
    with pytest.raises(host.ConfigError, match=message):
        host.ReplaySource(path, W, H, 30, depth=True)


def yuyv_source(w: int, h: int, full_range: bool) -> host.UvcSource:
    """A UVC source set up as open() leaves it for a YUYV camera, without a device."""
    src = host.UvcSource("/dev/video-none", w, h, 30)
    src.stride, src.full_range, src.yuyv = 2 * w, full_range, True
    return src


def test_yuyv_converts_to_known_colours() -> None:
    """BT.601: limited range (16..235) black, white and pure red; full range white."""
    # Two pixel pairs per row: (Y0 U Y1 V) each.
    black_white = [16, 128, 235, 128]
    red = [81, 90, 81, 240]
    data = bytes(black_white + red)
    rgb = yuyv_source(4, 1, full_range=False)._yuyv(data, len(data))
    assert rgb.shape == (1, 4, 3) and rgb.dtype == np.uint8
    assert rgb[0, 0].tolist() == [0, 0, 0]
    assert rgb[0, 1].tolist() == [255, 255, 255]
    assert rgb[0, 2].tolist() == [254, 0, 0] and rgb[0, 3].tolist() == [254, 0, 0]
    full = bytes([255, 128, 0, 128])
    assert yuyv_source(2, 1, full_range=True)._yuyv(full, 4)[0].tolist() == [[255, 255, 255], [0, 0, 0]]


def test_a_short_yuyv_frame_is_a_size_change() -> None:
    """Fewer bytes than the configured size holds: the camera changed resolution."""
    src = yuyv_source(4, 2, full_range=False)
    with pytest.raises(host.SizeChanged, match="a 4x2 YUYV frame has 16"):
        src._yuyv(bytes(8), 8)
