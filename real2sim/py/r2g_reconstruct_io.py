"""Input side of `r2g reconstruct`: the BOP scene layout, PNG files, joints, and the geometry
service that gives depth to RGB-only frames.

Every problem with the input is a `FramesError` whose message names the file, the image and the
field that is wrong. Nothing here writes files except `write_png`.
"""

from __future__ import annotations

import base64
import json
import math
import os
import struct
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class FramesError(Exception):
    """Bad input frames, joints, task or service answer; the message says what and where."""


# --------------------------------------------------------------------------------------------
# PNG (standard library + numpy)
# --------------------------------------------------------------------------------------------

def read_png(path: Path) -> np.ndarray:
    """A PNG file as (H, W) or (H, W, C) array: uint8 for 8-bit, uint16 for 16-bit images.

    Supports grey, grey+alpha, RGB and RGBA at 8 or 16 bits, without interlacing, every filter.
    """
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise FramesError(f"cannot read {path}: {e.strerror or e}") from None
    if data[:8] != _PNG_SIGNATURE:
        raise FramesError(f"{path} is not a PNG file")
    pos, idat = 8, []
    width = height = 0
    depth = color = -1
    try:
        while pos < len(data):
            (length,) = struct.unpack(">I", data[pos:pos + 4])
            kind = data[pos + 4:pos + 8]
            body = data[pos + 8:pos + 8 + length]
            pos += 12 + length
            if kind == b"IHDR":
                width, height, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", body)
                if interlace:
                    raise FramesError(f"{path}: interlaced PNGs are not supported")
            elif kind == b"IDAT":
                idat.append(body)
            elif kind == b"IEND":
                break
        raw = zlib.decompress(b"".join(idat))
    except (struct.error, zlib.error) as e:
        raise FramesError(f"{path}: damaged PNG ({e})") from None
    channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(color)
    if channels is None or depth not in (8, 16):
        raise FramesError(f"{path}: PNG colour type {color} at {depth} bits is not supported "
                          "(accepted: grey, grey+alpha, RGB, RGBA at 8 or 16 bits)")
    bpp = channels * depth // 8
    stride = width * bpp
    if len(raw) != height * (stride + 1):
        raise FramesError(f"{path}: damaged PNG (pixel data of {len(raw)} bytes, expected {height * (stride + 1)})")
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(height, stride + 1)
    filt = rows[:, 0].astype(np.int32)
    if filt.max(initial=0) > 4:
        raise FramesError(f"{path}: damaged PNG (filter type {int(filt.max())})")
    x = rows[:, 1:].reshape(height, width, bpp).astype(np.int32)
    out = x if not filt.any() else _unfilter(x, filt)
    b = out.astype(np.uint8).reshape(height, stride)
    if depth == 16:
        img = b.reshape(height, width * channels, 2)
        arr = (img[..., 0].astype(np.uint16) << 8) | img[..., 1].astype(np.uint16)
        arr = arr.reshape(height, width, channels)
    else:
        arr = b.reshape(height, width, channels)
    return arr[..., 0] if channels == 1 else arr


def _unfilter(x: np.ndarray, filt: np.ndarray) -> np.ndarray:
    """Undoes PNG row filters over anti-diagonal wavefronts: pixel (y, x) depends on its left,
    upper and upper-left neighbours only, so every pixel with the same y + x is done at once."""
    H, W, B = x.shape
    o = np.zeros((H + 1, W + 1, B), dtype=np.int32)
    for t in range(H + W - 1):
        y0, y1 = max(0, t - W + 1), min(H, t + 1)
        ys = np.arange(y0, y1)
        xs = t - ys
        a = o[ys + 1, xs]
        b = o[ys, xs + 1]
        c = o[ys, xs]
        f = filt[ys][:, None]
        p = a + b - c
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
        paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
        pred = np.select([f == 1, f == 2, f == 3, f == 4], [a, b, (a + b) >> 1, paeth], 0)
        o[ys + 1, xs + 1] = (x[ys, xs] + pred) & 0xFF
    return o[1:, 1:]


def write_png(path: Path, image: np.ndarray) -> None:
    """(H, W) or (H, W, 3) uint8, or (H, W) uint16, as a PNG file (no filter)."""
    a = np.ascontiguousarray(image)
    if a.dtype == np.uint16 and a.ndim == 2:
        depth, color, rowbytes = 16, 0, a.astype(">u2").tobytes()
        w = a.shape[1]
        rows = np.frombuffer(rowbytes, dtype=np.uint8).reshape(a.shape[0], 2 * w)
    elif a.dtype == np.uint8 and a.ndim in (2, 3):
        depth, color = 8, (0 if a.ndim == 2 else {3: 2, 4: 6}[a.shape[2]])
        rows = a.reshape(a.shape[0], -1)
    else:
        raise ValueError(f"write_png: unsupported array {a.shape} {a.dtype}")
    h, w = a.shape[0], a.shape[1]
    raw = np.concatenate([np.zeros((h, 1), dtype=np.uint8), rows], axis=1).tobytes()

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    head = struct.pack(">IIBBBBB", w, h, depth, color, 0, 0, 0)
    Path(path).write_bytes(_PNG_SIGNATURE + chunk(b"IHDR", head) + chunk(b"IDAT", zlib.compress(raw, 3))
                           + chunk(b"IEND", b""))


# --------------------------------------------------------------------------------------------
# The BOP scene layout
# --------------------------------------------------------------------------------------------

@dataclass
class Frame:
    """One image of the input: its calibration (world = robot base frame), RGB and depth."""

    id: str
    K: np.ndarray                  # 3x3
    R_w2c: np.ndarray              # 3x3
    t_w2c_m: np.ndarray            # (3,), metres
    rgb: np.ndarray                # (H, W, 3) uint8
    depth_m: Optional[np.ndarray]  # (H, W) float32 metres, NaN where invalid; None before the service
    rgb_path: Path
    depth_path: Optional[Path]
    depth_source: str = "depth png"
    joints: Optional[list] = None
    gripper: Optional[float] = None
    extra: dict = field(default_factory=dict)

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def intrinsics(self) -> dict:
        return {"fx": float(self.K[0, 0]), "fy": float(self.K[1, 1]), "cx": float(self.K[0, 2]),
                "cy": float(self.K[1, 2]), "width": self.width, "height": self.height}

    @property
    def base_from_camera(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R_w2c.T
        T[:3, 3] = -self.R_w2c.T @ self.t_w2c_m
        return T


def _numbers(entry: dict, key: str, n: int, where: str) -> np.ndarray:
    if key not in entry:
        what = {"cam_K": "the 3x3 intrinsics [fx, 0, cx, 0, fy, cy, 0, 0, 1]; frames without intrinsics "
                         "cannot be reconstructed",
                "cam_R_w2c": "the world-to-camera rotation, 9 numbers row-major (world = the robot base frame)",
                "cam_t_w2c": "the world-to-camera translation, 3 numbers in millimetres",
                "depth_scale": "millimetres per unit of the depth PNG"}.get(key, "")
        raise FramesError(f"{where}: no \"{key}\" ({what})")
    v = entry[key]
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = [v]
    if not isinstance(v, list) or len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                         for x in v):
        raise FramesError(f"{where}: \"{key}\" must be {n} number{'s' if n > 1 else ''}, got {json.dumps(v)[:80]}")
    a = np.array(v, dtype=float)
    if not np.isfinite(a).all():
        raise FramesError(f"{where}: \"{key}\" holds NaN or an infinity: {json.dumps(v)[:80]}")
    return a


def _image_file(folder: Path, im_id: str, what: str) -> Optional[Path]:
    names = [f"{int(im_id):06d}" if im_id.isdigit() else im_id, im_id]
    for n in names:
        p = folder / f"{n}.png"
        if p.is_file():
            return p
    for n in names:
        for ext in (".jpg", ".jpeg", ".tif", ".tiff"):
            if (folder / f"{n}{ext}").is_file():
                raise FramesError(f"{folder / (n + ext)}: {what} must be PNG files ({ext} is not read)")
    return None


def read_frames(frames_dir: Path, need_depth: bool) -> list[Frame]:
    """Reads `scene_camera.json`, `rgb/*.png` and (when there) `depth/*.png` of a BOP scene folder.

    Without a depth folder, frames carry depth_m None (the geometry service fills it) unless
    ``need_depth``, which makes it an error.
    """
    frames_dir = Path(frames_dir)
    if not frames_dir.is_dir():
        raise FramesError(f"frames folder {frames_dir} does not exist")
    cam_path = frames_dir / "scene_camera.json"
    if not cam_path.is_file():
        raise FramesError(f"{frames_dir} has no scene_camera.json (the BOP scene layout: scene_camera.json, "
                          "rgb/<id>.png, depth/<id>.png)")
    try:
        doc = json.loads(cam_path.read_text(), parse_constant=lambda c: float("nan"))
    except (ValueError, UnicodeDecodeError) as e:
        raise FramesError(f"{cam_path} is not JSON: {e}") from None
    if not isinstance(doc, dict) or not doc:
        raise FramesError(f"{cam_path}: expected an object keyed by image id with at least one image")
    depth_dir = frames_dir / "depth"
    has_depth = depth_dir.is_dir()
    if need_depth and not has_depth:
        raise FramesError(f"{frames_dir} has no depth/ folder: give depth PNGs or a geometry service "
                          "(--geometry-url) that answers depth for RGB images")
    frames = []
    ids = sorted(doc, key=lambda k: (0, int(k), "") if k.isdigit() else (1, 0, k))
    for im_id in ids:
        entry = doc[im_id]
        where = f"{cam_path} image '{im_id}'"
        if not isinstance(entry, dict):
            raise FramesError(f"{where}: expected an object with cam_K, cam_R_w2c, cam_t_w2c, depth_scale")
        K = _numbers(entry, "cam_K", 9, where).reshape(3, 3)
        if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or abs(K[2, 2] - 1) > 1e-9:
            raise FramesError(f"{where}: cam_K must be a pinhole matrix [fx, 0, cx, 0, fy, cy, 0, 0, 1] (no skew)")
        R = _numbers(entry, "cam_R_w2c", 9, where).reshape(3, 3)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or abs(np.linalg.det(R) - 1) > 1e-4:
            raise FramesError(f"{where}: cam_R_w2c is not a rotation (orthonormal rows, determinant 1)")
        t = _numbers(entry, "cam_t_w2c", 3, where) / 1000.0
        rgb_path = _image_file(frames_dir / "rgb", im_id, "colour images")
        if rgb_path is None:
            raise FramesError(f"{where}: no colour image rgb/{int(im_id):06d}.png" if im_id.isdigit()
                              else f"{where}: no colour image rgb/{im_id}.png")
        rgb = read_png(rgb_path)
        if rgb.ndim == 2:
            rgb = np.repeat(rgb[..., None], 3, axis=2)
        if rgb.dtype == np.uint16:
            rgb = (rgb >> 8).astype(np.uint8)
        rgb = np.ascontiguousarray(rgb[..., :3])
        H, W = rgb.shape[:2]
        for key, size in (("width", W), ("height", H)):
            if key in entry and entry[key] != size:
                raise FramesError(f"{where}: \"{key}\" = {entry[key]} but {rgb_path.name} is {W}x{H}")
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        if not (fx > 0 and fy > 0):
            raise FramesError(f"{where}: cam_K has a focal length that is not positive (fx {fx}, fy {fy})")
        if not (0 <= cx <= W - 1 and 0 <= cy <= H - 1):
            raise FramesError(f"{where}: cam_K principal point (cx {cx}, cy {cy}) lies outside the {W}x{H} image "
                              f"({rgb_path.name}); it must satisfy 0 <= cx <= {W - 1} and 0 <= cy <= {H - 1} "
                              "(pixel-index convention)")
        depth = None
        depth_path = None
        if has_depth:
            scale = float(_numbers(entry, "depth_scale", 1, where)[0])
            if scale <= 0:
                raise FramesError(f"{where}: depth_scale = {scale}: must be positive (mm per depth unit)")
            depth_path = _image_file(depth_dir, im_id, "depth images")
            if depth_path is None:
                raise FramesError(f"{where}: no depth image depth/{int(im_id):06d}.png beside the colour image"
                                  if im_id.isdigit() else f"{where}: no depth image depth/{im_id}.png")
            d = read_png(depth_path)
            if d.ndim != 2:
                raise FramesError(f"{depth_path}: a depth image must have one channel (uint16), this one has "
                                  f"{d.shape[2]}")
            if d.dtype != np.uint16:
                raise FramesError(f"{depth_path}: a depth image must be 16-bit grey (uint16 x depth_scale = mm); "
                                  f"this one holds {8 * d.dtype.itemsize}-bit values, which would be misread "
                                  "as depth")
            if d.shape != (H, W):
                raise FramesError(f"{depth_path} is {d.shape[1]}x{d.shape[0]} but its colour image {rgb_path.name} "
                                  f"is {W}x{H}: depth and colour must be registered at the same size")
            if not (d > 0).any():
                raise FramesError(f"{depth_path} holds no valid depth (every pixel is 0)")
            dm = d.astype(np.float32) * np.float32(scale / 1000.0)
            dm[d == 0] = np.nan
            depth = dm
        frames.append(Frame(id=str(im_id), K=K, R_w2c=R, t_w2c_m=t, rgb=rgb, depth_m=depth,
                            rgb_path=rgb_path, depth_path=depth_path))
    return frames


# --------------------------------------------------------------------------------------------
# Joints at capture
# --------------------------------------------------------------------------------------------

FINGER_MAX_M = 0.04
"""One finger's travel on the Franka Hand (both fingers open 8 cm)."""


def _finite_list(v: Any, n: int, where: str) -> list:
    if not isinstance(v, list) or len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                         for x in v):
        raise FramesError(f"{where}: expected {n} numbers, got {json.dumps(v)[:80]}")
    if not all(math.isfinite(float(x)) for x in v):
        raise FramesError(f"{where}: holds NaN or an infinity")
    return [float(x) for x in v]


def read_joints(spec: str, frames: list[Frame]) -> None:
    """Sets each frame's joints (7 values, rad) and gripper (-1 open .. +1 closed).

    ``spec``: "q1,...,q7" or "q1,...,q7,gripper" for every image, or a JSON file
    {"<im_id>": {"joints_rad": [7], "finger_m": f}} (as `r2g render` writes joints.json; "gripper"
    may stand in for finger_m), or {"joints_rad": [7], ...} for every image.
    """
    p = Path(spec)
    if p.is_file():
        try:
            doc = json.loads(p.read_text(), parse_constant=lambda c: float("nan"))
        except (ValueError, UnicodeDecodeError) as e:
            raise FramesError(f"joints file {p} is not JSON: {e}") from None
        if not isinstance(doc, dict):
            raise FramesError(f"joints file {p}: expected an object")
        per_image = "joints_rad" not in doc
        for f in frames:
            entry = doc.get(f.id) if per_image else doc
            if entry is None and per_image and f.id.isdigit():
                entry = doc.get(str(int(f.id)))
            if not isinstance(entry, dict):
                raise FramesError(f"joints file {p} has no entry for image '{f.id}' "
                                  f"(ids there: {', '.join(list(doc)[:8])})")
            where = f"joints file {p} image '{f.id}'"
            f.joints = _finite_list(entry.get("joints_rad"), 7, where + " joints_rad")
            if "finger_m" in entry:
                fm = _finite_list([entry["finger_m"]], 1, where + " finger_m")[0]
                f.gripper = float(np.clip(1.0 - 2.0 * fm / FINGER_MAX_M, -1.0, 1.0))
            elif "gripper" in entry:
                f.gripper = float(np.clip(_finite_list([entry["gripper"]], 1, where + " gripper")[0], -1, 1))
            else:
                f.gripper = -1.0
        return
    parts = [s for s in spec.replace(" ", "").split(",") if s != ""]
    try:
        vals = [float(s) for s in parts]
    except ValueError:
        if len(parts) == 1:
            raise FramesError(f"--joints {spec}: no such file, and not a list of numbers") from None
        raise FramesError(f"--joints {spec}: expected 7 numbers (rad) separated by commas, or a joints file") from None
    if len(vals) not in (7, 8):
        raise FramesError(f"--joints: {len(vals)} values given; expected 7 joint angles (rad), optionally an 8th "
                          "for the gripper (-1 open .. +1 closed)")
    if not all(math.isfinite(v) for v in vals):
        raise FramesError("--joints holds NaN or an infinity")
    for f in frames:
        f.joints = vals[:7]
        f.gripper = vals[7] if len(vals) == 8 else -1.0


# --------------------------------------------------------------------------------------------
# The geometry service (RGB in, depth out)
# --------------------------------------------------------------------------------------------

def _lib_path() -> None:
    lib = Path(__file__).resolve().parents[2] / "agent-host" / "py" / "lib"
    if str(lib) not in sys.path:
        sys.path.insert(0, str(lib))


def request_depth(url: str, frame: Frame, timeout_s: float = 60.0) -> np.ndarray:
    """Asks the geometry service for the depth of one RGB image.

    Request (POST, JSON): {"image": {"png": base64 PNG}, "intrinsics": {fx, fy, cx, cy},
    "width": W, "height": H}. Answer: {"depth": {"dtype": "float32", "shape": [H, W],
    "data": base64 little-endian float32, metres along the optical axis, 0 where unknown}}, or
    {"points": {...same, shape [H, W, 3], metres in the camera's optical frame}}. Errors name the
    service and what was wrong (down, not JSON, wrong shape, NaN).
    """
    _lib_path()
    import robo_services as rs  # noqa: E402 - the shared HTTP client of the perception adapters

    name = f"geometry service {url}"
    body = {"image": {"png": base64.b64encode(rs.encode_png(frame.rgb)).decode("ascii")},
            "intrinsics": {k: v for k, v in frame.intrinsics.items() if k in ("fx", "fy", "cx", "cy")},
            "width": frame.width, "height": frame.height}
    try:
        ans = rs._post_json("geometry", url, timeout_s, body)
    except rs.PerceptionServiceError as e:
        raise FramesError(f"image '{frame.id}': {e}") from None
    H, W = frame.height, frame.width
    key = "depth" if "depth" in ans else ("points" if "points" in ans else None)
    if key is None:
        raise FramesError(f"{name}: the answer for image '{frame.id}' has neither 'depth' nor 'points'")
    arr = ans[key]
    want = [H, W] if key == "depth" else [H, W, 3]
    if not isinstance(arr, dict) or arr.get("dtype") != "float32" or not isinstance(arr.get("data"), str):
        raise FramesError(f"{name}: '{key}' for image '{frame.id}' must be {{dtype: float32, shape, data: base64}}")
    if arr.get("shape") != want:
        raise FramesError(f"{name}: '{key}' for image '{frame.id}' has shape {arr.get('shape')}, expected {want} "
                          "(the image's size)")
    try:
        raw = base64.b64decode(arr["data"], validate=True)
    except ValueError:
        raise FramesError(f"{name}: '{key}' data for image '{frame.id}' is not base64") from None
    n = int(np.prod(want))
    if len(raw) != 4 * n:
        raise FramesError(f"{name}: '{key}' for image '{frame.id}' has {len(raw)} bytes, expected {4 * n}")
    a = np.frombuffer(raw, dtype="<f4").reshape(want).astype(np.float32)
    bad = ~np.isfinite(a)
    if bad.any():
        raise FramesError(f"{name}: '{key}' for image '{frame.id}' holds {int(bad.sum())} NaN or infinite values "
                          "(answer 0 where depth is unknown)")
    d = a if key == "depth" else a[..., 2]
    if (d < 0).any():
        raise FramesError(f"{name}: depth for image '{frame.id}' has negative values")
    if not (d > 0).any():
        raise FramesError(f"{name}: depth for image '{frame.id}' is 0 everywhere (no geometry)")
    d = d.copy()
    d[d == 0] = np.nan
    return d


def fill_depth(frames: list[Frame], url: Optional[str]) -> None:
    """Depth for frames without a depth PNG, from the geometry service."""
    missing = [f for f in frames if f.depth_m is None]
    if not missing:
        return
    if not url:
        raise FramesError(f"image '{missing[0].id}' has no depth and no geometry service was given "
                          "(--geometry-url)")
    for f in missing:
        f.depth_m = request_depth(url, f, float(os.environ.get("R2G_GEOMETRY_TIMEOUT_S", "60")))
        f.depth_source = f"geometry service {url}"
