"""Read the parent's /proc/<ppid>/environ, cmdline and memory maps (API keys, paths); contained = every open fails."""
import os
import sys

ppid = os.getppid()
for name in ("environ", "cmdline", "maps", "status", "cwd", "root"):
    path = f"/proc/{ppid}/{name}"
    try:
        if name in ("cwd", "root"):
            print(f"ESCAPED: listed {path}: {os.listdir(path)[:10]}")
            continue
        with open(path, "rb") as f:
            data = f.read(65536)
        secret = any(k in data for k in (b"API_KEY", b"TOKEN", b"SECRET", b"sk-"))
        print(f"ESCAPED: read {len(data)} bytes of {path}" + (" (contains a secret)" if secret else ""))
    except OSError as e:
        print(f"BLOCKED: {path}: {e!r}")
sys.exit(1)
