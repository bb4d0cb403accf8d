"""Read /etc/shadow (password hashes); contained = PermissionError/absent, the program exits nonzero."""
import sys

for path in ("/etc/shadow", "/etc/gshadow", "/etc/sudoers"):
    try:
        with open(path, "rb") as f:
            data = f.read(4096)
        print(f"ESCAPED: read {len(data)} bytes of {path}")
    except OSError as e:
        print(f"BLOCKED: {path}: {e!r}")
sys.exit(1)
