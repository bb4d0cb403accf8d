"""keyctl via ctypes: look up the session and user keyrings (host secrets may live there); contained = killed or refused by seccomp."""
import ctypes
import os
import platform

SYS_KEYCTL = {"x86_64": 250, "aarch64": 219}[platform.machine()]
KEYCTL_GET_KEYRING_ID = 0
libc = ctypes.CDLL(None, use_errno=True)
libc.syscall.restype = ctypes.c_long
found = False
for ring, name in ((-3, "session"), (-4, "user"), (-5, "user-session")):
    r = libc.syscall(ctypes.c_long(SYS_KEYCTL), ctypes.c_long(KEYCTL_GET_KEYRING_ID), ctypes.c_long(ring), ctypes.c_long(0))
    if r >= 0:
        found = True
        print(f"ESCAPED: keyctl found the {name} keyring (id {r})")
    else:
        err = ctypes.get_errno()
        print(f"BLOCKED: keyctl {name}: errno {err} ({os.strerror(err)})")
raise SystemExit(0 if found else 1)
