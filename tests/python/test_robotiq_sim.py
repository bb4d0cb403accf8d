"""OUR Robotiq 2F-85 simulator (rig/py/robotiq_sim.py) answers the manual's worked examples byte
for byte, CRC included, to raw bytes written on a pseudo-terminal (pyserial, no Modbus library
on this side); and it behaves as the register map says on errors. gripper/src/robotiq.rs checks
the same frames on r2g-robotiq's side, so a misreading of the map cannot hide on both sides."""
from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Iterator

import pytest
import serial

from conftest import need_program
from robotiq_rig import PYTHON, SIM, stop

need_program("socat", "socat is missing (scripts/install-deps.sh installs it; make test does)")


def crc16(b: bytes) -> bytes:
    """CRC-16/MODBUS, written out here (independent of pymodbus and rmodbus)."""
    c = 0xFFFF
    for x in b:
        c ^= x
        for _ in range(8):
            c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
    return bytes([c & 0xFF, c >> 8])


class Line:
    def __init__(self, tmp: Path) -> None:
        self.socat = subprocess.Popen(
            ["socat", f"pty,raw,echo=0,link={tmp}/g", f"pty,raw,echo=0,link={tmp}/d"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 10
        while not ((tmp / "g").exists() and (tmp / "d").exists()):
            assert time.monotonic() < deadline
            time.sleep(0.02)
        self.sim = subprocess.Popen([str(PYTHON), str(SIM), "--port", str(tmp / "g"), "--activation-s", "0.4"],
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self.sim.stdout.readline().strip() == "READY"
        self.port = serial.Serial(str(tmp / "d"), 115200, timeout=0.5)

    def ask(self, hex_frame: str, answer_len: int) -> bytes:
        self.port.reset_input_buffer()
        self.port.write(bytes.fromhex(hex_frame))
        return self.port.read(answer_len)

    def control(self, **msg) -> None:
        self.sim.stdin.write(json.dumps(msg) + "\n")
        self.sim.stdin.flush()
        assert json.loads(self.sim.stdout.readline())["ok"]

    def close(self) -> None:
        self.port.close()
        stop(self.sim)
        stop(self.socat)


@pytest.fixture
def line(tmp_path: Path) -> Iterator[Line]:
    ln = Line(tmp_path)
    try:
        yield ln
    finally:
        ln.close()


WRITE_OK = bytes.fromhex("09 10 03 E8 00 03 01 30")
STATUS1 = "09 03 07 D0 00 01 85 CF"
STATUS3 = "09 03 07 D0 00 03 04 0E"


def test_the_manuals_worked_examples_byte_for_byte(line: Line) -> None:
    assert line.ask("09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30", 8) == WRITE_OK
    assert line.ask("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1", 8) == WRITE_OK
    assert line.ask(STATUS1, 7) == bytes.fromhex("09 03 02 11 00 55 D5"), "activation in progress"
    time.sleep(0.5)
    assert line.ask(STATUS1, 7) == bytes.fromhex("09 03 02 31 00 4C 15"), "activation completed"
    line.control(object_at=0xBD)
    assert line.ask("09 10 03 E8 00 03 06 09 00 00 FF FF FF 42 29", 8) == WRITE_OK
    moving = line.ask(STATUS3, 11)
    assert moving[:4] == bytes.fromhex("09 03 06 39") and moving[6] == 0xFF, moving.hex(" ")
    assert crc16(moving[:-2]) == moving[-2:]
    for _ in range(5):  # polled, as a driver does (1 s without a request is fault 0x09)
        time.sleep(0.3)
        line.ask(STATUS3, 11)
    assert line.ask(STATUS3, 11) == bytes.fromhex("09 03 06 B9 00 00 FF BD 00 1D 7C"), "stopped on the object"
    assert line.ask("09 10 03 E8 00 03 06 09 00 00 00 FF FF 72 19", 8) == WRITE_OK


def test_errors_follow_the_register_map(line: Line) -> None:
    # Another slave id: no answer at all.
    frame = bytes.fromhex("0A 03 07 D0 00 03")
    line.port.write(frame + crc16(frame))
    assert line.port.read(11) == b""
    # Go without activation: fault 0x07, nothing moves.
    assert line.ask("09 10 03 E8 00 03 06 08 00 00 FF FF FF " + crc16(bytes.fromhex("09 10 03 E8 00 03 06 08 00 00 FF FF FF")).hex(), 8) == WRITE_OK
    a = line.ask(STATUS3, 11)
    assert a[5] & 0x0F == 0x07 and a[7] == 0, a.hex(" ")
    # Activate, start closing, inject an overcurrent: the fingers stop and the fault stays
    # until a reset (rACT 0 then 1).
    line.ask("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1", 8)
    time.sleep(0.5)
    line.ask("09 10 03 E8 00 03 06 09 00 00 FF 40 FF " + crc16(bytes.fromhex("09 10 03 E8 00 03 06 09 00 00 FF 40 FF")).hex(), 8)
    time.sleep(0.2)
    line.control(fault=0x0E)
    a = line.ask(STATUS3, 11)
    time.sleep(0.3)
    b = line.ask(STATUS3, 11)
    assert a[5] == b[5] == 0x0E and a[7] == b[7], (a.hex(" "), b.hex(" "))
    line.ask("09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30", 8)
    line.ask("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1", 8)
    assert line.ask(STATUS3, 11)[5] == 0
    # A corrupted answer fails the CRC; silence is silence.
    line.control(corrupt_crc=1)
    bad = line.ask(STATUS3, 11)
    assert len(bad) == 11 and crc16(bad[:-2]) != bad[-2:]
    line.control(silent=True)
    assert line.ask(STATUS3, 11) == b""
    line.control(silent=False)
    good = line.ask(STATUS3, 11)
    assert crc16(good[:-2]) == good[-2:]


def test_minor_faults_end_by_themselves_major_ones_need_a_reset(line: Line) -> None:
    """The manual's classes: 0x08 and 0x09 are minor (no reset), 0x0A-0x0F and kFLT major."""
    line.ask("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1", 8)
    time.sleep(0.5)
    assert line.ask(STATUS3, 11)[3] & 0x31 == 0x31, "activated"
    # Too hot: reported while it lasts, gone without a reset.
    line.control(fault=0x08)
    assert line.ask(STATUS3, 11)[5] == 0x08
    line.control(fault=0)
    assert line.ask(STATUS3, 11)[5] == 0x00
    # No request for 1 s while activated: 0x09 in the next answer, gone with the one after.
    time.sleep(1.1)
    assert line.ask(STATUS3, 11)[5] == 0x09
    assert line.ask(STATUS3, 11)[5] == 0x00
    # A controller fault: kFLT in the high nibble; only a reset (rACT 0, then 1) ends it.
    line.control(kflt=3)
    assert line.ask(STATUS3, 11)[5] == 0x30
    line.control(fault=0)
    assert line.ask(STATUS3, 11)[5] == 0x30
    line.ask("09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30", 8)
    line.ask("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1", 8)
    assert line.ask(STATUS3, 11)[5] == 0x00
