"""List host directories outside the granted set (/, /root, /home, /tmp, /work, /etc); contained = every listing fails."""
import os
import sys

for path in ("/", "/root", "/home", "/tmp", "/var/tmp", "/work", "/work/main", "/etc", "/run", "/proc", "/sys/fs/cgroup"):
    try:
        names = sorted(os.listdir(path))
        print(f"ESCAPED: listed {path}: {names[:12]}")
    except OSError as e:
        print(f"BLOCKED: listdir {path}: {e!r}")
sys.exit(1)
