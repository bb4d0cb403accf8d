"""Send SIGKILL to the parent process (the sandbox worker); contained = PermissionError from landlock signal scoping."""
import os
import signal
import sys
import time

ppid = os.getppid()
if ppid <= 1:
    sys.exit(f"BLOCKED: parent pid is {ppid}; pid 1 is never targeted")
os.kill(ppid, signal.SIGKILL)
time.sleep(0.5)
print(f"ESCAPED: SIGKILL delivered to parent pid {ppid} (parent is now {os.getppid()})")
