"""Call io_uring_setup through ctypes (io_uring ops bypass seccomp's per-syscall checks); contained = killed or refused by seccomp."""
import ctypes
import os

SYS_IO_URING_SETUP = 425  # same number on x86_64 and aarch64
libc = ctypes.CDLL(None, use_errno=True)
libc.syscall.restype = ctypes.c_long
params = ctypes.create_string_buffer(120)  # struct io_uring_params, zeroed
fd = libc.syscall(ctypes.c_long(SYS_IO_URING_SETUP), ctypes.c_long(8), params)
if fd >= 0:
    print(f"ESCAPED: io_uring_setup returned ring fd {fd}")
    os.close(fd)
else:
    err = ctypes.get_errno()
    raise SystemExit(f"BLOCKED: io_uring_setup: errno {err} ({os.strerror(err)})")
