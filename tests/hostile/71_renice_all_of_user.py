"""Renice every process of our user (PRIO_USER, which includes the host and the runtime) and idle their disk I/O; contained = refused (exit 1)."""
import ctypes
import os
import sys

try:
    cur = os.getpriority(os.PRIO_USER, 0)
    os.setpriority(os.PRIO_USER, 0, cur)  # the value it already has: a no-op if allowed
    print("ESCAPED: setpriority(PRIO_USER) is allowed")
except OSError as e:
    print(f"BLOCKED: setpriority(PRIO_USER): {e!r}")
libc = ctypes.CDLL(None, use_errno=True)
SYS_ioprio_get, SYS_ioprio_set, IOPRIO_WHO_USER = 252, 251, 3
cur = libc.syscall(SYS_ioprio_get, IOPRIO_WHO_USER, 0)
if cur >= 0 and libc.syscall(SYS_ioprio_set, IOPRIO_WHO_USER, 0, cur) == 0:
    print("ESCAPED: ioprio_set(IOPRIO_WHO_USER) is allowed")
else:
    print(f"BLOCKED: ioprio_set(IOPRIO_WHO_USER): errno {ctypes.get_errno()}")
sys.exit(1)
