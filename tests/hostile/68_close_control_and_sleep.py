"""Close the worker's control socket and sleep (no CPU used), hoping the host waits forever; contained = the wall clock kills it."""
import os
import time

os.close(3)
time.sleep(10**9)
print("ESCAPED: the host never stopped this program")
