"""setpgid() into a new process group to dodge the group kill, then linger 300 s; contained = killed or refused by seccomp, group unchanged."""
import os
import sys
import time

before = os.getpgid(0)
for target in (0, os.getppid()):
    try:
        os.setpgid(0, target)
    except OSError as e:
        print(f"BLOCKED: setpgid(0, {target}): {e!r}")
after = os.getpgid(0)
if after == before:
    sys.exit(f"BLOCKED: process group unchanged ({before})")
print(f"ESCAPED: process group moved from {before} to {after}; lingering", flush=True)
time.sleep(300)
