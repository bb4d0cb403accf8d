"""Make ourselves the last OOM victim (oom_score_adj -1000) and the parent the first (+1000, only if ours worked); contained = both writes fail."""
import os
import sys

try:
    with open("/proc/self/oom_score_adj", "w") as f:
        f.write("-1000")
    print("ESCAPED: set our own oom_score_adj to -1000")
except OSError as e:
    sys.exit(f"BLOCKED: /proc/self/oom_score_adj: {e!r}")
ppid = os.getppid()
if ppid > 1:
    try:
        with open(f"/proc/{ppid}/oom_score_adj", "r+") as f:  # opened for writing, left unchanged
            print(f"ESCAPED: /proc/{ppid}/oom_score_adj is writable (value {f.read().strip()})")
    except OSError as e:
        print(f"BLOCKED: /proc/{ppid}/oom_score_adj: {e!r}")
