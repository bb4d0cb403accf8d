"""Sleep forever while ignoring catchable signals (deliberately unbounded, uses no CPU); contained = killed by the wall-clock limit."""
import signal
import time

for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGALRM, signal.SIGUSR1):
    signal.signal(sig, signal.SIG_IGN)
while True:
    time.sleep(3600)
