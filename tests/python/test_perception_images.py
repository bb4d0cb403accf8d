"""robo_perception.images: PNG encoding and atomic files, crops, projection, markers, visibility.

Offline tests use a synthetic camera; PNGs are read back with `pngdecode` (RGB, every filter)
and a small grey/RGB reader here. One live test on the shared lockstep pick_block_plate
instance (conftest `lockstep`) projects the measured TCP and fingertips into both cameras: the
evidence for "Cameras: image axes and what they show of the hand" in robot-skill/api/README.md.
"""

from __future__ import annotations

import math
import os
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "agent-host" / "py" / "lib"))
import pngdecode  # noqa: E402
import robo_perception as rp  # noqa: E402
from robo_perception import images  # noqa: E402


def read_png(data: bytes) -> np.ndarray:
    """Grey (colour type 0) or RGB (2), 8 bit, filter 0 or 2 -> (H, W) or (H, W, 3) uint8."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, kinds = 8, b"", []
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF, kind
        kinds.append(kind)
        if kind == b"IHDR":
            W, H, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", body)
            assert depth == 8 and color in (0, 2) and interlace == 0
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    assert kinds[0] == b"IHDR" and kinds[-1] == b"IEND"
    ch = 3 if color == 2 else 1
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(H, 1 + W * ch)
    out = np.zeros((H, W * ch), dtype=np.uint8)
    for r in range(H):
        f, line = raw[r, 0], raw[r, 1:]
        assert f in (0, 2)
        out[r] = line if f == 0 or r == 0 else line + out[r - 1]
    return out.reshape(H, W, 3) if ch == 3 else out


def rand_image(h: int = 37, w: int = 53, seed: int = 4) -> np.ndarray:
    return (np.random.default_rng(seed).random((h, w, 3)) * 255).astype(np.uint8)


# A synthetic camera 1 m above the base origin looking straight down: +u = base -y, +v = base -x.
K = {"fx": 100.0, "fy": 100.0, "cx": 39.5, "cy": 29.5, "width": 80, "height": 60}
T_DOWN = np.array([[0.0, -1.0, 0.0, 0.0],     # camera x (u) = base -y
                   [-1.0, 0.0, 0.0, 0.0],     # camera y (v) = base -x
                   [0.0, 0.0, -1.0, 1.0],     # camera z (view) = base -z, origin 1 m up
                   [0.0, 0.0, 0.0, 1.0]])


def synthetic_state(depth: np.ndarray | None = None) -> dict:
    s = {"camera_intrinsics": {"top": dict(K)}, "camera_extrinsics": {"top": T_DOWN.tolist()},
         "image": {"top": np.zeros((60, 80, 3), dtype=np.uint8)}}
    if depth is not None:
        s["depth"] = {"top": depth}
    return s


def expected_pixel(p: np.ndarray) -> tuple[float, float]:
    """Independent pinhole projection for T_DOWN: camera point = (-y, -x, 1 - z)."""
    x, y, z = p
    xc, yc, zc = -y, -x, 1.0 - z
    return K["fx"] * xc / zc + K["cx"], K["fy"] * yc / zc + K["cy"]


# ---------------------------------------------------------------------------------------------
# PNG
# ---------------------------------------------------------------------------------------------

def test_png_round_trip_rgb_grey_and_mask():
    img = rand_image()
    data = rp.encode_png(img)
    w, h, c, raw = pngdecode.decode(data)
    assert (w, h, c) == (53, 37, 3)
    assert np.array_equal(np.frombuffer(raw, dtype=np.uint8).reshape(h, w, 3), img)
    assert np.array_equal(read_png(data), img)
    grey = img[:, :, 1].copy()
    assert np.array_equal(read_png(rp.encode_png(grey)), grey)
    mask = grey > 128
    assert np.array_equal(read_png(rp.encode_png(mask)), mask.astype(np.uint8) * 255)
    one = np.array([[[1, 2, 3]]], dtype=np.uint8)
    assert np.array_equal(read_png(rp.encode_png(one, level=9)), one)
    # non-contiguous views encode their values
    assert np.array_equal(read_png(rp.encode_png(img[::2, ::3])), img[::2, ::3])


def test_png_bad_inputs():
    img = rand_image()
    for bad, match in ((img.astype(np.float32), "uint8"), (img[:, :, :2], r"\(H, W, 3\)"),
                       (np.zeros((0, 4, 3), np.uint8), "empty"), (b"\x89PNG...", "PNG bytes"),
                       ([[1, 2], [3, 4]], "numpy array"), (np.zeros((2, 2, 2, 3), np.uint8), "shape")):
        with pytest.raises(ValueError, match=match):
            rp.encode_png(bad)
    with pytest.raises(ValueError, match="level"):
        rp.encode_png(img, level=10)


def test_robo_services_uses_the_same_encoder():
    import robo_services as rs
    img = rand_image(9, 11)
    assert rs.encode_png(img) == rp.encode_png(img)
    with pytest.raises(ValueError, match="encode_png needs an"):
        rs.encode_png(img[:, :, 0])          # the service takes RGB only


# ---------------------------------------------------------------------------------------------
# Crops and files
# ---------------------------------------------------------------------------------------------

def test_crop_and_scale():
    img = rand_image(40, 50)
    c = rp.crop_image(img, (10, 5, 20, 25))
    assert c.shape == (20, 10, 3) and np.array_equal(c, img[5:25, 10:20])
    c[:] = 0
    assert img[5:25, 10:20].any(), "crop_image must copy"
    big = rp.crop_image(img, (10, 5, 20, 25), scale=3)
    assert big.shape == (60, 30, 3)
    assert np.array_equal(big[::3, ::3], img[5:25, 10:20]) and np.array_equal(big[2::3, 1::3], img[5:25, 10:20])
    assert np.array_equal(rp.crop_image(img, (-10, -10, 5, 5)), img[:5, :5])       # cut at the border
    assert np.array_equal(rp.crop_image(img, (45.4, 30.6, 1000, 1000)), img[31:, 45:])  # rounded
    assert np.array_equal(rp.crop_image(img, np.array([1, 2, 3, 4])), img[2:4, 1:3])
    assert rp.crop_image(img[:, :, 0], None, 2).shape == (80, 100)
    for bad, match in (((5, 5, 5, 10), "empty"), ((20, 5, 10, 10), "empty"), ((60, 0, 70, 10), "outside"),
                       ((0, -20, 10, -1), "outside"), ((0, 0, 10), "4 numbers"), ("0,0,1,1", "crop must be"),
                       ((0, 0, float("nan"), 4), "finite"), ((0, 0, True, 4), "finite")):
        with pytest.raises(ValueError, match=match):
            rp.crop_image(img, bad)
    for bad_scale in (0, 33, 1.5, True):
        with pytest.raises(ValueError, match="scale"):
            rp.crop_image(img, scale=bad_scale)


def test_save_png_writes_atomically(tmp_path, monkeypatch):
    img = rand_image(40, 50)
    path = tmp_path / "shot.png"
    assert rp.save_png(path, img, crop=(10, 5, 20, 25), scale=2) == str(path)
    got = read_png(path.read_bytes())
    assert got.shape == (40, 20, 3) and np.array_equal(got[::2, ::2], img[5:25, 10:20])
    assert sorted(os.listdir(tmp_path)) == ["shot.png"]
    before = path.read_bytes()
    # a bad argument writes nothing, the old file stays
    with pytest.raises(ValueError):
        rp.save_png(path, img.astype(float))
    with pytest.raises(ValueError):
        rp.save_png(path, img, crop=(100, 100, 200, 200))
    assert path.read_bytes() == before and sorted(os.listdir(tmp_path)) == ["shot.png"]

    # a failure while writing leaves the old file whole and no temporary file behind
    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(images.os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        rp.save_png(path, rand_image(8, 8, seed=1))
    monkeypatch.undo()
    assert path.read_bytes() == before and sorted(os.listdir(tmp_path)) == ["shot.png"]
    with pytest.raises(FileNotFoundError):
        rp.save_png(tmp_path / "missing" / "x.png", img)
    # a relative path lands in the current folder (stage programs run in their scratch folder)
    monkeypatch.chdir(tmp_path)
    rp.save_png("rel.png", img[:, :, 0])
    assert read_png((tmp_path / "rel.png").read_bytes()).shape == (40, 50)


# ---------------------------------------------------------------------------------------------
# Projection, visibility, markers
# ---------------------------------------------------------------------------------------------

def test_project_matches_the_pinhole_model():
    s = synthetic_state()
    P = np.array([[0.0, 0.0, 0.0], [0.05, -0.1, 0.2], [0.0, 0.0, 1.5], [2.0, 0.0, 0.0], [0.1, 0.1, 0.5]])
    uv, z, inside = rp.project(P, s, "top")
    for p, (u, v) in zip(P[[0, 1, 4]], uv[[0, 1, 4]]):
        assert np.allclose((u, v), expected_pixel(p))
    assert np.allclose(z, 1.0 - P[:, 2])
    assert inside.tolist() == [True, True, False, False, True]     # behind; off the image
    uv1, _, _ = rp.project([0.05, -0.1, 0.2], s)                     # one camera: name optional
    assert np.allclose(uv1[0], uv[1])
    view = rp.CameraView("top", s["image"]["top"], np.ones((60, 80), np.float32), K, T_DOWN)
    assert np.allclose(rp.project(P, view)[0][:2], uv[:2])
    with pytest.raises(ValueError, match="is not in this state"):
        rp.project(P, s, "wrist")
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        rp.project(P[:, :2], s, "top")


def test_visible_uses_depth():
    depth = np.full((60, 80), 1.0, dtype=np.float32)          # a floor at base z = 0
    depth[20:40, 30:50] = 0.8                                  # a 20 cm high box over the middle
    s = synthetic_state(depth)
    P = np.array([[0.0, 0.0, 0.2],        # top of the box: seen
                  [0.0, 0.0, 0.0],        # floor under the box: hidden
                  [0.2, 0.3, 0.0],        # floor beside it: seen
                  [0.0, 0.0, 1.2],        # behind the camera
                  [0.0, 0.0, 0.195]])     # 5 mm inside the box top: within the tolerance
    assert rp.visible(P, s, "top").tolist() == [True, False, True, False, True]
    assert rp.visible(P, s, "top", tolerance=0.001).tolist() == [True, False, True, False, False]
    with pytest.raises(ValueError, match="no depth"):
        rp.visible(P, synthetic_state(), "top")


def test_fingertip_points():
    down = [0.4, 0.1, 0.3, math.pi, 0.0, 0.0]                 # TCP y = base -y when pointing down
    tips = rp.fingertip_points(down, [-1.0])
    assert np.allclose(tips, [[0.4, 0.06, 0.291], [0.4, 0.14, 0.291]])
    assert np.allclose(rp.fingertip_points(down, 1.0), [[0.4, 0.1, 0.291]] * 2)


def test_markers_land_on_the_projected_pixel():
    s = synthetic_state()
    img = s["image"]["top"]
    img.setflags(write=False)                                   # like a raw native-size image
    P = np.array([[0.05, -0.1, 0.2], [-0.05, 0.1, 0.03], [0.0, 0.0, 1.5], [3.0, 0.0, 0.0], [np.nan, 0, 0]])
    out, drawn = rp.draw_markers(img, P, s, "top", color=[(255, 0, 0), "green", "blue", "red", "red"], size=3)
    assert drawn.tolist() == [True, True, False, False, False]
    assert not img.any() and out is not img and out.flags.writeable
    for p, col in ((P[0], (255, 0, 0)), (P[1], (0, 255, 0))):
        u, v = expected_pixel(p)
        cu, cv = int(math.floor(u + 0.5)), int(math.floor(v + 0.5))
        assert tuple(out[cv, cu]) == col
        assert tuple(out[cv, cu + 3]) == col and tuple(out[cv - 3, cu]) == col      # the cross's arms
        assert not out[cv + 1, cu + 1].any() and not out[cv, cu + 4].any()
    assert (out.any(axis=2)).sum() == 2 * 13                    # two crosses of 13 pixels, nothing else

    # explicit calibration gives the same picture; pixels skip the projection
    out2, _ = rp.draw_markers(img, P, intrinsics=K, base_from_camera=T_DOWN,
                              color=[(255, 0, 0), "green", "blue", "red", "red"], size=3)
    assert np.array_equal(out, out2)
    px, ok = rp.draw_markers(img, [[0, 0], [79, 59], [80, 10], [-1, 3]], color="white", shape="dot", size=2)
    assert ok.tolist() == [True, True, False, False]
    assert px[0, 0].all() and px[59, 79].all() and px[2, 0].all() and not px[3, 0].any()


def test_marker_shapes_and_border():
    img = np.zeros((21, 21, 3), np.uint8)
    c = (10, 10)
    counts = {}
    for shape in images.MARKER_SHAPES:
        out, ok = rp.draw_markers(img, c, shape=shape, size=4, color="white")
        assert ok.tolist() == [True]
        m = out[:, :, 0] > 0
        counts[shape] = int(m.sum())
        assert m[10, 10] == (shape in ("cross", "x", "dot"))
        assert not m[:6].any() and not m[15:].any()               # nothing beyond the size
    assert counts["cross"] == 17 and counts["x"] == 17 and counts["square"] == 32
    thick, _ = rp.draw_markers(img, c, size=4, thickness=3, color="white")
    assert int((thick[:, :, 0] > 0).sum()) == 3 * 9 * 2 - 9
    edge, ok = rp.draw_markers(img, (0, 20), size=4, color="white")   # corner: cut, not skipped
    assert ok.tolist() == [True] and int((edge[:, :, 0] > 0).sum()) == 9
    grey, _ = rp.draw_markers(np.zeros((5, 5), bool), (2, 2), size=1)
    assert grey.shape == (5, 5, 3) and tuple(grey[2, 2]) == (255, 0, 0)


def test_marker_errors():
    s = synthetic_state()
    img = s["image"]["top"]
    with pytest.raises(ValueError, match="intrinsics are for"):
        rp.draw_markers(img[:30], [0, 0, 0], s, "top")
    with pytest.raises(ValueError, match="name the camera"):
        rp.draw_markers(img, [0, 0, 0], {"camera_intrinsics": {"a": K, "b": K}, "camera_extrinsics": {}})
    with pytest.raises(ValueError, match="a get_state"):
        rp.draw_markers(img, [0, 0, 0])
    with pytest.raises(ValueError, match="both intrinsics"):
        rp.draw_markers(img, [0, 0, 0], intrinsics=K)
    with pytest.raises(ValueError, match="not both"):
        rp.draw_markers(img, [0, 0, 0], s, "top", intrinsics=K, base_from_camera=T_DOWN)
    with pytest.raises(ValueError, match="4x4"):
        rp.draw_markers(img, [0, 0, 0], intrinsics=K, base_from_camera=np.eye(3))
    with pytest.raises(ValueError, match="intrinsics lack"):
        rp.draw_markers(img, [0, 0, 0], intrinsics={"fx": 1.0}, base_from_camera=T_DOWN)
    with pytest.raises(ValueError, match=r"\(N, 2\) pixels"):
        rp.draw_markers(img, [[0, 0, 0, 0]])
    with pytest.raises(ValueError, match="shape"):
        rp.draw_markers(img, [1, 1], shape="star")
    with pytest.raises(ValueError, match="size"):
        rp.draw_markers(img, [1, 1], size=0)
    with pytest.raises(ValueError, match="thickness"):
        rp.draw_markers(img, [1, 1], size=2, thickness=6)
    with pytest.raises(ValueError, match="unknown colour"):
        rp.draw_markers(img, [1, 1], color="mauve")
    with pytest.raises(ValueError, match="0-255"):
        rp.draw_markers(img, [1, 1], color=(300, 0, 0))
    with pytest.raises(ValueError, match="one per point"):
        rp.draw_markers(img, [[1, 1], [2, 2], [3, 3]], color=["red", "blue"])
    with pytest.raises(ValueError, match="uint8"):
        rp.draw_markers(img.astype(np.float64), [1, 1])


# ---------------------------------------------------------------------------------------------
# Live: what the cameras show of the hand (pick_block_plate, home pose)
# ---------------------------------------------------------------------------------------------

def test_live_cameras_show_the_fingertips(lockstep, tmp_path):
    from robo import get_state
    s = get_state(["agentview", "wrist"], raw=True)
    T = rp.pose_to_matrix(s["ee_pose"])
    points = np.vstack([T[:3, 3], rp.fingertip_points(s["ee_pose"], s["gripper"])])
    report = {}
    for cam in ("agentview", "wrist"):
        uv, z, inside = rp.project(points, s, cam)
        seen = rp.visible(points, s, cam)
        report[cam] = {"uv": uv.round(1).tolist(), "inside": inside.tolist(), "visible": seen.tolist()}
        # in the image and uncovered: the fingers are drawn as the real ones (their meshes), and
        # the TCP between them is open space the cameras look through
        assert inside.all() and seen.all(), (cam, report[cam])
        out, drawn = rp.draw_markers(s["image"][cam], points, s, cam, color=["yellow", "red", "blue"], shape="circle")
        assert drawn.all()
        c = uv.mean(axis=0)
        rp.save_png(tmp_path / f"{cam}.png", out, crop=(c[0] - 40, c[1] - 30, c[0] + 40, c[1] + 30), scale=3)
        assert read_png((tmp_path / f"{cam}.png").read_bytes()).shape == (180, 240, 3)
    print("TCP, +y tip, -y tip:", report)

    # the axes the README states
    A = np.array(s["camera_extrinsics"]["agentview"])
    assert np.allclose(A[:3, 0], [0, 1, 0], atol=0.02)                      # +u = base +y
    assert A[0, 1] > 0.5 and A[2, 1] < -0.75                                # +v: toward +x and down
    rel = rp.invert_transform(T) @ np.array(s["camera_extrinsics"]["wrist"])
    assert np.allclose(rel[:3, 3], [-0.100, 0.0, -0.1034], atol=0.003)     # wrist camera in the TCP frame
    assert np.allclose(rel[:3, 0], [0, -1, 0], atol=0.02)                   # +u = TCP -y
    assert np.allclose(rel[:3, 2], [0.514, 0, 0.857], atol=0.02)            # 31 deg off the approach
