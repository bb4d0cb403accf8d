"""Create a file in scratch and rename/move it outside (/tmp canary); contained = rename fails (EACCES/EXDEV)."""
import os
import shutil
import sys

with open("payload.txt", "w") as f:
    f.write("moved out of scratch by tests/hostile/15_rename_out_of_scratch.py\n")
try:
    os.rename("payload.txt", "/tmp/r2g-hostile-canary-rename")
    print("ESCAPED: os.rename moved a scratch file to /tmp/r2g-hostile-canary-rename")
except OSError as e:
    print(f"BLOCKED: rename: {e!r}")
try:  # shutil.move falls back to copy + unlink on EXDEV
    shutil.move("payload.txt", "/tmp/r2g-hostile-canary-rename")
    print("ESCAPED: shutil.move put a scratch file at /tmp/r2g-hostile-canary-rename")
except OSError as e:
    print(f"BLOCKED: shutil.move: {e!r}")
sys.exit(1)
