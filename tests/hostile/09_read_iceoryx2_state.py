"""List and read the runtime's iceoryx2 state (/tmp/iceoryx2, /dev/shm/iox2_*); contained = every listing and open fails."""
import os
import sys

for top in ("/tmp/iceoryx2", "/tmp/iceoryx2/services", "/tmp/iceoryx2/nodes", "/dev/shm"):
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
