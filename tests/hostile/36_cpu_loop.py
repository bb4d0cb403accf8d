"""Infinite CPU loop that ignores SIGXCPU/SIGTERM/SIGINT/SIGHUP (deliberately unbounded); contained = killed by the CPU rlimit or the wall clock."""
import signal

for sig in (signal.SIGXCPU, signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
    signal.signal(sig, signal.SIG_IGN)
x = 0
while True:
    x += 1
