"""personality() via ctypes to turn off ASLR / make reads imply exec; contained = killed or refused by seccomp, persona unchanged."""
import ctypes
import os
import sys

ADDR_NO_RANDOMIZE, READ_IMPLIES_EXEC, QUERY = 0x0040000, 0x0400000, 0xFFFFFFFF
libc = ctypes.CDLL(None, use_errno=True)
libc.personality.restype = ctypes.c_int
libc.personality.argtypes = [ctypes.c_ulong]
before = libc.personality(QUERY)
r = libc.personality((before & 0xFFFFFFFF) | ADDR_NO_RANDOMIZE | READ_IMPLIES_EXEC)
err = ctypes.get_errno()
after = libc.personality(QUERY)
if after != -1 and after & (ADDR_NO_RANDOMIZE | READ_IMPLIES_EXEC):
    print(f"ESCAPED: personality changed from {before:#x} to {after:#x}")
    sys.exit(0)
sys.exit(f"BLOCKED: personality set returned {r} errno {err} ({os.strerror(err)}); persona {after:#x}")
