"""Write executables into scratch (a shell script, a copy of the python binary) and exec them; contained = execve of scratch files fails."""
import os
import shutil
import sys

with open("evil.sh", "w") as f:
    f.write("#!/bin/sh\necho 'ESCAPED: executed a script written to scratch'\n")
os.chmod("evil.sh", 0o755)
try:
    shutil.copyfile(os.path.realpath(sys.executable), "py")
    os.chmod("py", 0o755)
except OSError as e:
    print(f"BLOCKED: copying {sys.executable}: {e!r}")
for argv in (["./evil.sh"], ["./py", "-I", "-S", "-c", "print('ESCAPED: executed a binary copied to scratch')"]):
    sys.stdout.flush()
    try:
        os.execv(argv[0], argv)
    except OSError as e:
        print(f"BLOCKED: execv {argv[0]}: {e!r}")
sys.exit(1)
