"""Spawn a shell with os.system (the shell itself prints ESCAPED and touches a /tmp canary); contained = killed, or os.system fails."""
import os
import sys

rc = os.system("echo 'ESCAPED: os.system ran /bin/sh'; id; touch /tmp/r2g-hostile-canary-system")
sys.exit(f"BLOCKED: os.system returned {rc}" if rc else 0)
