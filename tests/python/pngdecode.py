"""A minimal PNG reader on the standard library (numpy only for `read`), so tests can check real
pixels without an imaging dependency: grey, grey + alpha, RGB and RGBA at 8 or 16 bits, every
filter, no interlace, no palette."""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

# Colour type -> channels.
CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}


def header(data: bytes) -> tuple[int, int, int, int]:
    """(width, height, bit depth, channels) of a PNG we can read; ValueError otherwise."""
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG")
    if data[12:16] != b"IHDR":
        raise ValueError("a PNG starts with IHDR")
    width, height, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", data[16:29])
    if depth not in (8, 16) or color not in CHANNELS or interlace:
        raise ValueError(f"unsupported PNG: depth {depth} color {color} interlace {interlace}")
    return width, height, depth, CHANNELS[color]


def _unfilter(raw: bytes, height: int, stride: int, bpp: int) -> bytes:
    out = bytearray()
    prev = bytearray(stride)
    for y in range(height):
        f = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)])
        if f == 1:
            for i in range(bpp, stride):
                line[i] = (line[i] + line[i - bpp]) & 0xFF
        elif f == 2:
            line = bytearray((x + p) & 0xFF for x, p in zip(line, prev))
        elif f == 3:
            for i in range(stride):
                a = line[i - bpp] if i >= bpp else 0
                line[i] = (line[i] + (a + prev[i]) // 2) & 0xFF
        elif f == 4:
            for i in range(stride):
                a = line[i - bpp] if i >= bpp else 0
                b = prev[i]
                c = prev[i - bpp] if i >= bpp else 0
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                line[i] = (line[i] + pred) & 0xFF
        elif f != 0:
            raise ValueError(f"row {y}: unknown filter {f}")
        out += line
        prev = line
    return bytes(out)


def decode16(data: bytes) -> tuple[int, int, int, int, bytes]:
    """(width, height, bit depth, channels, pixel rows without filter bytes); 16-bit samples
    are big-endian byte pairs."""
    width, height, depth, channels = header(data)
    pos, idat = 8, b""
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        if kind == b"IDAT":
            idat += data[pos + 8 : pos + 8 + length]
        elif kind == b"IEND":
            break
        pos += 12 + length
    bpp = channels * depth // 8
    stride = width * bpp
    raw = zlib.decompress(idat)
    if len(raw) != height * (stride + 1):
        raise ValueError(f"{len(raw)} bytes of pixel data for {width}x{height}x{bpp}")
    return width, height, depth, channels, _unfilter(raw, height, stride, bpp)


def decode(data: bytes) -> tuple[int, int, int, bytes]:
    """An 8-bit PNG: (width, height, channels, raw pixel rows without filter bytes)."""
    width, height, depth, channels, px = decode16(data)
    if depth != 8:
        raise ValueError(f"decode reads 8-bit PNGs; this one has {depth} bits (use read)")
    return width, height, channels, px


def read(src: bytes | str | Path):
    """A PNG (bytes or a file) as a numpy array: height x width for grey, height x width x
    channels otherwise; uint8 or uint16 by its bit depth."""
    import numpy as np

    data = src if isinstance(src, bytes) else Path(src).read_bytes()
    w, h, depth, ch, px = decode16(data)
    a = np.frombuffer(px, dtype=np.uint8 if depth == 8 else ">u2").astype(np.uint8 if depth == 8 else np.uint16)
    return a.reshape(h, w) if ch == 1 else a.reshape(h, w, ch)
