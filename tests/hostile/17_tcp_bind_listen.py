"""Bind and listen on TCP ports (any address, a fixed port) to offer a backdoor; contained = socket() killed or refused by seccomp."""
import socket

for addr in (("0.0.0.0", 0), ("127.0.0.1", 8765)):
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    print("ESCAPED: socket(AF_INET, SOCK_STREAM) was allowed")
    try:
        s.bind(addr)
        s.listen(1)
        print(f"ESCAPED: listening on {s.getsockname()}")
    except OSError as e:
        print(f"BLOCKED: bind/listen {addr}: {e!r}")
    finally:
        s.close()
