"""Fork bomb capped at 200 children (children sleep 30 s, never fork); contained = the first fork is killed or refused (seccomp, pids cgroup)."""
import os
import signal
import time

children = []
try:
    for i in range(200):
        pid = os.fork()
        if pid == 0:  # child: never forks again, exits on its own
            try:
                time.sleep(30)
            finally:
                os._exit(0)
        children.append(pid)
except OSError as e:
    print(f"BLOCKED: fork number {len(children) + 1} failed: {e!r}")
    raise
finally:
    if children:
        print(f"ESCAPED: forked {len(children)} children", flush=True)
    for pid in children:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
