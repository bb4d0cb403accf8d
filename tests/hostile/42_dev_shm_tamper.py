"""Tamper with the runtime's shared memory: open /dev/shm/iox2_* read-write (existing segments are not overwritten) and create a fake iox2 segment; contained = every open fails."""
import mmap
import os
import sys

try:
    names = sorted(n for n in os.listdir("/dev/shm") if n.startswith("iox2_"))
    print(f"ESCAPED: listed /dev/shm: {len(names)} iox2 segments")
except OSError as e:
    print(f"BLOCKED: listdir /dev/shm: {e!r}")
    names = []
for name in names[:16]:
    path = f"/dev/shm/{name}"
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError as e:
        print(f"BLOCKED: open {path} O_RDWR: {e!r}")
        continue
    try:
        size = os.fstat(fd).st_size
        if size:
            with mmap.mmap(fd, min(size, 4096), mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE):
                pass  # a writable shared mapping of the live segment: garbage could go here
        print(f"ESCAPED: mapped {path} ({size} bytes) read-write")
    finally:
        os.close(fd)
fake = "/dev/shm/iox2_r2g-hostile-canary"
try:
    with open(fake, "wb") as f:
        f.write(os.urandom(4096))
    print(f"ESCAPED: created garbage segment {fake}")
except OSError as e:
    print(f"BLOCKED: create {fake}: {e!r}")
sys.exit(1)
