"""The sandboxed worker: reads one stage program from the host on fd 3, runs it (its own
globals, `__name__ == "__main__"`) in the scratch folder, answers with what it printed and how it
ended, and exits; every program gets a fresh confined process. Started by `r2g-sandbox` after confinement; the `robo`
it offers is the forwarding shim next to this file, not the real extension."""
from __future__ import annotations

import importlib.abc
import importlib.machinery
import io
import json
import os
import socket
import struct
import sys
import time
import traceback

HERE = os.path.dirname(os.path.abspath(__file__))
CAP = 64 * 1024


class Capped(io.TextIOBase):
    """A text sink that keeps the first CAP characters and counts the rest."""

    def __init__(self) -> None:
        self.parts: list[str] = []
        self.size = 0
        self.dropped = 0

    def writable(self) -> bool:
        return True

    def write(self, s: str) -> int:
        room = CAP - self.size
        if room > 0:
            self.parts.append(s[:room])
        self.size += min(len(s), max(room, 0))
        self.dropped += max(0, len(s) - max(room, 0))
        return len(s)

    def text(self) -> str:
        out = "".join(self.parts)
        if self.dropped:
            out += f"\n[... {self.dropped} more characters not kept]"
        return out


def recv(sock: socket.socket) -> dict | None:
    head = b""
    while len(head) < 4:
        chunk = sock.recv(4 - len(head))
        if not chunk:
            return None
        head += chunk
    (n,) = struct.unpack(">I", head)
    body = bytearray()
    while len(body) < n:
        chunk = sock.recv(min(65536, n - len(body)))
        if not chunk:
            return None
        body += chunk
    return json.loads(body)


def send(sock: socket.socket, msg: dict) -> None:
    data = json.dumps(msg).encode()
    sock.sendall(struct.pack(">I", len(data)) + data)


def run(code: str, name: str) -> dict:
    out, err = Capped(), Capped()
    saved = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = out, err
    result: dict = {"exit": "ok"}
    t0 = time.monotonic()
    try:
        exec(compile(code, name, "exec"), {"__name__": "__main__", "__file__": name})
    except SystemExit as e:
        result = {"exit": "exit", "code": e.code if isinstance(e.code, int) else (0 if e.code is None else 1)}
    except BaseException as e:  # noqa: BLE001 - everything the program raises is feedback
        result = {"exit": "exception", "exc_type": type(e).__name__, "exception": traceback.format_exc(limit=8)}
    finally:
        sys.stdout, sys.stderr = saved
    result.update(stdout=out.text(), stderr=err.text(), wall_s=time.monotonic() - t0)
    return result


# What a stage program may import (the answer format says the same, agent-host/src/prompt.rs):
# these, the standard library, modules the program itself saved in its scratch folder, and the
# example programs of robot-skill/examples.
SUPPORTED = ("robo", "robo_perception", "robo_skills", "robo_services", "robo_memory", "numpy")


class OnlySupported(importlib.abc.MetaPathFinder):
    """Refuses, with a clear ImportError, any other package the interpreter's environment holds
    (it is there for the host, not for programs). Not a security boundary: the sandbox is."""

    def __init__(self, scratch: str) -> None:
        import sysconfig

        self.scratch = os.path.realpath(scratch) + os.sep
        # The documents' example programs (robot-skill/examples, read-only) may be imported too.
        self.examples = os.path.realpath(os.path.join(scratch, "robot-skill", "examples")) + os.sep
        # The standard library's own folders (private modules such as _sysconfigdata_* are not
        # in sys.stdlib_module_names), never a site-packages folder.
        self.stdlib = tuple({os.path.realpath(sysconfig.get_paths()[k]) + os.sep for k in ("stdlib", "platstdlib")})

    def allowed(self, origin: str) -> bool:
        real = os.path.realpath(origin)
        if real.startswith((self.scratch, self.examples)):
            return True  # the program's own module, saved in the scratch folder, or an example
        return real.startswith(self.stdlib) and "-packages" + os.sep not in real

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        top = name.partition(".")[0]
        if path is not None or top in SUPPORTED or top in sys.stdlib_module_names:
            return None  # a submodule of an imported package, or allowed: the normal finders
        spec = importlib.machinery.PathFinder.find_spec(name)
        if spec is not None and spec.origin and self.allowed(spec.origin):
            return None
        raise ModuleNotFoundError(
            f"No module named {name!r} for stage programs: they may import "
            f"{', '.join(SUPPORTED)}, the Python standard library, their own modules in the scratch folder "
            f"and the examples in robot-skill/examples",
            name=name,
        )


def main() -> int:
    sys.path = [p for p in sys.path if p not in ("", ".")]
    sys.path.insert(0, os.path.join(HERE, "lib"))  # robo_perception
    sys.path.insert(0, os.path.join(HERE, "shim"))  # robo
    sys.path.append(os.getcwd())  # the program's own modules, after everything they must not shadow
    sys.meta_path.insert(0, OnlySupported(os.getcwd()))
    ctl = socket.socket(fileno=3)
    msg = recv(ctl)
    if msg is None:
        return 0
    send(ctl, run(msg["code"], msg.get("name", "stage.py")))
    ctl.close()
    # Threads the program left behind end with the process.
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
