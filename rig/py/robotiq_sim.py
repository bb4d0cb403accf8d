"""A Robotiq 2F-85 gripper simulator on a serial port, for tests and benches (synthetic: no real
gripper). The gripper's behaviour is written here from the published register map (see
gripper/src/robotiq.rs for the map); the Modbus RTU side (framing, CRC, exceptions) is
pymodbus's serial server in its simulator mode (a SimDevice whose action callback sees every
access), an implementation independent of the rmodbus framing r2g-robotiq uses.

    python rig/py/robotiq_sim.py --port PATH [--activation-s S] [--closed-count N] [--position N]

Faults follow the manual's classes: 0x08 (too hot) and 0x09 (no communication for 1 s) are
minor: the fingers hold while one lasts and it ends by itself, no reset needed (0x09 is set when
a request comes after at least 1 s without one while activated, and ends with the next request);
0x0A to 0x0F, and a controller fault (kFLT), are major: the fingers stop and only a reset
(rACT 0, then 1) ends them. Our modelling, not the manual's: the fingers also hold while the
gripper is too hot, and go on through a 0x09.

Prints `READY` once it serves. Reads JSON lines on stdin, each answered with one JSON line
(`{"ok": true, "position": COUNT, "activations": N}` or `{"ok": false, "error": ...}`;
`activations` counts rising edges of rACT, i.e. activations and resets):
  {"object_at": 120}     an object blocks closing at that position count (null: none)
  {"fault": 14}          set gFLT (14 = 0x0E overcurrent); {"fault": 0} ends a minor fault
                         (a major one ends only with a reset)
  {"kflt": 3}            set kFLT, the controller's own fault (major)
  {"corrupt_crc": 2}     the next 2 answers go out with a wrong CRC
  {"silent": true}       stop answering, as a cut line (false: answer again)
  {} (anything)          just the reply: where the fingers are
  {"quit": true}
Ends on SIGTERM/SIGINT or when stdin closes.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import logging
import signal
import sys
import threading
import time

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer
from pymodbus.simulator import DataType, SimData, SimDevice

OUTPUT, INPUT = 0x03E8, 0x07D0
SLAVE = 9
STROKE_MM = 85.0


MINOR = (0x08, 0x09)


def major(code: int) -> bool:
    return code >= 0x0A


class Gripper:
    """The gripper's state; positions are counts (0 open … closed_count touching)."""

    def __init__(self, activation_s: float, closed_count: int, position: int = 0) -> None:
        self.lock = threading.Lock()
        self.activation_s, self.closed = activation_s, closed_count
        self.act = self.gto = False
        self.activated_at: float | None = None  # when rACT went 1
        self.activations = 0
        self.req = self.speed = self.force = 0
        self.fault = 0
        self.kflt = 0
        self.obj = 0
        self.pos = float(position)  # where the fingers are, counts
        self.moved_at = time.monotonic()
        self.object_at: int | None = None
        self.corrupt = 0
        self.silent = False
        self.last_request: float | None = None

    def sta(self, now: float) -> int:
        if not self.act or self.activated_at is None:
            return 0
        return 3 if now - self.activated_at >= self.activation_s else 1

    def stopped(self) -> bool:
        """A fault that holds the fingers: too hot while it lasts, a major one until a reset."""
        return self.fault == 0x08 or major(self.fault) or self.kflt != 0

    def request(self, now: float) -> None:
        """Every request that reaches the gripper: 1 s or more since the last one while activated
        is fault 0x09 for this answer; the request after it ends it."""
        self.advance(now)
        if self.fault == 0x09:
            self.fault = 0
        if self.act and self.last_request is not None and now - self.last_request >= 1.0 and not self.stopped():
            self.fault = 0x09
        self.last_request = now

    def advance(self, now: float) -> None:
        """Moves the fingers for the time since the last call."""
        dt, self.moved_at = now - self.moved_at, now
        if self.sta(now) != 3 or not self.gto or self.stopped() or self.obj != 0:
            return
        mm_s = 20.0 + (150.0 - 20.0) * self.speed / 255.0
        step = mm_s * dt * self.closed / STROKE_MM
        target = min(self.req, self.closed)
        if self.pos < target:  # closing
            stop = self.object_at if self.object_at is not None and self.pos <= self.object_at < target else None
            nxt = min(self.pos + step, target)
            if stop is not None and nxt >= stop:
                self.pos, self.obj = float(stop), 2
            else:
                self.pos = nxt
                if nxt >= target:
                    self.obj = 3
        elif self.pos > target:  # opening
            self.pos = max(self.pos - step, float(target))
            if self.pos <= target:
                self.obj = 3
        else:
            self.obj = 3

    def write(self, regs: list[int], now: float) -> None:
        self.advance(now)
        action = regs[0] >> 8
        act, gto = bool(action & 0x01), bool(action & 0x08)
        if not act:
            # Reset: everything stops; major faults and 0x09 end (a hot motor stays hot).
            self.act = self.gto = False
            self.activated_at, self.obj, self.kflt = None, 0, 0
            if self.fault != 0x08:
                self.fault = 0
        elif not self.act:
            self.act, self.activated_at = True, now
            self.activations += 1
            if self.fault != 0x08:
                self.fault = 0
        self.req = regs[1] & 0xFF
        self.speed, self.force = regs[2] >> 8, regs[2] & 0xFF
        if gto and act:
            if major(self.fault) or self.kflt:
                pass  # ignored until a reset
            elif self.sta(now) == 1:
                self.fault = 0x05
            elif self.sta(now) == 0:
                self.fault = 0x07
            else:
                self.obj = 0  # a new request: the fingers move toward it (once no fault holds them)
                if self.fault in (0x05, 0x07):
                    self.fault = 0
        elif gto and not act:
            self.fault = 0x07
        self.gto = gto and act

    def status(self, now: float) -> list[int]:
        self.advance(now)
        sta = self.sta(now)
        moving = sta == 3 and self.gto and self.obj == 0 and not self.stopped()
        obj = self.obj if sta == 3 and self.gto else 0
        b0 = int(self.act) | (int(self.gto) << 3) | (sta << 4) | (obj << 6)
        # The motor draws current while the fingers move; stalled on an object it reads 0, as
        # in the manual's worked example.
        current = 10 if moving else 0
        pos = int(round(self.pos))
        fault = (self.kflt & 0x0F) << 4 | (self.fault & 0x0F)
        return [b0 << 8, fault << 8 | self.req, (pos & 0xFF) << 8 | current]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", required=True)
    ap.add_argument("--baud", type=int, default=115200)
    ap.add_argument("--activation-s", type=float, default=0.3)
    ap.add_argument("--closed-count", type=int, default=230)
    ap.add_argument("--position", type=int, default=0, help="where the fingers are at power-up, counts")
    a = ap.parse_args()
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    g = Gripper(a.activation_s, a.closed_count, a.position)

    async def action(func, start, address, count, registers, values):
        now = time.monotonic()
        with g.lock:
            if g.silent:
                return ExcCodes.DEVICE_BUSY  # replaced by no answer below (trace_packet)
            g.request(now)
            if values is not None and address == OUTPUT and func in (6, 16):
                full = [registers[OUTPUT - start + i] for i in range(3)]
                full[: len(values)] = list(values)
                g.write(full, now)
            if values is None and INPUT <= address < INPUT + 3:
                s = g.status(now)
                for i in range(3):
                    registers[INPUT - start + i] = s[i]
        return None

    def trace_packet(sending: bool, data: bytes) -> bytes:
        if not sending:
            return data
        if data and data[0] != SLAVE:
            return b""  # on a bus, only the addressed device answers
        with g.lock:
            if g.silent:
                return b""
            if g.corrupt > 0:
                g.corrupt -= 1
                return data[:-1] + bytes([data[-1] ^ 0xFF])
        return data

    device = SimDevice(
        id=SLAVE,
        simdata=[
            SimData(OUTPUT, count=3, values=0, datatype=DataType.REGISTERS),
            SimData(INPUT, count=3, values=0, datatype=DataType.REGISTERS),
        ],
        action=action,
    )

    async def serve() -> None:
        server = ModbusSerialServer(
            device, framer=FramerType.RTU, port=a.port, baudrate=a.baud, timeout=0.05,
            reconnect_delay=0.2, trace_packet=trace_packet,
        )
        loop = asyncio.get_running_loop()
        done = asyncio.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, done.set)

        def control() -> None:
            for line in sys.stdin:
                try:
                    msg = json.loads(line)
                    with g.lock:
                        now = time.monotonic()
                        g.advance(now)
                        if "object_at" in msg:
                            v = msg["object_at"]
                            g.object_at = None if v is None else int(v)
                            if g.obj == 2 and g.object_at is None:
                                g.obj = 0  # the object is gone: the fingers go on
                        if "fault" in msg:
                            code = int(msg["fault"])
                            if code != 0 or g.fault in MINOR:
                                g.fault = code
                        if "kflt" in msg:
                            g.kflt = int(msg["kflt"])
                        if "corrupt_crc" in msg:
                            g.corrupt = int(msg["corrupt_crc"])
                        if "silent" in msg:
                            g.silent = bool(msg["silent"])
                        reply = {"ok": True, "position": int(round(g.pos)), "activations": g.activations}
                    print(json.dumps(reply), flush=True)
                    if msg.get("quit"):
                        break
                except (ValueError, TypeError) as e:
                    print(json.dumps({"ok": False, "error": str(e)}), flush=True)
            loop.call_soon_threadsafe(done.set)

        await server.serve_forever(background=True)
        print("READY", flush=True)
        threading.Thread(target=control, daemon=True).start()
        await done.wait()
        await server.shutdown()

    asyncio.run(serve())
    return 0


if __name__ == "__main__":
    sys.exit(main())
