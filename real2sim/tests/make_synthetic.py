"""SYNTHETIC test episodes in the DROID and EgoDex layouts, made from one of our gyms.

    make_synthetic.py droid  --gym gyms/pick_block_plate --out DIR [--seed N] [--break KIND] [--no-action]
    make_synthetic.py egodex --gym gyms/pick_block_plate --out DIR [--seed N] [--break KIND]

Everything written here is synthetic (generated from a gym's demonstration, not recorded),
labelled so in the files (`synthetic` attribute / metadata key) and in `truth.json`.

This script is deliberately independent of the importer it tests: it parses the robot's URDF
itself and computes forward kinematics with numpy and scipy's rotations, and it writes each
source's conventions from their published descriptions (DROID: flange pose as xyz + Euler
"xyz" in the base, gripper 1 - width/max, 15 Hz, robot timestamps; EgoDex: 4x4 world poses in
ARKit's y-up world with an arbitrary origin, ARKit camera axes, confidences, 30 Hz). Had the
importer a convention wrong, the ground truth would not come back.

Ground truth, noise, a non-identity ARKit offset and low-confidence frames go into DIR:
`truth.json` (the gym's rows, the expected registration, camera intrinsics and the pixels of a
point per frame for reprojection tests) and, for EgoDex, `registration.json` (the
`--registration` file a user would give).

--break makes a bad file on purpose: missing_field, wrong_shape, nan, nonmonotonic and rotated
(DROID: the recorded flange turned at one frame), hand_never_seen (EgoDex), unreachable.
EgoDex episodes always hold one confident frame with coinciding thumb and index tips. --no-action leaves out DROID's commanded
`action/gripper_position` (a valid file: only the measured opening tells the gripper).
"""

import argparse
import json
import math
import os
import xml.etree.ElementTree as ET
from typing import Dict, List, Optional, Tuple

import h5py
import numpy as np
from scipy.spatial.transform import Rotation

Pose = Tuple[np.ndarray, Rotation]


class Chain:
    """Serial chain from the URDF root to one link: fixed and revolute joints only."""

    def __init__(self, urdf: str, tip: str) -> None:
        root = ET.parse(urdf).getroot()
        by_child = {j.find("child").get("link"): j for j in root.findall("joint")}  # type: ignore[union-attr]
        joints = []
        link = tip
        while link in by_child:
            j = by_child[link]
            joints.append(j)
            link = j.find("parent").get("link")  # type: ignore[union-attr]
        self.joints = list(reversed(joints))

    def fk(self, q: np.ndarray) -> Pose:
        p = np.zeros(3)
        r = Rotation.identity()
        k = 0
        for j in self.joints:
            o = j.find("origin")
            xyz = np.array([float(v) for v in (o.get("xyz") if o is not None else "0 0 0").split()])
            rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
            p = p + r.apply(xyz)
            r = r * Rotation.from_euler("xyz", rpy)  # URDF rpy: fixed-axis roll, pitch, yaw
            if j.get("type") == "revolute":
                axis = np.array([float(v) for v in j.find("axis").get("xyz").split()])  # type: ignore[union-attr]
                r = r * Rotation.from_rotvec(axis / np.linalg.norm(axis) * q[k])
                k += 1
        return p, r


def read_gym(gym: str) -> Tuple[dict, np.ndarray, str]:
    import tomllib

    with open(os.path.join(gym, "scene.toml"), "rb") as f:
        scene = tomllib.load(f)
    rows = np.loadtxt(os.path.join(gym, scene["task"].get("demonstration", "demo.csv")), delimiter=",", skiprows=1)
    urdf = os.path.normpath(os.path.join(gym, scene["robot"]["urdf"]))
    return scene, rows, urdf


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> Rotation:
    """Optical frame (x right, y down, z forward) at `eye` looking at `target`."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Rotation.from_matrix(np.column_stack([x, y, z]))


def project(k: np.ndarray, cam_p: np.ndarray, cam_r: Rotation, point: np.ndarray) -> List[float]:
    c = cam_r.inv().apply(point - cam_p)
    return [float(k[0, 0] * c[0] / c[2] + k[0, 2]), float(k[1, 1] * c[1] / c[2] + k[1, 2])]


def interp_rows(t_new: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t_new, t, rows[:, j]) for j in range(rows.shape[1])])


def hold(t_new: np.ndarray, hz: float, values: np.ndarray) -> np.ndarray:
    idx = np.clip(np.floor(t_new * hz + 1e-9).astype(int), 0, len(values) - 1)
    return values[idx]


def droid(gym: str, out: str, seed: int, brk: Optional[str], action: bool = True) -> None:
    rng = np.random.default_rng(seed)
    scene, rows, urdf = read_gym(gym)
    hz = float(scene["task"].get("demonstration_hz", 20.0))
    t20 = np.arange(len(rows)) / hz
    t15 = np.arange(0.0, t20[-1] + 1e-9, 1.0 / 15.0)
    t15[1:-1] += rng.uniform(-0.002, 0.002, len(t15) - 2)  # clock jitter
    q = interp_rows(t15, t20, rows[:, :7])
    closed_cmd = hold(t15, hz, (rows[:, 7] + 1.0) / 2.0)
    # The measured opening lags the command (first order, 0.1 s) and stops at the object.
    measured = np.zeros_like(closed_cmd)
    for k in range(1, len(t15)):
        a = 1.0 - math.exp(-(t15[k] - t15[k - 1]) / 0.1)
        measured[k] = measured[k - 1] + a * (min(closed_cmd[k], 0.55) - measured[k - 1])
    flange = Chain(urdf, "link8")
    cart = np.zeros((len(t15), 6))
    for k in range(len(t15)):
        p, r = flange.fk(q[k])
        p = p + rng.normal(0.0, 3e-4, 3)
        r = Rotation.from_rotvec(rng.normal(0.0, 0.002, 3)) * r
        cart[k, :3] = p
        cart[k, 3:] = r.as_euler("xyz")
    q_written = q + rng.normal(0.0, 1e-4, q.shape)
    if brk == "rotated":
        # The recorded flange turned 0.1 rad about x at frame 50 only, its position kept.
        cart[50, 3:] = (Rotation.from_euler("xyz", cart[50, 3:]) * Rotation.from_rotvec([0.1, 0.0, 0.0])).as_euler("xyz")
    if brk == "unreachable":
        # Joint 4 past its upper limit (-0.0698 rad) from frame 40 on, the pose made to match.
        q_written[40:, 3] = 0.2
        for k in range(40, len(t15)):
            p, r = flange.fk(q_written[k])
            cart[k, :3], cart[k, 3:] = p, r.as_euler("xyz")
    stamps = 1.7e9 + t15
    if brk == "nonmonotonic":
        stamps[30], stamps[31] = stamps[31], stamps[30]
    # A fixed camera across the table; its left optical frame in the base.
    k_mat = np.array([[523.0, 0.0, 640.0], [0.0, 523.0, 360.0], [0.0, 0.0, 1.0]])
    cam_p = np.array([1.25, 0.45, 0.65])
    cam_r = look_at(cam_p, np.array([0.45, 0.0, 0.1]), np.array([0.0, 0.0, 1.0]))
    ext = np.tile(np.concatenate([cam_p, cam_r.as_euler("xyz")]), (len(t15), 1))
    os.makedirs(out, exist_ok=True)
    with h5py.File(os.path.join(out, "trajectory.h5"), "w") as f:
        f.attrs["synthetic"] = "generated by real2sim/tests/make_synthetic.py from " + os.path.basename(os.path.normpath(gym))
        rs = f.create_group("observation/robot_state")
        if brk == "wrong_shape":
            rs["joint_positions"] = q_written[:, :6]
        else:
            rs["joint_positions"] = q_written
        if brk != "missing_field":
            if brk == "nan":
                cart[17, 3] = np.nan
            rs["cartesian_position"] = cart
        rs["gripper_position"] = measured
        rs["joint_velocities"] = np.gradient(q_written, t15, axis=0)
        if action:
            f["action/gripper_position"] = closed_cmd
        ts = f.create_group("observation/timestamp/robot_state")
        ts["robot_timestamp_seconds"] = np.floor(stamps).astype(np.int64)
        ts["robot_timestamp_nanos"] = np.round((stamps - np.floor(stamps)) * 1e9).astype(np.int64)
        f["observation/camera_extrinsics/22008760_left"] = ext
    meta = {
        "synthetic": True,
        "uuid": f"synthetic+{os.path.basename(os.path.normpath(gym))}+{seed}",
        "current_task": scene["task"].get("instruction", ""),
        "ext1_cam_serial": "22008760",
        "ext2_cam_serial": "24400334",
        "wrist_cam_serial": "18026681",
        "trajectory_length": len(t15),
    }
    with open(os.path.join(out, f"metadata_synthetic-{seed}.json"), "w") as f:
        json.dump(meta, f)
    p_flange = [flange.fk(q_written[k])[0] for k in range(len(t15))]
    truth = {
        "synthetic": True,
        "gym": os.path.basename(os.path.normpath(gym)),
        "demo_hz": hz,
        "rows": rows.tolist(),
        "source_times_s": t15.tolist(),
        "camera": "ext1",
        "intrinsics": {"fx": 523.0, "fy": 523.0, "cx": 640.0, "cy": 360.0},
        "flange_pixels": [project(k_mat, cam_p, cam_r, p) for p in p_flange],
    }
    with open(os.path.join(out, "truth.json"), "w") as f:
        json.dump(truth, f)


# ARKit's world is y up: a z-up point (x, y, z) is (x, z, -y) there.
ARKIT_FROM_ZUP = Rotation.from_matrix(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]))


def matrix(p: np.ndarray, r: Rotation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r.as_matrix()
    m[:3, 3] = p
    return m


def egodex(gym: str, out: str, seed: int, brk: Optional[str]) -> None:
    rng = np.random.default_rng(seed)
    scene, rows, urdf = read_gym(gym)
    hz = float(scene["task"].get("demonstration_hz", 20.0))
    t20 = np.arange(len(rows)) / hz
    t30 = np.arange(0.0, t20[-1] + 1e-9, 1.0 / 30.0)
    n = len(t30)
    q = interp_rows(t30, t20, rows[:, :7])
    tcp = Chain(urdf, scene["robot"].get("tcp_link", "hand_tcp"))
    # The hand's aperture follows the gripper command with a 0.3 s ramp: 8.5 cm wide open, 4.5 cm
    # pinched (the fingertips rest on the object's sides), part open in between (-0.2: 6.9 cm).
    cmd = hold(t30, hz, rows[:, 7])
    target = np.where(cmd > 0.0, 0.045, 0.045 + 0.5 * (1.0 - cmd) * 0.04)
    aperture = np.zeros(n)
    aperture[0] = target[0]
    for k in range(1, n):
        step = (t30[k] - t30[k - 1]) * (0.04 / 0.3)
        aperture[k] = aperture[k - 1] + np.clip(target[k] - aperture[k - 1], -step, step)
    # ARKit's world: y up, turned 37 deg about its vertical, origin somewhere in the room.
    yaw = Rotation.from_rotvec([0.0, math.radians(37.0), 0.0])
    world_from_base_r = yaw * ARKIT_FROM_ZUP
    world_from_base_p = np.array([0.31, -0.92, 1.4])

    def to_world(p: np.ndarray) -> np.ndarray:
        return world_from_base_r.apply(p) + world_from_base_p

    pts: Dict[str, np.ndarray] = {name: np.zeros((n, 4, 4)) for name in ["ThumbTip", "IndexFingerTip", "IndexFingerKnuckle", "Hand"]}
    clean_index = np.zeros((n, 3))
    for k in range(n):
        p, r = tcp.fk(q[k])
        y, z = r.apply([0.0, 1.0, 0.0]), r.apply([0.0, 0.0, 1.0])
        a = aperture[k]
        base_pts = {
            "ThumbTip": p - 0.5 * a * y,
            "IndexFingerTip": p + 0.5 * a * y,
            "IndexFingerKnuckle": p - 0.09 * z + 0.015 * y,
            "Hand": p - 0.12 * z,
        }
        for name, bp in base_pts.items():
            wp = to_world(bp + rng.normal(0.0, 0.0015, 3))
            pts[name][k] = matrix(wp, world_from_base_r * r)
        clean_index[k] = pts["IndexFingerTip"][k][:3, 3]
    conf = {name: rng.uniform(0.85, 1.0, n) for name in pts}
    low = rng.random(n) < 0.06
    low[[0, 1, n - 1]] = False
    low[int(0.15 * n) : int(0.15 * n) + 8] = True  # a burst: the hand out of view
    for name in pts:
        conf[name][low] = rng.uniform(0.0, 0.3, int(low.sum()))
        # Untracked frames carry garbage positions.
        pts[name][low, :3, 3] += rng.normal(0.0, 0.3, (int(low.sum()), 3))
    # One confident frame whose thumb and index tips coincide (a tracking glitch): no pinch frame.
    degenerate = int(np.nonzero(~low[n // 2 :])[0][0]) + n // 2
    pts["ThumbTip"][degenerate, :3, 3] = pts["IndexFingerTip"][degenerate, :3, 3]
    if brk == "hand_never_seen":
        for name in pts:
            conf[name][:] = 0.05
    if brk == "unreachable":
        for name in pts:
            pts[name][:, :3, 3] += world_from_base_r.apply([1.5, 0.0, 0.0])
    # The head: behind and above the robot's left, looking at the workspace (ARKit camera axes:
    # x right, y up, looking along -z).
    k_mat = np.array([[736.6, 0.0, 960.0], [0.0, 736.6, 540.0], [0.0, 0.0, 1.0]])
    cams = np.zeros((n, 4, 4))
    for k in range(n):
        eye = np.array([-0.05, -0.45, 0.7]) + 0.01 * np.array([math.sin(t30[k]), math.cos(0.7 * t30[k]), 0.0])
        optical = look_at(eye, np.array([0.5, 0.0, 0.05]), np.array([0.0, 0.0, 1.0]))
        arkit_cam = optical * Rotation.from_rotvec([math.pi, 0.0, 0.0])
        cams[k] = matrix(to_world(eye), world_from_base_r * arkit_cam)
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, "episode.hdf5")
    with h5py.File(path, "w") as f:
        f.attrs["synthetic"] = "generated by real2sim/tests/make_synthetic.py from " + os.path.basename(os.path.normpath(gym))
        f.attrs["llm_description"] = scene["task"].get("instruction", "")
        f.attrs["llm_description2"] = "(reverse) " + scene["task"].get("instruction", "")
        f.attrs["which_llm_description"] = 1
        if brk != "missing_field":
            f["camera/intrinsic"] = k_mat
        f["transforms/camera"] = cams
        for name, arr in pts.items():
            data = arr
            if brk == "wrong_shape" and name == "IndexFingerTip":
                data = arr[:, :3, :]
            if brk == "nan" and name == "ThumbTip":
                data = arr.copy()
                data[17, 0, 3] = np.nan
                conf[name][17] = 0.95
            f["transforms/right" + name] = data
            f["confidences/right" + name] = conf[name]
            # The other hand rests out of view, never tracked well.
            f["transforms/left" + name] = arr
            f["confidences/left" + name] = np.full(n, 0.1)
    base_from_world = np.linalg.inv(matrix(world_from_base_p, world_from_base_r))
    with open(os.path.join(out, "registration.json"), "w") as fh:
        json.dump({"synthetic": True, "base_from_world": base_from_world.tolist()}, fh)
    truth = {
        "synthetic": True,
        "gym": os.path.basename(os.path.normpath(gym)),
        "demo_hz": hz,
        "rows": rows.tolist(),
        "source_times_s": t30.tolist(),
        "base_from_world": base_from_world.tolist(),
        "intrinsics": {"fx": 736.6, "fy": 736.6, "cx": 960.0, "cy": 540.0},
        "index_tip_pixels": [
            project(k_mat, cams[k][:3, 3], Rotation.from_matrix(cams[k][:3, :3]) * Rotation.from_rotvec([math.pi, 0.0, 0.0]), clean_index[k])
            for k in range(n)
        ],
        "low_confidence_frames": [int(k) for k in np.nonzero(low)[0]],
        "degenerate_frames": [degenerate],
    }
    with open(os.path.join(out, "truth.json"), "w") as fh:
        json.dump(truth, fh)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("layout", choices=["droid", "egodex"])
    ap.add_argument("--gym", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-action", action="store_true", help="DROID: no action/gripper_position group")
    ap.add_argument("--break", dest="brk", choices=["missing_field", "wrong_shape", "nan", "nonmonotonic", "rotated", "hand_never_seen", "unreachable"])
    a = ap.parse_args()
    if a.layout == "droid":
        droid(a.gym, a.out, a.seed, a.brk, action=not a.no_action)
    else:
        egodex(a.gym, a.out, a.seed, a.brk)


if __name__ == "__main__":
    main()
