#!/usr/bin/env python3
"""The force felt during a chunk, as control_feedback["contact"] reports it, for the three cases
of tests/python/test_contact_feedback.py, printed whole: a free move and a push of
push_to_line's 60 g block with the closed fingers, and a press of the closed fingers 8 mm into
close_cabinet's fixed carcass top. Live lockstep instances (started and stopped here).

    .venv/bin/python bench/py/contact_during_chunk.py

Why the push reads several newtons where sliding the block takes about 0.5 N: see the docstring
of tests/python/test_contact_feedback.py (the fingers' friction presses the block into the table).

Prints one line per case, then one JSON object.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "python"))
from conftest import _instance  # noqa: E402
from test_contact_feedback import move  # noqa: E402

import robo  # noqa: E402


def run(gym: str, tag: str, steps: list[tuple[str, list[float]]]) -> dict:
    out = {}
    inst = _instance("lockstep", tag, gym=gym)
    next(inst)
    try:
        robo.reset()
        for name, goal in steps:
            fb = move(goal, 1.0)
            out[name] = {k: fb[k] for k in ("status", "reason", "executed", "contact")}
        out[f"external_force_n after the last ({gym})"] = robo.get_state([])["external_force_n"]
    finally:
        next(inst, None)
    return out


def main() -> int:
    cases = {}
    cases.update(run("push_to_line", "cd1", [("free move", [0.36, -0.05, 0.30]), ("to the block", [0.36, -0.05, 0.025]),
                                              ("push the 60 g block 8 cm", [0.44, -0.05, 0.025])]))
    cases.update(run("close_cabinet", "cd2", [("over the cabinet", [0.72, -0.10, 0.35]),
                                               ("press 8 mm into the fixed top", [0.72, -0.10, 0.292])]))
    for name, v in cases.items():
        print(f"{name}: {json.dumps(v)}")
    print(json.dumps(cases))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
