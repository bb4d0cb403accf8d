"""Create files and a directory outside scratch (/tmp canary, scratch's parent); contained = every create fails."""
import os
import sys

attempts = [
    ("open", "/tmp/r2g-hostile-canary-write"),
    ("open", "../r2g-hostile-canary-dotdot"),
    ("open", "/var/tmp/r2g-hostile-canary-write"),
    ("mkdir", "/tmp/r2g-hostile-canary-mkdir"),
]
for op, path in attempts:
    try:
        if op == "mkdir":
            os.mkdir(path)
        else:
            with open(path, "w") as f:
                f.write("written by tests/hostile/10_write_tmp_canary.py\n")
        print(f"ESCAPED: {op} {path} outside scratch succeeded")
    except OSError as e:
        print(f"BLOCKED: {op} {path}: {e!r}")
sys.exit(1)
