"""Create raw IP, packet, ICMP, netlink, AF_ALG and vsock sockets (no traffic sent); contained = the first socket() is killed or refused."""
import socket

KINDS = [
    ("AF_INET/SOCK_RAW/ICMP", socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_ICMP),
    ("AF_PACKET/SOCK_RAW", getattr(socket, "AF_PACKET", 17), socket.SOCK_RAW, socket.htons(0x0003)),
    ("AF_INET/SOCK_DGRAM/ICMP (ping)", socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_ICMP),
    ("AF_NETLINK/ROUTE", getattr(socket, "AF_NETLINK", 16), socket.SOCK_RAW, 0),
    ("AF_ALG", getattr(socket, "AF_ALG", 38), socket.SOCK_SEQPACKET, 0),
    ("AF_VSOCK", getattr(socket, "AF_VSOCK", 40), socket.SOCK_STREAM, 0),
]
created = []
for name, family, kind, proto in KINDS:
    try:
        s = socket.socket(family, kind, proto)
        created.append(name)
        print(f"ESCAPED: created a {name} socket")
        s.close()
    except OSError as e:
        print(f"BLOCKED: {name}: {e!r}")
if not created:
    raise SystemExit("BLOCKED: no socket of any family could be created")
