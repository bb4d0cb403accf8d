"""Read the real home's dotfiles and keys (/root/.bashrc, ~/.ssh, cloud credentials); contained = every open fails."""
import sys

PATHS = [
    "/root/.bashrc",
    "/root/.profile",
    "/root/.ssh/id_rsa",
    "/root/.ssh/id_ed25519",
    "/root/.ssh/authorized_keys",
    "/root/.aws/credentials",
    "/root/.config/gh/hosts.yml",
    "/root/.netrc",
    "/root/.gitconfig",
]
for path in PATHS:
    try:
        with open(path, "rb") as f:
            data = f.read(4096)
        print(f"ESCAPED: read {len(data)} bytes of {path}")
    except OSError as e:
        print(f"BLOCKED: {path}: {e!r}")
sys.exit(1)
