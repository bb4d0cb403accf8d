"""tests/python/pngdecode.py, the PNG reader the other tests use, against PNGs written here with
every filter type on every row pattern, at 8 and 16 bits, in every colour type it reads."""
from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

import pngdecode


def chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def paeth(a: int, b: int, c: int) -> int:
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else (b if pb <= pc else c)


def encode(img: np.ndarray, depth: int, color: int, channels: int) -> bytes:
    """A PNG whose row y uses filter y % 5 (none, sub, up, average, Paeth)."""
    h, w = img.shape[:2]
    raw = img.astype(">u2").tobytes() if depth == 16 else img.astype(np.uint8).tobytes()
    bpp = channels * depth // 8
    stride, out, prev = w * bpp, b"", bytes(w * bpp)
    for y in range(h):
        line, f = raw[y * stride:(y + 1) * stride], y % 5
        enc = bytearray()
        for i in range(stride):
            a = line[i - bpp] if i >= bpp else 0
            b, c = prev[i], (prev[i - bpp] if i >= bpp else 0)
            enc.append((line[i] - [0, a, b, (a + b) // 2, paeth(a, b, c)][f]) & 0xFF)
        out += bytes([f]) + bytes(enc)
        prev = line
    ihdr = struct.pack(">IIBBBBB", w, h, depth, color, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(out)) + chunk(b"IEND", b"")


@pytest.mark.parametrize("depth", [8, 16])
@pytest.mark.parametrize("color,channels", [(0, 1), (2, 3), (4, 2), (6, 4)])
def test_every_filter_depth_and_colour_type_reads_back(depth: int, color: int, channels: int) -> None:
    rng = np.random.default_rng(depth * 10 + color)
    shape = (11, 13) if channels == 1 else (11, 13, channels)
    img = rng.integers(0, 2**depth, shape)
    got = pngdecode.read(encode(img, depth, color, channels))
    assert got.dtype == (np.uint8 if depth == 8 else np.uint16) and got.shape == shape
    assert np.array_equal(got, img)
    if depth == 8:
        w, h, ch, px = pngdecode.decode(encode(img, depth, color, channels))
        assert (w, h, ch) == (13, 11, channels) and px == img.astype(np.uint8).tobytes()
    else:
        with pytest.raises(ValueError, match="16 bits"):
            pngdecode.decode(encode(img, depth, color, channels))


def test_what_it_cannot_read_is_refused() -> None:
    with pytest.raises(ValueError, match="not a PNG"):
        pngdecode.read(b"GIF89a" + bytes(40))
    palette = encode(np.zeros((2, 2)), 8, 0, 1).replace(b"\x00\x00\x00\x02\x00\x00\x00\x02\x08\x00", b"\x00\x00\x00\x02\x00\x00\x00\x02\x08\x03")
    with pytest.raises(ValueError, match="color 3"):
        pngdecode.read(palette)
