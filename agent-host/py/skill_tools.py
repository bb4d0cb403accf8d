"""Host-side skill geometry for `r2g skills ...` (trusted; never in the sandbox). One JSON request
on stdin, one JSON answer on stdout; errors as {"error": "..."} with exit status 2.

    skill_tools.py relate   {"obs": npz, "calls": [...], "native": {"block": [x, y, z], ...}}
        The motion of one executed round expressed against the objects seen at its start: each
        chunk becomes a step (a move bound to an object anchor, a gripper change or a hold); the
        rule's anchor, offset and yaw are computed from the chunk's final target and the round's
        first observation (robo_skills.relate), with the TCP measured then as the reference.
        `native` (scene object -> position at the round's start, from the trace) names which
        perceived object is which scene object, so checks found in the trace can be written
        against perceived roles.
    skill_tools.py perceive {"obs": npz}
        The objects perception finds: colour, shape, prompt, centre, sides.
    skill_tools.py check    {"skill": {...}, "sources": [{"obs": npz, "reference": pose,
                                                          "targets": {rule: pose}}]}
        Code lint (robo_skills.lint) and compile for every stage's code, and the rules bound
        again on the recorded observations: position and rotation error against the recorded
        targets, per rule.
"""
from __future__ import annotations

import json
import os
import sys
from typing import Any

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "lib"))

import robo_perception as rp  # noqa: E402
import robo_skills as rs  # noqa: E402
from robo_perception.transforms import pose_to_matrix  # noqa: E402

MOVE_MIN_M, MOVE_MIN_RAD = 0.002, 0.01  # less motion than this over a chunk: the gripper or a hold
MAX_OFFSET_M = 0.40                      # a rule may not reach further from its anchor
HELD_FALLBACK_M = 0.08                   # a target this far from every free object is about the held one
HELD_ABOVE_M = 0.03                      # ... and so is one this close above it (in the plane)


def load_obs(path: str) -> dict:
    """A run record's obs.npz as a raw get_state() dict."""
    with np.load(path, allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    state = json.loads(str(data["state_json"]))
    s: dict[str, Any] = {"image": {}, "depth": {}, "camera_intrinsics": {}, "camera_extrinsics": {}}
    for k, v in data.items():
        kind, _, cam = k.partition(".")
        if kind == "rgb":
            s["image"][cam] = v
        elif kind == "depth":
            s["depth"][cam] = v
        elif kind == "intrinsics":
            s["camera_intrinsics"][cam] = dict(zip(("fx", "fy", "cx", "cy"), (float(x) for x in v)))
        elif kind == "base_from_camera":
            s["camera_extrinsics"][cam] = v.tolist()
    s.update({k: state.get(k) for k in ("joint", "ee_pose", "gripper", "timestamp", "external_force_n")})
    return s


def scene_of(state: dict):
    return rp.segment_scene(state, tracker=None)


MARKING_COLORS = ("red", "orange", "yellow", "green", "cyan", "blue", "purple", "pink")


class MarkingAnchor:
    """A coloured mark on the support plane seen as an anchor (its plane box; no height)."""

    def __init__(self, m, color: str, ident: int) -> None:
        self.id, self.obb, self.center, self.points = ident, m.obb, np.asarray(m.center), m.points
        self.color_name, self.shape_name, self.top, self.held = color, "marking", 0.0, False

    def describe(self) -> str:
        c, e = self.center, self.obb.extents
        return f"{self.color_name} marking at ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}) size {e[0]:.3f}x{e[1]:.3f} m"


def markings(scene) -> list:
    """The largest mark of each saturated colour on the support plane (a line, a target zone),
    unless it lies under an object (the plane-level pixels of an object's own base)."""
    out = []
    for k, color in enumerate(MARKING_COLORS):
        found = rp.find_markings(scene, color)
        if not found or float(np.max(found[0].obb.extents[:2])) < 0.03:
            continue
        c = np.asarray(found[0].center)
        under = any(bool(o.obb.contains(c[None], margin=0.02)[0]) or
                    float(np.linalg.norm(np.asarray(o.center)[:2] - c[:2])) < 0.5 * float(np.max(o.obb.extents[:2])) + 0.02
                    for o in scene.objects)
        if not under:
            out.append(MarkingAnchor(found[0], color, 10_000 + k))
    return out


def role_names(scene) -> dict:
    """cluster id -> (role, prompt): colour and shape as perception names them; a position word
    is added when two objects would share a prompt."""
    base = {o.id: (o.color_name, o.shape_name) for o in scene.objects}
    out = {}
    for o in scene.objects:
        color, shape = base[o.id]
        prompt = f"{color} {shape}"
        twins = [p for p in scene.objects if base[p.id] == base[o.id]]
        if len(twins) > 1:
            for word in ("left", "right", "front", "back", "largest", "smallest"):
                ranked = rp.rank_objects(scene, f"{prompt} {word}")
                if ranked and ranked[0][0].id == o.id:
                    prompt = f"{word} {prompt}"
                    break
        out[o.id] = (prompt.replace(" ", "_"), prompt)
    for m in markings(scene):
        out[m.id] = (f"{m.color_name}_marking", f"{m.color_name} marking")
    return out


def perceive(req: dict) -> dict:
    scene = scene_of(load_obs(req["obs"]))
    names = role_names(scene)
    return {"objects": [{"role": names[o.id][0], "prompt": names[o.id][1], "color": o.color_name,
                         "shape": o.shape_name, "center": [float(v) for v in o.center],
                         "sides_m": [float(v) for v in o.obb.extents], "held": bool(o.held)}
                        for o in list(scene.objects) + markings(scene)]}


def _chunk_poses(call: dict, state: dict) -> list[np.ndarray]:
    acts = call.get("actions") or []
    if call.get("type") == "joint":
        return [np.append(np.asarray(rp.tcp_pose(a[:7]), dtype=float), a[7] if len(a) > 7 else 0.0) for a in acts]
    return [np.asarray(a, dtype=float) for a in acts]


def relate_round(req: dict) -> dict:
    state = load_obs(req["obs"])
    scene = scene_of(state)
    names = role_names(scene)
    ref = pose_to_matrix(state["ee_pose"])
    here = np.asarray(state["ee_pose"], dtype=float)
    grip = float(state["gripper"][0])
    native = {k: np.asarray(v, dtype=float) for k, v in (req.get("native") or {}).items()}
    # native scene object -> perceived role (nearest centre in the plane, within 4 cm)
    roles_of_native = {}
    for name, p in native.items():
        best = min(scene.objects, key=lambda o: float(np.linalg.norm(np.asarray(o.center)[:2] - p[:2])), default=None)
        if best is not None and float(np.linalg.norm(np.asarray(best.center)[:2] - p[:2])) < 0.04:
            roles_of_native[name] = names[best.id][0]
    steps, rules, objects, targets = [], [], {}, {}
    held_ids = {o.id for o in scene.objects if o.held}
    # Objects, and marks on the table: a target beyond a line is about the line.
    marks = markings(scene)
    for call in req.get("calls", []):
        if call.get("fn") != "post_actions" or call.get("result") != 1:
            continue
        poses = _chunk_poses(call, state)
        if not poses:
            continue
        last = poses[-1]
        g_end = float(last[6]) if len(last) > 6 else grip
        T_end = pose_to_matrix(last[:6])
        T_here = pose_to_matrix(here[:6])
        moved = float(np.linalg.norm(T_end[:3, 3] - T_here[:3, 3]))
        turned = rp.rotation_distance(T_here[:3, :3], T_end[:3, :3])
        n = len(poses)
        hz = 20.0 if not call.get("freq") else float(call["freq"])
        if moved < MOVE_MIN_M and turned < MOVE_MIN_RAD:
            if abs(g_end - grip) > 0.5:
                steps.append({"gripper": "close" if g_end > grip else "open", "settle_s": round(n / hz, 3)})
            else:
                steps.append({"hold_s": round(n / hz, 3)})
            grip = g_end
            continue
        # The object this target is about: one the target is over (within its footprint), of
        # those not in the hand when the round began; else the object in the hand when the
        # target is right above it (a lift); else the nearest free one in the plane (a mark on
        # the table included); else the held one.
        def xy_dist(o) -> float:
            return float(np.linalg.norm(np.asarray(o.center)[:2] - T_end[:2, 3]))
        free = [o for o in scene.objects if o.id not in held_ids] + marks
        held = [o for o in scene.objects if o.id in held_ids]
        over = [o for o in free if bool(o.obb.contains(np.array([[T_end[0, 3], T_end[1, 3], float(o.center[2])]]), margin=0.01)[0])]
        if over:
            obj = min(over, key=xy_dist)
        elif held and min(map(xy_dist, held)) < HELD_ABOVE_M:
            obj = min(held, key=xy_dist)
        else:
            obj = min(free, key=xy_dist, default=None)
            if obj is None or (held and xy_dist(obj) > HELD_FALLBACK_M):
                obj = min(held, key=xy_dist, default=obj)
        if obj is None:
            raise ValueError(f"{req['obs']}: no object seen to anchor a move to")
        plane_h = float(-scene.plane.offset / scene.plane.normal[2]) if abs(scene.plane.normal[2]) > 1e-6 else 0.0
        top_z = plane_h + float(obj.top)
        feature = "top_face" if T_end[2, 3] >= top_z - 0.005 else "centre"
        anchor = rs.Anchor.from_cluster(obj, scene.plane.normal, names[obj.id][0])
        rule = rs.relate(T_end, anchor, feature, ref)
        if float(np.linalg.norm(rule["offset_m"])) > MAX_OFFSET_M:
            raise ValueError(f"a target {np.linalg.norm(rule['offset_m']):.2f} m from the nearest object "
                             f"({names[obj.id][1]}): too far to be about it")
        role, prompt = names[obj.id]
        objects[role] = {"prompt": prompt, "class": obj.shape_name}
        pos = np.array([p[:3] for p in poses])
        spacing = np.linalg.norm(np.diff(np.vstack([here[None, :3], pos]), axis=0), axis=1)
        rid = f"r{len(rules) + 1}"
        # the spacing the round used, within what a rule may ask (a turn in place has none; one
        # long waypoint is interpolated by the runner anyway)
        step = min(max(float(np.median(spacing)), 0.002), 0.04)
        rule.update(id=rid, approach={"step_m": round(step, 4)}, gripper=round(g_end, 3),
                    stop={"kind": "reached"})
        rule["anchor"]["object"] = role
        rules.append(rule)
        steps.append({"move": rid})
        targets[rid] = [float(v) for v in last[:6]]
        here, grip = np.asarray(last[:6], dtype=float), g_end
    # every perceived object the trace names (checks may be about one no rule is anchored to)
    for o in scene.objects:
        role, prompt = names[o.id]
        if role in roles_of_native.values():
            objects.setdefault(role, {"prompt": prompt, "class": o.shape_name})
    return {"steps": steps, "rules": rules, "objects": objects, "targets": targets,
            "reference": [float(v) for v in state["ee_pose"]], "roles_of_native": roles_of_native,
            "seen": [o.describe() for o in list(scene.objects) + marks]}


def check(req: dict) -> dict:
    skill = req["skill"]
    lint = []
    for stage in skill.get("procedure", []):
        if stage.get("code"):
            try:
                rs.check_code(stage["code"], f"stage {stage.get('name')}")
            except rs.LintError as e:
                lint.append(str(e))
    runner = rs.SkillRunner(skill, log=lambda e: None)
    errors = []
    for src in req.get("sources", []):
        state = load_obs(src["obs"])
        scene = scene_of(state)
        for rid, pose in src["targets"].items():
            if rid not in runner.rules:
                errors.append({"rule": rid, "error": "no such rule in the skill"})
                continue
            try:
                got = pose_to_matrix(runner.target(rid, scene, state, reference=src["reference"]))
            except rs.AnchorError as e:
                errors.append({"rule": rid, "error": str(e)})
                continue
            dp, dr = rs.same_grasp(got, pose_to_matrix(pose))
            errors.append({"rule": rid, "position_m": dp, "rotation_rad": dr})
    return {"lint": lint, "reinstantiation": errors}


def main() -> int:
    cmd = sys.argv[1] if len(sys.argv) > 1 else ""
    fns = {"relate": relate_round, "perceive": perceive, "check": check}
    if cmd not in fns:
        print(json.dumps({"error": f"usage: skill_tools.py {'|'.join(fns)} < request.json"}))
        return 2
    try:
        out = fns[cmd](json.load(sys.stdin))
    except (ValueError, KeyError, OSError, rs.AnchorError) as e:
        print(json.dumps({"error": f"{type(e).__name__}: {e}"}))
        return 2
    print(json.dumps(out, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
