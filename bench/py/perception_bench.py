"""`r2g bench perception`: local perception (agent-host/py/lib/robo_perception/) over the pack's
graspable objects, at the cameras' native 640x480.

For every free object of every gym: reset, observe agentview + wrist (raw RGB-D), segment the
scene and pick the object with a text prompt; IoU of its mask in each camera against MuJoCo's own
segmentation of the very same model and state (tests/python/render_truth.py: ground truth the
library never sees); propose grasps; then run the worked example stage program
(robot-skill/examples/pick_object.py) with the same prompt and read from the sim-host's native
trace whether the object really ended 5 cm or more above where it started.

Timing baseline in the same run: back-projecting the 640x480 depth image to base-frame points,
the first step of any RGB-D method, so `segment_ms / backproject_ms` carries across machines.

Usage: perception_bench.py [--gyms a,b] [--no-lift]   (R2G_BIN: the r2g binary)
Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT / "tests" / "python"), str(ROOT / "agent-host" / "py" / "lib")]
import render_truth as rt  # noqa: E402
import robo_perception as rp  # noqa: E402

R2G = Path(os.environ.get("R2G_BIN", str(ROOT / "target" / "release" / "r2g")))
GYMS_DIR = Path(os.environ.get("R2G_GYMS", str(ROOT / "gyms")))
EXAMPLE = ROOT / "robot-skill" / "examples" / "pick_object.py"

# The pack's graspable objects and the words a user would use for each.
OBJECTS = [
    ("pick_block_plate", "block", "red block"),
    ("pick_block_plate", "plate", "blue plate"),
    ("push_to_line", "block", "green block"),
    ("stack_bowls", "small_bowl", "orange bowl"),
    ("stack_bowls", "big_bowl", "blue bowl"),
    ("microwave_cup", "cup", "white cup"),
    ("hang_mug", "mug", "blue mug"),
    ("shelf_plate", "plate", "white plate"),
]
MIN_TRUTH_PX = 50  # a camera that sees less of the object than this does not count for IoU
LIFT_M = 0.05


def timed(fn, *args, **kwargs):
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, 1e3 * (time.perf_counter() - t)


def bench_gym(gym: str, items: list, lift: bool, trace_root: Path) -> list[dict]:
    g = rt.LiveGym(R2G, GYMS_DIR, gym, trace_dir=trace_root / gym, tag="bperc")
    truth = None
    rows = []
    try:
        if not g.ready.wait(90):
            raise RuntimeError(f"{gym}: r2g up did not print READY")
        truth = rt.TruthRenderer(rt.compiled_mjcf(R2G.parent / "r2g-sim", g.scene_path))
        fixtures = rt.initial_fixtures(g.scene)
        g.end_episode()
        for name, prompt in items:
            obs = g.observe()
            truth.set_state(obs["joint"], rp.gripper_to_width(obs["gripper"][0]) / 2, fixtures=fixtures)
            _, bp_ms = timed(rp.depth_to_points, obs["depth"]["agentview"], obs["camera_intrinsics"]["agentview"],
                             obs["camera_extrinsics"]["agentview"])
            _, seg1_ms = timed(rp.segment_scene, obs, ["agentview"])
            scene, segf_ms = timed(rp.segment_scene, obs)
            obj = rp.select(scene, prompt)
            row = {"gym": gym, "object": name, "prompt": prompt, "found": obj is not None,
                   "backproject_ms": bp_ms, "segment_ms": seg1_ms, "segment_fused_ms": segf_ms, "iou": {}}
            for cam in ("agentview", "wrist"):
                # the ground truth must draw the very picture the camera delivered
                mad = float(np.abs(truth.rgb(cam).astype(int) - obs["image"][cam]).mean())
                if mad > 1.0:
                    raise RuntimeError(f"{gym}/{cam}: the ground-truth render differs from the camera image "
                                       f"(mean abs difference {mad:.2f}); IoU would be meaningless")
                row.setdefault("truth_rgb_mad", {})[cam] = mad
                t = truth.masks(cam)[name]
                if t.sum() >= MIN_TRUTH_PX:
                    row["iou"][cam] = rt.iou(obj.masks[cam], t) if obj is not None else 0.0
            grasps, row["grasp_ms"] = timed(rp.propose_grasps, obj, scene, reference_pose=obs["ee_pose"]) \
                if obj is not None else ([], float("nan"))
            row["grasps"] = len(grasps)
            if lift:
                env = dict(os.environ, R2G_INSTANCE=g.instance)
                try:
                    out = subprocess.run([sys.executable, str(EXAMPLE), prompt], env=env, capture_output=True,
                                         text=True, timeout=240)
                    row["program_says_lifted"] = "RESULT lifted=True" in out.stdout
                    row["program_tail"] = (out.stdout + out.stderr).strip().splitlines()[-1:]
                except subprocess.TimeoutExpired:
                    row["program_says_lifted"] = False
                    row["program_tail"] = ["timed out after 240 s"]
                row["rise_m"] = rt.object_rise(g.end_episode(), name)
                row["lifted"] = row["rise_m"] >= LIFT_M
            rows.append(row)
    finally:
        if truth is not None:
            truth.close()
        g.stop()
    return rows


def _median_or_none(values: list) -> float | None:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.median(finite)) if finite else None


def main() -> int:
    # stopped (or r2g gone): unwind, so every gym started here is stopped by its finally block
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    ap = argparse.ArgumentParser()
    ap.add_argument("--gyms", default="", help="comma-separated subset of gyms")
    ap.add_argument("--no-lift", action="store_true", help="segmentation and grasp proposals only")
    a = ap.parse_args()
    want = [x for x in a.gyms.split(",") if x]
    by_gym: dict[str, list] = {}
    for gym, name, prompt in OBJECTS:
        if not want or gym in want:
            by_gym.setdefault(gym, []).append((name, prompt))
    if not by_gym:
        print(f"no gym of {want} has graspable objects", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory(prefix="r2g-bench-perception-") as tmp:
        for gym, items in by_gym.items():
            rows += bench_gym(gym, items, not a.no_lift, Path(tmp))

    print("\n## Local perception over the pack's graspable objects (640x480 RGB-D)\n")
    print("| gym | object | prompt | IoU agentview | IoU wrist | segment ms (agentview / fused) | grasps | grasp ms | rise m | lifted |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        iou = [f"{r['iou'][c]:.3f}" if c in r["iou"] else "-" for c in ("agentview", "wrist")]
        rise = f"{r['rise_m']:.3f}" if "rise_m" in r else "-"
        print(f"| {r['gym']} | {r['object']} | {r['prompt']} | {iou[0]} | {iou[1]} | {r['segment_ms']:.0f} / "
              f"{r['segment_fused_ms']:.0f} | {r['grasps']} | {r['grasp_ms']:.0f} | {rise} | {r.get('lifted', '-')} |")
    ious = [v for r in rows for v in r["iou"].values()]
    lifts = [r["lifted"] for r in rows if "lifted" in r]
    seg = [r["segment_ms"] for r in rows]
    bp = [r["backproject_ms"] for r in rows]
    out = {
        "objects": len(rows),
        "iou_mean": float(np.mean(ious)) if ious else 0.0,
        "iou_min": float(np.min(ious)) if ious else 0.0,
        "found_rate": float(np.mean([r["found"] for r in rows])),
        "lift_rate": float(np.mean(lifts)) if lifts else None,
        "lifted": [f"{r['gym']}/{r['object']}" for r in rows if r.get("lifted")],
        "not_lifted": [f"{r['gym']}/{r['object']}" for r in rows if "lifted" in r and not r["lifted"]],
        "segment_ms": float(np.median(seg)),
        "segment_fused_ms": float(np.median([r["segment_fused_ms"] for r in rows])),
        "grasp_ms": _median_or_none([r["grasp_ms"] for r in rows]),
        "backproject_ms": float(np.median(bp)),
        "segment_over_backproject": float(np.median(seg) / max(np.median(bp), 1e-9)),
        "resolution": [640, 480],
    }
    for r in rows:
        if r.get("lifted") is False:
            print(f"\nnot lifted: {r['gym']}/{r['object']} ({r['prompt']}): rise {r['rise_m']:.3f} m; "
                  f"program: {' '.join(r.get('program_tail', []))}")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
