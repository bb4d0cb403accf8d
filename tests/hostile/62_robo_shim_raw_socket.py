"""Grab the robo shim's socket and send garbage and forged frames straight to the proxy; contained = the proxy drops us (robo raises), no network socket reachable, exit nonzero."""
import os
import random
import socket
import stat
import sys

import robo

print(f"INFO: robo is {getattr(robo, '__file__', '?')}; names {[n for n in dir(robo) if not n.startswith('__')]}")
found = []
for fd in range(3, 1024):
    try:
        if stat.S_ISSOCK(os.fstat(fd).st_mode):
            found.append(fd)
    except OSError:
        pass
if not found:
    sys.exit("BLOCKED: no socket descriptor reachable from the program")
rng = random.Random(2024)
for fd in found:
    s = socket.socket(fileno=os.dup(fd))
    print(f"INFO: fd {fd}: family {s.family!r} type {s.type!r}")
    if s.family in (socket.AF_INET, socket.AF_INET6):
        print(f"ESCAPED: fd {fd} is a network socket")
    frames = [
        b"\xff\xff\xff\x7f" + b"A" * 64,  # a length prefix claiming 2 GiB
        b'{"op": "exec", "cmd": "/bin/sh"}\n',
        b'{"method": "post_actions", "params": {"actions": [[9, 9, 9, 9, 9, 9, 9, 1]], "type": "joint", "freq": ""}, "trusted": true}\n',
        bytes(rng.getrandbits(8) for _ in range(1 << 16)),
    ]
    try:
        s.settimeout(2.0)
        for frame in frames:
            s.sendall(frame)
        print(f"INFO: sent {sum(map(len, frames))} bytes of garbage on fd {fd}")
    except OSError as e:
        print(f"BLOCKED: send on fd {fd}: {e!r}")
    s.close()
try:
    st = robo.get_state([])
    print(f"INFO: robo still answers after the garbage (proxy resynchronised): joint {st['joint'][:2]}...")
except (ConnectionError, RuntimeError, OSError, ValueError) as e:
    print(f"BLOCKED: robo after the garbage: {e!r}")
sys.exit(1)
