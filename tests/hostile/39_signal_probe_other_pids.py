"""Probe every other pid with signal 0 (permission check, nothing delivered); contained = EPERM/ESRCH everywhere, never success."""
import os
import sys

me = os.getpid()
try:
    pids = sorted(int(n) for n in os.listdir("/proc") if n.isdigit())
    print(f"ESCAPED?: listed {len(pids)} pids in /proc")
except OSError as e:
    print(f"BLOCKED: listdir /proc: {e!r}")
    around = {p for c in (me, os.getppid()) for p in range(max(2, c - 5000), c + 5000)}
    pids = sorted(set(range(2, 1 << 16)) | around)
permitted, denied = [], 0
for pid in pids:
    if pid in (1, me):  # pid 1 is never targeted
        continue
    try:
        os.kill(pid, 0)
        permitted.append(pid)
    except PermissionError:
        denied += 1
    except ProcessLookupError:
        pass
print(f"INFO: {denied} pids denied")
if permitted:
    print(f"ESCAPED: allowed to signal {len(permitted)} other pids, e.g. {permitted[:10]}")
sys.exit("BLOCKED: no other pid can be signalled")
