"""Copies what the wheel's environments load into r2g_gym/data/ (the gym pack, the Panda
description and the meshes it draws, with their licences), or removes that copy again.

    python gym-env/bundle.py add | remove
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "gym-env" / "python" / "r2g_gym" / "data"
MESHES = "packages/example-robot-data/robots/panda_description/meshes/visual"
PARTS = [
    ("gyms", "gyms"),
    ("robots/panda", "robots/panda"),
    (f"robots/{MESHES}", f"robots/{MESHES}"),
    ("robots/packages/example-robot-data/licenses", "robots/packages/example-robot-data/licenses"),
]


def add() -> None:
    remove()
    for src, dst in PARTS:
        s = ROOT / src
        if not s.is_dir():
            raise SystemExit(f"bundle: {s} is missing (make venv unpacks the robot meshes)")
        shutil.copytree(s, DATA / dst, ignore=shutil.ignore_patterns("*.py", "__pycache__", "*.png"))


def remove() -> None:
    if DATA.exists():
        shutil.rmtree(DATA)


if __name__ == "__main__":
    {"add": add, "remove": remove}[sys.argv[1] if len(sys.argv) > 1 else "add"]()
