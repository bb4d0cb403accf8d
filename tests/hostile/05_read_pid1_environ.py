"""Read /proc/1/environ and /proc/1/cmdline (init of the host or container); contained = every open fails."""
import os
import sys

if os.getpid() == 1:
    sys.exit("BLOCKED: this program is pid 1 of its own namespace; /proc/1 is itself")
for name in ("environ", "cmdline", "mountinfo"):
    path = f"/proc/1/{name}"
    try:
        with open(path, "rb") as f:
            data = f.read(65536)
        print(f"ESCAPED: read {len(data)} bytes of {path}")
    except OSError as e:
        print(f"BLOCKED: {path}: {e!r}")
sys.exit(1)
