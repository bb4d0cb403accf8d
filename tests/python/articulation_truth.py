"""Ground truth for the articulated-part helpers (robo_perception.articulation): gyms whose
door or drawer starts at another value, and the value the simulator had when an observation was
taken (never used by `robo` or the helpers).

`scene_with_joint` writes a copy of a gym's scene.toml with its jointed fixture's `initial`
changed (the scene format's own field: degrees for hinges, metres for slides; seeds and
`--perturb` move free objects only, never fixtures), its relative paths made absolute so that the
copy can live anywhere. `SceneGym` runs `r2g up <that file> --mode lockstep --trace-dir` and
stops it by its pid; `joint_at` reads the fixture's joint from the native trace at a simulated
time.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path
from typing import Optional

from render_truth import LiveGym

ROOT = Path(__file__).resolve().parents[2]
R2G = Path(os.environ.get("R2G_BIN", str(ROOT / "target" / "release" / "r2g")))
GYMS_DIR = Path(os.environ.get("R2G_GYMS", str(ROOT / "gyms")))


def scene_with_joint(gym: str, initial: float, out_dir: Path, name: Optional[str] = None) -> Path:
    """A copy of gyms/<gym>/scene.toml whose jointed fixture starts at `initial` (deg or m), in
    `out_dir`/<name>/scene.toml. The scene keeps its `name` (so the setup report and the
    evaluator's file say the gym it is)."""
    src_dir = GYMS_DIR / gym
    text = (src_dir / "scene.toml").read_text()
    text, n = re.subn(r"(?m)^initial\s*=\s*[-+0-9.eE]+", f"initial = {float(initial)!r}", text)
    if n != 1:
        raise ValueError(f"{gym}: expected one jointed fixture with `initial`, found {n}")

    def absolute(m: re.Match) -> str:
        return f'{m.group(1)} = "{(src_dir / m.group(2)).resolve()}"'
    text = re.sub(r'(?m)^(urdf|demonstration)\s*=\s*"([^"/][^"]*)"', absolute, text)
    if re.search(r'mesh\s*=\s*"[^"/]', text):
        raise ValueError(f"{gym}: relative mesh paths are not rewritten here")
    d = Path(out_dir) / (name or f"{gym}_at_{initial:g}")
    d.mkdir(parents=True, exist_ok=True)
    (d / "scene.toml").write_text(text)
    return d / "scene.toml"


class SceneGym(LiveGym):
    """`r2g up <scene file> --mode lockstep --trace-dir DIR` (render_truth's LiveGym from a scene
    file), ready when constructed."""

    def __init__(self, scene: Path, trace_dir: Path, tag: str = "art", ready_s: float = 120.0) -> None:
        Path(trace_dir).mkdir(parents=True, exist_ok=True)
        super().__init__(R2G, GYMS_DIR, str(int(time.time() * 1000) % 100000), trace_dir=Path(trace_dir), tag=tag,
                         scene=Path(scene))
        if not self.ready.wait(ready_s):
            self.stop()
            raise RuntimeError(f"r2g up {scene} did not print READY within {ready_s} s")

    def last(self, kind: str) -> dict:
        """The newest episode-N.<kind>.json (kind "trace" or "eval")."""
        assert self.trace_dir is not None
        files = sorted(self.trace_dir.glob(f"episode-*.{kind}.json"), key=lambda p: int(p.name.split("-")[1].split(".")[0]))
        if not files:
            raise FileNotFoundError(f"no episode-*.{kind}.json in {self.trace_dir}")
        return json.loads(files[-1].read_text())


def joint_at(trace: dict, t: float, fixture: Optional[str] = None) -> float:
    """The fixture joint (deg for a hinge, m for a slide) in the trace sample nearest simulated
    time `t` (s); the first jointed fixture unless `fixture` names one."""
    i = 0 if fixture is None else trace["joints"].index(fixture)
    s = min(trace["samples"], key=lambda x: abs(x["t_s"] - t))
    return float(s["joints"][i])
