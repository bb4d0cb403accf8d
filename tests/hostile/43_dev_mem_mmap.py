"""Open and mmap /dev/mem read-only, and open raw disks and kernel log devices; contained = every open fails."""
import mmap
import os
import sys

try:
    fd = os.open("/dev/mem", os.O_RDONLY)
    print("ESCAPED: opened /dev/mem")
    with mmap.mmap(fd, 4096, mmap.MAP_SHARED, mmap.PROT_READ, offset=0xF0000) as m:
        print(f"ESCAPED: mapped /dev/mem at 0xF0000, first bytes {m[:8].hex()}")
    os.close(fd)
except OSError as e:
    print(f"BLOCKED: /dev/mem: {e!r}")
for path in ("/dev/kmem", "/dev/port", "/dev/kmsg", "/dev/sda", "/dev/vda", "/dev/nvme0n1", "/dev/nvidia0", "/dev/fuse"):
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        os.close(fd)
        print(f"ESCAPED: opened {path}")
    except OSError as e:
        print(f"BLOCKED: {path}: {type(e).__name__} errno={e.errno}")
sys.exit(1)
