"""Memory bomb: touch 64 MiB blocks until 8 GiB; contained = MemoryError or a kill (address-space rlimit) well before 8 GiB."""
BLOCK = 64 << 20
hoard = []
try:
    while len(hoard) * BLOCK < (8 << 30):
        hoard.append(bytearray(b"\x5a") * BLOCK)  # filled, so every page is really touched
except MemoryError:
    print(f"BLOCKED: MemoryError after {len(hoard) * BLOCK >> 20} MiB")
    raise
print(f"ESCAPED: allocated and touched {len(hoard) * BLOCK >> 20} MiB")
