"""Plant symlinks in scratch pointing outside (read /etc/shadow, write a /tmp canary through the link); contained = opens through the links fail."""
import os
import sys

links = {"shadow_link": "/etc/shadow", "canary_link": "/tmp/r2g-hostile-canary-symlink",
         "root_link": "/", "proc_parent": f"/proc/{os.getppid()}/environ"}
for name, target in links.items():
    try:
        os.symlink(target, name)
    except OSError as e:
        print(f"BLOCKED: symlink {name} -> {target}: {e!r}")
for name, mode in (("shadow_link", "rb"), ("proc_parent", "rb"), ("canary_link", "w")):
    try:
        with open(name, mode) as f:
            if "w" in mode:
                f.write("written through a symlink by tests/hostile/13_symlink_escape.py\n")
            else:
                f.read(64)
        print(f"ESCAPED: opened {name} -> {links[name]} with mode {mode}")
    except OSError as e:
        print(f"BLOCKED: open {name} ({mode}): {e!r}")
try:
    print(f"ESCAPED: listed / through root_link: {sorted(os.listdir('root_link'))[:8]}")
except OSError as e:
    print(f"BLOCKED: listdir root_link: {e!r}")
sys.exit(1)
