"""Allocate System V shared memory through ctypes (it would outlive the worker and escape its memory limit); contained = the call is a forbidden syscall (killed)."""
import ctypes

libc = ctypes.CDLL(None, use_errno=True)
IPC_PRIVATE, IPC_CREAT = 0, 0o1000
shmid = libc.shmget(IPC_PRIVATE, 64 << 20, IPC_CREAT | 0o600)
if shmid >= 0:
    print(f"ESCAPED: shmget gave segment {shmid}")
    libc.shmctl(shmid, 0, None)  # IPC_RMID: do not leave it behind
raise SystemExit(f"BLOCKED: shmget errno {ctypes.get_errno()}")
