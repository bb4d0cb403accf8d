"""Read the parent's memory with process_vm_readv (read only, never writev); contained = killed or refused; EFAULT would mean access was granted."""
import ctypes
import errno
import os
import sys


class IoVec(ctypes.Structure):
    _fields_ = [("base", ctypes.c_void_p), ("len", ctypes.c_size_t)]


libc = ctypes.CDLL(None, use_errno=True)
libc.process_vm_readv.restype = ctypes.c_ssize_t
libc.process_vm_readv.argtypes = [ctypes.c_int, ctypes.POINTER(IoVec), ctypes.c_ulong,
                                  ctypes.POINTER(IoVec), ctypes.c_ulong, ctypes.c_ulong]
ppid = os.getppid()
if ppid <= 1:
    sys.exit(f"BLOCKED: parent pid is {ppid}; pid 1 is never targeted")
buf = ctypes.create_string_buffer(64)
local = IoVec(ctypes.addressof(buf), 64)
# Any address will do: EFAULT already means the access check on the parent passed.
remote = IoVec(ctypes.cast(libc.printf, ctypes.c_void_p).value, 64)
n = libc.process_vm_readv(ppid, ctypes.byref(local), 1, ctypes.byref(remote), 1, 0)
err = ctypes.get_errno()
if n >= 0 or err == errno.EFAULT:
    print(f"ESCAPED: process_vm_readv on parent {ppid} permitted (returned {n}, errno {err})")
    sys.exit(0)
sys.exit(f"BLOCKED: process_vm_readv({ppid}): errno {err} ({os.strerror(err)})")
