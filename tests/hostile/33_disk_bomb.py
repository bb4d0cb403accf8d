"""Disk bomb in scratch: append 1 MiB blocks to one file until 2 GiB; contained = EFBIG/SIGXFSZ or ENOSPC well before 2 GiB."""
import os

BLOCK = b"\xa5" * (1 << 20)
written = 0
try:
    with open("bomb.bin", "wb") as f:
        while written < (2 << 30):
            f.write(BLOCK)
            f.flush()
            written += len(BLOCK)
except OSError as e:
    print(f"BLOCKED: write failed after {written >> 20} MiB: {e!r}")
    raise
print(f"ESCAPED: wrote {written >> 20} MiB into scratch, no file-size limit")
os.remove("bomb.bin")
