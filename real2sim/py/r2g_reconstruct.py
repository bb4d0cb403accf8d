"""`r2g reconstruct`'s geometry: RGB-D frames of a table scene in the BOP layout -> a gym's
scene.toml (robot, table, cameras, objects as primitives, compounds or convex-hull meshes).

Run by `cli/src/reconstruct_cmd.rs` with the checkout's `.venv` Python, in steps:

* ``fit``: read the frames (r2g_reconstruct_io), remove the robot's pixels (the robot rendered
  alone at the capture joints by `r2g render`, and for the Panda also the capsule self-filter of
  `robo_perception.robot`), segment the objects over all views fused (`robo_perception`), fit a
  primitive to each one and write scene.toml (+ meshes/) into the staging folder given, and the
  state the later steps need into a work folder.
* ``gate``: after the Rust side has let physics settle the objects, render the reconstruction from
  every source camera (`r2g render --cameras`), compare each object with its source mask (mask
  IoU, depth error, centroid error) and, unless it is the last round, correct positions, sizes
  and colours; the round's figures go to reconstruction.json in the staging folder.

"World" is the robot base frame throughout. Everything printed on stdout is one JSON line; an
input problem exits 2 with one line "error: ..." on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import subprocess
import sys
import time
import traceback
import tomllib
from pathlib import Path
from typing import Any, Optional

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT / "agent-host" / "py" / "lib"))

import r2g_reconstruct_io as rio  # noqa: E402
import r2g_reconstruct_parts as rparts  # noqa: E402
from r2g_reconstruct_io import FramesError  # noqa: E402
import robo_perception as rp  # noqa: E402

DENSITY_KG_M3 = 600.0
"""Mass from the fitted volume at this density (wood, light plastic), clamped to 20 g .. 2 kg."""
WALL_M = 0.004
"""Wall thickness of a hollow round object (a bowl or cup): not seen from outside, so assumed."""
FLOOR_M = 0.005
FIXTURE_HEIGHT_M = 0.15
FIXTURE_SIDE_M = 0.25
"""An object taller or longer than these is welded to the world (a cabinet, a shelf, a rack):
the frames cannot tell furniture from things to move, and furniture must not topple."""
LIFT_M = 0.0005
"""Objects start this far above what they rest on; settling puts them down."""
ROBOT_DEPTH_TOLERANCE_M = 0.015
"""A source pixel belongs to the robot when it is no more than this in front of the robot's
rendered surface there (or behind it)."""


STAGE = ["starting"]
"""What the running step is doing, for the one-line error of an unexpected failure."""


def set_stage(what: str) -> None:
    STAGE[0] = what


def fail(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)
    sys.exit(2)


def r(v: float, n: int = 5) -> float:
    return float(round(float(v), n))


# --------------------------------------------------------------------------------------------
# TOML (the subset scene.toml needs)
# --------------------------------------------------------------------------------------------

def _tv(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            raise ValueError(f"non-finite number {f} in the scene")
        s = repr(round(f, 6))
        return s if ("." in s or "e" in s) else s + ".0"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_tv(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_tv(x)}" for k, x in v.items()) + " }"
    raise ValueError(f"cannot write {type(v).__name__} to TOML")


def _table(name: str, d: dict, array: bool = False) -> str:
    head = f"[[{name}]]" if array else f"[{name}]"
    lines = [head]
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, list) and v and isinstance(v[0], dict):
            lines.append(f"{k} = [")
            lines += [f"    {_tv(x)}," for x in v]
            lines.append("]")
        else:
            lines.append(f"{k} = {_tv(v)}")
    return "\n".join(lines) + "\n"


def scene_toml(model: dict) -> str:
    out = [f"# {model['name']}: reconstructed by `r2g reconstruct` from {model['source']}",
           "# (see reconstruction.json). World = the robot base frame.",
           f"name = {_tv(model['name'])}", "timestep_s = 0.001", ""]
    out.append(_table("robot", model["robot"]))
    out.append(_table("table", model["table"]))
    for c in model["cameras"]:
        out.append(_table("cameras", c, array=True))
    for o in model["objects"]:
        d = {k: v for k, v in o.items() if not k.startswith("_")}
        if "parts" in d:
            d["parts"] = [{k: v for k, v in p.items() if not k.startswith("_")} for p in d["parts"]]
        out.append(_table("objects", d, array=True))
    task = model["task"]
    out.append(_table("task", task))
    return "\n".join(out)


# --------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------

def quat_yaw(yaw: float) -> list:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def yaw_of(q: list) -> float:
    w, x, y, z = q
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def plane_z(plane: Any, x: float, y: float) -> float:
    n = plane.normal
    return float(-(plane.offset + n[0] * x + n[1] * y) / n[2])


def fit_circle(xy: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares circle (Kasa) -> (centre, radius, rms residual / radius)."""
    A = np.column_stack([2 * xy[:, 0], 2 * xy[:, 1], np.ones(len(xy))])
    b = (xy ** 2).sum(1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:2]
    rad = math.sqrt(max(sol[2] + c @ c, 1e-12))
    res = np.sqrt(np.mean((np.linalg.norm(xy - c, axis=1) - rad) ** 2)) / rad
    return c, rad, float(res)


def fit_sphere(P: np.ndarray) -> tuple[np.ndarray, float, float]:
    A = np.column_stack([2 * P, np.ones(len(P))])
    b = (P ** 2).sum(1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:3]
    rad = math.sqrt(max(sol[3] + c @ c, 1e-12))
    res = np.sqrt(np.mean((np.linalg.norm(P - c, axis=1) - rad) ** 2)) / rad
    return c, rad, float(res)


def hull_outline(xy: np.ndarray, step: float = 0.002) -> np.ndarray:
    """Points every `step` m along the convex hull of 2-D points."""
    hull = rp.convex_hull_2d(xy)
    if len(hull) < 3:
        return hull
    pts = []
    for a, b in zip(hull, np.roll(hull, -1, axis=0)):
        n = max(1, int(np.linalg.norm(b - a) / step))
        t = np.arange(n)[:, None] / n
        pts.append(a + t * (b - a))
    return np.concatenate(pts)


def polygon_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


# --------------------------------------------------------------------------------------------
# The robot's pixels
# --------------------------------------------------------------------------------------------

# ipc_schema::MAX_CAMERAS: the cameras a scene may name (one shared-memory image slot each).
SCENE_CAMERAS = 4


def cameras_json(frames: list, path: Path) -> None:
    """The frames' cameras as a BOP scene_camera.json with the image size beside them, the form
    `r2g render --cameras` takes."""
    doc = {}
    for f in frames:
        doc[f.id] = {"cam_K": [float(v) for v in f.K.reshape(-1)],
                     "cam_R_w2c": [float(v) for v in f.R_w2c.reshape(-1)],
                     "cam_t_w2c": [float(v) * 1000.0 for v in f.t_w2c_m],
                     "depth_scale": 0.1, "width": f.width, "height": f.height}
    path.write_text(json.dumps(doc, indent=1))


def run_render(r2g: str, gym: Path, cams: Path, out: Path) -> dict:
    """`r2g render <gym> --cameras <cams> --out <out>`; returns {source id: (depth m, rgb, masks
    dir, rendered id)} keyed by the ids of `cams`."""
    cmd = [r2g, "render", str(gym), "--cameras", str(cams), "--out", str(out)]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        tail = (p.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise RuntimeError(f"`{' '.join(cmd)}` failed: {tail}")
    sc = json.loads((out / "scene_camera.json").read_text())
    src_ids = list(json.loads(cams.read_text()).keys())
    rendered = list(sc.keys())
    if len(rendered) != len(src_ids):
        raise RuntimeError(f"r2g render wrote {len(rendered)} images for {len(src_ids)} cameras")
    by_src = {}
    for sid in src_ids:
        rid = sid if sid in sc else None
        if rid is None:
            rid = next((k for k, e in sc.items() if str(e.get("r2g_camera", "")).endswith(sid)), None)
        if rid is None:
            rid = rendered[src_ids.index(sid)]
        e = sc[rid]
        stem = f"{int(rid):06d}" if rid.isdigit() else rid
        d = rio.read_png(out / "depth" / f"{stem}.png").astype(np.float32) * np.float32(e.get("depth_scale", 0.1) / 1000)
        d[d == 0] = np.nan
        rgb = rio.read_png(out / "rgb" / f"{stem}.png")[..., :3]
        by_src[sid] = {"depth": d, "rgb": rgb, "stem": stem, "dir": out}
    return by_src


def robot_pixels(frames: list, urdf: str, r2g: str, work: Path, tcp_link: str = "hand_tcp") -> dict:
    """{frame id: (H, W) bool}: where the source sees the robot, from the robot alone rendered at
    each frame's joints (same URDF, same renderer as the gym)."""
    groups: dict = {}
    for f in frames:
        groups.setdefault((tuple(round(q, 9) for q in f.joints), round(f.gripper, 6)), []).append(f)
    out = {}
    for gi, ((q, g), fs) in enumerate(groups.items()):
        gdir = work / f"robot_{gi}"
        gdir.mkdir(parents=True, exist_ok=True)
        model = {"name": "robot_only", "source": "the capture joints",
                 "robot": {"urdf": urdf, "tcp_link": tcp_link, "initial_joints_rad": list(q), "initial_gripper": g},
                 "table": None, "cameras": [], "objects": [], "task": {}}
        # A small table far below puts the floor (drawn 0.75 m under the table top) where no
        # robot part is: what the render shows above z = -1 m is the robot.
        far = {"top_center_m": [20.0, 20.0, -5.0], "size_m": [0.01, 0.01]}
        text = f"name = \"robot_only\"\n{_table('robot', model['robot'])}{_table('table', far)}"
        (gdir / "scene.toml").write_text(text)
        cams = gdir / "cams.json"
        cameras_json(fs, cams)
        ren = run_render(r2g, gdir, cams, gdir / "render")
        for f in fs:
            rd = ren[f.id]["depth"].copy()
            sd = f.depth_m
            ok = np.isfinite(rd)
            P, idx = rp.depth_to_points(np.where(ok, rd, 0), f.intrinsics, f.base_from_camera, min_depth=1e-4,
                                        max_depth=100.0)
            below = np.zeros(rd.size, dtype=bool)
            below[idx[P[:, 2] < -1.0]] = True
            rd[below.reshape(rd.shape)] = np.nan
            with np.errstate(invalid="ignore"):
                m = np.isfinite(rd) & (~np.isfinite(sd) | (sd > rd - ROBOT_DEPTH_TOLERANCE_M))
            # one pixel more around the robot's outline where the source is near the robot's depth
            grown = m.copy()
            grown[1:, :] |= m[:-1, :]
            grown[:-1, :] |= m[1:, :]
            grown[:, 1:] |= m[:, :-1]
            grown[:, :-1] |= m[:, 1:]
            near = np.zeros_like(m)
            ref = np.where(np.isfinite(rd), rd, 0)
            for sl_a, sl_b in (((slice(1, None), slice(None)), (slice(None, -1), slice(None))),
                               ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
                               ((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                               ((slice(None), slice(None, -1)), (slice(None), slice(1, None)))):
                with np.errstate(invalid="ignore"):
                    near[sl_a] |= m[sl_b] & (np.abs(sd[sl_a] - ref[sl_b]) < 0.03)
            out[f.id] = m | (grown & near)
    return out


# --------------------------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------------------------

def fit_object(o: Any, plane: Any, others: dict, force: Optional[str] = None,
               fs: Optional["rparts.FreeSpace"] = None, foreign: Optional[np.ndarray] = None,
               solid: Optional[np.ndarray] = None) -> dict:
    """One segmented object -> an object spec (dict), with the fit's evidence under "_fit".
    `force` (one of PRIMITIVES) overrides the shape the evidence picks (the model's choice).
    `fs` (the space the source views saw through): with it, an object the footprint would make
    a box or a hull is first tried as a disc standing on edge and as an open round body with
    attachments (a mug), and a box or hull that holds space a view saw empty is decomposed into
    convex parts (r2g_reconstruct_parts); `foreign` (the other objects' points) counts as space
    the object cannot hold too, and `solid` (samples filling the other objects' fitted solids)
    as space no part may hold at all."""
    P = o.points
    h = plane.distance(P)
    xy = P[:, :2]
    top = float(np.percentile(h, 99.5))
    bottom = max(0.0, float(o.bottom)) if o.support is not None else float(o.lowest_seen)
    support = o.support
    if isinstance(support, (int, np.integer)) and support in others:
        bottom = others[support]
    outline = hull_outline(xy)
    centre2, axes, ext, hull_area = rp.min_area_rect(xy)
    fill = hull_area / max(ext[0] * ext[1], 1e-9)
    circ_c, circ_r, circ_res = fit_circle(outline) if len(outline) >= 8 else (centre2, 0.0, 1.0)
    height = max(top - bottom, 0.004)
    evidence = {"points": int(len(P)), "footprint_fill": r(fill, 3), "circle_residual": r(circ_res, 4),
                "rect_m": [r(ext[0], 4), r(ext[1], 4)], "circle_radius_m": r(circ_r, 4),
                "top_m": r(top, 4), "bottom_m": r(bottom, 4), "hollow": bool(o.hollow),
                "support": support if not isinstance(support, np.integer) else int(support)}
    round_like = circ_res < 0.035 and fill < 0.9 and ext[1] / max(ext[0], 1e-9) > 0.85
    shape = "mesh"
    if o.hollow and circ_res < 0.06 and ext[1] / max(ext[0], 1e-9) > 0.8:
        shape = "bowl"
    elif round_like:
        shape = "cylinder"
        if abs(height - 2 * circ_r) < 0.2 * 2 * circ_r and len(P) >= 30:
            sc, sr, sres = fit_sphere(P)
            evidence["sphere_residual"] = r(sres, 4)
            if sres < 0.05 and abs(sr - circ_r) < 0.2 * circ_r:
                shape = "sphere"
    elif fill >= 0.85:
        shape = "box"
    special = None
    if force is None and fs is not None and shape in ("box", "mesh"):
        special = _free_space_fit(o, plane, bottom, centre2, fs, foreign, evidence, solid)
        if special is not None:
            shape = special[0]
    if force is not None:
        evidence["evidence_chose"] = shape
        shape = force
        evidence["chosen_by"] = "model"
    evidence["chosen"] = shape
    cz_base = plane_z(plane, *(circ_c if shape in ("cylinder", "sphere", "bowl") else centre2))
    spec: dict = {}
    if special is not None:
        spec, volume = special[1], special[2]
    elif shape == "box":
        yaw = math.atan2(axes[1, 0], axes[0, 0])
        yaw = (yaw + math.pi / 2) % math.pi - math.pi / 2
        hx, hy, hz = ext[0] / 2, ext[1] / 2, height / 2
        spec = {"shape": "box", "size_m": [r(hx), r(hy), r(hz)],
                "position_m": [r(centre2[0]), r(centre2[1]), r(cz_base + bottom + hz + LIFT_M)],
                "quat_wxyz": [r(v, 6) for v in quat_yaw(yaw)]}
        volume = 8 * hx * hy * hz
    elif shape == "cylinder":
        spec = {"shape": "cylinder", "size_m": [r(circ_r), r(height / 2)],
                "position_m": [r(circ_c[0]), r(circ_c[1]), r(cz_base + bottom + height / 2 + LIFT_M)]}
        volume = math.pi * circ_r ** 2 * height
    elif shape == "sphere":
        rad = (circ_r + height / 2) / 2
        spec = {"shape": "sphere", "size_m": [r(rad)],
                "position_m": [r(circ_c[0]), r(circ_c[1]), r(cz_base + bottom + rad + LIFT_M)]}
        volume = 4 / 3 * math.pi * rad ** 3
    elif shape == "bowl":
        spec, volume = bowl_parts(circ_c, circ_r, height, cz_base + bottom)
    else:
        spec, volume = hull_mesh(P, plane, bottom, centre2)
    spec["mass_kg"] = r(min(MASS_RANGE_KG[1], max(MASS_RANGE_KG[0], DENSITY_KG_M3 * volume)), 4)
    evidence["volume_m3"] = float(f"{volume:.4g}")
    spec["_fit"] = evidence
    spec["_top"] = top
    return spec


SOLID_CLEARANCE_M = 0.0015
"""Another object's fitted solid counts as not-ours this much beyond its surface, so the parts
cut around it leave it room instead of touching (and squeezing) it."""


def solid_samples(spec: dict, step: float = 0.003, clearance: float = SOLID_CLEARANCE_M) -> np.ndarray:
    """World points filling a single-shape fit (box, cylinder or disc, sphere) grown by
    `clearance`, on a grid; empty for compounds and meshes."""
    shape = spec.get("shape")
    if shape not in ("box", "cylinder", "sphere") or "parts" in spec:
        return np.zeros((0, 3))
    s = [v + clearance for v in spec["size_m"]]
    half = {"box": s[:3], "cylinder": [s[0], s[0], s[1]], "sphere": [s[0]] * 3}[shape]
    axes = [np.arange(-h + step / 2, h, step) if h > step / 2 else np.array([0.0]) for h in half]
    L = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    if shape == "cylinder":
        L = L[np.hypot(L[:, 0], L[:, 1]) <= s[0]]
    elif shape == "sphere":
        L = L[np.linalg.norm(L, axis=1) <= s[0]]
    Rm = rparts.quat_matrix(spec.get("quat_wxyz", [1.0, 0.0, 0.0, 0.0]))
    return L @ Rm.T + np.array(spec["position_m"])


def solid_contains(spec: dict, X: np.ndarray, clearance: float = SOLID_CLEARANCE_M) -> np.ndarray:
    """Which world points lie inside a single-shape fit (box, cylinder or disc, sphere) grown by
    `clearance`; none for compounds and meshes."""
    shape = spec.get("shape")
    if shape not in ("box", "cylinder", "sphere") or "parts" in spec or not len(X):
        return np.zeros(len(X), dtype=bool)
    Rm = rparts.quat_matrix(spec.get("quat_wxyz", [1.0, 0.0, 0.0, 0.0]))
    L = (X - np.array(spec["position_m"])) @ Rm
    s = [v + clearance for v in spec["size_m"]]
    if shape == "box":
        return (np.abs(L) <= np.array(s[:3])).all(1)
    if shape == "cylinder":
        return (np.hypot(L[:, 0], L[:, 1]) <= s[0]) & (np.abs(L[:, 2]) <= s[1])
    return np.linalg.norm(L, axis=1) <= s[0]


SEGMENT_MIN_HEIGHT_M = 0.005
SEGMENT_PLANE_M = 0.006
"""robo_perception.segment_scene's defaults: points within SEGMENT_PLANE_M of the plane are the
plane's, objects start SEGMENT_MIN_HEIGHT_M above it."""
NOISE_CUT_SIGMAS = 3.0
"""With depth noise of standard deviation s (measured on the support plane), both become at least
this many s."""


NOISE_CUT_MAX_M = 0.015
"""The height cut never goes above this (3 sigma of 5 mm): noisier depth is reported, and objects
lower than the cut are lost."""


def depth_noise(views: list) -> tuple[float, float]:
    """(sigma of the heights, sigma along the cameras' rays) of the depth noise in metres, read
    off the support plane: a RANSAC plane through every view's points (every 4th pixel, inliers
    within 3 mm); the heights within 2 cm of it; their mode m (the 0.25 mm bin with most heights,
    then the median of those within 3 mm of it); and 1.4826 x the median of m - h over
    the points below the mode only, since whatever stands on the table (a plate, a tray, the
    bottom of a side face) adds heights above it and nothing lies below it. Along the rays each
    height is divided by the cosine between the ray and the plane's normal first (a camera at
    45 degrees sees 3 mm of depth noise as about 2 mm of height). Synthetic renders give about
    0.1 mm."""
    pts, rays = [], []
    for v in views:
        P = rp.depth_to_points(np.nan_to_num(v.depth, nan=0.0), v.intrinsics, v.base_from_camera, stride=4)[0]
        if len(P):
            d = P - np.asarray(v.base_from_camera, dtype=float)[:3, 3]
            pts.append(P)
            rays.append(d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9))
    if not pts or sum(len(p) for p in pts) < 100:
        return 0.0, 0.0
    P, D = np.concatenate(pts), np.concatenate(rays)
    try:
        plane, _ = rp.fit_plane_ransac(P, threshold=0.5 * SEGMENT_PLANE_M)
    except (ValueError, np.linalg.LinAlgError):
        return 0.0, 0.0
    h = plane.distance(P)
    near = np.abs(h) < 0.02
    h, cos = h[near], np.maximum(np.abs(D[near] @ np.asarray(plane.normal, dtype=float)), 0.2)
    if len(h) < 100:
        return 0.0, 0.0
    counts, edges = np.histogram(h, bins=160, range=(-0.02, 0.02))
    m = float((edges[:-1] + edges[1:])[int(np.argmax(counts))] / 2)
    m = float(np.median(h[np.abs(h - m) < 0.003]))   # the peak's centre, finer than a bin
    below = h < m
    if below.sum() < 50:
        return 0.0, 0.0
    return (float(1.4826 * np.median(m - h[below])), float(1.4826 * np.median((m - h[below]) / cos[below])))


def cradle_parts(columns: list, spec: dict, solid: np.ndarray) -> tuple[list, float]:
    """Support columns under a resting object -> box parts of the compound `spec` (in its frame:
    relative to its origin and turned by its `quat_wxyz`, a bin's yaw), each lowered below any of
    `solid` (the other objects' grown solids) it would reach into. Returns (parts, volume)."""
    origin = np.array(spec["position_m"]) - np.array([0.0, 0.0, LIFT_M])
    Rm = rparts.quat_matrix(spec.get("quat_wxyz", [1.0, 0.0, 0.0, 0.0]))
    turned = not np.allclose(Rm, np.eye(3))
    out, volume = [], 0.0
    for c, half in rparts.cradle_boxes(columns):
        lo, hi = c - half, c + half
        S = solid[((solid >= lo) & (solid <= hi)).all(1)] if len(solid) else solid
        if len(S):
            hi[2] = float(S[:, 2].min()) - 0.001
        if hi[2] - lo[2] < 0.001:
            continue
        c, half = (lo + hi) / 2, (hi - lo) / 2
        part = {"shape": "box", "size_m": [r(float(v), 5) for v in half],
                "position_m": [r(float(v), 5) for v in Rm.T @ (c - origin)]}
        if turned:
            # World axes in the compound's frame: the inverse of its rotation.
            part["quat_wxyz"] = [r(v, 6) for v in rparts.quat_of(Rm.T)]
        out.append(part)
        volume += 8 * float(np.prod(half))
    return out, volume


def bowl_parts(c: np.ndarray, radius: float, height: float, z_bottom: float) -> tuple[dict, float]:
    """A round hollow object as a compound: a floor disc and 16 wall boxes on a circle, origin at
    the centre of its underside (as the shipped bowls are written)."""
    rc = max(radius - WALL_M / 2, 0.01)
    half_w = 1.05 * math.pi * rc / 16
    parts = [{"shape": "cylinder", "size_m": [r(rc), r(FLOOR_M / 2)], "position_m": [0.0, 0.0, r(FLOOR_M / 2)]}]
    for k in range(16):
        a = 2 * math.pi * k / 16
        parts.append({"shape": "box", "size_m": [r(WALL_M / 2), r(half_w), r(height / 2)],
                      "position_m": [r(rc * math.cos(a)), r(rc * math.sin(a)), r(height / 2)],
                      "quat_wxyz": [r(v, 6) for v in quat_yaw(a)]})
    inner = (rc - WALL_M / 2) / math.sqrt(2)
    spec = {"position_m": [r(c[0]), r(c[1]), r(z_bottom + LIFT_M)], "parts": parts,
            "cavity_min_m": [r(-inner), r(-inner), 0.0], "cavity_max_m": [r(inner), r(inner), r(height)],
            "_bowl": {"radius_m": radius, "height_m": height}}
    volume = math.pi * rc ** 2 * FLOOR_M + 16 * (2 * half_w) * WALL_M * height
    return spec, volume


def bin_parts(axes: np.ndarray, half: np.ndarray, height: float, c: np.ndarray, z_bottom: float) -> tuple[dict, float]:
    """An open rectangular body as a compound: a floor box and four wall boxes (walls WALL_M, floor
    FLOOR_M), its frame turned to the rectangle's sides, origin at the centre of its underside."""
    hx, hy = float(half[0]), float(half[1])
    w = WALL_M / 2
    parts = [{"shape": "box", "size_m": [r(hx), r(hy), r(FLOOR_M / 2)], "position_m": [0.0, 0.0, r(FLOOR_M / 2)]}]
    for x, y, sx, sy in ((hx - w, 0.0, w, hy), (-(hx - w), 0.0, w, hy), (0.0, hy - w, hx, w), (0.0, -(hy - w), hx, w)):
        parts.append({"shape": "box", "size_m": [r(sx), r(sy), r(height / 2)], "position_m": [r(x), r(y), r(height / 2)]})
    yaw = math.atan2(axes[1, 0], axes[0, 0])
    spec = {"position_m": [r(c[0]), r(c[1]), r(z_bottom + LIFT_M)], "quat_wxyz": [r(v, 6) for v in quat_yaw(yaw)],
            "parts": parts, "cavity_min_m": [r(-(hx - WALL_M)), r(-(hy - WALL_M)), 0.0],
            "cavity_max_m": [r(hx - WALL_M), r(hy - WALL_M), r(height)]}
    volume = 4 * hx * hy * FLOOR_M + 2 * (2 * hy) * WALL_M * height + 2 * (2 * hx) * WALL_M * height
    return spec, volume


def _free_space_fit(o: Any, plane: Any, bottom: float, centre2: np.ndarray, fs: "rparts.FreeSpace",
                    foreign: Optional[np.ndarray], evidence: dict,
                    solid: Optional[np.ndarray] = None) -> Optional[tuple[str, dict, float]]:
    """For an object the footprint makes a box or a hull: (shape, spec, volume) of a better fit
    that the frames support, or None to keep the box or hull. In order: a disc standing on edge
    (a cylinder about its horizontal normal); an open round body (a cup's walls and floor, as
    the bowls) with what sticks out of it (a handle) decomposed into convex parts; the box or
    hull itself cut into convex parts where the source views saw through it."""
    P = o.points
    base_z = plane_z(plane, *centre2) + bottom
    disc = rparts.disc_fit(P)
    if disc is not None:
        evidence["disc"] = {"radius_m": r(disc["radius"], 4), "outline_residual": r(disc["residual"], 4),
                            "outline_inliers": r(disc["outline_inliers"], 3),
                            "normal": [r(v, 4) for v in disc["normal"]]}
        c = disc["centre"]
        spec = {"shape": "cylinder", "size_m": [r(disc["radius"]), r(disc["half_thickness"])],
                "position_m": [r(c[0]), r(c[1]), r(c[2] + LIFT_M)],
                "quat_wxyz": [r(v, 6) for v in rparts.z_to(disc["normal"])]}
        return "disc", spec, math.pi * disc["radius"] ** 2 * 2 * disc["half_thickness"]
    cont = rparts.container_fit(P, base_z, fs)
    if cont is not None:
        spec, volume = bowl_parts(cont["centre"], cont["radius"], cont["height"], base_z)
        origin = np.array([cont["centre"][0], cont["centre"][1], base_z])
        extra: list = []
        cuts = 0
        if len(cont["rest"]) >= rparts.MIN_PART_POINTS:
            dec = rparts.decompose(cont["rest"], fs, foreign, solid=solid)
            keep = [Q for Q in dec["parts"] if len(Q) >= rparts.MIN_PART_POINTS]
            extra, v2 = rparts.part_specs(keep, origin, solid)
            volume += v2
            cuts = dec["cuts"]
        spec["parts"] += extra
        evidence["container"] = {"radius_m": r(cont["radius"], 4), "height_m": r(cont["height"], 4),
                                 "wall_points": r(cont["inliers"], 3),
                                 "middle_seen_empty": r(cont["middle_seen_empty"], 3),
                                 "footprint_fill": r(cont["footprint_fill"], 3),
                                 "attached_points": int(len(cont["rest"])), "attached_parts": len(extra),
                                 "cuts": cuts}
        return "container", spec, volume
    binf = rparts.box_container_fit(P, base_z, fs)
    if binf is not None:
        spec, volume = bin_parts(binf["axes"], binf["half"], binf["height"], binf["centre"], base_z)
        evidence["container"] = {"footprint": "rectangle", "half_m": [r(v, 4) for v in binf["half"]],
                                 "height_m": r(binf["height"], 4),
                                 "middle_seen_empty": r(binf["middle_seen_empty"], 3),
                                 "footprint_fill": r(binf["footprint_fill"], 3)}
        return "container", spec, volume
    # The box or hull as fitted: does it hold space a view saw through?
    S = rp.voxel_downsample(P, 0.003)[0] if len(P) > 3000 else P
    Q = rparts.grounded(S, fs, base_z)
    h = rparts.hull_of(Q)
    if h is None:
        return None
    # The size guard comes before any sampling of the hull: furniture is neither checked nor cut.
    if h.volume > rparts.MAX_DECOMPOSE_M3:
        evidence["not_decomposed"] = (f"hull of {h.volume * 1e3:.1f} l: objects over "
                                      f"{rparts.MAX_DECOMPOSE_M3 * 1e3:.0f} l (furniture) are not checked against "
                                      "free space nor cut into parts")
        return None
    E, cell = rparts.not_ours(h, fs, foreign)
    seen = float(len(E) * cell)
    evidence["hull_seen_empty_cm3"] = r(seen * 1e6, 2)
    in_solid = int(rparts.inside(h, solid).sum()) if solid is not None and len(solid) else 0
    if in_solid:
        evidence["hull_other_solid_samples"] = in_solid
    if seen < 4 * rparts.EMPTY_TOL_M3 and seen < 0.03 * h.volume and not in_solid:
        return None
    dec = rparts.decompose(Q, fs, foreign, solid=solid)
    if dec.get("solid_samples_left"):
        evidence["other_solid_samples_left"] = dec["solid_samples_left"]
    keep = [X for X in dec["parts"] if len(X) >= rparts.MIN_PART_POINTS]
    if not keep:
        evidence["not_decomposed"] = (f"every part of the cut hull has under {rparts.MIN_PART_POINTS} points: "
                                      "kept whole")
        return None
    origin = np.array([centre2[0], centre2[1], base_z])
    parts, volume = rparts.part_specs(keep, origin, solid)
    spec = {"position_m": [r(origin[0]), r(origin[1]), r(origin[2] + LIFT_M)], "parts": parts}
    # Its cavity: the box spanning the space seen empty inside the first hull (between the
    # parts: a rack's slots, the room under a peg), from the lowest such point to the top. An
    # axis where that space is thinner than one sample cell (one grid column of a narrow slot, a
    # flat sheet of another object's points) is widened to one cell about its middle.
    E = dec["empty"]
    if len(E) >= 8:
        lo = np.quantile(E, 0.02, axis=0) - origin
        hi = np.quantile(E, 0.98, axis=0) - origin
        hi[2] = max(float(h.points[h.vertices][:, 2].max() - origin[2]), float(hi[2]))
        edge = max(float(dec["cell_m3"]) ** (1 / 3), 0.002)
        thin = (hi - lo) < edge
        if thin.any():
            mid = (lo + hi) / 2
            lo = np.where(thin, mid - edge / 2, lo)
            hi = np.where(thin, mid + edge / 2, hi)
            evidence["cavity_widened_axes"] = [ax for ax, t in zip("xyz", thin) if t]
        spec["cavity_min_m"] = [r(v) for v in lo]
        spec["cavity_max_m"] = [r(v) for v in hi]
    evidence["decomposition"] = {"parts": len(parts), "cuts": dec["cuts"],
                                 "residual_seen_empty_cm3": r(dec["residual_m3"] * 1e6, 2),
                                 "boxes": sum(1 for p in parts if p["shape"] == "box"),
                                 "meshes": sum(1 for p in parts if p["shape"] == "mesh")}
    return "parts", spec, volume


def hull_mesh(P: np.ndarray, plane: Any, bottom: float, centre2: np.ndarray) -> tuple[dict, float]:
    """The convex hull of the object's points and their shadow on what it stands on, as an OBJ
    mesh in the object frame (origin: the footprint centre at the bottom)."""
    from scipy.spatial import ConvexHull

    base_z = plane_z(plane, *centre2) + bottom
    down = P.copy()
    down[:, 2] = base_z
    Q = np.concatenate([P, down])
    Q = rp.voxel_downsample(Q, 0.003)[0] if len(Q) > 4000 else Q
    origin = np.array([centre2[0], centre2[1], base_z])
    hull = ConvexHull(Q - origin)
    spec = {"shape": "mesh", "_mesh": rparts.mesh_of(hull, np.zeros(3)),
            "position_m": [r(origin[0]), r(origin[1]), r(origin[2] + LIFT_M)]}
    return spec, float(hull.volume)


def obj_text(mesh: dict) -> str:
    lines = ["# convex hull written by r2g reconstruct"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh["vertices"]]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh["faces"]]
    return "\n".join(lines) + "\n"


def colour_of(o: Any, plane: Any) -> list:
    h = plane.distance(o.points)
    sel = h >= 0.3 * max(h.max(), 1e-6)
    c = np.median(o.colors[sel] if sel.sum() >= 10 else o.colors, axis=0) / 255.0
    return [r(float(v), 3) for v in c] + [1.0]


# --------------------------------------------------------------------------------------------
# Task
# --------------------------------------------------------------------------------------------

TASK_KEYS = {"instruction", "demonstration", "demonstration_hz", "success", "max_penetration_m", "settle_s",
             "demonstration_scene"}
"""[task] keys of a task file: scene.toml's, plus `demonstration_scene` (the scene.toml the
demonstration was recorded in; with it the demonstration is re-anchored to the reconstructed
objects, and the key is not written into the gym)."""


def read_task(path: Optional[str], instruction: Optional[str]) -> tuple[dict, dict, Optional[Path], Optional[Path]]:
    """(task table, names table, demonstration file, the scene it was recorded in) from --task
    and --instruction."""
    task: dict = {}
    names: dict = {}
    demo = None
    demo_scene = None
    if path:
        p = Path(path)
        try:
            doc = tomllib.loads(p.read_text())
        except FileNotFoundError:
            raise FramesError(f"task file {p} does not exist") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise FramesError(f"task file {p} is not valid TOML: {e}") from None
        unknown = set(doc) - {"task", "names"}
        if unknown:
            raise FramesError(f"task file {p}: unknown table(s) {sorted(unknown)} (accepted: [task], [names])")
        task = dict(doc.get("task", {}))
        bad = set(task) - TASK_KEYS
        if bad:
            raise FramesError(f"task file {p}: [task] has unknown key(s) {sorted(bad)} (accepted: {sorted(TASK_KEYS)})")
        names = dict(doc.get("names", {}))
        if "demonstration" in task:
            demo = (p.parent / task["demonstration"]).resolve()
            if not demo.is_file():
                raise FramesError(f"task file {p}: demonstration {task['demonstration']} does not exist ({demo})")
            task["demonstration"] = "demo.csv"
        if "demonstration_scene" in task:
            if demo is None:
                raise FramesError(f"task file {p}: demonstration_scene is given without a demonstration")
            v = task.pop("demonstration_scene")
            demo_scene = (p.parent / str(v)).resolve()
            if demo_scene.is_dir():
                demo_scene = demo_scene / "scene.toml"
            if not demo_scene.is_file():
                raise FramesError(f"task file {p}: demonstration_scene {v} does not exist ({demo_scene})")
            try:
                st = tomllib.loads(demo_scene.read_text()).get("task", {})
            except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
                raise FramesError(f"task file {p}: demonstration_scene {demo_scene} is not valid TOML: {e}") from None
            own = (demo_scene.parent / st["demonstration"]).resolve() if st.get("demonstration") else None
            if own is None or not own.is_file() or own.read_bytes() != demo.read_bytes():
                raise FramesError(f"task file {p}: demonstration_scene {demo_scene} does not hold the same "
                                  f"demonstration ({own or 'none'}) as the task's {demo}: the re-anchoring replays "
                                  "the demonstration in the scene it was recorded in")
        if not isinstance(task.get("success", []), list):
            raise FramesError(f"task file {p}: success must be a list of rules")
    if instruction:
        task["instruction"] = instruction
    return task, names, demo, demo_scene


def _span(o: dict, plane: Any) -> tuple[float, float]:
    """An object's vertical extent in the world (bottom, top), from its fit."""
    f = o["_fit"]
    z0 = plane_z(plane, *o["position_m"][:2])
    return z0 + f["bottom_m"], z0 + f["top_m"]


PRIMITIVES = ("box", "cylinder", "sphere", "bowl", "mesh")
"""Shapes the model may impose: the fit is redone with that primitive, whatever the frames say."""
FITTED_SHAPES = ("disc", "container", "parts")
"""Shapes only the frames can give (they need the free-space evidence): named in an answer, they
mean "keep the fit if it is this"; where the fit came out otherwise, the request is reported as
a warning and the fit kept."""
MATERIALS = {
    # name: (density of the fitted solid in kg/m^3, sliding friction), rounded handbook values;
    # the fitted solid of a cup or bowl is its walls, of anything else its whole volume.
    "wood": (600.0, 0.5),
    "ceramic": (2300.0, 0.5),
    "glass": (2500.0, 0.4),
    "metal": (7800.0, 0.4),
    "plastic": (1000.0, 0.4),
    "rubber": (1100.0, 1.0),
    "cardboard": (250.0, 0.6),
    "foam": (60.0, 0.8),
    "fabric": (300.0, 0.8),
    "fruit": (950.0, 0.6),
}
"""The model's optional `material`: sets the object's mass (density x fitted volume, within
MASS_RANGE_KG; not for a static object, whose mass does nothing) and friction. Without one an
object has the simulator's default friction, 1.0. A MuJoCo contact takes the larger friction of
its two geoms (the table 0.8, the fingers 1.2), so a material's friction shows between objects
and against the table, and hardly against the fingers."""
MASS_RANGE_KG = (0.02, 2.0)
NAME_CHARS = set("abcdefghijklmnopqrstuvwxyz0123456789_")


def read_model_answer(text: str, n: int) -> dict:
    """The model's answer -> {"o<k>": {"name"?, "primitive"? | "keep"?, "material"?}}, checked
    strictly: a JSON object {"objects": [{"id", "name"?, "primitive"?, "material"?, "why"?}]}, ids
    among o1..o<n> (the model may not invent objects), each once, primitives among PRIMITIVES (imposed)
    or FITTED_SHAPES (kept only if the fit agrees), materials among MATERIALS, names lower-case
    identifiers."""
    body = text.strip()
    if body.startswith("```"):
        body = body.split("\n", 1)[1] if "\n" in body else ""
        body = body.rsplit("```", 1)[0]
    try:
        doc = json.loads(body)
    except ValueError as e:
        raise FramesError(f"the model's answer is not JSON ({e}); it began: {text[:200]!r}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("objects"), list):
        raise FramesError(f"the model's answer has no \"objects\" list; it began: {text[:200]!r}")
    ids = [f"o{k + 1}" for k in range(n)]
    out: dict = {}
    names: dict = {}
    for i, e in enumerate(doc["objects"]):
        if not isinstance(e, dict) or not isinstance(e.get("id"), str):
            raise FramesError(f"the model's answer: objects[{i}] is not an object with an \"id\" string")
        bad = set(e) - {"id", "name", "primitive", "material", "why"}
        if bad:
            raise FramesError(f"the model's answer: objects[{i}] has unknown key(s) {sorted(bad)}")
        oid = e["id"]
        if oid not in ids:
            raise FramesError(f"the model's answer names object id {oid!r}, which the reconstruction does not have "
                              f"(ids: {', '.join(ids)}); objects are never added from the model's answer")
        if oid in out:
            raise FramesError(f"the model's answer lists object {oid} twice")
        c: dict = {}
        prim = e.get("primitive")
        if prim is not None:
            if prim not in PRIMITIVES + FITTED_SHAPES:
                raise FramesError(f"the model's answer: object {oid}: primitive {prim!r} is not one of "
                                  f"{', '.join(PRIMITIVES + FITTED_SHAPES)}")
            c["primitive" if prim in PRIMITIVES else "keep"] = prim
        mat = e.get("material")
        if mat is not None:
            if not isinstance(mat, str) or mat not in MATERIALS:
                raise FramesError(f"the model's answer: object {oid}: material {mat!r} is not one of "
                                  f"{', '.join(MATERIALS)}")
            c["material"] = mat
        nm = e.get("name")
        if nm is not None:
            if (not isinstance(nm, str) or not nm or len(nm) > 40 or not set(nm) <= NAME_CHARS
                    or not nm[0].isalpha()):
                raise FramesError(f"the model's answer: object {oid}: name {nm!r} is not a lower-case identifier "
                                  "(a-z, 0-9, _; a letter first; at most 40)")
            if nm in ("table", "robot") or nm in names:
                raise FramesError(f"the model's answer: object {oid}: name {nm!r} is "
                                  + ("reserved" if nm in ("table", "robot") else f"also given to {names[nm]}"))
            names[nm] = oid
            c["name"] = nm
        out[oid] = c
    return out


def apply_model_physics(choices: dict, objects: list, warn: list) -> None:
    """The model's materials (mass and friction from MATERIALS and the fitted volume) and the
    fitted shapes it asked to keep, checked against what the frames gave (a mismatch warns)."""
    for k, o in enumerate(objects):
        c = choices.get(f"o{k + 1}") or {}
        if c.get("keep") and c["keep"] != o["_fit"]["chosen"]:
            msg = (f"o{k + 1} ({o['name']}): the model asked to keep a {c['keep']} fit, but the frames gave a "
                   f"{o['_fit']['chosen']}; kept the {o['_fit']['chosen']}")
            o["_fit"]["model_asked"] = c["keep"]
            warn.append(msg)
        if c.get("material"):
            density, friction = MATERIALS[c["material"]]
            vol = float(o["_fit"]["volume_m3"])
            if o.get("free") is not False:
                o["mass_kg"] = r(min(MASS_RANGE_KG[1], max(MASS_RANGE_KG[0], density * vol)), 4)
            o["friction"] = friction
            o["_fit"]["material"] = {"name": c["material"], "density_kg_m3": density, "friction": friction,
                                     "chosen_by": "model"}


def apply_model_names(choices: dict, objects: list, names: dict) -> list:
    """Gives objects the model's names, except where the task file's [names] will name them
    (its names are the ones its rules use; applied after this). Returns [id, old, new]."""
    done = []
    for k, o in enumerate(objects):
        nm = (choices.get(f"o{k + 1}") or {}).get("name")
        if nm and nm not in names:
            done.append([f"o{k + 1}", o["name"], nm])
            o["name"] = nm
    return done


def apply_names(names: dict, objects: list, scene: Any, clusters: list, where: str) -> None:
    """Renames objects as [names] asks: name = "colour shape" prompt, [x, y] or [x, y, z] (m,
    base frame)."""
    plane = scene.plane
    taken: dict = {}
    fixed: dict = {}
    for new, how in names.items():
        if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]*", new):
            raise FramesError(f"{where}: [names] {new!r}: a name is letters, digits, '_', '.' and '-' (it names "
                              "files under meshes/ too)")
        if isinstance(how, dict):
            bad = set(how) - {"prompt", "at", "fixed"}
            if bad or ("prompt" in how) == ("at" in how) or not isinstance(how.get("fixed", False), bool):
                raise FramesError(f"{where}: [names] {new}: a table takes prompt = \"colour shape\" or at = [x, y], "
                                  "and optionally fixed = true (welded to the world, as a fixture)")
            if "fixed" in how:
                fixed[new] = how["fixed"]
            how = how.get("prompt", how.get("at"))
        if isinstance(how, str):
            try:
                hit = rp.select(scene, how)
            except Exception as e:  # noqa: BLE001 - PromptError and friends: say which name
                raise FramesError(f"{where}: [names] {new} = {how!r}: {e}") from None
            idx = next((i for i, c in enumerate(clusters) if hit is not None and c.id == hit.id), None)
            if idx is None:
                raise FramesError(f"{where}: [names] {new} = {how!r} matches no reconstructed object")
        elif isinstance(how, list) and len(how) in (2, 3) and all(isinstance(v, (int, float)) for v in how):
            # [x, y]: the nearest object horizontally. [x, y, z]: z also counts, as its distance
            # from the object's vertical span, so a plate standing in its holder and the holder
            # under it (the same x, y) are told apart.
            d = [math.dist(how[:2], o["position_m"][:2]) for o in objects]
            dz = [0.0] * len(objects)
            if len(how) == 3:
                dz = [max(0.0, zb - how[2], how[2] - zt) for zb, zt in (_span(o, plane) for o in objects)]
            score = [math.hypot(a, b) for a, b in zip(d, dz)]
            idx = int(np.argmin(score)) if score else None
            if idx is None or d[idx] > 0.05:
                raise FramesError(f"{where}: [names] {new} = {how}: no reconstructed object within 5 cm")
        else:
            raise FramesError(f"{where}: [names] {new} must be a prompt (\"red box\") or a point [x, y]")
        if idx in taken:
            raise FramesError(f"{where}: [names] {new} and {taken[idx]} name the same object")
        taken[idx] = new
    for idx, new in taken.items():
        objects[idx]["name"] = new
        if new in fixed:
            objects[idx]["free"] = not fixed[new]


def check_rules(task: dict, objects: list) -> None:
    known = {o["name"] for o in objects} | {"table", "robot"}
    for i, rule in enumerate(task.get("success", [])):
        if not isinstance(rule, dict):
            raise FramesError(f"task rule {i + 1} is not a table")
        for key in ("object", "support", "container", "a", "b"):
            v = rule.get(key)
            if isinstance(v, str) and v not in known:
                raise FramesError(f"task rule {i + 1} ({rule.get('kind')}) names {key} '{v}', which the reconstruction "
                                  f"does not have (objects: {', '.join(o['name'] for o in objects) or 'none'}); "
                                  "name objects with [names] in the task file")
        c = rule.get("container")
        if isinstance(c, str) and c not in ("table", "robot"):
            o = next(o for o in objects if o["name"] == c)
            if "cavity_min_m" not in o:
                raise FramesError(f"task rule {i + 1} ({rule.get('kind')}) needs container '{c}' to be hollow, but the "
                                  f"reconstruction made it a solid {o['_kind']} (only round bowls, cups, open bins and "
                                  "objects cut into parts around space the frames saw empty get a cavity)")
        if rule.get("kind") == "joint":
            raise FramesError(f"task rule {i + 1} (joint) needs an articulated fixture; reconstructed fixtures are static "
                              "objects (doors and drawers from the optional model: not yet)")
        for key in ("objects", "others"):
            for v in rule.get(key, []) or []:
                if v not in known:
                    raise FramesError(f"task rule {i + 1} ({rule.get('kind')}) names '{v}' in {key}, which the "
                                      "reconstruction does not have; name objects with [names] in the task file")


# --------------------------------------------------------------------------------------------
# fit
# --------------------------------------------------------------------------------------------

def cmd_fit(a: argparse.Namespace) -> None:
    t0 = time.perf_counter()
    stage, work = Path(a.out), Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    set_stage("reading the task and the frames")
    task, names, demo, demo_scene = read_task(a.task, a.instruction)
    frames = rio.read_frames(Path(a.frames), need_depth=not a.geometry_url)
    rio.read_joints(a.joints, frames)
    rio.fill_depth(frames, a.geometry_url)
    t_read = time.perf_counter()
    urdf = str(Path(a.urdf).resolve())
    set_stage("removing the robot's pixels")
    robot_px = robot_pixels(frames, urdf, a.r2g, work, a.tcp_link)
    panda = a.panda
    views = []
    for f in frames:
        d = f.depth_m.copy()
        d[robot_px[f.id]] = np.nan
        if not np.isfinite(d).any():
            raise FramesError(f"image '{f.id}': every pixel with depth is the robot's")
        views.append(rp.CameraView(name=f"im{f.id}", rgb=f.rgb, depth=d, intrinsics=f.intrinsics,
                                   base_from_camera=f.base_from_camera,
                                   joint=f.joints if panda else None, gripper=f.gripper if panda else None))
    t_filter = time.perf_counter()
    set_stage("segmenting the scene")
    choices: dict = {}
    import warnings
    # Depth noise, read off the support plane: the height cut above the plane and the margin of
    # the free space grow with it (a fixed 5 mm cut turns the table's noise into objects).
    noise, noise_ray = depth_noise(views)
    cut = min(NOISE_CUT_MAX_M, max(SEGMENT_MIN_HEIGHT_M, NOISE_CUT_SIGMAS * noise))
    noise_warn = []
    if cut > SEGMENT_MIN_HEIGHT_M:
        noise_warn.append(f"depth noise: {noise * 1000:.1f} mm of height on the support plane ({noise_ray * 1000:.1f} mm "
                          f"along the rays): objects start {cut * 1000:.0f} mm above the table instead of "
                          f"{SEGMENT_MIN_HEIGHT_M * 1000:.0f} mm"
                          + (" (the most it is raised; anything lower is lost: average or filter the frames)"
                             if cut >= NOISE_CUT_MAX_M else ""))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            scene = rp.segment_scene(views, tracker=None, ignore_hand=panda, min_height=cut,
                                     plane_threshold=max(SEGMENT_PLANE_M, cut))
        except (ValueError, np.linalg.LinAlgError) as e:
            raise FramesError(f"no support plane or objects could be found in the frames: {e}") from None
    warn = noise_warn + [str(w.message) for w in caught] + list(scene.warnings)
    plane = scene.plane
    tilt = math.degrees(math.acos(min(1.0, abs(float(plane.normal[2])))))
    if tilt > 10:
        raise FramesError(f"the support plane is tilted {tilt:.1f} degrees from the base frame's xy plane: check "
                          "cam_R_w2c/cam_t_w2c (world must be the robot base frame, z up)")
    clusters = [o for o in scene.objects if not o.held]
    if not clusters:
        raise FramesError(f"no object found on the support plane in any of the {len(frames)} view(s) (empty masks "
                          "after removing the table and the robot)")
    llm = json.loads(Path(a.llm_answer).read_text()) if a.llm_answer else None
    if llm is not None:
        choices = read_model_answer(llm["text"], len(clusters))
    set_stage("fitting the objects")
    # Supports first, so an object on another gets that one's top.
    order = sorted(range(len(clusters)), key=lambda i: (clusters[i].support not in (None, "plane"), i))
    tops: dict = {}
    fitted: dict = {}
    # The space the source views saw through (robot pixels unknown): it checks hulls and boxes.
    free = rparts.FreeSpace(views, noise_m=noise_ray)
    sparse = [rp.voxel_downsample(c.points, 0.004)[0] if len(c.points) > 1 else c.points for c in clusters]
    for i in order:
        o = clusters[i]
        others_pts = [sparse[j] for j in range(len(clusters)) if j != i]
        foreign = np.concatenate(others_pts) if others_pts else None
        spec = fit_object(o, plane, tops, force=(choices.get(f"o{i + 1}") or {}).get("primitive"), fs=free,
                          foreign=foreign)
        tops[o.id] = spec["_top"]
        fitted[i] = spec
    # An object cut into parts must not hold another object's fitted solid either (a plate
    # standing in its holder hides the holder's slot and its own lower rim from the cameras):
    # where another object's primitive reaches into the points' extent, fit it again with that
    # solid's volume counted as not its own.
    solids = {i: solid_samples(fitted[i]) for i in fitted}
    for i in order:
        if fitted[i]["_fit"]["chosen"] not in ("parts", "container"):
            continue
        lo, hi = clusters[i].points.min(0) - 0.01, clusters[i].points.max(0) + 0.01
        extra = [S[((S >= lo) & (S <= hi)).all(1)] for j, S in solids.items() if j != i and len(S)]
        extra = [S for S in extra if len(S)]
        if not extra:
            continue
        others_pts = [sparse[j] for j in range(len(clusters)) if j != i]
        o = clusters[i]
        # What rests on it and is fitted as a solid: the unseen space under it is this
        # object's (a holder's hidden chocks under the plate standing in it).
        held = [j for j in range(len(clusters)) if j != i and clusters[j].support == o.id and len(solids.get(j, []))]
        base_z = plane_z(plane, *o.points[:, :2].mean(0)) + max(0.0, float(o.bottom))
        under = [c for j in held
                 for c in rparts.support_columns(solid_samples(fitted[j], clearance=0.0), free, base_z, lo, hi)]
        solid = np.concatenate(extra)
        # Its points inside another object's fitted solid are that object's (the shaded lower
        # rim of a plate standing in its holder, taken for the holder's colour).
        inner = np.zeros(len(o.points), dtype=bool)
        for j in fitted:
            if j != i:
                inner |= solid_contains(fitted[j], o.points)
        dropped = bool(inner.any() and (~inner).sum() >= rparts.MIN_PART_POINTS)
        if dropped:
            o = dataclasses.replace(o, points=o.points[~inner])
        spec = fit_object(o, plane, tops, fs=free, foreign=np.concatenate(others_pts) if others_pts else None,
                          solid=solid)
        spec["_fit"]["others_solids_counted"] = True
        if dropped:
            spec["_fit"]["points_in_other_solids_dropped"] = int(inner.sum())
        if under and "parts" in spec:
            boxes, vol = cradle_parts(under, spec, solid)
            spec["parts"] += boxes
            spec["_fit"]["support_columns_under"] = [clusters[j].id for j in held]
            spec["_fit"]["cradle_boxes"] = len(boxes)
            if boxes:
                volume = float(spec["_fit"]["volume_m3"]) + vol
                spec["_fit"]["volume_m3"] = float(f"{volume:.4g}")
                spec["mass_kg"] = r(min(MASS_RANGE_KG[1], max(MASS_RANGE_KG[0], DENSITY_KG_M3 * volume)), 4)
            else:
                warn.append(f"{o.color_name} object: {len(under)} support columns under what rests on it gave no "
                            "cradle box (each would reach into the object it holds up)")
        elif under:
            spec["_fit"]["support_columns_unused"] = len(under)
            warn.append(f"{o.color_name} object: fitted as a {spec['_fit']['chosen']}, not parts: the {len(under)} "
                        "support columns under what rests on it were not added (nothing holds it up where the "
                        "cameras could not see)")
        tops[o.id] = spec["_top"]
        fitted[i] = spec
    objects = []
    used_names: dict = {}
    for i, o in enumerate(clusters):
        spec = fitted[i]
        chosen = spec["_fit"]["chosen"]
        kind = {"box": "box", "cylinder": "cylinder", "sphere": "ball", "mesh": "object", "disc": "disc",
                "container": "cup", "parts": "object"}.get(chosen, "bowl")
        rect = (spec["_fit"].get("container") or {}).get("footprint") == "rectangle"
        if rect:
            kind = "bin"
        base = f"{o.color_name}_{kind}".replace(" ", "_")
        used_names[base] = used_names.get(base, 0) + 1
        name = base if used_names[base] == 1 else f"{base}_{used_names[base]}"
        obj = {"name": name}
        obj.update({k: v for k, v in spec.items() if k in ("shape", "size_m")})
        if spec.get("shape") == "mesh":
            obj["mesh"] = f"meshes/{name}.obj"
        obj["position_m"] = spec["position_m"]
        if "quat_wxyz" in spec:
            obj["quat_wxyz"] = spec["quat_wxyz"]
        if "parts" in spec:
            obj["parts"] = spec["parts"]
            if "cavity_min_m" in spec:
                obj["cavity_min_m"] = spec["cavity_min_m"]
                obj["cavity_max_m"] = spec["cavity_max_m"]
        ext = spec["_fit"]["rect_m"]
        if spec["_top"] - spec["_fit"]["bottom_m"] > FIXTURE_HEIGHT_M or max(ext) > FIXTURE_SIDE_M:
            obj["free"] = False
            spec["_fit"]["static"] = (f"taller than {FIXTURE_HEIGHT_M} m or longer than {FIXTURE_SIDE_M} m: "
                                      "kept static, as furniture; it may be an articulated fixture (a door, a "
                                      "drawer), which without the optional model becomes a static piece (box or hull) with "
                                      "no joint")
        obj["mass_kg"] = spec["mass_kg"]
        obj["rgba"] = colour_of(o, plane)
        obj["_fit"] = spec["_fit"]
        obj["_kind"] = "bin" if rect else {"container": "cup", "parts": "compound", "disc": "disc"}.get(
            chosen, "bowl" if "parts" in spec else spec["shape"])
        if "_mesh" in spec:
            obj["_mesh"] = spec["_mesh"]
        if "_bowl" in spec:
            obj["_bowl"] = spec["_bowl"]
        obj["_cluster"] = int(o.id)
        objects.append(obj)
    set_stage("naming the objects and checking the task")
    apply_model_physics(choices, objects, warn)
    llm_named = apply_model_names(choices, objects, names)
    apply_names(names, objects, scene, clusters, a.task or "--task")
    seen: dict = {}
    for k, o in enumerate(objects):
        if o["name"] in seen:
            raise FramesError(f"objects o{seen[o['name']] + 1} and o{k + 1} would both be named {o['name']!r} "
                              "(the model's names and the task file's [names] must not collide)")
        seen[o["name"]] = k
    check_rules(task, objects)
    for o in objects:
        if o["_fit"].get("static"):
            warn.append(f"{o['name']}: {o['_fit']['static']}")
    set_stage("fitting the table")
    # Table: the plane's points seen, widened to hold every object with 5 cm to spare.
    pts = []
    cols = []
    for v in views:
        m = scene.plane_masks.get(v.name)
        if m is None:
            continue
        P, idx = rp.depth_to_points(v.depth, v.intrinsics, v.base_from_camera, mask=m, stride=2)
        pts.append(P)
        cols.append(v.rgb.reshape(-1, 3)[idx])
    P = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(P) < 50:
        raise FramesError("the support plane was found but hardly any of it is seen (under 50 points)")
    lo, hi = np.percentile(P[:, :2], 1, axis=0), np.percentile(P[:, :2], 99, axis=0)
    for o in objects:
        p = np.array(o["position_m"][:2])
        lo = np.minimum(lo, p - 0.05)
        hi = np.maximum(hi, p + 0.05)
    tc = (lo + hi) / 2
    table = {"top_center_m": [r(tc[0]), r(tc[1]), r(plane_z(plane, *tc))],
             "size_m": [r(hi[0] - lo[0]), r(hi[1] - lo[1])],
             "rgba": [r(float(v), 3) for v in np.median(np.concatenate(cols), axis=0) / 255.0] + [1.0]}
    # Cameras: the scene holds at most SCENE_CAMERAS (the runtime's image slots); the gate and
    # `r2g compare --frames` use every source camera from the frames themselves.
    cameras = []
    if len(frames) > SCENE_CAMERAS:
        warn.append(f"{len(frames)} source cameras; the scene keeps the first {SCENE_CAMERAS} "
                    f"(images {', '.join(str(f.id) for f in frames[:SCENE_CAMERAS])}); every view is still "
                    "used for the fit and the gate")
    for f in frames[:SCENE_CAMERAS]:
        T = f.base_from_camera
        pos = T[:3, 3]
        cameras.append({"name": f"cam_{f.id}", "position_m": [r(v) for v in pos],
                        "look_at_m": [r(v) for v in pos + T[:3, 2]], "up": [r(v, 6) for v in -T[:3, 1]],
                        "fx": r(f.K[0, 0], 4), "fy": r(f.K[1, 1], 4), "cx": r(f.K[0, 2], 4), "cy": r(f.K[1, 2], 4),
                        "width": f.width, "height": f.height})
    f0 = frames[0]
    robot = {"urdf": urdf, "tcp_link": a.tcp_link, "base_position_m": [0.0, 0.0, 0.0],
             "initial_joints_rad": [r(q, 7) for q in f0.joints], "initial_gripper": r(f0.gripper, 4)}
    if a.limits != "panda":
        robot["limits"] = a.limits
    model = {"name": a.name or stage.name.lstrip(".").split(".partial")[0] or "reconstructed",
             "source": str(Path(a.frames).resolve()), "robot": robot, "table": table, "cameras": cameras,
             "objects": objects, "task": dict(task)}
    set_stage("writing scene.toml")
    write_scene(stage, model)
    if demo is not None:
        (stage / "demo.csv").write_bytes(demo.read_bytes())
    set_stage("writing the state for the reprojection gate")
    # State for the gate: source masks per object and view, depth, rgb.
    arrays = {}
    for f in frames:
        arrays[f"depth_{f.id}"] = f.depth_m
        arrays[f"rgb_{f.id}"] = f.rgb
        arrays[f"robot_{f.id}"] = robot_px[f.id]
        for k, o in enumerate(clusters):
            m = o.masks.get(f"im{f.id}")
            arrays[f"mask_{k}_{f.id}"] = m if m is not None else np.zeros((f.height, f.width), bool)
    np.savez_compressed(work / "state.npz", **arrays)
    cameras_json(frames, work / "cams.json")
    state = {"ids": [f.id for f in frames], "plane": [float(v) for v in plane.normal] + [float(plane.offset)],
             "model": model}
    (work / "model.json").write_text(json.dumps(state))
    report = {
        "source": model["source"], "images": [{"id": f.id, "size": [f.width, f.height], "depth": f.depth_source,
                                               "robot_pixels": int(robot_px[f.id].sum())} for f in frames],
        "world": "robot base frame", "robot": {"urdf": urdf, "self_filter": "render of the URDF at the capture joints"
                                               + (" + Panda capsules (robo_perception)" if panda else "")},
        "depth_noise": {"sigma_mm": r(noise * 1000, 2), "sigma_along_rays_mm": r(noise_ray * 1000, 2),
                        "height_cut_m": r(cut, 4), "free_space_margin_m": r(free.margin, 4),
                        "how": "1.4826 x the median distance below the mode of the heights within 2 cm of a "
                               "RANSAC support plane (points below it only)"},
        "support_plane": {"normal": [r(v, 5) for v in plane.normal], "tilt_deg": r(tilt, 3),
                          "z_at_origin_m": r(plane.height_at_origin, 5)},
        "table": table,
        "objects": [{"name": o["name"], "kind": o["_kind"], "fit": o["_fit"],
                     "first_fit": {k: o.get(k) for k in ("size_m", "position_m", "quat_wxyz")}} for o in objects],
        "task": {"empty": not task.get("success"), "instruction": task.get("instruction", "")},
        "warnings": warn, "rounds": [],
        "model": None if llm is None else {**{k: v for k, v in llm.items() if k != "text"}, "raw_answer": llm["text"],
                                           "choices": choices, "names_applied": llm_named},
        "seconds": {"read": r(t_read - t0, 3), "robot_filter": r(t_filter - t_read, 3),
                    "segment_fit": r(time.perf_counter() - t_filter, 3)},
    }
    (stage / "reconstruction.json").write_text(json.dumps(report, indent=1))
    print(json.dumps({"objects": [o["name"] for o in objects], "kinds": [o["_kind"] for o in objects],
                      "for_model": [{"id": f"o{k + 1}", "name": o["name"], "primitive": o["_fit"]["chosen"],
                                     "kind": o["_kind"], "size_m": o.get("size_m"),
                                     "position_m": o["position_m"], "rgba": o["rgba"][:3],
                                     "height_m": r(o["_fit"]["top_m"] - o["_fit"]["bottom_m"], 4),
                                     "footprint_m": o["_fit"]["rect_m"], "footprint_fill": o["_fit"]["footprint_fill"],
                                     "round_outline_residual": o["_fit"]["circle_residual"],
                                     "hollow_top": o["_fit"]["hollow"], "static": o.get("free") is False}
                                    for k, o in enumerate(objects)],
                      "materials": list(MATERIALS),
                      "task_empty": not task.get("success"), "warnings": warn,
                      "demonstration": demo is not None,
                      "demonstration_scene": str(demo_scene) if demo_scene else None}))


def write_scene(stage: Path, model: dict) -> None:
    for o in model["objects"]:
        if "_mesh" in o:
            (stage / "meshes").mkdir(exist_ok=True)
            (stage / "meshes" / f"{o['name']}.obj").write_text(obj_text(o["_mesh"]))
            o["mesh"] = f"meshes/{o['name']}.obj"
        for k, p in enumerate(o.get("parts", [])):
            if "_mesh" in p:
                (stage / "meshes").mkdir(exist_ok=True)
                # A folder per object: no part's file can take the name of another object's mesh.
                (stage / "meshes" / o["name"]).mkdir(parents=True, exist_ok=True)
                (stage / "meshes" / o["name"] / f"part{k}.obj").write_text(obj_text(p["_mesh"]))
                p["mesh"] = f"meshes/{o['name']}/part{k}.obj"
    tmp = stage / ".scene.toml.tmp"
    tmp.write_text(scene_toml(model))
    os.replace(tmp, stage / "scene.toml")


# --------------------------------------------------------------------------------------------
# gate
# --------------------------------------------------------------------------------------------

def _points(depth: np.ndarray, mask: np.ndarray, K: dict, T: np.ndarray) -> np.ndarray:
    return rp.depth_to_points(np.nan_to_num(depth, nan=0.0), K, T, mask=mask)[0]


def cmd_gate(a: argparse.Namespace) -> None:
    t0 = time.perf_counter()
    set_stage(f"reading the state of round {a.round}")
    stage, work = Path(a.out), Path(a.work)
    st = json.loads((work / "model.json").read_text())
    model = st["model"]
    ids = st["ids"]
    n = np.array(st["plane"][:3])
    plane = rp.Plane(normal=n, offset=st["plane"][3])
    arr = np.load(work / "state.npz")
    cams = json.loads((work / "cams.json").read_text())
    # The settled poses the Rust side wrote.
    settled = tomllib.loads((stage / "scene.toml").read_text())
    for o, s in zip(model["objects"], settled.get("objects", [])):
        o["position_m"] = [r(v) for v in s["position_m"]]
        if "quat_wxyz" in s:
            o["quat_wxyz"] = [r(v, 6) for v in s["quat_wxyz"]]
    out = work / f"render_{a.round}"
    set_stage(f"rendering round {a.round}")
    ren = run_render(a.r2g, stage, work / "cams.json", out)
    set_stage(f"comparing round {a.round}'s render with the source")
    per_obj = []
    for k, o in enumerate(model["objects"]):
        views = []
        for fid in ids:
            e = cams[fid]
            K = {"fx": e["cam_K"][0], "fy": e["cam_K"][4], "cx": e["cam_K"][2], "cy": e["cam_K"][5]}
            R = np.array(e["cam_R_w2c"]).reshape(3, 3)
            T = np.eye(4)
            T[:3, :3] = R.T
            T[:3, 3] = -R.T @ (np.array(e["cam_t_w2c"]) / 1000)
            src = arr[f"mask_{k}_{fid}"]
            rv = ren[fid]
            mp = rv["dir"] / "mask_visib" / f"{rv['stem']}_{k:06d}.png"
            rm = rio.read_png(mp) > 127 if mp.is_file() else np.zeros_like(src)
            # The IoU compares the whole masks (the source's from the segmentation, the render's
            # from mask_visib); the centroids below use only the points more than 5 mm above the
            # plane, as the segmentation cut does, so the bottom millimetres do not shift them.
            sd, rd = arr[f"depth_{fid}"], rv["depth"]
            inter, union = (src & rm).sum(), (src | rm).sum()
            v = {"image": fid, "source_px": int(src.sum()), "render_px": int(rm.sum()),
                 "iou": r(inter / union, 4) if union else None}
            if src.sum() >= 20 and rm.sum() >= 20:
                both = src & rm & np.isfinite(sd) & np.isfinite(rd)
                if both.sum():
                    v["depth_error_mm"] = r(float(np.mean(np.abs(sd[both] - rd[both]))) * 1000, 2)
                Ps, Pr = _points(sd, src, K, T), _points(rd, rm, K, T)
                hs, hr = plane.distance(Ps), plane.distance(Pr)
                Ps, Pr = Ps[hs > 0.005], Pr[hr > 0.005]
                if len(Ps) >= 10 and len(Pr) >= 10:
                    v["centroid_error_cm"] = r(np.linalg.norm(Ps.mean(0) - Pr.mean(0)) * 100, 3)
                    v["_dxy"] = (Ps.mean(0) - Pr.mean(0))[:2].tolist()
                    v["_area"] = [int((hs > 0.005).sum()), int((hr > 0.005).sum())]
                    v["_top"] = [float(np.percentile(hs, 99)), float(np.percentile(hr, 99))]
                rgb_s, rgb_r = arr[f"rgb_{fid}"][src & rm], rv["rgb"][src & rm]
                if len(rgb_s) >= 20:
                    v["_rgb"] = [np.mean(rgb_s, 0).tolist(), np.mean(rgb_r, 0).tolist()]
            views.append(v)
        per_obj.append(views)
    # Figures of this round.
    figures = []
    for o, views in zip(model["objects"], per_obj):
        w = [v for v in views if v.get("iou") is not None and v["source_px"] > 0]
        wt = np.array([v["source_px"] for v in w], float)
        mean = lambda key: (r(float(np.average([v[key] for v in w if key in v],  # noqa: E731
                                               weights=[v["source_px"] for v in w if key in v])), 4)
                            if any(key in v for v in w) else None)
        figures.append({"name": o["name"], "iou": mean("iou") if len(wt) else None,
                        "depth_error_mm": mean("depth_error_mm"), "centroid_error_cm": mean("centroid_error_cm"),
                        "per_view": [{k: x for k, x in v.items() if not k.startswith("_")} for v in views],
                        "position_m": o["position_m"], "size_m": o.get("size_m")})
    ious = [f["iou"] for f in figures if f["iou"] is not None]
    rnd = {"round": a.round, "mean_iou": r(float(np.mean(ious)), 4) if ious else None,
           "min_iou": r(float(np.min(ious)), 4) if ious else None, "objects": figures, "corrections": []}
    # The best round so far is kept: a correction that lowered the mean IoU is undone (the
    # scene goes back to the best round's settled poses and sizes) and the gate stops.
    best_path = work / "best.json"
    best = json.loads(best_path.read_text()) if best_path.is_file() else None
    if rnd["mean_iou"] is not None and (best is None or rnd["mean_iou"] >= best["mean_iou"]):
        best = {"round": a.round, "mean_iou": rnd["mean_iou"], "min_iou": rnd["min_iou"], "model": model}
        best_path.write_text(json.dumps(best))
        regressed = False
    else:
        regressed = best is not None
    converged = bool(ious) and min(ious) >= a.iou_goal
    if regressed:
        model = best["model"]
        st["model"] = model
        write_scene(stage, model)
        (work / "model.json").write_text(json.dumps(st))
        rnd["reverted_to_round"] = best["round"]
        converged = True
    set_stage(f"correcting round {a.round}'s objects")
    if not a.last and not converged and not regressed:
        for o, views in zip(model["objects"], per_obj):
            cor = correct(o, views, plane)
            if cor:
                rnd["corrections"].append({"name": o["name"], **cor})
        if rnd["corrections"]:
            write_scene(stage, model)
            (work / "model.json").write_text(json.dumps(st))
        else:
            converged = True
    rnd["seconds"] = r(time.perf_counter() - t0, 3)
    rep = json.loads((stage / "reconstruction.json").read_text())
    rep["rounds"].append(rnd)
    rep["kept_round"] = best["round"] if best else a.round
    if a.last or converged:
        kept_round = next((x for x in rep["rounds"] if x["round"] == rep["kept_round"]), rnd)
        rep["spurious_suspects"] = spurious_suspects(kept_round["objects"])
        rep["objects_final"] = [{k: o.get(k) for k in ("name", "shape", "size_m", "position_m", "quat_wxyz", "rgba",
                                                        "mesh")} | {"kind": o["_kind"]} for o in model["objects"]]
    tmp = stage / ".reconstruction.json.tmp"
    tmp.write_text(json.dumps(rep, indent=1))
    os.replace(tmp, stage / "reconstruction.json")
    kept = best if best is not None and regressed else rnd
    print(json.dumps({"round": a.round, "mean_iou": kept["mean_iou"], "min_iou": kept["min_iou"],
                      "corrections": len(rnd["corrections"]), "converged": converged}))


SUSPECT_IOU = 0.3
"""An object whose rendered silhouette overlaps its source mask less than this (weighted over the
views) after the gate is reported as a likely spurious piece: a fit that reproduces nothing the
frames show (a part of something else, such as a handle fitted as an object of its own)."""


def spurious_suspects(figures: list) -> list:
    """The objects of a round that are likely not objects of their own, each with the reason."""
    out = []
    for f in figures:
        if f.get("iou") is not None and f["iou"] < SUSPECT_IOU:
            out.append({"name": f["name"], "iou": f["iou"],
                        "why": f"reprojection IoU {f['iou']:.2f} < {SUSPECT_IOU}: the fitted shape does not "
                               "reproduce its pixels (likely a part of another object)"})
    return out


def correct(o: dict, views: list, plane: Any) -> dict:
    """Moves, resizes and recolours one object from its per-view comparison; returns what changed."""
    use = [v for v in views if "_dxy" in v]
    if not use:
        return {}
    wts = np.array([v["source_px"] for v in use], float)
    dxy = np.average(np.array([v["_dxy"] for v in use]), axis=0, weights=wts)
    area = np.array([v["_area"] for v in use], float)
    scale = math.sqrt(area[:, 0].sum() / max(area[:, 1].sum(), 1.0))
    tops = np.array([v["_top"] for v in use])
    dtop = float(np.average(tops[:, 0] - tops[:, 1], weights=wts))
    out: dict = {}
    kind = o["_kind"]
    # Only the colour of these is corrected. A compound cut around seen-empty space and a disc
    # on edge are placed by their fit against the other objects' points and solids: a centroid
    # shift of their visible pixels would push them into their neighbours. A cup is placed by
    # the circle fitted to its walls, which the source masks (the reconstruction's own
    # segmentation, handle and rim included) measure less well.
    fitted_in_place = kind in ("compound", "cup", "disc")
    if np.linalg.norm(dxy) > 0.0015 and not fitted_in_place:
        o["position_m"][0] = r(o["position_m"][0] + dxy[0])
        o["position_m"][1] = r(o["position_m"][1] + dxy[1])
        out["moved_xy_m"] = [r(dxy[0]), r(dxy[1])]
    s = float(np.clip(scale, 0.85, 1.15))
    if kind in ("box", "cylinder") and abs(s - 1) > 0.03:
        # The apparent area grows with the horizontal size and (for side views) with the height;
        # the height is corrected from the tops, so the rest goes to the footprint.
        if kind == "box":
            o["size_m"][0] = r(o["size_m"][0] * s)
            o["size_m"][1] = r(o["size_m"][1] * s)
        else:
            o["size_m"][0] = r(o["size_m"][0] * s)
        out["footprint_scale"] = r(s, 4)
    if kind in ("box", "cylinder") and abs(dtop) > 0.002:
        i = 2 if kind == "box" else 1
        new_half = max(0.002, o["size_m"][i] + dtop / 2)
        o["position_m"][2] = r(o["position_m"][2] + (new_half - o["size_m"][i]))
        o["size_m"][i] = r(new_half)
        out["height_change_m"] = r(dtop)
    cols = [v["_rgb"] for v in use if "_rgb" in v]
    if cols:
        src = np.mean([c[0] for c in cols], axis=0)
        ren = np.mean([c[1] for c in cols], axis=0)
        ratio = np.clip((src + 1) / (ren + 1), 0.7, 1.4)
        if np.abs(ratio - 1).max() > 0.04:
            o["rgba"] = [r(float(np.clip(o["rgba"][i] * ratio[i], 0, 1)), 3) for i in range(3)] + [1.0]
            out["colour_ratio"] = [r(v, 3) for v in ratio]
    return out


# --------------------------------------------------------------------------------------------
# anchor: how each entity of the demonstration's scene moved into the reconstruction
# --------------------------------------------------------------------------------------------

ANCHOR_NEAREST_M = 0.10
"""An entity of the demonstration's scene without a reconstructed object of its name is paired
with the nearest unpaired reconstructed object within this horizontal distance."""
ANCHOR_STILL_M = 0.0015
ANCHOR_STILL_DEG = 1.0
"""A pair closer than these is not re-anchored (the fit's own scatter)."""


def _yaw_symmetry(e: dict) -> Optional[float]:
    """The period of an entity's yaw as seen from the frames: a box's is a quarter turn when its
    footprint is (near) square, else a half turn; round and hull shapes have none we can read."""
    if e.get("shape") != "box" or e.get("parts"):
        return None
    sx, sy = e["size_m"][0], e["size_m"][1]
    return math.pi / 2 if min(sx, sy) / max(sx, sy, 1e-9) > 0.9 else math.pi


def anchor_moves(source_scene: Path, gym: Path) -> dict:
    """Pairs every entity of the demonstration's scene (objects and fixtures) with a
    reconstructed object (same name, else the nearest within ANCHOR_NEAREST_M) and measures its
    move: the world bounding-box centre from the source to the reconstruction, and for a box
    the yaw change within the box's symmetry."""
    import r2g_reconstruct_eval as ev

    src_doc = tomllib.loads(source_scene.read_text())
    rec_doc = tomllib.loads((gym / "scene.toml").read_text())
    src = []
    for kind, items in (("object", src_doc.get("objects", [])), ("fixture", src_doc.get("fixtures", []))):
        for e in items:
            b = ev.entity_box(e, source_scene.parent, kind == "fixture")
            if b is not None:
                src.append((e, b))
    rec = [(e, ev.entity_box(e, gym)) for e in rec_doc.get("objects", [])]
    rec = [(e, b) for e, b in rec if b is not None]
    pairs: dict = {}
    used: set = set()
    for i, (e, _) in enumerate(src):
        j = next((j for j, (q, _) in enumerate(rec) if q["name"] == e["name"]), None)
        if j is not None:
            pairs[i] = (j, "name")
            used.add(j)
    cand = sorted((math.dist(b[0][:2], q[0][:2]), i, j) for i, (_, b) in enumerate(src) if i not in pairs
                  for j, (_, q) in enumerate(rec) if j not in used)
    for d, i, j in cand:
        if d > ANCHOR_NEAREST_M or i in pairs or j in used:
            continue
        pairs[i] = (j, "nearest")
        used.add(j)
    moves, still, unmatched = [], [], []
    for i, (e, b) in enumerate(src):
        if i not in pairs:
            unmatched.append(e["name"])
            continue
        j, by = pairs[i]
        q, qb = rec[j]
        dyaw = 0.0
        period = _yaw_symmetry(e)
        if period is not None and q.get("shape") == "box":
            d = yaw_of(q.get("quat_wxyz", [1, 0, 0, 0])) - yaw_of(e.get("quat_wxyz", [1, 0, 0, 0]))
            dyaw = (d + period / 2) % period - period / 2
        t = (qb[0] - b[0]).tolist()
        row = {"entity": e["name"], "to": q["name"], "by": by, "from_m": [r(v) for v in b[0]],
               "to_m": [r(v) for v in qb[0]], "translation_m": [r(v) for v in t], "yaw_deg": r(math.degrees(dyaw), 3)}
        if np.linalg.norm(t) < ANCHOR_STILL_M and abs(math.degrees(dyaw)) < ANCHOR_STILL_DEG:
            still.append(row)
        else:
            moves.append(row)
    return {"moves": moves, "unchanged": still, "unmatched": unmatched,
            "unpaired_reconstructed": [rec[j][0]["name"] for j in range(len(rec)) if j not in used]}


def cmd_anchor(a: argparse.Namespace) -> None:
    print(json.dumps(anchor_moves(Path(a.source_scene), Path(a.out))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fit")
    f.add_argument("--frames", required=True)
    f.add_argument("--urdf", required=True)
    f.add_argument("--panda", action="store_true", help="the URDF is the Panda's: use its capsule self-filter too")
    f.add_argument("--limits", default="panda")
    f.add_argument("--tcp-link", default="hand_tcp", help="the URDF link the scene's robot uses as its TCP")
    f.add_argument("--joints", required=True)
    f.add_argument("--out", required=True)
    f.add_argument("--work", required=True)
    f.add_argument("--r2g", required=True)
    f.add_argument("--name")
    f.add_argument("--task")
    f.add_argument("--instruction")
    f.add_argument("--geometry-url")
    f.add_argument("--llm-answer", help="JSON {text, model, source}: the model's answer to apply")
    g = sub.add_parser("gate")
    g.add_argument("--out", required=True)
    g.add_argument("--work", required=True)
    g.add_argument("--r2g", required=True)
    g.add_argument("--round", type=int, required=True)
    g.add_argument("--last", action="store_true")
    g.add_argument("--iou-goal", type=float, default=0.9)
    n = sub.add_parser("anchor")
    n.add_argument("--out", required=True)
    n.add_argument("--source-scene", required=True)
    a = ap.parse_args()
    run_step({"fit": cmd_fit, "gate": cmd_gate, "anchor": cmd_anchor}[a.cmd], a)


def run_step(fn, a: argparse.Namespace) -> None:
    """Runs one step; every failure leaves as one "error: ..." line on stderr (exit status 2).

    Input problems (FramesError) and failed sub-commands (RuntimeError) say what was wrong. Any
    other exception is a fault of this program: the line names the step and the stage it was in;
    the traceback goes to ``<work>/traceback-<step>.txt`` only when R2G_RECONSTRUCT_KEEP_WORK or
    R2G_DEBUG is set (the Rust side removes the work folder otherwise).
    """
    STAGE[0] = "starting"
    try:
        fn(a)
    except (FramesError, RuntimeError) as e:
        fail(str(e))
    except Exception as e:  # noqa: BLE001 - the last line of defence: one line, never a raw traceback
        where = f"the reconstruction's {a.cmd} step failed while {STAGE[0]}: {type(e).__name__}: {e}"
        work = getattr(a, "work", None)
        if work and (os.environ.get("R2G_RECONSTRUCT_KEEP_WORK") or os.environ.get("R2G_DEBUG")):
            try:
                Path(work).mkdir(parents=True, exist_ok=True)
                tb = Path(work) / f"traceback-{a.cmd}.txt"
                tb.write_text(traceback.format_exc())
                where += f" (traceback in {tb})"
            except OSError:
                pass
        else:
            where += " (set R2G_RECONSTRUCT_KEEP_WORK=1 to keep the traceback in the work folder)"
        fail(" ".join(where.split("\n")))


if __name__ == "__main__":
    main()
