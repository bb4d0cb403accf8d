"""perf_event_open on ourselves via ctypes (perf is kernel attack surface and a side channel); contained = killed or refused by seccomp."""
import ctypes
import os
import platform
import struct

SYS_PERF_EVENT_OPEN = {"x86_64": 298, "aarch64": 241}[platform.machine()]
libc = ctypes.CDLL(None, use_errno=True)
libc.syscall.restype = ctypes.c_long
attr = ctypes.create_string_buffer(struct.pack("IIQ", 1, 64, 0), 128)  # SOFTWARE, size VER0, CPU_CLOCK
fd = libc.syscall(ctypes.c_long(SYS_PERF_EVENT_OPEN), attr, ctypes.c_long(0), ctypes.c_long(-1),
                  ctypes.c_long(-1), ctypes.c_long(0))
if fd >= 0:
    print(f"ESCAPED: perf_event_open returned fd {fd}")
    os.close(fd)
else:
    err = ctypes.get_errno()
    raise SystemExit(f"BLOCKED: perf_event_open: errno {err} ({os.strerror(err)})")
