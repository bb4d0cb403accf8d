"""Keep opening scratch files until 100000 descriptors are held; contained = EMFILE at the open-files rlimit."""
held = []
try:
    while len(held) < 100000:
        held.append(open(f"fd_{len(held)}", "w"))
except OSError as e:
    print(f"BLOCKED: open number {len(held) + 1} failed: {e!r}")
    raise
print(f"ESCAPED: holding {len(held)} open files, no open-files limit")
