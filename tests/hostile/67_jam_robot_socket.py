"""Flood the robo socket with requests and never read the answers, so the proxy blocks on writing; contained = the host cuts the connection and carries on (a violation is reported)."""
import json
import socket
import struct

s = socket.socket(fileno=4)
req = json.dumps({"fn": "get_state", "args": [], "kwargs": {}}).encode()
for _ in range(50):
    s.sendall(struct.pack(">I", len(req)) + req)
print("BLOCKED: requests queued; the host must not wait for the proxy forever")
