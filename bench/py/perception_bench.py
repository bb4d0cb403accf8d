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

Robot parts reported as objects (the self-filter's target is 0): in every gym of the pack, at the
reset state and at mid-manipulation states (the arm swung aside by a joint chunk, the hand a few
centimetres above the table next to objects or stretched out, by ee_pose chunks; a block held just
above the table; with lifting, every object the example program holds up), the scene is segmented
and each reported object whose mask is mostly (over half) pixels MuJoCo draws for the robot counts
as a robot part; also how many of the robot's pixels ended in some object's mask.

Usage: perception_bench.py [--gyms a,b] [--no-lift]   (R2G_BIN: the r2g binary;
R2G_PERCEPTION_LIB: the library's folder, default agent-host/py/lib of this checkout, e.g. an older
checkout's to measure it; its checkout's robot-skill/examples/pick_object.py is run when present)
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
LIB = Path(os.environ.get("R2G_PERCEPTION_LIB") or ROOT / "agent-host" / "py" / "lib").resolve()
sys.path[:0] = [str(ROOT / "tests" / "python"), str(LIB)]
import render_truth as rt  # noqa: E402
import robo_perception as rp  # noqa: E402

R2G = Path(os.environ.get("R2G_BIN", str(ROOT / "target" / "release" / "r2g")))
GYMS_DIR = Path(os.environ.get("R2G_GYMS", str(ROOT / "gyms")))
# the example of the library's own checkout (it puts that checkout's library on its path)
EXAMPLE = next(p for p in (LIB.parents[2] / "robot-skill" / "examples" / "pick_object.py",
                           ROOT / "robot-skill" / "examples" / "pick_object.py") if p.exists())

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

# Mid-manipulation states for the robot-part count, per gym: TCP targets (x, y, z in the base
# frame, yaw about the vertical; hand pointing down, reached from 0.2 m above so that nothing is
# pushed on the way), low over the table next to objects or stretched out; a joint-space swing
# (offsets from the ready pose: the arm turned aside, the hand low); a scripted grasp (x, y, TCP z,
# lifted to).
READY = [0.0, -0.7853982, 0.0, -2.3561945, 0.0, 1.5707963, 0.7853982]
SWING_RIGHT = [-0.8, 0.89, 0.06, -0.11, -0.04, 0.66, 0.0]
SWING_LEFT = [0.82, 0.97, 0.15, -0.01, -0.21, 0.55, 0.0]
ROBOT_STATES = {
    "pick_block_plate": {"poses": [("near the block", (0.42, -0.12, 0.05), 0.0), ("between", (0.5, 0.02, 0.06), 1.57),
                                   ("stretched", (0.72, 0.0, 0.07), 0.0)],
                         "swing": SWING_LEFT, "grasp": ((0.5, -0.12), 0.03, 0.06)},
    "push_to_line": {"poses": [("behind the block", (0.33, -0.05, 0.05), 0.0), ("stretched", (0.70, 0.1, 0.06), 0.0)],
                     "swing": SWING_LEFT},
    "stack_bowls": {"poses": [("in front", (0.38, 0.0, 0.05), 0.0), ("stretched", (0.72, 0.0, 0.08), 0.7)],
                    "swing": SWING_RIGHT},
    "microwave_cup": {"poses": [("near the cup", (0.36, 0.12, 0.05), 0.0), ("left", (0.40, 0.30, 0.05), 0.5)],
                      "swing": SWING_LEFT},
    "hang_mug": {"poses": [("near the mug", (0.40, 0.12, 0.05), 0.0), ("in front", (0.38, -0.05, 0.06), 1.57)],
                 "swing": SWING_LEFT},
    "shelf_plate": {"poses": [("in front", (0.36, 0.0, 0.05), 0.0), ("near the plate", (0.32, -0.2, 0.08), 0.0)],
                    "swing": SWING_RIGHT},
    "open_drawer": {"poses": [("low left", (0.40, 0.15, 0.05), 0.0), ("at the handle", (0.45, 0.0, 0.22), 1.57),
                              ("low right", (0.45, -0.2, 0.04), 0.5)]},
    "close_cabinet": {"poses": [("front left", (0.35, 0.2, 0.05), 0.0), ("front right", (0.38, -0.2, 0.06), 0.5)],
                      "swing": SWING_RIGHT},
}
MOSTLY = 0.5  # an object with more than this share of its mask on the robot is a robot part


def timed(fn, *args, **kwargs):
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, 1e3 * (time.perf_counter() - t)





def judge_robot(obs: dict, truth, objects=None, fixtures=None) -> dict:
    """Segments `obs`; against MuJoCo's segmentation of that state: the objects that are mostly
    robot, how many robot pixels ended in object masks, and whether the truth draws the camera's
    very picture (mean absolute RGB difference, `mad`)."""
    truth.set_state(obs["joint"], rp.gripper_to_width(obs["gripper"][0]) / 2, objects=objects, fixtures=fixtures)
    scene = rp.segment_scene(obs)
    robot_id = truth.names.index("robot")
    counts = np.zeros((len(scene.objects), 2))
    leak = robot_px = 0
    mad = 0.0
    for cam in ("agentview", "wrist"):
        mad = max(mad, float(np.abs(truth.rgb(cam).astype(int) - obs["image"][cam]).mean()))
        robot = truth.segmentation(cam) == robot_id
        any_obj = np.zeros_like(robot)
        for i, o in enumerate(scene.objects):
            counts[i] += [(o.masks[cam] & robot).sum(), o.masks[cam].sum()]
            any_obj |= o.masks[cam]
        leak += int((robot & any_obj).sum())
        robot_px += int(robot.sum())
    parts = [f"{o.describe()} ({r / max(n, 1):.0%} robot)" for o, (r, n) in zip(scene.objects, counts)
             if r > MOSTLY * max(n, 1)]
    return {"objects": len(scene.objects), "robot_parts": len(parts), "parts": parts, "robot_px_in_objects": leak,
            "robot_px": robot_px, "mad": mad}


def robot_states(g, truth, fixtures: dict) -> list[dict]:
    """The robot-part count over the gym's reset and mid-manipulation states (the scene is reset
    at the start and left reset). A state whose ground truth no longer draws the camera's picture
    (something was moved) is judged again with the object poses of the native trace."""
    import robo
    spec = ROBOT_STATES.get(g.gym, {})
    rows = []

    def judge(label: str, ok: bool = True, objects=None, fx=None) -> None:
        if not ok:
            fb = robo.get_state([])["control_feedback"]
            print(f"   {g.gym} / {label}: the move failed ({fb.get('reason')}); judged where the arm stopped",
                  file=sys.stderr)
        obs = g.observe()
        r = judge_robot(obs, truth, objects, fx or fixtures)
        if r["mad"] > 1.0:
            objects, fx = rt.trace_state(g.scene, g.end_episode())
            r = judge_robot(obs, truth, objects, fx)
        rows.append(dict(r, gym=g.gym, state=label))

    g.end_episode()
    judge("reset")
    if "swing" in spec:  # one control type per episode: the joint chunk first, then a reset
        judge("arm swung aside", rt.move_joints(np.asarray(READY) + spec["swing"]))
        g.end_episode()
    for label, xyz, yaw in spec.get("poses", []):
        judge(label, rt.move_tcp(xyz, yaw))
    if "grasp" in spec:
        (x, y), z, lift = spec["grasp"]
        g.end_episode()
        ok = rt.move_tcp((x, y, 0.10), 0.0) and rt.move_tcp((x, y, z), 0.0, hop=0.0)
        here = robo.get_state([])["ee_pose"]
        ok = ok and robo.post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints([here] * 12, 1.0)}) == 1
        ok = ok and rt.move_tcp((x, y, lift), 0.0, gripper=1.0, hop=0.0)
        obs = g.observe()
        objects, fx = rt.trace_state(g.scene, g.end_episode())
        rows.append(dict(judge_robot(obs, truth, objects, fx), gym=g.gym, state="object held above the table"))
        if not ok:
            print(f"   {g.gym}: the scripted grasp did not go through", file=sys.stderr)
    g.end_episode()
    return rows


def bench_gym(gym: str, items: list, lift: bool, trace_root: Path) -> tuple[list[dict], list[dict]]:
    g = rt.LiveGym(R2G, GYMS_DIR, gym, trace_dir=trace_root / gym, tag="bperc")
    truth = None
    rows, robot_rows = [], []
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
                held = g.observe()  # the object in the hand (or not), for the robot-part count
                trace = g.end_episode()
                row["rise_m"] = rt.object_rise(trace, name)
                row["lifted"] = row["rise_m"] >= LIFT_M
                objects, fx = rt.trace_state(g.scene, trace)
                robot_rows.append(dict(judge_robot(held, truth, objects, fx), gym=gym,
                                       state=f"after the example program lifts the {prompt}"))
            rows.append(row)
        robot_rows += robot_states(g, truth, fixtures)
    finally:
        if truth is not None:
            truth.close()
        g.stop()
    return rows, robot_rows


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
    for gym in ROBOT_STATES:  # gyms without graspable objects still count robot parts
        if not want or gym in want:
            by_gym.setdefault(gym, [])
    if not by_gym:
        print(f"no gym of {want} is benchmarked", file=sys.stderr)
        return 2
    rows, robot_rows = [], []
    with tempfile.TemporaryDirectory(prefix="r2g-bench-perception-") as tmp:
        for gym, items in by_gym.items():
            r, rr = bench_gym(gym, items, not a.no_lift, Path(tmp))
            rows += r
            robot_rows += rr

    print("\n## Local perception over the pack's graspable objects (640x480 RGB-D)\n")
    print("| gym | object | prompt | IoU agentview | IoU wrist | segment ms (agentview / fused) | grasps | grasp ms | rise m | lifted |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        iou = [f"{r['iou'][c]:.3f}" if c in r["iou"] else "-" for c in ("agentview", "wrist")]
        rise = f"{r['rise_m']:.3f}" if "rise_m" in r else "-"
        print(f"| {r['gym']} | {r['object']} | {r['prompt']} | {iou[0]} | {iou[1]} | {r['segment_ms']:.0f} / "
              f"{r['segment_fused_ms']:.0f} | {r['grasps']} | {r['grasp_ms']:.0f} | {rise} | {r.get('lifted', '-')} |")
    print(f"\n## Robot parts reported as objects (library {LIB})\n")
    print("| gym | states | objects reported | robot parts | robot pixels in objects |")
    print("|---|---|---|---|---|")
    parts_by_gym: dict[str, int] = {}
    for gym in dict.fromkeys(r["gym"] for r in robot_rows):
        rr = [r for r in robot_rows if r["gym"] == gym]
        parts_by_gym[gym] = sum(r["robot_parts"] for r in rr)
        px = sum(r["robot_px_in_objects"] for r in rr)
        print(f"| {gym} | {len(rr)} | {sum(r['objects'] for r in rr)} | {parts_by_gym[gym]} | "
              f"{px} of {sum(r['robot_px'] for r in rr)} |")
    for r in robot_rows:
        for p in r["parts"]:
            print(f"\nrobot part: {r['gym']} / {r['state']}: {p}")
    robot_px = sum(r["robot_px"] for r in robot_rows)
    ious = [v for r in rows for v in r["iou"].values()]
    lifts = [r["lifted"] for r in rows if "lifted" in r]
    seg = [r["segment_ms"] for r in rows]
    bp = [r["backproject_ms"] for r in rows]
    out = {
        "objects": len(rows),
        "iou_mean": float(np.mean(ious)) if ious else 0.0,
        "iou_min": float(np.min(ious)) if ious else 0.0,
        "found_rate": float(np.mean([r["found"] for r in rows])) if rows else None,
        "lift_rate": float(np.mean(lifts)) if lifts else None,
        "lifted": [f"{r['gym']}/{r['object']}" for r in rows if r.get("lifted")],
        "not_lifted": [f"{r['gym']}/{r['object']}" for r in rows if "lifted" in r and not r["lifted"]],
        "segment_ms": float(np.median(seg)) if seg else None,
        "segment_fused_ms": float(np.median([r["segment_fused_ms"] for r in rows])) if rows else None,
        "grasp_ms": _median_or_none([r["grasp_ms"] for r in rows]),
        "backproject_ms": float(np.median(bp)) if bp else None,
        "segment_over_backproject": float(np.median(seg) / max(np.median(bp), 1e-9)) if seg else None,
        "resolution": [640, 480],
        "robot_parts": sum(parts_by_gym.values()),
        "robot_parts_by_gym": parts_by_gym,
        "robot_states": len(robot_rows),
        "robot_px_in_objects": sum(r["robot_px_in_objects"] for r in robot_rows),
        "robot_px_in_objects_frac": sum(r["robot_px_in_objects"] for r in robot_rows) / max(robot_px, 1),
        "library": str(LIB),
    }
    for r in rows:
        if r.get("lifted") is False:
            print(f"\nnot lifted: {r['gym']}/{r['object']} ({r['prompt']}): rise {r['rise_m']:.3f} m; "
                  f"program: {' '.join(r.get('program_tail', []))}")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
