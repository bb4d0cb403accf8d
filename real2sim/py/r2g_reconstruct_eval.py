"""Scoring `r2g reconstruct` on synthetic frames: a shipped gym rendered by `r2g render` from its
agentview and extra viewpoints (BOP layout), reconstructed, and compared with the gym's own
scene.toml (the truth): object count (missed and spurious), position and size errors of each
object's world bounding box, the gate's reprojection IoU, and `r2g validate` on the
reconstructed gym with the gym's demonstration and success rules.

Used by tests/python/test_reconstruct.py and bench/py/reconstruct_all.py. Synthetic data: the
frames are rendered from the very scenes they are compared with.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import time
import tomllib
from pathlib import Path
from typing import Any, Optional

import numpy as np

import r2g_reconstruct_io as rio

ROOT = Path(__file__).resolve().parents[2]
R2G = ROOT / "target" / "release" / "r2g"


def look_at_entry(pos: list, look: list, fovy_deg: float, width: int = 640, height: int = 480,
                  up: tuple = (0.0, 0.0, 1.0)) -> dict:
    """A BOP scene_camera.json entry for a camera at `pos` looking at `look` (base frame, m)."""
    p, t = np.array(pos, float), np.array(look, float)
    z = t - p
    z /= np.linalg.norm(z)
    x = np.cross(z, np.array(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: world -> camera
    f = 0.5 * height / math.tan(math.radians(fovy_deg) / 2)
    return {"cam_K": [f, 0.0, (width - 1) / 2, 0.0, f, (height - 1) / 2, 0.0, 0.0, 1.0],
            "cam_R_w2c": R.reshape(-1).tolist(), "cam_t_w2c": (-R @ p * 1000).tolist(),
            "depth_scale": 0.1, "width": width, "height": height}


EXTRA_VIEWS = [
    # beside the table on the robot's left and right, looking down at the work area (a camera
    # there sees across a dish rack's slots, not into them)
    {"pos": [0.55, 0.85, 0.75], "look": [0.5, 0.0, 0.03], "fovy": 50.0},
    {"pos": [0.55, -0.85, 0.75], "look": [0.5, 0.0, 0.03], "fovy": 50.0},
    # straight down over the left and right halves of the work area (into open tops and slots:
    # the dish rack's cross bars show only from above)
    {"pos": [0.5, 0.25, 1.3], "look": [0.5, 0.25, 0.0], "fovy": 50.0, "up": [1.0, 0.0, 0.0]},
    {"pos": [0.5, -0.25, 1.3], "look": [0.5, -0.25, 0.0], "fovy": 50.0, "up": [1.0, 0.0, 0.0]},
]


def cameras_for(gym_dir: Path, extra: int = len(EXTRA_VIEWS)) -> dict:
    """The gym's agentview plus `extra` of EXTRA_VIEWS, as a scene_camera.json document."""
    scene = tomllib.loads((gym_dir / "scene.toml").read_text())
    av = next((c for c in scene.get("cameras", []) if c["name"] == "agentview"),
              {"position_m": [1.4, 0.0, 0.95], "look_at_m": [0.3, 0.0, 0.18], "fovy_deg": 50.0})
    doc = {"0": look_at_entry(av["position_m"], av["look_at_m"], av.get("fovy_deg", 45.0),
                              av.get("width", 640), av.get("height", 480))}
    for i, v in enumerate(EXTRA_VIEWS[:extra]):
        doc[str(i + 1)] = look_at_entry(v["pos"], v["look"], v["fovy"], up=tuple(v.get("up", (0.0, 0.0, 1.0))))
    return doc


def run(cmd: list, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=timeout)


def moved_copy(gym: str, to: Path, obj: str, dxy: tuple) -> Path:
    """A copy of a shipped gym with one object moved by dxy (m) and the robot's URDF made
    absolute: the scene a set of synthetic frames is rendered from when the demonstration was
    recorded in another arrangement."""
    src = ROOT / "gyms" / gym
    shutil.copytree(src, to)
    doc = tomllib.loads((src / "scene.toml").read_text())
    urdf = (src / doc["robot"]["urdf"]).resolve()
    lines, inside = [], False
    for ln in (src / "scene.toml").read_text().splitlines():
        if ln.startswith("urdf = "):
            ln = f"urdf = {json.dumps(str(urdf))}"
        if ln.startswith("[["):
            inside = False
        if ln.strip() == f'name = "{obj}"':
            inside = True
        if inside and ln.startswith("position_m = "):
            p = json.loads(ln.split("=", 1)[1])
            p[0] += dxy[0]
            p[1] += dxy[1]
            ln = f"position_m = {json.dumps(p)}"
        lines.append(ln)
    (to / "scene.toml").write_text("\n".join(lines) + "\n")
    return to


def render_frames(gym: str, out: Path, extra: int = len(EXTRA_VIEWS), gym_dir: Optional[Path] = None) -> Path:
    """`gym` (a shipped gym's name, or any gym folder given as gym_dir) rendered from its
    agentview and `extra` more viewpoints into `out` (BOP layout)."""
    gym_dir = gym_dir or ROOT / "gyms" / gym
    cams = out.parent / f"{out.name}.cameras.json"
    cams.write_text(json.dumps(cameras_for(gym_dir, extra)))
    p = run([R2G, "render", gym_dir, "--cameras", cams, "--out", out])
    if p.returncode != 0:
        raise RuntimeError(f"r2g render {gym}: {p.stderr.strip()[-400:]}")
    return out


def add_depth_noise(frames: Path, sigma_mm: float, rel: float = 0.0, seed: int = 0) -> dict:
    """Synthetic sensor noise on rendered frames, in place: every measured depth pixel gets
    Gaussian noise of standard deviation `sigma_mm` + `rel` x its depth (independent per pixel,
    seeded), rounded back to the PNG's units; 0 (no measurement) stays 0. Returns the figures."""
    import r2g_reconstruct_io as rio

    cams = json.loads((frames / "scene_camera.json").read_text())
    rng = np.random.default_rng(seed)
    changed = 0
    for k, c in sorted(cams.items()):
        path = frames / "depth" / f"{int(k):06d}.png"
        d = rio.read_png(path).astype(np.float64)
        scale = float(c["depth_scale"])
        mm = d * scale
        seen = d > 0
        noisy = mm + rng.normal(size=mm.shape) * (sigma_mm + rel * mm)
        units = np.clip(np.rint(noisy / scale), 1, 65535)
        out = np.where(seen, units, 0).astype(np.uint16)
        rio.write_png(path, out)
        changed += int(seen.sum())
    return {"sigma_mm": sigma_mm, "relative": rel, "seed": seed, "pixels": changed}


# --------------------------------------------------------------------------------------------
# Bounding boxes of objects (world frame)
# --------------------------------------------------------------------------------------------

def _quat_mat(q: list) -> np.ndarray:
    import r2g_reconstruct_parts as rparts

    return rparts.quat_matrix(q)


def _part_corners(shape: str, size: list, mesh: Optional[Path], scale: list) -> np.ndarray:
    if shape == "mesh" and mesh is not None:
        V = [list(map(float, ln.split()[1:4])) for ln in mesh.read_text().splitlines() if ln.startswith("v ")]
        return np.array(V) * np.array(scale)
    if shape == "box":
        h = np.array(size[:3])
    elif shape in ("cylinder", "capsule"):
        rr, hl = size[0], size[1] + (size[0] if shape == "capsule" else 0)
        h = np.array([rr, rr, hl])
    elif shape == "sphere":
        h = np.array([size[0]] * 3)
    else:
        return np.zeros((1, 3))
    return np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h


def entity_box(e: dict, scene_dir: Path, is_fixture: bool = False) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """(centre, extents) of an object's or fixture's world bounding box; None for a flat visual
    marking (under 5 mm tall)."""
    parts = e.get("parts") or [{"shape": e.get("shape"), "size_m": e.get("size_m", []), "mesh": e.get("mesh")}]
    return _parts_box(e, parts, scene_dir, is_fixture)


def _axis_angle(axis: list, angle: float) -> np.ndarray:
    a = np.array(axis, float)
    a /= np.linalg.norm(a) or 1.0
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def moving_box(e: dict, scene_dir: Path) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """(centre, extents) of an articulated fixture's moving part (door, drawer) at its joint's
    initial value, world frame."""
    j = e["joint"]
    anchor = np.array(j.get("anchor_m", [0, 0, 0]), float)
    v = float(j.get("initial", 0.0))
    if j.get("kind") == "hinge":
        R, t = _axis_angle(j["axis"], math.radians(v)), np.zeros(3)
    else:
        R, t = np.eye(3), v * np.array(j["axis"], float) / (np.linalg.norm(j["axis"]) or 1.0)
    parts = []
    for p in j.get("parts", []):
        q = dict(p)
        q["position_m"] = (R @ np.array(p.get("position_m", [0, 0, 0]), float) + anchor + t).tolist()
        Rp = R @ _quat_mat(p.get("quat_wxyz", [1, 0, 0, 0]))
        q["_R"] = Rp
        parts.append(q)
    return _parts_box(e, parts, scene_dir, True)


def _parts_box(e: dict, parts: list, scene_dir: Path, is_fixture: bool) -> Optional[tuple[np.ndarray, np.ndarray]]:
    R0 = _quat_mat(e.get("quat_wxyz", [1, 0, 0, 0]))
    p0 = np.array(e["position_m"], float)
    pts = []
    for p in parts:
        if p.get("role") == "visual" and is_fixture:
            continue
        mesh = scene_dir / p["mesh"] if p.get("mesh") else None
        C = _part_corners(p.get("shape") or "", p.get("size_m", []), mesh, p.get("mesh_scale", [1, 1, 1]))
        Rp = p["_R"] if "_R" in p else _quat_mat(p.get("quat_wxyz", [1, 0, 0, 0]))
        pts.append((C @ Rp.T + np.array(p.get("position_m", [0, 0, 0]))) @ R0.T + p0)
    if not pts:
        return None
    P = np.concatenate(pts)
    lo, hi = P.min(0), P.max(0)
    if hi[2] - lo[2] < 0.005:
        return None
    return (lo + hi) / 2, hi - lo


def truth_entities(gym_dir: Path) -> list[dict]:
    s = tomllib.loads((gym_dir / "scene.toml").read_text())
    out = []
    for kind, items in (("object", s.get("objects", [])), ("fixture", s.get("fixtures", []))):
        for k, e in enumerate(items):
            b = entity_box(e, gym_dir, kind == "fixture")
            if b is not None:
                out.append({"name": e["name"], "kind": kind, "centre": b[0], "extent": b[1],
                            "articulated": bool(e.get("joint")), "index": k if kind == "object" else None})
            # A door or drawer stands apart from its body in the frames: its own entity, at the
            # joint's initial value.
            mb = moving_box(e, gym_dir) if kind == "fixture" and e.get("joint") else None
            if mb is not None:
                out.append({"name": f"{e['name']}.{'door' if e['joint'].get('kind') == 'hinge' else 'drawer'}",
                            "kind": "fixture", "centre": mb[0], "extent": mb[1], "articulated": True})
    return out


def recon_entities(gym_dir: Path) -> list[dict]:
    s = tomllib.loads((gym_dir / "scene.toml").read_text())
    out = []
    for k, e in enumerate(s.get("objects", [])):
        b = entity_box(e, gym_dir)
        if b is not None:
            out.append({"name": e["name"], "centre": b[0], "extent": b[1], "free": e.get("free", True), "index": k})
    return out


def true_mask_iou(frames: Path, gym: Path, truth: list, rec: list, pairs: list, out: Path) -> dict:
    """IoU of the reconstruction's render against the true masks of the synthetic frames.

    The gate's IoU compares the render with the reconstruction's own segmentation of the source;
    this one renders the reconstructed gym from the source cameras (`r2g render --cameras`) and
    compares each matched object's mask_visib with the source object's mask_visib, which `r2g
    render` wrote from the true scene. Only objects of the true scene have such masks (fixtures
    do not). Returns {"per_object": {truth name: mean IoU over views}, "mean": ..., "min": ...}.
    """
    p = run([R2G, "render", gym, "--cameras", frames / "scene_camera.json", "--out", out])
    if p.returncode != 0:
        return {"error": (p.stderr.strip().splitlines() or ["?"])[-1]}
    src_ids = list(json.loads((frames / "scene_camera.json").read_text()))
    ren_ids = list(json.loads((out / "scene_camera.json").read_text()))
    stem = lambda i: f"{int(i):06d}" if i.isdigit() else i  # noqa: E731
    per = {}
    for i, j in pairs:
        t, q = truth[i], rec[j]
        if t.get("index") is None:
            continue
        ious = []
        for sid, rid in zip(src_ids, ren_ids):
            tm = frames / "mask_visib" / f"{stem(sid)}_{t['index']:06d}.png"
            rm = out / "mask_visib" / f"{stem(rid)}_{q['index']:06d}.png"
            if not tm.is_file():
                continue
            a = rio.read_png(tm) > 127
            b = rio.read_png(rm) > 127 if rm.is_file() else np.zeros_like(a)
            union = (a | b).sum()
            if union:
                ious.append(float((a & b).sum() / union))
        if ious:
            per[t["name"]] = round(float(np.mean(ious)), 4)
    vals = list(per.values())
    return {"per_object": per, "mean": round(float(np.mean(vals)), 4) if vals else None,
            "min": round(float(np.min(vals)), 4) if vals else None}


def match(truth: list, rec: list, max_xy: float = 0.06) -> list[tuple[int, int]]:
    """Greedy nearest pairs by the distance between box centres (3-D, so a plate standing in
    its holder pairs with the plate, not the holder), within max_xy horizontally."""
    pairs = sorted((float(np.linalg.norm(t["centre"] - q["centre"])), float(np.linalg.norm(t["centre"][:2] - q["centre"][:2])),
                    i, j) for i, t in enumerate(truth) for j, q in enumerate(rec))
    used_t, used_r, out = set(), set(), []
    for _, d, i, j in pairs:
        if d > max_xy or i in used_t or j in used_r:
            continue
        used_t.add(i)
        used_r.add(j)
        out.append((i, j))
    return out


def task_file(gym_dir: Path, out: Path, reanchor: bool = True, names_from: Optional[Path] = None) -> Path:
    """The gym's [task] (demonstration path made absolute; with `reanchor`, the gym's scene as
    the demonstration's `demonstration_scene`) and [names] from the objects' truth positions in
    `names_from` (the scene the frames show; the gym itself by default), so the reconstructed
    objects carry the names the success rules use."""
    s = tomllib.loads((gym_dir / "scene.toml").read_text())
    task = dict(s.get("task", {}))
    lines = ["[task]"]
    for k, v in task.items():
        if k == "demonstration":
            v = str((gym_dir / v).resolve())
        lines.append(f"{k} = {_toml(v)}")
    if reanchor and task.get("demonstration"):
        lines.append(f"demonstration_scene = {_toml(str((gym_dir / 'scene.toml').resolve()))}")
    lines.append("[names]")
    for e in truth_entities(names_from or gym_dir):
        if "." in e["name"]:
            continue  # a door or drawer: part of its fixture, no object of its own to name
        at = f"[{e['centre'][0]:.4f}, {e['centre'][1]:.4f}, {e['centre'][2]:.4f}]"
        if e["kind"] == "object":
            lines.append(f"{e['name']} = {at}")
        else:
            lines.append(f"{e['name']} = {{ at = {at}, fixed = true }}")
    out.write_text("\n".join(lines) + "\n")
    return out


def _toml(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + " }"
    raise ValueError(type(v))


def evaluate(gym: str, work: Path, extra: int = len(EXTRA_VIEWS), validate: bool = True, rounds: int = 2,
             noise_mm: float = 0.0, noise_rel: float = 0.0) -> dict:
    """Render, reconstruct, compare with the truth, validate. Returns the figures. With
    `noise_mm`/`noise_rel`, synthetic Gaussian depth noise is added to the rendered frames."""
    gym_dir = ROOT / "gyms" / gym
    work.mkdir(parents=True, exist_ok=True)
    frames = render_frames(gym, work / "frames", extra)
    if noise_mm or noise_rel:
        add_depth_noise(frames, noise_mm, noise_rel)
    t0 = time.monotonic()
    out = work / "gym"
    cmd = [R2G, "reconstruct", frames, "--robot", "panda", "--joints", frames / "joints.json", "--out", out,
           "--rounds", str(rounds)]
    rules = tomllib.loads((gym_dir / "scene.toml").read_text()).get("task", {}).get("success", [])
    # A rule on a fixture's joint cannot hold in a reconstruction whose fixtures are static
    # objects: such gyms are reconstructed without their task and reported so.
    articulated = any(r.get("kind") == "joint" for r in rules)
    has_task = bool(rules) and not articulated
    if has_task:
        cmd += ["--task", task_file(gym_dir, work / "task.toml")]
    p = run(cmd)
    res: dict = {"gym": gym, "views": 1 + extra, "articulated_task": articulated}
    if p.returncode != 0 and has_task and "to be hollow" in p.stderr:
        # The task cannot be stated on this reconstruction (a container came out solid): say so
        # and measure the geometry without it.
        res["task_error"] = (p.stderr.strip().splitlines() or ["?"])[-1]
        has_task = False
        t0 = time.monotonic()
        p = run(cmd[:cmd.index("--task")])
    res["seconds"] = round(time.monotonic() - t0, 2)
    if p.returncode != 0:
        res.update({"error": (p.stderr.strip().splitlines() or ["?"])[-1], "verdict": "reconstruct failed"})
        return res
    line = json.loads(p.stdout.strip().splitlines()[-1])
    truth, rec = truth_entities(gym_dir), recon_entities(out)
    pairs = match(truth, rec)
    pos_err, size_err, rows = [], [], []
    for i, j in pairs:
        t, q = truth[i], rec[j]
        pe = float(np.linalg.norm(t["centre"] - q["centre"]))
        se = float(np.abs(t["extent"] - q["extent"]).max())
        rows.append({"truth": t["name"], "kind": t["kind"], "articulated": t["articulated"], "as": q["name"],
                     "static": not q["free"], "position_error_cm": round(pe * 100, 2),
                     "size_error_cm": round(se * 100, 2)})
        if t["kind"] == "object":
            pos_err.append(pe)
            size_err.append(se)
    matched_t = {i for i, _ in pairs}
    matched_r = {j for _, j in pairs}
    rep = json.loads((out / "reconstruction.json").read_text())
    kept = rep.get("kept_round", len(rep.get("rounds", [])) - 1)
    last = next((rd for rd in rep.get("rounds", []) if rd["round"] == kept), {})
    res.update({
        "truth_objects": sum(1 for t in truth if t["kind"] == "object"),
        "truth_fixtures": sum(1 for t in truth if t["kind"] == "fixture"),
        "found": len(rec), "matched": len(pairs),
        "missed": [truth[i]["name"] for i in range(len(truth)) if i not in matched_t],
        "spurious": [rec[j]["name"] for j in range(len(rec)) if j not in matched_r],
        "objects": rows,
        "position_error_cm_mean": round(float(np.mean(pos_err)) * 100, 2) if pos_err else None,
        "position_error_cm_max": round(float(np.max(pos_err)) * 100, 2) if pos_err else None,
        "size_error_cm_mean": round(float(np.mean(size_err)) * 100, 2) if size_err else None,
        # Gate IoU: the render against the reconstruction's own segmentation of the source.
        "iou_mean": last.get("mean_iou"), "iou_min": last.get("min_iou"),
        "iou_first_round": rep["rounds"][0].get("mean_iou") if rep.get("rounds") else None,
        "rounds": len(rep.get("rounds", [])), "kinds": line.get("kinds"), "task_empty": line.get("task_empty"),
        "suspects": [x["name"] for x in rep.get("spurious_suspects") or []],
        "demonstration": (rep.get("demonstration") or {}).get("status"),
    })
    # True-mask IoU: the render against the synthetic frames' mask_visib (the truth).
    tm = true_mask_iou(frames, out, truth, rec, pairs, work / "true_iou")
    res.update({"true_iou_mean": tm.get("mean"), "true_iou_min": tm.get("min"),
                "true_iou_per_object": tm.get("per_object"), "true_iou_error": tm.get("error")})
    if validate and has_task:
        v = run([R2G, "validate", out, "--out", work / "validate"])
        try:
            vl = json.loads(v.stdout.strip().splitlines()[-1])
            res["validate"] = {"success": vl.get("success"),
                               "failed": sorted(k for k, c in vl.get("checks", {}).items() if not c.get("pass"))}
        except (ValueError, IndexError):
            res["validate"] = {"success": False, "failed": [v.stderr.strip()[-200:]]}
    res["verdict"] = verdict(res)
    return res


def verdict(res: dict) -> str:
    if res.get("error"):
        return "reconstruct failed"
    bad = []
    obj_missed = [m for m in res["missed"]]
    if obj_missed:
        bad.append(f"missed {','.join(obj_missed)}")
    if res["spurious"]:
        bad.append(f"spurious {','.join(res['spurious'])}")
    if res.get("validate") and not res["validate"]["success"]:
        bad.append("validate failed: " + ",".join(res["validate"]["failed"]))
    if res.get("task_error"):
        bad.append("task not stated: " + res["task_error"].replace("r2g: error: ", ""))
    if res.get("articulated_task"):
        bad.append("articulated fixture reconstructed as static objects: task not validated")
    return "ok" if not bad else "; ".join(bad)


def clean(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
