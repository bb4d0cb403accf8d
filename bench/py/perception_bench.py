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

What perception says about objects the hand acts on, against MuJoCo's truth (the sim-host's
native trace posing the compiled model, tests/python/render_truth.py), each in the same scripted
motion whatever the library (so an older one is measured on the very same states):
- a block held and lifted 1, 2 and 3 cm (pick_block_plate): its box bottom and top against the
  block's true lowest and highest points, and `held`;
- the block put on the plate and released: the plate's top and box height, the block's box
  bottom against the truth, and `on(block, plate)` against the judge's own verdict;
- a block pushed 9 cm by part-open fingers that never closed on it (push_to_line): `held`
  (must stay False), `in_contact` and `pushed`;
- the open cabinet door seen from the wrist camera up close (close_cabinet), one tracker over
  the approach: how many reported objects are mostly the door's leaf (1 wanted, a panel), and
  how many track ids were handed from one true part to another (0 wanted: a shadow or a
  fragment taking the handle's id);
- the yellow line of push_to_line from agentview alone, the wrist alone and both, in three
  states: markings that are not the line, and the spread of the line's `center`.

Usage: perception_bench.py [--gyms a,b] [--no-lift] [--cases-only]   (R2G_BIN: the r2g binary;
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


# ------------------------------------------------------------------------------------------
# Objects the hand acts on (the cases of issue 32), against MuJoCo's truth
# ------------------------------------------------------------------------------------------

def _box_bottom(o, plane) -> float:
    """Height above the plane of a cluster's box bottom (any library version)."""
    return float(plane.distance(o.obb.center) - 0.5 * o.obb.extents[2])


def _label_of(o, gseg: dict, part_of) -> str:
    """The true part owning most of a cluster's pixels over both cameras."""
    votes: dict = {}
    for cam, seg in gseg.items():
        ids, cnt = np.unique(seg[o.masks[cam]], return_counts=True)
        for i, c in zip(ids, cnt):
            lab = part_of(int(i))
            votes[lab] = votes.get(lab, 0) + int(c)
    return max(votes, key=votes.get) if votes else "none"


def _truth_at(g, truth, trace, obs) -> None:
    objects, fx = rt.trace_state(g.scene, trace, obs["timestamp"])
    truth.set_state(obs["joint"], rp.gripper_to_width(obs["gripper"][0]) / 2, objects=objects, fixtures=fx)


def _grasp_block(x: float, y: float, z: float) -> bool:
    import robo
    ok = rt.move_tcp((x, y, 0.10), 0.0) and rt.move_tcp((x, y, z), 0.0, hop=0.0)
    here = robo.get_state([])["ee_pose"]
    return ok and robo.post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints([here] * 12, 1.0)}) == 1


def case_block_lift_and_place(trace_root: Path) -> dict:
    """pick_block_plate: the block held and lifted 1, 2, 3 cm; then put on the plate."""
    g = rt.LiveGym(R2G, GYMS_DIR, "pick_block_plate", trace_dir=trace_root / "case_block", tag="bpc")
    truth = None
    out: dict = {"lifts": []}
    try:
        if not g.ready.wait(90):
            raise RuntimeError("pick_block_plate: r2g up did not print READY")
        truth = rt.TruthRenderer(rt.compiled_mjcf(R2G.parent / "r2g-sim", g.scene_path))
        block_g, plate_g = truth.subtree_geoms("block"), truth.subtree_geoms("plate")
        g.end_episode()
        tracker = rp.Tracker()
        obs0 = g.observe()
        rp.segment_scene(obs0, tracker=tracker)
        x, y = (float(v) for v in g.scene["objects"][0]["position_m"][:2])
        if not _grasp_block(x, y, 0.03):
            raise RuntimeError("pick_block_plate: the scripted grasp did not go through")
        seen = []
        for lift in (0.01, 0.02, 0.03):
            ok = rt.move_tcp((x, y, 0.03 + lift), 0.0, gripper=1.0, hop=0.0)
            obs = g.observe()
            seen.append((lift, ok, obs, rp.segment_scene(obs, tracker=tracker)))
        ok = rt.move_tcp((x, y, 0.10), 0.0, gripper=1.0, hop=0.0)
        px, py = (float(v) for v in g.scene["objects"][1]["position_m"][:2])
        ok = ok and rt.move_tcp((px, py, 0.10), 0.0, gripper=1.0, hop=0.0)
        ok = ok and rt.move_tcp((px, py, 0.047), 0.0, gripper=1.0, hop=0.0)
        ok = ok and rt.move_tcp((px, py, 0.047), 0.0, gripper=-1.0, hop=0.0)
        ok = ok and rt.move_tcp((px, py, 0.15), 0.0, gripper=-1.0, hop=0.0)
        placed_obs = g.observe()
        placed = rp.segment_scene(placed_obs, tracker=tracker)
        trace = g.end_episode()
        verdict = json.loads(sorted((trace_root / "case_block").glob("episode-*.eval.json"),
                                    key=lambda p: int(p.name.split("-")[1].split(".")[0]))[-1].read_text())
        for lift, lok, obs, scene in seen:
            _truth_at(g, truth, trace, obs)
            lo, hi = truth.vertical_extent(block_g)
            gseg = {c: truth.geom_segmentation(c) for c in ("agentview", "wrist")}
            blk = [o for o in scene.objects if _label_of(o, gseg, lambda i: "block" if i in block_g else "other") == "block"]
            row = {"lift_m": lift, "moved": lok, "truth_bottom_m": lo, "truth_top_m": hi, "found": bool(blk)}
            if blk:
                o = max(blk, key=lambda o: len(o.points))
                row.update(box_bottom_m=_box_bottom(o, scene.plane), top_m=float(o.top), held=bool(o.held),
                           bottom_err_m=_box_bottom(o, scene.plane) - lo, top_err_m=float(o.top) - hi,
                           pieces=len(blk))
            out["lifts"].append(row)
        _truth_at(g, truth, trace, placed_obs)
        blo, bhi = truth.vertical_extent(block_g)
        plo, phi = truth.vertical_extent(plate_g)
        gseg = {c: truth.geom_segmentation(c) for c in ("agentview", "wrist")}
        lab = {id(o): _label_of(o, gseg, lambda i: "block" if i in block_g else ("plate" if i in plate_g else "other"))
               for o in placed.objects}
        blk = max((o for o in placed.objects if lab[id(o)] == "block"), key=lambda o: len(o.points), default=None)
        plt = max((o for o in placed.objects if lab[id(o)] == "plate"), key=lambda o: len(o.points), default=None)
        row = {"moved": ok, "truth_block_bottom_m": blo, "truth_plate_top_m": phi,
               "judge_on": bool(verdict["checks"].get("on:block:plate", {}).get("pass"))}
        if plt is not None:
            row.update(plate_top_m=float(plt.top), plate_height_m=float(plt.obb.extents[2]),
                       plate_top_err_m=float(plt.top) - phi)
        if blk is not None:
            row.update(block_box_bottom_m=_box_bottom(blk, placed.plane),
                       block_bottom_err_m=_box_bottom(blk, placed.plane) - blo)
        if blk is not None and plt is not None and hasattr(rp, "on"):
            rel = rp.on(blk, plt, placed)
            row.update(on=bool(rel.holds), on_why=rel.why)
        out["placed"] = row
    finally:
        if truth is not None:
            truth.close()
        g.stop()
    return out


def case_pushed_block(trace_root: Path) -> dict:
    """push_to_line: part-open fingers (commanded 0: 4 cm) push the block; they never close."""
    g = rt.LiveGym(R2G, GYMS_DIR, "push_to_line", trace_dir=trace_root / "case_push", tag="bpp")
    rows = []
    try:
        if not g.ready.wait(90):
            raise RuntimeError("push_to_line: r2g up did not print READY")
        g.end_episode()
        tracker = rp.Tracker()
        x, y = (float(v) for v in g.scene["objects"][0]["position_m"][:2])
        steps = [("at the start", None), ("fingers behind it", (x - 0.06, y, 0.03)),
                 ("hand 9 cm on, fingers at it", (x + 0.03, y, 0.03)), ("hand lifted away", (x + 0.03, y, 0.13))]
        for label, xyz in steps:
            ok = True if xyz is None else rt.move_tcp(xyz, 0.0, gripper=0.0, hop=0.0 if "hand" in label else 0.15)
            obs = g.observe()
            scene = rp.segment_scene(obs, tracker=tracker)
            o = rp.select(scene, "green block")
            rows.append({"state": label, "moved": ok, "grasp": obs["control_feedback"]["grasp"]["status"],
                         "gripper": float(obs["gripper"][0]), "found": o is not None,
                         "held": bool(o.held) if o is not None else None,
                         "in_contact": getattr(o, "in_contact", None) if o is not None else None,
                         "pushed": getattr(o, "pushed", None) if o is not None else None,
                         "track": o.track_id if o is not None else None})
        trace = g.end_episode()
        i = trace["objects"].index("block")
        moved = float(np.linalg.norm(np.subtract(trace["samples"][-1]["objects"][i][:2],
                                                 trace["samples"][0]["objects"][i][:2])))
    finally:
        g.stop()
    return {"rows": rows, "true_push_m": moved}


def case_door_up_close(trace_root: Path) -> dict:
    """close_cabinet: one tracker while the hand comes up to the open door's outer face."""
    g = rt.LiveGym(R2G, GYMS_DIR, "close_cabinet", trace_dir=trace_root / "case_door", tag="bpd")
    truth = None
    rows = []
    try:
        if not g.ready.wait(90):
            raise RuntimeError("close_cabinet: r2g up did not print READY")
        truth = rt.TruthRenderer(rt.compiled_mjcf(R2G.parent / "r2g-sim", g.scene_path))
        fixtures = rt.initial_fixtures(g.scene)
        moving = truth.drawn_geoms("cabinet__moving")
        leaf, handle = moving[:1], set(moving[1:])
        carcass = set(truth.drawn_geoms("cabinet"))
        robot_id = truth.names.index("robot")

        def part_of(i: int) -> str:
            if i in leaf:
                return "door leaf"
            if i in handle:
                return "door handle"
            if i in carcass:
                return "carcass"
            if i >= 0 and truth.owner[i] == robot_id:
                return "robot"
            return "other"

        g.end_episode()
        tracker = rp.Tracker()
        poses = [None, ((0.45, 0.22, 0.25), -1.57), ((0.42, 0.17, 0.18), -1.57), ((0.40, 0.14, 0.15), -1.57),
                 ((0.36, 0.13, 0.15), -1.57), ((0.30, 0.14, 0.16), -1.2)]
        history: dict = {}
        for k, pose in enumerate(poses):
            ok = True if pose is None else rt.move_tcp(pose[0], pose[1], hop=0.0)
            obs = g.observe()
            scene = rp.segment_scene(obs, tracker=tracker)
            truth.set_state(obs["joint"], rp.gripper_to_width(obs["gripper"][0]) / 2, fixtures=fixtures)
            gseg = {c: truth.geom_segmentation(c) for c in ("agentview", "wrist")}
            labels = [_label_of(o, gseg, part_of) for o in scene.objects]
            door = [o for o, lab in zip(scene.objects, labels) if lab == "door leaf"]
            for o, lab in zip(scene.objects, labels):
                history.setdefault(o.track_id, []).append(lab)
            rows.append({"state": "reset" if pose is None else f"TCP {pose[0]}", "moved": ok,
                         "door_objects": len(door), "door_shapes": [o.shape_name for o in door],
                         "door_seen_as": [getattr(o, "seen_as", "") or o.shape_name for o in door],
                         "handle_tracks": sorted({o.track_id for o, lab in zip(scene.objects, labels)
                                                  if lab == "door handle"}),
                         "objects": [f"{lab}: {o.describe()}" for o, lab in zip(scene.objects, labels)]})
        stolen = {t: labs for t, labs in history.items() if len(set(labs)) > 1}
        handle_tracks = sorted({t for t, labs in history.items() if "door handle" in labs})
    finally:
        if truth is not None:
            truth.close()
        g.stop()
    return {"rows": rows, "stolen_tracks": {str(k): v for k, v in stolen.items()}, "handle_tracks": handle_tracks}


def case_markings(trace_root: Path) -> dict:
    """push_to_line: the yellow line from each camera and both, in three states."""
    g = rt.LiveGym(R2G, GYMS_DIR, "push_to_line", trace_dir=trace_root / "case_marks", tag="bpm")
    rows = []
    try:
        if not g.ready.wait(90):
            raise RuntimeError("push_to_line: r2g up did not print READY")
        g.end_episode()
        fx = next(f for f in g.scene["fixtures"] if f["name"] == "line")
        lx, ly = (float(v) for v in fx["position_m"][:2])
        hx, hy = (float(v) for v in fx["parts"][0]["size_m"][:2])       # half sides
        for label, xyz in (("reset", None), ("hand over the block", (0.40, -0.05, 0.15)),
                           ("hand past the line", (0.62, 0.05, 0.12))):
            ok = True if xyz is None else rt.move_tcp(xyz, 0.0, gripper=1.0)
            obs = g.observe()
            for cams in (["agentview"], ["wrist"], None):
                scene = rp.segment_scene(obs, cams, tracker=None)
                marks = rp.find_markings(scene, "yellow")
                # on the tape: 80 % of its points within 5 mm of the tape's rectangle
                on_tape = [bool(np.mean((np.abs(m.points[:, 0] - lx) <= hx + 0.005)
                                        & (np.abs(m.points[:, 1] - ly) <= hy + 0.005)) >= 0.8) for m in marks]
                line = sorted((m for m, t in zip(marks, on_tape) if t), key=lambda m: -m.obb.extents[0])
                rows.append({"state": label, "moved": ok, "cameras": "+".join(cams or ["agentview", "wrist"]),
                             "markings": len(marks), "not_the_line": len(marks) - sum(on_tape),
                             "center": [float(v) for v in line[0].center[:2]] if line else None,
                             "length": float(line[0].obb.extents[0]) if line else None,
                             "seen_whole": getattr(line[0], "seen_whole", None) if line else None,
                             "extra": [m.describe() for m, t in zip(marks, on_tape) if not t]})
    finally:
        g.stop()
    cs = np.array([r["center"] for r in rows if r["center"] is not None])
    whole = np.array([r["center"] for r in rows if r["center"] is not None and r["seen_whole"]])
    fused = np.array([r["center"] for r in rows if r["center"] is not None and "+" in r["cameras"]])
    single = np.array([r["center"] for r in rows if r["center"] is not None and r["cameras"] == "agentview"]
                      + [r["center"] for r in rows if r["center"] is not None and r["cameras"] == "wrist"
                         and r["state"] == "reset"])

    def spread(c):
        return float(np.max(np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2))) if len(c) > 1 else 0.0
    return {"rows": rows, "truth_center": [lx, ly], "center_spread_m": spread(cs),
            "center_spread_seen_whole_m": spread(whole) if len(whole) else None,
            "center_spread_fused_m": spread(fused) if len(fused) else None,
            "center_spread_two_cameras_m": spread(single) if len(single) else None,
            "max_center_err_m": float(np.max(np.linalg.norm(cs - [lx, ly], axis=1))) if len(cs) else None}


def run_cases(want: list, trace_root: Path) -> dict:
    out: dict = {}
    for gym, key, fn in (("pick_block_plate", "block", case_block_lift_and_place),
                         ("push_to_line", "push", case_pushed_block),
                         ("close_cabinet", "door", case_door_up_close),
                         ("push_to_line", "markings", case_markings)):
        if not want or gym in want:
            try:
                out[key] = fn(trace_root)
            except Exception as e:  # noqa: BLE001 - one case failing costs only its figures
                print(f"   case {key}: {type(e).__name__}: {e}", file=sys.stderr)
                out[key] = {"error": f"{type(e).__name__}: {e}"}
    return out


def _mm(v) -> str:
    return "-" if v is None else f"{1e3 * v:+.1f}"


def print_cases(c: dict) -> dict:
    """Tables of the cases; returns their headline figures for the JSON line."""
    fig: dict = {}
    if "block" in c and "error" not in c["block"]:
        b = c["block"]
        print("\n## A block held and lifted (pick_block_plate; truth: MuJoCo's block at the traced pose)\n")
        print("| lift | held | box bottom m (truth) | bottom error mm | top m (truth) | top error mm | pieces |")
        print("|---|---|---|---|---|---|---|")
        for r in b["lifts"]:
            print(f"| {100 * r['lift_m']:.0f} cm | {r.get('held', '-')} | {r.get('box_bottom_m', float('nan')):.4f} "
                  f"({r['truth_bottom_m']:.4f}) | {_mm(r.get('bottom_err_m'))} | {r.get('top_m', float('nan')):.4f} "
                  f"({r['truth_top_m']:.4f}) | {_mm(r.get('top_err_m'))} | {r.get('pieces', 0)} |")
        p = b.get("placed", {})
        print("\n## The block put on the plate and released\n")
        print("| plate top m (truth) | plate top error mm | plate box height m | block box bottom m (truth) | "
              "block bottom error mm | on(block, plate) | judge's on |")
        print("|---|---|---|---|---|---|---|")
        print(f"| {p.get('plate_top_m', float('nan')):.4f} ({p.get('truth_plate_top_m', float('nan')):.4f}) | "
              f"{_mm(p.get('plate_top_err_m'))} | {p.get('plate_height_m', float('nan')):.4f} | "
              f"{p.get('block_box_bottom_m', float('nan')):.4f} ({p.get('truth_block_bottom_m', float('nan')):.4f}) | "
              f"{_mm(p.get('block_bottom_err_m'))} | {p.get('on', '-')} | {p.get('judge_on')} |")
        errs = [abs(r["bottom_err_m"]) for r in b["lifts"] if "bottom_err_m" in r]
        fig.update(lifted_block_bottom_err_max_m=max(errs) if errs else None,
                   lifted_block_held=[r.get("held") for r in b["lifts"]],
                   placed_plate_top_err_m=p.get("plate_top_err_m"), placed_block_bottom_err_m=p.get("block_bottom_err_m"),
                   placed_on=p.get("on"), placed_judge_on=p.get("judge_on"))
    if "push" in c and "error" not in c["push"]:
        print(f"\n## A block pushed by part-open fingers (push_to_line; truth: it slid "
              f"{c['push']['true_push_m']:.3f} m)\n")
        print("| state | grasp status | gripper | held | in_contact | pushed | track |")
        print("|---|---|---|---|---|---|---|")
        for r in c["push"]["rows"]:
            print(f"| {r['state']} | {r['grasp']} | {r['gripper']:.2f} | {r['held']} | {r['in_contact']} | "
                  f"{r['pushed']} | {r['track']} |")
        fig.update(pushed_block_held=[r["held"] for r in c["push"]["rows"]],
                   pushed_block_flagged=[r["pushed"] for r in c["push"]["rows"]])
    if "door" in c and "error" not in c["door"]:
        d = c["door"]
        print("\n## The open cabinet door up close (close_cabinet; truth: MuJoCo's geoms of the door)\n")
        print("| state | objects mostly the door's leaf | their shapes | handle tracks |")
        print("|---|---|---|---|")
        for r in d["rows"]:
            print(f"| {r['state']} | {r['door_objects']} | {', '.join(r['door_shapes']) or '-'} | "
                  f"{r['handle_tracks'] or '-'} |")
        print(f"\ntracks handed from one true part to another: {len(d['stolen_tracks'])} {d['stolen_tracks']}; "
              f"tracks the handle had: {d['handle_tracks']}")
        fig.update(door_leaf_objects_max=max(r["door_objects"] for r in d["rows"]),
                   door_leaf_not_panel=sum(1 for r in d["rows"] for s in r["door_shapes"] if s != "panel"),
                   door_stolen_tracks=len(d["stolen_tracks"]), door_handle_tracks=len(d["handle_tracks"]))
    if "markings" in c and "error" not in c["markings"]:
        m = c["markings"]
        print("\n## The yellow line (push_to_line; truth centre "
              f"({m['truth_center'][0]:.3f}, {m['truth_center'][1]:.3f}))\n")
        print("| state | cameras | markings | not the line | line centre | length m | seen whole |")
        print("|---|---|---|---|---|---|---|")
        for r in m["rows"]:
            cen = "-" if r["center"] is None else f"({r['center'][0]:.4f}, {r['center'][1]:.4f})"
            ln = "-" if r["length"] is None else f"{r['length']:.3f}"
            print(f"| {r['state']} | {r['cameras']} | {r['markings']} | {r['not_the_line']} | {cen} | {ln} | "
                  f"{r['seen_whole']} |")
        sw, sf, s2 = m["center_spread_seen_whole_m"], m["center_spread_fused_m"], m["center_spread_two_cameras_m"]

        def mm(v):
            return "-" if v is None else f"{1e3 * v:.1f} mm"
        print(f"\nline centre spread: both cameras fused, over the three states {mm(sf)}; agentview alone (three "
              f"states) and the wrist alone where it sees the whole tape {mm(s2)}; every row the library says it saw "
              f"whole {mm(sw)}; every row {mm(m['center_spread_m'])} (a wrist view that sees a part of the tape "
              f"centres that part)")
        fig.update(markings_not_the_line=sum(r["not_the_line"] for r in m["rows"]),
                   marking_center_spread_fused_m=sf, marking_center_spread_two_cameras_m=s2,
                   marking_center_spread_seen_whole_m=sw)
    for k, v in c.items():
        if "error" in v:
            print(f"\ncase {k} failed: {v['error']}")
            fig[f"{k}_error"] = v["error"]
    return fig


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
    ap.add_argument("--cases-only", action="store_true", help="only the cases of objects the hand acts on")
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
        for gym, items in ({} if a.cases_only else by_gym).items():
            r, rr = bench_gym(gym, items, not a.no_lift, Path(tmp))
            rows += r
            robot_rows += rr
        cases = run_cases(want, Path(tmp))

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
    out.update(print_cases(cases))
    out["cases"] = cases
    for r in rows:
        if r.get("lifted") is False:
            print(f"\nnot lifted: {r['gym']}/{r['object']} ({r['prompt']}): rise {r['rise_m']:.3f} m; "
                  f"program: {' '.join(r.get('program_tail', []))}")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
