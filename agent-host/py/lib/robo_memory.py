"""Memory records for stage programs, exactly as robot-skill/memory/README.md defines them: the
fingerprint of the setup, the records that match it (invalidated ones left out), and writing a new
record. Standard library and `robo` only.

    import robo_memory
    fp = robo_memory.fingerprint()            # {"gym": ..., "robot_config_sha256": ..., "backend": ...}
    for r in robo_memory.records():           # this setup's valid records, newest first
        print(r["file"], r["kind"], r["stage"], r["content"])
    robo_memory.write("warmup", "warmup", {"outcome": "success", "measured": {...}}, task="...")
"""
from __future__ import annotations

import datetime
import json
import os
import uuid
from typing import Any, Optional

KINDS = ("observation", "warmup", "action", "outcome", "invalidation")
"""The record kinds."""
SHARED = os.path.join("robot-skill", "memory")
"""The memory folder as the host keeps it (read-only in a stage program's scratch folder)."""
OWN = "memory"
"""Where a program writes new records (the host appends new files there to the memory folder)."""


def fingerprint(state: Optional[dict] = None) -> dict:
    """The setup's fingerprint: the gym and the robot configuration in force as the runtime reports
    them (``get_state()["setup"]``), and the backend. ``state``: a get_state() result (default: a
    fresh numeric one)."""
    if state is None:
        from robo import get_state

        state = get_state([])
    setup = state.get("setup") or {}
    return {"gym": setup.get("gym"), "robot_config_sha256": setup.get("robot_config_sha256"),
            "backend": state.get("backend")}


def _read(folder: str) -> dict[str, dict]:
    out: dict[str, dict] = {}
    try:
        names = os.listdir(folder)
    except OSError:
        return out
    for name in names:
        if not (name[:1].isdigit() and name.endswith(".json")):
            continue  # the README, .md records (front matter: not parsed here) and anything else
        try:
            with open(os.path.join(folder, name), encoding="utf-8") as f:
                record = json.load(f)
        except (OSError, ValueError):
            continue
        if isinstance(record, dict):
            out[name] = dict(record, file=name)
    return out


def records(fingerprint_: Optional[dict] = None, folders: Optional[list[str]] = None,
            include_invalidated: bool = False) -> list[dict]:
    """The JSON records of ``folders`` (default: robot-skill/memory and this program's memory/) whose
    ``fingerprint`` equals ``fingerprint_`` (default: this setup's; pass ``{}`` for every record),
    newest first, each with its file name under ``"file"``; records an ``invalidation`` record
    names are left out unless ``include_invalidated``."""
    seen: dict[str, dict] = {}
    for folder in folders or [SHARED, OWN]:
        seen.update(_read(folder))
    invalidated = {str((r.get("content") or {}).get("invalidates")) for r in seen.values()
                   if r.get("kind") == "invalidation" and isinstance(r.get("content"), dict)}
    want = fingerprint() if fingerprint_ is None else fingerprint_
    out = [r for r in seen.values() if (not want or r.get("fingerprint") == want)
           and (include_invalidated or r["file"] not in invalidated)]
    return sorted(out, key=lambda r: r["file"], reverse=True)


def write(kind: str, stage: str, content: Any, task: str = "", state: Optional[dict] = None) -> str:
    """Writes one new record to memory/ (never overwriting one) and returns its file name.
    ValueError for an unknown kind or content that is not JSON."""
    if kind not in KINDS:
        raise ValueError(f"kind {kind!r} is not one of {', '.join(KINDS)}")
    record = {"kind": kind, "fingerprint": fingerprint(state), "task": task, "stage": stage, "content": content}
    try:
        text = json.dumps(record, indent=2, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"a memory record must be plain JSON (no NaN, no numpy types): {e}") from None
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    name = f"{stamp}-{uuid.uuid4()}.json"
    os.makedirs(OWN, exist_ok=True)
    with open(os.path.join(OWN, name), "x", encoding="utf-8") as f:
        f.write(text)
    return name
