"""Raise rlimits above their hard caps, look for missing caps, and set the parent's limits; contained = every raise refused, caps finite (exit 1)."""
import os
import resource
import sys

INF = resource.RLIM_INFINITY
NAMES = ["RLIMIT_CPU", "RLIMIT_AS", "RLIMIT_NOFILE", "RLIMIT_FSIZE", "RLIMIT_NPROC", "RLIMIT_DATA", "RLIMIT_MEMLOCK"]
MUST_BE_FINITE = {"RLIMIT_CPU", "RLIMIT_AS", "RLIMIT_NOFILE", "RLIMIT_FSIZE"}
for name in NAMES:
    res = getattr(resource, name)
    soft, hard = resource.getrlimit(res)
    print(f"INFO: {name} soft={soft} hard={hard}")
    if name in MUST_BE_FINITE and hard == INF:
        print(f"ESCAPED: {name} has no hard limit")
        continue
    if hard == INF:
        continue
    try:
        resource.setrlimit(res, (INF, INF))
        print(f"ESCAPED: raised {name} hard limit from {hard} to infinity")
    except (ValueError, OSError) as e:
        print(f"BLOCKED: raise {name}: {e!r}")
ppid = os.getppid()
if ppid > 1:
    try:  # sets the parent's RLIMIT_CORE to the value it already has: a no-op if it works
        cur = resource.prlimit(ppid, resource.RLIMIT_CORE)
        resource.prlimit(ppid, resource.RLIMIT_CORE, cur)
        print(f"ESCAPED: prlimit can set the rlimits of parent pid {ppid}")
    except (ValueError, OSError) as e:
        print(f"BLOCKED: prlimit on parent {ppid}: {e!r}")
sys.exit(1)
