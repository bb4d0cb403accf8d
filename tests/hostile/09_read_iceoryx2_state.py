"""List and read the runtime's iceoryx2 state (/tmp/iceoryx2, /dev/shm/iox2_*); contained = every listing and open fails."""
import os
import sys

# The configured root (R2G_IPC_CONFIG, passed in as R2G_IPC_ROOT) and iceoryx2's default.
roots = {os.environ.get("R2G_IPC_ROOT") or "/tmp/iceoryx2", "/tmp/iceoryx2"}
tops = [os.path.join(r, sub) for r in sorted(roots) for sub in ("", "services", "nodes")]
for top in tops + ["/dev/shm"]:
    try:
        names = sorted(os.listdir(top))
    except OSError as e:
        print(f"BLOCKED: listdir {top}: {e!r}")
        continue
    print(f"ESCAPED: listed {top}: {names[:8]}")
    for name in names[:8]:
        path = os.path.join(top, name)
        try:
            with open(path, "rb") as f:
                print(f"ESCAPED: read {len(f.read(4096))} bytes of {path}")
        except OSError as e:
            print(f"BLOCKED: {path}: {e!r}")
sys.exit(1)
