"""Host-side skill geometry for `r2g skills ...` (trusted; never in the sandbox). One JSON request
on stdin, one JSON answer on stdout; errors as {"error": "..."} with exit status 2.

    skill_tools.py relate_record {"rounds": [{"round": n, "obs": npz, "obs_after": npz,
                                  "native": {"block": [x, y, z], ...}, "native_after": {...},
                                  "calls": [...], "relate": bool, "pushed": [...],
                                  "gripper_commanded": g}, ...]}
        Every executed round of a record expressed against the objects seen at its start. One
        perception tracker runs over the record's observations in order, and the trace's object
        positions (`native`) say which perceived object is which scene object, so each scene
        object has one role for the whole record (`Identities`). Each chunk becomes a step (a
        move bound to an object anchor, a gripper change or a hold); a rule's anchor, offset and
        yaw are computed from the chunk's final target (robo_skills.relate), with the TCP
        measured at the round's start as the reference. A target about a line while the round
        pushed an object gets that object as a second anchor along the line; moves made holding
        a fixture's part (a drawer's handle) are about that part.
    skill_tools.py relate   {"obs": npz, "calls": [...], "native": {...}, "history": [npz, ...]}
        The same for one round (`history`: the observations before it, for the tracker).
    skill_tools.py targets  {"obs": npz, "calls": [...]}
        A round's steps and move targets from its calls alone (no perception).
    skill_tools.py perceive {"obs": npz}
        The objects perception finds: colour, shape, prompt, centre, sides.
    skill_tools.py offer    {"obs": npz, "skills": [{...}, ...]}
        `perceive`, and the pose every rule of each skill binds to in that observation (each
        stage with the hand where the previous stage leaves it).
    skill_tools.py check    {"skill": {...}, "sources": [{"obs": npz, "history": [npz, ...],
                                                          "reference": pose, "targets": {rule: pose}}]}
        Code lint (robo_skills.lint) and compile for every stage's code, and the rules bound
        again on the recorded observations (the tracker carried over `history` first): position
        and rotation error against the recorded targets, per rule.
"""
from __future__ import annotations

import json
import os
import sys
from typing import Any, Optional

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "lib"))

import robo_perception as rp  # noqa: E402
import robo_skills as rs  # noqa: E402
from robo_perception.transforms import matrix_to_pose, pose_to_matrix  # noqa: E402

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
    return perceive_scene(scene_of(load_obs(req["obs"])))


def perceive_scene(scene) -> dict:
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


def motion(calls: list, state: dict) -> list[dict]:
    """The steps of a round's executed chunks, from the calls alone (no perception): a move
    (its final target, gripper, waypoint spacing), a gripper change or a hold. Chunks that were
    refused or failed are left out; so is everything before the round's last reset() (the
    caller passes only the calls that count)."""
    here = np.asarray(state["ee_pose"], dtype=float)
    grip = float(state["gripper"][0])
    out = []
    for call in calls:
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
                out.append({"gripper": "close" if g_end > grip else "open", "settle_s": round(n / hz, 3)})
            else:
                out.append({"hold_s": round(n / hz, 3)})
            grip = g_end
            continue
        pos = np.array([p[:3] for p in poses])
        spacing = np.linalg.norm(np.diff(np.vstack([here[None, :3], pos]), axis=0), axis=1)
        # the spacing the round used, within what a rule may ask (a turn in place has none; one
        # long waypoint is interpolated by the runner anyway)
        step = min(max(float(np.median(spacing)), 0.002), 0.04)
        out.append({"move": f"r{sum('move' in m for m in out) + 1}", "target": [float(v) for v in last[:6]],
                    "gripper_from": grip, "gripper_to": g_end, "step_m": round(step, 4)})
        here, grip = np.asarray(last[:6], dtype=float), g_end
    return out


NATIVE_GATE_M = 0.04   # a scene object and a perceived one this close in the plane are the same


class Identities:
    """One role per scene object for a whole record. Perception's tracker (carried over the
    record's observations in order) keeps a cluster's number and first name; the native trace's
    object positions say which scene object each track is, so a track that is lost and found
    again as a new one, or renamed, still gets the scene object's role. Each role is named once,
    at its first sighting (colour and shape, a position word when two look alike, a number when
    even that is taken), and never changes: the same bowl is never two roles, and two objects
    are never one."""

    def __init__(self) -> None:
        self.native_of_track: dict[int, str] = {}
        self.role_of_native: dict[str, str] = {}
        self.role_of_track: dict[int, str] = {}
        self.spec: dict[str, dict] = {}   # role -> {"prompt", "class"}

    def observe(self, scene, native: dict, held: Optional[list] = None) -> None:
        """Names the tracks of `scene` by the scene objects the trace places at `native` (name ->
        position); `held`: the scene objects the fingers hold then, by the trace: a cluster
        perception flags held is that object even where the fingers leave only a slice of it
        in view, off its centre (a bowl held by its rim)."""
        seen_natives = {n for t, n in self.native_of_track.items() if any(o.track_id == t for o in scene.objects)}
        pairs = []
        for name, p in native.items():
            if name in seen_natives:
                continue
            for o in scene.objects:
                if o.track_id in self.native_of_track:
                    continue
                d = float(np.linalg.norm(np.asarray(o.center)[:2] - np.asarray(p)[:2]))
                if d < NATIVE_GATE_M:
                    pairs.append((d, name, o.track_id))
        pairs.sort()
        used_n, used_t = set(), set()
        for _, name, tid in pairs:
            if name in used_n or tid in used_t:
                continue
            used_n.add(name)
            used_t.add(tid)
            self.native_of_track[tid] = name
        free_held = [n for n in (held or []) if n not in seen_natives and n not in used_n]
        held_clusters = [o for o in scene.objects if o.held and o.track_id not in self.native_of_track]
        if len(free_held) == 1 and len(held_clusters) == 1:
            self.native_of_track[held_clusters[0].track_id] = free_held[0]
        for o in scene.objects:
            n = self.native_of_track.get(o.track_id)
            if n is not None and n not in self.role_of_native:
                # A track named before the trace placed it keeps its name for the scene object.
                self.role_of_native[n] = self.role_of_track.get(o.track_id) or self._name(o, scene)
            elif n is None and o.track_id not in self.role_of_track:
                self.role_of_track[o.track_id] = self._name(o, scene)

    def _name(self, o, scene) -> str:
        prompt = f"{o.color_name} {o.shape_name}"
        twins = [p for p in scene.objects if (p.color_name, p.shape_name) == (o.color_name, o.shape_name)]
        taken = lambda r: r in self.spec  # noqa: E731
        if len(twins) > 1 or taken(prompt.replace(" ", "_")):
            for word in ("left", "right", "front", "back", "largest", "smallest"):
                ranked = rp.rank_objects(scene, f"{prompt} {word}")
                if ranked and ranked[0][0] is o and not taken(f"{word}_{prompt}".replace(" ", "_")):
                    prompt = f"{word} {prompt}"
                    break
        role = prompt.replace(" ", "_")
        k = 2
        while taken(role):
            role = f"{prompt.replace(' ', '_')}_{k}"
            k += 1
        self.spec[role] = {"prompt": prompt, "class": o.shape_name}
        return role

    def role(self, o) -> str:
        n = self.native_of_track.get(o.track_id)
        return self.role_of_native[n] if n is not None else self.role_of_track[o.track_id]

    def is_native(self, o) -> bool:
        return o.track_id in self.native_of_track


NEAR_M = 0.02          # a target inside an object's box grown by this is at that object
PART_NEAR_M = 0.03     # a held part whose box, grown by this, holds the TCP is in the hand
GRIP_CLOSED = 0.5      # a gripper command above this keeps the hand closed on what it holds


def _elongated(o) -> bool:
    """A line or a bar: the shape robo_skills faces across (frames.LINE_RATIO)."""
    e = np.asarray(o.obb.extents, dtype=float)
    return float(e[0]) > 1e-9 and float(e[1] / e[0]) < rs.frames.LINE_RATIO


def relate_scene(scene, state: dict, calls: list, ident: Identities, ctx: dict) -> dict:
    """The motion of one executed round expressed against the objects seen at its start (see
    the module text); ``ctx``: "pushed" (roles of scene objects the round moved without lifting
    or grasping them), "gripper_commanded" (the gripper value last commanded before the round)."""
    ref = pose_to_matrix(state["ee_pose"])
    steps, rules, objects, targets = [], [], {}, {}
    # In the hand: what perception calls held, when the gripper had been commanded closed (a
    # bar between half-open fingers is not held yet).
    commanded = ctx.get("gripper_commanded")
    held_ids = {o.id for o in scene.objects if o.held and (commanded is None or float(commanded) > 0.0)}
    # Objects, and marks on the table: a target beyond a line is about the line.
    marks = markings(scene)
    mark_role = {m.id: (f"{m.color_name}_marking", f"{m.color_name} marking") for m in marks}

    def role_of(o) -> tuple[str, str, str]:
        if o.id in mark_role:
            r, p = mark_role[o.id]
            return r, p, "marking"
        r = ident.role(o)
        return r, ident.spec[r]["prompt"], ident.spec[r]["class"]

    free = [o for o in scene.objects if o.id not in held_ids] + marks
    held = [o for o in scene.objects if o.id in held_ids]
    tcp0 = np.asarray(state["ee_pose"], dtype=float)[:3]
    # A fixture's part in the hand (a drawer's handle: no scene object of the trace): moves made
    # with the fingers kept closed are about it as it was when the round began (pull 2 cm, 4 cm,
    # ... from it), wherever they lead.
    parts = [o for o in held if not ident.is_native(o) and bool(o.obb.contains(tcp0[None], margin=PART_NEAR_M)[0])]
    part = min(parts, key=lambda o: float(np.linalg.norm(np.asarray(o.center) - tcp0)), default=None)
    pushed_roles = set(ctx.get("pushed") or [])
    pushed = [o for o in scene.objects if o.id not in held_ids and ident.is_native(o) and ident.role(o) in pushed_roles]
    for m in motion(calls, state):
        if "move" not in m:
            steps.append(m)
            continue
        T_end = pose_to_matrix(m["target"])
        tp = T_end[:3, 3]

        def xy_dist(o) -> float:
            return float(np.linalg.norm(np.asarray(o.center)[:2] - tp[:2]))

        # The object this target is about: a fixture's part being pulled or pushed (above);
        # else the object in the hand when the target is right above it (a lift: whatever else
        # perception sees near the hand then, a slice of the arm included, is not what a lift is
        # about); else one the target is at (inside its box grown by 2 cm; the smallest such: a
        # handle before its cabinet); else one it is over (within its footprint), of those not
        # in the hand when the round began; else the nearest free one in the plane (a mark on the
        # table included); else the held one.
        at = [o for o in free if bool(o.obb.contains(tp[None], margin=NEAR_M)[0])]
        over = [o for o in free if bool(o.obb.contains(np.array([[tp[0], tp[1], float(o.center[2])]]), margin=0.01)[0])]
        pulling = part is not None and m["gripper_to"] > GRIP_CLOSED and m["gripper_from"] > GRIP_CLOSED
        # A lift: the hand, closed on a scene object, moves up from where it holds it (a bowl
        # held by its rim is lifted from its rim, off the bowl's centre).
        straight_up = float(np.linalg.norm(tp[:2] - tcp0[:2])) < HELD_ABOVE_M and tp[2] > tcp0[2]
        lifting = [o for o in held if ident.is_native(o)] if straight_up and m["gripper_from"] > GRIP_CLOSED else []
        if pulling:
            obj = part
        elif lifting:
            obj = min(lifting, key=lambda o: float(np.linalg.norm(np.asarray(o.center) - tcp0)))
        elif at:
            obj = min(at, key=lambda o: float(np.prod(np.maximum(o.obb.extents, 0.005))))
        elif over:
            obj = min(over, key=xy_dist)
        elif held and min(map(xy_dist, held)) < HELD_ABOVE_M:
            obj = min(held, key=xy_dist)
        else:
            obj = min(free, key=xy_dist, default=None)
            if obj is None or (held and xy_dist(obj) > HELD_FALLBACK_M):
                obj = min(held, key=xy_dist, default=obj)
        if obj is None:
            raise ValueError("no object seen to anchor a move to")
        plane_h = float(-scene.plane.offset / scene.plane.normal[2]) if abs(scene.plane.normal[2]) > 1e-6 else 0.0
        top_z = plane_h + float(obj.top)
        feature = "top_face" if tp[2] >= top_z - 0.005 else "centre"
        if pulling:
            feature = "in_hand"
        role, prompt, cls = role_of(obj)
        anchor = rs.Anchor.from_cluster(obj, scene.plane.normal, role)
        # A target about a line (or a bar) while the round pushed an object: "past the line" is
        # measured from the line, and where along the line from the object pushed.
        second = None
        if feature != "in_hand" and _elongated(obj) and pushed:
            near = min(pushed, key=xy_dist)
            if near is not obj:
                second = near
        if second is not None:
            r2, p2, c2 = role_of(second)
            rule = rs.relate(T_end, anchor, feature, ref, second=rs.Anchor.from_cluster(second, scene.plane.normal, r2),
                             along=("x",))
            rule["second_anchor"]["object"] = r2
            objects[r2] = {"prompt": p2, "class": c2}
        else:
            rule = rs.relate(T_end, anchor, feature, ref)
        if float(np.linalg.norm(rule["offset_m"])) > MAX_OFFSET_M:
            raise ValueError(f"a target {np.linalg.norm(rule['offset_m']):.2f} m from the nearest object "
                             f"({prompt}): too far to be about it")
        objects[role] = {"prompt": prompt, "class": cls}
        rid = m["move"]
        rule.update(id=rid, approach={"step_m": m["step_m"]}, gripper=round(m["gripper_to"], 3),
                    stop={"kind": "reached"})
        rule["anchor"]["object"] = role
        rules.append(rule)
        steps.append({"move": rid})
        targets[rid] = m["target"]
    grip_end = float(state["gripper"][0])
    for call in calls:
        poses = _chunk_poses(call, state) if call.get("fn") == "post_actions" and call.get("result") == 1 else []
        if poses and len(poses[-1]) > 6:
            grip_end = float(poses[-1][6])
    return {"steps": steps, "rules": rules, "objects": objects, "targets": targets,
            "reference": [float(v) for v in state["ee_pose"]], "gripper_end": grip_end,
            "part": role_of(part)[0] if part is not None and any(r["anchor"]["object"] == role_of(part)[0] for r in rules) else None,
            "seen": [o.describe() for o in list(scene.objects) + marks]}


def relate_record(req: dict) -> dict:
    """Every round of a record against the objects seen at its start, with one tracker carried
    over the observations in order (see `Identities`). Request: {"rounds": [{"round": n, "obs":
    npz, "obs_after": npz, "native": {...}, "native_after": {...}, "calls": [...], "relate": bool,
    "pushed": [native names], "gripper_commanded": g}]}, the rounds in order from the episode's last
    reset() on. Answer: {"rounds": {"n": geometry or {"error": why}}, "roles_of_native": {...}}."""
    tracker = rp.Tracker()
    ident = Identities()
    scenes: dict[str, tuple] = {}
    unreadable: dict[str, str] = {}

    def seen(path: Optional[str], native: Optional[dict], held: Optional[list] = None):
        """An observation, segmented with the record's tracker; an observation that cannot be read
        or segmented costs only the rounds that need it (named in `unreadable`)."""
        if not path or path in unreadable:
            return None
        if path not in scenes:
            try:
                state = load_obs(path)
                scene = rp.segment_scene(state, tracker=tracker)
            except Exception as e:  # noqa: BLE001 - a broken file is one round's problem
                unreadable[path] = f"{type(e).__name__}: {e}"
                return None
            ident.observe(scene, {k: np.asarray(v, dtype=float) for k, v in (native or {}).items()}, held)
            scenes[path] = (scene, state)
        return scenes[path]

    order = req.get("rounds") or []
    for r in order:
        seen(r.get("obs"), r.get("native"), r.get("held"))
        seen(r.get("obs_after"), r.get("native_after"), r.get("held_after"))
    out = {}
    for r in order:
        if not r.get("relate"):
            continue
        key = str(r["round"])
        if not r.get("obs") or r["obs"] not in scenes:
            why = unreadable.get(r.get("obs") or "")
            out[key] = {"error": f"the observation from the round's start could not be read: {why}" if why
                        else "the record has no observation from the round's start"}
            continue
        scene, state = scenes[r["obs"]]
        pushed_roles = [ident.role_of_native[n] for n in r.get("pushed") or [] if n in ident.role_of_native]
        try:
            g = relate_scene(scene, state, r.get("calls") or [], ident,
                             {"pushed": pushed_roles, "gripper_commanded": r.get("gripper_commanded")})
        except Exception as e:  # noqa: BLE001 - one round that cannot be related is skipped alone
            out[key] = {"error": f"{type(e).__name__}: {e}"}
            continue
        # every perceived scene object the trace names (checks may be about one no rule is anchored to)
        for o in scene.objects:
            if ident.is_native(o):
                g["objects"].setdefault(ident.role(o), dict(ident.spec[ident.role(o)]))
        g["roles_of_native"] = dict(ident.role_of_native)
        # How far perception saw the fixture part in the hand move over the round (a drawer's
        # handle pulled with it): checked where the trace shows its joint moved.
        after = scenes.get(r.get("obs_after") or "")
        g["part_moved_m"] = None
        if after is not None and g["part"] is not None:
            then = [o for o in scene.objects if not ident.is_native(o) and ident.role(o) == g["part"]]
            now = [o for o in after[0].objects if not ident.is_native(o) and ident.role(o) == g["part"]]
            if then and now:
                g["part_moved_m"] = float(np.linalg.norm(np.asarray(now[0].center) - np.asarray(then[0].center)))
        out[key] = g
    return {"rounds": out, "roles_of_native": dict(ident.role_of_native)}


def relate_round(req: dict) -> dict:
    """One round (`relate`): the observations before it (``history``) carry the tracker."""
    rounds = [{"round": -1 - i, "obs": p, "relate": False} for i, p in enumerate(req.get("history") or [])]
    rounds.append({"round": 0, "obs": req["obs"], "calls": req.get("calls", []), "native": req.get("native"),
                   "relate": True})
    g = relate_record({"rounds": rounds})["rounds"]["0"]
    if "error" in g:
        raise ValueError(f"{req['obs']}: {g['error']}")
    return g


def targets(req: dict) -> dict:
    """The steps and targets of a round's calls (what `relate` moves by), without perception."""
    state = load_obs(req["obs"])
    steps, out = [], {}
    for m in motion(req.get("calls", []), state):
        if "move" in m:
            out[m["move"]] = m["target"]
            steps.append({"move": m["move"]})
        else:
            steps.append(m)
    return {"steps": steps, "targets": out, "reference": [float(v) for v in state["ee_pose"]]}


def offer(req: dict) -> dict:
    """What an episode's first observation shows (as `perceive`) and, for each skill given, the
    pose each rule binds to in it (rule id -> pose [x, y, z, ax, ay, az] base frame, or
    {"error": why}). The first stage's rules take the TCP measured now as their reference; each
    later stage the pose its previous stage's last move binds to (where the hand will be when
    it begins, if the objects are where they are now); an in_hand rule is bound to that pose as
    if the previous stage left the part in the hand."""
    state = load_obs(req["obs"])
    scene = scene_of(state)
    bound = {}
    for skill in req.get("skills", []):
        runner = rs.SkillRunner(skill, log=lambda e: None)
        poses: dict = {}
        ref = [float(v) for v in state["ee_pose"]]
        for stage in skill.get("procedure", []):
            last = None
            for step in stage.get("steps", []):
                rid = step.get("move")
                rule = runner.rules.get(rid) if rid else None
                if rule is None:
                    continue
                try:
                    if (rule.get("anchor") or {}).get("feature") == "in_hand":
                        hand = rs.Anchor(np.zeros(3), np.eye(3), np.full(3, 0.01), np.asarray(scene.plane.normal, dtype=float))
                        pose = matrix_to_pose(rs.bind(rule, hand, ref))
                    else:
                        pose = runner.target(rid, scene, state, reference=ref)
                    poses[rid] = [round(float(v), 4) for v in pose]
                    last = [float(v) for v in pose]
                except Exception as e:  # noqa: BLE001 - one rule that cannot be bound is that rule's note
                    # the reason, without the list of everything seen (the prompt shows the scene)
                    poses[rid] = {"error": str(e).split("; seen:")[0].split(" Seen:")[0][:160]}
            if last is not None:
                ref = last
        bound[skill.get("id", "?")] = poses
    return {**perceive_scene(scene), "bound": bound,
            "reference": [round(float(v), 4) for v in state["ee_pose"]]}


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
        # The tracker carried over the record's observations up to this one, as extraction did:
        # an object keeps the name it had when first seen.
        tracker = rp.Tracker()
        for path in src.get("history") or []:
            rp.segment_scene(load_obs(path), tracker=tracker)
        state = load_obs(src["obs"])
        scene = rp.segment_scene(state, tracker=tracker)
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
    fns = {"relate": relate_round, "relate_record": relate_record, "targets": targets, "perceive": perceive,
           "check": check, "offer": offer}
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
