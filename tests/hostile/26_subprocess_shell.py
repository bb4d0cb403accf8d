"""Spawn /bin/sh and python via subprocess (the child prints ESCAPED); contained = killed, or subprocess raises."""
import subprocess
import sys

for argv in (["/bin/sh", "-c", "echo 'ESCAPED: subprocess ran /bin/sh'"],
             [sys.executable, "-c", "print('ESCAPED: subprocess ran python')"]):
    try:
        subprocess.run(argv, timeout=10, check=True)
    except (OSError, subprocess.SubprocessError) as e:
        print(f"BLOCKED: {argv[0]}: {e!r}")
sys.exit(1)
