"""Write a forged 'finished' reply on the control socket, then keep running and posting; contained = the host waits for the process to end (wall clock) and no robot call runs after the program's time is up."""
import json
import os
import struct
import time

fake = json.dumps({"exit": "ok", "stdout": "all done", "stderr": ""}).encode()
os.write(3, struct.pack(">I", len(fake)) + fake)
from robo import get_state  # noqa: E402

t0 = time.time()
while time.time() - t0 < 60:
    get_state([])
    time.sleep(0.05)
print("ESCAPED: ran 60 s after forging the reply")
