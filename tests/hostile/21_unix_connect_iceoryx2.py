"""AF_UNIX connect to iceoryx2 sockets, the Docker/containerd/D-Bus sockets and abstract names; contained = socket() killed or refused."""
import os
import socket

paths = []
roots = {os.environ.get("R2G_IPC_ROOT") or "/tmp/iceoryx2", "/tmp/iceoryx2"}
for top in [os.path.join(r, sub) for r in sorted(roots) for sub in ("", "services", "nodes")]:
    try:
        paths += [os.path.join(top, n) for n in sorted(os.listdir(top))]
    except OSError as e:
        print(f"BLOCKED: listdir {top}: {e!r}")
paths += ["/var/run/docker.sock", "/run/containerd/containerd.sock", "/run/dbus/system_bus_socket",
          "\0iceoryx2", "\0/tmp/iceoryx2", "\0/tmp/.X11-unix/X0"]
for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
    s = socket.socket(socket.AF_UNIX, kind)
    print(f"ESCAPED: socket(AF_UNIX, {kind!r}) was allowed")
    s.settimeout(0.5)
    for path in paths:
        try:
            s.connect(path)
            print(f"ESCAPED: connected to {path!r} ({kind!r})")
            s.close()
            s = socket.socket(socket.AF_UNIX, kind)
            s.settimeout(0.5)
        except OSError as e:
            print(f"BLOCKED: connect {path!r}: {e!r}")
    s.close()
