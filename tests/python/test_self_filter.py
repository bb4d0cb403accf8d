"""Tests for the self-filter of robo_perception (module `robot`): the robot's own arm and hand are
removed before segmentation, so no part of the robot is ever reported as an object.

Run:  .venv/bin/python -m pytest tests/python/test_self_filter.py -s

Offline: the description in `robo_perception.robot` against robots/panda/panda.urdf (so the
two cannot drift apart), its forward kinematics against the runtime's (`r2g kin fk`), and the
mask on synthetic points. Live: one gym at a time (`r2g up <gym> --mode lockstep`), at the reset
state and at mid-manipulation states (the hand a few centimetres above the table next to
objects, the arm stretched or swung aside, an object held between the fingers), judged against
MuJoCo's own segmentation of the same model and state (render_truth.py): no reported object may
be mostly robot, and almost no pixel MuJoCo draws for the robot may end in an object's mask.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT / "agent-host" / "py" / "lib"))
import robo_perception as rp  # noqa: E402
from robo_perception import robot as rb  # noqa: E402
import render_truth as rt  # noqa: E402

R2G, GYMS_DIR = rt.R2G, rt.GYMS_DIR
URDF = ROOT / "robots" / "panda" / "panda.urdf"
EXAMPLE = ROOT / "robot-skill" / "examples" / "pick_object.py"
READY = [0.0, -0.7853982, 0.0, -2.3561945, 0.0, 1.5707963, 0.7853982]

MOSTLY_ROBOT = 0.2       # an object with more of its mask on the robot than this is a robot part
LEAK_MAX = 0.002         # largest share of the robot's pixels allowed inside object masks


# ------------------------------------------------------------------------------------------
# Offline: the description, kinematics and the mask
# ------------------------------------------------------------------------------------------

def _floats(text: str | None, n: int = 3) -> tuple:
    return tuple(float(v) for v in (text or " ".join(["0"] * n)).split())


def _origin(el) -> tuple[tuple, tuple]:
    o = el.find("origin")
    if o is None:
        return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    return _floats(o.get("xyz")), _floats(o.get("rpy"))


def test_description_matches_urdf():
    """Every joint, capsule and finger box of `robot.PANDA` is the URDF's, and nothing is missing."""
    root = ET.parse(URDF).getroot()
    joints = {j.get("name"): j for j in root.findall("joint")}
    assert {j.name for j in rb.PANDA.joints} == set(joints)
    for j in rb.PANDA.joints:
        u = joints[j.name]
        assert (j.parent, j.child) == (u.find("parent").get("link"), u.find("child").get("link")), j.name
        assert j.kind == u.get("type"), j.name
        xyz, rpy = _origin(u)
        assert np.allclose(j.xyz, xyz, atol=1e-12) and np.allclose(j.rpy, rpy, atol=1e-12), j.name
        if j.kind != "fixed":
            assert np.allclose(j.axis, _floats(u.find("axis").get("xyz")), atol=1e-12), j.name
    arm = [n for n, u in joints.items() if u.get("type") == "revolute"]
    assert list(rb.PANDA.arm_joints) == arm
    assert list(rb.PANDA.finger_joints) == [n for n, u in joints.items() if u.get("type") == "prismatic"]
    assert joints["tcp_joint"].find("child").get("link") == rb.PANDA.tcp_link

    # capsules: every visual or collision capsule of every link, once
    want = set()
    guards = set()
    for link in root.findall("link"):
        for el in link.findall("visual") + link.findall("collision"):
            cap = el.find("geometry/capsule")
            if cap is None:
                continue
            xyz, rpy = _origin(el)
            key = (link.get("name"),) + tuple(round(v, 9) for v in xyz + rpy) + (
                round(float(cap.get("radius")), 9), round(float(cap.get("length")), 9))
            want.add(key)
            if (el.get("name") or "").endswith("_envelope"):
                guards.add(key)
    described = [c for c in rb.PANDA.capsules if not c.drawn]
    have = {(c.link,) + tuple(round(v, 9) for v in c.xyz + c.rpy) + (round(c.radius, 9), round(c.length, 9))
            for c in described}
    assert have == want and len(have) == len(described)
    assert {(c.link,) + tuple(round(v, 9) for v in c.xyz + c.rpy) + (round(c.radius, 9), round(c.length, 9))
            for c in rb.PANDA.capsules if c.guard} == guards
    # fingers: one box each, the same in both fingers' frames (visuals may be the real meshes)
    for name in ("finger_left", "finger_right"):
        link = root.find(f"link[@name='{name}']")
        for el in link.findall("visual") + link.findall("collision"):
            box = el.find("geometry/box")
            if box is None and el.tag == "visual" and el.find("geometry/mesh") is not None:
                continue
            xyz, rpy = _origin(el)
            assert np.allclose(_floats(box.get("size")), rb.PANDA.finger_box_size, atol=1e-12)
            assert np.allclose(xyz, rb.PANDA.finger_box_center, atol=1e-12) and not any(rpy)
    # the hand model (hand.py) agrees: fingertips beyond the TCP, the guard behind it
    tcp_z = _origin(joints["tcp_joint"])[0][2]
    finger_z = _origin(joints["finger_joint1"])[0][2]
    assert math.isclose(rp.FRANKA_HAND.tip_beyond_tcp, finger_z + rb.PANDA.finger_box_size[2] - tcp_z, abs_tol=1e-9)
    guard = next(c for c in rb.PANDA.capsules if c.guard)
    assert math.isclose(rp.FRANKA_HAND.envelope_behind_tcp, tcp_z - guard.xyz[2], abs_tol=1e-9)
    limit = float(joints["finger_joint1"].find("limit").get("upper"))
    assert math.isclose(2 * limit, rp.GRIPPER_MAX_WIDTH, abs_tol=1e-12)


def test_the_drawn_meshes_lie_inside_the_filter_shapes():
    """Every vertex of every mesh the cameras see (the Panda's and the Franka Hand's visual
    meshes, as robots/assets.py converted them) lies inside its link's capsules, and each finger's
    inside the self-filter's finger box, so the filter can remove every robot pixel."""
    sys.path.insert(0, str(ROOT / "robots"))
    import envelopes  # noqa: E402

    root = ET.parse(URDF).getroot()
    drawn = {link.get("name"): Path(el.find("geometry/mesh").get("filename")).stem
             for link in root.findall("link") for el in link.findall("visual")
             if el.find("geometry/mesh") is not None}
    assert set(drawn) >= set(envelopes.LINKS) | {"finger_left", "finger_right"}, drawn
    for link, mesh in drawn.items():
        V = envelopes.vertices(mesh)
        if link.startswith("finger"):
            c, size = rb.PANDA.filter_finger_box()
            assert np.all(np.abs(V - c) <= 0.5 * size + 1e-3), link  # within the finger margin
            continue
        gap = np.full(len(V), np.inf)
        for cap in (c for c in rb.PANDA.capsules if c.link == link):
            R = rb.rpy_to_matrix(cap.rpy)
            a = np.asarray(cap.xyz) - 0.5 * cap.length * R[:, 2]
            gap = np.minimum(gap, envelopes.segment_d(V, a, R[:, 2], cap.length) - cap.radius)
        assert gap.max() <= 0.0, f"{link}: a vertex of {mesh} lies {1e3 * gap.max():.1f} mm outside"


def _quat_to_matrix(q):  # x, y, z, w
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_forward_kinematics_matches_the_runtime():
    """Link and TCP poses equal `r2g kin fk` (the controllers crate, from the URDF itself)."""
    if not R2G.exists():
        pytest.skip(f"{R2G} not built")
    rng = np.random.default_rng(5)
    qs = [READY] + [list(np.asarray(READY) + rng.uniform(-0.8, 0.8, 7)) for _ in range(4)]
    frames = ["link1", "link3", "link5", "link7", "hand", "tcp"]
    for frame in frames:
        args = [str(R2G), "kin", "fk"] + (["--frame", frame] if frame != "tcp" else [])
        out = subprocess.run(args, input="".join(json.dumps({"q": q}) + "\n" for q in qs), capture_output=True,
                             text=True, timeout=30, check=True).stdout.strip().splitlines()
        for q, line in zip(qs, out):
            a = json.loads(line)
            T = rp.link_poses(q)["hand_tcp" if frame == "tcp" else frame]
            assert np.allclose(T[:3, 3], a["position"], atol=1e-9), frame
            assert np.allclose(T[:3, :3], _quat_to_matrix(a["quaternion"]), atol=1e-9), frame
    assert np.allclose(rp.tcp_pose(READY)[:3], [0.3069, 0.0, 0.4869], atol=1e-4)


def test_robot_mask_on_synthetic_points():
    """Points on every capsule's surface and on the fingers are the robot; points a little
    beyond the margins are not; a block held between the fingers is kept."""
    rng = np.random.default_rng(3)
    q, g = READY, 0.0                       # fingers half open: 4 cm apart
    s = rb.robot_shapes(q, g)
    on, off = [], []
    for k in range(len(s.a)):
        t = rng.uniform(0, s.length[k], 400)
        n = rng.normal(size=(400, 3))
        n -= np.outer(n @ s.u[k], s.u[k])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        axis = s.a[k] + np.outer(t, s.u[k])
        on.append(axis + n * (s.radius[k] - 0.0005))
        off.append(axis + n * (s.radius[k] + rb.SELF_FILTER_MARGIN + 0.002))
    on, off = np.concatenate(on), np.concatenate(off)
    m_on = rp.robot_mask(on, q, g)
    assert m_on.all()
    # beyond the margin of one capsule a point may still lie on a neighbour: judge by distance
    d = (rb.capsule_distances(off, s) - s.radius).min(axis=1)
    clear = d > rb.SELF_FILTER_MARGIN + 1e-4
    T = s.tcp
    L = (off - T[:3, 3]) @ T[:3, :3]
    near_fingers = (np.abs(L[:, 2]) < 0.07) & (np.abs(L[:, 0]) < 0.03)
    assert not rp.robot_mask(off[clear & ~near_fingers], q, g).any()
    # a 3 cm cube held between the fingers (4 cm apart): its faces are kept, the fingers masked
    u = rng.uniform(-0.015, 0.015, (3000, 2))
    face = np.c_[u[:, 0], np.full(3000, 0.0), u[:, 1]]
    block = []
    for axis in range(3):
        for sgn in (-1, 1):
            f = np.roll(face, axis, axis=1)
            f[:, axis] = sgn * 0.015
            block.append(f)
    block = np.concatenate(block)                                 # centred on the TCP
    world = block @ T[:3, :3].T + T[:3, 3]
    # points inside the fingertip guard are hidden in a real image; only count visible ones
    d_guard = (rb.capsule_distances(world, s) - s.radius)[:, s.guard][:, 0]
    visible = d_guard > rb.SELF_FILTER_GUARD_MARGIN + 1e-4
    kept = ~rp.robot_mask(world[visible], q, g)
    assert kept.mean() > 0.95
    finger = np.array([[0.0, 0.02 + 0.006, -0.02], [0.0, -0.02 - 0.006, -0.02]]) @ T[:3, :3].T + T[:3, 3]
    assert rp.robot_mask(finger, q, g).all()
    # the cubes only speed things up: same answer point by point, on a sparse cloud and on a dense
    # one (150 000 points in a 3 cm cube around the fingertips, as close as a wrist camera sees)
    cloud = np.concatenate([on, off, world, rng.uniform([-0.2, -0.4, 0.0], [0.8, 0.4, 0.9], (20000, 3))])
    assert np.array_equal(rp.robot_mask(cloud, q, g), rp.robot_mask(cloud, q, g, cell=0.0))
    dense = T[:3, 3] + rng.uniform(-0.015, 0.015, (150000, 3)) @ T[:3, :3].T + T[:3, 1] * 0.02
    m = rp.robot_mask(dense, q, g)
    assert 0.1 < m.mean() < 0.9 and np.array_equal(m, rp.robot_mask(dense, q, g, cell=0.0))


# ------------------------------------------------------------------------------------------
# Live gyms against MuJoCo's own segmentation
# ------------------------------------------------------------------------------------------

# TCP targets (x, y, z), yaw about the vertical, hand pointing down: low over the table, next to
# objects, stretched out; reached from 0.2 m above so that nothing is pushed on the way.
POSES = {
    "pick_block_plate": [("near the block", (0.42, -0.12, 0.05), 0.0), ("between", (0.5, 0.02, 0.06), 1.57),
                         ("stretched", (0.72, 0.0, 0.07), 0.0)],
    "stack_bowls": [("in front", (0.38, 0.0, 0.05), 0.0), ("stretched", (0.72, 0.0, 0.08), 0.7)],
    "open_drawer": [("low left", (0.40, 0.15, 0.05), 0.0), ("at the handle", (0.45, 0.0, 0.22), 1.57),
                    ("low right", (0.45, -0.2, 0.04), 0.5)],
    "microwave_cup": [("near the cup", (0.36, 0.12, 0.05), 0.0)],
}
# Joint-space swings (offsets from the ready pose): the arm turned aside, the hand low.
SWING_RIGHT = [-0.8, 0.89, 0.06, -0.11, -0.04, 0.66, 0.0]
SWING_LEFT = [0.82, 0.97, 0.15, -0.01, -0.21, 0.55, 0.0]
SWINGS = {"stack_bowls": SWING_RIGHT, "microwave_cup": SWING_LEFT, "pick_block_plate": SWING_LEFT}
# Held objects: a scripted grasp (x, y, TCP z, then lifted to) or the example program's prompt.
GRASPS = {"pick_block_plate": ((0.5, -0.12), 0.03, 0.06)}
PICKS = {"microwave_cup": ("white cup", "cup")}


def judge(obs: dict, truth: rt.TruthRenderer, objects=None, fixtures=None) -> dict:
    """Segments `obs` and compares with MuJoCo's segmentation of the same state: per object the
    share of its mask pixels that MuJoCo draws for the robot, and how many robot pixels ended in
    some object's mask."""
    truth.set_state(obs["joint"], rp.gripper_to_width(obs["gripper"][0]) / 2, objects=objects, fixtures=fixtures)
    scene = rp.segment_scene(obs)
    robot_id = truth.names.index("robot")
    out = {"scene": scene, "share": [], "leak": 0, "robot_px": 0, "mad": {}}
    per_obj = np.zeros((len(scene.objects), 2))
    for cam in ("agentview", "wrist"):
        out["mad"][cam] = float(np.abs(truth.rgb(cam).astype(int) - obs["image"][cam]).mean())
        robot = truth.segmentation(cam) == robot_id
        any_obj = np.zeros_like(robot)
        for i, o in enumerate(scene.objects):
            m = o.masks[cam]
            per_obj[i] += [(m & robot).sum(), m.sum()]
            any_obj |= m
        out["leak"] += int((robot & any_obj).sum())
        out["robot_px"] += int(robot.sum())
    out["share"] = [float(r / max(n, 1)) for r, n in per_obj]
    return out


GYMS = ["pick_block_plate", "stack_bowls", "open_drawer", "microwave_cup"]
TIMES: dict = {}


@pytest.mark.parametrize("gym", GYMS)
def test_no_robot_part_is_an_object(gym):
    if not R2G.exists():
        pytest.skip(f"{R2G} not built")
    import robo
    with tempfile.TemporaryDirectory(prefix="r2g-self-filter-") as tmp:
        g = rt.LiveGym(R2G, GYMS_DIR, gym, trace_dir=Path(tmp), tag="self")
        truth = None
        try:
            assert g.ready.wait(90), f"{gym} did not print READY"
            truth = rt.TruthRenderer(rt.compiled_mjcf(R2G.parent / "r2g-sim", g.scene_path))
            fixtures = rt.initial_fixtures(g.scene)
            g.use()
            checked = []

            def check(label, obs, objects=None, fx=fixtures, held=None):
                # the measured joints give the measured TCP
                assert np.allclose(rp.tcp_pose(obs["joint"])[:3], obs["ee_pose"][:3], atol=1e-4), label
                assert np.allclose(rp.tcp_matrix(obs["joint"])[:3, :3], rp.pose_to_matrix(obs["ee_pose"])[:3, :3],
                                   atol=1e-4), label
                r = judge(obs, truth, objects, fx)
                assert max(r["mad"].values()) < 1.0, f"{label}: ground truth does not draw the camera's picture {r['mad']}"
                scene = r["scene"]
                lines = [f"   {gym} / {label}: {len(scene.objects)} objects, robot pixels in objects "
                         f"{r['leak']}/{r['robot_px']}"]
                lines += [f"      {o.describe()}  robot {s:.2f}" for o, s in zip(scene.objects, r["share"])]
                print("\n".join(lines))
                for o, s in zip(scene.objects, r["share"]):
                    assert s <= MOSTLY_ROBOT, f"{label}: {o.describe()} is {s:.0%} robot"
                assert r["leak"] <= LEAK_MAX * r["robot_px"], f"{label}: {r['leak']} robot pixels in objects"
                if held is not None:
                    hits = [o for o in scene.objects if o.held]
                    assert hits, f"{label}: nothing reported held"
                    # the object, not a sliver of it: at its place (the body origin's xy) and tall
                    o = min(hits, key=lambda o: np.linalg.norm(o.center[:2] - np.asarray(held[:2])))
                    assert np.linalg.norm(o.center[:2] - np.asarray(held[:2])) < 0.02, o.describe()
                    assert o.extents[2] > 0.03, o.describe()
                checked.append(label)
                return r

            obs = g.observe()
            check("reset", obs)
            # the filter's cost on one camera pair (points above the table, as segment_scene has them)
            clouds = []
            for cam in ("agentview", "wrist"):
                P, _ = rp.depth_to_points(obs["depth"][cam], obs["camera_intrinsics"][cam], obs["camera_extrinsics"][cam])
                clouds.append(P[P[:, 2] > 0.005])
            best = math.inf
            for _ in range(3):
                t = time.perf_counter()
                for P in clouds:
                    rp.robot_mask(P, obs["joint"], obs["gripper"][0])
                best = min(best, time.perf_counter() - t)
            TIMES[gym] = 1e3 * best
            print(f"   self-filter on agentview + wrist ({sum(map(len, clouds))} points above the table): "
                  f"{TIMES[gym]:.0f} ms")  # a figure, not a check: timing is the bench's
            if gym in SWINGS:  # an episode takes one control type: joints first, then a reset
                assert rt.move_joints(np.asarray(READY) + SWINGS[gym]), robo.get_state([])['control_feedback']
                check("arm swung aside (joint chunk)", g.observe())
                g.end_episode()
            for label, xyz, yaw in POSES.get(gym, []):
                assert rt.move_tcp(xyz, yaw), robo.get_state([])['control_feedback']
                check(label, g.observe())
            if gym in GRASPS:
                (x, y), z, lift = GRASPS[gym]
                g.end_episode()
                assert rt.move_tcp((x, y, 0.10), 0.0), robo.get_state([])['control_feedback']
                assert rt.move_tcp((x, y, z), 0.0, hop=0.0), robo.get_state([])['control_feedback']
                here = robo.get_state([])["ee_pose"]
                robo.post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints([here] * 12, 1.0)})
                assert rt.move_tcp((x, y, lift), 0.0, gripper=1.0, hop=0.0), robo.get_state([])['control_feedback']
                obs = g.observe()
                trace = g.end_episode()
                objects = {n: trace["samples"][-1]["objects"][i] for i, n in enumerate(trace["objects"])}
                block = objects["block"][:3]
                assert block[2] > 0.04, "the scripted grasp did not lift the block"
                check("block held just above the table", obs, objects, rt.trace_state(g.scene, trace)[1], held=block)
            if gym in PICKS:
                g.end_episode()
                prompt, name = PICKS[gym]
                out = subprocess.run([sys.executable, str(EXAMPLE), prompt], capture_output=True, text=True,
                                     env=dict(os.environ, R2G_INSTANCE=g.instance), timeout=180)
                assert "RESULT lifted=True" in out.stdout, out.stdout + out.stderr
                obs = g.observe()
                trace = g.end_episode()
                objects = {n: trace["samples"][-1]["objects"][i] for i, n in enumerate(trace["objects"])}
                check(f"{prompt} held by the example program", obs, objects, rt.trace_state(g.scene, trace)[1],
                      held=objects[name][:3])
            assert len(checked) >= 3
        finally:
            if truth is not None:
                truth.close()
            g.stop()


def test_an_image_older_than_the_joints_is_not_filtered_with_them(tmp_path):
    """The robot parts that escaped the filter in a scripted stack_bowls run (a "grey plate" of
    3295 wrist points 16 cm above the closed fingers, a "grey cylinder" of agentview points)
    were the arm as it was seconds earlier: that observation's images were 1.8 s (agentview) and
    3.3 s (wrist) older than its joints (the renderer lagged), and the filter poses the robot from
    the joints. Here the same mix is made on purpose: the images of the hand 11 cm higher with
    the joints of the fingers closed on the bowl's wall. Filtered with those joints, the old
    fingers come out as objects; `segment_scene` leaves the stale view out (and says so), or,
    when every view is stale, says that robot parts may be objects."""
    if not R2G.exists():
        pytest.skip(f"{R2G} not built")
    import robo
    g = rt.LiveGym(R2G, GYMS_DIR, "stack_bowls", trace_dir=tmp_path, tag="stale")
    try:
        assert g.ready.wait(90), "stack_bowls did not print READY"
        g.end_episode()
        assert rt.move_tcp((0.576, -0.129, 0.167), -1.5708), robo.get_state([])["control_feedback"]
        high = g.observe()
        assert rt.move_tcp((0.576, -0.129, 0.058), -1.5708, hop=0.0), robo.get_state([])["control_feedback"]
        here = robo.get_state([])["ee_pose"]
        assert robo.post_actions({"type": "ee_pose", "freq": "", "actions": rp.waypoints([here] * 20, 1.0)}) == 1
        low = g.observe()
        assert low["timestamp"] - high["image_timestamp"]["wrist"] > 0.5

        def mixed(cams):
            s = dict(low)
            for key in ("image", "depth", "camera_extrinsics", "image_timestamp"):
                s[key] = dict(low[key])
                for c in cams:
                    s[key][c] = high[key][c]
            return s

        def on_old_robot(scene) -> list:
            """Objects that are (mostly) the robot as posed in the old images."""
            return [o for o in scene.objects
                    if np.mean(rp.robot_distance(o.points, high["joint"], high["gripper"][0]) < 0.01) > 0.5]

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rp.PerceptionWarning)
            blind = rp.segment_scene(mixed(["wrist"]), tracker=None, stale_s=None)
            old = on_old_robot(blind)
            print("\n   filtered with the newer joints:\n" + "\n".join("      " + o.describe() for o in old))
            assert old, "the stale wrist image should show the hand where it was"
            scene = rp.segment_scene(mixed(["wrist"]), tracker=None)
            assert [v.name for v in scene.views] == ["agentview"]
            assert any("wrist" in w and "left out" in w for w in scene.warnings), scene.warnings
            assert not on_old_robot(scene), scene.summary()
            both = rp.segment_scene(mixed(["agentview", "wrist"]), tracker=None)
            assert any("may be reported as objects" in w for w in both.warnings), both.warnings
            fresh = rp.segment_scene(low, tracker=None)
            assert not fresh.warnings and not on_old_robot(fresh)
    finally:
        g.stop()
