"""Create a new file in the project tree (repository root, robot-skill/memory, tests/hostile); contained = every create fails."""
import sys
from pathlib import Path

roots = {Path("/work/main"), Path(sys.prefix).parent}
targets = []
for root in sorted(roots):
    targets += [root / "r2g-hostile-canary-project",
                root / "robot-skill" / "memory" / "r2g-hostile-canary-project",
                root / "tests" / "hostile" / "r2g-hostile-canary-project"]
for path in targets:
    try:
        with open(path, "x") as f:
            f.write("written by tests/hostile/11_write_project_tree.py\n")
        print(f"ESCAPED: created {path}")
    except FileExistsError:
        print(f"ESCAPED?: {path} already exists (left by an earlier broken run?)")
    except OSError as e:
        print(f"BLOCKED: {path}: {e!r}")
sys.exit(1)
