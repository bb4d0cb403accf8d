"""Change metadata of a host file landlock may not cover (chmod/chown/utime/truncate of robot.json to current values, removexattr of an absent name: no-ops if they work); contained = each refused."""
import errno
import os
import sys
from pathlib import Path

for root in sorted({Path("/work/main"), Path(sys.prefix).parent}):
    path = root / "robot-skill" / "config" / "robot.json"
    try:
        st = os.stat(path)
    except OSError as e:
        print(f"INFO: stat {path}: {e!r}")
        continue
    ops = [
        ("chmod", lambda: os.chmod(path, st.st_mode & 0o7777)),
        ("chown", lambda: os.chown(path, st.st_uid, st.st_gid)),
        ("utime", lambda: os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))),
        ("truncate", lambda: os.truncate(path, st.st_size)),
        ("removexattr", lambda: os.removexattr(path, "user.r2g_hostile_absent")),
    ]
    for name, op in ops:
        try:
            op()
            print(f"ESCAPED: {name} on {path} succeeded")
        except OSError as e:
            if e.errno == errno.ENODATA:  # permission granted; the attribute just is not there
                print(f"ESCAPED: {name} on {path} was permitted ({e!r})")
            else:
                print(f"BLOCKED: {name} on {path}: {e!r}")
sys.exit(1)
