"""Leave the pids cgroup (write our pid to the root and parent cgroup.procs) and lift our own pids.max; contained = every cgroup write fails."""
import os
import sys

me = str(os.getpid())
own = None
try:
    with open("/proc/self/cgroup") as f:
        own = next((l.strip().split(":", 2)[2] for l in f if l.startswith("0::")), None)
    print(f"INFO: own cgroup {own!r}")
except OSError as e:
    print(f"BLOCKED: /proc/self/cgroup: {e!r}")
base = "/sys/fs/cgroup"
writes = [(f"{base}/cgroup.procs", me)]
if own and own != "/":
    writes += [(f"{base}{os.path.dirname(own)}/cgroup.procs", me), (f"{base}{own}/pids.max", "max"),
               (f"{base}{own}/memory.max", "max")]
for path, value in writes:
    try:
        with open(path, "w") as f:
            f.write(value)
        print(f"ESCAPED: wrote {value!r} to {path}")
    except OSError as e:
        print(f"BLOCKED: write {path}: {e!r}")
sys.exit(1)
