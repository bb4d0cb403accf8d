"""Read the gyms' privileged scene files (object poses, success criteria); contained = every open fails."""
import sys
from pathlib import Path

# Where the project may live: the usual checkout, the venv's parent, and this file's repository.
roots = {Path("/work/main"), Path(sys.prefix).parent}
here = Path(__file__).resolve()
if len(here.parents) > 2:
    roots.add(here.parents[2])

GYMS = ["close_cabinet", "hang_mug", "microwave_cup", "open_drawer",
        "pick_block_plate", "push_to_line", "shelf_plate", "stack_bowls"]
FILES = ["scene.toml", "keyframes.toml", "demo.csv"]

for root in sorted(roots):
    try:  # a directory listing would also reveal the gym set
        print(f"ESCAPED: listed {root}/gyms: {sorted(p.name for p in (root / 'gyms').iterdir())}")
    except OSError as e:
        print(f"BLOCKED: listdir {root}/gyms: {e!r}")
    for gym in GYMS:
        for name in FILES:
            path = root / "gyms" / gym / name
            try:
                data = path.read_bytes()
                print(f"ESCAPED: read {len(data)} bytes of {path}")
            except OSError as e:
                print(f"BLOCKED: {path}: {type(e).__name__} errno={e.errno}")
sys.exit(1)
