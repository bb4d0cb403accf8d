"""The trusted side of a sandboxed worker's `robo`: holds the real connection to the runtime and
serves the shim over fd 3 (JSON requests in, pickled results out: the shim trusts us, we never
unpickle what it sends). The host drives it on stdin/stdout with JSON lines:
`{"cmd": "begin", "budget": N, "observe_only": bool}` before a program runs and `{"cmd": "end"}`
after it (answered with the program's robot calls and control steps).

`perception` requests (from robo_services in the program) are served here too: the program names
a camera and the timestamp of a frame it observed, this process takes that frame's image and depth
from its own connection, and calls the HTTP services configured in
robot-skill/config/perception.json (or $R2G_PERCEPTION_CONFIG): the program never picks a URL."""
from __future__ import annotations

import base64
import json
import os
import pickle
import selectors
import socket
import struct
import sys

import robo

ALLOWED = {"reset", "get_state", "post_actions", "instance", "schema_version", "perception"}
CALLS_KEPT = 500  # reset/post_actions calls logged per program for the run record
FRAMES_KEPT = 4  # raw frames remembered per camera for perception requests...
FRAMES_BYTES = 64 << 20  # ...within this many bytes in all
_services = None


def services():
    """robo_services (agent-host/py/lib), imported on first use: this process runs isolated (-I)."""
    global _services
    if _services is None:
        lib = os.path.join(os.path.dirname(os.path.abspath(__file__)), "lib")
        if lib not in sys.path:
            sys.path.insert(0, lib)
        import robo_services

        _services = robo_services
    return _services


class Session:
    def __init__(self) -> None:
        self.budget = 600
        self.observe_only = False
        self.steps = 0
        self.calls = 0
        self.refused = 0
        self.observe_refused = 0
        self.override: dict | None = None
        # The program's own robot calls, for the host's feedback: chunks by outcome, resets, and
        # the last reset/post_actions (status and reason as the program's control_feedback had them).
        self.chunks = {"executed": 0, "failed": 0, "rejected": 0}
        self.resets = {"done": 0, "refused": 0}
        self.last: dict | None = None
        # What the program asked of the robot and what came of it (the run record's calls.json;
        # skill extraction reads the targets of successful rounds from it).
        self.calls_log: list[dict] = []
        # camera -> [(image_timestamp, rgb, depth, intrinsics)]: the raw frames this program was
        # given, so that a perception request works on exactly the frame the program saw.
        self.frames: dict[str, list] = {}

    def remember(self, s: dict) -> None:
        depth = s.get("depth") or {}
        for cam, img in (s.get("image") or {}).items():
            if cam in depth and hasattr(img, "shape"):
                kept = self.frames.setdefault(cam, [])
                ts = (s.get("image_timestamp") or {}).get(cam)
                kept.append((ts, img, depth[cam], s["camera_intrinsics"][cam]))
                del kept[:-FRAMES_KEPT]
        # the newest frames win the byte budget
        while sum(f[1].nbytes + f[2].nbytes for k in self.frames.values() for f in k) > FRAMES_BYTES:
            max(self.frames.values(), key=len).pop(0)

    def camera_frame(self, camera: str, ts: float, shape: tuple) -> dict:
        """The raw frame of `camera` taken at `ts` with (H, W) = `shape`: one this program was
        given, else the current one if it is still that frame."""
        for t, img, depth, K in reversed(self.frames.get(camera, [])):
            if t == ts and tuple(depth.shape) == tuple(shape):
                return {"image": img, "depth": depth, "intrinsics": K}
        s = robo.get_state({camera: (shape[1], shape[0])}, raw=True)
        now = (s.get("image_timestamp") or {}).get(camera)
        if camera not in (s.get("depth") or {}):
            raise ValueError(f"perception: camera {camera!r} delivers no depth")
        if now != ts:
            raise RuntimeError(
                f"perception: the {camera} camera frame changed since the program observed it (frame of "
                f"{ts} s, now {now} s); observe again with get_state(..., raw=True) and retry"
            )
        return {"image": s["image"][camera], "depth": s["depth"][camera], "intrinsics": s["camera_intrinsics"][camera]}

    def refuse(self, fn: str, reason: str, budget: bool = True) -> int:
        """Answers a reset/post_actions with 0 without sending it: the control-step budget is
        spent (`budget`), or the turn is observation-only."""
        if budget:
            self.refused += 1
        else:
            self.observe_refused += 1
        fb = robo.get_state([])["control_feedback"]
        fb.update(status="rejected", reason=reason, executed=0, request_id=0, submit_to_accept_us=None, submit_to_first_motion_us=None)
        self.override = fb
        self.outcome(fn, fb)
        return 0

    def outcome(self, fn: str, fb: dict) -> None:
        """Counts one reset/post_actions of the program by its feedback and keeps it as the last."""
        status = fb.get("status")
        if fn == "reset":
            self.resets["refused" if status == "rejected" else "done"] += 1
        else:
            kind = status if status in ("executed", "rejected") else "failed"
            self.chunks[kind] += 1
        self.last = {"fn": fn, **{k: fb.get(k) for k in ("status", "reason", "executed", "contact")}}

    def call(self, req: dict) -> object:
        fn, args, kwargs = req.get("fn"), req.get("args", []), req.get("kwargs", {})
        if fn not in ALLOWED or not isinstance(args, list) or not isinstance(kwargs, dict):
            raise TypeError(f"robo has no function {fn!r}")
        self.calls += 1
        if fn == "instance":
            return robo.instance()
        if fn == "schema_version":
            return robo.SCHEMA_VERSION
        if fn == "get_state":
            cams = args[0] if args else kwargs.pop("cameras", None)
            if isinstance(cams, (list, dict)) and len(cams) > 16:
                raise ValueError("get_state: at most 16 cameras per call")
            if isinstance(cams, dict):
                cams = {k: tuple(v) if isinstance(v, list) else v for k, v in cams.items()}
            raw = bool(kwargs.get("raw", False))
            s = robo.get_state(cams, raw=raw)
            if raw:
                self.remember(s)
            if self.override is not None:
                s["control_feedback"] = dict(self.override)
            return s
        if fn == "perception":
            # observation only: allowed in observe-only turns; the URLs come from the config
            if len(args) != 2 or kwargs or not isinstance(args[0], str):
                raise TypeError("perception(op, payload)")
            return services().serve_proxy(args[0], args[1], self.camera_frame)
        if self.observe_only:
            return self.refuse(fn, "this turn is observation-only: reset() and post_actions() are not allowed yet",
                               budget=False)
        if fn == "reset":
            self.override = None
            self.frames.clear()  # simulated time starts again: old timestamps would match anew
            t_before = robo.get_state([])["timestamp"]
            r = robo.reset()
            after = robo.get_state([])
            self.outcome("reset", after["control_feedback"])
            self.log({"fn": "reset", "result": r, "t_before": t_before, "t_after": after["timestamp"]})
            return r
        cmd = args[0] if args else None
        n = len(cmd.get("actions", [])) if isinstance(cmd, dict) and isinstance(cmd.get("actions"), list) else 0
        if self.steps + n > self.budget:
            return self.refuse(
                fn,
                f"control-step budget spent: this program has used {self.steps} of {self.budget} waypoints and this "
                f"chunk has {n}; end the program, observe, and continue in the next decision"
            )
        self.override = None
        t_before = robo.get_state([])["timestamp"]
        try:
            r = robo.post_actions(cmd)
        except Exception as e:  # a malformed command: nothing reached the runtime
            self.chunks["rejected"] += 1
            self.last = {"fn": fn, "status": "refused by robo", "reason": f"{type(e).__name__}: {e}", "executed": 0}
            raise
        self.steps += n
        after = robo.get_state([])
        fb = after["control_feedback"]
        self.outcome(fn, fb)
        entry = {"fn": "post_actions", "result": r, "t_before": t_before, "t_after": after["timestamp"],
                 "feedback": {k: fb.get(k) for k in ("status", "reason", "executed", "contact")}}
        if isinstance(cmd, dict):
            entry.update(type=cmd.get("type"), freq=cmd.get("freq"), actions=cmd.get("actions"))
        self.log(entry)
        return r

    def log(self, entry: dict) -> None:
        if len(self.calls_log) < CALLS_KEPT:
            self.calls_log.append(_strict(entry))


def _strict(v: object) -> object:
    """A value the host's JSON reader takes: what the program passed may hold NaN, infinities
    or integers past any float; those are kept as their text."""
    if isinstance(v, float) and (v != v or abs(v) == float("inf")):
        return repr(v)
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) > 2**63:
        return f"an integer of {len(str(abs(v)))} digits"
    if isinstance(v, dict):
        return {str(k): _strict(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_strict(x) for x in v]
    return v


def save_raw(path: str) -> None:
    """Every camera's raw frame (RGB, depth in metres, intrinsics, base_from_camera) and the
    numeric state into one .npz for the run record (skill extraction binds rules to it);
    written under a temporary name, then renamed."""
    import numpy as np

    s = robo.get_state(None, raw=True)
    arrays: dict = {}
    for cam, rgb in (s.get("image") or {}).items():
        arrays[f"rgb.{cam}"] = rgb
        if cam in (s.get("depth") or {}):
            arrays[f"depth.{cam}"] = s["depth"][cam]
        k = s["camera_intrinsics"][cam]
        arrays[f"intrinsics.{cam}"] = np.array([k["fx"], k["fy"], k["cx"], k["cy"]], dtype=np.float64)
        arrays[f"base_from_camera.{cam}"] = np.asarray(s["camera_extrinsics"][cam], dtype=np.float64)
    numbers = {k: s.get(k) for k in ("joint", "ee_pose", "gripper", "timestamp", "external_force_n", "image_timestamp")}
    arrays["state_json"] = np.array(json.dumps(numbers))
    tmp = path + ".partial"
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def observe(images: bool, raw: str | None = None) -> dict:
    """For the host's prompts: the numeric state and, optionally, both images as base64 PNG;
    with `raw`, the raw frames are saved there first (save_raw)."""
    if raw:
        save_raw(raw)
    s = robo.get_state(None if images else [])
    pngs = {k: base64.b64encode(v).decode() for k, v in s.pop("image").items()}
    for k in ("image_timestamp", "camera_intrinsics", "camera_extrinsics"):
        s.pop(k, None)
    return {"state": s, "images": pngs}


def frame(data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + data


def main() -> int:
    sess = Session()
    shim = socket.socket(fileno=3)
    shim.setblocking(True)
    sel = selectors.DefaultSelector()
    sel.register(shim, selectors.EVENT_READ, "shim")
    sel.register(sys.stdin, selectors.EVENT_READ, "host")
    buf = bytearray()
    print(json.dumps({"ready": True, "instance": robo.instance()}), flush=True)
    while True:
        for key, _ in sel.select():
            if key.data == "host":
                line = sys.stdin.readline()
                if not line:
                    return 0
                cmd = json.loads(line)
                if cmd.get("cmd") == "begin":
                    sess.budget = int(cmd.get("budget", 600))
                    sess.observe_only = bool(cmd.get("observe_only", False))
                    sess.steps = sess.calls = sess.refused = sess.observe_refused = 0
                    sess.chunks = dict.fromkeys(sess.chunks, 0)
                    sess.resets = dict.fromkeys(sess.resets, 0)
                    sess.last = None
                    sess.calls_log = []
                    print(json.dumps({"ok": True}), flush=True)
                elif cmd.get("cmd") == "end":
                    print(json.dumps(_strict({"steps": sess.steps, "calls": sess.calls, "refused": sess.refused,
                                              "observe_refused": sess.observe_refused,
                                              "chunks": sess.chunks, "resets": sess.resets, "last": sess.last,
                                              "log": sess.calls_log})), flush=True)
                elif cmd.get("cmd") == "observe":
                    print(json.dumps(observe(bool(cmd.get("images", True)), cmd.get("raw"))), flush=True)
                elif cmd.get("cmd") == "reset":
                    sess.override = None
                    sess.frames.clear()
                    print(json.dumps({"ok": robo.reset(), "feedback": robo.get_state([])["control_feedback"]}), flush=True)
                continue
            chunk = shim.recv(1 << 20)
            if not chunk:
                sel.unregister(shim)
                continue
            buf += chunk
            while len(buf) >= 4:
                (n,) = struct.unpack(">I", buf[:4])
                if n > 1 << 20:
                    return 1  # far more than any robo call needs: drop the worker
                if len(buf) < 4 + n:
                    break
                body, buf = bytes(buf[4 : 4 + n]), buf[4 + n :]
                try:
                    req = json.loads(body)
                    if not isinstance(req, dict):
                        raise TypeError("a robo request must be a JSON object")
                    out = ("ok", sess.call(req))
                except Exception as e:  # noqa: BLE001 - any error goes back to the program
                    out = ("raise", (type(e).__name__, str(e)))
                shim.sendall(frame(pickle.dumps(out, protocol=5)))


if __name__ == "__main__":
    os.environ.pop("PYTHONPATH", None)
    sys.exit(main())
