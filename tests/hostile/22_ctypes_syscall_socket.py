"""Call socket(AF_INET) and socket(AF_UNIX) through ctypes libc.syscall, bypassing the socket module; contained = killed or refused by seccomp."""
import ctypes
import os
import platform

SYS_SOCKET = {"x86_64": 41, "aarch64": 198}[platform.machine()]
libc = ctypes.CDLL(None, use_errno=True)
libc.syscall.restype = ctypes.c_long
for family, name in ((2, "AF_INET"), (1, "AF_UNIX"), (10, "AF_INET6")):
    fd = libc.syscall(ctypes.c_long(SYS_SOCKET), ctypes.c_long(family), ctypes.c_long(1), ctypes.c_long(0))
    if fd >= 0:
        print(f"ESCAPED: raw syscall socket({name}, SOCK_STREAM) returned fd {fd}")
        os.close(fd)
    else:
        err = ctypes.get_errno()
        print(f"BLOCKED: raw syscall socket({name}): errno {err} ({os.strerror(err)})")
raise SystemExit(1)
