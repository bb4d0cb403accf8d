"""`robo` inside the sandbox: the same functions as the real module, forwarded over the socket
the host opened for this worker (fd 4) to the trusted proxy, which holds the real connection to
the runtime. Limits are enforced by the runtime, whatever is sent here."""
from __future__ import annotations

import json
import pickle
import socket
import struct
from typing import Any

_FD = 4
_sock: socket.socket | None = None


def _call(fn: str, *args: Any, **kwargs: Any) -> Any:
    global _sock
    if _sock is None:
        _sock = socket.socket(fileno=_FD)
    try:
        data = json.dumps({"fn": fn, "args": args, "kwargs": kwargs}).encode()
    except (TypeError, ValueError) as e:
        raise TypeError(f"{fn}: arguments must be plain Python data (lists, dicts, str, numbers): {e}") from None
    _sock.sendall(struct.pack(">I", len(data)) + data)
    head = _recv(4)
    (n,) = struct.unpack(">I", head)
    kind, value = pickle.loads(_recv(n))
    if kind == "ok":
        return value
    exc = {"TypeError": TypeError, "ValueError": ValueError, "ConnectionError": ConnectionError}.get(value[0], RuntimeError)
    raise exc(value[1])


def _recv(n: int) -> bytes:
    assert _sock is not None
    buf = bytearray()
    while len(buf) < n:
        chunk = _sock.recv(min(1 << 20, n - len(buf)))
        if not chunk:
            raise ConnectionError("the robo proxy closed the connection")
        buf += chunk
    return bytes(buf)


def reset() -> int:
    """Restores the scene (simulation) or refreshes observations (Franka). 1 or 0."""
    return _call("reset")


def get_state(cameras: Any = None, raw: bool = False) -> dict:
    """Measured state, images and limits; see robot-skill/api/README.md."""
    if isinstance(cameras, dict):
        cameras = {k: list(v) if isinstance(v, tuple) else v for k, v in cameras.items()}
    elif isinstance(cameras, tuple):
        cameras = list(cameras)
    return _call("get_state", cameras, raw=raw)


def post_actions(cmd: Any) -> int:
    """Executes a chunk of absolute targets; 1 executed, 0 rejected or failed."""
    return _call("post_actions", cmd)


def instance() -> str:
    return _call("instance")


def __getattr__(name: str) -> Any:
    # The real module's interface version, asked of the proxy (which runs the real module).
    if name == "SCHEMA_VERSION":
        return _call("schema_version")
    raise AttributeError(f"module 'robo' has no attribute {name!r}")
