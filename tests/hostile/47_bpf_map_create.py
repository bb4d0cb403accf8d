"""bpf(BPF_MAP_CREATE) via ctypes (eBPF is kernel attack surface); contained = killed or refused by seccomp."""
import ctypes
import os
import platform
import struct

SYS_BPF = {"x86_64": 321, "aarch64": 280}[platform.machine()]
libc = ctypes.CDLL(None, use_errno=True)
libc.syscall.restype = ctypes.c_long
attr = ctypes.create_string_buffer(struct.pack("IIII", 2, 4, 4, 1), 72)  # ARRAY map, key 4, value 4, 1 entry
fd = libc.syscall(ctypes.c_long(SYS_BPF), ctypes.c_long(0), attr, ctypes.c_long(72))
if fd >= 0:
    print(f"ESCAPED: bpf(BPF_MAP_CREATE) returned fd {fd}")
    os.close(fd)
else:
    err = ctypes.get_errno()
    raise SystemExit(f"BLOCKED: bpf: errno {err} ({os.strerror(err)})")
