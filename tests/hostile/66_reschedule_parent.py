"""Re-pin, re-prioritise and renice the parent (the host), as one might to starve the 1 kHz runtime; contained = every call refused (exit 1)."""
import os
import sys

ppid = os.getppid()
for what, call in [
    ("sched_setaffinity", lambda: os.sched_setaffinity(ppid, os.sched_getaffinity(ppid))),
    ("sched_setscheduler", lambda: os.sched_setscheduler(ppid, os.sched_getscheduler(ppid), os.sched_getparam(ppid))),
    ("setpriority", lambda: os.setpriority(os.PRIO_PROCESS, ppid, os.getpriority(os.PRIO_PROCESS, ppid))),
]:
    try:
        call()  # each sets the value the parent already has: a no-op if it works
        print(f"ESCAPED: {what} on the parent {ppid} is allowed")
    except OSError as e:
        print(f"BLOCKED: {what}: {e!r}")
sys.exit(1)
