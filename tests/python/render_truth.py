"""Ground truth for perception tests and the perception benchmark (never used by `robo`).

`LiveGym` runs one `r2g up <gym> --mode lockstep` (optionally with the native trace, whose
recorded object poses say whether something was really lifted).

Renders MuJoCo's own segmentation of a gym with the pinned `mujoco` Python wheel, from the very
MJCF the sim-host compiles (`r2g-sim <scene> --dump-mjcf F --exit-after-dump`), posed from the
measured joint positions and, when given, object poses from the sim-host's native trace. Each
pixel is labelled with the name of the scene element owning the geom drawn there: an object or
fixture name, `robot`, or `world` (table, floor).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT / "agent-host" / "py" / "lib") not in sys.path:  # robo_perception, for the tooling below
    sys.path.insert(0, str(ROOT / "agent-host" / "py" / "lib"))
R2G = Path(os.environ.get("R2G_BIN", str(ROOT / "target" / "release" / "r2g")))
"""The r2g binary live tests run ($R2G_BIN, default this checkout's release build)."""
GYMS_DIR = Path(os.environ.get("R2G_GYMS", str(ROOT / "gyms")))
"""The gym pack ($R2G_GYMS, default this checkout's gyms/)."""

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
import mujoco  # noqa: E402


class LiveGym:
    """One `r2g up` process (`mode` lockstep, or wall for real time), stopped with SIGTERM to its
    own pid. `use` points this process's `robo` at it; `stop` points it back where it pointed
    before (a fixture's instance)."""

    def __init__(self, r2g: Path, gyms_dir: Path, gym: str, trace_dir: Optional[Path] = None, tag: str = "g",
                 mode: str = "lockstep", scene: Optional[Path] = None):
        """``gym``: a gym of ``gyms_dir``, or with ``scene`` (a scene file elsewhere, started
        from its path) only a label for the instance's name."""
        self.gym = gym
        self.previous_instance = os.environ.get("R2G_INSTANCE")
        self.instance = f"{tag}{os.getpid()}_{gym}"
        self.scene_path = Path(scene) if scene is not None else gyms_dir / gym / "scene.toml"
        self.scene = tomllib.loads(self.scene_path.read_text())
        self.trace_dir = trace_dir
        cmd = [str(r2g), "up", str(scene) if scene is not None else gym, "--instance", self.instance, "--mode", mode]
        if trace_dir is not None:
            cmd += ["--trace-dir", str(trace_dir)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
                                     text=True)
        self.ready = threading.Event()
        threading.Thread(target=self._watch, daemon=True).start()

    def _watch(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("READY"):
                self.ready.set()

    def stop(self) -> None:
        """Stops the instance (the episode in progress is judged and its trace written)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if os.environ.get("R2G_INSTANCE") == self.instance:
            if self.previous_instance is None:
                os.environ.pop("R2G_INSTANCE", None)
            else:
                os.environ["R2G_INSTANCE"] = self.previous_instance

    def use(self) -> None:
        os.environ["R2G_INSTANCE"] = self.instance

    def observe(self, cameras: Sequence[str] = ("agentview", "wrist")) -> dict:
        """A raw observation with copied arrays (so the instance can change afterwards)."""
        import robo
        self.use()
        s = dict(robo.get_state(list(cameras), raw=True))
        s["image"] = {k: np.array(v) for k, v in s["image"].items()}
        s["depth"] = {k: np.array(v) for k, v in s["depth"].items()}
        return s

    def traces(self) -> list[Path]:
        assert self.trace_dir is not None
        return sorted(self.trace_dir.glob("episode-*.trace.json"), key=lambda p: int(p.name.split("-")[1].split(".")[0]))

    def end_episode(self, timeout: float = 20.0) -> dict:
        """Resets the scene (which ends the episode) and returns its native trace."""
        import robo
        before = len(self.traces())
        self.use()
        robo.reset()
        deadline = time.time() + timeout
        while time.time() < deadline:
            t = self.traces()
            if len(t) > before:
                for _ in range(50):
                    try:
                        return json.loads(t[-1].read_text())
                    except json.JSONDecodeError:  # still being written
                        time.sleep(0.1)
            time.sleep(0.1)
        raise TimeoutError(f"{self.gym}: no new trace in {self.trace_dir} within {timeout} s")


def object_rise(trace: dict, name: str) -> float:
    """How far the object's centre ended above where it started (m), from the native trace."""
    i = trace["objects"].index(name)
    samples = trace["samples"]
    return float(samples[-1]["objects"][i][2] - samples[0]["objects"][i][2])


def compiled_mjcf(r2g_sim: Path, scene: Path) -> str:
    """The MJCF the sim-host runs for `scene`."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "model.xml"
        r = subprocess.run([str(r2g_sim), str(scene), "--instance", f"truth{os.getpid()}", "--render-hz", "0",
                            "--dump-mjcf", str(out), "--exit-after-dump"], capture_output=True, text=True, timeout=60)
        if r.returncode != 0:
            raise RuntimeError(f"r2g-sim could not compile {scene}: {r.stderr.strip()}")
        return out.read_text()


class TruthRenderer:
    """Segmentation (and RGB, to check alignment) of one gym's model at a given state."""

    def __init__(self, xml: str, width: int = 640, height: int = 480):
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        self.width, self.height = width, height
        self.renderer = mujoco.Renderer(self.model, height, width)
        m = self.model
        self.objects = {}  # root body id -> scene element name
        owner = np.zeros(m.ngeom, dtype=np.int64)
        names = []
        for g in range(m.ngeom):
            b = int(m.geom_bodyid[g])
            while b != 0 and m.body_parentid[b] != 0:
                b = int(m.body_parentid[b])
            name = "world" if b == 0 else m.body(b).name
            if name == "link0":
                name = "robot"
            if name not in names:
                names.append(name)
            owner[g] = names.index(name)
        self.names = names
        self.owner = owner
        mujoco.mj_forward(m, self.data)

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

    def set_state(self, joints: Sequence[float], finger_m: Optional[float] = None,
                  objects: Optional[Mapping[str, Sequence[float]]] = None,
                  fixtures: Optional[Mapping[str, float]] = None) -> None:
        """Arm joints (7, rad), one finger's opening (m), object poses (name -> world position +
        quaternion w, x, y, z, as the trace records them) and fixture joints (name -> rad or m);
        the rest stays as compiled."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        for i, q in enumerate(joints):
            d.qpos[m.jnt_qposadr[m.joint(f"joint{i + 1}").id]] = q
        if finger_m is not None:
            for j in ("finger_joint1", "finger_joint2"):
                d.qpos[m.jnt_qposadr[m.joint(j).id]] = finger_m
        for name, pose in (objects or {}).items():
            body = m.body(name)
            jnt = int(m.body_jntadr[body.id])
            if jnt < 0 or m.jnt_type[jnt] != mujoco.mjtJoint.mjJNT_FREE:
                raise ValueError(f"{name} has no free joint")
            a = m.jnt_qposadr[jnt]
            d.qpos[a:a + 7] = pose
        for name, value in (fixtures or {}).items():
            d.qpos[m.jnt_qposadr[m.joint(f"{name}__joint").id]] = value
        mujoco.mj_forward(m, d)

    def segmentation(self, camera: str) -> np.ndarray:
        """(H, W) int array of indices into `self.names`; -1 where nothing is drawn."""
        self.renderer.enable_segmentation_rendering()
        self.renderer.update_scene(self.data, camera=camera)
        seg = self.renderer.render()
        self.renderer.disable_segmentation_rendering()
        ids, types = seg[..., 0], seg[..., 1]
        out = np.full(ids.shape, -1, dtype=np.int64)
        geom = (types == int(mujoco.mjtObj.mjOBJ_GEOM)) & (ids >= 0)
        out[geom] = self.owner[ids[geom]]
        return out

    def masks(self, camera: str) -> dict[str, np.ndarray]:
        seg = self.segmentation(camera)
        return {n: seg == i for i, n in enumerate(self.names)}

    def geom_segmentation(self, camera: str) -> np.ndarray:
        """(H, W) int array of the geom drawn at each pixel; -1 where nothing is drawn. Finer
        than `segmentation`: it tells a door's leaf from its handle."""
        self.renderer.enable_segmentation_rendering()
        self.renderer.update_scene(self.data, camera=camera)
        seg = self.renderer.render()
        self.renderer.disable_segmentation_rendering()
        ids, types = seg[..., 0], seg[..., 1]
        return np.where((types == int(mujoco.mjtObj.mjOBJ_GEOM)) & (ids >= 0), ids, -1).astype(np.int64)

    def drawn_geoms(self, body: str) -> list[int]:
        """The geoms of `body` itself (not its children) that cameras draw (groups 0-2)."""
        m = self.model
        b = m.body(body).id
        return [g for g in range(m.ngeom) if int(m.geom_bodyid[g]) == b and int(m.geom_group[g]) <= 2]

    def vertical_extent(self, geoms: Sequence[int]) -> tuple[float, float]:
        """Lowest and highest world z of the given geoms at the current state (corners of each
        geom's bounding box, which for boxes is the box itself)."""
        m, d = self.model, self.data
        s = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=float)
        zs = []
        for g in geoms:
            c, h = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
            local = c + s * h
            world = local @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
            zs.append(world[:, 2])
        z = np.concatenate(zs)
        return float(z.min()), float(z.max())

    def subtree_geoms(self, body: str) -> list[int]:
        """The drawn geoms of `body` and every body under it."""
        m = self.model
        root = m.body(body).id
        out = []
        for g in range(m.ngeom):
            b = int(m.geom_bodyid[g])
            while b not in (0, root):
                b = int(m.body_parentid[b])
            if b == root and int(m.geom_group[g]) <= 2:
                out.append(g)
        return out

    def rgb(self, camera: str) -> np.ndarray:
        self.renderer.update_scene(self.data, camera=camera)
        return self.renderer.render()


def initial_fixtures(scene: Mapping) -> dict[str, float]:
    """Each jointed fixture's starting value from a parsed scene.toml, in MuJoCo units."""
    out = {}
    for fx in scene.get("fixtures", []):
        j = fx.get("joint")
        if j:
            v = float(j.get("initial", 0.0))
            out[fx["name"]] = np.radians(v) if j.get("kind", "hinge") == "hinge" else v
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


# ------------------------------------------------------------------------------------------
# Moving a live gym (test and benchmark tooling; the instance is the one last `use`d)
# ------------------------------------------------------------------------------------------

def down(yaw: float) -> list[float]:
    """Axis-angle of the hand pointing straight down, turned by `yaw` about the vertical."""
    import robo_perception as rp
    R = rp.axis_angle_to_matrix([0.0, 0.0, yaw]) @ rp.axis_angle_to_matrix([math.pi, 0.0, 0.0])
    return [float(v) for v in rp.matrix_to_axis_angle(R)]


def move_tcp(xyz: Sequence[float], yaw: float, gripper: float = -1.0, hop: float = 0.2) -> bool:
    """One ee_pose chunk to `xyz` pointing down at `yaw`: up to `hop`, across, down (steps of at
    most 4 cm / 0.3 rad). True when it executed."""
    import robo
    import robo_perception as rp
    here = list(robo.get_state([])["ee_pose"])
    goal = list(xyz) + down(yaw)
    via = [here[:2] + [max(hop, here[2])] + here[3:], list(xyz[:2]) + [max(hop, xyz[2])] + goal[3:], goal]
    path, start = [], here
    for p in via:
        if p is goal or np.linalg.norm(np.subtract(p[:3], start[:3])) > 1e-4:
            path += rp.interpolate_poses(start, p, 0.04, 0.3)
            start = p
    return robo.post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints(path, gripper)}) == 1


def move_joints(target: Sequence[float], gripper: float = -1.0) -> bool:
    """One joint chunk, straight in joint space, steps of at most 0.3 rad. True when it executed."""
    import robo
    here = np.asarray(robo.get_state([])["joint"])
    n = max(1, int(math.ceil(np.abs(np.asarray(target) - here).max() / 0.3)))
    path = [list(here + (np.asarray(target) - here) * (k / n)) + [gripper] for k in range(1, n + 1)]
    return robo.post_actions({"type": "joint", "freq": "", "actions": path}) == 1


def trace_state(scene: dict, trace: dict, t: Optional[float] = None) -> tuple[dict, dict]:
    """Object poses and fixture joints (MuJoCo units) of a native trace's last sample, or of the
    sample nearest simulated time `t` (s)."""
    last = trace["samples"][-1] if t is None else min(trace["samples"], key=lambda s: abs(s["t_s"] - t))
    objects = {n: last["objects"][i] for i, n in enumerate(trace["objects"])}
    kinds = {f["name"]: (f.get("joint") or {}).get("kind", "hinge") for f in scene.get("fixtures", [])}
    fixtures = {n: (math.radians(v) if kinds.get(n) == "hinge" else v) for n, v in zip(trace["joints"], last["joints"])}
    return objects, fixtures
