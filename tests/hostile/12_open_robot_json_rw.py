"""Open robot-skill/config/robot.json (the safety caps; in the checkout and the copy the program is shown) for writing, without writing a byte; contained = every open fails."""
import os
import sys
from pathlib import Path

roots = {Path("/work/main"), Path(sys.prefix).parent, Path(".")}  # "." : the scratch folder's read-only view
for root in sorted(roots):
    path = root / "robot-skill" / "config" / "robot.json"
    try:
        print(f"INFO: {path} readable, {len(path.read_bytes())} bytes")
    except OSError as e:
        print(f"INFO: {path} not readable: {e!r}")
    for flags, what in ((os.O_WRONLY | os.O_APPEND, "O_WRONLY|O_APPEND"), (os.O_RDWR, "O_RDWR")):
        try:
            fd = os.open(path, flags)  # no O_TRUNC, nothing written: the file stays intact
            os.close(fd)
            print(f"ESCAPED: opened {path} with {what}")
        except OSError as e:
            print(f"BLOCKED: open {path} {what}: {e!r}")
sys.exit(1)
