"""Remote perception services for `robo` stage programs (numpy + standard library only).

Two HTTP services can stand in for the local numpy perception of `robo_perception`:

* **segmentation** (SAM3-style): an RGB image and a text or point prompt in, scored masks out;
* **grasps** (Contact-GraspNet-style): a depth image, the intrinsics and a target mask in,
  parallel-jaw grasp poses in the camera frame out.

The wire formats are this project's own; they are described in robot-skill/api/PERCEPTION.md
("Remote services (HTTP)"). Which backend a program uses is chosen by the operator in
``robot-skill/config/perception.json`` (path overridable with ``R2G_PERCEPTION_CONFIG``):
``"local"`` (robo_perception, no network) or ``"http"`` (the services). There is no fallback
from one to the other: a failing service raises `PerceptionServiceError`.

Typical use in a stage program, the same code for both backends::

    from robo import get_state
    import robo_services as rs
    state = get_state(["agentview"], raw=True)
    block = rs.find(state, "red block")          # ObjectCluster (local) or RemoteMask (http)
    grasps = rs.grasps_for(state, block)         # [robo_perception.Grasp], best first

Both kinds of target offer ``.masks[camera]`` ((H, W) bool), ``.points`` ((N, 3) base frame)
and ``.centroid``.

Inside the sandbox a program cannot open sockets. There ``robo`` is the forwarding shim, and this
module sends small requests (camera, frame timestamp, prompt or mask) to the trusted proxy, which
takes the image and depth of that very frame from its own connection, reads the configuration
and calls the services itself: the program never chooses a URL.
"""

from __future__ import annotations

import base64
import json
import math
import numbers
import os
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np

import robo_perception as rp

__all__ = [
    "BACKENDS", "CONFIG_ENV", "ServiceConfig", "PerceptionConfig", "config_path", "parse_config", "load_config",
    "backend", "serve_proxy",
    "PerceptionServiceError", "RemoteMask", "find", "grasps_for", "segment_http", "grasps_http",
    "request_segment", "request_grasps", "rle_encode", "rle_decode", "encode_png",
    "MAX_RESPONSE_BYTES", "PREGRASP_OFFSET",
]

BACKENDS = ("local", "http")
CONFIG_ENV = "R2G_PERCEPTION_CONFIG"
MAX_RESPONSE_BYTES = 64 << 20
"""Largest answer body read from a service; a longer one is an error."""
MAX_MASKS = 256
MAX_MASK_PIXELS = 1 << 26  # all masks of one answer together, decoded (64 MiB of bool)
"""Most masks one segmentation answer may hold (each decodes to a full-size boolean image)."""
PREGRASP_OFFSET = 0.10
"""Pre-grasp distance behind a remote grasp, along its approach (m)."""
OPEN_MARGIN = 0.016
"""Added to a remote grasp's width to get the opening to approach with (m)."""
PROXY_FRAME_LIMIT = 1 << 20
"""The proxy drops a worker whose request frame is larger than this (agent-host/py/robo_proxy.py)."""
MAX_SIDE = 4096


class PerceptionServiceError(RuntimeError):
    """A perception service failed: unreachable, too slow, an HTTP error, or an answer that
    does not follow the wire format. The message names the service's URL and what went wrong."""


def _finite(v: Any) -> bool:
    """A JSON number (not a bool) that is finite as a float."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ServiceConfig:
    url: str
    timeout_s: float


@dataclass(frozen=True)
class PerceptionConfig:
    path: str
    backend: str
    segment: ServiceConfig
    grasp: ServiceConfig


def config_path() -> Path:
    """``$R2G_PERCEPTION_CONFIG`` if set, else ``<repo>/robot-skill/config/perception.json``."""
    env = os.environ.get(CONFIG_ENV)
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "robot-skill" / "config" / "perception.json"


def _no_duplicates(pairs: list) -> dict:
    out: dict = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"key {k!r} appears twice")
        out[k] = v
    return out


def _check_keys(obj: Any, where: str, prefix: str, known: Sequence[str]) -> None:
    label = prefix.rstrip(".") or "the top level"
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: {label!r} must be a JSON object" if prefix else f"{where}: the top level must be a JSON object")
    for k in obj:
        if k not in known:
            raise ValueError(f"{where}: unknown key '{prefix}{k}' (known: {', '.join(known)})")
    for k in known:
        if k not in obj:
            raise ValueError(f"{where}: missing key '{prefix}{k}'")


def _service(obj: Any, where: str, name: str) -> ServiceConfig:
    _check_keys(obj, where, f"{name}.", ("url", "timeout_s"))
    url = obj["url"]
    if not isinstance(url, str):
        raise ValueError(f"{where}: key '{name}.url' must be a string, got {url!r}")
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 - raises on a malformed port
    except ValueError as e:
        raise ValueError(f"{where}: key '{name}.url' is not a valid URL ({e}): {url!r}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"{where}: key '{name}.url' must be an http:// or https:// URL with a host, got {url!r}")
    t = obj["timeout_s"]
    if not _finite(t) or t <= 0:
        raise ValueError(f"{where}: key '{name}.timeout_s' must be a positive, finite number of seconds, got {t!r}")
    return ServiceConfig(url=url, timeout_s=float(t))


def parse_config(raw: Any, where: str = "perception config") -> PerceptionConfig:
    """Validates an already-decoded configuration object (strict: no unknown or missing keys)."""
    _check_keys(raw, where, "", ("backend", "segment", "grasp"))
    b = raw["backend"]
    if b not in BACKENDS:
        raise ValueError(f"{where}: key 'backend' must be one of {', '.join(map(repr, BACKENDS))}, got {b!r}")
    return PerceptionConfig(path=where, backend=b, segment=_service(raw["segment"], where, "segment"),
                            grasp=_service(raw["grasp"], where, "grasp"))


def load_config(path: Optional[os.PathLike | str] = None) -> PerceptionConfig:
    """Reads and validates the configuration (default: `config_path()`); ValueError naming the
    file and the key on any problem."""
    p = Path(path) if path is not None else config_path()
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{p}: perception config not found (set ${CONFIG_ENV} or create it)") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{p}: cannot read the perception config: {e}") from None
    try:
        raw = json.loads(text, object_pairs_hook=_no_duplicates)
    except ValueError as e:
        raise ValueError(f"{p}: not valid JSON: {e}") from None
    return parse_config(raw, str(p))


# --------------------------------------------------------------------------------------------
# Encodings: run-length masks, PNG
# --------------------------------------------------------------------------------------------

def rle_encode(mask: np.ndarray) -> dict:
    """(H, W) boolean mask -> ``{"size": [H, W], "counts": [...]}``: run lengths over the
    row-major flattened mask, alternating false/true and starting with a (possibly empty) run
    of false."""
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise ValueError(f"a mask must be 2-D, got shape {m.shape}")
    H, W = m.shape
    flat = m.reshape(-1)
    if flat.size == 0:
        return {"size": [H, W], "counts": []}
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    counts = np.diff(np.concatenate(([0], change, [flat.size])))
    if flat[0]:
        counts = np.concatenate(([0], counts))
    return {"size": [int(H), int(W)], "counts": counts.tolist()}


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def rle_decode(rle: Any, shape: Optional[tuple[int, int]] = None) -> np.ndarray:
    """Inverse of `rle_encode`, with checks (ValueError): the size is two positive integers
    (equal to ``shape`` when given), counts are non-negative integers summing to H*W."""
    if not isinstance(rle, dict) or "size" not in rle or "counts" not in rle:
        raise ValueError("an RLE mask must be an object with 'size' and 'counts'")
    size, counts = rle["size"], rle["counts"]
    if not (isinstance(size, list) and len(size) == 2 and all(_is_int(s) and 0 < s <= MAX_SIDE for s in size)):
        raise ValueError(f"RLE 'size' must be [H, W] with 1..{MAX_SIDE} each, got {str(size)[:60]}")
    H, W = size
    if shape is not None and (H, W) != tuple(shape):
        raise ValueError(f"is {H}x{W} but the image is {shape[0]}x{shape[1]}")
    if not isinstance(counts, list):
        raise ValueError("RLE 'counts' must be a list of integers")
    c = np.asarray(counts) if counts else np.zeros(0, dtype=np.int64)
    if c.ndim != 1 or c.dtype.kind not in "iu":
        raise ValueError("RLE 'counts' must be a list of integers")
    if c.size and (int(c.min()) < 0 or int(c.max()) > H * W):
        raise ValueError("RLE counts must lie in 0..H*W")
    total = int(c.sum(dtype=np.int64))
    if total != H * W:
        raise ValueError(f"RLE counts sum to {total}, expected {H}*{W} = {H * W}")
    values = (np.arange(c.size) % 2).astype(bool)
    return np.repeat(values, c).reshape(H, W)


def encode_png(rgb: np.ndarray, level: int = 3) -> bytes:
    """(H, W, 3) uint8 RGB -> PNG bytes (8 bit, zlib ``level``); the encoder is
    `robo_perception.encode_png`, limited here to RGB as the segmentation service expects."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ValueError(f"encode_png needs an (H, W, 3) uint8 array, got {a.shape} {a.dtype}")
    return rp.encode_png(a, level)


def _pack_mask(mask: np.ndarray) -> bytes:
    return np.packbits(np.asarray(mask, dtype=bool).reshape(-1)).tobytes()


def _unpack_mask(bits: bytes, shape: tuple[int, int]) -> np.ndarray:
    n = shape[0] * shape[1]
    if len(bits) != (n + 7) // 8:
        raise ValueError(f"a packed {shape[0]}x{shape[1]} mask must have {(n + 7) // 8} bytes, got {len(bits)}")
    return np.unpackbits(np.frombuffer(bits, dtype=np.uint8), count=n).astype(bool).reshape(shape)


# --------------------------------------------------------------------------------------------
# HTTP
# --------------------------------------------------------------------------------------------



def _post_json(what: str, url: str, timeout: float, body: dict) -> dict:
    """POSTs ``body`` as JSON and returns the decoded JSON object; PerceptionServiceError on
    anything else. No proxies from the environment, no redirects, at most MAX_RESPONSE_BYTES."""
    import http.client
    import urllib.error
    import urllib.request

    class NoRedirect(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *args: Any, **kwargs: Any) -> None:
            return None  # a 3xx then surfaces as an HTTPError with its status

    name = f"{what} service {url}"
    data = json.dumps(body, allow_nan=False).encode()
    req = urllib.request.Request(url, data=data, method="POST",
                                 headers={"Content-Type": "application/json", "Accept": "application/json"})
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}), NoRedirect())
    deadline = time.monotonic() + timeout
    late = f"{name} did not answer within {timeout:.1f} s"
    try:
        with opener.open(req, timeout=timeout) as resp:
            length = resp.headers.get("Content-Length")
            if length is not None and length.strip().isdigit() and int(length) > MAX_RESPONSE_BYTES:
                raise PerceptionServiceError(f"{name} answered {int(length)} bytes, more than the "
                                             f"{MAX_RESPONSE_BYTES >> 20} MiB allowed")
            buf = bytearray()
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise PerceptionServiceError(late)
                sock = getattr(getattr(resp.fp, "raw", None), "_sock", None)
                if sock is not None:
                    # each read waits at most the time left, so a trickling answer cannot stretch it
                    sock.settimeout(left)
                chunk = resp.read1(min(1 << 16, MAX_RESPONSE_BYTES + 1 - len(buf)))
                if not chunk:
                    break
                buf += chunk
                if len(buf) > MAX_RESPONSE_BYTES:
                    raise PerceptionServiceError(f"{name} answered more than the {MAX_RESPONSE_BYTES >> 20} MiB allowed")
                if time.monotonic() > deadline:
                    raise PerceptionServiceError(late)
    except urllib.error.HTTPError as e:
        try:
            text = e.read(4096).decode("utf-8", "replace").strip()
        except Exception:  # noqa: BLE001 - the status is what matters
            text = ""
        raise PerceptionServiceError(f"{name} answered HTTP {e.code}: {text[:200] or '(empty body)'}") from None
    except urllib.error.URLError as e:
        r = e.reason
        if isinstance(r, TimeoutError):
            raise PerceptionServiceError(late) from None
        if isinstance(r, ConnectionRefusedError):
            raise PerceptionServiceError(f"{name} is not reachable: connection refused") from None
        raise PerceptionServiceError(f"{name} is not reachable: {getattr(r, 'strerror', None) or r}") from None
    except TimeoutError:
        raise PerceptionServiceError(late) from None
    except (http.client.HTTPException, OSError) as e:
        raise PerceptionServiceError(f"{name} broke off its answer: {type(e).__name__}: {e}") from None
    try:
        ans = json.loads(bytes(buf))
    except (ValueError, RecursionError):
        snippet = bytes(buf[:80]).decode("utf-8", "replace")
        raise PerceptionServiceError(f"{name} answered something that is not JSON: {snippet!r}") from None
    if not isinstance(ans, dict):
        raise PerceptionServiceError(f"{name} answered JSON that is not an object")
    return ans


def request_segment(service: ServiceConfig, image: np.ndarray | bytes, height: int, width: int,
                    text: Optional[str] = None, point: Optional[Sequence[float]] = None
                    ) -> list[tuple[np.ndarray, float, Optional[str]]]:
    """One segmentation request. ``image``: (H, W, 3) uint8 RGB or PNG bytes of that size.
    Returns ``[(mask (H, W) bool, score, label or None)]`` sorted by score, best first."""
    prompt = _prompt(text, point, width, height)
    png = bytes(image) if isinstance(image, (bytes, bytearray, memoryview)) else encode_png(image)
    body = {"image": {"format": "png", "data": base64.b64encode(png).decode("ascii")},
            "width": int(width), "height": int(height), "prompt": prompt}
    ans = _post_json("segment", service.url, service.timeout_s, body)
    return _parse_masks(ans, f"segment service {service.url}", (int(height), int(width)))


def _prompt(text: Optional[str], point: Optional[Sequence[float]], width: int, height: int) -> dict:
    prompt: dict = {}
    if text is not None:
        if not isinstance(text, str) or not text.strip() or len(text) > 1000:
            raise ValueError("the text prompt must be a non-empty string of at most 1000 characters")
        prompt["text"] = text
    if point is not None:
        if not (isinstance(point, (list, tuple, np.ndarray)) and len(point) == 2
                and all(isinstance(x, numbers.Real) and not isinstance(x, bool) for x in point)):
            raise ValueError(f"the point prompt must be (u, v) pixel coordinates, got {point!r}")
        u, v = float(point[0]), float(point[1])
        if not (math.isfinite(u) and math.isfinite(v) and 0 <= u < width and 0 <= v < height):
            raise ValueError(f"the point ({u}, {v}) lies outside the {width}x{height} image")
        prompt["points"] = [[u, v]]
        prompt["labels"] = [1]
    if not prompt:
        raise ValueError("the segmentation service needs a text prompt or a point")
    return prompt


def _parse_masks(ans: dict, name: str, shape: tuple[int, int]) -> list[tuple[np.ndarray, float, Optional[str]]]:
    if "masks" not in ans:
        raise PerceptionServiceError(f"{name} answer lacks 'masks'")
    items = ans["masks"]
    if not isinstance(items, list):
        raise PerceptionServiceError(f"{name}: 'masks' is not a list")
    if len(items) > MAX_MASKS:
        raise PerceptionServiceError(f"{name}: {len(items)} masks, more than the {MAX_MASKS} allowed")
    if len(items) * shape[0] * shape[1] > MAX_MASK_PIXELS:
        raise PerceptionServiceError(f"{name}: {len(items)} masks of {shape[0]}x{shape[1]} are more than the "
                                     f"{MAX_MASK_PIXELS} mask pixels one answer may hold")
    out = []
    for i, it in enumerate(items):
        if not isinstance(it, dict) or "mask" not in it or "score" not in it:
            raise PerceptionServiceError(f"{name}: mask {i} must be an object with 'mask' and 'score'")
        try:
            m = rle_decode(it["mask"], shape)
        except ValueError as e:
            raise PerceptionServiceError(f"{name}: mask {i} {e}" if str(e).startswith("is ") else f"{name}: mask {i}: {e}") from None
        score = it["score"]
        if not _finite(score):
            raise PerceptionServiceError(f"{name}: mask {i} has a score that is not a finite number: {score!r}")
        label = it.get("label")
        if label is not None and not isinstance(label, str):
            raise PerceptionServiceError(f"{name}: mask {i} has a label that is not a string")
        out.append((m, float(score), label))
    out.sort(key=lambda t: -t[1])
    return out


def request_grasps(service: ServiceConfig, depth: np.ndarray, intrinsics: Mapping[str, float],
                   mask: np.ndarray) -> list[tuple[np.ndarray, float, float]]:
    """One grasp request. Returns ``[(pose 4x4 in the camera optical frame, score, width)]``
    sorted by score, every pose checked (finite, rigid)."""
    d = np.asarray(depth)
    m = np.asarray(mask, dtype=bool)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {d.shape}")
    if m.shape != d.shape:
        raise ValueError(f"the mask is {m.shape[0]}x{m.shape[1]} but the depth image is {d.shape[0]}x{d.shape[1]}")
    if not m.any():
        raise ValueError("the target mask is empty")
    K = {k: float(intrinsics[k]) for k in ("fx", "fy", "cx", "cy")}
    body = {"depth": {"dtype": "float32", "shape": [int(d.shape[0]), int(d.shape[1])],
                      "data": base64.b64encode(np.ascontiguousarray(d, dtype="<f4").tobytes()).decode("ascii")},
            "intrinsics": K, "segmap": rle_encode(m), "segmap_id": 1}
    ans = _post_json("grasp", service.url, service.timeout_s, body)
    return _parse_grasps(ans, f"grasp service {service.url}")


def _pose_matrix(pose: Any) -> Optional[np.ndarray]:
    if not (isinstance(pose, list) and len(pose) == 4
            and all(isinstance(r, list) and len(r) == 4 for r in pose)):
        return None
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for r in pose for v in r):
        return None
    try:
        return np.array(pose, dtype=float)
    except OverflowError:  # an integer beyond float range
        return np.full((4, 4), np.inf)


def _parse_grasps(ans: dict, name: str) -> list[tuple[np.ndarray, float, float]]:
    if "grasps" not in ans:
        raise PerceptionServiceError(f"{name} answer lacks 'grasps'")
    items = ans["grasps"]
    if not isinstance(items, list):
        raise PerceptionServiceError(f"{name}: 'grasps' is not a list")
    out = []
    for i, it in enumerate(items):
        if not isinstance(it, dict) or not all(k in it for k in ("pose", "score", "width")):
            raise PerceptionServiceError(f"{name}: grasp {i} must be an object with 'pose', 'score' and 'width'")
        T = _pose_matrix(it["pose"])
        if T is None:
            raise PerceptionServiceError(f"{name}: grasp {i}: 'pose' is not a 4x4 matrix of numbers (nested rows)")
        if not np.isfinite(T).all():
            raise PerceptionServiceError(f"{name}: grasp {i}: the pose has non-finite values")
        if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
            raise PerceptionServiceError(f"{name}: grasp {i}: the pose's last row is not [0, 0, 0, 1]")
        R = T[:3, :3]
        err = float(np.abs(R.T @ R - np.eye(3)).max())
        if err > 1e-3 or np.linalg.det(R) < 0:
            raise PerceptionServiceError(f"{name}: grasp {i}: the pose's rotation is not orthonormal "
                                         f"(max |R^T R - I| = {err:.3g}, det {np.linalg.det(R):.3f})")
        score, width = it["score"], it["width"]
        if not _finite(score):
            raise PerceptionServiceError(f"{name}: grasp {i} has a score that is not a finite number: {score!r}")
        if not _finite(width) or width < 0:
            raise PerceptionServiceError(f"{name}: grasp {i} has a width that is not a non-negative number: {width!r}")
        out.append((T, float(score), float(width)))
    out.sort(key=lambda t: -t[1])
    return out


# --------------------------------------------------------------------------------------------
# Results in the base frame
# --------------------------------------------------------------------------------------------

@dataclass
class RemoteMask:
    """One mask from the segmentation service. ``mask``: (H, W) bool in ``camera``'s image;
    ``points``: its (N, 3) base-frame points from the state's depth (None when the state had no
    depth for that camera); ``score`` and ``label`` as the service gave them."""

    camera: str
    mask: np.ndarray
    score: float
    label: Optional[str]
    points: Optional[np.ndarray]

    @property
    def masks(self) -> dict:
        """``{camera: mask}``, the same shape of access as `ObjectCluster.masks`."""
        return {self.camera: self.mask}

    @property
    def centroid(self) -> Optional[np.ndarray]:
        """Mean of the visible points (None without points or with no valid depth)."""
        if self.points is None or len(self.points) == 0:
            return None
        return self.points.mean(axis=0)

    @property
    def pixel_count(self) -> int:
        return int(self.mask.sum())

    def describe(self) -> str:
        c = self.centroid
        at = f" at ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f})" if c is not None else ""
        return f"{self.label or 'mask'} score {self.score:.2f} in {self.camera}{at}, {self.pixel_count} px"


def _frame(state: Mapping[str, Any], camera: str) -> dict:
    images = state.get("image") or {}
    if camera not in images:
        raise ValueError(f"the state has no image from camera {camera!r} (it has {sorted(images)}); "
                         f"observe with get_state([{camera!r}], raw=True)")
    img = images[camera]
    K = (state.get("camera_intrinsics") or {}).get(camera)
    ext = (state.get("camera_extrinsics") or {}).get(camera)
    if K is None or ext is None:
        raise ValueError(f"the state lacks camera_intrinsics/camera_extrinsics for {camera!r}")
    depth = (state.get("depth") or {}).get(camera)
    if isinstance(img, np.ndarray):
        H, W = int(img.shape[0]), int(img.shape[1])
    else:
        H, W = int(K["height"]), int(K["width"])
    if depth is not None and tuple(np.shape(depth)) != (H, W):
        raise ValueError(f"camera {camera!r}: depth {np.shape(depth)} and image {H}x{W} differ")
    ts = (state.get("image_timestamp") or {}).get(camera)
    return {"image": img, "depth": depth, "K": K, "base_from_camera": np.asarray(ext, dtype=float),
            "height": H, "width": W, "timestamp": ts}


def _points(fr: dict, mask: np.ndarray) -> Optional[np.ndarray]:
    if fr["depth"] is None:
        return None
    return rp.depth_to_points(np.asarray(fr["depth"]), fr["K"], fr["base_from_camera"], mask=mask)[0]


def _to_grasp(T_cam: np.ndarray, score: float, width: float, base_from_camera: np.ndarray, camera: str,
              source: str, reference: Optional[np.ndarray] = None) -> rp.Grasp:
    T = base_from_camera @ T_cam
    # of the two equivalent yaws, the one the local grasps would take
    T[:3, :3] = rp.grasp_rotation(T[:3, 1], T[:3, 2], reference)
    pre = T.copy()
    pre[:3, 3] -= T[:3, 2] * PREGRASP_OFFSET
    open_w = min(width + OPEN_MARGIN, rp.GRIPPER_MAX_WIDTH)
    return rp.Grasp(pose=rp.matrix_to_pose(T), pregrasp=rp.matrix_to_pose(pre), width=width, open_width=open_w,
                    gripper_open=rp.width_to_gripper(open_w), score=score, kind="remote",
                    approach=T[:3, 2].copy(), closing=T[:3, 1].copy(), position=T[:3, 3].copy(),
                    clearance=float("nan"),
                    details={"camera": camera, "camera_pose": T_cam.tolist(), "source": source})


# --------------------------------------------------------------------------------------------
# Inside the sandbox: through the proxy
# --------------------------------------------------------------------------------------------

def _shim() -> Any:
    """The sandbox's forwarding `robo` (it has ``_call``), or None for the real module."""
    mod = sys.modules.get("robo")
    if mod is None:
        try:
            import robo as mod  # type: ignore[no-redef]
        except ImportError:
            return None
    return mod if callable(getattr(mod, "_call", None)) else None


def _remote(shim: Any, op: str, payload: dict) -> Any:
    size = len(json.dumps({"fn": "perception", "args": [op, payload], "kwargs": {}}))
    if size > PROXY_FRAME_LIMIT - 1024:
        raise ValueError(f"perception request of {size} bytes is too large for the robo proxy "
                         f"({PROXY_FRAME_LIMIT >> 20} MiB); the mask is too fragmented")
    out = shim._call("perception", op, payload)
    if isinstance(out, dict) and "service_error" in out:
        raise PerceptionServiceError(str(out["service_error"]))
    return out


def _remote_frame_args(fr: dict, camera: str) -> dict:
    ts = fr["timestamp"]
    if not _finite(ts):
        raise ValueError(f"the state has no image_timestamp for {camera!r}")
    return {"camera": camera, "image_timestamp": float(ts), "width": fr["width"], "height": fr["height"]}


def serve_proxy(op: str, payload: Any, frame: Callable[[str, float, tuple[int, int]], dict]) -> Any:
    """The proxy's side of ``robo._call("perception", op, payload)`` (agent-host/py/robo_proxy.py).

    ``frame(camera, image_timestamp, (H, W))`` returns ``{"image", "depth", "intrinsics"}`` of the
    frame the program observed, or raises. ``payload`` comes from the untrusted program and is
    checked here; the URLs come only from the configuration. Service failures are returned as
    ``{"service_error": message}`` so the program can raise `PerceptionServiceError` itself.
    """
    if op == "backend":
        return load_config().backend
    if op not in ("segment", "grasps"):
        raise ValueError(f"perception has no operation {op!r} (backend, segment, grasps)")
    if not isinstance(payload, dict):
        raise TypeError("the perception payload must be an object")
    cam, ts, W, H = (payload.get(k) for k in ("camera", "image_timestamp", "width", "height"))
    if not isinstance(cam, str) or not 0 < len(cam) <= 64:
        raise ValueError("perception: 'camera' must be a camera name")
    if not _finite(ts):
        raise ValueError("perception: 'image_timestamp' must be the frame's timestamp from get_state")
    if not (_is_int(W) and _is_int(H) and 0 < W <= MAX_SIDE and 0 < H <= MAX_SIDE):
        raise ValueError(f"perception: 'width' and 'height' must be 1..{MAX_SIDE}")
    cfg = load_config()
    fr = frame(cam, float(ts), (H, W))
    try:
        if op == "segment":
            res = request_segment(cfg.segment, fr["image"], H, W, payload.get("text"), payload.get("point"))
            return {"masks": [{"bits": _pack_mask(m), "score": s, "label": lb} for m, s, lb in res]}
        mk = payload.get("mask")
        if not isinstance(mk, dict) or mk.get("size") != [H, W] or not isinstance(mk.get("bits"), str):
            raise ValueError(f"perception: 'mask' must be {{'size': [{H}, {W}], 'bits': ...}}")
        n = (H * W + 7) // 8
        try:
            z = zlib.decompressobj()
            bits = z.decompress(base64.b64decode(mk["bits"], validate=True), n + 1)
        except (ValueError, zlib.error):
            raise ValueError("perception: 'mask.bits' is not base64 zlib data") from None
        mask = _unpack_mask(bits, (H, W))
        res = request_grasps(cfg.grasp, fr["depth"], fr["intrinsics"], mask)
        return {"grasps": [{"pose": T.tolist(), "score": s, "width": w} for T, s, w in res]}
    except PerceptionServiceError as e:
        return {"service_error": str(e)}


# --------------------------------------------------------------------------------------------
# Public client
# --------------------------------------------------------------------------------------------

def backend() -> str:
    """The configured backend, "local" or "http" (inside the sandbox: as the proxy read it)."""
    shim = _shim()
    if shim is not None:
        return str(_remote(shim, "backend", {}))
    return load_config().backend


def segment_http(state: Mapping[str, Any], camera: str = "agentview", text: Optional[str] = None,
                 point: Optional[Sequence[float]] = None) -> list[RemoteMask]:
    """Masks for a text prompt and/or a pixel ``point=(u, v)`` of ``camera`` from the
    segmentation service, best score first (possibly empty). ``state`` is a `get_state` result
    holding that camera; with ``raw=True`` each mask also gets its base-frame ``points``."""
    fr = _frame(state, camera)
    H, W = fr["height"], fr["width"]
    shim = _shim()
    if shim is not None:
        _prompt(text, point, W, H)  # the same checks, before anything is sent
        args = _remote_frame_args(fr, camera)
        if text is not None:
            args["text"] = text
        if point is not None:
            args["point"] = [float(point[0]), float(point[1])]
        out = _remote(shim, "segment", args)
        found = [(_unpack_mask(m["bits"], (H, W)), float(m["score"]), m.get("label")) for m in out["masks"]]
    else:
        img = fr["image"]
        if not isinstance(img, (np.ndarray, bytes, bytearray)):
            raise ValueError(f"camera {camera!r}: the image is neither a numpy array nor PNG bytes")
        found = request_segment(load_config().segment, img, H, W, text, point)
    return [RemoteMask(camera=camera, mask=m, score=s, label=lb, points=_points(fr, m)) for m, s, lb in found]


def _as_mask(mask: Any, camera: str) -> np.ndarray:
    if hasattr(mask, "masks") and not isinstance(mask, np.ndarray):
        masks = mask.masks
        if camera not in masks:
            raise ValueError(f"the target has no mask in camera {camera!r} (it has {sorted(masks)})")
        mask = masks[camera]
    return np.asarray(mask, dtype=bool)


def grasps_http(state: Mapping[str, Any], camera: str, mask: Any,
                reference_pose: Optional[Sequence[float]] = None) -> list[rp.Grasp]:
    """Grasps on ``mask`` ((H, W) bool of ``camera``, or a target with ``.masks``) from the grasp
    service, as base-frame `robo_perception.Grasp`s (kind "remote"), best first. Needs depth
    (``get_state(..., raw=True)``). Grasps wider than the gripper stroke are dropped. Of the two
    equivalent yaws of each grasp, the one nearer ``reference_pose`` (default: the state's
    ``ee_pose``) is returned."""
    fr = _frame(state, camera)
    if fr["depth"] is None:
        raise ValueError(f"grasps need depth for {camera!r}: observe with get_state([{camera!r}], raw=True)")
    m = _as_mask(mask, camera)
    if m.shape != (fr["height"], fr["width"]):
        raise ValueError(f"the mask is {m.shape[0]}x{m.shape[1]} but the {camera} image is {fr['height']}x{fr['width']}")
    if not m.any():
        raise ValueError("the target mask is empty")
    shim = _shim()
    if shim is not None:
        args = _remote_frame_args(fr, camera)
        args["mask"] = {"size": [fr["height"], fr["width"]],
                        "bits": base64.b64encode(zlib.compress(_pack_mask(m), 6)).decode("ascii")}
        out = _remote(shim, "grasps", args)
        found = [(np.asarray(g["pose"], dtype=float), float(g["score"]), float(g["width"])) for g in out["grasps"]]
        source = "proxy"
    else:
        cfg = load_config()
        found = request_grasps(cfg.grasp, np.asarray(fr["depth"]), fr["K"], m)
        source = cfg.grasp.url
    ref = reference_pose if reference_pose is not None else state.get("ee_pose")
    R_ref = rp.pose_to_matrix(ref)[:3, :3] if ref is not None else None
    return [_to_grasp(T, s, w, fr["base_from_camera"], camera, source, R_ref)
            for T, s, w in found if w <= rp.GRIPPER_MAX_WIDTH]


_last_local: Optional[rp.SceneSegmentation] = None


def find(state: Mapping[str, Any], prompt: Optional[str] = None, point: Optional[Sequence[float]] = None,
         camera: str = "agentview") -> Any:
    """The object a text ``prompt`` and/or a pixel ``point`` of ``camera`` designates, or None.

    Backend "local": `robo_perception.segment_scene` over every camera with depth in ``state``,
    then `select`; returns an `ObjectCluster`. Backend "http": `segment_http` on ``camera``;
    returns the best `RemoteMask`. Either has ``.masks[camera]``, ``.points`` and ``.centroid``.
    """
    global _last_local
    if backend() == "local":
        scene = rp.segment_scene(state)
        _last_local = scene
        return rp.select(scene, prompt, tuple(point) if point is not None else None, camera)
    masks = segment_http(state, camera, text=prompt, point=point)
    return masks[0] if masks else None


def _same_state(scene: rp.SceneSegmentation, state: Any) -> bool:
    depth = state.get("depth") if isinstance(state, Mapping) else None
    if not depth:
        return False
    return all(depth.get(v.name) is v.depth for v in scene.views)


def _local_target(state: Mapping[str, Any], target: Any, camera: str) -> tuple[Any, rp.SceneSegmentation]:
    scene = _last_local
    if scene is not None and any(o is target for o in scene.objects) and _same_state(scene, state):
        return target, scene
    scene = rp.segment_scene(state)
    best, best_iou = None, 0.0
    tmasks = getattr(target, "masks", {}) or {}
    for o in scene.objects:
        for cam, tm in tmasks.items():
            om = o.masks.get(cam)
            if om is None or om.shape != np.shape(tm):
                continue
            union = int(np.logical_or(om, tm).sum())
            iou = int(np.logical_and(om, tm).sum()) / union if union else 0.0
            if iou > best_iou:
                best, best_iou = o, iou
    if best is not None and best_iou >= 0.2:
        return best, scene
    c = getattr(target, "centroid", None)
    if c is not None and scene.objects:
        o = min(scene.objects, key=lambda o: float(np.linalg.norm(o.centroid - c)))
        if float(np.linalg.norm(o.centroid - c)) < 0.03:
            return o, scene
    raise ValueError(f"local backend: no object segmented in this state matches the target "
                     f"(best mask overlap {best_iou:.2f}); call find() on this state first")


def grasps_for(state: Mapping[str, Any], target: Any, camera: str = "agentview") -> list[rp.Grasp]:
    """Grasps for a `find` result, best first, as base-frame `robo_perception.Grasp`s.

    Backend "local": `propose_grasps` in the scene ``target`` was found in when ``state`` is the
    same observation, else in a fresh segmentation of ``state`` (the object matched by mask
    overlap or position). Backend "http": `grasps_http` with ``target.masks[camera]``."""
    if target is None:
        raise ValueError("grasps_for: no target (find() returned None?)")
    if backend() == "local":
        obj, scene = _local_target(state, target, camera)
        return rp.propose_grasps(obj, scene, reference_pose=state.get("ee_pose"))
    return grasps_http(state, camera, _as_mask(target, camera))
