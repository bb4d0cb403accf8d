"""Running a skill's procedure with `robo` and no model: each stage observes, binds its motion
rules to the objects it sees now (frames.bind), moves, and checks its effects on a fresh
observation; a stage whose check fails is retried from a new observation as often as the
skill allows, then the run stops with the reason.

Used by `r2g skills run` (one sandboxed program per run) and importable by stage programs:

    import robo_skills as rs
    runner = rs.SkillRunner(skill)            # the skill's JSON as a dict
    result = runner.run()                     # {"ok": bool, "stages": [...], "reason": ...}

or one rule at a time inside a program of one's own:

    scene, state = runner.observe()
    pose = runner.target("approach_item", scene, state)   # [x, y, z, ax, ay, az] for post_actions
"""

from __future__ import annotations

import json
import time
from typing import Any, Callable, Optional

import numpy as np

import robo_perception as rp
from robo_perception.transforms import matrix_to_pose, pose_to_matrix

from .frames import Anchor, AnchorError, bind
from .lint import LintError, check_code

CAMERAS = ("agentview", "wrist")
MAX_STEP_M, MAX_STEP_RAD = 0.04, 0.30  # under the runtime's 5 cm / 0.35 rad caps
CHUNK = 200                            # waypoints per post_actions call (cap 256)
CONTACT_CHUNK = 4                      # waypoints between force checks when stopping on contact


class StageFailed(RuntimeError):
    """A stage could not do what it should: a refused or failed chunk, a failed effect check, an
    object not found. The message is the reason."""


def _robo():
    import robo  # the shim in the sandbox, the real one elsewhere

    return robo


class SkillRunner:
    """Executes ``skill`` (a dict in the skill format, robot-skill/skills/README.md). ``prompts``
    overrides the perception prompt of an object role ({"item": "green block"}); ``log`` gets
    one JSON-able dict per event (default: printed as a JSON line)."""

    def __init__(self, skill: dict, prompts: Optional[dict] = None, cameras=CAMERAS,
                 log: Optional[Callable[[dict], None]] = None, absolute: Optional[dict] = None) -> None:
        self.skill = skill
        self.rules = {r["id"]: r for r in skill.get("rules", [])}
        self.objects = {k: dict(v) for k, v in (skill.get("objects") or {}).items()}
        for role, prompt in (prompts or {}).items():
            self.objects.setdefault(role, {})["prompt"] = prompt
        self.cameras = list(cameras)
        self.log = log or (lambda e: print(json.dumps(e), flush=True))
        self.tracker = rp.Tracker()
        self.gripper = -1.0
        # Baseline only (never part of a skill): rule id -> fixed [x, y, z, ax, ay, az] targets,
        # the original episode's absolute poses, played where the objects may no longer be.
        self.absolute = absolute or {}

    # ---- observation and anchors ----

    def observe(self) -> tuple[Any, dict]:
        robo = _robo()
        state = robo.get_state(self.cameras, raw=True)
        scene = rp.segment_scene(state, tracker=self.tracker)
        return scene, state

    def find(self, role: str, scene) -> Any:
        """The cluster of object role ``role`` in ``scene``: its prompt's best match; an error
        when nothing matches or when two objects match equally well and nothing in the prompt
        orders them."""
        spec = self.objects.get(role)
        if not spec or not spec.get("prompt"):
            raise AnchorError(f"object role {role!r} has no perception prompt (roles: {', '.join(self.objects) or 'none'})")
        prompt = spec["prompt"]
        if spec.get("class") == "marking":
            return self._marking(role, prompt, scene)
        ranked = rp.rank_objects(scene, prompt)
        seen = "; ".join(o.describe() for o in scene.objects) or "nothing"
        if not ranked:
            raise AnchorError(f"no object matches {prompt!r} (role {role!r}); seen: {seen}")
        if len(ranked) > 1 and not rp.parse_prompt(prompt)["spatial"] and ranked[1][1] >= ranked[0][1] - 1e-9:
            raise AnchorError(f"{prompt!r} (role {role!r}) is ambiguous: {len([r for r in ranked if r[1] >= ranked[0][1] - 1e-9])} "
                              f"objects match equally well; add a colour, shape or position word. Seen: {seen}")
        return ranked[0][0]

    def _marking(self, role: str, prompt: str, scene) -> Any:
        """A coloured mark on the support plane (rp.find_markings): the largest of its colour;
        two of nearly the same size are ambiguous."""
        found = rp.find_markings(scene, prompt.split()[0])
        if not found:
            raise AnchorError(f"no {prompt!r} on the support plane (role {role!r})")
        if len(found) > 1 and len(found[1].points) >= 0.8 * len(found[0].points):
            raise AnchorError(f"{prompt!r} (role {role!r}) is ambiguous: {len(found)} marks of that colour of similar size")
        return found[0]

    def anchor(self, role: str, scene) -> Anchor:
        # A skill of schema 1 was extracted and admitted before the line frame (frames.py).
        lines = int(self.skill.get("schema", 1)) >= 2
        return Anchor.from_cluster(self.find(role, scene), scene.plane.normal, role, lines=lines)

    def in_hand(self, role: str, scene, state: dict) -> Anchor:
        """The anchor of an ``in_hand`` rule: the object is not looked for (seen through the
        fingers it is too rough to pull by); the gripper must hold something."""
        g = float(state["gripper"][0])
        if not -0.95 < g < 0.95:
            raise AnchorError(f"object role {role!r} should be in the hand (an in_hand rule) but the gripper reads "
                              f"{g:+.2f}: open or closed on nothing")
        return Anchor(np.zeros(3), np.eye(3), np.full(3, 0.01), np.asarray(scene.plane.normal, dtype=float), "box", role)

    def target(self, rule_id: str, scene, state: dict, reference=None) -> list[float]:
        """The TCP pose rule ``rule_id`` asks for in this scene (reference: the TCP pose the stage
        began with; default the measured one)."""
        rule = self.rules[rule_id]
        if rule_id in self.absolute:
            return [float(v) for v in self.absolute[rule_id]]
        ref = state["ee_pose"] if reference is None else reference
        spec = rule.get("second_anchor")
        second = self.anchor(spec["object"], scene) if spec else None
        role = rule["anchor"]["object"]
        first = self.in_hand(role, scene, state) if rule["anchor"].get("feature") == "in_hand" else self.anchor(role, scene)
        T = bind(rule, first, ref, second=second)
        return matrix_to_pose(T)

    # ---- motion ----

    def _post(self, poses: list, gripper: float, what: str) -> bool:
        """Posts the poses in chunks. A refused chunk (nothing moved) fails the stage. A chunk the
        arm could not finish because something stopped it ("not reached": the hand touched
        down, a held object met its support) ends this motion where the arm is; the stage's
        checks then judge whether that was the effect wanted. Returns False when it stopped
        short, True when every pose was reached."""
        robo = _robo()
        for k in range(0, len(poses), CHUNK):
            chunk = rp.waypoints(poses[k:k + CHUNK], gripper)
            if not robo.post_actions({"actions": chunk, "type": "ee_pose", "freq": ""}):
                fb = robo.get_state([])["control_feedback"]
                reason = str(fb.get("reason") or "")
                if fb.get("status") == "failed" and reason.startswith("not reached"):
                    self.log({"event": "stopped_short", "what": what, "executed": fb.get("executed"), "reason": reason})
                    self.gripper = gripper
                    return False
                raise StageFailed(f"{what}: {fb.get('status')} after {fb.get('executed')} waypoints: {reason}")
        self.gripper = gripper
        return True

    def move(self, rule_id: str, goal: list) -> None:
        robo = _robo()
        rule = self.rules.get(rule_id, {})
        step = float((rule.get("approach") or {}).get("step_m", MAX_STEP_M))
        step = min(max(step, 0.002), MAX_STEP_M)
        grip = float(rule.get("gripper", self.gripper))
        here = robo.get_state([])["ee_pose"]
        appr = rule.get("approach") or {}
        dist = float(appr.get("distance_m", 0.0))
        path = []
        if dist > 0 and appr.get("axis") is not None:
            # pre-pose: back off the goal along the approach axis (in the goal's TCP frame)
            G = pose_to_matrix(goal)
            axis_base = self._approach_axis_base(rule, G)
            pre = G.copy()
            pre[:3, 3] -= dist * axis_base
            path += rp.interpolate_poses(here, matrix_to_pose(pre), max_step_m=MAX_STEP_M, max_step_rad=MAX_STEP_RAD)
            start = matrix_to_pose(pre)
        else:
            start = here
        final = rp.interpolate_poses(start, goal, max_step_m=step, max_step_rad=MAX_STEP_RAD)
        stop = (rule.get("stop") or {}).get("kind", "reached")
        if stop == "contact":
            if path and not self._post(path, grip, f"rule {rule_id}: to the pre-pose"):
                return  # stopped before the approach even began: the checks judge
            limit = float(rule["stop"].get("force_n", 5.0))
            for k in range(0, len(final), CONTACT_CHUNK):
                if not self._post(final[k:k + CONTACT_CHUNK], grip, f"rule {rule_id}"):
                    # The runtime stopped the arm short: that is the contact; never push on.
                    self.log({"event": "contact", "rule": rule_id, "stopped_short": True})
                    return
                f = robo.get_state([]).get("external_force_n") or [0.0]
                if float(np.linalg.norm(np.asarray(f, dtype=float))) > limit:
                    self.log({"event": "contact", "rule": rule_id, "force_n": [float(v) for v in f]})
                    return
            return
        self._post(path + final, grip, f"rule {rule_id}")

    def _approach_axis_base(self, rule: dict, goal: np.ndarray) -> np.ndarray:
        # The approach axis is given in the TCP frame of the bound goal, so it turns with the
        # object: [0, 0, 1] is "along the fingers", straight down for a top-down grasp.
        a = np.asarray(rule["approach"]["axis"], dtype=float)
        a = a / max(np.linalg.norm(a), 1e-12)
        return goal[:3, :3] @ a

    def grip(self, value: float, settle_s: float) -> None:
        robo = _robo()
        here = robo.get_state([])["ee_pose"]
        n = max(2, int(round(settle_s * 20)))
        self._post([here] * n, value, f"gripper to {value:+.1f}")

    # ---- effect checks ----

    def check(self, c: dict, scene, state: dict, start: dict) -> tuple[bool, str]:
        """One machine-checkable effect on a fresh observation; (passed, what was measured)."""
        kind = c["kind"]
        g = float(state["gripper"][0])
        if kind == "holding":
            ok = -0.95 < g < 0.95
            return ok, f"gripper {g:+.2f} ({'stopped on something' if ok else 'open or closed on nothing'})"
        if kind == "released":
            return g <= -0.9, f"gripper {g:+.2f}"
        if kind in ("lifted", "moved"):
            o = self.find(c["object"], scene)
            c0 = start.get(c["object"])
            if c0 is None:
                raise AnchorError(f"check {kind}: object {c['object']!r} was not seen when the stage began")
            d = np.asarray(o.center) - c0
            if kind == "lifted":
                return float(d[2]) >= float(c.get("min_m", 0.03)), f"{c['object']} rose {d[2]:.3f} m"
            return float(np.linalg.norm(d)) >= float(c.get("min_m", 0.01)), f"{c['object']} moved {np.linalg.norm(d):.3f} m"
        if kind == "on":
            # Rests on the support, or in it (a bowl in a bowl, a cup in a box): over its
            # footprint, its lowest points at the support's top or between its top and bottom.
            o, s = self.find(c["object"], scene), self.find(c["support"], scene)
            tol = float(c.get("tolerance_m", 0.02))
            local = s.obb.to_local(np.asarray(o.center)[None])[0]
            inside = bool(np.all(np.abs(local[:2]) <= s.obb.extents[:2] / 2.0 + tol))
            n, off = scene.plane.normal, scene.plane.offset
            h_obj = np.asarray(o.points) @ n + off
            # The support's top away from the object (points of one may sit on the other's box).
            sp = np.asarray(s.points)
            far = np.linalg.norm((sp - np.asarray(o.center))[:, :2], axis=1) > 0.5 * float(np.max(o.obb.extents[:2])) + 0.01
            h_sup = (sp[far] if far.any() else sp) @ n + off
            bottom, top = float(np.percentile(h_obj, 2)), float(np.percentile(h_sup, 90))
            gap = bottom - top
            within = gap < 0 and bottom >= float(np.min(h_sup)) - tol
            ok = inside and (abs(gap) <= tol or within)
            where = "in" if within else ("over" if inside else "beside")
            return ok, f"{c['object']} {where} {c['support']}, bottom {gap:+.3f} m from its top"
        raise ValueError(f"unknown effect check {kind!r}")

    # ---- the procedure ----

    def run_stage(self, stage: dict) -> None:
        scene, state = self.observe()
        ref = state["ee_pose"]
        start = {}
        for role in self.objects:
            try:
                start[role] = np.asarray(self.find(role, scene).center, dtype=float)
            except AnchorError:
                pass
        for step in stage.get("steps", []):
            if "move" in step:
                goal = self.target(step["move"], scene, state, reference=ref)
                self.move(step["move"], goal)
            elif "gripper" in step:
                self.grip(1.0 if step["gripper"] == "close" else -1.0, float(step.get("settle_s", 0.6)))
            elif "hold_s" in step:
                self.grip(self.gripper, float(step["hold_s"]))
        if stage.get("code"):
            # Stage code (linted before the run: no base-frame numbers) sees the runner and a fresh
            # observation; anything it raises fails the stage.
            scene, state = self.observe()
            env = {"runner": self, "scene": scene, "state": state, "rp": rp, "np": np, "__name__": "__skill_stage__"}
            try:
                exec(compile(stage["code"], f"<skill stage {stage['name']}>", "exec"), env)
            except (StageFailed, AnchorError):
                raise
            except Exception as e:  # noqa: BLE001 - the stage's own code failed: the stage failed
                raise StageFailed(f"stage {stage['name']}: its code raised {type(e).__name__}: {e}") from None
        if stage.get("checks"):
            scene, state = self.observe()
            for c in stage["checks"]:
                ok, what = self.check(c, scene, state, start)
                self.log({"event": "check", "stage": stage["name"], "check": c["kind"], "ok": ok, "measured": what})
                if not ok:
                    raise StageFailed(f"stage {stage['name']}: check {c['kind']} failed ({what})")

    def run(self) -> dict:
        t0 = time.monotonic()
        stages: list[dict] = []
        # Whatever the skill came from (a library or a file given to `r2g skills run`), its
        # code is linted before anything moves.
        for stage in self.skill.get("procedure", []):
            if stage.get("code"):
                try:
                    check_code(stage["code"], f"stage {stage.get('name')}")
                except LintError as e:
                    stages.append({"stage": stage.get("name"), "ok": False, "attempts": 0, "reason": str(e)})
                    return {"ok": False, "stages": stages, "reason": f"refused before running: {e}",
                            "wall_s": time.monotonic() - t0}
        for stage in self.skill.get("procedure", []):
            tries = 1 + int(stage.get("retries", 1))
            for attempt in range(tries):
                try:
                    self.run_stage(stage)
                    stages.append({"stage": stage["name"], "ok": True, "attempts": attempt + 1})
                    self.log({"event": "stage", "stage": stage["name"], "ok": True, "attempt": attempt + 1})
                    break
                except (StageFailed, AnchorError) as e:
                    self.log({"event": "stage", "stage": stage["name"], "ok": False, "attempt": attempt + 1, "reason": str(e)})
                    if attempt + 1 == tries:
                        stages.append({"stage": stage["name"], "ok": False, "attempts": attempt + 1, "reason": str(e)})
                        return {"ok": False, "stages": stages, "reason": str(e), "wall_s": time.monotonic() - t0}
        return {"ok": True, "stages": stages, "reason": None, "wall_s": time.monotonic() - t0}


def run_skill(skill: Any, prompts: Optional[dict] = None, absolute: Optional[dict] = None) -> dict:
    """Runs a skill (dict or JSON text) and prints one final line ``SKILL RESULT {json}``."""
    if isinstance(skill, str):
        skill = json.loads(skill)
    result = SkillRunner(skill, prompts=prompts, absolute=absolute).run()
    print("SKILL RESULT " + json.dumps(result), flush=True)
    return result


__all__ = ["SkillRunner", "StageFailed", "run_skill", "CAMERAS"]
