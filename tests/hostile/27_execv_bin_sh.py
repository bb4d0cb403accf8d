"""Replace this process with a shell via os.execv (no fork needed; the shell prints ESCAPED); contained = every execv fails."""
import os
import sys

for path in ("/bin/sh", "/usr/bin/sh", "/bin/bash", "/bin/dash", "/bin/busybox", "/usr/bin/env"):
    sys.stdout.flush()
    try:
        os.execv(path, [path, "-c", "echo 'ESCAPED: execv ran a shell'"] if "env" not in path
                 else [path, "sh", "-c", "echo 'ESCAPED: execv ran env then a shell'"])
    except OSError as e:
        print(f"BLOCKED: execv {path}: {e!r}")
sys.exit(1)
