"""How well `robo_perception.measure_hinged` reads a door's angle, against the simulator's joint.

For each door angle of the sweep, `close_cabinet` is started from a copy of its scene whose door
starts at that angle (the scene's own `initial` field; tests/python/articulation_truth.py), the
robot at its start pose observes both cameras raw, and the door is measured:

* ``fused``: `measure_hinged(state)` with both cameras, no reference (what a program calls first);
* ``agentview``: the agentview camera alone, no reference;
* ``wrist+ref``: the wrist camera alone, with ``reference=`` a measurement taken (both cameras) of
  the shipped scene, whose door stands at 85 deg: the hinge and shut frame from there, the angle
  from the wrist image alone;
* ``fused+ref``: both cameras, with that reference (the estimator the door example uses after
  its first look).

The truth is the door's joint in the native trace at the observation's simulated time. A reading
that is None or NaN (nothing measured) is counted apart, not as an error. With ``--push`` it also
runs robot-skill/examples/close_door.py in this process on the shipped scene and compares every
measurement the example takes (the hand beside and in front of the door) with the trace.

Usage: door_angle_sweep.py [--angles 0,5,...,100] [--push] [--json FILE]
(R2G_BIN: the r2g binary.) Prints a table per method, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT / "tests" / "python"), str(ROOT / "agent-host" / "py" / "lib"),
                str(ROOT / "robot-skill" / "examples")]
import articulation_truth as at  # noqa: E402
import robo_perception as rp  # noqa: E402

METHODS = ("fused", "agentview", "wrist+ref", "fused+ref")


def measure_all(obs: dict, reference) -> dict:
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rp.PerceptionWarning)
        fused = rp.segment_scene(obs, tracker=None)
        agent = rp.segment_scene(obs, ["agentview"], tracker=None)
        wrist = rp.segment_scene(obs, ["wrist"], tracker=None)
        t0 = time.perf_counter()
        m = rp.measure_hinged(fused)
        out["fused_ms"] = (time.perf_counter() - t0) * 1e3
        out["fused"] = m
        out["agentview"] = rp.measure_hinged(agent)
        out["wrist+ref"] = rp.measure_hinged(wrist, reference=reference) if reference is not None else None
        out["fused+ref"] = rp.measure_hinged(fused, reference=reference) if reference is not None else None
    return out


def angle_of(m) -> float:
    return float("nan") if m is None else float(m.angle_deg)


def sweep(angles: list[float], tmp: Path) -> tuple[list[dict], object]:
    # the reference: the shipped scene (door at 85 deg), both cameras
    g = at.SceneGym(at.GYMS_DIR / "close_cabinet" / "scene.toml", tmp / "ref-trace", tag="dsw")
    try:
        obs = g.observe()
    finally:
        g.stop()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rp.PerceptionWarning)
        reference = rp.measure_hinged(obs)
    truth_ref = at.joint_at(g.last("trace"), obs["timestamp"])
    print(f"reference: {reference.describe() if reference else None} (truth {truth_ref:.2f} deg)")
    rows = []
    for a in angles:
        scene = at.scene_with_joint("close_cabinet", a, tmp / "scenes")
        g = at.SceneGym(scene, tmp / f"trace-{a:g}", tag="dsw")
        try:
            obs = g.observe()
        finally:
            g.stop()
        truth = at.joint_at(g.last("trace"), obs["timestamp"])
        ms = measure_all(obs, reference)
        row = {"initial_deg": a, "truth_deg": truth, "measure_ms": ms["fused_ms"]}
        for k in METHODS:
            row[k] = angle_of(ms[k])
        f = ms["fused"]
        if f is not None:
            row["hinge_xy"] = [round(float(v), 4) for v in f.hinge_point[:2]]
            row["hinge_axis"] = [round(float(v), 3) for v in f.hinge_axis]
            row["outward_normal"] = [round(float(v), 3) for v in f.outward_normal]
        rows.append(row)
        print(f"{a:6.1f} truth {truth:7.2f}  " + "  ".join(f"{k} {row[k]:7.2f}" for k in METHODS)
              + f"  ({row['measure_ms']:.0f} ms)")
    return rows, reference


def push(tmp: Path) -> list[dict]:
    """The door example on the shipped scene; every measurement it takes against the trace."""
    import close_door as cd
    from robo import get_state
    seen = []
    original = cd.measure

    def recording(prompt, reference=None):
        t = get_state([])["timestamp"]
        tcp = get_state([])["ee_pose"][:3]
        m = original(prompt, reference)
        seen.append({"t_s": t, "tcp": [round(float(v), 3) for v in tcp], "measured_deg": angle_of(m),
                     "with_reference": reference is not None})
        return m

    cd.measure = recording
    g = at.SceneGym(at.GYMS_DIR / "close_cabinet" / "scene.toml", tmp / "push-trace", tag="dpush")
    try:
        g.use()
        result = cd.close_door()
    finally:
        cd.measure = original
        g.stop()
    trace = g.last("trace")
    verdict = g.last("eval")
    for s in seen:
        s["truth_deg"] = at.joint_at(trace, s["t_s"])
    print(f"close_door: RESULT closed={result['closed']}, native verdict success={verdict['success']}")
    for s in seen:
        print(f"  t {s['t_s']:6.2f} s tcp {s['tcp']} truth {s['truth_deg']:7.2f} measured {s['measured_deg']:7.2f}"
              + (" (reference)" if s["with_reference"] else ""))
    return seen


def stats(errors: list[float]) -> dict:
    e = [abs(x) for x in errors if math.isfinite(x)]
    return {"n": len(e), "mean_abs_deg": round(sum(e) / len(e), 3) if e else None,
            "max_abs_deg": round(max(e), 3) if e else None}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--angles", default=",".join(str(a) for a in range(0, 101, 5)))
    ap.add_argument("--push", action="store_true", help="also run examples/close_door.py and score its measurements")
    ap.add_argument("--json", help="write the result here too")
    a = ap.parse_args()
    angles = [float(x) for x in a.angles.split(",") if x.strip()]
    with tempfile.TemporaryDirectory(prefix="door-sweep-") as td:
        rows, _ = sweep(angles, Path(td))
        pushes = push(Path(td)) if a.push else []
    summary = {}
    print("\nmethod      n  missing  mean |err| deg  max |err| deg")
    for k in METHODS:
        errs = [r[k] - r["truth_deg"] for r in rows]
        s = stats(errs)
        s["missing"] = sum(1 for r in rows if not math.isfinite(r[k]))
        summary[k] = s
        print(f"{k:10s} {s['n']:2d}  {s['missing']:7d}  {s['mean_abs_deg']!s:>14}  {s['max_abs_deg']!s:>13}")
    if pushes:
        s = stats([p["measured_deg"] - p["truth_deg"] for p in pushes])
        s["missing"] = sum(1 for p in pushes if not math.isfinite(p["measured_deg"]))
        summary["during_push"] = s
        print(f"{'push':10s} {s['n']:2d}  {s['missing']:7d}  {s['mean_abs_deg']!s:>14}  {s['max_abs_deg']!s:>13}")
    out = {"r2g": str(at.R2G), "angles": angles, "rows": rows, "push": pushes, "summary": summary}
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    print(json.dumps({"summary": summary}))


if __name__ == "__main__":
    main()
