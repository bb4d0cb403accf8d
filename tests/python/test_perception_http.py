"""Tests for robo_services: the HTTP adapters for remote segmentation and grasp services.

Run:  .venv/bin/python -m pytest tests/python/test_perception_http.py -q
The services are real HTTP servers on loopback (port 0), scripted here to speak the wire format
of robot-skill/api/PERCEPTION.md: segmentation thresholds the red pixels of the PNG it receives,
grasping back-projects the masked depth it receives. Offline tests use a small synthetic state;
live ones share one lockstep pick_block_plate instance (conftest `lockstep`, stopped by pid).
"""

from __future__ import annotations

import base64
import importlib.util
import itertools
import json
import math
import os
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT / "agent-host" / "py" / "lib"))
import pngdecode  # noqa: E402
import robo_perception as rp  # noqa: E402
import robo_services as rs  # noqa: E402

R2G = ROOT / "target" / "release" / "r2g"
PROXY = ROOT / "agent-host" / "py" / "robo_proxy.py"
SHIM = ROOT / "agent-host" / "py" / "shim" / "robo.py"
BLOCK = np.array([0.5, -0.12, 0.02])  # pick_block_plate: centre of the 4 cm red block


# ------------------------------------------------------------------------------------------
# Scripted services
# ------------------------------------------------------------------------------------------

class Service:
    """A loopback HTTP server; ``respond(path, body)`` returns (status, bytes or JSON object).
    Counts accepted connections, keeps the requests and any error raised while answering."""

    def __init__(self, respond: Callable[[str, bytes], tuple[int, Any]]) -> None:
        self.respond = respond
        self.requests: list[tuple[str, bytes]] = []
        self.errors: list[str] = []
        self.connections = 0
        self.stop = threading.Event()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
                outer.requests.append((self.path, body))
                try:
                    status, out = outer.respond(self.path, body)
                except Exception as e:  # noqa: BLE001 - reported to the test
                    outer.errors.append(f"{type(e).__name__}: {e}")
                    status, out = 599, f"scripted service failed: {e}".encode()
                data = out if isinstance(out, bytes) else json.dumps(out).encode()
                try:
                    self.send_response(status)
                    if status in (301, 302, 303, 307, 308):
                        self.send_header("Location", "http://127.0.0.1:9/elsewhere")
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                except OSError:
                    pass  # the client gave up (timeout tests)

            do_GET = do_POST

            def log_message(self, *args: Any) -> None:
                pass

        class Server(ThreadingHTTPServer):
            daemon_threads = True
            block_on_close = False

            def verify_request(self, request: Any, client_address: Any) -> bool:
                outer.connections += 1
                return True

            def handle_error(self, request: Any, client_address: Any) -> None:
                pass

        self.httpd = Server(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.port}{path}"

    def close(self) -> None:
        self.stop.set()
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def serve():
    started: list[Service] = []

    def start(respond: Callable[[str, bytes], tuple[int, Any]]) -> Service:
        s = Service(respond)
        started.append(s)
        return s

    try:
        yield start
    finally:
        for s in started:
            s.close()


def closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def write_config(path: Path, backend: str, segment: str, grasp: str, seg_timeout: float = 10,
                 grasp_timeout: float = 10) -> Path:
    path.write_text(json.dumps({"backend": backend, "segment": {"url": segment, "timeout_s": seg_timeout},
                                "grasp": {"url": grasp, "timeout_s": grasp_timeout}}))
    return path


@pytest.fixture
def configure(tmp_path, monkeypatch):
    """configure(backend, segment_url, grasp_url, ...) writes a config and points
    R2G_PERCEPTION_CONFIG at it."""
    def go(backend: str, segment: str, grasp: str = "http://127.0.0.1:9/grasp", **kw: float) -> Path:
        p = write_config(tmp_path / "perception.json", backend, segment, grasp, **kw)
        monkeypatch.setenv(rs.CONFIG_ENV, str(p))
        return p
    return go


# The services' own codecs, independent of robo_services: a round trip through both would hide
# a shared mistake (e.g. column-major runs).

def rle_encode_naive(mask: np.ndarray) -> dict:
    counts, expect = [], False
    for value, run in itertools.groupby(mask.reshape(-1).tolist()):
        n = sum(1 for _ in run)
        if bool(value) != expect:
            counts.append(0)
            expect = not expect
        counts.append(n)
        expect = not expect
    return {"size": list(mask.shape), "counts": counts}


def rle_decode_naive(rle: dict) -> np.ndarray:
    H, W = rle["size"]
    flat = []
    for i, n in enumerate(rle["counts"]):
        flat += [i % 2 == 1] * n
    return np.array(flat, dtype=bool).reshape(H, W)


def png_rgb(data: bytes) -> np.ndarray:
    """PNG -> (H, W, 3): numpy for unfiltered rows, tests/python/pngdecode otherwise."""
    pos, idat, W, H = 8, b"", 0, 0
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        pos += 12 + n
        if kind == b"IHDR":
            W, H, depth, color = struct.unpack(">IIBB", body[:10])
            assert depth == 8 and color == 2, "the client must send 8-bit RGB"
        elif kind == b"IDAT":
            idat += body
    rows = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(H, 1 + 3 * W)
    if not rows[:, 0].any():
        return rows[:, 1:].reshape(H, W, 3)
    w, h, c, raw = pngdecode.decode(data)
    return np.frombuffer(raw, dtype=np.uint8).reshape(h, w, c)[:, :, :3]


def red_pixels(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[:, :, k].astype(int) for k in range(3))
    return (r > 120) & (g < 90) & (b < 90)


def blue_pixels(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[:, :, k].astype(int) for k in range(3))
    return (b > 120) & (r < 110) & (b > g + 30)


def segmenter(path: str, body: bytes) -> tuple[int, Any]:
    """Scripted SAM3 stand-in: red pixels for a red prompt (and the plate, scored lower, so
    that ordering is tested); for a point, the colour region holding it."""
    req = json.loads(body)
    assert set(req) == {"image", "width", "height", "prompt"}, sorted(req)
    assert req["image"]["format"] == "png"
    img = png_rgb(base64.b64decode(req["image"]["data"]))
    assert img.shape == (req["height"], req["width"], 3)
    red, blue = red_pixels(img), blue_pixels(img)
    prompt = req["prompt"]
    masks = []
    if "text" in prompt:
        if "fail" in prompt["text"]:
            return 500, b"scripted failure: the model is not loaded"
        if "red" in prompt["text"]:
            masks = [{"mask": rle_encode_naive(blue), "score": 0.21, "label": "plate"},
                     {"mask": rle_encode_naive(red), "score": 0.93, "label": "red block"}]
    else:
        assert prompt["labels"] == [1] and len(prompt["points"]) == 1
        u, v = prompt["points"][0]
        for m, label in ((red, "red region"), (blue, "blue region")):
            if m[int(round(v)), int(round(u))]:
                masks.append({"mask": rle_encode_naive(m), "score": 0.8, "label": label})
    return 200, {"masks": masks}


def grasper(base_from_camera: np.ndarray) -> Callable[[str, bytes], tuple[int, Any]]:
    """Scripted Contact-GraspNet stand-in: a top-down grasp (in the base frame, known to the
    script) at the centroid of the masked depth, answered in the camera frame; and a second,
    better scored one that is too wide for the Franka Hand (the client must drop it)."""
    E = np.asarray(base_from_camera, dtype=float)

    def respond(path: str, body: bytes) -> tuple[int, Any]:
        req = json.loads(body)
        assert set(req) == {"depth", "intrinsics", "segmap", "segmap_id"}, sorted(req)
        assert req["depth"]["dtype"] == "float32" and req["segmap_id"] == 1
        H, W = req["depth"]["shape"]
        depth = np.frombuffer(base64.b64decode(req["depth"]["data"]), dtype="<f4").reshape(H, W)
        seg = rle_decode_naive(req["segmap"])
        K = req["intrinsics"]
        assert set(K) == {"fx", "fy", "cx", "cy"}
        v, u = np.nonzero(seg & np.isfinite(depth) & (depth > 0))
        z = depth[v, u].astype(float)
        pc = np.stack([(u - K["cx"]) * z / K["fx"], (v - K["cy"]) * z / K["fy"], z], axis=1).mean(axis=0)
        T_base = np.eye(4)
        T_base[:3, :3] = rp.axis_angle_to_matrix([math.pi, 0.0, 0.0])  # z down, fingers along y
        T_base[:3, 3] = E[:3, :3] @ pc + E[:3, 3]
        T_cam = rp.invert_transform(E) @ T_base
        wide = T_cam.copy()
        return 200, {"grasps": [{"pose": T_cam.tolist(), "score": 0.7, "width": 0.04},
                                {"pose": wide.tolist(), "score": 0.9, "width": 0.12}]}
    return respond


# ------------------------------------------------------------------------------------------
# Offline: codecs, configuration, errors (a small synthetic state)
# ------------------------------------------------------------------------------------------

def fake_state(H: int = 48, W: int = 64) -> dict:
    img = np.zeros((H, W, 3), dtype=np.uint8)
    img[10:20, 20:30] = [200, 30, 30]
    return {"image": {"agentview": img}, "depth": {"agentview": np.full((H, W), 1.0, dtype=np.float32)},
            "camera_intrinsics": {"agentview": {"fx": 50.0, "fy": 50.0, "cx": W / 2, "cy": H / 2, "width": W, "height": H}},
            "camera_extrinsics": {"agentview": np.eye(4).tolist()}, "image_timestamp": {"agentview": 1.0},
            "ee_pose": [0.3, 0.0, 0.5, math.pi, 0.0, 0.0]}


def test_rle_layout_and_roundtrip():
    m = np.zeros((3, 4), dtype=bool)
    m[0, 0] = m[2, 3] = True
    assert rs.rle_encode(m) == {"size": [3, 4], "counts": [0, 1, 10, 1]}  # row-major, zeros first
    m2 = np.zeros((2, 3), dtype=bool)
    m2[0, 1:] = True
    assert rs.rle_encode(m2) == {"size": [2, 3], "counts": [1, 2, 3]}
    rng = np.random.default_rng(3)
    for shape in ((1, 1), (7, 5), (480, 640)):
        for p in (0.0, 0.02, 0.5, 1.0):
            mask = rng.random(shape) < p
            enc = rs.rle_encode(mask)
            assert sum(enc["counts"]) == mask.size
            assert enc == rle_encode_naive(mask) or shape == (480, 640)
            assert np.array_equal(rs.rle_decode(enc, shape), mask)
            if shape != (480, 640):
                assert np.array_equal(rle_decode_naive(enc), mask)
    with pytest.raises(ValueError, match=r"RLE counts sum to 5, expected 3\*4 = 12"):
        rs.rle_decode({"size": [3, 4], "counts": [2, 3]})
    with pytest.raises(ValueError, match="is 3x4 but the image is 4x3"):
        rs.rle_decode({"size": [3, 4], "counts": [12]}, (4, 3))
    for bad in ({"size": [3, 4], "counts": [-1, 13]}, {"size": [3, 4], "counts": [1.5, 10.5]},
                {"size": [3, 4], "counts": "12"}, {"size": [0, 4], "counts": []}, {"counts": [12]}):
        with pytest.raises(ValueError):
            rs.rle_decode(bad)


def test_png_encoder():
    img = (np.random.default_rng(4).random((37, 53, 3)) * 255).astype(np.uint8)
    w, h, c, raw = pngdecode.decode(rs.encode_png(img))
    assert (w, h, c) == (53, 37, 3)
    assert np.array_equal(np.frombuffer(raw, dtype=np.uint8).reshape(h, w, 3), img)
    with pytest.raises(ValueError):
        rs.encode_png(img.astype(np.float32))


def test_shipped_config(monkeypatch):
    monkeypatch.delenv(rs.CONFIG_ENV, raising=False)
    cfg = rs.load_config()
    assert Path(cfg.path) == ROOT / "robot-skill" / "config" / "perception.json"
    assert cfg.backend == "local"
    assert cfg.segment == rs.ServiceConfig("http://127.0.0.1:8600/segment", 10.0)
    assert cfg.grasp == rs.ServiceConfig("http://127.0.0.1:8601/grasp", 20.0)


GOOD = {"backend": "http", "segment": {"url": "http://127.0.0.1:1/s", "timeout_s": 1},
        "grasp": {"url": "https://gpu.example:8443/g", "timeout_s": 2.5}}


def _with(path: tuple, value: Any) -> dict:
    d = json.loads(json.dumps(GOOD))
    tgt = d
    for k in path[:-1]:
        tgt = tgt[k]
    if value is KeyError:
        del tgt[path[-1]]
    else:
        tgt[path[-1]] = value
    return d


@pytest.mark.parametrize("text, key", [
    (json.dumps(_with(("colour",), "red")), "colour"),
    (json.dumps(_with(("segment", "retries"), 3)), "segment.retries"),
    (json.dumps(_with(("grasp", "url"), KeyError)), "grasp.url"),
    (json.dumps(_with(("backend",), "remote")), "backend"),
    (json.dumps(_with(("segment", "url"), "ftp://127.0.0.1/s")), "segment.url"),
    (json.dumps(_with(("segment", "url"), "file:///etc/passwd")), "segment.url"),
    (json.dumps(_with(("grasp", "url"), "http://")), "grasp.url"),
    (json.dumps(_with(("grasp", "url"), "http://h:notaport/")), "grasp.url"),
    (json.dumps(_with(("grasp", "url"), 8601)), "grasp.url"),
    (json.dumps(_with(("segment", "timeout_s"), 0)), "segment.timeout_s"),
    (json.dumps(_with(("segment", "timeout_s"), -2)), "segment.timeout_s"),
    (json.dumps(_with(("grasp", "timeout_s"), float("nan"))), "grasp.timeout_s"),
    (json.dumps(_with(("grasp", "timeout_s"), float("inf"))), "grasp.timeout_s"),
    (json.dumps(_with(("grasp", "timeout_s"), "10")), "grasp.timeout_s"),
    (json.dumps(_with(("grasp", "timeout_s"), 10**400)), "grasp.timeout_s"),
    (json.dumps(_with(("grasp", "timeout_s"), True)), "grasp.timeout_s"),
    (json.dumps(_with(("segment",), "http://127.0.0.1:1/s")), "segment"),
    ('{"backend": "local", "backend": "http"}', "backend"),
    ('{"backend": "local",', "JSON"),
    ("[1, 2]", "top level"),
])
def test_config_errors_name_file_and_key(tmp_path, monkeypatch, text, key):
    p = tmp_path / "perception.json"
    p.write_text(text)
    monkeypatch.setenv(rs.CONFIG_ENV, str(p))
    with pytest.raises(ValueError) as e:
        rs.load_config()
    msg = str(e.value)
    assert str(p) in msg and key in msg, msg


def test_config_missing_file(tmp_path, monkeypatch):
    p = tmp_path / "nope.json"
    monkeypatch.setenv(rs.CONFIG_ENV, str(p))
    with pytest.raises(ValueError, match="not found"):
        rs.backend()
    p.write_text(json.dumps(GOOD))
    assert rs.backend() == "http"
    assert rs.load_config().grasp.timeout_s == 2.5


def test_http_500_names_url_and_status(serve, configure):
    svc = serve(lambda path, body: (500, b"CUDA out of memory " + b"x" * 500))
    configure("http", svc.url("/segment"))
    with pytest.raises(rs.PerceptionServiceError) as e:
        rs.segment_http(fake_state(), "agentview", text="red block")
    msg = str(e.value)
    assert msg.startswith(f"segment service {svc.url('/segment')} answered HTTP 500: CUDA out of memory")
    assert len(msg.split(": ", 1)[1]) <= 200
    assert isinstance(e.value, RuntimeError)


def test_redirect_is_not_followed(serve, configure):
    svc = serve(lambda path, body: (302, b""))
    configure("http", svc.url("/segment"))
    with pytest.raises(rs.PerceptionServiceError, match="answered HTTP 302"):
        rs.segment_http(fake_state(), "agentview", text="red block")


def test_timeout_is_reported_promptly(serve, configure):
    def slow(path: str, body: bytes) -> tuple[int, Any]:
        svc.stop.wait(5.0)
        return 200, {"masks": []}
    svc = serve(slow)
    configure("http", svc.url("/segment"), seg_timeout=0.5)
    t = time.monotonic()
    with pytest.raises(rs.PerceptionServiceError) as e:
        rs.segment_http(fake_state(), "agentview", text="red block")
    took = time.monotonic() - t
    assert str(e.value) == f"segment service {svc.url('/segment')} did not answer within 0.5 s"
    assert 0.45 < took < 1.2, took


def test_grasp_service_500_and_timeout(serve, configure):
    state, mask = fake_state(), np.zeros((48, 64), dtype=bool)
    mask[10:20, 20:30] = True
    bad = serve(lambda path, body: (500, b"model crashed"))
    configure("http", "http://127.0.0.1:9/segment", bad.url("/grasp"))
    with pytest.raises(rs.PerceptionServiceError) as e:
        rs.grasps_http(state, "agentview", mask)
    assert str(e.value) == f"grasp service {bad.url('/grasp')} answered HTTP 500: model crashed"

    def slow(path: str, body: bytes) -> tuple[int, Any]:
        stalled.stop.wait(5.0)
        return 200, {"grasps": []}
    stalled = serve(slow)
    configure("http", "http://127.0.0.1:9/segment", stalled.url("/grasp"), grasp_timeout=0.5)
    t = time.monotonic()
    with pytest.raises(rs.PerceptionServiceError, match=r"did not answer within 0\.5 s$"):
        rs.grasps_http(state, "agentview", mask)
    assert time.monotonic() - t < 1.2


def test_a_trickling_answer_is_cut_at_the_timeout(configure):
    """Headers at once, then a byte every 50 ms: every socket read succeeds, only the deadline
    for the whole request can stop it."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    stop = threading.Event()

    def trickle() -> None:
        try:
            conn, _ = srv.accept()
        except OSError:
            return
        with conn:
            conn.recv(1 << 16)
            conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n")
            give_up = time.monotonic() + 3.0  # a client without a deadline fails, it does not hang
            while not stop.wait(0.05) and time.monotonic() < give_up:
                try:
                    conn.sendall(b" ")
                except OSError:
                    return
    threading.Thread(target=trickle, daemon=True).start()
    try:
        configure("http", f"http://127.0.0.1:{srv.getsockname()[1]}/segment", seg_timeout=0.5)
        t = time.monotonic()
        with pytest.raises(rs.PerceptionServiceError, match=r"did not answer within 0\.5 s$"):
            rs.segment_http(fake_state(), "agentview", text="red block")
        assert time.monotonic() - t < 1.2
    finally:
        stop.set()
        srv.close()


def test_connection_refused(configure):
    url = f"http://127.0.0.1:{closed_port()}/segment"
    configure("http", url)
    with pytest.raises(rs.PerceptionServiceError) as e:
        rs.segment_http(fake_state(), "agentview", text="red block")
    assert str(e.value) == f"segment service {url} is not reachable: connection refused"


def _mask(size: list, counts: list, score: Any = 0.5) -> dict:
    return {"mask": {"size": size, "counts": counts}, "score": score}


@pytest.mark.parametrize("answer, expect", [
    (b"<html>Bad gateway</html>", "answered something that is not JSON: '<html>Bad gateway</html>'"),
    (b"", "answered something that is not JSON"),
    (b"[]", "answered JSON that is not an object"),
    ({"result": []}, "answer lacks 'masks'"),
    ({"masks": {"0": 1}}, "'masks' is not a list"),
    ({"masks": [_mask([10, 10], [100])]}, "mask 0 is 10x10 but the image is 48x64"),
    ({"masks": [_mask([48, 64], [3000, 70])]}, "mask 0: RLE counts sum to 3070, expected 48*64 = 3072"),
    ({"masks": [_mask([48, 64], [3072]), _mask([48, 64], [-1, 3073])]}, "mask 1: RLE counts must lie in 0..H*W"),
    ({"masks": [_mask([48, 64], [3072], float("nan"))]}, "mask 0 has a score that is not a finite number"),
    ({"masks": [{"mask": {"size": [48, 64], "counts": [3072]}}]}, "mask 0 must be an object with 'mask' and 'score'"),
])
def test_malformed_segmentation_answers(serve, configure, answer, expect):
    svc = serve(lambda path, body: (200, answer))
    configure("http", svc.url("/segment"))
    with pytest.raises(rs.PerceptionServiceError) as e:
        rs.segment_http(fake_state(), "agentview", text="red block")
    assert str(e.value).startswith(f"segment service {svc.url('/segment')}"), str(e.value)
    assert expect in str(e.value), str(e.value)


def _pose(T: Any, width: float = 0.04) -> dict:
    return {"grasps": [{"pose": T.tolist() if isinstance(T, np.ndarray) else T, "score": 0.5, "width": width}]}


_nan = np.eye(4)
_nan[0, 3] = float("nan")
_skewed = np.eye(4)
_skewed[:3, :3] *= 1.5
_mirror = np.diag([1.0, 1.0, -1.0, 1.0])
_row = np.eye(4)
_row[3, 0] = 0.2


@pytest.mark.parametrize("answer, expect", [
    (_pose(_nan), "grasp 0: the pose has non-finite values"),
    (_pose(_skewed), "grasp 0: the pose's rotation is not orthonormal"),
    (_pose(_mirror), "grasp 0: the pose's rotation is not orthonormal"),
    (_pose(_row), "grasp 0: the pose's last row is not [0, 0, 0, 1]"),
    (_pose(np.eye(3)), "grasp 0: 'pose' is not a 4x4 matrix of numbers"),
    (_pose([[1, 0, 0, "0"], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "'pose' is not a 4x4 matrix of numbers"),
    (_pose(np.eye(4), -0.01), "grasp 0 has a width that is not a non-negative number"),
    (_pose(np.eye(4), 10**400), "grasp 0 has a width that is not a non-negative number"),
    ({"poses": []}, "answer lacks 'grasps'"),
])
def test_malformed_grasp_answers(serve, configure, answer, expect):
    svc = serve(lambda path, body: (200, answer))
    configure("http", "http://127.0.0.1:9/segment", svc.url("/grasp"))
    state = fake_state()
    with pytest.raises(rs.PerceptionServiceError) as e:
        rs.grasps_http(state, "agentview", red_pixels(state["image"]["agentview"]))
    assert str(e.value).startswith(f"grasp service {svc.url('/grasp')}"), str(e.value)
    assert expect in str(e.value), str(e.value)


def test_answer_size_is_capped(serve, configure, monkeypatch):
    monkeypatch.setattr(rs, "MAX_RESPONSE_BYTES", 4096)
    svc = serve(lambda path, body: (200, {"masks": [], "padding": "x" * 10000}))
    configure("http", svc.url("/segment"))
    with pytest.raises(rs.PerceptionServiceError, match="more than"):
        rs.segment_http(fake_state(), "agentview", text="red block")


def test_client_side_checks(configure):
    configure("http", f"http://127.0.0.1:{closed_port()}/segment")
    state = fake_state()
    with pytest.raises(ValueError, match="text prompt or a point"):
        rs.find(state)
    with pytest.raises(ValueError, match="outside"):
        rs.segment_http(state, "agentview", point=(64, 3))
    with pytest.raises(ValueError, match="no image from camera 'wrist'"):
        rs.segment_http(state, "wrist", text="red block")
    with pytest.raises(ValueError, match="mask is empty"):
        rs.grasps_http(state, "agentview", np.zeros((48, 64), dtype=bool))
    with pytest.raises(ValueError, match="the mask is 4x4"):
        rs.grasps_http(state, "agentview", np.ones((4, 4), dtype=bool))
    del state["depth"]
    with pytest.raises(ValueError, match="need depth"):
        rs.grasps_http(state, "agentview", np.ones((48, 64), dtype=bool))


# ------------------------------------------------------------------------------------------
# Live: one lockstep pick_block_plate
# ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def obs(lockstep) -> dict:
    import robo
    return robo.get_state(["agentview", "wrist"], raw=True)


def _near_block(points: np.ndarray) -> None:
    assert points is not None and len(points) > 50
    c = points.mean(axis=0)
    assert np.linalg.norm(c - BLOCK) < 0.02, c
    # nearly every point on the 4 cm block (its box plus 5 mm; a few edge pixels see the table)
    on = np.all(np.abs(points - BLOCK) < 0.02 + 0.005, axis=1)
    assert on.mean() > 0.95, on.mean()


def test_segment_text_prompt(obs, serve, configure):
    svc = serve(segmenter)
    configure("http", svc.url("/segment"))
    masks = rs.segment_http(obs, "agentview", text="red block")
    assert not svc.errors, svc.errors
    req = json.loads(svc.requests[0][1])
    assert req["prompt"] == {"text": "red block"} and (req["height"], req["width"]) == (480, 640)
    assert [m.label for m in masks] == ["red block", "plate"] and masks[0].score == 0.93
    best = masks[0]
    assert best.mask.shape == (480, 640) and best.mask.dtype == bool
    assert np.array_equal(best.mask, red_pixels(np.asarray(obs["image"]["agentview"])))
    _near_block(best.points)
    assert masks[1].centroid[1] > 0.05  # the plate is on the left (+y)
    got = rs.find(obs, "red block")  # the same through the dispatcher
    assert isinstance(got, rs.RemoteMask) and np.array_equal(got.masks["agentview"], best.mask)
    assert rs.find(obs, "green cup") is None


def test_segment_point_prompt(obs, serve, configure):
    svc = serve(segmenter)
    configure("http", svc.url("/segment"))
    K, E = obs["camera_intrinsics"]["agentview"], obs["camera_extrinsics"]["agentview"]
    uv, _ = rp.project_points(BLOCK + [0, 0, 0.02], K, E)  # the top face's centre
    got = rs.find(obs, point=tuple(uv[0]), camera="agentview")
    assert not svc.errors, svc.errors
    req = json.loads(svc.requests[0][1])
    assert req["prompt"] == {"points": [[float(uv[0][0]), float(uv[0][1])]], "labels": [1]}
    assert got is not None and got.label == "red region"
    _near_block(got.points)


def test_remote_grasps(obs, serve, configure):
    E = np.asarray(obs["camera_extrinsics"]["agentview"])
    seg, grasp = serve(segmenter), serve(grasper(E))
    configure("http", seg.url("/segment"), grasp.url("/grasp"))
    block = rs.find(obs, "red block")
    grasps = rs.grasps_for(obs, block)
    assert not grasp.errors, grasp.errors
    assert len(grasps) == 1, "the 12 cm wide grasp must be dropped"
    g = grasps[0]
    assert g.kind == "remote" and g.score == 0.7 and g.width == 0.04
    assert abs(g.open_width - 0.056) < 1e-12 and g.gripper_open == rp.width_to_gripper(0.056)
    T = rp.pose_to_matrix(g.pose)
    assert math.degrees(math.acos(min(1.0, -T[2, 2]))) < 3.0  # pointing down
    assert np.linalg.norm(T[:2, 3] - BLOCK[:2]) < 0.02 and 0.0 < T[2, 3] < 0.06
    assert np.allclose(rp.pose_to_matrix(g.pregrasp)[:3, 3], T[:3, 3] + [0, 0, 0.10], atol=1e-6)
    assert np.allclose(g.approach, [0, 0, -1], atol=0.05)
    # a local ObjectCluster works as the target too (its mask in that camera is sent)
    cluster = rp.select(rp.segment_scene(obs), "red block")
    assert len(rs.grasps_for(obs, cluster)) == 1
    sent = rle_decode_naive(json.loads(grasp.requests[-1][1])["segmap"])
    assert np.array_equal(sent, cluster.masks["agentview"])


def test_local_backend_never_touches_the_network(obs, serve, configure):
    svc = serve(segmenter)
    configure("local", svc.url("/segment"), svc.url("/grasp"))
    assert rs.backend() == "local"
    block = rs.find(obs, "red block")
    assert isinstance(block, rp.ObjectCluster) and block.color_name == "red"
    grasps = rs.grasps_for(obs, block)
    assert grasps and grasps[0].kind in ("top_down", "antipodal")
    # a target from elsewhere (here a RemoteMask-like mask of the same pixels) is matched
    rm = rs.RemoteMask("agentview", block.masks["agentview"], 1.0, None, block.points)
    assert rs.grasps_for(obs, rm)
    assert svc.connections == 0 and not svc.requests


def test_http_backend_down_raises_instead_of_falling_back(obs, configure):
    url = f"http://127.0.0.1:{closed_port()}/segment"
    configure("http", url)
    with pytest.raises(rs.PerceptionServiceError, match="not reachable: connection refused"):
        rs.find(obs, "red block")


# ------------------------------------------------------------------------------------------
# The program side through the real proxy (no sandbox needed), then the sandbox itself
# ------------------------------------------------------------------------------------------

@pytest.fixture
def proxied(lockstep, monkeypatch, tmp_path):
    """The real robo_proxy.py serving the real shim (agent-host/py/shim/robo.py) over a socketpair;
    the shim is installed as `robo` while the test runs, as in the sandbox. The proxy's
    R2G_PERCEPTION_CONFIG is the path `configure` writes."""
    monkeypatch.setenv(rs.CONFIG_ENV, str(tmp_path / "perception.json"))
    ours, theirs = socket.socketpair()
    launch = ("import os, runpy, sys; fd = int(sys.argv[1]); os.dup2(fd, 3); os.close(fd); "
              "p = sys.argv[2]; sys.argv = [p]; runpy.run_path(p, run_name='__main__')")
    proc = subprocess.Popen([sys.executable, "-I", "-B", "-c", launch, str(theirs.fileno()), str(PROXY)],
                            pass_fds=(theirs.fileno(),), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True, env=dict(os.environ))
    theirs.close()
    try:
        assert proc.stdout is not None and proc.stdin is not None
        assert '"ready"' in proc.stdout.readline()
        proc.stdin.write(json.dumps({"cmd": "begin", "budget": 0, "observe_only": True}) + "\n")
        proc.stdin.flush()
        assert json.loads(proc.stdout.readline()) == {"ok": True}
        spec = importlib.util.spec_from_file_location("robo_shim_under_test", SHIM)
        shim = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(shim)
        shim._sock = ours
        monkeypatch.setitem(sys.modules, "robo", shim)
        yield shim
    finally:
        ours.close()
        if proc.stdin:
            proc.stdin.close()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.terminate()
            proc.wait()


def test_through_the_proxy(proxied, serve, configure):
    shim = proxied
    sizes: list[int] = []
    call = shim._call

    def recording(fn: str, *args: Any, **kwargs: Any) -> Any:
        sizes.append(len(json.dumps({"fn": fn, "args": args, "kwargs": kwargs})))
        return call(fn, *args, **kwargs)
    shim._call = recording
    state = shim.get_state(["agentview"], raw=True)
    E = np.asarray(state["camera_extrinsics"]["agentview"])
    seg, grasp = serve(segmenter), serve(grasper(E))
    cfg = configure("http", seg.url("/segment"), grasp.url("/grasp"))  # the proxy reads it per call
    assert shim._call("perception", "backend", {}) == "http"
    assert rs.backend() == "http"
    block = rs.find(state, "red block")
    assert isinstance(block, rs.RemoteMask) and block.label == "red block"
    _near_block(block.points)
    grasps = rs.grasps_for(state, block)
    assert len(grasps) == 1 and grasps[0].kind == "remote" and grasps[0].details["source"] == "proxy"
    assert np.linalg.norm(grasps[0].position[:2] - BLOCK[:2]) < 0.02
    assert not seg.errors and not grasp.errors
    # one request per call reached each service; what the program sent the proxy stayed small
    # (names, numbers, the packed mask) next to the proxy's 1 MiB frame limit
    assert len(seg.requests) == 1 and len(grasp.requests) == 1
    assert max(sizes) < 16 * 1024, sizes
    # a frame the proxy did not hand out raw: taken fresh, accepted because it is the same frame
    png_state = shim.get_state(["agentview"])
    again = rs.segment_http(png_state, "agentview", text="red block")
    assert np.array_equal(again[0].mask, block.mask) and again[0].points is None
    # a frame that is not the current one
    with pytest.raises(RuntimeError, match="camera frame changed since the program observed it"):
        shim._call("perception", "segment", {"camera": "agentview", "width": 640, "height": 480, "text": "red",
                                             "image_timestamp": state["image_timestamp"]["agentview"] + 1.0})
    # a service failure keeps its type and message on the program's side
    with pytest.raises(rs.PerceptionServiceError) as e:
        rs.find(state, "fail now")
    assert str(e.value).startswith(f"segment service {seg.url('/segment')} answered HTTP 500: scripted failure")
    # the program cannot steer the proxy: bad operations and payloads are refused
    with pytest.raises(ValueError, match="no operation"):
        shim._call("perception", "fetch", {"url": "http://example.com"})
    with pytest.raises(ValueError, match="image_timestamp"):
        shim._call("perception", "segment", {"camera": "agentview", "width": 640, "height": 480, "image_timestamp": "now"})
    with pytest.raises(TypeError):
        shim._call("perception", "segment")
    # the config is the proxy's to read: a broken one is reported to the program
    cfg.write_text('{"backend": "http"}')
    with pytest.raises(ValueError, match="missing key 'segment'"):
        rs.backend()


def test_in_the_sandbox(lockstep, serve, tmp_path):
    """`r2g exec` of a stage program under backend http: find + grasps via the proxy, and a
    service failure arrives as PerceptionServiceError. The host hands R2G_PERCEPTION_CONFIG to the
    proxy, never to the program."""
    import robo
    state = robo.get_state(["agentview"], raw=True)
    seg, grasp = serve(segmenter), serve(grasper(np.asarray(state["camera_extrinsics"]["agentview"])))
    cfg = write_config(tmp_path / "perception.json", "http", seg.url("/segment"), grasp.url("/grasp"))
    prog = tmp_path / "stage.py"
    prog.write_text("""
import json
import robo_services as rs
from robo import get_state
state = get_state(["agentview"], raw=True)
import os
out = {"backend": rs.backend(), "program_sees_config": "R2G_PERCEPTION_CONFIG" in os.environ}
block = rs.find(state, "red block")
out["centroid"] = block.centroid.tolist()
out["grasps"] = [g.pose for g in rs.grasps_for(state, block)]
try:
    rs.find(state, "fail now")
except rs.PerceptionServiceError as e:
    out["error"] = str(e)
print(json.dumps(out))
""")
    env = dict(os.environ, R2G_PERCEPTION_CONFIG=str(cfg))
    run = subprocess.run([str(R2G), "exec", str(prog), "--instance", lockstep.name, "--observe-only",
                          "--scratch", str(tmp_path / "scratch")], cwd=str(ROOT), env=env,
                         capture_output=True, text=True, timeout=120)
    res = json.loads(run.stdout.strip().splitlines()[-1])
    assert res["exit"] == "ok" and res["violation"] is None, res
    got = json.loads(res["stdout"].strip().splitlines()[-1])
    assert got["backend"] == "http", "the proxy did not get R2G_PERCEPTION_CONFIG"
    assert got["program_sees_config"] is False
    assert np.linalg.norm(np.array(got["centroid"]) - BLOCK) < 0.02
    assert len(got["grasps"]) == 1 and np.linalg.norm(np.array(got["grasps"][0][:2]) - BLOCK[:2]) < 0.02
    assert got["error"].startswith(f"segment service {seg.url('/segment')} answered HTTP 500")
