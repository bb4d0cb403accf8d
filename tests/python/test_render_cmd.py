"""`r2g render` as a user runs it (the real binary, real MuJoCo, synthetic frames of a shipped
gym): the BOP folder it writes, the states of a native trace from `r2g replay`, a
scene_camera.json given back with --cameras, and bad input refused with a precise message and
nothing written. The pixel-level truth (masks and depth against the block's box, intrinsics) is
checked in sim-host/tests/bop.rs and sim-host/tests/intrinsics.rs."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import R2G
from pngdecode import decode, read

GYM = "pick_block_plate"


def gray(path: Path) -> np.ndarray:
    """A grey PNG (8 or 16 bits) as signed integers, so differences do not wrap."""
    img = read(path)
    assert img.ndim == 2, (path, img.shape)
    return img.astype(np.int32)


def r2g(*args: str) -> subprocess.CompletedProcess:
    if not R2G.is_file():
        pytest.fail(f"{R2G} missing: run `make build` first", pytrace=False)
    return subprocess.run([str(R2G), *args], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def trace(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("replay")
    p = r2g("replay", GYM, "--out", str(out))
    assert p.returncode == 0, p.stderr
    return out / f"{GYM}-seed0.trace.json"


def test_the_scene_at_rest_in_the_bop_layout(tmp_path):
    out = tmp_path / "frames"
    p = r2g("render", GYM, "--out", str(out))
    assert p.returncode == 0, p.stderr
    summary = json.loads(p.stdout.strip().splitlines()[-1])
    assert summary["images"] == 2 and summary["objects"] == ["block", "plate"]
    cams = json.loads((out / "scene_camera.json").read_text())
    assert sorted(cams) == ["0", "1"]
    assert [cams[i]["r2g_camera"] for i in ("0", "1")] == ["agentview", "wrist"]
    for i in range(2):
        c = cams[str(i)]
        assert len(c["cam_K"]) == 9 and len(c["cam_R_w2c"]) == 9 and len(c["cam_t_w2c"]) == 3
        assert c["depth_scale"] == 0.1 and (c["width"], c["height"]) == (640, 480)
        w, h, ch, _ = decode((out / "rgb" / f"{i:06d}.png").read_bytes())
        assert (w, h, ch) == (640, 480, 3)
        for k in range(2):
            assert (out / "mask_visib" / f"{i:06d}_{k:06d}.png").is_file()
        assert (out / "depth" / f"{i:06d}.png").is_file()
    gt = json.loads((out / "scene_gt.json").read_text())
    assert [o["r2g_name"] for o in gt["0"]] == ["block", "plate"] and [o["obj_id"] for o in gt["0"]] == [1, 2]
    joints = json.loads((out / "joints.json").read_text())
    assert len(joints["0"]["joints_rad"]) == 7 and joints["0"]["finger_m"] > 0.03
    info = json.loads((out / "scene_gt_info.json").read_text())
    assert all(o["px_count_visib"] > 100 for o in info["0"]), info
    # Nothing but the folder itself is left beside it.
    assert sorted(x.name for x in tmp_path.iterdir()) == ["frames"]


def test_trace_states_and_the_cameras_of_a_file(tmp_path, trace):
    samples = json.loads(trace.read_text())["samples"]
    mid = samples[len(samples) // 2]
    out = tmp_path / "states"
    p = r2g("render", GYM, "--out", str(out), "--trace", str(trace), "--at", f"0,{mid['t_s']}", "--camera", "wrist")
    assert p.returncode == 0, p.stderr
    cams = json.loads((out / "scene_camera.json").read_text())
    joints = json.loads((out / "joints.json").read_text())
    assert [cams[i]["r2g_t_s"] for i in ("0", "1")] == [0.0, pytest.approx(mid["t_s"], abs=1e-6)]
    assert joints["1"]["joints_rad"] == pytest.approx(mid["arm_rad"], abs=1e-12)
    # The wrist camera rides on the hand: it moved with the arm.
    assert cams["0"]["cam_t_w2c"] != pytest.approx(cams["1"]["cam_t_w2c"], abs=1.0)

    # The same views from that scene_camera.json: fixed cameras with the same K and pose.
    again = tmp_path / "again"
    p = r2g("render", GYM, "--out", str(again), "--trace", str(trace), "--at", str(mid["t_s"]),
            "--cameras", str(out / "scene_camera.json"))
    assert p.returncode == 0, p.stderr
    cams2 = json.loads((again / "scene_camera.json").read_text())
    assert [cams2[i]["r2g_camera"] for i in ("0", "1")] == ["0", "1"]
    for i in ("0", "1"):
        assert cams2[i]["cam_K"] == pytest.approx(cams[i]["cam_K"], abs=1e-3)
    # Image 1 of the file was taken at mid: rendered again there, it sees what it saw.
    assert cams2["1"]["cam_R_w2c"] == pytest.approx(cams["1"]["cam_R_w2c"], abs=1e-6)
    assert cams2["1"]["cam_t_w2c"] == pytest.approx(cams["1"]["cam_t_w2c"], abs=1e-3)
    a, b = gray(out / "depth" / "000001.png"), gray(again / "depth" / "000001.png")
    assert a.shape == (480, 640) and (a > 0).mean() > 0.9
    close = (np.abs(a - b) <= 5).mean()  # 0.5 mm
    assert close > 0.999, f"only {close:.4f} of the depths agree within 0.5 mm"
    seen = 0
    for k in range(2):
        ma, mb = gray(out / "mask_visib" / f"000001_{k:06d}.png"), gray(again / "mask_visib" / f"000001_{k:06d}.png")
        assert set(np.unique(ma)) <= {0, 255}
        union = ((ma > 0) | (mb > 0)).sum()
        seen += union
        if union:
            iou = ((ma > 0) & (mb > 0)).sum() / union
            assert iou > 0.99, (k, iou)
    assert seen > 100, "the objects are in view"


def test_bad_input_is_refused_and_nothing_is_written(tmp_path, trace):
    good = {"cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1], "cam_R_w2c": [1, 0, 0, 0, 1, 0, 0, 0, 1],
            "cam_t_w2c": [0, 0, 1000], "width": 640, "height": 480}
    no_size = tmp_path / "no_size.json"
    no_size.write_text(json.dumps({"7": {k: v for k, v in good.items() if k != "width"}}))
    bad_k = tmp_path / "bad_k.json"
    bad_k.write_text(json.dumps({"0": {**good, "cam_K": [[500, 0, 320], [0, 500, 240]]}}))
    out = tmp_path / "out"
    cases = [
        (["no_such_gym"], ["no gym 'no_such_gym'"]),
        ([GYM, "--camera", "front"], ["--camera front", "no such camera", "agentview, wrist"]),
        ([GYM, "--cameras", str(no_size)], ["image '7'", 'no "width"']),
        ([GYM, "--cameras", str(bad_k)], ["image '0'", "cam_K", "3x3"]),
        ([GYM, "--trace", str(trace), "--at", "1000"], ["--at 1000", "outside the trace"]),
        ([GYM, "--trace", str(trace)], ["--trace needs --at"]),
    ]
    for args, want in cases:
        p = r2g("render", *args, "--out", str(out))
        assert p.returncode != 0, args
        for w in want:
            assert w in p.stderr, (args, p.stderr)
        assert "panicked" not in p.stderr
        assert not out.exists(), args
    leftovers = [x.name for x in tmp_path.iterdir() if x.name.startswith(".")]
    assert leftovers == [], leftovers
