"""Open an AF_INET6 socket and connect to ::1 and a v4-mapped loopback; contained = socket() killed or refused by seccomp."""
import socket

s = socket.socket(socket.AF_INET6, socket.SOCK_STREAM)
print("ESCAPED: socket(AF_INET6, SOCK_STREAM) was allowed")
s.settimeout(0.5)
for addr in (("::1", 22, 0, 0), ("::ffff:127.0.0.1", 80, 0, 0)):
    try:
        s.connect(addr)
        print(f"ESCAPED: connected to {addr[0]}:{addr[1]}")
        break
    except OSError as e:
        print(f"BLOCKED: connect {addr[0]}:{addr[1]}: {e!r}")
s.close()
