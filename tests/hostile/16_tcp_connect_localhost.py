"""Open an AF_INET TCP socket and connect to local services and the cloud metadata address; contained = socket() killed or refused by seccomp."""
import socket

TARGETS = [("127.0.0.1", 22), ("127.0.0.1", 80), ("127.0.0.1", 8080), ("127.0.0.1", 11434),
           ("127.0.0.1", 6379), ("169.254.169.254", 80)]
s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)  # the design forbids socket() of any family
print("ESCAPED: socket(AF_INET, SOCK_STREAM) was allowed")
s.close()
for host, port in TARGETS:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as c:
        c.settimeout(0.5)
        try:
            c.connect((host, port))
            print(f"ESCAPED: connected to {host}:{port}")
        except OSError as e:
            print(f"BLOCKED: connect {host}:{port}: {e!r}")
