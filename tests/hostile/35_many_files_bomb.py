"""Many-files bomb in scratch: 500000 files of 4 KiB (2 GiB, each file under any per-file cap); contained = a scratch quota, inode limit or time limit stops it."""
import os

BODY = b"\x3c" * 4096
os.mkdir("many")
count = 0
try:
    while count < 500000:
        with open(f"many/{count:06d}", "wb") as f:
            f.write(BODY)
        count += 1
except OSError as e:
    print(f"BLOCKED: file number {count + 1} failed: {e!r}")
    raise
print(f"ESCAPED: created {count} files ({count * len(BODY) >> 20} MiB) in scratch, no quota")
