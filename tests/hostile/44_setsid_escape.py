"""setsid() to leave the process group the sandbox kills, then linger 300 s; contained = killed or refused by seccomp (EPERM also if already a group leader)."""
import os
import sys
import time

before = os.getsid(0)
try:
    os.setsid()
except OSError as e:
    sys.exit(f"BLOCKED: setsid: {e!r} (session stays {before})")
print(f"ESCAPED: setsid moved from session {before} to {os.getsid(0)}; lingering", flush=True)
time.sleep(300)
