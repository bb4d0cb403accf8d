"""unshare(CLONE_NEWUSER|CLONE_NEWNS) and mount a tmpfs via ctypes (only ever on a scratch subfolder); contained = killed or refused by seccomp."""
import ctypes
import os
import sys

CLONE_NEWNS, CLONE_NEWUSER, MNT_DETACH = 0x00020000, 0x10000000, 2
libc = ctypes.CDLL(None, use_errno=True)
os.mkdir("mnt")
target = os.path.abspath("mnt").encode()
if libc.unshare(CLONE_NEWUSER | CLONE_NEWNS) == 0:
    print("ESCAPED: unshare created a new user and mount namespace")
else:
    err = ctypes.get_errno()
    print(f"BLOCKED: unshare: errno {err} ({os.strerror(err)})")
if libc.mount(b"none", target, b"tmpfs", 0, None) == 0:
    print(f"ESCAPED: mounted a tmpfs on {target.decode()}")
    libc.umount2(target, MNT_DETACH)
    sys.exit(0)
err = ctypes.get_errno()
sys.exit(f"BLOCKED: mount: errno {err} ({os.strerror(err)})")
