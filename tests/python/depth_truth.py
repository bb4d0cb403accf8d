"""Ground truth for the cameras' depth (tests and bench/py/depth_agreement.py; never used by `robo`).

Back-projects a raw observation the documented way (robot-skill/api/README.md, "Raw images and
depth": pixel `[v, u]` with depth `d` is the camera-frame point `((u - cx) d / fx, (v - cy) d / fy,
d)`, intrinsics of the size returned, times `camera_extrinsics[cam]` = base_from_camera) and
compares every pixel with what MuJoCo's own ray caster (`mj_multiRay`) hits through the centre
of the same pixel, in the very MJCF the sim-host runs, posed from the measured joints and the
native trace's object and fixture poses. The truth uses MuJoCo's camera (its pose in `MjData`,
the frustum its `fovy` defines) and nothing the sim-host publishes, so a wrong principal point,
focal length, camera pose or depth sample all show up as errors.

Classes of pixels: `table` (the table's top), `top` (the upward faces of the scene's boxes and
cylinders whose axis is vertical: a block's top, a plate, a bowl's floor, a cabinet's roof) and
`edge` (any pixel whose 4-neighbours show another geom or a depth more than 1 cm away: there a
pixel's centre and a neighbour's differ in what they see; reported, never used for the table and
top-face figures).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Mapping, Optional, Sequence

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
import mujoco  # noqa: E402


# The geom groups the sim-host's renderer draws (MuJoCo's default visualisation: 0, 1, 2); the
# sim-host's collision geoms are in group 3, invisible.
VISIBLE_GROUPS = np.array([1, 1, 1, 0, 0, 0], dtype=np.uint8)


def backproject(depth: np.ndarray, intr: Mapping, base_from_camera) -> np.ndarray:
    """(H, W, 3) base-frame points of a depth image, the documented way."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = depth.astype(np.float64)
    pc = np.stack([(u - intr["cx"]) * d / intr["fx"], (v - intr["cy"]) * d / intr["fy"], d], -1)
    T = np.asarray(base_from_camera, dtype=np.float64)
    return pc @ T[:3, :3].T + T[:3, 3]


class Truth:
    """One gym's model (the compiled MJCF), posed with `set_state`; `cast` gives per pixel what
    MuJoCo sees through its centre."""

    def __init__(self, xml: str):
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.table = m.geom("table").id
        self.floor = m.geom("floor").id  # drawn 6 m x 6 m; MuJoCo's rays hit the plane forever
        base_body = int(m.body_parentid[m.jnt_bodyid[m.joint("joint1").id]])
        self.base_body = base_body
        # every geom's top-level body under the world; robot geoms hang from the base body
        top = np.zeros(m.ngeom, dtype=np.int64)
        for g in range(m.ngeom):
            b = int(m.geom_bodyid[g])
            while b != 0 and m.body_parentid[b] != 0:
                b = int(m.body_parentid[b])
            top[g] = b
        self.top_body = top

    def owner(self, g: int) -> str:
        b = int(self.top_body[g])
        if b == 0:
            return mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, g) or "world"
        if b == self.base_body:
            return "robot"
        return self.model.body(b).name

    def set_state(self, joints: Sequence[float], finger_m: float, objects: Mapping[str, Sequence[float]],
                  fixtures: Mapping[str, float]) -> None:
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        for i, q in enumerate(joints):
            d.qpos[m.jnt_qposadr[m.joint(f"joint{i + 1}").id]] = q
        for j in ("finger_joint1", "finger_joint2"):
            d.qpos[m.jnt_qposadr[m.joint(j).id]] = finger_m
        for name, pose in objects.items():
            jnt = int(m.body_jntadr[m.body(name).id])
            if jnt >= 0 and m.jnt_type[jnt] == mujoco.mjtJoint.mjJNT_FREE:
                a = m.jnt_qposadr[jnt]
                d.qpos[a:a + 7] = pose
        for name, value in fixtures.items():
            d.qpos[m.jnt_qposadr[m.joint(f"{name}__joint").id]] = value
        mujoco.mj_forward(m, d)

    def world_from_base(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[self.base_body].reshape(3, 3)
        T[:3, 3] = self.data.xpos[self.base_body]
        return T

    def camera(self, name: str) -> np.ndarray:
        """MuJoCo's camera as a world-from-optical 4x4 (x right, y down, z forward)."""
        c = self.model.camera(name).id
        T = np.eye(4)
        T[:3, :3] = self.data.cam_xmat[c].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
        T[:3, 3] = self.data.cam_xpos[c]
        return T

    def cast(self, name: str, width: int, height: int) -> "Cast":
        """What the centre of every pixel of camera `name` (rendered `width` x `height`) sees."""
        m, d = self.model, self.data
        f = 0.5 * height / np.tan(0.5 * np.radians(m.cam_fovy[m.camera(name).id]))
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        # MuJoCo's frustum is symmetric about the image centre; pixel [v, u] spans [u, u+1) x [v, v+1).
        dc = np.stack([(u + 0.5 - width / 2) / f, (v + 0.5 - height / 2) / f, np.ones_like(u)], -1).reshape(-1, 3)
        Twc = self.camera(name)
        dw = dc @ Twc[:3, :3].T
        dw /= np.linalg.norm(dw, axis=1, keepdims=True)
        n = dw.shape[0]
        geom = np.zeros(n, dtype=np.int32)
        dist = np.zeros(n)
        mujoco.mj_multiRay(m, d, Twc[:3, 3].copy(), dw.ravel(), VISIBLE_GROUPS, 1, -1, geom, dist, None, n, 1e3)
        planar = dist / np.linalg.norm(dc, axis=1)  # ray length -> depth along the optical axis
        hit = Twc[:3, 3] + dw * dist[:, None]
        Tbw = np.linalg.inv(self.world_from_base())
        hit_base = hit @ Tbw[:3, :3].T + Tbw[:3, 3]
        geom = geom.reshape(height, width)
        planar = np.where(geom >= 0, planar.reshape(height, width), np.nan)
        hit_base[(geom < 0).ravel()] = np.nan
        top = self._top_faces(geom, hit.reshape(height, width, 3))
        edge = _edges(geom, planar)
        return Cast(name, geom, planar, hit_base.reshape(height, width, 3), top, edge, Twc)

    def _top_faces(self, geom: np.ndarray, hit: np.ndarray) -> np.ndarray:
        """Pixels whose hit lies on the upward face of a box or a vertical cylinder of an object or
        fixture (not the robot, table or floor)."""
        m, d = self.model, self.data
        out = np.zeros(geom.shape, dtype=bool)
        for g in np.unique(geom[geom >= 0]):
            if self.top_body[g] in (0, self.base_body):
                continue
            kind = int(m.geom_type[g])
            if kind not in (mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_CYLINDER):
                continue
            R = d.geom_xmat[g].reshape(3, 3)
            if R[2, 2] < np.cos(np.radians(0.5)):  # its axis is not vertical
                continue
            half = m.geom_size[g][2 if kind == mujoco.mjtGeom.mjGEOM_BOX else 1]
            sel = geom == g
            local_z = (hit[sel] - d.geom_xpos[g]) @ R[:, 2]
            on_top = np.abs(local_z - half) < 1e-5
            idx = np.flatnonzero(sel.ravel())[on_top]
            out.ravel()[idx] = True
        return out


def _edges(geom: np.ndarray, depth: np.ndarray) -> np.ndarray:
    e = np.zeros(geom.shape, dtype=bool)
    dd = np.nan_to_num(depth, nan=1e9)
    for axis in (0, 1):
        a = np.diff(geom, axis=axis) != 0
        b = np.abs(np.diff(dd, axis=axis)) > 0.01
        x = a | b
        if axis == 0:
            e[:-1] |= x
            e[1:] |= x
        else:
            e[:, :-1] |= x
            e[:, 1:] |= x
    return e


@dataclass
class Cast:
    camera: str
    geom: np.ndarray  # (H, W) geom id, -1: nothing
    depth: np.ndarray  # (H, W) planar depth through the pixel centre, m (nan: nothing)
    point: np.ndarray  # (H, W, 3) hit point, base frame
    top: np.ndarray  # (H, W) bool: an upward flat face
    edge: np.ndarray  # (H, W) bool
    world_from_camera: np.ndarray


def _stats(x: np.ndarray) -> dict:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"n": 0}
    return {"n": int(x.size), "median_mm": float(np.median(x) * 1e3), "p5_mm": float(np.percentile(x, 5) * 1e3),
            "p95_mm": float(np.percentile(x, 95) * 1e3), "max_abs_mm": float(np.abs(x).max() * 1e3)}


@dataclass
class CameraReport:
    camera: str
    intrinsics: dict
    extrinsics_error_m: float  # published base_from_camera vs MuJoCo's camera, largest entry
    depth_error: dict  # rendered depth - truth depth, interior pixels but the floor
    table: dict  # back-projected z - truth z on the table's top (interior pixels)
    table_regions: list  # 3 x 3 medians (mm) of the table's height error, image rows x columns
    top: dict  # the same on upward flat faces
    top_faces: dict  # "owner@height" -> {"n", "height_m" (median read), "truth_m", "median_mm"} (faces of 20+ pixels)
    edge: dict  # 3-D distance back-projected point - truth point on edge pixels
    points: np.ndarray = field(repr=False, default=None)


def measure(obs: Mapping, truth: Truth, camera: str) -> CameraReport:
    """Per-pixel comparison of one camera of a raw observation with the posed `truth`."""
    depth = np.asarray(obs["depth"][camera], dtype=np.float64)
    intr = obs["camera_intrinsics"][camera]
    h, w = depth.shape
    c = truth.cast(camera, w, h)
    T = np.asarray(obs["camera_extrinsics"][camera], dtype=np.float64)
    Twc_pub = truth.world_from_base() @ T
    ext_err = float(np.abs(Twc_pub - c.world_from_camera).max())
    P = backproject(depth, intr, T)
    dz = P[..., 2] - c.point[..., 2]
    interior = ~c.edge & (c.geom >= 0)
    table = interior & (c.geom == truth.table)
    top = interior & c.top
    regions = []
    for i in range(3):
        row = []
        for j in range(3):
            sel = np.zeros_like(table)
            sel[i * h // 3:(i + 1) * h // 3, j * w // 3:(j + 1) * w // 3] = True
            sel &= table
            row.append(float(np.median(dz[sel]) * 1e3) if sel.any() else None)
        regions.append(row)
    # each flat face seen: (owner, its height to 0.1 mm) -> heights read and true
    faces = {}
    for g in np.unique(c.geom[top]):
        sel = top & (c.geom == g)
        t = c.point[..., 2][sel]
        key = f"{truth.owner(int(g))}@{np.median(t):.4f}"
        e = faces.setdefault(key, {"z": [], "t": []})
        e["z"].append(P[..., 2][sel])
        e["t"].append(t)
    top_faces = {}
    for key, e in sorted(faces.items()):
        z, t = np.concatenate(e["z"]), np.concatenate(e["t"])
        if z.size >= 20:
            top_faces[key] = {"n": int(z.size), "height_m": float(np.median(z)), "truth_m": float(np.median(t)),
                              "median_mm": float(np.median(z - t) * 1e3)}
    edge = c.edge & (c.geom >= 0) & (c.geom != truth.floor)
    return CameraReport(
        camera=camera, intrinsics=dict(intr), extrinsics_error_m=ext_err,
        depth_error=_stats((depth - c.depth)[interior & (c.geom != truth.floor)]),
        table=_stats(dz[table]), table_regions=regions, top=_stats(dz[top]), top_faces=top_faces,
        edge=_stats(np.linalg.norm(P - c.point, axis=-1)[edge]), points=P)


def posed_truth(xml_or_truth, obs: Mapping, objects: Mapping, fixtures: Mapping) -> Truth:
    """`Truth` posed as the observation's robot (measured joints and finger) and the trace's objects."""
    t = xml_or_truth if isinstance(xml_or_truth, Truth) else Truth(xml_or_truth)
    finger = 0.04 * (1.0 - float(obs["gripper"][0])) / 2.0  # one finger's opening (api/README.md)
    t.set_state(obs["joint"], finger, objects, fixtures)
    return t


def first_free_object(scene: Mapping) -> Optional[Sequence[float]]:
    for o in scene.get("objects", []):
        if o.get("free", True):
            return o["position_m"]
    return None
