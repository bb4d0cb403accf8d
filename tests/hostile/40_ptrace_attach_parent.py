"""ptrace the parent via ctypes (PTRACE_SEIZE, which does not stop it; detached at once if it works); contained = killed or refused by seccomp."""
import ctypes
import os
import sys

PTRACE_DETACH, PTRACE_SEIZE = 17, 0x4206
libc = ctypes.CDLL(None, use_errno=True)
libc.ptrace.restype = ctypes.c_long
libc.ptrace.argtypes = [ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]
ppid = os.getppid()
if ppid <= 1:
    sys.exit(f"BLOCKED: parent pid is {ppid}; pid 1 is never targeted")
if libc.ptrace(PTRACE_SEIZE, ppid, None, None) == 0:
    print(f"ESCAPED: PTRACE_SEIZE attached to parent pid {ppid}", flush=True)
    libc.ptrace(PTRACE_DETACH, ppid, None, None)
    sys.exit(0)
err = ctypes.get_errno()
sys.exit(f"BLOCKED: ptrace(PTRACE_SEIZE, {ppid}): errno {err} ({os.strerror(err)})")
