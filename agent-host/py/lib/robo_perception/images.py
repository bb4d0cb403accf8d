"""Images without an imaging library: project base-frame points into a camera, draw markers on a
copy of an image, crop and enlarge it, and write it as a PNG file (numpy + zlib only).

Pixel convention (that of `robo` and `camera.project_points`): ``u`` is the column (right),
``v`` the row (down); pixel ``[v, u]`` of an image has its centre at coordinates ``(u, v)``, so a
projected point belongs to pixel ``(round(u), round(v))``. Crop boxes are ``(u0, v0, u1, v1)``
with the upper bounds excluded, like ``image[v0:v1, u0:u1]``.
"""

from __future__ import annotations

import math
import numbers
import os
import struct
import zlib
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from .camera import CameraView, project_points
from .hand import FRANKA_HAND, HandGeometry, gripper_to_width
from .transforms import ArrayLike, pose_to_matrix, transform_points


COLORS = {
    "red": (255, 0, 0), "green": (0, 255, 0), "blue": (0, 0, 255), "yellow": (255, 255, 0),
    "cyan": (0, 255, 255), "magenta": (255, 0, 255), "orange": (255, 128, 0),
    "white": (255, 255, 255), "black": (0, 0, 0),
}
"""Colour names `draw_markers` accepts besides RGB triples."""

MARKER_SHAPES = ("cross", "x", "circle", "square", "dot")
"""Marker shapes `draw_markers` draws."""

_MAX_SCALE = 32
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------

def _as_image(image: Any, what: str = "image") -> np.ndarray:
    """(H, W, 3) uint8 RGB or (H, W) uint8/bool grey -> that array (bool becomes 0/255 uint8)."""
    if isinstance(image, (bytes, bytearray, memoryview)):
        raise ValueError(f"{what} is PNG bytes, not pixels: call get_state(..., raw=True) for numpy arrays")
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{what} must be a numpy array, got {type(image).__name__}")
    a = image
    if a.dtype == np.bool_ and a.ndim == 2:
        a = a.astype(np.uint8) * np.uint8(255)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.dtype != np.uint8:
        raise ValueError(f"{what} must have dtype uint8 (or bool for a mask), got {a.dtype}; "
                         f"for values in 0..1 use (np.clip(a, 0, 1) * 255).astype(np.uint8)")
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise ValueError(f"{what} must be (H, W, 3) RGB or (H, W) grey, got shape {a.shape}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"{what} is empty: shape {a.shape}")
    return a


def _number(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(float(v)):
        raise ValueError(f"{what} must be a finite number, got {v!r}")
    return float(v)


def _int_in(v: Any, what: str, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or not lo <= int(v) <= hi:
        raise ValueError(f"{what} must be an integer from {lo} to {hi}, got {v!r}")
    return int(v)


def _crop_box(crop: Any, height: int, width: int) -> tuple[int, int, int, int]:
    """Validates ``(u0, v0, u1, v1)`` and clips it to the image; returns integer bounds."""
    if isinstance(crop, (str, bytes)) or not isinstance(crop, Sequence) and not isinstance(crop, np.ndarray):
        raise ValueError(f"crop must be (u0, v0, u1, v1) in pixels, got {crop!r}")
    c = list(np.asarray(crop, dtype=object).reshape(-1)) if isinstance(crop, np.ndarray) else list(crop)
    if len(c) != 4:
        raise ValueError(f"crop must have 4 numbers (u0, v0, u1, v1), got {len(c)}")
    u0, v0, u1, v1 = (int(math.floor(_number(x, f"crop[{i}]") + 0.5)) for i, x in enumerate(c))
    if u1 <= u0 or v1 <= v0:
        raise ValueError(f"crop {tuple(crop)} is empty: need u0 < u1 and v0 < v1 (upper bounds excluded)")
    cu0, cv0, cu1, cv1 = max(u0, 0), max(v0, 0), min(u1, width), min(v1, height)
    if cu1 <= cu0 or cv1 <= cv0:
        raise ValueError(f"crop {tuple(crop)} lies outside the {width}x{height} image (u 0..{width}, v 0..{height})")
    return cu0, cv0, cu1, cv1


# ---------------------------------------------------------------------------------------------
# PNG
# ---------------------------------------------------------------------------------------------

def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def encode_png(image: np.ndarray, level: int = 3) -> bytes:
    """(H, W, 3) uint8 RGB or (H, W) uint8/bool grey -> PNG file bytes (8 bit, zlib ``level`` 0-9).

    Rows are stored unfiltered (filter type 0): on rendered images with flat colours that
    gives smaller files in half the time of the "up" filter. Raises ValueError for another shape
    or dtype.
    """
    a = _as_image(image)
    level = _int_in(level, "level", 0, 9)
    H, W = a.shape[:2]
    channels = 3 if a.ndim == 3 else 1
    rows = np.zeros((H, 1 + W * channels), dtype=np.uint8)    # column 0: the filter byte
    rows[:, 1:] = a.reshape(H, W * channels)
    header = struct.pack(">IIBBBBB", W, H, 8, 2 if channels == 3 else 0, 0, 0, 0)
    return (_PNG_SIGNATURE + _png_chunk(b"IHDR", header)
            + _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), level)) + _png_chunk(b"IEND", b""))


def crop_image(image: np.ndarray, crop: Optional[Sequence[float]] = None, scale: int = 1) -> np.ndarray:
    """A copy of ``image[v0:v1, u0:u1]``, each pixel repeated ``scale`` times in both directions.

    ``crop = (u0, v0, u1, v1)`` in pixels (rounded to integers, upper bounds excluded); a box
    reaching past the border is cut at the border, one entirely outside or empty is a ValueError.
    ``scale``: integer 1-32 (pixel repetition, no smoothing: each source pixel becomes a
    ``scale`` x ``scale`` block, so measured pixel positions stay exact).
    """
    a = _as_image(image)
    scale = _int_in(scale, "scale", 1, _MAX_SCALE)
    if crop is not None:
        u0, v0, u1, v1 = _crop_box(crop, a.shape[0], a.shape[1])
        a = a[v0:v1, u0:u1]
    if scale > 1:
        a = np.repeat(np.repeat(a, scale, axis=0), scale, axis=1)
    return np.array(a)


def save_png(path: Union[str, os.PathLike], image: np.ndarray, crop: Optional[Sequence[float]] = None,
             scale: int = 1) -> str:
    """Writes ``image`` (optionally cropped and enlarged, see `crop_image`) as a PNG file; returns the path.

    The file is written under a temporary name in the same folder and then renamed, so ``path``
    never holds a half-written image. The folder must exist. ValueError for a bad image, crop
    or scale (nothing is written then).
    """
    return _write_atomic(path, encode_png(crop_image(image, crop, scale)))


def _write_atomic(path: Union[str, os.PathLike], data: bytes) -> str:
    """Writes ``data`` under a temporary name in the folder of ``path``, then renames it."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    base = os.path.basename(path)
    while True:
        # Created with the umask's permissions (like open()); the sandbox forbids chmod.
        tmp = os.path.join(folder, f".{base}.{os.urandom(6).hex()}.part")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
            break
        except FileExistsError:
            continue
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


SHOW_DIR = "show"
"""The folder (in a stage program's scratch folder) whose PNG files the host attaches to the
model's next request."""
MAX_SHOWN = 4
"""Images the host attaches per program; more are not shown (the feedback names them)."""
MAX_SHOWN_SIDE = 1280
"""Largest width or height of an image the host attaches, pixels."""
MAX_SHOWN_BYTES = 2 << 20
"""Largest PNG file the host attaches, bytes."""


def show(image: np.ndarray, name: str = "image", crop: Optional[Sequence[float]] = None, scale: int = 1) -> str:
    """Hands ``image`` (optionally cropped and enlarged, see `crop_image`) to the model: written as
    ``show/<NN>-<name>.png`` in the current folder, which the host attaches to the next request
    after the fresh camera images (in a stage program; elsewhere it is just a file). Returns the
    path. ValueError for a bad image, crop or scale, a result wider or taller than
    ``MAX_SHOWN_SIDE``, a PNG larger than ``MAX_SHOWN_BYTES``, or a program's ``MAX_SHOWN + 1``-th
    image (nothing is written then).
    """
    a = crop_image(image, crop, scale)
    if max(a.shape[:2]) > MAX_SHOWN_SIDE:
        raise ValueError(f"show: the image is {a.shape[1]}x{a.shape[0]} pixels; at most {MAX_SHOWN_SIDE} on a side "
                         f"are shown: crop it or use a smaller scale")
    data = encode_png(a)
    if len(data) > MAX_SHOWN_BYTES:
        raise ValueError(f"show: the image is {len(data)} bytes as a PNG; at most {MAX_SHOWN_BYTES} are shown: crop it")
    os.makedirs(SHOW_DIR, exist_ok=True)
    taken = sorted(n for n in os.listdir(SHOW_DIR) if n.endswith(".png") and not n.startswith("."))
    if len(taken) >= MAX_SHOWN:
        raise ValueError(f"show: at most {MAX_SHOWN} images are shown per program ({', '.join(taken)} already)")
    clean = "".join(c if c.isascii() and (c.isalnum() or c in "-_") else "-" for c in str(name))[:40] or "image"
    return _write_atomic(os.path.join(SHOW_DIR, f"{len(taken) + 1:02d}-{clean}.png"), data)


# ---------------------------------------------------------------------------------------------
# Projection
# ---------------------------------------------------------------------------------------------

def _calibration(state: Any, camera: Optional[str], intrinsics: Optional[Mapping[str, float]],
                 base_from_camera: Optional[ArrayLike]) -> tuple[Mapping[str, float], np.ndarray, Optional[str]]:
    """(intrinsics, base_from_camera, camera name) from explicit values, a CameraView or a state."""
    if intrinsics is not None or base_from_camera is not None:
        if intrinsics is None or base_from_camera is None:
            raise ValueError("pass both intrinsics and base_from_camera, or a state and a camera")
        if state is not None:
            raise ValueError("pass either a state (and camera) or intrinsics and base_from_camera, not both")
        K, T, name = intrinsics, base_from_camera, camera
    elif isinstance(state, CameraView):
        K, T, name = state.intrinsics, state.base_from_camera, state.name
    elif isinstance(state, Mapping):
        intr = state.get("camera_intrinsics") or {}
        extr = state.get("camera_extrinsics") or {}
        if camera is None:
            if len(intr) != 1:
                raise ValueError(f"name the camera: this state has calibrations for {sorted(intr)}")
            camera = next(iter(intr))
        if camera not in intr or camera not in extr:
            raise ValueError(f"camera {camera!r} is not in this state (it has {sorted(intr)}); "
                             f"call get_state with that camera, e.g. get_state([{camera!r}], raw=True)")
        K, T, name = intr[camera], extr[camera], camera
    else:
        raise ValueError("need a get_state() dict (with a camera name), a CameraView, "
                         "or intrinsics= and base_from_camera=")
    for key in ("fx", "fy", "cx", "cy", "width", "height"):
        if key not in K:
            raise ValueError(f"intrinsics lack {key!r} (need fx, fy, cx, cy, width, height)")
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"base_from_camera must be a finite 4x4 matrix, got shape {T.shape}")
    return K, T, name


def _points3(points: ArrayLike) -> np.ndarray:
    P = np.asarray(points, dtype=float)
    if P.ndim == 1:
        P = P.reshape(1, -1)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must be (N, 3) base-frame points, got shape {np.shape(points)}")
    return P


def _pixel_index(uv: np.ndarray, z: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Nearest pixel (column, row) of each projection and whether it lies in the image and in front."""
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(uv).all(axis=1) & np.isfinite(z) & (z > 0)
        f = np.floor(uv + 0.5)
        ok &= (f[:, 0] >= 0) & (f[:, 0] < width) & (f[:, 1] >= 0) & (f[:, 1] < height)
        pix = np.where(ok[:, None], f, -1).astype(np.int64)   # cast only in-image values
    return pix, ok


def project(points: ArrayLike, state: Any, camera: Optional[str] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Base-frame points -> ``(uv (N, 2), z (N,), inside (N,) bool)`` in ``camera`` of ``state``.

    ``state``: a `get_state` dict that includes that camera (raw or not; its intrinsics are for
    the size actually returned) or a `CameraView`. ``uv`` are (column, row) pixel coordinates,
    ``z`` the depth in front of the camera (m, negative behind it), ``inside`` is True where the
    point is in front of the camera and its pixel ``(round(u), round(v))`` lies in the image.
    Being inside says nothing about occlusion: see `visible`.
    """
    K, T, _ = _calibration(state, camera, None, None)
    P = _points3(points)
    uv, z = project_points(P, K, T)
    _, inside = _pixel_index(uv, z, int(K["width"]), int(K["height"]))
    return uv, z, inside


def fingertip_points(ee_pose: ArrayLike, gripper: Any, hand: HandGeometry = FRANKA_HAND) -> np.ndarray:
    """(2, 3) base-frame points: the tips of the two finger pads' inner (gripping) faces.

    Row 0 is the finger on the TCP's +y side, row 1 the one on its -y side; both lie ``hand.
    tip_beyond_tcp`` past the TCP along the approach, ``gripper_to_width(gripper) / 2`` either
    side of it. ``gripper``: the measured value (a number or get_state's ``[g]``). Meant for
    `project` / `draw_markers`: the cameras do not show the fingers themselves.
    """
    g = gripper[0] if isinstance(gripper, (list, tuple, np.ndarray)) else gripper
    half = gripper_to_width(_number(float(g), "gripper"), hand) / 2.0
    T = pose_to_matrix(ee_pose)
    local = np.array([[0.0, half, hand.tip_beyond_tcp], [0.0, -half, hand.tip_beyond_tcp]])
    return transform_points(T, local)


def visible(points: ArrayLike, state: Any, camera: Optional[str] = None, tolerance: float = 0.01) -> np.ndarray:
    """(N,) bool: which base-frame points the camera actually sees.

    A point is visible when it is `inside` the image (see `project`) and the depth image at its
    pixel is not more than ``tolerance`` (m) in front of the point's own depth, i.e. nothing
    stands between it and the camera. Needs the camera's depth (``get_state(..., raw=True)``).
    """
    K, T, name = _calibration(state, camera, None, None)
    if isinstance(state, CameraView):
        depth = state.depth
    else:
        depth = (state.get("depth") or {}).get(name)
        if depth is None:
            raise ValueError(f"camera {name!r}: no depth in this state; call get_state(..., raw=True)")
    depth = np.asarray(depth)
    W, H = int(K["width"]), int(K["height"])
    if depth.shape != (H, W):
        raise ValueError(f"camera {name!r}: depth is {depth.shape} but the intrinsics are for {H}x{W}")
    tol = _number(tolerance, "tolerance")
    P = _points3(points)
    uv, z = project_points(P, K, T)
    pix, ok = _pixel_index(uv, z, W, H)
    seen = np.zeros(len(P), dtype=bool)
    if ok.any():
        d = depth[pix[ok, 1], pix[ok, 0]].astype(float)
        with np.errstate(invalid="ignore"):
            seen[ok] = ~(np.isfinite(d) & (d > 0) & (d < z[ok] - tol))
    return seen


# ---------------------------------------------------------------------------------------------
# Markers
# ---------------------------------------------------------------------------------------------

def _colors(color: Any, n: int) -> np.ndarray:
    def one(c: Any) -> np.ndarray:
        if isinstance(c, str):
            if c.lower() not in COLORS:
                raise ValueError(f"unknown colour {c!r}; use an (r, g, b) triple 0-255 or one of {sorted(COLORS)}")
            return np.array(COLORS[c.lower()], dtype=np.uint8)
        a = np.asarray(c, dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 255:
            raise ValueError(f"colour must be (r, g, b) with values 0-255 or a name, got {c!r}")
        return np.round(a).astype(np.uint8)

    if isinstance(color, str):
        return np.tile(one(color), (n, 1))
    arr = np.asarray(color, dtype=object)
    if arr.ndim == 1 and len(arr) == 3 and not any(isinstance(c, str) for c in arr):
        return np.tile(one(color), (n, 1))
    seq = list(color)
    if len(seq) != n:
        raise ValueError(f"give one colour for all markers or one per point ({n}), got {len(seq)}")
    return np.stack([one(c) for c in seq]) if n else np.zeros((0, 3), dtype=np.uint8)


def _stencil(shape: str, size: int, thickness: int) -> np.ndarray:
    """Boolean (2 size + 1) square: the marker's pixels around its centre."""
    r = np.arange(-size, size + 1)
    dv, du = np.meshgrid(r, r, indexing="ij")
    h = (thickness - 1) // 2
    if shape == "cross":
        return (np.abs(dv) <= h) | (np.abs(du) <= h)
    if shape == "x":
        return (np.abs(du - dv) <= h) | (np.abs(du + dv) <= h)
    if shape == "circle":
        return np.abs(np.hypot(du, dv) - size) <= h + 0.5
    if shape == "square":
        return np.abs(np.maximum(np.abs(du), np.abs(dv)) - size) <= h
    return np.hypot(du, dv) <= size + 0.25          # dot


def draw_markers(image: np.ndarray, points: ArrayLike, state: Any = None, camera: Optional[str] = None, *,
                 intrinsics: Optional[Mapping[str, float]] = None, base_from_camera: Optional[ArrayLike] = None,
                 color: Any = "red", shape: str = "cross", size: int = 6,
                 thickness: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Draws one marker per point on a copy of ``image``; returns ``(marked copy, drawn (N,) bool)``.

    ``points``: (N, 3) base-frame points, projected with the calibration of ``camera`` in
    ``state`` (a `get_state` dict or a `CameraView`) or with explicit ``intrinsics`` and
    ``base_from_camera`` (``get_state``'s ``camera_intrinsics[cam]`` / ``camera_extrinsics[cam]``);
    or (N, 2) pixel coordinates ``(u, v)`` used as they are (no calibration needed). One point may
    be given flat, ``(x, y, z)`` or ``(u, v)``.
    ``color``: a name (see `COLORS`), an (r, g, b) triple 0-255, or one of those per point.
    ``shape``: ``"cross"``, ``"x"``, ``"circle"``, ``"square"`` or ``"dot"``; ``size``: its
    radius in pixels (1-200); ``thickness``: line width in pixels (1, 3, 5 ...; even widths
    round down). A grey image or bool mask comes back as RGB.

    A point is skipped (``drawn`` False) when it is behind the camera, not finite, or its pixel
    lies outside the image; markers near the border are cut at the border. ``image`` itself is
    never changed (raw images at the native size are read-only anyway).
    """
    a = _as_image(image)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    out = np.array(a)
    H, W = out.shape[:2]
    if shape not in MARKER_SHAPES:
        raise ValueError(f"unknown marker shape {shape!r}; use one of {list(MARKER_SHAPES)}")
    size = _int_in(size, "size", 1, 200)
    thickness = _int_in(thickness, "thickness", 1, 2 * size + 1)
    P = np.asarray(points, dtype=float)
    if P.ndim == 1:
        P = P.reshape(1, -1)
    if P.ndim != 2 or P.shape[1] not in (2, 3):
        raise ValueError(f"points must be (N, 3) base-frame points or (N, 2) pixels (u, v), got shape {np.shape(points)}")
    if P.shape[1] == 3:
        K, T, name = _calibration(state, camera, intrinsics, base_from_camera)
        if (int(K["width"]), int(K["height"])) != (W, H):
            raise ValueError(f"the image is {W}x{H} but camera {name!r}'s intrinsics are for "
                             f"{int(K['width'])}x{int(K['height'])}: use the state the image came from")
        uv, z = project_points(P, K, T)
    else:
        uv, z = P, np.ones(len(P))
    pix, ok = _pixel_index(uv, z, W, H)
    cols = _colors(color, len(P))
    st = _stencil(shape, size, thickness)
    for i in np.flatnonzero(ok):
        u, v = int(pix[i, 0]), int(pix[i, 1])
        u0, v0, u1, v1 = max(u - size, 0), max(v - size, 0), min(u + size + 1, W), min(v + size + 1, H)
        m = st[v0 - (v - size):v1 - (v - size), u0 - (u - size):u1 - (u - size)]
        out[v0:v1, u0:u1][m] = cols[i]
    return out, ok
