"""Hard-link outside files into scratch (/etc/shadow, robot.json) and open the links; contained = link() or the open fails."""
import os
import sys
from pathlib import Path

sources = ["/etc/shadow", "/etc/passwd"]
sources += [str(r / "robot-skill" / "config" / "robot.json") for r in sorted({Path("/work/main"), Path(sys.prefix).parent})]
for i, src in enumerate(sources):
    name = f"hardlink_{i}"
    try:
        os.link(src, name)
    except OSError as e:
        print(f"BLOCKED: link {src} -> {name}: {e!r}")
        continue
    print(f"ESCAPED: hard-linked {src} into scratch as {name}")
    try:
        fd = os.open(name, os.O_WRONLY | os.O_APPEND)  # nothing is written
        os.close(fd)
        print(f"ESCAPED: {name} (= {src}) is writable through the link")
    except OSError as e:
        print(f"BLOCKED: open {name} for writing: {e!r}")
sys.exit(1)
